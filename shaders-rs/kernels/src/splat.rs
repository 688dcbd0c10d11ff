//! Differentiable Gaussian splatting kernels. The math is `drape_shared::splat`; these
//! entry points index buffers and call it.
//!
//! Buffers (n Gaussians, m tile intersections, P pixels, K SH coefficients/channel):
//! `frame`: one `FrameParams`; parameters `means` 3n, `log_scales` 3n, `quats` 4n,
//! `opacity_logits` n, `sh` 3Kn as `[gaussian][k][channel]`; `splats` n
//! `ProjectedSplat`; `depth_keys`/`order` n; `counts`/`offsets` n + 1 (the last is the
//! total); `isect_keys`/`isect_values` m (tile id, Gaussian); `ranges` 2 per tile
//! ([start, end) into the sorted intersections, zero-filled before `tile_ranges`);
//! per-pixel outputs `rgb` 3P, `alpha` P, `depth` P, `contributors` P, `transmittance` P,
//! `blended` P; per-splat gradients `splat_grads` 10n (zero-filled before the backward
//! rasterizer); parameter gradients with the parameters' shapes.
//! NaN policy: a Gaussian with a non-finite parameter gets `tiles = 0` and
//! `SPLAT_DROPPED`, and `dropped[0]` counts it; nothing downstream reads it.

use drape_shared::radix_sort::bounded_len;
use drape_shared::splat::layout::{sh_coeffs, FrameParams, HalfSplat, ProjectChunk, ProjectedSplat, SplatCounts, MAX_SH_COEFFS, SPLAT_DROPPED, SPLAT_GRAD_FLOATS, RASTER_BLOCK};
use drape_shared::splat::project::{project_bwd as project_bwd_math, project_fwd as project_fwd_math, tile_rect, Camera, Gaussian, SplatGrad};
use drape_shared::half::{pack2, sh_half_sources, sh_half_words, ShHalfParams};
#[cfg(feature = "subgroup-ballot")]
use drape_shared::splat::raster::may_touch_rect;
use drape_shared::splat::raster::{BlendSettings, FusedPixel, FusedPixelBwd, PixelBwd, PixelFwd, SplatView};
use spirv_std::arch::workgroup_memory_barrier_with_group_sync as barrier;
use spirv_std::glam::UVec3;
#[cfg(feature = "subgroup-ballot")]
use spirv_std::glam::Vec4;
use spirv_std::spirv;

use crate::{atomics, flat_index};


/// Gaussian `i`, whose SH starts at Gaussian `sh_i` of the `sh` binding (see
/// `ProjectChunk`).
#[allow(clippy::too_many_arguments)]
fn load_gaussian(
    i: usize,
    sh_i: usize,
    degree: u32,
    means: &[f32],
    log_scales: &[f32],
    quats: &[f32],
    opacity_logits: &[f32],
    sh: &[f32],
) -> Gaussian<f32> {
    let k_count = sh_coeffs(degree);
    let mut coeffs = [[0.0f32; 3]; MAX_SH_COEFFS];
    // Constant indices into `coeffs` (see `drape_shared::each_index!`).
    drape_shared::each_index!(16, k => {
        if k < k_count {
            let base = (sh_i * k_count + k) * 3;
            coeffs[k] = [sh[base], sh[base + 1], sh[base + 2]];
        }
    });
    Gaussian {
        mean: [means[3 * i], means[3 * i + 1], means[3 * i + 2]],
        log_scale: [log_scales[3 * i], log_scales[3 * i + 1], log_scales[3 * i + 2]],
        quat: [quats[4 * i], quats[4 * i + 1], quats[4 * i + 2], quats[4 * i + 3]],
        opacity_logit: opacity_logits[i],
        sh: coeffs,
    }
}

/// Projects Gaussian `i`: its splat, its depth key and its index for the depth sort.
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(256)))]
pub fn project_fwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] chunk: &ProjectChunk,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] means: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] log_scales: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] quats: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] opacity_logits: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] sh: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] splats: &mut [ProjectedSplat],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] depth_keys: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] order: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] dropped: &mut [u32],
) {
    let local = flat_index(id, groups);
    let index = chunk.first + local;
    if local >= chunk.len || index >= frame.count {
        return;
    }
    let g = load_gaussian(index as usize, local as usize, frame.sh_degree, means, log_scales, quats, opacity_logits, sh);
    project_store(index, &g, frame, splats, depth_keys, order, dropped);
}

/// [`project_fwd`] reading half-precision SH (`sh_half`: two halves a word,
/// [`sh_half_words`] words per Gaussian from `splat::pack_sh_half`): the render-only
/// knob of `engine-bench trade` (no backward reads these).
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(256)))]
pub fn project_fwd_sh_half(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] chunk: &ProjectChunk,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] means: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] log_scales: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] quats: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] opacity_logits: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] sh_half: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] splats: &mut [ProjectedSplat],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] depth_keys: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] order: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] dropped: &mut [u32],
) {
    let local = flat_index(id, groups);
    let index = chunk.first + local;
    if local >= chunk.len || index >= frame.count {
        return;
    }
    let i = index as usize;
    let k_count = sh_coeffs(frame.sh_degree);
    let words = sh_half_words(k_count);
    let mut flat = [0.0f32; 3 * MAX_SH_COEFFS];
    let mut w = 0;
    while w < words {
        // GLSL's UnpackHalf2x16: exact, as `half::unpack2` (one conversion instruction
        // on llvmpipe where the integer code is a dozen).
        let v = spirv_std::float::f16x2_to_vec2(sh_half[local as usize * words + w]);
        let (lo, hi) = (v.x, v.y);
        flat[2 * w] = lo;
        // The padding half of an odd count lands past the last coefficient: unread.
        if 2 * w + 1 < 3 * MAX_SH_COEFFS {
            flat[2 * w + 1] = hi;
        }
        w += 1;
    }
    let mut coeffs = [[0.0f32; 3]; MAX_SH_COEFFS];
    drape_shared::each_index!(16, k => {
        if k < k_count {
            coeffs[k] = [flat[3 * k], flat[3 * k + 1], flat[3 * k + 2]];
        }
    });
    let g = Gaussian {
        mean: [means[3 * i], means[3 * i + 1], means[3 * i + 2]],
        log_scale: [log_scales[3 * i], log_scales[3 * i + 1], log_scales[3 * i + 2]],
        quat: [quats[4 * i], quats[4 * i + 1], quats[4 * i + 2], quats[4 * i + 3]],
        opacity_logit: opacity_logits[i],
        sh: coeffs,
    };
    project_store(index, &g, frame, splats, depth_keys, order, dropped);
}

/// Packs SH to half precision for [`project_fwd_sh_half`]: output word `w` holds two
/// consecutive floats of the `[gaussian][k][channel]` layout, rounded to nearest even
/// (`drape_shared::half`, the same bits on every device).
#[spirv(compute(threads(256)))]
pub fn pack_sh_half(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &ShHalfParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] sh: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] sh_half: &mut [u32],
) {
    let w = flat_index(id, groups);
    if w >= p.count * sh_half_words(p.coeffs as usize) as u32 {
        return;
    }
    let (lo, hi) = sh_half_sources(w, p.coeffs);
    let hi = match hi {
        Some(j) => sh[j],
        None => 0.0,
    };
    sh_half[w as usize] = pack2(sh[lo], hi);
}

/// Writes the projection of Gaussian `index` (its splat, depth key and sort index).
#[allow(clippy::too_many_arguments)]
#[inline]
fn project_store(
    index: u32,
    g: &Gaussian<f32>,
    frame: &FrameParams,
    splats: &mut [ProjectedSplat],
    depth_keys: &mut [u32],
    order: &mut [u32],
    dropped: &mut [u32],
) {
    let i = index as usize;
    let cam = Camera::<f32>::from_frame(frame);
    let p = project_fwd_math(g, &cam);
    let mut out = ProjectedSplat::default();
    if p.visible {
        let r = tile_rect(p.x, p.y, p.radius, frame.tile_size, frame.tiles_x, frame.tiles_y);
        out = ProjectedSplat {
            x: p.x,
            y: p.y,
            depth: p.depth,
            conic_a: p.conic[0],
            conic_b: p.conic[1],
            conic_c: p.conic[2],
            opacity: p.opacity,
            r: p.color[0],
            g: p.color[1],
            b: p.color[2],
            tile_x0: r[0],
            tile_y0: r[1],
            tile_x1: r[2],
            tile_y1: r[3],
            tiles: (r[2] - r[0]) * (r[3] - r[1]),
            flags: 0,
        };
    }
    if p.dropped {
        out.flags = SPLAT_DROPPED;
        atomics::add_u32(&mut dropped[0], 1);
    }
    splats[i] = out;
    // Culled splats sort last; they emit no intersections either way.
    depth_keys[i] = if out.tiles > 0 { p.depth.to_bits() } else { u32::MAX };
    order[i] = index;
}

/// `counts[j]` = tiles of the `j`-th splat in depth order; `counts[n]` = 0, so that
/// after the exclusive scan `offsets[n]` is the number of intersections. The scan is
/// u32 and wraps past 2^32 - 1, so the total is also summed here without wrap:
/// `total[0]` (low word) and `total[1]` (carries), zero-filled before. A workgroup's
/// sum cannot wrap: 256 splats of at most 2^24 tiles each (the renderer refuses larger
/// tile grids).
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(256)))]
pub fn gather_counts(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] counts_pc: &SplatCounts,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] order: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[ProjectedSplat],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] counts: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] total: &mut [u32],
    #[spirv(workgroup)] group_sum: &mut [u32; 1],
) {
    let j = flat_index(id, groups);
    if lid == 0 {
        group_sum[0] = 0;
    }
    barrier();
    let mut tiles = 0;
    if j < counts_pc.count {
        tiles = splats[order[j as usize] as usize].tiles;
        counts[j as usize] = tiles;
    } else if j == counts_pc.count {
        counts[j as usize] = 0;
    }
    if tiles > 0 {
        atomics::add_u32_workgroup(&mut group_sum[0], tiles);
    }
    barrier();
    if lid == 0 && group_sum[0] > 0 {
        let sum = group_sum[0];
        // Each add sees the value before it: exactly the adds that wrap carry.
        let before = atomics::fetch_add_u32(&mut total[0], sum);
        if before > u32::MAX - sum {
            atomics::add_u32(&mut total[1], 1);
        }
    }
}

/// Writes (tile id, Gaussian) for every tile each splat covers, in depth order, into
/// buffers of `counts_pc.intersections` (their capacity) entries. Past the capacity
/// (the 64-bit `total` says so) nothing beyond it is written; the host sees the total
/// after the frame and renders again with larger buffers.
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(256)))]
pub fn emit_intersections(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] counts_pc: &SplatCounts,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] order: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] splats: &[ProjectedSplat],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] offsets: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] total: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] isect_keys: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] isect_values: &mut [u32],
) {
    let index = flat_index(id, groups);
    // A total past 2^32 wrapped the scanned offsets: write nothing.
    if index >= frame.count || total[1] != 0 {
        return;
    }
    let capacity = counts_pc.intersections as usize;
    let j = index as usize;
    let g = order[j];
    let s = splats[g as usize];
    if s.tiles == 0 {
        return;
    }
    let mut out = offsets[j] as usize;
    let mut ty = s.tile_y0;
    while ty < s.tile_y1 {
        let mut tx = s.tile_x0;
        while tx < s.tile_x1 {
            if out < capacity {
                isect_keys[out] = ty * frame.tiles_x + tx;
                isect_values[out] = g;
            }
            out += 1;
            tx += 1;
        }
        ty += 1;
    }
}

/// `ranges[2t], ranges[2t + 1]` = [start, end) of tile t in the sorted intersections:
/// the GPU-computed `total` of them, bounded by the capacity `counts_pc.intersections`
/// (the grid covers the capacity).
#[spirv(compute(threads(256)))]
pub fn tile_ranges(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] counts_pc: &SplatCounts,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] isect_keys: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] total: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] ranges: &mut [u32],
) {
    let k = flat_index(id, groups);
    let m = bounded_len(counts_pc.intersections, total[0], total[1]);
    if k >= m {
        return;
    }
    let key = isect_keys[k as usize];
    if k == 0 || isect_keys[k as usize - 1] != key {
        ranges[2 * key as usize] = k;
    }
    if k + 1 == m || isect_keys[k as usize + 1] != key {
        ranges[2 * key as usize + 1] = k + 1;
    }
}

/// Splats one workgroup loads into workgroup memory at a time. Besides sharing the
/// loads among a tile's pixels, batching keeps every loop short: llvmpipe abandons a
/// loop after 65,535 iterations, and a tile's list can be far longer.
const BATCH: usize = 256;
const _: () = assert!(BATCH == (RASTER_BLOCK * RASTER_BLOCK) as usize);
const _: () = assert!(BATCH as u32 % UNROLL == 0);

/// Splats handled per iteration of the per-pixel loops (see [`unroll`]).
const UNROLL: u32 = 8;

/// Repeats `$body` UNROLL (8) times with `$u` = 0, 1, ..., 7, without a loop.
macro_rules! unroll {
    ($u:ident, $body:block) => {
        $body $u += 1; $body $u += 1; $body $u += 1; $body $u += 1;
        $body $u += 1; $body $u += 1; $body $u += 1; $body
        let _ = $u;
    };
}

/// A splat layout the forward rasterizers read: its view.
trait RasterSplat {
    fn raster_view(&self) -> SplatView<f32>;
}

impl RasterSplat for ProjectedSplat {
    #[inline]
    fn raster_view(&self) -> SplatView<f32> {
        self.view()
    }
}

impl RasterSplat for SplatView<f32> {
    #[inline]
    fn raster_view(&self) -> SplatView<f32> {
        *self
    }
}

impl RasterSplat for HalfSplat {
    /// [`HalfSplat::view`] through GLSL's UnpackHalf2x16: exact, as the shared integer
    /// code, and one conversion instruction on llvmpipe where that is a dozen.
    #[inline]
    fn raster_view(&self) -> SplatView<f32> {
        use spirv_std::float::f16x2_to_vec2;
        let ab = f16x2_to_vec2(self.conic_ab);
        let co = f16x2_to_vec2(self.conic_c_opacity);
        let rg = f16x2_to_vec2(self.rg);
        let bd = f16x2_to_vec2(self.b_depth);
        SplatView { x: self.x, y: self.y, depth: bd.y, conic: [ab.x, ab.y, co.x], opacity: co.y, color: [rg.x, rg.y, bd.x] }
    }
}

/// Stores a splat's fields into slot `slot` of the workgroup batch.
#[allow(clippy::too_many_arguments)]
#[inline]
fn load_batch_slot(
    slot: usize,
    s: &SplatView<f32>,
    b_xy: &mut [[f32; 2]; BATCH],
    b_conic: &mut [[f32; 3]; BATCH],
    b_opacity_depth: &mut [[f32; 2]; BATCH],
    b_color: &mut [[f32; 3]; BATCH],
) {
    b_xy[slot] = [s.x, s.y];
    b_conic[slot] = s.conic;
    b_opacity_depth[slot] = [s.opacity, s.depth];
    b_color[slot] = s.color;
}

#[inline]
fn batch_view(
    slot: usize,
    b_xy: &[[f32; 2]; BATCH],
    b_conic: &[[f32; 3]; BATCH],
    b_opacity_depth: &[[f32; 2]; BATCH],
    b_color: &[[f32; 3]; BATCH],
) -> SplatView<f32> {
    let xy = b_xy[slot];
    let od = b_opacity_depth[slot];
    SplatView { x: xy[0], y: xy[1], depth: od[1], conic: b_conic[slot], opacity: od[0], color: b_color[slot] }
}

/// The tile whose list the workgroup rasterizer `group` walks: its 16 × 16 block's
/// (a tile of 32 is 2 × 2 blocks; the engine records these kernels for tiles of 16
/// and 32 only).
#[inline]
fn block_tile(group: UVec3, frame: &FrameParams) -> usize {
    let per = frame.tile_size / RASTER_BLOCK;
    let per = if per == 0 { 1 } else { per };
    ((group.y / per) * frame.tiles_x + group.x / per) as usize
}

/// One workgroup per 16 × 16 block of a tile, one invocation per pixel: blends the
/// tile's splats front to back, a batch at a time, until every pixel of the block is
/// saturated.
macro_rules! rasterize_fwd_entry {
    ($name:ident, $splat:ty, $(#[$attr:meta])*) => {
        $(#[$attr])*
        #[allow(clippy::too_many_arguments)]
        #[spirv(compute(threads(16, 16)))]
        pub fn $name(
            #[spirv(workgroup_id)] group: UVec3,
            #[spirv(local_invocation_id)] local: UVec3,
            #[spirv(local_invocation_index)] lid: u32,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[$splat],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] rgb: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] alpha: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] depth: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] contributors: &mut [u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] transmittance: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] blended: &mut [u32],
            #[spirv(workgroup)] b_xy: &mut [[f32; 2]; BATCH],
            #[spirv(workgroup)] b_conic: &mut [[f32; 3]; BATCH],
            #[spirv(workgroup)] b_opacity_depth: &mut [[f32; 2]; BATCH],
            #[spirv(workgroup)] b_color: &mut [[f32; 3]; BATCH],
            #[spirv(workgroup)] done_count: &mut [u32; 1],
        ) {
            let px = group.x * RASTER_BLOCK + local.x;
            let py = group.y * RASTER_BLOCK + local.y;
            let inside = px < frame.width && py < frame.height;
            let cfg = BlendSettings::<f32>::from_frame(frame);
            let t = block_tile(group, frame);
            let start = ranges[2 * t];
            let end = ranges[2 * t + 1];
            let (fx, fy) = (px as f32 + 0.5, py as f32 + 0.5);
            let mut state = PixelFwd::<f32>::new();
            state.done = !inside;
            let slot = lid as usize;
            let mut base = start;
            // Uniform loop: `base`, `end` and the vote are the same for the whole workgroup.
            while base < end {
                let k = base + lid;
                if k < end {
                    let s = splats[isect_values[k as usize] as usize];
                    load_batch_slot(slot, &s.raster_view(), b_xy, b_conic, b_opacity_depth, b_color);
                }
                if lid == 0 {
                    done_count[0] = 0;
                }
                barrier();
                let count = if end - base < BATCH as u32 { end - base } else { BATCH as u32 };
                let mut j = 0u32;
                while j < count && !state.done {
                    // UNROLL splats per iteration: llvmpipe caps the loop iterations of an
                    // invocation at 65,535, and a tile's list can hold ~10^5 splats.
                    let mut u = 0;
                    unroll!(u, {
                        if j + u < count && !state.done {
                            let s = batch_view((j + u) as usize, b_xy, b_conic, b_opacity_depth, b_color);
                            state.blend(&s, base - start + j + u, fx, fy, &cfg);
                        }
                    });
                    j += UNROLL;
                }
                if state.done {
                    atomics::add_u32_workgroup(&mut done_count[0], 1);
                }
                barrier();
                let all_done = done_count[0] == BATCH as u32;
                // Everyone has read the batch and the vote before they are overwritten.
                barrier();
                if all_done {
                    break;
                }
                base += count;
            }
            if !inside {
                return;
            }
            let p = (py * frame.width + px) as usize;
            let c = state.rgb(frame.background);
            rgb[3 * p] = c[0];
            rgb[3 * p + 1] = c[1];
            rgb[3 * p + 2] = c[2];
            alpha[p] = 1.0 - state.transmittance;
            depth[p] = state.depth;
            contributors[p] = state.contributors;
            transmittance[p] = state.transmittance;
            blended[p] = state.blended;
        }
    };
}
rasterize_fwd_entry!(rasterize_fwd, ProjectedSplat, #[doc = "The f32 splats' kernel (see the macro)."]);
rasterize_fwd_entry!(rasterize_fwd_half, HalfSplat, #[doc = "[`rasterize_fwd`] reading [`HalfSplat`]s (`RenderSettings::half_splats`)."]);

/// The fused rasterizer (`ops::splat::fused`): one walk of each tile's depth-sorted
/// list of every cloud's splats, blending each into the base, over and matte states
/// its mask (`masks`, per Gaussian) names (`drape_shared::splat::raster::FusedPixel`);
/// writes the base image over the frame's background, the over pass's image and alpha
/// over black, and the matte (3 channels, over black) for the composite, and for the
/// backward each state's final transmittance and end in the merged list (3 per pixel).
macro_rules! rasterize_fused_fwd_entry {
    ($name:ident, $splat:ty, $(#[$attr:meta])*) => {
        $(#[$attr])*
        #[allow(clippy::too_many_arguments)]
        #[spirv(compute(threads(16, 16)))]
        pub fn $name(
            #[spirv(workgroup_id)] group: UVec3,
            #[spirv(local_invocation_id)] local: UVec3,
            #[spirv(local_invocation_index)] lid: u32,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[$splat],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] masks: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] base_rgb: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] over_rgb: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] over_alpha: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] matte_rgb: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] transmittances: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 10)] ends: &mut [u32],
            #[spirv(workgroup)] b_xy: &mut [[f32; 2]; BATCH],
            #[spirv(workgroup)] b_conic: &mut [[f32; 3]; BATCH],
            #[spirv(workgroup)] b_opacity_depth: &mut [[f32; 2]; BATCH],
            #[spirv(workgroup)] b_color: &mut [[f32; 3]; BATCH],
            #[spirv(workgroup)] b_mask: &mut [u32; BATCH],
            #[spirv(workgroup)] done_count: &mut [u32; 1],
        ) {
            let px = group.x * RASTER_BLOCK + local.x;
            let py = group.y * RASTER_BLOCK + local.y;
            let inside = px < frame.width && py < frame.height;
            let cfg = BlendSettings::<f32>::from_frame(frame);
            let t = block_tile(group, frame);
            let start = ranges[2 * t];
            let end = ranges[2 * t + 1];
            let (fx, fy) = (px as f32 + 0.5, py as f32 + 0.5);
            let mut state = FusedPixel::<f32>::new();
            let mut done = !inside;
            let slot = lid as usize;
            let mut base = start;
            // Uniform loop, as in rasterize_fwd.
            while base < end {
                let k = base + lid;
                if k < end {
                    let g = isect_values[k as usize];
                    let s = splats[g as usize];
                    load_batch_slot(slot, &s.raster_view(), b_xy, b_conic, b_opacity_depth, b_color);
                    b_mask[slot] = masks[g as usize];
                }
                if lid == 0 {
                    done_count[0] = 0;
                }
                barrier();
                let count = if end - base < BATCH as u32 { end - base } else { BATCH as u32 };
                let mut j = 0u32;
                while j < count && !done {
                    let mut u = 0;
                    unroll!(u, {
                        if j + u < count && !done {
                            let slot = (j + u) as usize;
                            let s = batch_view(slot, b_xy, b_conic, b_opacity_depth, b_color);
                            state.blend(&s, b_mask[slot], base - start + j + u, fx, fy, &cfg);
                            done = state.done();
                        }
                    });
                    j += UNROLL;
                }
                if done {
                    atomics::add_u32_workgroup(&mut done_count[0], 1);
                }
                barrier();
                let all_done = done_count[0] == BATCH as u32;
                barrier();
                if all_done {
                    break;
                }
                base += count;
            }
            if !inside {
                return;
            }
            let p = (py * frame.width + px) as usize;
            store_pixel_fused(p, &state, frame, base_rgb, over_rgb, over_alpha, matte_rgb, transmittances, ends);
        }
    };
}
rasterize_fused_fwd_entry!(rasterize_fused_fwd, ProjectedSplat, #[doc = "The f32 splats' kernel (see the macro)."]);
rasterize_fused_fwd_entry!(rasterize_fused_fwd_half, HalfSplat, #[doc = "[`rasterize_fused_fwd`] reading [`HalfSplat`]s (`RenderSettings::half_splats`)."]);

/// Writes one pixel of the fused rasterizer's outputs (both variants).
#[allow(clippy::too_many_arguments)]
#[inline]
fn store_pixel_fused(
    p: usize,
    state: &FusedPixel<f32>,
    frame: &FrameParams,
    base_rgb: &mut [f32],
    over_rgb: &mut [f32],
    over_alpha: &mut [f32],
    matte_rgb: &mut [f32],
    transmittances: &mut [f32],
    ends: &mut [u32],
) {
    let c = state.base.rgb(frame.background);
    base_rgb[3 * p] = c[0];
    base_rgb[3 * p + 1] = c[1];
    base_rgb[3 * p + 2] = c[2];
    over_rgb[3 * p] = state.over.color[0];
    over_rgb[3 * p + 1] = state.over.color[1];
    over_rgb[3 * p + 2] = state.over.color[2];
    over_alpha[p] = 1.0 - state.over.transmittance;
    matte_rgb[3 * p] = state.matte.color[0];
    matte_rgb[3 * p + 1] = state.matte.color[1];
    matte_rgb[3 * p + 2] = state.matte.color[2];
    let t = state.transmittances();
    let e = state.ends();
    transmittances[3 * p] = t[0];
    transmittances[3 * p + 1] = t[1];
    transmittances[3 * p + 2] = t[2];
    ends[3 * p] = e[0];
    ends[3 * p + 1] = e[1];
    ends[3 * p + 2] = e[2];
}

/// The backward rasterizer: one workgroup per 16 × 16 block, one invocation per pixel, walking
/// the tile's batches back to front from the last splat any pixel blended, each pixel
/// skipping what lies behind its own last one; `$accumulate(grads, index, value)` adds
/// into the per-splat gradients (float atomics or a compare-and-swap loop).
macro_rules! rasterize_bwd_entry {
    ($name:ident, $grad_ty:ty, $accumulate:path, $($attr:meta),*) => {
        $(#[$attr])*
        #[allow(clippy::too_many_arguments)]
        #[spirv(compute(threads(16, 16)))]
        pub fn $name(
            #[spirv(workgroup_id)] group: UVec3,
            #[spirv(local_invocation_id)] local: UVec3,
            #[spirv(local_invocation_index)] lid: u32,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[ProjectedSplat],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] contributors: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] transmittance: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] grad_rgb: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] grad_alpha: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] grad_depth: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] splat_grads: &mut [$grad_ty],
            #[spirv(workgroup)] b_xy: &mut [[f32; 2]; BATCH],
            #[spirv(workgroup)] b_conic: &mut [[f32; 3]; BATCH],
            #[spirv(workgroup)] b_opacity_depth: &mut [[f32; 2]; BATCH],
            #[spirv(workgroup)] b_color: &mut [[f32; 3]; BATCH],
            #[spirv(workgroup)] b_id: &mut [u32; BATCH],
            #[spirv(workgroup)] max_contributors: &mut [u32; 1],
        ) {
            let px = group.x * RASTER_BLOCK + local.x;
            let py = group.y * RASTER_BLOCK + local.y;
            let inside = px < frame.width && py < frame.height;
            let cfg = BlendSettings::<f32>::from_frame(frame);
            let t = block_tile(group, frame);
            let start = ranges[2 * t];
            let p = if inside { (py * frame.width + px) as usize } else { 0 };
            let (fx, fy) = (px as f32 + 0.5, py as f32 + 0.5);
            let mine = if inside { contributors[p] } else { 0 };
            let mut state = PixelBwd::<f32>::new(
                if inside { transmittance[p] } else { 1.0 },
                frame.background,
                if inside { [grad_rgb[3 * p], grad_rgb[3 * p + 1], grad_rgb[3 * p + 2]] } else { [0.0; 3] },
                if inside { grad_alpha[p] } else { 0.0 },
                if inside { grad_depth[p] } else { 0.0 },
            );
            if lid == 0 {
                max_contributors[0] = 0;
            }
            barrier();
            atomics::max_u32_workgroup(&mut max_contributors[0], mine);
            barrier();
            let slot = lid as usize;
            let mut batch_end = start + max_contributors[0];
            // Uniform loop: the bounds are the same for the whole workgroup.
            while batch_end > start {
                let batch_start = if batch_end - start > BATCH as u32 { batch_end - BATCH as u32 } else { start };
                let k = batch_start + lid;
                if k < batch_end {
                    let id = isect_values[k as usize];
                    b_id[slot] = id;
                    load_batch_slot(slot, &splats[id as usize].view(), b_xy, b_conic, b_opacity_depth, b_color);
                }
                barrier();
                // Back to front, UNROLL splats per iteration (see the forward pass).
                let mut top = batch_end - batch_start;
                while top > 0 {
                    let mut u = 0;
                    unroll!(u, {
                        if u < top {
                            let j = top - 1 - u;
                            let index = batch_start + j;
                            if index < start + mine {
                                let s = batch_view(j as usize, b_xy, b_conic, b_opacity_depth, b_color);
                                if let Some(grad) = state.step(&s, fx, fy, &cfg) {
                                    let base = b_id[j as usize] as usize * SPLAT_GRAD_FLOATS;
                                    let v = grad.to_array();
                                    $accumulate(splat_grads, base, v[0]);
                                    $accumulate(splat_grads, base + 1, v[1]);
                                    $accumulate(splat_grads, base + 2, v[2]);
                                    $accumulate(splat_grads, base + 3, v[3]);
                                    $accumulate(splat_grads, base + 4, v[4]);
                                    $accumulate(splat_grads, base + 5, v[5]);
                                    $accumulate(splat_grads, base + 6, v[6]);
                                    $accumulate(splat_grads, base + 7, v[7]);
                                    $accumulate(splat_grads, base + 8, v[8]);
                                    $accumulate(splat_grads, base + 9, v[9]);
                                }
                            }
                        }
                    });
                    top = if top > UNROLL { top - UNROLL } else { 0 };
                }
                // Everyone is done with the batch before it is overwritten.
                barrier();
                batch_end = batch_start;
            }
        }
    };
}

#[cfg(feature = "float-atomics")]
rasterize_bwd_entry!(rasterize_bwd_atomic, f32, atomics::add_f32, doc = "Backward rasterizer with float atomics (needs shaderBufferFloat32AtomicAdd).");
rasterize_bwd_entry!(rasterize_bwd_cas, u32, atomics::add_f32_cas, doc = "Backward rasterizer with compare-and-swap loops on the bits of f32 (any device).");
// One line per entry: the kernel list test (`tests/tests/engine/runtime.rs`) reads the name here.
rasterize_bwd_entry!(rasterize_bwd_fixed, u32, atomics::add_fixed, doc = "Deterministic backward rasterizer: per-splat gradients in 64-bit fixed point (`fixed_point::resolve` turns them into f32).");

/// The fused rasterizer's backward (`ops::splat::fused`): one workgroup per 16 × 16 block, one
/// invocation per pixel, walking the merged list back to front from the furthest end
/// any pixel's states reached; each pixel runs its three states' backward walks
/// (`drape_shared::splat::raster::FusedPixelBwd`) and adds each splat the sum of what
/// they send it. Upstream: the gradients on the base rgb, the over rgb and alpha, and
/// the matte (channel 0 of 3, as the composite's backward writes it).
/// `$accumulate(grads, index, value)` adds into the per-splat gradients.
macro_rules! rasterize_fused_bwd_entry {
    ($name:ident, $grad_ty:ty, $accumulate:path, $($attr:meta),*) => {
        $(#[$attr])*
        #[allow(clippy::too_many_arguments)]
        #[spirv(compute(threads(16, 16)))]
        pub fn $name(
            #[spirv(workgroup_id)] group: UVec3,
            #[spirv(local_invocation_id)] local: UVec3,
            #[spirv(local_invocation_index)] lid: u32,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[ProjectedSplat],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] masks: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] transmittances: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] ends: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] grad_base: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] grad_over: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] grad_over_alpha: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 10)] grad_matte: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 11)] splat_grads: &mut [$grad_ty],
            #[spirv(workgroup)] b_xy: &mut [[f32; 2]; BATCH],
            #[spirv(workgroup)] b_conic: &mut [[f32; 3]; BATCH],
            #[spirv(workgroup)] b_opacity_depth: &mut [[f32; 2]; BATCH],
            #[spirv(workgroup)] b_color: &mut [[f32; 3]; BATCH],
            #[spirv(workgroup)] b_id: &mut [u32; BATCH],
            #[spirv(workgroup)] b_mask: &mut [u32; BATCH],
            #[spirv(workgroup)] max_end: &mut [u32; 1],
        ) {
            let px = group.x * RASTER_BLOCK + local.x;
            let py = group.y * RASTER_BLOCK + local.y;
            let inside = px < frame.width && py < frame.height;
            let cfg = BlendSettings::<f32>::from_frame(frame);
            let t = block_tile(group, frame);
            let start = ranges[2 * t];
            let p = if inside { (py * frame.width + px) as usize } else { 0 };
            let (fx, fy) = (px as f32 + 0.5, py as f32 + 0.5);
            let mut state = if inside {
                FusedPixelBwd::<f32>::new(
                    [transmittances[3 * p], transmittances[3 * p + 1], transmittances[3 * p + 2]],
                    [ends[3 * p], ends[3 * p + 1], ends[3 * p + 2]],
                    frame.background,
                    [grad_base[3 * p], grad_base[3 * p + 1], grad_base[3 * p + 2]],
                    [grad_over[3 * p], grad_over[3 * p + 1], grad_over[3 * p + 2]],
                    grad_over_alpha[p],
                    grad_matte[3 * p],
                )
            } else {
                FusedPixelBwd::<f32>::new([1.0; 3], [0; 3], frame.background, [0.0; 3], [0.0; 3], 0.0, 0.0)
            };
            let mine = state.end();
            if lid == 0 {
                max_end[0] = 0;
            }
            barrier();
            atomics::max_u32_workgroup(&mut max_end[0], mine);
            barrier();
            let slot = lid as usize;
            let mut batch_end = start + max_end[0];
            // Uniform loop: the bounds are the same for the whole workgroup.
            while batch_end > start {
                let batch_start = if batch_end - start > BATCH as u32 { batch_end - BATCH as u32 } else { start };
                let k = batch_start + lid;
                if k < batch_end {
                    let id = isect_values[k as usize];
                    b_id[slot] = id;
                    b_mask[slot] = masks[id as usize];
                    load_batch_slot(slot, &splats[id as usize].view(), b_xy, b_conic, b_opacity_depth, b_color);
                }
                barrier();
                // Back to front, UNROLL splats per iteration (see the forward pass).
                let mut top = batch_end - batch_start;
                while top > 0 {
                    let mut u = 0;
                    unroll!(u, {
                        if u < top {
                            let j = top - 1 - u;
                            let index = batch_start + j - start;
                            if index < mine {
                                let s = batch_view(j as usize, b_xy, b_conic, b_opacity_depth, b_color);
                                if let Some(grad) = state.step(&s, b_mask[j as usize], index, fx, fy, &cfg) {
                                    let base = b_id[j as usize] as usize * SPLAT_GRAD_FLOATS;
                                    let v = grad.to_array();
                                    $accumulate(splat_grads, base, v[0]);
                                    $accumulate(splat_grads, base + 1, v[1]);
                                    $accumulate(splat_grads, base + 2, v[2]);
                                    $accumulate(splat_grads, base + 3, v[3]);
                                    $accumulate(splat_grads, base + 4, v[4]);
                                    $accumulate(splat_grads, base + 5, v[5]);
                                    $accumulate(splat_grads, base + 6, v[6]);
                                    $accumulate(splat_grads, base + 7, v[7]);
                                    $accumulate(splat_grads, base + 8, v[8]);
                                    $accumulate(splat_grads, base + 9, v[9]);
                                }
                            }
                        }
                    });
                    top = if top > UNROLL { top - UNROLL } else { 0 };
                }
                // Everyone is done with the batch before it is overwritten.
                barrier();
                batch_end = batch_start;
            }
        }
    };
}

#[cfg(feature = "float-atomics")]
rasterize_fused_bwd_entry!(rasterize_fused_bwd_atomic, f32, atomics::add_f32, doc = "Fused backward rasterizer with float atomics (needs shaderBufferFloat32AtomicAdd).");
rasterize_fused_bwd_entry!(rasterize_fused_bwd_cas, u32, atomics::add_f32_cas, doc = "Fused backward rasterizer with compare-and-swap loops on the bits of f32 (any device).");
rasterize_fused_bwd_entry!(rasterize_fused_bwd_fixed, u32, atomics::add_fixed, doc = "Deterministic fused backward rasterizer: per-splat gradients in 64-bit fixed point.");

const _: () = assert!(SPLAT_GRAD_FLOATS == 10, "project_bwd unrolls the splat gradient's 10 floats");

/// Gradients of Gaussian `i`'s parameters from its splat's gradient. Culled Gaussians
/// get zeros.
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(256)))]
pub fn project_bwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] chunk: &ProjectChunk,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] means: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] log_scales: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] quats: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] opacity_logits: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] sh: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] splats: &[ProjectedSplat],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] splat_grads: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] grad_means: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] grad_log_scales: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 10)] grad_quats: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 11)] grad_opacity_logits: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 12)] grad_sh: &mut [f32],
) {
    let local = flat_index(id, groups);
    let index = chunk.first + local;
    if local >= chunk.len || index >= frame.count {
        return;
    }
    let i = index as usize;
    let sh_i = local as usize;
    let k_count = sh_coeffs(frame.sh_degree);
    let mut out = drape_shared::splat::project::GaussianGrad::<f32>::zero();
    if splats[i].tiles > 0 {
        let cam = Camera::<f32>::from_frame(frame);
        let g = load_gaussian(i, sh_i, frame.sh_degree, means, log_scales, quats, opacity_logits, sh);
        let base = i * SPLAT_GRAD_FLOATS;
        let mut up = [0.0f32; SPLAT_GRAD_FLOATS];
        drape_shared::each_index!(10, c => {
            up[c] = splat_grads[base + c];
        });
        out = project_bwd_math(&g, &cam, &SplatGrad::from_array(&up));
    }
    drape_shared::each_index!(3, c => {
        grad_means[3 * i + c] = out.mean[c];
        grad_log_scales[3 * i + c] = out.log_scale[c];
    });
    drape_shared::each_index!(4, c => {
        grad_quats[4 * i + c] = out.quat[c];
    });
    grad_opacity_logits[i] = out.opacity_logit;
    drape_shared::each_index!(16, k => {
        if k < k_count {
            let base = (sh_i * k_count + k) * 3;
            grad_sh[base] = out.sh[k][0];
            grad_sh[base + 1] = out.sh[k][1];
            grad_sh[base + 2] = out.sh[k][2];
        }
    });
}

/// Packs the projected splats for the half-precision rasterizers
/// (`RenderSettings::half_splats`): `half[i]` = [`HalfSplat::pack`] of splat `i`, for
/// `i < counts.count`.
#[spirv(compute(threads(256)))]
pub fn pack_splats_half(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] counts: &SplatCounts,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] splats: &[ProjectedSplat],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] half_splats: &mut [HalfSplat],
) {
    let i = flat_index(id, groups);
    if i >= counts.count {
        return;
    }
    half_splats[i as usize] = HalfSplat::pack(&splats[i as usize].view());
}

/// Densification statistics (`drape_shared::splat::densify`): one invocation per
/// Gaussian of `[p.first, p.first + p.count)` of the last render adds its frame into
/// `stats[3 (p.out_first + local) ..]`; reads the projected splats and the per-splat
/// gradients of the last backward pass.
#[spirv(compute(threads(256)))]
pub fn screen_stats(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &drape_shared::splat::densify::ScreenStatsParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] splats: &[ProjectedSplat],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splat_grads: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] stats: &mut [f32],
) {
    let local = flat_index(id, groups);
    if local >= p.count {
        return;
    }
    let i = (p.first + local) as usize;
    let o = 3 * (p.out_first + local) as usize;
    let g = i * SPLAT_GRAD_FLOATS;
    let s = drape_shared::splat::densify::accumulate([stats[o], stats[o + 1], stats[o + 2]], &splats[i], splat_grads[g], splat_grads[g + 1], p.width, p.height);
    stats[o] = s[0];
    stats[o + 1] = s[1];
    stats[o + 2] = s[2];
}

// ---------------------------------------------------------------------------------
// Subgroup rasterizers for CPU devices (lavapipe), built with `subgroup-ballot`.
//
// llvmpipe runs the 8 lanes of a subgroup as one SIMD register, compiles a load whose
// address it cannot prove uniform to a loop over the lanes, and runs a workgroup
// barrier as a switch between coroutines. The workgroup rasterizers above pay both for
// every splat: 256 invocations read each splat's 10 fields from workgroup memory, and
// each batch costs three barriers. Here a workgroup is one subgroup of 8 lanes covering
// an 8 × 4 block of a tile (8 workgroups per 16 × 16 tile, 2 per tile of 8, 32 per tile
// of 32); each lane loads one splat
// of the next 8 of the tile's list, and every lane gets each of the 8 by broadcasts
// with constant lane numbers (a register shuffle there): 4 loads per lane feed
// 8 splats × 4 pixels, and no barrier is needed. The engine records these only where
// the device is a CPU with subgroups of exactly 8 lanes, so every loop below is uniform
// (the whole subgroup runs it to the end) and every broadcast reads an active lane.
// ---------------------------------------------------------------------------------

/// Pixel rows per lane of the subgroup rasterizers (an 8 × 4 block per workgroup).
#[cfg(feature = "subgroup-ballot")]
const SG_ROWS: u32 = 4;
#[cfg(feature = "subgroup-ballot")]

/// Lane `$u`'s splat view, in every lane, for a uniform but not constant `$u`.
#[cfg(feature = "subgroup-ballot")]
macro_rules! sg_view_at {
    ($s:ident, $u:expr) => {
        SplatRows {
            a: crate::subgroup::broadcast_vec4_at($s.a, $u),
            b: crate::subgroup::broadcast_vec4_at($s.b, $u),
            c: crate::subgroup::broadcast_vec4_at($s.c, $u),
        }
        .raster_view()
    };
}

/// Lane `$u`'s [`HalfSplat`]'s view, in every lane: 6 broadcasts (the centre and the
/// four packed words), unpacked after.
#[cfg(feature = "subgroup-ballot")]
macro_rules! sg_half_at {
    ($s:ident, $u:expr) => {
        HalfSplat {
            x: crate::subgroup::broadcast_at($s.x, $u),
            y: crate::subgroup::broadcast_at($s.y, $u),
            conic_ab: crate::subgroup::broadcast_u32_at($s.conic_ab, $u),
            conic_c_opacity: crate::subgroup::broadcast_u32_at($s.conic_c_opacity, $u),
            rg: crate::subgroup::broadcast_u32_at($s.rg, $u),
            b_depth: crate::subgroup::broadcast_u32_at($s.b_depth, $u),
        }
        .raster_view()
    };
}

/// A [`ProjectedSplat`] as the f32 subgroup rasterizers bind it: its 64 bytes as four
/// `Vec4`s (`x y depth conic_a`, `conic_b conic_c opacity r`, `g b tile_x0 tile_y0`,
/// and the tile fields they do not read).
#[cfg(feature = "subgroup-ballot")]
#[derive(Clone, Copy)]
#[repr(C)]
pub struct SplatQuads {
    a: Vec4,
    b: Vec4,
    c: Vec4,
    d: Vec4,
}

/// The three `Vec4`s of a [`SplatQuads`] that hold the splat's view.
///
/// Why not the ten fields: on llvmpipe each storage-buffer load at a per-lane address is
/// one loop over the 8 lanes, whatever its width, so ten `f32` loads cost ten loops and
/// three `Vec4` loads three. The compiler keeps a `Vec4` load whole only where the vector
/// is used whole (taken apart field by field, `spirv-opt` makes it four scalar loads, as
/// `spirv-dis` showed); here the whole vectors go through the subgroup shuffles
/// ([`sg_view_at`]), which is what keeps them.
#[cfg(feature = "subgroup-ballot")]
#[derive(Clone, Copy)]
struct SplatRows {
    a: Vec4,
    b: Vec4,
    c: Vec4,
}

#[cfg(feature = "subgroup-ballot")]
impl RasterSplat for SplatRows {
    #[inline]
    fn raster_view(&self) -> SplatView<f32> {
        SplatView {
            x: self.a.x,
            y: self.a.y,
            depth: self.a.z,
            conic: [self.a.w, self.b.x, self.b.y],
            opacity: self.b.z,
            color: [self.b.w, self.c.x, self.c.y],
        }
    }
}

/// A lane's splat as the f32 subgroup rasterizers keep it: three `Vec4` loads.
#[cfg(feature = "subgroup-ballot")]
macro_rules! sg_load_view {
    ($e:expr) => {{
        let quads = &$e;
        SplatRows { a: quads.a, b: quads.b, c: quads.c }
    }};
}

/// A lane's splat as the half-precision subgroup rasterizers keep it: packed.
#[cfg(feature = "subgroup-ballot")]
macro_rules! sg_load_raw {
    ($e:expr) => {
        $e
    };
}

/// Repeats `$m!(u, ...)` for u = 0..8 (constant lane numbers for the broadcasts).
#[cfg(feature = "subgroup-ballot")]
macro_rules! sg_lanes {
    ($m:ident $(, $arg:tt)*) => {
        $m!(0 $(, $arg)*); $m!(1 $(, $arg)*); $m!(2 $(, $arg)*); $m!(3 $(, $arg)*);
        $m!(4 $(, $arg)*); $m!(5 $(, $arg)*); $m!(6 $(, $arg)*); $m!(7 $(, $arg)*);
    };
}

/// Longest walk (splats of a tile's list) the subgroup rasterizers take sparsely: a
/// round of 8 splats, then a loop over those that may reach the block
/// ([`may_touch_rect`]), so only those cost a blend (llvmpipe runs both sides of every
/// `if`; only a loop skips work). llvmpipe stops an invocation's loops after 65,535
/// iterations in all, and a sparse walk of `n` splats may spend `n / 8 + n`; longer
/// walks go densely, every lane's splat by constant lane numbers, one iteration per
/// round (`8 × 65,535` splats). The choice is made once per walk, outside the loops,
/// so the branch not taken costs one masked round.
#[cfg(feature = "subgroup-ballot")]
const SPARSE_MAX_WALK: u32 = 56_000;

/// [`SPARSE_MAX_WALK`] for the compare-and-swap backwards, where each of a lane's 10 adds
/// a round is a loop of at least one iteration (taken or not: llvmpipe runs a loop in an
/// untaken branch once): a sparse walk of `n` may spend `11 n / 8 + n`.
#[cfg(feature = "subgroup-ballot")]
const SPARSE_MAX_WALK_CAS: u32 = 24_000;

/// Where one lane of a subgroup rasterizer works: its tile, its pixel column and the 4
/// rows of its 8 × 4 block (workgroup `group` of the `[T/8 · tiles_x, T/4 · tiles_y]`
/// grid for tiles of side T).
#[cfg(feature = "subgroup-ballot")]
struct Block {
    tile: usize,
    px: u32,
    /// The block's first row.
    py: u32,
    fx: f32,
    fy: [f32; 4],
    /// Whether the lane's pixel of each row is inside the image.
    inside: [bool; 4],
    /// The block's first and last pixel centres (for [`may_touch_rect`]).
    lo: [f32; 2],
    hi: [f32; 2],
}

#[cfg(feature = "subgroup-ballot")]
impl Block {
    #[inline]
    fn new(group: UVec3, lane: u32, frame: &FrameParams) -> Self {
        let px = group.x * 8 + lane;
        let py = group.y * SG_ROWS;
        let x_in = px < frame.width;
        Block {
            tile: ((group.y / (frame.tile_size / SG_ROWS)) * frame.tiles_x + group.x / (frame.tile_size / 8)) as usize,
            px,
            py,
            fx: px as f32 + 0.5,
            fy: [py as f32 + 0.5, py as f32 + 1.5, py as f32 + 2.5, py as f32 + 3.5],
            inside: [x_in && py < frame.height, x_in && py + 1 < frame.height, x_in && py + 2 < frame.height, x_in && py + 3 < frame.height],
            lo: [(group.x * 8) as f32 + 0.5, py as f32 + 0.5],
            hi: [(group.x * 8) as f32 + 7.5, py as f32 + 3.5],
        }
    }

    /// The pixel index of row `r` (only meaningful where `inside[r]`).
    #[inline]
    fn pixel(&self, r: u32, frame: &FrameParams) -> usize {
        ((self.py + r) * frame.width + self.px) as usize
    }
}

/// Writes one pixel of the forward outputs.
#[cfg(feature = "subgroup-ballot")]
#[allow(clippy::too_many_arguments)]
#[inline]
fn store_pixel_fwd(
    p: usize,
    state: &PixelFwd<f32>,
    frame: &FrameParams,
    rgb: &mut [f32],
    alpha: &mut [f32],
    depth: &mut [f32],
    contributors: &mut [u32],
    transmittance: &mut [f32],
    blended: &mut [u32],
) {
    let c = state.rgb(frame.background);
    rgb[3 * p] = c[0];
    rgb[3 * p + 1] = c[1];
    rgb[3 * p + 2] = c[2];
    alpha[p] = 1.0 - state.transmittance;
    depth[p] = state.depth;
    contributors[p] = state.contributors;
    transmittance[p] = state.transmittance;
    blended[p] = state.blended;
}

/// [`rasterize_fwd`] for CPU devices with subgroups of 8 (see the section header):
/// the same blending of the same splats in the same order per pixel, so the same
/// outputs. Dispatched on `[T/8 · tiles_x, T/4 · tiles_y]` workgroups of 8 (tiles of side T).
#[cfg(feature = "subgroup-ballot")]
macro_rules! rasterize_fwd_subgroup_entry {
    ($name:ident, $splat:ty, $load:ident, $at:ident, $(#[$attr:meta])*) => {
        $(#[$attr])*
        #[allow(clippy::too_many_arguments)]
        #[spirv(compute(threads(8)))]
        pub fn $name(
            #[spirv(workgroup_id)] group: UVec3,
            #[spirv(local_invocation_index)] lane: u32,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[$splat],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] rgb: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] alpha: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] depth: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] contributors: &mut [u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] transmittance: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] blended: &mut [u32],
        ) {
            let b = Block::new(group, lane, frame);
            let (fx, fy) = (b.fx, b.fy);
            let cfg = BlendSettings::<f32>::from_frame(frame);
            let start = ranges[2 * b.tile];
            let end = ranges[2 * b.tile + 1];
            let mut s0 = PixelFwd::<f32>::new();
            let mut s1 = PixelFwd::<f32>::new();
            let mut s2 = PixelFwd::<f32>::new();
            let mut s3 = PixelFwd::<f32>::new();
            s0.done = !b.inside[0];
            s1.done = !b.inside[1];
            s2.done = !b.inside[2];
            s3.done = !b.inside[3];
            // Blends lane `u`'s splat of the round at `base` into the 4 pixels.
            macro_rules! blend {
                ($mine:ident, $base:ident, $u:expr) => {{
                    let u = $u;
                    let v = $at!($mine, u);
                    let index = $base - start + u;
                    if !s0.done {
                        s0.blend(&v, index, fx, fy[0], &cfg);
                    }
                    if !s1.done {
                        s1.blend(&v, index, fx, fy[1], &cfg);
                    }
                    if !s2.done {
                        s2.blend(&v, index, fx, fy[2], &cfg);
                    }
                    if !s3.done {
                        s3.blend(&v, index, fx, fy[3], &cfg);
                    }
                }};
            }
            // Uniform loops (start, end and the votes are the same in every lane).
            let mut base = start;
            if end - start <= SPARSE_MAX_WALK {
                while base < end {
                    // Lanes past the list's end load its first splat of this round, never used.
                    let k = if base + lane < end { base + lane } else { base };
                    let mine = $load!(splats[isect_values[k as usize] as usize]);
                    // The round's splats that may reach the block, in list order.
                    let mut todo = crate::subgroup::ballot8(base + lane < end && may_touch_rect(&mine.raster_view(), b.lo, b.hi, &cfg));
                    while todo != 0 {
                        let u = todo.trailing_zeros();
                        todo &= todo - 1;
                        blend!(mine, base, u);
                    }
                    if crate::subgroup::all8(s0.done && s1.done && s2.done && s3.done) {
                        break;
                    }
                    base += 8;
                }
            } else {
                while base < end {
                    let k = if base + lane < end { base + lane } else { base };
                    let mine = $load!(splats[isect_values[k as usize] as usize]);
                    macro_rules! lane {
                        ($u:literal) => {
                            if base + $u < end {
                                blend!(mine, base, $u);
                            }
                        };
                    }
                    sg_lanes!(lane);
                    if crate::subgroup::all8(s0.done && s1.done && s2.done && s3.done) {
                        break;
                    }
                    base += 8;
                }
            }
            if b.inside[0] {
                store_pixel_fwd(b.pixel(0, frame), &s0, frame, rgb, alpha, depth, contributors, transmittance, blended);
            }
            if b.inside[1] {
                store_pixel_fwd(b.pixel(1, frame), &s1, frame, rgb, alpha, depth, contributors, transmittance, blended);
            }
            if b.inside[2] {
                store_pixel_fwd(b.pixel(2, frame), &s2, frame, rgb, alpha, depth, contributors, transmittance, blended);
            }
            if b.inside[3] {
                store_pixel_fwd(b.pixel(3, frame), &s3, frame, rgb, alpha, depth, contributors, transmittance, blended);
            }
        }
    };
}
#[cfg(feature = "subgroup-ballot")]
rasterize_fwd_subgroup_entry!(rasterize_fwd_subgroup, SplatQuads, sg_load_view, sg_view_at, #[doc = "The f32 splats' kernel (see the macro)."]);
#[cfg(feature = "subgroup-ballot")]
rasterize_fwd_subgroup_entry!(rasterize_fwd_subgroup_half, HalfSplat, sg_load_raw, sg_half_at, #[doc = "[`rasterize_fwd_subgroup`] reading [`HalfSplat`]s (`RenderSettings::half_splats`): 6 words shuffled a splat where the f32 kernel shuffles 12 (three `Vec4`s)."]);

/// [`rasterize_fused_fwd`] for CPU devices with subgroups of 8 (see the section
/// header), on `[T/8 · tiles_x, T/4 · tiles_y]` workgroups of 8 (tiles of side T).
#[cfg(feature = "subgroup-ballot")]
macro_rules! rasterize_fused_fwd_subgroup_entry {
    ($name:ident, $splat:ty, $load:ident, $at:ident, $(#[$attr:meta])*) => {
        $(#[$attr])*
        #[allow(clippy::too_many_arguments)]
        #[spirv(compute(threads(8)))]
        pub fn $name(
            #[spirv(workgroup_id)] group: UVec3,
            #[spirv(local_invocation_index)] lane: u32,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[$splat],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] masks: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] base_rgb: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] over_rgb: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] over_alpha: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] matte_rgb: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] transmittances: &mut [f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 10)] ends: &mut [u32],
        ) {
            let b = Block::new(group, lane, frame);
            let (fx, fy) = (b.fx, b.fy);
            let cfg = BlendSettings::<f32>::from_frame(frame);
            let start = ranges[2 * b.tile];
            let end = ranges[2 * b.tile + 1];
            let mut s0 = FusedPixel::<f32>::new();
            let mut s1 = FusedPixel::<f32>::new();
            let mut s2 = FusedPixel::<f32>::new();
            let mut s3 = FusedPixel::<f32>::new();
            let mut d0 = !b.inside[0];
            let mut d1 = !b.inside[1];
            let mut d2 = !b.inside[2];
            let mut d3 = !b.inside[3];
            // Blends lane `u`'s splat of the round at `base` into the 4 pixels' states.
            macro_rules! blend {
                ($mine:ident, $mine_mask:ident, $base:ident, $u:expr) => {{
                    let u = $u;
                    let v = $at!($mine, u);
                    let mask = crate::subgroup::broadcast_u32_at($mine_mask, u);
                    let index = $base - start + u;
                    if !d0 {
                        s0.blend(&v, mask, index, fx, fy[0], &cfg);
                        d0 = s0.done();
                    }
                    if !d1 {
                        s1.blend(&v, mask, index, fx, fy[1], &cfg);
                        d1 = s1.done();
                    }
                    if !d2 {
                        s2.blend(&v, mask, index, fx, fy[2], &cfg);
                        d2 = s2.done();
                    }
                    if !d3 {
                        s3.blend(&v, mask, index, fx, fy[3], &cfg);
                        d3 = s3.done();
                    }
                }};
            }
            // Uniform loops, sparse or dense as in rasterize_fwd_subgroup.
            let mut base = start;
            if end - start <= SPARSE_MAX_WALK {
                while base < end {
                    let k = if base + lane < end { base + lane } else { base };
                    let g = isect_values[k as usize] as usize;
                    let mine = $load!(splats[g]);
                    let mine_mask = masks[g];
                    let mut todo = crate::subgroup::ballot8(base + lane < end && may_touch_rect(&mine.raster_view(), b.lo, b.hi, &cfg));
                    while todo != 0 {
                        let u = todo.trailing_zeros();
                        todo &= todo - 1;
                        blend!(mine, mine_mask, base, u);
                    }
                    if crate::subgroup::all8(d0 && d1 && d2 && d3) {
                        break;
                    }
                    base += 8;
                }
            } else {
                while base < end {
                    let k = if base + lane < end { base + lane } else { base };
                    let g = isect_values[k as usize] as usize;
                    let mine = $load!(splats[g]);
                    let mine_mask = masks[g];
                    macro_rules! lane {
                        ($u:literal) => {
                            if base + $u < end {
                                blend!(mine, mine_mask, base, $u);
                            }
                        };
                    }
                    sg_lanes!(lane);
                    if crate::subgroup::all8(d0 && d1 && d2 && d3) {
                        break;
                    }
                    base += 8;
                }
            }
            if b.inside[0] {
                store_pixel_fused(b.pixel(0, frame), &s0, frame, base_rgb, over_rgb, over_alpha, matte_rgb, transmittances, ends);
            }
            if b.inside[1] {
                store_pixel_fused(b.pixel(1, frame), &s1, frame, base_rgb, over_rgb, over_alpha, matte_rgb, transmittances, ends);
            }
            if b.inside[2] {
                store_pixel_fused(b.pixel(2, frame), &s2, frame, base_rgb, over_rgb, over_alpha, matte_rgb, transmittances, ends);
            }
            if b.inside[3] {
                store_pixel_fused(b.pixel(3, frame), &s3, frame, base_rgb, over_rgb, over_alpha, matte_rgb, transmittances, ends);
            }
        }
    };
}
#[cfg(feature = "subgroup-ballot")]
rasterize_fused_fwd_subgroup_entry!(rasterize_fused_fwd_subgroup, SplatQuads, sg_load_view, sg_view_at, #[doc = "The f32 splats' kernel (see the macro)."]);
#[cfg(feature = "subgroup-ballot")]
rasterize_fused_fwd_subgroup_entry!(rasterize_fused_fwd_subgroup_half, HalfSplat, sg_load_raw, sg_half_at, #[doc = "[`rasterize_fused_fwd_subgroup`] reading [`HalfSplat`]s (`RenderSettings::half_splats`): 6 words shuffled a splat where the f32 kernel shuffles 12 (three `Vec4`s)."]);

/// One pixel's backward state for [`rasterize_bwd_subgroup_entry`]: its state, and the
/// number of its tile's splats it blended up to its last (0 outside the image).
#[cfg(feature = "subgroup-ballot")]
#[allow(clippy::too_many_arguments)]
#[inline]
fn load_pixel_bwd(
    b: &Block,
    r: u32,
    frame: &FrameParams,
    contributors: &[u32],
    transmittance: &[f32],
    grad_rgb: &[f32],
    grad_alpha: &[f32],
    grad_depth: &[f32],
) -> (PixelBwd<f32>, u32) {
    if !b.inside[r as usize] {
        return (PixelBwd::new(1.0, frame.background, [0.0; 3], 0.0, 0.0), 0);
    }
    let p = b.pixel(r, frame);
    let state = PixelBwd::new(
        transmittance[p],
        frame.background,
        [grad_rgb[3 * p], grad_rgb[3 * p + 1], grad_rgb[3 * p + 2]],
        grad_alpha[p],
        grad_depth[p],
    );
    (state, contributors[p])
}

/// The backward rasterizer for CPU devices with subgroups of 8 (see the section
/// header): each workgroup walks its 8 × 4 block's splats back to front, 8 at a time
/// (lane `l` loads the `l`-th from the back), each pixel skipping what lies behind its
/// own last splat; per splat the lanes' gradients (4 pixels each) are summed across
/// the subgroup by broadcasts and the splat's lane adds the sum once, so a splat costs
/// 10 atomics per block instead of 10 per pixel. `$accumulate(grads, index, value)`
/// adds into the per-splat gradients (float atomics, compare-and-swap on f32 bits, or
/// fixed point).
#[cfg(feature = "subgroup-ballot")]
macro_rules! rasterize_bwd_subgroup_entry {
    ($name:ident, $grad_ty:ty, $accumulate:path, $sparse_max:expr, $($attr:meta),*) => {
        $(#[$attr])*
        #[allow(clippy::too_many_arguments)]
        #[spirv(compute(threads(8)))]
        pub fn $name(
            #[spirv(workgroup_id)] group: UVec3,
            #[spirv(local_invocation_index)] lane: u32,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[SplatQuads],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] contributors: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] transmittance: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] grad_rgb: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] grad_alpha: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] grad_depth: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] splat_grads: &mut [$grad_ty],
        ) {
            let b = Block::new(group, lane, frame);
            let (fx, fy) = (b.fx, b.fy);
            let cfg = BlendSettings::<f32>::from_frame(frame);
            let start = ranges[2 * b.tile];
            let (mut s0, m0) = load_pixel_bwd(&b, 0, frame, contributors, transmittance, grad_rgb, grad_alpha, grad_depth);
            let (mut s1, m1) = load_pixel_bwd(&b, 1, frame, contributors, transmittance, grad_rgb, grad_alpha, grad_depth);
            let (mut s2, m2) = load_pixel_bwd(&b, 2, frame, contributors, transmittance, grad_rgb, grad_alpha, grad_depth);
            let (mut s3, m3) = load_pixel_bwd(&b, 3, frame, contributors, transmittance, grad_rgb, grad_alpha, grad_depth);
            let last = crate::subgroup::max8_u32(m0.max(m1).max(m2.max(m3)));
            // Lane `u`'s splat of the round ending at `top`: its gradient from the 4
            // pixels, summed over the block (into `sums` of lane `u`).
            macro_rules! splat {
                ($mine:ident, $top:ident, $sums:ident, $u:expr) => {{
                    let u = $u;
                    let v = sg_view_at!($mine, u);
                    let at = $top - 1 - u;
                    let mut g = [0.0f32; SPLAT_GRAD_FLOATS];
                    macro_rules! pixel {
                        ($s:ident, $m:ident, $r:literal) => {
                            if at < $m {
                                if let Some(grad) = $s.step(&v, fx, fy[$r], &cfg) {
                                    let a = grad.to_array();
                                    g[0] += a[0]; g[1] += a[1]; g[2] += a[2]; g[3] += a[3]; g[4] += a[4];
                                    g[5] += a[5]; g[6] += a[6]; g[7] += a[7]; g[8] += a[8]; g[9] += a[9];
                                }
                            }
                        };
                    }
                    pixel!(s0, m0, 0);
                    pixel!(s1, m1, 1);
                    pixel!(s2, m2, 2);
                    pixel!(s3, m3, 3);
                    // No vote on whether any pixel was hit: llvmpipe would run
                    // the sums anyway (it predicates every `if`), and a zero sum
                    // adds nothing below.
                    let total = [
                        crate::subgroup::sum8(g[0]), crate::subgroup::sum8(g[1]),
                        crate::subgroup::sum8(g[2]), crate::subgroup::sum8(g[3]),
                        crate::subgroup::sum8(g[4]), crate::subgroup::sum8(g[5]),
                        crate::subgroup::sum8(g[6]), crate::subgroup::sum8(g[7]),
                        crate::subgroup::sum8(g[8]), crate::subgroup::sum8(g[9]),
                    ];
                    if lane == u {
                        $sums = total;
                    }
                }};
            }
            // The round's splats that may reach the block, back to front (lowest lane
            // first); the others send nothing.
            macro_rules! sparse {
                ($mine:ident, $top:ident, $len:ident, $sums:ident) => {
                    let mut todo = crate::subgroup::ballot8(lane < $len && may_touch_rect(&$mine.raster_view(), b.lo, b.hi, &cfg));
                    while todo != 0 {
                        let u = todo.trailing_zeros();
                        todo &= todo - 1;
                        splat!($mine, $top, $sums, u);
                    }
                };
            }
            // Every lane's splat, by constant lane numbers.
            macro_rules! dense {
                ($mine:ident, $top:ident, $len:ident, $sums:ident) => {
                    macro_rules! lane {
                        ($u:literal) => {
                            if $u < $len {
                                splat!($mine, $top, $sums, $u);
                            }
                        };
                    }
                    sg_lanes!(lane);
                };
            }
            // The walk: `top` is the number of the tile's splats still to visit (uniform),
            // 8 a round from the back, each round visited by `$visit`.
            macro_rules! walk {
                ($visit:ident) => {
                    let mut top = last;
                    while top > 0 {
                        let len = if top < 8 { top } else { 8 };
                        // Lane l: list index top - 1 - l (lanes past the round load its first).
                        let index = if lane < len { top - 1 - lane } else { top - 1 };
                        let id = isect_values[(start + index) as usize];
                        let mine = sg_load_view!(splats[id as usize]);
                        // The subgroup's sums for this lane's splat.
                        let mut sums = [0.0f32; SPLAT_GRAD_FLOATS];
                        $visit!(mine, top, len, sums);
                        // One lane per splat adds the block's sum (the accumulators skip zeros).
                        // Written out, not looped: a loop here would spend 10 of llvmpipe's
                        // 65,535 loop iterations per round (the loop over the round's splats
                        // above already spends up to 8).
                        if lane < len {
                            let base = id as usize * SPLAT_GRAD_FLOATS;
                            $accumulate(splat_grads, base, sums[0]);
                            $accumulate(splat_grads, base + 1, sums[1]);
                            $accumulate(splat_grads, base + 2, sums[2]);
                            $accumulate(splat_grads, base + 3, sums[3]);
                            $accumulate(splat_grads, base + 4, sums[4]);
                            $accumulate(splat_grads, base + 5, sums[5]);
                            $accumulate(splat_grads, base + 6, sums[6]);
                            $accumulate(splat_grads, base + 7, sums[7]);
                            $accumulate(splat_grads, base + 8, sums[8]);
                            $accumulate(splat_grads, base + 9, sums[9]);
                        }
                        top -= len;
                    }
                };
            }
            // Sparse or dense once per walk, as the forward.
            if last <= $sparse_max {
                walk!(sparse);
            } else {
                walk!(dense);
            }
        }
    };
}

#[cfg(all(feature = "subgroup-ballot", feature = "float-atomics"))]
rasterize_bwd_subgroup_entry!(rasterize_bwd_subgroup_atomic, f32, atomics::add_f32, SPARSE_MAX_WALK, doc = "Backward rasterizer for CPU devices with subgroups of 8, float atomics.");
#[cfg(feature = "subgroup-ballot")]
rasterize_bwd_subgroup_entry!(rasterize_bwd_subgroup_cas, u32, atomics::add_f32_cas, SPARSE_MAX_WALK_CAS, doc = "Backward rasterizer for CPU devices with subgroups of 8, compare-and-swap on the bits of f32.");
#[cfg(feature = "subgroup-ballot")]
rasterize_bwd_subgroup_entry!(rasterize_bwd_subgroup_fixed, u32, atomics::add_fixed, SPARSE_MAX_WALK, doc = "Deterministic backward rasterizer for CPU devices with subgroups of 8 (64-bit fixed point).");

/// One pixel's state for [`rasterize_fused_bwd_subgroup_entry`]: its three backward
/// walks and where the furthest starts (0 outside the image).
#[cfg(feature = "subgroup-ballot")]
#[allow(clippy::too_many_arguments)]
#[inline]
fn load_pixel_fused_bwd(
    b: &Block,
    r: u32,
    frame: &FrameParams,
    transmittances: &[f32],
    ends: &[u32],
    grad_base: &[f32],
    grad_over: &[f32],
    grad_over_alpha: &[f32],
    grad_matte: &[f32],
) -> (FusedPixelBwd<f32>, u32) {
    if !b.inside[r as usize] {
        return (FusedPixelBwd::new([1.0; 3], [0; 3], frame.background, [0.0; 3], [0.0; 3], 0.0, 0.0), 0);
    }
    let p = b.pixel(r, frame);
    let state = FusedPixelBwd::new(
        [transmittances[3 * p], transmittances[3 * p + 1], transmittances[3 * p + 2]],
        [ends[3 * p], ends[3 * p + 1], ends[3 * p + 2]],
        frame.background,
        [grad_base[3 * p], grad_base[3 * p + 1], grad_base[3 * p + 2]],
        [grad_over[3 * p], grad_over[3 * p + 1], grad_over[3 * p + 2]],
        grad_over_alpha[p],
        grad_matte[3 * p],
    );
    let end = state.end();
    (state, end)
}

/// The fused backward for CPU devices with subgroups of 8: the walk of
/// [`rasterize_bwd_subgroup_entry`] (8 splats a round from the back, each lane's 4 pixels,
/// block sums by broadcasts, one lane adding each splat's sum) with each pixel's three
/// states (`FusedPixelBwd`) and each splat's layer mask broadcast beside its view.
#[cfg(feature = "subgroup-ballot")]
macro_rules! rasterize_fused_bwd_subgroup_entry {
    ($name:ident, $grad_ty:ty, $accumulate:path, $sparse_max:expr, $($attr:meta),*) => {
        $(#[$attr])*
        #[allow(clippy::too_many_arguments)]
        #[spirv(compute(threads(8)))]
        pub fn $name(
            #[spirv(workgroup_id)] group: UVec3,
            #[spirv(local_invocation_index)] lane: u32,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
            #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[SplatQuads],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] masks: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] transmittances: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] ends: &[u32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] grad_base: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] grad_over: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] grad_over_alpha: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 10)] grad_matte: &[f32],
            #[spirv(storage_buffer, descriptor_set = 0, binding = 11)] splat_grads: &mut [$grad_ty],
        ) {
            let b = Block::new(group, lane, frame);
            let (fx, fy) = (b.fx, b.fy);
            let cfg = BlendSettings::<f32>::from_frame(frame);
            let start = ranges[2 * b.tile];
            let (mut s0, m0) = load_pixel_fused_bwd(&b, 0, frame, transmittances, ends, grad_base, grad_over, grad_over_alpha, grad_matte);
            let (mut s1, m1) = load_pixel_fused_bwd(&b, 1, frame, transmittances, ends, grad_base, grad_over, grad_over_alpha, grad_matte);
            let (mut s2, m2) = load_pixel_fused_bwd(&b, 2, frame, transmittances, ends, grad_base, grad_over, grad_over_alpha, grad_matte);
            let (mut s3, m3) = load_pixel_fused_bwd(&b, 3, frame, transmittances, ends, grad_base, grad_over, grad_over_alpha, grad_matte);
            let last = crate::subgroup::max8_u32(m0.max(m1).max(m2.max(m3)));
            // Lane `u`'s splat of the round ending at `top`: its gradient from the 4
            // pixels, summed over the block (into `sums` of lane `u`).
            macro_rules! splat {
                ($mine:ident, $mine_mask:ident, $top:ident, $sums:ident, $u:expr) => {{
                    let u = $u;
                    let v = sg_view_at!($mine, u);
                    let mask = crate::subgroup::broadcast_u32_at($mine_mask, u);
                    let at = $top - 1 - u;
                    let mut g = [0.0f32; SPLAT_GRAD_FLOATS];
                    macro_rules! pixel {
                        ($s:ident, $m:ident, $r:literal) => {
                            if at < $m {
                                if let Some(grad) = $s.step(&v, mask, at, fx, fy[$r], &cfg) {
                                    let a = grad.to_array();
                                    g[0] += a[0]; g[1] += a[1]; g[2] += a[2]; g[3] += a[3]; g[4] += a[4];
                                    g[5] += a[5]; g[6] += a[6]; g[7] += a[7]; g[8] += a[8]; g[9] += a[9];
                                }
                            }
                        };
                    }
                    pixel!(s0, m0, 0);
                    pixel!(s1, m1, 1);
                    pixel!(s2, m2, 2);
                    pixel!(s3, m3, 3);
                    let total = [
                        crate::subgroup::sum8(g[0]), crate::subgroup::sum8(g[1]),
                        crate::subgroup::sum8(g[2]), crate::subgroup::sum8(g[3]),
                        crate::subgroup::sum8(g[4]), crate::subgroup::sum8(g[5]),
                        crate::subgroup::sum8(g[6]), crate::subgroup::sum8(g[7]),
                        crate::subgroup::sum8(g[8]), crate::subgroup::sum8(g[9]),
                    ];
                    if lane == u {
                        $sums = total;
                    }
                }};
            }
            // The round's splats that may reach the block, back to front (lowest lane
            // first); the others send nothing.
            macro_rules! sparse {
                ($mine:ident, $mine_mask:ident, $top:ident, $len:ident, $sums:ident) => {
                    let mut todo = crate::subgroup::ballot8(lane < $len && may_touch_rect(&$mine.raster_view(), b.lo, b.hi, &cfg));
                    while todo != 0 {
                        let u = todo.trailing_zeros();
                        todo &= todo - 1;
                        splat!($mine, $mine_mask, $top, $sums, u);
                    }
                };
            }
            // Every lane's splat, by constant lane numbers.
            macro_rules! dense {
                ($mine:ident, $mine_mask:ident, $top:ident, $len:ident, $sums:ident) => {
                    macro_rules! lane {
                        ($u:literal) => {
                            if $u < $len {
                                splat!($mine, $mine_mask, $top, $sums, $u);
                            }
                        };
                    }
                    sg_lanes!(lane);
                };
            }
            // The walk: `top` is the number of the tile's splats still to visit (uniform),
            // 8 a round from the back, each round visited by `$visit`.
            macro_rules! walk {
                ($visit:ident) => {
                    let mut top = last;
                    while top > 0 {
                        let len = if top < 8 { top } else { 8 };
                        let index = if lane < len { top - 1 - lane } else { top - 1 };
                        let id = isect_values[(start + index) as usize];
                        let mine = sg_load_view!(splats[id as usize]);
                        let mine_mask = masks[id as usize];
                        // The subgroup's sums for this lane's splat.
                        let mut sums = [0.0f32; SPLAT_GRAD_FLOATS];
                        $visit!(mine, mine_mask, top, len, sums);
                        // Written out, as in rasterize_bwd_subgroup_entry (llvmpipe's loop budget).
                        if lane < len {
                            let base = id as usize * SPLAT_GRAD_FLOATS;
                            $accumulate(splat_grads, base, sums[0]);
                            $accumulate(splat_grads, base + 1, sums[1]);
                            $accumulate(splat_grads, base + 2, sums[2]);
                            $accumulate(splat_grads, base + 3, sums[3]);
                            $accumulate(splat_grads, base + 4, sums[4]);
                            $accumulate(splat_grads, base + 5, sums[5]);
                            $accumulate(splat_grads, base + 6, sums[6]);
                            $accumulate(splat_grads, base + 7, sums[7]);
                            $accumulate(splat_grads, base + 8, sums[8]);
                            $accumulate(splat_grads, base + 9, sums[9]);
                        }
                        top -= len;
                    }
                };
            }
            // Sparse or dense once per walk, as the forward.
            if last <= $sparse_max {
                walk!(sparse);
            } else {
                walk!(dense);
            }
        }
    };
}

#[cfg(all(feature = "subgroup-ballot", feature = "float-atomics"))]
rasterize_fused_bwd_subgroup_entry!(rasterize_fused_bwd_subgroup_atomic, f32, atomics::add_f32, SPARSE_MAX_WALK, doc = "Fused backward rasterizer for CPU devices with subgroups of 8, float atomics.");
#[cfg(feature = "subgroup-ballot")]
rasterize_fused_bwd_subgroup_entry!(rasterize_fused_bwd_subgroup_cas, u32, atomics::add_f32_cas, SPARSE_MAX_WALK_CAS, doc = "Fused backward rasterizer for CPU devices with subgroups of 8, compare-and-swap on the bits of f32.");
#[cfg(feature = "subgroup-ballot")]
rasterize_fused_bwd_subgroup_entry!(rasterize_fused_bwd_subgroup_fixed, u32, atomics::add_fixed, SPARSE_MAX_WALK, doc = "Deterministic fused backward rasterizer for CPU devices with subgroups of 8 (64-bit fixed point).");
