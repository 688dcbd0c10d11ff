//! `drape export RUN --out NAME.avatar`: the trained avatar as one file an app ships
//! (`docs/avatar-format.md`), which `drape view`, the C ABI's `drape_avatar_load` and
//! `AvatarPlayer::load` open without the run directory or the data it was trained on.

use std::path::PathBuf;
use std::time::Instant;

use drape_cli_support::DeviceArgs;
use drape_trainer::avatar::file::AvatarFile;

/// Options of `drape export`.
#[derive(Clone, Debug, clap::Args)]
pub struct ExportArgs {
    /// The run directory (`drape train --out`, or `drape edit --out`); its `run.json`
    /// names the data it was trained on, read once for the default view and body shape.
    pub run: PathBuf,
    /// The avatar file to write (NAME.avatar).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(device: &DeviceArgs, args: &ExportArgs) -> anyhow::Result<()> {
    let ctx = device.open()?;
    let t0 = Instant::now();
    let file = AvatarFile::from_run(&ctx, &args.run)?;
    file.write(&args.out)?;
    device.check_validation(&ctx)?;
    let bytes = std::fs::metadata(&args.out).map(|m| m.len()).unwrap_or(0);
    let gaussians: usize = file.layers.iter().map(|(_, l)| l.count()).sum();
    println!(
        "wrote {} ({bytes} bytes: {} layers, {gaussians} Gaussians) in {:.2} s",
        args.out.display(),
        file.layers.len() + usize::from(file.scene.is_some()),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}
