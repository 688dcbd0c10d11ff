//! The CPU reference renderer: the same shared functions as the kernels, run on the
//! host, generic over the float type (f32 to check the GPU, f64 for gradient checks).
//!
//! Binning is the GPU's, done directly: splats in a stable order of their f32 depth
//! bits (culled ones last), then each tile's list in that order. Intersections beyond
//! what is used are not materialised.

use drape_shared::real::Real;
use drape_shared::splat::layout::{FrameParams, HalfSplat};
use drape_shared::splat::project::{
    project_bwd, project_fwd, tile_rect, Camera, Gaussian, GaussianGrad, Projection, SplatGrad,
};
use drape_shared::splat::raster::{
    BlendSettings, FusedPixel, FusedPixelBwd, PixelBwd, PixelFwd, SplatView,
};

/// A forward render and what the backward pass needs of it.
#[derive(Clone, Debug)]
pub struct ReferenceRender<F> {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// 3 per pixel, row-major.
    pub rgb: Vec<F>,
    /// 1 per pixel: `1 − T`.
    pub alpha: Vec<F>,
    /// `Σ wᵢ zᵢ` per pixel.
    pub depth: Vec<F>,
    /// Per pixel, how many splats of its tile list it blended.
    pub contributors: Vec<u32>,
    /// Per pixel, the transmittance left after the last splat.
    pub transmittance: Vec<F>,
    /// Gaussian-pixel blend steps.
    pub blend_steps: u64,
    /// Gaussians dropped for non-finite parameters.
    pub dropped: u32,
    /// Tile intersections.
    pub intersections: u64,
    /// Each Gaussian's projection (its splat in screen space).
    pub projections: Vec<Projection<F>>,
    /// Per tile, the Gaussians in blending order.
    pub tile_lists: Vec<Vec<u32>>,
}

fn view<F: Real>(p: &Projection<F>) -> SplatView<F> {
    SplatView {
        x: p.x,
        y: p.y,
        depth: p.depth,
        conic: p.conic,
        opacity: p.opacity,
        color: p.color,
    }
}

/// Renders `gaussians` with the camera and settings of `frame` (its `count` is ignored).
pub fn render<F: Real>(gaussians: &[Gaussian<F>], frame: &FrameParams) -> ReferenceRender<F> {
    render_with(gaussians, frame, |v| v)
}

/// [`render`] rasterizing half-precision projected splats, as the GPU does with
/// `RenderSettings::half_splats`: each splat's view packed to a [`HalfSplat`] and
/// unpacked (binning from the f32 projection, as there).
pub fn render_half_splats(
    gaussians: &[Gaussian<f32>],
    frame: &FrameParams,
) -> ReferenceRender<f32> {
    render_with(gaussians, frame, |v| HalfSplat::pack(&v).view())
}

/// [`render`] with every splat's view passed through `rasterized` before blending.
fn render_with<F: Real>(
    gaussians: &[Gaussian<F>],
    frame: &FrameParams,
    rasterized: impl Fn(SplatView<F>) -> SplatView<F>,
) -> ReferenceRender<F> {
    let cam = Camera::<F>::from_frame(frame);
    let cfg = BlendSettings::<F>::from_frame(frame);
    let projections: Vec<Projection<F>> = gaussians.iter().map(|g| project_fwd(g, &cam)).collect();
    let rects: Vec<Option<[u32; 4]>> = projections
        .iter()
        .map(|p| {
            p.visible
                .then(|| {
                    tile_rect(
                        p.x,
                        p.y,
                        p.radius,
                        frame.tile_size,
                        frame.tiles_x,
                        frame.tiles_y,
                    )
                })
                .filter(|r| r[2] > r[0] && r[3] > r[1])
        })
        .collect();
    let mut order: Vec<u32> = (0..gaussians.len() as u32).collect();
    let key = |i: u32| match rects[i as usize] {
        Some(_) => projections[i as usize].depth.to_f32().to_bits(),
        None => u32::MAX,
    };
    order.sort_by_key(|&i| key(i)); // stable, like the GPU radix sort
    let tiles = (frame.tiles_x * frame.tiles_y) as usize;
    let mut tile_lists = vec![Vec::new(); tiles];
    let mut intersections = 0u64;
    for &g in &order {
        if let Some(r) = rects[g as usize] {
            for ty in r[1]..r[3] {
                for tx in r[0]..r[2] {
                    tile_lists[(ty * frame.tiles_x + tx) as usize].push(g);
                    intersections += 1;
                }
            }
        }
    }

    let (w, h) = (frame.width, frame.height);
    let pixels = (w * h) as usize;
    let mut out = ReferenceRender {
        width: w,
        height: h,
        rgb: vec![F::zero(); 3 * pixels],
        alpha: vec![F::zero(); pixels],
        depth: vec![F::zero(); pixels],
        contributors: vec![0; pixels],
        transmittance: vec![F::one(); pixels],
        blend_steps: 0,
        dropped: projections.iter().filter(|p| p.dropped).count() as u32,
        intersections,
        projections: Vec::new(),
        tile_lists: Vec::new(),
    };
    let background = frame.background.map(F::of);
    for py in 0..h {
        for px in 0..w {
            let tile = ((py / frame.tile_size) * frame.tiles_x + px / frame.tile_size) as usize;
            let (fx, fy) = (F::of(px as f32 + 0.5), F::of(py as f32 + 0.5));
            let mut state = PixelFwd::<F>::new();
            for (k, &g) in tile_lists[tile].iter().enumerate() {
                state.blend(
                    &rasterized(view(&projections[g as usize])),
                    k as u32,
                    fx,
                    fy,
                    &cfg,
                );
                if state.done {
                    break;
                }
            }
            let p = (py * w + px) as usize;
            let c = state.rgb(background);
            out.rgb[3 * p..3 * p + 3].copy_from_slice(&c);
            out.alpha[p] = F::one() - state.transmittance;
            out.depth[p] = state.depth;
            out.contributors[p] = state.contributors;
            out.transmittance[p] = state.transmittance;
            out.blend_steps += u64::from(state.blended);
        }
    }
    out.projections = projections;
    out.tile_lists = tile_lists;
    out
}

/// Gradients of a loss with respect to every Gaussian's parameters, given the loss's
/// gradient on each pixel's colour (3 per pixel), alpha and depth. Also returns the
/// per-splat gradients (the GPU's intermediate) for checking.
pub fn backward<F: Real>(
    gaussians: &[Gaussian<F>],
    frame: &FrameParams,
    fwd: &ReferenceRender<F>,
    grad_rgb: &[F],
    grad_alpha: &[F],
    grad_depth: &[F],
) -> (Vec<GaussianGrad<F>>, Vec<SplatGrad<F>>) {
    let cam = Camera::<F>::from_frame(frame);
    let cfg = BlendSettings::<F>::from_frame(frame);
    let background = frame.background.map(F::of);
    let mut splat_grads = vec![SplatGrad::<F>::zero(); gaussians.len()];
    for py in 0..fwd.height {
        for px in 0..fwd.width {
            let p = (py * fwd.width + px) as usize;
            let tile = ((py / frame.tile_size) * frame.tiles_x + px / frame.tile_size) as usize;
            let (fx, fy) = (F::of(px as f32 + 0.5), F::of(py as f32 + 0.5));
            let mut state = PixelBwd::new(
                fwd.transmittance[p],
                background,
                [grad_rgb[3 * p], grad_rgb[3 * p + 1], grad_rgb[3 * p + 2]],
                grad_alpha[p],
                grad_depth[p],
            );
            let list = &fwd.tile_lists[tile];
            for &g in list[..fwd.contributors[p] as usize].iter().rev() {
                if let Some(d) = state.step(&view(&fwd.projections[g as usize]), fx, fy, &cfg) {
                    splat_grads[g as usize] = splat_grads[g as usize].add(&d);
                }
            }
        }
    }
    (
        project_grads(gaussians, &cam, &fwd.projections, &splat_grads),
        splat_grads,
    )
}

/// Every Gaussian's parameter gradients from its splat's (culled ones get zeros).
fn project_grads<F: Real>(
    gaussians: &[Gaussian<F>],
    cam: &Camera<F>,
    projections: &[Projection<F>],
    splat_grads: &[SplatGrad<F>],
) -> Vec<GaussianGrad<F>> {
    gaussians
        .iter()
        .zip(projections)
        .zip(splat_grads)
        .map(|((g, p), up)| {
            if p.visible {
                project_bwd(g, cam, up)
            } else {
                GaussianGrad::zero()
            }
        })
        .collect()
}

/// The fused rasterizer's forward on the CPU (`ops::splat::fused`): per pixel, the
/// three states of [`FusedPixel`] over the merged tile list of `fwd` (a [`render`] of
/// the merged cloud, for its projections and lists), with each Gaussian's layer mask.
#[derive(Clone, Debug)]
pub struct FusedReference<F> {
    /// 3 per pixel: the base over the frame's background, the over pass over black, the
    /// matte (all three channels equal).
    pub base_rgb: Vec<F>,
    /// 3 per pixel: the over pass over black.
    pub over_rgb: Vec<F>,
    /// 1 per pixel: the over pass's alpha.
    pub over_alpha: Vec<F>,
    /// 3 per pixel: the matte.
    pub matte_rgb: Vec<F>,
    /// 3 per pixel (base, over, matte).
    pub transmittances: Vec<F>,
    /// 3 per pixel (base, over, matte): where each state stopped in the tile's list.
    pub ends: Vec<u32>,
}

/// Runs the fused forward over `fwd`'s merged lists (see [`FusedReference`]).
pub fn fused_render<F: Real>(
    fwd: &ReferenceRender<F>,
    masks: &[u32],
    frame: &FrameParams,
) -> FusedReference<F> {
    let cfg = BlendSettings::<F>::from_frame(frame);
    let pixels = (fwd.width * fwd.height) as usize;
    let z = F::zero();
    let mut out = FusedReference {
        base_rgb: vec![z; 3 * pixels],
        over_rgb: vec![z; 3 * pixels],
        over_alpha: vec![z; pixels],
        matte_rgb: vec![z; 3 * pixels],
        transmittances: vec![F::one(); 3 * pixels],
        ends: vec![0; 3 * pixels],
    };
    let background = frame.background.map(F::of);
    for py in 0..fwd.height {
        for px in 0..fwd.width {
            let p = (py * fwd.width + px) as usize;
            let tile = ((py / frame.tile_size) * frame.tiles_x + px / frame.tile_size) as usize;
            let (fx, fy) = (F::of(px as f32 + 0.5), F::of(py as f32 + 0.5));
            let mut state = FusedPixel::<F>::new();
            for (k, &g) in fwd.tile_lists[tile].iter().enumerate() {
                state.blend(
                    &view(&fwd.projections[g as usize]),
                    masks[g as usize],
                    k as u32,
                    fx,
                    fy,
                    &cfg,
                );
                if state.done() {
                    break;
                }
            }
            out.base_rgb[3 * p..3 * p + 3].copy_from_slice(&state.base.rgb(background));
            out.over_rgb[3 * p..3 * p + 3].copy_from_slice(&state.over.color);
            out.over_alpha[p] = F::one() - state.over.transmittance;
            out.matte_rgb[3 * p..3 * p + 3].copy_from_slice(&state.matte.color);
            out.transmittances[3 * p..3 * p + 3].copy_from_slice(&state.transmittances());
            out.ends[3 * p..3 * p + 3].copy_from_slice(&state.ends());
        }
    }
    out
}

/// The fused backward on the CPU: gradients of a loss with respect to every Gaussian of
/// the merged cloud, given the loss's gradients on the base rgb, the over rgb and
/// alpha, and the matte (channel 0 of 3 per pixel); also the per-splat gradients.
#[allow(clippy::too_many_arguments)]
pub fn fused_backward<F: Real>(
    gaussians: &[Gaussian<F>],
    masks: &[u32],
    frame: &FrameParams,
    fwd: &ReferenceRender<F>,
    fused: &FusedReference<F>,
    grad_base: &[F],
    grad_over: &[F],
    grad_over_alpha: &[F],
    grad_matte: &[F],
) -> (Vec<GaussianGrad<F>>, Vec<SplatGrad<F>>) {
    let cam = Camera::<F>::from_frame(frame);
    let cfg = BlendSettings::<F>::from_frame(frame);
    let background = frame.background.map(F::of);
    let mut splat_grads = vec![SplatGrad::<F>::zero(); gaussians.len()];
    for py in 0..fwd.height {
        for px in 0..fwd.width {
            let p = (py * fwd.width + px) as usize;
            let tile = ((py / frame.tile_size) * frame.tiles_x + px / frame.tile_size) as usize;
            let (fx, fy) = (F::of(px as f32 + 0.5), F::of(py as f32 + 0.5));
            let three = |v: &[F]| [v[3 * p], v[3 * p + 1], v[3 * p + 2]];
            let mut state = FusedPixelBwd::new(
                three(&fused.transmittances),
                [
                    fused.ends[3 * p],
                    fused.ends[3 * p + 1],
                    fused.ends[3 * p + 2],
                ],
                background,
                three(grad_base),
                three(grad_over),
                grad_over_alpha[p],
                grad_matte[3 * p],
            );
            let list = &fwd.tile_lists[tile];
            for (k, &g) in list.iter().enumerate().take(state.end() as usize).rev() {
                if let Some(d) = state.step(
                    &view(&fwd.projections[g as usize]),
                    masks[g as usize],
                    k as u32,
                    fx,
                    fy,
                    &cfg,
                ) {
                    splat_grads[g as usize] = splat_grads[g as usize].add(&d);
                }
            }
        }
    }
    (
        project_grads(gaussians, &cam, &fwd.projections, &splat_grads),
        splat_grads,
    )
}
