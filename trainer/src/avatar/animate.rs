//! Animating a trained avatar (`drape animate`): the avatar posed by a motion it was
//! not trained on, seen from a camera orbiting it, written as a PNG per frame and an
//! animated GIF.
//!
//! The motion is placed where the run's first held-out frame puts the person (its root
//! rotation, translation and scale, or ZJU-MoCap's `Rh`, `Th`): the motion's root
//! rotation turns the person about that frame's root, and the motion's translation is
//! carried into that frame's world. The camera starts where that frame's camera is, keeps
//! its height and distance from the pelvis, circles the body's up axis and looks at the
//! pelvis of each frame, so a walking person stays in view.

use std::path::Path;
use std::time::Instant;

use drape_engine::ops::splat::scene::RenderSettings;
use glam::DVec3;

use crate::avatar::run::OpenRun;
use crate::body::kinematics::{rodrigues, Pose, M3};
use crate::camera::Camera;
use crate::dataset::loader::{BodyParams, DatasetFrame};
use crate::mesh::rotation_to_quaternion;
use crate::motion::Motion;
use crate::TrainerError;

/// How the animation is made.
#[derive(Clone, Debug)]
pub struct AnimateOptions {
    /// Frames to render (at most the motion's).
    pub frames: usize,
    /// Degrees the camera circles over the whole animation (0: it stays put).
    pub orbit_degrees: f64,
    /// Background colour where nothing is rendered.
    pub background: [f32; 3],
    /// Also write `animation.gif`.
    pub gif: bool,
}

/// What [`animate`] did.
#[derive(Clone, Debug, serde::Serialize)]
pub struct AnimateReport {
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    /// Per frame: posing (decoders, skinning) + rendering + reading the image back, ms.
    pub frame_ms: Vec<f64>,
    pub mean_ms: f64,
    pub fps: f64,
}

fn matmul(a: &M3, b: &M3) -> M3 {
    std::array::from_fn(|r| std::array::from_fn(|c| (0..3).map(|k| a[r][k] * b[k][c]).sum()))
}

fn mat_vec(a: &M3, v: DVec3) -> DVec3 {
    DVec3::from_array(a.map(|row| DVec3::from_array(row).dot(v)))
}

/// The axis-angle vector of a rotation matrix (the inverse of `rodrigues`).
pub fn axis_angle(m: &M3) -> DVec3 {
    let q = rotation_to_quaternion(m);
    let v = DVec3::new(q[1], q[2], q[3]);
    let s = v.length();
    if s < 1e-12 {
        return DVec3::ZERO;
    }
    v * (2.0 * s.atan2(q[0]) / s)
}

/// The body of `anchor` in the motion's pose `pose` moved by `trans` (see the module
/// header).
pub fn place_pose(anchor: &BodyParams, pose: &Pose, trans: DVec3) -> BodyParams {
    match anchor {
        BodyParams::Smpl {
            pose: p0,
            betas,
            translation,
            scale: s,
        } => {
            let r0 = rodrigues(p0[0]);
            let mut p = *pose;
            p[0] = axis_angle(&matmul(&r0, &rodrigues(pose[0])));
            BodyParams::Smpl {
                pose: p,
                betas: betas.clone(),
                translation: *translation + mat_vec(&r0, trans) * *s,
                scale: *s,
            }
        }
        BodyParams::Zju(z) => {
            let r0 = rodrigues(DVec3::from_array(z.rh));
            let mut z = z.clone();
            for (j, q) in pose.iter().enumerate().skip(1) {
                z.poses[3 * j..3 * j + 3].copy_from_slice(&q.to_array());
            }
            z.rh = axis_angle(&matmul(&r0, &rodrigues(pose[0]))).to_array();
            z.th = (DVec3::from_array(z.th) + mat_vec(&r0, trans)).to_array();
            BodyParams::Zju(z)
        }
    }
}

/// The pelvis in the world and the body's up axis for a frame's transforms (24 × 3x4).
pub fn pelvis_and_up(transforms: &[f32], rest_pelvis: DVec3) -> (DVec3, DVec3) {
    let t = |r: usize, c: usize| f64::from(transforms[4 * r + c]);
    let pelvis = DVec3::from_array(std::array::from_fn(|r| {
        t(r, 0) * rest_pelvis[0] + t(r, 1) * rest_pelvis[1] + t(r, 2) * rest_pelvis[2] + t(r, 3)
    }));
    (
        pelvis,
        DVec3::new(t(0, 1), t(1, 1), t(2, 1)).normalize_or(DVec3::Z),
    )
}

/// `v` turned by `angle` (radians) about the unit axis `k` (Rodrigues' formula).
fn rotate_about(v: DVec3, k: DVec3, angle: f64) -> DVec3 {
    let (s, c) = angle.sin_cos();
    v * c + k.cross(v) * s + k * (k.dot(v) * (1.0 - c))
}

/// The orbit's camera for a frame: `start`'s height and distance from the anchor's
/// pelvis, turned by `angle` about `up`, looking at `pelvis`.
fn orbit_camera(
    start: &Camera,
    anchor_pelvis: DVec3,
    up: DVec3,
    pelvis: DVec3,
    angle: f64,
) -> Camera {
    let offset = start.centre() - anchor_pelvis;
    let h = offset.dot(up);
    let radial = offset - up * h;
    let eye = pelvis + up * h + rotate_about(radial, up, angle);
    start.moved_to(eye, pelvis, up)
}

/// Renders `motion` on the run's avatar into `out` (which must exist): `frameNNNN.png`
/// per frame and, with `options.gif`, `animation.gif` at the motion's frame rate.
pub fn animate(
    ctx: &drape_engine::Context,
    run: &mut OpenRun,
    motion: &Motion,
    options: &AnimateOptions,
    out: &Path,
    progress: &mut dyn FnMut(usize, usize),
) -> crate::Result<AnimateReport> {
    let anchor: &DatasetFrame = run
        .test_frames()
        .first()
        .copied()
        .or_else(|| run.seq.frames.first())
        .ok_or_else(|| TrainerError::run(&run.dir, "the run's sequence has no frames"))?;
    let (anchor_body, start_camera) = (anchor.body.clone(), anchor.camera);
    let mut target = AnimateTarget {
        avatar: &mut run.avatar,
        renderer: &mut run.renderer,
        rig: &run.rig,
        anchor_body: &anchor_body,
        camera: start_camera,
    };
    animate_avatar(ctx, &mut target, motion, options, out, progress)
}

/// What [`animate_avatar`] renders: an avatar and its renderer (of the camera's size),
/// its rig, and the body and camera the motion and the orbit start from (a run's
/// first held-out frame's, or an avatar file's defaults).
pub struct AnimateTarget<'a> {
    pub avatar: &'a mut crate::avatar::model::Avatar,
    pub renderer: &'a mut crate::avatar::composite::AvatarRenderer,
    pub rig: &'a crate::avatar::rig::Rig,
    pub anchor_body: &'a crate::dataset::loader::BodyParams,
    pub camera: crate::camera::Camera,
}

/// [`animate`] of any avatar (a run's, or an avatar file's).
pub fn animate_avatar(
    ctx: &drape_engine::Context,
    run: &mut AnimateTarget<'_>,
    motion: &Motion,
    options: &AnimateOptions,
    out: &Path,
    progress: &mut dyn FnMut(usize, usize),
) -> crate::Result<AnimateReport> {
    let frames = options.frames.min(motion.len());
    if frames == 0 {
        return Err(TrainerError::invalid("motion", "the motion has no frames"));
    }
    let (anchor_body, start_camera) = (run.anchor_body.clone(), run.camera);
    let (width, height) = (start_camera.width, start_camera.height);
    let rest_pelvis = run.rig.rest_joints()[0];
    let (anchor_pelvis, up) = pelvis_and_up(&run.rig.frame(&anchor_body).transforms, rest_pelvis);
    let settings = RenderSettings::default();
    let mut frame_ms = Vec::with_capacity(frames);
    let mut images = Vec::with_capacity(if options.gif { frames } else { 0 });
    for k in 0..frames {
        progress(k, frames);
        let body = place_pose(&anchor_body, &motion.poses[k], motion.translations[k]);
        let ft = run.rig.frame(&body);
        let (pelvis, _) = pelvis_and_up(&ft.transforms, rest_pelvis);
        let angle = options.orbit_degrees.to_radians() * k as f64 / frames as f64;
        let cam = orbit_camera(&start_camera, anchor_pelvis, up, pelvis, angle);
        let t0 = Instant::now();
        run.avatar.set_frame(ctx, &ft)?;
        {
            let mut rec = ctx.record("animate forward")?;
            run.avatar.record_forward(&mut rec, ft.log_scale)?;
            rec.submit_and_wait()?;
        }
        run.renderer.forward(
            ctx,
            run.avatar,
            &cam.to_pinhole(options.background),
            &settings,
        )?;
        let rgb = run.renderer.read_rgb(ctx)?;
        frame_ms.push(t0.elapsed().as_secs_f64() * 1e3);
        crate::dataset::image::write_rgb(
            &out.join(format!("frame{k:04}.png")),
            width,
            height,
            &rgb,
        )?;
        if options.gif {
            images.push(rgb);
        }
    }
    if options.gif {
        write_gif(
            &out.join("animation.gif"),
            width,
            height,
            &images,
            motion.fps,
        )?;
    }
    let mean_ms = frame_ms.iter().sum::<f64>() / frames as f64;
    Ok(AnimateReport {
        frames,
        width,
        height,
        frame_ms,
        mean_ms,
        fps: 1e3 / mean_ms.max(1e-9),
    })
}

/// An endlessly looping GIF of HWC RGB images in [0, 1] at `fps` (each frame's 256
/// colours chosen by the `gif` crate's NeuQuant), written to a temporary file and renamed.
pub fn write_gif(
    path: &Path,
    width: u32,
    height: u32,
    images: &[Vec<f32>],
    fps: f64,
) -> crate::Result<()> {
    let (Ok(w), Ok(h)) = (u16::try_from(width), u16::try_from(height)) else {
        return Err(TrainerError::invalid(
            "GIF size",
            format!(
                "{}: {width} x {height}, but a GIF is at most 65535 x 65535",
                path.display()
            ),
        ));
    };
    // The gif crate's errors are I/O errors or frames it cannot encode; the latter
    // travel out of the writer as invalid data.
    let err = |e: gif::EncodingError| match e {
        gif::EncodingError::Io(e) => e,
        gif::EncodingError::Format(e) => std::io::Error::new(std::io::ErrorKind::InvalidData, e),
    };
    drape_io::write_with(path, |file| {
        let mut encoder = gif::Encoder::new(file, w, h, &[]).map_err(err)?;
        encoder.set_repeat(gif::Repeat::Infinite).map_err(err)?;
        // GIF delays are in hundredths of a second.
        let delay = (100.0 / fps.max(1.0)).round().clamp(2.0, 65535.0) as u16;
        for rgb in images {
            let bytes: Vec<u8> = rgb
                .iter()
                .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
                .collect();
            let mut frame = gif::Frame::from_rgb_speed(w, h, &bytes, 10);
            frame.delay = delay;
            encoder.write_frame(&frame).map_err(err)?;
        }
        // The trailer, written here so that a failure is seen.
        encoder.into_inner().map(|_| ())
    })
    .map_err(|e| TrainerError::io(path, e))
}
