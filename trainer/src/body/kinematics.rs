//! Posing a body in f64 (the CPU reference): shape blend shapes, the joint regressor,
//! pose blend shapes, forward kinematics from axis-angle, and linear blend skinning,
//! as SMPL defines them; and the backward pass from the gradient of the per-joint
//! skinning transforms to the pose.
//!
//! Transforms are 3x4 row-major `[R | t]` with an implied bottom row `0 0 0 1`; the
//! skinning transform of joint j is `A_j = G_j · [I | -J_j]`, where `G_j` is the joint's
//! world transform and `J_j` its rest position, so the rest pose gives identities.

use crate::body::model::{SmplModel, NUM_JOINTS, NUM_POSE_FEATURES};
use crate::mesh::{add, cross, dot, norm, scale, sub, V3};

pub type M3 = [[f64; 3]; 3];
/// `[R | t]`, row-major 3x4.
pub type Affine = [[f64; 4]; 3];

pub const IDENTITY: M3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

fn mat_mul(a: &M3, b: &M3) -> M3 {
    let mut o = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            o[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    o
}

fn mat_vec(a: &M3, v: V3) -> V3 {
    [dot(a[0], v), dot(a[1], v), dot(a[2], v)]
}

fn transpose(a: &M3) -> M3 {
    [[a[0][0], a[1][0], a[2][0]], [a[0][1], a[1][1], a[2][1]], [a[0][2], a[1][2], a[2][2]]]
}

fn skew(v: V3) -> M3 {
    [[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]]
}

/// Rotation of an axis-angle vector (Rodrigues).
pub fn rodrigues(r: V3) -> M3 {
    let theta = norm(r);
    if theta < 1e-12 {
        // First order: I + [r]x.
        let k = skew(r);
        return [[1.0, k[0][1], k[0][2]], [k[1][0], 1.0, k[1][2]], [k[2][0], k[2][1], 1.0]];
    }
    let k = skew(scale(r, 1.0 / theta));
    let k2 = mat_mul(&k, &k);
    let (s, c) = theta.sin_cos();
    let mut out = IDENTITY;
    for i in 0..3 {
        for j in 0..3 {
            out[i][j] += s * k[i][j] + (1.0 - c) * k2[i][j];
        }
    }
    out
}

/// dR/dr_i for each axis i (Gallego and Yezzi's formula; first order near 0).
pub fn rodrigues_jacobian(r: V3) -> [M3; 3] {
    let theta2 = dot(r, r);
    let e = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    if theta2 < 1e-16 {
        return e.map(skew);
    }
    let rot = rodrigues(r);
    let i_minus_r = {
        let mut m = IDENTITY;
        for a in 0..3 {
            for b in 0..3 {
                m[a][b] -= rot[a][b];
            }
        }
        m
    };
    e.map(|ei| {
        let k = add(scale(r, 0.0), cross(r, mat_vec(&i_minus_r, ei)));
        let vi = dot(r, ei);
        let s = skew(r);
        let mut m = [[0.0; 3]; 3];
        let ks = skew(k);
        for a in 0..3 {
            for b in 0..3 {
                m[a][b] = (vi * s[a][b] + ks[a][b]) / theta2;
            }
        }
        mat_mul(&m, &rot)
    })
}

/// Pose parameters: 24 axis-angle vectors, root first (SMPL's 72 numbers).
pub type Pose = [V3; NUM_JOINTS];

/// The canonical "Da-pose" HUGS uses: left and right hip rotated by +1 and -1 rad
/// about z.
pub fn da_pose() -> Pose {
    let mut p = [[0.0; 3]; NUM_JOINTS];
    p[1][2] = 1.0;
    p[2][2] = -1.0;
    p
}

/// The T-pose: all zero.
pub fn t_pose() -> Pose {
    [[0.0; 3]; NUM_JOINTS]
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
    let mut o = [[0.0; 4]; 3];
    for i in 0..3 {
        for j in 0..4 {
            o[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum::<f64>() + if j == 3 { a[i][3] } else { 0.0 };
        }
    }
    o
}

/// The inverse of a rigid transform `[R | t]`: `[Rᵀ | -Rᵀ t]`.
pub fn rigid_inverse(a: &Affine) -> Affine {
    let mut o = [[0.0; 4]; 3];
    for i in 0..3 {
        for j in 0..3 {
            o[i][j] = a[j][i];
        }
        o[i][3] = -(0..3).map(|k| a[k][i] * a[k][3]).sum::<f64>();
    }
    o
}

/// Skinning transforms that take points from the body in pose `from` to pose `to`:
/// `A_j(to) · A_j(from)⁻¹` per joint (what a mesh made on the posed body is skinned with).
pub fn relative_transforms(to: &[Affine; NUM_JOINTS], from: &[Affine; NUM_JOINTS]) -> [Affine; NUM_JOINTS] {
    std::array::from_fn(|j| compose(&to[j], &rigid_inverse(&from[j])))
}

/// Template plus shape blend shapes (missing betas count as 0, extra ones are ignored).
pub fn shaped_vertices(model: &SmplModel, betas: &[f64]) -> Vec<V3> {
    let b = betas.len().min(model.num_betas);
    model
        .v_template
        .iter()
        .zip(&model.shapedirs)
        .map(|(v, d)| [0, 1, 2].map(|k| v[k] + (0..b).map(|i| d[k][i] * betas[i]).sum::<f64>()))
        .collect()
}

/// Joint positions from the regressor.
pub fn regress_joints(model: &SmplModel, vertices: &[V3]) -> [V3; NUM_JOINTS] {
    let mut j = [[0.0; 3]; NUM_JOINTS];
    for (row, out) in model.j_regressor.iter().zip(j.iter_mut()) {
        for (w, v) in row.iter().zip(vertices) {
            if *w != 0.0 {
                *out = add(*out, scale(*v, *w));
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
pub fn forward_kinematics(parents: &[i32; NUM_JOINTS], joints: &[V3; NUM_JOINTS], pose: &Pose) -> ([Affine; NUM_JOINTS], [Affine; NUM_JOINTS]) {
    let mut a = [[[0.0; 4]; 3]; NUM_JOINTS];
    for j in 0..NUM_JOINTS {
        let r = rodrigues(pose[j]);
        let rj = mat_vec(&r, joints[j]);
        let local_t = sub(joints[j], rj);
        let local: Affine = std::array::from_fn(|row| [r[row][0], r[row][1], r[row][2], local_t[row]]);
        a[j] = if parents[j] < 0 { local } else { compose(&a[parents[j] as usize], &local) };
    }
    let mut g = a;
    for j in 0..NUM_JOINTS {
        for r in 0..3 {
            g[j][r][3] = a[j][r][3] + (0..3).map(|c| a[j][r][c] * joints[j][c]).sum::<f64>();
        }
    }
    (a, g)
}

/// SMPL's pose features: `R_j - I` of joints 1..23, flattened row-major.
pub fn pose_features(pose: &Pose) -> [f64; NUM_POSE_FEATURES] {
    let mut f = [0.0; NUM_POSE_FEATURES];
    for j in 1..NUM_JOINTS {
        let r = rodrigues(pose[j]);
        for a in 0..3 {
            for b in 0..3 {
                f[9 * (j - 1) + 3 * a + b] = r[a][b] - IDENTITY[a][b];
            }
        }
    }
    f
}

/// Linear blend skinning of points with per-point joint weights, as
/// `p + Σ_j w_j (A_j p - p)` (equal to `Σ_j w_j A_j p` for weights summing to 1, and
/// exactly `p` when every transform is the identity).
/// The GPU kernel's CPU reference (`drape_engine::ops::skinning`) runs the very same
/// shared functions.
pub fn skin(weights: &[[f64; NUM_JOINTS]], transforms: &[Affine; NUM_JOINTS], points: &[V3]) -> Vec<V3> {
    let flat_t: Vec<f64> = transforms.iter().flatten().flatten().copied().collect();
    let flat_w: Vec<f64> = weights.iter().flatten().copied().collect();
    let flat_p: Vec<f64> = points.iter().flatten().copied().collect();
    drape_engine::ops::skinning::reference_fwd(&flat_t, &flat_w, &flat_p).chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

/// A posed body.
#[derive(Clone, Debug)]
pub struct Posed {
    pub vertices: Vec<V3>,
    /// Joint positions after posing (world space).
    pub joints: [V3; NUM_JOINTS],
    /// Rest joint positions (after shaping).
    pub rest_joints: [V3; NUM_JOINTS],
    pub transforms: [Affine; NUM_JOINTS],
}

/// SMPL's forward function: shape, pose blend shapes, kinematics, skinning, translation.
pub fn pose_body(model: &SmplModel, betas: &[f64], pose: &Pose, translation: V3) -> Posed {
    let shaped = shaped_vertices(model, betas);
    let rest_joints = regress_joints(model, &shaped);
    let features = pose_features(pose);
    let blended: Vec<V3> = if features.iter().all(|&f| f == 0.0) || model.posedirs.iter().all(|d| d.iter().all(|a| a.iter().all(|&x| x == 0.0))) {
        shaped
    } else {
        shaped
            .iter()
            .zip(&model.posedirs)
            .map(|(v, d)| [0, 1, 2].map(|k| v[k] + d[k].iter().zip(&features).map(|(a, b)| a * b).sum::<f64>()))
            .collect()
    };
    let (transforms, g) = forward_kinematics(&model.parents, &rest_joints, pose);
    let vertices = skin(&model.weights, &transforms, &blended).into_iter().map(|v| add(v, translation)).collect();
    let joints = g.map(|m| add([m[0][3], m[1][3], m[2][3]], translation));
    Posed { vertices, joints, rest_joints, transforms }
}

/// The gradient of a loss with respect to the pose, given its gradient with respect to
/// the skinning transforms `A_j` (pose blend shapes not included).
pub fn pose_gradient(parents: &[i32; NUM_JOINTS], joints: &[V3; NUM_JOINTS], pose: &Pose, grad_a: &[Affine; NUM_JOINTS]) -> Pose {
    let (_, g) = forward_kinematics(parents, joints, pose);
    let rot = |m: &Affine| -> M3 { [[m[0][0], m[0][1], m[0][2]], [m[1][0], m[1][1], m[1][2]], [m[2][0], m[2][1], m[2][2]]] };
    // A = [G_R | G_t - G_R J]: dG_R = dA_R - dA_t Jᵀ, dG_t = dA_t.
    let mut d_rot = [[[0.0; 3]; 3]; NUM_JOINTS];
    let mut d_t = [[0.0; 3]; NUM_JOINTS];
    for j in 0..NUM_JOINTS {
        for r in 0..3 {
            d_t[j][r] = grad_a[j][r][3];
            for c in 0..3 {
                d_rot[j][r][c] = grad_a[j][r][c] - grad_a[j][r][3] * joints[j][c];
            }
        }
    }
    let mut d_local = [[[0.0; 3]; 3]; NUM_JOINTS];
    for j in (0..NUM_JOINTS).rev() {
        if parents[j] < 0 {
            d_local[j] = d_rot[j];
            continue;
        }
        let p = parents[j] as usize;
        let prot = rot(&g[p]);
        let r = rodrigues(pose[j]);
        let offset = sub(joints[j], joints[p]);
        // G_R,j = G_R,p R_j ; G_t,j = G_R,p (J_j - J_p) + G_t,p
        d_local[j] = mat_mul(&transpose(&prot), &d_rot[j]);
        let d_prot_from_rot = mat_mul(&d_rot[j], &transpose(&r));
        for a in 0..3 {
            for b in 0..3 {
                d_rot[p][a][b] += d_prot_from_rot[a][b] + d_t[j][a] * offset[b];
            }
            d_t[p][a] += d_t[j][a];
        }
    }
    let mut out = [[0.0; 3]; NUM_JOINTS];
    for j in 0..NUM_JOINTS {
        let jac = rodrigues_jacobian(pose[j]);
        for (i, d) in jac.iter().enumerate() {
            out[j][i] = (0..3).flat_map(|a| (0..3).map(move |b| (a, b))).map(|(a, b)| d[a][b] * d_local[j][a][b]).sum();
        }
    }
    out
}
