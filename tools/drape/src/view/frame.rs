//! The frame loop: what each turn of the event loop does ([`Viewer::tick`]): which motion
//! frame to show ([`Playback`]), its render by the engine into a frame in flight's image
//! and the blit and present of that image, the title's statistics, and after `--frames N`
//! the end or the screenshot's hold.
//!
//! # A frame (slot `s = frame mod K`, K frames in flight)
//!
//! 1. Wait for `fence[s]`: the viewer's command buffer of frame − K has completed, so
//!    `image[s]` is no longer read by its blit (and is back in `TRANSFER_DST_OPTIMAL`,
//!    the layout it keeps between frames), and `acquired[s]` / `render_done[s]` were
//!    consumed by that submission's waits.
//! 2. Acquire a swapchain image, signalling `acquired[s]`.
//! 3. `AvatarPlayer::submit_frame`: the engine records and submits the frame (posing,
//!    splatting, compositing) and copies the premultiplied RGBA into `image[s]`
//!    (`TRANSFER_DST_OPTIMAL`, the `ImageTarget` contract); it signals `render_done[s]`.
//!    It waits on the host only for the player's own frame − K.
//! 4. The viewer's command buffer, waiting on `render_done[s]` and `acquired[s]` at the
//!    `TRANSFER` stage: `image[s]` `TRANSFER_DST → TRANSFER_SRC`, swapchain image
//!    `UNDEFINED → TRANSFER_DST`, `vkCmdBlitImage` (float to the swapchain's UNORM
//!    format, nearest filter, same size), swapchain image `→ PRESENT_SRC`, `image[s]`
//!    back to `TRANSFER_DST`; it signals `present_ready[image]` and `fence[s]`.
//! 5. Present, waiting on `present_ready[image]`.
//!
//! The engine's copy into `image[s]` (a transfer write) is ordered after the previous
//! blit out of it (and the layout transition back) by step 1's fence wait, which the
//! host performs before it calls `submit_frame`.
// `ImageTarget::new` is an `unsafe fn`: the frame's image handed to the engine.
#![allow(unsafe_code)]

use std::time::{Duration, Instant};

use drape_engine::ash::vk;
use drape_engine::{ImageTarget, SubmitSync};
use drape_trainer::avatar::animate::place_pose;
use drape_trainer::dataset::loader::BodyParams;
use drape_trainer::motion::Motion;

use super::Viewer;

/// Which motion frame is shown, and how many frames were rendered.
pub(super) struct Playback {
    pub(super) motion: Motion,
    /// The body each motion frame's pose is placed on.
    anchor_body: BodyParams,
    /// `--frames N`: motion frame k on rendered frame k, and N frames in all.
    pub(super) frames_limit: Option<u32>,
    /// Frames submitted so far (the --screenshot hold's presents included).
    pub(super) frame: u64,
    /// The position in the motion, in frames (fractional while playing by time).
    motion_pos: f64,
    pub(super) playing: bool,
    /// The slot of the latest rendered frame (what the --screenshot hold presents).
    last_slot: usize,
    last_tick: Instant,
}

impl Playback {
    pub(super) fn new(
        motion: Motion,
        anchor_body: BodyParams,
        frames_limit: Option<u32>,
        now: Instant,
    ) -> Self {
        Self {
            motion,
            anchor_body,
            frames_limit,
            frame: 0,
            motion_pos: 0.0,
            playing: true,
            last_slot: 0,
            last_tick: now,
        }
    }

    /// Pauses and moves `by` frames (wrapping around the motion).
    pub(super) fn step(&mut self, by: i64) {
        self.playing = false;
        let n = self.motion.len() as f64;
        self.motion_pos = (self.motion_pos.floor() + by as f64).rem_euclid(n);
    }
}

impl Viewer {
    /// One iteration of the loop; false to quit.
    pub(super) fn tick(&mut self) -> anyhow::Result<bool> {
        let now = Instant::now();
        let dt = now.duration_since(self.playback.last_tick).as_secs_f64();
        self.playback.last_tick = now;
        if let Some(capture) = self.capture.as_ref().filter(|c| c.holding()) {
            if capture.hold_over() {
                return Ok(false);
            }
            self.present(self.playback.last_slot)?;
            std::thread::sleep(Duration::from_millis(30));
            return Ok(true);
        }
        if self.presenter.stale || !self.presenter.has_swapchain() {
            self.presenter.recreate_swapchain(&self.gpu)?;
            if !self.presenter.has_swapchain() {
                std::thread::sleep(Duration::from_millis(20));
                return Ok(true);
            }
        }
        // Motion frame: one per rendered frame with --frames, else by time when playing.
        let p = &mut self.playback;
        let n = p.motion.len();
        let k = if p.frames_limit.is_some() {
            p.frame as usize % n
        } else {
            if p.playing {
                p.motion_pos = (p.motion_pos + dt * p.motion.fps).rem_euclid(n as f64);
            }
            (p.motion_pos.floor() as usize).min(n - 1)
        };
        if !self.render_frame(k)? {
            return Ok(true); // the swapchain was out of date: recreated, try again.
        }
        self.update_title(k);
        if let Some(limit) = self.playback.frames_limit {
            if self.playback.frame >= u64::from(limit) {
                return self.finish_frames();
            }
        }
        Ok(true)
    }

    /// Renders motion frame `k` and presents it. False if the swapchain had to be
    /// recreated before anything was submitted.
    fn render_frame(&mut self, k: usize) -> anyhow::Result<bool> {
        let s = (self.playback.frame % self.presenter.slots.len() as u64) as usize;
        self.presenter.wait_slot(s)?;
        let Some(image_index) = self.presenter.acquire(&self.gpu, s)? else {
            return Ok(false);
        };
        let motion = &self.playback.motion;
        let body = place_pose(
            &self.playback.anchor_body,
            &motion.poses[k],
            motion.translations[k],
        );
        let (width, height) = (self.presenter.width, self.presenter.height);
        self.player.set_body(body.clone());
        let cam = self.orbit.camera(&self.player, &body, width, height);
        let slot = &self.presenter.slots[s];
        // SAFETY: the slot's image is a live image of the engine's device with
        // TRANSFER_DST usage, width x height, 16-byte texels; it is in
        // TRANSFER_DST_OPTIMAL (kept there between frames; the fence wait above
        // ordered the last blit out of it and its transition back before this
        // submission); it lives until the Presenter drops, after the player.
        let target = unsafe {
            ImageTarget::new(
                slot.image,
                vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                width,
                height,
                16,
            )
        };
        let sync = SubmitSync {
            wait: vec![],
            signal: vec![(slot.render_done, 0)],
        };
        let (_, timings) = self
            .player
            .submit_frame(&cam, width, height, &sync, Some(&target))?;
        self.stats.record_timings(timings);
        self.presenter.blit_and_present(s, s, image_index, true)?;
        self.playback.last_slot = s;
        self.playback.frame += 1;
        self.stats.frame_done();
        Ok(true)
    }

    /// Presents `src_slot`'s image again (`--screenshot`'s hold): every frame in flight
    /// is waited for first, so the image is idle and in TRANSFER_DST_OPTIMAL.
    fn present(&mut self, src_slot: usize) -> anyhow::Result<()> {
        self.presenter.wait_all()?;
        if self.presenter.stale {
            self.presenter.recreate_swapchain(&self.gpu)?;
        }
        let s = (self.playback.frame % self.presenter.slots.len() as u64) as usize;
        let Some(i) = self.presenter.acquire(&self.gpu, s)? else {
            return Ok(());
        };
        self.presenter.blit_and_present(s, src_slot, i, false)?;
        self.playback.frame += 1;
        Ok(())
    }

    fn update_title(&mut self, k: usize) {
        let paused = !(self.playback.playing || self.playback.frames_limit.is_some());
        if let Some(title) = self.stats.title(k, self.playback.motion.len(), paused) {
            self.window.set_title(&title);
        }
    }

    /// After `--frames N`: prints the rate; with `--screenshot` writes the library's
    /// render and the `.ready` marker and starts holding the last frame.
    fn finish_frames(&mut self) -> anyhow::Result<bool> {
        let Some(capture) = self.capture.as_mut() else {
            return Ok(false);
        };
        let (width, height) = (self.presenter.width, self.presenter.height);
        let body = self.player.body().clone();
        let cam = self.orbit.camera(&self.player, &body, width, height);
        capture.write_and_hold(&mut self.player, &cam, width, height)?;
        Ok(true)
    }
}
