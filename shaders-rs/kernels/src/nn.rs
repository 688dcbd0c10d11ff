//! Dense layers on the GPU: a tiled GEMM in workgroup memory (forward and both halves
//! of the backward of `y = x Wᵀ + b`, chosen by strides: see `drape_shared::nn`), the
//! deterministic reduction of split weight gradients, and the activations.
//!
//! `gemm` bindings: `a`, `b`, `bias` (read), `c` (written, or added to). One workgroup
//! of 16 × 16 invocations computes a 64 × 64 block of `C`, each invocation a 4 × 4
//! sub-block, stepping through `k` 16 at a time with the 64 × 16 slices of `A` and `B`
//! staged in workgroup memory (two barriers per step).
//! `sum_weight_grad` bindings: `partials` (read), `grad` (written).
//! `act_fwd`: `pre` (read), `post` (written). `act_bwd`: `pre`, `post`, `grad_post`
//! (read), `grad_pre` (written).

use drape_shared::nn::{
    activate, activate_bwd, softmax_row, softmax_row_bwd, ActParams, GemmParams, WeightGradParams, ACT_SOFTMAX,
    GEMM_ACCUMULATE, GEMM_BIAS, GEMM_K_STEP, GEMM_ONES_COLUMN, GEMM_TILE, SOFTMAX_MAX_WIDTH,
};
use spirv_std::arch::workgroup_memory_barrier_with_group_sync as barrier;
use spirv_std::glam::UVec3;
use spirv_std::spirv;

const TILE: usize = GEMM_TILE as usize;
const KS: usize = GEMM_K_STEP as usize;
const STAGED: usize = TILE * KS;

/// `C (+)= A B (+ bias)` for one 64 × 64 block of one split of `k`.
#[spirv(compute(threads(16, 16)))]
pub fn gemm(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &GemmParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] a: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] b: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] bias: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] c: &mut [f32],
    #[spirv(workgroup)] a_tile: &mut [f32; STAGED],
    #[spirv(workgroup)] b_tile: &mut [f32; STAGED],
) {
    let lid = lid as usize;
    let n0 = group.x * GEMM_TILE;
    let m0 = group.y * GEMM_TILE;
    let k_begin = group.z * p.k_chunk;
    let k_end = if k_begin + p.k_chunk < p.k { k_begin + p.k_chunk } else { p.k };
    let tx = (lid % 16) * 4;
    let ty = (lid / 16) * 4;
    let ones_col = if p.flags & GEMM_ONES_COLUMN != 0 { p.n - 1 } else { u32::MAX };
    let mut acc = [[0.0f32; 4]; 4];
    let mut k0 = k_begin;
    while k0 < k_end {
        // Stage A[m0.., k0..] as a_tile[kk * 64 + row] and B[k0.., n0..] as
        // b_tile[kk * 64 + col]; out-of-range elements are 0.
        let mut l = 0;
        while l < STAGED / 256 {
            let idx = lid + 256 * l;
            let row = (idx / KS) as u32;
            let kk = (idx % KS) as u32;
            let (m, k) = (m0 + row, k0 + kk);
            a_tile[kk as usize * TILE + row as usize] =
                if m < p.m && k < k_end { a[(p.a_off + m * p.a_sm + k * p.a_sk) as usize] } else { 0.0 };
            let kk = (idx / TILE) as u32;
            let col = (idx % TILE) as u32;
            let (k, n) = (k0 + kk, n0 + col);
            b_tile[kk as usize * TILE + col as usize] = if k < k_end && n < p.n {
                if n == ones_col {
                    1.0
                } else {
                    b[(p.b_off + k * p.b_sk + n * p.b_sn) as usize]
                }
            } else {
                0.0
            };
            l += 1;
        }
        barrier();
        let mut kk = 0;
        while kk < KS {
            let ar = [a_tile[kk * TILE + ty], a_tile[kk * TILE + ty + 1], a_tile[kk * TILE + ty + 2], a_tile[kk * TILE + ty + 3]];
            let br = [b_tile[kk * TILE + tx], b_tile[kk * TILE + tx + 1], b_tile[kk * TILE + tx + 2], b_tile[kk * TILE + tx + 3]];
            let mut i = 0;
            while i < 4 {
                acc[i][0] += ar[i] * br[0];
                acc[i][1] += ar[i] * br[1];
                acc[i][2] += ar[i] * br[2];
                acc[i][3] += ar[i] * br[3];
                i += 1;
            }
            kk += 1;
        }
        // Everyone is done with the slices before they are overwritten.
        barrier();
        k0 += GEMM_K_STEP;
    }
    let mut i = 0;
    while i < 4 {
        let m = m0 + ty as u32 + i as u32;
        let mut j = 0;
        while j < 4 {
            let n = n0 + tx as u32 + j as u32;
            if m < p.m && n < p.n {
                let at = (p.c_off + group.z * p.c_split + m * p.ldc + n) as usize;
                let mut v = acc[i][j];
                if p.flags & GEMM_BIAS != 0 {
                    v += bias[(p.bias_off + n) as usize];
                }
                if p.flags & GEMM_ACCUMULATE != 0 {
                    v += c[at];
                }
                c[at] = v;
            }
            j += 1;
        }
        i += 1;
    }
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
    let mut sum = 0.0f32;
    let mut s = 0;
    while s < p.splits {
        sum += partials[(s * slots + id.x) as usize];
        s += 1;
    }
    let (o, i) = (id.x / cols, id.x % cols);
    if i == p.in_features {
        grad[(p.b_off + o) as usize] = sum;
    } else {
        grad[(p.w_off + o * p.in_features + i) as usize] = sum;
    }
}

/// `post = act(pre)`; softmax runs one invocation per row, the others one per element.
#[spirv(compute(threads(256)))]
pub fn act_fwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &ActParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pre: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] post: &mut [f32],
) {
    // Two-dimensional grid: 150k rows of 128 are more than 65,535 groups of 256.
    let flat = id.y * groups.x * 256 + id.x;
    let i = flat as usize;
    if p.kind == ACT_SOFTMAX {
        if flat >= p.rows {
            return;
        }
        let w = p.width as usize;
        let mut row = [0.0f32; SOFTMAX_MAX_WIDTH];
        let mut j = 0;
        while j < w {
            row[j] = pre[i * w + j];
            j += 1;
        }
        softmax_row(&mut row, w, p.temperature);
        j = 0;
        while j < w {
            post[i * w + j] = row[j];
            j += 1;
        }
    } else {
        if flat >= p.rows * p.width {
            return;
        }
        post[i] = activate(p.kind, pre[i]);
    }
}

/// `grad_pre` from `grad_post` (the layout of [`act_fwd`]).
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
    // Two-dimensional grid: 150k rows of 128 are more than 65,535 groups of 256.
    let flat = id.y * groups.x * 256 + id.x;
    let i = flat as usize;
    if p.kind == ACT_SOFTMAX {
        if flat >= p.rows {
            return;
        }
        let w = p.width as usize;
        let mut y = [0.0f32; SOFTMAX_MAX_WIDTH];
        let mut g = [0.0f32; SOFTMAX_MAX_WIDTH];
        let mut j = 0;
        while j < w {
            y[j] = post[i * w + j];
            g[j] = grad_post[i * w + j];
            j += 1;
        }
        softmax_row_bwd(&y, &mut g, w, p.temperature);
        j = 0;
        while j < w {
            grad_pre[i * w + j] = g[j];
            j += 1;
        }
    } else {
        if flat >= p.rows * p.width {
            return;
        }
        grad_pre[i] = activate_bwd(p.kind, pre[i], post[i], grad_post[i]);
    }
}
