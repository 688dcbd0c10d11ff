//! Fitting random Gaussians to one image: the smallest end-to-end use of the forward
//! pass, the image loss, the backward pass and Adam, all on the GPU.
//!
//! The camera sits at the origin looking down +z with `fx = fy = width`; Gaussians
//! start at depth 2.5 to 3.5 over random pixels, about one pixel wide, half opaque,
//! coloured by the target at their pixel. The loss is the mean squared error over RGB
//! on a black background. The Gaussians are one group (0).

use drape_shared::adam::LossParams;
use drape_shared::splat::layout::MAX_SH_COEFFS;
use drape_shared::splat::project::Gaussian;
use rand::{Rng, SeedableRng};

use drape_engine::ops::adam::{GaussianAdam, LearningRates};
use drape_engine::ops::splat::render::{Accumulation, GaussianBuffers, SplatRenderer};
use drape_engine::ops::splat::scene::{GaussianCloud, PinholeCamera, RenderSettings};
use drape_engine::recorder::flat_grid;
use drape_engine::{kernels, BufferDesc, Context, Result};

use crate::image_io::Image;

/// What to fit.
#[derive(Clone, Copy, Debug)]
pub struct FitConfig {
    pub count: usize,
    pub iterations: u32,
    pub seed: u64,
    pub sh_degree: u32,
    /// In units of one pixel's width at the Gaussians' depth, for means; absolute for
    /// the others.
    pub lrs: LearningRates,
}

impl Default for FitConfig {
    fn default() -> Self {
        Self {
            count: 2000,
            iterations: 1000,
            seed: 1,
            sh_degree: 0,
            lrs: LearningRates {
                means: 0.15,
                log_scales: 0.02,
                quats: 0.02,
                opacity_logits: 0.05,
                sh: 0.02,
            },
        }
    }
}

/// Result of a fit.
#[derive(Clone, Debug)]
pub struct FitResult {
    pub cloud: GaussianCloud,
    /// PSNR (dB) after the last iteration.
    pub psnr: f64,
    pub camera: PinholeCamera,
}

/// The fitting camera for an image size.
pub fn fit_camera(width: u32, height: u32) -> PinholeCamera {
    let f = width as f32;
    PinholeCamera {
        fx: f,
        fy: f,
        cx: 0.5 * width as f32,
        cy: 0.5 * height as f32,
        width,
        height,
        rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        translation: [0.0; 3],
        near: 0.01,
        far: 100.0,
        background: [0.0; 3],
    }
}

fn initial_cloud(target: &Image, cfg: &FitConfig, cam: &PinholeCamera) -> GaussianCloud {
    let mut rng = rand::rngs::StdRng::seed_from_u64(cfg.seed);
    let mut cloud = GaussianCloud::new(cfg.sh_degree);
    let spacing = ((target.width * target.height) as f32 / cfg.count as f32).sqrt();
    for _ in 0..cfg.count {
        let u: f32 = rng.random_range(0.0..target.width as f32);
        let v: f32 = rng.random_range(0.0..target.height as f32);
        let z: f32 = rng.random_range(2.5..3.5);
        let p = ((v as u32).min(target.height - 1) * target.width
            + (u as u32).min(target.width - 1)) as usize;
        let mut sh = [[0.0f32; 3]; MAX_SH_COEFFS];
        // Colour = 0.5 + C0 * dc at degree 0.
        sh[0] = [0, 1, 2].map(|c| (target.rgb[3 * p + c] - 0.5) / 0.282_094_8);
        let pixel = z / cam.fx;
        cloud.push(
            &Gaussian {
                mean: [(u - cam.cx) * pixel, (v - cam.cy) * pixel, z],
                log_scale: [(0.6 * spacing * pixel).ln(); 3],
                quat: [
                    1.0,
                    rng.random_range(-0.2..0.2),
                    rng.random_range(-0.2..0.2),
                    rng.random_range(-0.2..0.2),
                ],
                opacity_logit: 0.0,
                sh,
            },
            0u32,
        );
    }
    cloud
}

/// Peak signal-to-noise ratio (dB) for values in [0, 1] from a mean squared error.
pub fn psnr(mse: f64) -> f64 {
    -10.0 * mse.max(1e-20).log10()
}

/// Fits `cfg.count` Gaussians to `target`; `report(iteration, psnr)` is called every
/// `report_every` iterations and at the end.
pub fn fit_image(
    ctx: &Context,
    target: &Image,
    cfg: &FitConfig,
    report_every: u32,
    mut report: impl FnMut(u32, f64),
) -> Result<FitResult> {
    assert_eq!(
        target.rgb.len(),
        (3 * target.width * target.height) as usize,
        "target size"
    );
    let cam = fit_camera(target.width, target.height);
    let settings = RenderSettings::default();
    let cloud = initial_cloud(target, cfg, &cam);
    let params = GaussianBuffers::upload(ctx, "fit params", &cloud)?;
    let grads = GaussianBuffers::new(ctx, "fit grads", cloud.len(), cfg.sh_degree)?;
    let pixel = 3.0 / cam.fx; // a pixel's width at the middle depth
    let lrs = LearningRates {
        means: cfg.lrs.means * pixel,
        ..cfg.lrs
    };
    let adam = GaussianAdam::new(ctx, cloud.len(), cfg.sh_degree, lrs)?;
    let mut renderer = SplatRenderer::new(ctx, target.width, target.height, cloud.len())?;
    let pixels = (target.width * target.height) as usize;
    let target_buf = ctx.upload("fit target", &target.rgb)?;
    let grad_rgb = ctx.create_buffer("fit grad rgb", BufferDesc::gpu_only(12 * pixels as u64))?;
    let mut squared_error = ctx.create_buffer(
        "fit squared error",
        BufferDesc::gpu_only(12 * pixels as u64),
    )?;
    let zeros = ctx.create_buffer("fit zero grads", BufferDesc::gpu_only(4 * pixels as u64))?;
    {
        let mut rec = ctx.record("fit zero")?;
        rec.fill(&zeros, 0);
        rec.submit_and_wait()?;
    }
    let loss = LossParams {
        len: 3 * pixels as u32,
        scale: 1.0 / (3 * pixels) as f32,
        _pad: [0; 2],
    };
    for it in 1..=cfg.iterations {
        let saved = renderer.forward(&params, &cam, &settings)?.saved;
        {
            let (rgb, _, _) = renderer.outputs();
            let mut rec = ctx.record("fit loss")?;
            rec.dispatch(
                "loss.mse_grad",
                kernels::train::MseGrad {
                    pred: rgb.read(),
                    target: target_buf.read(),
                    grad: grad_rgb.write(),
                    squared_error: squared_error.write(),
                },
                &loss,
                flat_grid(loss.len),
            )?;
            rec.submit_and_wait()?;
        }
        if it == 1 || it % report_every.max(1) == 0 || it == cfg.iterations {
            let se = ctx.read_buffer::<f32>(&mut squared_error, 3 * pixels)?;
            let mse = se.iter().map(|&v| f64::from(v)).sum::<f64>() / se.len() as f64;
            let p = psnr(mse);
            report(it - 1, p);
        }
        renderer.backward(
            &saved,
            &params,
            &grad_rgb,
            &zeros,
            &zeros,
            &grads,
            Accumulation::Auto,
        )?;
        let mut rec = ctx.record("fit adam")?;
        adam.record_step(&mut rec, &params, &grads)?;
        rec.submit_and_wait()?;
    }
    // The PSNR of the final parameters.
    renderer.forward(&params, &cam, &settings)?;
    let image = renderer.read_image()?;
    let mse = image
        .rgb
        .iter()
        .zip(&target.rgb)
        .map(|(a, b)| f64::from(a - b).powi(2))
        .sum::<f64>()
        / image.rgb.len() as f64;
    let final_psnr = psnr(mse);
    report(cfg.iterations, final_psnr);
    let mut params = params;
    let cloud = params.download(ctx, &cloud.groups)?;
    Ok(FitResult {
        cloud,
        psnr: final_psnr,
        camera: cam,
    })
}

#[cfg(test)]
mod tests {
    use super::{fit_image, FitConfig};
    use crate::image_io::Image;

    /// The bar `drape fit` is held to: PSNR of at least 28 dB on a 64x64 target within
    /// 1,000 iterations of 2,000 Gaussians.
    #[test]
    fn fit_reaches_28_db_on_64x64() {
        let gpu = drape_tests::gpu();
        let picture = drape_tests::test_picture(64, 64);
        let target = Image {
            width: picture.width,
            height: picture.height,
            rgb: picture.rgb,
        };
        // 400 iterations: meeting the bar well inside the 1,000 allowed, in a third of the time.
        let cfg = FitConfig {
            iterations: 400,
            count: 2000,
            ..FitConfig::default()
        };
        let mut history = Vec::new();
        let result = fit_image(&gpu, &target, &cfg, 100, |it, psnr| {
            history.push((it, psnr))
        })
        .expect("fit");
        eprintln!("PSNR by iteration: {history:?}");
        assert!(
            result.psnr >= 28.0,
            "final PSNR {:.2} dB; history {history:?}",
            result.psnr
        );
        assert!(
            history.first().is_some_and(|(_, p)| *p < result.psnr),
            "the fit improves on its start"
        );
    }
}
