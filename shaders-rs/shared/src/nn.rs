//! Neural-network math shared by the `nn::*` kernels and their CPU references: the
//! tiled GEMM's parameters, the activations (GELU in PyTorch's erf form, sigmoid, exp,
//! softmax with a temperature) and their derivatives.
//!
//! One GEMM serves a linear layer's forward and both halves of its backward because
//! it addresses its operands by strides: `C[m][n] (+)= Σ_k A[m][k] B[k][n] (+ bias[n])`
//! with `A[m][k] = a[a_off + m a_sm + k a_sk]` and `B[k][n] = b[b_off + k b_sk + n b_sn]`.
//! For `y = x Wᵀ + b` with `x` rows × in and `W` out × in (PyTorch's layout):
//! forward `A = x`, `B = Wᵀ`; `dx = dy W`; `dWᵀ = xᵀ dy`, with the bias gradient as
//! one more row of `xᵀ` that is all ones ([`GEMM_ONES_ROW`]), the rows split into
//! chunks whose partial sums a second kernel adds in a fixed order (no atomics, so
//! the result is deterministic).
//!
//! Several kernels compute it, the same sums in the same order of `k`: `nn::gemm_tiled`
//! for GPUs (a 64 × 64 tile per workgroup, slices of `A` and `B` staged in workgroup
//! memory, a 4 × 4 block of sums per invocation), and for CPU devices the kernels of
//! `nn_lavapipe` (see its table): `gemm_subgroup` (lanes of a subgroup of 8 passing values by
//! broadcasts), the texel GEMMs (subgroup tiles reading their operands through texel
//! views) and `gemm_blocked` (an 8 × 8 block per invocation, for narrow outputs): on
//! lavapipe, which runs 8 invocations per SIMD instruction, per-invocation indices into
//! workgroup memory are gathers. The narrow heads' weight gradients
//! (`nn_lavapipe::gemm_weight_grad_cols4` / `_cols8`) alone sum `k` in another order
//! (strided by lane).

use crate::real::Real;

/// Rows and columns of the tile of `C` one workgroup of `nn::gemm_tiled` computes
/// (16 × 16 invocations of 4 × 4).
pub const GEMM_TILE: u32 = 64;
/// Rows and columns of `C` one invocation of the register-blocked kernel owns.
pub const GEMM_BLOCK: u32 = 8;
/// Depth of one step of `nn::gemm_tiled` through `k` (the staged slices of `A` and `B`
/// are 16 × 64).
pub const GEMM_K_STEP: u32 = 16;
/// Rows of `C` one subgroup of the broadcast kernel (`nn_lavapipe::gemm_subgroup`) owns: 4
/// per lane of a subgroup of 8.
pub const GEMM_SG_ROWS: u32 = 32;
/// Columns of `C` one subgroup of the broadcast kernel owns.
pub const GEMM_SG_COLS: u32 = 32;
/// Rows of the tile of `nn_lavapipe::gemm_texel` and the other 64 × 32 tiles (8 per lane of
/// a subgroup of 8; their columns are `GEMM_SG_COLS`).
pub const GEMM_TX_ROWS: u32 = 64;
/// Rows of the tile of the forward GEMMs `nn_lavapipe::gemm_fwd_cols*` (16 per lane).
pub const GEMM_FWD_ROWS: u32 = 128;
/// Rows of the tile of the narrow weight gradients `nn_lavapipe::gemm_weight_grad_cols4` /
/// `_cols8` (every lane sums all 32, over its own steps of `k`).
pub const GEMM_NARROW_ROWS: u32 = 32;

/// Add `bias[bias_off + n]` to every row.
pub const GEMM_BIAS: u32 = 1;
/// Add to `C` instead of overwriting it.
pub const GEMM_ACCUMULATE: u32 = 2;
/// `A[m][k] = 1` for `m = m_count - 1` (the bias row of a transposed weight gradient).
pub const GEMM_ONES_ROW: u32 = 4;

/// Push constants of `nn::gemm_tiled` and of every `nn_lavapipe` GEMM. The
/// dispatch is `[ceil(n / 64), ceil(m / 64), splits]` (tiled), `[ceil(n / 64),
/// ceil(m / 64), splits]` (blocked, 8 × 8 invocations of 8 × 8) or
/// `[x, y, splits]` with `x y >= ceil(m / 32) ceil(n / 32)` (subgroup: one 32 × 32 tile
/// per workgroup of 8, rows fastest);
/// split `z` sums `k` over `[z k_chunk, (z + 1) k_chunk)` and writes its `C` at
/// `c_off + z c_split + m ldc + n`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct GemmParams {
    pub m: u32,
    pub n: u32,
    pub k: u32,
    pub flags: u32,
    pub a_off: u32,
    pub a_sm: u32,
    pub a_sk: u32,
    pub b_off: u32,
    pub b_sk: u32,
    pub b_sn: u32,
    pub c_off: u32,
    pub ldc: u32,
    pub bias_off: u32,
    pub k_chunk: u32,
    pub c_split: u32,
    pub _pad: u32,
}

/// Push constants of `nn::sum_weight_grad`: adds `splits` partial `(in + 1) × out`
/// matrices (`dWᵀ` with the bias row) and writes the weight part to `grad[w_off..]`
/// (out × in) and the last column to `grad[b_off..]` (out).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct WeightGradParams {
    pub out_features: u32,
    pub in_features: u32,
    pub splits: u32,
    pub w_off: u32,
    pub b_off: u32,
    pub _pad: [u32; 3],
}

/// No activation (a head's raw output).
pub const ACT_IDENTITY: u32 = 0;
/// `x Φ(x)`, PyTorch's default (erf) GELU.
pub const ACT_GELU: u32 = 1;
pub const ACT_SIGMOID: u32 = 2;
pub const ACT_EXP: u32 = 3;
/// `softmax(x / T)` over each whole row.
pub const ACT_SOFTMAX: u32 = 4;

/// Push constants of `nn::act_fwd` / `nn::act_bwd`: `rows × width`, row-major.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct ActParams {
    pub rows: u32,
    pub width: u32,
    pub kind: u32,
    /// Softmax temperature.
    pub temperature: f32,
}

/// Longest row a softmax kernel handles (SMPL's 24 joints fit).
pub const SOFTMAX_MAX_WIDTH: usize = 32;
const _: () = assert!(SOFTMAX_MAX_WIDTH == 32, "softmax_row unrolls 32 columns");

/// `erfc(x)` with fractional error below 1.2e-7 everywhere (Numerical Recipes'
/// Chebyshev fit `erfcc`): relative accuracy also in the tail, where `1 - erf(x)`
/// would cancel; only adds, multiplies and one `exp`.
#[inline]
pub fn erfc<F: Real>(x: F) -> F {
    let c = F::of;
    let z = x.abs();
    let t = F::one() / (F::one() + c(0.5) * z);
    let poly = c(-1.265_512_2)
        + t * (c(1.000_023_7)
            + t * (c(0.374_091_96)
                + t * (c(0.096_784_18)
                    + t * (c(-0.186_288_06)
                        + t * (c(0.278_868_07)
                            + t * (c(-1.135_203_98)
                                + t * (c(1.488_515_87)
                                    + t * (c(-0.822_152_23) + t * c(0.170_872_77)))))))));
    let ans = t * (poly - z * z).exp_k();
    if x >= F::zero() {
        ans
    } else {
        c(2.0) - ans
    }
}

/// `Φ(x)`, the standard normal CDF.
#[inline]
pub fn normal_cdf<F: Real>(x: F) -> F {
    F::of(0.5) * erfc(-x * F::of(core::f32::consts::FRAC_1_SQRT_2))
}

/// GELU, erf form: `x Φ(x)`. Finite for every finite `x` (0 below -14, `x` above 14).
#[inline]
pub fn gelu<F: Real>(x: F) -> F {
    x * normal_cdf(x)
}

/// `d gelu / dx = Φ(x) + x φ(x)`.
#[inline]
pub fn gelu_grad<F: Real>(x: F) -> F {
    let pdf = F::of(0.398_942_28) * (F::of(-0.5) * x * x).exp_k();
    normal_cdf(x) + x * pdf
}

/// Logistic sigmoid, evaluated so that neither branch overflows (finite at ±80 and
/// beyond).
#[inline]
pub fn sigmoid<F: Real>(x: F) -> F {
    if x >= F::zero() {
        F::one() / (F::one() + (-x).exp_k())
    } else {
        let e = x.exp_k();
        e / (F::one() + e)
    }
}

/// Element-wise activation (not softmax).
#[inline]
pub fn activate<F: Real>(kind: u32, x: F) -> F {
    if kind == ACT_GELU {
        gelu(x)
    } else if kind == ACT_SIGMOID {
        sigmoid(x)
    } else if kind == ACT_EXP {
        x.exp_k()
    } else {
        x
    }
}

/// Gradient on the input of an element-wise activation from the gradient `g` on its
/// output, given the input `x` and the output `y`.
#[inline]
pub fn activate_bwd<F: Real>(kind: u32, x: F, y: F, g: F) -> F {
    if kind == ACT_GELU {
        g * gelu_grad(x)
    } else if kind == ACT_SIGMOID {
        g * y * (F::one() - y)
    } else if kind == ACT_EXP {
        g * y
    } else {
        g
    }
}

/// `softmax(x / t)` of one row of `width <= SOFTMAX_MAX_WIDTH` values, in place.
/// Subtracts the row's largest value first, so logits of any finite size stay finite.
#[inline]
pub fn softmax_row<F: Real>(row: &mut [F; SOFTMAX_MAX_WIDTH], width: usize, t: F) {
    // Constant indices, each guarded by the width (see `each_index!`).
    let mut max = row[0];
    crate::each_index!(32, j => {
        if j >= 1 && j < width && row[j] > max {
            max = row[j];
        }
    });
    let mut sum = F::zero();
    crate::each_index!(32, j => {
        if j < width {
            row[j] = ((row[j] - max) / t).exp_k();
            sum += row[j];
        }
    });
    crate::each_index!(32, j => {
        if j < width {
            row[j] /= sum;
        }
    });
}

/// Gradient on the logits of `y = softmax(x / t)`: `(y ⊙ (g - Σ g y)) / t`, in place
/// over `g`.
#[inline]
pub fn softmax_row_bwd<F: Real>(
    y: &[F; SOFTMAX_MAX_WIDTH],
    g: &mut [F; SOFTMAX_MAX_WIDTH],
    width: usize,
    t: F,
) {
    let mut dot = F::zero();
    crate::each_index!(32, j => {
        if j < width {
            dot += g[j] * y[j];
        }
    });
    crate::each_index!(32, j => {
        if j < width {
            g[j] = y[j] * (g[j] - dot) / t;
        }
    });
}

/// Push constants of `nn::weight_norm_fwd` and `nn::weight_norm_bwd`: a weight-normalised
/// linear layer of `out_features` × `in_features` whose direction `v` is at `w_off` of the
/// parameters (where a plain layer's `W` is) and whose norms `g` (one per output) are at
/// `g_off`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct WeightNormParams {
    pub out_features: u32,
    pub in_features: u32,
    pub w_off: u32,
    pub g_off: u32,
}

/// Below this a direction's norm is taken as this (a zero-initialised head: PyTorch
/// would divide by zero).
pub const WEIGHT_NORM_EPS: f32 = 1e-12;

/// `‖v_o‖` of output row `o`, at least [`WEIGHT_NORM_EPS`].
pub fn weight_norm_row_norm<F: Real>(params: &[F], p: &WeightNormParams, o: usize) -> F {
    let base = p.w_off as usize + o * p.in_features as usize;
    let mut s = F::zero();
    let mut i = 0;
    while i < p.in_features as usize {
        let v = params[base + i];
        s += v * v;
        i += 1;
    }
    s.sqrt().max(F::of(WEIGHT_NORM_EPS))
}

/// PyTorch's `weight_norm(dim=0)`: element `(o, i)` of `W = g_o v_o / ‖v_o‖`, given the
/// row's norm.
pub fn weight_norm_value<F: Real>(
    params: &[F],
    p: &WeightNormParams,
    o: usize,
    i: usize,
    norm: F,
) -> F {
    params[p.g_off as usize + o] * params[p.w_off as usize + o * p.in_features as usize + i] / norm
}

/// The backward of one output row: from `∂L/∂W_o` (in `grads` at the row's `W` slot) to
/// `∂L/∂g_o = (∂L/∂W_o · v_o) / ‖v_o‖` and `∂L/∂v_o = (g_o / ‖v_o‖) ∂L/∂W_o −
/// (g_o ∂L/∂g_o / ‖v_o‖²) v_o`, written over the `W` slot and into `g`'s.
pub fn weight_norm_row_bwd<F: Real>(params: &[F], grads: &mut [F], p: &WeightNormParams, o: usize) {
    let base = p.w_off as usize + o * p.in_features as usize;
    let n = p.in_features as usize;
    let norm = weight_norm_row_norm(params, p, o);
    let g = params[p.g_off as usize + o];
    let mut dot = F::zero();
    let mut i = 0;
    while i < n {
        dot += grads[base + i] * params[base + i];
        i += 1;
    }
    let dg = dot / norm;
    let mut i = 0;
    while i < n {
        grads[base + i] = g / norm * grads[base + i] - g * dg / (norm * norm) * params[base + i];
        i += 1;
    }
    grads[p.g_off as usize + o] = dg;
}
