//! The engine inside an application that owns its Vulkan device: the test creates its
//! own instance and device with `ash`, hands them over with `Context::from_raw`, renders
//! the tiny run's avatar into an image it owns (signalling a timeline semaphore it waits
//! on, or recorded into its own command buffer), and compares the pixels with the
//! owned-context path. Validation (with synchronization validation) runs on the test's
//! instance and must stay silent, leaks included; a host barrier left out must show.
//! The host's side is `drape_tests::host`.
//
// SAFETY (every unsafe block in this file): Vulkan calls on the test host's own objects,
// alive for each call, and the engine's raw-handle constructors given those objects.
#![allow(clippy::undocumented_unsafe_blocks)]

use drape_engine::ash::vk;
use drape_engine::ops::accumulate::{Accumulation, Method};
use drape_engine::{Context, ExternalOptions, HostCommandBuffer, ImageTarget, SubmitSync};
use drape_tests::host::Host;
use drape_trainer::avatar::player::{clamp_premultiplied, AvatarPlayer, ViewCamera};
use drape_trainer::testing::tiny_run;

/// Largest difference between the from_raw and owned-context renders: the same device
/// and kernels on the same inputs; only a different order of equal floats could differ.
const SAME_DEVICE_TOLERANCE: f32 = 1e-5;

/// The owned-context path: the library's own render of the default pose and camera.
fn owned_render() -> (Vec<f32>, ViewCamera, u32, u32) {
    let ctx = drape_tests::gpu();
    let mut player = AvatarPlayer::load(&ctx, tiny_run(&ctx), 1).expect("player");
    let cam = ViewCamera::from_camera(player.default_camera());
    let (w, h) = (
        player.default_camera().width,
        player.default_camera().height,
    );
    let pixels = player.render(&cam, w, h).expect("render");
    (pixels, cam, w, h)
}

fn max_difference(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn from_raw_renders_into_the_hosts_image_and_signals_its_timeline_semaphore() {
    let (expected, cam, w, h) = owned_render();
    assert!(
        expected.chunks(4).any(|p| p[3] > 0.5),
        "the avatar covers some pixels"
    );
    let host = Host::new(false);
    let t = host.image_and_readback(w, h);
    let cmd = host.begin();
    host.image_barrier(
        cmd,
        t.image,
        (
            vk::ImageLayout::UNDEFINED,
            vk::PipelineStageFlags::TOP_OF_PIPE,
            vk::AccessFlags::empty(),
        ),
        (
            vk::ImageLayout::TRANSFER_DST_OPTIMAL,
            vk::PipelineStageFlags::TRANSFER,
            vk::AccessFlags::TRANSFER_WRITE,
        ),
    );
    host.submit(cmd, None);
    let mut type_info = vk::SemaphoreTypeCreateInfo::default()
        .semaphore_type(vk::SemaphoreType::TIMELINE)
        .initial_value(0);
    let semaphore = unsafe {
        host.device.create_semaphore(
            &vk::SemaphoreCreateInfo::default().push_next(&mut type_info),
            None,
        )
    }
    .expect("semaphore");
    {
        let ctx = host.context();
        assert!(!ctx.owns_device());
        assert_eq!(
            ctx.info().float_atomic_add,
            host.features.shader_buffer_float32_atomic_add
        );
        let mut player = AvatarPlayer::load(&ctx, tiny_run(&ctx), 1).expect("player");
        let target =
            unsafe { ImageTarget::new(t.image, vk::ImageLayout::TRANSFER_DST_OPTIMAL, w, h, 16) };
        let sync = SubmitSync {
            wait: vec![],
            signal: vec![(semaphore, 1)],
        };
        player
            .submit_frame(&cam, w, h, &sync, Some(&target))
            .expect("frame");
        let sems = [semaphore];
        let values = [1u64];
        unsafe {
            host.device.wait_semaphores(
                &vk::SemaphoreWaitInfo::default()
                    .semaphores(&sems)
                    .values(&values),
                u64::MAX,
            )
        }
        .expect("timeline wait");
        let cmd = host.begin();
        host.record_readback(cmd, &t);
        host.submit(cmd, Some((semaphore, 1)));
        // The image a frame is recorded into is not clamped; `render` reads back clamped.
        let mut got = host.read(&t);
        clamp_premultiplied(&mut got);
        let d = max_difference(&got, &expected);
        assert!(
            d <= SAME_DEVICE_TOLERANCE,
            "from_raw render differs from the owned context's by {d}"
        );
        player.wait_idle().expect("idle");
    }
    unsafe { host.device.destroy_semaphore(semaphore, None) };
    host.destroy_target(t);
    let messages = host.finish();
    assert!(
        messages.is_empty(),
        "validation on the host's instance:\n{}",
        messages.join("\n")
    );
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
        let (w, h) = (
            player.default_camera().width,
            player.default_camera().height,
        );
        let t = host.image_and_readback(w, h);
        let queries = unsafe {
            host.device.create_query_pool(
                &vk::QueryPoolCreateInfo::default()
                    .query_type(vk::QueryType::TIMESTAMP)
                    .query_count(2),
                None,
            )
        }
        .expect("query pool");
        let cmd = host.begin();
        unsafe { host.device.cmd_reset_query_pool(cmd, queries, 0, 2) };
        let general = vk::ImageLayout::GENERAL;
        let write = (
            general,
            vk::PipelineStageFlags::TRANSFER,
            vk::AccessFlags::TRANSFER_WRITE,
        );
        host.image_barrier(
            cmd,
            t.image,
            (
                vk::ImageLayout::UNDEFINED,
                vk::PipelineStageFlags::TOP_OF_PIPE,
                vk::AccessFlags::empty(),
            ),
            write,
        );
        let range = vk::ImageSubresourceRange::default()
            .aspect_mask(vk::ImageAspectFlags::COLOR)
            .level_count(1)
            .layer_count(1);
        unsafe {
            host.device.cmd_clear_color_image(
                cmd,
                t.image,
                general,
                &vk::ClearColorValue { float32: [0.5; 4] },
                &[range],
            )
        };
        // The documented "before" barrier: the host's clear, then the engine's copy.
        host.image_barrier(cmd, t.image, write, write);
        let hcb = unsafe { HostCommandBuffer::new(cmd, Some((queries, 0))) };
        let target = unsafe { ImageTarget::new(t.image, general, w, h, 16) };
        player
            .record_frame_into(&cam, w, h, &hcb, Some(&target))
            .expect("record");
        if documented_after_barrier {
            host.image_barrier(
                cmd,
                t.image,
                write,
                (
                    general,
                    vk::PipelineStageFlags::TRANSFER,
                    vk::AccessFlags::TRANSFER_READ,
                ),
            );
        }
        let region = vk::BufferImageCopy::default()
            .image_subresource(
                vk::ImageSubresourceLayers::default()
                    .aspect_mask(vk::ImageAspectFlags::COLOR)
                    .layer_count(1),
            )
            .image_extent(vk::Extent3D {
                width: w,
                height: h,
                depth: 1,
            });
        unsafe {
            host.device
                .cmd_copy_image_to_buffer(cmd, t.image, general, t.buffer, &[region])
        };
        host.submit(cmd, None);
        pixels = host.read(&t);
        unsafe {
            host.device.get_query_pool_results(
                queries,
                0,
                &mut stamps,
                vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
            )
        }
        .expect("timestamps");
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
    let (mut pixels, stamps, messages) = record_into_host(true);
    // The host's image is not clamped; `render` reads back clamped.
    clamp_premultiplied(&mut pixels);
    assert!(
        messages.is_empty(),
        "synchronization validation:\n{}",
        messages.join("\n")
    );
    // lavapipe has timestamps (DRAPE_EXPECT_FEATURES): the frame took some time.
    assert!(
        stamps[1] > stamps[0] && stamps[0] > 0,
        "the engine's timestamps in the host's pool: {stamps:?}"
    );
    let d = max_difference(&pixels, &expected);
    assert!(
        d <= SAME_DEVICE_TOLERANCE,
        "host-recorded render differs from the owned context's by {d}"
    );
}

#[test]
fn leaving_out_the_documented_barrier_after_the_copy_is_a_reported_hazard() {
    let (_, _, messages) = record_into_host(false);
    assert!(
        messages
            .iter()
            .any(|m| m.contains("SYNC-HAZARD-READ-AFTER-WRITE")),
        "expected a read-after-write hazard, got:\n{}",
        messages.join("\n")
    );
}

#[test]
fn a_host_device_without_float_atomics_gets_the_cas_kernels_and_one_without_the_memory_model_is_refused(
) {
    let host = Host::new(true);
    {
        let ctx = host.context();
        assert!(
            !ctx.info().float_atomic_add,
            "the host did not enable float atomics"
        );
        let mut ext = host.external();
        ext.enabled_features.vulkan_memory_model = false;
        let err =
            unsafe { Context::from_raw(ext, ExternalOptions::default()) }.expect_err("refused");
        assert!(err.to_string().contains("vulkanMemoryModel"), "{err}");
        let mut ext = host.external();
        ext.enabled_features.shader_buffer_float32_atomic_add = true;
        let err =
            unsafe { Context::from_raw(ext, ExternalOptions::default()) }.expect_err("refused");
        assert!(
            err.to_string().contains("VK_EXT_shader_atomic_float"),
            "{err}"
        );
        assert_eq!(Accumulation::Auto.method(&ctx), Method::CompareAndSwap);
        cas_backward_matches_the_reference(&ctx);
        let mut player = AvatarPlayer::load(&ctx, tiny_run(&ctx), 1).expect("player");
        let cam = ViewCamera::from_camera(player.default_camera());
        let (w, h) = (
            player.default_camera().width,
            player.default_camera().height,
        );
        let pixels = player
            .render(&cam, w, h)
            .expect("render without float atomics");
        assert!(pixels.chunks(4).any(|p| p[3] > 0.5));
    }
    let messages = host.finish();
    assert!(messages.is_empty(), "validation:\n{}", messages.join("\n"));
}

/// The splatter's backward with `Accumulation::Auto` on `ctx` against the CPU reference.
fn cas_backward_matches_the_reference(ctx: &Context) {
    use drape_engine::ops::splat::reference;
    use drape_engine::ops::splat::render::{GaussianBuffers, SplatRenderer};
    use drape_engine::ops::splat::scene::{
        frame_params, GaussianCloud, PinholeCamera, RenderSettings,
    };
    let n = 300;
    let cloud = GaussianCloud::random(n, 1, 1.6, (-1.0, 1.0), 0.05, 7);
    let cam = PinholeCamera {
        fx: 40.0,
        fy: 40.0,
        cx: 24.0,
        cy: 16.0,
        width: 48,
        height: 32,
        rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        translation: [0.0, 0.0, 4.0],
        near: 0.01,
        far: 100.0,
        background: [0.0; 3],
    };
    let settings = RenderSettings::default();
    let gaussians = GaussianBuffers::upload(ctx, "gaussians", &cloud).expect("upload");
    let mut renderer = SplatRenderer::new(ctx, 48, 32, n).expect("renderer");
    let saved = renderer
        .forward(&gaussians, &cam, &settings)
        .expect("forward")
        .saved;
    let pixels = 48 * 32;
    let (g_rgb, g_alpha, g_depth) = (
        vec![1.0f32; 3 * pixels],
        vec![0.5f32; pixels],
        vec![0.0f32; pixels],
    );
    let b_rgb = ctx.upload("grad rgb", &g_rgb).expect("upload");
    let b_alpha = ctx.upload("grad alpha", &g_alpha).expect("upload");
    let b_depth = ctx.upload("grad depth", &g_depth).expect("upload");
    let mut grads = GaussianBuffers::new(ctx, "grads", n, 1).expect("grads");
    renderer
        .backward(
            &saved,
            &gaussians,
            &b_rgb,
            &b_alpha,
            &b_depth,
            &grads,
            Accumulation::Auto,
        )
        .expect("backward through compare-and-swap");
    let got = grads.download(ctx, &cloud.groups).expect("download");
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
    assert!(
        den > 0.0 && (num / den).sqrt() <= 1e-4,
        "SH gradients through CAS: relative error {:e}",
        (num / den).sqrt()
    );
}

#[test]
fn k_frames_in_flight_wait_n_minus_k_times() {
    let ctx = drape_tests::gpu();
    let run = tiny_run(&ctx).to_path_buf();
    for k in 1..=3usize {
        let mut player = AvatarPlayer::load(&ctx, &run, k).expect("player");
        let cam = ViewCamera::from_camera(player.default_camera());
        let (w, h) = (
            player.default_camera().width,
            player.default_camera().height,
        );
        let n = 8u64;
        // One frame first: pipelines and lazily made buffers are not what is counted.
        player
            .submit_frame(&cam, w, h, &SubmitSync::default(), None)
            .expect("warm-up");
        player.wait_idle().expect("idle");
        let (waits, submissions) = (ctx.fence_waits(), ctx.submission_count());
        for _ in 0..n {
            player
                .submit_frame(&cam, w, h, &SubmitSync::default(), None)
                .expect("frame");
        }
        let waited = ctx.fence_waits() - waits;
        assert_eq!(waited, n - k as u64, "{k} frames in flight over {n} frames");
        assert_eq!(
            ctx.submission_count() - submissions,
            n,
            "one submission a frame"
        );
        player.wait_idle().expect("idle");
    }
}

/// A borrowed device outlives the context: after the context, its buffers and its
/// work are dropped, the host still records, submits and waits on its own device, and
/// destroying everything itself is clean under validation (nothing destroyed twice,
/// nothing of the engine's left behind).
#[test]
fn a_dropped_borrowing_context_leaves_the_hosts_device_to_the_host() {
    let host = Host::new(false);
    {
        let ctx = host.context();
        let data: Vec<f32> = (0..1000).map(|i| i as f32).collect();
        let mut buffer = ctx.upload("borrowed", &data).expect("upload");
        let back: Vec<f32> = ctx.read_buffer(&mut buffer, data.len()).expect("read");
        assert_eq!(back, data, "the borrowed device ran the engine's copies");
    }
    let cmd = host.begin();
    host.submit(cmd, None);
    let messages = host.finish();
    assert!(messages.is_empty(), "validation: {messages:#?}");
}
