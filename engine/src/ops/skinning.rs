//! Linear blend skinning on the GPU (kernels `skinning::*`), forward and backward, and
//! its CPU reference from the same shared functions (`drape_shared::skinning`),
//! generic over f32/f64.
//!
//! Backward gives the gradients with respect to the points, the per-point weights and
//! the 24 transforms; the trainer turns the transforms' gradient into the pose's
//! (`drape_trainer::body::kinematics::pose_gradient`).

use drape_shared::real::Real;
use drape_shared::skinning::{
    dot3, rotation_minus_identity_t, transform_delta, SkinParams, SKIN_JOINTS, TRANSFORM_FLOATS,
    TRANSFORM_GRAD_CHUNK,
};

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::{EngineError, Result};
use crate::kernels;
use crate::recorder::Recording;

/// Floats of all 24 transforms.
pub const TRANSFORMS_LEN: usize = SKIN_JOINTS * TRANSFORM_FLOATS;

/// Scratch for skinning up to `max_count` points.
pub struct Skinning {
    max_count: u32,
    partials: Buffer,
}

impl Skinning {
    /// Scratch for up to `max_count` points.
    pub fn new(ctx: &Context, max_count: usize) -> Result<Self> {
        // Beyond 65,535 workgroups of 256 the 1-D dispatches would not fit; say so now.
        let limit = 65_535u64 * 256;
        if max_count as u64 > limit {
            return Err(EngineError::too_large(
                "points to skin",
                max_count as u64,
                limit,
                "skinning (65,535 workgroups of 256)",
            ));
        }
        let max_count = max_count as u32;
        let groups = max_count.div_ceil(TRANSFORM_GRAD_CHUNK).max(1);
        Ok(Self {
            max_count,
            partials: ctx.create_buffer(
                "skinning partial transform gradients",
                BufferDesc::gpu_only(u64::from(groups) * TRANSFORMS_LEN as u64 * 4),
            )?,
        })
    }

    /// Records `skinned = skin(points)`.
    pub fn record_fwd<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        transforms: &'a Buffer,
        weights: &'a Buffer,
        points: &'a Buffer,
        skinned: &'a Buffer,
        count: u32,
    ) -> Result<()> {
        if count > self.max_count {
            return Err(EngineError::too_large(
                "points to skin",
                count.into(),
                self.max_count.into(),
                "the skinning plan",
            ));
        }
        let p = SkinParams {
            count,
            groups: 0,
            _pad: [0; 2],
        };
        rec.dispatch(
            "skinning.fwd",
            kernels::skinning::SkinFwd {
                transforms: transforms.read(),
                weights: weights.read(),
                points: points.read(),
                skinned: skinned.write(),
            },
            &p,
            [count.div_ceil(256), 1, 1],
        )
    }

    /// Records the backward pass for an upstream gradient on the skinned points.
    #[allow(clippy::too_many_arguments)]
    pub fn record_bwd<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        transforms: &'a Buffer,
        weights: &'a Buffer,
        points: &'a Buffer,
        grad_skinned: &'a Buffer,
        grad_points: &'a Buffer,
        grad_weights: &'a Buffer,
        grad_transforms: &'a Buffer,
        count: u32,
    ) -> Result<()> {
        if count > self.max_count {
            return Err(EngineError::too_large(
                "points to skin",
                count.into(),
                self.max_count.into(),
                "the skinning plan",
            ));
        }
        let groups = count.div_ceil(TRANSFORM_GRAD_CHUNK);
        let p = SkinParams {
            count,
            groups,
            _pad: [0; 2],
        };
        // The two passes read the same inputs and write different buffers: no barrier.
        rec.dispatch(
            "skinning.bwd_points",
            kernels::skinning::SkinBwdPoints {
                transforms: transforms.read(),
                weights: weights.read(),
                points: points.read(),
                grad_skinned: grad_skinned.read(),
                grad_points: grad_points.write(),
                grad_weights: grad_weights.write(),
            },
            &p,
            [count.div_ceil(256), 1, 1],
        )?;
        rec.dispatch(
            "skinning.bwd_transforms",
            kernels::skinning::SkinBwdTransforms {
                weights: weights.read(),
                points: points.read(),
                grad_skinned: grad_skinned.read(),
                partials: self.partials.write(),
            },
            &p,
            [groups, 1, 1],
        )?;
        if groups == 0 {
            rec.fill(grad_transforms, 0);
            return Ok(());
        }
        rec.dispatch(
            "skinning.sum_partials",
            kernels::skinning::SumPartials {
                partials: self.partials.read(),
                grad_transforms: grad_transforms.write(),
            },
            &p,
            [(TRANSFORMS_LEN as u32).div_ceil(256), 1, 1],
        )
    }
}

fn transform_of<F: Real>(transforms: &[F], j: usize) -> [F; TRANSFORM_FLOATS] {
    let mut a = [F::zero(); TRANSFORM_FLOATS];
    a.copy_from_slice(&transforms[j * TRANSFORM_FLOATS..(j + 1) * TRANSFORM_FLOATS]);
    a
}

/// CPU references of the skinning kernels: the same `drape_shared` math, generic over f32/f64.
pub mod reference {
    use super::*;

    /// CPU reference of the forward pass: `transforms` 288, `weights` V×24, `points` V×3.
    pub fn forward<F: Real>(transforms: &[F], weights: &[F], points: &[F]) -> Vec<F> {
        let mut out = points.to_vec();
        for (i, x) in points.chunks_exact(3).enumerate() {
            let x = [x[0], x[1], x[2]];
            for j in 0..SKIN_JOINTS {
                let w = weights[i * SKIN_JOINTS + j];
                if w != F::zero() {
                    let d = transform_delta(&transform_of(transforms, j), x);
                    for k in 0..3 {
                        out[3 * i + k] += w * d[k];
                    }
                }
            }
        }
        out
    }

    /// CPU reference of the backward pass: (grad points, grad weights, grad transforms).
    pub fn backward<F: Real>(
        transforms: &[F],
        weights: &[F],
        points: &[F],
        grad_skinned: &[F],
    ) -> (Vec<F>, Vec<F>, Vec<F>) {
        let n = points.len() / 3;
        let mut gp = grad_skinned.to_vec();
        let mut gw = vec![F::zero(); n * SKIN_JOINTS];
        let mut ga = vec![F::zero(); TRANSFORMS_LEN];
        for i in 0..n {
            let x = [points[3 * i], points[3 * i + 1], points[3 * i + 2]];
            let g = [
                grad_skinned[3 * i],
                grad_skinned[3 * i + 1],
                grad_skinned[3 * i + 2],
            ];
            for j in 0..SKIN_JOINTS {
                let a = transform_of(transforms, j);
                let w = weights[i * SKIN_JOINTS + j];
                gw[i * SKIN_JOINTS + j] = dot3(g, transform_delta(&a, x));
                let r = rotation_minus_identity_t(&a, g);
                for k in 0..3 {
                    gp[3 * i + k] += w * r[k];
                }
                for r in 0..3 {
                    for c in 0..4 {
                        let xc = if c == 3 { F::one() } else { x[c] };
                        ga[j * TRANSFORM_FLOATS + 4 * r + c] += w * g[r] * xc;
                    }
                }
            }
        }
        (gp, gw, ga)
    }
}
