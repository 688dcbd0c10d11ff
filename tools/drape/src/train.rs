//! `drape train`: fits the avatar to a sequence (NeuMan or ZJU-MoCap layout, or the
//! root `drape synth` writes) and writes a run directory: `config.json`, `run.json`
//! (the data and body it was trained on), `log.jsonl` (one line per logged step),
//! `checkpoint.npz` (every `schedule.checkpoint_every` steps, replaced atomically; `--resume RUN`
//! continues from it), `model.npz` (the trained model; format in
//! `drape_trainer::avatar::checkpoint`), `metrics.json`, `eval/` (a sheet for every
//! held-out frame, `eval.json`, `eval.md`), `novel_pose.png` and the posed body of the
//! first held-out frame as PLY; with `--profile`, `profile.txt` and `profile.json`
//! (where a step's time goes); `incomplete` while it trains and `complete` once done.
//!
//! SIGTERM, SIGINT or SIGUSR1 stop it after the step in flight, with the checkpoint
//! written: exit status 75 ([`EXIT_RESUMABLE`]), and `--resume RUN` continues.

use std::io::Write;
use std::path::PathBuf;

use anyhow::Context as _;
use drape_cli_support::DeviceArgs;
use drape_trainer::avatar::composite::{Compositing, Matte};
use drape_trainer::avatar::model::LayerChoice;
use drape_trainer::avatar::run::RunInfo;
use drape_trainer::avatar::train::{
    body_model, load_sequence, Layout, Outcome, Preset, Progress, TrainConfig, TrainJob,
};

/// Options of `drape train`.
#[derive(Clone, Debug, clap::Args)]
pub struct TrainArgs {
    /// The sequence: a NeuMan directory (sparse/), a ZJU-MoCap one (annots.npy), or the
    /// output root of `drape synth` (its neuman/ is used). With `--resume`, default: the
    /// run's (its run.json).
    #[arg(long, required_unless_present = "resume")]
    pub data: Option<PathBuf>,
    /// The run directory to create (must not exist, or be empty).
    #[arg(long, required_unless_present = "resume", conflicts_with = "resume")]
    pub out: Option<PathBuf>,
    /// Continue the run in this directory from its last checkpoint, with its
    /// config.json and data (run.json; `--steps` may raise the step count).
    #[arg(long)]
    pub resume: Option<PathBuf>,
    /// `quick` (small sizes for lavapipe at 128x128; docs/results.md gives its speed) or
    /// `paper` (the paper's setting, for a GPU).
    #[arg(long, default_value = "quick")]
    pub preset: String,
    /// A TOML file overriding any field of the preset, in its groups ([schedule] steps,
    /// [layers] choice, [layers.body] triplane_resolution, [losses] lambda_sim, [densify]
    /// every; see `config.json` of a run for the fields); unknown keys are an error. The
    /// flat keys of configs before the groups (steps, [body]) still name theirs.
    #[arg(long, conflicts_with = "resume")]
    pub config: Option<PathBuf>,
    /// Which layers: auto (a cloth layer where the data has garment masks, a scene
    /// layer where it has sparse scene points: NeuMan), or body joined by '+' with
    /// cloth and/or scene: body (the single-layer baseline, as HUGS), body+cloth,
    /// body+scene, body+cloth+scene (overrides the config's layers.choice).
    #[arg(long)]
    pub layers: Option<String>,
    /// LPIPS weights (safetensors, from scripts/lpips-to-safetensors.py): LPIPS joins
    /// the loss (weight losses.lambda_lpips) and the metrics; without it, LPIPS is n/a.
    #[arg(long)]
    pub lpips_weights: Option<PathBuf>,
    /// How the layers become one image where there is a cloth layer: three-pass (the
    /// paper's: body + scene, cloth, and a matte in which only the scene hides the
    /// cloth, composited), three-pass-occlusion (the body also hides the cloth in the
    /// matte), or single-pass (every layer in one depth-sorted pass; no matte)
    /// (overrides the config). fused / fused-occlusion: the same images and gradients as
    /// three-pass / three-pass-occlusion from one sort and one walk of every layer,
    /// forward and backward.
    #[arg(long)]
    pub compositing: Option<String>,
    /// Training steps (overrides the preset and the config file).
    #[arg(long, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=10_000_000))]
    pub steps: Option<u32>,
    /// A multi-camera (ZJU-MoCap layout) sequence's training cameras by index, e.g.
    /// 0,1,2 (default: the config's zju_train_camera, 0 in the presets; sets the
    /// config's zju_train_cameras).
    #[arg(long, value_delimiter = ',', conflicts_with = "resume")]
    pub train_cameras: Vec<usize>,
    /// Its held-out cameras, e.g. 3 (default: every camera that does not train; sets
    /// the config's zju_test_cameras).
    #[arg(long, value_delimiter = ',', conflicts_with = "resume")]
    pub test_cameras: Vec<usize>,
    /// An SMPL-format body (.npz, smplx layout); default: the sequence's own
    /// `body_model.npz` where it has one (`drape prepare` writes it: the body its
    /// parameters were fitted with), else the project's procedural body, which is also
    /// what `drape synth` animates.
    #[arg(long)]
    pub body: Option<PathBuf>,
    /// Profile the training steps: GPU time per pass and per stage (from timestamp
    /// queries), host wall time per submission and host phase; printed at the end and
    /// written to RUN/profile.txt and RUN/profile.json.
    #[arg(long)]
    pub profile: bool,
    /// Bit-identical runs: the splat and triplane backward passes add their gradients
    /// in 64-bit fixed point instead of float atomics, so two runs with the same seed
    /// (or a run resumed from a checkpoint and one that was not) end with the same
    /// bits. Slower backward passes; gradients rounded to 2^-36 (sets the config's `deterministic`).
    #[arg(long)]
    pub deterministic: bool,
    /// Train again into a run directory that holds a complete or unfinished run
    /// (its files are removed first). Without it, a complete run is left as it is (exit
    /// 0) and an unfinished one is refused with the command that resumes it.
    #[arg(long, conflicts_with = "resume")]
    pub force: bool,
}

/// Exit status of a run stopped by SIGTERM, SIGINT or SIGUSR1 after checkpointing:
/// `EX_TEMPFAIL`, "try again" (`--resume`), which cluster scripts requeue on.
pub const EXIT_RESUMABLE: u8 = 75;

/// The flag the signal handlers set. A first SIGTERM, SIGINT or SIGUSR1 only sets it
/// (the step in flight finishes and is checkpointed); a second one exits at once,
/// with 128 + the signal's number.
fn interrupt_flag() -> anyhow::Result<std::sync::Arc<std::sync::atomic::AtomicBool>> {
    use signal_hook::consts::{SIGINT, SIGTERM, SIGUSR1};
    let flag = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    for signal in [SIGTERM, SIGINT, SIGUSR1] {
        // Registered first, so it sees the flag as the previous signal left it.
        signal_hook::flag::register_conditional_shutdown(
            signal,
            128 + signal,
            std::sync::Arc::clone(&flag),
        )
        .context("installing the signal handlers")?;
        signal_hook::flag::register(signal, std::sync::Arc::clone(&flag))
            .context("installing the signal handlers")?;
    }
    Ok(flag)
}

fn load_config(args: &TrainArgs) -> anyhow::Result<TrainConfig> {
    if let Some(run) = &args.resume {
        anyhow::ensure!(
            args.config.is_none(),
            "--config cannot change a run being resumed (edit {} instead)",
            run.join("config.json").display()
        );
        let mut config = TrainConfig::read_run(run)?;
        if let Some(s) = args.steps {
            config.schedule.steps = s;
        }
        return Ok(config);
    }
    let mut config = TrainConfig::preset(Preset::parse(&args.preset).context("--preset")?);
    if let Some(path) = &args.config {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("{}: cannot read", path.display()))?;
        config = config.with_toml(&text, path)?;
    }
    if let Some(s) = args.steps {
        config.schedule.steps = s;
    }
    if !args.train_cameras.is_empty() {
        config.zju_train_cameras = args.train_cameras.clone();
    }
    if !args.test_cameras.is_empty() {
        config.zju_test_cameras = args.test_cameras.clone();
    }
    if let Some(l) = &args.layers {
        config.layers.choice = LayerChoice::parse(l).context("--layers")?;
    }
    if let Some(c) = &args.compositing {
        config.layers.compositing = Compositing::parse(c).context("--compositing")?;
    }
    if let Some(w) = &args.lpips_weights {
        config.losses.lpips_weights = Some(w.clone());
    }
    if args.deterministic {
        config.deterministic = true;
    }
    config.validate()?;
    Ok(config)
}

/// "every vertex", "every 2nd vertex", "every 6th vertex" (the decimation).
fn every_nth_vertex(n: u32) -> String {
    let suffix = match (n % 10, n % 100) {
        (1, r) if r != 11 => "st",
        (2, r) if r != 12 => "nd",
        (3, r) if r != 13 => "rd",
        _ => "th",
    };
    if n <= 1 {
        "every vertex".into()
    } else {
        format!("every {n}{suffix} vertex")
    }
}

pub fn run(device: &DeviceArgs, args: &TrainArgs) -> anyhow::Result<()> {
    use drape_trainer::avatar::train::{run_state, RunState};
    let interrupt = interrupt_flag()?;
    // A complete run is not trained again (a requeued job array reruns its command).
    let dir = args
        .resume
        .as_ref()
        .or(args.out.as_ref())
        .expect("clap requires --out or --resume");
    if run_state(dir)? == RunState::Complete
        && !args.force
        && (args.resume.is_none() || args.steps.is_none())
    {
        println!(
            "{} is a complete run ('complete' marker); nothing to do (--force trains it again)",
            dir.display()
        );
        return Ok(());
    }
    if args.force && matches!(run_state(dir)?, RunState::Complete | RunState::Resumable) {
        std::fs::remove_dir_all(dir).with_context(|| {
            format!("{}: cannot remove the earlier run (--force)", dir.display())
        })?;
    }
    if args.resume.is_none() {
        drape_trainer::avatar::train::check_fresh(dir)?;
    }
    let config = load_config(args)?;
    // Which data and body the run is trained on, for `drape eval` and `drape animate`
    // (read before training, so that a damaged run.json costs nothing).
    let earlier = match &args.resume {
        Some(run) => RunInfo::read(run)?,
        None => None,
    };
    let body = match (&earlier, &args.body) {
        (Some(info), None) => info.body.clone(),
        (_, b) => b.clone(),
    };
    let data = match (&args.data, &earlier) {
        (Some(d), _) => d.clone(),
        (None, Some(info)) => info.data.clone(),
        (None, None) => anyhow::bail!(
            "--data: the run {} has no run.json saying what it was trained on",
            dir.display()
        ),
    };
    let seq = load_sequence(&data, config.camera_split())?;
    // A sequence `drape prepare` wrote carries the body its parameters were fitted with.
    let body = body.or_else(|| {
        Some(seq.dir.join("body_model.npz")).filter(|p| earlier.is_none() && p.is_file())
    });
    let info = RunInfo::new(&data, body.as_deref());
    let model = body_model(body.as_deref())?;
    let ctx = device.open()?;
    let (train_n, test_n) = seq.frames.iter().fold((0, 0), |(a, b), f| match f.split {
        drape_trainer::dataset::split::Split::Train => (a + 1, b),
        drape_trainer::dataset::split::Split::Test => (a, b + 1),
        drape_trainer::dataset::split::Split::Val => (a, b),
    });
    let garments = seq.frames.iter().any(|f| f.garment_masks.is_some());
    let layers = drape_trainer::avatar::train::choose_layers(&seq, &config)?;
    let cloth = layers.cloth;
    println!(
        "data: {} ({}: {}), {train_n} training and {test_n} held-out images at {}x{}",
        seq.dir.display(),
        seq.variant.name(),
        seq.variant.describe(),
        seq.frames[0].width,
        seq.frames[0].height
    );
    if let Some(b) = &body {
        println!("body: {}", b.display());
    }
    if seq.layout == Layout::NeuMan
        && !(config.zju_train_cameras.is_empty() && config.zju_test_cameras.is_empty())
    {
        eprintln!("warning: --train-cameras/--test-cameras (zju_train_cameras, zju_test_cameras) split a multi-camera sequence; {} is monocular (NeuMan), whose split is by frame, so they are not used", seq.dir.display());
    }
    if config.layers.choice.cloth.is_none() && !cloth {
        println!("layers: no cloth layer: the data has no garment masks (masks_upper/, masks_lower/) to train one on");
    }
    println!("model ({} preset, on {}):", config.preset, ctx.info().name);
    let decoders = |w: u32| {
        if w >= 128 {
            "HUGS decoders".to_string()
        } else {
            format!("HUGS decoders at most {w} wide (HUGS: 128)")
        }
    };
    println!(
        "  body layer: triplane {0}x{0}x{1}, {2}, SH degree {3}, subdivision {4}, {5}",
        config.layers.body.triplane_resolution,
        config.layers.body.triplane_channels,
        decoders(config.layers.body.decoder_width),
        config.layers.body.sh_degree,
        config.layers.subdivision,
        every_nth_vertex(config.layers.decimate)
    );
    match (cloth, garments) {
        (true, _) => println!(
            "  cloth layer: {10} T-shirt + pants made on the body, one triplane {0}x{0}x{1}, {7}, SH degree {9}; losses cloth-LBS {2}, simulation {3} (Geman–McClure σ {4} m), ARAP {5}, mask {6}; {8}",
            config.layers.cloth.triplane_resolution, config.layers.cloth.triplane_channels, config.losses.lambda_cloth_lbs, config.losses.lambda_sim, config.losses.gm_sigma, config.losses.lambda_arap, config.losses.lambda_mask, decoders(config.layers.cloth.decoder_width),
            match (config.layers.compositing, layers.scene) {
                (Compositing::SinglePass, _) => "rendered with the other layers in one depth-sorted pass",
                (Compositing::ThreePass(Matte::Occlusion), true) => "rendered alone and composited over body + scene through a matte in which the scene and the body hide it",
                (Compositing::ThreePass(Matte::Occlusion), false) => "rendered alone and composited over the body through a matte in which the body hides it",
                (Compositing::Fused(Matte::Paper), true) => "composited over body + scene through a matte in which the scene hides it (the paper's three images from one sort and one walk of every layer, forward and backward)",
                (Compositing::Fused(Matte::Paper), false) => "composited over the body (the paper's images from one sort and one walk of every layer, forward and backward; nothing hides the cloth)",
                (Compositing::Fused(Matte::Occlusion), true) => "composited over body + scene through a matte in which the scene and the body hide it (one sort and one walk of every layer, forward and backward)",
                (Compositing::Fused(Matte::Occlusion), false) => "composited over the body through a matte in which the body hides it (one sort and one walk of every layer, forward and backward)",
                (Compositing::ThreePass(Matte::Paper), true) => "rendered alone and composited over body + scene through a matte in which the scene hides it (the paper's three passes)",
                (Compositing::ThreePass(Matte::Paper), false) => "rendered alone and composited over the body (the paper's passes; with no scene nothing hides the cloth, so the matte is its alpha and is not rendered)",
            },
            config.layers.cloth.sh_degree,
            config.layers.cloth_fit.name()
        ),
        (false, true) => println!("  cloth layer: none (--layers body: the cloth is folded into the body, as HUGS)"),
        (false, false) => println!("  cloth layer: none (no garment masks in the data: the model is HUGS)"),
    }
    match (layers.scene, seq.layout) {
        (true, _) => println!("  scene layer: plain 3DGS from the sparse points, SH degree {} (position rate {:.1e} -> {:.1e} x the scene extent); trained and judged on the whole frame", config.layers.scene.sh_degree, config.layers.scene.lr_position, config.layers.scene.lr_position_final),
        (false, Layout::NeuMan) => println!("  scene layer: none (--layers without scene: the person is trained on a random background colour)"),
        (false, Layout::ZjuMocap) => println!("  scene layer: none (masked studio data: the person is trained on a random background colour)"),
    }
    if config.deterministic {
        println!("  gradients: deterministic (fixed-point accumulation; a rerun or a resumed run gives the same bits)");
    }
    let t0 = std::time::Instant::now();
    let mut last_eval = usize::MAX;
    let (out, resume) = match (&args.resume, &args.out) {
        (Some(run), _) => (run.clone(), true),
        (None, Some(out)) => (out.clone(), false),
        (None, None) => anyhow::bail!("--out or --resume is required"),
    };
    if args.profile {
        ctx.start_profile();
    }
    let outcome = TrainJob::new(&seq, model, &config, &out)
        .resume(resume)
        .run_info(&info)
        .interrupt(&interrupt)
        .progress(&mut |p| {
            match p {
            Progress::Fit { layer, step, total, mse } => eprint!("\rfitting {layer} skinning weights {step:>5}/{total}  mse {mse:.3e}   "),
            Progress::Step { step, total, l1, psnr, it_per_s } => eprint!("\rstep {step:>6}/{total}  L1 {l1:.4}  PSNR {psnr:5.2} dB  {it_per_s:.2} it/s   "),
            Progress::Simulate { done, total } => eprint!("\rsimulating the garments through the motion {done:>4}/{total}   "),
            Progress::Densify { step, counts } => {
                let c: Vec<String> = counts.iter().map(|(name, before, after)| format!("{name} {before} -> {after}")).collect();
                eprintln!("\rdensified after step {step}: {}            ", c.join(", "));
            }
            Progress::Eval { done, total } => {
                if done == 0 && last_eval != 0 {
                    eprintln!();
                }
                last_eval = done;
                eprint!("\revaluating {}/{total}   ", done + 1)
            }
        }
            let _ = std::io::stderr().flush();
        })
        .run(&ctx)?;
    eprintln!();
    let report = match outcome {
        Outcome::Finished(report) => report,
        Outcome::Interrupted { step } => {
            return Err(drape_cli_support::Exit {
                code: EXIT_RESUMABLE,
                message: format!("interrupted by a signal: checkpointed after step {step} of {} in {}; `drape train --resume {}` continues it (exit status {EXIT_RESUMABLE})", config.schedule.steps, out.display(), out.display()),
            }
            .into())
        }
    };
    info.write(&out)?;
    device.check_validation(&ctx)?;
    println!(
        "{}trained steps {}..{} in {:.1} s ({:.2} it/s); Gaussians: {}",
        if report.start_step == 0 {
            format!(
                "fitted skinning weights in {} steps ({:.1} s, mse {:.2e}); ",
                report.fit_steps, report.fit_seconds, report.fit_mse
            )
        } else {
            format!("resumed at step {}; ", report.start_step)
        },
        report.start_step,
        report.steps,
        report.train_seconds,
        report.iterations_per_second,
        report
            .gaussians
            .iter()
            .map(|(n, c)| format!("{c} {n}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    if args.profile {
        let path = out.join("profile.txt");
        let table = std::fs::read_to_string(&path)
            .with_context(|| format!("{}: cannot read", path.display()))?;
        println!(
            "profile of the training steps ({}):\n{table}",
            path.display()
        );
    }
    if report.skipped_steps > 0 {
        println!(
            "skipped {} steps with non-finite gradients (logged in log.jsonl)",
            report.skipped_steps
        );
    }
    println!(
        "held-out ({} images, {}): PSNR {:.2} dB full, {:.2} dB human crop; SSIM {:.4} full, {:.4} crop (before training: PSNR {:.2} / {:.2}, SSIM {:.4} / {:.4})",
        report.fin.frames,
        if layers.scene { "whole frame" } else { "person on black" }, report.fin.psnr_full, report.fin.psnr_crop, report.fin.ssim_full, report.fin.ssim_crop, report.initial.psnr_full, report.initial.psnr_crop, report.initial.ssim_full, report.initial.ssim_crop
    );
    let na = |v: Option<f64>| {
        v.map_or("n/a (no --lpips-weights)".to_string(), |v| {
            format!("{v:.4}")
        })
    };
    println!(
        "held-out LPIPS ({}): {} full, {} crop",
        config.losses.lpips_net,
        na(report.fin.lpips_full),
        na(report.fin.lpips_crop)
    );
    if let (Some(before), Some(after)) = (report.initial.cloth_chamfer, report.fin.cloth_chamfer) {
        println!("cloth Gaussians to the ground-truth garments (held-out frames): Chamfer {:.2} mm (before training: {:.2} mm)", 1e3 * after, 1e3 * before);
    }
    println!("wrote {} (model.npz, checkpoint.npz, eval/, novel_pose.png, log.jsonl, metrics.json) in {:.1} s", out.display(), t0.elapsed().as_secs_f64());
    Ok(())
}
