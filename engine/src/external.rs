//! A context over the host application's Vulkan objects ([`Context::from_raw`]), and what
//! the host must enable on its device before it creates it ([`device_requirements`]).
//!
//! Ownership: the host creates and destroys the instance, the physical-device choice, the
//! device and the queue. The engine borrows them and never destroys them; it creates and
//! destroys only its own objects on that device (buffers and their memory through its own
//! `gpu-allocator`, pipelines, descriptor and command pools, fences). The context must be
//! dropped before the host destroys the device, and only when none of its submissions is
//! pending (every [`crate::Submission`] waits for itself when dropped; a
//! [`crate::HostRecorded`] must outlive the host's submission of its command buffer).
//!
//! Queue access: Vulkan requires `vkQueueSubmit` on one queue to be externally
//! synchronised. The engine serialises its own submissions with a mutex; the host must
//! not submit to the same queue from another thread while an engine call that submits
//! (`submit`, `submit_and_wait`, uploads and read-backs through staging) runs.

use std::ffi::{CStr, CString};
use std::mem::ManuallyDrop;
use std::sync::{Arc, Mutex};

use ash::vk;
use gpu_allocator::vulkan::{Allocator, AllocatorCreateDesc};

use crate::context::{
    cstr_array, describe, BufferPolicy, Candidate, Context, DebugHooks, Device, DeviceKind, Enabled,
};
use crate::error::{EngineError, Result};
pub use crate::requirements::{device_requirements, DeviceFeatures, DeviceRequirements};

/// The host's Vulkan objects, borrowed by [`Context::from_raw`].
#[derive(Clone)]
pub struct ExternalVulkan {
    /// The loader the host's instance came from.
    pub entry: ash::Entry,
    /// The host's instance.
    pub instance: ash::Instance,
    /// The physical device the host's device was created on.
    pub physical_device: vk::PhysicalDevice,
    /// The host's logical device.
    pub device: ash::Device,
    /// The family of the queue the engine submits to; it must support compute.
    pub queue_family: u32,
    /// The index of that queue in its family.
    pub queue_index: u32,
    /// `VkApplicationInfo::apiVersion` the instance was created with (at least 1.2).
    pub api_version: u32,
    /// The device extensions the host enabled (names as in `VkDeviceCreateInfo`).
    pub enabled_extensions: Vec<CString>,
    /// The features the host enabled.
    pub enabled_features: DeviceFeatures,
    /// Whether the instance has `VK_EXT_debug_utils` enabled: the engine then names its
    /// objects for validation messages and captures.
    pub debug_utils: bool,
}

impl std::fmt::Debug for ExternalVulkan {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ExternalVulkan")
            .field("physical_device", &self.physical_device)
            .field("device", &self.device.handle())
            .field("queue_family", &self.queue_family)
            .field("queue_index", &self.queue_index)
            .field("enabled_extensions", &self.enabled_extensions)
            .field("enabled_features", &self.enabled_features)
            .finish()
    }
}

/// Options of a context over the host's device (the rest of [`crate::ContextDesc`] is
/// the host's: device choice and validation layers belong to its instance).
#[derive(Clone, Copy, Debug, Default)]
pub struct ExternalOptions {
    /// See [`crate::ContextDesc::poison_new_buffers`].
    pub poison_new_buffers: bool,
    /// See [`crate::ContextDesc::force_staging`].
    pub force_staging: bool,
}

impl Context {
    /// A context over the host's instance, device and queue (see the module header for
    /// who owns what and who synchronises the queue). Float atomics and 64-bit integers
    /// are used where the host enabled them; a device without them gets the
    /// compare-and-swap and 32-bit kernels. A missing required feature is
    /// [`EngineError::HostDeviceMissing`] naming it.
    ///
    /// # Safety
    /// Every handle in `external` is valid and stays valid until the returned context and
    /// everything made from it are dropped; `enabled_extensions` and `enabled_features`
    /// say what the device was really created with; the queue exists.
    pub unsafe fn from_raw(external: ExternalVulkan, options: ExternalOptions) -> Result<Self> {
        let ExternalVulkan {
            entry,
            instance,
            physical_device,
            device,
            queue_family,
            queue_index,
            api_version,
            enabled_extensions,
            enabled_features,
            debug_utils,
        } = external;
        let f = enabled_features;
        if api_version < vk::API_VERSION_1_2 {
            return Err(EngineError::HostDeviceMissing {
                what: "Vulkan 1.2",
                hint: "create the instance with apiVersion VK_API_VERSION_1_2 or later",
            });
        }
        if !f.vulkan_memory_model {
            return Err(EngineError::HostDeviceMissing { what: "vulkanMemoryModel", hint: "set VkPhysicalDeviceVulkan12Features::vulkanMemoryModel when creating the device (drape_engine::external::device_requirements lists what to enable)" });
        }
        let has = |name: &CStr| enabled_extensions.iter().any(|e| e.as_c_str() == name);
        if f.shader_buffer_float32_atomic_add && !has(ash::ext::shader_atomic_float::NAME) {
            return Err(EngineError::HostDeviceMissing {
                what: "VK_EXT_shader_atomic_float",
                hint: "shaderBufferFloat32AtomicAdd was said enabled without its extension",
            });
        }
        // SAFETY: the caller's instance and physical device.
        let props = unsafe { instance.get_physical_device_properties(physical_device) };
        // SAFETY: as above.
        let families =
            unsafe { instance.get_physical_device_queue_family_properties(physical_device) };
        match families.get(queue_family as usize) {
            Some(fam) if fam.queue_flags.contains(vk::QueueFlags::COMPUTE) && queue_index < fam.queue_count => {}
            _ => return Err(EngineError::HostDeviceMissing { what: "a compute queue", hint: "queue_family must name a family with VK_QUEUE_COMPUTE_BIT, and queue_index one of its queues" }),
        }
        let candidate = Candidate {
            physical: physical_device,
            name: cstr_array(&props.device_name),
            kind: DeviceKind::from_vk(props.device_type),
            queue_family,
        };
        let info = describe(
            &instance,
            &candidate,
            Enabled {
                float_atomic_add: f.shader_buffer_float32_atomic_add,
                shader_int64: f.shader_int64,
                timeline_semaphore: f.timeline_semaphore,
            },
        );
        // SAFETY: the caller guarantees the queue exists (checked against the family above).
        let queue = unsafe { device.get_device_queue(queue_family, queue_index) };
        let allocator = Allocator::new(&AllocatorCreateDesc {
            instance: instance.clone(),
            device: device.clone(),
            physical_device,
            debug_settings: {
                let mut d = gpu_allocator::AllocatorDebugSettings::default();
                d.log_leaks_on_shutdown = true;
                d
            },
            buffer_device_address: false,
            allocation_sizes: gpu_allocator::AllocationSizes::default(),
        })
        .map_err(|e| EngineError::Allocation {
            what: "allocator".into(),
            detail: e.to_string(),
        })?;
        let debug_utils =
            debug_utils.then(|| ash::ext::debug_utils::Device::new(&instance, &device));
        let dev = Device {
            raw: device,
            instance,
            queue_family,
            queue: Mutex::new(queue),
            allocator: ManuallyDrop::new(Mutex::new(allocator)),
            debug: DebugHooks {
                names: debug_utils,
                ..Default::default()
            },
            pipelines: Default::default(),
            info,
            buffers: BufferPolicy {
                poison: options.poison_new_buffers,
                force_staging: options.force_staging,
            },
            profile: Mutex::new(None),
            pools: Default::default(),
            counters: Default::default(),
            pending: Mutex::new(Default::default()),
            owns_device: false,
            _entry: entry,
        };
        let ctx = Context {
            device: Arc::new(dev),
        };
        crate::kernels::check_manifest()?;
        Ok(ctx)
    }
}
