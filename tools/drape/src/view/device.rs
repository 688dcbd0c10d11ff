//! The viewer's Vulkan device: the instance (with validation and its messenger when
//! asked), the window's surface, the physical device and its queue family, the logical
//! device with one queue, and the engine's [`Context`] over them; their creation in
//! [`Gpu::new`] and their teardown in its `Drop`. The swapchain and the frames in flight
//! are `swapchain`'s.
#![allow(unsafe_code)]

use std::ffi::{CStr, CString};
use std::sync::Arc;

use anyhow::{anyhow, bail, Context as _};
use drape_engine::ash::{self, vk};
use drape_engine::validation::ValidationSink;
use drape_engine::{Context, DeviceKind, DeviceRequirements, ExternalOptions, ExternalVulkan};
use raw_window_handle::{HasDisplayHandle, HasWindowHandle, RawDisplayHandle, RawWindowHandle};
use winit::window::Window;

// Validation messages of the viewer's own messenger: the engine's collector (it prints
// each as `vulkan validation: ...`), in a static that outlives the messenger.

pub(super) static VALIDATION: std::sync::LazyLock<Arc<ValidationSink>> =
    std::sync::LazyLock::new(Default::default);

fn messenger_info() -> vk::DebugUtilsMessengerCreateInfoEXT<'static> {
    drape_engine::validation::messenger_info(&VALIDATION)
}

/// The window's X11 handles and the surface extension they call for.
#[derive(Clone, Copy)]
pub(super) struct X11Window {
    display: RawDisplayHandle,
    window: RawWindowHandle,
    surface_ext: &'static CStr,
    /// The X window id (what `drape view` prints for a test to capture).
    pub(super) id: u64,
}

impl X11Window {
    /// The handles of `window`; an error unless it is an Xlib or XCB window.
    pub(super) fn of(window: &Window) -> anyhow::Result<Self> {
        let display = window
            .display_handle()
            .map_err(|e| anyhow!("window display handle: {e}"))?
            .as_raw();
        let window = window
            .window_handle()
            .map_err(|e| anyhow!("window handle: {e}"))?
            .as_raw();
        let (surface_ext, id): (&CStr, u64) = match (display, window) {
            // `c_ulong`: 64 bits here, but 32 on some targets, where the cast widens.
            #[allow(clippy::unnecessary_cast)]
            (RawDisplayHandle::Xlib(_), RawWindowHandle::Xlib(w)) => {
                (ash::khr::xlib_surface::NAME, w.window as u64)
            }
            (RawDisplayHandle::Xcb(_), RawWindowHandle::Xcb(w)) => {
                (ash::khr::xcb_surface::NAME, u64::from(w.window.get()))
            }
            _ => {
                bail!("drape view supports X11 windows only (Xlib or XCB handles); got {display:?}")
            }
        };
        Ok(Self {
            display,
            window,
            surface_ext,
            id,
        })
    }
}

/// The viewer's instance, surface and device (see the module header).
pub(super) struct Gpu {
    /// The loader, kept loaded while the instance lives.
    entry: ash::Entry,
    pub(super) instance: ash::Instance,
    messenger: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    pub(super) surface_fn: ash::khr::surface::Instance,
    pub(super) surface: vk::SurfaceKHR,
    pub(super) physical: vk::PhysicalDevice,
    pub(super) queue_family: u32,
    pub(super) device: ash::Device,
    pub(super) queue: vk::Queue,
    /// What the engine asked for and the device was created with.
    requirements: DeviceRequirements,
    debug_utils: bool,
    /// The physical device's name.
    pub(super) label: String,
}

impl Gpu {
    /// Loads Vulkan and creates the instance, the surface of `window`, and the device:
    /// the one named like `device_name` (else the best kind) with a queue family that has
    /// graphics, compute and present, with what the engine needs and `VK_KHR_swapchain`.
    pub(super) fn new(
        window: &X11Window,
        validation: bool,
        device_name: Option<&str>,
    ) -> anyhow::Result<Self> {
        let X11Window {
            display: display_handle,
            window: window_handle,
            surface_ext,
            ..
        } = *window;
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
        // From here on, a failure must destroy what was created: `Partial` holds it until
        // the Gpu does, and its Drop undoes it.
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
                // SAFETY: the display and window are live (the window is owned by the Viewer, which drops it after its Gpu, so it outlives the surface).
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
            _ => unreachable!("checked by X11Window::of"),
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
        let Some((_, physical, queue_family, label)) = candidates.into_iter().next() else {
            bail!("no Vulkan device{} with a graphics + compute queue that can present to the window (devices: {})", device_name.map(|n| format!(" named like '{n}'")).unwrap_or_default(), names.join(", "));
        };

        // What the engine needs, enabled on the viewer's device.
        let mut requirements = drape_engine::device_requirements(&instance, physical)?;
        // One queue of the family that presents (graphics + compute), which need not be
        // the first with compute.
        requirements.queue_family = queue_family;
        let device = requirements
            .with_create_info(&[ash::khr::swapchain::NAME], |dci| {
                // SAFETY: every pointer in `dci` refers to locals alive for the call.
                unsafe { instance.create_device(physical, dci, None) }
            })
            .context("vkCreateDevice")?;
        // SAFETY: family `queue_family`, index 0 was requested above.
        let queue = unsafe { device.get_device_queue(queue_family, 0) };
        // Nothing below can fail: the Gpu owns everything now, and its Drop undoes it.
        partial.disarm();
        Ok(Self {
            entry,
            instance,
            messenger,
            surface_fn,
            surface,
            physical,
            queue_family,
            device,
            queue,
            requirements,
            debug_utils,
            label,
        })
    }

    /// The engine over the viewer's device (it borrows instance, device and queue and
    /// never destroys them).
    pub(super) fn engine_context(&self) -> anyhow::Result<Context> {
        let external = ExternalVulkan {
            entry: self.entry.clone(),
            instance: self.instance.clone(),
            physical_device: self.physical,
            device: self.device.clone(),
            queue_family: self.queue_family,
            queue_index: 0,
            api_version: vk::API_VERSION_1_2,
            enabled_extensions: self
                .requirements
                .extensions
                .iter()
                .map(|e| CString::from(*e))
                .chain([CString::from(ash::khr::swapchain::NAME)])
                .collect(),
            enabled_features: self.requirements.features,
            debug_utils: self.debug_utils,
        };
        // SAFETY: every handle is live and outlives the context: the Viewer declares the
        // player and the context before its Presenter and Gpu, so they drop first (and in
        // `Viewer::new`, a local context drops before the Gpu made before it); the
        // extensions and features are those the device was created with.
        let ctx = unsafe { Context::from_raw(external, ExternalOptions::default()) }?;
        Ok(ctx)
    }
}

/// What `Gpu::new` has created so far, destroyed in reverse on an early return.
#[derive(Default)]
struct Partial {
    surface: Option<(ash::khr::surface::Instance, vk::SurfaceKHR)>,
    messenger: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    instance: Option<ash::Instance>,
}

impl Partial {
    /// Success: the Gpu owns everything now.
    fn disarm(mut self) {
        self.surface = None;
        self.messenger = None;
        self.instance = None;
    }
}

impl Drop for Partial {
    fn drop(&mut self) {
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

impl Drop for Gpu {
    fn drop(&mut self) {
        // SAFETY: whoever made objects on the device (the engine, the Presenter) is gone
        // by now (the Viewer's field order, `Viewer::new`'s locals); once idle nothing is
        // pending. Each object is destroyed before the one it was made from: the device,
        // the surface and the messenger before the instance.
        unsafe {
            let _ = self.device.device_wait_idle();
            self.device.destroy_device(None);
            self.surface_fn.destroy_surface(self.surface, None);
            if let Some((du, m)) = self.messenger.take() {
                du.destroy_debug_utils_messenger(m, None);
            }
            self.instance.destroy_instance(None);
        }
    }
}
