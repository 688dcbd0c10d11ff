//! `drape fit`: random Gaussians fitted to an image on the GPU, saved as PLY.

use std::path::PathBuf;

use drape_cli_support::DeviceArgs;
use drape_engine::ops::splat::render::render_image;
use drape_engine::ops::splat::scene::RenderSettings;
use drape_trainer::ply;

use crate::fitting::{fit_image, FitConfig};
use crate::image_io::{read_rgb, write_png};

/// Options of `drape fit`.
#[derive(Clone, Debug, clap::Args)]
pub struct FitArgs {
    /// Target image: PNG (8 or 16 bit; grey, grey + alpha, RGB or RGBA; alpha is
    /// ignored) or JPEG (grey, RGB or CMYK).
    #[arg(long)]
    pub target: PathBuf,
    /// Number of Gaussians.
    #[arg(long, allow_negative_numbers = true, default_value_t = 2000, value_parser = clap::value_parser!(u32).range(1..=10_000_000))]
    pub n: u32,
    /// Adam iterations.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1000, value_parser = clap::value_parser!(u32).range(1..=10_000_000))]
    pub iters: u32,
    /// Seed of the initial Gaussians.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Output PLY of the fitted Gaussians (camera at the origin looking down +z, fx = width).
    #[arg(long)]
    pub out: PathBuf,
    /// Also write the final render as PNG.
    #[arg(long)]
    pub render: Option<PathBuf>,
}

pub fn run(device: &DeviceArgs, args: &FitArgs) -> anyhow::Result<()> {
    let target = read_rgb(&args.target)?;
    anyhow::ensure!(
        target.width * target.height <= 4096 * 4096,
        "{}: {}x{} is larger than 4096x4096",
        args.target.display(),
        target.width,
        target.height
    );
    // Staged before the work, so that an unwritable path costs nothing.
    let out = drape_cli_support::output::StagedFile::new(&args.out, "--out")?;
    let render_out = args
        .render
        .as_deref()
        .map(|p| drape_cli_support::output::StagedFile::new(p, "--render"))
        .transpose()?;
    let ctx = device.open()?;
    let cfg = FitConfig {
        count: args.n as usize,
        iterations: args.iters,
        seed: args.seed,
        ..FitConfig::default()
    };
    let t0 = std::time::Instant::now();
    let every = (args.iters / 20).max(1);
    let result = fit_image(&ctx, &target, &cfg, every, |it, psnr| {
        let done = it as f64 / args.iters.max(1) as f64;
        let bar = "#".repeat((done * 30.0) as usize);
        eprint!(
            "\r[{bar:<30}] iteration {it:>6}/{}  PSNR {psnr:6.2} dB",
            args.iters
        );
    })?;
    eprintln!();
    device.check_validation(&ctx)?;
    ply::write(out.path(), &result.cloud)?;
    if let Some(staged) = &render_out {
        let (image, _) = render_image(
            &ctx,
            &result.cloud,
            &result.camera,
            &RenderSettings::default(),
        )?;
        write_png(staged.path(), image.width, image.height, &image.rgb)?;
    }
    out.commit()?;
    if let Some(staged) = render_out {
        staged.commit()?;
    }
    println!(
        "fitted {} Gaussians to {} ({}x{}) in {} iterations, {:.1} s: PSNR {:.2} dB; wrote {}",
        cfg.count,
        args.target.display(),
        target.width,
        target.height,
        args.iters,
        t0.elapsed().as_secs_f64(),
        result.psnr,
        args.out.display()
    );
    Ok(())
}
