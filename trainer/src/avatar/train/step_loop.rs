//! The step loop: from the run's first step to its last, each step (`step::run`) on the
//! frame and background of `(seed, step)`, then the pose refinement, the log line,
//! densification and the checkpoint that fall on it; the guard that stops a run whose
//! gradients stay non-finite; the stop at a signal, and the preemption test's failpoint
//! that lets a signal land at a known step.

use std::io::Write;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use drape_engine::ops::splat::scene::RenderSettings;
use drape_engine::Context;

use super::setup::renderer_for;
use crate::avatar::checkpoint;
use crate::avatar::cloth_losses::ClothLosses;
use crate::avatar::composite::AvatarRenderer;
use crate::avatar::config::TrainConfig;
use crate::avatar::densify;
use crate::avatar::inputs::Sequence;
use crate::avatar::losses::ImageLosses;
use crate::avatar::model::Avatar;
use crate::avatar::pose_refine::PoseRefiner;
use crate::avatar::report::Progress;
use crate::avatar::rig::Rig;
use crate::avatar::step::{self, HostWaits, Sample, Stages, StepBuffers, StepKind, StepOutcome};
use crate::dataset::loader::DatasetFrame;
use crate::error::TrainerError;

/// Times host phases of a step into the context's profile (a no-op without one).
pub(super) struct Lap<'c> {
    ctx: &'c Context,
    on: bool,
    since: Instant,
}

impl<'c> Lap<'c> {
    pub(super) fn new(ctx: &'c Context, on: bool) -> Self {
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

/// The guard's bookkeeping: steps skipped for non-finite gradients, and the stop after
/// too many in a row.
pub(super) struct SkipGuard {
    pub(super) total: u32,
    in_a_row: u32,
    limit: u32,
}

impl SkipGuard {
    pub(super) fn new(limit: u32) -> Self {
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

/// What densification did to each layer: (layer, before, after).
type DensifyCounts = Vec<(String, usize, usize)>;

/// Densifies and prunes every layer after `step + 1` steps; everything sized by the
/// layers' counts follows them. Returns the log's summaries and the counts.
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

/// The loop over steps and what it works on: each step (`step::run`), then the pose
/// refinement, the log line, densification and the checkpoint that fall on it.
pub(super) struct StepLoop<'r> {
    pub(super) ctx: &'r Context,
    pub(super) config: &'r TrainConfig,
    pub(super) seq: &'r Sequence,
    pub(super) rig: &'r Rig,
    pub(super) train_frames: &'r [&'r DatasetFrame],
    /// With a scene layer the avatar is trained on the whole image; without one, on the
    /// person over a background colour.
    pub(super) whole_image: bool,
    pub(super) size: (u32, u32),
    pub(super) settings: &'r RenderSettings,
    pub(super) checkpoint_path: &'r Path,
    pub(super) log_path: &'r Path,
    pub(super) log: &'r mut std::fs::File,
    pub(super) avatar: &'r mut Avatar,
    pub(super) renderer: &'r mut AvatarRenderer,
    pub(super) cloth_losses: Option<&'r mut ClothLosses>,
    pub(super) image_losses: ImageLosses,
    pub(super) buffers: StepBuffers,
    pub(super) refiner: Option<&'r mut PoseRefiner>,
    pub(super) skips: SkipGuard,
    pub(super) waits: HostWaits,
    pub(super) lap: Lap<'r>,
    pub(super) t_train: Instant,
    pub(super) start_step: u32,
    pub(super) stop_at: u32,
}

impl StepLoop<'_> {
    /// Steps from `start_step` to `stop_at`; `Some(step)` when `interrupt` stopped the
    /// run with its checkpoint written after `step` steps.
    pub(super) fn steps(
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

    /// A logging step's line (losses read back) with its L1 and PSNR.
    /// `seconds`: since training started.
    fn losses_line(
        &mut self,
        step: u32,
        frame: usize,
        seconds: f64,
    ) -> crate::Result<(serde_json::Value, f64, f64)> {
        let v = self.image_losses.read_values(self.ctx)?;
        let mut line = serde_json::json!({ "step": step, "frame": frame, "l1": v.l1, "ssim": v.ssim, "loss": v.loss, "psnr_train": v.psnr, "lr_position": self.avatar.layers[0].groups.position.lr(), "seconds": seconds });
        if let Some(c) = self.cloth_losses.as_deref_mut() {
            line["cloth"] = json_value(&c.read_values(self.ctx)?);
        }
        if let Some(l) = v.lpips {
            line["lpips"] = l.into();
        }
        if let Some(r) = self.refiner.as_deref() {
            // Mean over training frames of the largest joint correction and of the
            // translation's.
            let (rot, tr) = r.summary();
            line["pose_correction_rad"] = rot.into();
            line["translation_correction"] = tr.into();
        }
        Ok((line, v.l1, v.psnr))
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
            let (line, l1, psnr) = self.losses_line(step, s.frame.frame, seconds)?;
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
    pub(super) fn save(&mut self, step: u32, path: &Path) -> crate::Result<()> {
        let mut state = self.avatar.state(self.ctx, step)?;
        state.poses = self.refiner.as_deref().map(|r| r.state().clone());
        checkpoint::write(path, &state)
    }
}
