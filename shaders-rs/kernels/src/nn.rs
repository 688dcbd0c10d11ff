//! Dense layers on any device: the workgroup-tiled GEMM (forward and both halves of the
//! backward of `y = x Wᵀ + b`, chosen by strides: see `drape_shared::nn`), the
//! deterministic reduction of split weight gradients, the activations, softmax and
//! weight normalisation. The GEMMs tuned for CPU devices (lavapipe) are in
//! [`crate::nn_lavapipe`], which the engine records there instead of `gemm_tiled`.
//!
//! | kernel | what | the engine records it for |
//! | --- | --- | --- |
//! | `gemm_tiled` | `C (+)= A B (+ bias)`, 64 × 64 tiles staged in workgroup memory | every GEMM on a GPU (`GemmVariant::Auto`, `Tiled`) |
//! | `sum_weight_grad` | the splits of a weight gradient, summed in order | every layer's backward |
//! | `act_fwd`, `act_bwd` | an activation and its gradient, an element an invocation | buffers not in whole 16-byte texels |
//! | `act_fwd4`, `act_bwd4` | the same, 4 elements an invocation (`vec4` views) | every other activation but GELU and softmax |
//! | `act_fwd4_gelu`, `act_bwd4_gelu` | GELU alone, 4 elements an invocation | GELU layers (the decoders' hidden ones) |
//! | `softmax_fwd`, `softmax_bwd` | a softmax over each row, an invocation a row | softmax layers (at most 32 wide) |
//! | `weight_norm_fwd`, `weight_norm_bwd` | `W = g v / ‖v‖` and its gradient, an invocation an output row | weight-normalised layers |
//!
//! GEMM bindings: `a`, `b`, `bias` (read), `c` (written, or added to).
//! `sum_weight_grad` bindings: `partials` (read), `grad` (written).
//! `act_fwd`, `act_fwd4*`, `softmax_fwd`: `pre` (read), `post` (written). `act_bwd`,
//! `act_bwd4*`: `pre`, `post`, `grad_post` (read), `grad_pre` (written); `softmax_bwd`
//! the same without `pre`.
//! `weight_norm_fwd`: `params` (read), `effective` (written); `weight_norm_bwd`:
//! `params` (read), `grads` (read and written).

use drape_shared::each_index;
use drape_shared::nn::{
    activate, activate_bwd, gelu, gelu_grad, softmax_row, softmax_row_bwd, ActParams, GemmParams,
    WeightGradParams, GEMM_ACCUMULATE, GEMM_BIAS, GEMM_K_STEP, GEMM_ONES_ROW, GEMM_TILE,
    SOFTMAX_MAX_WIDTH,
};
use spirv_std::arch::workgroup_memory_barrier_with_group_sync as barrier;
use spirv_std::glam::UVec3;
use spirv_std::glam::Vec4;
use spirv_std::spirv;

const TILE: usize = GEMM_TILE as usize;
const KS: usize = GEMM_K_STEP as usize;
/// Words per staged row of `k`: one more than the tile, so that staging along `k`
/// (consecutive invocations 65 words apart) spreads over the banks instead of hitting
/// one.
const PITCH: usize = TILE + 1;
/// Side of the grid of invocations in a workgroup of `gemm_tiled` (16 × 16).
const SIDE: u32 = GEMM_TILE / 4;

/// The 4 × 4 multiply-adds of one step of `k`: rows `a[i]` (the invocation's rows
/// `ty + 16 i`) times columns `b[j]` (`tx + 16 j`) into `acc[4 i + j]`, every index a
/// constant so that the sums stay in registers.
#[inline]
fn fma_4x4(mut acc: [f32; 16], a: [f32; 4], b: [f32; 4]) -> [f32; 16] {
    each_index!(4, i => {
        each_index!(4, j => {
            acc[4 * i + j] += a[i] * b[j];
        });
    });
    acc
}

/// Stores `acc[4 i + j]` at (row `m0 + 16 i`, column `n0 + 16 j`) of split `base` where
/// it lies inside `C`, adding the bias or what `C` holds as the flags say.
#[inline]
fn store_4x4(
    acc: [f32; 16],
    p: &GemmParams,
    c: &mut [f32],
    bias: &[f32],
    base: u32,
    m0: u32,
    n0: u32,
) {
    each_index!(4, i => {
        each_index!(4, j => {
            let (m, n) = (m0 + 16 * i as u32, n0 + 16 * j as u32);
            if m < p.m && n < p.n {
                let at = (base + m * p.ldc + n) as usize;
                let mut v = acc[4 * i + j];
                if p.flags & GEMM_BIAS != 0 {
                    v += bias[(p.bias_off + n) as usize];
                }
                if p.flags & GEMM_ACCUMULATE != 0 {
                    v += c[at];
                }
                c[at] = v;
            }
        });
    });
}

/// `C (+)= A B (+ bias)` for a 64 × 64 tile of one split of `k` (the GPU kernel): 256
/// invocations in a 16 × 16 grid, each keeping a 4 × 4 block of sums (rows `ty + 16 i`,
/// columns `tx + 16 j`) in registers. Each step through `k` stages 16 × 64 slices of `A`
/// and `B` in workgroup memory (loaded along whichever of their strides is 1, so the
/// loads coalesce for all three GEMMs of a layer) and every invocation reads 4 + 4
/// values per 16 multiply-adds. The sums of `k` run in order, so the result does not
/// depend on scheduling. The 4 × 4 block is what keeps workgroup-memory reads at half a
/// value per multiply-add; one row and 32 columns per invocation would read one
/// (docs/performance.md, H100 "Training", compares the two).
#[spirv(compute(threads(256)))]
pub fn gemm_tiled(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &GemmParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] a: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] b: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] bias: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] c: &mut [f32],
    #[spirv(workgroup)] a_tile: &mut [f32; KS * PITCH],
    #[spirv(workgroup)] b_tile: &mut [f32; KS * PITCH],
) {
    let (tx, ty) = (lid % SIDE, lid / SIDE);
    let m_tile = group.y * GEMM_TILE;
    let n_tile = group.x * GEMM_TILE;
    let k_begin = group.z * p.k_chunk;
    let k_end = if k_begin + p.k_chunk < p.k {
        k_begin + p.k_chunk
    } else {
        p.k
    };
    let ones_row = if p.flags & GEMM_ONES_ROW != 0 {
        p.m - 1
    } else {
        u32::MAX
    };
    // The rows of the matrices as stored (the ones row past the end of `a`).
    let a_rows = if p.flags & GEMM_ONES_ROW != 0 {
        p.m - 1
    } else {
        p.m
    };
    let mut acc = [0.0f32; 16];
    let mut k0 = k_begin;
    while k0 < k_end {
        // Stage A[m_tile..+64][k0..+16] as a_tile[kk * 65 + mm] and B[k0..+16][n_tile..+64]
        // as b_tile[kk * 65 + nn]: 4 values of each per invocation, consecutive
        // invocations along the operand's unit stride.
        let mut l = 0;
        while l < (KS * TILE) as u32 / (SIDE * SIDE) {
            let idx = lid + SIDE * SIDE * l;
            let (mm, kk) = if p.a_sk == 1 {
                (idx / KS as u32, idx % KS as u32)
            } else {
                (idx % GEMM_TILE, idx / GEMM_TILE)
            };
            let (m, k) = (m_tile + mm, k0 + kk);
            a_tile[kk as usize * PITCH + mm as usize] = if k >= k_end || m >= p.m {
                0.0
            } else if m == ones_row {
                1.0
            } else if m < a_rows {
                a[(p.a_off + m * p.a_sm + k * p.a_sk) as usize]
            } else {
                0.0
            };
            let (nn, kk) = if p.b_sn == 1 {
                (idx % GEMM_TILE, idx / GEMM_TILE)
            } else {
                (idx / KS as u32, idx % KS as u32)
            };
            let (n, k) = (n_tile + nn, k0 + kk);
            b_tile[kk as usize * PITCH + nn as usize] = if k < k_end && n < p.n {
                b[(p.b_off + k * p.b_sk + n * p.b_sn) as usize]
            } else {
                0.0
            };
            l += 1;
        }
        barrier();
        // Past the end of the split the staged values are zeros: the full step adds
        // nothing there.
        let mut kk = 0;
        while kk < KS {
            let row = kk * PITCH;
            let av = [
                a_tile[row + ty as usize],
                a_tile[row + ty as usize + 16],
                a_tile[row + ty as usize + 32],
                a_tile[row + ty as usize + 48],
            ];
            let bv = [
                b_tile[row + tx as usize],
                b_tile[row + tx as usize + 16],
                b_tile[row + tx as usize + 32],
                b_tile[row + tx as usize + 48],
            ];
            acc = fma_4x4(acc, av, bv);
            kk += 1;
        }
        // Everyone is done with the slices before they are overwritten.
        barrier();
        k0 += GEMM_K_STEP;
    }
    let base = p.c_off + group.z * p.c_split;
    store_4x4(acc, p, c, bias, base, m_tile + ty, n_tile + tx);
}

/// Sums the splits of a weight gradient in split order and scatters the weight and
/// bias parts.
#[spirv(compute(threads(256)))]
pub fn sum_weight_grad(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] p: &WeightGradParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] partials: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] grad: &mut [f32],
) {
    let cols = p.in_features + 1;
    let slots = p.out_features * cols;
    if id.x >= slots {
        return;
    }
    let (o, i) = (id.x / cols, id.x % cols);
    // Partials are dWᵀ: [split][input (+ the ones row)][output].
    let at = i * p.out_features + o;
    let mut sum = 0.0f32;
    let mut s = 0;
    while s < p.splits {
        sum += partials[(s * slots + at) as usize];
        s += 1;
    }
    if i == p.in_features {
        grad[(p.b_off + o) as usize] = sum;
    } else {
        grad[(p.w_off + o * p.in_features + i) as usize] = sum;
    }
}

/// `post = act(pre)`, one invocation per element (softmax: [`softmax_fwd`]).
#[spirv(compute(threads(256)))]
pub fn act_fwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &ActParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pre: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] post: &mut [f32],
) {
    // Two-dimensional grid: 150k rows of 128 are more than 65,535 groups of 256.
    let flat = crate::flat_index(id, groups);
    if flat >= p.rows * p.width {
        return;
    }
    let i = flat as usize;
    post[i] = activate(p.kind, pre[i]);
}

/// `grad_pre` from `grad_post`, one invocation per element (softmax: [`softmax_bwd`]).
#[spirv(compute(threads(256)))]
pub fn act_bwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &ActParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pre: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] post: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] grad_post: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] grad_pre: &mut [f32],
) {
    let flat = crate::flat_index(id, groups);
    if flat >= p.rows * p.width {
        return;
    }
    let i = flat as usize;
    grad_pre[i] = activate_bwd(p.kind, pre[i], post[i], grad_post[i]);
}

/// An element-wise activation of the 4-wide kernels, chosen at compile time: llvmpipe
/// runs every branch of [`activate`], so a kernel for one activation alone does not
/// compute the others for every element.
trait Activation4 {
    /// `post` from `pre`.
    fn fwd(p: &ActParams, x: f32) -> f32;
    /// `grad_pre` from `pre`, `post` and `grad_post`.
    fn bwd(p: &ActParams, x: f32, y: f32, g: f32) -> f32;
}

/// The activation `p.kind` names ([`activate`], [`activate_bwd`]).
struct AnyActivation;

impl Activation4 for AnyActivation {
    #[inline]
    fn fwd(p: &ActParams, x: f32) -> f32 {
        activate(p.kind, x)
    }

    #[inline]
    fn bwd(p: &ActParams, x: f32, y: f32, g: f32) -> f32 {
        activate_bwd(p.kind, x, y, g)
    }
}

/// GELU alone (the decoders' hidden layers).
struct Gelu;

impl Activation4 for Gelu {
    #[inline]
    fn fwd(_: &ActParams, x: f32) -> f32 {
        gelu(x)
    }

    #[inline]
    fn bwd(_: &ActParams, x: f32, _y: f32, g: f32) -> f32 {
        g * gelu_grad(x)
    }
}

/// [`act_fwd`] 4 elements an invocation, through `vec4` views of the same buffers: on
/// llvmpipe a storage-buffer access at a per-lane address is one loop over the lanes
/// whatever its width, so this is a quarter of the loops (on a GPU, 16-byte accesses).
/// Covers `rows · width` rounded up to 4: buffers are whole 16-byte texels, and the up
/// to 3 floats past a layer's end are never read as data.
#[inline]
fn act_fwd4_with<A: Activation4>(
    id: UVec3,
    groups: UVec3,
    p: &ActParams,
    pre: &[Vec4],
    post: &mut [Vec4],
) {
    let flat = crate::flat_index(id, groups);
    if flat >= (p.rows * p.width).div_ceil(4) {
        return;
    }
    let i = flat as usize;
    let x = pre[i];
    post[i] = Vec4::new(
        A::fwd(p, x.x),
        A::fwd(p, x.y),
        A::fwd(p, x.z),
        A::fwd(p, x.w),
    );
}

/// [`act_bwd`] 4 elements an invocation (as [`act_fwd4_with`]).
#[inline]
fn act_bwd4_with<A: Activation4>(
    id: UVec3,
    groups: UVec3,
    p: &ActParams,
    pre: &[Vec4],
    post: &[Vec4],
    grad_post: &[Vec4],
    grad_pre: &mut [Vec4],
) {
    let flat = crate::flat_index(id, groups);
    if flat >= (p.rows * p.width).div_ceil(4) {
        return;
    }
    let i = flat as usize;
    let (x, y, g) = (pre[i], post[i], grad_post[i]);
    grad_pre[i] = Vec4::new(
        A::bwd(p, x.x, y.x, g.x),
        A::bwd(p, x.y, y.y, g.y),
        A::bwd(p, x.z, y.z, g.z),
        A::bwd(p, x.w, y.w, g.w),
    );
}

/// `post = act(pre)`, 4 elements an invocation (see [`act_fwd4_with`]).
#[spirv(compute(threads(256)))]
pub fn act_fwd4(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &ActParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pre: &[Vec4],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] post: &mut [Vec4],
) {
    act_fwd4_with::<AnyActivation>(id, groups, p, pre, post);
}

/// `post = gelu(pre)`, 4 elements an invocation (see [`act_fwd4_with`]).
#[spirv(compute(threads(256)))]
pub fn act_fwd4_gelu(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &ActParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pre: &[Vec4],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] post: &mut [Vec4],
) {
    act_fwd4_with::<Gelu>(id, groups, p, pre, post);
}

/// `grad_pre` from `grad_post`, 4 elements an invocation (see [`act_bwd4_with`]).
#[spirv(compute(threads(256)))]
pub fn act_bwd4(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &ActParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pre: &[Vec4],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] post: &[Vec4],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] grad_post: &[Vec4],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] grad_pre: &mut [Vec4],
) {
    act_bwd4_with::<AnyActivation>(id, groups, p, pre, post, grad_post, grad_pre);
}

/// GELU's `grad_pre` from `grad_post`, 4 elements an invocation (see [`act_bwd4_with`]).
#[spirv(compute(threads(256)))]
pub fn act_bwd4_gelu(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &ActParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pre: &[Vec4],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] post: &[Vec4],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] grad_post: &[Vec4],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] grad_pre: &mut [Vec4],
) {
    act_bwd4_with::<Gelu>(id, groups, p, pre, post, grad_post, grad_pre);
}

/// `post = softmax(pre / T)` of each row of `p.width` (at most 32), one invocation per
/// row. Its own kernel: llvmpipe runs both sides of a branch, so a softmax in
/// [`act_fwd`] would cost every element-wise activation its code.
#[spirv(compute(threads(256)))]
pub fn softmax_fwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &ActParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pre: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] post: &mut [f32],
) {
    let flat = crate::flat_index(id, groups);
    if flat >= p.rows {
        return;
    }
    let (i, w) = (flat as usize, p.width as usize);
    // Constant indices into the row (see `drape_shared::each_index!`).
    let mut row = [0.0f32; SOFTMAX_MAX_WIDTH];
    drape_shared::each_index!(32, j => {
        if j < w {
            row[j] = pre[i * w + j];
        }
    });
    softmax_row(&mut row, w, p.temperature);
    drape_shared::each_index!(32, j => {
        if j < w {
            post[i * w + j] = row[j];
        }
    });
}

/// The gradient of [`softmax_fwd`] on its logits, one invocation per row.
#[spirv(compute(threads(256)))]
pub fn softmax_bwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &ActParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] post: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] grad_post: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] grad_pre: &mut [f32],
) {
    let flat = crate::flat_index(id, groups);
    if flat >= p.rows {
        return;
    }
    let (i, w) = (flat as usize, p.width as usize);
    let mut y = [0.0f32; SOFTMAX_MAX_WIDTH];
    let mut g = [0.0f32; SOFTMAX_MAX_WIDTH];
    drape_shared::each_index!(32, j => {
        if j < w {
            y[j] = post[i * w + j];
            g[j] = grad_post[i * w + j];
        }
    });
    softmax_row_bwd(&y, &mut g, w, p.temperature);
    drape_shared::each_index!(32, j => {
        if j < w {
            grad_pre[i * w + j] = g[j];
        }
    });
}

/// Weight normalisation's forward (`drape_shared::nn::weight_norm_value`): one
/// invocation per output row writes the row of `W = g v / ‖v‖` into `effective` (a copy
/// of the parameters the GEMMs then read).
#[spirv(compute(threads(64)))]
pub fn weight_norm_fwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] p: &drape_shared::nn::WeightNormParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] params: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] effective: &mut [f32],
) {
    let o = id.x;
    if o >= p.out_features {
        return;
    }
    let o = o as usize;
    let norm = drape_shared::nn::weight_norm_row_norm(params, p, o);
    let base = p.w_off as usize + o * p.in_features as usize;
    let mut i = 0;
    while i < p.in_features as usize {
        effective[base + i] = drape_shared::nn::weight_norm_value(params, p, o, i, norm);
        i += 1;
    }
}

/// Weight normalisation's backward (`drape_shared::nn::weight_norm_row_bwd`): one
/// invocation per output row turns the row's `∂L/∂W` in `grads` into `∂L/∂v` (in place)
/// and `∂L/∂g`.
#[spirv(compute(threads(64)))]
pub fn weight_norm_bwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] p: &drape_shared::nn::WeightNormParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] params: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] grads: &mut [f32],
) {
    if id.x >= p.out_features {
        return;
    }
    drape_shared::nn::weight_norm_row_bwd(params, grads, p, id.x as usize);
}
