//! The fused three-pass frame: one depth sort of every layer's Gaussians (each tagged
//! with its layer), one tile binning, and one rasterization (`splat::rasterize_fused_fwd`)
//! that keeps three blending states per pixel and writes the base image (body and
//! scene), the cloth image and alpha, and the matte in a single walk of each tile,
//! for the composite of `ops::splat::composite`.
//!
//! Each state's Gaussians keep their depth order in the merged list (the sort is
//! stable and each pass's cloud is a subsequence of the fused one in the same order),
//! so each state sums the same terms in the same order as its own pass: the three
//! images equal the three-pass renders within float tolerance (tested). Layer masks
//! (`drape_shared::splat::raster::FUSED_*`) say which states a Gaussian blends into,
//! for the paper's matte (cloth against the scene) or the occlusion-correct one (the
//! body hides the cloth too). Forward only: training's backward goes through the three
//! passes.

use drape_shared::splat::raster::{FUSED_BASE, FUSED_CLOTH, FUSED_MATTE_ONE, FUSED_MATTE_ZERO};

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::Result;
use crate::kernels::Kernel;
use crate::ops::splat::composite::CompositeInputs;
use crate::ops::splat::render::{ForwardStats, GaussianBuffers, SplatRenderer};
use crate::ops::splat::scene::{Layer, PinholeCamera, RenderSettings};
use crate::recorder::Recording;

/// The fused rasterizer's layer mask of each Gaussian: body into the base (and, with
/// `occlusion`, into the matte at 0), cloth into the cloth state and the matte at 1,
/// scene into the base and the matte at 0.
pub fn layer_masks(layers: &[Layer], occlusion: bool) -> Vec<u32> {
    layers
        .iter()
        .map(|l| match l {
            Layer::Body if occlusion => FUSED_BASE | FUSED_MATTE_ZERO,
            Layer::Body => FUSED_BASE,
            Layer::Cloth => FUSED_CLOTH | FUSED_MATTE_ONE,
            Layer::Scene => FUSED_BASE | FUSED_MATTE_ZERO,
        })
        .collect()
}

/// A fused renderer for clouds of up to `max_count` Gaussians at one image size.
pub struct FusedRenderer {
    ctx: Context,
    renderer: SplatRenderer,
    masks: Buffer,
    base_rgb: Buffer,
    cloth_rgb: Buffer,
    cloth_alpha: Buffer,
    matte_rgb: Buffer,
    pixels: u32,
}

impl FusedRenderer {
    pub fn new(ctx: &Context, width: u32, height: u32, max_count: usize) -> Result<Self> {
        let renderer = SplatRenderer::new(ctx, width, height, max_count)?;
        let pixels = width * height;
        let image = |name: &str, floats: u32| ctx.create_buffer(name, BufferDesc::gpu_only(4 * u64::from(floats)));
        Ok(Self {
            ctx: ctx.clone(),
            renderer,
            masks: ctx.create_buffer("fused layer masks", BufferDesc::gpu_only(4 * max_count.max(1) as u64))?,
            base_rgb: image("fused base rgb", 3 * pixels)?,
            cloth_rgb: image("fused cloth rgb", 3 * pixels)?,
            cloth_alpha: image("fused cloth alpha", pixels)?,
            matte_rgb: image("fused matte", 3 * pixels)?,
            pixels,
        })
    }

    /// Chooses the rasterizer kernels (see [`SplatRenderer::set_raster_variant`]).
    pub fn set_raster_variant(&mut self, variant: crate::ops::splat::render::RasterVariant) -> Result<()> {
        self.renderer.set_raster_variant(variant)
    }

    /// Sets each Gaussian's layer mask ([`layer_masks`]), in the cloud's order.
    pub fn set_masks(&mut self, ctx: &Context, masks: &[u32]) -> Result<()> {
        ctx.write_buffer(&mut self.masks, masks)
    }

    /// As [`SplatRenderer::prepare_forward`], with the frame's background under the base.
    pub fn prepare_forward(&mut self, gaussians: &GaussianBuffers, camera: &PinholeCamera, settings: &RenderSettings) -> Result<()> {
        self.renderer.prepare_forward(gaussians, camera, settings)
    }

    /// Records projection, one depth sort, binning and the fused rasterization.
    pub fn record_forward<'a>(&'a self, rec: &mut Recording<'a>, gaussians: &'a GaussianBuffers) -> Result<()> {
        self.renderer.record_binning(rec, gaussians)?;
        let (frame, splats, isect_values, ranges) = self.renderer.binned();
        let (kernel, grid) = self.renderer.raster_dispatch(Kernel::SplatRasterizeFusedFwd, Kernel::SplatRasterizeFusedFwdSubgroup);
        rec.pass("splat.rasterize_fused_fwd", kernel)
            .read("frame", frame)
            .read("splats", splats)
            .read("isect_values", isect_values)
            .read("ranges", ranges)
            .read("masks", &self.masks)
            .write("base_rgb", &self.base_rgb)
            .write("cloth_rgb", &self.cloth_rgb)
            .write("cloth_alpha", &self.cloth_alpha)
            .write("matte_rgb", &self.matte_rgb)
            .dispatch(grid)
    }

    /// As [`SplatRenderer::finish_forward`].
    pub fn finish_forward(&mut self) -> Result<ForwardStats> {
        self.renderer.finish_forward()
    }

    /// Renders in one submission (two if the intersections outgrew the buffers).
    pub fn forward(&mut self, ctx: &Context, gaussians: &GaussianBuffers, camera: &PinholeCamera, settings: &RenderSettings) -> Result<ForwardStats> {
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
                return Ok(ForwardStats { rerendered, timings, ..stats });
            }
            rerendered = true;
        }
    }

    /// The three images, as the composite reads them (the matte is 3 channels).
    pub fn outputs(&self) -> CompositeInputs<'_> {
        CompositeInputs { base_rgb: &self.base_rgb, over_rgb: &self.cloth_rgb, over_alpha: &self.cloth_alpha, matte_rgb: Some(&self.matte_rgb) }
    }

    /// Pixels of one image.
    pub fn pixels(&self) -> u32 {
        self.pixels
    }

    /// Reads the last forward's (base, cloth, cloth alpha, matte) images back.
    pub fn read_images(&mut self) -> Result<[Vec<f32>; 4]> {
        let n = self.pixels as usize;
        let ctx = self.ctx.clone();
        Ok([
            ctx.read_buffer(&mut self.base_rgb, 3 * n)?,
            ctx.read_buffer(&mut self.cloth_rgb, 3 * n)?,
            ctx.read_buffer(&mut self.cloth_alpha, n)?,
            ctx.read_buffer(&mut self.matte_rgb, 3 * n)?,
        ])
    }
}
