//! Fitting an SMPL-format body to 3D landmarks of a sequence (`drape prepare`'s body
//! stage): one shape for the sequence, a pose (24 axis-angle rotations, the root's in
//! the landmarks' world frame) and a translation per frame.
//!
//! **Limb lengths.** The procedural body has two shape directions (height, girth); a
//! real person's proportions differ limb by limb, so [`with_limb_lengths`] writes eight
//! more into betas 2..9: per-bone length scales (hip width, thigh, shin, torso,
//! shoulder width, upper arm, forearm, neck), one unit = +10% of that bone (left and
//! right share one: a person is close to symmetric and it halves what the data must
//! decide). A bone's scale moves every joint below it, and each vertex by its skinning
//! weights' mix of its joints' displacements, each interpolated along the bone the
//! vertex sits on (a thigh vertex halfway down moves half as far as the knee; for the
//! pelvis and spine3, which have three children, the nearest child's bone: otherwise a
//! pelvis vertex at the hip would stay put and the regressed hip joint, the centroid of
//! a ring of vertices there, would move half as far as its bone says), then each
//! joint's regressor ring is moved by what its joint still lacks, so that the regressed
//! joints move exactly as the bones say; so the directions are
//! linear in the betas and the result is still a plain SMPL-format model: the trainer
//! poses it with no change, and the fitted betas are ordinary `betas`.
//!
//! **Markers.** Landmarks are not joints: each landmark is a [`Marker`], a point fixed
//! in one joint's frame (its rest offset from the joint, in the T-pose, metres).
//! [`MEDIAPIPE_MARKERS`] maps mediapipe's pose landmarks: shoulders, elbows, wrists,
//! hips, knees and ankles onto SMPL's joints (offset zero; the limb scales absorb the
//! systematic difference, e.g. mediapipe's hips sit wider and higher than SMPL's hip
//! joints), the nose and ears onto the head, index and pinky knuckles onto the wrists,
//! heels onto the ankles and the toe tips onto the feet, at offsets read off the
//! procedural body. Eyes and mouth are left out (they add nothing to the head's
//! pose that the nose and ears do not).
//!
//! **World frame.** The fit runs in the landmarks' world frame whatever its up axis (a
//! Qualisys rig's is z-up; the body is y-up, facing +z): the root's rotation carries
//! the turn, initialised per frame from the torso (hips left-right, hips to shoulders
//! up), so `poses[0]` poses the body directly in the calibration's world.
//!
//! **Objective**, per frame, in units of its stated scale (a residual of 1 is one
//! "sigma"): markers (3D distance / [`FitOptions::marker_sigma`], weighted by the
//! landmark's confidence and by an iteratively reweighted Cauchy factor of scale
//! [`FitOptions::robust_scale`], so a mis-triangulated wrist does not drag the arm);
//! temporal smoothness (each rotation and the translation against the previous and
//! next frame's); a pose prior (per joint, tight where the landmarks cannot see the
//! rotation: hands, toes, spine twist); joint limits (knees and elbows bend one way
//! and hardly twist: a one-sided penalty, so a missed detection cannot flip a limb).
//!
//! **Solver.** Levenberg-Marquardt in f64 with forward-difference Jacobians; the root
//! rotation is updated multiplicatively (`R <- exp(d) R`) so it never meets the
//! axis-angle singularity at pi. Frames are solved one at a time with their
//! neighbours held (Gauss-Seidel sweeps, warm-started from the previous frame),
//! alternating with the shape (all frames' markers at once).

use glam::{DMat3, DQuat, DVec3};

use crate::body::kinematics::{forward_kinematics, rodrigues, Pose};
use crate::body::least_squares::levenberg_marquardt;
use crate::body::model::{SmplModel, NUM_JOINTS, PARENTS};

/// The first beta index of the limb lengths, and how many there are.
pub const LIMB_BETAS: std::ops::Range<usize> = 2..10;

/// The bones (child joints) each limb-length beta scales, in beta order from 2.
pub const LIMBS: [(&str, &[usize]); 8] = [
    ("hip width", &[1, 2]),
    ("thigh", &[4, 5]),
    ("shin", &[7, 8]),
    ("torso", &[3, 6, 9, 12]),
    ("shoulder width", &[13, 14, 16, 17]),
    ("upper arm", &[18, 19]),
    ("forearm", &[20, 21, 22, 23]),
    ("neck", &[15]),
];

/// Length change per unit of a limb beta.
const LIMB_UNIT: f64 = 0.10;

fn rest_joints(model: &SmplModel, vertices: &[DVec3]) -> [DVec3; NUM_JOINTS] {
    crate::body::kinematics::regress_joints(model, vertices)
}

fn is_ancestor_or_self(a: usize, mut j: usize) -> bool {
    loop {
        if j == a {
            return true;
        }
        if PARENTS[j] < 0 {
            return false;
        }
        j = PARENTS[j] as usize;
    }
}

/// `model` with limb-length shape directions in betas 2..9 (module header); the model
/// keeps at least 10 betas, and whatever directions 2..9 held are replaced.
pub fn with_limb_lengths(model: &SmplModel) -> SmplModel {
    let mut out = model.clone();
    let nb = model.num_betas.max(LIMB_BETAS.end);
    for d in &mut out.shapedirs {
        for axis in d.iter_mut() {
            axis.resize(nb, 0.0);
        }
    }
    out.num_betas = nb;
    let joints = rest_joints(model, &model.v_template);
    let children: [Vec<usize>; NUM_JOINTS] = std::array::from_fn(|j| {
        (0..NUM_JOINTS)
            .filter(|&k| PARENTS[k] == j as i32)
            .collect()
    });
    // Per vertex and joint, the bone it sits on: the child whose segment from the joint
    // is nearest (the pelvis and spine3 have three), and how far along it (0..1).
    let along = |v: DVec3, j: usize| -> Option<(usize, f64)> {
        children[j]
            .iter()
            .map(|&c| {
                let bone = joints[c] - joints[j];
                let t =
                    ((v - joints[j]).dot(bone) / bone.length_squared().max(1e-12)).clamp(0.0, 1.0);
                (c, t, (v - joints[j] - bone * t).length())
            })
            .min_by(|a, b| a.2.total_cmp(&b.2))
            .map(|(c, t, _)| (c, t))
    };
    for (k, (_, bones)) in LIMBS.iter().enumerate() {
        // Each joint's displacement for one unit of this beta.
        let delta: [DVec3; NUM_JOINTS] = std::array::from_fn(|j| {
            bones
                .iter()
                .filter(|&&b| is_ancestor_or_self(b, j))
                .map(|&b| (joints[b] - joints[PARENTS[b] as usize]) * LIMB_UNIT)
                .sum()
        });
        for ((v, w), d) in model
            .v_template
            .iter()
            .zip(&model.weights)
            .zip(&mut out.shapedirs)
        {
            let mut disp = DVec3::ZERO;
            for j in 0..NUM_JOINTS {
                if w[j] == 0.0 {
                    continue;
                }
                let mut dj = delta[j];
                if let Some((c, t)) = along(*v, j) {
                    dj += (delta[c] - delta[j]) * t;
                }
                disp += dj * w[j];
            }
            for axis in 0..3 {
                d[axis][LIMB_BETAS.start + k] = disp[axis];
            }
        }
        // The regressed joints should move exactly as the bones say; the blend above
        // gets them to within a few percent (a joint's ring takes in vertices of
        // neighbouring parts). Move each ring by what its joint lacks, a few times over
        // (rings can share vertices).
        let b = LIMB_BETAS.start + k;
        for _ in 0..8 {
            for (j, row) in model.j_regressor.iter().enumerate() {
                let regressed: DVec3 = row
                    .iter()
                    .zip(&out.shapedirs)
                    .filter(|(w, _)| **w != 0.0)
                    .map(|(w, d)| DVec3::new(d[0][b], d[1][b], d[2][b]) * *w)
                    .sum();
                let total: f64 = row.iter().sum();
                if !(total > 0.0) {
                    continue;
                }
                let fix = (delta[j] - regressed) / total;
                for (w, d) in row.iter().zip(&mut out.shapedirs) {
                    if *w != 0.0 {
                        for axis in 0..3 {
                            d[axis][b] += fix[axis];
                        }
                    }
                }
            }
        }
    }
    out
}

/// A landmark as a point fixed in a joint's frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Marker {
    pub joint: usize,
    /// The rest-pose offset from the joint (metres, the body's T-pose axes).
    pub offset: DVec3,
    /// Relative weight (mediapipe's hand points are noisier than its joints).
    pub weight: f64,
}

const fn marker(joint: usize, x: f64, y: f64, z: f64, weight: f64) -> Marker {
    Marker {
        joint,
        offset: DVec3::new(x, y, z),
        weight,
    }
}

/// mediapipe pose landmark index -> marker (module header); landmarks not listed are
/// not fitted.
pub const MEDIAPIPE_MARKERS: [(usize, Marker); 23] = [
    (0, marker(15, 0.0, 0.04, 0.09, 0.5)),     // nose
    (7, marker(15, 0.075, 0.04, -0.02, 0.5)),  // left ear
    (8, marker(15, -0.075, 0.04, -0.02, 0.5)), // right ear
    (11, marker(16, 0.0, 0.0, 0.0, 1.0)),      // left shoulder
    (12, marker(17, 0.0, 0.0, 0.0, 1.0)),
    (13, marker(18, 0.0, 0.0, 0.0, 1.0)), // left elbow
    (14, marker(19, 0.0, 0.0, 0.0, 1.0)),
    (15, marker(20, 0.0, 0.0, 0.0, 1.0)), // left wrist
    (16, marker(21, 0.0, 0.0, 0.0, 1.0)),
    (17, marker(20, 0.085, 0.0, -0.03, 0.3)), // left pinky knuckle
    (18, marker(21, -0.085, 0.0, -0.03, 0.3)),
    (19, marker(20, 0.09, 0.0, 0.03, 0.3)), // left index knuckle
    (20, marker(21, -0.09, 0.0, 0.03, 0.3)),
    (23, marker(1, 0.0, 0.0, 0.0, 1.0)), // left hip
    (24, marker(2, 0.0, 0.0, 0.0, 1.0)),
    (25, marker(4, 0.0, 0.0, 0.0, 1.0)), // left knee
    (26, marker(5, 0.0, 0.0, 0.0, 1.0)),
    (27, marker(7, 0.0, 0.0, 0.0, 1.0)), // left ankle
    (28, marker(8, 0.0, 0.0, 0.0, 1.0)),
    (29, marker(7, 0.0, -0.06, -0.05, 0.5)), // left heel
    (30, marker(8, 0.0, -0.06, -0.05, 0.5)),
    (31, marker(10, 0.0, -0.005, 0.06, 0.5)), // left toe tip
    (32, marker(10 + 1, 0.0, -0.005, 0.06, 0.5)),
];

/// The fit's scales (module header).
#[derive(Clone, Copy, Debug)]
pub struct FitOptions {
    /// Metres per unit of marker residual.
    pub marker_sigma: f64,
    /// Distance (metres) at which a marker's weight halves.
    pub robust_scale: f64,
    /// Radians (and `smooth_translation` metres) per unit of frame-to-frame change.
    pub smooth_rotation: f64,
    pub smooth_translation: f64,
    /// Per unit of limb beta (a prior pulling to the procedural body's proportions).
    pub shape_sigma: f64,
    /// Rounds of (pose sweep, shape step).
    pub rounds: usize,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            marker_sigma: 0.02,
            robust_scale: 0.08,
            smooth_rotation: 0.15,
            smooth_translation: 0.03,
            shape_sigma: 3.0,
            rounds: 10,
        }
    }
}

/// The pose prior: radians per unit, per joint (all three axes).
fn prior_sigma(j: usize) -> f64 {
    match j {
        3 | 6 | 9 => 0.25, // spine
        12 | 15 => 0.5,    // neck, head
        13 | 14 => 0.15,   // collars
        10 | 11 => 0.02,   // toes: unseen
        22 | 23 => 0.02,   // hands: the knuckles pin the wrist
        _ => 1.5,
    }
}

/// A body to fit: the model's rest joints as functions of the betas.
pub struct FitBody {
    joints0: [DVec3; NUM_JOINTS],
    /// `dirs[j][b]`: the joint's shape direction.
    dirs: Vec<Vec<DVec3>>,
    pub num_betas: usize,
}

impl FitBody {
    pub fn new(model: &SmplModel) -> Self {
        let joints0 = rest_joints(model, &model.v_template);
        let nb = model.num_betas;
        let dirs = (0..NUM_JOINTS)
            .map(|j| {
                (0..nb)
                    .map(|b| {
                        model.j_regressor[j]
                            .iter()
                            .zip(&model.shapedirs)
                            .filter(|(w, _)| **w != 0.0)
                            .map(|(w, d)| DVec3::new(d[0][b], d[1][b], d[2][b]) * *w)
                            .sum()
                    })
                    .collect()
            })
            .collect();
        Self {
            joints0,
            dirs,
            num_betas: nb,
        }
    }

    /// Rest joints for `betas`.
    pub fn rest(&self, betas: &[f64]) -> [DVec3; NUM_JOINTS] {
        std::array::from_fn(|j| {
            self.joints0[j]
                + betas
                    .iter()
                    .zip(&self.dirs[j])
                    .map(|(b, d)| *d * *b)
                    .sum::<DVec3>()
        })
    }

    /// Posed joint positions and the markers' positions.
    pub fn pose(
        &self,
        rest: &[DVec3; NUM_JOINTS],
        pose: &Pose,
        translation: DVec3,
        markers: &[Marker],
    ) -> ([DVec3; NUM_JOINTS], Vec<DVec3>) {
        let (_, g) = forward_kinematics(&PARENTS, rest, pose);
        let joints = g.map(|m| DVec3::new(m[0][3], m[1][3], m[2][3]) + translation);
        let markers = markers
            .iter()
            .map(|mk| {
                let m = g[mk.joint];
                let r = DMat3::from_cols_array_2d(&[
                    [m[0][0], m[1][0], m[2][0]],
                    [m[0][1], m[1][1], m[2][1]],
                    [m[0][2], m[1][2], m[2][2]],
                ]);
                joints[mk.joint] + r * mk.offset
            })
            .collect();
        (joints, markers)
    }
}

/// One frame's parameters, the root as a matrix.
#[derive(Clone, Copy, Debug)]
struct FrameParams {
    root: DMat3,
    pose: Pose,
    translation: DVec3,
}

const FRAME_PARAMS: usize = 3 * NUM_JOINTS + 3;

impl FrameParams {
    fn as_pose(&self) -> Pose {
        let mut p = self.pose;
        p[0] = log_rotation(self.root);
        p
    }

    fn stepped(&self, dx: &[f64]) -> Self {
        let mut out = *self;
        let d = DVec3::new(dx[0], dx[1], dx[2]);
        out.root = mat(rodrigues(d)) * self.root;
        for j in 1..NUM_JOINTS {
            out.pose[j] += DVec3::new(dx[3 * j], dx[3 * j + 1], dx[3 * j + 2]);
        }
        out.translation += DVec3::new(dx[72], dx[73], dx[74]);
        out
    }
}

fn mat(m: [[f64; 3]; 3]) -> DMat3 {
    DMat3::from_cols_array_2d(&m).transpose()
}

/// The axis-angle vector of a rotation matrix.
pub fn log_rotation(m: DMat3) -> DVec3 {
    DQuat::from_mat3(&m).normalize().to_scaled_axis()
}

/// Per-frame targets: `targets[frame][marker]` = (point, confidence), confidence 0 (and
/// any point) where there is no landmark.
pub type Targets = Vec<Vec<(DVec3, f64)>>;

/// The fitted sequence.
#[derive(Clone, Debug)]
pub struct Fit {
    pub betas: Vec<f64>,
    pub poses: Vec<Pose>,
    pub translations: Vec<DVec3>,
}

impl Fit {
    /// Posed joints and markers of every frame.
    pub fn posed(
        &self,
        body: &FitBody,
        markers: &[Marker],
    ) -> Vec<([DVec3; NUM_JOINTS], Vec<DVec3>)> {
        let rest = body.rest(&self.betas);
        self.poses
            .iter()
            .zip(&self.translations)
            .map(|(p, t)| body.pose(&rest, p, *t, markers))
            .collect()
    }
}

/// The root rotation (body axes to world) from the torso's landmarks, None when
/// missing. `lh, rh, ls, rs`: marker indices of hips and shoulders.
fn torso_frame(t: &[(DVec3, f64)], markers: &[Marker]) -> Option<(DMat3, DVec3)> {
    let find = |joint: usize| {
        markers
            .iter()
            .position(|m| m.joint == joint && m.offset == DVec3::ZERO)
            .and_then(|i| (t[i].1 > 0.0).then_some(t[i].0))
    };
    let (lh, rh, ls, rs) = (find(1)?, find(2)?, find(16)?, find(17)?);
    let x = (lh - rh).normalize_or_zero();
    let up = ((ls + rs) * 0.5 - (lh + rh) * 0.5).normalize_or_zero();
    let z = x.cross(up).normalize_or_zero();
    if z == DVec3::ZERO {
        return None;
    }
    let y = z.cross(x);
    Some((DMat3::from_cols(x, y, z), (lh + rh) * 0.5))
}

/// Fits `model` (with limb betas: [`with_limb_lengths`]) to `targets` (module header).
pub fn fit_sequence(
    body: &FitBody,
    markers: &[Marker],
    targets: &Targets,
    options: &FitOptions,
) -> Fit {
    let frames = targets.len();
    let mut betas = vec![0.0; body.num_betas];
    // Initial roots from the torso, carried over frames without one.
    let mut params: Vec<FrameParams> = Vec::with_capacity(frames);
    let rest = body.rest(&betas);
    let mut last = (DMat3::IDENTITY, DVec3::ZERO);
    let mid_hips_rest = (rest[1] + rest[2]) * 0.5;
    for t in targets {
        if let Some((r, mid)) = torso_frame(t, markers) {
            last = (r, mid - r * (mid_hips_rest - rest[0]) - rest[0]);
        }
        let mut pose = [DVec3::ZERO; NUM_JOINTS];
        // Arms down, as people mostly stand: a start nearer than the T-pose.
        pose[16].z = -1.2;
        pose[17].z = 1.2;
        params.push(FrameParams {
            root: last.0,
            pose,
            translation: last.1,
        });
    }
    let mut robust: Vec<Vec<f64>> = targets.iter().map(|t| vec![1.0; t.len()]).collect();
    for round in 0..=options.rounds {
        // Pose sweeps, forward then backward, neighbours held.
        let sweeps = if round == 0 { 2 } else { 1 };
        for sweep in 0..sweeps * 2 {
            let order: Vec<usize> = if sweep % 2 == 0 {
                (0..frames).collect()
            } else {
                (0..frames).rev().collect()
            };
            let rest = body.rest(&betas);
            for f in order {
                // Reweight this frame's markers from their current distances.
                let (_, m) = body.pose(&rest, &params[f].as_pose(), params[f].translation, markers);
                for (i, (p, tgt)) in m.iter().zip(&targets[f]).enumerate() {
                    let d = (*p - tgt.0).length() / options.robust_scale;
                    robust[f][i] = 1.0 / (1.0 + d * d);
                }
                let prev = (f > 0).then(|| params[f - 1]);
                let next = (f + 1 < frames).then(|| params[f + 1]);
                let mut current = params[f];
                let problem = FrameProblem {
                    body,
                    rest: &rest,
                    markers,
                    targets: &targets[f],
                    robust: &robust[f],
                    prev: prev.as_ref(),
                    next: next.as_ref(),
                    options,
                };
                levenberg_marquardt(
                    &mut current,
                    FRAME_PARAMS,
                    if round == 0 && sweep == 0 { 30 } else { 8 },
                    |current, dx| frame_residuals(&problem, &current.stepped(dx)),
                    |current, dx| current.stepped(dx),
                );
                params[f] = current;
            }
        }
        if round == options.rounds {
            break;
        }
        // The shape, all frames at once.
        let limbs = LIMB_BETAS.len();
        let poses: Vec<(Pose, DVec3)> = params
            .iter()
            .map(|p| (p.as_pose(), p.translation))
            .collect();
        let mut current = betas.clone();
        levenberg_marquardt(
            &mut current,
            limbs,
            10,
            |current, dx| {
                let mut b = current.clone();
                for (k, d) in dx.iter().enumerate() {
                    b[LIMB_BETAS.start + k] += d;
                }
                let rest = body.rest(&b);
                let mut r = Vec::new();
                for ((pose, tr), (t, w)) in poses.iter().zip(targets.iter().zip(&robust)) {
                    let (_, m) = body.pose(&rest, pose, *tr, markers);
                    push_marker_residuals(&mut r, &m, t, w, markers, options);
                }
                r.extend(b[LIMB_BETAS].iter().map(|x| x / options.shape_sigma));
                r
            },
            |current, dx| {
                let mut b = current.clone();
                for (k, d) in dx.iter().enumerate() {
                    b[LIMB_BETAS.start + k] += d;
                }
                b
            },
        );
        betas = current;
    }
    Fit {
        betas,
        poses: params.iter().map(FrameParams::as_pose).collect(),
        translations: params.iter().map(|p| p.translation).collect(),
    }
}

fn push_marker_residuals(
    r: &mut Vec<f64>,
    predicted: &[DVec3],
    targets: &[(DVec3, f64)],
    robust: &[f64],
    markers: &[Marker],
    options: &FitOptions,
) {
    for (((p, (t, c)), w), mk) in predicted.iter().zip(targets).zip(robust).zip(markers) {
        let s = (c * w * mk.weight).sqrt() / options.marker_sigma;
        if s > 0.0 {
            let e = (*p - *t) * s;
            r.extend([e.x, e.y, e.z]);
        } else {
            r.extend([0.0; 3]);
        }
    }
}

/// One frame's pose problem: the body at the current shape, the markers with this
/// frame's targets and robust weights, and the neighbouring frames the smoothness terms
/// hold fixed.
struct FrameProblem<'a> {
    body: &'a FitBody,
    rest: &'a [DVec3; NUM_JOINTS],
    markers: &'a [Marker],
    targets: &'a [(DVec3, f64)],
    robust: &'a [f64],
    prev: Option<&'a FrameParams>,
    next: Option<&'a FrameParams>,
    options: &'a FitOptions,
}

/// The residuals of `p` in `problem`: markers, smoothness, prior and limits.
fn frame_residuals(problem: &FrameProblem, p: &FrameParams) -> Vec<f64> {
    let FrameProblem {
        body,
        rest,
        markers,
        targets,
        robust,
        prev,
        next,
        options,
    } = *problem;
    let pose = p.as_pose();
    let (_, m) = body.pose(rest, &pose, p.translation, markers);
    let mut r = Vec::with_capacity(markers.len() * 3 + 3 * FRAME_PARAMS);
    push_marker_residuals(&mut r, &m, targets, robust, markers, options);
    for q in [prev, next].into_iter().flatten() {
        let d = log_rotation(p.root * q.root.transpose()) / options.smooth_rotation;
        r.extend([d.x, d.y, d.z]);
        for j in 1..NUM_JOINTS {
            let d = (p.pose[j] - q.pose[j]) / options.smooth_rotation;
            r.extend([d.x, d.y, d.z]);
        }
        let d = (p.translation - q.translation) / options.smooth_translation;
        r.extend([d.x, d.y, d.z]);
    }
    for j in 1..NUM_JOINTS {
        let d = p.pose[j] / prior_sigma(j);
        r.extend([d.x, d.y, d.z]);
    }
    // Joint limits: knees flex about +x only, elbows about -y (left) / +y (right), and
    // neither twists much (0.1 rad per unit beyond the limit, 0.15 rad for the off
    // axes).
    let hinge = |v: f64| v.max(0.0) / 0.02;
    for k in [4, 5] {
        let q = p.pose[k];
        r.extend([hinge(-q.x - 0.05), q.y / 0.15, q.z / 0.15]);
    }
    for (k, sign) in [(18, -1.0), (19, 1.0)] {
        let q = p.pose[k];
        r.extend([q.x / 0.4, hinge(-sign * q.y - 0.05), q.z / 0.2]);
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::kinematics::pose_body;
    use crate::body::procedural::{default_body, BodyOptions};

    /// The limb directions move the regressed joints as the bones they scale: +1 of
    /// the thigh beta lengthens the thigh by 10% and leaves the shin as it was.
    #[test]
    fn limb_betas_scale_their_bones() {
        let model = with_limb_lengths(&default_body(&BodyOptions {
            cell: 0.05,
            num_betas: 10,
        }));
        let mut betas = vec![0.0; 10];
        let rest = pose_body(&model, &betas, &[DVec3::ZERO; NUM_JOINTS], DVec3::ZERO).rest_joints;
        betas[3] = 1.0;
        let long = pose_body(&model, &betas, &[DVec3::ZERO; NUM_JOINTS], DVec3::ZERO).rest_joints;
        let thigh = |j: &[DVec3; NUM_JOINTS]| (j[4] - j[1]).length();
        let shin = |j: &[DVec3; NUM_JOINTS]| (j[7] - j[4]).length();
        // Within 1% of the bone (the rings' correction is exact unless rings overlap).
        assert!((thigh(&long) / thigh(&rest) - 1.1).abs() < 0.01);
        assert!((shin(&long) / shin(&rest) - 1.0).abs() < 0.01);
        // The same for the hips, whose rings take in pelvis vertices.
        betas[3] = 0.0;
        betas[2] = 1.0;
        let wide = pose_body(&model, &betas, &[DVec3::ZERO; NUM_JOINTS], DVec3::ZERO).rest_joints;
        let hip = |j: &[DVec3; NUM_JOINTS]| (j[1] - j[0]).length();
        assert!(
            (hip(&wide) / hip(&rest) - 1.1).abs() < 0.01,
            "{}",
            hip(&wide) / hip(&rest)
        );
    }
}
