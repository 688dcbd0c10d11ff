//! `drape view RUN`: a real-time viewer of a trained run, built the way an application
//! that embeds the engine builds it: the viewer owns the window and every Vulkan object
//! of its own, and lends its device to the engine.
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
//!   player and the context first (they wait for their own submissions), then waits for
//!   the device to go idle and destroys its own objects, the device and the instance
//!   ([`Viewer`]'s `Drop`).
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
#![allow(unsafe_code)]

use std::ffi::{CStr, CString};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context as _};
use drape_engine::ash::{self, vk};
use drape_engine::validation::ValidationSink;
use drape_engine::{
    Context, DeviceKind, ExternalOptions, ExternalVulkan, ImageTarget, PassTimings, SubmitSync,
};
use drape_trainer::avatar::animate::{pelvis_and_up, place_pose};
use drape_trainer::avatar::player::{AvatarPlayer, ViewCamera};
use drape_trainer::dataset::loader::BodyParams;
use drape_trainer::motion::{procedural, Motion, MotionKind};
use glam::DVec3;
use raw_window_handle::{HasDisplayHandle, HasWindowHandle, RawDisplayHandle, RawWindowHandle};
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, MouseButton, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::{Key, NamedKey};
use winit::window::{Window, WindowId};

/// How long `--screenshot` keeps the window up waiting for `S.png.done`.
const HOLD_TIMEOUT: Duration = Duration::from_secs(30);

/// Options of `drape view`.
#[derive(Clone, Debug, clap::Args)]
pub struct ViewArgs {
    /// The run directory (`drape train --out`, or `drape edit --out`).
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
    anyhow::ensure!(
        args.run.join("run.json").is_file(),
        "{}: not a run directory (no run.json)",
        args.run.display()
    );
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
        match event {
            WindowEvent::CloseRequested => el.exit(),
            WindowEvent::KeyboardInput { event, .. } if event.state == ElementState::Pressed => {
                match event.logical_key {
                    Key::Named(NamedKey::Escape) => el.exit(),
                    Key::Named(NamedKey::Space) if !event.repeat => v.playing = !v.playing,
                    Key::Named(NamedKey::ArrowRight) => v.step(1),
                    Key::Named(NamedKey::ArrowLeft) => v.step(-1),
                    _ => {}
                }
            }
            WindowEvent::MouseInput {
                state,
                button: MouseButton::Left,
                ..
            } => v.dragging = state == ElementState::Pressed,
            WindowEvent::CursorMoved { position, .. } => {
                if let (true, Some((x, y))) = (v.dragging, v.cursor) {
                    v.yaw -= (position.x - x) * 0.01;
                    v.pitch = (v.pitch + (position.y - y) * 0.01).clamp(-1.3, 1.3);
                }
                v.cursor = Some((position.x, position.y));
            }
            WindowEvent::Resized(_) => v.swapchain_stale = true,
            _ => {}
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

// ---------------------------------------------------------------------------------
// Validation messages of the viewer's own messenger: the engine's collector (it prints
// each as `vulkan validation: ...`), in a static that outlives the messenger.

static VALIDATION: std::sync::LazyLock<Arc<ValidationSink>> =
    std::sync::LazyLock::new(Default::default);

fn messenger_info() -> vk::DebugUtilsMessengerCreateInfoEXT<'static> {
    drape_engine::validation::messenger_info(&VALIDATION)
}

// ---------------------------------------------------------------------------------
// The viewer.

/// One frame in flight's objects (see the module header).
struct Slot {
    image: vk::Image,
    memory: vk::DeviceMemory,
    cmd: vk::CommandBuffer,
    fence: vk::Fence,
    render_done: vk::Semaphore,
    acquired: vk::Semaphore,
}

struct Swapchain {
    raw: vk::SwapchainKHR,
    images: Vec<vk::Image>,
    /// One per swapchain image: signalled by the blit, waited by the present.
    present_ready: Vec<vk::Semaphore>,
    extent: vk::Extent2D,
}

#[derive(Clone, Copy, PartialEq)]
enum Phase {
    Running,
    /// `--screenshot`: the last frame is written; presenting it until `.done` appears.
    Holding(Instant),
}

struct Viewer {
    // Engine objects: dropped (player first) before the device in Drop.
    player: Option<AvatarPlayer>,
    ctx: Option<Context>,
    // The viewer's Vulkan objects.
    _entry: ash::Entry,
    instance: ash::Instance,
    messenger: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    surface_fn: ash::khr::surface::Instance,
    surface: vk::SurfaceKHR,
    physical: vk::PhysicalDevice,
    device: ash::Device,
    queue: vk::Queue,
    swapchain_fn: ash::khr::swapchain::Device,
    swapchain: Option<Swapchain>,
    swap_format: vk::SurfaceFormatKHR,
    present_mode: vk::PresentModeKHR,
    pool: vk::CommandPool,
    slots: Vec<Slot>,
    // Dropped after the surface (field order: the Drop body runs first).
    window: Window,
    device_label: String,
    // Frame state.
    width: u32,
    height: u32,
    motion: Motion,
    anchor_body: BodyParams,
    anchor_pelvis: DVec3,
    up: DVec3,
    frames_limit: Option<u32>,
    screenshot: Option<PathBuf>,
    phase: Phase,
    frame: u64,
    motion_pos: f64,
    playing: bool,
    dragging: bool,
    cursor: Option<(f64, f64)>,
    yaw: f64,
    pitch: f64,
    swapchain_stale: bool,
    last_slot: usize,
    started: Instant,
    last_tick: Instant,
    title_at: Instant,
    title_frames: u64,
    timings: Option<PassTimings>,
    busy_ms_sum: f64,
    busy_count: u64,
    first_frame_at: Option<Instant>,
    last_frame_at: Instant,
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
        let display_handle = window
            .display_handle()
            .map_err(|e| anyhow!("window display handle: {e}"))?
            .as_raw();
        let window_handle = window
            .window_handle()
            .map_err(|e| anyhow!("window handle: {e}"))?
            .as_raw();
        let (surface_ext, window_id): (&CStr, u64) = match (display_handle, window_handle) {
            (RawDisplayHandle::Xlib(_), RawWindowHandle::Xlib(w)) => (ash::khr::xlib_surface::NAME, w.window as u64),
            (RawDisplayHandle::Xcb(_), RawWindowHandle::Xcb(w)) => (ash::khr::xcb_surface::NAME, u64::from(w.window.get())),
            _ => bail!("drape view supports X11 windows only (Xlib or XCB handles); got {display_handle:?}"),
        };

        // SAFETY: loads the system's Vulkan loader; nothing else is running Vulkan yet.
        let entry = unsafe { ash::Entry::load() }
            .map_err(|e| anyhow!("cannot load the Vulkan loader (libvulkan.so.1): {e}"))?;
        // SAFETY: an instance-level query with no layer.
        let available = unsafe { entry.enumerate_instance_extension_properties(None) }?;
        let has_ext = |n: &CStr| {
            available
                .iter()
                .any(|e| e.extension_name_as_c_str() == Ok(n))
        };
        for n in [ash::khr::surface::NAME, surface_ext] {
            anyhow::ensure!(has_ext(n), "the Vulkan instance lacks {} (no X11 presentation support in the installed drivers)", n.to_string_lossy());
        }
        let debug_utils = has_ext(ash::ext::debug_utils::NAME);
        let mut extensions = vec![ash::khr::surface::NAME.as_ptr(), surface_ext.as_ptr()];
        if debug_utils {
            extensions.push(ash::ext::debug_utils::NAME.as_ptr());
        }
        let layer = c"VK_LAYER_KHRONOS_validation";
        let mut layers = Vec::new();
        if validation {
            // SAFETY: an instance-level query.
            let props = unsafe { entry.enumerate_instance_layer_properties() }?;
            anyhow::ensure!(props.iter().any(|l| l.layer_name_as_c_str() == Ok(layer)), "DRAPE_VALIDATION=1 but VK_LAYER_KHRONOS_validation is not installed (package vulkan-validationlayers)");
            anyhow::ensure!(
                debug_utils,
                "DRAPE_VALIDATION=1 but VK_EXT_debug_utils is unavailable"
            );
            layers.push(layer.as_ptr());
            extensions.push(ash::ext::validation_features::NAME.as_ptr());
        }
        let app_name = c"drape view";
        let app = vk::ApplicationInfo::default()
            .application_name(app_name)
            .engine_name(c"drape")
            .api_version(vk::API_VERSION_1_2);
        let sync_validation = [vk::ValidationFeatureEnableEXT::SYNCHRONIZATION_VALIDATION];
        let mut features =
            vk::ValidationFeaturesEXT::default().enabled_validation_features(&sync_validation);
        let mut chained = messenger_info();
        let mut info = vk::InstanceCreateInfo::default()
            .application_info(&app)
            .enabled_layer_names(&layers)
            .enabled_extension_names(&extensions);
        if validation {
            // Chained so messages of instance creation and destruction are caught too.
            info = info.push_next(&mut features).push_next(&mut chained);
        }
        // SAFETY: every pointer in `info` refers to locals alive for the call.
        let instance = unsafe { entry.create_instance(&info, None) }.context("vkCreateInstance")?;
        // From here on, a failure must destroy what was created: a partial Viewer is
        // assembled step by step through `Partial`, whose Drop undoes it.
        let mut partial = Partial::default();
        partial.instance = Some(instance.clone());
        let messenger = if debug_utils && validation {
            let du = ash::ext::debug_utils::Instance::new(&entry, &instance);
            // SAFETY: the instance has VK_EXT_debug_utils enabled; the callback is a static fn.
            let m = unsafe { du.create_debug_utils_messenger(&messenger_info(), None) }
                .context("vkCreateDebugUtilsMessengerEXT")?;
            partial.messenger = Some((du.clone(), m));
            Some((du, m))
        } else {
            None
        };
        let surface_fn = ash::khr::surface::Instance::new(&entry, &instance);
        let surface = match (display_handle, window_handle) {
            (RawDisplayHandle::Xlib(d), RawWindowHandle::Xlib(w)) => {
                let dpy = d
                    .display
                    .ok_or_else(|| anyhow!("the Xlib display handle has no Display pointer"))?;
                let f = ash::khr::xlib_surface::Instance::new(&entry, &instance);
                let ci = vk::XlibSurfaceCreateInfoKHR::default()
                    .dpy(dpy.as_ptr().cast())
                    .window(w.window);
                // SAFETY: the display and window are live (the window is owned by this Viewer and outlives the surface).
                unsafe { f.create_xlib_surface(&ci, None) }.context("vkCreateXlibSurfaceKHR")?
            }
            (RawDisplayHandle::Xcb(d), RawWindowHandle::Xcb(w)) => {
                let conn = d
                    .connection
                    .ok_or_else(|| anyhow!("the XCB display handle has no connection"))?;
                let f = ash::khr::xcb_surface::Instance::new(&entry, &instance);
                let ci = vk::XcbSurfaceCreateInfoKHR::default()
                    .connection(conn.as_ptr())
                    .window(w.window.get());
                // SAFETY: as above, for the XCB connection and window.
                unsafe { f.create_xcb_surface(&ci, None) }.context("vkCreateXcbSurfaceKHR")?
            }
            _ => unreachable!("checked above"),
        };
        partial.surface = Some((surface_fn.clone(), surface));

        // The physical device: DRAPE_DEVICE / --device substring, else the best kind;
        // it needs a family with graphics, compute and present.
        // SAFETY: a query of the live instance.
        let physicals = unsafe { instance.enumerate_physical_devices() }
            .context("vkEnumeratePhysicalDevices")?;
        let mut candidates = Vec::new();
        let mut names = Vec::new();
        for &p in &physicals {
            // SAFETY: p is a physical device of this instance.
            let props = unsafe { instance.get_physical_device_properties(p) };
            let name = props
                .device_name_as_c_str()
                .map(|c| c.to_string_lossy().into_owned())
                .unwrap_or_default();
            names.push(name.clone());
            if let Some(want) = device_name {
                if !name.to_lowercase().contains(&want.to_lowercase()) {
                    continue;
                }
            }
            // SAFETY: as above.
            let families = unsafe { instance.get_physical_device_queue_family_properties(p) };
            let family = families.iter().enumerate().position(|(i, f)| {
                let flags = vk::QueueFlags::GRAPHICS | vk::QueueFlags::COMPUTE;
                // SAFETY: the surface and physical device belong to this instance.
                f.queue_flags.contains(flags)
                    && unsafe {
                        surface_fn.get_physical_device_surface_support(p, i as u32, surface)
                    }
                    .unwrap_or(false)
            });
            if let Some(family) = family {
                candidates.push((
                    DeviceKind::from_vk(props.device_type),
                    p,
                    family as u32,
                    name,
                ));
            }
        }
        candidates.sort_by_key(|c| c.0);
        let Some((_, physical, queue_family, device_label)) = candidates.into_iter().next() else {
            bail!("no Vulkan device{} with a graphics + compute queue that can present to the window (devices: {})", device_name.map(|n| format!(" named like '{n}'")).unwrap_or_default(), names.join(", "));
        };

        // What the engine needs, enabled on the viewer's device.
        let req = drape_engine::device_requirements(&instance, physical)?;
        let f = req.features;
        let mut device_exts: Vec<&CStr> = req.extensions.clone();
        device_exts.push(ash::khr::swapchain::NAME);
        let device_ext_ptrs: Vec<_> = device_exts.iter().map(|e| e.as_ptr()).collect();
        let mut f12 = vk::PhysicalDeviceVulkan12Features::default()
            .vulkan_memory_model(f.vulkan_memory_model)
            .vulkan_memory_model_device_scope(f.vulkan_memory_model_device_scope)
            .timeline_semaphore(f.timeline_semaphore);
        let mut atomic_float = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default()
            .shader_buffer_float32_atomic_add(f.shader_buffer_float32_atomic_add);
        let core = vk::PhysicalDeviceFeatures::default().shader_int64(f.shader_int64);
        let priorities = [1.0f32];
        let queue_info = [vk::DeviceQueueCreateInfo::default()
            .queue_family_index(queue_family)
            .queue_priorities(&priorities)];
        let mut dci = vk::DeviceCreateInfo::default()
            .queue_create_infos(&queue_info)
            .enabled_extension_names(&device_ext_ptrs)
            .enabled_features(&core)
            .push_next(&mut f12);
        if f.shader_buffer_float32_atomic_add {
            dci = dci.push_next(&mut atomic_float);
        }
        // SAFETY: every pointer in `dci` refers to locals alive for the call.
        let device =
            unsafe { instance.create_device(physical, &dci, None) }.context("vkCreateDevice")?;
        partial.device = Some(device.clone());
        // SAFETY: family `queue_family`, index 0 was requested above.
        let queue = unsafe { device.get_device_queue(queue_family, 0) };
        let swapchain_fn = ash::khr::swapchain::Device::new(&instance, &device);

        // The engine over the viewer's device.
        let external = ExternalVulkan {
            entry: entry.clone(),
            instance: instance.clone(),
            physical_device: physical,
            device: device.clone(),
            queue_family,
            queue_index: 0,
            api_version: vk::API_VERSION_1_2,
            enabled_extensions: req
                .extensions
                .iter()
                .map(|e| CString::from(*e))
                .chain([CString::from(ash::khr::swapchain::NAME)])
                .collect(),
            enabled_features: f,
            debug_utils,
        };
        // SAFETY: every handle is live and outlives the context: Viewer's Drop (and
        // Partial's) drop the player and the context before destroying the device and
        // instance; the extensions and features are those the device was created with.
        let ctx = unsafe { Context::from_raw(external, ExternalOptions::default()) }?;
        eprintln!("device: {}", ctx.info());
        let k = args.frames_in_flight as usize;
        let player = AvatarPlayer::load(&ctx, &args.run, k)?;
        partial.engine = Some((player, ctx));
        let (width, height) = {
            let (player, _) = partial.engine.as_ref().expect("just set");
            size.unwrap_or((
                player.default_camera().width,
                player.default_camera().height,
            ))
        };
        if (width, height) != provisional {
            let _ = window.request_inner_size(PhysicalSize::new(width, height));
        }

        // The blit's formats.
        // SAFETY: a query on the chosen physical device.
        let rgba_props = unsafe {
            instance
                .get_physical_device_format_properties(physical, vk::Format::R32G32B32A32_SFLOAT)
        };
        anyhow::ensure!(
            rgba_props
                .optimal_tiling_features
                .contains(vk::FormatFeatureFlags::BLIT_SRC | vk::FormatFeatureFlags::TRANSFER_DST),
            "{device_label}: R32G32B32A32_SFLOAT images cannot be blitted from"
        );
        // SAFETY: surface queries on the chosen device and the viewer's surface.
        let formats = unsafe { surface_fn.get_physical_device_surface_formats(physical, surface) }
            .context("vkGetPhysicalDeviceSurfaceFormatsKHR")?;
        let blit_dst = |fmt: vk::Format| {
            // SAFETY: as above.
            unsafe { instance.get_physical_device_format_properties(physical, fmt) }
                .optimal_tiling_features
                .contains(vk::FormatFeatureFlags::BLIT_DST)
        };
        // UNORM first: the window then shows the render's values as they are (the test
        // compares them with the library's render at 8 bits).
        let swap_format = [
            vk::Format::B8G8R8A8_UNORM,
            vk::Format::R8G8B8A8_UNORM,
            vk::Format::A8B8G8R8_UNORM_PACK32,
        ]
        .iter()
        .find_map(|want| {
            formats
                .iter()
                .find(|f| f.format == *want && blit_dst(f.format))
                .copied()
        })
        .or_else(|| formats.iter().find(|f| blit_dst(f.format)).copied())
        .ok_or_else(|| anyhow!("{device_label}: no swapchain format the blit can write"))?;
        // SAFETY: as above.
        let modes =
            unsafe { surface_fn.get_physical_device_surface_present_modes(physical, surface) }
                .context("vkGetPhysicalDeviceSurfacePresentModesKHR")?;
        let present_mode = [vk::PresentModeKHR::MAILBOX, vk::PresentModeKHR::IMMEDIATE]
            .into_iter()
            .find(|m| modes.contains(m))
            .unwrap_or(vk::PresentModeKHR::FIFO);

        // Per frame in flight.
        let pool_info = vk::CommandPoolCreateInfo::default()
            .queue_family_index(queue_family)
            .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
        // SAFETY: a pool on the live device.
        let pool = unsafe { device.create_command_pool(&pool_info, None) }
            .context("vkCreateCommandPool")?;
        partial.pool = pool;
        let alloc = vk::CommandBufferAllocateInfo::default()
            .command_pool(pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(k as u32 + 1);
        // SAFETY: the pool is live; the buffers are freed with it.
        let cmds = unsafe { device.allocate_command_buffers(&alloc) }
            .context("vkAllocateCommandBuffers")?;
        // SAFETY: a query on the chosen physical device.
        let mem_props = unsafe { instance.get_physical_device_memory_properties(physical) };
        for i in 0..k {
            let slot = create_slot(&device, &mem_props, width, height, cmds[i])?;
            partial.slots.push(slot);
        }
        // The images start UNDEFINED: one submission moves them to TRANSFER_DST_OPTIMAL,
        // the layout they keep between frames.
        let init = cmds[k];
        // SAFETY: a fresh primary command buffer of the pool; the barriers name the
        // slots' live images; the submission is waited for before anything else uses them.
        unsafe {
            device.begin_command_buffer(
                init,
                &vk::CommandBufferBeginInfo::default()
                    .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT),
            )?;
            let barriers: Vec<_> = partial
                .slots
                .iter()
                .map(|s| {
                    image_barrier(
                        s.image,
                        vk::ImageLayout::UNDEFINED,
                        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                        vk::AccessFlags::empty(),
                        vk::AccessFlags::TRANSFER_WRITE,
                    )
                })
                .collect();
            device.cmd_pipeline_barrier(
                init,
                vk::PipelineStageFlags::TOP_OF_PIPE,
                vk::PipelineStageFlags::TRANSFER,
                vk::DependencyFlags::empty(),
                &[],
                &[],
                &barriers,
            );
            device.end_command_buffer(init)?;
            let cb = [init];
            let submit = vk::SubmitInfo::default().command_buffers(&cb);
            device.queue_submit(queue, &[submit], vk::Fence::null())?;
            device.queue_wait_idle(queue)?;
        }

        let (player, ctx) = partial.engine.take().expect("set above");
        let anchor_body = player.default_body().clone();
        let rest_pelvis = player.rig().rest_joints()[0];
        let (anchor_pelvis, up) =
            pelvis_and_up(&player.rig().frame(&anchor_body).transforms, rest_pelvis);
        let slots = std::mem::take(&mut partial.slots);
        partial.disarm();
        println!("window 0x{window_id:x}");
        let now = Instant::now();
        let mut viewer = Viewer {
            player: Some(player),
            ctx: Some(ctx),
            _entry: entry,
            instance,
            messenger,
            surface_fn,
            surface,
            physical,
            device,
            queue,
            swapchain_fn,
            swapchain: None,
            swap_format,
            present_mode,
            pool,
            slots,
            window,
            device_label,
            width,
            height,
            motion,
            anchor_body,
            anchor_pelvis,
            up,
            frames_limit: args.frames,
            screenshot: args.screenshot.clone(),
            phase: Phase::Running,
            frame: 0,
            motion_pos: 0.0,
            playing: true,
            dragging: false,
            cursor: None,
            yaw: 0.0,
            pitch: 0.0,
            swapchain_stale: false,
            last_slot: 0,
            started: now,
            last_tick: now,
            title_at: now,
            title_frames: 0,
            timings: None,
            busy_ms_sum: 0.0,
            busy_count: 0,
            first_frame_at: None,
            last_frame_at: now,
        };
        viewer.recreate_swapchain()?;
        eprintln!(
            "view: {}x{} render, swapchain {:?} {:?}, {} frames in flight",
            width, height, swap_format.format, present_mode, k
        );
        Ok(viewer)
    }

    /// (Re)creates the swapchain at the surface's size (the render is blitted to fit).
    fn recreate_swapchain(&mut self) -> anyhow::Result<()> {
        // SAFETY: waits for the viewer's and the engine's work on the device's only queue
        // to finish before the old swapchain and its semaphores go.
        unsafe { self.device.device_wait_idle() }.context("vkDeviceWaitIdle")?;
        // SAFETY: a query on the viewer's surface.
        let caps = unsafe {
            self.surface_fn
                .get_physical_device_surface_capabilities(self.physical, self.surface)
        }
        .context("vkGetPhysicalDeviceSurfaceCapabilitiesKHR")?;
        anyhow::ensure!(
            caps.supported_usage_flags
                .contains(vk::ImageUsageFlags::TRANSFER_DST),
            "{}: swapchain images cannot be transfer destinations (needed by the blit)",
            self.device_label
        );
        let extent = if caps.current_extent.width == u32::MAX {
            vk::Extent2D {
                width: self.width,
                height: self.height,
            }
        } else {
            caps.current_extent
        };
        self.swapchain_stale = false;
        if extent.width == 0 || extent.height == 0 {
            return Ok(()); // minimised: keep the old one (or none) until it has a size.
        }
        let mut count = caps.min_image_count.max(self.slots.len() as u32 + 1);
        if caps.max_image_count > 0 {
            count = count.min(caps.max_image_count);
        }
        let alpha = [
            vk::CompositeAlphaFlagsKHR::OPAQUE,
            vk::CompositeAlphaFlagsKHR::INHERIT,
            vk::CompositeAlphaFlagsKHR::PRE_MULTIPLIED,
            vk::CompositeAlphaFlagsKHR::POST_MULTIPLIED,
        ]
        .into_iter()
        .find(|a| caps.supported_composite_alpha.contains(*a))
        .unwrap_or(vk::CompositeAlphaFlagsKHR::OPAQUE);
        let old = self
            .swapchain
            .as_ref()
            .map_or(vk::SwapchainKHR::null(), |s| s.raw);
        let info = vk::SwapchainCreateInfoKHR::default()
            .surface(self.surface)
            .min_image_count(count)
            .image_format(self.swap_format.format)
            .image_color_space(self.swap_format.color_space)
            .image_extent(extent)
            .image_array_layers(1)
            .image_usage(vk::ImageUsageFlags::TRANSFER_DST)
            .image_sharing_mode(vk::SharingMode::EXCLUSIVE)
            .pre_transform(caps.current_transform)
            .composite_alpha(alpha)
            .present_mode(self.present_mode)
            .clipped(true)
            .old_swapchain(old);
        // SAFETY: the surface is live; the old swapchain (if any) is idle (waited above).
        let raw = unsafe { self.swapchain_fn.create_swapchain(&info, None) }
            .context("vkCreateSwapchainKHR")?;
        self.destroy_swapchain();
        // SAFETY: the swapchain was just created.
        let images = unsafe { self.swapchain_fn.get_swapchain_images(raw) }
            .context("vkGetSwapchainImagesKHR")?;
        let mut present_ready = Vec::with_capacity(images.len());
        for _ in &images {
            // SAFETY: a binary semaphore on the live device.
            present_ready.push(
                unsafe {
                    self.device
                        .create_semaphore(&vk::SemaphoreCreateInfo::default(), None)
                }
                .context("vkCreateSemaphore")?,
            );
        }
        self.swapchain = Some(Swapchain {
            raw,
            images,
            present_ready,
            extent,
        });
        Ok(())
    }

    fn destroy_swapchain(&mut self) {
        if let Some(s) = self.swapchain.take() {
            // SAFETY: callers wait for the device to go idle first, so no submission or
            // present uses the semaphores or the swapchain's images.
            unsafe {
                for sem in s.present_ready {
                    self.device.destroy_semaphore(sem, None);
                }
                self.swapchain_fn.destroy_swapchain(s.raw, None);
            }
        }
    }

    fn step(&mut self, by: i64) {
        self.playing = false;
        let n = self.motion.len() as f64;
        self.motion_pos = (self.motion_pos.floor() + by as f64).rem_euclid(n);
    }

    /// The camera: the run's default with --frames; else orbiting the pelvis.
    fn camera(&self, player: &AvatarPlayer, body: &BodyParams) -> ViewCamera {
        let start = *player.default_camera();
        let cam = if self.frames_limit.is_some() {
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
        if (self.width, self.height) != (start.width, start.height) {
            let (sx, sy) = (
                self.width as f32 / start.width as f32,
                self.height as f32 / start.height as f32,
            );
            v.fx *= sx;
            v.cx *= sx;
            v.fy *= sy;
            v.cy *= sy;
        }
        v
    }

    /// One iteration of the loop; false to quit.
    fn tick(&mut self) -> anyhow::Result<bool> {
        let now = Instant::now();
        let dt = now.duration_since(self.last_tick).as_secs_f64();
        self.last_tick = now;
        if let Phase::Holding(since) = self.phase {
            let shot = self
                .screenshot
                .as_ref()
                .expect("holding only with --screenshot");
            if marker(shot, "done").exists() {
                return Ok(false);
            }
            if since.elapsed() > HOLD_TIMEOUT {
                eprintln!(
                    "view: {} did not appear within {} s; exiting",
                    marker(shot, "done").display(),
                    HOLD_TIMEOUT.as_secs()
                );
                return Ok(false);
            }
            self.present(self.last_slot)?;
            std::thread::sleep(Duration::from_millis(30));
            return Ok(true);
        }
        if self.swapchain_stale || self.swapchain.is_none() {
            self.recreate_swapchain()?;
            if self.swapchain.is_none() {
                std::thread::sleep(Duration::from_millis(20));
                return Ok(true);
            }
        }
        // Motion frame: one per rendered frame with --frames, else by time when playing.
        let n = self.motion.len();
        let k = if self.frames_limit.is_some() {
            self.frame as usize % n
        } else {
            if self.playing {
                self.motion_pos = (self.motion_pos + dt * self.motion.fps).rem_euclid(n as f64);
            }
            (self.motion_pos.floor() as usize).min(n - 1)
        };
        if !self.render_frame(k)? {
            return Ok(true); // the swapchain was out of date: recreated, try again.
        }
        self.update_title(k);
        if let Some(limit) = self.frames_limit {
            if self.frame >= u64::from(limit) {
                return self.finish_frames();
            }
        }
        Ok(true)
    }

    /// Renders motion frame `k` and presents it. False if the swapchain had to be
    /// recreated before anything was submitted.
    fn render_frame(&mut self, k: usize) -> anyhow::Result<bool> {
        let s = (self.frame % self.slots.len() as u64) as usize;
        let slot_fence = self.slots[s].fence;
        // SAFETY: the fence is the slot's, submitted with its previous command buffer
        // (or created signalled).
        unsafe { self.device.wait_for_fences(&[slot_fence], true, u64::MAX) }
            .context("vkWaitForFences")?;
        let Some(image_index) = self.acquire(s)? else {
            return Ok(false);
        };
        let body = place_pose(
            &self.anchor_body,
            &self.motion.poses[k],
            self.motion.translations[k],
        );
        let mut player = self.player.take().expect("present until Drop");
        let result = (|| -> anyhow::Result<()> {
            player.set_body(body.clone());
            let cam = self.camera(&player, &body);
            // SAFETY: the slot's image is a live image of the engine's device with
            // TRANSFER_DST usage, width x height, 16-byte texels; it is in
            // TRANSFER_DST_OPTIMAL (kept there between frames; the fence wait above
            // ordered the last blit out of it and its transition back before this
            // submission); it lives until Drop, after the player.
            let target = unsafe {
                ImageTarget::new(
                    self.slots[s].image,
                    vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                    self.width,
                    self.height,
                    16,
                )
            };
            let sync = SubmitSync {
                wait: vec![],
                signal: vec![(self.slots[s].render_done, 0)],
            };
            let (_, timings) =
                player.submit_frame(&cam, self.width, self.height, &sync, Some(&target))?;
            if let Some(t) = timings {
                self.busy_ms_sum += t.busy_ms();
                self.busy_count += 1;
                self.timings = Some(t);
            }
            Ok(())
        })();
        self.player = Some(player);
        result?;
        self.blit_and_present(s, s, image_index, true)?;
        self.last_slot = s;
        self.frame += 1;
        self.title_frames += 1;
        // The rate counts from the end of the first frame (start-up and first-use costs out).
        let now = Instant::now();
        self.first_frame_at.get_or_insert(now);
        self.last_frame_at = now;
        Ok(true)
    }

    /// Acquires the next swapchain image into slot `s`'s semaphore and resets the slot's
    /// fence; None (after recreating the swapchain) if it is out of date.
    fn acquire(&mut self, s: usize) -> anyhow::Result<Option<u32>> {
        let sc = self.swapchain.as_ref().expect("created before a frame");
        // SAFETY: the semaphore is unsignalled with no pending operation: the slot's
        // fence (waited by the caller) covers the submission that waited on it.
        let r = unsafe {
            self.swapchain_fn.acquire_next_image(
                sc.raw,
                u64::MAX,
                self.slots[s].acquired,
                vk::Fence::null(),
            )
        };
        match r {
            Ok((i, suboptimal)) => {
                if suboptimal {
                    self.swapchain_stale = true;
                }
                // SAFETY: the fence was waited for by the caller and is not in use.
                unsafe { self.device.reset_fences(&[self.slots[s].fence]) }
                    .context("vkResetFences")?;
                Ok(Some(i))
            }
            Err(vk::Result::ERROR_OUT_OF_DATE_KHR) => {
                self.recreate_swapchain()?;
                Ok(None)
            }
            Err(e) => Err(anyhow!("vkAcquireNextImageKHR: {e}")),
        }
    }

    /// Records and submits slot `s`'s command buffer that blits `src_slot`'s image into
    /// swapchain image `image_index` and presents it; waits on the slot's `acquired`
    /// semaphore and, with `wait_render`, on its `render_done` (see the module header).
    fn blit_and_present(
        &mut self,
        s: usize,
        src_slot: usize,
        image_index: u32,
        wait_render: bool,
    ) -> anyhow::Result<()> {
        let sc = self.swapchain.as_ref().expect("created before a frame");
        let dev = &self.device;
        let slot = &self.slots[s];
        let src = self.slots[src_slot].image;
        let dst = sc.images[image_index as usize];
        let (w, h) = (self.width as i32, self.height as i32);
        let (dw, dh) = (sc.extent.width as i32, sc.extent.height as i32);
        // SAFETY: the slot's command buffer is not pending (its fence was waited for);
        // every image named is live; the layouts are those the module header describes.
        unsafe {
            dev.begin_command_buffer(
                slot.cmd,
                &vk::CommandBufferBeginInfo::default()
                    .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT),
            )
            .context("vkBeginCommandBuffer")?;
            let before = [
                image_barrier(
                    src,
                    vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                    vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                    vk::AccessFlags::TRANSFER_WRITE,
                    vk::AccessFlags::TRANSFER_READ,
                ),
                image_barrier(
                    dst,
                    vk::ImageLayout::UNDEFINED,
                    vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                    vk::AccessFlags::empty(),
                    vk::AccessFlags::TRANSFER_WRITE,
                ),
            ];
            dev.cmd_pipeline_barrier(
                slot.cmd,
                vk::PipelineStageFlags::TRANSFER,
                vk::PipelineStageFlags::TRANSFER,
                vk::DependencyFlags::empty(),
                &[],
                &[],
                &before,
            );
            let layers = vk::ImageSubresourceLayers::default()
                .aspect_mask(vk::ImageAspectFlags::COLOR)
                .layer_count(1);
            let blit = vk::ImageBlit::default()
                .src_subresource(layers)
                .src_offsets([vk::Offset3D::default(), vk::Offset3D { x: w, y: h, z: 1 }])
                .dst_subresource(layers)
                .dst_offsets([vk::Offset3D::default(), vk::Offset3D { x: dw, y: dh, z: 1 }]);
            dev.cmd_blit_image(
                slot.cmd,
                src,
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                dst,
                vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                &[blit],
                vk::Filter::NEAREST,
            );
            let to_present = [image_barrier(
                dst,
                vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                vk::ImageLayout::PRESENT_SRC_KHR,
                vk::AccessFlags::TRANSFER_WRITE,
                vk::AccessFlags::empty(),
            )];
            dev.cmd_pipeline_barrier(
                slot.cmd,
                vk::PipelineStageFlags::TRANSFER,
                vk::PipelineStageFlags::BOTTOM_OF_PIPE,
                vk::DependencyFlags::empty(),
                &[],
                &[],
                &to_present,
            );
            let back = [image_barrier(
                src,
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                vk::AccessFlags::TRANSFER_READ,
                vk::AccessFlags::TRANSFER_WRITE,
            )];
            dev.cmd_pipeline_barrier(
                slot.cmd,
                vk::PipelineStageFlags::TRANSFER,
                vk::PipelineStageFlags::TRANSFER,
                vk::DependencyFlags::empty(),
                &[],
                &[],
                &back,
            );
            dev.end_command_buffer(slot.cmd)
                .context("vkEndCommandBuffer")?;
        }
        let mut waits = vec![slot.acquired];
        if wait_render {
            waits.push(slot.render_done);
        }
        let stages = vec![vk::PipelineStageFlags::TRANSFER; waits.len()];
        let cmds = [slot.cmd];
        let signal = [sc.present_ready[image_index as usize]];
        let submit = vk::SubmitInfo::default()
            .wait_semaphores(&waits)
            .wait_dst_stage_mask(&stages)
            .command_buffers(&cmds)
            .signal_semaphores(&signal);
        // SAFETY: the queue is used from this thread only (the engine submits from the
        // same thread, inside player calls); the fence was reset in `acquire`.
        unsafe { dev.queue_submit(self.queue, &[submit], slot.fence) }
            .context("vkQueueSubmit (blit)")?;
        let swapchains = [sc.raw];
        let indices = [image_index];
        let present = vk::PresentInfoKHR::default()
            .wait_semaphores(&signal)
            .swapchains(&swapchains)
            .image_indices(&indices);
        // SAFETY: the image was acquired and its blit submitted, signalling `signal`.
        match unsafe { self.swapchain_fn.queue_present(self.queue, &present) } {
            Ok(false) => {}
            Ok(true) | Err(vk::Result::ERROR_OUT_OF_DATE_KHR) => self.swapchain_stale = true,
            Err(e) => bail!("vkQueuePresentKHR: {e}"),
        }
        Ok(())
    }

    /// Presents `src_slot`'s image again (`--screenshot`'s hold): every frame in flight
    /// is waited for first, so the image is idle and in TRANSFER_DST_OPTIMAL.
    fn present(&mut self, src_slot: usize) -> anyhow::Result<()> {
        let fences: Vec<_> = self.slots.iter().map(|s| s.fence).collect();
        // SAFETY: the slots' fences, each submitted or created signalled.
        unsafe { self.device.wait_for_fences(&fences, true, u64::MAX) }
            .context("vkWaitForFences")?;
        if self.swapchain_stale {
            self.recreate_swapchain()?;
        }
        let s = (self.frame % self.slots.len() as u64) as usize;
        let Some(i) = self.acquire(s)? else {
            return Ok(());
        };
        self.blit_and_present(s, src_slot, i, false)?;
        self.frame += 1;
        Ok(())
    }

    fn update_title(&mut self, k: usize) {
        let elapsed = self.title_at.elapsed().as_secs_f64();
        if elapsed < 0.5 {
            return;
        }
        let fps = self.title_frames as f64 / elapsed;
        self.title_at = Instant::now();
        self.title_frames = 0;
        let gpu = match &self.timings {
            Some(t) => {
                let scopes: Vec<String> = t
                    .by_scope()
                    .iter()
                    .map(|(s, ms)| format!("{s} {ms:.1}"))
                    .collect();
                format!("GPU {:.1} ms ({})", t.busy_ms(), scopes.join(", "))
            }
            None => "GPU -".into(),
        };
        let paused = if self.playing || self.frames_limit.is_some() {
            ""
        } else {
            " [paused]"
        };
        self.window.set_title(&format!(
            "drape view | {fps:.1} FPS | {gpu} | frame {}/{}{paused}",
            k + 1,
            self.motion.len()
        ));
    }

    /// After `--frames N`: prints the rate; with `--screenshot` writes the library's
    /// render and the `.ready` marker and starts holding the last frame.
    fn finish_frames(&mut self) -> anyhow::Result<bool> {
        let Some(shot) = self.screenshot.clone() else {
            return Ok(false);
        };
        let mut player = self.player.take().expect("present until Drop");
        let result = (|| -> anyhow::Result<()> {
            let body = player.body().clone();
            let cam = self.camera(&player, &body);
            let rgba = player.render(&cam, self.width, self.height)?;
            write_png16(&shot, self.width, self.height, &rgba)
        })();
        self.player = Some(player);
        result?;
        std::fs::write(marker(&shot, "ready"), b"")
            .with_context(|| format!("{}", marker(&shot, "ready").display()))?;
        eprintln!(
            "view: wrote {}; presenting the last frame until {} exists",
            shot.display(),
            marker(&shot, "done").display()
        );
        self.phase = Phase::Holding(Instant::now());
        Ok(true)
    }

    fn summary(&self) -> String {
        let frames = self
            .frames_limit
            .map_or(self.frame, |n| u64::from(n).min(self.frame));
        // Up to the last rendered frame (not the --screenshot hold).
        let secs = self
            .last_frame_at
            .duration_since(self.started)
            .as_secs_f64();
        let steady = match self.first_frame_at {
            Some(t) if frames > 1 => format!(
                ", {:.2} FPS after the first",
                (frames - 1) as f64 / self.last_frame_at.duration_since(t).as_secs_f64().max(1e-9)
            ),
            _ => String::new(),
        };
        let gpu = if self.busy_count > 0 {
            format!(
                ", GPU busy {:.1} ms per frame",
                self.busy_ms_sum / self.busy_count as f64
            )
        } else {
            String::new()
        };
        format!("view: {frames} frames at {}x{} on {} ({} frames in flight): {:.2} FPS over {:.1} s from the first frame's start{steady}{gpu}", self.width, self.height, self.device_label, self.slots.len(), frames as f64 / secs.max(1e-9), secs)
    }
}

fn marker(shot: &Path, what: &str) -> PathBuf {
    let mut s = shot.as_os_str().to_os_string();
    s.push(format!(".{what}"));
    PathBuf::from(s)
}

/// Premultiplied RGBA floats (over black: the colour as it is) as a 16-bit RGB PNG.
fn write_png16(path: &Path, w: u32, h: u32, rgba: &[f32]) -> anyhow::Result<()> {
    let mut data = Vec::with_capacity(3 * (w * h) as usize);
    for px in rgba.chunks_exact(4) {
        for &c in &px[..3] {
            data.push((c.clamp(0.0, 1.0) * 65535.0).round() as u16);
        }
    }
    let img = image::ImageBuffer::<image::Rgb<u16>, _>::from_raw(w, h, data)
        .ok_or_else(|| anyhow!("screenshot: {} floats for {w}x{h}", rgba.len()))?;
    img.save(path)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

fn image_barrier(
    image: vk::Image,
    old: vk::ImageLayout,
    new: vk::ImageLayout,
    src: vk::AccessFlags,
    dst: vk::AccessFlags,
) -> vk::ImageMemoryBarrier<'static> {
    vk::ImageMemoryBarrier::default()
        .src_access_mask(src)
        .dst_access_mask(dst)
        .old_layout(old)
        .new_layout(new)
        .src_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
        .dst_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
        .image(image)
        .subresource_range(
            vk::ImageSubresourceRange::default()
                .aspect_mask(vk::ImageAspectFlags::COLOR)
                .level_count(1)
                .layer_count(1),
        )
}

fn create_slot(
    device: &ash::Device,
    mem_props: &vk::PhysicalDeviceMemoryProperties,
    width: u32,
    height: u32,
    cmd: vk::CommandBuffer,
) -> anyhow::Result<Slot> {
    let info = vk::ImageCreateInfo::default()
        .image_type(vk::ImageType::TYPE_2D)
        .format(vk::Format::R32G32B32A32_SFLOAT)
        .extent(vk::Extent3D {
            width,
            height,
            depth: 1,
        })
        .mip_levels(1)
        .array_layers(1)
        .samples(vk::SampleCountFlags::TYPE_1)
        .tiling(vk::ImageTiling::OPTIMAL)
        .usage(vk::ImageUsageFlags::TRANSFER_DST | vk::ImageUsageFlags::TRANSFER_SRC)
        .sharing_mode(vk::SharingMode::EXCLUSIVE)
        .initial_layout(vk::ImageLayout::UNDEFINED);
    // SAFETY: creation on the live device; on any later failure the objects made so far
    // are destroyed below before returning.
    unsafe {
        let image = device.create_image(&info, None).context("vkCreateImage")?;
        let req = device.get_image_memory_requirements(image);
        let types =
            (0..mem_props.memory_type_count).filter(|&i| req.memory_type_bits & (1 << i) != 0);
        let local = types.clone().find(|&i| {
            mem_props.memory_types[i as usize]
                .property_flags
                .contains(vk::MemoryPropertyFlags::DEVICE_LOCAL)
        });
        let Some(type_index) = local.or_else(|| types.clone().next()) else {
            device.destroy_image(image, None);
            bail!("no memory type for the render image");
        };
        let memory = match device.allocate_memory(
            &vk::MemoryAllocateInfo::default()
                .allocation_size(req.size)
                .memory_type_index(type_index),
            None,
        ) {
            Ok(m) => m,
            Err(e) => {
                device.destroy_image(image, None);
                bail!("vkAllocateMemory (render image): {e}");
            }
        };
        let slot = Slot {
            image,
            memory,
            cmd,
            fence: vk::Fence::null(),
            render_done: vk::Semaphore::null(),
            acquired: vk::Semaphore::null(),
        };
        let mut slot = slot;
        let made = (|| -> Result<(), vk::Result> {
            device.bind_image_memory(image, memory, 0)?;
            slot.fence = device.create_fence(
                &vk::FenceCreateInfo::default().flags(vk::FenceCreateFlags::SIGNALED),
                None,
            )?;
            slot.render_done =
                device.create_semaphore(&vk::SemaphoreCreateInfo::default(), None)?;
            slot.acquired = device.create_semaphore(&vk::SemaphoreCreateInfo::default(), None)?;
            Ok(())
        })();
        if let Err(e) = made {
            destroy_slot(device, &slot);
            bail!("render image / sync objects: {e}");
        }
        Ok(slot)
    }
}

fn destroy_slot(device: &ash::Device, s: &Slot) {
    // SAFETY: callers wait for the device to go idle first; null handles are ignored by
    // the destroy calls.
    unsafe {
        device.destroy_semaphore(s.acquired, None);
        device.destroy_semaphore(s.render_done, None);
        device.destroy_fence(s.fence, None);
        device.destroy_image(s.image, None);
        device.free_memory(s.memory, None);
    }
}

/// What `Viewer::new` has created so far, destroyed in reverse on an early return.
#[derive(Default)]
struct Partial {
    engine: Option<(AvatarPlayer, Context)>,
    slots: Vec<Slot>,
    pool: vk::CommandPool,
    device: Option<ash::Device>,
    surface: Option<(ash::khr::surface::Instance, vk::SurfaceKHR)>,
    messenger: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    instance: Option<ash::Instance>,
}

impl Partial {
    /// Success: the Viewer owns everything now.
    fn disarm(mut self) {
        self.engine = None;
        self.slots.clear();
        self.pool = vk::CommandPool::null();
        self.device = None;
        self.surface = None;
        self.messenger = None;
        self.instance = None;
    }
}

impl Drop for Partial {
    fn drop(&mut self) {
        // The engine's objects before the device they live on.
        drop(self.engine.take());
        if let Some(d) = self.device.take() {
            // SAFETY: nothing is pending once idle; the objects were made on `d`.
            unsafe {
                let _ = d.device_wait_idle();
                for s in &self.slots {
                    destroy_slot(&d, s);
                }
                d.destroy_command_pool(self.pool, None);
                d.destroy_device(None);
            }
        }
        // SAFETY: children of the instance, destroyed before it.
        unsafe {
            if let Some((f, s)) = self.surface.take() {
                f.destroy_surface(s, None);
            }
            if let Some((du, m)) = self.messenger.take() {
                du.destroy_debug_utils_messenger(m, None);
            }
            if let Some(i) = self.instance.take() {
                i.destroy_instance(None);
            }
        }
    }
}

impl Drop for Viewer {
    fn drop(&mut self) {
        // The engine first: the player waits for its frames in flight, the context
        // frees its buffers, pipelines and pools on the viewer's device.
        drop(self.player.take());
        drop(self.ctx.take());
        // SAFETY: after the device is idle nothing uses the viewer's objects; each is
        // destroyed before the object it was made from (swapchain and surface before
        // the instance, everything on the device before the device).
        unsafe {
            let _ = self.device.device_wait_idle();
        }
        self.destroy_swapchain();
        for s in &self.slots {
            destroy_slot(&self.device, s);
        }
        // SAFETY: as above.
        unsafe {
            self.device.destroy_command_pool(self.pool, None);
            self.device.destroy_device(None);
            self.surface_fn.destroy_surface(self.surface, None);
            if let Some((du, m)) = self.messenger.take() {
                du.destroy_debug_utils_messenger(m, None);
            }
            self.instance.destroy_instance(None);
        }
    }
}
