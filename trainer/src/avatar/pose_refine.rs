//! Per-frame pose and translation refinement: every training frame carries a
//! learned correction to its body parameters (root rotation, the 23 joints'
//! axis-angles, translation; `rig::REFINED_PARAMS`), added to what the data says.
//!
//! The image and cloth losses reach it through the skinning transforms: each layer's
//! backward sums `∂L/∂A_j` on the GPU (`ops::deform`), the rig chains that through
//! the kinematic tree to the parameters (`Rig::frame_gradient`), and a per-frame Adam
//! on the host (75 values a frame; f64, so deterministic) applies it. HUGS refines
//! the pose as 6D rotations at 1e-4 and never the translation (PAPER.md); we refine
//! the axis-angles directly, at the same rate, and the translation as well, since
//! a monocular capture's depth is its least certain part. Each frame's Adam counts its
//! own steps (a frame is visited on average once per `frames` steps, and its bias
//! correction must follow its own updates). A frame seen by several training cameras
//! (a multi-camera sequence) has one correction, which every one of its images
//! trains: the body was in one pose at that instant. A held-out image of a trained
//! instant (another camera, the same frame) is rendered with that instant's
//! correction ([`PoseRefiner::body_of_frame`]); held-out instants with the data's
//! parameters: there is nothing to refine them from.

use crate::avatar::rig::{refined_body, REFINED_PARAMS};
use crate::dataset::loader::BodyParams;
use crate::TrainerError;

/// HUGS's Adam ε (its optimiser's for every group).
const ADAM_EPS: f64 = 1e-15;
const BETA1: f64 = 0.9;
const BETA2: f64 = 0.999;

/// Saved state: per frame (by dataset frame number, each once) its correction, Adam
/// moments and step count.
#[derive(Clone, Debug, PartialEq)]
pub struct PoseState {
    pub frames: Vec<u32>,
    pub deltas: Vec<[f64; REFINED_PARAMS]>,
    pub m: Vec<[f64; REFINED_PARAMS]>,
    pub v: Vec<[f64; REFINED_PARAMS]>,
    pub steps: Vec<u32>,
}

impl PoseState {
    /// `body` with frame `frame`'s correction where that frame was trained, else as
    /// the data has it (what a held-out image of that instant is rendered with).
    /// A state saved with one correction per image (a frame number repeated: drape
    /// before the corrections were shared per instant) has no one correction per
    /// instant, and its held-out images keep the data's pose, as they were evaluated.
    pub fn body_of_frame(&self, frame: u32, body: &BodyParams) -> BodyParams {
        let mut at = self.frames.iter().enumerate().filter(|(_, &f)| f == frame);
        match (at.next(), at.next()) {
            (Some((k, _)), None) if !self.per_image() => refined_body(body, &self.deltas[k]),
            _ => body.clone(),
        }
    }

    /// Whether a frame number repeats (corrections saved per image, not per instant).
    pub fn per_image(&self) -> bool {
        let mut seen = std::collections::BTreeSet::new();
        !self.frames.iter().all(|f| seen.insert(*f))
    }

    /// No frame refined yet.
    pub fn zeros(frames: &[u32]) -> Self {
        let z = vec![[0.0; REFINED_PARAMS]; frames.len()];
        Self {
            frames: frames.to_vec(),
            deltas: z.clone(),
            m: z.clone(),
            v: z,
            steps: vec![0; frames.len()],
        }
    }
}

/// The refinement of a run's training frames.
#[derive(Clone, Debug)]
pub struct PoseRefiner {
    state: PoseState,
    /// Per training image, its frame's slot in `state`.
    slots: Vec<usize>,
    lr_pose: f64,
    lr_translation: f64,
}

impl PoseRefiner {
    /// Corrections (all zero) for the training images of dataset frames `frames` (in
    /// the order the trainer indexes its images; a frame seen by several cameras
    /// appears once per image and gets one correction).
    pub fn new(frames: &[u32], lr_pose: f64, lr_translation: f64) -> Self {
        let mut unique: Vec<u32> = Vec::new();
        let slots = frames
            .iter()
            .map(|f| match unique.iter().position(|u| u == f) {
                Some(k) => k,
                None => {
                    unique.push(*f);
                    unique.len() - 1
                }
            })
            .collect();
        Self {
            state: PoseState::zeros(&unique),
            slots,
            lr_pose,
            lr_translation,
        }
    }

    /// The body parameters training image `index` is rendered with.
    pub fn body(&self, index: usize, body: &BodyParams) -> BodyParams {
        refined_body(body, &self.state.deltas[self.slots[index]])
    }

    /// The body parameters an image of dataset frame `frame` is rendered with: its
    /// frame's correction where the frame was trained, else the data's.
    pub fn body_of_frame(&self, frame: u32, body: &BodyParams) -> BodyParams {
        self.state.body_of_frame(frame, body)
    }

    /// One Adam step on training image `index`'s frame from the gradient on its
    /// parameters. A non-finite gradient is the caller's to refuse (the step guard).
    pub fn step(&mut self, index: usize, grad: &[f64; REFINED_PARAMS]) {
        let index = self.slots[index];
        let s = &mut self.state;
        s.steps[index] += 1;
        let t = s.steps[index] as i32;
        let (c1, c2) = (1.0 - BETA1.powi(t), 1.0 - BETA2.powi(t));
        for k in 0..REFINED_PARAMS {
            let lr = if k >= REFINED_PARAMS - 3 {
                self.lr_translation
            } else {
                self.lr_pose
            };
            let g = grad[k];
            s.m[index][k] = BETA1 * s.m[index][k] + (1.0 - BETA1) * g;
            s.v[index][k] = BETA2 * s.v[index][k] + (1.0 - BETA2) * g * g;
            s.deltas[index][k] -=
                lr * (s.m[index][k] / c1) / ((s.v[index][k] / c2).sqrt() + ADAM_EPS);
        }
    }

    /// The correction of training image `index`'s frame.
    pub fn delta(&self, index: usize) -> &[f64; REFINED_PARAMS] {
        &self.state.deltas[self.slots[index]]
    }

    pub fn state(&self) -> &PoseState {
        &self.state
    }

    /// Restores saved corrections; the frames must be this run's, in its order.
    pub fn restore(&mut self, state: PoseState) -> crate::Result<()> {
        if state.per_image() {
            return Err(TrainerError::invalid(
                "refined poses",
                "saved one per image by a drape before they were shared per frame instant: this run cannot resume from them (train it afresh)",
            ));
        }
        if state.frames != self.state.frames {
            return Err(TrainerError::invalid(
                "refined poses",
                format!(
                    "of frames {:?}, but this run trains on {:?}",
                    state.frames, self.state.frames
                ),
            ));
        }
        self.state = state;
        Ok(())
    }

    /// Mean over frames of the largest joint-rotation correction (radians) and of
    /// the translation correction's length: what the log reports.
    pub fn summary(&self) -> (f64, f64) {
        let n = self.state.deltas.len().max(1) as f64;
        let t = REFINED_PARAMS - 3;
        let rot = self
            .state
            .deltas
            .iter()
            .map(|d| {
                d[..t]
                    .chunks_exact(3)
                    .map(|r| (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt())
                    .fold(0.0, f64::max)
            })
            .sum::<f64>()
            / n;
        let tr = self
            .state
            .deltas
            .iter()
            .map(|d| (d[t] * d[t] + d[t + 1] * d[t + 1] + d[t + 2] * d[t + 2]).sqrt())
            .sum::<f64>()
            / n;
        (rot, tr)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Adam on f(x) = ½ Σ (x - c)² moves every parameter toward c, the first step by
    /// exactly the learning rate (bias-corrected m / √v = ±1).
    #[test]
    fn adam_steps_toward_the_minimum() {
        let mut r = PoseRefiner::new(&[4, 9], 1e-2, 1e-3);
        let target: [f64; REFINED_PARAMS] = std::array::from_fn(|k| 0.05 * ((k % 7) as f64 - 3.0));
        let grad = |d: &[f64; REFINED_PARAMS]| -> [f64; REFINED_PARAMS] {
            std::array::from_fn(|k| d[k] - target[k])
        };
        let g = grad(r.delta(1));
        r.step(1, &g);
        for k in 0..REFINED_PARAMS {
            let lr = if k >= REFINED_PARAMS - 3 { 1e-3 } else { 1e-2 };
            let expected = if target[k] == 0.0 {
                0.0
            } else {
                lr * target[k].signum()
            };
            assert!(
                (r.delta(1)[k] - expected).abs() < 1e-12,
                "parameter {k}: {} vs {expected}",
                r.delta(1)[k]
            );
        }
        assert_eq!(
            r.delta(0),
            &[0.0; REFINED_PARAMS],
            "another frame is untouched"
        );
        let start: f64 = target.iter().map(|t| t * t).sum();
        for _ in 0..200 {
            let g = grad(r.delta(1));
            r.step(1, &g);
        }
        let end: f64 = r
            .delta(1)
            .iter()
            .zip(&target)
            .map(|(d, t)| (d - t) * (d - t))
            .sum();
        assert!(
            end < 0.05 * start,
            "200 steps: squared error {end} from {start}"
        );
        assert_eq!(r.state().steps, vec![0, 201]);
    }

    #[test]
    fn restore_refuses_other_frames() {
        let mut r = PoseRefiner::new(&[1, 2], 1e-4, 1e-4);
        let e = r.restore(PoseState::zeros(&[1, 3])).unwrap_err();
        assert!(
            matches!(
                e,
                TrainerError::InvalidInput {
                    what: "refined poses",
                    ..
                }
            ),
            "{e}"
        );
        let e = e.to_string();
        assert!(e.contains("[1, 3]") && e.contains("[1, 2]"), "{e}");
    }

    /// Images of one instant (several cameras) share one correction; a held-out image
    /// of a trained instant takes it, one of an untrained instant the data's pose.
    #[test]
    fn cameras_of_one_instant_share_a_correction() {
        let mut r = PoseRefiner::new(&[3, 5, 3, 5, 7], 0.1, 0.1);
        assert_eq!(r.state().frames, vec![3, 5, 7]);
        let mut g = [0.0; REFINED_PARAMS];
        g[REFINED_PARAMS - 1] = 1.0;
        r.step(2, &g);
        assert_ne!(r.delta(0)[REFINED_PARAMS - 1], 0.0);
        assert_eq!(r.delta(0), r.delta(2), "image 2 is frame 3's other camera");
        assert_eq!(r.delta(1), &[0.0; REFINED_PARAMS]);
        let body = BodyParams::Zju(crate::dataset::zju::ZjuSmpl {
            poses: [0.0; 72],
            rh: [0.0; 3],
            th: [0.0; 3],
            shapes: [0.0; 10],
        });
        assert_eq!(r.body_of_frame(3, &body), r.body(0, &body));
        assert_ne!(r.body_of_frame(3, &body), body);
        assert_eq!(r.body_of_frame(9, &body), body, "an untrained instant");
    }

    /// A state saved per image (a frame number repeated) keeps the data's pose for
    /// held-out images and cannot be resumed from.
    #[test]
    fn a_state_saved_per_image_is_not_taken_for_one_per_instant() {
        let mut old = PoseState::zeros(&[3, 5, 3]);
        old.deltas[0][REFINED_PARAMS - 1] = 0.5;
        // Frame 5 appears once, but its correction too is one image's.
        old.deltas[1][REFINED_PARAMS - 1] = 0.5;
        assert!(old.per_image());
        let body = BodyParams::Zju(crate::dataset::zju::ZjuSmpl {
            poses: [0.0; 72],
            rh: [0.0; 3],
            th: [0.0; 3],
            shapes: [0.0; 10],
        });
        assert_eq!(old.body_of_frame(3, &body), body);
        assert_eq!(old.body_of_frame(5, &body), body);
        let mut r = PoseRefiner::new(&[3, 5, 3], 0.1, 0.1);
        let e = r.restore(old).expect_err("refused").to_string();
        assert!(e.contains("saved one per image"), "{e}");
    }
}
