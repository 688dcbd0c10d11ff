//! Multi-layer perceptrons on the GPU (kernels `nn::*` and, on CPU devices,
//! `nn_lavapipe::*`): linear layers as a GEMM (workgroup-tiled on GPUs; register-blocked, or
//! subgroup and texel-reading kernels on CPU devices: [`GemmVariant`]), GELU / sigmoid / exp / softmax activations, several
//! output heads on one trunk, forward and backward, and the CPU reference from the same
//! shared functions (`drape_shared::nn`), generic over f32/f64.
//!
//! An [`Mlp`] is described by an input width, hidden layers (width and activation) and
//! heads (width, activation, optional zero init): `x → [Linear → act]* → {Linear_h →
//! act_h}` for every head h. Heads are separate linear layers on the last hidden
//! output, which is the same function as one linear layer over the concatenated
//! heads followed by per-column-range activations. All weights and biases live in
//! one flat parameter buffer (for each layer: W out × in, row-major as PyTorch's
//! `nn.Linear.weight`, then b, each starting on a 16-byte boundary:
//! [`MlpDesc::layout`]), so one Adam group covers a decoder.
//!
//! Weight normalisation (PyTorch's `weight_norm(dim=0)`, which HUGS puts on its
//! deformation decoder) is an option per linear layer ([`MlpDesc::weight_norm`]): the
//! layer's `W` slot holds the direction `v` and its norms `g` (one per output) follow
//! every layer's parameters at the end of the buffer; the forward pass writes
//! `W = g v / ‖v‖` into a copy of the parameters that the GEMMs read
//! (`nn::weight_norm_fwd`), and the backward turns `∂L/∂W` into `∂L/∂v` and `∂L/∂g`
//! (`nn::weight_norm_bwd`; `drape_shared::nn` is the math).
//!
//! Backward is deterministic: the weight gradient sums rows in fixed chunks and adds
//! the chunks in order (`nn::sum_weight_grad`), with no atomics.

use drape_shared::nn::{
    activate, activate_bwd, softmax_row, softmax_row_bwd, weight_norm_row_bwd,
    weight_norm_row_norm, weight_norm_value, ActParams, GemmParams, WeightGradParams,
    WeightNormParams, ACT_EXP, ACT_GELU, ACT_IDENTITY, ACT_SIGMOID, ACT_SOFTMAX, GEMM_ACCUMULATE,
    GEMM_BIAS, GEMM_BLOCK, GEMM_FWD_ROWS, GEMM_NARROW_ROWS, GEMM_ONES_ROW, GEMM_SG_COLS,
    GEMM_SG_ROWS, GEMM_TILE, GEMM_TX_ROWS, SOFTMAX_MAX_WIDTH,
};
use drape_shared::real::Real;
use rand::{Rng, SeedableRng};

use crate::buffer::{Buffer, BufferDesc};
use crate::context::{Context, DeviceKind};
use crate::error::{EngineError, Result};
use crate::kernels;
use crate::kernels::nn::{ActBwdKernel, ActFwdKernel, GemmTiledKernel as GemmKernel};
use crate::recorder::{flat_grid as grid, Recording};

/// An activation after a linear layer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Activation {
    /// `x`.
    Identity,
    /// `x Φ(x)` (PyTorch's default, erf form).
    Gelu,
    /// `1 / (1 + e^-x)`.
    Sigmoid,
    /// `e^x`.
    Exp,
    /// `softmax(x / temperature)` over the layer's whole output (at most 32 wide).
    Softmax {
        /// Divides the inputs before the softmax.
        temperature: f32,
    },
}

impl Activation {
    fn kind(self) -> u32 {
        match self {
            Activation::Identity => ACT_IDENTITY,
            Activation::Gelu => ACT_GELU,
            Activation::Sigmoid => ACT_SIGMOID,
            Activation::Exp => ACT_EXP,
            Activation::Softmax { .. } => ACT_SOFTMAX,
        }
    }

    fn temperature(self) -> f32 {
        match self {
            Activation::Softmax { temperature } => temperature,
            _ => 1.0,
        }
    }
}

/// One output head.
#[derive(Clone, Debug, PartialEq)]
pub struct HeadDesc {
    /// Names the head in checkpoints and buffer names.
    pub name: String,
    /// Outputs per row.
    pub width: usize,
    /// The activation on its outputs.
    pub activation: Activation,
    /// Start with zero weights and bias (so the head first outputs `act(0)`).
    pub zero_init: bool,
}

impl HeadDesc {
    /// A head with random initial weights.
    pub fn new(name: &str, width: usize, activation: Activation) -> Self {
        Self {
            name: name.to_string(),
            width,
            activation,
            zero_init: false,
        }
    }

    /// The head with zero initial weights and bias.
    pub fn zero_init(mut self) -> Self {
        self.zero_init = true;
        self
    }
}

/// The shape of an MLP.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MlpDesc {
    /// Inputs per row.
    pub input: usize,
    /// (width, activation) of each hidden layer.
    pub hidden: Vec<(usize, Activation)>,
    /// The output heads, each a linear layer on the last hidden layer.
    pub heads: Vec<HeadDesc>,
    /// Linear layers (hidden layers, then heads, counted from 0) under weight
    /// normalisation, in increasing order.
    pub weight_norm: Vec<usize>,
}

impl MlpDesc {
    /// HUGS's appearance decoder: 96-64-64 (GELU) → opacity logit (1) and SH (48).
    /// The opacity head has no activation here because the splatter applies the
    /// sigmoid to the logit itself (the same function as HUGS's sigmoid head).
    pub fn hugs_appearance(input: usize, sh_values: usize) -> Self {
        Self {
            input,
            hidden: vec![(64, Activation::Gelu), (64, Activation::Gelu)],
            heads: vec![
                HeadDesc::new("opacity", 1, Activation::Identity),
                HeadDesc::new("sh", sh_values, Activation::Identity),
            ],
            weight_norm: Vec::new(),
        }
    }

    /// HUGS's geometry decoder: 96-128-128 (GELU) → offset (3), 6D rotation (6),
    /// log-scale delta (3).
    pub fn hugs_geometry(input: usize) -> Self {
        Self {
            input,
            hidden: vec![(128, Activation::Gelu), (128, Activation::Gelu)],
            heads: vec![
                HeadDesc::new("offset", 3, Activation::Identity),
                HeadDesc::new("rot6d", 6, Activation::Identity),
                HeadDesc::new("log_scale_delta", 3, Activation::Identity),
            ],
            weight_norm: Vec::new(),
        }
    }

    /// HUGS's deformation decoder: 96-128-128-128-128 (GELU) → 24 skinning weights
    /// (softmax, T = 0.1).
    pub fn hugs_deformation(input: usize) -> Self {
        Self {
            input,
            hidden: vec![(128, Activation::Gelu); 4],
            heads: vec![HeadDesc::new(
                "skinning_weights",
                24,
                Activation::Softmax { temperature: 0.1 },
            )],
            weight_norm: Vec::new(),
        }
    }

    /// The same MLP with weight normalisation on linear layer `layer` (HUGS: the
    /// deformation decoder's last hidden layer, before the skinning logits).
    pub fn with_weight_norm(mut self, layer: usize) -> Self {
        if !self.weight_norm.contains(&layer) {
            self.weight_norm.push(layer);
            self.weight_norm.sort_unstable();
        }
        self
    }

    /// Where each weight-normalised layer's `g` lives: (`WeightNormParams` of the layer).
    pub fn weight_norm_params(&self) -> Vec<WeightNormParams> {
        let (offsets, mut at) = self.plain_layout();
        let linears = self.linears();
        self.weight_norm
            .iter()
            .map(|&l| {
                let (i, o) = linears[l];
                let p = WeightNormParams {
                    out_features: o as u32,
                    in_features: i as u32,
                    w_off: offsets[l].0 as u32,
                    g_off: at as u32,
                };
                at += o;
                p
            })
            .collect()
    }

    /// The same MLP with every hidden layer at most `max_width` wide (a speed knob:
    /// `hugs_deformation(96).capped(64)` is 96-64-64-64-64 → 24). Heads keep their
    /// widths.
    pub fn capped(mut self, max_width: usize) -> Self {
        for (w, _) in &mut self.hidden {
            *w = (*w).min(max_width.max(1));
        }
        self
    }

    /// (in, out) of every linear layer: the hidden layers, then the heads.
    pub fn linears(&self) -> Vec<(usize, usize)> {
        let mut out = Vec::new();
        let mut width = self.input;
        for &(w, _) in &self.hidden {
            out.push((width, w));
            width = w;
        }
        for h in &self.heads {
            out.push((width, h.width));
        }
        out
    }

    /// Offsets of (W, b) of each linear layer in the flat parameter vector, and its
    /// length (the weight-normalised layers' `g` come after every `W` and `b`). `W`
    /// (out × in, row-major) is `in · out` floats from its offset; padding may follow
    /// it before `b` (see `plain_layout`).
    pub fn layout(&self) -> (Vec<(usize, usize)>, usize) {
        let (offsets, at) = self.plain_layout();
        let gs: usize = self.weight_norm.iter().map(|&l| self.linears()[l].1).sum();
        (offsets, at + gs)
    }

    /// Every `W` and `b` starts on a whole 16-byte texel (4 floats; the floats between
    /// are zero padding, with zero gradients): the forward GEMMs on CPU devices read
    /// `W` and the bias through 4-float texel views, which address whole texels, so a
    /// layer after a head of odd width (the 1-wide opacity before the 48 SH) would
    /// otherwise fall back to a much slower kernel (docs/performance.md, "GEMM and the
    /// decoders").
    fn plain_layout(&self) -> (Vec<(usize, usize)>, usize) {
        let aligned = |at: usize| at.next_multiple_of(4);
        let mut at = 0;
        let mut offsets = Vec::new();
        for (i, o) in self.linears() {
            let w = aligned(at);
            let b = aligned(w + i * o);
            offsets.push((w, b));
            at = b + o;
        }
        (offsets, aligned(at))
    }

    /// Width of the trunk's output (the heads' input).
    pub fn trunk_width(&self) -> usize {
        self.hidden.last().map_or(self.input, |h| h.0)
    }

    fn activations(&self) -> Vec<Activation> {
        self.hidden
            .iter()
            .map(|h| h.1)
            .chain(self.heads.iter().map(|h| h.activation))
            .collect()
    }

    fn check(&self) {
        assert!(!self.heads.is_empty(), "an MLP needs at least one head");
        assert!(
            self.weight_norm.windows(2).all(|w| w[0] < w[1]),
            "weight_norm layers must be increasing"
        );
        assert!(
            self.weight_norm.iter().all(|&l| l < self.linears().len()),
            "weight_norm names a layer the MLP does not have"
        );
        for (i, o) in self.linears() {
            assert!(
                i > 0 && o > 0 && i <= 1024 && o <= 1024,
                "layer widths must be 1..=1024, got {i} -> {o}"
            );
        }
        for a in self.activations() {
            if let Activation::Softmax { temperature } = a {
                assert!(temperature > 0.0, "softmax temperature must be positive");
            }
        }
        for h in &self.heads {
            if matches!(h.activation, Activation::Softmax { .. }) {
                assert!(
                    h.width <= SOFTMAX_MAX_WIDTH,
                    "softmax heads are at most {SOFTMAX_MAX_WIDTH} wide"
                );
            }
        }
        for &(w, a) in &self.hidden {
            if matches!(a, Activation::Softmax { .. }) {
                assert!(
                    w <= SOFTMAX_MAX_WIDTH,
                    "softmax layers are at most {SOFTMAX_MAX_WIDTH} wide"
                );
            }
        }
    }

    /// Parameters initialised as PyTorch's `nn.Linear` default (weights and biases
    /// uniform in ±1/√in), reproducible from `seed`; zero-init heads are zero.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let (offsets, len) = self.layout();
        let mut params = vec![0.0f32; len];
        let hidden = self.hidden.len();
        for (l, ((i, o), (w_off, b_off))) in self.linears().into_iter().zip(offsets).enumerate() {
            if l >= hidden && self.heads[l - hidden].zero_init {
                continue;
            }
            let bound = 1.0 / (i as f32).sqrt();
            // W then b, drawn in that order: which values a seed gives depends on it.
            for at in (w_off..w_off + i * o).chain(b_off..b_off + o) {
                params[at] = rng.random_range(-bound..bound);
            }
        }
        // As PyTorch's `weight_norm` when applied to an initialised layer: v = W and
        // g = ‖W_o‖, so the layer starts as the plain one.
        let wide: Vec<f64> = params.iter().map(|&v| f64::from(v)).collect();
        for p in self.weight_norm_params() {
            for o in 0..p.out_features as usize {
                params[p.g_off as usize + o] = weight_norm_row_norm(&wide, &p, o) as f32;
            }
        }
        params
    }
}

/// Which GEMM kernel an [`Mlp`] records.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum GemmVariant {
    /// On CPU devices (lavapipe): [`Texel4`](Self::Texel4) where subgroups are 8
    /// lanes with ballot operations, the operands can be texel views and `C` has at
    /// least 16 columns or a narrow kernel fits, else [`Subgroup`](Self::Subgroup) for
    /// 16 columns or more, else the register-blocked one (narrow heads waste less of its
    /// 8-column blocks); on GPUs the workgroup-tiled kernel.
    #[default]
    Auto,
    /// `nn::gemm_tiled`: slices of `B` staged in workgroup memory.
    Tiled,
    /// `nn_lavapipe::gemm_blocked`: 8 × 8 blocks in registers.
    Blocked,
    /// `nn_lavapipe::gemm_subgroup`: 32 × 32 tiles per subgroup of 8, `B` shared by
    /// broadcasts. Needs subgroups of exactly 8 lanes with ballot operations.
    Subgroup,
    /// `nn_lavapipe::gemm_texel`: `gemm_subgroup` reading `A` and `B` as uniform texel
    /// buffers (on llvmpipe a gather per read instead of a loop over the lanes; the same
    /// sums in the same order). Same device needs, and both operands within
    /// `maxTexelBufferElements` floats.
    Texel,
    /// The 4-float texel kernels of `nn_lavapipe`, chosen by the operands' layout:
    /// `gemm_fwd_cols*` for forwards (`record_fwd`), `gemm_input_grad*`,
    /// `gemm_weight_grad_*` or `gemm_b_along_n*` for the backward
    /// (`narrow_weight_grad_kernel`, `texel4_grad_kernel`); `gemm_texel` where none
    /// fits. [`Texel`](Self::Texel)'s tiles reading 4 floats a fetch, the operand shared
    /// by the subgroup fetched by every lane at one address instead of broadcast (on
    /// llvmpipe a broadcast costs about what a fetch does). The same sums in the same
    /// order as `Texel` (but the narrow weight gradients'). Same device needs.
    Texel4,
}

/// Whether the device can run `nn_lavapipe::gemm_subgroup` (subgroups of 8 lanes, ballot
/// operations in compute).
pub fn subgroup_gemm_supported(info: &crate::DeviceInfo) -> bool {
    info.subgroup_size == 8 && info.subgroup_ballot
}

/// Largest number of chunks the weight gradient's rows are split into (2M rows give
/// chunks of 8,192, well inside llvmpipe's 65,535 loop iterations per invocation).
const MAX_SPLITS: u32 = 256;
/// Fewest rows one split of the weight gradient sums on a CPU device: there a split
/// is a core's serial loop, and more splits only add partials to sum.
const MIN_ROWS_PER_SPLIT_CPU: u32 = 1024;
/// The same on a GPU: a split and an output tile make one workgroup, so the splits are
/// what fills the device. A decoder layer's weight gradient has 4-12 output tiles; at
/// the avatar's few thousand Gaussians per layer, 1,024 rows per split would give 12-36
/// workgroups, far fewer than a large GPU's multiprocessors (an H100 has 132), each
/// walking 1,024 rows alone (docs/performance.md, H100 "Training", has the figures).
const MIN_ROWS_PER_SPLIT_GPU: u32 = 128;

/// How many chunks the weight gradient's `rows` are summed in, and the rows per chunk.
fn splits_for(rows: u32, min_rows_per_split: u32) -> (u32, u32) {
    let splits = rows.div_ceil(min_rows_per_split).clamp(1, MAX_SPLITS);
    (splits, rows.div_ceil(splits).max(1))
}

fn f32_buffer(ctx: &Context, name: &str, len: usize) -> Result<Buffer> {
    ctx.create_buffer(name, BufferDesc::gpu_only(len as u64 * 4))
}

/// Activations of one linear layer for up to `max_rows` rows.
struct LayerBuffers {
    /// Linear output (before the activation).
    pre: Buffer,
    /// Activation output (unused for the identity: `pre` is the output).
    post: Buffer,
    /// Gradient on the output.
    grad_post: Buffer,
    /// Gradient on `pre` (unused for the identity).
    grad_pre: Buffer,
}

/// An MLP's parameters, gradients and saved activations on the GPU.
pub struct Mlp {
    /// The shape it was built for.
    pub desc: MlpDesc,
    /// The GEMM kernel to record (both give the same sums in the same order).
    pub variant: GemmVariant,
    max_rows: u32,
    offsets: Vec<(usize, usize)>,
    /// All weights and biases (see the module header).
    pub params: Buffer,
    /// Their gradients, written by [`Mlp::record_backward`].
    pub grads: Buffer,
    layers: Vec<LayerBuffers>,
    partials: Buffer,
    /// Fewest rows per chunk of the weight gradient on this device (see [`splits_for`]).
    min_rows_per_split: u32,
    /// With weight normalisation: the parameters with every normalised `W` slot holding
    /// `g v / ‖v‖` (what the GEMMs read); without, the GEMMs read `params`.
    effective: Option<Buffer>,
}

/// The linear layer whose output layer `l` reads (`None`: the MLP's input); heads
/// (`l >= hidden`) read the last hidden layer.
fn below(l: usize, hidden: usize) -> Option<usize> {
    if l < hidden {
        l.checked_sub(1)
    } else {
        hidden.checked_sub(1)
    }
}

impl Mlp {
    /// An MLP for up to `max_rows` rows with parameters from [`MlpDesc::init_params`].
    pub fn new(
        ctx: &Context,
        label: &str,
        desc: MlpDesc,
        max_rows: usize,
        seed: u64,
    ) -> Result<Self> {
        let params = desc.init_params(seed);
        Self::with_params(ctx, label, desc, max_rows, &params)
    }

    /// An MLP with the given flat parameters.
    pub fn with_params(
        ctx: &Context,
        label: &str,
        desc: MlpDesc,
        max_rows: usize,
        params: &[f32],
    ) -> Result<Self> {
        desc.check();
        let (offsets, len) = desc.layout();
        assert_eq!(
            params.len(),
            len,
            "{label}: {} parameters for a layout of {len}",
            params.len()
        );
        let max_rows_u32 = u32::try_from(max_rows)
            .ok()
            .filter(|&r| u64::from(r) * 1024 <= u64::from(u32::MAX))
            .ok_or(EngineError::too_large(
                "MLP rows",
                max_rows as u64,
                u64::from(u32::MAX) / 1024,
                "the MLP (u32 indices over 1,024 columns)",
            ))?;
        let acts = desc.activations();
        let min_rows_per_split = if ctx.info().kind == DeviceKind::Cpu {
            MIN_ROWS_PER_SPLIT_CPU
        } else {
            MIN_ROWS_PER_SPLIT_GPU
        };
        let mut layers = Vec::new();
        let mut partial_len = 0usize;
        for (l, (i, o)) in desc.linears().into_iter().enumerate() {
            let identity = acts[l] == Activation::Identity;
            let n = max_rows * o;
            let post_len = if identity { 0 } else { n };
            layers.push(LayerBuffers {
                pre: f32_buffer(ctx, &format!("{label} layer {l} pre"), n)?,
                post: f32_buffer(ctx, &format!("{label} layer {l} post"), post_len)?,
                grad_post: f32_buffer(ctx, &format!("{label} layer {l} grad post"), n)?,
                grad_pre: f32_buffer(ctx, &format!("{label} layer {l} grad pre"), post_len)?,
            });
            partial_len = partial_len
                .max(splits_for(max_rows_u32, min_rows_per_split).0 as usize * o * (i + 1));
        }
        let mut p = f32_buffer(ctx, &format!("{label} params"), len)?;
        ctx.write_buffer(&mut p, params)?;
        // The backward writes every gradient but the layout's padding, which stays zero
        // (the optimizer and the non-finite check read the whole vector).
        let mut grads = f32_buffer(ctx, &format!("{label} grads"), len)?;
        ctx.write_buffer(&mut grads, &vec![0.0f32; len])?;
        let desc_has_weight_norm = !desc.weight_norm.is_empty();
        Ok(Self {
            desc,
            variant: GemmVariant::Auto,
            max_rows: max_rows_u32,
            offsets,
            params: p,
            grads,
            layers,
            partials: f32_buffer(ctx, &format!("{label} weight-grad partials"), partial_len)?,
            min_rows_per_split,
            effective: if desc_has_weight_norm {
                Some(f32_buffer(
                    ctx,
                    &format!("{label} weight-normalised params"),
                    len,
                )?)
            } else {
                None
            },
        })
    }

    /// The weights the GEMMs read.
    fn weights(&self) -> &Buffer {
        self.effective.as_ref().unwrap_or(&self.params)
    }

    /// Floats in the parameter vector (every `W`, `b` and weight-norm `g`).
    pub fn param_count(&self) -> usize {
        self.desc.layout().1
    }

    /// The most rows one forward or backward may have.
    pub fn max_rows(&self) -> u32 {
        self.max_rows
    }

    fn output_of(&self, l: usize) -> &Buffer {
        let layer = &self.layers[l];
        if self.desc.activations()[l] == Activation::Identity {
            &layer.pre
        } else {
            &layer.post
        }
    }

    /// Head `h`'s output after the last forward pass: rows × width.
    pub fn head_output(&self, h: usize) -> &Buffer {
        self.output_of(self.desc.hidden.len() + h)
    }

    /// Where the caller writes the gradient on head `h`'s output before
    /// [`record_backward`](Self::record_backward).
    pub fn head_grad(&self, h: usize) -> &Buffer {
        &self.layers[self.desc.hidden.len() + h].grad_post
    }

    /// Copies a head's output gradient from the host (tests, small inputs).
    pub fn write_head_grad(&mut self, ctx: &Context, h: usize, data: &[f32]) -> Result<()> {
        let l = self.desc.hidden.len() + h;
        ctx.write_buffer(&mut self.layers[l].grad_post, data)
    }

    /// Reads a head's output for `rows` rows back to the host.
    pub fn read_head(&mut self, ctx: &Context, h: usize, rows: usize) -> Result<Vec<f32>> {
        let l = self.desc.hidden.len() + h;
        let len = rows * self.desc.heads[h].width;
        let layer = &mut self.layers[l];
        let buffer = if self.desc.heads[h].activation == Activation::Identity {
            &mut layer.pre
        } else {
            &mut layer.post
        };
        ctx.read_buffer(buffer, len)
    }

    /// Index of the head named `name`.
    pub fn head(&self, name: &str) -> usize {
        self.desc
            .heads
            .iter()
            .position(|h| h.name == name)
            .unwrap_or_else(|| panic!("no head named '{name}'"))
    }

    #[allow(clippy::too_many_arguments)]
    fn record_gemm<'a>(
        &self,
        rec: &mut Recording<'a>,
        name: &str,
        a: &'a Buffer,
        b: &'a Buffer,
        bias: &'a Buffer,
        c: &'a Buffer,
        p: GemmParams,
        splits: u32,
    ) -> Result<()> {
        let info = rec.context().info();
        // Texel views cover a whole buffer, so both must be within the device's limit
        // (and made for texel reads: a caller's buffer may not be).
        let texels_fit = a.texel_readable(info.max_texel_buffer_elements)
            && b.texel_readable(info.max_texel_buffer_elements);
        let variant = match self.variant {
            GemmVariant::Auto if info.kind != DeviceKind::Cpu => GemmVariant::Tiled,
            // Narrow outputs (the 1- to 6-wide heads) only where the forward kernels'
            // narrow tiles fit; elsewhere a 32-wide tile would be mostly waste.
            GemmVariant::Auto
                if subgroup_gemm_supported(info)
                    && texels_fit
                    && (p.n >= 16
                        || fwd_fits(&p, a, b, bias, info.max_texel_buffer_elements)
                        || narrow_weight_grad_kernel(&p, a).is_some()) =>
            {
                GemmVariant::Texel4
            }
            GemmVariant::Auto if subgroup_gemm_supported(info) && p.n >= 16 => {
                GemmVariant::Subgroup
            }
            GemmVariant::Auto => GemmVariant::Blocked,
            v => v,
        };
        let texel = matches!(variant, GemmVariant::Texel | GemmVariant::Texel4);
        if (texel || variant == GemmVariant::Subgroup) && !subgroup_gemm_supported(info) {
            let kernel = if texel {
                "nn_lavapipe::gemm_texel"
            } else {
                "nn_lavapipe::gemm_subgroup"
            };
            return Err(EngineError::MissingFeature {
                kernel,
                feature: "subgroups of 8 lanes with ballot operations",
            });
        }
        if variant == GemmVariant::Texel4
            && fwd_fits(&p, a, b, bias, info.max_texel_buffer_elements)
        {
            return record_fwd(rec, name, a, b, bias, c, p);
        }
        if let (GemmVariant::Texel4, Some((kernel, width))) =
            (variant, narrow_weight_grad_kernel(&p, a))
        {
            let tiles = p.m.div_ceil(GEMM_NARROW_ROWS) * p.n.div_ceil(width);
            let x = tiles.min(65_535);
            return rec.dispatch_as(
                name,
                kernel,
                gemm_bindings(a, b, bias, c),
                &p,
                [x, tiles.div_ceil(x.max(1)), splits],
            );
        }
        let (kernel, groups) = match variant {
            GemmVariant::Blocked => (
                GemmKernel::NnLavapipeGemmBlocked,
                [
                    p.n.div_ceil(8 * GEMM_BLOCK),
                    p.m.div_ceil(8 * GEMM_BLOCK),
                    splits,
                ],
            ),
            GemmVariant::Subgroup | GemmVariant::Texel | GemmVariant::Texel4 => {
                // One workgroup (one subgroup) per tile (32 × 32, or 64 × 32 for the
                // texel kernels), in rows of at most 65,535 workgroups, the limit every
                // device has.
                let (kernel, tile_rows) = match variant {
                    GemmVariant::Texel4 => (
                        texel4_grad_kernel(&p, a, b, bias, c, info.max_texel_buffer_elements)
                            .unwrap_or(GemmKernel::NnLavapipeGemmTexel),
                        GEMM_TX_ROWS,
                    ),
                    GemmVariant::Texel => (GemmKernel::NnLavapipeGemmTexel, GEMM_TX_ROWS),
                    _ => (GemmKernel::NnLavapipeGemmSubgroup, GEMM_SG_ROWS),
                };
                let tiles = p.m.div_ceil(tile_rows) * p.n.div_ceil(GEMM_SG_COLS);
                let x = tiles.min(65_535);
                (kernel, [x, tiles.div_ceil(x.max(1)), splits])
            }
            _ => (
                GemmKernel::NnGemmTiled,
                [p.n.div_ceil(GEMM_TILE), p.m.div_ceil(GEMM_TILE), splits],
            ),
        };
        rec.dispatch_as(name, kernel, gemm_bindings(a, b, bias, c), &p, groups)
    }

    fn record_act<'a>(
        rec: &mut Recording<'a>,
        name: &str,
        act: Activation,
        pre: &'a Buffer,
        post: &'a Buffer,
        rows: u32,
        width: u32,
    ) -> Result<()> {
        let p = ActParams {
            rows,
            width,
            kind: act.kind(),
            temperature: act.temperature(),
        };
        if act.kind() == ACT_SOFTMAX {
            return rec.dispatch(
                name,
                kernels::nn::SoftmaxFwd {
                    pre: pre.read(),
                    post: post.write(),
                },
                &p,
                grid(rows),
            );
        }
        if let Some((fwd, _)) = act4_kernels(act, &[pre, post]) {
            return rec.dispatch_as(
                name,
                fwd,
                kernels::nn::ActFwd {
                    pre: pre.read(),
                    post: post.write(),
                },
                &p,
                grid((rows * width).div_ceil(4)),
            );
        }
        rec.dispatch(
            name,
            kernels::nn::ActFwd {
                pre: pre.read(),
                post: post.write(),
            },
            &p,
            grid(rows * width),
        )
    }

    /// Records the forward pass over `rows` rows of `input` (rows × `desc.input`).
    pub fn record_forward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        input: &'a Buffer,
        rows: u32,
    ) -> Result<()> {
        assert!(
            rows <= self.max_rows,
            "{rows} rows for an MLP of {}",
            self.max_rows
        );
        let acts = self.desc.activations();
        let linears = self.desc.linears();
        let hidden = self.desc.hidden.len();
        if let Some(effective) = &self.effective {
            rec.copy(&self.params, effective, self.params.size);
            for p in self.desc.weight_norm_params() {
                rec.dispatch(
                    "mlp.weight_norm_fwd",
                    kernels::nn::WeightNormFwd {
                        params: self.params.read(),
                        effective: effective.write(),
                    },
                    &p,
                    [p.out_features.div_ceil(64), 1, 1],
                )?;
            }
        }
        for (l, &(i, o)) in linears.iter().enumerate() {
            let x = match below(l, hidden) {
                Some(k) => self.output_of(k),
                None => input,
            };
            let (w_off, b_off) = self.offsets[l];
            let p = GemmParams {
                m: rows,
                n: o as u32,
                k: i as u32,
                flags: GEMM_BIAS,
                a_sm: i as u32,
                a_sk: 1,
                b_off: w_off as u32,
                b_sk: 1,
                b_sn: i as u32,
                ldc: o as u32,
                bias_off: b_off as u32,
                k_chunk: i as u32,
                ..Default::default()
            };
            let layer = &self.layers[l];
            self.record_gemm(
                rec,
                "mlp.linear_fwd",
                x,
                self.weights(),
                self.weights(),
                &layer.pre,
                p,
                1,
            )?;
            if acts[l] != Activation::Identity {
                Self::record_act(
                    rec,
                    "mlp.act_fwd",
                    acts[l],
                    &layer.pre,
                    &layer.post,
                    rows,
                    o as u32,
                )?;
            }
            // Heads read the trunk only; they need no barrier between each other.
            if l < hidden || l == linears.len() - 1 {}
        }
        Ok(())
    }

    /// Records the backward pass: reads the gradients the caller wrote into every
    /// [`head_grad`](Self::head_grad), writes the parameter gradients to `grads` and,
    /// when given, the input's gradient (rows × `desc.input`) to `grad_input`.
    /// `input` and `rows` must be those of the last forward pass. With `add_to_grad_input`
    /// the input's gradient is added to what `grad_input` holds (several MLPs reading
    /// one input).
    pub fn record_backward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        input: &'a Buffer,
        rows: u32,
        grad_input: Option<&'a Buffer>,
        add_to_grad_input: bool,
    ) -> Result<()> {
        assert!(
            rows <= self.max_rows,
            "{rows} rows for an MLP of {}",
            self.max_rows
        );
        let acts = self.desc.activations();
        let linears = self.desc.linears();
        let hidden = self.desc.hidden.len();
        let (splits, k_chunk) = splits_for(rows, self.min_rows_per_split);
        // Heads first (each adds its input gradient to the trunk's), then the trunk
        // from the top.
        let order: Vec<usize> = (hidden..linears.len()).chain((0..hidden).rev()).collect();
        for (step, &l) in order.iter().enumerate() {
            let (i, o) = linears[l];
            let layer = &self.layers[l];
            let x = match below(l, hidden) {
                Some(k) => self.output_of(k),
                None => input,
            };
            let g = if acts[l] == Activation::Identity {
                &layer.grad_post
            } else {
                let p = ActParams {
                    rows,
                    width: o as u32,
                    kind: acts[l].kind(),
                    temperature: acts[l].temperature(),
                };
                if acts[l].kind() == ACT_SOFTMAX {
                    rec.dispatch(
                        "mlp.act_bwd",
                        kernels::nn::SoftmaxBwd {
                            post: layer.post.read(),
                            grad_post: layer.grad_post.read(),
                            grad_pre: layer.grad_pre.write(),
                        },
                        &p,
                        grid(rows),
                    )?;
                } else {
                    let four = act4_kernels(
                        acts[l],
                        &[&layer.pre, &layer.post, &layer.grad_post, &layer.grad_pre],
                    );
                    rec.dispatch_as(
                        "mlp.act_bwd",
                        four.map_or(ActBwdKernel::NnActBwd, |(_, bwd)| bwd),
                        kernels::nn::ActBwd {
                            pre: layer.pre.read(),
                            post: layer.post.read(),
                            grad_post: layer.grad_post.read(),
                            grad_pre: layer.grad_pre.write(),
                        },
                        &p,
                        grid(if four.is_some() {
                            (rows * o as u32).div_ceil(4)
                        } else {
                            rows * o as u32
                        }),
                    )?;
                }
                &layer.grad_pre
            };
            let (w_off, b_off) = self.offsets[l];
            // dWᵀ = xᵀ g (with db as the ones row): (in + 1) × out per split.
            let p = GemmParams {
                m: i as u32 + 1,
                n: o as u32,
                k: rows,
                flags: GEMM_ONES_ROW,
                a_sm: 1,
                a_sk: i as u32,
                b_sk: o as u32,
                b_sn: 1,
                ldc: o as u32,
                k_chunk,
                c_split: (o * (i + 1)) as u32,
                ..Default::default()
            };
            self.record_gemm(
                rec,
                "mlp.weight_grad",
                x,
                g,
                &self.params,
                &self.partials,
                p,
                splits,
            )?;
            // dX = g W, into the layer below's grad_post (heads: the trunk's; the first
            // head overwrites, the others add).
            let target = match below(l, hidden) {
                Some(k) => Some(&self.layers[k].grad_post),
                None => grad_input,
            };
            if let Some(target) = target {
                // Every head adds to the trunk's gradient; the first one overwrites it.
                let accumulate = l > hidden || (below(l, hidden).is_none() && add_to_grad_input);
                let p = GemmParams {
                    m: rows,
                    n: i as u32,
                    k: o as u32,
                    flags: if accumulate { GEMM_ACCUMULATE } else { 0 },
                    a_sm: o as u32,
                    a_sk: 1,
                    b_off: w_off as u32,
                    b_sk: i as u32,
                    b_sn: 1,
                    ldc: i as u32,
                    k_chunk: o as u32,
                    ..Default::default()
                };
                self.record_gemm(
                    rec,
                    "mlp.input_grad",
                    g,
                    self.weights(),
                    self.weights(),
                    target,
                    p,
                    1,
                )?;
            }
            let wp = WeightGradParams {
                out_features: o as u32,
                in_features: i as u32,
                splits,
                w_off: w_off as u32,
                b_off: b_off as u32,
                _pad: [0; 3],
            };
            rec.dispatch(
                "mlp.sum_weight_grad",
                kernels::nn::SumWeightGrad {
                    partials: self.partials.read(),
                    grad: self.grads.write(),
                },
                &wp,
                grid(wp.out_features * (wp.in_features + 1)),
            )?;
            // The next layer's dW reuses the partials, and reads the dX just written.
            if step + 1 < order.len() {}
        }
        if self.effective.is_some() {
            for p in self.desc.weight_norm_params() {
                rec.dispatch(
                    "mlp.weight_norm_bwd",
                    kernels::nn::WeightNormBwd {
                        params: self.params.read(),
                        grads: self.grads.write(),
                    },
                    &p,
                    [p.out_features.div_ceil(64), 1, 1],
                )?;
            }
        }
        Ok(())
    }
}

fn apply<F: Real>(act: Activation, pre: &[F], width: usize) -> Vec<F> {
    if let Activation::Softmax { temperature } = act {
        let mut out = Vec::with_capacity(pre.len());
        for row in pre.chunks_exact(width) {
            let mut r = [F::zero(); SOFTMAX_MAX_WIDTH];
            r[..width].copy_from_slice(row);
            softmax_row(&mut r, width, F::of(temperature));
            out.extend_from_slice(&r[..width]);
        }
        out
    } else {
        pre.iter().map(|&x| activate(act.kind(), x)).collect()
    }
}

fn apply_bwd<F: Real>(act: Activation, pre: &[F], post: &[F], grad: &[F], width: usize) -> Vec<F> {
    if let Activation::Softmax { temperature } = act {
        let mut out = Vec::with_capacity(pre.len());
        for (y, g) in post.chunks_exact(width).zip(grad.chunks_exact(width)) {
            let mut yy = [F::zero(); SOFTMAX_MAX_WIDTH];
            let mut gg = [F::zero(); SOFTMAX_MAX_WIDTH];
            yy[..width].copy_from_slice(y);
            gg[..width].copy_from_slice(g);
            softmax_row_bwd(&yy, &mut gg, width, F::of(temperature));
            out.extend_from_slice(&gg[..width]);
        }
        out
    } else {
        pre.iter()
            .zip(post)
            .zip(grad)
            .map(|((&x, &y), &g)| activate_bwd(act.kind(), x, y, g))
            .collect()
    }
}

fn linear<F: Real>(x: &[F], w: &[F], b: &[F], rows: usize, i: usize, o: usize) -> Vec<F> {
    let mut y = vec![F::zero(); rows * o];
    for r in 0..rows {
        for c in 0..o {
            let mut s = b[c];
            for k in 0..i {
                s += x[r * i + k] * w[c * i + k];
            }
            y[r * o + c] = s;
        }
    }
    y
}

/// CPU references of the MLP forward and backward, generic over f32/f64.
pub mod reference {
    use super::*;

    /// What the CPU reference's forward pass saves: each linear layer's output before and
    /// after its activation (rows × width).
    #[derive(Clone, Debug)]
    pub struct Activations<F> {
        /// Each linear layer's output before its activation.
        pub pre: Vec<Vec<F>>,
        /// Each linear layer's output after its activation.
        pub post: Vec<Vec<F>>,
    }

    impl<F: Real> Activations<F> {
        /// Head `h`'s output.
        pub fn head(&self, desc: &MlpDesc, h: usize) -> &[F] {
            &self.post[desc.hidden.len() + h]
        }
    }

    /// The parameters with every weight-normalised layer's `W` slot holding `g v / ‖v‖`
    /// (what the GPU's GEMMs read); the parameters themselves without weight normalisation.
    pub fn effective_params<F: Real>(desc: &MlpDesc, params: &[F]) -> Vec<F> {
        let mut out = params.to_vec();
        for p in desc.weight_norm_params() {
            for o in 0..p.out_features as usize {
                let norm = weight_norm_row_norm(params, &p, o);
                for i in 0..p.in_features as usize {
                    out[p.w_off as usize + o * p.in_features as usize + i] =
                        weight_norm_value(params, &p, o, i, norm);
                }
            }
        }
        out
    }

    /// CPU reference of the forward pass.
    pub fn forward<F: Real>(
        desc: &MlpDesc,
        params: &[F],
        input: &[F],
        rows: usize,
    ) -> Activations<F> {
        let params = &effective_params(desc, params)[..];
        let (offsets, _) = desc.layout();
        let acts = desc.activations();
        let hidden = desc.hidden.len();
        let mut pre = Vec::new();
        let mut post: Vec<Vec<F>> = Vec::new();
        for (l, (i, o)) in desc.linears().into_iter().enumerate() {
            let x: &[F] = match below(l, hidden) {
                Some(k) => &post[k],
                None => input,
            };
            let (w_off, b_off) = offsets[l];
            let y = linear(
                x,
                &params[w_off..b_off],
                &params[b_off..b_off + o],
                rows,
                i,
                o,
            );
            let a = apply(acts[l], &y, o);
            pre.push(y);
            post.push(a);
        }
        Activations { pre, post }
    }

    /// CPU reference of the backward pass from the gradients on each head's output:
    /// (parameter gradients, input gradient).
    pub fn backward<F: Real>(
        desc: &MlpDesc,
        raw_params: &[F],
        input: &[F],
        rows: usize,
        saved: &Activations<F>,
        head_grads: &[Vec<F>],
    ) -> (Vec<F>, Vec<F>) {
        let effective = effective_params(desc, raw_params);
        let params = &effective[..];
        let (offsets, len) = desc.layout();
        let acts = desc.activations();
        let linears = desc.linears();
        let hidden = desc.hidden.len();
        let mut grads = vec![F::zero(); len];
        let mut grad_out: Vec<Vec<F>> = linears
            .iter()
            .map(|&(_, o)| vec![F::zero(); rows * o])
            .collect();
        for (h, g) in head_grads.iter().enumerate() {
            grad_out[hidden + h] = g.clone();
        }
        let mut grad_input = vec![F::zero(); rows * desc.input];
        let order: Vec<usize> = (hidden..linears.len()).chain((0..hidden).rev()).collect();
        for l in order {
            let (i, o) = linears[l];
            let g = apply_bwd(acts[l], &saved.pre[l], &saved.post[l], &grad_out[l], o);
            let x: &[F] = match below(l, hidden) {
                Some(k) => &saved.post[k],
                None => input,
            };
            let (w_off, b_off) = offsets[l];
            let mut gx = vec![F::zero(); rows * i];
            for r in 0..rows {
                for c in 0..o {
                    let gc = g[r * o + c];
                    grads[b_off + c] += gc;
                    for k in 0..i {
                        grads[w_off + c * i + k] += gc * x[r * i + k];
                        gx[r * i + k] += gc * params[w_off + c * i + k];
                    }
                }
            }
            let target = match below(l, hidden) {
                Some(k) => &mut grad_out[k],
                None => &mut grad_input,
            };
            for (d, v) in target.iter_mut().zip(gx) {
                *d += v;
            }
        }
        for p in desc.weight_norm_params() {
            for o in 0..p.out_features as usize {
                weight_norm_row_bwd(raw_params, &mut grads, &p, o);
            }
        }
        (grads, grad_input)
    }
}

/// The element-wise activation kernels that take 4 elements an invocation
/// (`nn::act_fwd4[_gelu]`, `nn::act_bwd4[_gelu]`: a quarter of llvmpipe's loops over
/// the lanes, 16-byte accesses on a GPU), where every buffer is whole 16-byte texels
/// (the engine makes its buffers so): they cover `rows · width` rounded up to 4.
fn act4_kernels(act: Activation, buffers: &[&Buffer]) -> Option<(ActFwdKernel, ActBwdKernel)> {
    if buffers.iter().any(|b| b.vk_size() % 16 != 0) {
        return None;
    }
    Some(if act.kind() == drape_shared::nn::ACT_GELU {
        (ActFwdKernel::NnActFwd4Gelu, ActBwdKernel::NnActBwd4Gelu)
    } else {
        (ActFwdKernel::NnActFwd4, ActBwdKernel::NnActBwd4)
    })
}

/// The bindings every GEMM kernel has (`nn::gemm_tiled`'s struct; the kernels of
/// `nn_lavapipe` bind the same names, some of them as texel views of the same buffers), for
/// the kernels chosen at run time (`Recording::dispatch_as`).
fn gemm_bindings<'a>(
    a: &'a Buffer,
    b: &'a Buffer,
    bias: &'a Buffer,
    c: &'a Buffer,
) -> kernels::nn::GemmTiled<'a> {
    kernels::nn::GemmTiled {
        a: a.read(),
        b: b.read(),
        bias: bias.read(),
        c: c.write(),
    }
}

/// Whether the forward 4-float texel GEMMs (`nn_lavapipe::gemm_fwd_cols*`) fit these operands:
/// `A` and `B` both contiguous along `k` (`x Wᵀ`), offsets and strides in whole
/// 16-byte texels, no ones row, nothing added to `C`, and the bias readable as a texel
/// buffer (the float epilogue fetches it).
fn fwd_fits(p: &GemmParams, a: &Buffer, b: &Buffer, bias: &Buffer, max_texels: u64) -> bool {
    let whole = |buffer: &Buffer| buffer.vk_size() % 16 == 0;
    p.a_sk == 1
        && p.b_sk == 1
        && p.a_off % 4 == 0
        && p.a_sm % 4 == 0
        && p.b_off % 4 == 0
        && p.b_sn % 4 == 0
        && p.k % 4 == 0
        && p.k_chunk % 4 == 0
        && p.flags & (GEMM_ONES_ROW | GEMM_ACCUMULATE) == 0
        && whole(a)
        && whole(b)
        && bias.texel_readable(max_texels)
}

/// The forward kernels by tile width: (width, float epilogue, 4-float epilogue).
const FWD_WIDTHS: [(u32, GemmKernel, GemmKernel); 4] = [
    (
        32,
        GemmKernel::NnLavapipeGemmFwdCols32,
        GemmKernel::NnLavapipeGemmFwdCols32Vec4,
    ),
    (
        16,
        GemmKernel::NnLavapipeGemmFwdCols16,
        GemmKernel::NnLavapipeGemmFwdCols16Vec4,
    ),
    (
        8,
        GemmKernel::NnLavapipeGemmFwdCols8,
        GemmKernel::NnLavapipeGemmFwdCols8Vec4,
    ),
    (
        4,
        GemmKernel::NnLavapipeGemmFwdCols4,
        GemmKernel::NnLavapipeGemmFwdCols4Vec4,
    ),
];

/// What llvmpipe spends on one tile of `width` columns per 4 steps of `k`, in
/// instructions of its machine code: a 4-float fetch (about 45: a call, 8 loads and a
/// transpose) per row of a lane (16) and per column, and about 14 per accumulator
/// update (4 multiply-adds, its spilled operands, and the masked store every value
/// written in a loop gets). Only the ratios matter.
fn fwd_tile_cost(width: u32) -> u32 {
    (16 + width) * 45 + 16 * width * 14
}

/// How the forward kernels cover `n` columns: `(first column, columns, tile width)`
/// per dispatch. 32-wide tiles as far as they fill, then the cheapest set of narrower
/// tiles for the rest (by `fwd_tile_cost`): llvmpipe runs every column of a tile,
/// existing or not, so a head of 3 columns in a 32-wide tile costs what 32 do.
pub fn fwd_column_tiles(n: u32) -> Vec<(u32, u32, u32)> {
    // cheapest[r]: (cost, widths) covering r columns.
    let mut cheapest: Vec<(u32, Vec<u32>)> = vec![(0, Vec::new())];
    for r in 1..32u32 {
        let best = FWD_WIDTHS
            .iter()
            .map(|&(w, ..)| {
                let (cost, widths) = &cheapest[r.saturating_sub(w) as usize];
                let mut widths = widths.clone();
                widths.push(w);
                (cost + fwd_tile_cost(w), widths)
            })
            .min_by_key(|(cost, _)| *cost)
            .expect("widths");
        cheapest.push(best);
    }
    let mut widths = vec![32; (n / 32) as usize];
    let mut rest = cheapest[(n % 32) as usize].1.clone();
    rest.sort_unstable_by(|x, y| y.cmp(x));
    widths.extend(rest);
    let mut tiles: Vec<(u32, u32, u32)> = Vec::new();
    let mut first = 0;
    for w in widths {
        let cols = w.min(n - first);
        match tiles.last_mut() {
            Some(last) if last.2 == w => last.1 += cols,
            _ => tiles.push((first, cols, w)),
        }
        first += cols;
    }
    tiles
}

/// Records a forward GEMM through `nn_lavapipe::gemm_fwd_cols*` (see [`fwd_fits`]): one dispatch
/// per run of [`fwd_column_tiles`], each shifted to its first column through the
/// offsets, with the 4-float epilogue where its columns, `C` and the bias allow.
fn record_fwd<'a>(
    rec: &mut Recording<'a>,
    name: &str,
    a: &'a Buffer,
    b: &'a Buffer,
    bias: &'a Buffer,
    c: &'a Buffer,
    p: GemmParams,
) -> Result<()> {
    let whole = |buffer: &Buffer| buffer.vk_size() % 16 == 0;
    for (first, cols, width) in fwd_column_tiles(p.n) {
        let q = GemmParams {
            n: cols,
            b_off: p.b_off + first * p.b_sn,
            c_off: p.c_off + first,
            bias_off: p.bias_off + first,
            ..p
        };
        let quads = q.n % 4 == 0
            && q.ldc % 4 == 0
            && q.c_off % 4 == 0
            && q.c_split % 4 == 0
            && whole(c)
            && whole(bias)
            && (q.flags & GEMM_BIAS == 0 || q.bias_off % 4 == 0);
        let &(_, floats, fours) = FWD_WIDTHS
            .iter()
            .find(|(w, ..)| *w == width)
            .expect("a tile width of FWD_WIDTHS");
        let tiles = q.m.div_ceil(GEMM_FWD_ROWS) * cols.div_ceil(width);
        let x = tiles.min(65_535);
        rec.dispatch_as(
            name,
            if quads { fours } else { floats },
            gemm_bindings(a, b, bias, c),
            &q,
            [x, tiles.div_ceil(x.max(1)), 1],
        )?;
    }
    Ok(())
}

/// The narrow weight gradient with `k` across the lanes
/// (`nn_lavapipe::gemm_weight_grad_cols4` or `_cols8`) and its tile width, where `C` is at
/// most 8 wide (the weight gradient of a 1- to 6-wide head, `A = Xᵀ` contiguous along
/// `m` in whole texels): the column-owning tiles would run 32 columns for 3.
fn narrow_weight_grad_kernel(p: &GemmParams, a: &Buffer) -> Option<(GemmKernel, u32)> {
    let fits = p.a_sm == 1 && p.a_off % 4 == 0 && p.a_sk % 4 == 0 && a.vk_size() % 16 == 0;
    match p.n {
        1..=4 if fits => Some((GemmKernel::NnLavapipeGemmWeightGradCols4, 4)),
        5..=8 if fits => Some((GemmKernel::NnLavapipeGemmWeightGradCols8, 8)),
        _ => None,
    }
}

/// The 4-float texel GEMM for the backward's operand layouts, if one fits (`Auto` on
/// CPU devices, where `nn_lavapipe::gemm_texel` would run; forwards go through
/// [`record_fwd`]): `nn_lavapipe::gemm_input_grad_vec4` or `gemm_input_grad` (`A` along `k`,
/// `B` along `n`: input gradients; the first where `C` and the bias are read and
/// written 4 floats at a time), `nn_lavapipe::gemm_weight_grad_vec4` (`A` along `m`, `B`
/// along `n`: weight gradients where `C` takes 4 floats a store), else
/// `gemm_b_along_n_vec4` or `gemm_b_along_n` (`B` along `n`, `A` in any layout: a
/// narrow head's input gradient, a weight gradient of odd width). A 4-float view covers
/// whole 16-byte texels, so offsets and strides must be multiples of 4 floats and the
/// buffers whole texels.
fn texel4_grad_kernel(
    p: &GemmParams,
    a: &Buffer,
    b: &Buffer,
    bias: &Buffer,
    c: &Buffer,
    max_texels: u64,
) -> Option<GemmKernel> {
    let whole = |buffer: &Buffer| buffer.vk_size() % 16 == 0;
    // The `c4` epilogues store 4 columns at a time and read the bias as 4-float texels.
    let c_quads =
        p.n % 4 == 0 && p.ldc % 4 == 0 && p.c_off % 4 == 0 && p.c_split % 4 == 0 && whole(c);
    // (The bias is bound, as a texel buffer, with or without GEMM_BIAS.)
    let bias_quads = bias.texel_readable(max_texels)
        && whole(bias)
        && (p.flags & GEMM_BIAS == 0 || p.bias_off % 4 == 0);
    let a_k4 = p.a_sk == 1
        && p.a_off % 4 == 0
        && p.a_sm % 4 == 0
        && p.k % 4 == 0
        && p.k_chunk % 4 == 0
        && p.flags & GEMM_ONES_ROW == 0
        && whole(a);
    let a_m4 = p.a_sm == 1 && p.a_off % 4 == 0 && p.a_sk % 4 == 0 && whole(a);
    let b_n4 = p.b_sn == 1 && p.b_off % 4 == 0 && p.b_sk % 4 == 0 && whole(b);
    match (a_k4, b_n4) {
        (true, true) if c_quads && bias_quads => Some(GemmKernel::NnLavapipeGemmInputGradVec4),
        (true, true) => Some(GemmKernel::NnLavapipeGemmInputGrad),
        (false, true) if a_m4 && c_quads && bias_quads => {
            Some(GemmKernel::NnLavapipeGemmWeightGradVec4)
        }
        (false, true) if c_quads && bias_quads => Some(GemmKernel::NnLavapipeGemmBAlongNVec4),
        (false, true) => Some(GemmKernel::NnLavapipeGemmBAlongN),
        _ => None,
    }
}

#[cfg(test)]
mod capped_tests {
    use super::*;

    #[test]
    fn fwd_column_tiles_cover_every_column_once() {
        // The HUGS heads and layers, and every width up to 200.
        assert_eq!(fwd_column_tiles(1), vec![(0, 1, 4)]);
        assert_eq!(fwd_column_tiles(3), vec![(0, 3, 4)]);
        assert_eq!(fwd_column_tiles(6), vec![(0, 6, 8)]);
        assert_eq!(fwd_column_tiles(24), vec![(0, 16, 16), (16, 8, 8)]);
        assert_eq!(fwd_column_tiles(48), vec![(0, 32, 32), (32, 16, 16)]);
        assert_eq!(
            fwd_column_tiles(49),
            vec![(0, 32, 32), (32, 16, 16), (48, 1, 4)]
        );
        assert_eq!(fwd_column_tiles(128), vec![(0, 128, 32)]);
        for n in 1..=200 {
            let tiles = fwd_column_tiles(n);
            let mut next = 0;
            for &(first, cols, width) in &tiles {
                assert_eq!(first, next, "n = {n}: {tiles:?}");
                assert!(
                    cols > 0 && [32, 16, 8, 4].contains(&width),
                    "n = {n}: {tiles:?}"
                );
                next += cols;
            }
            assert_eq!(next, n, "n = {n}: {tiles:?}");
        }
    }

    #[test]
    fn capped_narrows_hidden_layers_only() {
        let d = MlpDesc::hugs_deformation(48).capped(64);
        assert_eq!(
            d.linears(),
            vec![(48, 64), (64, 64), (64, 64), (64, 64), (64, 24)]
        );
        let a = MlpDesc::hugs_appearance(48, 3).capped(64);
        assert_eq!(
            a,
            MlpDesc::hugs_appearance(48, 3),
            "the appearance decoder is 64 wide already"
        );
        let g = MlpDesc::hugs_geometry(96).capped(200);
        assert_eq!(
            g,
            MlpDesc::hugs_geometry(96),
            "a cap above every width changes nothing"
        );
    }
}
