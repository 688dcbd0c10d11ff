//! Adam over the Gaussian parameters, on the GPU (kernel `train::adam_step`, math in
//! `drape_shared::adam`). One learning rate per parameter group; the moments live in
//! two more sets of [`GaussianBuffers`].


use crate::context::Context;
use crate::error::Result;
use crate::kernels::Kernel;
use crate::ops::splat::render::GaussianBuffers;
use crate::recorder::{flat_grid, Recording};

/// Learning rate of each parameter group.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LearningRates {
    pub means: f32,
    pub log_scales: f32,
    pub quats: f32,
    pub opacity_logits: f32,
    pub sh: f32,
}

impl LearningRates {
    fn in_binding_order(&self) -> [f32; 5] {
        [self.means, self.log_scales, self.quats, self.opacity_logits, self.sh]
    }
}

/// Adam state for one cloud.
pub struct GaussianAdam {
    pub lrs: LearningRates,
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
    step: u32,
    m: GaussianBuffers,
    v: GaussianBuffers,
}

impl GaussianAdam {
    /// Zeroed moments for `count` Gaussians of SH degree `sh_degree`; β = (0.9, 0.999),
    /// ε = 1e-15 (as HUGS uses).
    pub fn new(ctx: &Context, count: usize, sh_degree: u32, lrs: LearningRates) -> Result<Self> {
        let m = GaussianBuffers::new(ctx, "adam m", count, sh_degree)?;
        let v = GaussianBuffers::new(ctx, "adam v", count, sh_degree)?;
        let mut rec = ctx.record("adam zero moments")?;
        for b in m.all().into_iter().chain(v.all()) {
            rec.fill(b, 0);
        }
        rec.submit_and_wait()?;
        Ok(Self { lrs, beta1: 0.9, beta2: 0.999, eps: 1e-15, step: 0, m, v })
    }

    /// Steps taken so far.
    pub fn steps(&self) -> u32 {
        self.step
    }

    /// Records one step of every group (independent passes: no barriers between them).
    pub fn record_step<'a>(&'a mut self, rec: &mut Recording<'a>, params: &'a GaussianBuffers, grads: &'a GaussianBuffers) -> Result<()> {
        assert_eq!(params.count, grads.count, "gradients are for another cloud");
        assert_eq!(params.count, self.m.count, "Adam state is for another cloud");
        self.step += 1;
        let lens = params.lens();
        let lrs = self.lrs.in_binding_order();
        let (p, g, m, v) = (params.all(), grads.all(), self.m.all(), self.v.all());
        for i in 0..5 {
            let len = lens[i] as u32;
            let pc = crate::ops::adam::step_params(len, lrs[i], self.beta1, self.beta2, self.eps, self.step);
            rec.pass("adam.step", Kernel::TrainAdamStep)
                .write("params", p[i])
                .read("grads", g[i])
                .write("m", m[i])
                .write("v", v[i])
                .push(&pc)
                .dispatch(flat_grid(len))?;
        }
        Ok(())
    }
}
