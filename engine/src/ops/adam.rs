//! Adam, the engine's one optimizer (kernel `train::adam_step`, math in
//! `drape_shared::adam`), over flat parameter buffers with parameter groups: each
//! [`AdamGroup`] has its own learning rate (optionally an exponential decay schedule),
//! ε, bias correction from its own step count, and its moments, which checkpoints and
//! densification read and restore ([`AdamGroup::read_moments`], [`AdamGroup::restore`]).
//! [`GaussianAdam`] is the five groups of one cloud's [`GaussianBuffers`], stepped
//! together.

use std::cell::Cell;

use drape_shared::adam::AdamParams;

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::Result;
use crate::kernels;
use crate::ops::splat::render::GaussianBuffers;
use crate::recorder::{flat_grid, Recording};

/// A learning rate, constant or decaying exponentially from `initial` to `final_lr`
/// over `steps` steps (log-linear interpolation, as 3DGS's position schedule), then
/// held.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LrSchedule {
    /// The rate at step 0.
    pub initial: f32,
    /// The rate from step `steps` on.
    pub final_lr: f32,
    /// Steps from `initial` to `final_lr`.
    pub steps: u32,
}

impl LrSchedule {
    /// The same rate at every step.
    pub fn constant(lr: f32) -> Self {
        Self {
            initial: lr,
            final_lr: lr,
            steps: 1,
        }
    }

    /// From `initial` to `final_lr` over `steps` steps (at least 1).
    pub fn exponential(initial: f32, final_lr: f32, steps: u32) -> Self {
        Self {
            initial,
            final_lr,
            steps: steps.max(1),
        }
    }

    /// The rate at `step` (0-based).
    pub fn at(&self, step: u32) -> f32 {
        if self.initial == self.final_lr || self.initial <= 0.0 || self.final_lr <= 0.0 {
            return self.initial;
        }
        let t = (f64::from(step) / f64::from(self.steps)).min(1.0);
        (f64::from(self.initial).ln() * (1.0 - t) + f64::from(self.final_lr).ln() * t).exp() as f32
    }
}

/// The push constants of Adam step `t` (1-based) over `len` floats, with the bias
/// corrections `1 - β^t`.
pub fn step_params(len: u32, lr: f32, beta1: f32, beta2: f32, eps: f32, t: u32) -> AdamParams {
    let t = t as i32;
    AdamParams {
        len,
        lr,
        beta1,
        beta2,
        eps,
        bias1: 1.0 - beta1.powi(t),
        bias2: 1.0 - beta2.powi(t),
        _pad: 0,
    }
}

/// One parameter group: `len` floats of some parameter buffer.
pub struct AdamGroup {
    /// Names the moments' buffers and the group in assertion messages.
    pub name: String,
    /// Floats the group steps.
    pub len: usize,
    /// The learning rate by step.
    pub schedule: LrSchedule,
    /// Decay of the first moment.
    pub beta1: f32,
    /// Decay of the second moment.
    pub beta2: f32,
    /// Added to the second moment's square root.
    pub eps: f32,
    /// Steps recorded so far (a `Cell` so that a step borrows the group immutably for
    /// the recording's lifetime, like every other buffer it records).
    step: Cell<u32>,
    m: Buffer,
    v: Buffer,
}

impl AdamGroup {
    /// Zeroed moments for `len` floats; β = (0.9, 0.999), ε = 1e-15 (HUGS).
    pub fn new(ctx: &Context, name: &str, len: usize, schedule: LrSchedule) -> Result<Self> {
        let m = ctx.create_buffer(
            &format!("adam {name} m"),
            BufferDesc::gpu_only(len as u64 * 4),
        )?;
        let v = ctx.create_buffer(
            &format!("adam {name} v"),
            BufferDesc::gpu_only(len as u64 * 4),
        )?;
        let mut rec = ctx.record("adam zero moments")?;
        rec.fill(&m, 0);
        rec.fill(&v, 0);
        rec.submit_and_wait()?;
        Ok(Self {
            name: name.to_string(),
            len,
            schedule,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-15,
            step: Cell::new(0),
            m,
            v,
        })
    }

    /// Steps taken so far.
    pub fn steps(&self) -> u32 {
        self.step.get()
    }

    /// The learning rate the next step uses.
    pub fn lr(&self) -> f32 {
        self.schedule.at(self.step.get())
    }

    /// Records one step on `params` from `grads` (both at least `len` floats). A
    /// non-finite gradient element leaves its parameter and moments unchanged.
    pub fn record_step<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        params: &'a Buffer,
        grads: &'a Buffer,
    ) -> Result<()> {
        let pc = self.next_step_params(params, grads);
        self.advance();
        rec.dispatch(
            "adam.step",
            kernels::train::AdamStep {
                params: params.write(),
                grads: grads.read(),
                m: self.m.write(),
                v: self.v.write(),
            },
            &pc,
            flat_grid(pc.len),
        )
    }

    /// Records one step like [`record_step`](Self::record_step) that the GPU applies
    /// only while `guard`'s first word is 0 (`train::adam_step_guarded`). The step
    /// count does not advance: after the submission, call [`advance`](Self::advance)
    /// if the guard stayed down (the next step's bias correction and learning rate
    /// then follow the steps applied, as with a step the host skipped).
    pub fn record_guarded_step<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        params: &'a Buffer,
        grads: &'a Buffer,
        guard: &'a Buffer,
    ) -> Result<()> {
        let pc = self.next_step_params(params, grads);
        rec.dispatch(
            "adam.step",
            kernels::train::AdamStepGuarded {
                params: params.write(),
                grads: grads.read(),
                m: self.m.write(),
                v: self.v.write(),
                guard: guard.read(),
            },
            &pc,
            flat_grid(pc.len),
        )
    }

    /// The push constants of the next step on `params` from `grads`: the learning rate
    /// of the steps taken so far, the bias corrections of step `steps() + 1`.
    fn next_step_params(&self, params: &Buffer, grads: &Buffer) -> AdamParams {
        assert!(
            params.size >= self.len as u64 * 4 && grads.size >= self.len as u64 * 4,
            "Adam group '{}': buffers shorter than {} floats",
            self.name,
            self.len
        );
        step_params(
            self.len as u32,
            self.lr(),
            self.beta1,
            self.beta2,
            self.eps,
            self.step.get() + 1,
        )
    }

    /// Counts a step of [`record_guarded_step`](Self::record_guarded_step) the GPU
    /// applied.
    pub fn advance(&self) {
        self.step.set(self.step.get() + 1);
    }

    /// The moments, for checkpoints: (m, v).
    pub fn read_moments(&mut self, ctx: &Context) -> Result<(Vec<f32>, Vec<f32>)> {
        Ok((
            ctx.read_buffer(&mut self.m, self.len)?,
            ctx.read_buffer(&mut self.v, self.len)?,
        ))
    }

    /// Restores moments and the step count from a checkpoint.
    pub fn restore(&mut self, ctx: &Context, m: &[f32], v: &[f32], step: u32) -> Result<()> {
        assert!(
            m.len() == self.len && v.len() == self.len,
            "Adam group '{}': moments of the wrong length",
            self.name
        );
        ctx.write_buffer(&mut self.m, m)?;
        ctx.write_buffer(&mut self.v, v)?;
        self.step.set(step);
        Ok(())
    }
}

/// Learning rate of each of a cloud's parameter groups.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LearningRates {
    /// Of the means.
    pub means: f32,
    /// Of the log scales.
    pub log_scales: f32,
    /// Of the rotations (quaternions).
    pub quats: f32,
    /// Of the opacity logits.
    pub opacity_logits: f32,
    /// Of the SH coefficients.
    pub sh: f32,
}

impl LearningRates {
    fn in_binding_order(&self) -> [f32; 5] {
        [
            self.means,
            self.log_scales,
            self.quats,
            self.opacity_logits,
            self.sh,
        ]
    }
}

/// Adam over one cloud's [`GaussianBuffers`]: one [`AdamGroup`] per buffer, each at a
/// constant rate, stepped together.
pub struct GaussianAdam {
    count: u32,
    groups: [AdamGroup; 5],
}

impl GaussianAdam {
    /// Zeroed moments for `count` Gaussians of SH degree `sh_degree`; β = (0.9, 0.999),
    /// ε = 1e-15 (as HUGS uses).
    pub fn new(ctx: &Context, count: usize, sh_degree: u32, lrs: LearningRates) -> Result<Self> {
        let n = count;
        let lens = [
            3 * n,
            3 * n,
            4 * n,
            n,
            3 * drape_shared::splat::layout::sh_coeffs(sh_degree) * n,
        ];
        let names = ["means", "log_scales", "quats", "opacity_logits", "sh"];
        let lrs = lrs.in_binding_order();
        let group = |i: usize| AdamGroup::new(ctx, names[i], lens[i], LrSchedule::constant(lrs[i]));
        let groups = [group(0)?, group(1)?, group(2)?, group(3)?, group(4)?];
        let count = u32::try_from(count).map_err(|_| {
            crate::error::EngineError::too_large(
                "Gaussians",
                count as u64,
                u64::from(u32::MAX),
                "u32 indices",
            )
        })?;
        Ok(Self { count, groups })
    }

    /// Steps taken so far.
    pub fn steps(&self) -> u32 {
        self.groups[0].steps()
    }

    /// Records one step of every group (independent passes: no barriers between them).
    pub fn record_step<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        params: &'a GaussianBuffers,
        grads: &'a GaussianBuffers,
    ) -> Result<()> {
        assert_eq!(params.count, grads.count, "gradients are for another cloud");
        assert_eq!(params.count, self.count, "Adam state is for another cloud");
        for ((group, p), g) in self.groups.iter().zip(params.all()).zip(grads.all()) {
            group.record_step(rec, p, g)?;
        }
        Ok(())
    }
}
