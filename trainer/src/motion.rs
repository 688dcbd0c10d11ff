//! Motions: per-frame SMPL pose parameters at a frame rate, made procedurally (walk,
//! jog, raise arms, turn in place) or loaded, saved as `.npz` with `poses` F×72,
//! `trans` F×3 and `fps` (1).
//!
//! The frame is the body's: y up, the body facing +z (see `body::procedural`). A
//! motion's translation moves the body from where its rest pose stands: every
//! procedural motion starts at zero, and its users add it to where the body already is
//! (the cloth simulation ramps it in from zero while settling; `animate` carries it into
//! a run's world).
//!
//! [`Motion::load_npz`] reads motions as people have them:
//! - Ours and numpy users': `poses` F×72 (SMPL's 24 joints), `trans` F×3 and `fps`,
//!   0-d (`np.savez(f, fps=30)`) or of shape (1); taken as written.
//! - `poses` F×66: SMPL's first 22 joints only (text-to-motion outputs such as
//!   HumanML3D-style SMPL fits); the two hand joints are set to zero as below.
//! - AMASS, recognised by `mocap_framerate` (SMPL-X releases: `mocap_frame_rate`) or by
//!   `poses` of 156 columns (SMPL-H, 52 joints × 3) or 165 (SMPL-X, 55 × 3). The first
//!   22 joints of SMPL-H and SMPL-X are SMPL's first 22 in the same order (pelvis to
//!   wrists) and are taken as they are. SMPL's joints 22 and 23 (one rigid 'hand'
//!   beyond each wrist) have no SMPL-H or SMPL-X counterpart, whose hands are 15 finger
//!   joints each, so they get zero rotation, as the common AMASS-to-SMPL converters do.
//!   `betas`, `gender`, `dmpls` and the like are not read (a text or pickled `gender`
//!   does not stop the file being read, see `npy::Npz`).
//!
//!   AMASS is z up. Its motions are brought into our y-up frame by the -90° rotation
//!   about x that AMASS users apply, (x, y, z) -> (x, z, -y), to the root orientation
//!   (composed on the left) and to `trans`. Its `trans` is where the body is in the
//!   capture room (the root about 0.9 m above the floor, wherever the subject began),
//!   not a displacement from rest, so the first frame's is subtracted from every frame:
//!   the motion starts where the body stands, as the procedural ones do. That also
//!   removes the constant `(R - I)·pelvis` that rotating about the world origin instead
//!   of the pelvis adds, which the loader could not compute without the body. The
//!   heading and every later displacement (a jump, a walk) are kept.

use std::collections::BTreeMap;
use std::f64::consts::PI;
use std::path::Path;

use glam::DVec3;

use crate::body::kinematics::Pose;
use crate::npy::{self, Array, NpyError};

/// A sequence of poses.
#[derive(Clone, Debug, PartialEq)]
pub struct Motion {
    pub fps: f64,
    pub poses: Vec<Pose>,
    pub translations: Vec<DVec3>,
}

/// The procedural motions.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MotionKind {
    Walk,
    Jog,
    RaiseArms,
    Turn,
}

impl MotionKind {
    pub const ALL: [MotionKind; 4] = [
        MotionKind::Walk,
        MotionKind::Jog,
        MotionKind::RaiseArms,
        MotionKind::Turn,
    ];

    pub fn name(self) -> &'static str {
        match self {
            MotionKind::Walk => "walk",
            MotionKind::Jog => "jog",
            MotionKind::RaiseArms => "raise-arms",
            MotionKind::Turn => "turn",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == s)
    }
}

/// Smooth 0 -> 1 over the first `ramp` seconds, so every motion starts at rest.
fn ease_in(t: f64, ramp: f64) -> f64 {
    let x = (t / ramp).clamp(0.0, 1.0);
    x * x * (3.0 - 2.0 * x)
}

/// A procedural motion of `frames` frames at `fps`, played `speed` times faster than
/// normal (the cycle frequency scales, the frame rate does not).
pub fn procedural(kind: MotionKind, frames: usize, fps: f64, speed: f64) -> Motion {
    let mut poses = Vec::with_capacity(frames);
    let mut translations = Vec::with_capacity(frames);
    let arms_down = crate::body::kinematics::A_POSE_ARMS_DOWN;
    for f in 0..frames {
        let t = f as f64 / fps * speed;
        let e = ease_in(t, 0.6);
        // Every motion starts from the A-pose.
        let mut p: Pose = crate::body::kinematics::a_pose();
        let mut trans = DVec3::ZERO;
        match kind {
            MotionKind::Walk | MotionKind::Jog => {
                let (freq, swing, knee, lift, arm) = if kind == MotionKind::Walk {
                    (0.9, 0.25, 0.5, 0.0, 0.3)
                } else {
                    (1.4, 0.7, 1.2, 0.03, 0.6)
                };
                let phase = 2.0 * PI * freq * t;
                let s = phase.sin() * e;
                // Hips swing about x (forward is -x rotation for the +z-facing body).
                p[1][0] = -swing * s;
                p[2][0] = swing * s;
                // Knees bend on the back swing only.
                p[4][0] = knee
                    * (0.5 - 0.5 * (phase + 0.8).cos()).max(0.0)
                    * e
                    * (0.5 + 0.5 * phase.sin()).min(1.0);
                p[5][0] = knee
                    * (0.5 - 0.5 * (phase + 0.8 + PI).cos()).max(0.0)
                    * e
                    * (0.5 - 0.5 * phase.sin()).min(1.0);
                // Arms swing opposite to the legs, about the shoulder's x axis.
                p[16][0] = arm * s;
                p[17][0] = -arm * s;
                p[18][1] = 0.3 * e;
                p[19][1] = -0.3 * e;
                p[3][1] = 0.08 * s;
                trans = DVec3::new(
                    0.0,
                    lift * (2.0 * phase).sin().abs() * e,
                    (if kind == MotionKind::Walk { 1.2 } else { 2.4 }) * t * e,
                );
            }
            MotionKind::RaiseArms => {
                let up = (0.5 - 0.5 * (2.0 * PI * 0.4 * t).cos()) * e;
                p[16][2] = -arms_down + 2.3 * up;
                p[17][2] = arms_down - 2.3 * up;
                p[18][1] = 0.2 * up;
                p[19][1] = -0.2 * up;
            }
            MotionKind::Turn => {
                p[0][1] = 1.2 * PI * t / 3.0 * e;
                let step = (2.0 * PI * 1.0 * t).sin() * e;
                p[1][0] = -0.15 * step;
                p[2][0] = 0.15 * step;
            }
        }
        poses.push(p);
        translations.push(trans);
    }
    Motion {
        fps,
        poses,
        translations,
    }
}

impl Motion {
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    pub fn save_npz(&self, path: &Path) -> Result<(), NpyError> {
        let mut a = BTreeMap::new();
        a.insert(
            "poses".to_string(),
            Array::f64(
                vec![self.len(), 72],
                self.poses
                    .iter()
                    .flatten()
                    .flat_map(|r| r.to_array())
                    .collect(),
            ),
        );
        a.insert(
            "trans".to_string(),
            Array::f64(
                vec![self.len(), 3],
                self.translations
                    .iter()
                    .flat_map(|t| t.to_array())
                    .collect(),
            ),
        );
        a.insert("fps".to_string(), Array::f64(vec![1], vec![self.fps]));
        npy::write_npz(path, &a)
    }

    /// Reads a motion file of any layout in the module header. Errors are one line
    /// naming the file and the field.
    pub fn load_npz(path: &Path) -> Result<Self, NpyError> {
        let npz = npy::Npz::read(path)?;
        let bad = |key: &str, problem: String| NpyError::Format {
            file: npz.file.clone(),
            key: Some(key.to_string()),
            problem,
        };
        let poses = npz.require("poses", &[None, None])?;
        let (frames, width) = (poses.shape[0], poses.shape[1]);
        // Joints read from the file; SMPL's others (the hands) stay at zero.
        let joints = match width {
            72 => 24,
            66 | 156 | 165 => 22,
            _ => {
                return Err(bad(
                    "poses",
                    format!("{width} values per frame; expected 72 (SMPL, 24 joints × 3), 66 (22 body joints), 156 (SMPL-H, AMASS) or 165 (SMPL-X)"),
                ))
            }
        };
        if frames == 0 {
            return Err(bad("poses", format!("no frames (shape [0, {width}])")));
        }
        let trans = npz.require("trans", &[None, Some(3)])?;
        if trans.shape[0] != frames {
            return Err(bad(
                "trans",
                format!("{} frames, but 'poses' has {frames}", trans.shape[0]),
            ));
        }
        let rate_key = ["fps", "mocap_framerate", "mocap_frame_rate"]
            .into_iter()
            .find(|k| npz.contains(k));
        let rate_key = rate_key.ok_or_else(|| {
            bad(
                "fps",
                "missing key (nor is there AMASS's 'mocap_framerate')".into(),
            )
        })?;
        let fps = npz.scalar(rate_key)?;
        if !(MIN_FPS..=MAX_FPS).contains(&fps) {
            return Err(bad(
                rate_key,
                format!(
                    "{fps} is not a positive frame rate of {MIN_FPS} to {MAX_FPS} frames a second"
                ),
            ));
        }
        for (key, a) in [("poses", poses), ("trans", trans)] {
            if let Some(i) = a.data.iter().position(|v| !v.is_finite()) {
                return Err(bad(key, format!("value {i} is {} (not finite)", a.data[i])));
            }
        }
        if let Some(i) = poses.data.iter().position(|v| v.abs() > MAX_AXIS_ANGLE) {
            return Err(bad("poses", format!("value {i} is {} rad; axis-angles are at most {MAX_AXIS_ANGLE} (degrees instead of radians?)", poses.data[i])));
        }
        let translations_read: Vec<DVec3> =
            trans.data.chunks_exact(3).map(DVec3::from_slice).collect();
        check_root_speed(&translations_read, fps).map_err(|problem| bad("trans", problem))?;
        if let Some(i) = trans.data.iter().position(|v| v.abs() > MAX_TRANSLATION) {
            return Err(bad("trans", format!("value {i} is {} m; drape takes translations within {MAX_TRANSLATION} m of the origin (is the file in millimetres?)", trans.data[i])));
        }
        let amass = width == 156
            || width == 165
            || npz.contains("mocap_framerate")
            || npz.contains("mocap_frame_rate");
        let mut poses: Vec<Pose> = poses
            .data
            .chunks_exact(width)
            .map(|c| {
                std::array::from_fn(|j| {
                    if j < joints {
                        DVec3::from_slice(&c[3 * j..3 * j + 3])
                    } else {
                        DVec3::ZERO
                    }
                })
            })
            .collect();
        let mut translations: Vec<DVec3> =
            trans.data.chunks_exact(3).map(DVec3::from_slice).collect();
        if amass {
            let first = z_up_to_y_up(translations[0]);
            for t in &mut translations {
                *t = z_up_to_y_up(*t) - first;
            }
            for p in &mut poses {
                p[0] = z_up_to_y_up_orientation(p[0]);
            }
        }
        Ok(Self {
            fps,
            poses,
            translations,
        })
    }
}

/// The frame rates a motion file may have.
pub const MIN_FPS: f64 = 1.0;
pub const MAX_FPS: f64 = 1000.0;
/// How far from the origin a motion's root may go (metres): a capture hall is tens of
/// metres across; millimetres read as metres are thousands.
pub const MAX_TRANSLATION: f64 = 1000.0;

/// The largest axis-angle component a motion may have (radians; a rotation needs at
/// most π, a few turns more are tolerated).
pub const MAX_AXIS_ANGLE: f64 = 4.0 * PI;

/// The fastest a person's root moves (m/s): a sprinter reaches about 12.
pub const MAX_ROOT_SPEED: f64 = 20.0;

/// Refuses a root that moves faster than [`MAX_ROOT_SPEED`] between two frames at
/// `fps` (a teleporting body would drag the simulated cloth across the distance).
pub fn check_root_speed(translations: &[DVec3], fps: f64) -> Result<(), String> {
    for (i, w) in translations.windows(2).enumerate() {
        let d = w[1] - w[0];
        let step = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        if !(step * fps <= MAX_ROOT_SPEED) {
            return Err(format!("the root moves {step:.3} m between frames {i} and {} ({:.1} m/s at {fps} fps; people move at most {MAX_ROOT_SPEED} m/s)", i + 1, step * fps));
        }
    }
    Ok(())
}

/// The -90° rotation about x: AMASS's z-up world to our y-up one.
fn z_up_to_y_up(v: DVec3) -> DVec3 {
    DVec3::new(v[0], v[2], -v[1])
}

/// An axis-angle root orientation in AMASS's world, in ours: the -90° rotation about x
/// composed on the left. Through quaternions, which stay accurate near 180°.
fn z_up_to_y_up_orientation(r: DVec3) -> DVec3 {
    let h = std::f64::consts::FRAC_1_SQRT_2;
    quaternion_to_axis_angle(quaternion_mul(
        [h, -h, 0.0, 0.0],
        axis_angle_to_quaternion(r),
    ))
}

/// `[w, x, y, z]` of the rotation by |r| about r.
fn axis_angle_to_quaternion(r: DVec3) -> [f64; 4] {
    let angle = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
    // sin(a/2)/a, by its series where the division loses accuracy.
    let k = if angle < 1e-6 {
        0.5 - angle * angle / 48.0
    } else {
        (angle / 2.0).sin() / angle
    };
    [(angle / 2.0).cos(), k * r[0], k * r[1], k * r[2]]
}

fn quaternion_mul(a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
    [
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    ]
}

/// The axis-angle of a unit quaternion, angle in [0, π].
fn quaternion_to_axis_angle(q: [f64; 4]) -> DVec3 {
    let q = if q[0] < 0.0 { q.map(|c| -c) } else { q };
    let s = (q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    let angle = 2.0 * s.atan2(q[0]);
    // angle / sin(angle/2), which tends to 2/w for a small angle.
    let k = if s < 1e-12 { 2.0 / q[0] } else { angle / s };
    DVec3::new(k * q[1], k * q[2], k * q[3])
}
