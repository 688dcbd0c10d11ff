//! Motions: per-frame SMPL pose parameters at a frame rate, made procedurally (walk,
//! jog, raise arms, turn in place) or loaded, saved as `.npz` with `poses` F×72,
//! `trans` F×3 and `fps` (1).

use std::collections::BTreeMap;
use std::f64::consts::PI;
use std::path::Path;

use crate::body::kinematics::Pose;
use crate::mesh::V3;
use crate::npy::{self, Array, NpyError};

/// A sequence of poses.
#[derive(Clone, Debug, PartialEq)]
pub struct Motion {
    pub fps: f64,
    pub poses: Vec<Pose>,
    pub translations: Vec<V3>,
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
    pub const ALL: [MotionKind; 4] = [MotionKind::Walk, MotionKind::Jog, MotionKind::RaiseArms, MotionKind::Turn];

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
        let mut trans = [0.0; 3];
        match kind {
            MotionKind::Walk | MotionKind::Jog => {
                let (freq, swing, knee, lift, arm) = if kind == MotionKind::Walk { (0.9, 0.25, 0.5, 0.0, 0.3) } else { (1.4, 0.7, 1.2, 0.03, 0.6) };
                let phase = 2.0 * PI * freq * t;
                let s = phase.sin() * e;
                // Hips swing about x (forward is -x rotation for the +z-facing body).
                p[1][0] = -swing * s;
                p[2][0] = swing * s;
                // Knees bend on the back swing only.
                p[4][0] = knee * (0.5 - 0.5 * (phase + 0.8).cos()).max(0.0) * e * (0.5 + 0.5 * phase.sin()).min(1.0);
                p[5][0] = knee * (0.5 - 0.5 * (phase + 0.8 + PI).cos()).max(0.0) * e * (0.5 - 0.5 * phase.sin()).min(1.0);
                // Arms swing opposite to the legs, about the shoulder's x axis.
                p[16][0] = arm * s;
                p[17][0] = -arm * s;
                p[18][1] = 0.3 * e;
                p[19][1] = -0.3 * e;
                p[3][1] = 0.08 * s;
                trans = [0.0, lift * (2.0 * phase).sin().abs() * e, (if kind == MotionKind::Walk { 1.2 } else { 2.4 }) * t * e];
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
    Motion { fps, poses, translations }
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
        a.insert("poses".to_string(), Array::f64(vec![self.len(), 72], self.poses.iter().flatten().flatten().copied().collect()));
        a.insert("trans".to_string(), Array::f64(vec![self.len(), 3], self.translations.iter().flatten().copied().collect()));
        a.insert("fps".to_string(), Array::f64(vec![1], vec![self.fps]));
        npy::write_npz(path, &a)
    }

    pub fn load_npz(path: &Path) -> Result<Self, NpyError> {
        let file = path.display().to_string();
        let a = npy::read_npz(path)?;
        let poses = npy::require(&a, &file, "poses", &[None, Some(72)])?;
        let frames = poses.shape[0];
        let trans = npy::require(&a, &file, "trans", &[Some(frames), Some(3)])?;
        let fps = npy::require(&a, &file, "fps", &[Some(1)])?.data[0];
        if !(fps > 0.0) {
            return Err(NpyError::Format { file, key: Some("fps".into()), problem: format!("{fps} is not a positive frame rate") });
        }
        Ok(Self {
            fps,
            poses: poses.data.chunks_exact(72).map(|c| std::array::from_fn(|j| [c[3 * j], c[3 * j + 1], c[3 * j + 2]])).collect(),
            translations: trans.data.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        })
    }
}
