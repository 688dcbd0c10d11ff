//! The fused three-pass frame: one depth sort of one cloud holding every pass's
//! Gaussians (each with a mask naming the passes it is drawn in), one tile binning, and
//! one rasterization (`splat::rasterize_fused_fwd`) that keeps three blending states
//! per pixel and writes the base image, the over pass's image and alpha, and the matte
//! in a single walk of each tile, for the composite of `ops::splat::composite`.
//!
//! Each state's Gaussians keep their depth order in the merged list (the sort is
//! stable and each pass's cloud is a subsequence of the fused one in the same order),
//! so each state sums the same terms in the same order as its own pass: the three
//! images equal the three-pass renders within float tolerance (tested). The masks
//! (`drape_shared::splat::raster::FUSED_*`, one per Gaussian, set by the caller) say
//! which states a Gaussian blends into and in which matte colour; the trainer's
//! `avatar::composite::layer_masks` makes the paper's matte (the cloth against the
//! scene) or the occlusion-correct one (the body hides the cloth too).
//!
//! The backward ([`FusedRenderer::backward`]) walks the same merged list back to front
//! once, each pixel running its three states' backward walks from where the forward
//! left them (each state's final transmittance and end in the merged list, saved per
//! pixel) and adding each Gaussian the sum of what its states send it: the three
//! passes' backward passes summed, with no colour gradient from the matte (its colour
//! is fixed). Like the forward, it runs the workgroup kernels on GPUs and their
//! subgroup twins on CPU devices with subgroups of 8 (`RasterVariant`).

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::Result;
use crate::kernels;
use crate::ops::accumulate::{Accumulation, Method};
use crate::ops::splat::composite::CompositeInputs;
use crate::ops::splat::render::{ForwardStats, GaussianBuffers, SavedForward, SplatRenderer};
use crate::ops::splat::scene::{PinholeCamera, RenderSettings};
use crate::recorder::{PassTimings, Recording};

/// A fused renderer for clouds of up to `max_count` Gaussians at one image size.
pub struct FusedRenderer {
    ctx: Context,
    renderer: SplatRenderer,
    masks: Buffer,
    base_rgb: Buffer,
    over_rgb: Buffer,
    over_alpha: Buffer,
    matte_rgb: Buffer,
    /// Per pixel, each state's final transmittance (base, over, matte).
    transmittances: Buffer,
    /// Per pixel, each state's end in the merged tile list.
    ends: Buffer,
    pixels: u32,
}

/// The upstream gradients of a fused backward: on the base rgb and the over rgb (3 per
/// pixel), the over alpha (1 per pixel) and the matte (3 per pixel, only channel 0
/// read: the composite's backward writes the visibility's gradient there).
#[derive(Clone, Copy)]
pub struct FusedGrads<'a> {
    /// Gradient on the base rgb.
    pub base_rgb: &'a Buffer,
    /// Gradient on the over rgb.
    pub over_rgb: &'a Buffer,
    /// Gradient on the over alpha.
    pub over_alpha: &'a Buffer,
    /// Gradient on the matte rgb (channel 0 read).
    pub matte_rgb: &'a Buffer,
}

impl FusedRenderer {
    /// A renderer for `width × height` images of up to `max_count` Gaussians.
    pub fn new(ctx: &Context, width: u32, height: u32, max_count: usize) -> Result<Self> {
        let renderer = SplatRenderer::new(ctx, width, height, max_count)?;
        let pixels = width * height;
        let image = |name: &str, floats: u32| {
            ctx.create_buffer(name, BufferDesc::gpu_only(4 * u64::from(floats)))
        };
        Ok(Self {
            ctx: ctx.clone(),
            renderer,
            masks: ctx.create_buffer(
                "fused layer masks",
                BufferDesc::gpu_only(4 * max_count.max(1) as u64),
            )?,
            base_rgb: image("fused base rgb", 3 * pixels)?,
            over_rgb: image("fused over rgb", 3 * pixels)?,
            over_alpha: image("fused over alpha", pixels)?,
            matte_rgb: image("fused matte", 3 * pixels)?,
            transmittances: image("fused final transmittances", 3 * pixels)?,
            ends: image("fused state ends", 3 * pixels)?,
            pixels,
        })
    }

    /// Chooses the rasterizer kernels (see [`SplatRenderer::set_raster_variant`]).
    pub fn set_raster_variant(
        &mut self,
        variant: crate::ops::splat::render::RasterVariant,
    ) -> Result<()> {
        self.renderer.set_raster_variant(variant)
    }

    /// Sets each Gaussian's mask (`drape_shared::splat::raster::FUSED_*`), in the
    /// cloud's order.
    pub fn set_masks(&mut self, ctx: &Context, masks: &[u32]) -> Result<()> {
        ctx.write_buffer(&mut self.masks, masks)
    }

    /// As [`SplatRenderer::prepare_forward`], with the frame's background under the base.
    pub fn prepare_forward(
        &mut self,
        gaussians: &GaussianBuffers,
        camera: &PinholeCamera,
        settings: &RenderSettings,
    ) -> Result<()> {
        self.renderer.prepare_forward(gaussians, camera, settings)
    }

    /// Records projection, one depth sort, binning and the fused rasterization.
    pub fn record_forward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        gaussians: &'a GaussianBuffers,
    ) -> Result<()> {
        self.renderer.record_binning(rec, gaussians)?;
        let (frame, splats, isect_values, ranges) = self.renderer.binned();
        let (kernel, grid) = if self.renderer.half_splats() {
            self.renderer.raster_dispatch(
                kernels::splat::RasterizeFusedFwdKernel::SplatRasterizeFusedFwdHalf,
                kernels::splat::RasterizeFusedFwdKernel::SplatLavapipeRasterizeFusedFwdHalf,
            )
        } else {
            self.renderer.raster_dispatch(
                kernels::splat::RasterizeFusedFwdKernel::SplatRasterizeFusedFwd,
                kernels::splat::RasterizeFusedFwdKernel::SplatLavapipeRasterizeFusedFwd,
            )
        };
        rec.dispatch_as(
            "splat.rasterize_fused_fwd",
            kernel,
            kernels::splat::RasterizeFusedFwd {
                frame: frame.read(),
                splats: splats.read(),
                isect_values: isect_values.read(),
                ranges: ranges.read(),
                masks: self.masks.read(),
                base_rgb: self.base_rgb.write(),
                over_rgb: self.over_rgb.write(),
                over_alpha: self.over_alpha.write(),
                matte_rgb: self.matte_rgb.write(),
                transmittances: self.transmittances.write(),
                ends: self.ends.write(),
            },
            &(),
            grid,
        )
    }

    /// Records the backward of the last forward into the per-splat gradients and then
    /// every Gaussian's parameter gradients (`out`, written, not accumulated), given
    /// the loss's gradients on the three images, for the forward `saved` names. Call
    /// [`Self::prepare_backward`] first (a deterministic backward panics without it).
    pub fn record_backward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        saved: &SavedForward,
        gaussians: &'a GaussianBuffers,
        grads: FusedGrads<'a>,
        out: &'a GaussianBuffers,
        accumulation: Accumulation,
    ) -> Result<()> {
        self.renderer.refuse_render_only()?;
        self.renderer
            .check_saved("fused backward", saved, gaussians.count)?;
        let method = accumulation.method(&self.ctx);
        let (kernel, grid) = match method {
            Method::FloatAtomics => self.renderer.raster_dispatch(
                kernels::splat::RasterizeFusedBwdAtomicKernel::SplatRasterizeFusedBwdAtomic,
                kernels::splat::RasterizeFusedBwdAtomicKernel::SplatLavapipeRasterizeFusedBwdAtomic,
            ),
            Method::CompareAndSwap => self.renderer.raster_dispatch(
                kernels::splat::RasterizeFusedBwdAtomicKernel::SplatRasterizeFusedBwdCas,
                kernels::splat::RasterizeFusedBwdAtomicKernel::SplatLavapipeRasterizeFusedBwdCas,
            ),
            Method::FixedPoint => self.renderer.raster_dispatch(
                kernels::splat::RasterizeFusedBwdAtomicKernel::SplatRasterizeFusedBwdFixed,
                kernels::splat::RasterizeFusedBwdAtomicKernel::SplatLavapipeRasterizeFusedBwdFixed,
            ),
        };
        let (frame, splats, isect_values, ranges) = self.renderer.binned();
        let target = self.renderer.grad_target(method);
        rec.fill(target, 0);
        rec.dispatch_as(
            "splat.rasterize_fused_bwd",
            kernel,
            kernels::splat::RasterizeFusedBwdAtomic {
                frame: frame.read(),
                splats: splats.read(),
                isect_values: isect_values.read(),
                ranges: ranges.read(),
                masks: self.masks.read(),
                transmittances: self.transmittances.read(),
                ends: self.ends.read(),
                grad_base: grads.base_rgb.read(),
                grad_over: grads.over_rgb.read(),
                grad_over_alpha: grads.over_alpha.read(),
                grad_matte: grads.matte_rgb.read(),
                splat_grads: target.write(),
            },
            &(),
            grid,
        )?;
        self.renderer
            .record_grad_resolve(rec, gaussians.count, method)?;
        self.renderer.record_project_backward(rec, gaussians, out)
    }

    /// Makes what a backward adding with `accumulation` needs (the fixed-point scratch).
    pub fn prepare_backward(&mut self, accumulation: Accumulation) -> Result<()> {
        let method = accumulation.method(&self.ctx);
        self.renderer.make_scratch(method)
    }

    /// The backward in one submission (see [`Self::record_backward`]).
    pub fn backward(
        &mut self,
        saved: &SavedForward,
        gaussians: &GaussianBuffers,
        grads: FusedGrads<'_>,
        out: &GaussianBuffers,
        accumulation: Accumulation,
    ) -> Result<PassTimings> {
        self.prepare_backward(accumulation)?;
        let ctx = self.ctx.clone();
        let mut rec = ctx.record("fused backward")?;
        self.record_backward(&mut rec, saved, gaussians, grads, out, accumulation)?;
        rec.submit_and_wait()
    }

    /// The splatter whose projection, sorts and binning the fused frame uses (its
    /// per-splat gradients are the fused backward's: `ops::splat::densify` reads them).
    pub fn splat_renderer(&self) -> &SplatRenderer {
        &self.renderer
    }

    /// The per-splat gradients of the last backward (10 per Gaussian), for tests.
    pub fn read_splat_grads(&mut self, count: usize) -> Result<Vec<f32>> {
        self.renderer.read_splat_grads(count)
    }

    /// As [`SplatRenderer::finish_forward`].
    pub fn finish_forward(&mut self) -> Result<ForwardStats> {
        self.renderer.finish_forward()
    }

    /// Renders in one submission (two if the intersections outgrew the buffers).
    pub fn forward(
        &mut self,
        ctx: &Context,
        gaussians: &GaussianBuffers,
        camera: &PinholeCamera,
        settings: &RenderSettings,
    ) -> Result<ForwardStats> {
        self.prepare_forward(gaussians, camera, settings)?;
        let mut rerendered = false;
        loop {
            let timings = {
                let mut rec = ctx.record("fused forward")?;
                self.record_forward(&mut rec, gaussians)?;
                rec.submit_and_wait()?
            };
            let stats = self.finish_forward()?;
            if !stats.rerendered {
                return Ok(ForwardStats {
                    rerendered,
                    timings,
                    ..stats
                });
            }
            rerendered = true;
        }
    }

    /// The three images, as the composite reads them (the matte is 3 channels).
    pub fn outputs(&self) -> CompositeInputs<'_> {
        CompositeInputs {
            base_rgb: &self.base_rgb,
            over_rgb: &self.over_rgb,
            over_alpha: &self.over_alpha,
            matte_rgb: Some(&self.matte_rgb),
        }
    }

    /// Per pixel, each state's final transmittance (base, over, matte: 3 floats).
    pub fn transmittances(&self) -> &Buffer {
        &self.transmittances
    }

    /// Pixels of one image.
    pub fn pixels(&self) -> u32 {
        self.pixels
    }

    /// Reads the last forward's (base, over, over alpha, matte) images back.
    pub fn read_images(&mut self) -> Result<[Vec<f32>; 4]> {
        let n = self.pixels as usize;
        let ctx = self.ctx.clone();
        Ok([
            ctx.read_buffer(&mut self.base_rgb, 3 * n)?,
            ctx.read_buffer(&mut self.over_rgb, 3 * n)?,
            ctx.read_buffer(&mut self.over_alpha, n)?,
            ctx.read_buffer(&mut self.matte_rgb, 3 * n)?,
        ])
    }
}
