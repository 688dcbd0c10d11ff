//! The engine inside an application that owns its Vulkan device: the test creates its
//! own instance and device with `ash`, hands them over with `Context::from_raw`, renders
//! the tiny run's avatar into an image it owns (signalling a timeline semaphore it waits
//! on, or recorded into its own command buffer), and compares the pixels with the
//! owned-context path. Validation (with synchronization validation) runs on the test's
//! instance and must stay silent, leaks included; a host barrier left out must show.

use std::ffi::CString;
use std::sync::Arc;

use drape_engine::ash::{self, vk};
use drape_engine::validation::{messenger_info, ValidationSink};
use drape_engine::ops::accumulate::{Accumulation, Method};
use drape_engine::{device_requirements, Context, ContextDesc, DeviceFeatures, ExternalOptions, ExternalVulkan, HostCommandBuffer, ImageTarget, SubmitSync};
use drape_trainer::avatar::player::{AvatarPlayer, ViewCamera};
use drape_trainer::testing::tiny_run;

/// Largest difference between the from_raw and owned-context renders: the same device
/// and kernels on the same inputs; only a different order of equal floats could differ.
const SAME_DEVICE_TOLERANCE: f32 = 1e-5;

/// The test's own Vulkan objects.
struct Host {
    entry: ash::Entry,
    instance: ash::Instance,
    messenger: (ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT),
    sink: Arc<ValidationSink>,
    physical: vk::PhysicalDevice,
    device: ash::Device,
    family: u32,
    queue: vk::Queue,
    features: DeviceFeatures,
    extensions: Vec<CString>,
    pool: vk::CommandPool,
}

impl Host {
    /// An instance with validation (and synchronization validation), the test device,
    /// and a device with what `device_requirements` lists, minus `drop` features.
    fn new(without_float_atomics: bool) -> Self {
        // SAFETY (every block in this test file): plain Vulkan calls on objects this test
        // created and destroys in order; arguments are locals alive for each call.
        let entry = unsafe { ash::Entry::load() }.expect("loader");
        let app = vk::ApplicationInfo::default().application_name(c"drape embedding test").api_version(vk::API_VERSION_1_2);
        let layers = [c"VK_LAYER_KHRONOS_validation".as_ptr()];
        let exts = [ash::ext::debug_utils::NAME.as_ptr(), ash::ext::validation_features::NAME.as_ptr()];
        let enables = [vk::ValidationFeatureEnableEXT::SYNCHRONIZATION_VALIDATION];
        let mut features = vk::ValidationFeaturesEXT::default().enabled_validation_features(&enables);
        let info = vk::InstanceCreateInfo::default().application_info(&app).enabled_layer_names(&layers).enabled_extension_names(&exts).push_next(&mut features);
        let instance = unsafe { entry.create_instance(&info, None) }.expect("instance");
        let sink = Arc::new(ValidationSink::default());
        let du = ash::ext::debug_utils::Instance::new(&entry, &instance);
        // Validation only: the layer's performance warnings advise TRANSFER_*_OPTIMAL
        // over GENERAL, which the record-into test keeps on purpose.
        let info = messenger_info(&sink).message_type(vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION);
        let messenger = unsafe { du.create_debug_utils_messenger(&info, None) }.expect("messenger");
        let wanted = std::env::var("DRAPE_DEVICE").unwrap_or_default().to_lowercase();
        let physical = unsafe { instance.enumerate_physical_devices() }
            .expect("devices")
            .into_iter()
            .find(|&p| {
                let props = unsafe { instance.get_physical_device_properties(p) };
                let name = props.device_name_as_c_str().map(|n| n.to_string_lossy().to_lowercase()).unwrap_or_default();
                name.contains(&wanted) && props.api_version >= vk::API_VERSION_1_2
            })
            .expect("the test device");
        let req = device_requirements(&instance, physical).expect("requirements");
        let mut f = req.features;
        let mut extensions: Vec<CString> = req.extensions.iter().map(|e| CString::from(*e)).collect();
        if without_float_atomics {
            f.shader_buffer_float32_atomic_add = false;
            extensions.clear();
        }
        let ext_ptrs: Vec<_> = extensions.iter().map(|e| e.as_ptr()).collect();
        let mut f12 = vk::PhysicalDeviceVulkan12Features::default()
            .vulkan_memory_model(f.vulkan_memory_model)
            .vulkan_memory_model_device_scope(f.vulkan_memory_model_device_scope)
            .timeline_semaphore(f.timeline_semaphore);
        let mut atomics = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default().shader_buffer_float32_atomic_add(true);
        let core = vk::PhysicalDeviceFeatures::default().shader_int64(f.shader_int64);
        let priorities = [1.0];
        let queues = [vk::DeviceQueueCreateInfo::default().queue_family_index(req.queue_family).queue_priorities(&priorities)];
        let mut info = vk::DeviceCreateInfo::default().queue_create_infos(&queues).enabled_extension_names(&ext_ptrs).enabled_features(&core).push_next(&mut f12);
        if f.shader_buffer_float32_atomic_add {
            info = info.push_next(&mut atomics);
        }
        let device = unsafe { instance.create_device(physical, &info, None) }.expect("device");
        let queue = unsafe { device.get_device_queue(req.queue_family, 0) };
        let pool = unsafe { device.create_command_pool(&vk::CommandPoolCreateInfo::default().queue_family_index(req.queue_family), None) }.expect("pool");
        Host { entry, instance, messenger: (du, messenger), sink, physical, device, family: req.queue_family, queue, features: f, extensions, pool }
    }

    fn external(&self) -> ExternalVulkan {
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

    fn context(&self) -> Context {
        let options = ExternalOptions { poison_new_buffers: true, force_staging: false };
        unsafe { Context::from_raw(self.external(), options) }.expect("from_raw")
    }

    fn memory_type(&self, bits: u32, flags: vk::MemoryPropertyFlags) -> u32 {
        let props = unsafe { self.instance.get_physical_device_memory_properties(self.physical) };
        (0..props.memory_type_count).find(|&i| bits & (1 << i) != 0 && props.memory_types[i as usize].property_flags.contains(flags)).expect("memory type")
    }

    /// An RGBA32F image the size of the render, and a host-visible buffer to read it.
    fn image_and_readback(&self, w: u32, h: u32) -> Target {
        let info = vk::ImageCreateInfo::default()
            .image_type(vk::ImageType::TYPE_2D)
            .format(vk::Format::R32G32B32A32_SFLOAT)
            .extent(vk::Extent3D { width: w, height: h, depth: 1 })
            .mip_levels(1)
            .array_layers(1)
            .samples(vk::SampleCountFlags::TYPE_1)
            .tiling(vk::ImageTiling::OPTIMAL)
            .usage(vk::ImageUsageFlags::TRANSFER_DST | vk::ImageUsageFlags::TRANSFER_SRC);
        let image = unsafe { self.device.create_image(&info, None) }.expect("image");
        let req = unsafe { self.device.get_image_memory_requirements(image) };
        let alloc = vk::MemoryAllocateInfo::default().allocation_size(req.size).memory_type_index(self.memory_type(req.memory_type_bits, vk::MemoryPropertyFlags::DEVICE_LOCAL));
        let image_memory = unsafe { self.device.allocate_memory(&alloc, None) }.expect("image memory");
        unsafe { self.device.bind_image_memory(image, image_memory, 0) }.expect("bind");
        let bytes = 16 * u64::from(w) * u64::from(h);
        let buffer = unsafe { self.device.create_buffer(&vk::BufferCreateInfo::default().size(bytes).usage(vk::BufferUsageFlags::TRANSFER_DST), None) }.expect("buffer");
        let req = unsafe { self.device.get_buffer_memory_requirements(buffer) };
        let host = vk::MemoryPropertyFlags::HOST_VISIBLE | vk::MemoryPropertyFlags::HOST_COHERENT;
        let alloc = vk::MemoryAllocateInfo::default().allocation_size(req.size).memory_type_index(self.memory_type(req.memory_type_bits, host));
        let buffer_memory = unsafe { self.device.allocate_memory(&alloc, None) }.expect("buffer memory");
        unsafe { self.device.bind_buffer_memory(buffer, buffer_memory, 0) }.expect("bind");
        Target { image, image_memory, buffer, buffer_memory, w, h }
    }

    fn begin(&self) -> vk::CommandBuffer {
        let info = vk::CommandBufferAllocateInfo::default().command_pool(self.pool).level(vk::CommandBufferLevel::PRIMARY).command_buffer_count(1);
        let cmd = unsafe { self.device.allocate_command_buffers(&info) }.expect("command buffer")[0];
        unsafe { self.device.begin_command_buffer(cmd, &vk::CommandBufferBeginInfo::default()) }.expect("begin");
        cmd
    }

    /// Ends and submits `cmd` (waiting on `wait` at transfer) and waits for its fence.
    fn submit(&self, cmd: vk::CommandBuffer, wait: Option<(vk::Semaphore, u64)>) {
        unsafe { self.device.end_command_buffer(cmd) }.expect("end");
        let fence = unsafe { self.device.create_fence(&vk::FenceCreateInfo::default(), None) }.expect("fence");
        let cmds = [cmd];
        let (sems, values, stages): (Vec<_>, Vec<_>, Vec<_>) = match wait {
            Some((s, v)) => (vec![s], vec![v], vec![vk::PipelineStageFlags::TRANSFER]),
            None => (vec![], vec![], vec![]),
        };
        let mut timeline = vk::TimelineSemaphoreSubmitInfo::default().wait_semaphore_values(&values);
        let submit = vk::SubmitInfo::default().command_buffers(&cmds).wait_semaphores(&sems).wait_dst_stage_mask(&stages).push_next(&mut timeline);
        unsafe { self.device.queue_submit(self.queue, &[submit], fence) }.expect("submit");
        unsafe { self.device.wait_for_fences(&[fence], true, u64::MAX) }.expect("wait");
        unsafe { self.device.destroy_fence(fence, None) };
        unsafe { self.device.free_command_buffers(self.pool, &cmds) };
    }

    fn image_barrier(&self, cmd: vk::CommandBuffer, image: vk::Image, from: (vk::ImageLayout, vk::PipelineStageFlags, vk::AccessFlags), to: (vk::ImageLayout, vk::PipelineStageFlags, vk::AccessFlags)) {
        let range = vk::ImageSubresourceRange::default().aspect_mask(vk::ImageAspectFlags::COLOR).level_count(1).layer_count(1);
        let barrier = vk::ImageMemoryBarrier::default()
            .old_layout(from.0)
            .new_layout(to.0)
            .src_access_mask(from.2)
            .dst_access_mask(to.2)
            .src_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
            .dst_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
            .image(image)
            .subresource_range(range);
        unsafe { self.device.cmd_pipeline_barrier(cmd, from.1, to.1, vk::DependencyFlags::empty(), &[], &[], &[barrier]) };
    }

    /// Records the image's copy into the read-back buffer (after the documented "after"
    /// barrier, from TRANSFER_DST to TRANSFER_SRC).
    fn record_readback(&self, cmd: vk::CommandBuffer, t: &Target) {
        let t_write = (vk::ImageLayout::TRANSFER_DST_OPTIMAL, vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_WRITE);
        self.image_barrier(cmd, t.image, t_write, (vk::ImageLayout::TRANSFER_SRC_OPTIMAL, vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_READ));
        let region = vk::BufferImageCopy::default()
            .image_subresource(vk::ImageSubresourceLayers::default().aspect_mask(vk::ImageAspectFlags::COLOR).layer_count(1))
            .image_extent(vk::Extent3D { width: t.w, height: t.h, depth: 1 });
        unsafe { self.device.cmd_copy_image_to_buffer(cmd, t.image, vk::ImageLayout::TRANSFER_SRC_OPTIMAL, t.buffer, &[region]) };
    }

    fn read(&self, t: &Target) -> Vec<f32> {
        let n = 4 * t.w as usize * t.h as usize;
        let ptr = unsafe { self.device.map_memory(t.buffer_memory, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()) }.expect("map");
        let out = unsafe { std::slice::from_raw_parts(ptr as *const f32, n) }.to_vec();
        unsafe { self.device.unmap_memory(t.buffer_memory) };
        out
    }

    fn destroy_target(&self, t: Target) {
        unsafe {
            self.device.destroy_image(t.image, None);
            self.device.free_memory(t.image_memory, None);
            self.device.destroy_buffer(t.buffer, None);
            self.device.free_memory(t.buffer_memory, None);
        }
    }

    /// Destroys everything and returns the validation messages of the whole test.
    fn finish(self) -> Vec<String> {
        unsafe {
            self.device.destroy_command_pool(self.pool, None);
            self.device.destroy_device(None);
            self.messenger.0.destroy_debug_utils_messenger(self.messenger.1, None);
            self.instance.destroy_instance(None);
        }
        self.sink.drain()
    }
}

struct Target {
    image: vk::Image,
    image_memory: vk::DeviceMemory,
    buffer: vk::Buffer,
    buffer_memory: vk::DeviceMemory,
    w: u32,
    h: u32,
}

/// The owned-context path: the library's own render of the default pose and camera.
fn owned_render() -> (Vec<f32>, ViewCamera, u32, u32) {
    let ctx = drape_tests::gpu();
    let mut player = AvatarPlayer::load(&ctx, tiny_run(&ctx), 1).expect("player");
    let cam = ViewCamera::from_camera(player.default_camera());
    let (w, h) = (player.default_camera().width, player.default_camera().height);
    let pixels = player.render(&cam, w, h).expect("render");
    (pixels, cam, w, h)
}

fn max_difference(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

#[test]
fn from_raw_renders_into_the_hosts_image_and_signals_its_timeline_semaphore() {
    let (expected, cam, w, h) = owned_render();
    assert!(expected.chunks(4).any(|p| p[3] > 0.5), "the avatar covers some pixels");
    let host = Host::new(false);
    let t = host.image_and_readback(w, h);
    let cmd = host.begin();
    host.image_barrier(cmd, t.image, (vk::ImageLayout::UNDEFINED, vk::PipelineStageFlags::TOP_OF_PIPE, vk::AccessFlags::empty()), (vk::ImageLayout::TRANSFER_DST_OPTIMAL, vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_WRITE));
    host.submit(cmd, None);
    let mut type_info = vk::SemaphoreTypeCreateInfo::default().semaphore_type(vk::SemaphoreType::TIMELINE).initial_value(0);
    let semaphore = unsafe { host.device.create_semaphore(&vk::SemaphoreCreateInfo::default().push_next(&mut type_info), None) }.expect("semaphore");
    {
        let ctx = host.context();
        assert!(!ctx.owns_device());
        assert_eq!(ctx.info().float_atomic_add, host.features.shader_buffer_float32_atomic_add);
        let mut player = AvatarPlayer::load(&ctx, tiny_run(&ctx), 1).expect("player");
        let target = unsafe { ImageTarget::new(t.image, vk::ImageLayout::TRANSFER_DST_OPTIMAL, w, h, 16) };
        let sync = SubmitSync { wait: vec![], signal: vec![(semaphore, 1)] };
        player.submit_frame(&cam, w, h, &sync, Some(&target)).expect("frame");
        let sems = [semaphore];
        let values = [1u64];
        unsafe { host.device.wait_semaphores(&vk::SemaphoreWaitInfo::default().semaphores(&sems).values(&values), u64::MAX) }.expect("timeline wait");
        let cmd = host.begin();
        host.record_readback(cmd, &t);
        host.submit(cmd, Some((semaphore, 1)));
        let got = host.read(&t);
        let d = max_difference(&got, &expected);
        assert!(d <= SAME_DEVICE_TOLERANCE, "from_raw render differs from the owned context's by {d}");
        player.wait_idle().expect("idle");
    }
    unsafe { host.device.destroy_semaphore(semaphore, None) };
    host.destroy_target(t);
    let messages = host.finish();
    assert!(messages.is_empty(), "validation on the host's instance:\n{}", messages.join("\n"));
}

/// Records the avatar into the host's command buffer between the host's clear of the
/// image and its read-back, the image in `GENERAL` throughout; `documented_after_barrier`
/// says whether the host places the barrier the engine documents after a copy into its
/// image (`TRANSFER` / `TRANSFER_WRITE` to the host's read). The engine writes a
/// timestamp before and after its part into the host's query pool. Returns the pixels,
/// the two timestamps and the validation messages.
fn record_into_host(documented_after_barrier: bool) -> (Vec<f32>, [u64; 2], Vec<String>) {
    let ctx0 = drape_tests::gpu();
    let run = tiny_run(&ctx0).to_path_buf();
    drop(ctx0);
    let host = Host::new(false);
    let (pixels, messages);
    let mut stamps = [0u64; 2];
    {
        let ctx = host.context();
        let mut player = AvatarPlayer::load(&ctx, &run, 1).expect("player");
        let cam = ViewCamera::from_camera(player.default_camera());
        let (w, h) = (player.default_camera().width, player.default_camera().height);
        let t = host.image_and_readback(w, h);
        let queries = unsafe { host.device.create_query_pool(&vk::QueryPoolCreateInfo::default().query_type(vk::QueryType::TIMESTAMP).query_count(2), None) }.expect("query pool");
        let cmd = host.begin();
        unsafe { host.device.cmd_reset_query_pool(cmd, queries, 0, 2) };
        let general = vk::ImageLayout::GENERAL;
        let write = (general, vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_WRITE);
        host.image_barrier(cmd, t.image, (vk::ImageLayout::UNDEFINED, vk::PipelineStageFlags::TOP_OF_PIPE, vk::AccessFlags::empty()), write);
        let range = vk::ImageSubresourceRange::default().aspect_mask(vk::ImageAspectFlags::COLOR).level_count(1).layer_count(1);
        unsafe { host.device.cmd_clear_color_image(cmd, t.image, general, &vk::ClearColorValue { float32: [0.5; 4] }, &[range]) };
        // The documented "before" barrier: the host's clear, then the engine's copy.
        host.image_barrier(cmd, t.image, write, write);
        let hcb = unsafe { HostCommandBuffer::new(cmd, Some((queries, 0))) };
        let target = unsafe { ImageTarget::new(t.image, general, w, h, 16) };
        player.record_frame_into(&cam, w, h, &hcb, Some(&target)).expect("record");
        if documented_after_barrier {
            host.image_barrier(cmd, t.image, write, (general, vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_READ));
        }
        let region = vk::BufferImageCopy::default()
            .image_subresource(vk::ImageSubresourceLayers::default().aspect_mask(vk::ImageAspectFlags::COLOR).layer_count(1))
            .image_extent(vk::Extent3D { width: w, height: h, depth: 1 });
        unsafe { host.device.cmd_copy_image_to_buffer(cmd, t.image, general, t.buffer, &[region]) };
        host.submit(cmd, None);
        pixels = host.read(&t);
        unsafe { host.device.get_query_pool_results(queries, 0, &mut stamps, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT) }.expect("timestamps");
        player.wait_idle().expect("idle");
        drop(player);
        drop(ctx);
        unsafe { host.device.destroy_query_pool(queries, None) };
        host.destroy_target(t);
    }
    messages = host.finish();
    (pixels, stamps, messages)
}

#[test]
fn recorded_into_the_hosts_command_buffer_with_the_documented_barriers_has_no_hazard() {
    let (expected, ..) = owned_render();
    let (pixels, stamps, messages) = record_into_host(true);
    assert!(messages.is_empty(), "synchronization validation:\n{}", messages.join("\n"));
    // lavapipe has timestamps (DRAPE_EXPECT_FEATURES): the frame took some time.
    assert!(stamps[1] > stamps[0] && stamps[0] > 0, "the engine's timestamps in the host's pool: {stamps:?}");
    let d = max_difference(&pixels, &expected);
    assert!(d <= SAME_DEVICE_TOLERANCE, "host-recorded render differs from the owned context's by {d}");
}

#[test]
fn leaving_out_the_documented_barrier_after_the_copy_is_a_reported_hazard() {
    let (_, _, messages) = record_into_host(false);
    assert!(messages.iter().any(|m| m.contains("SYNC-HAZARD-READ-AFTER-WRITE")), "expected a read-after-write hazard, got:\n{}", messages.join("\n"));
}

#[test]
fn a_host_device_without_float_atomics_gets_the_cas_kernels_and_one_without_the_memory_model_is_refused() {
    let host = Host::new(true);
    {
        let ctx = host.context();
        assert!(!ctx.info().float_atomic_add, "the host did not enable float atomics");
        let mut ext = host.external();
        ext.enabled_features.vulkan_memory_model = false;
        let err = unsafe { Context::from_raw(ext, ExternalOptions::default()) }.expect_err("refused");
        assert!(err.to_string().contains("vulkanMemoryModel"), "{err}");
        let mut ext = host.external();
        ext.enabled_features.shader_buffer_float32_atomic_add = true;
        let err = unsafe { Context::from_raw(ext, ExternalOptions::default()) }.expect_err("refused");
        assert!(err.to_string().contains("VK_EXT_shader_atomic_float"), "{err}");
        assert_eq!(Accumulation::Auto.method(&ctx), Method::CompareAndSwap);
        cas_backward_matches_the_reference(&ctx);
        let mut player = AvatarPlayer::load(&ctx, tiny_run(&ctx), 1).expect("player");
        let cam = ViewCamera::from_camera(player.default_camera());
        let (w, h) = (player.default_camera().width, player.default_camera().height);
        let pixels = player.render(&cam, w, h).expect("render without float atomics");
        assert!(pixels.chunks(4).any(|p| p[3] > 0.5));
    }
    let messages = host.finish();
    assert!(messages.is_empty(), "validation:\n{}", messages.join("\n"));
}

/// The splatter's backward with `Accumulation::Auto` on `ctx` against the CPU reference.
fn cas_backward_matches_the_reference(ctx: &Context) {
    use drape_engine::ops::splat::reference;
    use drape_engine::ops::splat::render::{GaussianBuffers, SplatRenderer};
    use drape_engine::ops::splat::scene::{frame_params, GaussianCloud, PinholeCamera, RenderSettings};
    let n = 300;
    let cloud = GaussianCloud::random(n, 1, 1.6, (-1.0, 1.0), 0.05, 7);
    let cam = PinholeCamera { fx: 40.0, fy: 40.0, cx: 24.0, cy: 16.0, width: 48, height: 32, rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], translation: [0.0, 0.0, 4.0], near: 0.01, far: 100.0, background: [0.0; 3] };
    let settings = RenderSettings::default();
    let gaussians = GaussianBuffers::upload(ctx, "gaussians", &cloud).expect("upload");
    let mut renderer = SplatRenderer::new(ctx, 48, 32, n).expect("renderer");
    let saved = renderer.forward(&gaussians, &cam, &settings).expect("forward").saved;
    let pixels = 48 * 32;
    let (g_rgb, g_alpha, g_depth) = (vec![1.0f32; 3 * pixels], vec![0.5f32; pixels], vec![0.0f32; pixels]);
    let b_rgb = ctx.upload("grad rgb", &g_rgb).expect("upload");
    let b_alpha = ctx.upload("grad alpha", &g_alpha).expect("upload");
    let b_depth = ctx.upload("grad depth", &g_depth).expect("upload");
    let mut grads = GaussianBuffers::new(ctx, "grads", n, 1).expect("grads");
    renderer.backward(&saved, &gaussians, &b_rgb, &b_alpha, &b_depth, &grads, Accumulation::Auto).expect("backward through compare-and-swap");
    let got = grads.download(ctx, &cloud.layers).expect("download");
    let gs = cloud.gaussians::<f32>();
    let frame = frame_params(&cam, &settings, 1, n);
    let cpu = reference::render(&gs, &frame);
    let (want, _) = reference::backward(&gs, &frame, &cpu, &g_rgb, &g_alpha, &g_depth);
    let (mut num, mut den) = (0.0f64, 0.0f64);
    for i in 0..n {
        for k in 0..4 {
            for c in 0..3 {
                let (a, b) = (got.sh[(i * 4 + k) * 3 + c], want[i].sh[k][c]);
                num += f64::from(a - b).powi(2);
                den += f64::from(b).powi(2);
            }
        }
    }
    // The splatter's backward tolerance: CAS adds in another order than the CPU.
    assert!(den > 0.0 && (num / den).sqrt() <= 1e-4, "SH gradients through CAS: relative error {:e}", (num / den).sqrt());
}

#[test]
fn k_frames_in_flight_wait_n_minus_k_times() {
    let ctx = drape_tests::gpu();
    let run = tiny_run(&ctx).to_path_buf();
    for k in 1..=3usize {
        let mut player = AvatarPlayer::load(&ctx, &run, k).expect("player");
        let cam = ViewCamera::from_camera(player.default_camera());
        let (w, h) = (player.default_camera().width, player.default_camera().height);
        let n = 8u64;
        // One frame first: pipelines and lazily made buffers are not what is counted.
        player.submit_frame(&cam, w, h, &SubmitSync::default(), None).expect("warm-up");
        player.wait_idle().expect("idle");
        let (waits, submissions) = (ctx.fence_waits(), ctx.submission_count());
        for _ in 0..n {
            player.submit_frame(&cam, w, h, &SubmitSync::default(), None).expect("frame");
        }
        let waited = ctx.fence_waits() - waits;
        assert_eq!(waited, n - k as u64, "{k} frames in flight over {n} frames");
        assert_eq!(ctx.submission_count() - submissions, n, "one submission a frame");
        player.wait_idle().expect("idle");
    }
}

/// Context::new is the owned path the others are compared with; keep it in use here so
/// a change to it shows in this file's failures too.
#[test]
fn the_owned_context_owns_its_device() {
    let ctx = Context::new(&ContextDesc::for_tests()).expect("context");
    assert!(ctx.owns_device());
}
