//! A triplane-driven Gaussian layer of the avatar (body or cloth): its canonical
//! Gaussians, triplane, the three decoders, the posed Gaussians the renderer reads,
//! and its optimiser groups. Every per-Gaussian step runs on the GPU:
//!
//! forward: triplane(μ) → appearance / geometry / deformation decoders → deform and
//! skin (`ops::deform`) → posed Gaussians;
//! backward: posed gradients (from the splatter) → deform backward → decoder
//! backwards (their input gradients summed) → triplane backward → Adam.
//!
//! Decoder heads start at the initial values rather than being fitted to them (HUGS
//! fits for 7,000 steps): the opacity, SH, offset, rotation and log-scale heads have
//! zero weights and a bias equal to the initial value (opacity logit of 0.1, SH 0,
//! zero offset, the identity 6D rotation, zero log-scale delta), so the first forward
//! pass reproduces the initial Gaussians exactly. Only the skinning weights, a softmax
//! of a per-Gaussian function, need a fit ([`HumanLayer::fit_skinning_weights`]).

use drape_engine::ops::adam::{AdamGroup, LrSchedule};
use drape_engine::ops::deform::{self, DeformGrads, DeformInputs};
use drape_engine::ops::accumulate::Accumulation;
use drape_engine::ops::nn::{Activation, HeadDesc, Mlp, MlpDesc};
use drape_engine::ops::splat::densify::SCREEN_STATS_FLOATS;
use drape_engine::ops::splat::render::GaussianBuffers;
use drape_engine::ops::splat::scene::GaussianCloud;
use crate::avatar::groups::Layer;
use drape_engine::ops::triplane::{Triplane, TriplaneDesc, TriplaneInit};
use drape_engine::recorder::flat_grid;
use drape_engine::{Buffer, BufferDesc, Context, kernels, Recording, Result};
use drape_shared::adam::LossParams;
use drape_shared::splat::layout::sh_coeffs;

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
        Self { triplane_resolution: 256, triplane_channels: 32, sh_degree: 0, lr_position: 1.6e-4, lr_triplane: 1e-3, lr_decoders: 1e-3, lr_deformation: 1e-4, decoder_width: hugs_decoder_width(), pose_offsets: false, weight_norm: true }
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
    features: Buffer,
    grad_features: Buffer,
    pub appearance: Mlp,
    pub geometry: Mlp,
    pub deformation: Mlp,
    /// The frame's 24 transforms (written before each forward pass).
    pub transforms: Buffer,
    /// Posed Gaussians, as the splatter reads them.
    pub posed: GaussianBuffers,
    /// Their gradients, as the splatter's backward writes them.
    pub posed_grads: GaussianBuffers,
    grad_means: Buffer,
    grad_points: Buffer,
    /// Target skinning weights (count × 24).
    pub weight_targets: Buffer,
    weight_sq_error: Buffer,
    /// The cloth-LBS term's gradient on the weights, added to the deformation head's.
    lbs_grad: Buffer,
    /// Per-Gaussian terms of the transforms' gradient, and their per-chunk sums
    /// (`ops::deform`): what pose refinement reads.
    transform_terms: Buffer,
    transform_partials: Buffer,
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
    /// The frame's pose features (`FrameTransforms::pose_features`; read with
    /// `pose_offsets` only).
    pub pose_features: Buffer,
    /// With `pose_offsets`: the decoded offsets plus the pose blend (n × 3), which the
    /// deformation reads instead of the geometry decoder's offsets.
    blended_offsets: Option<Buffer>,
    /// Whether the forward adds the pose blend (with `pose_offsets`); off only for
    /// renders that measure what it is worth (`engine-bench trade`).
    pose_blend_on: bool,
}

/// The layer's Adam groups.
pub struct LayerGroups {
    pub position: AdamGroup,
    pub triplane: AdamGroup,
    pub appearance: AdamGroup,
    pub geometry: AdamGroup,
    pub deformation: AdamGroup,
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
    pub fn new(ctx: &Context, name: &str, cloud: &GaussianCloud, weights: &[f32], config: &LayerConfig, steps: u32, seed: u64) -> Result<Self> {
        let n = cloud.len();
        assert_eq!(weights.len(), n * NUM_JOINTS, "{name}: skinning targets for another cloud");
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
        let tdesc = TriplaneDesc { resolution: config.triplane_resolution, channels: config.triplane_channels, box_min: lo, box_max: hi };
        let triplane = Triplane::new(ctx, &format!("{name} triplane"), tdesc, TriplaneInit::Normal { seed })?;
        let width = tdesc.feature_width();
        let sh_values = 3 * sh_coeffs(config.sh_degree);

        let cap = config.decoder_width as usize;
        let appearance_desc = MlpDesc::hugs_appearance(width, sh_values).capped(cap);
        let mut appearance_params = appearance_desc.init_params(seed + 1);
        let opacity_logit = (0.1f32 / 0.9).ln();
        set_head_bias(&appearance_desc, &mut appearance_params, 0, &[opacity_logit]);
        // SH 0 is colour 0.5 (the splatter adds 0.5), HUGS's initial colour.
        set_head_bias(&appearance_desc, &mut appearance_params, 1, &vec![0.0; sh_values]);
        let geometry_desc = MlpDesc::hugs_geometry(width).capped(cap);
        let mut geometry_params = geometry_desc.init_params(seed + 2);
        set_head_bias(&geometry_desc, &mut geometry_params, 0, &[0.0; 3]);
        set_head_bias(&geometry_desc, &mut geometry_params, 1, &IDENTITY_6D);
        set_head_bias(&geometry_desc, &mut geometry_params, 2, &[0.0; 3]);
        let mut deformation_desc = MlpDesc::hugs_deformation(width).capped(cap);
        if config.weight_norm {
            let last_hidden = deformation_desc.hidden.len() - 1;
            deformation_desc = deformation_desc.with_weight_norm(last_hidden);
        }
        if config.pose_offsets {
            // Zero weights and bias: no offsets until training moves them (HUGS).
            deformation_desc.heads.push(HeadDesc::new("pose_blend", deform::POSE_BLEND_FLOATS, Activation::Identity).zero_init());
        }
        let appearance = Mlp::with_params(ctx, &format!("{name} appearance"), appearance_desc, n, &appearance_params)?;
        let geometry = Mlp::with_params(ctx, &format!("{name} geometry"), geometry_desc, n, &geometry_params)?;
        let deformation = Mlp::new(ctx, &format!("{name} deformation"), deformation_desc, n, seed + 3)?;

        let mut means = f32_buffer(ctx, &format!("{name} canonical means"), 3 * n)?;
        ctx.write_buffer(&mut means, &cloud.means)?;
        let mut quats = f32_buffer(ctx, &format!("{name} canonical quats"), 4 * n)?;
        ctx.write_buffer(&mut quats, &cloud.quats)?;
        let mut log_scales = f32_buffer(ctx, &format!("{name} canonical log-scales"), 3 * n)?;
        ctx.write_buffer(&mut log_scales, &cloud.log_scales)?;
        let mut weight_targets = f32_buffer(ctx, &format!("{name} skinning targets"), NUM_JOINTS * n)?;
        ctx.write_buffer(&mut weight_targets, weights)?;

        let groups = LayerGroups {
            position: AdamGroup::new(ctx, &format!("{name} position"), 3 * n, LrSchedule::exponential(config.lr_position, 0.01 * config.lr_position, steps))?,
            triplane: AdamGroup::new(ctx, &format!("{name} triplane"), tdesc.len(), LrSchedule::constant(config.lr_triplane))?,
            appearance: AdamGroup::new(ctx, &format!("{name} appearance"), appearance.param_count(), LrSchedule::constant(config.lr_decoders))?,
            geometry: AdamGroup::new(ctx, &format!("{name} geometry"), geometry.param_count(), LrSchedule::constant(config.lr_decoders))?,
            deformation: AdamGroup::new(ctx, &format!("{name} deformation"), deformation.param_count(), LrSchedule::constant(config.lr_deformation))?,
        };
        Ok(Self {
            name: name.to_string(),
            count: n as u32,
            config: config.clone(),
            means,
            quats,
            log_scales,
            triplane,
            features: f32_buffer(ctx, &format!("{name} features"), width * n)?,
            grad_features: f32_buffer(ctx, &format!("{name} feature grads"), width * n)?,
            appearance,
            geometry,
            deformation,
            // Rewritten every frame (`AvatarModel::set_frame`): host-written memory.
            transforms: ctx.create_buffer(&format!("{name} transforms"), BufferDesc::host_written(NUM_JOINTS as u64 * 12 * 4))?,
            posed: GaussianBuffers::new(ctx, &format!("{name} posed"), n, config.sh_degree)?,
            posed_grads: GaussianBuffers::new(ctx, &format!("{name} posed grads"), n, config.sh_degree)?,
            grad_means: f32_buffer(ctx, &format!("{name} canonical mean grads"), 3 * n)?,
            grad_points: f32_buffer(ctx, &format!("{name} triplane point grads"), 3 * n)?,
            weight_targets,
            weight_sq_error: f32_buffer(ctx, &format!("{name} skinning weight errors"), NUM_JOINTS * n)?,
            lbs_grad: f32_buffer(ctx, &format!("{name} cloth-LBS gradient"), NUM_JOINTS * n)?,
            transform_terms: f32_buffer(ctx, &format!("{name} transform gradient terms"), deform::transform_terms_len(n as u32))?,
            // Read by the host every step (the pose gradient): the kernel writes it into
            // host-visible memory, so reading it needs no copy submission.
            transform_partials: ctx.create_buffer(&format!("{name} transform gradient partials"), BufferDesc::readback(4 * deform::transform_partials_len(n as u32).max(1) as u64))?,
            groups,
            accumulation: Accumulation::Auto,
            screen_stats: ctx.upload(&format!("{name} screen stats"), &vec![0.0f32; SCREEN_STATS_FLOATS * n.max(1)])?,
            edges: Vec::new(),
            steps,
            seed,
            pose_features: ctx.create_buffer(&format!("{name} pose features"), BufferDesc::host_written(deform::POSE_FEATURES as u64 * 4))?,
            blended_offsets: if config.pose_offsets { Some(f32_buffer(ctx, &format!("{name} pose-blended offsets"), 3 * n)?) } else { None },
            pose_blend_on: true,
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

    /// Whether the layer was built with pose-dependent offsets.
    pub fn has_pose_blend(&self) -> bool {
        self.blended_offsets.is_some()
    }

    /// Renders with (`true`, the default) or without the pose blend: without it the
    /// deformation reads the decoded offsets alone. For measuring the blend's worth in
    /// renders; the backward needs it on (asserted).
    pub fn set_pose_blend(&mut self, on: bool) {
        self.pose_blend_on = on;
    }

    fn pose_blended(&self) -> Option<&Buffer> {
        self.blended_offsets.as_ref().filter(|_| self.pose_blend_on)
    }

    fn deform_inputs(&self) -> DeformInputs<'_> {
        DeformInputs {
            transforms: &self.transforms,
            means: &self.means,
            quats: &self.quats,
            log_scales: &self.log_scales,
            offsets: self.pose_blended().unwrap_or(self.geometry.head_output(0)),
            rot6d: self.geometry.head_output(1),
            log_scale_deltas: self.geometry.head_output(2),
            weights: self.deformation.head_output(0),
        }
    }

    /// Records the forward pass into `posed` (the transforms must be written).
    pub fn record_forward<'a>(&'a self, rec: &mut Recording<'a>, log_scale_offset: f32) -> Result<()> {
        let n = self.count;
        self.triplane.record_forward(rec, &self.means, &self.features, n)?;
        self.appearance.record_forward(rec, &self.features, n)?;
        self.geometry.record_forward(rec, &self.features, n)?;
        self.deformation.record_forward(rec, &self.features, n)?;
        if let Some(blended) = self.pose_blended() {
            deform::record_pose_blend_forward(rec, self.deformation.head_output(1), &self.pose_features, self.geometry.head_output(0), blended, n)?;
        }
        let inputs = self.deform_inputs();
        deform::record_forward(rec, &inputs, &self.posed.means, &self.posed.quats, &self.posed.log_scales, n, log_scale_offset)?;
        rec.copy(self.appearance.head_output(0), &self.posed.opacity_logits, u64::from(n) * 4);
        rec.copy(self.appearance.head_output(1), &self.posed.sh, self.posed.sh.size.min(self.appearance.head_output(1).size));
        Ok(())
    }

    /// Records the backward pass from `posed_grads` into every parameter's gradient,
    /// with the skinning-weight term `lbs_weight · mean((W - W_gt)²)` (the paper's
    /// cloth-LBS loss; 0 leaves it out); with `pose_gradient`, also the chunk sums of
    /// the gradient on the frame's transforms that [`read_transform_grad`](Self::read_transform_grad)
    /// reads (pose refinement; left out otherwise).
    pub fn record_backward<'a>(&'a self, rec: &mut Recording<'a>, lbs_weight: f32, pose_gradient: bool) -> Result<()> {
        assert!(self.pose_blend_on, "the backward of a layer rendered without its pose blend");
        let n = self.count;
        rec.copy(&self.posed_grads.opacity_logits, self.appearance.head_grad(0), u64::from(n) * 4);
        rec.copy(&self.posed_grads.sh, self.appearance.head_grad(1), self.posed_grads.sh.size.min(self.appearance.head_grad(1).size));
        let inputs = self.deform_inputs();
        let grads = DeformGrads {
            means: &self.grad_means,
            offsets: self.geometry.head_grad(0),
            rot6d: self.geometry.head_grad(1),
            log_scale_deltas: self.geometry.head_grad(2),
            weights: self.deformation.head_grad(0),
            transform_terms: &self.transform_terms,
        };
        deform::record_backward(rec, &inputs, &self.posed_grads.means, &self.posed_grads.quats, &self.posed_grads.log_scales, &grads, n)?;
        if self.blended_offsets.is_some() {
            // The offsets' gradient (in the geometry head: the blend adds to it) drives
            // the basis's.
            deform::record_pose_blend_backward(rec, &self.pose_features, self.geometry.head_grad(0), self.deformation.head_grad(1), n)?;
        }
        if pose_gradient {
            deform::record_transform_grad(rec, self.deformation.head_output(0), &self.transform_terms, &self.transform_partials, n)?;
        }
        if lbs_weight > 0.0 {
            let len = NUM_JOINTS as u32 * n;
            let p = LossParams { len, scale: lbs_weight / len.max(1) as f32, _pad: [0; 2] };
            rec.dispatch(
                "loss.cloth_lbs",
                kernels::train::MseGrad {
                    pred: self.deformation.head_output(0).read(),
                    target: self.weight_targets.read(),
                    grad: self.lbs_grad.write(),
                    squared_error: self.weight_sq_error.write(),
                },
                &p,
                flat_grid(len),
            )?;
            rec.dispatch("loss.cloth_lbs_add", kernels::train::AddInto { src: self.lbs_grad.read(), dst: self.deformation.head_grad(0).write() }, &p, flat_grid(len))?;
        }
        self.record_decoder_backward(rec, true)
    }

    /// `∂L/∂A` on the frame's 24 transforms (24 × 12, row-major 3x4) from the last
    /// backward pass.
    pub fn read_transform_grad(&mut self, ctx: &Context) -> Result<Vec<f64>> {
        let partials = ctx.read_buffer::<f32>(&mut self.transform_partials, deform::transform_partials_len(self.count))?;
        Ok(deform::sum_transform_partials(&partials))
    }

    /// Decoders' and triplane's backward from the gradients in the decoders' heads;
    /// with `to_means`, the canonical means' gradient (deformation path + triplane
    /// path) ends in `grad_means`.
    fn record_decoder_backward<'a>(&'a self, rec: &mut Recording<'a>, to_means: bool) -> Result<()> {
        let n = self.count;
        // The decoders add their input gradients into one buffer: one after another.
        self.appearance.record_backward(rec, &self.features, n, Some(&self.grad_features), false)?;
        self.geometry.record_backward(rec, &self.features, n, Some(&self.grad_features), true)?;
        self.deformation.record_backward(rec, &self.features, n, Some(&self.grad_features), true)?;
        self.triplane.record_backward(rec, &self.means, &self.grad_features, &self.grad_points, n, self.accumulation)?;
        if to_means {
            let p = LossParams { len: 3 * n, scale: 1.0, _pad: [0; 2] };
            rec.dispatch("layer.sum_mean_grads", kernels::train::AddInto { src: self.grad_points.read(), dst: self.grad_means.write() }, &p, flat_grid(p.len))?;
        }
        Ok(())
    }

    /// Records a count of the non-finite values among every gradient the Adam step
    /// would apply into `counter[0]` (which the caller zeroes first).
    /// Records the count of non-finite gradient values into `counter`, with
    /// `pose_gradient` also the pose refiner's partial sums of `∂L/∂A`.
    pub fn record_count_nonfinite<'a>(&'a self, rec: &mut Recording<'a>, counter: &'a Buffer, pose_gradient: bool) -> Result<()> {
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
            record_count_nonfinite(rec, [(&self.transform_partials, deform::transform_partials_len(self.count))], counter)?;
        }
        Ok(())
    }

    /// Records one Adam step of every group (after the backward pass); with `guard`,
    /// a step the GPU applies only while the guard's first word is 0 (then call
    /// [`advance_adam`](Self::advance_adam) once the host has seen it stay down).
    pub fn record_adam<'a>(&'a self, rec: &mut Recording<'a>, include_position: bool, guard: Option<&'a Buffer>) -> Result<()> {
        let g = &self.groups;
        if include_position {
            record_adam_step(rec, &g.position, &self.means, &self.grad_means, guard)?;
        }
        record_adam_step(rec, &g.triplane, &self.triplane.planes, &self.triplane.grads, guard)?;
        record_adam_step(rec, &g.appearance, &self.appearance.params, &self.appearance.grads, guard)?;
        record_adam_step(rec, &g.geometry, &self.geometry.params, &self.geometry.grads, guard)?;
        record_adam_step(rec, &g.deformation, &self.deformation.params, &self.deformation.grads, guard)
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

    pub fn fit_skinning_weights(&mut self, ctx: &Context, steps: u32, lr: f32, report_every: u32, mut report: impl FnMut(u32, f64)) -> Result<f64> {
        let n = self.count;
        let len = NUM_JOINTS * n as usize;
        let deformation_adam = AdamGroup::new(ctx, "fit deformation", self.deformation.param_count(), LrSchedule::constant(lr))?;
        let triplane_adam = AdamGroup::new(ctx, "fit triplane", self.triplane.desc.len(), LrSchedule::constant(lr))?;
        let p = LossParams { len: len as u32, scale: 1.0 / len.max(1) as f32, _pad: [0; 2] };
        let mut mse = f64::NAN;
        for step in 0..=steps {
            {
                let mut rec = ctx.record("fit skinning weights")?;
                if self.blended_offsets.is_some() {
                    // Only the weights are fitted: the pose-blend head gets no gradient.
                    rec.fill(self.deformation.head_grad(1), 0);
                }
                self.triplane.record_forward(&mut rec, &self.means, &self.features, n)?;
                self.deformation.record_forward(&mut rec, &self.features, n)?;
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
                    self.deformation.record_backward(&mut rec, &self.features, n, Some(&self.grad_features), false)?;
                    self.triplane.record_backward(&mut rec, &self.means, &self.grad_features, &self.grad_points, n, self.accumulation)?;
                    deformation_adam.record_step(&mut rec, &self.deformation.params, &self.deformation.grads)?;
                    triplane_adam.record_step(&mut rec, &self.triplane.planes, &self.triplane.grads)?;
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
            decoders: [self.appearance.param_count(), self.geometry.param_count(), self.deformation.param_count()],
        }
    }

    fn groups_mut(&mut self) -> [&mut AdamGroup; 5] {
        let g = &mut self.groups;
        [&mut g.position, &mut g.triplane, &mut g.appearance, &mut g.geometry, &mut g.deformation]
    }

    /// Everything learned, and the optimiser's state, read back to the host.
    pub fn state(&mut self, ctx: &Context) -> Result<LayerState> {
        let n = self.count as usize;
        let d = self.triplane.desc;
        let sizes = [self.appearance.param_count(), self.geometry.param_count(), self.deformation.param_count()];
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
            let k = sh_coeffs(self.config.sh_degree);
            let cloud = GaussianCloud { sh_degree: self.config.sh_degree, means: s.means.clone(), log_scales: s.log_scales.clone(), quats: s.quats.clone(), opacity_logits: vec![0.0; n], sh: vec![0.0; 3 * k * n], groups: vec![Layer::Body.group(); n] };
            let weights = s.weight_targets.as_deref().expect("checkpoint::read requires the skinning targets of a layer of another count");
            let mut fresh = Self::new(ctx, &self.name, &cloud, weights, &self.config, self.steps, self.seed)?;
            fresh.set_accumulation(ctx, self.accumulation)?;
            fresh.edges = std::mem::take(&mut self.edges);
            *self = fresh;
        }
        if let Some(w) = &s.weight_targets {
            ctx.write_buffer(&mut self.weight_targets, w)?;
        }
        match &s.screen_stats {
            Some(st) => ctx.write_buffer(&mut self.screen_stats, st)?,
            None => ctx.write_buffer(&mut self.screen_stats, &vec![0.0f32; SCREEN_STATS_FLOATS * n])?,
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

    /// The posed Gaussians of the last forward pass, read back.
    pub fn read_posed(&mut self, ctx: &Context) -> Result<GaussianCloud> {
        let layers = vec![Layer::Body; self.count as usize];
        self.posed.download(ctx, &layers)
    }
}

/// Records `counter[0] += ` the number of non-finite values in each `(buffer, floats)`
/// (the training guard's count; independent passes, no barrier).
pub fn record_count_nonfinite<'a>(rec: &mut Recording<'a>, buffers: impl IntoIterator<Item = (&'a Buffer, usize)>, counter: &'a Buffer) -> Result<()> {
    for (b, len) in buffers {
        let p = LossParams { len: len as u32, scale: 1.0, _pad: [0; 2] };
        rec.dispatch("guard.count_nonfinite", kernels::train::CountNonfinite { values: b.read(), counter: counter.write() }, &p, flat_grid(p.len))?;
    }
    Ok(())
}

/// One Adam step of `group`, guarded by `guard`'s first word where there is one.
pub(crate) fn record_adam_step<'a>(rec: &mut Recording<'a>, group: &'a AdamGroup, params: &'a Buffer, grads: &'a Buffer, guard: Option<&'a Buffer>) -> Result<()> {
    match guard {
        Some(guard) => group.record_guarded_step(rec, params, grads, guard),
        None => group.record_step(rec, params, grads),
    }
}
