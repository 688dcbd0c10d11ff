//! A host application's side of Vulkan for the embedding tests (the engine's, the
//! trainer's and the C ABI's): the test's own instance (validation and synchronization
//! validation on, messages collected), device (what `device_requirements` lists), queue,
//! command pool, and an `R32G32B32A32_SFLOAT` image with a read-back buffer.
#![allow(unsafe_code)]
// SAFETY (every block in this module): plain Vulkan calls on objects this module created
// and destroys in order; arguments are locals alive for each call.
#![allow(clippy::undocumented_unsafe_blocks)]

use std::ffi::CString;
use std::sync::Arc;

use drape_engine::ash::{self, vk};
use drape_engine::validation::{messenger_info, ValidationSink};
use drape_engine::{device_requirements, Context, DeviceFeatures, ExternalOptions, ExternalVulkan};

/// The test's own Vulkan objects.
pub struct Host {
    pub entry: ash::Entry,
    pub instance: ash::Instance,
    pub messenger: (ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT),
    pub sink: Arc<ValidationSink>,
    pub physical: vk::PhysicalDevice,
    pub device: ash::Device,
    pub family: u32,
    pub queue: vk::Queue,
    pub features: DeviceFeatures,
    pub extensions: Vec<CString>,
    pub pool: vk::CommandPool,
}

impl Host {
    /// An instance with validation (and synchronization validation), the test device
    /// (`DRAPE_DEVICE`), and a device with what `device_requirements` lists (without
    /// float atomics if asked).
    pub fn new(without_float_atomics: bool) -> Self {
        // SAFETY (every block in this test file): plain Vulkan calls on objects this test
        // created and destroys in order; arguments are locals alive for each call.
        let entry = unsafe { ash::Entry::load() }.expect("loader");
        let app = vk::ApplicationInfo::default()
            .application_name(c"drape embedding test")
            .api_version(vk::API_VERSION_1_2);
        let layers = [c"VK_LAYER_KHRONOS_validation".as_ptr()];
        let exts = [
            ash::ext::debug_utils::NAME.as_ptr(),
            ash::ext::validation_features::NAME.as_ptr(),
        ];
        let enables = [vk::ValidationFeatureEnableEXT::SYNCHRONIZATION_VALIDATION];
        let mut features =
            vk::ValidationFeaturesEXT::default().enabled_validation_features(&enables);
        let info = vk::InstanceCreateInfo::default()
            .application_info(&app)
            .enabled_layer_names(&layers)
            .enabled_extension_names(&exts)
            .push_next(&mut features);
        let instance = unsafe { entry.create_instance(&info, None) }.expect("instance");
        let sink = Arc::new(ValidationSink::default());
        let du = ash::ext::debug_utils::Instance::new(&entry, &instance);
        // Validation only: the layer's performance warnings advise TRANSFER_*_OPTIMAL
        // over GENERAL, which the record-into test keeps on purpose.
        let info =
            messenger_info(&sink).message_type(vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION);
        let messenger = unsafe { du.create_debug_utils_messenger(&info, None) }.expect("messenger");
        let wanted = std::env::var("DRAPE_DEVICE")
            .unwrap_or_default()
            .to_lowercase();
        let physical = unsafe { instance.enumerate_physical_devices() }
            .expect("devices")
            .into_iter()
            .find(|&p| {
                let props = unsafe { instance.get_physical_device_properties(p) };
                let name = props
                    .device_name_as_c_str()
                    .map(|n| n.to_string_lossy().to_lowercase())
                    .unwrap_or_default();
                name.contains(&wanted) && props.api_version >= vk::API_VERSION_1_2
            })
            .expect("the test device");
        let mut req = device_requirements(&instance, physical).expect("requirements");
        if without_float_atomics {
            req.features.shader_buffer_float32_atomic_add = false;
            req.extensions.clear();
        }
        let f = req.features;
        let extensions: Vec<CString> = req.extensions.iter().map(|e| CString::from(*e)).collect();
        let device = req
            .with_create_info(&[], |info| unsafe {
                instance.create_device(physical, info, None)
            })
            .expect("device");
        let queue = unsafe { device.get_device_queue(req.queue_family, 0) };
        let pool = unsafe {
            device.create_command_pool(
                &vk::CommandPoolCreateInfo::default().queue_family_index(req.queue_family),
                None,
            )
        }
        .expect("pool");
        Host {
            entry,
            instance,
            messenger: (du, messenger),
            sink,
            physical,
            device,
            family: req.queue_family,
            queue,
            features: f,
            extensions,
            pool,
        }
    }

    pub fn external(&self) -> ExternalVulkan {
        ExternalVulkan {
            entry: self.entry.clone(),
            instance: self.instance.clone(),
            physical_device: self.physical,
            device: self.device.clone(),
            queue_family: self.family,
            queue_index: 0,
            api_version: vk::API_VERSION_1_2,
            enabled_extensions: self.extensions.clone(),
            enabled_features: self.features,
            debug_utils: true,
        }
    }

    pub fn context(&self) -> Context {
        let options = ExternalOptions {
            poison_new_buffers: true,
            force_staging: false,
        };
        unsafe { Context::from_raw(self.external(), options) }.expect("from_raw")
    }

    pub fn memory_type(&self, bits: u32, flags: vk::MemoryPropertyFlags) -> u32 {
        let props = unsafe {
            self.instance
                .get_physical_device_memory_properties(self.physical)
        };
        (0..props.memory_type_count)
            .find(|&i| {
                bits & (1 << i) != 0
                    && props.memory_types[i as usize]
                        .property_flags
                        .contains(flags)
            })
            .expect("memory type")
    }

    /// An RGBA32F image the size of the render, and a host-visible buffer to read it.
    pub fn image_and_readback(&self, w: u32, h: u32) -> Target {
        let info = vk::ImageCreateInfo::default()
            .image_type(vk::ImageType::TYPE_2D)
            .format(vk::Format::R32G32B32A32_SFLOAT)
            .extent(vk::Extent3D {
                width: w,
                height: h,
                depth: 1,
            })
            .mip_levels(1)
            .array_layers(1)
            .samples(vk::SampleCountFlags::TYPE_1)
            .tiling(vk::ImageTiling::OPTIMAL)
            .usage(vk::ImageUsageFlags::TRANSFER_DST | vk::ImageUsageFlags::TRANSFER_SRC);
        let image = unsafe { self.device.create_image(&info, None) }.expect("image");
        let req = unsafe { self.device.get_image_memory_requirements(image) };
        let alloc = vk::MemoryAllocateInfo::default()
            .allocation_size(req.size)
            .memory_type_index(
                self.memory_type(req.memory_type_bits, vk::MemoryPropertyFlags::DEVICE_LOCAL),
            );
        let image_memory =
            unsafe { self.device.allocate_memory(&alloc, None) }.expect("image memory");
        unsafe { self.device.bind_image_memory(image, image_memory, 0) }.expect("bind");
        let bytes = 16 * u64::from(w) * u64::from(h);
        let buffer = unsafe {
            self.device.create_buffer(
                &vk::BufferCreateInfo::default()
                    .size(bytes)
                    .usage(vk::BufferUsageFlags::TRANSFER_DST),
                None,
            )
        }
        .expect("buffer");
        let req = unsafe { self.device.get_buffer_memory_requirements(buffer) };
        let host = vk::MemoryPropertyFlags::HOST_VISIBLE | vk::MemoryPropertyFlags::HOST_COHERENT;
        let alloc = vk::MemoryAllocateInfo::default()
            .allocation_size(req.size)
            .memory_type_index(self.memory_type(req.memory_type_bits, host));
        let buffer_memory =
            unsafe { self.device.allocate_memory(&alloc, None) }.expect("buffer memory");
        unsafe { self.device.bind_buffer_memory(buffer, buffer_memory, 0) }.expect("bind");
        Target {
            image,
            image_memory,
            buffer,
            buffer_memory,
            w,
            h,
        }
    }

    pub fn begin(&self) -> vk::CommandBuffer {
        let info = vk::CommandBufferAllocateInfo::default()
            .command_pool(self.pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(1);
        let cmd =
            unsafe { self.device.allocate_command_buffers(&info) }.expect("command buffer")[0];
        unsafe {
            self.device
                .begin_command_buffer(cmd, &vk::CommandBufferBeginInfo::default())
        }
        .expect("begin");
        cmd
    }

    /// Ends and submits `cmd` (waiting on `wait` at transfer) and waits for its fence.
    pub fn submit(&self, cmd: vk::CommandBuffer, wait: Option<(vk::Semaphore, u64)>) {
        unsafe { self.device.end_command_buffer(cmd) }.expect("end");
        let fence = unsafe {
            self.device
                .create_fence(&vk::FenceCreateInfo::default(), None)
        }
        .expect("fence");
        let cmds = [cmd];
        let (sems, values, stages): (Vec<_>, Vec<_>, Vec<_>) = match wait {
            Some((s, v)) => (vec![s], vec![v], vec![vk::PipelineStageFlags::TRANSFER]),
            None => (vec![], vec![], vec![]),
        };
        let mut timeline =
            vk::TimelineSemaphoreSubmitInfo::default().wait_semaphore_values(&values);
        let submit = vk::SubmitInfo::default()
            .command_buffers(&cmds)
            .wait_semaphores(&sems)
            .wait_dst_stage_mask(&stages)
            .push_next(&mut timeline);
        unsafe { self.device.queue_submit(self.queue, &[submit], fence) }.expect("submit");
        unsafe { self.device.wait_for_fences(&[fence], true, u64::MAX) }.expect("wait");
        unsafe { self.device.destroy_fence(fence, None) };
        unsafe { self.device.free_command_buffers(self.pool, &cmds) };
    }

    pub fn image_barrier(
        &self,
        cmd: vk::CommandBuffer,
        image: vk::Image,
        from: (vk::ImageLayout, vk::PipelineStageFlags, vk::AccessFlags),
        to: (vk::ImageLayout, vk::PipelineStageFlags, vk::AccessFlags),
    ) {
        let range = vk::ImageSubresourceRange::default()
            .aspect_mask(vk::ImageAspectFlags::COLOR)
            .level_count(1)
            .layer_count(1);
        let barrier = vk::ImageMemoryBarrier::default()
            .old_layout(from.0)
            .new_layout(to.0)
            .src_access_mask(from.2)
            .dst_access_mask(to.2)
            .src_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
            .dst_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
            .image(image)
            .subresource_range(range);
        unsafe {
            self.device.cmd_pipeline_barrier(
                cmd,
                from.1,
                to.1,
                vk::DependencyFlags::empty(),
                &[],
                &[],
                &[barrier],
            )
        };
    }

    /// Records the image's copy into the read-back buffer (after the documented "after"
    /// barrier, from TRANSFER_DST to TRANSFER_SRC).
    pub fn record_readback(&self, cmd: vk::CommandBuffer, t: &Target) {
        let t_write = (
            vk::ImageLayout::TRANSFER_DST_OPTIMAL,
            vk::PipelineStageFlags::TRANSFER,
            vk::AccessFlags::TRANSFER_WRITE,
        );
        self.image_barrier(
            cmd,
            t.image,
            t_write,
            (
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                vk::PipelineStageFlags::TRANSFER,
                vk::AccessFlags::TRANSFER_READ,
            ),
        );
        let region = vk::BufferImageCopy::default()
            .image_subresource(
                vk::ImageSubresourceLayers::default()
                    .aspect_mask(vk::ImageAspectFlags::COLOR)
                    .layer_count(1),
            )
            .image_extent(vk::Extent3D {
                width: t.w,
                height: t.h,
                depth: 1,
            });
        unsafe {
            self.device.cmd_copy_image_to_buffer(
                cmd,
                t.image,
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                t.buffer,
                &[region],
            )
        };
    }

    pub fn read(&self, t: &Target) -> Vec<f32> {
        let n = 4 * t.w as usize * t.h as usize;
        let ptr = unsafe {
            self.device.map_memory(
                t.buffer_memory,
                0,
                vk::WHOLE_SIZE,
                vk::MemoryMapFlags::empty(),
            )
        }
        .expect("map");
        let out = unsafe { std::slice::from_raw_parts(ptr as *const f32, n) }.to_vec();
        unsafe { self.device.unmap_memory(t.buffer_memory) };
        out
    }

    pub fn destroy_target(&self, t: Target) {
        unsafe {
            self.device.destroy_image(t.image, None);
            self.device.free_memory(t.image_memory, None);
            self.device.destroy_buffer(t.buffer, None);
            self.device.free_memory(t.buffer_memory, None);
        }
    }

    /// Destroys everything and returns the validation messages of the whole test.
    pub fn finish(self) -> Vec<String> {
        unsafe {
            self.device.destroy_command_pool(self.pool, None);
            self.device.destroy_device(None);
            self.messenger
                .0
                .destroy_debug_utils_messenger(self.messenger.1, None);
            self.instance.destroy_instance(None);
        }
        self.sink.drain()
    }
}

pub struct Target {
    pub image: vk::Image,
    pub image_memory: vk::DeviceMemory,
    pub buffer: vk::Buffer,
    pub buffer_memory: vk::DeviceMemory,
    pub w: u32,
    pub h: u32,
}
