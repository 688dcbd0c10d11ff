//! The Vulkan context: instance, optional validation, device choice, logical device,
//! compute queue, memory allocator and the kernel pipeline cache.
//!
//! [`Context`] is a cheap handle (`Arc`) to the [`Device`] that owns all of it; buffers
//! and recordings hold the same `Arc`, so the device outlives everything made from it.
//! Drop order is deliberate: recycled command pools and pipelines, then the allocator,
//! then the device, then the messenger, then the instance.

use std::ffi::{c_char, CStr, CString};
use std::fmt;
use std::mem::ManuallyDrop;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use ash::vk;
use gpu_allocator::vulkan::{Allocator, AllocatorCreateDesc};

use crate::error::{EngineError, Result, VkResultExt};
use crate::kernels::{self, Kernel, Pipeline, PipelineCache};
use crate::pools::PoolRecycler;
use crate::profile::Profile;
use crate::requirements::device_requirements;
use crate::validation::{self, ValidationSink};

const VALIDATION_LAYER: &CStr = c"VK_LAYER_KHRONOS_validation";

/// How to open a context.
#[derive(Clone, Debug, Default)]
pub struct ContextDesc {
    /// Case-insensitive substring of the device name to use instead of the automatic
    /// choice (discrete, then integrated, then CPU).
    pub device_name: Option<String>,
    /// Enable `VK_LAYER_KHRONOS_validation` and collect its messages.
    pub validation: bool,
    /// Fill every new buffer with [`POISON_WORD`], so code that relies on zeroed memory fails.
    pub poison_new_buffers: bool,
    /// Never map device buffers, even where their memory is host-visible (lavapipe, and
    /// integrated GPUs): uploads and readbacks go through staging buffers and copies, and
    /// poisoning through `vkCmdFillBuffer`, the path a discrete GPU takes. `for_tests`
    /// sets it from `DRAPE_FORCE_STAGING=1`, so the test command runs the GPU suite this
    /// way once on a machine without a discrete GPU.
    pub force_staging: bool,
    /// With `validation`: also turn on the layer's synchronization validation, which
    /// reports read-after-write and write-after-read hazards between commands that no
    /// barrier orders (what a missing derived barrier would be). Needs the layer's
    /// `VK_EXT_validation_features`; an error without it.
    pub synchronization_validation: bool,
    /// Bind at most this many bytes through one storage-buffer binding, below the
    /// device's `maxStorageBufferRange` ([`DeviceInfo::max_storage_buffer_range`] reports
    /// the smaller): the chunked paths a device with a small limit takes (lavapipe's
    /// 128 MiB), exercised on a device whose limit is far above any test's scene.
    /// `for_tests` reads it from `DRAPE_MAX_STORAGE_BUFFER_RANGE`.
    pub max_storage_buffer_range: Option<u64>,
}

impl ContextDesc {
    /// What tests use: validation on, poisoned buffers, device from `DRAPE_DEVICE` if set.
    pub fn for_tests() -> Self {
        Self {
            device_name: std::env::var("DRAPE_DEVICE").ok().filter(|s| !s.is_empty()),
            validation: true,
            poison_new_buffers: true,
            force_staging: std::env::var("DRAPE_FORCE_STAGING").is_ok_and(|v| v == "1"),
            synchronization_validation: true,
            max_storage_buffer_range: std::env::var("DRAPE_MAX_STORAGE_BUFFER_RANGE")
                .ok()
                .and_then(|v| v.parse().ok()),
        }
    }
}

/// The pattern every new buffer is filled with when poisoning is on.
pub const POISON_WORD: u32 = 0xDEAD_BEEF;

/// Kind of physical device, in order of preference.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum DeviceKind {
    /// A discrete GPU.
    DiscreteGpu,
    /// A GPU integrated with the CPU.
    IntegratedGpu,
    /// A GPU in a virtual machine.
    VirtualGpu,
    /// A CPU implementation (lavapipe).
    Cpu,
    /// Anything else.
    Other,
}

impl DeviceKind {
    /// The kind of a Vulkan device type (its `Ord` is the automatic choice's preference).
    pub fn from_vk(t: vk::PhysicalDeviceType) -> Self {
        match t {
            vk::PhysicalDeviceType::DISCRETE_GPU => Self::DiscreteGpu,
            vk::PhysicalDeviceType::INTEGRATED_GPU => Self::IntegratedGpu,
            vk::PhysicalDeviceType::VIRTUAL_GPU => Self::VirtualGpu,
            vk::PhysicalDeviceType::CPU => Self::Cpu,
            _ => Self::Other,
        }
    }
}

/// Device memory held by the engine's allocator ([`Context::memory_in_use`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MemoryInUse {
    /// Bytes of live allocations.
    pub allocated_bytes: u64,
    /// Bytes of the memory blocks the allocations are carved from.
    pub reserved_bytes: u64,
}

/// Dispatches and barriers recorded so far ([`Context::recorded_work`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct RecordedWork {
    /// `vkCmdDispatch` calls (dispatches of empty grids are skipped, so not counted).
    pub dispatches: u64,
    /// `vkCmdPipelineBarrier` calls.
    pub barriers: u64,
}

impl std::ops::Sub for RecordedWork {
    type Output = RecordedWork;
    fn sub(self, earlier: RecordedWork) -> RecordedWork {
        RecordedWork {
            dispatches: self.dispatches - earlier.dispatches,
            barriers: self.barriers - earlier.barriers,
        }
    }
}

/// What a device has done so far, counted for tests and profiles: read by
/// [`Context::submission_count`], [`Context::fence_waits`] and [`Context::recorded_work`].
#[derive(Default)]
pub(crate) struct Counters {
    submissions: AtomicU64,
    fence_waits: AtomicU64,
    dispatches: AtomicU64,
    barriers: AtomicU64,
}

impl Counters {
    /// One `vkQueueSubmit`.
    pub(crate) fn submitted(&self) {
        self.submissions.fetch_add(1, Ordering::Relaxed);
    }

    /// One host wait on a fence.
    pub(crate) fn waited(&self) {
        self.fence_waits.fetch_add(1, Ordering::Relaxed);
    }

    /// `n` `vkCmdDispatch` calls.
    pub(crate) fn dispatched(&self, n: u32) {
        self.dispatches.fetch_add(u64::from(n), Ordering::Relaxed);
    }

    /// One `vkCmdPipelineBarrier`.
    pub(crate) fn barrier(&self) {
        self.barriers.fetch_add(1, Ordering::Relaxed);
    }
}

/// Buffers whose destruction waited for pending work ([`Context::deferred_buffers`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DeferredBuffers {
    /// Dropped, not yet destroyed: their submissions are still pending.
    pub waiting: usize,
    /// Deferred since the context was made.
    pub total: u64,
}

/// What the chosen device is and can do.
#[derive(Clone, Debug)]
pub struct DeviceInfo {
    /// The device name the driver reports.
    pub name: String,
    /// What kind of device it is.
    pub kind: DeviceKind,
    /// The device's Vulkan version (major, minor, patch).
    pub api_version: (u32, u32, u32),
    /// The driver's name and version.
    pub driver: String,
    /// Lanes per subgroup in compute shaders.
    pub subgroup_size: u32,
    /// Nanoseconds per timestamp tick.
    pub timestamp_period_ns: f64,
    /// Valid bits of compute-queue timestamps (0: no timestamps).
    pub timestamp_valid_bits: u32,
    /// `shaderBufferFloat32AtomicAdd` (VK_EXT_shader_atomic_float).
    pub float_atomic_add: bool,
    /// Subgroup ballot and shuffle operations in compute shaders: what the modules built
    /// with subgroups use (their broadcasts, sums and votes are shuffles, which llvmpipe
    /// compiles to one register permute).
    pub subgroup_ballot: bool,
    /// `shaderInt64`: 64-bit integers in shaders (the chunked sort stores its pairs as
    /// one u64 each where it is there).
    pub shader_int64: bool,
    /// `timelineSemaphore` (Vulkan 1.2 core, optional): what
    /// [`crate::SubmitSync`]'s timeline waits and signals need.
    pub timeline_semaphore: bool,
    /// `maxComputeWorkGroupCount`: the most workgroups one dispatch may have per axis.
    pub max_compute_workgroup_count: [u32; 3],
    /// `maxStorageBufferRange`: the most bytes one storage-buffer binding may cover.
    pub max_storage_buffer_range: u64,
    /// `maxMemoryAllocationSize` (Vulkan 1.1): the most bytes one allocation may have.
    pub max_memory_allocation_size: u64,
    /// `minStorageBufferOffsetAlignment`: a binding of part of a buffer starts at a multiple.
    pub min_storage_buffer_offset_alignment: u64,
    /// `maxTexelBufferElements`: the most texels (here `f32`s) one texel-buffer view may
    /// cover; a buffer past it cannot be bound to a texel binding.
    pub max_texel_buffer_elements: u64,
}

impl fmt::Display for DeviceInfo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (ma, mi, pa) = self.api_version;
        write!(
            f,
            "{} [{:?}, Vulkan {ma}.{mi}.{pa}, {}, subgroup {}]",
            self.name, self.kind, self.driver, self.subgroup_size
        )
    }
}

/// Owner of every Vulkan object of a context. Reached through [`Context`].
pub struct Device {
    pub(crate) raw: ash::Device,
    pub(crate) instance: ash::Instance,
    pub(crate) queue_family: u32,
    pub(crate) queue: Mutex<vk::Queue>,
    pub(crate) allocator: ManuallyDrop<Mutex<Allocator>>,
    pub(crate) debug: DebugHooks,
    pub(crate) pipelines: PipelineCache,
    pub(crate) info: DeviceInfo,
    pub(crate) buffers: BufferPolicy,
    /// Pass and submission times while a profile is on (`Context::start_profile`).
    pub(crate) profile: Mutex<Option<Profile>>,
    /// Command, descriptor and query pools of finished recordings, for the next ones.
    pub(crate) pools: PoolRecycler,
    /// Submissions, fence waits, dispatches and barriers so far.
    pub(crate) counters: Counters,
    /// Fences of submissions not yet waited for ([`crate::Submission`] registers its
    /// fence at submission and removes it when it waits), and the buffers dropped while
    /// they may still use them (`crate::retire`).
    pub(crate) pending: Mutex<crate::retire::PendingWork>,
    /// False for a context over the host's handles ([`Context::from_raw`]): the engine
    /// destroys only what it created, never the device or the instance.
    pub(crate) owns_device: bool,
    // Keeps libvulkan loaded for as long as any handle exists.
    pub(crate) _entry: ash::Entry,
}

/// A device's debug-utils hooks: object names, the engine's own messenger and the sink
/// of validation messages.
#[derive(Default)]
pub(crate) struct DebugHooks {
    /// Names objects, when the instance has `VK_EXT_debug_utils`.
    pub(crate) names: Option<ash::ext::debug_utils::Device>,
    /// The messenger on the engine's own instance (none over a host's), destroyed with it.
    pub(crate) messenger: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    /// Where validation messages go (none without validation).
    pub(crate) sink: Option<Arc<ValidationSink>>,
}

/// How new buffers are made.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct BufferPolicy {
    /// See [`ContextDesc::poison_new_buffers`].
    pub(crate) poison: bool,
    /// See [`ContextDesc::force_staging`].
    pub(crate) force_staging: bool,
}

/// A cheap, clonable handle to an open device.
#[derive(Clone)]
pub struct Context {
    pub(crate) device: Arc<Device>,
}

/// The library `ash::Entry::load` opens on this platform.
const DEFAULT_LOADER: &str = if cfg!(windows) {
    "vulkan-1.dll"
} else if cfg!(any(target_os = "macos", target_os = "ios")) {
    "libvulkan.dylib"
} else if cfg!(any(target_os = "android", target_os = "fuchsia")) {
    "libvulkan.so"
} else {
    "libvulkan.so.1"
};

fn load_entry() -> Result<ash::Entry> {
    // DRAPE_VULKAN_LOADER names a loader library explicitly (tests use it to check the
    // error a machine without a loader gets).
    let (library, loaded) = match std::env::var_os("DRAPE_VULKAN_LOADER") {
        // SAFETY: loading libvulkan runs its initialisers; the loader is designed for it.
        Some(path) => (path.to_string_lossy().into_owned(), unsafe {
            ash::Entry::load_from(&path)
        }),
        // SAFETY: as above.
        None => (DEFAULT_LOADER.to_string(), unsafe { ash::Entry::load() }),
    };
    loaded.map_err(|error| EngineError::LoaderMissing { library, error })
}

pub(crate) fn cstr_array(raw: &[c_char]) -> String {
    // SAFETY: Vulkan property strings are nul-terminated within their fixed arrays.
    unsafe { CStr::from_ptr(raw.as_ptr()) }
        .to_string_lossy()
        .into_owned()
}

pub(crate) struct Candidate {
    pub(crate) physical: vk::PhysicalDevice,
    pub(crate) name: String,
    pub(crate) kind: DeviceKind,
    pub(crate) queue_family: u32,
}

impl Context {
    /// Opens the device `desc` asks for.
    pub fn new(desc: &ContextDesc) -> Result<Self> {
        let entry = load_entry()?;

        // SAFETY: plain queries on a loaded entry.
        let layers = unsafe { entry.enumerate_instance_layer_properties() }
            .vk("vkEnumerateInstanceLayerProperties", "instance")?;
        // SAFETY: as above.
        let extensions = unsafe { entry.enumerate_instance_extension_properties(None) }
            .vk("vkEnumerateInstanceExtensionProperties", "instance")?;
        let has_layer = layers
            .iter()
            .any(|l| l.layer_name_as_c_str() == Ok(VALIDATION_LAYER));
        let has_debug_utils = extensions
            .iter()
            .any(|e| e.extension_name_as_c_str() == Ok(ash::ext::debug_utils::NAME));
        if desc.validation && !has_layer {
            return Err(EngineError::ValidationLayerMissing);
        }

        let sink = desc.validation.then(|| Arc::new(ValidationSink::default()));
        let app = vk::ApplicationInfo::default()
            .application_name(c"drape")
            .engine_name(c"drape-engine")
            .api_version(vk::API_VERSION_1_2);
        let layer_names: Vec<*const c_char> = if desc.validation {
            vec![VALIDATION_LAYER.as_ptr()]
        } else {
            vec![]
        };
        let mut ext_names: Vec<*const c_char> = if has_debug_utils {
            vec![ash::ext::debug_utils::NAME.as_ptr()]
        } else {
            vec![]
        };
        let sync_validation = desc.validation && desc.synchronization_validation;
        if sync_validation {
            // SAFETY: a plain query of the layer's own extensions.
            let layer_extensions =
                unsafe { entry.enumerate_instance_extension_properties(Some(VALIDATION_LAYER)) }
                    .vk("vkEnumerateInstanceExtensionProperties", "validation layer")?;
            if !layer_extensions
                .iter()
                .any(|e| e.extension_name_as_c_str() == Ok(ash::ext::validation_features::NAME))
            {
                return Err(EngineError::ValidationLayerMissing);
            }
            ext_names.push(ash::ext::validation_features::NAME.as_ptr());
        }
        let enabled_features = [vk::ValidationFeatureEnableEXT::SYNCHRONIZATION_VALIDATION];
        let mut validation_features =
            vk::ValidationFeaturesEXT::default().enabled_validation_features(&enabled_features);
        let mut instance_info = vk::InstanceCreateInfo::default()
            .application_info(&app)
            .enabled_layer_names(&layer_names)
            .enabled_extension_names(&ext_names);
        if sync_validation {
            instance_info = instance_info.push_next(&mut validation_features);
        }
        // Chained so that messages during instance creation and destruction are caught.
        let mut chained_messenger = sink.as_ref().map(validation::messenger_info);
        if let Some(m) = chained_messenger.as_mut() {
            instance_info = instance_info.push_next(m);
        }
        // SAFETY: every pointer in instance_info refers to locals alive for the call.
        let instance = unsafe { entry.create_instance(&instance_info, None) }
            .vk("vkCreateInstance", "instance")?;

        // From here on, a failure must destroy the instance: wrap it in a guard.
        let guard = InstanceGuard {
            instance: Some(instance),
            messenger: None,
        };
        let mut guard = guard;
        let instance_ref = guard
            .instance
            .as_ref()
            .expect("instance present until disarmed");
        if let Some(sink) = &sink {
            let loader = ash::ext::debug_utils::Instance::new(&entry, instance_ref);
            let info = validation::messenger_info(sink);
            // SAFETY: valid instance with debug utils enabled; the sink outlives the messenger.
            let messenger = unsafe { loader.create_debug_utils_messenger(&info, None) }
                .vk("vkCreateDebugUtilsMessengerEXT", "messenger")?;
            guard.messenger = Some((loader, messenger));
        }

        let instance_ref = guard
            .instance
            .as_ref()
            .expect("instance present until disarmed");
        let chosen = choose_device(instance_ref, desc.device_name.as_deref())?;
        let parts = create_device(instance_ref, chosen, has_debug_utils)?;
        let (instance, debug_instance) = guard.disarm();
        let device = Device {
            raw: parts.raw,
            instance,
            queue_family: parts.queue_family,
            queue: Mutex::new(parts.queue),
            allocator: ManuallyDrop::new(Mutex::new(parts.allocator)),
            debug: DebugHooks {
                names: parts.debug_utils,
                messenger: debug_instance,
                sink,
            },
            pipelines: PipelineCache::default(),
            info: DeviceInfo {
                max_storage_buffer_range: desc
                    .max_storage_buffer_range
                    .map_or(parts.info.max_storage_buffer_range, |cap| {
                        cap.min(parts.info.max_storage_buffer_range)
                    }),
                ..parts.info
            },
            buffers: BufferPolicy {
                poison: desc.poison_new_buffers,
                force_staging: desc.force_staging,
            },
            profile: Mutex::new(None),
            counters: Counters::default(),
            pending: Mutex::new(Default::default()),
            owns_device: true,
            pools: PoolRecycler::default(),
            _entry: entry,
        };
        let ctx = Context {
            device: Arc::new(device),
        };
        kernels::check_manifest()?;
        Ok(ctx)
    }

    /// What the device is.
    pub fn info(&self) -> &DeviceInfo {
        &self.device.info
    }

    /// Starts (or restarts, discarding what was gathered) the context-wide profile:
    /// from now on every submission adds its passes' GPU time and its host wall time.
    pub fn start_profile(&self) {
        *self
            .device
            .profile
            .lock()
            .unwrap_or_else(|p| p.into_inner()) = Some(Profile::default());
    }

    /// Stops the profile and returns what it gathered (None when none was started).
    pub fn take_profile(&self) -> Option<Profile> {
        self.device
            .profile
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take()
    }

    /// Adds a host phase the caller timed (`ms`) to the running profile, if any.
    pub fn profile_host(&self, name: &str, ms: f64) {
        if let Some(p) = self
            .device
            .profile
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_mut()
        {
            p.add_host(name, ms);
        }
    }

    /// Whether a profile is running (callers skip their own timing otherwise).
    pub fn profiling(&self) -> bool {
        self.device
            .profile
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .is_some()
    }

    /// Takes the validation messages collected so far (empty without validation).
    pub fn take_validation_messages(&self) -> Vec<String> {
        self.device
            .debug
            .sink
            .as_ref()
            .map(|s| s.drain())
            .unwrap_or_default()
    }

    /// The validation sink, to read messages after the context is dropped.
    pub fn validation_sink(&self) -> Option<Arc<ValidationSink>> {
        self.device.debug.sink.clone()
    }

    /// Makes one deliberately invalid call (a zero-size buffer) so tests can prove
    /// that validation messages reach the sink. Not for anything else.
    #[doc(hidden)]
    pub fn provoke_validation_error_for_tests(&self) {
        if self.device.debug.sink.is_none() {
            return; // without the layer the invalid call would reach the driver
        }
        let info = vk::BufferCreateInfo::default()
            .size(0)
            .usage(vk::BufferUsageFlags::STORAGE_BUFFER)
            .sharing_mode(vk::SharingMode::EXCLUSIVE);
        // SAFETY: invalid on purpose (size 0), which the validation layer reports and
        // lavapipe tolerates; the buffer is never bound or used, and destroyed at once.
        if let Ok(buffer) = unsafe { self.device.raw.create_buffer(&info, None) } {
            // SAFETY: created just above, unused.
            unsafe { self.device.raw.destroy_buffer(buffer, None) };
        }
    }

    /// The pipeline of `kernel`, created on first use.
    pub(crate) fn pipeline(&self, kernel: Kernel) -> Result<Arc<Pipeline>> {
        if kernel.requires_float_atomics() && !self.device.info.float_atomic_add {
            return Err(EngineError::MissingFeature {
                kernel: kernel.entry_point(),
                feature: "shaderBufferFloat32AtomicAdd",
            });
        }
        if kernel.requires_int64() && !self.device.info.shader_int64 {
            return Err(EngineError::MissingFeature {
                kernel: kernel.entry_point(),
                feature: "shaderInt64",
            });
        }
        if kernel.requires_subgroup_ballot() && !self.device.info.subgroup_ballot {
            return Err(EngineError::MissingFeature {
                kernel: kernel.entry_point(),
                feature: "subgroup ballot and shuffle operations in compute",
            });
        }
        self.device
            .pipelines
            .get_or_create(&self.device.raw, kernel)
    }

    /// How many command buffers this device has submitted (`vkQueueSubmit` calls), for
    /// tests and profiles: a rendered frame should cost one.
    pub fn submission_count(&self) -> u64 {
        self.device.counters.submissions.load(Ordering::Relaxed)
    }

    /// How many times the host has waited on a fence for this device's work (every
    /// `submit_and_wait`, staging copy and [`crate::Submission::wait`], whether or not
    /// the work had finished by then): a frame loop with k frames in flight waits N - k
    /// times over N frames.
    pub fn fence_waits(&self) -> u64 {
        self.device.counters.fence_waits.load(Ordering::Relaxed)
    }

    /// Device memory the engine holds now, from its allocator: what its live buffers and
    /// images use, and the memory blocks it reserved for them (allocations are carved
    /// from blocks, so `reserved_bytes >= allocated_bytes`). For reports such as "the
    /// GPU memory an avatar takes": the difference of two readings around a load.
    pub fn memory_in_use(&self) -> MemoryInUse {
        let report = self
            .device
            .allocator
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .generate_report();
        MemoryInUse {
            allocated_bytes: report.total_allocated_bytes,
            reserved_bytes: report.total_capacity_bytes,
        }
    }

    /// Compute dispatches and pipeline barriers recorded on this device so far (into the
    /// engine's command buffers or the host's): the difference of two readings around a
    /// frame is the frame's work as the GPU's front end sees it, which a launch-bound
    /// frame is made of.
    pub fn recorded_work(&self) -> RecordedWork {
        RecordedWork {
            dispatches: self.device.counters.dispatches.load(Ordering::Relaxed),
            barriers: self.device.counters.barriers.load(Ordering::Relaxed),
        }
    }

    /// Buffers dropped while submissions were pending, whose destruction waits for them
    /// (`retire` in the engine's source): how many wait now, and how many have so far.
    /// A frame loop that drops buffers while frames are in flight defers them instead
    /// of waiting ([`Context::fence_waits`] does not grow); the count now stays bounded.
    pub fn deferred_buffers(&self) -> DeferredBuffers {
        let pending = self
            .device
            .pending
            .lock()
            .unwrap_or_else(|p| p.into_inner());
        DeferredBuffers {
            waiting: pending.deferred_now(),
            total: pending.deferred_total(),
        }
    }

    /// Whether the engine created the device ([`Context::new`]) or borrows the host's
    /// ([`Context::from_raw`]).
    pub fn owns_device(&self) -> bool {
        self.device.owns_device
    }

    /// The raw handles, for an application that records the engine's work into its own
    /// command buffers or builds its own objects beside the engine's.
    pub fn raw_device(&self) -> &ash::Device {
        &self.device.raw
    }

    /// The queue family the engine submits to (and records for).
    pub fn queue_family(&self) -> u32 {
        self.device.queue_family
    }

    /// How many command pools recordings have created: a frame loop reuses the pools
    /// of finished recordings, so this stays flat (for tests).
    pub fn command_pools_created(&self) -> u64 {
        self.device.pools.created()
    }

    /// Names a Vulkan object for validation messages and captures.
    pub(crate) fn set_name<H: vk::Handle>(&self, handle: H, name: &str) {
        if let Some(du) = &self.device.debug.names {
            let Ok(name) = CString::new(name.replace('\0', " ")) else {
                return;
            };
            let info = vk::DebugUtilsObjectNameInfoEXT::default()
                .object_handle(handle)
                .object_name(&name);
            // SAFETY: the handle is a live object of this device.
            let _ = unsafe { du.set_debug_utils_object_name(&info) };
        }
    }
}

impl fmt::Debug for Context {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Context")
            .field("device", &self.device.info.name)
            .finish()
    }
}

/// Destroys a half-built instance (and its messenger) if context creation fails.
struct InstanceGuard {
    instance: Option<ash::Instance>,
    messenger: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
}

impl InstanceGuard {
    #[allow(clippy::type_complexity)]
    fn disarm(
        mut self,
    ) -> (
        ash::Instance,
        Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    ) {
        (
            self.instance.take().expect("disarmed once"),
            self.messenger.take(),
        )
    }
}

impl Drop for InstanceGuard {
    fn drop(&mut self) {
        if let Some((loader, m)) = self.messenger.take() {
            // SAFETY: created from this instance, destroyed once.
            unsafe { loader.destroy_debug_utils_messenger(m, None) };
        }
        if let Some(instance) = self.instance.take() {
            // SAFETY: no device was created from it (or it was destroyed); destroyed once.
            unsafe { instance.destroy_instance(None) };
        }
    }
}

fn choose_device(instance: &ash::Instance, requested: Option<&str>) -> Result<Candidate> {
    // SAFETY: valid instance.
    let physicals = unsafe { instance.enumerate_physical_devices() }
        .vk("vkEnumeratePhysicalDevices", "instance")?;
    let mut all_names = Vec::new();
    let mut rejected = Vec::new();
    let mut eligible = Vec::new();
    for physical in physicals {
        // SAFETY: physical comes from this instance.
        let props = unsafe { instance.get_physical_device_properties(physical) };
        let name = cstr_array(&props.device_name);
        all_names.push(name.clone());
        let mut f12 = vk::PhysicalDeviceVulkan12Features::default();
        let mut f2 = vk::PhysicalDeviceFeatures2::default().push_next(&mut f12);
        // SAFETY: Vulkan 1.1+ query with a valid chain.
        unsafe { instance.get_physical_device_features2(physical, &mut f2) };
        // SAFETY: as above.
        let families = unsafe { instance.get_physical_device_queue_family_properties(physical) };
        let queue_family = families
            .iter()
            .position(|f| f.queue_flags.contains(vk::QueueFlags::COMPUTE));
        let reason = if vk::api_version_major(props.api_version) == 1
            && vk::api_version_minor(props.api_version) < 2
        {
            Some("Vulkan < 1.2")
        } else if f12.vulkan_memory_model == vk::FALSE {
            Some("no vulkanMemoryModel")
        } else if queue_family.is_none() {
            Some("no compute queue")
        } else {
            None
        };
        match (reason, queue_family) {
            (None, Some(qf)) => eligible.push(Candidate {
                physical,
                name,
                kind: DeviceKind::from_vk(props.device_type),
                queue_family: qf as u32,
            }),
            (r, _) => rejected.push(format!("{name}: {}", r.unwrap_or("unusable"))),
        }
    }
    if let Some(wanted) = requested {
        let lower = wanted.to_lowercase();
        return eligible
            .into_iter()
            .find(|c| c.name.to_lowercase().contains(&lower))
            .ok_or(EngineError::DeviceNotFound {
                requested: wanted.to_string(),
                available: all_names,
            });
    }
    eligible.sort_by_key(|c| c.kind);
    eligible
        .into_iter()
        .next()
        .ok_or(EngineError::NoDevice { rejected })
}

/// A created logical device, before it is owned by a [`Device`].
struct DeviceParts {
    raw: ash::Device,
    queue_family: u32,
    queue: vk::Queue,
    allocator: Allocator,
    debug_utils: Option<ash::ext::debug_utils::Device>,
    info: DeviceInfo,
}

fn create_device(
    instance: &ash::Instance,
    c: Candidate,
    has_debug_utils: bool,
) -> Result<DeviceParts> {
    // What the engine needs and uses where present, as a host's device would enable it
    // (choose_device has checked what it requires).
    let mut requirements = device_requirements(instance, c.physical)?;
    requirements.queue_family = c.queue_family;
    let features = requirements.features;
    let info = describe(
        instance,
        &c,
        Enabled {
            float_atomic_add: features.shader_buffer_float32_atomic_add,
            shader_int64: features.shader_int64,
            timeline_semaphore: features.timeline_semaphore,
        },
    );
    let raw = requirements
        .with_create_info(&[], |device_info| {
            // SAFETY: pointers in device_info refer to locals alive for the call.
            unsafe { instance.create_device(c.physical, device_info, None) }
        })
        .vk("vkCreateDevice", &c.name)?;
    // SAFETY: family and index 0 were requested above.
    let queue = unsafe { raw.get_device_queue(c.queue_family, 0) };

    let allocator = Allocator::new(&AllocatorCreateDesc {
        instance: instance.clone(),
        device: raw.clone(),
        physical_device: c.physical,
        debug_settings: {
            let mut d = gpu_allocator::AllocatorDebugSettings::default();
            d.log_leaks_on_shutdown = true;
            d
        },
        buffer_device_address: false,
        allocation_sizes: gpu_allocator::AllocationSizes::default(),
    });
    let allocator = match allocator {
        Ok(a) => a,
        Err(e) => {
            // SAFETY: nothing was created from the device yet.
            unsafe { raw.destroy_device(None) };
            return Err(EngineError::Allocation {
                what: "allocator".into(),
                detail: e.to_string(),
            });
        }
    };
    let debug_utils = has_debug_utils.then(|| ash::ext::debug_utils::Device::new(instance, &raw));
    Ok(DeviceParts {
        raw,
        queue_family: c.queue_family,
        queue,
        allocator,
        debug_utils,
        info,
    })
}

/// The optional features a logical device has enabled.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Enabled {
    pub(crate) float_atomic_add: bool,
    pub(crate) shader_int64: bool,
    pub(crate) timeline_semaphore: bool,
}

/// What device `c` is and can do, with the optional features as enabled on the
/// logical device.
pub(crate) fn describe(instance: &ash::Instance, c: &Candidate, enabled: Enabled) -> DeviceInfo {
    let Enabled {
        float_atomic_add,
        shader_int64,
        timeline_semaphore,
    } = enabled;
    // SAFETY: a query on a physical device of this instance.
    let props = unsafe { instance.get_physical_device_properties(c.physical) };
    let mut subgroup = vk::PhysicalDeviceSubgroupProperties::default();
    let mut driver = vk::PhysicalDeviceDriverProperties::default();
    let mut maintenance3 = vk::PhysicalDeviceMaintenance3Properties::default();
    let mut p2 = vk::PhysicalDeviceProperties2::default()
        .push_next(&mut subgroup)
        .push_next(&mut driver)
        .push_next(&mut maintenance3);
    // SAFETY: valid chain of Vulkan 1.1/1.2 property structs.
    unsafe { instance.get_physical_device_properties2(c.physical, &mut p2) };
    // SAFETY: query on a physical device of this instance.
    let families = unsafe { instance.get_physical_device_queue_family_properties(c.physical) };
    let timestamp_valid_bits = families[c.queue_family as usize].timestamp_valid_bits;

    DeviceInfo {
        name: c.name.clone(),
        kind: c.kind,
        api_version: (
            vk::api_version_major(props.api_version),
            vk::api_version_minor(props.api_version),
            vk::api_version_patch(props.api_version),
        ),
        driver: format!(
            "{} {}",
            cstr_array(&driver.driver_name),
            cstr_array(&driver.driver_info)
        ),
        subgroup_size: subgroup.subgroup_size,
        timestamp_period_ns: f64::from(props.limits.timestamp_period),
        timestamp_valid_bits,
        float_atomic_add,
        subgroup_ballot: subgroup
            .supported_stages
            .contains(vk::ShaderStageFlags::COMPUTE)
            && subgroup
                .supported_operations
                .contains(vk::SubgroupFeatureFlags::BALLOT | vk::SubgroupFeatureFlags::SHUFFLE),
        shader_int64,
        timeline_semaphore,
        max_compute_workgroup_count: props.limits.max_compute_work_group_count,
        max_storage_buffer_range: u64::from(props.limits.max_storage_buffer_range),
        max_memory_allocation_size: maintenance3.max_memory_allocation_size,
        min_storage_buffer_offset_alignment: props.limits.min_storage_buffer_offset_alignment,
        max_texel_buffer_elements: u64::from(props.limits.max_texel_buffer_elements),
    }
}

impl Device {
    /// Frees the deferred buffers whose submissions have finished (a poll, no wait).
    pub(crate) fn retire_finished(&self) {
        let done = {
            let mut pending = self.pending.lock().unwrap_or_else(|p| p.into_inner());
            // SAFETY: registered fences are live fences of this device: a submission
            // removes its fence under this lock before it destroys it.
            unsafe { pending.take_finished(&self.raw) }
        };
        for b in done {
            // SAFETY: every submission pending at the buffer's drop has finished.
            unsafe { b.destroy(&self.raw, &self.allocator) };
        }
    }

    /// A dropped buffer's objects: destroyed now when no submission is pending, else
    /// deferred until those pending now have finished (no wait either way).
    pub(crate) fn free_buffer(&self, buffer: crate::retire::DeferredBuffer) {
        let now = self
            .pending
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .defer(buffer);
        match now {
            // SAFETY: no engine submission is pending, so none uses it; work in the
            // host's command buffers is the host's to finish first (`HostCommandBuffer`).
            Some(b) => unsafe { b.destroy(&self.raw, &self.allocator) },
            None => self.retire_finished(),
        }
    }
}

impl Drop for Device {
    fn drop(&mut self) {
        // Fences of leaked submissions: wait for their work, then destroy them, and the
        // buffers deferred behind them.
        let (leaked, deferred) = {
            let mut pending = self.pending.lock().unwrap_or_else(|p| p.into_inner());
            (pending.take_fences(), pending.take_deferred())
        };
        if !leaked.is_empty() {
            // SAFETY: live fences of this device, destroyed once after their work ended.
            unsafe {
                let _ = self.raw.wait_for_fences(&leaked, true, u64::MAX);
                for f in leaked {
                    self.raw.destroy_fence(f, None);
                }
            }
        }
        for b in deferred {
            // SAFETY: every engine submission has finished (waited just above).
            unsafe { b.destroy(&self.raw, &self.allocator) };
        }
        if self.owns_device {
            // SAFETY: the device is valid; nothing else uses it (we are its last owner).
            unsafe {
                let _ = self.raw.device_wait_idle();
            }
        }
        // A borrowed device is not waited on (the host's other queues may be busy, and
        // vkDeviceWaitIdle would need them all externally synchronised): every engine
        // submission holds an Arc<Device> until its fence was waited, so none of the
        // objects below is in use when the last Arc goes.
        self.pools.destroy_all(&self.raw);
        self.pipelines.destroy_all(&self.raw);
        // SAFETY: dropped exactly once, here, before the device it allocates from.
        unsafe { ManuallyDrop::drop(&mut self.allocator) };
        if !self.owns_device {
            return; // the host's device and instance: the host destroys them
        }
        // SAFETY: all objects of the device are gone: buffers and recordings hold an
        // Arc<Device>, so none outlives this drop.
        unsafe { self.raw.destroy_device(None) };
        if let Some((loader, m)) = self.debug.messenger.take() {
            // SAFETY: created from this instance, destroyed once, before the instance.
            unsafe { loader.destroy_debug_utils_messenger(m, None) };
        }
        // SAFETY: every child object is destroyed.
        unsafe { self.instance.destroy_instance(None) };
    }
}
