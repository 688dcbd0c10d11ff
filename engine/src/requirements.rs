//! What the engine needs of a device and what it uses where present
//! ([`device_requirements`]), and the one `VkDeviceCreateInfo` that enables it
//! ([`DeviceRequirements::with_create_info`]): the engine's own device, a host's (the
//! viewer's, the test host's) and any embedder's are created from it. A leaf: it knows
//! the physical device, not the engine's device. Re-exported from [`crate::external`].

use std::ffi::{c_char, CStr};

use ash::vk;

use crate::error::{EngineError, Result, VkResultExt};

/// The device features the engine reads, as the host enabled them (or, from
/// [`device_requirements`], as it should).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DeviceFeatures {
    /// `vulkanMemoryModel` (Vulkan 1.2): required; every kernel declares the capability.
    pub vulkan_memory_model: bool,
    /// `vulkanMemoryModelDeviceScope` (Vulkan 1.2): used where present.
    pub vulkan_memory_model_device_scope: bool,
    /// `timelineSemaphore` (Vulkan 1.2): needed by timeline waits and signals in
    /// [`crate::SubmitSync`]; binary semaphores work without it.
    pub timeline_semaphore: bool,
    /// `shaderInt64`: the chunked sort's 64-bit pairs; without it the 32-bit sort.
    pub shader_int64: bool,
    /// `shaderBufferFloat32AtomicAdd` of `VK_EXT_shader_atomic_float`: gradient
    /// accumulation by float atomics; without it the compare-and-swap kernels.
    pub shader_buffer_float32_atomic_add: bool,
}

/// What a host must enable on `physical_device` for the engine, and what it may.
#[derive(Clone, Debug)]
pub struct DeviceRequirements {
    /// The lowest `apiVersion` of the instance and device: Vulkan 1.2.
    pub api_version: u32,
    /// A queue family with compute (the first), to create a queue in.
    pub queue_family: u32,
    /// Features the engine needs (`vulkan_memory_model`) and those it uses where the
    /// device has them: enable every one set here.
    pub features: DeviceFeatures,
    /// Device extensions to enable with them (`VK_EXT_shader_atomic_float` where the
    /// device has float atomics).
    pub extensions: Vec<&'static CStr>,
}

/// What to enable on `physical_device` before creating the device the engine will use
/// ([`crate::Context::from_raw`]). An error names what the device lacks.
pub fn device_requirements(
    instance: &ash::Instance,
    physical_device: vk::PhysicalDevice,
) -> Result<DeviceRequirements> {
    // SAFETY: the caller's instance and one of its physical devices.
    let props = unsafe { instance.get_physical_device_properties(physical_device) };
    if props.api_version < vk::API_VERSION_1_2 {
        return Err(EngineError::HostDeviceMissing {
            what: "Vulkan 1.2",
            hint: "the physical device reports an older API version",
        });
    }
    // SAFETY: as above.
    let extensions = unsafe { instance.enumerate_device_extension_properties(physical_device) }
        .vk("vkEnumerateDeviceExtensionProperties", "host device")?;
    let has_float_ext = extensions
        .iter()
        .any(|e| e.extension_name_as_c_str() == Ok(ash::ext::shader_atomic_float::NAME));
    let mut atomic_float = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default();
    let mut f12 = vk::PhysicalDeviceVulkan12Features::default();
    let mut f2 = vk::PhysicalDeviceFeatures2::default().push_next(&mut f12);
    if has_float_ext {
        f2 = f2.push_next(&mut atomic_float);
    }
    // SAFETY: as above, with a valid chain.
    unsafe { instance.get_physical_device_features2(physical_device, &mut f2) };
    let shader_int64 = f2.features.shader_int64 == vk::TRUE;
    if f12.vulkan_memory_model != vk::TRUE {
        return Err(EngineError::HostDeviceMissing {
            what: "vulkanMemoryModel",
            hint: "the physical device does not support it",
        });
    }
    // SAFETY: as above.
    let families = unsafe { instance.get_physical_device_queue_family_properties(physical_device) };
    let queue_family = families
        .iter()
        .position(|f| f.queue_flags.contains(vk::QueueFlags::COMPUTE))
        .ok_or(EngineError::HostDeviceMissing {
            what: "a compute queue",
            hint: "no queue family of the physical device has VK_QUEUE_COMPUTE_BIT",
        })? as u32;
    let float_atomics = has_float_ext && atomic_float.shader_buffer_float32_atomic_add == vk::TRUE;
    Ok(DeviceRequirements {
        api_version: vk::API_VERSION_1_2,
        queue_family,
        features: DeviceFeatures {
            vulkan_memory_model: true,
            vulkan_memory_model_device_scope: f12.vulkan_memory_model_device_scope == vk::TRUE,
            timeline_semaphore: f12.timeline_semaphore == vk::TRUE,
            shader_int64,
            shader_buffer_float32_atomic_add: float_atomics,
        },
        extensions: if float_atomics {
            vec![ash::ext::shader_atomic_float::NAME]
        } else {
            vec![]
        },
    })
}

impl DeviceRequirements {
    /// Calls `f` with the `VkDeviceCreateInfo` of a device with everything these
    /// requirements list enabled (their features, their extensions and
    /// `extra_extensions`, one queue of `queue_family`), for `vkCreateDevice`. The info
    /// points into locals that live only during `f`.
    pub fn with_create_info<R>(
        &self,
        extra_extensions: &[&CStr],
        f: impl FnOnce(&vk::DeviceCreateInfo<'_>) -> R,
    ) -> R {
        let features = self.features;
        let extensions: Vec<*const c_char> = self
            .extensions
            .iter()
            .chain(extra_extensions)
            .map(|e| e.as_ptr())
            .collect();
        let mut f12 = vk::PhysicalDeviceVulkan12Features::default()
            .vulkan_memory_model(features.vulkan_memory_model)
            .vulkan_memory_model_device_scope(features.vulkan_memory_model_device_scope)
            .timeline_semaphore(features.timeline_semaphore);
        let mut atomic_float = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default()
            .shader_buffer_float32_atomic_add(features.shader_buffer_float32_atomic_add);
        let core = vk::PhysicalDeviceFeatures::default().shader_int64(features.shader_int64);
        let priorities = [1.0f32];
        let queues = [vk::DeviceQueueCreateInfo::default()
            .queue_family_index(self.queue_family)
            .queue_priorities(&priorities)];
        let mut info = vk::DeviceCreateInfo::default()
            .queue_create_infos(&queues)
            .enabled_extension_names(&extensions)
            .enabled_features(&core)
            .push_next(&mut f12);
        if features.shader_buffer_float32_atomic_add {
            info = info.push_next(&mut atomic_float);
        }
        f(&info)
    }
}
