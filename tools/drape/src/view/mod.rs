//! `drape view RUN`: a real-time viewer of a trained run, built the way an application
//! that embeds the engine builds it: the viewer owns the window and every Vulkan object
//! of its own, and lends its device to the engine.
//!
//! This file holds the command (its options, the event loop) and the [`Viewer`] that
//! ties the parts together; the parts are:
//!
//! - `device`: the instance, surface and device ([`device::Gpu`]), and the engine's
//!   context over them;
//! - `swapchain`: the swapchain and the frames in flight ([`swapchain::Presenter`]);
//! - `frame`: the frame loop, and the order of a frame's waits and signals;
//! - `orbit`: what keys and the mouse do, and the camera that follows;
//! - `capture`: the `--screenshot` protocol;
//! - `stats`: the title's frame rate and GPU times, and the final summary.
//!
//! # Who owns what
//!
//! - The viewer creates the `winit` window, the Vulkan instance (API 1.2; with
//!   `VK_LAYER_KHRONOS_validation` and synchronization validation when
//!   `DRAPE_VALIDATION=1` or `--validation`; `VK_EXT_debug_utils` with a messenger of its
//!   own that prints every validation message as `validation: ...` and makes the exit
//!   status non-zero), the surface (`VK_KHR_xlib_surface`, or `VK_KHR_xcb_surface` if the
//!   window system hands out an XCB handle), the device (with what
//!   [`drape_engine::device_requirements`] asks for, plus `VK_KHR_swapchain`), one queue
//!   of a family with graphics, compute and present, the swapchain, and per frame in
//!   flight an `R32G32B32A32_SFLOAT` image, its memory, a command buffer, a fence and
//!   two binary semaphores (`render_done`, `acquired`), plus one `present_ready`
//!   semaphore per swapchain image.
//! - The engine borrows instance, device and queue through
//!   [`drape_engine::Context::from_raw`] and never destroys them. The viewer drops the
//!   player and the context first (they wait for their own submissions), then its
//!   swapchain and frames in flight (after waiting for the device to go idle), then the
//!   device and the instance, then the window: the order of [`Viewer`]'s fields.
//!
//! # Modes
//!
//! Interactive: space plays or pauses the motion, Left / Right step a frame, a left-drag
//! orbits the camera about the pelvis, Escape quits; the title shows FPS and the GPU
//! time per scope of the latest completed frame. `--frames N` renders N frames (motion
//! frame k on frame k, the run's default camera) and exits, printing the FPS; with
//! `--screenshot S.png` it then writes the library's render of the last frame
//! (`AvatarPlayer::render`, over black) to S.png, creates `S.png.ready`, and keeps
//! presenting the last frame until `S.png.done` appears (or 30 s pass), so that a test
//! can capture the X window and compare the two.

mod capture;
mod device;
mod frame;
mod orbit;
mod stats;
mod swapchain;

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{anyhow, bail};
use drape_engine::Context;
use drape_trainer::avatar::player::AvatarPlayer;
use drape_trainer::motion::{procedural, Motion, MotionKind};
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::WindowEvent;
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::window::{Window, WindowId};

use capture::Capture;
use device::{Gpu, X11Window, VALIDATION};
use frame::Playback;
use orbit::{Action, Orbit};
use stats::Stats;
use swapchain::Presenter;

/// Options of `drape view`.
#[derive(Clone, Debug, clap::Args)]
pub struct ViewArgs {
    /// The run directory (`drape train --out`, or `drape edit --out`), or an avatar
    /// file (`drape export`).
    pub run: PathBuf,
    /// walk, run (= jog), jog, raise-arms, turn, or a motion file (.npz, as `drape animate`).
    #[arg(long, default_value = "walk")]
    pub motion: String,
    /// Render this many frames at the default camera, print the frame rate and exit.
    #[arg(long, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    pub frames: Option<u32>,
    /// With --frames: write the library's render of the last frame to this PNG (16-bit
    /// RGB, over black), create PNG.ready and keep the window presenting that frame
    /// until PNG.done exists (at most 30 s).
    #[arg(long, requires = "frames")]
    pub screenshot: Option<PathBuf>,
    /// Frames in flight (1 to 8).
    #[arg(long, allow_negative_numbers = true, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=8))]
    pub frames_in_flight: u32,
    /// Render (and window) size WxH (default: the run's image size).
    #[arg(long)]
    pub size: Option<String>,
}

fn parse_size(s: &str) -> anyhow::Result<(u32, u32)> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| anyhow!("--size {s}: expected WxH, e.g. 640x480"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .ok()
            .filter(|&n| (1..=8192).contains(&n))
    };
    match (parse(w), parse(h)) {
        (Some(w), Some(h)) => Ok((w, h)),
        _ => bail!("--size {s}: width and height from 1 to 8192 expected, as WxH"),
    }
}

fn load_motion(spec: &str, min_frames: usize) -> anyhow::Result<Motion> {
    let kind = if spec == "run" {
        Some(MotionKind::Jog)
    } else {
        MotionKind::parse(spec)
    };
    match kind {
        Some(kind) => Ok(procedural(kind, min_frames.max(120), 30.0, 1.0)),
        None => {
            let path = PathBuf::from(spec);
            anyhow::ensure!(
                path.is_file(),
                "--motion {spec}: neither walk, run, jog, raise-arms, turn nor a motion file"
            );
            let m = Motion::load_npz(&path)?;
            anyhow::ensure!(
                !m.is_empty(),
                "{}: the motion has no frames",
                path.display()
            );
            Ok(m)
        }
    }
}

pub fn run(device: &drape_cli_support::DeviceArgs, args: &ViewArgs) -> anyhow::Result<()> {
    let size = args.size.as_deref().map(parse_size).transpose()?;
    let motion = load_motion(&args.motion, args.frames.unwrap_or(0) as usize)?;
    if args.run.is_file() {
        // Read once before the window opens, so that a damaged file is one error naming
        // it (without a window system too), not a window that closes.
        drape_trainer::avatar::file::AvatarFile::read(&args.run)?;
    } else {
        anyhow::ensure!(
            args.run.join("run.json").is_file(),
            "{}: neither an avatar file nor a run directory (no run.json)",
            args.run.display()
        );
    }
    let validation = device.validation || std::env::var("DRAPE_VALIDATION").is_ok_and(|v| v == "1");
    let device_name = device
        .device
        .clone()
        .or_else(|| std::env::var("DRAPE_DEVICE").ok().filter(|s| !s.is_empty()));
    let event_loop = EventLoop::new().map_err(|e| {
        anyhow!("cannot open the window system (is DISPLAY set to a running X server?): {e}")
    })?;
    event_loop.set_control_flow(ControlFlow::Poll);
    let mut app = App {
        args: args.clone(),
        size,
        motion: Some(motion),
        validation,
        device_name,
        viewer: None,
        error: None,
    };
    let result = event_loop.run_app(&mut app);
    // Engine objects first, then the viewer's device and instance (Viewer's Drop).
    let summary = app.viewer.take().map(|v| v.summary());
    if let Some(e) = app.error.take() {
        return Err(e);
    }
    result.map_err(|e| anyhow!("event loop: {e}"))?;
    let messages = VALIDATION.drain().len();
    anyhow::ensure!(
        messages == 0,
        "{messages} validation message(s) (printed above as validation: ...)"
    );
    if let Some(s) = summary {
        println!("{s}");
    }
    Ok(())
}

struct App {
    args: ViewArgs,
    size: Option<(u32, u32)>,
    motion: Option<Motion>,
    validation: bool,
    device_name: Option<String>,
    viewer: Option<Viewer>,
    error: Option<anyhow::Error>,
}

impl App {
    fn fail(&mut self, el: &ActiveEventLoop, e: anyhow::Error) {
        if self.error.is_none() {
            self.error = Some(e);
        }
        el.exit();
    }
}

impl ApplicationHandler for App {
    fn resumed(&mut self, el: &ActiveEventLoop) {
        if self.viewer.is_some() || self.error.is_some() {
            return;
        }
        let Some(motion) = self.motion.take() else {
            return;
        };
        match Viewer::new(
            el,
            &self.args,
            self.size,
            motion,
            self.validation,
            self.device_name.as_deref(),
        ) {
            Ok(v) => self.viewer = Some(v),
            Err(e) => self.fail(el, e),
        }
    }

    fn window_event(&mut self, el: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        let Some(v) = self.viewer.as_mut() else {
            return;
        };
        match v.orbit.event(&event) {
            Some(Action::Quit) => el.exit(),
            Some(Action::TogglePlay) => v.playback.playing = !v.playback.playing,
            Some(Action::Step(by)) => v.playback.step(by),
            Some(Action::Resized) => v.presenter.stale = true,
            None => {}
        }
    }

    fn about_to_wait(&mut self, el: &ActiveEventLoop) {
        let Some(v) = self.viewer.as_mut() else {
            return;
        };
        match v.tick() {
            Ok(true) => {}
            Ok(false) => el.exit(),
            Err(e) => self.fail(el, e),
        }
    }
}

/// The viewer: the engine's player on the viewer's own device, window and swapchain.
struct Viewer {
    // Dropped in this order (fields drop as declared): the engine (the player waits for
    // its frames in flight, the context frees its buffers, pipelines and pools), then
    // the objects on the viewer's device, the device and the instance, and the window
    // last, after the surface made for it.
    player: AvatarPlayer,
    /// Kept for the player, which runs on it.
    _ctx: Context,
    presenter: Presenter,
    gpu: Gpu,
    window: Window,
    playback: Playback,
    orbit: Orbit,
    /// `--screenshot`.
    capture: Option<Capture>,
    stats: Stats,
}

impl Viewer {
    fn new(
        el: &ActiveEventLoop,
        args: &ViewArgs,
        size: Option<(u32, u32)>,
        motion: Motion,
        validation: bool,
        device_name: Option<&str>,
    ) -> anyhow::Result<Self> {
        // The window first (the surface extension depends on its handle), at the run's
        // size; the run's size is only known from the player, so a provisional size here
        // when --size is absent, set once the player is loaded.
        let provisional = size.unwrap_or((64, 64));
        let attrs = Window::default_attributes()
            .with_title("drape view")
            .with_inner_size(PhysicalSize::new(provisional.0, provisional.1))
            .with_resizable(false)
            .with_decorations(false);
        let window = el
            .create_window(attrs)
            .map_err(|e| anyhow!("cannot create the window: {e}"))?;
        let x11 = X11Window::of(&window)?;
        // On an early return below, what was made drops in reverse: the engine before
        // the Gpu, the Gpu before the window.
        let gpu = Gpu::new(&x11, validation, device_name)?;

        // The engine over the viewer's device.
        let ctx = gpu.engine_context()?;
        eprintln!("device: {}", ctx.info());
        let k = args.frames_in_flight as usize;
        let player = AvatarPlayer::load(&ctx, &args.run, k)?;
        let (width, height) = size.unwrap_or((
            player.default_camera().width,
            player.default_camera().height,
        ));
        if (width, height) != provisional {
            let _ = window.request_inner_size(PhysicalSize::new(width, height));
        }

        let presenter = Presenter::new(&gpu, k, width, height)?;
        let anchor_body = player.default_body().clone();
        let orbit = Orbit::new(&player, &anchor_body, args.frames.is_some());
        println!("window 0x{:x}", x11.id);
        let now = Instant::now();
        let mut viewer = Viewer {
            player,
            _ctx: ctx,
            presenter,
            gpu,
            window,
            playback: Playback::new(motion, anchor_body, args.frames, now),
            orbit,
            capture: args.screenshot.clone().map(Capture::new),
            stats: Stats::new(now),
        };
        viewer.presenter.recreate_swapchain(&viewer.gpu)?;
        eprintln!(
            "view: {}x{} render, swapchain {:?} {:?}, {} frames in flight",
            width, height, viewer.presenter.format.format, viewer.presenter.present_mode, k
        );
        Ok(viewer)
    }

    fn summary(&self) -> String {
        let p = &self.playback;
        let frames = p
            .frames_limit
            .map_or(p.frame, |n| u64::from(n).min(p.frame));
        self.stats.summary(
            frames,
            (self.presenter.width, self.presenter.height),
            &self.gpu.label,
            self.presenter.slots.len(),
        )
    }
}
