//! Dense layers on the GPU: GEMM (forward and both halves of the backward of
//! `y = x Wᵀ + b`, chosen by strides: see `drape_shared::nn`), the deterministic
//! reduction of split weight gradients, the activations, softmax and weight
//! normalisation.
//!
//! GEMM kernels, one set of parameters (`GemmParams`): `gemm_tiled` (GPUs) stages slices
//! of `A` and `B` in workgroup memory; `gemm_blocked` (CPU devices) keeps an 8 × 8 block
//! per invocation in registers; for CPU devices with subgroups of 8 (`subgroup-ballot`
//! builds), `gemm_subgroup` shares `B` across the subgroup by broadcasts, and the texel
//! GEMMs (`gemm_texel`, `gemm_texel_k4*`, `gemm_texel_k4n4*`, `gemm_texel_b4*`,
//! `gemm_texel_m4n4c4`, `gemm_texel_klanes_*`) read their operands through texel views,
//! each for the operand layout its doc states. All but `gemm_texel_klanes_*` add the
//! same terms in the same order of `k`.
//!
//! GEMM bindings: `a`, `b`, `bias` (read), `c` (written, or added to); the texel GEMMs
//! bind some of them as texel buffers, and their `c4` epilogues write `c` as `vec4`s.
//! `sum_weight_grad` bindings: `partials` (read), `grad` (written).
//! `act_fwd`, `act_fwd4*`, `softmax_fwd`: `pre` (read), `post` (written). `act_bwd`,
//! `act_bwd4*`: `pre`, `post`, `grad_post` (read), `grad_pre` (written); `softmax_bwd`
//! the same without `pre`.
//! `weight_norm_fwd`: `params` (read), `effective` (written); `weight_norm_bwd`:
//! `params` (read), `grads` (read and written).

use drape_shared::each_index;
use drape_shared::nn::{
    activate, activate_bwd, gelu, gelu_grad, softmax_row, softmax_row_bwd, ActParams, GemmParams, WeightGradParams,
    GEMM_ACCUMULATE, GEMM_BIAS, GEMM_BLOCK, GEMM_K_STEP, GEMM_ONES_ROW, GEMM_TILE, SOFTMAX_MAX_WIDTH,
};
#[cfg(feature = "subgroup-ballot")]
use drape_shared::nn::{GEMM_K4_ROWS, GEMM_KL_ROWS, GEMM_SG_COLS, GEMM_SG_ROWS, GEMM_TX_ROWS};
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
fn store_4x4(acc: [f32; 16], p: &GemmParams, c: &mut [f32], bias: &[f32], base: u32, m0: u32, n0: u32) {
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
/// depend on scheduling. (A kernel of one row and 32 columns per invocation, reading one
/// staged value per multiply-add, makes 2.4-3.4 TFLOP/s on an H100.)
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
    let k_end = if k_begin + p.k_chunk < p.k { k_begin + p.k_chunk } else { p.k };
    let ones_row = if p.flags & GEMM_ONES_ROW != 0 { p.m - 1 } else { u32::MAX };
    // The rows of the matrices as stored (the ones row past the end of `a`).
    let a_rows = if p.flags & GEMM_ONES_ROW != 0 { p.m - 1 } else { p.m };
    let mut acc = [0.0f32; 16];
    let mut k0 = k_begin;
    while k0 < k_end {
        // Stage A[m_tile..+64][k0..+16] as a_tile[kk * 65 + mm] and B[k0..+16][n_tile..+64]
        // as b_tile[kk * 65 + nn]: 4 values of each per invocation, consecutive
        // invocations along the operand's unit stride.
        let mut l = 0;
        while l < (KS * TILE) as u32 / (SIDE * SIDE) {
            let idx = lid + SIDE * SIDE * l;
            let (mm, kk) = if p.a_sk == 1 { (idx / KS as u32, idx % KS as u32) } else { (idx % GEMM_TILE, idx / GEMM_TILE) };
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
            let (nn, kk) = if p.b_sn == 1 { (idx % GEMM_TILE, idx / GEMM_TILE) } else { (idx / KS as u32, idx % KS as u32) };
            let (n, k) = (n_tile + nn, k0 + kk);
            b_tile[kk as usize * PITCH + nn as usize] = if k < k_end && n < p.n { b[(p.b_off + k * p.b_sk + n * p.b_sn) as usize] } else { 0.0 };
            l += 1;
        }
        barrier();
        // Past the end of the split the staged values are zeros: the full step adds
        // nothing there.
        let mut kk = 0;
        while kk < KS {
            let row = kk * PITCH;
            let av = [a_tile[row + ty as usize], a_tile[row + ty as usize + 16], a_tile[row + ty as usize + 32], a_tile[row + ty as usize + 48]];
            let bv = [b_tile[row + tx as usize], b_tile[row + tx as usize + 16], b_tile[row + tx as usize + 32], b_tile[row + tx as usize + 48]];
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

/// One step of `k` of the register-blocked GEMM: 8 values of `A` (a column of the
/// invocation's rows) and 8 of `B` (a row of its columns), 64 multiply-adds into
/// accumulators with constant indices. Out-of-range rows and columns read the last
/// valid element (their results are never stored).
macro_rules! block_step {
    ($acc:ident, $a:ident, $b:ident, $p:ident, $m0:expr, $n0:expr, $k:expr, $ones_row:expr, $m_last:expr) => {{
        let a0 = if $m0 + 0 == $ones_row { 1.0 } else { $a[($p.a_off + ($m0 + 0).min($m_last) * $p.a_sm + $k * $p.a_sk) as usize] };
        let a1 = if $m0 + 1 == $ones_row { 1.0 } else { $a[($p.a_off + ($m0 + 1).min($m_last) * $p.a_sm + $k * $p.a_sk) as usize] };
        let a2 = if $m0 + 2 == $ones_row { 1.0 } else { $a[($p.a_off + ($m0 + 2).min($m_last) * $p.a_sm + $k * $p.a_sk) as usize] };
        let a3 = if $m0 + 3 == $ones_row { 1.0 } else { $a[($p.a_off + ($m0 + 3).min($m_last) * $p.a_sm + $k * $p.a_sk) as usize] };
        let a4 = if $m0 + 4 == $ones_row { 1.0 } else { $a[($p.a_off + ($m0 + 4).min($m_last) * $p.a_sm + $k * $p.a_sk) as usize] };
        let a5 = if $m0 + 5 == $ones_row { 1.0 } else { $a[($p.a_off + ($m0 + 5).min($m_last) * $p.a_sm + $k * $p.a_sk) as usize] };
        let a6 = if $m0 + 6 == $ones_row { 1.0 } else { $a[($p.a_off + ($m0 + 6).min($m_last) * $p.a_sm + $k * $p.a_sk) as usize] };
        let a7 = if $m0 + 7 == $ones_row { 1.0 } else { $a[($p.a_off + ($m0 + 7).min($m_last) * $p.a_sm + $k * $p.a_sk) as usize] };
        let b0 = $b[($p.b_off + $k * $p.b_sk + ($n0 + 0).min($p.n - 1) * $p.b_sn) as usize];
        let b1 = $b[($p.b_off + $k * $p.b_sk + ($n0 + 1).min($p.n - 1) * $p.b_sn) as usize];
        let b2 = $b[($p.b_off + $k * $p.b_sk + ($n0 + 2).min($p.n - 1) * $p.b_sn) as usize];
        let b3 = $b[($p.b_off + $k * $p.b_sk + ($n0 + 3).min($p.n - 1) * $p.b_sn) as usize];
        let b4 = $b[($p.b_off + $k * $p.b_sk + ($n0 + 4).min($p.n - 1) * $p.b_sn) as usize];
        let b5 = $b[($p.b_off + $k * $p.b_sk + ($n0 + 5).min($p.n - 1) * $p.b_sn) as usize];
        let b6 = $b[($p.b_off + $k * $p.b_sk + ($n0 + 6).min($p.n - 1) * $p.b_sn) as usize];
        let b7 = $b[($p.b_off + $k * $p.b_sk + ($n0 + 7).min($p.n - 1) * $p.b_sn) as usize];
        $acc[0] += a0 * b0;
        $acc[1] += a0 * b1;
        $acc[2] += a0 * b2;
        $acc[3] += a0 * b3;
        $acc[4] += a0 * b4;
        $acc[5] += a0 * b5;
        $acc[6] += a0 * b6;
        $acc[7] += a0 * b7;
        $acc[8] += a1 * b0;
        $acc[9] += a1 * b1;
        $acc[10] += a1 * b2;
        $acc[11] += a1 * b3;
        $acc[12] += a1 * b4;
        $acc[13] += a1 * b5;
        $acc[14] += a1 * b6;
        $acc[15] += a1 * b7;
        $acc[16] += a2 * b0;
        $acc[17] += a2 * b1;
        $acc[18] += a2 * b2;
        $acc[19] += a2 * b3;
        $acc[20] += a2 * b4;
        $acc[21] += a2 * b5;
        $acc[22] += a2 * b6;
        $acc[23] += a2 * b7;
        $acc[24] += a3 * b0;
        $acc[25] += a3 * b1;
        $acc[26] += a3 * b2;
        $acc[27] += a3 * b3;
        $acc[28] += a3 * b4;
        $acc[29] += a3 * b5;
        $acc[30] += a3 * b6;
        $acc[31] += a3 * b7;
        $acc[32] += a4 * b0;
        $acc[33] += a4 * b1;
        $acc[34] += a4 * b2;
        $acc[35] += a4 * b3;
        $acc[36] += a4 * b4;
        $acc[37] += a4 * b5;
        $acc[38] += a4 * b6;
        $acc[39] += a4 * b7;
        $acc[40] += a5 * b0;
        $acc[41] += a5 * b1;
        $acc[42] += a5 * b2;
        $acc[43] += a5 * b3;
        $acc[44] += a5 * b4;
        $acc[45] += a5 * b5;
        $acc[46] += a5 * b6;
        $acc[47] += a5 * b7;
        $acc[48] += a6 * b0;
        $acc[49] += a6 * b1;
        $acc[50] += a6 * b2;
        $acc[51] += a6 * b3;
        $acc[52] += a6 * b4;
        $acc[53] += a6 * b5;
        $acc[54] += a6 * b6;
        $acc[55] += a6 * b7;
        $acc[56] += a7 * b0;
        $acc[57] += a7 * b1;
        $acc[58] += a7 * b2;
        $acc[59] += a7 * b3;
        $acc[60] += a7 * b4;
        $acc[61] += a7 * b5;
        $acc[62] += a7 * b6;
        $acc[63] += a7 * b7;
    }};
}

/// Stores the invocation's 8 × 8 block (bias added or accumulated as flagged).
macro_rules! block_store {
    ($acc:ident, $p:ident, $m0:expr, $n0:expr, $z:expr, $bias:ident, $c:ident) => {{
        if $m0 + 0 < $p.m && $n0 + 0 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 0) * $p.ldc + $n0 + 0) as usize;
            let mut v = $acc[0];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 0) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 0 < $p.m && $n0 + 1 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 0) * $p.ldc + $n0 + 1) as usize;
            let mut v = $acc[1];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 1) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 0 < $p.m && $n0 + 2 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 0) * $p.ldc + $n0 + 2) as usize;
            let mut v = $acc[2];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 2) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 0 < $p.m && $n0 + 3 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 0) * $p.ldc + $n0 + 3) as usize;
            let mut v = $acc[3];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 3) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 0 < $p.m && $n0 + 4 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 0) * $p.ldc + $n0 + 4) as usize;
            let mut v = $acc[4];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 4) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 0 < $p.m && $n0 + 5 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 0) * $p.ldc + $n0 + 5) as usize;
            let mut v = $acc[5];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 5) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 0 < $p.m && $n0 + 6 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 0) * $p.ldc + $n0 + 6) as usize;
            let mut v = $acc[6];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 6) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 0 < $p.m && $n0 + 7 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 0) * $p.ldc + $n0 + 7) as usize;
            let mut v = $acc[7];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 7) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 1 < $p.m && $n0 + 0 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 1) * $p.ldc + $n0 + 0) as usize;
            let mut v = $acc[8];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 0) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 1 < $p.m && $n0 + 1 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 1) * $p.ldc + $n0 + 1) as usize;
            let mut v = $acc[9];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 1) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 1 < $p.m && $n0 + 2 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 1) * $p.ldc + $n0 + 2) as usize;
            let mut v = $acc[10];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 2) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 1 < $p.m && $n0 + 3 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 1) * $p.ldc + $n0 + 3) as usize;
            let mut v = $acc[11];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 3) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 1 < $p.m && $n0 + 4 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 1) * $p.ldc + $n0 + 4) as usize;
            let mut v = $acc[12];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 4) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 1 < $p.m && $n0 + 5 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 1) * $p.ldc + $n0 + 5) as usize;
            let mut v = $acc[13];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 5) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 1 < $p.m && $n0 + 6 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 1) * $p.ldc + $n0 + 6) as usize;
            let mut v = $acc[14];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 6) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 1 < $p.m && $n0 + 7 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 1) * $p.ldc + $n0 + 7) as usize;
            let mut v = $acc[15];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 7) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 2 < $p.m && $n0 + 0 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 2) * $p.ldc + $n0 + 0) as usize;
            let mut v = $acc[16];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 0) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 2 < $p.m && $n0 + 1 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 2) * $p.ldc + $n0 + 1) as usize;
            let mut v = $acc[17];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 1) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 2 < $p.m && $n0 + 2 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 2) * $p.ldc + $n0 + 2) as usize;
            let mut v = $acc[18];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 2) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 2 < $p.m && $n0 + 3 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 2) * $p.ldc + $n0 + 3) as usize;
            let mut v = $acc[19];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 3) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 2 < $p.m && $n0 + 4 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 2) * $p.ldc + $n0 + 4) as usize;
            let mut v = $acc[20];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 4) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 2 < $p.m && $n0 + 5 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 2) * $p.ldc + $n0 + 5) as usize;
            let mut v = $acc[21];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 5) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 2 < $p.m && $n0 + 6 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 2) * $p.ldc + $n0 + 6) as usize;
            let mut v = $acc[22];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 6) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 2 < $p.m && $n0 + 7 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 2) * $p.ldc + $n0 + 7) as usize;
            let mut v = $acc[23];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 7) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 3 < $p.m && $n0 + 0 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 3) * $p.ldc + $n0 + 0) as usize;
            let mut v = $acc[24];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 0) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 3 < $p.m && $n0 + 1 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 3) * $p.ldc + $n0 + 1) as usize;
            let mut v = $acc[25];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 1) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 3 < $p.m && $n0 + 2 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 3) * $p.ldc + $n0 + 2) as usize;
            let mut v = $acc[26];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 2) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 3 < $p.m && $n0 + 3 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 3) * $p.ldc + $n0 + 3) as usize;
            let mut v = $acc[27];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 3) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 3 < $p.m && $n0 + 4 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 3) * $p.ldc + $n0 + 4) as usize;
            let mut v = $acc[28];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 4) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 3 < $p.m && $n0 + 5 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 3) * $p.ldc + $n0 + 5) as usize;
            let mut v = $acc[29];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 5) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 3 < $p.m && $n0 + 6 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 3) * $p.ldc + $n0 + 6) as usize;
            let mut v = $acc[30];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 6) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 3 < $p.m && $n0 + 7 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 3) * $p.ldc + $n0 + 7) as usize;
            let mut v = $acc[31];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 7) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 4 < $p.m && $n0 + 0 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 4) * $p.ldc + $n0 + 0) as usize;
            let mut v = $acc[32];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 0) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 4 < $p.m && $n0 + 1 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 4) * $p.ldc + $n0 + 1) as usize;
            let mut v = $acc[33];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 1) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 4 < $p.m && $n0 + 2 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 4) * $p.ldc + $n0 + 2) as usize;
            let mut v = $acc[34];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 2) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 4 < $p.m && $n0 + 3 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 4) * $p.ldc + $n0 + 3) as usize;
            let mut v = $acc[35];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 3) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 4 < $p.m && $n0 + 4 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 4) * $p.ldc + $n0 + 4) as usize;
            let mut v = $acc[36];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 4) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 4 < $p.m && $n0 + 5 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 4) * $p.ldc + $n0 + 5) as usize;
            let mut v = $acc[37];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 5) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 4 < $p.m && $n0 + 6 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 4) * $p.ldc + $n0 + 6) as usize;
            let mut v = $acc[38];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 6) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 4 < $p.m && $n0 + 7 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 4) * $p.ldc + $n0 + 7) as usize;
            let mut v = $acc[39];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 7) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 5 < $p.m && $n0 + 0 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 5) * $p.ldc + $n0 + 0) as usize;
            let mut v = $acc[40];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 0) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 5 < $p.m && $n0 + 1 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 5) * $p.ldc + $n0 + 1) as usize;
            let mut v = $acc[41];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 1) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 5 < $p.m && $n0 + 2 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 5) * $p.ldc + $n0 + 2) as usize;
            let mut v = $acc[42];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 2) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 5 < $p.m && $n0 + 3 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 5) * $p.ldc + $n0 + 3) as usize;
            let mut v = $acc[43];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 3) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 5 < $p.m && $n0 + 4 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 5) * $p.ldc + $n0 + 4) as usize;
            let mut v = $acc[44];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 4) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 5 < $p.m && $n0 + 5 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 5) * $p.ldc + $n0 + 5) as usize;
            let mut v = $acc[45];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 5) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 5 < $p.m && $n0 + 6 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 5) * $p.ldc + $n0 + 6) as usize;
            let mut v = $acc[46];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 6) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 5 < $p.m && $n0 + 7 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 5) * $p.ldc + $n0 + 7) as usize;
            let mut v = $acc[47];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 7) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 6 < $p.m && $n0 + 0 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 6) * $p.ldc + $n0 + 0) as usize;
            let mut v = $acc[48];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 0) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 6 < $p.m && $n0 + 1 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 6) * $p.ldc + $n0 + 1) as usize;
            let mut v = $acc[49];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 1) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 6 < $p.m && $n0 + 2 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 6) * $p.ldc + $n0 + 2) as usize;
            let mut v = $acc[50];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 2) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 6 < $p.m && $n0 + 3 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 6) * $p.ldc + $n0 + 3) as usize;
            let mut v = $acc[51];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 3) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 6 < $p.m && $n0 + 4 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 6) * $p.ldc + $n0 + 4) as usize;
            let mut v = $acc[52];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 4) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 6 < $p.m && $n0 + 5 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 6) * $p.ldc + $n0 + 5) as usize;
            let mut v = $acc[53];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 5) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 6 < $p.m && $n0 + 6 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 6) * $p.ldc + $n0 + 6) as usize;
            let mut v = $acc[54];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 6) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 6 < $p.m && $n0 + 7 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 6) * $p.ldc + $n0 + 7) as usize;
            let mut v = $acc[55];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 7) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 7 < $p.m && $n0 + 0 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 7) * $p.ldc + $n0 + 0) as usize;
            let mut v = $acc[56];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 0) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 7 < $p.m && $n0 + 1 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 7) * $p.ldc + $n0 + 1) as usize;
            let mut v = $acc[57];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 1) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 7 < $p.m && $n0 + 2 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 7) * $p.ldc + $n0 + 2) as usize;
            let mut v = $acc[58];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 2) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 7 < $p.m && $n0 + 3 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 7) * $p.ldc + $n0 + 3) as usize;
            let mut v = $acc[59];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 3) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 7 < $p.m && $n0 + 4 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 7) * $p.ldc + $n0 + 4) as usize;
            let mut v = $acc[60];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 4) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 7 < $p.m && $n0 + 5 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 7) * $p.ldc + $n0 + 5) as usize;
            let mut v = $acc[61];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 5) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 7 < $p.m && $n0 + 6 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 7) * $p.ldc + $n0 + 6) as usize;
            let mut v = $acc[62];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 6) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
        if $m0 + 7 < $p.m && $n0 + 7 < $p.n {
            let at = ($p.c_off + $z * $p.c_split + ($m0 + 7) * $p.ldc + $n0 + 7) as usize;
            let mut v = $acc[63];
            if $p.flags & GEMM_BIAS != 0 {
                v += $bias[($p.bias_off + $n0 + 7) as usize];
            }
            if $p.flags & GEMM_ACCUMULATE != 0 {
                v += $c[at];
            }
            $c[at] = v;
        }
    }};
}

/// `C (+)= A B (+ bias)` register-blocked for CPU devices (lavapipe): invocation
/// (x, y) of an 8 × 8 workgroup owns rows `m0..m0 + 8` and columns `n0..n0 + 8` of one
/// split of `k` and keeps the 64 sums in registers. On llvmpipe every buffer or
/// workgroup-memory load is a loop over the SIMD lanes (about as costly as 30
/// multiply-adds), so this kernel makes 16 loads per 64 multiply-adds, where the
/// tiled kernel makes 33 per 32 and its staging through workgroup memory only adds
/// loads (measured: `engine-bench ops`).
#[spirv(compute(threads(8, 8)))]
pub fn gemm_blocked(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] p: &GemmParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] a: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] b: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] bias: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] c: &mut [f32],
) {
    let n0 = id.x * GEMM_BLOCK;
    let m0 = id.y * GEMM_BLOCK;
    let z = id.z;
    if m0 >= p.m || n0 >= p.n {
        return;
    }
    let k_begin = z * p.k_chunk;
    let k_end = if k_begin + p.k_chunk < p.k { k_begin + p.k_chunk } else { p.k };
    let ones_row = if p.flags & GEMM_ONES_ROW != 0 { p.m - 1 } else { u32::MAX };
    // The last row of A that exists (the ones row is not stored). Every load uses an
    // in-range index: the ones row's load may be evaluated and then discarded, and an
    // out-of-range index would end the invocation (slice bounds check).
    let m_last = if p.flags & GEMM_ONES_ROW != 0 && p.m >= 2 { p.m - 2 } else { p.m - 1 };
    let mut acc = [0.0f32; 64];
    let mut k = k_begin;
    while k < k_end {
        block_step!(acc, a, b, p, m0, n0, k, ones_row, m_last);
        k += 1;
    }
    block_store!(acc, p, m0, n0, z, bias, c);
}

/// `acc[r][c] += a[r] * b` for each of a lane's rows `r` listed (written out with
/// constant indices, which keep the sums in registers) and column `c`, `b` being lane
/// `j`'s value of `bv` (the subgroup loaded 8 columns of `B` with one load, lane `j`
/// column `j`).
#[cfg(feature = "subgroup-ballot")]
macro_rules! sg_column {
    ($acc:ident, $a:ident, $bv:ident, $c:expr, $j:literal; $($r:literal),+) => {{
        let b = crate::subgroup::broadcast::<$j>($bv);
        $( $acc[$r][$c] += $a[$r] * b; )+
    }};
}

/// The 8 columns `8 g .. 8 g + 8` of the tile from one load of `B` per lane, for the
/// lane's rows listed.
#[cfg(feature = "subgroup-ballot")]
macro_rules! sg_group {
    ($acc:ident, $a:ident, $bv:ident, $g:literal; $($r:literal),+) => {{
        sg_column!($acc, $a, $bv, $g * 8 + 0, 0; $($r),+);
        sg_column!($acc, $a, $bv, $g * 8 + 1, 1; $($r),+);
        sg_column!($acc, $a, $bv, $g * 8 + 2, 2; $($r),+);
        sg_column!($acc, $a, $bv, $g * 8 + 3, 3; $($r),+);
        sg_column!($acc, $a, $bv, $g * 8 + 4, 4; $($r),+);
        sg_column!($acc, $a, $bv, $g * 8 + 5, 5; $($r),+);
        sg_column!($acc, $a, $bv, $g * 8 + 6, 6; $($r),+);
        sg_column!($acc, $a, $bv, $g * 8 + 7, 7; $($r),+);
    }};
}

/// Writes one lane's row of a tile (bias and accumulation as the flags say). A loop,
/// not 32 written-out stores: every bounds-checked store nests the rest of the kernel
/// one level deeper, and llvmpipe stops masking correctly past 80 levels (written out,
/// the stores go missing from the third row on).
#[cfg(feature = "subgroup-ballot")]
#[inline]
fn store_tile_row<const W: usize>(p: &GemmParams, c: &mut [f32], bias: &[f32], vals: [f32; W], row: u32, n0: u32, z: u32) {
    if row >= p.m {
        return;
    }
    let mut j = 0;
    while j < W as u32 {
        let col = n0 + j;
        if col < p.n {
            let at = (p.c_off + z * p.c_split + row * p.ldc + col) as usize;
            let mut v = vals[j as usize];
            if p.flags & GEMM_BIAS != 0 {
                v += bias[(p.bias_off + col) as usize];
            }
            if p.flags & GEMM_ACCUMULATE != 0 {
                v += c[at];
            }
            c[at] = v;
        }
        j += 1;
    }
}

/// Where a subgroup GEMM's workgroup works: its tile of `C` (rows from `m0`, columns
/// from `n0`), its split `z` of `k` (`k_begin..k_end`), the ones row (`u32::MAX` when
/// none), the last row of `A` that exists, and the offsets in `B` of the lane's 4
/// columns (`n0 + lane + 8 g`, clamped to the last).
#[cfg(feature = "subgroup-ballot")]
struct SgTile {
    m0: u32,
    n0: u32,
    z: u32,
    k_begin: u32,
    k_end: u32,
    ones_row: u32,
    m_last: u32,
    b_col: [u32; 4],
}

/// The tile of workgroup `group` for tiles of `tile_rows` × `tile_cols` (a workgroup
/// is one subgroup of 8, so the tile never depends on how a device numbers the
/// subgroups of a workgroup), or `None` past the last tile (the whole subgroup leaves
/// together, so no broadcast ever reads an inactive lane). Workgroups come in rows of
/// at most 65,535 (2M rows of 1,024 columns are 2M tiles).
#[cfg(feature = "subgroup-ballot")]
#[inline]
fn sg_tile(p: &GemmParams, group: UVec3, groups: UVec3, lane: u32, tile_rows: u32, tile_cols: u32) -> Option<SgTile> {
    let row_tiles = (p.m + tile_rows - 1) / tile_rows;
    let col_tiles = (p.n + tile_cols - 1) / tile_cols;
    let tile = group.y * groups.x + group.x;
    if p.m == 0 || p.n == 0 || tile >= row_tiles * col_tiles {
        return None;
    }
    let m0 = (tile % row_tiles) * tile_rows;
    let n0 = (tile / row_tiles) * tile_cols;
    let z = group.z;
    let k_begin = z * p.k_chunk;
    let k_end = if k_begin + p.k_chunk < p.k { k_begin + p.k_chunk } else { p.k };
    let ones_row = if p.flags & GEMM_ONES_ROW != 0 { p.m - 1 } else { u32::MAX };
    // The last row of A that exists (the ones row is not stored): rows past it read
    // that row (in range) and are never stored.
    let m_last = if p.flags & GEMM_ONES_ROW != 0 && p.m >= 2 { p.m - 2 } else { p.m - 1 };
    let last_col = p.n - 1;
    let b_col = [
        p.b_off + (n0 + lane).min(last_col) * p.b_sn,
        p.b_off + (n0 + 8 + lane).min(last_col) * p.b_sn,
        p.b_off + (n0 + 16 + lane).min(last_col) * p.b_sn,
        p.b_off + (n0 + 24 + lane).min(last_col) * p.b_sn,
    ];
    Some(SgTile { m0, n0, z, k_begin, k_end, ones_row, m_last, b_col })
}

/// `C (+)= A B (+ bias)` for CPU devices whose subgroups are 8 lanes of one SIMD
/// register (lavapipe): each subgroup owns a 32 × 32 tile of `C`, lane `l` its rows
/// `l, l + 8, l + 16, l + 24`. Per step through `k` a lane loads its 4 values of `A`
/// and one value of each of the tile's 4 groups of 8 columns of `B`, and the 32 values
/// of `B` reach every lane by broadcasts with constant lane numbers, which llvmpipe
/// compiles to a register shuffle. So 8 loads feed 128 multiply-adds per lane, where
/// `gemm_blocked` makes 16 loads for 64: on llvmpipe a load the compiler cannot prove
/// uniform is a loop over the 8 lanes and costs tens of multiply-adds. A workgroup is
/// one subgroup; the engine dispatches it only where the subgroup size is 8 (every lane
/// of a subgroup runs the same `k` loop, so all lanes are active at each broadcast).
#[cfg(feature = "subgroup-ballot")]
#[spirv(compute(threads(8)))]
pub fn gemm_subgroup(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lane: u32,
    #[spirv(push_constant)] p: &GemmParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] a: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] b: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] bias: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] c: &mut [f32],
) {
    let Some(SgTile { m0, n0, z, k_begin, k_end, ones_row, m_last, b_col }) = sg_tile(p, group, groups, lane, GEMM_SG_ROWS, GEMM_SG_COLS) else {
        return;
    };
    let rows = [m0 + lane, m0 + lane + 8, m0 + lane + 16, m0 + lane + 24];
    let a_row = [
        p.a_off + rows[0].min(m_last) * p.a_sm,
        p.a_off + rows[1].min(m_last) * p.a_sm,
        p.a_off + rows[2].min(m_last) * p.a_sm,
        p.a_off + rows[3].min(m_last) * p.a_sm,
    ];
    let ones = [rows[0] == ones_row, rows[1] == ones_row, rows[2] == ones_row, rows[3] == ones_row];
    let mut acc = [[0.0f32; GEMM_SG_COLS as usize]; 4];
    let mut k = k_begin;
    while k < k_end {
        let ka = k * p.a_sk;
        let a0 = a[(a_row[0] + ka) as usize];
        let a1 = a[(a_row[1] + ka) as usize];
        let a2 = a[(a_row[2] + ka) as usize];
        let a3 = a[(a_row[3] + ka) as usize];
        let av = [
            if ones[0] { 1.0 } else { a0 },
            if ones[1] { 1.0 } else { a1 },
            if ones[2] { 1.0 } else { a2 },
            if ones[3] { 1.0 } else { a3 },
        ];
        let kb = k * p.b_sk;
        let bv0 = b[(b_col[0] + kb) as usize];
        let bv1 = b[(b_col[1] + kb) as usize];
        let bv2 = b[(b_col[2] + kb) as usize];
        let bv3 = b[(b_col[3] + kb) as usize];
        sg_group!(acc, av, bv0, 0; 0, 1, 2, 3);
        sg_group!(acc, av, bv1, 1; 0, 1, 2, 3);
        sg_group!(acc, av, bv2, 2; 0, 1, 2, 3);
        sg_group!(acc, av, bv3, 3; 0, 1, 2, 3);
        k += 1;
    }
    store_tile_row(p, c, bias, acc[0], rows[0], n0, z);
    store_tile_row(p, c, bias, acc[1], rows[1], n0, z);
    store_tile_row(p, c, bias, acc[2], rows[2], n0, z);
    store_tile_row(p, c, bias, acc[3], rows[3], n0, z);
}

/// `C (+)= A B (+ bias)` for CPU devices with subgroups of 8 (lavapipe), reading `A`
/// and `B` as uniform texel buffers (`crate::texel`): each subgroup owns a 64 × 32
/// tile of `C`, lane `l` its rows `l + 8 i` (i < 8); per step through `k` a lane
/// fetches its 8 values of `A` and one value of each of the tile's 4 groups of 8
/// columns of `B`, and the 32 values of `B` reach every lane by broadcasts, as in
/// [`gemm_subgroup`], whose sums (in the same order of `k`) these are. What it costs
/// on llvmpipe 22.3 (its machine code read at the hot addresses): a fetch is a call
/// with one `vpgatherdd`, where a storage-buffer load is a loop over the lanes; a
/// broadcast is a loop over the 8 lanes finding the first active one (about as dear
/// as a fetch); a multiply-add, a masked store of the accumulator. So 8 rows per lane
/// (twice `gemm_subgroup`'s) halve the broadcasts and fetches per multiply-add. Rows
/// past `m` and columns past `n` read clamped indices and are never stored.
#[cfg(feature = "subgroup-ballot")]
#[spirv(compute(threads(8)))]
pub fn gemm_texel(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lane: u32,
    #[spirv(push_constant)] p: &GemmParams,
    #[spirv(descriptor_set = 0, binding = 0)] a: &crate::texel::TexelBuffer,
    #[spirv(descriptor_set = 0, binding = 1)] b: &crate::texel::TexelBuffer,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] bias: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] c: &mut [f32],
) {
    use crate::texel::fetch;
    let Some(SgTile { m0, n0, z, k_begin, k_end, ones_row, m_last, b_col }) = sg_tile(p, group, groups, lane, GEMM_TX_ROWS, GEMM_SG_COLS) else {
        return;
    };
    let rows = [m0 + lane, m0 + lane + 8, m0 + lane + 16, m0 + lane + 24, m0 + lane + 32, m0 + lane + 40, m0 + lane + 48, m0 + lane + 56];
    let a_row = [
        p.a_off + rows[0].min(m_last) * p.a_sm,
        p.a_off + rows[1].min(m_last) * p.a_sm,
        p.a_off + rows[2].min(m_last) * p.a_sm,
        p.a_off + rows[3].min(m_last) * p.a_sm,
        p.a_off + rows[4].min(m_last) * p.a_sm,
        p.a_off + rows[5].min(m_last) * p.a_sm,
        p.a_off + rows[6].min(m_last) * p.a_sm,
        p.a_off + rows[7].min(m_last) * p.a_sm,
    ];
    let mut acc = [[0.0f32; GEMM_SG_COLS as usize]; 8];
    let mut k = k_begin;
    while k < k_end {
        let ka = k * p.a_sk;
        // The ones row (the bias column of a weight gradient) is not stored in `A`.
        let av = [
            if rows[0] == ones_row { 1.0 } else { fetch(a, a_row[0] + ka) },
            if rows[1] == ones_row { 1.0 } else { fetch(a, a_row[1] + ka) },
            if rows[2] == ones_row { 1.0 } else { fetch(a, a_row[2] + ka) },
            if rows[3] == ones_row { 1.0 } else { fetch(a, a_row[3] + ka) },
            if rows[4] == ones_row { 1.0 } else { fetch(a, a_row[4] + ka) },
            if rows[5] == ones_row { 1.0 } else { fetch(a, a_row[5] + ka) },
            if rows[6] == ones_row { 1.0 } else { fetch(a, a_row[6] + ka) },
            if rows[7] == ones_row { 1.0 } else { fetch(a, a_row[7] + ka) },
        ];
        let kb = k * p.b_sk;
        let bv0 = fetch(b, b_col[0] + kb);
        let bv1 = fetch(b, b_col[1] + kb);
        let bv2 = fetch(b, b_col[2] + kb);
        let bv3 = fetch(b, b_col[3] + kb);
        sg_group!(acc, av, bv0, 0; 0, 1, 2, 3, 4, 5, 6, 7);
        sg_group!(acc, av, bv1, 1; 0, 1, 2, 3, 4, 5, 6, 7);
        sg_group!(acc, av, bv2, 2; 0, 1, 2, 3, 4, 5, 6, 7);
        sg_group!(acc, av, bv3, 3; 0, 1, 2, 3, 4, 5, 6, 7);
        k += 1;
    }
    store_tile_row(p, c, bias, acc[0], rows[0], n0, z);
    store_tile_row(p, c, bias, acc[1], rows[1], n0, z);
    store_tile_row(p, c, bias, acc[2], rows[2], n0, z);
    store_tile_row(p, c, bias, acc[3], rows[3], n0, z);
    store_tile_row(p, c, bias, acc[4], rows[4], n0, z);
    store_tile_row(p, c, bias, acc[5], rows[5], n0, z);
    store_tile_row(p, c, bias, acc[6], rows[6], n0, z);
    store_tile_row(p, c, bias, acc[7], rows[7], n0, z);
}

/// `acc[r][c] += av[r] * B[c]` for a lane's 8 rows and the tile's 32 columns, `B`'s row
/// of 32 being the 8 four-float texels from `t` (the same address in every lane).
#[cfg(feature = "subgroup-ballot")]
macro_rules! rows8_times_b_row {
    ($acc:ident, $av:ident, $b:ident, $t:expr) => {{
        let t = $t;
        macro_rules! quad {
            ($q:literal) => {{
                let bq = crate::texel::fetch4($b, t + $q);
                let bs = [bq.x, bq.y, bq.z, bq.w];
                macro_rules! col {
                    ($j:literal) => {{
                        let bj = bs[$j];
                        $acc[0][4 * $q + $j] += $av[0] * bj;
                        $acc[1][4 * $q + $j] += $av[1] * bj;
                        $acc[2][4 * $q + $j] += $av[2] * bj;
                        $acc[3][4 * $q + $j] += $av[3] * bj;
                        $acc[4][4 * $q + $j] += $av[4] * bj;
                        $acc[5][4 * $q + $j] += $av[5] * bj;
                        $acc[6][4 * $q + $j] += $av[6] * bj;
                        $acc[7][4 * $q + $j] += $av[7] * bj;
                    }};
                }
                col!(0);
                col!(1);
                col!(2);
                col!(3);
            }};
        }
        quad!(0);
        quad!(1);
        quad!(2);
        quad!(3);
        quad!(4);
        quad!(5);
        quad!(6);
        quad!(7);
    }};
}

/// Stores an 8-row tile a float at a time.
#[cfg(feature = "subgroup-ballot")]
macro_rules! rows8_store_floats {
    ($p:ident, $c:ident, $bias:ident, $acc:ident, $rows:ident, $n0:ident, $z:ident) => {{
        macro_rules! one {
            ($r:literal) => {
                store_tile_row($p, $c, $bias, $acc[$r], $rows[$r], $n0, $z);
            };
        }
        one!(0); one!(1); one!(2); one!(3); one!(4); one!(5); one!(6); one!(7);
    }};
}

/// Stores an 8-row tile 4 floats at a time.
#[cfg(feature = "subgroup-ballot")]
macro_rules! rows8_store_quads {
    ($p:ident, $c:ident, $bias:ident, $acc:ident, $rows:ident, $n0:ident, $z:ident) => {{
        let bias4 = tile_bias4::<8>($p, $bias, $n0);
        macro_rules! one {
            ($r:literal) => {
                store_tile_row4($p, $c, &bias4, $acc[$r], $rows[$r], $n0, $z);
            };
        }
        one!(0); one!(1); one!(2); one!(3); one!(4); one!(5); one!(6); one!(7);
    }};
}

/// [`gemm_texel`] with `B` read 4 columns a fetch through a 4-float texel view, the
/// same address in every lane (no broadcasts): needs `b_sn == 1` and `b_off`, `b_sk`
/// multiples of 4. Two epilogues: `gemm_texel_b4` stores floats, `gemm_texel_b4c4` 4
/// at a time (see [`store_tile_row4`]; the input gradient of a narrow head, whose `k`
/// of 1 to 6 leaves the stores most of the work).
#[cfg(feature = "subgroup-ballot")]
macro_rules! gemm_texel_b4_entry {
    ($name:ident, $c_ty:ty, ($($bias_attr:tt)*), $bias_ty:ty, $store:ident, $doc:literal) => {
        #[doc = $doc]
        #[cfg(feature = "subgroup-ballot")]
        #[spirv(compute(threads(8)))]
        pub fn $name(
            #[spirv(workgroup_id)] group: UVec3,
            #[spirv(num_workgroups)] groups: UVec3,
            #[spirv(local_invocation_index)] lane: u32,
            #[spirv(push_constant)] p: &GemmParams,
            #[spirv(descriptor_set = 0, binding = 0)] a: &crate::texel::TexelBuffer,
            #[spirv(descriptor_set = 0, binding = 1)] b: &crate::texel::TexelBuffer4,
            #[spirv($($bias_attr)*)] bias: $bias_ty,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] c: &mut [$c_ty],
        ) {
            use crate::texel::fetch;
            let Some(SgTile { m0, n0, z, k_begin, k_end, ones_row, m_last, .. }) = sg_tile(p, group, groups, lane, GEMM_TX_ROWS, GEMM_SG_COLS) else {
                return;
            };
            let rows = [m0 + lane, m0 + lane + 8, m0 + lane + 16, m0 + lane + 24, m0 + lane + 32, m0 + lane + 40, m0 + lane + 48, m0 + lane + 56];
            let a_row = [
                p.a_off + rows[0].min(m_last) * p.a_sm,
                p.a_off + rows[1].min(m_last) * p.a_sm,
                p.a_off + rows[2].min(m_last) * p.a_sm,
                p.a_off + rows[3].min(m_last) * p.a_sm,
                p.a_off + rows[4].min(m_last) * p.a_sm,
                p.a_off + rows[5].min(m_last) * p.a_sm,
                p.a_off + rows[6].min(m_last) * p.a_sm,
                p.a_off + rows[7].min(m_last) * p.a_sm,
            ];
            let mut acc = [[0.0f32; GEMM_SG_COLS as usize]; 8];
            let b_first = (p.b_off + n0) / 4;
            let b_step = p.b_sk / 4;
            let mut k = k_begin;
            while k < k_end {
                let ka = k * p.a_sk;
                let av = [
                    if rows[0] == ones_row { 1.0 } else { fetch(a, a_row[0] + ka) },
                    if rows[1] == ones_row { 1.0 } else { fetch(a, a_row[1] + ka) },
                    if rows[2] == ones_row { 1.0 } else { fetch(a, a_row[2] + ka) },
                    if rows[3] == ones_row { 1.0 } else { fetch(a, a_row[3] + ka) },
                    if rows[4] == ones_row { 1.0 } else { fetch(a, a_row[4] + ka) },
                    if rows[5] == ones_row { 1.0 } else { fetch(a, a_row[5] + ka) },
                    if rows[6] == ones_row { 1.0 } else { fetch(a, a_row[6] + ka) },
                    if rows[7] == ones_row { 1.0 } else { fetch(a, a_row[7] + ka) },
                ];
                rows8_times_b_row!(acc, av, b, b_first + k * b_step);
                k += 1;
            }
            $store!(p, c, bias, acc, rows, n0, z);
        }
    };
}

#[cfg(feature = "subgroup-ballot")]
gemm_texel_b4_entry!(gemm_texel_b4, f32, (storage_buffer, descriptor_set = 0, binding = 2), &[f32], rows8_store_floats, "The texel GEMM with `B` 4 floats a fetch (see the macro), storing a float at a time.");
#[cfg(feature = "subgroup-ballot")]
gemm_texel_b4_entry!(gemm_texel_b4c4, Vec4, (descriptor_set = 0, binding = 2), &crate::texel::TexelBuffer4, rows8_store_quads, "The texel GEMM with `B` 4 floats a fetch (see the macro), storing 4 floats at a time.");

/// `C (+)= A B` for a narrow `C` (`n` up to `W`, 4 or 8: the weight gradient `Xᵀ dY`
/// of the 1- to 6-wide heads, `k` the batch rows) with `k` across the lanes: each
/// subgroup owns 32 rows of `C` (`A` contiguous along `m`, fetched as 8 four-float
/// texels per step) × `W` columns, lane `l` sums the steps `k ≡ l (mod 8)` of its
/// chunk, and the 8 partial sums meet in one subgroup reduce per value of `C` at the
/// end; lane 0 stores. The tiles that own the columns (`gemm_texel_m4n4c4`) would run
/// 32 columns for 3 and fetch every step's `B` row at one address in all lanes; here
/// each lane fetches its own step's `W` values. The ones row (the bias column) reads
/// 1. Needs `a_sm == 1` and `a_off`, `a_sk` multiples of 4. Sums in a different order
/// from the other GEMMs (strided by lane, then the reduce's order).
#[cfg(feature = "subgroup-ballot")]
macro_rules! gemm_texel_klanes_entry {
    ($name:ident, $w:literal, [$($j:literal)*], $doc:literal) => {
        #[doc = $doc]
        #[cfg(feature = "subgroup-ballot")]
        #[spirv(compute(threads(8)))]
        pub fn $name(
            #[spirv(workgroup_id)] group: UVec3,
            #[spirv(num_workgroups)] groups: UVec3,
            #[spirv(local_invocation_index)] lane: u32,
            #[spirv(push_constant)] p: &GemmParams,
            #[spirv(descriptor_set = 0, binding = 0)] a: &crate::texel::TexelBuffer4,
            #[spirv(descriptor_set = 0, binding = 1)] b: &crate::texel::TexelBuffer,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] bias: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] c: &mut [f32],
        ) {
            use crate::texel::{fetch, fetch4};
            let Some(SgTile { m0, n0, z, k_begin, k_end, ones_row, .. }) = sg_tile(p, group, groups, lane, GEMM_KL_ROWS, $w) else {
                return;
            };
            let last_col = p.n - 1;
            let mut acc = [[0.0f32; $w]; 32];
            let mut k = k_begin + lane;
            while k < k_end {
                let t = (p.a_off + k * p.a_sk + m0) / 4;
                let x4 = [fetch4(a, t), fetch4(a, t + 1), fetch4(a, t + 2), fetch4(a, t + 3), fetch4(a, t + 4), fetch4(a, t + 5), fetch4(a, t + 6), fetch4(a, t + 7)];
                let g = [$(fetch(b, p.b_off + k * p.b_sk + (n0 + $j).min(last_col) * p.b_sn)),*];
                macro_rules! row {
                    ($r:literal, $q:literal, $f:ident) => {{
                        // Rows past `A` read what lies there (never stored); the ones row reads 1.
                        let x = if m0 + $r == ones_row { 1.0 } else { x4[$q].$f };
                        $(acc[$r][$j] += x * g[$j];)*
                    }};
                }
                row!(0, 0, x); row!(1, 0, y); row!(2, 0, z); row!(3, 0, w);
                row!(4, 1, x); row!(5, 1, y); row!(6, 1, z); row!(7, 1, w);
                row!(8, 2, x); row!(9, 2, y); row!(10, 2, z); row!(11, 2, w);
                row!(12, 3, x); row!(13, 3, y); row!(14, 3, z); row!(15, 3, w);
                row!(16, 4, x); row!(17, 4, y); row!(18, 4, z); row!(19, 4, w);
                row!(20, 5, x); row!(21, 5, y); row!(22, 5, z); row!(23, 5, w);
                row!(24, 6, x); row!(25, 6, y); row!(26, 6, z); row!(27, 6, w);
                row!(28, 7, x); row!(29, 7, y); row!(30, 7, z); row!(31, 7, w);
                k += 8;
            }
            // Every lane is back here (the loop above is the only divergence), as the
            // reduces need.
            macro_rules! reduce {
                ($r:literal) => {{
                    $(acc[$r][$j] = crate::subgroup::sum8(acc[$r][$j]);)*
                }};
            }
            reduce!(0); reduce!(1); reduce!(2); reduce!(3); reduce!(4); reduce!(5); reduce!(6); reduce!(7);
            reduce!(8); reduce!(9); reduce!(10); reduce!(11); reduce!(12); reduce!(13); reduce!(14); reduce!(15);
            reduce!(16); reduce!(17); reduce!(18); reduce!(19); reduce!(20); reduce!(21); reduce!(22); reduce!(23);
            reduce!(24); reduce!(25); reduce!(26); reduce!(27); reduce!(28); reduce!(29); reduce!(30); reduce!(31);
            if lane == 0 {
                macro_rules! one {
                    ($r:literal) => {
                        store_tile_row(p, c, bias, acc[$r], m0 + $r, n0, z);
                    };
                }
                one!(0); one!(1); one!(2); one!(3); one!(4); one!(5); one!(6); one!(7);
                one!(8); one!(9); one!(10); one!(11); one!(12); one!(13); one!(14); one!(15);
                one!(16); one!(17); one!(18); one!(19); one!(20); one!(21); one!(22); one!(23);
                one!(24); one!(25); one!(26); one!(27); one!(28); one!(29); one!(30); one!(31);
            }
        }
    };
}

#[cfg(feature = "subgroup-ballot")]
gemm_texel_klanes_entry!(gemm_texel_klanes_w4, 4, [0 1 2 3], "The narrow GEMM with `k` across the lanes (see the macro), up to 4 columns a tile.");
#[cfg(feature = "subgroup-ballot")]
gemm_texel_klanes_entry!(gemm_texel_klanes_w8, 8, [0 1 2 3 4 5 6 7], "The narrow GEMM with `k` across the lanes (see the macro), up to 8 columns a tile.");

/// Writes one lane's row of a tile 4 columns a store (`C` viewed as `vec4`s): needs
/// `n`, `ldc`, `c_off`, `c_split` and, with a bias, `bias_off` multiples of 4, so each
/// group of 4 columns is all inside `C` or all past its last column. On llvmpipe each
/// store is a loop over the lanes, so 8 stores a row where [`store_tile_row`] makes 32
/// (and 32 loads of the bias). `W` columns, `Q = W / 4` texels.
#[cfg(feature = "subgroup-ballot")]
#[inline]
fn store_tile_row4<const W: usize, const Q: usize>(p: &GemmParams, c: &mut [Vec4], bias: &[Vec4; Q], vals: [f32; W], row: u32, n0: u32, z: u32) {
    if row >= p.m {
        return;
    }
    let mut q = 0;
    while q < Q {
        if n0 + 4 * (q as u32) < p.n {
            let at = ((p.c_off + z * p.c_split + row * p.ldc + n0) / 4) as usize + q;
            let j = 4 * q;
            let mut v = Vec4::new(vals[j], vals[j + 1], vals[j + 2], vals[j + 3]);
            if p.flags & GEMM_BIAS != 0 {
                v += bias[q];
            }
            if p.flags & GEMM_ACCUMULATE != 0 {
                v += c[at];
            }
            c[at] = v;
        }
        q += 1;
    }
}

/// The tile's `Q` texels of bias, 4 columns a fetch (zeros without one).
#[cfg(feature = "subgroup-ballot")]
#[inline]
fn tile_bias4<const Q: usize>(p: &GemmParams, bias: &crate::texel::TexelBuffer4, n0: u32) -> [Vec4; Q] {
    use crate::texel::fetch4;
    let mut out = [Vec4::ZERO; Q];
    if p.flags & GEMM_BIAS != 0 {
        let t = (p.bias_off + n0) / 4;
        let mut q = 0;
        while q < Q {
            out[q] = fetch4(bias, t + q as u32);
            q += 1;
        }
    }
    out
}

/// One lane's row of a forward tile (`gemm_texel_k4*` without `c4`), a float at a
/// time, adding the tile's bias fetched once per column (`bias`, zeros without
/// `GEMM_BIAS`). Never adds to `C`: the engine records these kernels only without
/// `GEMM_ACCUMULATE`, which spares every column a masked-off storage-buffer read (a
/// loop over the lanes of its own on llvmpipe).
#[cfg(feature = "subgroup-ballot")]
#[inline]
fn store_row_floats<const W: usize>(p: &GemmParams, c: &mut [f32], bias: &[f32; W], vals: [f32; W], row: u32, n0: u32, z: u32) {
    if row >= p.m {
        return;
    }
    let base = (p.c_off + z * p.c_split + row * p.ldc + n0) as usize;
    let mut j = 0;
    while j < W {
        if n0 + (j as u32) < p.n {
            c[base + j] = vals[j] + bias[j];
        }
        j += 1;
    }
}

/// `gemm_texel_k4`'s rows and stores: per row of the lane, `$store!(acc, row)`.
#[cfg(feature = "subgroup-ballot")]
macro_rules! for_k4_rows {
    ($m:ident $(, $arg:tt)*) => {
        $m!(0 $(, $arg)*);
        $m!(1 $(, $arg)*);
        $m!(2 $(, $arg)*);
        $m!(3 $(, $arg)*);
        $m!(4 $(, $arg)*);
        $m!(5 $(, $arg)*);
        $m!(6 $(, $arg)*);
        $m!(7 $(, $arg)*);
        $m!(8 $(, $arg)*);
        $m!(9 $(, $arg)*);
        $m!(10 $(, $arg)*);
        $m!(11 $(, $arg)*);
        $m!(12 $(, $arg)*);
        $m!(13 $(, $arg)*);
        $m!(14 $(, $arg)*);
        $m!(15 $(, $arg)*);
    };
}

/// [`gemm_texel`] with both operands contiguous along `k` (`a_sk == b_sk == 1`: the
/// forward `x Wᵀ`), each read 4 steps of `k` a fetch through 4-float texel views, in
/// tiles of 128 rows (16 a lane) × `W` columns: per 4 steps a lane fetches one texel
/// per row of `A` (16) and every lane the same texel per column of `B` (`W`, no
/// broadcasts), where [`gemm_texel`] makes 48 fetches and 128 broadcasts for half the
/// rows. Needs `a_off`, `a_sm`, `b_off`, `b_sn`, `k_chunk` and `k` multiples of 4, no
/// ones row and no `GEMM_ACCUMULATE`. Sums in the same order as [`gemm_texel`].
///
/// Widths 32, 16, 8 and 4: llvmpipe runs every column of a tile whether it exists or
/// not (a branch on a uniform value is a mask there, not a jump), so the engine covers
/// `n` with 32-wide tiles and the rest with the narrower ones (a head of 3 columns
/// runs 4, not 32). Two epilogues: `_c4` stores 4 floats at a time and reads the bias
/// as 4-float texels (see [`store_tile_row4`]); the other stores floats and fetches
/// the tile's bias once per column (see [`store_row_floats`]).
#[cfg(feature = "subgroup-ballot")]
macro_rules! gemm_texel_k4_entry {
    ($name:ident, $w:literal, [$($j:literal)*], $c_ty:ty, ($($bias_attr:tt)*), $bias_ty:ty, $store:ident, $doc:literal) => {
        #[doc = $doc]
        #[cfg(feature = "subgroup-ballot")]
        #[spirv(compute(threads(8)))]
        pub fn $name(
            #[spirv(workgroup_id)] group: UVec3,
            #[spirv(num_workgroups)] groups: UVec3,
            #[spirv(local_invocation_index)] lane: u32,
            #[spirv(push_constant)] p: &GemmParams,
            #[spirv(descriptor_set = 0, binding = 0)] a: &crate::texel::TexelBuffer4,
            #[spirv(descriptor_set = 0, binding = 1)] b: &crate::texel::TexelBuffer4,
            #[spirv($($bias_attr)*)] bias: $bias_ty,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] c: &mut [$c_ty],
        ) {
            use crate::texel::fetch4;
            let Some(SgTile { m0, n0, z, k_begin, k_end, m_last, .. }) = sg_tile(p, group, groups, lane, GEMM_K4_ROWS, $w) else {
                return;
            };
            let rows = [m0 + lane + 0, m0 + lane + 8, m0 + lane + 16, m0 + lane + 24, m0 + lane + 32, m0 + lane + 40, m0 + lane + 48, m0 + lane + 56, m0 + lane + 64, m0 + lane + 72, m0 + lane + 80, m0 + lane + 88, m0 + lane + 96, m0 + lane + 104, m0 + lane + 112, m0 + lane + 120];
            let a_row = [(p.a_off + rows[0].min(m_last) * p.a_sm) / 4, (p.a_off + rows[1].min(m_last) * p.a_sm) / 4, (p.a_off + rows[2].min(m_last) * p.a_sm) / 4, (p.a_off + rows[3].min(m_last) * p.a_sm) / 4, (p.a_off + rows[4].min(m_last) * p.a_sm) / 4, (p.a_off + rows[5].min(m_last) * p.a_sm) / 4, (p.a_off + rows[6].min(m_last) * p.a_sm) / 4, (p.a_off + rows[7].min(m_last) * p.a_sm) / 4, (p.a_off + rows[8].min(m_last) * p.a_sm) / 4, (p.a_off + rows[9].min(m_last) * p.a_sm) / 4, (p.a_off + rows[10].min(m_last) * p.a_sm) / 4, (p.a_off + rows[11].min(m_last) * p.a_sm) / 4, (p.a_off + rows[12].min(m_last) * p.a_sm) / 4, (p.a_off + rows[13].min(m_last) * p.a_sm) / 4, (p.a_off + rows[14].min(m_last) * p.a_sm) / 4, (p.a_off + rows[15].min(m_last) * p.a_sm) / 4];
            let last_col = p.n - 1;
            let mut acc = [[0.0f32; $w]; 16];
            let mut k = k_begin;
            // 8 steps of `k` a pass (two texels per row and column), the second 4
            // zeroed where `k` ends 4 steps in: every value written in a loop gets a
            // masked store on llvmpipe, so a pass of 8 halves those per multiply-add.
            while k < k_end {
                let kt = k / 4;
                let second = k + 4 < k_end;
                let av = [fetch4(a, a_row[0] + kt), fetch4(a, a_row[1] + kt), fetch4(a, a_row[2] + kt), fetch4(a, a_row[3] + kt), fetch4(a, a_row[4] + kt), fetch4(a, a_row[5] + kt), fetch4(a, a_row[6] + kt), fetch4(a, a_row[7] + kt), fetch4(a, a_row[8] + kt), fetch4(a, a_row[9] + kt), fetch4(a, a_row[10] + kt), fetch4(a, a_row[11] + kt), fetch4(a, a_row[12] + kt), fetch4(a, a_row[13] + kt), fetch4(a, a_row[14] + kt), fetch4(a, a_row[15] + kt)];
                let kt2 = kt + 1;
                let av2 = [fetch4(a, a_row[0] + kt2), fetch4(a, a_row[1] + kt2), fetch4(a, a_row[2] + kt2), fetch4(a, a_row[3] + kt2), fetch4(a, a_row[4] + kt2), fetch4(a, a_row[5] + kt2), fetch4(a, a_row[6] + kt2), fetch4(a, a_row[7] + kt2), fetch4(a, a_row[8] + kt2), fetch4(a, a_row[9] + kt2), fetch4(a, a_row[10] + kt2), fetch4(a, a_row[11] + kt2), fetch4(a, a_row[12] + kt2), fetch4(a, a_row[13] + kt2), fetch4(a, a_row[14] + kt2), fetch4(a, a_row[15] + kt2)];
                macro_rules! col {
                    ($jj:literal) => {{
                        let b_at = (p.b_off + (n0 + $jj).min(last_col) * p.b_sn) / 4 + kt;
                        let bq = fetch4(b, b_at);
                        // Past `k_end` the second texels hold the next row (or zeros past
                        // the view): a zero `B` and `A` add exact zeros instead.
                        let bq2 = if second { fetch4(b, b_at + 1) } else { Vec4::ZERO };
                        macro_rules! row {
                            ($r:literal) => {{
                                let a2 = if second { av2[$r] } else { Vec4::ZERO };
                                let mut v = acc[$r][$jj];
                                v += av[$r].x * bq.x;
                                v += av[$r].y * bq.y;
                                v += av[$r].z * bq.z;
                                v += av[$r].w * bq.w;
                                v += a2.x * bq2.x;
                                v += a2.y * bq2.y;
                                v += a2.z * bq2.z;
                                v += a2.w * bq2.w;
                                acc[$r][$jj] = v;
                            }};
                        }
                        for_k4_rows!(row);
                    }};
                }
                $(col!($j);)*
                k += 8;
            }
            $store!(p, c, bias, acc, rows, n0, z, [$($j)*]);
        }
    };
}

/// Stores the tile a float at a time, with the tile's bias fetched once per column
/// (a storage-buffer read per row and column would be a loop over the lanes each).
#[cfg(feature = "subgroup-ballot")]
macro_rules! k4_store_floats {
    ($p:ident, $c:ident, $bias:ident, $acc:ident, $rows:ident, $n0:ident, $z:ident, [$($j:literal)*]) => {{
        let last_col = $p.n - 1;
        let with_bias = $p.flags & GEMM_BIAS != 0;
        let bias_row = [$({
            let v = crate::texel::fetch($bias, $p.bias_off + ($n0 + $j).min(last_col));
            if with_bias { v } else { 0.0 }
        }),*];
        macro_rules! one {
            ($r:literal) => {
                store_row_floats($p, $c, &bias_row, $acc[$r], $rows[$r], $n0, $z);
            };
        }
        for_k4_rows!(one);
    }};
}

/// Stores the tile 4 floats at a time.
#[cfg(feature = "subgroup-ballot")]
macro_rules! k4_store_quads {
    ($p:ident, $c:ident, $bias:ident, $acc:ident, $rows:ident, $n0:ident, $z:ident, [$($j:literal)*]) => {{
        let bias4 = tile_bias4::<{ [$($j),*].len() / 4 }>($p, $bias, $n0);
        macro_rules! one {
            ($r:literal) => {
                store_tile_row4($p, $c, &bias4, $acc[$r], $rows[$r], $n0, $z);
            };
        }
        for_k4_rows!(one);
    }};
}

// The forward GEMMs: widths 32, 16, 8 and 4, each with both epilogues.
#[cfg(feature = "subgroup-ballot")]
gemm_texel_k4_entry!(gemm_texel_k4, 32, [0 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16 17 18 19 20 21 22 23 24 25 26 27 28 29 30 31], f32, (descriptor_set = 0, binding = 2), &crate::texel::TexelBuffer, k4_store_floats, "A 4-float texel forward GEMM (see the macro), 32 columns a tile, storing a float at a time.");
#[cfg(feature = "subgroup-ballot")]
gemm_texel_k4_entry!(gemm_texel_k4c4, 32, [0 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16 17 18 19 20 21 22 23 24 25 26 27 28 29 30 31], Vec4, (descriptor_set = 0, binding = 2), &crate::texel::TexelBuffer4, k4_store_quads, "A 4-float texel forward GEMM (see the macro), 32 columns a tile, storing 4 floats at a time and reading the bias as 4-float texels.");
#[cfg(feature = "subgroup-ballot")]
gemm_texel_k4_entry!(gemm_texel_k4w16, 16, [0 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15], f32, (descriptor_set = 0, binding = 2), &crate::texel::TexelBuffer, k4_store_floats, "A 4-float texel forward GEMM (see the macro), 16 columns a tile, storing a float at a time.");
#[cfg(feature = "subgroup-ballot")]
gemm_texel_k4_entry!(gemm_texel_k4w16c4, 16, [0 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15], Vec4, (descriptor_set = 0, binding = 2), &crate::texel::TexelBuffer4, k4_store_quads, "A 4-float texel forward GEMM (see the macro), 16 columns a tile, storing 4 floats at a time and reading the bias as 4-float texels.");
#[cfg(feature = "subgroup-ballot")]
gemm_texel_k4_entry!(gemm_texel_k4w8, 8, [0 1 2 3 4 5 6 7], f32, (descriptor_set = 0, binding = 2), &crate::texel::TexelBuffer, k4_store_floats, "A 4-float texel forward GEMM (see the macro), 8 columns a tile, storing a float at a time.");
#[cfg(feature = "subgroup-ballot")]
gemm_texel_k4_entry!(gemm_texel_k4w8c4, 8, [0 1 2 3 4 5 6 7], Vec4, (descriptor_set = 0, binding = 2), &crate::texel::TexelBuffer4, k4_store_quads, "A 4-float texel forward GEMM (see the macro), 8 columns a tile, storing 4 floats at a time and reading the bias as 4-float texels.");
#[cfg(feature = "subgroup-ballot")]
gemm_texel_k4_entry!(gemm_texel_k4w4, 4, [0 1 2 3], f32, (descriptor_set = 0, binding = 2), &crate::texel::TexelBuffer, k4_store_floats, "A 4-float texel forward GEMM (see the macro), 4 columns a tile, storing a float at a time.");
#[cfg(feature = "subgroup-ballot")]
gemm_texel_k4_entry!(gemm_texel_k4w4c4, 4, [0 1 2 3], Vec4, (descriptor_set = 0, binding = 2), &crate::texel::TexelBuffer4, k4_store_quads, "A 4-float texel forward GEMM (see the macro), 4 columns a tile, storing 4 floats at a time and reading the bias as 4-float texels.");

/// [`gemm_texel`] with `A` contiguous along `k` and `B` along `n` (`a_sk == b_sn == 1`:
/// the input gradient `dY W`): per 4 steps of `k` a lane fetches one 4-float texel per
/// row of `A` (8) and, per step, every lane the same 8 texels of `B` (32 columns, no
/// broadcasts). Needs `a_off`, `a_sm`, `b_off`, `b_sk`, `k_chunk` and `k` multiples of 4
/// and no ones row. Sums in the same order as [`gemm_texel`].
#[cfg(feature = "subgroup-ballot")]
macro_rules! gemm_texel_k4n4_entry {
    ($name:ident, $c_ty:ty, ($($bias_attr:tt)*), $bias_ty:ty, $store:ident, $doc:literal) => {
#[doc = $doc]
#[spirv(compute(threads(8)))]
pub fn $name(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lane: u32,
    #[spirv(push_constant)] p: &GemmParams,
    #[spirv(descriptor_set = 0, binding = 0)] a: &crate::texel::TexelBuffer4,
    #[spirv(descriptor_set = 0, binding = 1)] b: &crate::texel::TexelBuffer4,
    #[spirv($($bias_attr)*)] bias: $bias_ty,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] c: &mut [$c_ty],
) {
    use crate::texel::fetch4;
    let Some(SgTile { m0, n0, z, k_begin, k_end, m_last, .. }) = sg_tile(p, group, groups, lane, GEMM_TX_ROWS, GEMM_SG_COLS) else {
        return;
    };
    let rows = [m0 + lane, m0 + lane + 8, m0 + lane + 16, m0 + lane + 24, m0 + lane + 32, m0 + lane + 40, m0 + lane + 48, m0 + lane + 56];
    let a_row = [
        (p.a_off + rows[0].min(m_last) * p.a_sm) / 4,
        (p.a_off + rows[1].min(m_last) * p.a_sm) / 4,
        (p.a_off + rows[2].min(m_last) * p.a_sm) / 4,
        (p.a_off + rows[3].min(m_last) * p.a_sm) / 4,
        (p.a_off + rows[4].min(m_last) * p.a_sm) / 4,
        (p.a_off + rows[5].min(m_last) * p.a_sm) / 4,
        (p.a_off + rows[6].min(m_last) * p.a_sm) / 4,
        (p.a_off + rows[7].min(m_last) * p.a_sm) / 4,
    ];
    let mut acc = [[0.0f32; GEMM_SG_COLS as usize]; 8];
    let b_first = (p.b_off + n0) / 4;
    let b_step = p.b_sk / 4;
    let mut k = k_begin;
    while k < k_end {
        let kt = k / 4;
        let av = [
            fetch4(a, a_row[0] + kt),
            fetch4(a, a_row[1] + kt),
            fetch4(a, a_row[2] + kt),
            fetch4(a, a_row[3] + kt),
            fetch4(a, a_row[4] + kt),
            fetch4(a, a_row[5] + kt),
            fetch4(a, a_row[6] + kt),
            fetch4(a, a_row[7] + kt),
        ];
        // Step `k + kk` of `k`, component `$kk` of each row's texel.
        // Step `k + kk` of `k`: component `kk` of each row's texel.
        macro_rules! step {
            ($kk:literal, $x:ident) => {{
                let ak = [av[0].$x, av[1].$x, av[2].$x, av[3].$x, av[4].$x, av[5].$x, av[6].$x, av[7].$x];
                rows8_times_b_row!(acc, ak, b, b_first + (k + $kk) * b_step);
            }};
        }
        step!(0, x);
        step!(1, y);
        step!(2, z);
        step!(3, w);
        k += 4;
    }
    $store!(p, c, bias, acc, rows, n0, z);
}
    };
}


#[cfg(feature = "subgroup-ballot")]
gemm_texel_k4n4_entry!(gemm_texel_k4n4, f32, (storage_buffer, descriptor_set = 0, binding = 2), &[f32], rows8_store_floats, "The 4-float texel input-gradient GEMM (see the macro), storing a float at a time.");
#[cfg(feature = "subgroup-ballot")]
gemm_texel_k4n4_entry!(gemm_texel_k4n4c4, Vec4, (descriptor_set = 0, binding = 2), &crate::texel::TexelBuffer4, rows8_store_quads, "The 4-float texel input-gradient GEMM (see the macro), storing 4 floats at a time (see [`store_tile_row4`]).");

/// [`gemm_texel`] with `A` contiguous along `m` and `B` along `n` (`a_sm == b_sn == 1`:
/// the weight gradient `Xᵀ dY`, whose `k` is the rows of the batch), storing 4 floats
/// at a time: lane `l` owns rows `m0 + 4 l + {0, 1, 2, 3}` and the same 32 further,
/// so per step of `k` it fetches its 8 values of `A` as two 4-float texels and every
/// lane the same 8 texels of `B` (32 columns), where [`gemm_texel_b4`] fetches 8 values
/// of `A` one at a time. The ones row (the bias column of the gradient) reads 1. Needs
/// `a_off`, `a_sk`, `b_off`, `b_sk` multiples of 4 and `C` as [`store_tile_row4`] does.
/// Sums in the same order as [`gemm_texel`].
#[cfg(feature = "subgroup-ballot")]
#[spirv(compute(threads(8)))]
pub fn gemm_texel_m4n4c4(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lane: u32,
    #[spirv(push_constant)] p: &GemmParams,
    #[spirv(descriptor_set = 0, binding = 0)] a: &crate::texel::TexelBuffer4,
    #[spirv(descriptor_set = 0, binding = 1)] b: &crate::texel::TexelBuffer4,
    #[spirv(descriptor_set = 0, binding = 2)] bias: &crate::texel::TexelBuffer4,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] c: &mut [Vec4],
) {
    use crate::texel::fetch4;
    let Some(SgTile { m0, n0, z, k_begin, k_end, ones_row, .. }) = sg_tile(p, group, groups, lane, GEMM_TX_ROWS, GEMM_SG_COLS) else {
        return;
    };
    let r0 = m0 + 4 * lane;
    let rows = [r0, r0 + 1, r0 + 2, r0 + 3, r0 + 32, r0 + 33, r0 + 34, r0 + 35];
    let ones = [
        rows[0] == ones_row,
        rows[1] == ones_row,
        rows[2] == ones_row,
        rows[3] == ones_row,
        rows[4] == ones_row,
        rows[5] == ones_row,
        rows[6] == ones_row,
        rows[7] == ones_row,
    ];
    // Rows past the last of `A` read whatever lies there (or zeros past the view) and
    // are never stored.
    let a_first = [(p.a_off + r0) / 4, (p.a_off + r0 + 32) / 4];
    let a_step = p.a_sk / 4;
    let b_first = (p.b_off + n0) / 4;
    let b_step = p.b_sk / 4;
    let mut acc = [[0.0f32; GEMM_SG_COLS as usize]; 8];
    let mut k = k_begin;
    while k < k_end {
        let lo = fetch4(a, a_first[0] + k * a_step);
        let hi = fetch4(a, a_first[1] + k * a_step);
        let av = [
            if ones[0] { 1.0 } else { lo.x },
            if ones[1] { 1.0 } else { lo.y },
            if ones[2] { 1.0 } else { lo.z },
            if ones[3] { 1.0 } else { lo.w },
            if ones[4] { 1.0 } else { hi.x },
            if ones[5] { 1.0 } else { hi.y },
            if ones[6] { 1.0 } else { hi.z },
            if ones[7] { 1.0 } else { hi.w },
        ];
        rows8_times_b_row!(acc, av, b, b_first + k * b_step);
        k += 1;
    }
    rows8_store_quads!(p, c, bias, acc, rows, n0, z);
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
fn act_fwd4_with<A: Activation4>(id: UVec3, groups: UVec3, p: &ActParams, pre: &[Vec4], post: &mut [Vec4]) {
    let flat = crate::flat_index(id, groups);
    if flat >= (p.rows * p.width).div_ceil(4) {
        return;
    }
    let i = flat as usize;
    let x = pre[i];
    post[i] = Vec4::new(A::fwd(p, x.x), A::fwd(p, x.y), A::fwd(p, x.z), A::fwd(p, x.w));
}

/// [`act_bwd`] 4 elements an invocation (as [`act_fwd4_with`]).
#[inline]
fn act_bwd4_with<A: Activation4>(id: UVec3, groups: UVec3, p: &ActParams, pre: &[Vec4], post: &[Vec4], grad_post: &[Vec4], grad_pre: &mut [Vec4]) {
    let flat = crate::flat_index(id, groups);
    if flat >= (p.rows * p.width).div_ceil(4) {
        return;
    }
    let i = flat as usize;
    let (x, y, g) = (pre[i], post[i], grad_post[i]);
    grad_pre[i] = Vec4::new(A::bwd(p, x.x, y.x, g.x), A::bwd(p, x.y, y.y, g.y), A::bwd(p, x.z, y.z, g.z), A::bwd(p, x.w, y.w, g.w));
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
