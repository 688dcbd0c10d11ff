//! The cloth layer's training losses beyond cloth-LBS, each with the paper's weight
//! as its default and 0 turning it off (the ablation): the simulation term (Chamfer +
//! Geman–McClure to the frame's simulated garments), ARAP (the variance of the edge
//! lengths of the cloth Gaussians' garment graph), and the cloth mask (the mean
//! squared error between the cloth layer's own alpha, rendered alone, and the frame's
//! garment mask: the paper's matte V where there is no scene layer, since its matte
//! lets nothing but the scene hide the cloth).
//!
//! Each adds its gradient to the cloth layer's posed-Gaussian gradients between the
//! splatter's backward and the layer's own (`Avatar::record_scatter_grads` /
//! `record_layers_backward`).

use drape_engine::mirror::Mirror;
use drape_engine::ops::cloth_loss::{Arap, Chamfer};
use drape_engine::ops::splat::render::{GaussianBuffers, SplatRenderer};
use drape_engine::ops::splat::scene::{PinholeCamera, RenderSettings};
use drape_engine::{kernels, Buffer, BufferDesc, Context, Recording, Result};
use drape_shared::adam::LossParams;

use crate::avatar::cloth_target::GarmentFrames;
use crate::avatar::layer::HumanLayer;
use crate::dataset::loader::DatasetFrame;

/// Weights and σ of the cloth losses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClothLossWeights {
    pub sim: f32,
    pub gm_sigma: f32,
    pub arap: f32,
    pub mask: f32,
    /// Every k-th vertex of the simulated garments is a Chamfer target: the stride the
    /// cloth Gaussians were decimated with, so both sides have the same density.
    pub target_stride: u32,
}

/// The values of one step's cloth losses (without their weights).
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct ClothLossValues {
    /// `½ (mean ρ(d(p, Q)) + mean ρ(d(q, P)))`.
    pub sim: f64,
    /// The plain Chamfer distance to the simulated garments (metres).
    pub chamfer: f64,
    /// Variance of the garment graph's edge lengths (m²).
    pub arap: f64,
    /// Mean squared error of the cloth alpha against the garment mask.
    pub mask: f64,
}

/// Scratch and targets of the cloth losses.
pub struct ClothLosses {
    pub weights: ClothLossWeights,
    pub garments: GarmentFrames,
    count: u32,
    chamfer: Chamfer,
    arap: Arap,
    target_points: Buffer,
    target_count: u32,
    renderer: SplatRenderer,
    mask_target: Buffer,
    grad_alpha: Buffer,
    mask_sq_error: Buffer,
    mask_sq_error_mirror: Mirror,
    zeros: Buffer,
    mask_grads: GaussianBuffers,
    pixels: u32,
    has_mask: bool,
    /// The mask gradient joins the compositor's cloth pass (`record_mask_grad`)
    /// instead of coming from a render of its own (`mask_pass`).
    mask_in_composite: bool,
}

impl ClothLosses {
    /// The losses of the layer `cloth` (its ARAP graph is `cloth.edges`).
    pub fn new(
        ctx: &Context,
        cloth: &HumanLayer,
        garments: GarmentFrames,
        weights: ClothLossWeights,
        width: u32,
        height: u32,
    ) -> Result<Self> {
        let pixels = width * height;
        let b = |name: &str, floats: u32| {
            ctx.create_buffer(name, BufferDesc::gpu_only(4 * u64::from(floats.max(1))))
        };
        let zeros = b("cloth mask zeros", 3 * pixels)?;
        {
            let mut rec = ctx.record("cloth mask zero")?;
            rec.fill(&zeros, 0);
            rec.submit_and_wait()?;
        }
        let (chamfer, arap) = mirrored_scratch(ctx, cloth, &garments, &weights)?;
        let mask_sq_error = b("cloth mask squared error", pixels)?;
        Ok(Self {
            weights,
            count: cloth.count,
            chamfer,
            arap,
            // The frame's targets are rewritten every step (`set_frame`): host-written memory.
            target_points: ctx.create_buffer(
                "cloth target points",
                BufferDesc::host_written(4 * u64::from((3 * garments.vertices as u32).max(1))),
            )?,
            target_count: 0,
            renderer: SplatRenderer::new(ctx, width, height, cloth.count as usize)?,
            mask_target: ctx.create_buffer(
                "cloth mask target",
                BufferDesc::host_written(4 * u64::from(pixels.max(1))),
            )?,
            grad_alpha: b("cloth mask grad alpha", pixels)?,
            mask_sq_error_mirror: Mirror::new(ctx, &mask_sq_error)?,
            mask_sq_error,
            zeros,
            mask_grads: GaussianBuffers::new(
                ctx,
                "cloth mask grads",
                cloth.count as usize,
                cloth.deformer.posed.sh_degree,
            )?,
            garments,
            pixels,
            has_mask: false,
            mask_in_composite: false,
        })
    }

    /// Re-allocates what depends on the cloth layer's Gaussians (after densification
    /// changed them): the Chamfer and ARAP scratch, the mask pass; the next
    /// [`set_frame`](Self::set_frame) uploads the targets again.
    pub fn resize(&mut self, ctx: &Context, cloth: &HumanLayer) -> Result<()> {
        let (width, height) = self.renderer.size();
        self.count = cloth.count;
        (self.chamfer, self.arap) = mirrored_scratch(ctx, cloth, &self.garments, &self.weights)?;
        self.renderer = SplatRenderer::new(ctx, width, height, cloth.count as usize)?;
        self.mask_grads = GaussianBuffers::new(
            ctx,
            "cloth mask grads",
            cloth.count as usize,
            cloth.deformer.posed.sh_degree,
        )?;
        Ok(())
    }

    /// Uploads the frame's targets: its simulated garments and its garment mask.
    pub fn set_frame(&mut self, ctx: &Context, f: &DatasetFrame) -> Result<()> {
        let points = self
            .garments
            .by_frame
            .get(&f.frame)
            .expect("every frame of the sequence was simulated");
        let kept: Vec<f32> = points
            .iter()
            .step_by(self.weights.target_stride.max(1) as usize)
            .flatten()
            .copied()
            .collect();
        self.target_count = (kept.len() / 3) as u32;
        // This frame's mask error is not in the mirror until a step copies it there.
        self.mask_sq_error_mirror.mark_stale();
        ctx.write_buffer(&mut self.target_points, &kept)?;
        self.has_mask = self.weights.mask > 0.0 && f.garment_masks.is_some();
        if let Some((upper, lower)) = &f.garment_masks {
            let m: Vec<f32> = upper
                .iter()
                .zip(lower)
                .map(|(&a, &b)| if a || b { 1.0 } else { 0.0 })
                .collect();
            ctx.write_buffer(&mut self.mask_target, &m)?;
        }
        Ok(())
    }

    /// Takes the mask loss from the compositor's cloth pass (`record_mask_grad`) rather
    /// than from a render of its own (`mask_pass`).
    pub fn set_mask_in_composite(&mut self, on: bool) {
        self.mask_in_composite = on;
    }

    /// Records the mask loss on `alpha` (the cloth rendered alone, by the compositor)
    /// and adds its gradient into `grad_alpha` (that pass's alpha gradient).
    pub fn record_mask_grad<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        alpha: &'a Buffer,
        grad_alpha: &'a Buffer,
    ) -> Result<()> {
        if !self.has_mask {
            return Ok(());
        }
        let p = LossParams {
            len: self.pixels,
            scale: self.weights.mask / self.pixels as f32,
            _pad: [0; 2],
        };
        rec.dispatch(
            "cloth.mask_grad",
            kernels::train::MseGrad {
                pred: alpha.read(),
                target: self.mask_target.read(),
                grad: self.grad_alpha.write(),
                squared_error: self.mask_sq_error.write(),
            },
            &p,
            drape_engine::recorder::flat_grid(self.pixels),
        )?;
        let p = LossParams {
            len: self.pixels,
            scale: 1.0,
            _pad: [0; 2],
        };
        rec.dispatch(
            "cloth.mask_add",
            kernels::train::AddInto {
                src: self.grad_alpha.read(),
                dst: grad_alpha.write(),
            },
            &p,
            drape_engine::recorder::flat_grid(self.pixels),
        )?;
        Ok(())
    }

    /// Renders the cloth layer alone (after the avatar's forward pass) and back-
    /// propagates the mask loss into `mask_grads`: two submissions of the renderer.
    pub fn mask_pass(
        &mut self,
        ctx: &Context,
        cloth: &HumanLayer,
        camera: &PinholeCamera,
        settings: &RenderSettings,
    ) -> Result<()> {
        if !self.has_mask {
            return Ok(());
        }
        let saved = self
            .renderer
            .forward(&cloth.deformer.posed, camera, settings)?
            .saved;
        {
            let (_, alpha, _) = self.renderer.outputs();
            let p = LossParams {
                len: self.pixels,
                scale: self.weights.mask / self.pixels as f32,
                _pad: [0; 2],
            };
            let mut rec = ctx.record("cloth mask loss")?;
            rec.dispatch(
                "cloth.mask_grad",
                kernels::train::MseGrad {
                    pred: alpha.read(),
                    target: self.mask_target.read(),
                    grad: self.grad_alpha.write(),
                    squared_error: self.mask_sq_error.write(),
                },
                &p,
                drape_engine::recorder::flat_grid(self.pixels),
            )?;
            rec.submit_and_wait()?;
        }
        self.renderer.backward(
            &saved,
            &cloth.deformer.posed,
            &self.zeros,
            &self.grad_alpha,
            &self.zeros,
            &self.mask_grads,
            cloth.accumulation(),
        )?;
        Ok(())
    }

    /// Whether the mask loss needs a render of the cloth alone (no compositor renders
    /// it: single-pass compositing) in this frame.
    pub fn needs_mask_pass(&self) -> bool {
        self.has_mask && !self.mask_in_composite
    }

    /// Prepares [`record_mask_pass`](Self::record_mask_pass) (host-side).
    pub fn prepare_mask_pass(
        &mut self,
        cloth: &HumanLayer,
        camera: &PinholeCamera,
        settings: &RenderSettings,
    ) -> Result<()> {
        self.renderer
            .prepare_forward(&cloth.deformer.posed, camera, settings)?;
        self.renderer.prepare_backward(cloth.accumulation())
    }

    /// Records [`mask_pass`](Self::mask_pass) into `rec` (after the avatar's forward,
    /// with no host wait); its overflow flag goes to `guard`. After the submission,
    /// [`finish_mask_pass`](Self::finish_mask_pass).
    pub fn record_mask_pass<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        cloth: &'a HumanLayer,
        guard: &'a Buffer,
    ) -> Result<()> {
        self.renderer.record_forward(rec, &cloth.deformer.posed)?;
        self.renderer.record_overflow_flag(rec, guard)?;
        let (_, alpha, _) = self.renderer.outputs();
        let p = LossParams {
            len: self.pixels,
            scale: self.weights.mask / self.pixels as f32,
            _pad: [0; 2],
        };
        rec.dispatch(
            "cloth.mask_grad",
            kernels::train::MseGrad {
                pred: alpha.read(),
                target: self.mask_target.read(),
                grad: self.grad_alpha.write(),
                squared_error: self.mask_sq_error.write(),
            },
            &p,
            drape_engine::recorder::flat_grid(self.pixels),
        )?;
        self.renderer.record_backward(
            rec,
            &self.renderer.recorded_forward(),
            &cloth.deformer.posed,
            &self.zeros,
            &self.grad_alpha,
            &self.zeros,
            &self.mask_grads,
            cloth.accumulation(),
        )
    }

    /// After the submission of [`record_mask_pass`](Self::record_mask_pass): true when
    /// the render outgrew its buffers (they have grown; the step is to be done again).
    pub fn finish_mask_pass(&mut self) -> Result<bool> {
        Ok(self.renderer.finish_forward()?.rerendered)
    }

    /// Records the three losses' gradients into the cloth layer's posed gradients
    /// (after `Avatar::record_scatter_grads`).
    pub fn record<'a>(&'a self, rec: &mut Recording<'a>, cloth: &'a HumanLayer) -> Result<()> {
        let w = self.weights;
        let this = self;
        if this.has_mask && !this.mask_in_composite {
            let per = [3u32, 3, 4, 1];
            let src = [
                &this.mask_grads.means,
                &this.mask_grads.log_scales,
                &this.mask_grads.quats,
                &this.mask_grads.opacity_logits,
            ];
            let dst = [
                &cloth.deformer.posed_grads.means,
                &cloth.deformer.posed_grads.log_scales,
                &cloth.deformer.posed_grads.quats,
                &cloth.deformer.posed_grads.opacity_logits,
            ];
            for k in 0..4 {
                let len = per[k] * this.count;
                let p = LossParams {
                    len,
                    scale: 1.0,
                    _pad: [0; 2],
                };
                rec.dispatch(
                    "cloth.mask_add",
                    kernels::train::AddInto {
                        src: src[k].read(),
                        dst: dst[k].write(),
                    },
                    &p,
                    drape_engine::recorder::flat_grid(len),
                )?;
            }
        }
        let grad = &cloth.deformer.posed_grads.means;
        if w.sim > 0.0 {
            this.chamfer.record(
                rec,
                &cloth.deformer.posed.means,
                this.count,
                &this.target_points,
                this.target_count,
                w.gm_sigma,
                Some((grad, w.sim)),
            )?;
        }
        if w.arap > 0.0 {
            this.arap
                .record(rec, &cloth.deformer.posed.means, Some((grad, w.arap)))?;
        }
        Ok(())
    }

    /// Records, after [`ClothLosses::record`], the copy of the values the step
    /// computed into host memory, for [`ClothLosses::read_values`] to read without a
    /// wait.
    pub fn record_readback<'a>(&'a self, rec: &mut Recording<'a>) {
        if self.weights.sim > 0.0 {
            self.chamfer.record_readback(rec);
        }
        if self.weights.arap > 0.0 {
            self.arap.record_readback(rec);
        }
        if self.has_mask {
            self.mask_sq_error_mirror.record_copy(
                rec,
                &self.mask_sq_error,
                4 * u64::from(self.pixels),
            );
        }
    }

    /// The last recorded step's loss values: out of host memory (no wait) where that
    /// step recorded [`ClothLosses::record_readback`], otherwise read back from the
    /// device.
    pub fn read_values(&mut self, ctx: &Context) -> Result<ClothLossValues> {
        let mut v = ClothLossValues::default();
        if self.weights.sim > 0.0 {
            let c = self.chamfer.read_value(ctx)?;
            v.sim = c.robust;
            v.chamfer = c.distance;
        }
        if self.weights.arap > 0.0 {
            v.arap = f64::from(self.arap.read_stats(ctx)?[1]);
        }
        if self.has_mask {
            let e = self.mask_sq_error_mirror.read::<f32>(
                ctx,
                &mut self.mask_sq_error,
                self.pixels as usize,
            )?;
            v.mask = e.iter().map(|&x| f64::from(x)).sum::<f64>() / f64::from(self.pixels.max(1));
        }
        Ok(v)
    }
}

/// The Chamfer and ARAP scratch for the layer `cloth`, each keeping a host copy of its
/// values for logging steps (`record_readback`).
fn mirrored_scratch(
    ctx: &Context,
    cloth: &HumanLayer,
    garments: &GarmentFrames,
    weights: &ClothLossWeights,
) -> Result<(Chamfer, Arap)> {
    let mut chamfer = Chamfer::new(
        ctx,
        cloth.count,
        garments
            .vertices
            .div_ceil(weights.target_stride.max(1) as usize) as u32,
    )?;
    chamfer.keep_host_mirror(ctx)?;
    let mut arap = Arap::new(ctx, cloth.count, &cloth.edges)?;
    arap.keep_host_mirror(ctx)?;
    Ok((chamfer, arap))
}
