//! The body rig of an avatar: the canonical pose its Gaussians live in (HUGS's
//! "Da-pose"), and each frame's 24 skinning transforms from that pose to the frame's
//! world, with the layout's global rotation, translation and scale folded in.
//!
//! NeuMan/HUGS parameters: `world = s · (A(P) A(Da)⁻¹ x) + T`. ZJU-MoCap: the body is
//! posed with a zero root, then `world = R(Rh) · (A(P) A(Da)⁻¹ x) + Th`.

use glam::DVec3;

use crate::body::kinematics::{
    da_pose, forward_kinematics, pose_gradient, regress_joints, relative_transforms, rigid_inverse,
    rodrigues, rodrigues_jacobian, shaped_vertices, skin, Affine, Pose, M3,
};
use crate::body::model::{SmplModel, NUM_JOINTS};
use crate::dataset::loader::BodyParams;

/// Floats of one frame's transforms (24 × 3x4, row-major), the layout the GPU ops read.
pub const TRANSFORM_FLOATS: usize = NUM_JOINTS * 12;

/// A shaped body and its canonical pose.
pub struct Rig {
    pub model: SmplModel,
    pub betas: Vec<f64>,
    rest_joints: [DVec3; NUM_JOINTS],
    canonical: [Affine; NUM_JOINTS],
}

/// The parameters of a frame that pose refinement moves, in one flat vector: the
/// root rotation (NeuMan: SMPL's global orient; ZJU-MoCap: `Rh`), the 23 body joints'
/// axis-angles, then the translation (NeuMan: `T`; ZJU-MoCap: `Th`).
pub const REFINED_PARAMS: usize = 3 + 3 * (NUM_JOINTS - 1) + 3;

/// One frame's transforms for the GPU and the global log-scale.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameTransforms {
    pub transforms: Vec<f32>,
    /// `ln s` of the frame's global scale (0 for ZJU-MoCap).
    pub log_scale: f32,
    /// The pose features of the pose-dependent offsets: `R_j − I` of joints 1-23, each
    /// 3x3 row-major (SMPL's `pose_feature`; `ops::deform::POSE_FEATURES` values).
    pub pose_features: Vec<f32>,
}

impl Rig {
    pub fn new(model: SmplModel, betas: &[f64]) -> Self {
        let shaped = shaped_vertices(&model, betas);
        let rest_joints = regress_joints(&model, &shaped);
        let (canonical, _) = forward_kinematics(&model.parents, &rest_joints, &da_pose());
        Self {
            model,
            betas: betas.to_vec(),
            rest_joints,
            canonical,
        }
    }

    /// The rig of a body known only by its joints (an avatar file's): the kinematic
    /// tree and the shaped body's rest joints, which are all that posing reads. Its
    /// model has no mesh (no vertices, weights, shape or pose directions), so it poses
    /// Gaussians but cannot make a layer's initial ones.
    pub fn from_joints(
        parents: [i32; NUM_JOINTS],
        rest_joints: [DVec3; NUM_JOINTS],
        betas: &[f64],
    ) -> Self {
        let (canonical, _) = forward_kinematics(&parents, &rest_joints, &da_pose());
        Self {
            model: SmplModel {
                v_template: Vec::new(),
                shapedirs: Vec::new(),
                num_betas: 0,
                posedirs: Vec::new(),
                j_regressor: Vec::new(),
                weights: Vec::new(),
                parents,
                faces: Vec::new(),
            },
            betas: betas.to_vec(),
            rest_joints,
            canonical,
        }
    }

    /// Rest joint positions of the shaped body.
    pub fn rest_joints(&self) -> [DVec3; NUM_JOINTS] {
        self.rest_joints
    }

    /// The body's vertices in the canonical pose.
    pub fn canonical_vertices(&self) -> Vec<DVec3> {
        skin(
            &self.model.weights,
            &self.canonical,
            &shaped_vertices(&self.model, &self.betas),
        )
    }

    /// `A(P) A(Da)⁻¹` for a body pose.
    pub fn relative(&self, pose: &Pose) -> [Affine; NUM_JOINTS] {
        let (a, _) = forward_kinematics(&self.model.parents, &self.rest_joints, pose);
        relative_transforms(&a, &self.canonical)
    }

    /// The frame's transforms from canonical to world.
    pub fn frame(&self, body: &BodyParams) -> FrameTransforms {
        let (transforms, scale) = self.frame_f64(body);
        let pose = self.decompose(body).pose;
        let pose_features = pose[1..]
            .iter()
            .flat_map(|&r| {
                let m = rodrigues(r);
                (0..9)
                    .map(move |k| (m[k / 3][k % 3] - if k / 3 == k % 3 { 1.0 } else { 0.0 }) as f32)
            })
            .collect();
        FrameTransforms {
            transforms: transforms.iter().map(|&v| v as f32).collect(),
            log_scale: scale.ln() as f32,
            pose_features,
        }
    }

    /// The frame's transforms (24 × 3x4, row-major) in f64, and its global scale.
    pub fn frame_f64(&self, body: &BodyParams) -> (Vec<f64>, f64) {
        let f = self.decompose(body);
        let mut transforms = Vec::with_capacity(TRANSFORM_FLOATS);
        for a in &f.rel {
            for r in 0..3 {
                for c in 0..4 {
                    // world = scale · rot · (a x̂) + translation.
                    let v: f64 = (0..3).map(|k| f.rot[r][k] * a[k][c]).sum::<f64>() * f.scale
                        + if c == 3 { f.translation[r] } else { 0.0 };
                    transforms.push(v);
                }
            }
        }
        (transforms, f.scale)
    }

    fn decompose(&self, body: &BodyParams) -> Decomposed {
        match body {
            BodyParams::Smpl {
                pose,
                translation,
                scale,
                ..
            } => Decomposed {
                pose: *pose,
                rel: self.relative(pose),
                rot: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                scale: *scale,
                translation: *translation,
                zju_rh: None,
            },
            BodyParams::Zju(p) => {
                let mut pose: Pose = [DVec3::ZERO; NUM_JOINTS];
                for (j, q) in pose.iter_mut().enumerate().skip(1) {
                    *q = DVec3::from_slice(&p.poses[3 * j..3 * j + 3]);
                }
                Decomposed {
                    pose,
                    rel: self.relative(&pose),
                    rot: rodrigues(DVec3::from_array(p.rh)),
                    scale: 1.0,
                    translation: DVec3::from_array(p.th),
                    zju_rh: Some(DVec3::from_array(p.rh)),
                }
            }
        }
    }

    /// The gradient on the frame's refined parameters ([`REFINED_PARAMS`], in that
    /// order) from `grad` on its transforms (24 × 12, as [`Rig::frame`] lays them
    /// out). Pose blend shapes are not part of the avatar's deformation, so none enter.
    pub fn frame_gradient(&self, body: &BodyParams, grad: &[f64]) -> [f64; REFINED_PARAMS] {
        assert_eq!(grad.len(), TRANSFORM_FLOATS, "a gradient on 24 transforms");
        let f = self.decompose(body);
        let g = |j: usize, r: usize, c: usize| grad[12 * j + 4 * r + c];
        // A'_j = s R rel_j + T e₃ᵀ: ∂rel_j = s Rᵀ G_j, ∂T = Σ_j G_j e₃, ∂R = s Σ_j G_j rel_jᵀ.
        let mut grad_rot: M3 = [[0.0; 3]; 3];
        let mut grad_t = [0.0; 3];
        let mut grad_a: [Affine; NUM_JOINTS] = [[[0.0; 4]; 3]; NUM_JOINTS];
        for j in 0..NUM_JOINTS {
            let mut grad_rel: Affine = [[0.0; 4]; 3];
            for r in 0..3 {
                grad_t[r] += g(j, r, 3);
                for c in 0..4 {
                    grad_rel[r][c] =
                        f.scale * (0..3).map(|k| f.rot[k][r] * g(j, k, c)).sum::<f64>();
                }
                for k in 0..3 {
                    grad_rot[r][k] +=
                        f.scale * (0..4).map(|c| g(j, r, c) * f.rel[j][k][c]).sum::<f64>();
                }
            }
            // rel_j = A_j C_j⁻¹ (homogeneous): ∂A_j = ∂rel_j (C_j⁻¹)ᵀ.
            let inv = rigid_inverse(&self.canonical[j]);
            for r in 0..3 {
                for c in 0..4 {
                    grad_a[j][r][c] = (0..4)
                        .map(|k| {
                            grad_rel[r][k]
                                * if c < 3 {
                                    inv[c][k]
                                } else if k == 3 {
                                    1.0
                                } else {
                                    0.0
                                }
                        })
                        .sum();
                }
            }
        }
        let grad_pose = pose_gradient(&self.model.parents, &self.rest_joints, &f.pose, &grad_a);
        let mut out = [0.0; REFINED_PARAMS];
        out[0..3].copy_from_slice(&match f.zju_rh {
            None => grad_pose[0].to_array(),
            Some(rh) => rodrigues_jacobian(rh).map(|d| {
                (0..3)
                    .flat_map(|r| (0..3).map(move |k| (r, k)))
                    .map(|(r, k)| d[r][k] * grad_rot[r][k])
                    .sum()
            }),
        });
        for j in 1..NUM_JOINTS {
            out[3 * j..3 * j + 3].copy_from_slice(&grad_pose[j].to_array());
        }
        out[REFINED_PARAMS - 3..].copy_from_slice(&grad_t);
        out
    }
}

/// A frame's body split into what the transforms are built from.
struct Decomposed {
    /// The pose the kinematics run (ZJU-MoCap: root zeroed).
    pose: Pose,
    rel: [Affine; NUM_JOINTS],
    rot: M3,
    scale: f64,
    translation: DVec3,
    /// ZJU-MoCap's `Rh` (the root rotation outside the kinematics).
    zju_rh: Option<DVec3>,
}

/// `body` with `delta` ([`REFINED_PARAMS`], the order [`Rig::frame_gradient`]
/// uses) added to its root rotation, joints and translation.
pub fn refined_body(body: &BodyParams, delta: &[f64; REFINED_PARAMS]) -> BodyParams {
    let mut b = body.clone();
    let t = REFINED_PARAMS - 3;
    match &mut b {
        BodyParams::Smpl {
            pose, translation, ..
        } => {
            for (j, q) in pose.iter_mut().enumerate() {
                for k in 0..3 {
                    q[k] += delta[3 * j + k];
                }
            }
            for k in 0..3 {
                translation[k] += delta[t + k];
            }
        }
        BodyParams::Zju(p) => {
            for k in 0..3 {
                p.rh[k] += delta[k];
                p.th[k] += delta[t + k];
            }
            for i in 3..t {
                p.poses[i] += delta[i];
            }
        }
    }
    b
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::procedural::{default_body, BodyOptions};
    use crate::dataset::zju::ZjuSmpl;
    use rand::{Rng, SeedableRng};

    /// The refined parameters' gradient against central differences of
    /// `Σ G ⊙ transforms(params)`, for both layouts (NeuMan with a global scale;
    /// ZJU-MoCap with `Rh`, `Th`).
    #[test]
    fn frame_gradient_matches_central_differences() {
        let rig = Rig::new(default_body(&BodyOptions::default()), &[0.5, -0.3]);
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let mut pose: Pose = [DVec3::ZERO; NUM_JOINTS];
        pose.iter_mut()
            .flat_map(AsMut::<[f64; 3]>::as_mut)
            .for_each(|v| *v = rng.random_range(-0.6..0.6));
        let mut poses = [0.0; 72];
        poses
            .iter_mut()
            .for_each(|v| *v = rng.random_range(-0.6..0.6));
        let bodies = [
            BodyParams::Smpl {
                pose,
                betas: vec![0.5, -0.3],
                translation: DVec3::new(0.3, -1.2, 4.0),
                scale: 1.3,
            },
            BodyParams::Zju(ZjuSmpl {
                poses,
                rh: [0.4, -1.1, 0.2],
                th: [0.1, 0.2, -0.3],
                shapes: [0.0; 10],
            }),
        ];
        let grad: Vec<f64> = (0..TRANSFORM_FLOATS)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        for (layout, body) in ["NeuMan", "ZJU-MoCap"].iter().zip(&bodies) {
            let loss = |delta: &[f64; REFINED_PARAMS]| -> f64 {
                rig.frame_f64(&refined_body(body, delta))
                    .0
                    .iter()
                    .zip(&grad)
                    .map(|(a, b)| a * b)
                    .sum()
            };
            let analytic = rig.frame_gradient(body, &grad);
            let h = 1e-6;
            for i in 0..REFINED_PARAMS {
                let (mut a, mut b) = ([0.0; REFINED_PARAMS], [0.0; REFINED_PARAMS]);
                a[i] = h;
                b[i] = -h;
                let numeric = (loss(&a) - loss(&b)) / (2.0 * h);
                // Smooth in every parameter; f64 central differences at 1e-6 agree to ~1e-8.
                assert!(
                    (numeric - analytic[i]).abs() <= 1e-6 * (1.0 + numeric.abs()),
                    "{layout}: parameter {i}: analytic {} vs numeric {numeric}",
                    analytic[i]
                );
            }
        }
    }
}
