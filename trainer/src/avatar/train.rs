//! Training the avatar: load a sequence, build the layers the data requires, fit the
//! skinning weights, then step (sample a training frame → deform → render → losses →
//! backward → Adam) and evaluate on the held-out frames.
//!
//! The layers: the body and, where the data shows garments, the cloth (`model`:
//! triplane + decoders + learned skinning), rendered and composited as
//! [`LayersConfig::compositing`](crate::avatar::config::LayersConfig::compositing) says
//! (`composite`); where the data has a scene, the scene layer (`scene`) against the
//! whole frame. The losses: 0.8 L1 + 0.2 (1 - SSIM)
//! against the person masked onto a random background colour each step (HUGS), LPIPS
//! where weights are given, and on the cloth layer the paper's cloth-LBS, simulation
//! (Chamfer + Geman–McClure to the garments simulated through the sequence's motion),
//! ARAP and cloth-mask losses (`cloth_losses`). Adam steps every layer, each training
//! frame's pose and translation are refined (`pose_refine`), and the layers are
//! densified and pruned on the schedule of [`TrainConfig::densify`] (`densify`).

use std::io::Write;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use crate::avatar::groups::Layer;
use crate::ply;
use drape_engine::ops::splat::scene::RenderSettings;
use drape_engine::Context;

use crate::avatar::assemble::build_avatar;
use crate::avatar::checkpoint;
use crate::avatar::cloth_losses::{ClothLossWeights, ClothLosses};
use crate::avatar::cloth_target;
use crate::avatar::composite::AvatarRenderer;
use crate::avatar::densify::{self};
use crate::avatar::eval::{evaluate, write_reports, EvalInputs};
use crate::avatar::inputs::betas_of;
use crate::avatar::losses::{ImageLossWeights, ImageLosses};
use crate::avatar::model::Avatar;
use crate::avatar::pose_refine::PoseRefiner;
use crate::avatar::report::write_json;
use crate::avatar::rig::Rig;
use crate::avatar::step::{self, HostWaits, Sample, Stages, StepBuffers, StepKind, StepOutcome};
use crate::body::SmplModel;
use crate::dataset::error::DatasetError;
use crate::dataset::loader::{BodyParams, DatasetFrame};
use crate::dataset::split::Split;
use crate::error::TrainerError;
use drape_engine::ops::lpips::{Lpips, LpipsWeights};

// The paths the tools and tests know a run's parts by.
pub use crate::avatar::assemble::{choose_layers, Layers};
pub use crate::avatar::config::{Preset, TrainConfig};
pub use crate::avatar::eval::{mask_bbox, psnr, EvalMetrics};
pub use crate::avatar::inputs::{body_model, load_sequence, Layout, Sequence};
pub use crate::avatar::report::Progress;

/// What a run did.
#[derive(Clone, Debug, serde::Serialize)]
pub struct TrainReport {
    pub layout: Layout,
    pub gaussians: Vec<(String, u32)>,
    pub fit_steps: u32,
    pub fit_mse: f64,
    pub fit_seconds: f64,
    /// The step training started from (0, or the checkpoint's when resumed).
    pub start_step: u32,
    pub steps: u32,
    pub train_seconds: f64,
    pub iterations_per_second: f64,
    pub skipped_steps: u32,
    /// Host waits (fence waits) of the training steps.
    pub host_waits: HostWaits,
    pub initial: EvalMetrics,
    pub fin: EvalMetrics,
}

/// Times host phases of a step into the context's profile (a no-op without one).
struct Lap<'c> {
    ctx: &'c Context,
    on: bool,
    since: Instant,
}

impl<'c> Lap<'c> {
    fn new(ctx: &'c Context, on: bool) -> Self {
        Self {
            ctx,
            on,
            since: Instant::now(),
        }
    }

    fn reset(&mut self) {
        self.since = Instant::now();
    }

    /// Adds the time since the last reset or phase under `name`.
    fn host(&mut self, name: &str) {
        if self.on {
            self.ctx
                .profile_host(name, self.since.elapsed().as_secs_f64() * 1e3);
            self.since = Instant::now();
        }
    }
}

/// A log line's value: plain numbers and names, which always serialise.
fn json_value(value: &impl serde::Serialize) -> serde_json::Value {
    serde_json::to_value(value).expect("log values are numbers and names")
}

/// Trains on `seq` into the run directory `out`: a new one (it must not exist, or be
/// empty), or with `resume` the run's last checkpoint (`out/checkpoint.npz`), continued
/// to `config.schedule.steps`. The step's frame and background come from `(seed, step)`, so a
/// resumed run samples what the uninterrupted one would have.
pub fn train(
    ctx: &Context,
    seq: &Sequence,
    model: SmplModel,
    config: &TrainConfig,
    out: &Path,
    resume: bool,
    progress: &mut dyn FnMut(Progress),
) -> crate::Result<TrainReport> {
    train_until(
        ctx,
        seq,
        model,
        config,
        out,
        resume,
        config.schedule.steps,
        progress,
    )
}

/// [`train`], stopping after step `stop_at` (at most `config.schedule.steps`) as if the run
/// had been interrupted there: the checkpoint is written, the schedules still run to
/// `config.schedule.steps`, and a later `resume` continues as the uninterrupted run would.
#[allow(clippy::too_many_arguments)]
pub fn train_until(
    ctx: &Context,
    seq: &Sequence,
    model: SmplModel,
    config: &TrainConfig,
    out: &Path,
    resume: bool,
    stop_at: u32,
    progress: &mut dyn FnMut(Progress),
) -> crate::Result<TrainReport> {
    let never = AtomicBool::new(false);
    match run(
        ctx, seq, model, config, out, resume, stop_at, None, &never, progress,
    )? {
        Outcome::Finished(report) => Ok(*report),
        Outcome::Interrupted { .. } => unreachable!("nothing sets the flag"),
    }
}

/// How a run that can be interrupted ended.
#[derive(Debug)]
pub enum Outcome {
    /// Every step ran; the model, metrics and `complete` marker are written.
    Finished(Box<TrainReport>),
    /// `interrupt` was set: the step in flight finished and the checkpoint holds the
    /// state after `step` steps; `--resume` continues it.
    Interrupted { step: u32 },
}

/// [`train`] that stops cleanly when `interrupt` becomes true (a signal handler sets
/// it): the step in flight finishes, the checkpoint is written atomically, and the run
/// directory stays resumable. `info` (the data and body) is written as `run.json` when
/// the run directory is made, so that `--resume` and the other commands find the data
/// of an unfinished run.
#[allow(clippy::too_many_arguments)]
pub fn train_interruptible(
    ctx: &Context,
    seq: &Sequence,
    model: SmplModel,
    config: &TrainConfig,
    out: &Path,
    resume: bool,
    info: Option<&crate::avatar::run::RunInfo>,
    interrupt: &AtomicBool,
    progress: &mut dyn FnMut(Progress),
) -> crate::Result<Outcome> {
    run(
        ctx,
        seq,
        model,
        config,
        out,
        resume,
        config.schedule.steps,
        info,
        interrupt,
        progress,
    )
}

/// The marker a finished run holds (its command run again has nothing to do).
pub const COMPLETE_MARKER: &str = "complete";
/// The note an unfinished run holds (how to continue it).
pub const INCOMPLETE_MARKER: &str = "incomplete";

/// What is in a run directory before a run starts in it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RunState {
    /// Missing or empty: a new run can start.
    Fresh,
    /// A finished run ([`COMPLETE_MARKER`]).
    Complete,
    /// A run with a checkpoint and no [`COMPLETE_MARKER`]: `--resume` continues it.
    Resumable,
    /// Something else (files that are no drape run, or a run without a checkpoint).
    Occupied,
}

/// Classifies `out` (see [`RunState`]).
pub fn run_state(out: &Path) -> crate::Result<RunState> {
    if !out.exists() {
        return Ok(RunState::Fresh);
    }
    if !out.is_dir() {
        return Ok(RunState::Occupied);
    }
    if std::fs::read_dir(out)
        .map_err(|e| TrainerError::io(out, e))?
        .next()
        .is_none()
    {
        return Ok(RunState::Fresh);
    }
    Ok(if out.join(COMPLETE_MARKER).is_file() {
        RunState::Complete
    } else if out.join("checkpoint.npz").is_file() && out.join("config.json").is_file() {
        RunState::Resumable
    } else {
        RunState::Occupied
    })
}

/// The preemption test's hook: with `DRAPE_FAILPOINT=wait-for-signal-before-step:K`,
/// the run says so on stderr before step K and waits (at most a minute) until a signal
/// sets `interrupt`, so that a test's SIGTERM lands at a known step. Unset (always,
/// outside that test), it does nothing.
fn wait_for_signal_if_asked(step: u32, interrupt: &AtomicBool) {
    let Ok(spec) = std::env::var("DRAPE_FAILPOINT") else {
        return;
    };
    if spec
        .strip_prefix("wait-for-signal-before-step:")
        .and_then(|k| k.parse::<u32>().ok())
        != Some(step)
    {
        return;
    }
    eprintln!("\nfailpoint: waiting for a signal before step {step}");
    let t0 = Instant::now();
    while !interrupt.load(Ordering::SeqCst) && t0.elapsed().as_secs() < 60 {
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
}

/// Refuses to start a new run in `out` unless it is missing or empty, saying what is
/// there and what to do instead.
pub fn check_fresh(out: &Path) -> crate::Result<()> {
    match run_state(out)? {
        RunState::Fresh => Ok(()),
        RunState::Complete => Err(TrainerError::run(out, "holds a complete run (it has the 'complete' marker); --force trains it again")),
        RunState::Resumable => Err(TrainerError::run(out, format!("holds an unfinished run (see its '{INCOMPLETE_MARKER}'): `drape train --resume {}` continues it; --force starts it again", out.display()))),
        RunState::Occupied => Err(TrainerError::run(out, "exists and is not empty, and is no drape run to resume; choose another --out")),
    }
}

#[allow(clippy::too_many_arguments)]
/// The guard's bookkeeping: steps skipped for non-finite gradients, and the stop after
/// too many in a row.
struct SkipGuard {
    total: u32,
    in_a_row: u32,
    limit: u32,
}

impl SkipGuard {
    fn new(limit: u32) -> Self {
        Self {
            total: 0,
            in_a_row: 0,
            limit: limit.max(1),
        }
    }

    fn applied(&mut self) {
        self.in_a_row = 0;
    }

    /// Counts a skipped step; an error once `limit` steps in a row were skipped.
    fn skipped(
        &mut self,
        step: u32,
        nonfinite: u32,
        frame: usize,
        data: &Path,
        checkpoint: &Path,
    ) -> crate::Result<()> {
        self.total += 1;
        self.in_a_row += 1;
        if self.in_a_row < self.limit {
            return Ok(());
        }
        Err(TrainerError::numeric(
            "training",
            format!(
                "stopped at step {step}: {} steps in a row had non-finite gradients ({nonfinite} values in the last, frame {frame} of {}); the last checkpoint is {}",
                self.in_a_row,
                data.display(),
                checkpoint.display()
            ),
        ))
    }
}

/// The pose refiner's step on the frame of `s` from every human layer's share of
/// `∂L/∂A` (mapped memory: read after the step's wait with no other). A gradient
/// that the rig's chain rule makes non-finite is not applied: the log line says so.
fn refine_pose(
    ctx: &Context,
    avatar: &mut Avatar,
    rig: &Rig,
    refiner: &mut PoseRefiner,
    s: &Sample<'_>,
    step: u32,
) -> crate::Result<Option<serde_json::Value>> {
    let mut grad = vec![0.0f64; crate::avatar::rig::TRANSFORM_FLOATS];
    for l in &mut avatar.layers {
        for (g, v) in grad.iter_mut().zip(l.deformer.read_transform_grad(ctx)?) {
            *g += v;
        }
    }
    let g = rig.frame_gradient(&s.body, &grad);
    let bad = g.iter().filter(|v| !v.is_finite()).count();
    if bad > 0 {
        return Ok(Some(
            serde_json::json!({ "step": step, "frame": s.frame.frame, "pose_refinement_skipped": true, "nonfinite_pose_gradients": bad }),
        ));
    }
    refiner.step(s.index, &g);
    Ok(None)
}

/// A logging step's line (losses read back) with its L1 and PSNR.
/// `seconds`: since training started.
#[allow(clippy::too_many_arguments)]
fn log_line(
    ctx: &Context,
    image: &mut ImageLosses,
    cloth: Option<&mut ClothLosses>,
    avatar: &Avatar,
    refiner: Option<&PoseRefiner>,
    step: u32,
    frame: usize,
    seconds: f64,
) -> crate::Result<(serde_json::Value, f64, f64)> {
    let v = image.read_values(ctx)?;
    let mut line = serde_json::json!({ "step": step, "frame": frame, "l1": v.l1, "ssim": v.ssim, "loss": v.loss, "psnr_train": v.psnr, "lr_position": avatar.layers[0].groups.position.lr(), "seconds": seconds });
    if let Some(c) = cloth {
        line["cloth"] = json_value(&c.read_values(ctx)?);
    }
    if let Some(l) = v.lpips {
        line["lpips"] = l.into();
    }
    if let Some(r) = refiner {
        // Mean over training frames of the largest joint correction and of the
        // translation's.
        let (rot, tr) = r.summary();
        line["pose_correction_rad"] = rot.into();
        line["translation_correction"] = tr.into();
    }
    Ok((line, v.l1, v.psnr))
}

/// Densifies and prunes every layer after `step + 1` steps; everything sized by the
/// layers' counts follows them. Returns the log's summaries and (layer, before, after).
type DensifyCounts = Vec<(String, usize, usize)>;
fn densify_layers(
    ctx: &Context,
    avatar: &mut Avatar,
    config: &TrainConfig,
    step: u32,
    log_scale: f32,
) -> crate::Result<(serde_json::Map<String, serde_json::Value>, DensifyCounts)> {
    let dc = &config.densify;
    let mut counts = Vec::new();
    let mut summaries = serde_json::Map::new();
    let seed = config.seed ^ u64::from(step + 1).wrapping_mul(0xD1B5_4A32_D192_ED03);
    for l in avatar.layers.iter_mut() {
        let s = densify::apply_to_layer(ctx, l, dc, step + 1, log_scale)?;
        counts.push((l.name.clone(), s.before, s.after));
        summaries.insert(l.name.clone(), json_value(&s));
    }
    if let Some(sc) = avatar.scene.as_mut() {
        let s = densify::apply_to_scene(ctx, sc, dc, step + 1, seed.wrapping_add(1000))?;
        counts.push(("scene".into(), s.before, s.after));
        summaries.insert("scene".into(), json_value(&s));
    }
    avatar.resize_posed(ctx)?;
    Ok((summaries, counts))
}

fn run(
    ctx: &Context,
    seq: &Sequence,
    model: SmplModel,
    config: &TrainConfig,
    out: &Path,
    resume: bool,
    stop_at: u32,
    info: Option<&crate::avatar::run::RunInfo>,
    interrupt: &AtomicBool,
    progress: &mut dyn FnMut(Progress),
) -> crate::Result<Outcome> {
    let stop_at = stop_at.min(config.schedule.steps);
    config.validate()?;
    let train_frames: Vec<&DatasetFrame> = seq
        .frames
        .iter()
        .filter(|f| f.split == Split::Train)
        .collect();
    if train_frames.is_empty() {
        return Err(DatasetError::layout(&seq.dir, "no training frames").into());
    }
    let (width, height) = (train_frames[0].width, train_frames[0].height);
    if let Some(f) = seq
        .frames
        .iter()
        .find(|f| (f.width, f.height) != (width, height))
    {
        return Err(DatasetError::image(
            &f.image_path,
            format!(
                "{}x{}, but the sequence's first training image is {width}x{height}",
                f.width, f.height
            ),
        )
        .into());
    }
    // LPIPS where the run has weights: read before the run directory is made, so a
    // wrong path leaves nothing behind.
    let lpips_weights = match &config.losses.lpips_weights {
        Some(path) => Some(LpipsWeights::load(path, config.losses.lpips_net)?),
        None => None,
    };
    let checkpoint_path = out.join("checkpoint.npz");
    if resume {
        if !checkpoint_path.is_file() {
            return Err(TrainerError::run(
                &checkpoint_path,
                "no checkpoint to resume from",
            ));
        }
        return train_in(
            ctx,
            seq,
            model,
            config,
            out,
            true,
            stop_at,
            interrupt,
            lpips_weights,
            progress,
        );
    }
    check_fresh(out)?;
    let created = !out.exists();
    let made = (|| -> crate::Result<()> {
        std::fs::create_dir_all(out.join("eval")).map_err(|e| TrainerError::io(out, e))?;
        write_json(&out.join("config.json"), config)?;
        if let Some(info) = info {
            info.write(out)?;
        }
        let note = out.join(INCOMPLETE_MARKER);
        std::fs::write(&note, format!("this run has not finished; `drape train --resume {}` continues it from checkpoint.npz\n", out.display())).map_err(|e| TrainerError::io(&note, e))
    })();
    let result = made.and_then(|()| {
        train_in(
            ctx,
            seq,
            model,
            config,
            out,
            false,
            stop_at,
            interrupt,
            lpips_weights,
            progress,
        )
    });
    // A run that failed before its first checkpoint leaves nothing (an empty directory
    // that was there before stays, empty); after it, the run stays resumable.
    if result.is_err() && !checkpoint_path.exists() {
        if created {
            let _ = std::fs::remove_dir_all(out);
        } else if let Ok(entries) = std::fs::read_dir(out) {
            for e in entries.flatten() {
                let p = e.path();
                let _ = if p.is_dir() {
                    std::fs::remove_dir_all(&p)
                } else {
                    std::fs::remove_file(&p)
                };
            }
        }
    }
    result
}

#[allow(clippy::too_many_arguments)]
fn train_in(
    ctx: &Context,
    seq: &Sequence,
    model: SmplModel,
    config: &TrainConfig,
    out: &Path,
    resume: bool,
    stop_at: u32,
    interrupt: &AtomicBool,
    lpips_weights: Option<LpipsWeights>,
    progress: &mut dyn FnMut(Progress),
) -> crate::Result<Outcome> {
    let train_frames: Vec<&DatasetFrame> = seq
        .frames
        .iter()
        .filter(|f| f.split == Split::Train)
        .collect();
    let test_frames: Vec<&DatasetFrame> = seq
        .frames
        .iter()
        .filter(|f| f.split == Split::Test)
        .collect();
    let (width, height) = (train_frames[0].width, train_frames[0].height);
    let checkpoint_path = out.join("checkpoint.npz");
    let log_path = out.join("log.jsonl");
    let mut log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log_path)
        .map_err(|e| TrainerError::io(&log_path, e))?;

    let rig = Rig::new(model, &betas_of(train_frames[0]));
    let mut avatar = build_avatar(ctx, &rig, seq, config, choose_layers(seq, config)?)?;
    // With a scene layer the avatar is trained and judged on the whole image; without
    // one, on the person over a background colour.
    let whole_image = avatar.scene.is_some();
    let mut renderer = AvatarRenderer::new(ctx, &avatar, width, height, config.layers.compositing)?;
    let ground_truth = cloth_target::ground_truth_dir(&seq.dir);
    let mut cloth_losses =
        cloth_losses_of(ctx, &avatar, &rig, seq, config, (width, height), progress)?;

    // 1. The deformation decoder learns the body's skinning weights (or the run's
    //    checkpoint is loaded: its decoders have been fitted already).
    let t0 = Instant::now();
    let mut refiner = config.schedule.refine_pose.then(|| {
        PoseRefiner::new(
            &train_frames
                .iter()
                .map(|f| f.frame as u32)
                .collect::<Vec<_>>(),
            f64::from(config.schedule.lr_pose),
            f64::from(config.schedule.lr_translation),
        )
    });
    let (start_step, fit_mse) = if resume {
        let step = resume_from(ctx, &checkpoint_path, config, &mut avatar, refiner.as_mut())?;
        // The checkpoint's layers may have been densified to other counts.
        renderer = renderer_for(ctx, &avatar, cloth_losses.as_mut(), config, (width, height))?;
        (step, f64::NAN)
    } else {
        (0, fit_skinning_weights(ctx, &mut avatar, config, progress)?)
    };
    let fit_seconds = t0.elapsed().as_secs_f64();
    if let (Some(c), true) = (cloth_losses.as_mut(), renderer.is_three_pass()) {
        c.set_mask_in_composite(true);
    }
    let eval_inputs = |sheets| EvalInputs {
        rig: &rig,
        frames: &test_frames,
        ground_truth: ground_truth.as_deref(),
        lpips: lpips_weights.as_ref(),
        sheets,
    };
    let (initial, _) = evaluate(
        ctx,
        &mut avatar,
        &mut renderer,
        &eval_inputs(None),
        progress,
    )?;

    // 2. The main loop: a step is one submission and one host wait (`step`).
    let settings = RenderSettings::default();
    // With a profile running (`drape train --profile`), it covers the steps alone.
    let profiling = ctx.profiling();
    if profiling {
        ctx.start_profile();
    }
    let mut run = StepLoop {
        ctx,
        config,
        seq,
        rig: &rig,
        train_frames: &train_frames,
        whole_image,
        size: (width, height),
        settings: &settings,
        checkpoint_path: &checkpoint_path,
        log_path: &log_path,
        log: &mut log,
        avatar: &mut avatar,
        renderer: &mut renderer,
        cloth_losses: cloth_losses.as_mut(),
        refiner: refiner.as_mut(),
        image_losses: image_losses_of(ctx, config, lpips_weights.as_ref(), (width, height))?,
        buffers: StepBuffers::new(ctx, width, height)?,
        skips: SkipGuard::new(config.schedule.max_skipped_steps),
        waits: HostWaits::default(),
        lap: Lap::new(ctx, profiling),
        t_train: Instant::now(),
        start_step,
        stop_at,
    };
    if let Some(step) = run.steps(interrupt, progress)? {
        return Ok(Outcome::Interrupted { step });
    }
    if let Some(p) = if profiling { ctx.take_profile() } else { None } {
        write_profile(
            out,
            &p,
            &run.waits,
            u64::from(stop_at.saturating_sub(start_step)),
            run.t_train.elapsed().as_secs_f64(),
        )?;
    }
    let last = stop_at.max(start_step);
    run.save(last, &checkpoint_path)?;
    if interrupt.load(Ordering::SeqCst) {
        return Ok(Outcome::Interrupted { step: last });
    }
    run.save(last, &out.join("model.npz"))?;
    let loop_ = LoopSummary {
        start_step,
        stop_at,
        train_seconds: run.t_train.elapsed().as_secs_f64(),
        skipped_steps: run.skips.total,
        host_waits: run.waits,
    };
    // 3. Held-out evaluation and the run's exports.
    let eval_dir = out.join("eval");
    let (fin, per_frame) = evaluate(
        ctx,
        &mut avatar,
        &mut renderer,
        &eval_inputs(Some(&eval_dir)),
        progress,
    )?;
    write_reports(
        &eval_dir,
        &format!(
            "{} after {last} steps, {} held-out images of {}",
            out.display(),
            per_frame.len(),
            seq.dir.display()
        ),
        &fin,
        &per_frame,
    )?;
    if let Some(f) = test_frames.first() {
        export_posed_layers(ctx, &mut avatar, &rig, f, out)?;
        render_novel_pose(
            ctx,
            &mut avatar,
            &mut renderer,
            &rig,
            f,
            &settings,
            out,
            (width, height),
        )?;
    }
    let fit = FitSummary {
        fit_steps: config.schedule.fit_steps,
        fit_mse,
        fit_seconds,
    };
    let report = TrainReport::new(seq.layout, avatar.counts(), fit, loop_, initial, fin);
    write_json(&out.join("metrics.json"), &report)?;
    if stop_at == config.schedule.steps {
        mark_complete(out, config.schedule.steps)?;
    }
    Ok(Outcome::Finished(Box::new(report)))
}

/// The loop over steps and what it works on: each step (`step::run`), then the pose
/// refinement, the log line, densification and the checkpoint that fall on it.
struct StepLoop<'r> {
    ctx: &'r Context,
    config: &'r TrainConfig,
    seq: &'r Sequence,
    rig: &'r Rig,
    train_frames: &'r [&'r DatasetFrame],
    /// With a scene layer the avatar is trained on the whole image; without one, on the
    /// person over a background colour.
    whole_image: bool,
    size: (u32, u32),
    settings: &'r RenderSettings,
    checkpoint_path: &'r Path,
    log_path: &'r Path,
    log: &'r mut std::fs::File,
    avatar: &'r mut Avatar,
    renderer: &'r mut AvatarRenderer,
    cloth_losses: Option<&'r mut ClothLosses>,
    image_losses: ImageLosses,
    buffers: StepBuffers,
    refiner: Option<&'r mut PoseRefiner>,
    skips: SkipGuard,
    waits: HostWaits,
    lap: Lap<'r>,
    t_train: Instant,
    start_step: u32,
    stop_at: u32,
}

impl StepLoop<'_> {
    /// Steps from `start_step` to `stop_at`; `Some(step)` when `interrupt` stopped the
    /// run with its checkpoint written after `step` steps.
    fn steps(
        &mut self,
        interrupt: &AtomicBool,
        progress: &mut dyn FnMut(Progress),
    ) -> crate::Result<Option<u32>> {
        for step in self.start_step..self.stop_at {
            wait_for_signal_if_asked(step, interrupt);
            // A signal arrived during the step before: its state is complete, so it is
            // checkpointed here and the run stops, resumable.
            if interrupt.load(Ordering::SeqCst) {
                self.save(step, self.checkpoint_path)?;
                return Ok(Some(step));
            }
            let waits_before = self.ctx.fence_waits();
            self.lap.reset();
            let refiner = self.refiner.as_deref();
            let s = step::sample(
                self.train_frames,
                self.rig,
                refiner,
                self.config.seed,
                step,
                self.whole_image,
            );
            self.lap.host("host.frame_setup");
            let (outcome, attempts) = self.train_step(step, &s)?;
            self.lap.reset();
            let kind = match outcome {
                StepOutcome::Skipped { nonfinite } => {
                    self.log_line(&serde_json::json!({ "step": step, "frame": s.frame.frame, "skipped": true, "nonfinite_gradients": nonfinite }))?;
                    self.skips.skipped(
                        step,
                        nonfinite,
                        s.frame.frame,
                        &self.seq.dir,
                        self.checkpoint_path,
                    )?;
                    StepKind::Other
                }
                _ => {
                    self.skips.applied();
                    self.after_step(step, &s, progress)?
                }
            };
            self.waits
                .add(self.ctx.fence_waits() - waits_before, attempts, kind);
        }
        Ok(None)
    }

    /// One step on `s`, done again while a render outgrows its buffers; with the
    /// submissions it took.
    fn train_step(&mut self, step: u32, s: &Sample<'_>) -> crate::Result<(StepOutcome, u32)> {
        let dc = &self.config.densify;
        // Statistics are gathered from the step after one densification up to the next.
        let screen_stats =
            dc.every > 0 && step < dc.until.min(self.config.schedule.steps.saturating_sub(1));
        let read_losses = self.logs(step);
        let mut attempts = 0;
        loop {
            attempts += 1;
            let mut st = Stages {
                avatar: self.avatar,
                renderer: self.renderer,
                cloth_losses: self.cloth_losses.as_deref_mut(),
                image_losses: &mut self.image_losses,
                settings: self.settings,
                pose_gradient: self.refiner.is_some(),
                screen_stats,
                masked: !self.whole_image,
                read_losses,
            };
            match step::run(self.ctx, &mut st, &mut self.buffers, s)? {
                StepOutcome::Overflowed => continue,
                done => return Ok((done, attempts)),
            }
        }
    }

    /// Whether `step` writes a log line (its losses are copied to the host in its
    /// submission).
    fn logs(&self, step: u32) -> bool {
        step % self.config.schedule.log_every.max(1) == 0 || step + 1 == self.stop_at
    }

    /// After an applied step: the pose refinement, then the log line, densification and
    /// checkpoint that fall on it; which of those it did.
    fn after_step(
        &mut self,
        step: u32,
        s: &Sample<'_>,
        progress: &mut dyn FnMut(Progress),
    ) -> crate::Result<StepKind> {
        if let Some(r) = self.refiner.as_deref_mut() {
            if let Some(line) = refine_pose(self.ctx, self.avatar, self.rig, r, s, step)? {
                self.log_line(&line)?;
            }
        }
        self.lap.host("host.pose_gradient");
        let config = self.config;
        let logging = self.logs(step);
        if logging {
            let seconds = self.t_train.elapsed().as_secs_f64();
            let (line, l1, psnr) = log_line(
                self.ctx,
                &mut self.image_losses,
                self.cloth_losses.as_deref_mut(),
                self.avatar,
                self.refiner.as_deref(),
                step,
                s.frame.frame,
                seconds,
            )?;
            self.log_line(&line)?;
            let it_per_s = f64::from(step + 1 - self.start_step) / seconds.max(1e-9);
            progress(Progress::Step {
                step: step + 1,
                total: config.schedule.steps,
                l1,
                psnr,
                it_per_s,
            });
        }
        self.lap.host("host.log");
        let densified = config.densify.due(step + 1) && step + 1 < config.schedule.steps;
        if densified {
            self.densify(step, s.transforms.log_scale, progress)?;
            self.lap.host("host.densify");
        }
        let checkpointing = config.schedule.checkpoint_every > 0
            && (step + 1) % config.schedule.checkpoint_every == 0
            && step + 1 < self.stop_at;
        if checkpointing {
            self.save(step + 1, self.checkpoint_path)?;
        }
        Ok(match (densified || checkpointing, logging) {
            (true, _) => StepKind::Other,
            (false, true) => StepKind::Logged,
            (false, false) => StepKind::TrainingOnly,
        })
    }

    /// Densifies after `step + 1` steps; the renderer and the cloth losses follow the
    /// layers' new counts.
    fn densify(
        &mut self,
        step: u32,
        log_scale: f32,
        progress: &mut dyn FnMut(Progress),
    ) -> crate::Result<()> {
        let (summaries, counts) =
            densify_layers(self.ctx, self.avatar, self.config, step, log_scale)?;
        *self.renderer = renderer_for(
            self.ctx,
            self.avatar,
            self.cloth_losses.as_deref_mut(),
            self.config,
            self.size,
        )?;
        self.log_line(&serde_json::json!({ "step": step, "densify": summaries }))?;
        progress(Progress::Densify {
            step: step + 1,
            counts,
        });
        Ok(())
    }

    fn log_line(&mut self, line: &serde_json::Value) -> crate::Result<()> {
        writeln!(self.log, "{line}").map_err(|e| TrainerError::io(self.log_path, e))
    }

    /// The model and the optimisers' state after `step` steps, with the refined poses.
    fn save(&mut self, step: u32, path: &Path) -> crate::Result<()> {
        let mut state = self.avatar.state(self.ctx, step)?;
        state.poses = self.refiner.as_deref().map(|r| r.state().clone());
        checkpoint::write(path, &state)
    }
}

/// The image losses with the config's weights; LPIPS joins where there are weights and
/// `losses.lambda_lpips` is not 0.
fn image_losses_of(
    ctx: &Context,
    config: &TrainConfig,
    lpips_weights: Option<&LpipsWeights>,
    (width, height): (u32, u32),
) -> crate::Result<ImageLosses> {
    let lpips = match lpips_weights {
        Some(w) if config.losses.lambda_lpips > 0.0 => Some(Lpips::new(ctx, w, width, height)?),
        _ => None,
    };
    let weights = ImageLossWeights {
        l1: config.losses.lambda_l1,
        ssim: config.losses.lambda_ssim,
        lpips: config.losses.lambda_lpips,
    };
    Ok(ImageLosses::new(ctx, width, height, weights, lpips)?)
}

/// The renderer for the avatar's current counts, and the cloth losses resized to them
/// (after a checkpoint or a densification changed the counts).
fn renderer_for(
    ctx: &Context,
    avatar: &Avatar,
    cloth_losses: Option<&mut ClothLosses>,
    config: &TrainConfig,
    (width, height): (u32, u32),
) -> crate::Result<AvatarRenderer> {
    let renderer = AvatarRenderer::new(ctx, avatar, width, height, config.layers.compositing)?;
    if let (Some(c), Some(cloth)) = (cloth_losses, avatar.cloth()) {
        c.resize(ctx, cloth)?;
        c.set_mask_in_composite(renderer.is_three_pass());
    }
    Ok(renderer)
}

/// The skinning-weight fit's part of the report.
struct FitSummary {
    fit_steps: u32,
    fit_mse: f64,
    fit_seconds: f64,
}

/// The loop's part of the report.
struct LoopSummary {
    start_step: u32,
    stop_at: u32,
    train_seconds: f64,
    skipped_steps: u32,
    host_waits: HostWaits,
}

impl TrainReport {
    fn new(
        layout: Layout,
        gaussians: Vec<(String, u32)>,
        fit: FitSummary,
        run: LoopSummary,
        initial: EvalMetrics,
        fin: EvalMetrics,
    ) -> Self {
        let steps_run = run.stop_at.saturating_sub(run.start_step);
        Self {
            layout,
            gaussians,
            fit_steps: fit.fit_steps,
            fit_mse: fit.fit_mse,
            fit_seconds: fit.fit_seconds,
            start_step: run.start_step,
            steps: run.stop_at,
            train_seconds: run.train_seconds,
            iterations_per_second: f64::from(steps_run) / run.train_seconds.max(1e-9),
            skipped_steps: run.skipped_steps,
            host_waits: run.host_waits,
            initial,
            fin,
        }
    }
}

/// The cloth layer's losses, where the avatar has a cloth layer and the config weighs
/// them: their physics targets are the garments simulated through the sequence's motion.
fn cloth_losses_of(
    ctx: &Context,
    avatar: &Avatar,
    rig: &Rig,
    seq: &Sequence,
    config: &TrainConfig,
    (width, height): (u32, u32),
    progress: &mut dyn FnMut(Progress),
) -> crate::Result<Option<ClothLosses>> {
    match avatar.cloth() {
        Some(cloth)
            if config.losses.lambda_sim > 0.0
                || config.losses.lambda_arap > 0.0
                || config.losses.lambda_mask > 0.0 =>
        {
            let garments = cloth_target::simulate_sequence(
                rig,
                config.layers.cloth_fit,
                &seq.frames,
                &mut |done, total| progress(Progress::Simulate { done, total }),
            )?;
            let weights = ClothLossWeights {
                sim: config.losses.lambda_sim,
                gm_sigma: config.losses.gm_sigma,
                arap: config.losses.lambda_arap,
                mask: config.losses.lambda_mask,
                target_stride: config.layers.decimate,
            };
            Ok(Some(ClothLosses::new(
                ctx, cloth, garments, weights, width, height,
            )?))
        }
        _ => Ok(None),
    }
}

/// Loads the run's checkpoint into `avatar` (and the pose corrections into `refiner`);
/// the step it was taken at.
fn resume_from(
    ctx: &Context,
    checkpoint_path: &Path,
    config: &TrainConfig,
    avatar: &mut Avatar,
    refiner: Option<&mut PoseRefiner>,
) -> crate::Result<u32> {
    let state = checkpoint::read(checkpoint_path, &avatar.shapes(), avatar.scene_sh_degree())?;
    if state.step > config.schedule.steps {
        return Err(TrainerError::checkpoint(
            checkpoint_path,
            "step",
            format!(
                "the checkpoint is at step {}, past the run's {} steps (raise --steps)",
                state.step, config.schedule.steps
            ),
        ));
    }
    avatar.restore(ctx, &state)?;
    if let (Some(r), Some(p)) = (refiner, state.poses) {
        r.restore(p)
            .map_err(|e| TrainerError::checkpoint(checkpoint_path, "poses", e.to_string()))?;
    }
    Ok(state.step)
}

/// Fits every layer's deformation decoder to the body's skinning weights; the worst
/// layer's final mean squared error.
fn fit_skinning_weights(
    ctx: &Context,
    avatar: &mut Avatar,
    config: &TrainConfig,
    progress: &mut dyn FnMut(Progress),
) -> crate::Result<f64> {
    let total = config.schedule.fit_steps;
    let mut worst = 0.0f64;
    for l in &mut avatar.layers {
        let name = l.name.clone();
        let mse = l.fit_skinning_weights(ctx, total, config.schedule.fit_lr, 25, |step, mse| {
            progress(Progress::Fit {
                layer: name.clone(),
                step,
                total,
                mse,
            })
        })?;
        worst = worst.max(mse);
    }
    Ok(worst)
}

/// Writes the training steps' profile (`drape train --profile`): `profile.txt`, a table
/// whose shares are of the loop's wall time, and `profile.json`.
fn write_profile(
    out: &Path,
    profile: &drape_engine::Profile,
    waits: &HostWaits,
    steps: u64,
    loop_seconds: f64,
) -> crate::Result<()> {
    let table = format!("{steps} steps in {loop_seconds:.2} s ({:.1} ms/step); shares are of that wall time\n{}\n{}", 1e3 * loop_seconds / steps.max(1) as f64, waits.summary(), profile.table(1e3 * loop_seconds, steps, 25));
    let path = out.join("profile.txt");
    std::fs::write(&path, &table).map_err(|e| TrainerError::io(&path, e))?;
    write_json(&out.join("profile.json"), profile)
}

/// Marks the run finished: the complete marker written, the incomplete one removed.
fn mark_complete(out: &Path, steps: u32) -> crate::Result<()> {
    let marker = out.join(COMPLETE_MARKER);
    std::fs::write(&marker, format!("finished {steps} steps\n"))
        .map_err(|e| TrainerError::io(&marker, e))?;
    let _ = std::fs::remove_file(out.join(INCOMPLETE_MARKER));
    Ok(())
}

/// Exports the avatar posed as held-out frame `f`: one standard 3DGS PLY per layer
/// (`body_frameNNNN.ply`, `cloth_frameNNNN.ply`).
fn export_posed_layers(
    ctx: &Context,
    avatar: &mut Avatar,
    rig: &Rig,
    f: &DatasetFrame,
    out: &Path,
) -> crate::Result<()> {
    let ft = rig.frame(&f.body);
    avatar.set_frame(ctx, &ft)?;
    {
        let mut rec = ctx.record("export forward")?;
        avatar.record_forward(&mut rec, ft.log_scale)?;
        rec.submit_and_wait()?;
    }
    let cloud = avatar.read_posed(ctx)?;
    // One standard 3DGS PLY per layer.
    for layer in [Layer::Body, Layer::Cloth] {
        let mut part = drape_engine::ops::splat::scene::GaussianCloud::new(cloud.sh_degree);
        for i in (0..cloud.len()).filter(|&i| cloud.groups[i] == layer.group()) {
            part.push(&cloud.gaussian::<f32>(i), layer);
        }
        if !part.is_empty() {
            let name = if layer == Layer::Body {
                "body"
            } else {
                "cloth"
            };
            let path = out.join(format!("{name}_frame{:04}.ply", f.frame));
            ply::write(&path, &part)?;
        }
    }
    Ok(())
}

/// Renders `novel_pose.png`: the procedural raise-arms motion, halfway, on held-out
/// frame `f`'s root, translation and camera.
fn render_novel_pose(
    ctx: &Context,
    avatar: &mut Avatar,
    renderer: &mut AvatarRenderer,
    rig: &Rig,
    f: &DatasetFrame,
    settings: &RenderSettings,
    out: &Path,
    (width, height): (u32, u32),
) -> crate::Result<()> {
    let motion = crate::motion::procedural(crate::motion::MotionKind::RaiseArms, 30, 30.0, 1.0);
    let novel = &motion.poses[15];
    let body = match &f.body {
        BodyParams::Smpl {
            pose,
            betas,
            translation,
            scale,
        } => {
            let mut p = *pose;
            p[1..].copy_from_slice(&novel[1..]);
            BodyParams::Smpl {
                pose: p,
                betas: betas.clone(),
                translation: *translation,
                scale: *scale,
            }
        }
        BodyParams::Zju(z) => {
            let mut z = z.clone();
            for j in 1..24 {
                z.poses[3 * j..3 * j + 3].copy_from_slice(&novel[j].to_array());
            }
            BodyParams::Zju(z)
        }
    };
    let ft = rig.frame(&body);
    avatar.set_frame(ctx, &ft)?;
    {
        let mut rec = ctx.record("novel pose forward")?;
        avatar.record_forward(&mut rec, ft.log_scale)?;
        rec.submit_and_wait()?;
    }
    renderer.forward(ctx, avatar, &f.camera.to_pinhole([0.0; 3]), settings)?;
    let rgb = renderer.read_rgb(ctx)?;
    crate::dataset::image::write_rgb(&out.join("novel_pose.png"), width, height, &rgb)?;
    Ok(())
}
