//! One training step, as named stages: sample a frame → deform → render → losses →
//! backward → guard → Adam, recorded into one submission with one host wait.
//!
//! Nothing in the recording waits on the host. The guard is a count on the GPU: the
//! non-finite gradient values plus one per render whose tile intersections outgrew its
//! buffers (that image was drawn from a truncated list); Adam's kernel skips the whole
//! step while it is not 0 (`train::adam_step_guarded`). After the one wait the host
//! reads the guard and the renders' totals from mapped memory: a step that overflowed
//! is done again with the grown buffers, a step with non-finite gradients is counted
//! as skipped, and only an applied step advances Adam's step count. The pose
//! refiner's gradient is read from mapped memory too. A logging step also copies the
//! losses' values into host mirrors inside the same submission (`record_loss_readback`),
//! so the log line reads them after the one wait with no wait of its own.
//! Densification runs between steps (`densify`).

use drape_engine::ops::splat::scene::RenderSettings;
use drape_engine::{Buffer, BufferDesc, Context, Recording, Result};
use rand::{Rng, SeedableRng};

use crate::avatar::cloth_losses::ClothLosses;
use crate::avatar::composite::AvatarRenderer;
use crate::avatar::losses::ImageLosses;
use crate::avatar::model::Avatar;
use crate::avatar::pose_refine::PoseRefiner;
use crate::avatar::rig::{FrameTransforms, Rig};
use crate::dataset::loader::{BodyParams, DatasetFrame};

/// The training frame of one step and what it is rendered with.
pub(crate) struct Sample<'f> {
    /// Index into the training frames (the pose refiner's key).
    pub index: usize,
    pub frame: &'f DatasetFrame,
    /// The colour the person is masked onto (black where the scene layer fills the
    /// frame).
    pub background: [f32; 3],
    /// The body as rendered: the dataset's, with the refiner's correction.
    pub body: BodyParams,
    pub transforms: FrameTransforms,
}

/// Stage 1, sample: the frame and background colour of `step`, drawn from a generator
/// seeded by the step alone, so a resumed run draws what an uninterrupted one would.
pub(crate) fn sample<'f>(
    frames: &[&'f DatasetFrame],
    rig: &Rig,
    refiner: Option<&PoseRefiner>,
    seed: u64,
    step: u32,
    whole_image: bool,
) -> Sample<'f> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(
        seed ^ u64::from(step).wrapping_mul(0x9E37_79B9_7F4A_7C15),
    );
    let index = rng.random_range(0..frames.len());
    let frame = frames[index];
    let background: [f32; 3] = [rng.random(), rng.random(), rng.random()];
    let background = if whole_image { [0.0; 3] } else { background };
    let body = match refiner {
        Some(r) => r.body(index, &frame.body),
        None => frame.body.clone(),
    };
    let transforms = rig.frame(&body);
    Sample {
        index,
        frame,
        background,
        body,
        transforms,
    }
}

/// The step's own buffers: zeros for the renders' unused gradient inputs, and the
/// guard (read back after the wait from mapped memory).
pub(crate) struct StepBuffers {
    zeros: Buffer,
    guard: Buffer,
}

impl StepBuffers {
    /// Buffers for `width` × `height` images.
    pub fn new(ctx: &Context, width: u32, height: u32) -> Result<Self> {
        let zeros = ctx.create_buffer(
            "train zero grads",
            BufferDesc::gpu_only(4 * u64::from(width) * u64::from(height)),
        )?;
        let mut rec = ctx.record("train zero")?;
        rec.fill(&zeros, 0);
        rec.submit_and_wait()?;
        Ok(Self {
            zeros,
            guard: ctx.create_buffer("train guard", BufferDesc::readback(4))?,
        })
    }
}

/// What a step works on: the avatar, its renderer and losses.
pub(crate) struct Stages<'s> {
    pub avatar: &'s mut Avatar,
    pub renderer: &'s mut AvatarRenderer,
    pub cloth_losses: Option<&'s mut ClothLosses>,
    pub image_losses: &'s mut ImageLosses,
    pub settings: &'s RenderSettings,
    /// Whether the backward computes `∂L/∂A` for the pose refiner.
    pub pose_gradient: bool,
    /// Whether the step adds to the densification statistics.
    pub screen_stats: bool,
    /// The person over the background colour (false: the whole frame, with a scene).
    pub masked: bool,
    /// A logging step: the losses' values are copied to the host in the step's
    /// submission.
    pub read_losses: bool,
}

/// What became of a step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum StepOutcome {
    /// Adam applied it.
    Applied,
    /// Non-finite gradient values (this many): nothing was applied.
    Skipped { nonfinite: u32 },
    /// A render outgrew its buffers: nothing was applied; the buffers have grown and
    /// the step is to be done again.
    Overflowed,
}

/// One step on `s`: the host's writes, the recording of every stage, one submission
/// and one wait, then the guard.
pub(crate) fn run(
    ctx: &Context,
    st: &mut Stages<'_>,
    buffers: &mut StepBuffers,
    s: &Sample<'_>,
) -> Result<StepOutcome> {
    upload(ctx, st, s)?;
    prepare(st, s)?;
    {
        let st = &*st;
        let mut rec = ctx.record("train step")?;
        rec.fill(&buffers.guard, 0);
        record_deform(&mut rec, st.avatar, &s.transforms)?;
        record_render(&mut rec, st, buffers)?;
        st.image_losses.record(&mut rec, st.renderer.rgb())?;
        record_backward(&mut rec, st, buffers)?;
        record_guard(&mut rec, st, buffers)?;
        if st.read_losses {
            record_loss_readback(&mut rec, st);
        }
        st.avatar.record_adam(&mut rec, Some(&buffers.guard))?;
        rec.submit_and_wait()?;
    }
    finish(ctx, st, buffers)
}

/// The frame's host-written inputs: the target image and the cloth losses' targets
/// (host-visible memory: the last step's submission has completed).
fn upload(ctx: &Context, st: &mut Stages<'_>, s: &Sample<'_>) -> Result<()> {
    if st.masked {
        st.image_losses
            .set_target(ctx, &s.frame.masked_rgb(s.background))?;
    } else {
        st.image_losses.set_target(ctx, &s.frame.rgb)?;
    }
    if let Some(c) = st.cloth_losses.as_deref_mut() {
        c.set_frame(ctx, s.frame)?;
    }
    Ok(())
}

/// The renders' host-side settings for the frame's camera, forward and backward.
fn prepare(st: &mut Stages<'_>, s: &Sample<'_>) -> Result<()> {
    let camera = s.frame.camera.to_pinhole(s.background);
    st.renderer.prepare_frame(st.avatar, &camera, st.settings)?;
    st.renderer.prepare_backward(st.avatar)?;
    if let (Some(c), Some(cloth)) = (st.cloth_losses.as_deref_mut(), st.avatar.cloth()) {
        if c.needs_mask_pass() {
            c.prepare_mask_pass(cloth, &camera, st.settings)?;
        }
    }
    Ok(())
}

/// Stage 2, deform: the frame's transforms (written by the command buffer), each
/// layer's decoders and skinning, and the gather into the avatar's posed cloud.
fn record_deform<'a>(
    rec: &mut Recording<'a>,
    avatar: &'a Avatar,
    transforms: &FrameTransforms,
) -> Result<()> {
    avatar.record_set_frame(rec, transforms);
    avatar.record_forward(rec, transforms.log_scale)
}

/// Stage 3, render: the avatar's frame, and the renders' overflow flags into the guard.
/// (Stage 4, the image losses, is `ImageLosses::record`.)
fn record_render<'a>(
    rec: &mut Recording<'a>,
    st: &'a Stages<'_>,
    buffers: &'a StepBuffers,
) -> Result<()> {
    st.renderer.record_frame(rec, st.avatar)?;
    st.renderer.record_overflow_flags(rec, &buffers.guard)
}

/// Stage 5, backward: through the renders and the composite into every layer's posed
/// Gaussians, the cloth losses, then each layer's skinning, decoders and triplane;
/// the densification statistics where they are gathered.
fn record_backward<'a>(
    rec: &mut Recording<'a>,
    st: &'a Stages<'_>,
    buffers: &'a StepBuffers,
) -> Result<()> {
    let cloth_losses = st.cloth_losses.as_deref();
    st.renderer.record_backward(
        rec,
        st.avatar,
        st.image_losses.grad_rgb(),
        &buffers.zeros,
        cloth_losses,
    )?;
    if let (Some(c), Some(cloth)) = (cloth_losses, st.avatar.cloth()) {
        if c.needs_mask_pass() {
            c.record_mask_pass(rec, cloth, &buffers.guard)?;
        }
    }
    st.renderer.record_scatter(rec, st.avatar)?;
    if let (Some(c), Some(cloth)) = (cloth_losses, st.avatar.cloth()) {
        c.record(rec, cloth)?;
    }
    st.avatar.record_layers_backward(rec, st.pose_gradient)?;
    if st.screen_stats {
        st.renderer.record_screen_stats(rec, st.avatar)?;
    }
    Ok(())
}

/// Stage 6, guard: adds every non-finite gradient value (and the pose refiner's
/// partial sums) to the guard Adam reads.
fn record_guard<'a>(
    rec: &mut Recording<'a>,
    st: &'a Stages<'_>,
    buffers: &'a StepBuffers,
) -> Result<()> {
    st.avatar
        .record_count_nonfinite(rec, &buffers.guard, st.pose_gradient)
}

/// Stage 7 on logging steps, read-back: the losses' values into host memory, read
/// after the step's one wait (`ImageLosses::read_values`, `ClothLosses::read_values`).
fn record_loss_readback<'a>(rec: &mut Recording<'a>, st: &'a Stages<'_>) {
    st.image_losses.record_readback(rec);
    if let Some(c) = st.cloth_losses.as_deref() {
        c.record_readback(rec);
    }
}

/// After the wait: the renders' totals (an overflow grows their buffers), then the
/// guard; an applied step advances Adam's step count.
fn finish(ctx: &Context, st: &mut Stages<'_>, buffers: &mut StepBuffers) -> Result<StepOutcome> {
    let mut overflowed = st.renderer.finish_frame()?;
    if let Some(c) = st.cloth_losses.as_deref_mut() {
        if c.needs_mask_pass() {
            overflowed |= c.finish_mask_pass()?;
        }
    }
    if overflowed {
        return Ok(StepOutcome::Overflowed);
    }
    let nonfinite = ctx.read_buffer::<u32>(&mut buffers.guard, 1)?[0];
    if nonfinite > 0 {
        return Ok(StepOutcome::Skipped { nonfinite });
    }
    st.avatar.advance_adam();
    Ok(StepOutcome::Applied)
}

/// What a step did besides training, for counting its host waits apart.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum StepKind {
    /// It only trained.
    TrainingOnly,
    /// It trained and wrote a log line (the losses come from host mirrors filled in
    /// the step's own submission).
    Logged,
    /// It densified or checkpointed (those read the model back), or was skipped.
    Other,
}

/// Host waits (fence waits) per step: the steps that only trained, those that also
/// logged, and the rest: steps that densified or checkpointed (those read the model
/// back) or were done again after a render outgrew its buffers (growing makes
/// buffers, and the step is submitted twice).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct HostWaits {
    /// Steps that only trained, once.
    pub plain_steps: u64,
    pub plain_waits: u64,
    /// The most waits one of them took.
    pub plain_max: u64,
    /// Steps that trained and logged, once.
    pub logged_steps: u64,
    pub logged_waits: u64,
    /// The most waits one of them took.
    pub logged_max: u64,
    /// The other steps.
    pub other_steps: u64,
    pub other_waits: u64,
    /// Steps done again after an overflow (counted among the other steps).
    pub redone_steps: u64,
}

impl HostWaits {
    /// Counts a step of `kind` that took `waits` fence waits over `attempts`
    /// submissions.
    pub(crate) fn add(&mut self, waits: u64, attempts: u32, kind: StepKind) {
        if attempts > 1 {
            self.redone_steps += 1;
        }
        let (steps, total, max) = match (kind, attempts) {
            (StepKind::TrainingOnly, 1) => (
                &mut self.plain_steps,
                &mut self.plain_waits,
                Some(&mut self.plain_max),
            ),
            (StepKind::Logged, 1) => (
                &mut self.logged_steps,
                &mut self.logged_waits,
                Some(&mut self.logged_max),
            ),
            _ => (&mut self.other_steps, &mut self.other_waits, None),
        };
        *steps += 1;
        *total += waits;
        if let Some(m) = max {
            *m = (*m).max(waits);
        }
    }

    /// One line for the profile.
    pub fn summary(&self) -> String {
        let mean = |w: u64, n: u64| w as f64 / n.max(1) as f64;
        format!(
            "host waits (fence waits) per step: {:.2} mean, {} max over {} training-only steps; {:.2} mean, {} max over {} steps that also logged; {:.2} mean over {} steps that densified, checkpointed, were skipped or were done again after a render outgrew its buffers ({} such)",
            mean(self.plain_waits, self.plain_steps),
            self.plain_max,
            self.plain_steps,
            mean(self.logged_waits, self.logged_steps),
            self.logged_max,
            self.logged_steps,
            mean(self.other_waits, self.other_steps),
            self.other_steps,
            self.redone_steps
        )
    }
}
