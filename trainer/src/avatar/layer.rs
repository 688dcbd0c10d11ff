//! A triplane-driven Gaussian layer of the avatar (body or cloth): what it learns (its
//! canonical Gaussians, triplane and three decoders), its optimiser groups, its state on
//! the host and back, and the fit of its skinning weights. What a frame computes from
//! them, the posed Gaussians and the backward pass to every parameter's gradient, is the
//! layer's [`Deformer`] (`deform`).
//!
//! Decoder heads start at the initial values rather than being fitted to them (HUGS
//! fits for 7,000 steps): the opacity, SH, offset, rotation and log-scale heads have
//! zero weights and a bias equal to the initial value (opacity logit of 0.1, SH 0,
//! zero offset, the identity 6D rotation, zero log-scale delta), so the first forward
//! pass reproduces the initial Gaussians exactly. Only the skinning weights, a softmax
//! of a per-Gaussian function, need a fit ([`HumanLayer::fit_skinning_weights`]).

use crate::avatar::groups::Layer;
use drape_engine::ops::accumulate::Accumulation;
use drape_engine::ops::adam::{AdamGroup, LrSchedule};
use drape_engine::ops::deform::POSE_BLEND_FLOATS;
use drape_engine::ops::nn::{Activation, HeadDesc, Mlp, MlpDesc};
use drape_engine::ops::splat::densify::SCREEN_STATS_FLOATS;
use drape_engine::ops::splat::scene::GaussianCloud;
use drape_engine::ops::triplane::{Triplane, TriplaneDesc, TriplaneInit};
use drape_engine::recorder::flat_grid;
use drape_engine::{kernels, Buffer, BufferDesc, Context, Recording, Result};
use drape_shared::adam::LossParams;
use drape_shared::splat::layout::sh_coeffs;

use crate::avatar::deform::{Deformer, LayerParams};
use crate::avatar::state::{AdamState, LayerShape, LayerState};
use crate::body::model::NUM_JOINTS;

/// Sizes and rates of one layer.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LayerConfig {
    /// Texels per plane side (HUGS: 256).
    pub triplane_resolution: u32,
    /// Channels per plane (HUGS: 32; the feature is 3×).
    pub triplane_channels: u32,
    /// SH degree of the layer's colour (HUGS's human layer: 0).
    pub sh_degree: u32,
    /// Canonical-mean learning rate, decaying ×0.01 over the run (paper: 1.6e-4).
    pub lr_position: f32,
    /// HUGS: 1e-3.
    pub lr_triplane: f32,
    /// Appearance and geometry decoders (HUGS: 1e-3).
    pub lr_decoders: f32,
    /// Deformation decoder (HUGS: 1e-4).
    pub lr_deformation: f32,
    /// Widest hidden layer of the decoders (HUGS: 128, i.e. appearance 64-64,
    /// geometry 128-128, deformation 4 × 128); narrower is a speed knob: the decoders
    /// dominate a training step on CPU devices. A config file without it reads as 128.
    #[serde(default = "hugs_decoder_width")]
    pub decoder_width: u32,
    /// Pose-dependent offsets (the paper's option; HUGS's `posedirs`, off in its
    /// released configs): the deformation decoder gains a zero-initialised head of a
    /// 207 × 3 pose-blend basis per Gaussian, blended by the frame's pose features and
    /// added to the decoded offset before skinning (`ops::deform::record_pose_blend_forward`).
    /// Off by default, and when a config file lacks the key.
    #[serde(default)]
    pub pose_offsets: bool,
    /// Weight normalisation (PyTorch's `weight_norm`, dim 0) on the deformation
    /// decoder's last hidden layer, before the skinning logits, as HUGS has it. On in
    /// both presets; off when a config file lacks the key (a model saved without it has
    /// no norms to load).
    #[serde(default)]
    pub weight_norm: bool,
}

fn hugs_decoder_width() -> u32 {
    128
}

impl Default for LayerConfig {
    fn default() -> Self {
        Self {
            triplane_resolution: 256,
            triplane_channels: 32,
            sh_degree: 0,
            lr_position: 1.6e-4,
            lr_triplane: 1e-3,
            lr_decoders: 1e-3,
            lr_deformation: 1e-4,
            decoder_width: hugs_decoder_width(),
            pose_offsets: false,
            weight_norm: true,
        }
    }
}

/// The identity rotation in the 6D representation (first two rows of I).
const IDENTITY_6D: [f32; 6] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0];

/// A layer on the GPU.
pub struct HumanLayer {
    pub name: String,
    pub count: u32,
    pub config: LayerConfig,
    /// Canonical means (learned), quaternions and log-scales (fixed).
    pub means: Buffer,
    quats: Buffer,
    log_scales: Buffer,
    pub triplane: Triplane,
    pub appearance: Mlp,
    pub geometry: Mlp,
    pub deformation: Mlp,
    /// The canonical means' gradient (what the position group's Adam applies).
    grad_means: Buffer,
    /// Target skinning weights (count × 24), and the squared errors of the fit and of
    /// the cloth-LBS term.
    pub weight_targets: Buffer,
    weight_sq_error: Buffer,
    /// The frame's deformation: its transforms in, its posed Gaussians out.
    pub deformer: Deformer,
    pub groups: LayerGroups,
    /// How the triplane's backward accumulates ([`set_accumulation`](Self::set_accumulation)).
    accumulation: Accumulation,
    /// Densification statistics since the last densification (`ops::splat::densify`).
    pub screen_stats: Buffer,
    /// The mesh edges between the layer's Gaussians (the cloth's ARAP graph; empty for
    /// the body).
    pub edges: Vec<[u32; 2]>,
    /// The run's steps and the layer's seed (to rebuild it at another size).
    steps: u32,
    seed: u64,
}

/// The layer's Adam groups.
pub struct LayerGroups {
    pub position: AdamGroup,
    pub triplane: AdamGroup,
    pub appearance: AdamGroup,
    pub geometry: AdamGroup,
    pub deformation: AdamGroup,
}

/// The shapes of a layer's three decoders (appearance, geometry, deformation) for
/// `config`: what a file's decoder weights must fill.
pub fn decoder_descs(config: &LayerConfig) -> [MlpDesc; 3] {
    let width = 3 * config.triplane_channels as usize;
    let sh_values = 3 * sh_coeffs(config.sh_degree);
    let cap = config.decoder_width as usize;
    let appearance = MlpDesc::hugs_appearance(width, sh_values).capped(cap);
    let geometry = MlpDesc::hugs_geometry(width).capped(cap);
    let mut deformation = MlpDesc::hugs_deformation(width).capped(cap);
    if config.weight_norm {
        let last_hidden = deformation.hidden.len() - 1;
        deformation = deformation.with_weight_norm(last_hidden);
    }
    if config.pose_offsets {
        // Zero weights and bias: no offsets until training moves them (HUGS).
        deformation
            .heads
            .push(HeadDesc::new("pose_blend", POSE_BLEND_FLOATS, Activation::Identity).zero_init());
    }
    [appearance, geometry, deformation]
}

fn set_head_bias(desc: &MlpDesc, params: &mut [f32], head: usize, bias: &[f32]) {
    let (offsets, _) = desc.layout();
    let (w_off, b_off) = offsets[desc.hidden.len() + head];
    params[w_off..b_off].fill(0.0);
    params[b_off..b_off + bias.len()].copy_from_slice(bias);
}

fn f32_buffer(ctx: &Context, name: &str, len: usize) -> Result<Buffer> {
    ctx.create_buffer(name, BufferDesc::gpu_only(len as u64 * 4))
}

impl HumanLayer {
    /// A layer of the Gaussians of `cloud` (canonical space) with `weights` (count × 24)
    /// as the skinning targets; `steps` sizes the position schedule.
    pub fn new(
        ctx: &Context,
        name: &str,
        cloud: &GaussianCloud,
        weights: &[f32],
        config: &LayerConfig,
        steps: u32,
        seed: u64,
    ) -> Result<Self> {
        let n = cloud.len();
        assert_eq!(
            weights.len(),
            n * NUM_JOINTS,
            "{name}: skinning targets for another cloud"
        );
        // The triplane's box: the canonical bounds, 10% larger on every side.
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for p in cloud.means.chunks_exact(3) {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        for a in 0..3 {
            let pad = 0.1 * (hi[a] - lo[a]).max(0.01);
            lo[a] -= pad;
            hi[a] += pad;
        }
        let tdesc = TriplaneDesc {
            resolution: config.triplane_resolution,
            channels: config.triplane_channels,
            box_min: lo,
            box_max: hi,
        };
        let triplane = Triplane::new(
            ctx,
            &format!("{name} triplane"),
            tdesc,
            TriplaneInit::Normal { seed },
        )?;
        let width = tdesc.feature_width();
        let sh_values = 3 * sh_coeffs(config.sh_degree);
        let [appearance_desc, geometry_desc, deformation_desc] = decoder_descs(config);
        let mut appearance_params = appearance_desc.init_params(seed + 1);
        let opacity_logit = (0.1f32 / 0.9).ln();
        set_head_bias(
            &appearance_desc,
            &mut appearance_params,
            0,
            &[opacity_logit],
        );
        // SH 0 is colour 0.5 (the splatter adds 0.5), HUGS's initial colour.
        set_head_bias(
            &appearance_desc,
            &mut appearance_params,
            1,
            &vec![0.0; sh_values],
        );
        let mut geometry_params = geometry_desc.init_params(seed + 2);
        set_head_bias(&geometry_desc, &mut geometry_params, 0, &[0.0; 3]);
        set_head_bias(&geometry_desc, &mut geometry_params, 1, &IDENTITY_6D);
        set_head_bias(&geometry_desc, &mut geometry_params, 2, &[0.0; 3]);
        let appearance = Mlp::with_params(
            ctx,
            &format!("{name} appearance"),
            appearance_desc,
            n,
            &appearance_params,
        )?;
        let geometry = Mlp::with_params(
            ctx,
            &format!("{name} geometry"),
            geometry_desc,
            n,
            &geometry_params,
        )?;
        let deformation = Mlp::new(
            ctx,
            &format!("{name} deformation"),
            deformation_desc,
            n,
            seed + 3,
        )?;

        let mut means = f32_buffer(ctx, &format!("{name} canonical means"), 3 * n)?;
        ctx.write_buffer(&mut means, &cloud.means)?;
        let mut quats = f32_buffer(ctx, &format!("{name} canonical quats"), 4 * n)?;
        ctx.write_buffer(&mut quats, &cloud.quats)?;
        let mut log_scales = f32_buffer(ctx, &format!("{name} canonical log-scales"), 3 * n)?;
        ctx.write_buffer(&mut log_scales, &cloud.log_scales)?;
        let mut weight_targets =
            f32_buffer(ctx, &format!("{name} skinning targets"), NUM_JOINTS * n)?;
        ctx.write_buffer(&mut weight_targets, weights)?;

        let groups = LayerGroups {
            position: AdamGroup::new(
                ctx,
                &format!("{name} position"),
                3 * n,
                LrSchedule::exponential(config.lr_position, 0.01 * config.lr_position, steps),
            )?,
            triplane: AdamGroup::new(
                ctx,
                &format!("{name} triplane"),
                tdesc.len(),
                LrSchedule::constant(config.lr_triplane),
            )?,
            appearance: AdamGroup::new(
                ctx,
                &format!("{name} appearance"),
                appearance.param_count(),
                LrSchedule::constant(config.lr_decoders),
            )?,
            geometry: AdamGroup::new(
                ctx,
                &format!("{name} geometry"),
                geometry.param_count(),
                LrSchedule::constant(config.lr_decoders),
            )?,
            deformation: AdamGroup::new(
                ctx,
                &format!("{name} deformation"),
                deformation.param_count(),
                LrSchedule::constant(config.lr_deformation),
            )?,
        };
        Ok(Self {
            name: name.to_string(),
            count: n as u32,
            config: config.clone(),
            means,
            quats,
            log_scales,
            triplane,
            appearance,
            geometry,
            deformation,
            grad_means: f32_buffer(ctx, &format!("{name} canonical mean grads"), 3 * n)?,
            weight_targets,
            weight_sq_error: f32_buffer(
                ctx,
                &format!("{name} skinning weight errors"),
                NUM_JOINTS * n,
            )?,
            deformer: Deformer::new(ctx, name, n, width, config.sh_degree, config.pose_offsets)?,
            groups,
            accumulation: Accumulation::Auto,
            screen_stats: ctx.upload(
                &format!("{name} screen stats"),
                &vec![0.0f32; SCREEN_STATS_FLOATS * n.max(1)],
            )?,
            edges: Vec::new(),
            steps,
            seed,
        })
    }

    /// Chooses how the triplane's backward accumulates (deterministic: bit-identical
    /// runs, at the cost of a fixed-point scratch and slower atomics).
    pub fn set_accumulation(&mut self, ctx: &Context, accumulation: Accumulation) -> Result<()> {
        self.triplane.prepare(ctx, accumulation)?;
        self.accumulation = accumulation;
        Ok(())
    }

    pub fn accumulation(&self) -> Accumulation {
        self.accumulation
    }

    /// What the deformation reads of the layer (`deform::LayerParams`).
    pub fn params(&self) -> LayerParams<'_> {
        LayerParams {
            means: &self.means,
            quats: &self.quats,
            log_scales: &self.log_scales,
            grad_means: &self.grad_means,
            triplane: &self.triplane,
            appearance: &self.appearance,
            geometry: &self.geometry,
            deformation: &self.deformation,
            weight_targets: &self.weight_targets,
            weight_sq_error: &self.weight_sq_error,
            accumulation: self.accumulation,
        }
    }

    /// Records the forward pass into `deformer.posed` (the transforms must be written;
    /// [`Deformer::record_forward`]).
    pub fn record_forward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        log_scale_offset: f32,
    ) -> Result<()> {
        self.deformer
            .record_forward(rec, self.params(), log_scale_offset)
    }

    /// Records the backward pass from `deformer.posed_grads` into every parameter's
    /// gradient, with the cloth-LBS term and, with `pose_gradient`, the transforms'
    /// gradient ([`Deformer::record_backward`]).
    pub fn record_backward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        lbs_weight: f32,
        pose_gradient: bool,
    ) -> Result<()> {
        self.deformer
            .record_backward(rec, self.params(), lbs_weight, pose_gradient)
    }

    /// Records a count of the non-finite values among every gradient the Adam step
    /// would apply into `counter[0]` (which the caller zeroes first).
    /// Records the count of non-finite gradient values into `counter`, with
    /// `pose_gradient` also the pose refiner's partial sums of `∂L/∂A`.
    pub fn record_count_nonfinite<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        counter: &'a Buffer,
        pose_gradient: bool,
    ) -> Result<()> {
        let g = &self.groups;
        let buffers: [(&Buffer, usize); 5] = [
            (&self.grad_means, g.position.len),
            (&self.triplane.grads, g.triplane.len),
            (&self.appearance.grads, g.appearance.len),
            (&self.geometry.grads, g.geometry.len),
            (&self.deformation.grads, g.deformation.len),
        ];
        record_count_nonfinite(rec, buffers, counter)?;
        if pose_gradient {
            record_count_nonfinite(rec, [self.deformer.transform_partials()], counter)?;
        }
        Ok(())
    }

    /// Records one Adam step of every group (after the backward pass); with `guard`,
    /// a step the GPU applies only while the guard's first word is 0 (then call
    /// [`advance_adam`](Self::advance_adam) once the host has seen it stay down).
    pub fn record_adam<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        include_position: bool,
        guard: Option<&'a Buffer>,
    ) -> Result<()> {
        let g = &self.groups;
        if include_position {
            record_adam_step(rec, &g.position, &self.means, &self.grad_means, guard)?;
        }
        record_adam_step(
            rec,
            &g.triplane,
            &self.triplane.planes,
            &self.triplane.grads,
            guard,
        )?;
        record_adam_step(
            rec,
            &g.appearance,
            &self.appearance.params,
            &self.appearance.grads,
            guard,
        )?;
        record_adam_step(
            rec,
            &g.geometry,
            &self.geometry.params,
            &self.geometry.grads,
            guard,
        )?;
        record_adam_step(
            rec,
            &g.deformation,
            &self.deformation.params,
            &self.deformation.grads,
            guard,
        )
    }

    /// Counts a guarded step of [`record_adam`](Self::record_adam) that was applied.
    pub fn advance_adam(&self, include_position: bool) {
        let g = &self.groups;
        if include_position {
            g.position.advance();
        }
        for group in [&g.triplane, &g.appearance, &g.geometry, &g.deformation] {
            group.advance();
        }
    }

    pub fn fit_skinning_weights(
        &mut self,
        ctx: &Context,
        steps: u32,
        lr: f32,
        report_every: u32,
        mut report: impl FnMut(u32, f64),
    ) -> Result<f64> {
        let n = self.count;
        let len = NUM_JOINTS * n as usize;
        let deformation_adam = AdamGroup::new(
            ctx,
            "fit deformation",
            self.deformation.param_count(),
            LrSchedule::constant(lr),
        )?;
        let triplane_adam = AdamGroup::new(
            ctx,
            "fit triplane",
            self.triplane.desc.len(),
            LrSchedule::constant(lr),
        )?;
        let p = LossParams {
            len: len as u32,
            scale: 1.0 / len.max(1) as f32,
            _pad: [0; 2],
        };
        let mut mse = f64::NAN;
        for step in 0..=steps {
            {
                let mut rec = ctx.record("fit skinning weights")?;
                if self.deformer.has_pose_blend() {
                    // Only the weights are fitted: the pose-blend head gets no gradient.
                    rec.fill(self.deformation.head_grad(1), 0);
                }
                self.deformer
                    .record_weights_forward(&mut rec, self.params())?;
                rec.dispatch(
                    "fit.weight_mse",
                    kernels::train::MseGrad {
                        pred: self.deformation.head_output(0).read(),
                        target: self.weight_targets.read(),
                        grad: self.deformation.head_grad(0).write(),
                        squared_error: self.weight_sq_error.write(),
                    },
                    &p,
                    flat_grid(p.len),
                )?;
                if step < steps {
                    self.deformer
                        .record_weights_backward(&mut rec, self.params())?;
                    deformation_adam.record_step(
                        &mut rec,
                        &self.deformation.params,
                        &self.deformation.grads,
                    )?;
                    triplane_adam.record_step(
                        &mut rec,
                        &self.triplane.planes,
                        &self.triplane.grads,
                    )?;
                }
                rec.submit_and_wait()?;
            }
            if step == steps || (report_every > 0 && step % report_every == 0) {
                let e = ctx.read_buffer::<f32>(&mut self.weight_sq_error, len)?;
                mse = e.iter().map(|&v| f64::from(v)).sum::<f64>() / len.max(1) as f64;
                report(step, mse);
            }
        }
        Ok(mse)
    }

    /// What a file must hold to be loaded into this layer.
    pub fn shape(&self) -> LayerShape {
        LayerShape {
            name: self.name.clone(),
            count: self.count as usize,
            triplane_size: (self.triplane.desc.resolution, self.triplane.desc.channels),
            decoders: [
                self.appearance.param_count(),
                self.geometry.param_count(),
                self.deformation.param_count(),
            ],
        }
    }

    fn groups_mut(&mut self) -> [&mut AdamGroup; 5] {
        let g = &mut self.groups;
        [
            &mut g.position,
            &mut g.triplane,
            &mut g.appearance,
            &mut g.geometry,
            &mut g.deformation,
        ]
    }

    /// Everything learned, and the optimiser's state, read back to the host.
    pub fn state(&mut self, ctx: &Context) -> Result<LayerState> {
        let n = self.count as usize;
        let d = self.triplane.desc;
        let sizes = [
            self.appearance.param_count(),
            self.geometry.param_count(),
            self.deformation.param_count(),
        ];
        let mut adam = Vec::new();
        for g in self.groups_mut() {
            let step = g.steps();
            let (m, v) = g.read_moments(ctx)?;
            adam.push(AdamState { m, v, step });
        }
        Ok(LayerState {
            means: ctx.read_buffer(&mut self.means, 3 * n)?,
            quats: ctx.read_buffer(&mut self.quats, 4 * n)?,
            log_scales: ctx.read_buffer(&mut self.log_scales, 3 * n)?,
            triplane: ctx.read_buffer(&mut self.triplane.planes, d.len())?,
            triplane_size: (d.resolution, d.channels),
            triplane_box: [d.box_min, d.box_max],
            appearance: ctx.read_buffer(&mut self.appearance.params, sizes[0])?,
            geometry: ctx.read_buffer(&mut self.geometry.params, sizes[1])?,
            deformation: ctx.read_buffer(&mut self.deformation.params, sizes[2])?,
            adam,
            weight_targets: Some(ctx.read_buffer(&mut self.weight_targets, NUM_JOINTS * n)?),
            screen_stats: Some(ctx.read_buffer(&mut self.screen_stats, SCREEN_STATS_FLOATS * n)?),
            edges: Some(self.edges.clone()),
        })
    }

    /// Loads a state read by `checkpoint::read` against [`shape`](Self::shape). A state
    /// of another Gaussian count (densified) rebuilds the layer at that count first;
    /// such a state carries its skinning targets (`checkpoint::read` checks).
    pub fn restore(&mut self, ctx: &Context, s: &LayerState) -> Result<()> {
        let n = s.count();
        if n != self.count as usize {
            let cloud = canonical_cloud(s, self.config.sh_degree);
            let weights = s.weight_targets.as_deref().expect(
                "checkpoint::read requires the skinning targets of a layer of another count",
            );
            let mut fresh = Self::new(
                ctx,
                &self.name,
                &cloud,
                weights,
                &self.config,
                self.steps,
                self.seed,
            )?;
            fresh.set_accumulation(ctx, self.accumulation)?;
            fresh.edges = std::mem::take(&mut self.edges);
            *self = fresh;
        }
        if let Some(w) = &s.weight_targets {
            ctx.write_buffer(&mut self.weight_targets, w)?;
        }
        match &s.screen_stats {
            Some(st) => ctx.write_buffer(&mut self.screen_stats, st)?,
            None => ctx.write_buffer(
                &mut self.screen_stats,
                &vec![0.0f32; SCREEN_STATS_FLOATS * n],
            )?,
        }
        if let Some(e) = &s.edges {
            self.edges = e.clone();
        }
        ctx.write_buffer(&mut self.means, &s.means)?;
        ctx.write_buffer(&mut self.quats, &s.quats)?;
        ctx.write_buffer(&mut self.log_scales, &s.log_scales)?;
        self.triplane.desc.box_min = s.triplane_box[0];
        self.triplane.desc.box_max = s.triplane_box[1];
        ctx.write_buffer(&mut self.triplane.planes, &s.triplane)?;
        ctx.write_buffer(&mut self.appearance.params, &s.appearance)?;
        ctx.write_buffer(&mut self.geometry.params, &s.geometry)?;
        ctx.write_buffer(&mut self.deformation.params, &s.deformation)?;
        for (g, a) in self.groups_mut().into_iter().zip(&s.adam) {
            g.restore(ctx, &a.m, &a.v, a.step)?;
        }
        Ok(())
    }
}

/// A layer state's canonical Gaussians as a cloud to build a layer on (opacity and
/// colour are the decoders', so zero here).
pub(crate) fn canonical_cloud(s: &LayerState, sh_degree: u32) -> GaussianCloud {
    let n = s.count();
    GaussianCloud {
        sh_degree,
        means: s.means.clone(),
        log_scales: s.log_scales.clone(),
        quats: s.quats.clone(),
        opacity_logits: vec![0.0; n],
        sh: vec![0.0; 3 * sh_coeffs(sh_degree) * n],
        groups: vec![Layer::Body.group(); n],
    }
}

/// Records `counter[0] += ` the number of non-finite values in each `(buffer, floats)`
/// (the training guard's count; independent passes, no barrier).
pub fn record_count_nonfinite<'a>(
    rec: &mut Recording<'a>,
    buffers: impl IntoIterator<Item = (&'a Buffer, usize)>,
    counter: &'a Buffer,
) -> Result<()> {
    for (b, len) in buffers {
        let p = LossParams {
            len: len as u32,
            scale: 1.0,
            _pad: [0; 2],
        };
        rec.dispatch(
            "guard.count_nonfinite",
            kernels::train::CountNonfinite {
                values: b.read(),
                counter: counter.write(),
            },
            &p,
            flat_grid(p.len),
        )?;
    }
    Ok(())
}

/// One Adam step of `group`, guarded by `guard`'s first word where there is one.
pub(crate) fn record_adam_step<'a>(
    rec: &mut Recording<'a>,
    group: &'a AdamGroup,
    params: &'a Buffer,
    grads: &'a Buffer,
    guard: Option<&'a Buffer>,
) -> Result<()> {
    match guard {
        Some(guard) => group.record_guarded_step(rec, params, grads, guard),
        None => group.record_step(rec, params, grads),
    }
}
