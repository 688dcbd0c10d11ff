//! Deforming and posing the Gaussians of a triplane-driven layer on the GPU (kernels
//! `deform::*`): decoded offsets, 6D rotations and log-scale deltas applied to the
//! canonical Gaussians, then skinning with the predicted weights; forward and
//! backward, with the CPU reference from the same shared functions
//! (`drape_shared::deform`, which states what happens to the rotation).
//!
//! Optionally (a layer's `pose_offsets`), pose-dependent offsets are added to the
//! decoded offsets first ([`record_pose_blend_forward`]: HUGS's per-Gaussian pose-blend
//! basis, as SMPL's pose blend shapes).
//!
//! The gradient on the frame's 24 transforms (what pose refinement follows) is summed
//! in two deterministic stages: the backward writes 15 terms per Gaussian,
//! [`record_transform_grad`] sums them per (chunk of 1,024 Gaussians, joint) on the GPU
//! (a workgroup each, in a fixed order),
//! and [`sum_transform_partials`] adds the chunks in order in f64 on the host.

use drape_shared::deform::{
    deform_bwd, deform_fwd, pose_blend_basis_grad, pose_blend_offset, transform_grad_add,
    DeformGrad, DeformInput, DeformOutput, DeformParams, PoseBlendParams, TRANSFORM_GRAD_CHUNK,
    TRANSFORM_TERMS,
};
pub use drape_shared::deform::{POSE_BLEND_FLOATS, POSE_FEATURES};
use drape_shared::real::Real;
use drape_shared::skinning::{SKIN_JOINTS, TRANSFORM_FLOATS};

use crate::buffer::Buffer;
use crate::error::Result;
use crate::kernels;
use crate::recorder::{flat_grid, Recording};

/// The per-Gaussian inputs of a deformation, on the GPU (n Gaussians).
pub struct DeformInputs<'a> {
    /// 24 × 12 (3x4 row-major per joint).
    pub transforms: &'a Buffer,
    /// n × 3, canonical.
    pub means: &'a Buffer,
    /// n × 4 unit quaternions, canonical.
    pub quats: &'a Buffer,
    /// n × 3, canonical.
    pub log_scales: &'a Buffer,
    /// n × 3, decoded.
    pub offsets: &'a Buffer,
    /// n × 6, decoded.
    pub rot6d: &'a Buffer,
    /// n × 3, decoded.
    pub log_scale_deltas: &'a Buffer,
    /// n × 24, decoded (rows sum to 1).
    pub weights: &'a Buffer,
}

/// Records the posed means (n × 3), quaternions (n × 4, not normalised) and
/// log-scales (n × 3).
/// `log_scale_offset` (`ln` of the frame's global scale) is added to every posed
/// log-scale; the transforms carry the same scale for the means.
#[allow(clippy::too_many_arguments)]
pub fn record_forward<'a>(
    rec: &mut Recording<'a>,
    inputs: &DeformInputs<'a>,
    posed_means: &'a Buffer,
    posed_quats: &'a Buffer,
    posed_log_scales: &'a Buffer,
    count: u32,
    log_scale_offset: f32,
) -> Result<()> {
    let p = DeformParams {
        count,
        log_scale_offset,
        _pad: [0; 2],
    };
    rec.dispatch(
        "deform.fwd",
        kernels::deform::DeformFwd {
            transforms: inputs.transforms.read(),
            means: inputs.means.read(),
            quats: inputs.quats.read(),
            log_scales: inputs.log_scales.read(),
            offsets: inputs.offsets.read(),
            rot6d: inputs.rot6d.read(),
            deltas: inputs.log_scale_deltas.read(),
            weights: inputs.weights.read(),
            posed_means: posed_means.write(),
            posed_quats: posed_quats.write(),
            posed_log_scales: posed_log_scales.write(),
        },
        &p,
        [count.div_ceil(256), 1, 1],
    )
}

/// The gradients [`record_backward`] writes (n rows each).
pub struct DeformGrads<'a> {
    /// n × 3: the canonical means' gradient.
    pub means: &'a Buffer,
    /// n × 3: the offsets' gradient.
    pub offsets: &'a Buffer,
    /// n × 6: the 6D rotations' gradient.
    pub rot6d: &'a Buffer,
    /// n × 3: the log-scale deltas' gradient.
    pub log_scale_deltas: &'a Buffer,
    /// n × 24: the skinning weights' gradient.
    pub weights: &'a Buffer,
    /// n × 15: the terms [`record_transform_grad`] sums.
    pub transform_terms: &'a Buffer,
}

/// Floats of the transforms' gradient over all joints (24 × 3x4).
pub const TRANSFORM_GRAD_FLOATS: usize = SKIN_JOINTS * TRANSFORM_FLOATS;

/// Floats of the per-Gaussian terms buffer for `count` Gaussians.
pub fn transform_terms_len(count: u32) -> usize {
    count as usize * TRANSFORM_TERMS
}

/// Floats of the partial sums [`record_transform_grad`] writes for `count` Gaussians.
pub fn transform_partials_len(count: u32) -> usize {
    count.div_ceil(TRANSFORM_GRAD_CHUNK) as usize * TRANSFORM_GRAD_FLOATS
}

/// Records the per-chunk sums of `∂L/∂A_j` from the backward's terms (`weights`:
/// the decoded skinning weights, n × 24) into `partials`
/// ([`transform_partials_len`] floats).
pub fn record_transform_grad<'a>(
    rec: &mut Recording<'a>,
    weights: &'a Buffer,
    terms: &'a Buffer,
    partials: &'a Buffer,
    count: u32,
) -> Result<()> {
    let p = DeformParams {
        count,
        log_scale_offset: 0.0,
        _pad: [0; 2],
    };
    // One workgroup per (chunk, joint); 65,535 chunks are 67M Gaussians.
    rec.dispatch(
        "deform.transform_grad",
        kernels::deform::DeformTransformGrad {
            weights: weights.read(),
            terms: terms.read(),
            partials: partials.write(),
        },
        &p,
        [count.div_ceil(TRANSFORM_GRAD_CHUNK), SKIN_JOINTS as u32, 1],
    )
}

/// `∂L/∂A` (24 × 12, row-major 3x4 per joint) from the partial sums, chunks added in
/// order in f64 (the same result however the GPU scheduled the chunks).
pub fn sum_transform_partials(partials: &[f32]) -> Vec<f64> {
    let mut sum = vec![0.0f64; TRANSFORM_GRAD_FLOATS];
    for chunk in partials.chunks_exact(TRANSFORM_GRAD_FLOATS) {
        for (s, &v) in sum.iter_mut().zip(chunk) {
            *s += f64::from(v);
        }
    }
    sum
}

/// Records the backward pass from the gradients on the posed means, quaternions and
/// log-scales.
#[allow(clippy::too_many_arguments)]
pub fn record_backward<'a>(
    rec: &mut Recording<'a>,
    inputs: &DeformInputs<'a>,
    grad_posed_means: &'a Buffer,
    grad_posed_quats: &'a Buffer,
    grad_posed_log_scales: &'a Buffer,
    out: &DeformGrads<'a>,
    count: u32,
) -> Result<()> {
    let p = DeformParams {
        count,
        log_scale_offset: 0.0,
        _pad: [0; 2],
    };
    rec.dispatch(
        "deform.bwd",
        kernels::deform::DeformBwd {
            transforms: inputs.transforms.read(),
            means: inputs.means.read(),
            quats: inputs.quats.read(),
            offsets: inputs.offsets.read(),
            rot6d: inputs.rot6d.read(),
            weights: inputs.weights.read(),
            grad_posed_means: grad_posed_means.read(),
            grad_posed_quats: grad_posed_quats.read(),
            grad_posed_log_scales: grad_posed_log_scales.read(),
            grad_means: out.means.write(),
            grad_offsets: out.offsets.write(),
            grad_rot6d: out.rot6d.write(),
            grad_deltas: out.log_scale_deltas.write(),
            grad_weights: out.weights.write(),
            grad_transform_terms: out.transform_terms.write(),
        },
        &p,
        [count.div_ceil(256), 1, 1],
    )
}

/// Host copies of the inputs (flat, the GPU layout), for the CPU reference.
#[derive(Clone, Debug, Default)]
pub struct HostInputs<F> {
    /// 24 joint transforms, 12 floats each (row-major 3 × 4).
    pub transforms: Vec<F>,
    /// n × 3 canonical means.
    pub means: Vec<F>,
    /// n × 4 canonical rotations (w, x, y, z).
    pub quats: Vec<F>,
    /// n × 3 canonical log scales.
    pub log_scales: Vec<F>,
    /// n × 3 offsets added to the means.
    pub offsets: Vec<F>,
    /// n × 6 rotation corrections in the 6D representation.
    pub rot6d: Vec<F>,
    /// n × 3 deltas added to the log scales.
    pub log_scale_deltas: Vec<F>,
    /// n × 24 skinning weights.
    pub weights: Vec<F>,
}

impl<F: Real> HostInputs<F> {
    /// Gaussians in the inputs.
    pub fn len(&self) -> usize {
        self.means.len() / 3
    }

    /// Whether there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Gaussian `i`'s inputs.
    pub fn gaussian(&self, i: usize) -> DeformInput<F> {
        let v3 = |b: &[F]| [b[3 * i], b[3 * i + 1], b[3 * i + 2]];
        let mut weights = [F::zero(); SKIN_JOINTS];
        weights.copy_from_slice(&self.weights[i * SKIN_JOINTS..(i + 1) * SKIN_JOINTS]);
        let mut rot6d = [F::zero(); 6];
        rot6d.copy_from_slice(&self.rot6d[6 * i..6 * i + 6]);
        DeformInput {
            mean: v3(&self.means),
            quat: [
                self.quats[4 * i],
                self.quats[4 * i + 1],
                self.quats[4 * i + 2],
                self.quats[4 * i + 3],
            ],
            log_scale: v3(&self.log_scales),
            offset: v3(&self.offsets),
            rot6d,
            log_scale_delta: v3(&self.log_scale_deltas),
            weights,
        }
    }
}

/// Records the pose-dependent offsets (kernel `deform::pose_blend_fwd`, an option of a
/// layer): `offsets` (n × 3) = `decoded` (the geometry decoder's offsets) + the blend
/// of each Gaussian's basis (n × [`POSE_BLEND_FLOATS`], the deformation decoder's
/// pose-blend head) by the frame's pose `features` ([`POSE_FEATURES`]: `R_j − I` of
/// joints 1-23). The deformation then reads `offsets`.
pub fn record_pose_blend_forward<'a>(
    rec: &mut Recording<'a>,
    basis: &'a Buffer,
    features: &'a Buffer,
    decoded: &'a Buffer,
    offsets: &'a Buffer,
    count: u32,
) -> Result<()> {
    if count == 0 {
        return Ok(());
    }
    let p = PoseBlendParams {
        count,
        _pad: [0; 3],
    };
    rec.dispatch(
        "deform.pose_blend_fwd",
        kernels::deform::PoseBlendFwd {
            basis: basis.read(),
            features: features.read(),
            decoded: decoded.read(),
            offsets: offsets.write(),
        },
        &p,
        flat_grid(count),
    )
}

/// Records the basis's gradient from the offsets' (kernel `deform::pose_blend_bwd`).
/// The decoded offsets' gradient is the offsets' itself (they are added), so the
/// deformation's backward writes it straight into the geometry decoder's head. The
/// pose features' own dependence on the pose is not differentiated (pose refinement
/// sees the skinning transforms only).
pub fn record_pose_blend_backward<'a>(
    rec: &mut Recording<'a>,
    features: &'a Buffer,
    grad_offsets: &'a Buffer,
    grad_basis: &'a Buffer,
    count: u32,
) -> Result<()> {
    if count == 0 {
        return Ok(());
    }
    let p = PoseBlendParams {
        count,
        _pad: [0; 3],
    };
    rec.dispatch(
        "deform.pose_blend_bwd",
        kernels::deform::PoseBlendBwd {
            features: features.read(),
            grad_offsets: grad_offsets.read(),
            grad_basis: grad_basis.write(),
        },
        &p,
        flat_grid(count * POSE_BLEND_FLOATS as u32),
    )
}

/// CPU references of the deformation and pose-blend kernels, generic over f32/f64.
pub mod reference {
    use super::*;

    /// CPU reference of `∂L/∂A` (24 × 12): every Gaussian's terms from the reference
    /// backward, summed over the Gaussians.
    pub fn transform_grad<F: Real>(inputs: &HostInputs<F>, grads: &[DeformGrad<F>]) -> Vec<F> {
        let mut out = vec![F::zero(); TRANSFORM_GRAD_FLOATS];
        for (i, g) in grads.iter().enumerate() {
            for j in 0..SKIN_JOINTS {
                let mut a = [F::zero(); TRANSFORM_FLOATS];
                transform_grad_add(
                    &g.transform_terms,
                    inputs.weights[i * SKIN_JOINTS + j],
                    &mut a,
                );
                for (o, v) in out[j * TRANSFORM_FLOATS..(j + 1) * TRANSFORM_FLOATS]
                    .iter_mut()
                    .zip(a)
                {
                    *o += v;
                }
            }
        }
        out
    }

    /// CPU reference of the forward pass.
    pub fn forward<F: Real>(inputs: &HostInputs<F>) -> Vec<DeformOutput<F>> {
        (0..inputs.len())
            .map(|i| deform_fwd(&inputs.gaussian(i), &inputs.transforms))
            .collect()
    }

    /// CPU reference of the backward pass.
    pub fn backward<F: Real>(
        inputs: &HostInputs<F>,
        upstream: &[DeformOutput<F>],
    ) -> Vec<DeformGrad<F>> {
        (0..inputs.len())
            .map(|i| deform_bwd(&inputs.gaussian(i), &inputs.transforms, &upstream[i]))
            .collect()
    }

    /// CPU reference of [`record_pose_blend_forward`].
    pub fn pose_blend_forward<F: Real>(basis: &[F], features: &[F], decoded: &[F]) -> Vec<F> {
        let n = decoded.len() / 3;
        (0..n)
            .flat_map(|i| {
                let o = pose_blend_offset(basis, i, features);
                [
                    decoded[3 * i] + o[0],
                    decoded[3 * i + 1] + o[1],
                    decoded[3 * i + 2] + o[2],
                ]
            })
            .collect()
    }

    /// CPU reference of [`record_pose_blend_backward`].
    pub fn pose_blend_backward<F: Real>(features: &[F], grad_offsets: &[F]) -> Vec<F> {
        (0..grad_offsets.len() / 3 * POSE_BLEND_FLOATS)
            .map(|j| pose_blend_basis_grad(j, features, grad_offsets))
            .collect()
    }
}
