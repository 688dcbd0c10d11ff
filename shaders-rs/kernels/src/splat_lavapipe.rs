//! The rasterizers for CPU devices (lavapipe): the four rasterizers of `splat` (forward,
//! fused forward, and their backwards), tuned for llvmpipe, built with
//! `subgroup-ballot`. The engine records these only where the device is a CPU with
//! subgroups of exactly 8 lanes (`ops::splat::render::subgroup_raster_supported`);
//! they produce what their `splat` twins produce (the same blending of the same splats
//! in the same order per pixel).
//!
//! Why separate kernels: llvmpipe runs the 8 lanes of a subgroup as one SIMD register,
//! compiles a load whose address it cannot prove uniform to a loop over the lanes, and
//! runs a workgroup barrier as a switch between coroutines. The workgroup rasterizers
//! pay both for every splat: 256 invocations read each splat's 10 fields from
//! workgroup memory, and each batch costs three barriers. Here a workgroup is one
//! subgroup of 8 lanes covering an 8 × 4 block of a tile (8 workgroups per 16 × 16
//! tile, 2 per tile of 8, 32 per tile of 32), dispatched on `[T/8 · tiles_x, T/4 ·
//! tiles_y]` workgroups of 8 for tiles of side T; each lane loads one splat of the next
//! 8 of the tile's list, and every lane gets each of the 8 by shuffles (`subgroup`): 4
//! loads per lane feed 8 splats × 4 pixels, and no barrier is needed. Every loop here
//! is uniform (the whole subgroup runs it to the end) and every shuffle reads an active
//! lane.
//!
//! | entry point | twin in `splat` |
//! | --- | --- |
//! | `rasterize_fwd`, `rasterize_fwd_half` | `rasterize_fwd`, `rasterize_fwd_half` |
//! | `rasterize_fused_fwd`, `rasterize_fused_fwd_half` | `rasterize_fused_fwd`, `rasterize_fused_fwd_half` |
//! | `rasterize_bwd_{atomic,cas,fixed}` | `rasterize_bwd_{atomic,cas,fixed}` |
//! | `rasterize_fused_bwd_{atomic,cas,fixed}` | `rasterize_fused_bwd_{atomic,cas,fixed}` |
//!
//! `_half` reads `HalfSplat`s (`RenderSettings::half_splats`): 6 words shuffled a
//! splat where the f32 kernels shuffle 12 (three `Vec4`s). The backwards' suffix names
//! how they add into the per-splat gradients (`atomics::GradAdd`).
#![allow(clippy::too_many_arguments)]

use drape_shared::splat::layout::{FrameParams, HalfSplat, SPLAT_GRAD_FLOATS};
use drape_shared::splat::project::SplatGrad;
use drape_shared::splat::raster::{
    may_touch_rect, BlendSettings, FusedPixel, FusedPixelBwd, PixelBwd, PixelFwd, SplatView,
};
use spirv_std::glam::{UVec3, Vec4};
use spirv_std::spirv;

#[cfg(feature = "float-atomics")]
use crate::atomics::FloatAtomics;
use crate::atomics::{add_splat_grad, CompareAndSwap, FixedPoint, GradAdd};
use crate::splat::{store_pixel_fused, store_pixel_fwd, RasterSplat};
use crate::subgroup::{
    all8, ballot8, broadcast_at, broadcast_u32_at, broadcast_vec4_at, max8_u32, sum8,
};

/// Pixel rows per lane (an 8 × 4 block per workgroup).
const ROWS: u32 = 4;

/// Longest walk (splats of a tile's list) taken sparsely: a round of 8 splats, then a
/// loop over those that may reach the block ([`may_touch_rect`]), so only those cost a
/// blend (llvmpipe runs both sides of every `if`; only a loop skips work). llvmpipe
/// stops an invocation's loops after 65,535 iterations in all, and a sparse walk of `n`
/// splats may spend `n / 8 + n`; longer walks go densely, every lane's splat by
/// constant lane numbers, one iteration per round (`8 × 65,535` splats). The choice is
/// made once per walk, outside the loops (the `SPARSE` of the walks), so the branch not
/// taken costs one masked round.
const SPARSE_MAX_WALK: u32 = 56_000;

/// [`SPARSE_MAX_WALK`] for the compare-and-swap backwards, where each of a lane's 10 adds
/// a round is a loop of at least one iteration (taken or not: llvmpipe runs a loop in an
/// untaken branch once): a sparse walk of `n` may spend `11 n / 8 + n`.
const SPARSE_MAX_WALK_CAS: u32 = 24_000;

/// A [`ProjectedSplat`](drape_shared::splat::layout::ProjectedSplat) as the f32
/// kernels bind it: its 64 bytes as four `Vec4`s (`x y depth conic_a`, `conic_b
/// conic_c opacity r`, `g b tile_x0 tile_y0`, and the tile fields they do not read).
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
/// ([`LaneSplat::lane_view`]), which is what keeps them.
#[derive(Clone, Copy)]
pub(crate) struct SplatRows {
    a: Vec4,
    b: Vec4,
    c: Vec4,
}

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

/// A splat layout as a lane holds its splat of a round, and how every lane gets lane
/// `u`'s view (`u` uniform, constant or not).
pub(crate) trait LaneSplat {
    /// What a lane keeps of its splat.
    type Held: RasterSplat;
    /// The lane's own splat, loaded.
    fn hold(&self) -> Self::Held;
    /// Lane `u`'s splat's view, in every lane.
    fn lane_view(held: Self::Held, u: u32) -> SplatView<f32>;
}

impl LaneSplat for SplatQuads {
    type Held = SplatRows;

    /// Three `Vec4` loads.
    #[inline]
    fn hold(&self) -> SplatRows {
        SplatRows {
            a: self.a,
            b: self.b,
            c: self.c,
        }
    }

    /// Three `Vec4` shuffles.
    #[inline]
    fn lane_view(held: SplatRows, u: u32) -> SplatView<f32> {
        SplatRows {
            a: broadcast_vec4_at(held.a, u),
            b: broadcast_vec4_at(held.b, u),
            c: broadcast_vec4_at(held.c, u),
        }
        .raster_view()
    }
}

impl LaneSplat for HalfSplat {
    type Held = HalfSplat;

    /// Kept packed.
    #[inline]
    fn hold(&self) -> HalfSplat {
        *self
    }

    /// 6 shuffles (the centre and the four packed words), unpacked after.
    #[inline]
    fn lane_view(held: HalfSplat, u: u32) -> SplatView<f32> {
        HalfSplat {
            x: broadcast_at(held.x, u),
            y: broadcast_at(held.y, u),
            conic_ab: broadcast_u32_at(held.conic_ab, u),
            conic_c_opacity: broadcast_u32_at(held.conic_c_opacity, u),
            rg: broadcast_u32_at(held.rg, u),
            b_depth: broadcast_u32_at(held.b_depth, u),
        }
        .raster_view()
    }
}

/// Where one lane works: its tile, its pixel column and the 4 rows of its 8 × 4 block
/// (workgroup `group` of the `[T/8 · tiles_x, T/4 · tiles_y]` grid for tiles of side T).
struct Block {
    tile: usize,
    lane: u32,
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

impl Block {
    #[inline]
    fn new(group: UVec3, lane: u32, frame: &FrameParams) -> Self {
        let px = group.x * 8 + lane;
        let py = group.y * ROWS;
        let x_in = px < frame.width;
        Block {
            tile: ((group.y / (frame.tile_size / ROWS)) * frame.tiles_x
                + group.x / (frame.tile_size / 8)) as usize,
            lane,
            px,
            py,
            fx: px as f32 + 0.5,
            fy: [
                py as f32 + 0.5,
                py as f32 + 1.5,
                py as f32 + 2.5,
                py as f32 + 3.5,
            ],
            inside: [
                x_in && py < frame.height,
                x_in && py + 1 < frame.height,
                x_in && py + 2 < frame.height,
                x_in && py + 3 < frame.height,
            ],
            lo: [(group.x * 8) as f32 + 0.5, py as f32 + 0.5],
            hi: [(group.x * 8) as f32 + 7.5, py as f32 + 3.5],
        }
    }

    /// The pixel index of row `r` (only meaningful where `inside[r]`).
    #[inline]
    fn pixel(&self, r: u32, frame: &FrameParams) -> usize {
        ((self.py + r) * frame.width + self.px) as usize
    }

    /// The list index of the lane's splat in the round of `len` ending at `top`
    /// (back to front; lanes past the round take its first).
    #[inline]
    fn back_index(&self, top: u32, len: u32) -> u32 {
        if self.lane < len {
            top - 1 - self.lane
        } else {
            top - 1
        }
    }
}

/// Blends splat `v`, the tile list's `index`-th, into those of a lane's 4 pixels
/// (rows `fy`) not yet saturated.
///
/// The four states are four variables, not a struct of four: `spirv-opt` splits such
/// a struct only partly, and llvmpipe then carries whole-struct copies through the
/// walk's loops (12% slower forward on lavapipe, `engine-bench splat`).
#[inline]
fn blend_quad(
    p0: &mut PixelFwd<f32>,
    p1: &mut PixelFwd<f32>,
    p2: &mut PixelFwd<f32>,
    p3: &mut PixelFwd<f32>,
    v: &SplatView<f32>,
    index: u32,
    fx: f32,
    fy: &[f32; 4],
    cfg: &BlendSettings<f32>,
) {
    if !p0.done {
        p0.blend(v, index, fx, fy[0], cfg);
    }
    if !p1.done {
        p1.blend(v, index, fx, fy[1], cfg);
    }
    if !p2.done {
        p2.blend(v, index, fx, fy[2], cfg);
    }
    if !p3.done {
        p3.blend(v, index, fx, fy[3], cfg);
    }
}

/// [`blend_quad`] for the fused states, with the splat's layer mask.
#[inline]
fn blend_fused_quad(
    p0: &mut FusedPixel<f32>,
    p1: &mut FusedPixel<f32>,
    p2: &mut FusedPixel<f32>,
    p3: &mut FusedPixel<f32>,
    v: &SplatView<f32>,
    mask: u32,
    index: u32,
    fx: f32,
    fy: &[f32; 4],
    cfg: &BlendSettings<f32>,
) {
    if !p0.done() {
        p0.blend(v, mask, index, fx, fy[0], cfg);
    }
    if !p1.done() {
        p1.blend(v, mask, index, fx, fy[1], cfg);
    }
    if !p2.done() {
        p2.blend(v, mask, index, fx, fy[2], cfg);
    }
    if !p3.done() {
        p3.blend(v, mask, index, fx, fy[3], cfg);
    }
}

/// A fused state that is saturated already where its pixel is outside the image.
#[inline]
fn fused_pixel(inside: bool) -> FusedPixel<f32> {
    let mut p = FusedPixel::new();
    p.base.done = !inside;
    p.over.done = !inside;
    p.matte.done = !inside;
    p
}

/// The forward walk of the tile's list `[start, end)`, 8 splats a round, into the
/// lane's 4 pixels: `SPARSE`, each round's splats that may reach the block, in list
/// order, by a loop over them; else every lane's splat by constant lane numbers (see
/// [`SPARSE_MAX_WALK`]).
#[inline]
fn walk_fwd<S: LaneSplat, const SPARSE: bool>(
    p0: &mut PixelFwd<f32>,
    p1: &mut PixelFwd<f32>,
    p2: &mut PixelFwd<f32>,
    p3: &mut PixelFwd<f32>,
    b: &Block,
    cfg: &BlendSettings<f32>,
    start: u32,
    end: u32,
    splats: &[S],
    isect_values: &[u32],
) {
    let (lane, fx, fy) = (b.lane, b.fx, b.fy);
    let mut base = start;
    // Uniform loop (start, end and the votes are the same in every lane).
    while base < end {
        // Lanes past the list's end load its first splat of this round, never used.
        let k = if base + lane < end { base + lane } else { base };
        let mine = splats[isect_values[k as usize] as usize].hold();
        if SPARSE {
            let mut todo =
                ballot8(base + lane < end && may_touch_rect(&mine.raster_view(), b.lo, b.hi, cfg));
            while todo != 0 {
                let u = todo.trailing_zeros();
                todo &= todo - 1;
                blend_quad(
                    p0,
                    p1,
                    p2,
                    p3,
                    &S::lane_view(mine, u),
                    base - start + u,
                    fx,
                    &fy,
                    cfg,
                );
            }
        } else {
            drape_shared::each_index!(8, u => {
                let u = u as u32;
                if base + u < end {
                    blend_quad(p0, p1, p2, p3, &S::lane_view(mine, u), base - start + u, fx, &fy, cfg);
                }
            });
        }
        if all8(p0.done && p1.done && p2.done && p3.done) {
            break;
        }
        base += 8;
    }
}

/// [`walk_fwd`] for the fused forward: each splat's layer mask shuffled beside it.
#[inline]
fn walk_fused<S: LaneSplat, const SPARSE: bool>(
    p0: &mut FusedPixel<f32>,
    p1: &mut FusedPixel<f32>,
    p2: &mut FusedPixel<f32>,
    p3: &mut FusedPixel<f32>,
    b: &Block,
    cfg: &BlendSettings<f32>,
    start: u32,
    end: u32,
    splats: &[S],
    isect_values: &[u32],
    masks: &[u32],
) {
    let (lane, fx, fy) = (b.lane, b.fx, b.fy);
    let mut base = start;
    while base < end {
        let k = if base + lane < end { base + lane } else { base };
        let g = isect_values[k as usize] as usize;
        let mine = splats[g].hold();
        let mine_mask = masks[g];
        if SPARSE {
            let mut todo =
                ballot8(base + lane < end && may_touch_rect(&mine.raster_view(), b.lo, b.hi, cfg));
            while todo != 0 {
                let u = todo.trailing_zeros();
                todo &= todo - 1;
                blend_fused_quad(
                    p0,
                    p1,
                    p2,
                    p3,
                    &S::lane_view(mine, u),
                    broadcast_u32_at(mine_mask, u),
                    base - start + u,
                    fx,
                    &fy,
                    cfg,
                );
            }
        } else {
            drape_shared::each_index!(8, u => {
                let u = u as u32;
                if base + u < end {
                    blend_fused_quad(p0, p1, p2, p3, &S::lane_view(mine, u), broadcast_u32_at(mine_mask, u), base - start + u, fx, &fy, cfg);
                }
            });
        }
        if all8(p0.done() && p1.done() && p2.done() && p3.done()) {
            break;
        }
        base += 8;
    }
}

/// The forward rasterizer ([`rasterize_fwd`], [`rasterize_fwd_half`]).
#[inline]
fn rasterize_fwd_in<S: LaneSplat>(
    b: &Block,
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
) {
    let cfg = BlendSettings::<f32>::from_frame(frame);
    let (start, end) = (ranges[2 * b.tile], ranges[2 * b.tile + 1]);
    let (mut p0, mut p1, mut p2, mut p3) = (
        PixelFwd::new(),
        PixelFwd::new(),
        PixelFwd::new(),
        PixelFwd::new(),
    );
    p0.done = !b.inside[0];
    p1.done = !b.inside[1];
    p2.done = !b.inside[2];
    p3.done = !b.inside[3];
    if end - start <= SPARSE_MAX_WALK {
        walk_fwd::<S, true>(
            &mut p0,
            &mut p1,
            &mut p2,
            &mut p3,
            b,
            &cfg,
            start,
            end,
            splats,
            isect_values,
        );
    } else {
        walk_fwd::<S, false>(
            &mut p0,
            &mut p1,
            &mut p2,
            &mut p3,
            b,
            &cfg,
            start,
            end,
            splats,
            isect_values,
        );
    }
    if b.inside[0] {
        store_pixel_fwd(
            b.pixel(0, frame),
            &p0,
            frame,
            rgb,
            alpha,
            depth,
            contributors,
            transmittance,
            blended,
        );
    }
    if b.inside[1] {
        store_pixel_fwd(
            b.pixel(1, frame),
            &p1,
            frame,
            rgb,
            alpha,
            depth,
            contributors,
            transmittance,
            blended,
        );
    }
    if b.inside[2] {
        store_pixel_fwd(
            b.pixel(2, frame),
            &p2,
            frame,
            rgb,
            alpha,
            depth,
            contributors,
            transmittance,
            blended,
        );
    }
    if b.inside[3] {
        store_pixel_fwd(
            b.pixel(3, frame),
            &p3,
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

/// `splat::rasterize_fwd` for CPU devices with subgroups of 8.
#[spirv(compute(threads(8)))]
pub fn rasterize_fwd(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(local_invocation_index)] lane: u32,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[SplatQuads],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] isect_values: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] ranges: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] rgb: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] alpha: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] depth: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] contributors: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] transmittance: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] blended: &mut [u32],
) {
    rasterize_fwd_in(
        &Block::new(group, lane, frame),
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
    );
}

/// `splat::rasterize_fwd_half` for CPU devices with subgroups of 8.
#[spirv(compute(threads(8)))]
pub fn rasterize_fwd_half(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(local_invocation_index)] lane: u32,
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
) {
    rasterize_fwd_in(
        &Block::new(group, lane, frame),
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
    );
}

/// The fused forward rasterizer ([`rasterize_fused_fwd`], [`rasterize_fused_fwd_half`]).
#[inline]
fn rasterize_fused_fwd_in<S: LaneSplat>(
    b: &Block,
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
) {
    let cfg = BlendSettings::<f32>::from_frame(frame);
    let (start, end) = (ranges[2 * b.tile], ranges[2 * b.tile + 1]);
    let (mut p0, mut p1, mut p2, mut p3) = (
        fused_pixel(b.inside[0]),
        fused_pixel(b.inside[1]),
        fused_pixel(b.inside[2]),
        fused_pixel(b.inside[3]),
    );
    if end - start <= SPARSE_MAX_WALK {
        walk_fused::<S, true>(
            &mut p0,
            &mut p1,
            &mut p2,
            &mut p3,
            b,
            &cfg,
            start,
            end,
            splats,
            isect_values,
            masks,
        );
    } else {
        walk_fused::<S, false>(
            &mut p0,
            &mut p1,
            &mut p2,
            &mut p3,
            b,
            &cfg,
            start,
            end,
            splats,
            isect_values,
            masks,
        );
    }
    if b.inside[0] {
        store_pixel_fused(
            b.pixel(0, frame),
            &p0,
            frame,
            base_rgb,
            over_rgb,
            over_alpha,
            matte_rgb,
            transmittances,
            ends,
        );
    }
    if b.inside[1] {
        store_pixel_fused(
            b.pixel(1, frame),
            &p1,
            frame,
            base_rgb,
            over_rgb,
            over_alpha,
            matte_rgb,
            transmittances,
            ends,
        );
    }
    if b.inside[2] {
        store_pixel_fused(
            b.pixel(2, frame),
            &p2,
            frame,
            base_rgb,
            over_rgb,
            over_alpha,
            matte_rgb,
            transmittances,
            ends,
        );
    }
    if b.inside[3] {
        store_pixel_fused(
            b.pixel(3, frame),
            &p3,
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

/// `splat::rasterize_fused_fwd` for CPU devices with subgroups of 8.
#[spirv(compute(threads(8)))]
pub fn rasterize_fused_fwd(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(local_invocation_index)] lane: u32,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] frame: &FrameParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] splats: &[SplatQuads],
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
    rasterize_fused_fwd_in(
        &Block::new(group, lane, frame),
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
    );
}

/// `splat::rasterize_fused_fwd_half` for CPU devices with subgroups of 8.
#[spirv(compute(threads(8)))]
pub fn rasterize_fused_fwd_half(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(local_invocation_index)] lane: u32,
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
) {
    rasterize_fused_fwd_in(
        &Block::new(group, lane, frame),
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
    );
}

/// The sum over the subgroup's 8 lanes of each of a splat's 10 gradient floats, in
/// every lane. No vote on whether any pixel was hit: llvmpipe would run the sums anyway
/// (it predicates every `if`), and a zero sum adds nothing.
#[inline]
fn block_sums(g: &[f32; SPLAT_GRAD_FLOATS]) -> [f32; SPLAT_GRAD_FLOATS] {
    let mut total = [0.0f32; SPLAT_GRAD_FLOATS];
    drape_shared::each_index!(10, c => {
        total[c] = sum8(g[c]);
    });
    total
}

/// `g += grad`, written out.
#[inline]
fn add_into(g: &mut [f32; SPLAT_GRAD_FLOATS], grad: &[f32; SPLAT_GRAD_FLOATS]) {
    drape_shared::each_index!(10, c => {
        g[c] += grad[c];
    });
}

/// A pixel's backward state as the walks step it: plain ([`PixelBwd`]) or fused
/// ([`FusedPixelBwd`], which also reads the splat's layer mask and list index).
trait BwdPixel {
    fn grad(
        &mut self,
        v: &SplatView<f32>,
        mask: u32,
        at: u32,
        fx: f32,
        fy: f32,
        cfg: &BlendSettings<f32>,
    ) -> Option<SplatGrad<f32>>;
}

impl BwdPixel for PixelBwd<f32> {
    #[inline]
    fn grad(
        &mut self,
        v: &SplatView<f32>,
        _mask: u32,
        _at: u32,
        fx: f32,
        fy: f32,
        cfg: &BlendSettings<f32>,
    ) -> Option<SplatGrad<f32>> {
        self.step(v, fx, fy, cfg)
    }
}

impl BwdPixel for FusedPixelBwd<f32> {
    #[inline]
    fn grad(
        &mut self,
        v: &SplatView<f32>,
        mask: u32,
        at: u32,
        fx: f32,
        fy: f32,
        cfg: &BlendSettings<f32>,
    ) -> Option<SplatGrad<f32>> {
        self.step(v, mask, at, fx, fy, cfg)
    }
}

/// Splat `v`'s (layer mask `mask`, the list's `at`-th) gradient from those of a lane's
/// 4 pixels that blended it (`at` before their ends `e`), summed over the subgroup
/// ([`block_sums`]). Four variables, not a struct of four, as [`blend_quad`].
#[inline]
fn quad_grad<P: BwdPixel>(
    p0: &mut P,
    p1: &mut P,
    p2: &mut P,
    p3: &mut P,
    e: [u32; 4],
    v: &SplatView<f32>,
    mask: u32,
    at: u32,
    fx: f32,
    fy: &[f32; 4],
    cfg: &BlendSettings<f32>,
) -> [f32; SPLAT_GRAD_FLOATS] {
    let mut g = [0.0f32; SPLAT_GRAD_FLOATS];
    if at < e[0] {
        if let Some(grad) = p0.grad(v, mask, at, fx, fy[0], cfg) {
            add_into(&mut g, &grad.to_array());
        }
    }
    if at < e[1] {
        if let Some(grad) = p1.grad(v, mask, at, fx, fy[1], cfg) {
            add_into(&mut g, &grad.to_array());
        }
    }
    if at < e[2] {
        if let Some(grad) = p2.grad(v, mask, at, fx, fy[2], cfg) {
            add_into(&mut g, &grad.to_array());
        }
    }
    if at < e[3] {
        if let Some(grad) = p3.grad(v, mask, at, fx, fy[3], cfg) {
            add_into(&mut g, &grad.to_array());
        }
    }
    block_sums(&g)
}

/// Row `r`'s backward state and how many of the tile's splats it blended up to its
/// last (0 outside the image).
#[inline]
fn pixel_bwd(
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

/// The backward walk: the tile's list from its `last`-th splat back to its first, 8 a
/// round (lane `l` loads the `l`-th from the back); per splat the lanes' gradients
/// (4 pixels each) are summed across the subgroup and the splat's lane adds the sum
/// once, so a splat costs 10 adds per block instead of 10 per pixel. `SPARSE` as in
/// [`walk_fwd`].
#[inline]
fn walk_bwd<A: GradAdd, const SPARSE: bool>(
    p0: &mut PixelBwd<f32>,
    p1: &mut PixelBwd<f32>,
    p2: &mut PixelBwd<f32>,
    p3: &mut PixelBwd<f32>,
    e: [u32; 4],
    b: &Block,
    cfg: &BlendSettings<f32>,
    start: u32,
    last: u32,
    splats: &[SplatQuads],
    isect_values: &[u32],
    splat_grads: &mut [A::Word],
) {
    let (lane, fx, fy) = (b.lane, b.fx, b.fy);
    let mut top = last;
    // Uniform loop: `top` is the number of the tile's splats still to visit.
    while top > 0 {
        let len = if top < 8 { top } else { 8 };
        let id = isect_values[(start + b.back_index(top, len)) as usize];
        let mine = splats[id as usize].hold();
        // The subgroup's sums for this lane's splat.
        let mut sums = [0.0f32; SPLAT_GRAD_FLOATS];
        if SPARSE {
            // The round's splats that may reach the block, back to front (lowest lane
            // first); the others send nothing.
            let mut todo =
                ballot8(lane < len && may_touch_rect(&mine.raster_view(), b.lo, b.hi, cfg));
            while todo != 0 {
                let u = todo.trailing_zeros();
                todo &= todo - 1;
                let total = quad_grad(
                    p0,
                    p1,
                    p2,
                    p3,
                    e,
                    &SplatQuads::lane_view(mine, u),
                    0,
                    top - 1 - u,
                    fx,
                    &fy,
                    cfg,
                );
                if lane == u {
                    sums = total;
                }
            }
        } else {
            drape_shared::each_index!(8, u => {
                let u = u as u32;
                if u < len {
                    let total = quad_grad(p0, p1, p2, p3, e, &SplatQuads::lane_view(mine, u), 0, top - 1 - u, fx, &fy, cfg);
                    if lane == u {
                        sums = total;
                    }
                }
            });
        }
        // One lane per splat adds the block's sum (the adds skip zeros).
        if lane < len {
            add_splat_grad::<A>(splat_grads, id as usize, &sums);
        }
        top -= len;
    }
}

/// The backward rasterizer ([`rasterize_bwd_atomic`], [`rasterize_bwd_cas`],
/// [`rasterize_bwd_fixed`]): [`walk_bwd`], sparse up to `sparse_max` splats.
#[inline]
fn rasterize_bwd_in<A: GradAdd>(
    b: &Block,
    frame: &FrameParams,
    splats: &[SplatQuads],
    isect_values: &[u32],
    ranges: &[u32],
    contributors: &[u32],
    transmittance: &[f32],
    grad_rgb: &[f32],
    grad_alpha: &[f32],
    grad_depth: &[f32],
    splat_grads: &mut [A::Word],
    sparse_max: u32,
) {
    let cfg = BlendSettings::<f32>::from_frame(frame);
    let start = ranges[2 * b.tile];
    let (mut p0, e0) = pixel_bwd(
        b,
        0,
        frame,
        contributors,
        transmittance,
        grad_rgb,
        grad_alpha,
        grad_depth,
    );
    let (mut p1, e1) = pixel_bwd(
        b,
        1,
        frame,
        contributors,
        transmittance,
        grad_rgb,
        grad_alpha,
        grad_depth,
    );
    let (mut p2, e2) = pixel_bwd(
        b,
        2,
        frame,
        contributors,
        transmittance,
        grad_rgb,
        grad_alpha,
        grad_depth,
    );
    let (mut p3, e3) = pixel_bwd(
        b,
        3,
        frame,
        contributors,
        transmittance,
        grad_rgb,
        grad_alpha,
        grad_depth,
    );
    let e = [e0, e1, e2, e3];
    let last = max8_u32(e0.max(e1).max(e2.max(e3)));
    if last <= sparse_max {
        walk_bwd::<A, true>(
            &mut p0,
            &mut p1,
            &mut p2,
            &mut p3,
            e,
            b,
            &cfg,
            start,
            last,
            splats,
            isect_values,
            splat_grads,
        );
    } else {
        walk_bwd::<A, false>(
            &mut p0,
            &mut p1,
            &mut p2,
            &mut p3,
            e,
            b,
            &cfg,
            start,
            last,
            splats,
            isect_values,
            splat_grads,
        );
    }
}

/// `splat::rasterize_bwd_atomic` for CPU devices with subgroups of 8: float atomics.
#[cfg(feature = "float-atomics")]
#[spirv(compute(threads(8)))]
pub fn rasterize_bwd_atomic(
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
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] splat_grads: &mut [f32],
) {
    rasterize_bwd_in::<FloatAtomics>(
        &Block::new(group, lane, frame),
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
        SPARSE_MAX_WALK,
    );
}

/// `splat::rasterize_bwd_cas` for CPU devices with subgroups of 8: compare-and-swap on the bits of f32.
#[spirv(compute(threads(8)))]
pub fn rasterize_bwd_cas(
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
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] splat_grads: &mut [u32],
) {
    rasterize_bwd_in::<CompareAndSwap>(
        &Block::new(group, lane, frame),
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
        SPARSE_MAX_WALK_CAS,
    );
}

/// `splat::rasterize_bwd_fixed` for CPU devices with subgroups of 8: 64-bit fixed point (deterministic).
#[spirv(compute(threads(8)))]
pub fn rasterize_bwd_fixed(
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
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] splat_grads: &mut [u32],
) {
    rasterize_bwd_in::<FixedPoint>(
        &Block::new(group, lane, frame),
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
        SPARSE_MAX_WALK,
    );
}

/// Row `r`'s fused backward state (its three backward walks; saturated from the start
/// outside the image, where its end is 0).
#[inline]
fn pixel_fused_bwd(
    b: &Block,
    r: u32,
    frame: &FrameParams,
    transmittances: &[f32],
    ends: &[u32],
    grad_base: &[f32],
    grad_over: &[f32],
    grad_over_alpha: &[f32],
    grad_matte: &[f32],
) -> FusedPixelBwd<f32> {
    if !b.inside[r as usize] {
        return FusedPixelBwd::new(
            [1.0; 3],
            [0; 3],
            frame.background,
            [0.0; 3],
            [0.0; 3],
            0.0,
            0.0,
        );
    }
    let p = b.pixel(r, frame);
    FusedPixelBwd::new(
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
}

/// [`walk_bwd`] for the fused backward: each splat's layer mask shuffled beside it.
#[inline]
fn walk_fused_bwd<A: GradAdd, const SPARSE: bool>(
    p0: &mut FusedPixelBwd<f32>,
    p1: &mut FusedPixelBwd<f32>,
    p2: &mut FusedPixelBwd<f32>,
    p3: &mut FusedPixelBwd<f32>,
    e: [u32; 4],
    b: &Block,
    cfg: &BlendSettings<f32>,
    start: u32,
    last: u32,
    splats: &[SplatQuads],
    isect_values: &[u32],
    masks: &[u32],
    splat_grads: &mut [A::Word],
) {
    let (lane, fx, fy) = (b.lane, b.fx, b.fy);
    let mut top = last;
    while top > 0 {
        let len = if top < 8 { top } else { 8 };
        let id = isect_values[(start + b.back_index(top, len)) as usize];
        let mine = splats[id as usize].hold();
        let mine_mask = masks[id as usize];
        let mut sums = [0.0f32; SPLAT_GRAD_FLOATS];
        if SPARSE {
            let mut todo =
                ballot8(lane < len && may_touch_rect(&mine.raster_view(), b.lo, b.hi, cfg));
            while todo != 0 {
                let u = todo.trailing_zeros();
                todo &= todo - 1;
                let mask = broadcast_u32_at(mine_mask, u);
                let total = quad_grad(
                    p0,
                    p1,
                    p2,
                    p3,
                    e,
                    &SplatQuads::lane_view(mine, u),
                    mask,
                    top - 1 - u,
                    fx,
                    &fy,
                    cfg,
                );
                if lane == u {
                    sums = total;
                }
            }
        } else {
            drape_shared::each_index!(8, u => {
                let u = u as u32;
                if u < len {
                    let mask = broadcast_u32_at(mine_mask, u);
                    let total = quad_grad(p0, p1, p2, p3, e, &SplatQuads::lane_view(mine, u), mask, top - 1 - u, fx, &fy, cfg);
                    if lane == u {
                        sums = total;
                    }
                }
            });
        }
        if lane < len {
            add_splat_grad::<A>(splat_grads, id as usize, &sums);
        }
        top -= len;
    }
}

/// The fused backward ([`rasterize_fused_bwd_atomic`], [`rasterize_fused_bwd_cas`],
/// [`rasterize_fused_bwd_fixed`]): [`walk_fused_bwd`], sparse up to `sparse_max`.
#[inline]
fn rasterize_fused_bwd_in<A: GradAdd>(
    b: &Block,
    frame: &FrameParams,
    splats: &[SplatQuads],
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
    sparse_max: u32,
) {
    let cfg = BlendSettings::<f32>::from_frame(frame);
    let start = ranges[2 * b.tile];
    let mut p0 = pixel_fused_bwd(
        b,
        0,
        frame,
        transmittances,
        ends,
        grad_base,
        grad_over,
        grad_over_alpha,
        grad_matte,
    );
    let mut p1 = pixel_fused_bwd(
        b,
        1,
        frame,
        transmittances,
        ends,
        grad_base,
        grad_over,
        grad_over_alpha,
        grad_matte,
    );
    let mut p2 = pixel_fused_bwd(
        b,
        2,
        frame,
        transmittances,
        ends,
        grad_base,
        grad_over,
        grad_over_alpha,
        grad_matte,
    );
    let mut p3 = pixel_fused_bwd(
        b,
        3,
        frame,
        transmittances,
        ends,
        grad_base,
        grad_over,
        grad_over_alpha,
        grad_matte,
    );
    let e = [p0.end(), p1.end(), p2.end(), p3.end()];
    let last = max8_u32(e[0].max(e[1]).max(e[2].max(e[3])));
    if last <= sparse_max {
        walk_fused_bwd::<A, true>(
            &mut p0,
            &mut p1,
            &mut p2,
            &mut p3,
            e,
            b,
            &cfg,
            start,
            last,
            splats,
            isect_values,
            masks,
            splat_grads,
        );
    } else {
        walk_fused_bwd::<A, false>(
            &mut p0,
            &mut p1,
            &mut p2,
            &mut p3,
            e,
            b,
            &cfg,
            start,
            last,
            splats,
            isect_values,
            masks,
            splat_grads,
        );
    }
}

/// `splat::rasterize_fused_bwd_atomic` for CPU devices with subgroups of 8: float atomics.
#[cfg(feature = "float-atomics")]
#[spirv(compute(threads(8)))]
pub fn rasterize_fused_bwd_atomic(
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
    #[spirv(storage_buffer, descriptor_set = 0, binding = 11)] splat_grads: &mut [f32],
) {
    rasterize_fused_bwd_in::<FloatAtomics>(
        &Block::new(group, lane, frame),
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
        SPARSE_MAX_WALK,
    );
}

/// `splat::rasterize_fused_bwd_cas` for CPU devices with subgroups of 8: compare-and-swap on the bits of f32.
#[spirv(compute(threads(8)))]
pub fn rasterize_fused_bwd_cas(
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
    #[spirv(storage_buffer, descriptor_set = 0, binding = 11)] splat_grads: &mut [u32],
) {
    rasterize_fused_bwd_in::<CompareAndSwap>(
        &Block::new(group, lane, frame),
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
        SPARSE_MAX_WALK_CAS,
    );
}

/// `splat::rasterize_fused_bwd_fixed` for CPU devices with subgroups of 8: 64-bit fixed point (deterministic).
#[spirv(compute(threads(8)))]
pub fn rasterize_fused_bwd_fixed(
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
    #[spirv(storage_buffer, descriptor_set = 0, binding = 11)] splat_grads: &mut [u32],
) {
    rasterize_fused_bwd_in::<FixedPoint>(
        &Block::new(group, lane, frame),
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
        SPARSE_MAX_WALK,
    );
}
