//! A trained run as a library (what `drape view`, the C ABI and `engine-bench avatar`
//! use): load a run, set a pose (SMPL axis-angles and a translation, or any
//! [`BodyParams`]) and a camera, and record the frame (decoders, skinning, the renders
//! and their composite, premultiplied RGBA) into a recording the player submits with
//! semaphores, or into the host's command buffer, optionally copied into the host's
//! image. Recording submits nothing and waits for nothing: with k frames in flight,
//! frame i waits only for frame i − k ([`drape_engine::FramesInFlight`]).
//!
//! Each frame in flight has its own copy of the avatar (decoders, posed Gaussians,
//! renderers, its RGBA buffer): simple and safe, at k times the model's memory (the
//! decoders' parameters too are copied per frame, not shared). The player lives in the
//! trainer because the run format, the rig and the decoders do; the C ABI (`capi/`)
//! depends on the trainer for it.
//!
//! A frame whose tile intersections outgrew the renderer's buffers is found when its
//! slot comes round again: the buffers have grown by then, the frame is counted in
//! [`AvatarPlayer::overflowed_frames`], and [`AvatarPlayer::render`] renders again.
//!
//! ```no_run
//! use std::path::Path;
//! use drape_engine::{Context, ContextDesc, SubmitSync};
//! use drape_trainer::avatar::player::{AvatarPlayer, ViewCamera};
//! # fn f() -> drape_trainer::Result<()> {
//! let ctx = Context::new(&ContextDesc::default())?;
//! let mut player = AvatarPlayer::load(&ctx, Path::new("runs/me"), 2)?; // 2 frames in flight
//! let camera = ViewCamera::from_camera(player.default_camera());
//! let (w, h) = (player.default_camera().width, player.default_camera().height);
//! let pose = [0.0f32; 72]; // SMPL axis-angles, joint 0 the global orientation
//! player.set_pose(&pose, &[0.0, 0.0, 0.0])?;
//! // Pixels for callers that want them (waits):
//! let rgba = player.render(&camera, w, h)?; // premultiplied RGBA, top row first
//! // A frame loop: one submission a frame, waiting only for the frame two before.
//! for _ in 0..100 {
//!     player.submit_frame(&camera, w, h, &SubmitSync::default(), None)?;
//! }
//! # Ok(()) }
//! ```

use std::path::Path;

use drape_engine::ops::splat::scene::{PinholeCamera, RenderSettings};
use drape_engine::{
    Buffer, BufferDesc, Context, FramesInFlight, HostCommandBuffer, ImageTarget, PassTimings,
    Recording, SubmitSync,
};
use glam::DVec3;

use crate::avatar::composite::AvatarRenderer;
use crate::avatar::file::AvatarFile;
use crate::avatar::model::Avatar;
use crate::avatar::rig::{FrameTransforms, Rig};
use crate::body::kinematics::Pose;
use crate::camera::Camera;
use crate::dataset::loader::BodyParams;
use crate::TrainerError;

/// One frame in flight's resources.
pub struct PlayerFrame {
    avatar: Avatar,
    renderer: AvatarRenderer,
    /// Premultiplied RGBA, 4 floats per pixel, row-major from the top row.
    rgba: Buffer,
    width: u32,
    height: u32,
    compositing: crate::avatar::composite::Compositing,
}

/// A camera for the player: OpenCV axes (x right, y down, z forward), pinhole
/// intrinsics in pixels, a 4x4 world-to-camera matrix (row-major; its last row is
/// `0 0 0 1`) and the near and far planes. The same camera as `drape render --camera`'s
/// JSON (`rotation` = the matrix's upper-left 3x3, `translation` = its last column).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewCamera {
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub world_to_camera: [f32; 16],
    pub near: f32,
    pub far: f32,
}

impl ViewCamera {
    /// The splatter's camera of this one for a `width` x `height` image over black.
    /// Non-finite or non-positive intrinsics and planes, or a matrix whose last row is
    /// not `0 0 0 1`, are an error naming the field.
    pub fn to_pinhole(&self, width: u32, height: u32) -> crate::Result<PinholeCamera> {
        let bad =
            |field: &str, why: &str| TrainerError::invalid("camera", format!("{field}: {why}"));
        for (name, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(bad(
                    name,
                    &format!("{v} (a focal length in pixels, positive)"),
                ));
            }
        }
        if !(self.cx.is_finite() && self.cy.is_finite()) {
            return Err(bad("cx, cy", "not finite"));
        }
        if !(self.near.is_finite()
            && self.far.is_finite()
            && self.near > 0.0
            && self.far > self.near)
        {
            return Err(bad(
                "near, far",
                &format!("{} and {} (0 < near < far)", self.near, self.far),
            ));
        }
        let m = &self.world_to_camera;
        if m.iter().any(|v| !v.is_finite()) || m[12..] != [0.0, 0.0, 0.0, 1.0] {
            return Err(bad(
                "world_to_camera",
                "not finite, or its last row is not 0 0 0 1",
            ));
        }
        if width == 0 || height == 0 {
            return Err(bad("width, height", "at least 1 pixel"));
        }
        Ok(PinholeCamera {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            width,
            height,
            rotation: [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]],
            translation: [m[3], m[7], m[11]],
            near: self.near,
            far: self.far,
            background: [0.0; 3],
        })
    }

    /// The dataset camera as a view camera.
    pub fn from_camera(c: &Camera) -> Self {
        let r = c.rotation;
        let t = c.translation;
        let w2c = [
            r[0][0], r[0][1], r[0][2], t[0], r[1][0], r[1][1], r[1][2], t[1], r[2][0], r[2][1],
            r[2][2], t[2], 0.0, 0.0, 0.0, 1.0,
        ];
        Self {
            fx: c.fx as f32,
            fy: c.fy as f32,
            cx: c.cx as f32,
            cy: c.cy as f32,
            world_to_camera: w2c.map(|v| v as f32),
            near: c.near as f32,
            far: Camera::FAR,
        }
    }
}

/// A trained avatar ready to render frames in flight.
pub struct AvatarPlayer {
    ctx: Context,
    frames: FramesInFlight<PlayerFrame>,
    rig: Rig,
    betas: Vec<f64>,
    body: BodyParams,
    transforms: FrameTransforms,
    settings: RenderSettings,
    /// The file's default camera and body (a run's first held-out frame's).
    default_camera: Camera,
    default_body: BodyParams,
    overflowed: u64,
    rendered: u64,
    /// Per slot: a frame was submitted there whose overflow check is still to be read.
    unfinished: Vec<bool>,
}

impl AvatarPlayer {
    /// Opens an avatar file (`drape export`'s `NAME.avatar`), or a run directory (its
    /// `run.json` names the data it was trained on; it is exported in memory and read
    /// back as a file is, so both load through one path), with `frames_in_flight`
    /// frames in flight (1 to 8), each with its own avatar.
    pub fn load(ctx: &Context, path: &Path, frames_in_flight: usize) -> crate::Result<Self> {
        if !(1..=8).contains(&frames_in_flight) {
            return Err(TrainerError::invalid(
                "frames in flight",
                format!("{frames_in_flight} (1 to 8)"),
            ));
        }
        let file = if path.is_file() {
            AvatarFile::read(path)?
        } else {
            AvatarFile::from_bytes(&AvatarFile::from_run(ctx, path)?.to_bytes()?, path)?
        };
        Self::from_file(ctx, &file, frames_in_flight)
    }

    /// A player of an avatar file already read (see [`load`](Self::load)).
    pub fn from_file(
        ctx: &Context,
        file: &AvatarFile,
        frames_in_flight: usize,
    ) -> crate::Result<Self> {
        if !(1..=8).contains(&frames_in_flight) {
            return Err(TrainerError::invalid(
                "frames in flight",
                format!("{frames_in_flight} (1 to 8)"),
            ));
        }
        let camera = file.default_camera;
        let (width, height) = (camera.width, camera.height);
        let compositing = file.layers_config.compositing;
        let mut slots = Vec::with_capacity(frames_in_flight);
        for k in 0..frames_in_flight {
            let avatar = file.build(ctx)?;
            let renderer = AvatarRenderer::new(ctx, &avatar, width, height, compositing)?;
            let rgba = ctx.create_buffer(
                &format!("player rgba {k}"),
                BufferDesc::gpu_only(16 * u64::from(width) * u64::from(height)),
            )?;
            slots.push(PlayerFrame {
                avatar,
                renderer,
                rgba,
                width,
                height,
                compositing,
            });
        }
        let rig = file.rig();
        let body = file.default_body.clone();
        let transforms = rig.frame(&body);
        Ok(Self {
            ctx: ctx.clone(),
            frames: FramesInFlight::new(slots),
            betas: file.betas.clone(),
            rig,
            body: body.clone(),
            transforms,
            settings: RenderSettings::default(),
            default_camera: camera,
            default_body: body,
            overflowed: 0,
            rendered: 0,
            unfinished: vec![false; frames_in_flight],
        })
    }

    /// Frames in flight at most.
    pub fn frames_in_flight(&self) -> usize {
        self.frames.len()
    }

    /// The run's first held-out frame's camera (its image size is the run's).
    pub fn default_camera(&self) -> &Camera {
        &self.default_camera
    }

    /// The run's first held-out frame's body (the pose a loaded player starts in).
    pub fn default_body(&self) -> &BodyParams {
        &self.default_body
    }

    /// The rig (the body model with the run's shape).
    pub fn rig(&self) -> &Rig {
        &self.rig
    }

    /// Poses the avatar: SMPL axis-angles of the 24 joints in SMPL order (radians; joint
    /// 0 the root's global orientation) and the root translation in metres, with the
    /// run's body shape and scale 1.
    pub fn set_pose(&mut self, pose: &[f32; 72], translation: &[f32; 3]) -> crate::Result<()> {
        if let Some(i) = pose
            .iter()
            .position(|v| !v.is_finite() || v.abs() > 4.0 * std::f32::consts::PI)
        {
            return Err(TrainerError::invalid(
                "pose",
                format!(
                    "value {i} is {} (axis-angles in radians, at most 4π)",
                    pose[i]
                ),
            ));
        }
        if let Some(i) = translation
            .iter()
            .position(|v| !v.is_finite() || v.abs() > 1000.0)
        {
            return Err(TrainerError::invalid(
                "translation",
                format!("value {i} is {} (metres, at most 1 km)", translation[i]),
            ));
        }
        let p: Pose = std::array::from_fn(|j| {
            DVec3::from_array(std::array::from_fn(|c| f64::from(pose[3 * j + c])))
        });
        self.set_body(BodyParams::Smpl {
            pose: p,
            betas: self.betas.clone(),
            translation: DVec3::from_array(translation.map(f64::from)),
            scale: 1.0,
        });
        Ok(())
    }

    /// Poses the avatar with a dataset's body parameters (a motion frame placed by
    /// `avatar::animate::place_pose`, or a frame of the run's sequence).
    pub fn set_body(&mut self, body: BodyParams) {
        self.transforms = self.rig.frame(&body);
        self.body = body;
    }

    /// The current body parameters.
    pub fn body(&self) -> &BodyParams {
        &self.body
    }

    /// Frames found to have outgrown their renderer's intersection buffers (each drawn
    /// from a truncated list; the buffers have grown since).
    pub fn overflowed_frames(&self) -> u64 {
        self.overflowed
    }

    /// Frames recorded so far.
    pub fn frames_recorded(&self) -> u64 {
        self.rendered
    }

    /// Waits for the slot the next frame records into, reads its last frame's overflow
    /// check, and sizes it for `width` x `height` (recreating its renderer on a change).
    fn prepare_slot(
        &mut self,
        width: u32,
        height: u32,
    ) -> crate::Result<(usize, Option<PassTimings>)> {
        let ctx = self.ctx.clone();
        let (i, frame, timings) = self.frames.next_slot()?;
        let timings = timings.cloned();
        if std::mem::take(&mut self.unfinished[i]) && frame.renderer.finish_frame()? {
            self.overflowed += 1;
        }
        if (frame.width, frame.height) != (width, height) {
            frame.renderer =
                AvatarRenderer::new(&ctx, &frame.avatar, width, height, frame.compositing)?;
            frame.rgba = ctx.create_buffer(
                &format!("player rgba {i}"),
                BufferDesc::gpu_only(16 * u64::from(width) * u64::from(height)),
            )?;
            (frame.width, frame.height) = (width, height);
        }
        Ok((i, timings))
    }

    /// The recording of one frame into the slot's resources.
    fn record<'r>(
        ctx: &Context,
        frame: &'r mut PlayerFrame,
        transforms: &FrameTransforms,
        camera: &PinholeCamera,
        settings: &RenderSettings,
        target: Option<&ImageTarget>,
    ) -> drape_engine::Result<Recording<'r>> {
        frame
            .renderer
            .prepare_frame(&frame.avatar, camera, settings)?;
        let frame: &'r PlayerFrame = frame;
        let mut rec = ctx.record("avatar frame")?;
        frame.avatar.record_set_frame(&mut rec, transforms);
        frame
            .avatar
            .record_forward(&mut rec, transforms.log_scale)?;
        frame.renderer.record_frame(&mut rec, &frame.avatar)?;
        frame.renderer.record_rgba(&mut rec, &frame.rgba)?;
        if let Some(t) = target {
            rec.copy_to_image(&frame.rgba, t);
        }
        Ok(rec)
    }

    /// Records the current pose through `camera` into the next frame in flight and
    /// submits it with `sync`'s semaphores, copying the premultiplied RGBA into `target`
    /// (an `R32G32B32A32_SFLOAT` image of the camera's size) if given. Waits only for
    /// the frame that last used the slot. Returns the slot and that earlier frame's GPU
    /// times.
    pub fn submit_frame(
        &mut self,
        camera: &ViewCamera,
        width: u32,
        height: u32,
        sync: &SubmitSync,
        target: Option<&ImageTarget>,
    ) -> crate::Result<(usize, Option<PassTimings>)> {
        let pinhole = camera.to_pinhole(width, height)?;
        if let Some(t) = target {
            check_target(t, width, height)?;
        }
        let (_, timings) = self.prepare_slot(width, height)?;
        let (ctx, transforms, settings) = (self.ctx.clone(), &self.transforms, self.settings);
        let slot = self.frames.submit(sync, |frame| {
            Self::record(&ctx, frame, transforms, &pinhole, &settings, target)
        })?;
        self.unfinished[slot] = true;
        self.rendered += 1;
        Ok((slot, timings))
    }

    /// As [`submit_frame`](Self::submit_frame), but recorded into the host's command
    /// buffer, which the host submits (its work must complete before this player records
    /// [`frames_in_flight`](Self::frames_in_flight) frames more, and before the player is
    /// dropped: [`HostCommandBuffer::new`]'s contract).
    pub fn record_frame_into(
        &mut self,
        camera: &ViewCamera,
        width: u32,
        height: u32,
        host: &HostCommandBuffer,
        target: Option<&ImageTarget>,
    ) -> crate::Result<usize> {
        let pinhole = camera.to_pinhole(width, height)?;
        if let Some(t) = target {
            check_target(t, width, height)?;
        }
        self.prepare_slot(width, height)?;
        let (ctx, transforms, settings) = (self.ctx.clone(), &self.transforms, self.settings);
        let slot = self.frames.record_into(host, |frame| {
            Self::record(&ctx, frame, transforms, &pinhole, &settings, target)
        })?;
        self.unfinished[slot] = true;
        self.rendered += 1;
        Ok(slot)
    }

    /// Renders the current pose through `camera` and reads it back: `width` x `height` x
    /// 4 floats, premultiplied RGBA (alpha within [0, 1], each colour value within
    /// [0, alpha]: [`clamp_premultiplied`]), row-major from the top row. Waits for every frame in
    /// flight (a convenience for callers that want pixels, not a frame loop; frames
    /// recorded into the host's command buffers must have completed). A frame that
    /// outgrew its renderer's buffers is rendered again in the same slot, whose buffers
    /// have grown.
    pub fn render(
        &mut self,
        camera: &ViewCamera,
        width: u32,
        height: u32,
    ) -> crate::Result<Vec<f32>> {
        loop {
            let (slot, _) =
                self.submit_frame(camera, width, height, &SubmitSync::default(), None)?;
            self.unfinished[slot] = false;
            let frame = self.frames.all_mut()?.nth(slot).expect("the slot exists");
            if frame.renderer.finish_frame()? {
                self.overflowed += 1;
                self.frames.set_next(slot);
                continue;
            }
            let pixels = 4 * width as usize * height as usize;
            let mut rgba = self.ctx.read_buffer(&mut frame.rgba, pixels)?;
            clamp_premultiplied(&mut rgba);
            return Ok(rgba);
        }
    }

    /// Gives up the frame [`record_frame_into`](Self::record_frame_into) recorded into
    /// slot `slot` when the host will not submit its command buffer after all (it could
    /// not acquire or present an image, say): the slot is free again at once, and the
    /// frame's overflow counters are not read (the frame never ran). The host must not
    /// submit that command buffer afterwards. Returns whether the slot held such a frame.
    pub fn abandon_frame(&mut self, slot: usize) -> crate::Result<bool> {
        let abandoned = self.frames.abandon(slot)?;
        if abandoned {
            self.unfinished[slot] = false;
            self.rendered = self.rendered.saturating_sub(1);
        }
        Ok(abandoned)
    }

    /// Waits for every frame in flight.
    pub fn wait_idle(&mut self) -> crate::Result<()> {
        Ok(self.frames.wait_all()?)
    }
}

/// Makes premultiplied RGBA what [`AvatarPlayer::render`] promises: alpha within
/// [0, 1], each colour value within [0, alpha]. The spherical-harmonic colours are not
/// clamped on the GPU, so a composite can exceed its alpha (frames recorded into a host's
/// image are not clamped). Values already in range keep their bits; NaN becomes 0.
pub fn clamp_premultiplied(rgba: &mut [f32]) {
    // `!(v >= lo)` rather than `v < lo`: NaN fails the guard and becomes `lo`.
    let within = |v: f32, hi: f32| {
        if !(v >= 0.0) {
            0.0
        } else if v > hi {
            hi
        } else {
            v
        }
    };
    for p in rgba.chunks_exact_mut(4) {
        let a = within(p[3], 1.0);
        p[3] = a;
        for c in &mut p[..3] {
            *c = within(*c, a);
        }
    }
}

fn check_target(t: &ImageTarget, width: u32, height: u32) -> crate::Result<()> {
    if t.size() != (width, height) {
        return Err(TrainerError::invalid(
            "target image",
            format!(
                "{}x{}, but the frame is {width}x{height}",
                t.size().0,
                t.size().1
            ),
        ));
    }
    Ok(())
}

/// The dataset's camera of `body`'s frame pose, for tests and the viewer: a pose as the
/// 72 floats [`AvatarPlayer::set_pose`] takes, and the translation, of an SMPL body.
pub fn smpl_pose_of(body: &BodyParams) -> Option<([f32; 72], [f32; 3])> {
    match body {
        BodyParams::Smpl {
            pose, translation, ..
        } => {
            let mut p = [0f32; 72];
            for (j, a) in pose.iter().enumerate() {
                for c in 0..3 {
                    p[3 * j + c] = a[c] as f32;
                }
            }
            Some((p, translation.as_vec3().to_array()))
        }
        BodyParams::Zju(_) => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Colour over alpha, negative and NaN values are clamped; values in range (-0.0
    /// too) keep their bits.
    #[test]
    fn premultiplied_clamp() {
        let mut px = [
            1.3,
            0.5,
            -0.1,
            1.0, //
            0.2,
            0.3,
            0.4,
            0.25, //
            f32::NAN,
            0.1,
            0.0,
            1.5, //
            -0.0,
            0.1,
            0.2,
            0.3, //
            0.1,
            0.1,
            0.1,
            f32::NAN,
        ];
        clamp_premultiplied(&mut px);
        let expected = [
            1.0, 0.5, 0.0, 1.0, //
            0.2, 0.25, 0.25, 0.25, //
            0.0, 0.1, 0.0, 1.0, //
            -0.0, 0.1, 0.2, 0.3, //
            0.0, 0.0, 0.0, 0.0,
        ];
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&px), bits(&expected), "{px:?}");
    }
}
