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
use drape_shared::splat::layout::{sh_coeffs, FrameParams, ProjectChunk, ProjectedSplat, SplatCounts, MAX_SH_COEFFS, SPLAT_DROPPED, SPLAT_GRAD_FLOATS, TILE_SIZE};
use drape_shared::splat::project::{project_bwd as project_bwd_math, project_fwd as project_fwd_math, tile_rect, Camera, Gaussian, SplatGrad};
use drape_shared::splat::raster::{BlendSettings, FusedPixel, PixelBwd, PixelFwd, SplatView};
use spirv_std::arch::workgroup_memory_barrier_with_group_sync as barrier;
use spirv_std::glam::UVec3;
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
    let mut k = 0;
    while k < k_count {
        let base = (sh_i * k_count + k) * 3;
        coeffs[k] = [sh[base], sh[base + 1], sh[base + 2]];
        k += 1;
    }
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
    let i = index as usize;
    let cam = Camera::<f32>::from_frame(frame);
    let g = load_gaussian(i, local as usize, frame.sh_degree, means, log_scales, quats, opacity_logits, sh);
    let p = project_fwd_math(&g, &cam);
    let mut out = ProjectedSplat::default();
    if p.visible {
        let r = tile_rect(p.x, p.y, p.radius, frame.tiles_x, frame.tiles_y);
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
const _: () = assert!(BATCH == (TILE_SIZE * TILE_SIZE) as usize);
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

/// Stores a splat's fields into slot `slot` of the workgroup batch.
#[allow(clippy::too_many_arguments)]
#[inline]
fn load_batch_slot(
    slot: usize,
    s: &ProjectedSplat,
    b_xy: &mut [[f32; 2]; BATCH],
    b_conic: &mut [[f32; 3]; BATCH],
    b_opacity_depth: &mut [[f32; 2]; BATCH],
    b_color: &mut [[f32; 3]; BATCH],
) {
    b_xy[slot] = [s.x, s.y];
    b_conic[slot] = [s.conic_a, s.conic_b, s.conic_c];
    b_opacity_depth[slot] = [s.opacity, s.depth];
    b_color[slot] = [s.r, s.g, s.b];
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

/// One workgroup per tile, one invocation per pixel: blends the tile's splats front
/// to back, a batch at a time, until every pixel of the tile is saturated.
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(16, 16)))]
pub fn rasterize_fwd(
    #[spirv(workgroup_id)] tile: UVec3,
    #[spirv(local_invocation_id)] local: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[ProjectedSplat],
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
    let px = tile.x * TILE_SIZE + local.x;
    let py = tile.y * TILE_SIZE + local.y;
    let inside = px < frame.width && py < frame.height;
    let cfg = BlendSettings::<f32>::from_frame(frame);
    let t = (tile.y * frame.tiles_x + tile.x) as usize;
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
            load_batch_slot(slot, &s, b_xy, b_conic, b_opacity_depth, b_color);
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

/// The fused rasterizer (`ops::splat::fused`): one walk of each tile's depth-sorted
/// list of every layer's splats, blending each into the base, cloth and matte states
/// its layer mask (`masks`, per Gaussian) names (`drape_shared::splat::raster::FusedPixel`);
/// writes the base image over the frame's background, the cloth image and alpha over
/// black, and the matte (3 channels, over black) for the composite.
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(16, 16)))]
pub fn rasterize_fused_fwd(
    #[spirv(workgroup_id)] tile: UVec3,
    #[spirv(local_invocation_id)] local: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[ProjectedSplat],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] masks: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] base_rgb: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] cloth_rgb: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] cloth_alpha: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] matte_rgb: &mut [f32],
    #[spirv(workgroup)] b_xy: &mut [[f32; 2]; BATCH],
    #[spirv(workgroup)] b_conic: &mut [[f32; 3]; BATCH],
    #[spirv(workgroup)] b_opacity_depth: &mut [[f32; 2]; BATCH],
    #[spirv(workgroup)] b_color: &mut [[f32; 3]; BATCH],
    #[spirv(workgroup)] b_mask: &mut [u32; BATCH],
    #[spirv(workgroup)] done_count: &mut [u32; 1],
) {
    let px = tile.x * TILE_SIZE + local.x;
    let py = tile.y * TILE_SIZE + local.y;
    let inside = px < frame.width && py < frame.height;
    let cfg = BlendSettings::<f32>::from_frame(frame);
    let t = (tile.y * frame.tiles_x + tile.x) as usize;
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
            load_batch_slot(slot, &s, b_xy, b_conic, b_opacity_depth, b_color);
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
                    state.blend(&s, b_mask[slot], fx, fy, &cfg);
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
    let c = state.base.rgb(frame.background);
    base_rgb[3 * p] = c[0];
    base_rgb[3 * p + 1] = c[1];
    base_rgb[3 * p + 2] = c[2];
    cloth_rgb[3 * p] = state.cloth.color[0];
    cloth_rgb[3 * p + 1] = state.cloth.color[1];
    cloth_rgb[3 * p + 2] = state.cloth.color[2];
    cloth_alpha[p] = 1.0 - state.cloth.transmittance;
    matte_rgb[3 * p] = state.matte.color[0];
    matte_rgb[3 * p + 1] = state.matte.color[1];
    matte_rgb[3 * p + 2] = state.matte.color[2];
}

/// The backward rasterizer: one workgroup per tile, one invocation per pixel, walking
/// the tile's batches back to front from the last splat any pixel blended, each pixel
/// skipping what lies behind its own last one; `$accumulate(grads, index, value)` adds
/// into the per-splat gradients (float atomics or a compare-and-swap loop).
macro_rules! rasterize_bwd_entry {
    ($name:ident, $grad_ty:ty, $accumulate:path, $($attr:meta),*) => {
        $(#[$attr])*
        #[allow(clippy::too_many_arguments)]
        #[spirv(compute(threads(16, 16)))]
        pub fn $name(
            #[spirv(workgroup_id)] tile: UVec3,
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
            let px = tile.x * TILE_SIZE + local.x;
            let py = tile.y * TILE_SIZE + local.y;
            let inside = px < frame.width && py < frame.height;
            let cfg = BlendSettings::<f32>::from_frame(frame);
            let t = (tile.y * frame.tiles_x + tile.x) as usize;
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
                    load_batch_slot(slot, &splats[id as usize], b_xy, b_conic, b_opacity_depth, b_color);
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
// One line per entry: the kernel list test (`tests/tests/runtime.rs`) reads the name here.
rasterize_bwd_entry!(rasterize_bwd_fixed, u32, atomics::add_fixed, doc = "Deterministic backward rasterizer: per-splat gradients in 64-bit fixed point (`fixed_point::resolve` turns them into f32).");

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
        let mut c = 0;
        while c < SPLAT_GRAD_FLOATS {
            up[c] = splat_grads[base + c];
            c += 1;
        }
        out = project_bwd_math(&g, &cam, &SplatGrad::from_array(&up));
    }
    let mut c = 0;
    while c < 3 {
        grad_means[3 * i + c] = out.mean[c];
        grad_log_scales[3 * i + c] = out.log_scale[c];
        c += 1;
    }
    c = 0;
    while c < 4 {
        grad_quats[4 * i + c] = out.quat[c];
        c += 1;
    }
    grad_opacity_logits[i] = out.opacity_logit;
    let mut k = 0;
    while k < k_count {
        let base = (sh_i * k_count + k) * 3;
        grad_sh[base] = out.sh[k][0];
        grad_sh[base + 1] = out.sh[k][1];
        grad_sh[base + 2] = out.sh[k][2];
        k += 1;
    }
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
