//! The image losses of a training step: `λ_L1 L1 + λ_SSIM (1 − SSIM) + λ_LPIPS LPIPS`
//! of the render against the frame's target, their gradients summed into one gradient
//! on the rendered image. Recorded with no host wait. Their values are wanted on
//! logging steps only: such a step also records [`ImageLosses::record_readback`],
//! which copies them into host mirrors, so reading them after the step's one wait
//! waits no more. (The cloth layer's losses are `cloth_losses`.)

use drape_engine::mirror::Mirror;
use drape_engine::ops::lpips::Lpips;
use drape_engine::ops::ssim::Ssim;
use drape_engine::recorder::flat_grid;
use drape_engine::{kernels, Buffer, BufferDesc, Context, Recording, Result};
use drape_shared::adam::LossParams;

/// The losses' weights.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageLossWeights {
    pub l1: f32,
    pub ssim: f32,
    /// Used only with an LPIPS network.
    pub lpips: f32,
}

/// The losses' values of the last recorded step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageLossValues {
    /// Mean absolute error per channel.
    pub l1: f64,
    /// PSNR of the render against the target (dB).
    pub psnr: f64,
    /// Mean SSIM.
    pub ssim: f64,
    pub lpips: Option<f64>,
    /// `λ_L1 L1 + λ_SSIM (1 − SSIM)` (LPIPS apart).
    pub loss: f64,
}

/// The target, the gradient on the render, and the losses' own state.
pub struct ImageLosses {
    target: Buffer,
    grad_rgb: Buffer,
    abs_error: Buffer,
    abs_error_mirror: Mirror,
    l1: LossParams,
    ssim: Ssim,
    lpips: Option<Lpips>,
    weights: ImageLossWeights,
}

impl ImageLosses {
    /// The losses of `width` × `height` renders; LPIPS joins where `lpips` is given.
    pub fn new(
        ctx: &Context,
        width: u32,
        height: u32,
        weights: ImageLossWeights,
        mut lpips: Option<Lpips>,
    ) -> Result<Self> {
        let floats = 3 * u64::from(width) * u64::from(height);
        let abs_error = ctx.create_buffer("train abs error", BufferDesc::gpu_only(4 * floats))?;
        let mut ssim = Ssim::new(ctx, width, height)?;
        ssim.keep_host_mirror(ctx)?;
        if let Some(l) = lpips.as_mut() {
            l.keep_host_mirror(ctx)?;
        }
        Ok(Self {
            // Rewritten every step by the host: host-visible memory, no staging copy.
            target: ctx.create_buffer("train target", BufferDesc::host_written(4 * floats))?,
            grad_rgb: ctx.create_buffer("train grad rgb", BufferDesc::gpu_only(4 * floats))?,
            abs_error_mirror: Mirror::new(ctx, &abs_error)?,
            abs_error,
            l1: LossParams {
                len: floats as u32,
                scale: weights.l1 / floats as f32,
                _pad: [0; 2],
            },
            ssim,
            lpips,
            weights,
        })
    }

    /// Writes the next step's target image (3 floats per pixel; the last step's
    /// submission must have completed).
    pub fn set_target(&mut self, ctx: &Context, rgb: &[f32]) -> Result<()> {
        ctx.write_buffer(&mut self.target, rgb)
    }

    /// Records the losses of `rgb` against the target, their summed gradient into
    /// [`grad_rgb`](Self::grad_rgb).
    pub fn record<'a>(&'a self, rec: &mut Recording<'a>, rgb: &'a Buffer) -> Result<()> {
        let l1 = &self.l1;
        self.abs_error_mirror.mark_stale();
        rec.dispatch(
            "loss.l1_grad",
            kernels::train::L1Grad {
                pred: rgb.read(),
                target: self.target.read(),
                grad: self.grad_rgb.write(),
                abs_error: self.abs_error.write(),
            },
            l1,
            flat_grid(l1.len),
        )?;
        // λ (1 − SSIM) adds −λ ∂SSIM/∂rgb to the L1 gradient.
        self.ssim.record(
            rec,
            rgb,
            &self.target,
            Some((&self.grad_rgb, -self.weights.ssim)),
        )?;
        if let Some(l) = &self.lpips {
            l.record(
                rec,
                rgb,
                &self.target,
                Some((&self.grad_rgb, self.weights.lpips)),
            )?;
        }
        Ok(())
    }

    /// The summed gradient on the render of the last recorded step.
    pub fn grad_rgb(&self) -> &Buffer {
        &self.grad_rgb
    }

    /// Records, after [`ImageLosses::record`], the copy of the values it computed into
    /// host memory, for [`ImageLosses::read_values`] to read without a wait.
    pub fn record_readback<'a>(&'a self, rec: &mut Recording<'a>) {
        self.abs_error_mirror
            .record_copy(rec, &self.abs_error, 4 * u64::from(self.l1.len));
        self.ssim.record_readback(rec);
        if let Some(l) = &self.lpips {
            l.record_readback(rec);
        }
    }

    /// The last recorded step's values: out of host memory (no wait) where that step
    /// recorded [`ImageLosses::record_readback`], otherwise read back from the device.
    pub fn read_values(&mut self, ctx: &Context) -> Result<ImageLossValues> {
        let e =
            self.abs_error_mirror
                .read::<f32>(ctx, &mut self.abs_error, self.l1.len as usize)?;
        let n = e.len().max(1) as f64;
        let l1 = e.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
        let mse = e.iter().map(|&v| f64::from(v) * f64::from(v)).sum::<f64>() / n;
        let ssim = self.ssim.read_mean(ctx)?;
        let lpips = match self.lpips.as_mut() {
            Some(l) => Some(l.read_value(ctx)?),
            None => None,
        };
        let loss = f64::from(self.weights.l1) * l1 + f64::from(self.weights.ssim) * (1.0 - ssim);
        Ok(ImageLossValues {
            l1,
            psnr: -10.0 * mse.max(1e-20).log10(),
            ssim,
            lpips,
            loss,
        })
    }
}
