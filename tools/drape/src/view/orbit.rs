//! Orbit input: what the window's events mean to the viewer (Escape or closing quits,
//! space plays or pauses, Left / Right step a frame, a left-drag orbits the camera about
//! the pelvis) and the camera that follows from them: the run's default with `--frames`,
//! else the default turned about the body's pelvis by the drag.

use drape_trainer::avatar::animate::pelvis_and_up;
use drape_trainer::avatar::player::{AvatarPlayer, ViewCamera};
use drape_trainer::dataset::loader::BodyParams;
use glam::DVec3;
use winit::event::{ElementState, MouseButton, WindowEvent};
use winit::keyboard::{Key, NamedKey};

/// What an event asks of the viewer, beyond the orbit it updates itself.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Action {
    Quit,
    /// Play or pause the motion.
    TogglePlay,
    /// Step the motion by this many frames (and pause).
    Step(i64),
    /// The window changed size: the swapchain must be made again.
    Resized,
}

/// The orbit camera's state: the drag so far and the anchor it turns about.
pub(super) struct Orbit {
    /// `--frames`: the run's default camera, whatever the mouse does.
    fixed: bool,
    /// The default body's pelvis and up direction: the camera's default view of them is
    /// what the orbit turns.
    anchor_pelvis: DVec3,
    up: DVec3,
    dragging: bool,
    cursor: Option<(f64, f64)>,
    yaw: f64,
    pitch: f64,
}

impl Orbit {
    /// An orbit about `anchor_body`'s pelvis (the player's default body), not yet turned.
    pub(super) fn new(player: &AvatarPlayer, anchor_body: &BodyParams, fixed: bool) -> Self {
        let rest_pelvis = player.rig().rest_joints()[0];
        let (anchor_pelvis, up) =
            pelvis_and_up(&player.rig().frame(anchor_body).transforms, rest_pelvis);
        Self {
            fixed,
            anchor_pelvis,
            up,
            dragging: false,
            cursor: None,
            yaw: 0.0,
            pitch: 0.0,
        }
    }

    /// Takes a window event: mouse events turn the orbit; keys and window changes come
    /// back as the [`Action`] they ask for.
    pub(super) fn event(&mut self, event: &WindowEvent) -> Option<Action> {
        match event {
            WindowEvent::CloseRequested => Some(Action::Quit),
            WindowEvent::KeyboardInput { event, .. } if event.state == ElementState::Pressed => {
                match event.logical_key {
                    Key::Named(NamedKey::Escape) => Some(Action::Quit),
                    Key::Named(NamedKey::Space) if !event.repeat => Some(Action::TogglePlay),
                    Key::Named(NamedKey::ArrowRight) => Some(Action::Step(1)),
                    Key::Named(NamedKey::ArrowLeft) => Some(Action::Step(-1)),
                    _ => None,
                }
            }
            WindowEvent::MouseInput {
                state,
                button: MouseButton::Left,
                ..
            } => {
                self.dragging = *state == ElementState::Pressed;
                None
            }
            WindowEvent::CursorMoved { position, .. } => {
                if let (true, Some((x, y))) = (self.dragging, self.cursor) {
                    self.yaw -= (position.x - x) * 0.01;
                    self.pitch = (self.pitch + (position.y - y) * 0.01).clamp(-1.3, 1.3);
                }
                self.cursor = Some((position.x, position.y));
                None
            }
            WindowEvent::Resized(_) => Some(Action::Resized),
            _ => None,
        }
    }

    /// The camera: the run's default with --frames; else orbiting the pelvis. Its
    /// intrinsics are scaled from the run's image size to `width` x `height`.
    pub(super) fn camera(
        &self,
        player: &AvatarPlayer,
        body: &BodyParams,
        width: u32,
        height: u32,
    ) -> ViewCamera {
        let start = *player.default_camera();
        let cam = if self.fixed {
            start
        } else {
            let rest_pelvis = player.rig().rest_joints()[0];
            let (pelvis, _) = pelvis_and_up(&player.rig().frame(body).transforms, rest_pelvis);
            let up = self.up;
            let offset = start.centre() - self.anchor_pelvis;
            let dist = offset.dot(offset).sqrt();
            let h = offset.dot(up);
            let radial = offset - up * h;
            let radial_len = radial.dot(radial).sqrt();
            let elevation = (h.atan2(radial_len) + self.pitch).clamp(-1.4, 1.4);
            let dir = radial.normalize_or(DVec3::Z);
            // Turn `dir` by yaw about `up` (Rodrigues; dir ⟂ up).
            let (s, c) = self.yaw.sin_cos();
            let dir = dir * c + up.cross(dir) * s;
            let eye = pelvis + (up * (dist * elevation.sin()) + dir * (dist * elevation.cos()));
            start.moved_to(eye, pelvis, up)
        };
        let mut v = ViewCamera::from_camera(&cam);
        if (width, height) != (start.width, start.height) {
            let (sx, sy) = (
                width as f32 / start.width as f32,
                height as f32 / start.height as f32,
            );
            v.fx *= sx;
            v.cx *= sx;
            v.fy *= sy;
            v.cy *= sy;
        }
        v
    }
}
