//! The deformation of a human layer (body or cloth) for one frame: its per-frame
//! buffers ([`Deformer`]) and the recording of its forward and backward passes.
//!
//! forward: triplane(μ) → appearance / geometry / deformation decoders → pose blend
//! (with `pose_offsets`) → deform and skin (`ops::deform`) → posed Gaussians;
//! backward: posed gradients (from the splatter) → deform backward (and the transforms'
//! gradient, for pose refinement) → the cloth-LBS term → decoder backwards (their input
//! gradients summed) → triplane backward → the canonical means' gradient.
//!
//! What the deformation reads and writes of its layer, the parameters (canonical
//! Gaussians, triplane, decoders) and their gradients, stays with the layer
//! (`layer::HumanLayer`, which owns a `Deformer`) and is lent to each recording as
//! [`LayerParams`]: the layer keeps what is learned and its optimiser, state and fit;
//! this module keeps what a frame computes from them. The order of the recorded passes
//! is the order the deterministic runs were made with: reordering them changes no
//! value but is checked by nothing else.

use drape_engine::ops::accumulate::Accumulation;
use drape_engine::ops::deform::{self, DeformGrads, DeformInputs};
use drape_engine::ops::nn::Mlp;
use drape_engine::ops::splat::render::GaussianBuffers;
use drape_engine::ops::splat::scene::GaussianCloud;
use drape_engine::ops::triplane::Triplane;
use drape_engine::recorder::flat_grid;
use drape_engine::{kernels, Buffer, BufferDesc, Context, Recording, Result};
use drape_shared::adam::LossParams;

use crate::avatar::groups::Layer;
use crate::body::model::NUM_JOINTS;

/// What the deformation reads of its layer: the canonical Gaussians, the triplane and
/// the three decoders (parameters, activations and gradients), the canonical means'
/// gradient it writes, and the skinning targets of the cloth-LBS term.
#[derive(Clone, Copy)]
pub struct LayerParams<'a> {
    /// Canonical means (n × 3), quaternions (n × 4) and log-scales (n × 3).
    pub means: &'a Buffer,
    pub quats: &'a Buffer,
    pub log_scales: &'a Buffer,
    /// `∂L/∂μ` (n × 3): the deformation's path plus the triplane's.
    pub grad_means: &'a Buffer,
    pub triplane: &'a Triplane,
    pub appearance: &'a Mlp,
    pub geometry: &'a Mlp,
    pub deformation: &'a Mlp,
    /// Target skinning weights (n × 24) and the squared errors the cloth-LBS term
    /// writes beside its gradient.
    pub weight_targets: &'a Buffer,
    pub weight_sq_error: &'a Buffer,
    /// How the triplane's backward accumulates.
    pub accumulation: Accumulation,
}

/// One frame's deformation of a layer of `count` Gaussians: its inputs (the frame's
/// transforms and pose features), its outputs (the posed Gaussians the renderer reads)
/// and their gradients, and the intermediate buffers between.
pub struct Deformer {
    count: u32,
    /// The frame's 24 transforms (written before each forward pass).
    pub transforms: Buffer,
    /// The frame's pose features (`FrameTransforms::pose_features`; read with
    /// `pose_offsets` only).
    pub pose_features: Buffer,
    /// Posed Gaussians, as the splatter reads them.
    pub posed: GaussianBuffers,
    /// Their gradients, as the splatter's backward writes them.
    pub posed_grads: GaussianBuffers,
    /// The triplane's features at the canonical means, and their gradient (the three
    /// decoders' input gradients, summed).
    features: Buffer,
    grad_features: Buffer,
    /// The triplane's gradient on the canonical means.
    grad_points: Buffer,
    /// The cloth-LBS term's gradient on the weights, added to the deformation head's.
    lbs_grad: Buffer,
    /// Per-Gaussian terms of the transforms' gradient, and their per-chunk sums
    /// (`ops::deform`): what pose refinement reads.
    transform_terms: Buffer,
    transform_partials: Buffer,
    /// With `pose_offsets`: the decoded offsets plus the pose blend (n × 3), which the
    /// deformation reads instead of the geometry decoder's offsets.
    blended_offsets: Option<Buffer>,
    /// Whether the forward adds the pose blend (with `pose_offsets`); off only for
    /// renders that measure what it is worth (`engine-bench trade`).
    pose_blend_on: bool,
}

fn f32_buffer(ctx: &Context, name: &str, len: usize) -> Result<Buffer> {
    ctx.create_buffer(name, BufferDesc::gpu_only(len as u64 * 4))
}

impl Deformer {
    /// The buffers of the layer `name` of `count` Gaussians whose triplane feature is
    /// `feature_width` floats, posed at SH degree `sh_degree`; with `pose_offsets`, the
    /// pose blend's offsets too.
    pub fn new(
        ctx: &Context,
        name: &str,
        count: usize,
        feature_width: usize,
        sh_degree: u32,
        pose_offsets: bool,
    ) -> Result<Self> {
        let n = count;
        Ok(Self {
            count: n as u32,
            // Rewritten every frame (`Avatar::set_frame`): host-written memory.
            transforms: ctx.create_buffer(
                &format!("{name} transforms"),
                BufferDesc::host_written(NUM_JOINTS as u64 * 12 * 4),
            )?,
            pose_features: ctx.create_buffer(
                &format!("{name} pose features"),
                BufferDesc::host_written(deform::POSE_FEATURES as u64 * 4),
            )?,
            posed: GaussianBuffers::new(ctx, &format!("{name} posed"), n, sh_degree)?,
            posed_grads: GaussianBuffers::new(ctx, &format!("{name} posed grads"), n, sh_degree)?,
            features: f32_buffer(ctx, &format!("{name} features"), feature_width * n)?,
            grad_features: f32_buffer(ctx, &format!("{name} feature grads"), feature_width * n)?,
            grad_points: f32_buffer(ctx, &format!("{name} triplane point grads"), 3 * n)?,
            lbs_grad: f32_buffer(ctx, &format!("{name} cloth-LBS gradient"), NUM_JOINTS * n)?,
            transform_terms: f32_buffer(
                ctx,
                &format!("{name} transform gradient terms"),
                deform::transform_terms_len(n as u32),
            )?,
            // Read by the host every step (the pose gradient): the kernel writes it into
            // host-visible memory, so reading it needs no copy submission.
            transform_partials: ctx.create_buffer(
                &format!("{name} transform gradient partials"),
                BufferDesc::readback(4 * deform::transform_partials_len(n as u32).max(1) as u64),
            )?,
            blended_offsets: if pose_offsets {
                Some(f32_buffer(
                    ctx,
                    &format!("{name} pose-blended offsets"),
                    3 * n,
                )?)
            } else {
                None
            },
            pose_blend_on: true,
        })
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

    fn deform_inputs<'a>(&'a self, p: &LayerParams<'a>) -> DeformInputs<'a> {
        DeformInputs {
            transforms: &self.transforms,
            means: p.means,
            quats: p.quats,
            log_scales: p.log_scales,
            offsets: self.pose_blended().unwrap_or(p.geometry.head_output(0)),
            rot6d: p.geometry.head_output(1),
            log_scale_deltas: p.geometry.head_output(2),
            weights: p.deformation.head_output(0),
        }
    }

    /// Records the forward pass into `posed` (the transforms must be written).
    pub fn record_forward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        p: LayerParams<'a>,
        log_scale_offset: f32,
    ) -> Result<()> {
        let n = self.count;
        p.triplane.record_forward(rec, p.means, &self.features, n)?;
        p.appearance.record_forward(rec, &self.features, n)?;
        p.geometry.record_forward(rec, &self.features, n)?;
        p.deformation.record_forward(rec, &self.features, n)?;
        if let Some(blended) = self.pose_blended() {
            deform::record_pose_blend_forward(
                rec,
                p.deformation.head_output(1),
                &self.pose_features,
                p.geometry.head_output(0),
                blended,
                n,
            )?;
        }
        let inputs = self.deform_inputs(&p);
        deform::record_forward(
            rec,
            &inputs,
            &self.posed.means,
            &self.posed.quats,
            &self.posed.log_scales,
            n,
            log_scale_offset,
        )?;
        rec.copy(
            p.appearance.head_output(0),
            &self.posed.opacity_logits,
            u64::from(n) * 4,
        );
        rec.copy(
            p.appearance.head_output(1),
            &self.posed.sh,
            self.posed.sh.size().min(p.appearance.head_output(1).size()),
        );
        Ok(())
    }

    /// Records the backward pass from `posed_grads` into every parameter's gradient,
    /// with the skinning-weight term `lbs_weight · mean((W - W_gt)²)` (the paper's
    /// cloth-LBS loss; 0 leaves it out); with `pose_gradient`, also the chunk sums of
    /// the gradient on the frame's transforms that [`read_transform_grad`](Self::read_transform_grad)
    /// reads (pose refinement; left out otherwise).
    pub fn record_backward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        p: LayerParams<'a>,
        lbs_weight: f32,
        pose_gradient: bool,
    ) -> Result<()> {
        assert!(
            self.pose_blend_on,
            "the backward of a layer rendered without its pose blend"
        );
        let n = self.count;
        rec.copy(
            &self.posed_grads.opacity_logits,
            p.appearance.head_grad(0),
            u64::from(n) * 4,
        );
        rec.copy(
            &self.posed_grads.sh,
            p.appearance.head_grad(1),
            self.posed_grads
                .sh
                .size()
                .min(p.appearance.head_grad(1).size()),
        );
        let inputs = self.deform_inputs(&p);
        let grads = DeformGrads {
            means: p.grad_means,
            offsets: p.geometry.head_grad(0),
            rot6d: p.geometry.head_grad(1),
            log_scale_deltas: p.geometry.head_grad(2),
            weights: p.deformation.head_grad(0),
            transform_terms: &self.transform_terms,
        };
        deform::record_backward(
            rec,
            &inputs,
            &self.posed_grads.means,
            &self.posed_grads.quats,
            &self.posed_grads.log_scales,
            &grads,
            n,
        )?;
        if self.blended_offsets.is_some() {
            // The offsets' gradient (in the geometry head: the blend adds to it) drives
            // the basis's.
            deform::record_pose_blend_backward(
                rec,
                &self.pose_features,
                p.geometry.head_grad(0),
                p.deformation.head_grad(1),
                n,
            )?;
        }
        if pose_gradient {
            deform::record_transform_grad(
                rec,
                p.deformation.head_output(0),
                &self.transform_terms,
                &self.transform_partials,
                n,
            )?;
        }
        if lbs_weight > 0.0 {
            self.record_lbs_term(rec, &p, lbs_weight)?;
        }
        self.record_decoder_backward(rec, &p)
    }

    /// The cloth-LBS term `lbs_weight · mean((W - W_gt)²)`: its gradient added to the
    /// deformation head's, its squared errors into `weight_sq_error`.
    fn record_lbs_term<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        p: &LayerParams<'a>,
        lbs_weight: f32,
    ) -> Result<()> {
        let len = NUM_JOINTS as u32 * self.count;
        let lp = LossParams {
            len,
            scale: lbs_weight / len.max(1) as f32,
            _pad: [0; 2],
        };
        rec.dispatch(
            "loss.cloth_lbs",
            kernels::train::MseGrad {
                pred: p.deformation.head_output(0).read(),
                target: p.weight_targets.read(),
                grad: self.lbs_grad.write(),
                squared_error: p.weight_sq_error.write(),
            },
            &lp,
            flat_grid(len),
        )?;
        rec.dispatch(
            "loss.cloth_lbs_add",
            kernels::train::AddInto {
                src: self.lbs_grad.read(),
                dst: p.deformation.head_grad(0).write(),
            },
            &lp,
            flat_grid(len),
        )
    }

    /// Decoders' and triplane's backward from the gradients in the decoders' heads;
    /// the canonical means' gradient (deformation path + triplane path) ends in
    /// `grad_means`.
    fn record_decoder_backward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        p: &LayerParams<'a>,
    ) -> Result<()> {
        let n = self.count;
        // The decoders add their input gradients into one buffer: one after another.
        p.appearance
            .record_backward(rec, &self.features, n, Some(&self.grad_features), false)?;
        p.geometry
            .record_backward(rec, &self.features, n, Some(&self.grad_features), true)?;
        p.deformation
            .record_backward(rec, &self.features, n, Some(&self.grad_features), true)?;
        p.triplane.record_backward(
            rec,
            p.means,
            &self.grad_features,
            &self.grad_points,
            n,
            p.accumulation,
        )?;
        let lp = LossParams {
            len: 3 * n,
            scale: 1.0,
            _pad: [0; 2],
        };
        rec.dispatch(
            "layer.sum_mean_grads",
            kernels::train::AddInto {
                src: self.grad_points.read(),
                dst: p.grad_means.write(),
            },
            &lp,
            flat_grid(lp.len),
        )
    }

    /// The skinning-weight fit's forward (`HumanLayer::fit_skinning_weights`): the
    /// triplane and the deformation decoder alone, into the deformation head.
    pub fn record_weights_forward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        p: LayerParams<'a>,
    ) -> Result<()> {
        p.triplane
            .record_forward(rec, p.means, &self.features, self.count)?;
        p.deformation
            .record_forward(rec, &self.features, self.count)
    }

    /// The fit's backward, from the gradient in the deformation head into the
    /// deformation decoder's and the triplane's parameters (the means stay).
    pub fn record_weights_backward<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        p: LayerParams<'a>,
    ) -> Result<()> {
        p.deformation.record_backward(
            rec,
            &self.features,
            self.count,
            Some(&self.grad_features),
            false,
        )?;
        p.triplane.record_backward(
            rec,
            p.means,
            &self.grad_features,
            &self.grad_points,
            self.count,
            p.accumulation,
        )
    }

    /// The partial sums of `∂L/∂A` (the pose refiner's), for the non-finite guard.
    pub fn transform_partials(&self) -> (&Buffer, usize) {
        (
            &self.transform_partials,
            deform::transform_partials_len(self.count),
        )
    }

    /// `∂L/∂A` on the frame's 24 transforms (24 × 12, row-major 3x4) from the last
    /// backward pass.
    pub fn read_transform_grad(&mut self, ctx: &Context) -> Result<Vec<f64>> {
        let partials = ctx.read_buffer::<f32>(
            &mut self.transform_partials,
            deform::transform_partials_len(self.count),
        )?;
        Ok(deform::sum_transform_partials(&partials))
    }

    /// The posed Gaussians of the last forward pass, read back.
    pub fn read_posed(&mut self, ctx: &Context) -> Result<GaussianCloud> {
        let layers = vec![Layer::Body; self.count as usize];
        self.posed.download(ctx, &layers)
    }
}
