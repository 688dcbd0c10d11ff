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
#[cfg(feature = "subgroup-ballot")]
use crate::texel::{fetch, fetch4, TexelBuffer, TexelBuffer4};
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
#[inline]
#[allow(clippy::too_many_arguments)]
fn block_step(acc: &mut [f32; 64], a: &[f32], b: &[f32], p: &GemmParams, m0: u32, n0: u32, k: u32, ones_row: u32, m_last: u32) {
    let mut av = [0.0f32; 8];
    each_index!(8, r => {
        let m = m0 + r as u32;
        av[r] = if m == ones_row { 1.0 } else { a[(p.a_off + m.min(m_last) * p.a_sm + k * p.a_sk) as usize] };
    });
    let mut bv = [0.0f32; 8];
    each_index!(8, j => {
        bv[j] = b[(p.b_off + k * p.b_sk + (n0 + j as u32).min(p.n - 1) * p.b_sn) as usize];
    });
    each_index!(8, r => {
        each_index!(8, j => {
            acc[8 * r + j] += av[r] * bv[j];
        });
    });
}

/// Stores the invocation's 8 × 8 block (bias added or accumulated as flagged), each
/// value where it lies inside `C`.
#[inline]
fn block_store(acc: &[f32; 64], p: &GemmParams, c: &mut [f32], bias: &[f32], m0: u32, n0: u32, z: u32) {
    each_index!(8, r => {
        each_index!(8, j => {
            if m0 + (r as u32) < p.m && n0 + (j as u32) < p.n {
                let at = (p.c_off + z * p.c_split + (m0 + r as u32) * p.ldc + n0 + j as u32) as usize;
                let mut v = acc[8 * r + j];
                if p.flags & GEMM_BIAS != 0 {
                    v += bias[(p.bias_off + n0 + j as u32) as usize];
                }
                if p.flags & GEMM_ACCUMULATE != 0 {
                    v += c[at];
                }
                c[at] = v;
            }
        });
    });
}

/// `C (+)= A B (+ bias)` register-blocked: invocation (x, y) of an 8 × 8 workgroup owns
/// rows `m0..m0 + 8` and columns `n0..n0 + 8` of one split of `k` and keeps the 64 sums
/// in registers. Every buffer or workgroup-memory load is a loop over the SIMD lanes
/// on llvmpipe (about as costly as 30 multiply-adds), so this kernel makes 16 loads per
/// 64 multiply-adds, where `nn::gemm_tiled` makes 33 per 32 and its staging through
/// workgroup memory only adds loads (measured: `engine-bench ops`). The kernel of CPU
/// devices without subgroups of 8.
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
        block_step(&mut acc, a, b, p, m0, n0, k, ones_row, m_last);
        k += 1;
    }
    block_store(&acc, p, c, bias, m0, n0, z);
}

/// Where a subgroup GEMM's workgroup works: its tile of `C` (rows from `m0`, columns
/// from `n0`), its split `z` of `k` (`k_begin..k_end`), the ones row (`u32::MAX` when
/// none), the last row of `A` that exists, and the offsets in `B` of the lane's 4
/// columns (`n0 + lane + 8 g`, clamped to the last; for the broadcasting kernels).
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
/// together, so no broadcast or reduce ever reads an inactive lane). Workgroups come in
/// rows of at most 65,535 (2M rows of 1,024 columns are 2M tiles).
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

/// The `R` rows of a tile lane `lane` owns: `m0 + lane + 8 r`.
#[cfg(feature = "subgroup-ballot")]
#[inline]
fn lane_rows<const R: usize>(m0: u32, lane: u32) -> [u32; R] {
    let mut rows = [0u32; R];
    each_index!(R, r => {
        rows[r] = m0 + lane + 8 * r as u32;
    });
    rows
}

/// Where each of `rows` starts in `A`, in floats (a row past the last that exists,
/// `m_last`, reads that one).
#[cfg(feature = "subgroup-ballot")]
#[inline]
fn a_row_starts<const R: usize>(p: &GemmParams, rows: &[u32; R], m_last: u32) -> [u32; R] {
    let mut at = [0u32; R];
    each_index!(R, r => {
        at[r] = p.a_off + rows[r].min(m_last) * p.a_sm;
    });
    at
}

/// The same in 4-float texels (`A` along `k` in whole texels).
#[cfg(feature = "subgroup-ballot")]
#[inline]
fn a_row_texels<const R: usize>(p: &GemmParams, rows: &[u32; R], m_last: u32) -> [u32; R] {
    let mut at = [0u32; R];
    each_index!(R, r => {
        at[r] = (p.a_off + rows[r].min(m_last) * p.a_sm) / 4;
    });
    at
}

/// Step `k` of a lane's `R` rows of `A` through a 1-float texel view (`ka = k a_sk`):
/// the ones row (the bias column of a weight gradient, not stored in `A`) reads 1.
#[cfg(feature = "subgroup-ballot")]
#[inline]
fn fetch_rows<const R: usize>(a: &TexelBuffer, rows: &[u32; R], a_row: &[u32; R], ones_row: u32, ka: u32) -> [f32; R] {
    let mut av = [0.0f32; R];
    each_index!(R, r => {
        av[r] = if rows[r] == ones_row { 1.0 } else { fetch(a, a_row[r] + ka) };
    });
    av
}

/// `acc[r][c] += av[r] * B[c]` for a lane's rows and the tile's 32 columns, each lane
/// having loaded one value of each group of 8 columns (`bv[g]`: column `8 g + lane`)
/// that reaches every lane by broadcasts with constant lane numbers, which llvmpipe
/// compiles to a register shuffle.
#[cfg(feature = "subgroup-ballot")]
#[inline]
fn fma_broadcast<const R: usize>(acc: &mut [[f32; 32]; R], av: &[f32; R], bv: [f32; 4]) {
    each_index!(4, g => {
        each_index!(8, j => {
            let b = crate::subgroup::broadcast_at(bv[g], j as u32);
            each_index!(R, r => {
                acc[r][8 * g + j] += av[r] * b;
            });
        });
    });
}

/// `acc[r][c] += av[r] * B[c]` for a lane's rows and the tile's 32 columns, `B`'s row
/// of 32 being the 8 four-float texels from `t` (the same address in every lane, no
/// broadcasts).
#[cfg(feature = "subgroup-ballot")]
#[inline]
fn fma_b_row<const R: usize>(acc: &mut [[f32; 32]; R], av: &[f32; R], b: &TexelBuffer4, t: u32) {
    each_index!(8, q => {
        let bs = fetch4(b, t + q as u32).to_array();
        each_index!(4, j => {
            let bj = bs[j];
            each_index!(R, r => {
                acc[r][4 * q + j] += av[r] * bj;
            });
        });
    });
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
fn tile_bias4<const Q: usize>(p: &GemmParams, bias: &TexelBuffer4, n0: u32) -> [Vec4; Q] {
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

/// One lane's row of a forward tile, a float at a time, adding the tile's bias fetched
/// once per column (`bias`, zeros without `GEMM_BIAS`). Never adds to `C`: the engine
/// records the forwards only without `GEMM_ACCUMULATE`, which spares every column a
/// masked-off storage-buffer read (a loop over the lanes of its own on llvmpipe).
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

/// How a subgroup tile's sums reach `C`: the `c` and `bias` bindings a kernel declares,
/// and the stores of a lane's rows.
#[cfg(feature = "subgroup-ballot")]
trait Epilogue {
    /// What `c` is bound as an array of.
    type C;
    /// The `bias` binding.
    type Bias: ?Sized;
    /// Stores a lane's sums `acc[r]` (a row of `W` columns from `n0`) as row `rows[r]`
    /// of split `z`, for each of its `R` rows.
    fn store<const W: usize, const R: usize>(p: &GemmParams, c: &mut [Self::C], bias: &Self::Bias, acc: &[[f32; W]; R], rows: &[u32; R], n0: u32, z: u32);
}

/// A float at a time, the bias a storage buffer, bias and accumulation as flagged
/// ([`store_tile_row`]).
#[cfg(feature = "subgroup-ballot")]
struct Floats;

#[cfg(feature = "subgroup-ballot")]
impl Epilogue for Floats {
    type C = f32;
    type Bias = [f32];

    #[inline]
    fn store<const W: usize, const R: usize>(p: &GemmParams, c: &mut [f32], bias: &[f32], acc: &[[f32; W]; R], rows: &[u32; R], n0: u32, z: u32) {
        each_index!(R, r => {
            store_tile_row(p, c, bias, acc[r], rows[r], n0, z);
        });
    }
}

/// A float at a time with the tile's bias fetched once per column through a 1-float
/// texel view (a storage-buffer read per row and column would be a loop over the
/// lanes each), never adding to `C` ([`store_row_floats`]): the forwards'.
#[cfg(feature = "subgroup-ballot")]
struct FloatsTexelBias;

#[cfg(feature = "subgroup-ballot")]
impl Epilogue for FloatsTexelBias {
    type C = f32;
    type Bias = TexelBuffer;

    #[inline]
    fn store<const W: usize, const R: usize>(p: &GemmParams, c: &mut [f32], bias: &TexelBuffer, acc: &[[f32; W]; R], rows: &[u32; R], n0: u32, z: u32) {
        let last_col = p.n - 1;
        let with_bias = p.flags & GEMM_BIAS != 0;
        let mut bias_row = [0.0f32; W];
        each_index!(W, j => {
            let v = fetch(bias, p.bias_off + (n0 + j as u32).min(last_col));
            bias_row[j] = if with_bias { v } else { 0.0 };
        });
        each_index!(R, r => {
            store_row_floats(p, c, &bias_row, acc[r], rows[r], n0, z);
        });
    }
}

/// 4 floats a store, `C` bound as `vec4`s and the bias read as 4-float texels, `Q` of
/// them a row ([`store_tile_row4`], [`tile_bias4`]): the `_vec4` kernels'.
#[cfg(feature = "subgroup-ballot")]
struct Quads<const Q: usize>;

#[cfg(feature = "subgroup-ballot")]
impl<const Q: usize> Epilogue for Quads<Q> {
    type C = Vec4;
    type Bias = TexelBuffer4;

    #[inline]
    fn store<const W: usize, const R: usize>(p: &GemmParams, c: &mut [Vec4], bias: &TexelBuffer4, acc: &[[f32; W]; R], rows: &[u32; R], n0: u32, z: u32) {
        const { assert!(W == 4 * Q, "Quads<Q> stores rows of 4 Q columns") };
        let bias4 = tile_bias4::<Q>(p, bias, n0);
        each_index!(R, r => {
            store_tile_row4(p, c, &bias4, acc[r], rows[r], n0, z);
        });
    }
}

/// `C (+)= A B (+ bias)` for CPU devices whose subgroups are 8 lanes of one SIMD
/// register (lavapipe): each subgroup owns a 32 × 32 tile of `C`, lane `l` its rows
/// `l, l + 8, l + 16, l + 24`. Per step through `k` a lane loads its 4 values of `A`
/// and one value of each of the tile's 4 groups of 8 columns of `B`, and the 32 values
/// of `B` reach every lane by broadcasts ([`fma_broadcast`]). So 8 loads feed 128
/// multiply-adds per lane, where `gemm_blocked` makes 16 loads for 64: on llvmpipe a
/// load the compiler cannot prove uniform is a loop over the 8 lanes and costs tens of
/// multiply-adds. A workgroup is one subgroup; the engine dispatches it only where the
/// subgroup size is 8 (every lane of a subgroup runs the same `k` loop, so all lanes
/// are active at each broadcast).
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
    let rows = lane_rows::<4>(m0, lane);
    let a_row = a_row_starts(p, &rows, m_last);
    let ones = [rows[0] == ones_row, rows[1] == ones_row, rows[2] == ones_row, rows[3] == ones_row];
    let mut acc = [[0.0f32; 32]; 4];
    let mut k = k_begin;
    while k < k_end {
        // Every lane loads all 4 (in range: rows past `A` read its last row), then the
        // ones row (the bias column of a weight gradient) takes 1.
        let ka = k * p.a_sk;
        let mut loaded = [0.0f32; 4];
        each_index!(4, r => {
            loaded[r] = a[(a_row[r] + ka) as usize];
        });
        let mut av = [0.0f32; 4];
        each_index!(4, r => {
            av[r] = if ones[r] { 1.0 } else { loaded[r] };
        });
        let kb = k * p.b_sk;
        let mut bv = [0.0f32; 4];
        each_index!(4, g => {
            bv[g] = b[(b_col[g] + kb) as usize];
        });
        fma_broadcast(&mut acc, &av, bv);
        k += 1;
    }
    Floats::store(p, c, bias, &acc, &rows, n0, z);
}

/// [`gemm_subgroup`] reading `A` and `B` as uniform texel buffers: each subgroup owns a
/// 64 × 32 tile of `C`, lane `l` its rows `l + 8 i` (i < 8); per step through `k` a
/// lane fetches its 8 values of `A` and one value of each of the tile's 4 groups of 8
/// columns of `B`, and the 32 values of `B` reach every lane by broadcasts, as in
/// [`gemm_subgroup`], whose sums (in the same order of `k`) these are. What it costs
/// on llvmpipe 22.3 (its machine code read at the hot addresses): a fetch is a call
/// with one `vpgatherdd`, where a storage-buffer load is a loop over the lanes; a
/// broadcast is a loop over the 8 lanes finding the first active one (about as dear
/// as a fetch); a multiply-add, a masked store of the accumulator. So 8 rows per lane
/// (twice `gemm_subgroup`'s) halve the broadcasts and fetches per multiply-add. Rows
/// past `m` and columns past `n` read clamped indices and are never stored.
#[cfg(feature = "subgroup-ballot")]
#[inline]
#[allow(clippy::too_many_arguments)]
fn texel_body(group: UVec3, groups: UVec3, lane: u32, p: &GemmParams, a: &TexelBuffer, b: &TexelBuffer, bias: &[f32], c: &mut [f32]) {
    let Some(SgTile { m0, n0, z, k_begin, k_end, ones_row, m_last, b_col }) = sg_tile(p, group, groups, lane, GEMM_TX_ROWS, GEMM_SG_COLS) else {
        return;
    };
    let rows = lane_rows::<8>(m0, lane);
    let a_row = a_row_starts(p, &rows, m_last);
    let mut acc = [[0.0f32; 32]; 8];
    let mut k = k_begin;
    while k < k_end {
        let av = fetch_rows(a, &rows, &a_row, ones_row, k * p.a_sk);
        let kb = k * p.b_sk;
        let mut bv = [0.0f32; 4];
        each_index!(4, g => {
            bv[g] = fetch(b, b_col[g] + kb);
        });
        fma_broadcast(&mut acc, &av, bv);
        k += 1;
    }
    Floats::store(p, c, bias, &acc, &rows, n0, z);
}

/// [`texel_body`] with `B` read 4 columns a fetch through a 4-float texel view, the
/// same address in every lane (no broadcasts): needs `b_sn == 1` and `b_off`, `b_sk`
/// multiples of 4. The input gradient of a narrow head (`A = dY` of 1 to 6 columns,
/// not in whole texels), whose `k` of 1 to 6 leaves the stores most of the work, and
/// gradients the other 4-float kernels cannot read.
#[cfg(feature = "subgroup-ballot")]
#[inline]
#[allow(clippy::too_many_arguments)]
fn b_along_n_body<S: Epilogue>(group: UVec3, groups: UVec3, lane: u32, p: &GemmParams, a: &TexelBuffer, b: &TexelBuffer4, bias: &S::Bias, c: &mut [S::C]) {
    let Some(SgTile { m0, n0, z, k_begin, k_end, ones_row, m_last, .. }) = sg_tile(p, group, groups, lane, GEMM_TX_ROWS, GEMM_SG_COLS) else {
        return;
    };
    let rows = lane_rows::<8>(m0, lane);
    let a_row = a_row_starts(p, &rows, m_last);
    let mut acc = [[0.0f32; 32]; 8];
    let b_first = (p.b_off + n0) / 4;
    let b_step = p.b_sk / 4;
    let mut k = k_begin;
    while k < k_end {
        let av = fetch_rows(a, &rows, &a_row, ones_row, k * p.a_sk);
        fma_b_row(&mut acc, &av, b, b_first + k * b_step);
        k += 1;
    }
    S::store(p, c, bias, &acc, &rows, n0, z);
}

/// `C (+)= A B` for a narrow `C` (`n` up to `W`, 4 or 8: the weight gradient `Xᵀ dY`
/// of the 1- to 6-wide heads, `k` the batch rows) with `k` across the lanes: each
/// subgroup owns 32 rows of `C` (`A` contiguous along `m`, fetched as 8 four-float
/// texels per step) × `W` columns, lane `l` sums the steps `k ≡ l (mod 8)` of its
/// chunk, and the 8 partial sums meet in one subgroup reduce per value of `C` at the
/// end; lane 0 stores. The tiles that own the columns ([`weight_grad_vec4_body`])
/// would run 32 columns for 3 and fetch every step's `B` row at one address in all
/// lanes; here each lane fetches its own step's `W` values. The ones row (the bias
/// column) reads 1. Needs `a_sm == 1` and `a_off`, `a_sk` multiples of 4. Sums in a
/// different order from the other GEMMs (strided by lane, then the reduce's order).
#[cfg(feature = "subgroup-ballot")]
#[inline]
#[allow(clippy::too_many_arguments)]
fn narrow_weight_grad_body<const W: usize>(group: UVec3, groups: UVec3, lane: u32, p: &GemmParams, a: &TexelBuffer4, b: &TexelBuffer, bias: &[f32], c: &mut [f32]) {
    let Some(SgTile { m0, n0, z, k_begin, k_end, ones_row, .. }) = sg_tile(p, group, groups, lane, GEMM_KL_ROWS, W as u32) else {
        return;
    };
    let last_col = p.n - 1;
    let mut acc = [[0.0f32; W]; 32];
    let mut k = k_begin + lane;
    while k < k_end {
        let t = (p.a_off + k * p.a_sk + m0) / 4;
        let mut x4 = [Vec4::ZERO; 8];
        each_index!(8, q => {
            x4[q] = fetch4(a, t + q as u32);
        });
        let mut g = [0.0f32; W];
        each_index!(W, j => {
            g[j] = fetch(b, p.b_off + k * p.b_sk + (n0 + j as u32).min(last_col) * p.b_sn);
        });
        each_index!(32, r => {
            // Rows past `A` read what lies there (never stored); the ones row reads 1.
            let x = if m0 + r as u32 == ones_row { 1.0 } else { x4[r / 4].to_array()[r % 4] };
            each_index!(W, j => {
                acc[r][j] += x * g[j];
            });
        });
        k += 8;
    }
    // Every lane is back here (the loop above is the only divergence), as the reduces
    // need.
    each_index!(32, r => {
        each_index!(W, j => {
            acc[r][j] = crate::subgroup::sum8(acc[r][j]);
        });
    });
    if lane == 0 {
        each_index!(32, r => {
            store_tile_row(p, c, bias, acc[r], m0 + r as u32, n0, z);
        });
    }
}

/// [`texel_body`] with both operands contiguous along `k` (`a_sk == b_sk == 1`: the
/// forward `x Wᵀ`), each read 4 steps of `k` a fetch through 4-float texel views, in
/// tiles of 128 rows (16 a lane) × `W` columns: per 4 steps a lane fetches one texel
/// per row of `A` (16) and every lane the same texel per column of `B` (`W`, no
/// broadcasts), where [`texel_body`] makes 48 fetches and 128 broadcasts for half the
/// rows. Needs `a_off`, `a_sm`, `b_off`, `b_sn`, `k_chunk` and `k` multiples of 4, no
/// ones row and no `GEMM_ACCUMULATE`. Sums in the same order as [`texel_body`].
///
/// Widths 32, 16, 8 and 4: llvmpipe runs every column of a tile whether it exists or
/// not (a branch on a uniform value is a mask there, not a jump), so the engine covers
/// `n` with 32-wide tiles and the rest with the narrower ones (a head of 3 columns
/// runs 4, not 32). Epilogues [`FloatsTexelBias`] and [`Quads`].
#[cfg(feature = "subgroup-ballot")]
#[inline]
#[allow(clippy::too_many_arguments)]
fn fwd_body<const W: usize, S: Epilogue>(group: UVec3, groups: UVec3, lane: u32, p: &GemmParams, a: &TexelBuffer4, b: &TexelBuffer4, bias: &S::Bias, c: &mut [S::C]) {
    let Some(SgTile { m0, n0, z, k_begin, k_end, m_last, .. }) = sg_tile(p, group, groups, lane, GEMM_K4_ROWS, W as u32) else {
        return;
    };
    let rows = lane_rows::<16>(m0, lane);
    let a_row = a_row_texels(p, &rows, m_last);
    let last_col = p.n - 1;
    let mut acc = [[0.0f32; W]; 16];
    let mut k = k_begin;
    // 8 steps of `k` a pass (two texels per row and column), the second 4 zeroed where
    // `k` ends 4 steps in: every value written in a loop gets a masked store on
    // llvmpipe, so a pass of 8 halves those per multiply-add.
    while k < k_end {
        let kt = k / 4;
        let second = k + 4 < k_end;
        let mut av = [Vec4::ZERO; 16];
        each_index!(16, r => {
            av[r] = fetch4(a, a_row[r] + kt);
        });
        let kt2 = kt + 1;
        let mut av2 = [Vec4::ZERO; 16];
        each_index!(16, r => {
            av2[r] = fetch4(a, a_row[r] + kt2);
        });
        each_index!(W, j => {
            let b_at = (p.b_off + (n0 + j as u32).min(last_col) * p.b_sn) / 4 + kt;
            let bq = fetch4(b, b_at);
            // Past `k_end` the second texels hold the next row (or zeros past the
            // view): a zero `B` and `A` add exact zeros instead.
            let bq2 = if second { fetch4(b, b_at + 1) } else { Vec4::ZERO };
            each_index!(16, r => {
                let a2 = if second { av2[r] } else { Vec4::ZERO };
                let mut v = acc[r][j];
                v += av[r].x * bq.x;
                v += av[r].y * bq.y;
                v += av[r].z * bq.z;
                v += av[r].w * bq.w;
                v += a2.x * bq2.x;
                v += a2.y * bq2.y;
                v += a2.z * bq2.z;
                v += a2.w * bq2.w;
                acc[r][j] = v;
            });
        });
        k += 8;
    }
    S::store(p, c, bias, &acc, &rows, n0, z);
}

/// [`texel_body`] with `A` contiguous along `k` and `B` along `n` (`a_sk == b_sn == 1`:
/// the input gradient `dY W`): per 4 steps of `k` a lane fetches one 4-float texel per
/// row of `A` (8) and, per step, every lane the same 8 texels of `B` (32 columns, no
/// broadcasts). Needs `a_off`, `a_sm`, `b_off`, `b_sk`, `k_chunk` and `k` multiples of 4
/// and no ones row. Sums in the same order as [`texel_body`].
#[cfg(feature = "subgroup-ballot")]
#[inline]
#[allow(clippy::too_many_arguments)]
fn input_grad_body<S: Epilogue>(group: UVec3, groups: UVec3, lane: u32, p: &GemmParams, a: &TexelBuffer4, b: &TexelBuffer4, bias: &S::Bias, c: &mut [S::C]) {
    let Some(SgTile { m0, n0, z, k_begin, k_end, m_last, .. }) = sg_tile(p, group, groups, lane, GEMM_TX_ROWS, GEMM_SG_COLS) else {
        return;
    };
    let rows = lane_rows::<8>(m0, lane);
    let a_row = a_row_texels(p, &rows, m_last);
    let mut acc = [[0.0f32; 32]; 8];
    let b_first = (p.b_off + n0) / 4;
    let b_step = p.b_sk / 4;
    let mut k = k_begin;
    while k < k_end {
        let kt = k / 4;
        let mut av = [Vec4::ZERO; 8];
        each_index!(8, r => {
            av[r] = fetch4(a, a_row[r] + kt);
        });
        // Step `k + kk` of `k`: component `kk` of each row's texel.
        each_index!(4, kk => {
            let mut ak = [0.0f32; 8];
            each_index!(8, r => {
                ak[r] = av[r].to_array()[kk];
            });
            fma_b_row(&mut acc, &ak, b, b_first + (k + kk as u32) * b_step);
        });
        k += 4;
    }
    S::store(p, c, bias, &acc, &rows, n0, z);
}

/// [`texel_body`] with `A` contiguous along `m` and `B` along `n` (`a_sm == b_sn == 1`:
/// the weight gradient `Xᵀ dY`, whose `k` is the rows of the batch), storing 4 floats
/// at a time: lane `l` owns rows `m0 + 4 l + {0, 1, 2, 3}` and the same 32 further,
/// so per step of `k` it fetches its 8 values of `A` as two 4-float texels and every
/// lane the same 8 texels of `B` (32 columns), where [`b_along_n_body`] fetches 8
/// values of `A` one at a time. The ones row (the bias column of the gradient) reads 1.
/// Needs `a_off`, `a_sk`, `b_off`, `b_sk` multiples of 4 and `C` as [`Quads`] does.
/// Sums in the same order as [`texel_body`].
#[cfg(feature = "subgroup-ballot")]
#[inline]
#[allow(clippy::too_many_arguments)]
fn weight_grad_vec4_body(group: UVec3, groups: UVec3, lane: u32, p: &GemmParams, a: &TexelBuffer4, b: &TexelBuffer4, bias: &TexelBuffer4, c: &mut [Vec4]) {
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
    let mut acc = [[0.0f32; 32]; 8];
    let mut k = k_begin;
    while k < k_end {
        let lo_hi = [fetch4(a, a_first[0] + k * a_step), fetch4(a, a_first[1] + k * a_step)];
        let mut av = [0.0f32; 8];
        each_index!(8, r => {
            av[r] = if ones[r] { 1.0 } else { lo_hi[r / 4].to_array()[r % 4] };
        });
        fma_b_row(&mut acc, &av, b, b_first + k * b_step);
        k += 1;
    }
    Quads::<8>::store(p, c, bias, &acc, &rows, n0, z);
}

/// Declares a GEMM entry point of a subgroup tile (`subgroup-ballot` builds): a
/// workgroup of 8 invocations, one subgroup, that hands its builtins and its bindings
/// to the generic body named. `a` and `b` are texel views of the types given, `c` a
/// storage buffer of the element given, `bias` a storage buffer (`storage [f32]`) or a
/// texel view. One line an entry point: every entry point's signature written out
/// would be the same 12 lines each time.
macro_rules! subgroup_gemm_entry {
    ($name:ident, $body:expr, a: $a:ty, b: $b:ty, bias: storage $bias:ty, c: $c:ty) => {
        subgroup_gemm_entry!(@entry $name, $body, $a, $b, (storage_buffer, descriptor_set = 0, binding = 2) $bias, $c);
    };
    ($name:ident, $body:expr, a: $a:ty, b: $b:ty, bias: $bias:ty, c: $c:ty) => {
        subgroup_gemm_entry!(@entry $name, $body, $a, $b, (descriptor_set = 0, binding = 2) $bias, $c);
    };
    (@entry $name:ident, $body:expr, $a:ty, $b:ty, ($($bias_class:tt)*) $bias:ty, $c:ty) => {
        #[cfg(feature = "subgroup-ballot")]
        #[spirv(compute(threads(8)))]
        pub fn $name(
            #[spirv(workgroup_id)] group: UVec3,
            #[spirv(num_workgroups)] groups: UVec3,
            #[spirv(local_invocation_index)] lane: u32,
            #[spirv(push_constant)] p: &GemmParams,
            #[spirv(descriptor_set = 0, binding = 0)] a: &$a,
            #[spirv(descriptor_set = 0, binding = 1)] b: &$b,
            #[spirv($($bias_class)*)] bias: &$bias,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] c: &mut [$c],
        ) {
            $body(group, groups, lane, p, a, b, bias, c)
        }
    };
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

// The fallback of the 4-float kernels: 1-float texels, `B` broadcast.
subgroup_gemm_entry!(gemm_texel, texel_body, a: TexelBuffer, b: TexelBuffer, bias: storage [f32], c: f32);
// Forwards (`A` and `B` along `k`), by tile width, each storing floats or 4 at a time.
subgroup_gemm_entry!(gemm_texel_k4, fwd_body::<32, FloatsTexelBias>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer, c: f32);
subgroup_gemm_entry!(gemm_texel_k4c4, fwd_body::<32, Quads<8>>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer4, c: Vec4);
subgroup_gemm_entry!(gemm_texel_k4w16, fwd_body::<16, FloatsTexelBias>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer, c: f32);
subgroup_gemm_entry!(gemm_texel_k4w16c4, fwd_body::<16, Quads<4>>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer4, c: Vec4);
subgroup_gemm_entry!(gemm_texel_k4w8, fwd_body::<8, FloatsTexelBias>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer, c: f32);
subgroup_gemm_entry!(gemm_texel_k4w8c4, fwd_body::<8, Quads<2>>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer4, c: Vec4);
subgroup_gemm_entry!(gemm_texel_k4w4, fwd_body::<4, FloatsTexelBias>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer, c: f32);
subgroup_gemm_entry!(gemm_texel_k4w4c4, fwd_body::<4, Quads<1>>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer4, c: Vec4);
// Input gradients (`A` along `k`, `B` along `n`).
subgroup_gemm_entry!(gemm_texel_k4n4, input_grad_body::<Floats>, a: TexelBuffer4, b: TexelBuffer4, bias: storage [f32], c: f32);
subgroup_gemm_entry!(gemm_texel_k4n4c4, input_grad_body::<Quads<8>>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer4, c: Vec4);
// Weight gradients (`A` along `m`, `B` along `n`), and those of heads up to 4 or 8 wide.
subgroup_gemm_entry!(gemm_texel_m4n4c4, weight_grad_vec4_body, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer4, c: Vec4);
subgroup_gemm_entry!(gemm_texel_klanes_w4, narrow_weight_grad_body::<4>, a: TexelBuffer4, b: TexelBuffer, bias: storage [f32], c: f32);
subgroup_gemm_entry!(gemm_texel_klanes_w8, narrow_weight_grad_body::<8>, a: TexelBuffer4, b: TexelBuffer, bias: storage [f32], c: f32);
// `B` along `n`, `A` in any layout.
subgroup_gemm_entry!(gemm_texel_b4, b_along_n_body::<Floats>, a: TexelBuffer, b: TexelBuffer4, bias: storage [f32], c: f32);
subgroup_gemm_entry!(gemm_texel_b4c4, b_along_n_body::<Quads<8>>, a: TexelBuffer, b: TexelBuffer4, bias: TexelBuffer4, c: Vec4);
