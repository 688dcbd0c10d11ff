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
//!
//! The rasterizers here run one workgroup of 16 × 16 per block of a tile (GPUs);
//! `splat_lavapipe` has their twins for CPU devices. Each rasterizer is one generic
//! function (`rasterize_*_in`) behind thin entry points: by splat layout (f32 or
//! `_half`), or by how the backward adds into the per-splat gradients
//! (`atomics::GradAdd`: `_atomic`, `_cas`, `_fixed`).
#![allow(clippy::too_many_arguments)]

use drape_shared::half::{pack2, sh_half_sources, sh_half_words, ShHalfParams};
use drape_shared::radix_sort::bounded_len;
use drape_shared::splat::layout::{
    sh_coeffs, FrameParams, HalfSplat, ProjectChunk, ProjectedSplat, SplatCounts, MAX_SH_COEFFS,
    RASTER_BLOCK, SPLAT_DROPPED, SPLAT_GRAD_FLOATS,
};
use drape_shared::splat::project::{
    project_bwd as project_bwd_math, project_fwd as project_fwd_math, tile_rect, Camera, Gaussian,
    SplatGrad,
};
use drape_shared::splat::raster::{
    BlendSettings, FusedPixel, FusedPixelBwd, PixelBwd, PixelFwd, SplatView,
};
use spirv_std::arch::workgroup_memory_barrier_with_group_sync as barrier;
use spirv_std::glam::UVec3;
use spirv_std::spirv;

#[cfg(feature = "float-atomics")]
use crate::atomics::FloatAtomics;
use crate::atomics::{self, CompareAndSwap, FixedPoint, GradAdd};
use crate::flat_index;

/// Gaussian `i`, whose SH starts at Gaussian `sh_i` of the `sh` binding (see
/// `ProjectChunk`).
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
        log_scale: [
            log_scales[3 * i],
            log_scales[3 * i + 1],
            log_scales[3 * i + 2],
        ],
        quat: [
            quats[4 * i],
            quats[4 * i + 1],
            quats[4 * i + 2],
            quats[4 * i + 3],
        ],
        opacity_logit: opacity_logits[i],
        sh: coeffs,
    }
}

/// Projects Gaussian `i`: its splat, its depth key and its index for the depth sort.
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
    let g = load_gaussian(
        index as usize,
        local as usize,
        frame.sh_degree,
        means,
        log_scales,
        quats,
        opacity_logits,
        sh,
    );
    project_store(index, &g, frame, splats, depth_keys, order, dropped);
}

/// [`project_fwd`] reading half-precision SH (`sh_half`: two halves a word,
/// [`sh_half_words`] words per Gaussian from `splat::pack_sh_half`): the render-only
/// knob of `engine-bench trade` (no backward reads these).
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
        log_scale: [
            log_scales[3 * i],
            log_scales[3 * i + 1],
            log_scales[3 * i + 2],
        ],
        quat: [
            quats[4 * i],
            quats[4 * i + 1],
            quats[4 * i + 2],
            quats[4 * i + 3],
        ],
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
        let r = tile_rect(
            p.x,
            p.y,
            p.radius,
            frame.tile_size,
            frame.tiles_x,
            frame.tiles_y,
        );
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
    depth_keys[i] = if out.tiles > 0 {
        p.depth.to_bits()
    } else {
        u32::MAX
    };
    order[i] = index;
}

/// `counts[j]` = tiles of the `j`-th splat in depth order; `counts[n]` = 0, so that
/// after the exclusive scan `offsets[n]` is the number of intersections. The scan is
/// u32 and wraps past 2^32 - 1, so the total is also summed here without wrap:
/// `total[0]` (low word) and `total[1]` (carries), zero-filled before. A workgroup's
/// sum cannot wrap: 256 splats of at most 2^24 tiles each (the renderer refuses larger
/// tile grids).
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

/// Splats handled per iteration of the per-pixel loops, written out with
/// `each_index!(8, ..)` (no inner loop).
const UNROLL: u32 = 8;

/// A splat layout the rasterizers read: its view.
pub(crate) trait RasterSplat: Copy {
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
        SplatView {
            x: self.x,
            y: self.y,
            depth: bd.y,
            conic: [ab.x, ab.y, co.x],
            opacity: co.y,
            color: [rg.x, rg.y, bd.x],
        }
    }
}

/// A batch of splats in workgroup memory: their views, a field an array (each read
/// whole where the blend needs it), their Gaussians' indices (the backwards') and layer
/// masks (the fused rasterizers'), and a counter the workgroup votes into (the
/// forwards' saturated pixels, the backwards' furthest splat). One layout for all four
/// kernels: the fields a kernel leaves unused cost it 2 KiB of its 12 KiB.
pub struct Batch {
    xy: [[f32; 2]; BATCH],
    conic: [[f32; 3]; BATCH],
    opacity_depth: [[f32; 2]; BATCH],
    color: [[f32; 3]; BATCH],
    id: [u32; BATCH],
    mask: [u32; BATCH],
    counter: u32,
}

impl Batch {
    /// Stores a splat's view into slot `slot`.
    #[inline]
    fn store(&mut self, slot: usize, s: &SplatView<f32>) {
        self.xy[slot] = [s.x, s.y];
        self.conic[slot] = s.conic;
        self.opacity_depth[slot] = [s.opacity, s.depth];
        self.color[slot] = s.color;
    }

    /// The view in slot `slot`.
    #[inline]
    fn view(&self, slot: usize) -> SplatView<f32> {
        let xy = self.xy[slot];
        let od = self.opacity_depth[slot];
        SplatView {
            x: xy[0],
            y: xy[1],
            depth: od[1],
            conic: self.conic[slot],
            opacity: od[0],
            color: self.color[slot],
        }
    }
}

/// Where one invocation of a workgroup rasterizer works: its pixel (global invocation
/// `id`) of its workgroup's 16 × 16 block, and the tile whose list it walks (a tile of
/// 32 is 2 × 2 blocks; the engine records these kernels for tiles of 16 and 32 only).
struct BlockPixel {
    tile: usize,
    /// The invocation's index in the workgroup (its batch slot).
    lid: u32,
    px: u32,
    py: u32,
    inside: bool,
}

impl BlockPixel {
    #[inline]
    fn new(id: UVec3, frame: &FrameParams) -> Self {
        let per = frame.tile_size / RASTER_BLOCK;
        let per = if per == 0 { 1 } else { per };
        let (px, py) = (id.x, id.y);
        let (group_x, group_y) = (px / RASTER_BLOCK, py / RASTER_BLOCK);
        BlockPixel {
            tile: ((group_y / per) * frame.tiles_x + group_x / per) as usize,
            lid: (py % RASTER_BLOCK) * RASTER_BLOCK + px % RASTER_BLOCK,
            px,
            py,
            inside: px < frame.width && py < frame.height,
        }
    }

    /// The pixel's centre.
    #[inline]
    fn centre(&self) -> (f32, f32) {
        (self.px as f32 + 0.5, self.py as f32 + 0.5)
    }

    /// The pixel's index (only meaningful `inside`).
    #[inline]
    fn pixel(&self, frame: &FrameParams) -> usize {
        (self.py * frame.width + self.px) as usize
    }
}

/// Writes one pixel of the forward outputs (the workgroup and the CPU rasterizers').
#[inline]
pub(crate) fn store_pixel_fwd(
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

/// Writes one pixel of the fused rasterizer's outputs (the workgroup and the CPU ones').
#[inline]
pub(crate) fn store_pixel_fused(
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

/// The forward rasterizer: one workgroup per 16 × 16 block of a tile, one invocation
/// per pixel, blending the tile's splats front to back, a batch at a time, until every
/// pixel of the block is saturated. Entry points: [`rasterize_fwd`] (f32 splats),
/// [`rasterize_fwd_half`] ([`HalfSplat`]s, `RenderSettings::half_splats`).
#[inline]
fn rasterize_fwd_in<S: RasterSplat>(
    at: &BlockPixel,
    frame: &FrameParams,
    splats: &[S],
    isect_values: &[u32],
    ranges: &[u32],
    rgb: &mut [f32],
    alpha: &mut [f32],
    depth: &mut [f32],
    contributors: &mut [u32],
    transmittance: &mut [f32],
    blended: &mut [u32],
    batch: &mut Batch,
) {
    let cfg = BlendSettings::<f32>::from_frame(frame);
    let start = ranges[2 * at.tile];
    let end = ranges[2 * at.tile + 1];
    let (fx, fy) = at.centre();
    let lid = at.lid;
    let mut state = PixelFwd::<f32>::new();
    state.done = !at.inside;
    let mut base = start;
    // Uniform loop: `base`, `end` and the vote are the same for the whole workgroup.
    while base < end {
        let k = base + lid;
        if k < end {
            batch.store(
                lid as usize,
                &splats[isect_values[k as usize] as usize].raster_view(),
            );
        }
        if lid == 0 {
            batch.counter = 0;
        }
        barrier();
        let count = if end - base < BATCH as u32 {
            end - base
        } else {
            BATCH as u32
        };
        let mut j = 0u32;
        while j < count && !state.done {
            // UNROLL splats per iteration: llvmpipe caps the loop iterations of an
            // invocation at 65,535, and a tile's list can hold ~10^5 splats.
            drape_shared::each_index!(8, u => {
                let u = u as u32;
                if j + u < count && !state.done {
                    state.blend(&batch.view((j + u) as usize), base - start + j + u, fx, fy, &cfg);
                }
            });
            j += UNROLL;
        }
        if state.done {
            atomics::add_u32_workgroup(&mut batch.counter, 1);
        }
        barrier();
        let all_done = batch.counter == BATCH as u32;
        // Everyone has read the batch and the vote before they are overwritten.
        barrier();
        if all_done {
            break;
        }
        base += count;
    }
    if at.inside {
        store_pixel_fwd(
            at.pixel(frame),
            &state,
            frame,
            rgb,
            alpha,
            depth,
            contributors,
            transmittance,
            blended,
        );
    }
}

/// The f32 splats' forward rasterizer ([`rasterize_fwd_in`]).
#[spirv(compute(threads(16, 16)))]
pub fn rasterize_fwd(
    #[spirv(global_invocation_id)] id: UVec3,
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
    #[spirv(workgroup)] batch: &mut Batch,
) {
    rasterize_fwd_in(
        &BlockPixel::new(id, frame),
        frame,
        splats,
        isect_values,
        ranges,
        rgb,
        alpha,
        depth,
        contributors,
        transmittance,
        blended,
        batch,
    );
}

/// [`rasterize_fwd`] reading [`HalfSplat`]s (`RenderSettings::half_splats`).
#[spirv(compute(threads(16, 16)))]
pub fn rasterize_fwd_half(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[HalfSplat],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] rgb: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] alpha: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] depth: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] contributors: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] transmittance: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] blended: &mut [u32],
    #[spirv(workgroup)] batch: &mut Batch,
) {
    rasterize_fwd_in(
        &BlockPixel::new(id, frame),
        frame,
        splats,
        isect_values,
        ranges,
        rgb,
        alpha,
        depth,
        contributors,
        transmittance,
        blended,
        batch,
    );
}

/// The fused rasterizer (`ops::splat::fused`): one walk of each tile's depth-sorted
/// list of every cloud's splats, blending each into the base, over and matte states
/// its mask (`masks`, per Gaussian) names (`drape_shared::splat::raster::FusedPixel`);
/// writes the base image over the frame's background, the over pass's image and alpha
/// over black, and the matte (3 channels, over black) for the composite, and for the
/// backward each state's final transmittance and end in the merged list (3 per pixel).
/// Entry points: [`rasterize_fused_fwd`], [`rasterize_fused_fwd_half`].
#[inline]
fn rasterize_fused_fwd_in<S: RasterSplat>(
    at: &BlockPixel,
    frame: &FrameParams,
    splats: &[S],
    isect_values: &[u32],
    ranges: &[u32],
    masks: &[u32],
    base_rgb: &mut [f32],
    over_rgb: &mut [f32],
    over_alpha: &mut [f32],
    matte_rgb: &mut [f32],
    transmittances: &mut [f32],
    ends: &mut [u32],
    batch: &mut Batch,
) {
    let cfg = BlendSettings::<f32>::from_frame(frame);
    let start = ranges[2 * at.tile];
    let end = ranges[2 * at.tile + 1];
    let (fx, fy) = at.centre();
    let lid = at.lid;
    let mut state = FusedPixel::<f32>::new();
    let mut done = !at.inside;
    let mut base = start;
    // Uniform loop, as in rasterize_fwd_in.
    while base < end {
        let k = base + lid;
        if k < end {
            let g = isect_values[k as usize] as usize;
            batch.store(lid as usize, &splats[g].raster_view());
            batch.mask[lid as usize] = masks[g];
        }
        if lid == 0 {
            batch.counter = 0;
        }
        barrier();
        let count = if end - base < BATCH as u32 {
            end - base
        } else {
            BATCH as u32
        };
        let mut j = 0u32;
        while j < count && !done {
            drape_shared::each_index!(8, u => {
                let u = u as u32;
                if j + u < count && !done {
                    let slot = (j + u) as usize;
                    state.blend(&batch.view(slot), batch.mask[slot], base - start + j + u, fx, fy, &cfg);
                    done = state.done();
                }
            });
            j += UNROLL;
        }
        if done {
            atomics::add_u32_workgroup(&mut batch.counter, 1);
        }
        barrier();
        let all_done = batch.counter == BATCH as u32;
        barrier();
        if all_done {
            break;
        }
        base += count;
    }
    if at.inside {
        store_pixel_fused(
            at.pixel(frame),
            &state,
            frame,
            base_rgb,
            over_rgb,
            over_alpha,
            matte_rgb,
            transmittances,
            ends,
        );
    }
}

/// The f32 splats' fused rasterizer ([`rasterize_fused_fwd_in`]).
#[spirv(compute(threads(16, 16)))]
pub fn rasterize_fused_fwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[ProjectedSplat],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] masks: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] base_rgb: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] over_rgb: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] over_alpha: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] matte_rgb: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] transmittances: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 10)] ends: &mut [u32],
    #[spirv(workgroup)] batch: &mut Batch,
) {
    rasterize_fused_fwd_in(
        &BlockPixel::new(id, frame),
        frame,
        splats,
        isect_values,
        ranges,
        masks,
        base_rgb,
        over_rgb,
        over_alpha,
        matte_rgb,
        transmittances,
        ends,
        batch,
    );
}

/// [`rasterize_fused_fwd`] reading [`HalfSplat`]s (`RenderSettings::half_splats`).
#[spirv(compute(threads(16, 16)))]
pub fn rasterize_fused_fwd_half(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[HalfSplat],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] masks: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] base_rgb: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] over_rgb: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] over_alpha: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] matte_rgb: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] transmittances: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 10)] ends: &mut [u32],
    #[spirv(workgroup)] batch: &mut Batch,
) {
    rasterize_fused_fwd_in(
        &BlockPixel::new(id, frame),
        frame,
        splats,
        isect_values,
        ranges,
        masks,
        base_rgb,
        over_rgb,
        over_alpha,
        matte_rgb,
        transmittances,
        ends,
        batch,
    );
}

/// The backward rasterizer: one workgroup per 16 × 16 block, one invocation per pixel,
/// walking the tile's batches back to front from the last splat any pixel blended,
/// each pixel skipping what lies behind its own last one; `A` adds into the per-splat
/// gradients. Entry points: [`rasterize_bwd_atomic`], [`rasterize_bwd_cas`],
/// [`rasterize_bwd_fixed`].
#[inline]
fn rasterize_bwd_in<A: GradAdd>(
    at: &BlockPixel,
    frame: &FrameParams,
    splats: &[ProjectedSplat],
    isect_values: &[u32],
    ranges: &[u32],
    contributors: &[u32],
    transmittance: &[f32],
    grad_rgb: &[f32],
    grad_alpha: &[f32],
    grad_depth: &[f32],
    splat_grads: &mut [A::Word],
    batch: &mut Batch,
) {
    let cfg = BlendSettings::<f32>::from_frame(frame);
    let start = ranges[2 * at.tile];
    let inside = at.inside;
    let p = if inside { at.pixel(frame) } else { 0 };
    let (fx, fy) = at.centre();
    let lid = at.lid;
    let mine = if inside { contributors[p] } else { 0 };
    let mut state = PixelBwd::<f32>::new(
        if inside { transmittance[p] } else { 1.0 },
        frame.background,
        if inside {
            [grad_rgb[3 * p], grad_rgb[3 * p + 1], grad_rgb[3 * p + 2]]
        } else {
            [0.0; 3]
        },
        if inside { grad_alpha[p] } else { 0.0 },
        if inside { grad_depth[p] } else { 0.0 },
    );
    if lid == 0 {
        batch.counter = 0;
    }
    barrier();
    atomics::max_u32_workgroup(&mut batch.counter, mine);
    barrier();
    let mut batch_end = start + batch.counter;
    // Uniform loop: the bounds are the same for the whole workgroup.
    while batch_end > start {
        let batch_start = if batch_end - start > BATCH as u32 {
            batch_end - BATCH as u32
        } else {
            start
        };
        let k = batch_start + lid;
        if k < batch_end {
            let id = isect_values[k as usize];
            batch.id[lid as usize] = id;
            batch.store(lid as usize, &splats[id as usize].view());
        }
        barrier();
        // Back to front, UNROLL splats per iteration (see the forward pass).
        let mut top = batch_end - batch_start;
        while top > 0 {
            drape_shared::each_index!(8, u => {
                let u = u as u32;
                if u < top {
                    let j = top - 1 - u;
                    if batch_start + j < start + mine {
                        if let Some(grad) = state.step(&batch.view(j as usize), fx, fy, &cfg) {
                            atomics::add_splat_grad::<A>(splat_grads, batch.id[j as usize] as usize, &grad.to_array());
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

/// [`rasterize_bwd_in`] with float atomics (needs shaderBufferFloat32AtomicAdd).
#[cfg(feature = "float-atomics")]
#[spirv(compute(threads(16, 16)))]
pub fn rasterize_bwd_atomic(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[ProjectedSplat],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] contributors: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] transmittance: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] grad_rgb: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] grad_alpha: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] grad_depth: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] splat_grads: &mut [f32],
    #[spirv(workgroup)] batch: &mut Batch,
) {
    rasterize_bwd_in::<FloatAtomics>(
        &BlockPixel::new(id, frame),
        frame,
        splats,
        isect_values,
        ranges,
        contributors,
        transmittance,
        grad_rgb,
        grad_alpha,
        grad_depth,
        splat_grads,
        batch,
    );
}

/// [`rasterize_bwd_in`] with compare-and-swap loops on the bits of f32 (any device).
#[spirv(compute(threads(16, 16)))]
pub fn rasterize_bwd_cas(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[ProjectedSplat],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] contributors: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] transmittance: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] grad_rgb: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] grad_alpha: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] grad_depth: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] splat_grads: &mut [u32],
    #[spirv(workgroup)] batch: &mut Batch,
) {
    rasterize_bwd_in::<CompareAndSwap>(
        &BlockPixel::new(id, frame),
        frame,
        splats,
        isect_values,
        ranges,
        contributors,
        transmittance,
        grad_rgb,
        grad_alpha,
        grad_depth,
        splat_grads,
        batch,
    );
}

/// Deterministic [`rasterize_bwd_in`]: per-splat gradients in 64-bit fixed point
/// (`fixed_point::resolve` turns them into f32).
#[spirv(compute(threads(16, 16)))]
pub fn rasterize_bwd_fixed(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[ProjectedSplat],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] contributors: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] transmittance: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] grad_rgb: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] grad_alpha: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] grad_depth: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] splat_grads: &mut [u32],
    #[spirv(workgroup)] batch: &mut Batch,
) {
    rasterize_bwd_in::<FixedPoint>(
        &BlockPixel::new(id, frame),
        frame,
        splats,
        isect_values,
        ranges,
        contributors,
        transmittance,
        grad_rgb,
        grad_alpha,
        grad_depth,
        splat_grads,
        batch,
    );
}

/// The fused rasterizer's backward (`ops::splat::fused`): one workgroup per 16 × 16
/// block, one invocation per pixel, walking the merged list back to front from the
/// furthest end any pixel's states reached; each pixel runs its three states'
/// backward walks (`drape_shared::splat::raster::FusedPixelBwd`) and adds each splat
/// the sum of what they send it. Upstream: the gradients on the base rgb, the over rgb
/// and alpha, and the matte (channel 0 of 3, as the composite's backward writes it).
/// `A` adds into the per-splat gradients. Entry points: [`rasterize_fused_bwd_atomic`],
/// [`rasterize_fused_bwd_cas`], [`rasterize_fused_bwd_fixed`].
#[inline]
fn rasterize_fused_bwd_in<A: GradAdd>(
    at: &BlockPixel,
    frame: &FrameParams,
    splats: &[ProjectedSplat],
    isect_values: &[u32],
    ranges: &[u32],
    masks: &[u32],
    transmittances: &[f32],
    ends: &[u32],
    grad_base: &[f32],
    grad_over: &[f32],
    grad_over_alpha: &[f32],
    grad_matte: &[f32],
    splat_grads: &mut [A::Word],
    batch: &mut Batch,
) {
    let cfg = BlendSettings::<f32>::from_frame(frame);
    let start = ranges[2 * at.tile];
    let (fx, fy) = at.centre();
    let lid = at.lid;
    let mut state = if at.inside {
        let p = at.pixel(frame);
        FusedPixelBwd::<f32>::new(
            [
                transmittances[3 * p],
                transmittances[3 * p + 1],
                transmittances[3 * p + 2],
            ],
            [ends[3 * p], ends[3 * p + 1], ends[3 * p + 2]],
            frame.background,
            [grad_base[3 * p], grad_base[3 * p + 1], grad_base[3 * p + 2]],
            [grad_over[3 * p], grad_over[3 * p + 1], grad_over[3 * p + 2]],
            grad_over_alpha[p],
            grad_matte[3 * p],
        )
    } else {
        FusedPixelBwd::<f32>::new(
            [1.0; 3],
            [0; 3],
            frame.background,
            [0.0; 3],
            [0.0; 3],
            0.0,
            0.0,
        )
    };
    let mine = state.end();
    if lid == 0 {
        batch.counter = 0;
    }
    barrier();
    atomics::max_u32_workgroup(&mut batch.counter, mine);
    barrier();
    let mut batch_end = start + batch.counter;
    // Uniform loop: the bounds are the same for the whole workgroup.
    while batch_end > start {
        let batch_start = if batch_end - start > BATCH as u32 {
            batch_end - BATCH as u32
        } else {
            start
        };
        let k = batch_start + lid;
        if k < batch_end {
            let id = isect_values[k as usize];
            batch.id[lid as usize] = id;
            batch.mask[lid as usize] = masks[id as usize];
            batch.store(lid as usize, &splats[id as usize].view());
        }
        barrier();
        // Back to front, UNROLL splats per iteration (see the forward pass).
        let mut top = batch_end - batch_start;
        while top > 0 {
            drape_shared::each_index!(8, u => {
                let u = u as u32;
                if u < top {
                    let j = top - 1 - u;
                    let index = batch_start + j - start;
                    if index < mine {
                        if let Some(grad) = state.step(&batch.view(j as usize), batch.mask[j as usize], index, fx, fy, &cfg) {
                            atomics::add_splat_grad::<A>(splat_grads, batch.id[j as usize] as usize, &grad.to_array());
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

/// [`rasterize_fused_bwd_in`] with float atomics (needs shaderBufferFloat32AtomicAdd).
#[cfg(feature = "float-atomics")]
#[spirv(compute(threads(16, 16)))]
pub fn rasterize_fused_bwd_atomic(
    #[spirv(global_invocation_id)] id: UVec3,
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
    #[spirv(storage_buffer, descriptor_set = 0, binding = 11)] splat_grads: &mut [f32],
    #[spirv(workgroup)] batch: &mut Batch,
) {
    rasterize_fused_bwd_in::<FloatAtomics>(
        &BlockPixel::new(id, frame),
        frame,
        splats,
        isect_values,
        ranges,
        masks,
        transmittances,
        ends,
        grad_base,
        grad_over,
        grad_over_alpha,
        grad_matte,
        splat_grads,
        batch,
    );
}

/// [`rasterize_fused_bwd_in`] with compare-and-swap loops on the bits of f32 (any device).
#[spirv(compute(threads(16, 16)))]
pub fn rasterize_fused_bwd_cas(
    #[spirv(global_invocation_id)] id: UVec3,
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
    #[spirv(storage_buffer, descriptor_set = 0, binding = 11)] splat_grads: &mut [u32],
    #[spirv(workgroup)] batch: &mut Batch,
) {
    rasterize_fused_bwd_in::<CompareAndSwap>(
        &BlockPixel::new(id, frame),
        frame,
        splats,
        isect_values,
        ranges,
        masks,
        transmittances,
        ends,
        grad_base,
        grad_over,
        grad_over_alpha,
        grad_matte,
        splat_grads,
        batch,
    );
}

/// [`rasterize_fused_bwd_in`], deterministic: per-splat gradients in 64-bit fixed point.
#[spirv(compute(threads(16, 16)))]
pub fn rasterize_fused_bwd_fixed(
    #[spirv(global_invocation_id)] id: UVec3,
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
    #[spirv(storage_buffer, descriptor_set = 0, binding = 11)] splat_grads: &mut [u32],
    #[spirv(workgroup)] batch: &mut Batch,
) {
    rasterize_fused_bwd_in::<FixedPoint>(
        &BlockPixel::new(id, frame),
        frame,
        splats,
        isect_values,
        ranges,
        masks,
        transmittances,
        ends,
        grad_base,
        grad_over,
        grad_over_alpha,
        grad_matte,
        splat_grads,
        batch,
    );
}

const _: () = assert!(
    SPLAT_GRAD_FLOATS == 10,
    "project_bwd unrolls the splat gradient's 10 floats"
);

/// Gradients of Gaussian `i`'s parameters from its splat's gradient. Culled Gaussians
/// get zeros.
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
        let g = load_gaussian(
            i,
            sh_i,
            frame.sh_degree,
            means,
            log_scales,
            quats,
            opacity_logits,
            sh,
        );
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
    let s = drape_shared::splat::densify::accumulate(
        [stats[o], stats[o + 1], stats[o + 2]],
        &splats[i],
        splat_grads[g],
        splat_grads[g + 1],
        p.width,
        p.height,
    );
    stats[o] = s[0];
    stats[o + 1] = s[1];
    stats[o + 2] = s[2];
}
