//! Adam over flat parameter buffers with parameter groups (kernel `train::adam_step`,
//! math in `drape_shared::adam`): each group has its own learning rate (optionally an
//! exponential decay schedule), ε, bias correction from its own step count, and its
//! moments, which checkpoints and densification read and restore
//! ([`AdamGroup::read_moments`], [`AdamGroup::restore`]).

use std::cell::Cell;

use drape_shared::adam::AdamParams;

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::Result;
use crate::kernels::Kernel;
use crate::recorder::{flat_grid, Recording};

/// A learning rate, constant or decaying exponentially from `initial` to `final_lr`
/// over `steps` steps (log-linear interpolation, as 3DGS's position schedule), then
/// held.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LrSchedule {
    pub initial: f32,
    pub final_lr: f32,
    pub steps: u32,
}

impl LrSchedule {
    pub fn constant(lr: f32) -> Self {
        Self { initial: lr, final_lr: lr, steps: 1 }
    }

    pub fn exponential(initial: f32, final_lr: f32, steps: u32) -> Self {
        Self { initial, final_lr, steps: steps.max(1) }
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
    AdamParams { len, lr, beta1, beta2, eps, bias1: 1.0 - beta1.powi(t), bias2: 1.0 - beta2.powi(t), _pad: 0 }
}

/// One parameter group: `len` floats of some parameter buffer.
pub struct AdamGroup {
    pub name: String,
    pub len: usize,
    pub schedule: LrSchedule,
    pub beta1: f32,
    pub beta2: f32,
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
        let m = ctx.create_buffer(&format!("adam {name} m"), BufferDesc::gpu_only(len as u64 * 4))?;
        let v = ctx.create_buffer(&format!("adam {name} v"), BufferDesc::gpu_only(len as u64 * 4))?;
        let mut rec = ctx.record("adam zero moments")?;
        rec.fill(&m, 0);
        rec.fill(&v, 0);
        rec.submit_and_wait()?;
        Ok(Self { name: name.to_string(), len, schedule, beta1: 0.9, beta2: 0.999, eps: 1e-15, step: Cell::new(0), m, v })
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
    pub fn record_step<'a>(&'a self, rec: &mut Recording<'a>, params: &'a Buffer, grads: &'a Buffer) -> Result<()> {
        assert!(params.size >= self.len as u64 * 4 && grads.size >= self.len as u64 * 4, "Adam group '{}': buffers shorter than {} floats", self.name, self.len);
        let lr = self.lr();
        self.step.set(self.step.get() + 1);
        let pc = step_params(self.len as u32, lr, self.beta1, self.beta2, self.eps, self.step.get());
        rec.pass("adam.step", Kernel::TrainAdamStep)
            .write("params", params)
            .read("grads", grads)
            .write("m", &self.m)
            .write("v", &self.v)
            .push(&pc)
            .dispatch(flat_grid(pc.len))
    }

    /// Records one step like [`record_step`](Self::record_step) that the GPU applies
    /// only while `guard`'s first word is 0 (`train::adam_step_guarded`). The step
    /// count does not advance: after the submission, call [`advance`](Self::advance)
    /// if the guard stayed down (the next step's bias correction and learning rate
    /// then follow the steps applied, as with a step the host skipped).
    pub fn record_guarded_step<'a>(&'a self, rec: &mut Recording<'a>, params: &'a Buffer, grads: &'a Buffer, guard: &'a Buffer) -> Result<()> {
        assert!(params.size >= self.len as u64 * 4 && grads.size >= self.len as u64 * 4, "Adam group '{}': buffers shorter than {} floats", self.name, self.len);
        let pc = step_params(self.len as u32, self.lr(), self.beta1, self.beta2, self.eps, self.step.get() + 1);
        rec.pass("adam.step", Kernel::TrainAdamStepGuarded)
            .write("params", params)
            .read("grads", grads)
            .write("m", &self.m)
            .write("v", &self.v)
            .read("guard", guard)
            .push(&pc)
            .dispatch(flat_grid(pc.len))
    }

    /// Counts a step of [`record_guarded_step`](Self::record_guarded_step) the GPU
    /// applied.
    pub fn advance(&self) {
        self.step.set(self.step.get() + 1);
    }

    /// The moments, for checkpoints: (m, v).
    pub fn read_moments(&mut self, ctx: &Context) -> Result<(Vec<f32>, Vec<f32>)> {
        Ok((ctx.read_buffer(&mut self.m, self.len)?, ctx.read_buffer(&mut self.v, self.len)?))
    }

    /// Restores moments and the step count from a checkpoint.
    pub fn restore(&mut self, ctx: &Context, m: &[f32], v: &[f32], step: u32) -> Result<()> {
        assert!(m.len() == self.len && v.len() == self.len, "Adam group '{}': moments of the wrong length", self.name);
        ctx.write_buffer(&mut self.m, m)?;
        ctx.write_buffer(&mut self.v, v)?;
        self.step.set(step);
        Ok(())
    }
}
