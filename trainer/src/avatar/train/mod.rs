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
//!
//! A run is a [`TrainJob`]: what it trains on, its run directory and how it may stop
//! early, run on a device context. This module owns the job and the run's order of
//! phases; `run_dir` owns the run directory's life cycle, `setup` what the run is built
//! from, `step_loop` the steps and `exports` what a finished run writes besides its
//! model and metrics.

mod exports;
mod run_dir;
mod setup;
mod step_loop;

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use drape_engine::ops::lpips::LpipsWeights;
use drape_engine::ops::splat::scene::RenderSettings;
use drape_engine::Context;

use crate::avatar::assemble::build_avatar;
use crate::avatar::cloth_target;
use crate::avatar::composite::AvatarRenderer;
use crate::avatar::eval::{evaluate, write_reports, EvalInputs};
use crate::avatar::inputs::betas_of;
use crate::avatar::pose_refine::PoseRefiner;
use crate::avatar::report::write_json;
use crate::avatar::rig::Rig;
use crate::avatar::run::RunInfo;
use crate::avatar::step::{HostWaits, StepBuffers};
use crate::body::SmplModel;
use crate::dataset::loader::DatasetFrame;
use crate::dataset::split::Split;
use crate::error::TrainerError;
use exports::{export_posed_layers, render_novel_pose, write_profile};
use run_dir::{checkpoint_path, mark_complete, resume_from};
use setup::{cloth_losses_of, fit_skinning_weights, image_losses_of, image_size, renderer_for};
use step_loop::{Lap, SkipGuard, StepLoop};

// The paths the tools and tests know a run's parts by.
pub use crate::avatar::assemble::{choose_layers, Layers};
pub use crate::avatar::config::{Preset, TrainConfig};
pub use crate::avatar::eval::{mask_bbox, psnr, EvalMetrics};
pub use crate::avatar::inputs::{body_model, load_sequence, Layout, Sequence};
pub use crate::avatar::report::Progress;
pub use run_dir::{check_fresh, run_state, RunState, COMPLETE_MARKER, INCOMPLETE_MARKER};

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

/// How a run ended.
#[derive(Debug)]
pub enum Outcome {
    /// Every step ran; the model, metrics and `complete` marker are written.
    Finished(Box<TrainReport>),
    /// The interrupt flag was set: the step in flight finished and the checkpoint holds
    /// the state after `step` steps; `--resume` continues it.
    Interrupted { step: u32 },
}

/// One training run: the sequence and body it trains on, its configuration and run
/// directory, and how it starts and stops. [`TrainJob::new`] makes a new run trained to
/// `config.schedule.steps`, which no signal stops, writes no `run.json` and reports no
/// progress; the builder methods change that. [`TrainJob::run`] trains it.
///
/// The step's frame and background come from `(seed, step)`, so a resumed run samples
/// what the uninterrupted one would have.
pub struct TrainJob<'a> {
    seq: &'a Sequence,
    model: SmplModel,
    config: &'a TrainConfig,
    out: &'a Path,
    resume: bool,
    stop_after: Option<u32>,
    info: Option<&'a RunInfo>,
    interrupt: Option<&'a AtomicBool>,
    progress: Option<&'a mut dyn FnMut(Progress)>,
}

impl<'a> TrainJob<'a> {
    /// A new run on `seq` with the body `model` and `config`, in the run directory
    /// `out`, which must be missing or empty.
    pub fn new(
        seq: &'a Sequence,
        model: SmplModel,
        config: &'a TrainConfig,
        out: &'a Path,
    ) -> Self {
        Self {
            seq,
            model,
            config,
            out,
            resume: false,
            stop_after: None,
            info: None,
            interrupt: None,
            progress: None,
        }
    }

    /// With `resume`, continues the run in `out` from its last checkpoint
    /// (`out/checkpoint.npz`) to `config.schedule.steps` instead of starting a new one.
    pub fn resume(mut self, resume: bool) -> Self {
        self.resume = resume;
        self
    }

    /// Stops once `steps` steps are done (at most `config.schedule.steps`) as if the run
    /// had been interrupted there: the checkpoint is written, the schedules still run to
    /// `config.schedule.steps`, and a later resume continues as the uninterrupted run
    /// would.
    pub fn stop_after(mut self, steps: u32) -> Self {
        self.stop_after = Some(steps);
        self
    }

    /// Writes `info` (the data and body) as `run.json` when the run directory is made,
    /// so that `--resume` and the other commands find the data of an unfinished run.
    pub fn run_info(mut self, info: &'a RunInfo) -> Self {
        self.info = Some(info);
        self
    }

    /// Stops cleanly when `interrupt` becomes true (a signal handler sets it): the step
    /// in flight finishes, the checkpoint is written atomically, the run directory stays
    /// resumable and [`run`](Self::run) returns [`Outcome::Interrupted`].
    pub fn interrupt(mut self, interrupt: &'a AtomicBool) -> Self {
        self.interrupt = Some(interrupt);
        self
    }

    /// Tells `progress` of the skinning-weight fit, the garment simulation, the steps,
    /// densification and evaluation.
    pub fn progress(mut self, progress: &'a mut dyn FnMut(Progress)) -> Self {
        self.progress = Some(progress);
        self
    }

    /// Trains the job on `ctx`. Everything the run needs is checked before its run
    /// directory is made; a new run that fails before its first checkpoint leaves
    /// nothing behind (an empty directory that was there before stays, empty), and after
    /// it the run stays resumable.
    pub fn run(self, ctx: &Context) -> crate::Result<Outcome> {
        let Self {
            seq,
            model,
            config,
            out,
            resume,
            stop_after,
            info,
            interrupt,
            progress,
        } = self;
        let mut quiet = |_: Progress| {};
        let progress: &mut dyn FnMut(Progress) = match progress {
            Some(p) => p,
            None => &mut quiet,
        };
        let never = AtomicBool::new(false);
        let stop_at = stop_after
            .unwrap_or(config.schedule.steps)
            .min(config.schedule.steps);
        config.validate()?;
        let size = image_size(seq)?;
        // LPIPS where the run has weights: read before the run directory is made, so a
        // wrong path leaves nothing behind.
        let lpips_weights = match &config.losses.lpips_weights {
            Some(path) => Some(LpipsWeights::load(path, config.losses.lpips_net)?),
            None => None,
        };
        let plan = Plan {
            ctx,
            seq,
            config,
            out,
            resume,
            stop_at,
            size,
            interrupt: interrupt.unwrap_or(&never),
            lpips_weights,
        };
        if resume {
            let checkpoint = checkpoint_path(out);
            if !checkpoint.is_file() {
                return Err(TrainerError::run(
                    &checkpoint,
                    "no checkpoint to resume from",
                ));
            }
            return train_in(&plan, model, progress);
        }
        check_fresh(out)?;
        let created = !out.exists();
        let result =
            run_dir::make(out, config, info).and_then(|()| train_in(&plan, model, progress));
        if result.is_err() {
            run_dir::clean_up_failed(out, created);
        }
        result
    }

    /// [`run`](Self::run) for a job that is to finish: its report. A job stopped by its
    /// interrupt flag is an error that says where its checkpoint is.
    pub fn train(self, ctx: &Context) -> crate::Result<TrainReport> {
        let out = self.out;
        match self.run(ctx)? {
            Outcome::Finished(report) => Ok(*report),
            Outcome::Interrupted { step } => Err(TrainerError::run(
                out,
                format!(
                    "interrupted: checkpointed after step {step}; `drape train --resume {}` continues it",
                    out.display()
                ),
            )),
        }
    }
}

/// A job with its defaults resolved and its inputs checked: what training needs.
struct Plan<'a> {
    ctx: &'a Context,
    seq: &'a Sequence,
    config: &'a TrainConfig,
    out: &'a Path,
    resume: bool,
    /// The steps done when the loop stops (at most `config.schedule.steps`).
    stop_at: u32,
    /// Every image's size.
    size: (u32, u32),
    interrupt: &'a AtomicBool,
    lpips_weights: Option<LpipsWeights>,
}

/// Trains in the run directory, made or checked already: the layers built, their
/// skinning weights fitted (or the checkpoint loaded), the steps, then the held-out
/// evaluation and the exports.
fn train_in(
    plan: &Plan<'_>,
    model: SmplModel,
    progress: &mut dyn FnMut(Progress),
) -> crate::Result<Outcome> {
    let Plan {
        ctx,
        seq,
        config,
        out,
        resume,
        stop_at,
        size: (width, height),
        interrupt,
        ref lpips_weights,
    } = *plan;
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
    let checkpoint_path = checkpoint_path(out);
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
    // 3. Held-out evaluation and the run's exports. A held-out image of a trained
    //    instant (another camera, the same frame) takes that instant's refined pose.
    let eval_dir = out.join("eval");
    // Copies only of the images whose body changes (none without refinement, or for
    // a monocular sequence, whose held-out instants were not trained).
    let refined: Vec<Option<DatasetFrame>> = test_frames
        .iter()
        .map(|f| {
            let body = refiner.as_ref()?.body_of_frame(f.frame as u32, &f.body);
            (body != f.body).then(|| DatasetFrame {
                body,
                ..(*f).clone()
            })
        })
        .collect();
    let refined_tests: Vec<&DatasetFrame> = test_frames
        .iter()
        .zip(&refined)
        .map(|(f, r)| r.as_ref().unwrap_or(f))
        .collect();
    let (fin, per_frame) = evaluate(
        ctx,
        &mut avatar,
        &mut renderer,
        &EvalInputs {
            frames: &refined_tests,
            ..eval_inputs(Some(&eval_dir))
        },
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
        render_novel_pose(ctx, &mut avatar, &mut renderer, &rig, f, &settings, out)?;
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
