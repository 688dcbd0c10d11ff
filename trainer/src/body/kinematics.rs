//! Posing a body in f64 (the CPU reference): shape blend shapes, the joint regressor,
//! pose blend shapes, forward kinematics from axis-angle, and linear blend skinning,
//! as SMPL defines them; and the backward pass from the gradient of the per-joint
//! skinning transforms to the pose.
//!
//! Transforms are 3x4 row-major `[R | t]` with an implied bottom row `0 0 0 1`; the
//! skinning transform of joint j is `A_j = G_j · [I | -J_j]`, where `G_j` is the joint's
//! world transform and `J_j` its rest position, so the rest pose gives identities.

use glam::{DAffine3, DMat3, DVec3};

use crate::body::model::{SmplModel, NUM_JOINTS, NUM_POSE_FEATURES};

pub type M3 = [[f64; 3]; 3];
/// `[R | t]`, row-major 3x4.
pub type Affine = [[f64; 4]; 3];

pub const IDENTITY: M3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

// The public types are row-major arrays (other modules and the skinning kernel's
// flat layout read them); the arithmetic is glam's, whose matrices are column-major.
// glam's products sum in the order k = 0, 1, 2, as a row-by-column loop does.

/// A row-major matrix as glam's.
fn mat(m: &M3) -> DMat3 {
    DMat3::from_cols_array_2d(m).transpose()
}

/// A glam matrix as rows.
fn rows(m: DMat3) -> M3 {
    m.transpose().to_cols_array_2d()
}

fn affine(a: &Affine) -> DAffine3 {
    DAffine3::from_mat3_translation(
        mat(&a.map(|r| [r[0], r[1], r[2]])),
        DVec3::new(a[0][3], a[1][3], a[2][3]),
    )
}

fn affine_rows(a: DAffine3) -> Affine {
    let (m, t) = (rows(a.matrix3), a.translation);
    std::array::from_fn(|r| [m[r][0], m[r][1], m[r][2], t[r]])
}

/// `[v]x`, written entry by entry so that the sign of each zero entry is fixed.
fn skew(v: DVec3) -> DMat3 {
    mat(&[[0.0, -v.z, v.y], [v.z, 0.0, -v.x], [-v.y, v.x, 0.0]])
}

/// [`rodrigues`] in glam.
fn rotation(r: DVec3) -> DMat3 {
    let theta = r.length();
    if theta < 1e-12 {
        // First order: I + [r]x (the diagonal set, not added, so the zeros keep their signs).
        let k = skew(r);
        return DMat3::from_cols(
            k.x_axis.with_x(1.0),
            k.y_axis.with_y(1.0),
            k.z_axis.with_z(1.0),
        );
    }
    let k = skew(r * (1.0 / theta));
    let (s, c) = theta.sin_cos();
    DMat3::IDENTITY + (k * s + k * k * (1.0 - c))
}

/// Rotation of an axis-angle vector (Rodrigues).
pub fn rodrigues(r: DVec3) -> M3 {
    rows(rotation(r))
}

/// dR/dr_i for each axis i (Gallego and Yezzi's formula; first order near 0):
/// `(r_i [r]x + [r × (I - R) e_i]x) R / |r|²`.
pub fn rodrigues_jacobian(r: DVec3) -> [M3; 3] {
    let theta2 = r.length_squared();
    let axes = [DVec3::X, DVec3::Y, DVec3::Z];
    if theta2 < 1e-16 {
        return axes.map(|e| rows(skew(e)));
    }
    let rot = rotation(r);
    let i_minus_r = DMat3::IDENTITY - rot;
    axes.map(|e| rows((skew(r) * r.dot(e) + skew(r.cross(i_minus_r * e))) / theta2 * rot))
}

/// Pose parameters: 24 axis-angle vectors, root first (SMPL's 72 numbers).
pub type Pose = [DVec3; NUM_JOINTS];

/// The canonical "Da-pose" HUGS uses: left and right hip rotated by +1 and -1 rad
/// about z.
pub fn da_pose() -> Pose {
    let mut p = [DVec3::ZERO; NUM_JOINTS];
    p[1][2] = 1.0;
    p[2][2] = -1.0;
    p
}

/// The T-pose: all zero.
pub fn t_pose() -> Pose {
    [DVec3::ZERO; NUM_JOINTS]
}

/// How far the A-pose lowers the arms from the T-pose (radians, about 43 degrees: the
/// armpits stay open).
pub const A_POSE_ARMS_DOWN: f64 = 0.75;

/// The A-pose: the T-pose with both arms lowered by [`A_POSE_ARMS_DOWN`] about z. The
/// procedural motions start from it and the project's garments are made in it.
pub fn a_pose() -> Pose {
    let mut p = t_pose();
    // The left arm points along +x, so lowering it is a negative rotation about z.
    p[16][2] = -A_POSE_ARMS_DOWN;
    p[17][2] = A_POSE_ARMS_DOWN;
    p
}

/// `a · b` for affine transforms.
pub fn compose(a: &Affine, b: &Affine) -> Affine {
    affine_rows(affine(a) * affine(b))
}

/// The inverse of a rigid transform `[R | t]`: `[Rᵀ | -Rᵀ t]`.
pub fn rigid_inverse(a: &Affine) -> Affine {
    let a = affine(a);
    let rt = a.matrix3.transpose();
    affine_rows(DAffine3::from_mat3_translation(rt, -(rt * a.translation)))
}

/// Skinning transforms that take points from the body in pose `from` to pose `to`:
/// `A_j(to) · A_j(from)⁻¹` per joint (what a mesh made on the posed body is skinned with).
pub fn relative_transforms(
    to: &[Affine; NUM_JOINTS],
    from: &[Affine; NUM_JOINTS],
) -> [Affine; NUM_JOINTS] {
    std::array::from_fn(|j| compose(&to[j], &rigid_inverse(&from[j])))
}

/// Template plus shape blend shapes (missing betas count as 0, extra ones are ignored).
pub fn shaped_vertices(model: &SmplModel, betas: &[f64]) -> Vec<DVec3> {
    let b = betas.len().min(model.num_betas);
    model
        .v_template
        .iter()
        .zip(&model.shapedirs)
        .map(|(v, d)| {
            DVec3::from_array(
                [0, 1, 2].map(|k| v[k] + (0..b).map(|i| d[k][i] * betas[i]).sum::<f64>()),
            )
        })
        .collect()
}

/// Joint positions from the regressor.
pub fn regress_joints(model: &SmplModel, vertices: &[DVec3]) -> [DVec3; NUM_JOINTS] {
    let mut j = [DVec3::ZERO; NUM_JOINTS];
    for (row, out) in model.j_regressor.iter().zip(j.iter_mut()) {
        for (w, v) in row.iter().zip(vertices) {
            if *w != 0.0 {
                *out += *v * *w;
            }
        }
    }
    j
}

/// Skinning transforms `A_j` (and the world transforms `G_j`) of a pose.
///
/// Computed as `A_j = A_parent · [R_j | J_j - R_j J_j]` (equal to `G_j · [I | -J_j]`):
/// at rest every factor is exactly the identity, so the rest pose reproduces the
/// template bit for bit.
pub fn forward_kinematics(
    parents: &[i32; NUM_JOINTS],
    joints: &[DVec3; NUM_JOINTS],
    pose: &Pose,
) -> ([Affine; NUM_JOINTS], [Affine; NUM_JOINTS]) {
    let mut a = [DAffine3::IDENTITY; NUM_JOINTS];
    for j in 0..NUM_JOINTS {
        let (r, joint) = (rotation(pose[j]), joints[j]);
        let local = DAffine3::from_mat3_translation(r, joint - r * joint);
        a[j] = if parents[j] < 0 {
            local
        } else {
            a[parents[j] as usize] * local
        };
    }
    // G_j = A_j · [I | J_j].
    let g = std::array::from_fn(|j| {
        affine_rows(DAffine3 {
            translation: a[j].translation + a[j].matrix3 * joints[j],
            ..a[j]
        })
    });
    (a.map(affine_rows), g)
}

/// SMPL's pose features: `R_j - I` of joints 1..23, flattened row-major.
pub fn pose_features(pose: &Pose) -> [f64; NUM_POSE_FEATURES] {
    let mut f = [0.0; NUM_POSE_FEATURES];
    for (j, out) in f.chunks_exact_mut(9).enumerate() {
        out.copy_from_slice(rows(rotation(pose[j + 1]) - DMat3::IDENTITY).as_flattened());
    }
    f
}

/// Linear blend skinning of points with per-point joint weights, as
/// `p + Σ_j w_j (A_j p - p)` (equal to `Σ_j w_j A_j p` for weights summing to 1, and
/// exactly `p` when every transform is the identity).
/// The GPU kernel's CPU reference (`drape_engine::ops::skinning`) runs the very same
/// shared functions.
pub fn skin(
    weights: &[[f64; NUM_JOINTS]],
    transforms: &[Affine; NUM_JOINTS],
    points: &[DVec3],
) -> Vec<DVec3> {
    let flat_t: Vec<f64> = transforms.iter().flatten().flatten().copied().collect();
    let flat_w: Vec<f64> = weights.iter().flatten().copied().collect();
    let flat_p: Vec<f64> = points.iter().flat_map(|p| p.to_array()).collect();
    drape_engine::ops::skinning::reference::forward(&flat_t, &flat_w, &flat_p)
        .chunks_exact(3)
        .map(|c| DVec3::new(c[0], c[1], c[2]))
        .collect()
}

/// A posed body.
#[derive(Clone, Debug)]
pub struct Posed {
    pub vertices: Vec<DVec3>,
    /// Joint positions after posing (world space).
    pub joints: [DVec3; NUM_JOINTS],
    /// Rest joint positions (after shaping).
    pub rest_joints: [DVec3; NUM_JOINTS],
    pub transforms: [Affine; NUM_JOINTS],
}

/// SMPL's forward function: shape, pose blend shapes, kinematics, skinning, translation.
pub fn pose_body(model: &SmplModel, betas: &[f64], pose: &Pose, translation: DVec3) -> Posed {
    let shaped = shaped_vertices(model, betas);
    let rest_joints = regress_joints(model, &shaped);
    let features = pose_features(pose);
    let blended: Vec<DVec3> =
        if features.iter().all(|&f| f == 0.0)
            || model
                .posedirs
                .iter()
                .all(|d| d.iter().all(|a| a.iter().all(|&x| x == 0.0)))
        {
            shaped
        } else {
            shaped
                .iter()
                .zip(&model.posedirs)
                .map(|(v, d)| {
                    DVec3::from_array([0, 1, 2].map(|k| {
                        v[k] + d[k].iter().zip(&features).map(|(a, b)| a * b).sum::<f64>()
                    }))
                })
                .collect()
        };
    let (transforms, g) = forward_kinematics(&model.parents, &rest_joints, pose);
    let vertices = skin(&model.weights, &transforms, &blended)
        .into_iter()
        .map(|v| v + translation)
        .collect();
    let joints = g.map(|m| DVec3::new(m[0][3], m[1][3], m[2][3]) + translation);
    Posed {
        vertices,
        joints,
        rest_joints,
        transforms,
    }
}

/// The gradient of a loss with respect to the pose, given its gradient with respect to
/// the skinning transforms `A_j` (pose blend shapes not included).
pub fn pose_gradient(
    parents: &[i32; NUM_JOINTS],
    joints: &[DVec3; NUM_JOINTS],
    pose: &Pose,
    grad_a: &[Affine; NUM_JOINTS],
) -> Pose {
    let (_, g) = forward_kinematics(parents, joints, pose);
    // `x yᵀ`.
    let outer = |x: DVec3, y: DVec3| DMat3::from_cols(x * y.x, x * y.y, x * y.z);
    // A = [G_R | G_t - G_R J]: dG_R = dA_R - dA_t Jᵀ, dG_t = dA_t.
    let grad_a = grad_a.map(|m| affine(&m));
    let mut d_t = grad_a.map(|m| m.translation);
    let mut d_rot: [DMat3; NUM_JOINTS] =
        std::array::from_fn(|j| grad_a[j].matrix3 - outer(d_t[j], joints[j]));
    let mut d_local = [DMat3::ZERO; NUM_JOINTS];
    for j in (0..NUM_JOINTS).rev() {
        if parents[j] < 0 {
            d_local[j] = d_rot[j];
            continue;
        }
        let p = parents[j] as usize;
        // G_R,j = G_R,p R_j ; G_t,j = G_R,p (J_j - J_p) + G_t,p
        d_local[j] = affine(&g[p]).matrix3.transpose() * d_rot[j];
        let d_prot =
            d_rot[j] * rotation(pose[j]).transpose() + outer(d_t[j], joints[j] - joints[p]);
        d_rot[p] += d_prot;
        d_t[p] += d_t[j];
    }
    std::array::from_fn(|j| {
        // Summed row by row (a column-major sum would round differently).
        let dl = rows(d_local[j]);
        DVec3::from_array(rodrigues_jacobian(pose[j]).map(|d| {
            d.as_flattened()
                .iter()
                .zip(dl.as_flattened())
                .map(|(a, b)| a * b)
                .sum()
        }))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Our matrices are rows, glam's are columns: the conversions keep every entry in
    /// place, and a product through glam is the row-major one.
    #[test]
    fn glam_conversions_keep_rows() {
        let m = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 10.0]];
        assert_eq!(rows(mat(&m)), m);
        assert_eq!(
            mat(&m) * DVec3::new(1.0, 10.0, 100.0),
            DVec3::new(321.0, 654.0, 1087.0)
        );
        let a: Affine = [
            [1.0, 2.0, 3.0, 4.0],
            [5.0, 6.0, 7.0, 8.0],
            [9.0, 10.0, 11.0, 12.0],
        ];
        assert_eq!(affine_rows(affine(&a)), a);
        assert_eq!(
            affine(&a).transform_point3(DVec3::X),
            DVec3::new(5.0, 13.0, 21.0)
        );
    }
}
