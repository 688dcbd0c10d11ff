//! The FID Inception-v3 network as pytorch-fid defines it, on the CPU, and the reading
//! of its weights into it: an image in, its 2048 pool3 features out.
//!
//! Network: `pytorch_fid.inception.InceptionV3(use_fid_inception=True)` with its default
//! output block (3, pool3): torchvision's Inception-v3 stem and blocks with the FID
//! patches (FIDInceptionA/C/E_1 average-pool their branch without counting the zero
//! padding, `count_include_pad=False`, and FIDInceptionE_2 max-pools it), the input
//! resized to 299 × 299 (bilinear, `align_corners=False`, no antialiasing, as
//! `F.interpolate`) and mapped from [0, 1] to [-1, 1], and the 2048 channels averaged
//! over the last 8 × 8 map. Every BasicConv2d (convolution without bias, BatchNorm with
//! eps 0.001, ReLU) is one convolution here, the batchnorm folded into its weights and
//! bias; a convolution is im2col + one f32 GEMM (`ndarray`, which calls
//! `matrixmultiply`; the trainer forbids `unsafe`, and `matrixmultiply::sgemm` is an
//! `unsafe fn`). About 5.7 GFLOP per image; images run in parallel, one per core.
//!
//! Weights: a safetensors file holding the state dict of pytorch-fid's
//! `fid_inception_v3()` (the names of its downloaded `pt_inception-2015-12-05-*.pth`):
//! `NAME.conv.weight` (out × in × kh × kw) and `NAME.bn.weight|bias|running_mean|
//! running_var` (out) for every BasicConv2d `NAME` (`Conv2d_1a_3x3`, ...,
//! `Mixed_7c.branch_pool`), float32, as `scripts/fid-to-safetensors.py` writes them.
//! Other tensors (`fc.*`, `num_batches_tracked`) are ignored. Pretrained weights cannot
//! be downloaded here; without a file, FID is "n/a". (The file format itself is
//! `fid_weights`'.)

use std::borrow::Cow;
use std::path::Path;

use ndarray::linalg::general_mat_mul;
use ndarray::{ArrayView2, ArrayViewMut2};

use crate::metrics::fid_weights::{FidWeightsError, SafeTensors};
use crate::TrainerError;

/// Length of a feature vector (pool3).
pub const FEATURE_DIM: usize = 2048;
/// The side every image is resized to.
pub const INPUT_SIDE: usize = 299;
/// torchvision's BasicConv2d BatchNorm epsilon.
pub const BN_EPS: f64 = 0.001;

/// The BasicConv2d `name` with its batchnorm folded in.
fn basic_conv(
    f: &SafeTensors,
    name: &str,
    in_c: usize,
    out_c: usize,
    kernel: (usize, usize),
    stride: usize,
    pad: (usize, usize),
) -> Result<Conv, FidWeightsError> {
    let w = f.tensor(
        &format!("{name}.conv.weight"),
        &[out_c, in_c, kernel.0, kernel.1],
    )?;
    let gamma = f.tensor(&format!("{name}.bn.weight"), &[out_c])?;
    let beta = f.tensor(&format!("{name}.bn.bias"), &[out_c])?;
    let mean = f.tensor(&format!("{name}.bn.running_mean"), &[out_c])?;
    let var = f.tensor(&format!("{name}.bn.running_var"), &[out_c])?;
    if let Some(v) = var.iter().find(|&&v| f64::from(v) + BN_EPS <= 0.0) {
        return Err(FidWeightsError::Bad {
            path: f.path.into(),
            tensor: format!("{name}.bn.running_var"),
            detail: format!("a variance {v} at or below -eps"),
        });
    }
    let k = in_c * kernel.0 * kernel.1;
    let mut weight = Vec::with_capacity(w.len());
    let mut bias = Vec::with_capacity(out_c);
    // y = γ (conv(x) − μ) / √(σ² + ε) + β, with the scale taken into the weights.
    for o in 0..out_c {
        let scale = f64::from(gamma[o]) / (f64::from(var[o]) + BN_EPS).sqrt();
        weight.extend(
            w[o * k..(o + 1) * k]
                .iter()
                .map(|&v| (f64::from(v) * scale) as f32),
        );
        bias.push((f64::from(beta[o]) - f64::from(mean[o]) * scale) as f32);
    }
    Ok(Conv {
        in_c,
        out_c,
        kernel,
        stride,
        pad,
        weight,
        bias,
    })
}

/// A CHW activation.
#[derive(Clone, Debug)]
struct Act {
    c: usize,
    h: usize,
    w: usize,
    data: Vec<f32>,
}

/// Output side of a window of `k` at `stride` over `n` padded by `pad` (floor mode).
fn out_side(n: usize, k: usize, stride: usize, pad: usize) -> usize {
    (n + 2 * pad - k) / stride + 1
}

/// A BasicConv2d: convolution, folded batchnorm, ReLU.
#[derive(Clone, Debug)]
struct Conv {
    in_c: usize,
    out_c: usize,
    kernel: (usize, usize),
    stride: usize,
    pad: (usize, usize),
    /// out_c × (in_c · kh · kw), PyTorch's order.
    weight: Vec<f32>,
    bias: Vec<f32>,
}

impl Conv {
    fn forward(&self, x: &Act) -> Act {
        assert_eq!(x.c, self.in_c, "channels into a convolution");
        let ((kh, kw), (ph, pw), s) = (self.kernel, self.pad, self.stride);
        let (oh, ow) = (out_side(x.h, kh, s, ph), out_side(x.w, kw, s, pw));
        let (k, p) = (self.in_c * kh * kw, oh * ow);
        // A 1 × 1 convolution at stride 1 is a GEMM on the activation itself.
        let cols: Cow<[f32]> = if (kh, kw, s, ph, pw) == (1, 1, 1, 0, 0) {
            Cow::Borrowed(&x.data)
        } else {
            Cow::Owned(im2col(x, self.kernel, s, self.pad, (oh, ow)))
        };
        let mut out = vec![0.0f32; self.out_c * p];
        let w = ArrayView2::from_shape((self.out_c, k), &self.weight)
            .expect("weights are out_c x k by construction");
        let c = ArrayView2::from_shape((k, p), &cols).expect("columns are k x p by construction");
        let mut o = ArrayViewMut2::from_shape((self.out_c, p), &mut out)
            .expect("output is out_c x p by construction");
        general_mat_mul(1.0, &w, &c, 0.0, &mut o);
        for (row, &b) in out.chunks_exact_mut(p).zip(&self.bias) {
            for v in row {
                *v = (*v + b).max(0.0);
            }
        }
        Act {
            c: self.out_c,
            h: oh,
            w: ow,
            data: out,
        }
    }
}

/// The (in_c · kh · kw) × (oh · ow) patch matrix of `x`, zero outside the image.
fn im2col(
    x: &Act,
    (kh, kw): (usize, usize),
    stride: usize,
    (ph, pw): (usize, usize),
    (oh, ow): (usize, usize),
) -> Vec<f32> {
    let p = oh * ow;
    let mut cols = vec![0.0f32; x.c * kh * kw * p];
    for c in 0..x.c {
        let plane = &x.data[c * x.h * x.w..(c + 1) * x.h * x.w];
        for i in 0..kh {
            for j in 0..kw {
                let row = &mut cols[((c * kh + i) * kw + j) * p..][..p];
                for oy in 0..oh {
                    let Some(iy) = (oy * stride + i).checked_sub(ph).filter(|&y| y < x.h) else {
                        continue;
                    };
                    for ox in 0..ow {
                        if let Some(ix) = (ox * stride + j).checked_sub(pw).filter(|&v| v < x.w) {
                            row[oy * ow + ox] = plane[iy * x.w + ix];
                        }
                    }
                }
            }
        }
    }
    cols
}

/// Max pool (padding ignored, as PyTorch's -inf padding; floor mode).
fn max_pool(x: &Act, k: usize, stride: usize, pad: usize) -> Act {
    let (oh, ow) = (out_side(x.h, k, stride, pad), out_side(x.w, k, stride, pad));
    let mut data = Vec::with_capacity(x.c * oh * ow);
    for plane in x.data.chunks_exact(x.h * x.w) {
        for oy in 0..oh {
            for ox in 0..ow {
                let mut m = f32::NEG_INFINITY;
                for y in (oy * stride).saturating_sub(pad)
                    ..(oy * stride + k).saturating_sub(pad).min(x.h)
                {
                    for xx in (ox * stride).saturating_sub(pad)
                        ..(ox * stride + k).saturating_sub(pad).min(x.w)
                    {
                        m = m.max(plane[y * x.w + xx]);
                    }
                }
                data.push(m);
            }
        }
    }
    Act {
        c: x.c,
        h: oh,
        w: ow,
        data,
    }
}

/// 3 × 3 average pool, stride 1, padding 1, dividing by the pixels inside the image
/// (`count_include_pad=False`, the FID blocks' patch).
fn avg_pool_3x3_same(x: &Act) -> Act {
    let mut data = Vec::with_capacity(x.data.len());
    for plane in x.data.chunks_exact(x.h * x.w) {
        for y in 0..x.h {
            for xx in 0..x.w {
                let (ys, xs) = (
                    y.saturating_sub(1)..(y + 2).min(x.h),
                    xx.saturating_sub(1)..(xx + 2).min(x.w),
                );
                let count = (ys.len() * xs.len()) as f32;
                let sum: f32 = ys
                    .flat_map(|yy| xs.clone().map(move |xx| (yy, xx)))
                    .map(|(yy, xx)| plane[yy * x.w + xx])
                    .sum();
                data.push(sum / count);
            }
        }
    }
    Act {
        c: x.c,
        h: x.h,
        w: x.w,
        data,
    }
}

/// The 3 × 3 stride-1 max pool of FIDInceptionE_2's pool branch (padding 1).
fn max_pool_3x3_same(x: &Act) -> Act {
    max_pool(x, 3, 1, 1)
}

/// Channel concatenation of maps of one size.
fn concat(parts: Vec<Act>) -> Act {
    let (h, w) = (parts[0].h, parts[0].w);
    assert!(
        parts.iter().all(|p| p.h == h && p.w == w),
        "concatenated maps differ in size"
    );
    let c = parts.iter().map(|p| p.c).sum();
    Act {
        c,
        h,
        w,
        data: parts.into_iter().flat_map(|p| p.data).collect(),
    }
}

/// Mixed_5b/c/d: FIDInceptionA.
struct BlockA {
    b1x1: Conv,
    b5x5: [Conv; 2],
    b3x3dbl: [Conv; 3],
    pool: Conv,
}

impl BlockA {
    fn load(
        f: &SafeTensors,
        name: &str,
        in_c: usize,
        pool_features: usize,
    ) -> Result<Self, FidWeightsError> {
        let c =
            |branch: &str, i, o, k, p| basic_conv(f, &format!("{name}.{branch}"), i, o, k, 1, p);
        Ok(Self {
            b1x1: c("branch1x1", in_c, 64, (1, 1), (0, 0))?,
            b5x5: [
                c("branch5x5_1", in_c, 48, (1, 1), (0, 0))?,
                c("branch5x5_2", 48, 64, (5, 5), (2, 2))?,
            ],
            b3x3dbl: [
                c("branch3x3dbl_1", in_c, 64, (1, 1), (0, 0))?,
                c("branch3x3dbl_2", 64, 96, (3, 3), (1, 1))?,
                c("branch3x3dbl_3", 96, 96, (3, 3), (1, 1))?,
            ],
            pool: c("branch_pool", in_c, pool_features, (1, 1), (0, 0))?,
        })
    }

    fn forward(&self, x: &Act) -> Act {
        concat(vec![
            self.b1x1.forward(x),
            chain(&self.b5x5, x),
            chain(&self.b3x3dbl, x),
            self.pool.forward(&avg_pool_3x3_same(x)),
        ])
    }
}

/// Mixed_6a: torchvision's InceptionB (unpatched).
struct BlockB {
    b3x3: Conv,
    b3x3dbl: [Conv; 3],
}

impl BlockB {
    fn load(f: &SafeTensors, name: &str, in_c: usize) -> Result<Self, FidWeightsError> {
        let c =
            |branch: &str, i, o, k, s, p| basic_conv(f, &format!("{name}.{branch}"), i, o, k, s, p);
        Ok(Self {
            b3x3: c("branch3x3", in_c, 384, (3, 3), 2, (0, 0))?,
            b3x3dbl: [
                c("branch3x3dbl_1", in_c, 64, (1, 1), 1, (0, 0))?,
                c("branch3x3dbl_2", 64, 96, (3, 3), 1, (1, 1))?,
                c("branch3x3dbl_3", 96, 96, (3, 3), 2, (0, 0))?,
            ],
        })
    }

    fn forward(&self, x: &Act) -> Act {
        concat(vec![
            self.b3x3.forward(x),
            chain(&self.b3x3dbl, x),
            max_pool(x, 3, 2, 0),
        ])
    }
}

/// Mixed_6b/c/d/e: FIDInceptionC.
struct BlockC {
    b1x1: Conv,
    b7x7: [Conv; 3],
    b7x7dbl: [Conv; 5],
    pool: Conv,
}

impl BlockC {
    fn load(f: &SafeTensors, name: &str, in_c: usize, c7: usize) -> Result<Self, FidWeightsError> {
        let c =
            |branch: &str, i, o, k, p| basic_conv(f, &format!("{name}.{branch}"), i, o, k, 1, p);
        let (row, col) = (((1, 7), (0, 3)), ((7, 1), (3, 0)));
        Ok(Self {
            b1x1: c("branch1x1", in_c, 192, (1, 1), (0, 0))?,
            b7x7: [
                c("branch7x7_1", in_c, c7, (1, 1), (0, 0))?,
                c("branch7x7_2", c7, c7, row.0, row.1)?,
                c("branch7x7_3", c7, 192, col.0, col.1)?,
            ],
            b7x7dbl: [
                c("branch7x7dbl_1", in_c, c7, (1, 1), (0, 0))?,
                c("branch7x7dbl_2", c7, c7, col.0, col.1)?,
                c("branch7x7dbl_3", c7, c7, row.0, row.1)?,
                c("branch7x7dbl_4", c7, c7, col.0, col.1)?,
                c("branch7x7dbl_5", c7, 192, row.0, row.1)?,
            ],
            pool: c("branch_pool", in_c, 192, (1, 1), (0, 0))?,
        })
    }

    fn forward(&self, x: &Act) -> Act {
        concat(vec![
            self.b1x1.forward(x),
            chain(&self.b7x7, x),
            chain(&self.b7x7dbl, x),
            self.pool.forward(&avg_pool_3x3_same(x)),
        ])
    }
}

/// Mixed_7a: torchvision's InceptionD (unpatched).
struct BlockD {
    b3x3: [Conv; 2],
    b7x7x3: [Conv; 4],
}

impl BlockD {
    fn load(f: &SafeTensors, name: &str, in_c: usize) -> Result<Self, FidWeightsError> {
        let c =
            |branch: &str, i, o, k, s, p| basic_conv(f, &format!("{name}.{branch}"), i, o, k, s, p);
        Ok(Self {
            b3x3: [
                c("branch3x3_1", in_c, 192, (1, 1), 1, (0, 0))?,
                c("branch3x3_2", 192, 320, (3, 3), 2, (0, 0))?,
            ],
            b7x7x3: [
                c("branch7x7x3_1", in_c, 192, (1, 1), 1, (0, 0))?,
                c("branch7x7x3_2", 192, 192, (1, 7), 1, (0, 3))?,
                c("branch7x7x3_3", 192, 192, (7, 1), 1, (3, 0))?,
                c("branch7x7x3_4", 192, 192, (3, 3), 2, (0, 0))?,
            ],
        })
    }

    fn forward(&self, x: &Act) -> Act {
        concat(vec![
            chain(&self.b3x3, x),
            chain(&self.b7x7x3, x),
            max_pool(x, 3, 2, 0),
        ])
    }
}

/// How an E block pools its last branch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum EPool {
    /// FIDInceptionE_1 (Mixed_7b): average without the padding.
    Avg,
    /// FIDInceptionE_2 (Mixed_7c): max (the TensorFlow graph's quirk pytorch-fid keeps).
    Max,
}

/// Mixed_7b/c: FIDInceptionE_1 / FIDInceptionE_2.
struct BlockE {
    b1x1: Conv,
    b3x3_1: Conv,
    b3x3_2: [Conv; 2],
    b3x3dbl: [Conv; 2],
    b3x3dbl_3: [Conv; 2],
    pool: Conv,
    pool_kind: EPool,
}

impl BlockE {
    fn load(
        f: &SafeTensors,
        name: &str,
        in_c: usize,
        pool_kind: EPool,
    ) -> Result<Self, FidWeightsError> {
        let c =
            |branch: &str, i, o, k, p| basic_conv(f, &format!("{name}.{branch}"), i, o, k, 1, p);
        Ok(Self {
            b1x1: c("branch1x1", in_c, 320, (1, 1), (0, 0))?,
            b3x3_1: c("branch3x3_1", in_c, 384, (1, 1), (0, 0))?,
            b3x3_2: [
                c("branch3x3_2a", 384, 384, (1, 3), (0, 1))?,
                c("branch3x3_2b", 384, 384, (3, 1), (1, 0))?,
            ],
            b3x3dbl: [
                c("branch3x3dbl_1", in_c, 448, (1, 1), (0, 0))?,
                c("branch3x3dbl_2", 448, 384, (3, 3), (1, 1))?,
            ],
            b3x3dbl_3: [
                c("branch3x3dbl_3a", 384, 384, (1, 3), (0, 1))?,
                c("branch3x3dbl_3b", 384, 384, (3, 1), (1, 0))?,
            ],
            pool: c("branch_pool", in_c, 192, (1, 1), (0, 0))?,
            pool_kind,
        })
    }

    fn forward(&self, x: &Act) -> Act {
        let b3 = self.b3x3_1.forward(x);
        let bd = chain(&self.b3x3dbl, x);
        let pooled = match self.pool_kind {
            EPool::Avg => avg_pool_3x3_same(x),
            EPool::Max => max_pool_3x3_same(x),
        };
        concat(vec![
            self.b1x1.forward(x),
            self.b3x3_2[0].forward(&b3),
            self.b3x3_2[1].forward(&b3),
            self.b3x3dbl_3[0].forward(&bd),
            self.b3x3dbl_3[1].forward(&bd),
            self.pool.forward(&pooled),
        ])
    }
}

/// Convolutions applied one after another.
fn chain(convs: &[Conv], x: &Act) -> Act {
    let mut y = convs[0].forward(x);
    for c in &convs[1..] {
        y = c.forward(&y);
    }
    y
}

/// The FID Inception network up to pool3, with its weights.
pub struct FidInception {
    stem: [Conv; 3],
    stem2: [Conv; 2],
    a: [BlockA; 3],
    b: BlockB,
    c: [BlockC; 4],
    d: BlockD,
    e: [BlockE; 2],
}

impl std::fmt::Debug for FidInception {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FidInception")
    }
}

/// One image for [`FidInception::features_of_images`]: HWC RGB in [0, 1].
#[derive(Clone, Copy, Debug)]
pub struct ImageRef<'a> {
    pub rgb: &'a [f32],
    pub width: u32,
    pub height: u32,
}

impl FidInception {
    /// Reads a weights file (see the module header) and checks every tensor: present,
    /// float32, of the right shape, finite and inside the file.
    pub fn load(path: &Path) -> Result<Self, FidWeightsError> {
        let bytes = std::fs::read(path).map_err(|error| FidWeightsError::Io {
            path: path.into(),
            error,
        })?;
        let f = SafeTensors::parse(path, &bytes)?;
        Ok(Self {
            stem: [
                basic_conv(&f, "Conv2d_1a_3x3", 3, 32, (3, 3), 2, (0, 0))?,
                basic_conv(&f, "Conv2d_2a_3x3", 32, 32, (3, 3), 1, (0, 0))?,
                basic_conv(&f, "Conv2d_2b_3x3", 32, 64, (3, 3), 1, (1, 1))?,
            ],
            stem2: [
                basic_conv(&f, "Conv2d_3b_1x1", 64, 80, (1, 1), 1, (0, 0))?,
                basic_conv(&f, "Conv2d_4a_3x3", 80, 192, (3, 3), 1, (0, 0))?,
            ],
            a: [
                BlockA::load(&f, "Mixed_5b", 192, 32)?,
                BlockA::load(&f, "Mixed_5c", 256, 64)?,
                BlockA::load(&f, "Mixed_5d", 288, 64)?,
            ],
            b: BlockB::load(&f, "Mixed_6a", 288)?,
            c: [
                BlockC::load(&f, "Mixed_6b", 768, 128)?,
                BlockC::load(&f, "Mixed_6c", 768, 160)?,
                BlockC::load(&f, "Mixed_6d", 768, 160)?,
                BlockC::load(&f, "Mixed_6e", 768, 192)?,
            ],
            d: BlockD::load(&f, "Mixed_7a", 768)?,
            e: [
                BlockE::load(&f, "Mixed_7b", 1280, EPool::Avg)?,
                BlockE::load(&f, "Mixed_7c", 2048, EPool::Max)?,
            ],
        })
    }

    /// The 2048 pool3 features of one HWC RGB image in [0, 1] of any size.
    pub fn features(&self, rgb: &[f32], width: u32, height: u32) -> crate::Result<Vec<f32>> {
        let x = network_input(rgb, width as usize, height as usize)?;
        let x = max_pool(&chain(&self.stem, &x), 3, 2, 0);
        let mut x = max_pool(&chain(&self.stem2, &x), 3, 2, 0);
        for a in &self.a {
            x = a.forward(&x);
        }
        x = self.b.forward(&x);
        for c in &self.c {
            x = c.forward(&x);
        }
        x = self.d.forward(&x);
        for e in &self.e {
            x = e.forward(&x);
        }
        debug_assert_eq!(x.c, FEATURE_DIM);
        Ok(x.data
            .chunks_exact(x.h * x.w)
            .map(|plane| {
                (plane.iter().map(|&v| f64::from(v)).sum::<f64>() / plane.len() as f64) as f32
            })
            .collect())
    }

    /// [`features`](Self::features) of several images, one per core at a time, in order.
    pub fn features_of_images(&self, images: &[ImageRef]) -> crate::Result<Vec<Vec<f32>>> {
        let threads = std::thread::available_parallelism()
            .map_or(1, |n| n.get())
            .min(images.len())
            .max(1);
        let next = std::sync::atomic::AtomicUsize::new(0);
        type Features = crate::Result<Vec<f32>>;
        let done: Vec<Vec<(usize, Features)>> = std::thread::scope(|s| {
            let workers: Vec<_> = (0..threads)
                .map(|_| {
                    s.spawn(|| {
                        let mut out = Vec::new();
                        loop {
                            let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                            let Some(im) = images.get(i) else { break out };
                            out.push((i, self.features(im.rgb, im.width, im.height)));
                        }
                    })
                })
                .collect();
            workers
                .into_iter()
                .map(|w| w.join().unwrap_or_else(|p| std::panic::resume_unwind(p)))
                .collect()
        });
        // The workers took every index once between them: sorted, one result per image.
        let mut results: Vec<(usize, Features)> = done.into_iter().flatten().collect();
        results.sort_unstable_by_key(|&(i, _)| i);
        debug_assert!(
            results.iter().enumerate().all(|(k, &(i, _))| k == i),
            "an image was skipped or taken twice"
        );
        results.into_iter().map(|(_, r)| r).collect()
    }
}

/// An HWC RGB image in [0, 1] as the network's 3 × 299 × 299 input in [-1, 1]:
/// `F.interpolate(x, (299, 299), mode="bilinear", align_corners=False)` (no
/// antialiasing), then `2x − 1`, in f32 as PyTorch computes them on the CPU.
fn network_input(rgb: &[f32], width: usize, height: usize) -> crate::Result<Act> {
    if width == 0 || height == 0 || rgb.len() != 3 * width * height {
        return Err(TrainerError::invalid(
            "FID input",
            format!("{} values for a {width} x {height} RGB image", rgb.len()),
        ));
    }
    if rgb.iter().any(|v| !v.is_finite()) {
        return Err(TrainerError::numeric(
            "FID input",
            format!("a non-finite pixel in a {width} x {height} image"),
        ));
    }
    // Per output index: (first source index, second source index, weight of the second).
    let taps = |n_in: usize| -> Vec<(usize, usize, f32)> {
        let scale = n_in as f32 / INPUT_SIDE as f32;
        (0..INPUT_SIDE)
            .map(|o| {
                let src = (scale * (o as f32 + 0.5) - 0.5).max(0.0);
                let i0 = (src as usize).min(n_in - 1);
                let i1 = if i0 < n_in - 1 { i0 + 1 } else { i0 };
                (i0, i1, src - i0 as f32)
            })
            .collect()
    };
    let (ty, tx) = (taps(height), taps(width));
    let n = INPUT_SIDE * INPUT_SIDE;
    let mut data = vec![0.0f32; 3 * n];
    for (oy, &(y0, y1, ly)) in ty.iter().enumerate() {
        for (ox, &(x0, x1, lx)) in tx.iter().enumerate() {
            let px = |y: usize, x: usize, c: usize| rgb[3 * (y * width + x) + c];
            for c in 0..3 {
                let v = (1.0 - ly) * ((1.0 - lx) * px(y0, x0, c) + lx * px(y0, x1, c))
                    + ly * ((1.0 - lx) * px(y1, x0, c) + lx * px(y1, x1, c));
                data[c * n + oy * INPUT_SIDE + ox] = 2.0 * v - 1.0;
            }
        }
    }
    Ok(Act {
        c: 3,
        h: INPUT_SIDE,
        w: INPUT_SIDE,
        data,
    })
}
