//! Sizes that scale (lavapipe, validation on): counts past one row of 65,535
//! workgroups run on the 2-D grid, the intersection total is summed without wrap, and
//! every size past a limit is `EngineError::TooLarge` naming the size and the limit,
//! never a panic and never a wrong image.

use drape_engine::ops::adam::{AdamGroup, LrSchedule};
use drape_engine::ops::radix_sort::RadixSort;
use drape_engine::ops::scan::ExclusiveScan;
use drape_engine::ops::splat::reference;
use drape_engine::ops::splat::render::{GaussianBuffers, SplatRenderer};
use drape_engine::ops::splat::scene::{frame_params, GaussianCloud, RenderSettings};
use drape_engine::{kernels, EngineError};
use drape_shared::adam::{adam_update, LossParams};
use drape_shared::splat::layout::MAX_SH_COEFFS;
use drape_shared::splat::project::Gaussian;
use drape_tests::gpu;
use drape_tests::splat::{assert_forward_close, camera};
use rand::{Rng, SeedableRng};

fn gaussian(mean: [f32; 3], scale: f32, opacity_logit: f32, rgb: [f32; 3]) -> Gaussian<f32> {
    let mut sh = [[0.0; 3]; MAX_SH_COEFFS];
    sh[0] = rgb.map(|c| (c - 0.5) / 0.282_094_8);
    Gaussian {
        mean,
        log_scale: [scale.ln(); 3],
        quat: [1.0, 0.0, 0.0, 0.0],
        opacity_logit,
        sh,
    }
}

fn expect_too_large<T>(result: Result<T, EngineError>, what: &str) -> String {
    match result {
        Err(e @ EngineError::TooLarge { .. }) => e.to_string(),
        Err(e) => panic!("{what}: expected TooLarge, got {e}"),
        Ok(_) => panic!("{what}: expected TooLarge, got Ok"),
    }
}

/// 20M tile intersections (the per-intersection pass needs 78K workgroups, past one
/// row of 65,535) through the whole forward at 1920x1080, against the CPU reference.
#[test]
fn twenty_million_intersections_render_as_the_reference_does() {
    let gpu = gpu();
    let (w, h) = (1920, 1080);
    let cam = camera(w, h);
    let mut rng = rand::rngs::StdRng::seed_from_u64(31);
    let mut cloud = GaussianCloud::new(0);
    // Large splats (a third to most of the view) with high opacity: every one covers
    // thousands of tiles, but a pixel saturates after a few, so rasterizing stays fast.
    for _ in 0..6_500 {
        let mean = [
            rng.random_range(-1.5..1.5),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        ];
        let colour = [
            rng.random_range(0.0..1.0),
            rng.random_range(0.0..1.0),
            rng.random_range(0.0..1.0),
        ];
        cloud.push(
            &gaussian(
                mean,
                rng.random_range(0.35..0.75),
                rng.random_range(2.0..5.0),
                colour,
            ),
            0u32,
        );
    }
    let settings = RenderSettings::default();
    let gaussians = GaussianBuffers::upload(&gpu, "gaussians", &cloud).expect("upload");
    let mut renderer = SplatRenderer::new(&gpu, w, h, cloud.len()).expect("renderer");
    let stats = renderer
        .forward(&gaussians, &cam, &settings)
        .expect("forward");
    let image = renderer.read_image().expect("read");
    let frame = frame_params(&cam, &settings, 0, cloud.len());
    let gaussians_f32 = cloud.gaussians::<f32>();
    let cpu = reference::render(&gaussians_f32, &frame);
    eprintln!(
        "{} intersections (CPU {}), {} blend steps",
        stats.intersections, cpu.intersections, image.blend_steps
    );
    assert!(
        stats.intersections > 20_000_000,
        "the scene must reach 20M intersections, got {}",
        stats.intersections
    );
    assert!(
        u64::from(stats.intersections) > 65_535 * 256,
        "past one row of workgroups"
    );
    // Same count on both sides on lavapipe (no fused multiply-add); a GPU that fuses
    // may move a pair at a tile edge: 1e-4 relative.
    let d = (i64::from(stats.intersections) - cpu.intersections as i64).unsigned_abs();
    assert!(
        d as f64 <= 1e-4 * cpu.intersections as f64,
        "intersections GPU {} vs CPU {}",
        stats.intersections,
        cpu.intersections
    );
    // Every 7th pixel (a sample spread over every tile), compared as the forward test
    // does (1e-5 on a CPU device; see assert_forward_close).
    let seen = assert_forward_close(
        &gpu,
        &image,
        &gaussians_f32,
        &frame,
        &cpu,
        7,
        "1920x1080, 22.5M intersections",
    );
    let checked = seen.pixels;
    eprintln!(
        "largest error {:e}, {} pixels near a threshold",
        seen.max_error, seen.near_threshold
    );
    assert!(
        image.alpha.iter().filter(|&&a| a > 0.5).count() > (w * h / 2) as usize,
        "the splats cover most of the view"
    );
    eprintln!("{checked} pixels compared");
}

/// More than 2^32 - 1 intersections: the u32 scan would wrap to 48,904 and the frame
/// would be rendered from a wrong count; the total is summed without wrap and refused.
#[test]
fn an_intersection_total_past_u32_is_refused_with_its_exact_size() {
    let gpu = gpu();
    let (w, h) = (1920, 1080);
    let cam = camera(w, h);
    let tiles: u64 = 120 * 68;
    // ceil(2^32 / 8160) splats, each covering every tile.
    let n = (1u64 << 32).div_ceil(tiles) as usize;
    let expected = n as u64 * tiles;
    assert!(expected > u64::from(u32::MAX) && (expected as u32) < 100_000);
    let mut cloud = GaussianCloud::new(0);
    let big = gaussian([0.0, 0.0, 0.0], 1e3, 3.0, [0.5, 0.5, 0.5]);
    for _ in 0..n {
        cloud.push(&big, 0u32);
    }
    let gaussians = GaussianBuffers::upload(&gpu, "gaussians", &cloud).expect("upload");
    let mut renderer = SplatRenderer::new(&gpu, w, h, n).expect("renderer");
    let text = expect_too_large(
        renderer.forward(&gaussians, &cam, &RenderSettings::default()),
        "4.3G intersections",
    );
    assert!(
        text.contains(&expected.to_string()) && text.contains("1920x1080"),
        "{text}"
    );
}

#[test]
fn an_image_past_one_binding_is_too_large_naming_its_size() {
    let gpu = gpu();
    let text = expect_too_large(
        SplatRenderer::new(&gpu, 100_000, 100_000, 10),
        "100000x100000",
    );
    assert!(
        text.contains("100000x100000")
            && text.contains("120000000000")
            && text.contains("maxStorageBufferRange"),
        "{text}"
    );
    let Err(err) = SplatRenderer::new(&gpu, 0, 64, 10) else {
        panic!("a zero width is refused");
    };
    assert!(err.to_string().contains("at least 1 pixel"), "{err}");
}

#[test]
fn plans_and_buffers_past_the_limits_are_too_large() {
    let gpu = gpu();
    let text = expect_too_large(
        ExclusiveScan::new(&gpu, "scan", ExclusiveScan::LIMIT + 1),
        "scan plan",
    );
    assert!(text.contains("elements to scan"), "{text}");
    let text = expect_too_large(RadixSort::new(&gpu, RadixSort::LIMIT + 1), "sort plan");
    assert!(text.contains("keys to sort"), "{text}");
    let info = gpu.info().clone();
    eprintln!(
        "maxStorageBufferRange {}, maxMemoryAllocationSize {}",
        info.max_storage_buffer_range, info.max_memory_allocation_size
    );
    assert!(
        info.max_storage_buffer_range >= 1 << 27,
        "Vulkan guarantees 2^27"
    );
    // A buffer may be larger than one binding; binding all of it is refused, naming
    // the buffer, the pass and the limit.
    let past_binding = info.max_storage_buffer_range + 4;
    if past_binding <= info.max_memory_allocation_size {
        let huge = gpu
            .create_buffer("huge", drape_engine::BufferDesc::gpu_only(past_binding))
            .expect("a buffer past one binding");
        let small = gpu.upload("small", &[0.0f32; 4]).expect("upload");
        let mut rec = gpu.record("too wide a binding").expect("record");
        let p = LossParams {
            len: 4,
            scale: 1.0,
            _pad: [0; 2],
        };
        let text = expect_too_large(
            rec.dispatch(
                "test.add_into",
                kernels::train::AddInto {
                    src: huge.read(),
                    dst: small.write(),
                },
                &p,
                [1, 1, 1],
            ),
            "binding",
        );
        assert!(
            text.contains("'huge'")
                && text.contains("test.add_into")
                && text.contains("maxStorageBufferRange"),
            "{text}"
        );
        drop(rec);
    } else {
        // Where one binding reaches as far as one allocation (an H100: 4 GiB - 1 against
        // 4,292,870,144 bytes), no buffer outgrows a binding; making one is refused,
        // naming the buffer and the allocation limit.
        eprintln!("no buffer can be larger than one binding on this device: the allocation limit is checked instead");
        let text = expect_too_large(
            gpu.create_buffer("huge", drape_engine::BufferDesc::gpu_only(past_binding)),
            "allocation",
        );
        assert!(
            text.contains("'huge'") && text.contains("maxMemoryAllocationSize"),
            "{text}"
        );
    }
    let text = expect_too_large(
        SplatRenderer::new(&gpu, 64, 64, RadixSort::LIMIT as usize + 1),
        "Gaussians",
    );
    assert!(text.contains("Gaussians"), "{text}");
    // A renderer made for 10 Gaussians given 11.
    let mut renderer = SplatRenderer::new(&gpu, 64, 64, 10).expect("renderer");
    let mut cloud = GaussianCloud::new(0);
    for i in 0..11 {
        cloud.push(
            &gaussian([0.1 * i as f32, 0.0, 0.0], 0.1, 1.0, [0.5; 3]),
            0u32,
        );
    }
    let g = GaussianBuffers::upload(&gpu, "g", &cloud).expect("upload");
    let text = expect_too_large(
        renderer.forward(&g, &camera(64, 64), &RenderSettings::default()),
        "capacity",
    );
    assert!(text.contains("capacity"), "{text}");
}

/// SH past one binding (degree 3: 192 bytes a Gaussian; lavapipe binds at most 128 MiB,
/// 699k Gaussians): projection and its backward run in chunks of the SH buffer. The
/// image and the gradients of Gaussians in the last chunk against the CPU reference.
#[test]
fn sh_past_one_binding_is_projected_in_chunks() {
    // Bindings capped at lavapipe's limit, so that a device binding far more (a discrete
    // GPU's 4 GiB) takes the same chunked path on a scene of the same size.
    let gpu = drape_tests::gpu_with(&drape_engine::ContextDesc {
        max_storage_buffer_range: Some(128 << 20),
        ..drape_engine::ContextDesc::for_tests()
    });
    let per_gaussian = 192u64;
    let n = (gpu.info().max_storage_buffer_range / per_gaussian + 20_000) as usize;
    let cloud = GaussianCloud::random(n, 3, 1.6, (-1.0, 1.0), 0.01, 41);
    let cam = camera(48, 32);
    let settings = RenderSettings::default();
    let gaussians = GaussianBuffers::upload(&gpu, "gaussians", &cloud).expect("upload");
    let mut renderer = SplatRenderer::new(&gpu, 48, 32, n).expect("renderer");
    let saved = renderer
        .forward(&gaussians, &cam, &settings)
        .expect("forward")
        .saved;
    let image = renderer.read_image().expect("read");
    let frame = frame_params(&cam, &settings, 3, n);
    let gs = cloud.gaussians::<f32>();
    let cpu = reference::render(&gs, &frame);
    // The forward test's tolerance: the same f32 code on both sides.
    let e = image
        .rgb
        .iter()
        .zip(&cpu.rgb)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max);
    assert!(e <= 1e-5, "rgb differs by {e:e}");
    let pixels = 48 * 32;
    let g_rgb = vec![1.0f32; 3 * pixels];
    let (g_alpha, g_depth) = (vec![0.5f32; pixels], vec![0.0f32; pixels]);
    let b_rgb = gpu.upload("grad rgb", &g_rgb).expect("upload");
    let b_alpha = gpu.upload("grad alpha", &g_alpha).expect("upload");
    let b_depth = gpu.upload("grad depth", &g_depth).expect("upload");
    let mut grads = GaussianBuffers::new(&gpu, "grads", n, 3).expect("grads");
    renderer
        .backward(
            &saved,
            &gaussians,
            &b_rgb,
            &b_alpha,
            &b_depth,
            &grads,
            drape_engine::ops::splat::render::Accumulation::Auto,
        )
        .expect("backward");
    let got = grads.download(&gpu, &cloud.groups).expect("download");
    let (want, _) = reference::backward(&gs, &frame, &cpu, &g_rgb, &g_alpha, &g_depth);
    // The last chunk starts at the largest multiple of 256 that one binding covers.
    let first_of_last = (gpu.info().max_storage_buffer_range / per_gaussian / 256 * 256) as usize;
    let (mut num, mut den, mut seen) = (0.0f64, 0.0f64, 0);
    for i in first_of_last..n {
        for k in 0..16 {
            for c in 0..3 {
                let (a, b) = (got.sh[(i * 16 + k) * 3 + c], want[i].sh[k][c]);
                num += f64::from(a - b).powi(2);
                den += f64::from(b).powi(2);
            }
        }
        seen += usize::from(want[i].sh[0][0] != 0.0);
    }
    assert!(
        seen > 100,
        "Gaussians of the last chunk contribute to the image ({seen})"
    );
    // The backward test's 1e-4: atomics add in another order than the CPU.
    assert!(
        (num / den).sqrt() <= 1e-4,
        "SH gradients of the last chunk: relative error {:e}",
        (num / den).sqrt()
    );
}

#[test]
fn a_grid_past_the_workgroup_limit_is_an_error_naming_the_pass() {
    let gpu = gpu();
    let a = gpu.upload("a", &[0.0f32; 4]).expect("upload");
    let b = gpu.upload("b", &[0.0f32; 4]).expect("upload");
    let limit = gpu.info().max_compute_workgroup_count[0];
    let mut rec = gpu.record("too many groups").expect("record");
    let p = LossParams {
        len: 4,
        scale: 1.0,
        _pad: [0; 2],
    };
    let err = rec
        .dispatch(
            "test.add_into",
            kernels::train::AddInto {
                src: a.read(),
                dst: b.write(),
            },
            &p,
            [limit + 1, 1, 1],
        )
        .expect_err("refused");
    let text = err.to_string();
    assert!(
        matches!(err, EngineError::TooLarge { .. })
            && text.contains("test.add_into")
            && text.contains("maxComputeWorkGroupCount"),
        "{text}"
    );
    drop(rec);
}

/// Adam over 17M floats (67K workgroups of 256, past one row) updates every element:
/// the first, the last and a sample between against the shared CPU update.
#[test]
fn adam_covers_a_group_past_one_row_of_workgroups() {
    let gpu = gpu();
    let len = 65_536 * 256 + 1_000;
    let params: Vec<f32> = (0..len).map(|i| (i % 1000) as f32 * 1e-3).collect();
    let grads: Vec<f32> = (0..len).map(|i| ((i % 7) as f32 - 3.0) * 0.1).collect();
    let mut p = gpu.upload("params", &params).expect("upload");
    let g = gpu.upload("grads", &grads).expect("upload");
    let group = AdamGroup::new(&gpu, "big", len, LrSchedule::constant(0.01)).expect("group");
    let mut rec = gpu.record("adam").expect("record");
    group.record_step(&mut rec, &p, &g).expect("record step");
    rec.submit_and_wait().expect("submit");
    let out = gpu.read_buffer::<f32>(&mut p, len).expect("read");
    let pc = drape_engine::ops::adam::step_params(len as u32, 0.01, 0.9, 0.999, 1e-15, 1);
    for i in (0..len).step_by(4099).chain([len - 1]) {
        let (expected, _, _) = adam_update(params[i], grads[i], 0.0, 0.0, &pc);
        // Same shared f32 function on both sides.
        assert!(
            (out[i] - expected).abs() <= 1e-6,
            "element {i}: {} vs {expected}",
            out[i]
        );
        if grads[i] != 0.0 {
            assert_ne!(out[i], params[i], "element {i} was not updated");
        }
    }
}
