//! GEMMs for CPU devices (lavapipe): what the engine records for a dense layer on a
//! `DeviceKind::Cpu` device instead of `nn::gemm_tiled`, all computing
//! `C (+)= A B (+ bias)` with the operands addressed by strides (`GemmParams`, see
//! `drape_shared::nn`). llvmpipe runs 8 invocations a SIMD instruction, and there a
//! storage-buffer load at a per-invocation address is a loop over the 8 lanes (tens of
//! multiply-adds' worth), a texel fetch one gather, a branch on a uniform value a mask
//! (both sides run) and every value written in a loop a masked store: so these kernels
//! keep large tiles of sums in registers and read each operand value once per tile,
//! through texel views where the operand's layout allows (`crate::texel`).
//!
//! | kernel | a subgroup's tile, reads | the engine records it for (`engine/src/ops/nn.rs`) |
//! | --- | --- | --- |
//! | `gemm_blocked` | 8 × 8 an invocation, storage buffers | `GemmVariant::Blocked`; `Auto` without subgroups of 8, or for outputs under 16 columns no texel kernel takes |
//! | `gemm_subgroup` | 32 × 32, storage buffers, `B` broadcast | `Subgroup`; `Auto` where the operands can't be texel views |
//! | `gemm_texel` | 64 × 32, 1-float texels, `B` broadcast | `Texel`; `Texel4` where no 4-float kernel below fits |
//! | `gemm_fwd_cols{32,16,8,4}[_vec4]` | 128 × 32/16/8/4, `A` and `B` along `k`, 4 floats a fetch | forwards `x Wᵀ` (`Texel4`, `Auto`): 32-wide tiles, the rest of `n` in the cheapest narrower ones |
//! | `gemm_input_grad[_vec4]` | 64 × 32, `A` along `k`, `B` along `n` | input gradients `dY W` |
//! | `gemm_weight_grad_vec4` | 64 × 32, `A` along `m`, `B` along `n` | weight gradients `Xᵀ dY` where `C` takes `vec4`s |
//! | `gemm_weight_grad_cols{4,8}` | 32 × 4 or 8, `k` across the lanes | weight gradients of heads up to 8 wide |
//! | `gemm_b_along_n[_vec4]` | 64 × 32, `A` 1-float texels, `B` along `n` | gradients the kernels above can't read (a narrow head's input gradient, an odd-width layer's weight gradient) |
//!
//! Kernels ending in `_vec4` store `C` 4 floats at a time (`c` bound as `vec4`s, the
//! bias read as 4-float texels: [`Quads`]), which needs `n`, `ldc` and the offsets in
//! whole texels; the others store floats. The forwards never add to `C` and the
//! texel kernels need the operands' offsets and strides in whole texels; the engine
//! checks every condition before it picks a kernel. All but `gemm_weight_grad_cols*`
//! add the same terms in the same order of `k` (those sum `k` strided by lane, then
//! across the lanes).
//!
//! Bindings of every kernel: `a`, `b`, `bias` (read; storage buffers or texel views as
//! each declares), `c` (written, or added to). All but `gemm_blocked` need subgroups of
//! exactly 8 lanes (`subgroup-ballot` builds): a workgroup is one subgroup that owns one
//! tile, lane `l` the rows `l + 8 i` of it (or rows `4 l + ..`, `gemm_weight_grad_vec4`).
//!
//! Each body is written once, generic over the tile width and the epilogue
//! ([`Epilogue`]), and unrolled with `drape_shared::each_index!` (which takes a const
//! generic count), so every register is indexed with constants, as if each tile width
//! were written out by hand (docs/performance.md, "Kernels as generic functions",
//! compares the SPIR-V with such a hand-written form). One macro declares
//! the subgroup-tile entry points (rust-gpu cannot make a generic function an entry
//! point, and their 16 signatures written out are the same 12 lines each).

#[cfg(feature = "subgroup-ballot")]
use crate::texel::{fetch, fetch4, TexelBuffer, TexelBuffer4};
use drape_shared::each_index;
use drape_shared::nn::{GemmParams, GEMM_ACCUMULATE, GEMM_BIAS, GEMM_BLOCK, GEMM_ONES_ROW};
#[cfg(feature = "subgroup-ballot")]
use drape_shared::nn::{GEMM_FWD_ROWS, GEMM_NARROW_ROWS, GEMM_SG_COLS, GEMM_SG_ROWS, GEMM_TX_ROWS};
use spirv_std::glam::UVec3;
#[cfg(feature = "subgroup-ballot")]
use spirv_std::glam::Vec4;
use spirv_std::spirv;

/// One step of `k` of the register-blocked GEMM: 8 values of `A` (a column of the
/// invocation's rows) and 8 of `B` (a row of its columns), 64 multiply-adds into
/// accumulators with constant indices. Out-of-range rows and columns read the last
/// valid element (their results are never stored).
#[inline]
#[allow(clippy::too_many_arguments)]
fn block_step(
    acc: &mut [f32; 64],
    a: &[f32],
    b: &[f32],
    p: &GemmParams,
    m0: u32,
    n0: u32,
    k: u32,
    ones_row: u32,
    m_last: u32,
) {
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
fn block_store(
    acc: &[f32; 64],
    p: &GemmParams,
    c: &mut [f32],
    bias: &[f32],
    m0: u32,
    n0: u32,
    z: u32,
) {
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
    // The last row of A that exists (the ones row is not stored). Every load uses an
    // in-range index: the ones row's load may be evaluated and then discarded, and an
    // out-of-range index would end the invocation (slice bounds check).
    let m_last = if p.flags & GEMM_ONES_ROW != 0 && p.m >= 2 {
        p.m - 2
    } else {
        p.m - 1
    };
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
fn sg_tile(
    p: &GemmParams,
    group: UVec3,
    groups: UVec3,
    lane: u32,
    tile_rows: u32,
    tile_cols: u32,
) -> Option<SgTile> {
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
    // The last row of A that exists (the ones row is not stored): rows past it read
    // that row (in range) and are never stored.
    let m_last = if p.flags & GEMM_ONES_ROW != 0 && p.m >= 2 {
        p.m - 2
    } else {
        p.m - 1
    };
    let last_col = p.n - 1;
    let b_col = [
        p.b_off + (n0 + lane).min(last_col) * p.b_sn,
        p.b_off + (n0 + 8 + lane).min(last_col) * p.b_sn,
        p.b_off + (n0 + 16 + lane).min(last_col) * p.b_sn,
        p.b_off + (n0 + 24 + lane).min(last_col) * p.b_sn,
    ];
    Some(SgTile {
        m0,
        n0,
        z,
        k_begin,
        k_end,
        ones_row,
        m_last,
        b_col,
    })
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
fn fetch_rows<const R: usize>(
    a: &TexelBuffer,
    rows: &[u32; R],
    a_row: &[u32; R],
    ones_row: u32,
    ka: u32,
) -> [f32; R] {
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
fn store_tile_row<const W: usize>(
    p: &GemmParams,
    c: &mut [f32],
    bias: &[f32],
    vals: [f32; W],
    row: u32,
    n0: u32,
    z: u32,
) {
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
fn store_tile_row4<const W: usize, const Q: usize>(
    p: &GemmParams,
    c: &mut [Vec4],
    bias: &[Vec4; Q],
    vals: [f32; W],
    row: u32,
    n0: u32,
    z: u32,
) {
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
fn store_row_floats<const W: usize>(
    p: &GemmParams,
    c: &mut [f32],
    bias: &[f32; W],
    vals: [f32; W],
    row: u32,
    n0: u32,
    z: u32,
) {
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
    fn store<const W: usize, const R: usize>(
        p: &GemmParams,
        c: &mut [Self::C],
        bias: &Self::Bias,
        acc: &[[f32; W]; R],
        rows: &[u32; R],
        n0: u32,
        z: u32,
    );
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
    fn store<const W: usize, const R: usize>(
        p: &GemmParams,
        c: &mut [f32],
        bias: &[f32],
        acc: &[[f32; W]; R],
        rows: &[u32; R],
        n0: u32,
        z: u32,
    ) {
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
    fn store<const W: usize, const R: usize>(
        p: &GemmParams,
        c: &mut [f32],
        bias: &TexelBuffer,
        acc: &[[f32; W]; R],
        rows: &[u32; R],
        n0: u32,
        z: u32,
    ) {
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
    fn store<const W: usize, const R: usize>(
        p: &GemmParams,
        c: &mut [Vec4],
        bias: &TexelBuffer4,
        acc: &[[f32; W]; R],
        rows: &[u32; R],
        n0: u32,
        z: u32,
    ) {
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
    let Some(SgTile {
        m0,
        n0,
        z,
        k_begin,
        k_end,
        ones_row,
        m_last,
        b_col,
    }) = sg_tile(p, group, groups, lane, GEMM_SG_ROWS, GEMM_SG_COLS)
    else {
        return;
    };
    let rows = lane_rows::<4>(m0, lane);
    let a_row = a_row_starts(p, &rows, m_last);
    let ones = [
        rows[0] == ones_row,
        rows[1] == ones_row,
        rows[2] == ones_row,
        rows[3] == ones_row,
    ];
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
fn texel_body(
    group: UVec3,
    groups: UVec3,
    lane: u32,
    p: &GemmParams,
    a: &TexelBuffer,
    b: &TexelBuffer,
    bias: &[f32],
    c: &mut [f32],
) {
    let Some(SgTile {
        m0,
        n0,
        z,
        k_begin,
        k_end,
        ones_row,
        m_last,
        b_col,
    }) = sg_tile(p, group, groups, lane, GEMM_TX_ROWS, GEMM_SG_COLS)
    else {
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
fn b_along_n_body<S: Epilogue>(
    group: UVec3,
    groups: UVec3,
    lane: u32,
    p: &GemmParams,
    a: &TexelBuffer,
    b: &TexelBuffer4,
    bias: &S::Bias,
    c: &mut [S::C],
) {
    let Some(SgTile {
        m0,
        n0,
        z,
        k_begin,
        k_end,
        ones_row,
        m_last,
        ..
    }) = sg_tile(p, group, groups, lane, GEMM_TX_ROWS, GEMM_SG_COLS)
    else {
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
fn narrow_weight_grad_body<const W: usize>(
    group: UVec3,
    groups: UVec3,
    lane: u32,
    p: &GemmParams,
    a: &TexelBuffer4,
    b: &TexelBuffer,
    bias: &[f32],
    c: &mut [f32],
) {
    let Some(SgTile {
        m0,
        n0,
        z,
        k_begin,
        k_end,
        ones_row,
        ..
    }) = sg_tile(p, group, groups, lane, GEMM_NARROW_ROWS, W as u32)
    else {
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
fn fwd_body<const W: usize, S: Epilogue>(
    group: UVec3,
    groups: UVec3,
    lane: u32,
    p: &GemmParams,
    a: &TexelBuffer4,
    b: &TexelBuffer4,
    bias: &S::Bias,
    c: &mut [S::C],
) {
    let Some(SgTile {
        m0,
        n0,
        z,
        k_begin,
        k_end,
        m_last,
        ..
    }) = sg_tile(p, group, groups, lane, GEMM_FWD_ROWS, W as u32)
    else {
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
fn input_grad_body<S: Epilogue>(
    group: UVec3,
    groups: UVec3,
    lane: u32,
    p: &GemmParams,
    a: &TexelBuffer4,
    b: &TexelBuffer4,
    bias: &S::Bias,
    c: &mut [S::C],
) {
    let Some(SgTile {
        m0,
        n0,
        z,
        k_begin,
        k_end,
        m_last,
        ..
    }) = sg_tile(p, group, groups, lane, GEMM_TX_ROWS, GEMM_SG_COLS)
    else {
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
fn weight_grad_vec4_body(
    group: UVec3,
    groups: UVec3,
    lane: u32,
    p: &GemmParams,
    a: &TexelBuffer4,
    b: &TexelBuffer4,
    bias: &TexelBuffer4,
    c: &mut [Vec4],
) {
    let Some(SgTile {
        m0,
        n0,
        z,
        k_begin,
        k_end,
        ones_row,
        ..
    }) = sg_tile(p, group, groups, lane, GEMM_TX_ROWS, GEMM_SG_COLS)
    else {
        return;
    };
    let r0 = m0 + 4 * lane;
    let rows = [
        r0,
        r0 + 1,
        r0 + 2,
        r0 + 3,
        r0 + 32,
        r0 + 33,
        r0 + 34,
        r0 + 35,
    ];
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
        let lo_hi = [
            fetch4(a, a_first[0] + k * a_step),
            fetch4(a, a_first[1] + k * a_step),
        ];
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

// The fallback of the 4-float kernels: 1-float texels, `B` broadcast.
subgroup_gemm_entry!(gemm_texel, texel_body, a: TexelBuffer, b: TexelBuffer, bias: storage [f32], c: f32);
// Forwards (`A` and `B` along `k`), by tile width, each storing floats or 4 at a time.
subgroup_gemm_entry!(gemm_fwd_cols32, fwd_body::<32, FloatsTexelBias>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer, c: f32);
subgroup_gemm_entry!(gemm_fwd_cols32_vec4, fwd_body::<32, Quads<8>>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer4, c: Vec4);
subgroup_gemm_entry!(gemm_fwd_cols16, fwd_body::<16, FloatsTexelBias>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer, c: f32);
subgroup_gemm_entry!(gemm_fwd_cols16_vec4, fwd_body::<16, Quads<4>>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer4, c: Vec4);
subgroup_gemm_entry!(gemm_fwd_cols8, fwd_body::<8, FloatsTexelBias>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer, c: f32);
subgroup_gemm_entry!(gemm_fwd_cols8_vec4, fwd_body::<8, Quads<2>>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer4, c: Vec4);
subgroup_gemm_entry!(gemm_fwd_cols4, fwd_body::<4, FloatsTexelBias>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer, c: f32);
subgroup_gemm_entry!(gemm_fwd_cols4_vec4, fwd_body::<4, Quads<1>>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer4, c: Vec4);
// Input gradients (`A` along `k`, `B` along `n`).
subgroup_gemm_entry!(gemm_input_grad, input_grad_body::<Floats>, a: TexelBuffer4, b: TexelBuffer4, bias: storage [f32], c: f32);
subgroup_gemm_entry!(gemm_input_grad_vec4, input_grad_body::<Quads<8>>, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer4, c: Vec4);
// Weight gradients (`A` along `m`, `B` along `n`), and those of heads up to 4 or 8 wide.
subgroup_gemm_entry!(gemm_weight_grad_vec4, weight_grad_vec4_body, a: TexelBuffer4, b: TexelBuffer4, bias: TexelBuffer4, c: Vec4);
subgroup_gemm_entry!(gemm_weight_grad_cols4, narrow_weight_grad_body::<4>, a: TexelBuffer4, b: TexelBuffer, bias: storage [f32], c: f32);
subgroup_gemm_entry!(gemm_weight_grad_cols8, narrow_weight_grad_body::<8>, a: TexelBuffer4, b: TexelBuffer, bias: storage [f32], c: f32);
// `B` along `n`, `A` in any layout.
subgroup_gemm_entry!(gemm_b_along_n, b_along_n_body::<Floats>, a: TexelBuffer, b: TexelBuffer4, bias: storage [f32], c: f32);
subgroup_gemm_entry!(gemm_b_along_n_vec4, b_along_n_body::<Quads<8>>, a: TexelBuffer, b: TexelBuffer4, bias: TexelBuffer4, c: Vec4);
