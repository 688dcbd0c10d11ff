//! The trainer's one camera: a pinhole in f64 that the synthetic data is rendered with,
//! the datasets load into, animation moves, and training converts to the engine's
//! f32 [`PinholeCamera`] for the splatter ([`Camera::to_pinhole`], the only place that
//! conversion is written). The file formats keep their own records (COLMAP's
//! `cameras.txt`/`images.txt`, ZJU-MoCap's `annots.npy`), each converting to and
//! from this type in its module.
//!
//! Convention as everywhere in drape: world to camera `p_c = R p_w + t`, x right,
//! y down, z forward, pixel centres at +0.5.
//!
//! [`Camera::look_at`] is the trainer's only look-at. The engine has its own,
//! `PinholeCamera::look_at`, with the same axes but in f32 and by field of view: the
//! synthetic data is made in f64, and changing it to go through the engine's would
//! change every file `drape synth` writes.

use drape_engine::ops::splat::scene::PinholeCamera;

use glam::{DMat3, DVec3};

/// A pinhole camera in f64: intrinsics in pixels, world-to-camera pose, image size and
/// the near clipping distance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
    /// World-to-camera rotation, rows.
    pub rotation: [[f64; 3]; 3],
    pub translation: DVec3,
    pub near: f64,
}

/// The world-to-camera pose of a camera at `eye` looking at `target` with world up
/// `up`: rows right, down, forward.
fn pose_looking_at(eye: DVec3, target: DVec3, up: DVec3) -> ([[f64; 3]; 3], DVec3) {
    // A zero direction gives +z rather than NaN.
    let forward = (target - eye).normalize_or(DVec3::Z);
    let right = forward.cross(up).normalize_or(DVec3::Z);
    let down = forward.cross(right);
    (
        [right, down, forward].map(|v| v.to_array()),
        DVec3::new(-right.dot(eye), -down.dot(eye), -forward.dot(eye)),
    )
}

impl Camera {
    /// The near clipping distance of every camera the trainer makes or loads (metres):
    /// well inside the closest the synthetic cameras come to anything they see.
    pub const NEAR: f64 = 0.05;

    /// The far clipping distance handed to the splatter (the engine's default).
    pub const FAR: f32 = 1e4;

    /// A camera at `eye` looking at `target`, world up `up`, focal length `f` pixels,
    /// principal point at the image centre.
    pub fn look_at(eye: DVec3, target: DVec3, up: DVec3, f: f64, width: u32, height: u32) -> Self {
        let (rotation, translation) = pose_looking_at(eye, target, up);
        Self {
            fx: f,
            fy: f,
            cx: f64::from(width) / 2.0,
            cy: f64::from(height) / 2.0,
            width,
            height,
            rotation,
            translation,
            near: Self::NEAR,
        }
    }

    /// This camera (its intrinsics, image size and near plane) moved to `eye` and
    /// turned to look at `target`, world up `up`.
    pub fn moved_to(&self, eye: DVec3, target: DVec3, up: DVec3) -> Self {
        let (rotation, translation) = pose_looking_at(eye, target, up);
        Self {
            rotation,
            translation,
            ..*self
        }
    }

    /// The rotation as glam's (column-major) matrix.
    fn rotation_matrix(&self) -> DMat3 {
        DMat3::from_cols_array_2d(&self.rotation).transpose()
    }

    /// The camera centre in the world, `-Rᵀ t`.
    pub fn centre(&self) -> DVec3 {
        -(self.rotation_matrix().transpose() * self.translation)
    }

    /// Pixel coordinates of a world point (None behind the camera).
    pub fn project(&self, p: DVec3) -> Option<[f64; 2]> {
        let c = self.to_camera(p);
        (c[2] > 0.0).then(|| self.project_camera(c))
    }

    /// A world point in camera space.
    pub fn to_camera(&self, p: DVec3) -> DVec3 {
        self.rotation_matrix() * p + self.translation
    }

    /// Pixel coordinates (not rounded) of a camera-space point in front of the camera.
    pub fn project_camera(&self, c: DVec3) -> [f64; 2] {
        [
            self.fx * c[0] / c[2] + self.cx,
            self.fy * c[1] / c[2] + self.cy,
        ]
    }

    /// The splatter's camera: this one in f32 over `background`, far plane [`Self::FAR`].
    pub fn to_pinhole(&self, background: [f32; 3]) -> PinholeCamera {
        PinholeCamera {
            fx: self.fx as f32,
            fy: self.fy as f32,
            cx: self.cx as f32,
            cy: self.cy as f32,
            width: self.width,
            height: self.height,
            rotation: self.rotation.map(|r| r.map(|v| v as f32)),
            translation: self.translation.as_vec3().to_array(),
            near: self.near as f32,
            far: Self::FAR,
            background,
        }
    }
}

#[cfg(test)]
mod tests {
    use drape_engine::ops::splat::scene::{frame_params, RenderSettings};
    use drape_shared::splat::layout::MAX_SH_COEFFS;
    use drape_shared::splat::project::{project_fwd, Camera as KernelCamera, Gaussian};

    use super::*;

    /// A camera off every axis, with unequal focal lengths and an off-centre
    /// principal point, so that a swapped or transposed field shows.
    fn camera() -> Camera {
        let mut c = Camera::look_at(
            DVec3::new(1.3, 1.7, 3.1),
            DVec3::new(0.1, 0.9, -0.2),
            DVec3::Y,
            90.0,
            80,
            60,
        );
        (c.fy, c.cx, c.cy) = (84.0, 37.5, 33.0);
        c
    }

    /// The engine's projection of a point: the CPU reference of the projection kernel
    /// (in f64) for a small opaque Gaussian there, through `frame_params`.
    fn engine_projection(cam: &Camera, p: DVec3) -> Option<[f64; 3]> {
        let frame = frame_params(&cam.to_pinhole([0.0; 3]), &RenderSettings::default(), 0, 1);
        let kernel = KernelCamera::<f64>::from_frame(&frame);
        let g = Gaussian {
            mean: p.to_array(),
            log_scale: [0.01f64.ln(); 3],
            quat: [1.0, 0.0, 0.0, 0.0],
            opacity_logit: 5.0,
            sh: [[0.0; 3]; MAX_SH_COEFFS],
        };
        let s = project_fwd(&g, &kernel);
        s.visible.then_some([s.x, s.y, s.depth])
    }

    #[test]
    fn projection_matches_the_engine_cameras() {
        let cam = camera();
        for i in 0..7 {
            for j in 0..5 {
                for k in 0..4 {
                    let p = DVec3::new(
                        -0.9 + 0.3 * f64::from(i),
                        0.3 + 0.3 * f64::from(j),
                        -0.8 + 0.4 * f64::from(k),
                    );
                    let ours = cam
                        .project(p)
                        .expect("every point is in front of the camera");
                    assert!(
                        (0.0..80.0).contains(&ours[0]) && (0.0..60.0).contains(&ours[1]),
                        "{p:?} projects to {ours:?}, outside the image"
                    );
                    let depth = cam.to_camera(p)[2];
                    let [x, y, z] = engine_projection(&cam, p).unwrap_or_else(|| {
                        panic!("the engine culls {p:?}, which projects to {ours:?}")
                    });
                    // The engine's camera is this one rounded to f32 (relative 6e-8 per
                    // field): pixel coordinates under 100 px agree to well under 1e-3 px.
                    assert!(
                        (x - ours[0]).abs() < 1e-3 && (y - ours[1]).abs() < 1e-3,
                        "{p:?}: ours {ours:?}, engine ({x}, {y})"
                    );
                    assert!(
                        (z - depth).abs() < 1e-5 * depth,
                        "{p:?}: depth {depth} against the engine's {z}"
                    );
                }
            }
        }
        // Behind the camera: neither projects.
        let behind = DVec3::new(2.0, 2.0, 5.0);
        assert!(cam.to_camera(behind)[2] < 0.0);
        assert!(cam.project(behind).is_none() && engine_projection(&cam, behind).is_none());
    }

    #[test]
    fn look_at_puts_the_target_at_the_principal_point_and_the_eye_at_the_centre() {
        let (eye, target) = (DVec3::new(1.3, 1.7, 3.1), DVec3::new(0.1, 0.9, -0.2));
        let cam = Camera::look_at(eye, target, DVec3::Y, 90.0, 80, 60);
        let t = cam.project(target).expect("in front");
        assert!(
            (t[0] - 40.0).abs() < 1e-9 && (t[1] - 30.0).abs() < 1e-9,
            "{t:?}"
        );
        let c = cam.centre();
        assert!((0..3).all(|k| (c[k] - eye[k]).abs() < 1e-12), "{c:?}");
        // World up is image up (y down): a point above the target projects higher.
        assert!(cam.project(DVec3::new(0.1, 1.2, -0.2)).expect("in front")[1] < t[1]);
        // Moved, it keeps its intrinsics and is a look-at from the new eye.
        let moved = camera().moved_to(DVec3::new(-2.0, 1.0, 1.0), target, DVec3::Y);
        let fresh = Camera::look_at(DVec3::new(-2.0, 1.0, 1.0), target, DVec3::Y, 90.0, 80, 60);
        assert_eq!(
            (moved.rotation, moved.translation),
            (fresh.rotation, fresh.translation)
        );
        assert_eq!(
            (moved.fx, moved.fy, moved.cx, moved.cy, moved.near),
            (90.0, 84.0, 37.5, 33.0, Camera::NEAR)
        );
    }
}
