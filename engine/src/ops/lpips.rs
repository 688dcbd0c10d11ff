//! LPIPS on the GPU (kernels `lpips::*`) as a metric and as a loss with its gradient to
//! the first image, the weights file it reads, and the CPU reference from the same
//! shared functions (`drape_shared::lpips`, which states the math), generic over
//! f32/f64.
//!
//! Weights: a safetensors file holding the `lpips` package's state dict (v0.1) with
//! its torchvision backbone, as `scripts/lpips-to-safetensors.py` writes it:
//! `net.sliceS.I.weight` / `.bias` for each convolution (torchvision's feature index
//! `I`), `linL.model.1.weight` (1 × C × 1 × 1) for each tapped layer `L`, float32.
//! Pretrained weights cannot be downloaded here; without a file, LPIPS is "n/a".

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use drape_shared::lpips::{
    conv_at, layer_distance_at, out_size, pool_at, ConvParams, PoolParams, LPIPS_SCALE, LPIPS_SHIFT,
};
use drape_shared::real::Real;

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::{EngineError, Result};
use crate::kernels;
use crate::mirror::{read_through, Mirror};
use crate::recorder::{flat_grid as grid, Recording};

/// The backbone; in configuration files `"alex"` or `"vgg"` (`"vgg16"` is read too).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LpipsNet {
    /// AlexNet's five convolutions (LPIPS's default).
    Alex,
    /// VGG-16's thirteen convolutions.
    #[serde(rename = "vgg", alias = "vgg16")]
    Vgg16,
}

impl LpipsNet {
    /// The network by its name ([`Self::name`], or `vgg16`), as a command line gives
    /// it; [`EngineError::InvalidSetting`] for `lpips_net` names the allowed values.
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "alex" => Ok(Self::Alex),
            "vgg" | "vgg16" => Ok(Self::Vgg16),
            other => Err(EngineError::InvalidSetting {
                what: "lpips_net",
                problem: format!("LPIPS network must be alex or vgg, got '{other}'"),
            }),
        }
    }

    /// The name `parse` and configuration files use: `alex` or `vgg`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Alex => "alex",
            Self::Vgg16 => "vgg",
        }
    }

    /// The stack: convolutions (state-dict prefix, in, out, kernel, stride, pad; all
    /// followed by ReLU), max-pools (kernel, stride) and taps.
    pub fn stack(self) -> Vec<Stage> {
        use Stage::{Conv, Pool, Tap};
        let c = |key: &'static str, i, o, k, s, p| Conv {
            key,
            in_c: i,
            out_c: o,
            kernel: k,
            stride: s,
            pad: p,
        };
        match self {
            Self::Alex => vec![
                c("net.slice1.0", 3, 64, 11, 4, 2),
                Tap,
                Pool {
                    kernel: 3,
                    stride: 2,
                },
                c("net.slice2.3", 64, 192, 5, 1, 2),
                Tap,
                Pool {
                    kernel: 3,
                    stride: 2,
                },
                c("net.slice3.6", 192, 384, 3, 1, 1),
                Tap,
                c("net.slice4.8", 384, 256, 3, 1, 1),
                Tap,
                c("net.slice5.10", 256, 256, 3, 1, 1),
                Tap,
            ],
            Self::Vgg16 => vec![
                c("net.slice1.0", 3, 64, 3, 1, 1),
                c("net.slice1.2", 64, 64, 3, 1, 1),
                Tap,
                Pool {
                    kernel: 2,
                    stride: 2,
                },
                c("net.slice2.5", 64, 128, 3, 1, 1),
                c("net.slice2.7", 128, 128, 3, 1, 1),
                Tap,
                Pool {
                    kernel: 2,
                    stride: 2,
                },
                c("net.slice3.10", 128, 256, 3, 1, 1),
                c("net.slice3.12", 256, 256, 3, 1, 1),
                c("net.slice3.14", 256, 256, 3, 1, 1),
                Tap,
                Pool {
                    kernel: 2,
                    stride: 2,
                },
                c("net.slice4.17", 256, 512, 3, 1, 1),
                c("net.slice4.19", 512, 512, 3, 1, 1),
                c("net.slice4.21", 512, 512, 3, 1, 1),
                Tap,
                Pool {
                    kernel: 2,
                    stride: 2,
                },
                c("net.slice5.24", 512, 512, 3, 1, 1),
                c("net.slice5.26", 512, 512, 3, 1, 1),
                c("net.slice5.28", 512, 512, 3, 1, 1),
                Tap,
            ],
        }
    }

    /// Channels of each tapped layer.
    pub fn tap_channels(self) -> Vec<u32> {
        let mut last = 3;
        let mut taps = Vec::new();
        for s in self.stack() {
            match s {
                Stage::Conv { out_c, .. } => last = out_c,
                Stage::Tap => taps.push(last),
                Stage::Pool { .. } => {}
            }
        }
        taps
    }

    /// Every tensor the file must hold, with its shape.
    pub fn tensors(self) -> Vec<(String, Vec<usize>)> {
        let mut out = Vec::new();
        for s in self.stack() {
            if let Stage::Conv {
                key,
                in_c,
                out_c,
                kernel,
                ..
            } = s
            {
                let (i, o, k) = (in_c as usize, out_c as usize, kernel as usize);
                out.push((format!("{key}.weight"), vec![o, i, k, k]));
                out.push((format!("{key}.bias"), vec![o]));
            }
        }
        for (l, c) in self.tap_channels().into_iter().enumerate() {
            out.push((format!("lin{l}.model.1.weight"), vec![1, c as usize, 1, 1]));
        }
        out
    }
}

/// [`LpipsNet::name`].
impl std::fmt::Display for LpipsNet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One stage of the feature stack.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// A convolution followed by ReLU.
    Conv {
        /// The weights' tensor key prefix.
        key: &'static str,
        /// Input channels.
        in_c: u32,
        /// Output channels.
        out_c: u32,
        /// Kernel side.
        kernel: u32,
        /// Stride.
        stride: u32,
        /// Zero padding on each side.
        pad: u32,
    },
    /// Max pooling.
    Pool {
        /// Window side.
        kernel: u32,
        /// Stride.
        stride: u32,
    },
    /// A layer whose activations the distance compares.
    Tap,
}

/// A problem with a weights file, naming the file and the tensor.
#[derive(Debug, thiserror::Error)]
pub enum WeightsError {
    // `error`, not `source`: the message already carries it, and a `source` would make
    // anyhow print the OS error twice.
    /// The file could not be read or written.
    #[error("{path}: {error}")]
    Io {
        /// The weights file.
        path: PathBuf,
        /// The OS error.
        error: std::io::Error,
    },
    /// The file is not safetensors.
    #[error("{path}: not a safetensors file: {detail}")]
    Format {
        /// The weights file.
        path: PathBuf,
        /// What is malformed.
        detail: String,
    },
    /// A tensor the network needs is absent.
    #[error("{path}: tensor '{tensor}' is missing (is this an LPIPS {net} file?)")]
    Missing {
        /// The weights file.
        path: PathBuf,
        /// The tensor's name.
        tensor: String,
        /// The network that needs it.
        net: &'static str,
    },
    /// A tensor has the wrong shape or non-finite values.
    #[error("{path}: tensor '{tensor}' has {detail}")]
    Bad {
        /// The weights file.
        path: PathBuf,
        /// The tensor's name.
        tensor: String,
        /// What is wrong with its shape or values.
        detail: String,
    },
}

/// The weights of one network, by tensor name.
#[derive(Clone, Debug)]
pub struct LpipsWeights {
    /// The backbone the weights are for.
    pub net: LpipsNet,
    /// Every tensor by its safetensors name, flattened.
    pub tensors: BTreeMap<String, Vec<f32>>,
}

impl LpipsWeights {
    /// Reads and checks a safetensors file: every tensor the network needs present,
    /// float32, of the right shape, and inside the file.
    pub fn load(path: &Path, net: LpipsNet) -> std::result::Result<Self, WeightsError> {
        let bytes = std::fs::read(path).map_err(|error| WeightsError::Io {
            path: path.into(),
            error,
        })?;
        let format = |detail: String| WeightsError::Format {
            path: path.into(),
            detail,
        };
        if bytes.len() < 8 {
            return Err(format(format!(
                "{} bytes, shorter than the 8-byte header length",
                bytes.len()
            )));
        }
        let header_len = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes")) as usize;
        if header_len > bytes.len() - 8 {
            return Err(format(format!(
                "header of {header_len} bytes, but the file has {} after the length",
                bytes.len() - 8
            )));
        }
        let header: serde_json::Map<String, serde_json::Value> =
            serde_json::from_slice(&bytes[8..8 + header_len])
                .map_err(|e| format(format!("header: {e}")))?;
        let body = &bytes[8 + header_len..];
        let name = net.name();
        let mut tensors = BTreeMap::new();
        for (tensor, shape) in net.tensors() {
            let bad = |detail: String| WeightsError::Bad {
                path: path.into(),
                tensor: tensor.clone(),
                detail,
            };
            let entry = header.get(&tensor).ok_or_else(|| WeightsError::Missing {
                path: path.into(),
                tensor: tensor.clone(),
                net: name,
            })?;
            let dtype = entry.get("dtype").and_then(|d| d.as_str()).unwrap_or("?");
            if dtype != "F32" {
                return Err(bad(format!("dtype {dtype}, expected F32")));
            }
            let got: Vec<usize> = entry
                .get("shape")
                .and_then(|s| s.as_array())
                .map(|a| {
                    a.iter()
                        .filter_map(|v| v.as_u64().map(|v| v as usize))
                        .collect()
                })
                .unwrap_or_default();
            if got != shape {
                return Err(bad(format!("shape {got:?}, expected {shape:?}")));
            }
            let offsets: Vec<usize> = entry
                .get("data_offsets")
                .and_then(|s| s.as_array())
                .map(|a| {
                    a.iter()
                        .filter_map(|v| v.as_u64().map(|v| v as usize))
                        .collect()
                })
                .unwrap_or_default();
            let n: usize = shape.iter().product();
            if offsets.len() != 2 || offsets[1] < offsets[0] || offsets[1] - offsets[0] != 4 * n {
                return Err(bad(format!(
                    "data offsets {offsets:?}, expected a range of {} bytes",
                    4 * n
                )));
            }
            if offsets[1] > body.len() {
                return Err(bad(format!(
                    "bytes {}..{}, but the file's data ends at {} (truncated?)",
                    offsets[0],
                    offsets[1],
                    body.len()
                )));
            }
            let data: Vec<f32> = body[offsets[0]..offsets[1]]
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
                .collect();
            if data.iter().any(|v| !v.is_finite()) {
                return Err(bad("a non-finite value".into()));
            }
            tensors.insert(tensor, data);
        }
        Ok(Self { net, tensors })
    }

    /// Writes `tensors` (name → (shape, data)) as a safetensors file (tests, tools).
    pub fn write_safetensors(
        path: &Path,
        tensors: &BTreeMap<String, (Vec<usize>, Vec<f32>)>,
    ) -> std::io::Result<()> {
        let mut header = serde_json::Map::new();
        let mut body = Vec::new();
        for (name, (shape, data)) in tensors {
            let start = body.len();
            body.extend(data.iter().flat_map(|v| v.to_le_bytes()));
            header.insert(name.clone(), serde_json::json!({ "dtype": "F32", "shape": shape, "data_offsets": [start, body.len()] }));
        }
        let mut h = serde_json::to_vec(&serde_json::Value::Object(header)).expect("json");
        while h.len() % 8 != 0 {
            h.push(b' ');
        }
        let mut out = (h.len() as u64).to_le_bytes().to_vec();
        out.extend(h);
        out.extend(body);
        drape_io::write(path, out)
    }

    /// The smallest image side the stack accepts (every stage keeps at least one
    /// pixel).
    pub fn min_side(net: LpipsNet) -> u32 {
        (1..4096)
            .find(|&s| plan_sizes(net, s, s).is_some())
            .unwrap_or(u32::MAX)
    }
}

/// (channels, height, width) of every activation (the scaled input first), or None
/// when the image is too small for the stack.
fn plan_sizes(net: LpipsNet, width: u32, height: u32) -> Option<Vec<(u32, u32, u32)>> {
    let mut sizes = vec![(3, height, width)];
    for s in net.stack() {
        let (c, h, w) = *sizes.last().expect("input");
        match s {
            Stage::Conv {
                out_c,
                kernel,
                stride,
                pad,
                ..
            } => {
                if h + 2 * pad < kernel || w + 2 * pad < kernel {
                    return None;
                }
                sizes.push((
                    out_c,
                    out_size(h, kernel, stride, pad),
                    out_size(w, kernel, stride, pad),
                ));
            }
            Stage::Pool { kernel, stride } => {
                if h < kernel || w < kernel {
                    return None;
                }
                sizes.push((
                    c,
                    out_size(h, kernel, stride, 0),
                    out_size(w, kernel, stride, 0),
                ));
            }
            Stage::Tap => {}
        }
    }
    Some(sizes)
}

/// [`plan_sizes`], or [`EngineError::ImageTooSmall`] naming the smallest side.
fn plan_sizes_or_err(net: LpipsNet, width: u32, height: u32) -> Result<Vec<(u32, u32, u32)>> {
    plan_sizes(net, width, height).ok_or_else(|| EngineError::ImageTooSmall {
        op: "LPIPS",
        width,
        height,
        min_side: LpipsWeights::min_side(net),
    })
}

/// The network on the GPU for images of one size, with the activations of both
/// images and the gradients of the first.
pub struct Lpips {
    /// The backbone.
    pub net: LpipsNet,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    sizes: Vec<(u32, u32, u32)>,
    /// Per conv stage: (weights, bias).
    conv: Vec<(Buffer, Buffer)>,
    lin: Vec<Buffer>,
    acts: [Vec<Buffer>; 2],
    argmax: [Vec<Buffer>; 2],
    grads: Vec<Buffer>,
    distances: Vec<Buffer>,
    /// The distance maps in host memory, one per tap, where
    /// [`Lpips::keep_host_mirror`] asked for them (empty otherwise).
    distance_mirrors: Vec<Mirror>,
}

impl Lpips {
    /// Uploads the weights for `width × height` images; an image smaller than the
    /// stack allows is [`EngineError::ImageTooSmall`].
    pub fn new(ctx: &Context, weights: &LpipsWeights, width: u32, height: u32) -> Result<Self> {
        let sizes = plan_sizes_or_err(weights.net, width, height)?;
        Self::build(ctx, weights, width, height, sizes)
    }

    fn build(
        ctx: &Context,
        weights: &LpipsWeights,
        width: u32,
        height: u32,
        sizes: Vec<(u32, u32, u32)>,
    ) -> Result<Self> {
        let up = |name: &str, data: &[f32]| ctx.upload(name, data);
        let mut conv = Vec::new();
        for s in weights.net.stack() {
            if let Stage::Conv { key, .. } = s {
                conv.push((
                    up(
                        &format!("lpips {key}.weight"),
                        &weights.tensors[&format!("{key}.weight")],
                    )?,
                    up(
                        &format!("lpips {key}.bias"),
                        &weights.tensors[&format!("{key}.bias")],
                    )?,
                ));
            }
        }
        let mut lin = Vec::new();
        for l in 0..weights.net.tap_channels().len() {
            lin.push(up(
                &format!("lpips lin{l}"),
                &weights.tensors[&format!("lin{l}.model.1.weight")],
            )?);
        }
        let b = |name: String, floats: u32| {
            ctx.create_buffer(&name, BufferDesc::gpu_only(4 * u64::from(floats.max(1))))
        };
        let mut acts = [Vec::new(), Vec::new()];
        let mut argmax = [Vec::new(), Vec::new()];
        let mut grads = Vec::new();
        for (i, &(c, h, w)) in sizes.iter().enumerate() {
            for (k, a) in acts.iter_mut().enumerate() {
                a.push(b(format!("lpips act {i} image {k}"), c * h * w)?);
                argmax[k].push(b(format!("lpips argmax {i} image {k}"), c * h * w)?);
            }
            grads.push(b(format!("lpips grad {i}"), c * h * w)?);
        }
        let mut distances = Vec::new();
        let mut at = 0;
        for s in weights.net.stack() {
            match s {
                Stage::Tap => {
                    let (_, h, w) = sizes[at];
                    distances.push(b(format!("lpips distance {}", distances.len()), h * w)?);
                }
                _ => at += 1,
            }
        }
        Ok(Self {
            net: weights.net,
            width,
            height,
            sizes,
            conv,
            lin,
            acts,
            argmax,
            grads,
            distances,
            distance_mirrors: Vec::new(),
        })
    }

    /// Keeps a host copy of each tap's distance map: after [`Lpips::record_readback`]
    /// in the recording that computed them, [`Lpips::read_value`] reads them without a
    /// submission or a wait of its own.
    pub fn keep_host_mirror(&mut self, ctx: &Context) -> Result<()> {
        self.distance_mirrors = self
            .distances
            .iter()
            .map(|d| Mirror::new(ctx, d))
            .collect::<Result<_>>()?;
        Ok(())
    }

    /// Records the copy of the distance maps just recorded into the host mirrors
    /// (nothing without them).
    pub fn record_readback<'a>(&'a self, rec: &mut Recording<'a>) {
        for (m, d) in self.distance_mirrors.iter().zip(&self.distances) {
            m.record_copy(rec, d, d.size);
        }
    }

    /// Records LPIPS(pred, target) for HWC RGB images in [0, 1] and, with `grad =
    /// Some((buffer, λ))`, adds `λ ∂LPIPS/∂pred` to the buffer.
    pub fn record<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        pred: &'a Buffer,
        target: &'a Buffer,
        grad: Option<(&'a Buffer, f32)>,
    ) -> Result<()> {
        let (w, h) = (self.width, self.height);
        self.distance_mirrors.iter().for_each(Mirror::mark_stale);
        let scale = PoolParams {
            c: 3,
            in_h: h,
            in_w: w,
            ..Default::default()
        };
        for (k, img) in [pred, target].into_iter().enumerate() {
            rec.dispatch(
                "lpips.scale_input",
                kernels::lpips::ScaleInput {
                    rgb: img.read(),
                    out: self.acts[k][0].write(),
                },
                &scale,
                grid(3 * w * h),
            )?;
        }
        // Forward, both images side by side (no barrier between them).
        let stack = self.net.stack();
        let (mut at, mut conv_i, mut tap) = (0usize, 0usize, 0usize);
        for s in &stack {
            match *s {
                Stage::Conv {
                    kernel,
                    stride,
                    pad,
                    ..
                } => {
                    let p = self.conv_params(at, kernel, stride, pad);
                    for k in 0..2 {
                        let (wt, bias) = &self.conv[conv_i];
                        rec.dispatch(
                            "lpips.conv_fwd",
                            kernels::lpips::ConvFwd {
                                input: self.acts[k][at].read(),
                                weights: wt.read(),
                                bias: bias.read(),
                                output: self.acts[k][at + 1].write(),
                            },
                            &p,
                            grid(p.out_c * p.out_h * p.out_w),
                        )?;
                    }
                    at += 1;
                    conv_i += 1;
                }
                Stage::Pool { kernel, stride } => {
                    let p = self.pool_params(at, kernel, stride);
                    for k in 0..2 {
                        rec.dispatch(
                            "lpips.pool_fwd",
                            kernels::lpips::PoolFwd {
                                input: self.acts[k][at].read(),
                                output: self.acts[k][at + 1].write(),
                                argmax: self.argmax[k][at + 1].write(),
                            },
                            &p,
                            grid(p.c * p.out_h * p.out_w),
                        )?;
                    }
                    at += 1;
                }
                Stage::Tap => {
                    let (c, th, tw) = self.sizes[at];
                    let p = PoolParams {
                        c,
                        in_h: th,
                        in_w: tw,
                        ..Default::default()
                    };
                    rec.dispatch(
                        "lpips.distance",
                        kernels::lpips::Distance {
                            f0: self.acts[0][at].read(),
                            f1: self.acts[1][at].read(),
                            lin: self.lin[tap].read(),
                            out: self.distances[tap].write(),
                        },
                        &p,
                        grid(th * tw),
                    )?;
                    tap += 1;
                }
            }
        }
        let Some((grad_rgb, lambda)) = grad else {
            return Ok(());
        };
        // Backward from the deepest stage: a tap writes (the deepest) or adds its
        // gradient to its activation's; a conv or pool writes its input's.
        let mut written = vec![false; self.sizes.len()];
        for s in stack.iter().rev() {
            match *s {
                Stage::Tap => {
                    tap -= 1;
                    let (c, th, tw) = self.sizes[at];
                    let p = PoolParams {
                        c,
                        in_h: th,
                        in_w: tw,
                        kernel: u32::from(written[at]),
                        scale: 1.0 / (th * tw) as f32,
                        ..Default::default()
                    };
                    rec.dispatch(
                        "lpips.distance_grad",
                        kernels::lpips::DistanceGrad {
                            f0: self.acts[0][at].read(),
                            f1: self.acts[1][at].read(),
                            lin: self.lin[tap].read(),
                            grad: self.grads[at].write(),
                        },
                        &p,
                        grid(c * th * tw),
                    )?;
                    written[at] = true;
                }
                Stage::Conv {
                    kernel,
                    stride,
                    pad,
                    ..
                } => {
                    conv_i -= 1;
                    at -= 1;
                    let p = self.conv_params(at, kernel, stride, pad);
                    rec.dispatch(
                        "lpips.conv_bwd_input",
                        kernels::lpips::ConvBwdInput {
                            output: self.acts[0][at + 1].read(),
                            grad_out: self.grads[at + 1].read(),
                            weights: self.conv[conv_i].0.read(),
                            grad_in: self.grads[at].write(),
                        },
                        &p,
                        grid(p.in_c * p.in_h * p.in_w),
                    )?;
                    written[at] = true;
                }
                Stage::Pool { kernel, stride } => {
                    at -= 1;
                    let p = self.pool_params(at, kernel, stride);
                    rec.dispatch(
                        "lpips.pool_bwd",
                        kernels::lpips::PoolBwd {
                            argmax: self.argmax[0][at + 1].read(),
                            grad_out: self.grads[at + 1].read(),
                            grad_in: self.grads[at].write(),
                        },
                        &p,
                        grid(p.c * p.in_h * p.in_w),
                    )?;
                    written[at] = true;
                }
            }
        }
        let p = PoolParams {
            c: 3,
            in_h: h,
            in_w: w,
            scale: lambda,
            ..Default::default()
        };
        rec.dispatch(
            "lpips.scale_input_bwd",
            kernels::lpips::ScaleInputBwd {
                grad: self.grads[0].read(),
                grad_rgb: grad_rgb.write(),
            },
            &p,
            grid(3 * w * h),
        )?;
        Ok(())
    }

    fn conv_params(&self, at: usize, kernel: u32, stride: u32, pad: u32) -> ConvParams {
        let ((ic, ih, iw), (oc, oh, ow)) = (self.sizes[at], self.sizes[at + 1]);
        ConvParams {
            in_c: ic,
            in_h: ih,
            in_w: iw,
            out_c: oc,
            out_h: oh,
            out_w: ow,
            kernel,
            stride,
            pad,
            relu: 1,
            _pad: [0; 2],
        }
    }

    fn pool_params(&self, at: usize, kernel: u32, stride: u32) -> PoolParams {
        let ((c, ih, iw), (_, oh, ow)) = (self.sizes[at], self.sizes[at + 1]);
        PoolParams {
            c,
            in_h: ih,
            in_w: iw,
            out_h: oh,
            out_w: ow,
            kernel,
            stride,
            scale: 0.0,
        }
    }

    /// The value of the last recorded evaluation: Σ over tapped layers of the mean
    /// distance (from the host mirrors where the recording that computed it copied the
    /// maps there, otherwise read back from the device).
    pub fn read_value(&mut self, ctx: &Context) -> Result<f64> {
        let mut total = 0.0;
        let mut at = 0;
        let mut tap = 0;
        for s in self.net.stack() {
            match s {
                Stage::Tap => {
                    let (_, h, w) = self.sizes[at];
                    let d = read_through::<f32>(
                        ctx,
                        self.distance_mirrors.get_mut(tap),
                        &mut self.distances[tap],
                        (h * w) as usize,
                    )?;
                    total += d.iter().map(|&v| f64::from(v)).sum::<f64>() / f64::from(h * w);
                    tap += 1;
                }
                _ => at += 1,
            }
        }
        Ok(total)
    }
}

/// CPU reference: LPIPS of two `width × height` HWC RGB images in [0, 1].
/// An image smaller than the stack allows is [`EngineError::ImageTooSmall`], as for
/// [`Lpips::new`].
pub fn reference<F: Real>(
    weights: &LpipsWeights,
    pred: &[F],
    target: &[F],
    width: u32,
    height: u32,
) -> Result<F> {
    let sizes = plan_sizes_or_err(weights.net, width, height)?;
    let t = |name: &str| -> Vec<F> { weights.tensors[name].iter().map(|&v| F::of(v)).collect() };
    let features = |img: &[F]| -> Vec<Vec<F>> {
        let hw = width * height;
        let mut x: Vec<F> = (0..3 * hw)
            .map(|i| {
                let (c, p) = (i / hw, i % hw);
                (F::of(2.0) * img[(3 * p + c) as usize] - F::one() - F::of(LPIPS_SHIFT[c as usize]))
                    / F::of(LPIPS_SCALE[c as usize])
            })
            .collect();
        let mut taps = Vec::new();
        let mut at = 0;
        for s in weights.net.stack() {
            match s {
                Stage::Conv {
                    key,
                    kernel,
                    stride,
                    pad,
                    ..
                } => {
                    let ((ic, ih, iw), (oc, oh, ow)) = (sizes[at], sizes[at + 1]);
                    let p = ConvParams {
                        in_c: ic,
                        in_h: ih,
                        in_w: iw,
                        out_c: oc,
                        out_h: oh,
                        out_w: ow,
                        kernel,
                        stride,
                        pad,
                        relu: 1,
                        _pad: [0; 2],
                    };
                    let (wt, b) = (t(&format!("{key}.weight")), t(&format!("{key}.bias")));
                    x = (0..oc * oh * ow)
                        .map(|i| {
                            conv_at(&p, &x, &wt, &b, i / (oh * ow), (i % (oh * ow)) / ow, i % ow)
                        })
                        .collect();
                    at += 1;
                }
                Stage::Pool { kernel, stride } => {
                    let ((c, ih, iw), (_, oh, ow)) = (sizes[at], sizes[at + 1]);
                    let p = PoolParams {
                        c,
                        in_h: ih,
                        in_w: iw,
                        out_h: oh,
                        out_w: ow,
                        kernel,
                        stride,
                        scale: 0.0,
                    };
                    x = (0..c * oh * ow)
                        .map(|i| pool_at(&p, &x, i / (oh * ow), (i % (oh * ow)) / ow, i % ow).0)
                        .collect();
                    at += 1;
                }
                Stage::Tap => taps.push(x.clone()),
            }
        }
        taps
    };
    let (a, b) = (features(pred), features(target));
    let mut total = F::zero();
    let mut at = 0;
    let mut tap = 0;
    for s in weights.net.stack() {
        match s {
            Stage::Tap => {
                let (c, h, w) = sizes[at];
                let lin = t(&format!("lin{tap}.model.1.weight"));
                let mut sum = F::zero();
                for p in 0..h * w {
                    sum += layer_distance_at(c, h * w, &a[tap], &b[tap], &lin, p);
                }
                total += sum / F::of((h * w) as f32);
                tap += 1;
            }
            _ => at += 1,
        }
    }
    Ok(total)
}
