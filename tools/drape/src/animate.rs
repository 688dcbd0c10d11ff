//! `drape animate RUN --motion M`: the trained avatar (a run directory, or an avatar
//! file from `drape export`) in a motion it was not trained on
//! (walk, jog, raise-arms, turn, or an `.npz` motion file as `Motion::load_npz` reads
//! it: ours, SMPL's first 22 joints, or AMASS), from a camera that orbits it, as
//! `OUT/frameNNNN.png` and `OUT/animation.gif` at the run's resolution, with the time
//! per frame.

use std::io::Write;
use std::path::PathBuf;

use drape_cli_support::DeviceArgs;
use drape_trainer::avatar::animate::{animate, animate_avatar, AnimateOptions, AnimateTarget};
use drape_trainer::avatar::composite::AvatarRenderer;
use drape_trainer::avatar::file::AvatarFile;
use drape_trainer::avatar::run::OpenRun;
use drape_trainer::motion::{procedural, Motion, MotionKind};

/// Options of `drape animate`.
#[derive(Clone, Debug, clap::Args)]
pub struct AnimateArgs {
    /// The run directory (`drape train --out`, or `drape edit --out`), or an avatar
    /// file (`drape export`; then the default output is FILE.animate-MOTION beside it).
    pub run: PathBuf,
    /// walk, jog, raise-arms, turn, or a motion file (.npz: poses F×72 or F×66 axis-angle
    /// SMPL joints, trans F×3 metres, fps as a scalar; or an AMASS file: SMPL-H/SMPL-X
    /// poses, trans, mocap_framerate, turned from z-up to y-up, hands at rest).
    #[arg(long, default_value = "walk")]
    pub motion: String,
    /// Frames to render (a motion file: at most its own).
    #[arg(long, allow_negative_numbers = true, default_value_t = 60, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    pub frames: u32,
    /// Frame rate of the procedural motions and the GIF.
    #[arg(long, allow_negative_numbers = true, default_value_t = 30.0, value_parser = drape_cli_support::number_in::<f64>(0.1, 1000.0))]
    pub fps: f64,
    /// Degrees the camera circles the person over the animation (0: fixed camera).
    #[arg(long, default_value_t = 360.0, allow_negative_numbers = true, value_parser = drape_cli_support::number_in::<f64>(-36000.0, 36000.0))]
    pub orbit: f64,
    /// Background colour r,g,b in [0, 1] where nothing is rendered.
    #[arg(long, default_value = "1,1,1")]
    pub background: String,
    /// Skip the GIF (PNG frames only).
    #[arg(long)]
    pub no_gif: bool,
    /// The sequence the run was trained on (default: from its run.json).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Output directory (default: RUN/animate-MOTION).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

fn parse_background(s: &str) -> anyhow::Result<[f32; 3]> {
    let v: Vec<f32> = s
        .split(',')
        .map(|p| p.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .map_err(|e| anyhow::anyhow!("--background {s}: {e}"))?;
    anyhow::ensure!(
        v.len() == 3 && v.iter().all(|c| (0.0..=1.0).contains(c)),
        "--background {s}: three values in [0, 1] expected, as r,g,b"
    );
    Ok([v[0], v[1], v[2]])
}

pub fn run(device: &DeviceArgs, args: &AnimateArgs) -> anyhow::Result<()> {
    let background = parse_background(&args.background)?;
    // The motion first: a bad file is reported before the GPU is touched.
    let (motion, name): (Motion, String) = match MotionKind::parse(&args.motion) {
        Some(kind) => (
            procedural(kind, args.frames as usize, args.fps, 1.0),
            kind.name().to_string(),
        ),
        None => {
            let path = PathBuf::from(&args.motion);
            anyhow::ensure!(
                path.is_file(),
                "--motion {}: neither walk, jog, raise-arms, turn nor a motion file",
                args.motion
            );
            let m = Motion::load_npz(&path)?;
            anyhow::ensure!(
                !m.is_empty(),
                "{}: the motion has no frames",
                path.display()
            );
            (
                m,
                path.file_stem()
                    .map_or("motion".into(), |s| s.to_string_lossy().into_owned()),
            )
        }
    };
    let ctx = device.open()?;
    let options = AnimateOptions {
        frames: args.frames as usize,
        orbit_degrees: args.orbit,
        background,
        gif: !args.no_gif,
    };
    let progress = &mut |k: usize, n: usize| {
        eprint!("\rrendering {}/{n}   ", k + 1);
        let _ = std::io::stderr().flush();
    };
    let (staged, report) = if args.run.is_file() {
        // An avatar file (`drape export`): no run directory, no dataset.
        let file = AvatarFile::read(&args.run)?;
        anyhow::ensure!(
            args.data.is_none(),
            "--data: {} is an avatar file, which needs no data",
            args.run.display()
        );
        let staged = match &args.out {
            Some(o) => drape_cli_support::output::StagedDir::new(o, "--out", false)?,
            None => drape_cli_support::output::StagedDir::new(
                &args.run.with_extension(format!("animate-{name}")),
                "the default output FILE.animate-MOTION beside the avatar file",
                true,
            )?,
        };
        let mut avatar = file.build(&ctx)?;
        let camera = file.default_camera;
        let mut renderer = AvatarRenderer::new(
            &ctx,
            &avatar,
            camera.width,
            camera.height,
            file.layers_config.compositing,
        )?;
        let rig = file.rig();
        let mut target = AnimateTarget {
            avatar: &mut avatar,
            renderer: &mut renderer,
            rig: &rig,
            anchor_body: &file.default_body,
            camera,
        };
        let out = staged.path().to_path_buf();
        let report = animate_avatar(&ctx, &mut target, &motion, &options, &out, progress)?;
        (staged, report)
    } else {
        let mut run = OpenRun::open(&ctx, &args.run, args.data.as_deref(), None)?;
        let staged = match &args.out {
            Some(o) => drape_cli_support::output::StagedDir::new(o, "--out", false)?,
            None => drape_cli_support::output::StagedDir::new(
                &run.dir.join(format!("animate-{name}")),
                "the default output RUN/animate-MOTION",
                true,
            )?,
        };
        let out = staged.path().to_path_buf();
        let report = animate(&ctx, &mut run, &motion, &options, &out, progress)?;
        (staged, report)
    };
    eprintln!();
    device.check_validation(&ctx)?;
    let out = staged.target().to_path_buf();
    staged.commit()?;
    let mut sorted = report.frame_ms.clone();
    sorted.sort_by(f64::total_cmp);
    println!(
        "{} frames of {name} at {}x{} on {}: {:.1} ms per frame (median {:.1}, max {:.1}; posing + rendering + reading back), {:.2} FPS",
        report.frames,
        report.width,
        report.height,
        ctx.info().name,
        report.mean_ms,
        sorted[sorted.len() / 2],
        sorted[sorted.len() - 1],
        report.fps
    );
    println!(
        "wrote {}/frame0000.png ..{}",
        out.display(),
        if options.gif {
            " and animation.gif"
        } else {
            ""
        }
    );
    Ok(())
}
