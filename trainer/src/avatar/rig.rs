//! The body rig of an avatar: the canonical pose its Gaussians live in (HUGS's
//! "Da-pose"), and each frame's 24 skinning transforms from that pose to the frame's
//! world, with the layout's global rotation, translation and scale folded in.
//!
//! NeuMan/HUGS parameters: `world = s · (A(P) A(Da)⁻¹ x) + T`. ZJU-MoCap: the body is
//! posed with a zero root, then `world = R(Rh) · (A(P) A(Da)⁻¹ x) + Th`.

use crate::body::kinematics::{da_pose, forward_kinematics, regress_joints, relative_transforms, rodrigues, shaped_vertices, skin, Affine, Pose};
use crate::body::model::{SmplModel, NUM_JOINTS};
use crate::dataset::loader::BodyParams;
use crate::mesh::V3;

/// Floats of one frame's transforms (24 × 3x4, row-major), the layout the GPU ops read.
pub const TRANSFORM_FLOATS: usize = NUM_JOINTS * 12;

/// A shaped body and its canonical pose.
pub struct Rig {
    pub model: SmplModel,
    pub betas: Vec<f64>,
    rest_joints: [V3; NUM_JOINTS],
    canonical: [Affine; NUM_JOINTS],
}

/// One frame's transforms for the GPU and the global log-scale.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameTransforms {
    pub transforms: Vec<f32>,
    /// `ln s` of the frame's global scale (0 for ZJU-MoCap).
    pub log_scale: f32,
}

impl Rig {
    pub fn new(model: SmplModel, betas: &[f64]) -> Self {
        let shaped = shaped_vertices(&model, betas);
        let rest_joints = regress_joints(&model, &shaped);
        let (canonical, _) = forward_kinematics(&model.parents, &rest_joints, &da_pose());
        Self { model, betas: betas.to_vec(), rest_joints, canonical }
    }

    /// Rest joint positions of the shaped body.
    pub fn rest_joints(&self) -> [V3; NUM_JOINTS] {
        self.rest_joints
    }

    /// The body's vertices in the canonical pose.
    pub fn canonical_vertices(&self) -> Vec<V3> {
        skin(&self.model.weights, &self.canonical, &shaped_vertices(&self.model, &self.betas))
    }

    /// `A(P) A(Da)⁻¹` for a body pose.
    pub fn relative(&self, pose: &Pose) -> [Affine; NUM_JOINTS] {
        let (a, _) = forward_kinematics(&self.model.parents, &self.rest_joints, pose);
        relative_transforms(&a, &self.canonical)
    }

    /// The frame's transforms from canonical to world.
    pub fn frame(&self, body: &BodyParams) -> FrameTransforms {
        let (rel, rot, scale, translation) = match body {
            BodyParams::Smpl { pose, translation, scale, .. } => (self.relative(pose), [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], *scale, *translation),
            BodyParams::Zju(p) => {
                let mut pose: Pose = [[0.0; 3]; NUM_JOINTS];
                for (j, q) in pose.iter_mut().enumerate().skip(1) {
                    *q = [p.poses[3 * j], p.poses[3 * j + 1], p.poses[3 * j + 2]];
                }
                (self.relative(&pose), rodrigues(p.rh), 1.0, p.th)
            }
        };
        let mut transforms = Vec::with_capacity(TRANSFORM_FLOATS);
        for a in &rel {
            for r in 0..3 {
                for c in 0..4 {
                    // world = scale · rot · (a x̂) + translation.
                    let v: f64 = (0..3).map(|k| rot[r][k] * a[k][c]).sum::<f64>() * scale + if c == 3 { translation[r] } else { 0.0 };
                    transforms.push(v as f32);
                }
            }
        }
        FrameTransforms { transforms, log_scale: scale.ln() as f32 }
    }
}
