//! Invariance and numerical extremes of the GPU splatting renderer (lavapipe,
//! validation on). Each extreme asserts finite outputs and a sensible image, compares
//! the forward with the CPU renderer, and the backward with the f64 CPU reference
//! wherever that reference is finite.

use drape_engine::ops::splat::reference;
use drape_engine::ops::splat::render::{Accumulation, GaussianBuffers, SplatRenderer};
use drape_engine::ops::splat::scene::{frame_params, GaussianCloud, PinholeCamera, RenderSettings};
use drape_shared::splat::layout::MAX_SH_COEFFS;
use drape_shared::splat::project::Gaussian;
use drape_tests::splat::{assert_forward_close, camera, gpu_render, scene};
use drape_tests::{gpu, TestGpu};

fn gaussian(mean: [f32; 3], log_scale: f32, opacity_logit: f32, rgb: [f32; 3]) -> Gaussian<f32> {
    let mut sh = [[0.0; 3]; MAX_SH_COEFFS];
    // DC coefficient giving `rgb` (colour = 0.5 + C0 * dc).
    sh[0] = rgb.map(|c| (c - 0.5) / 0.282_094_8);
    Gaussian {
        mean,
        log_scale: [log_scale; 3],
        quat: [1.0, 0.0, 0.0, 0.0],
        opacity_logit,
        sh,
    }
}

fn assert_finite(what: &str, values: &[f32]) {
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        panic!("{what}: value {i} is {}", values[i]);
    }
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn renders_are_bit_identical_run_to_run() {
    let gpu = gpu();
    let cloud = scene(2000, 3, 21);
    let cam = camera(96, 80);
    let settings = RenderSettings::default();
    let gaussians = GaussianBuffers::upload(&gpu, "g", &cloud).expect("upload");
    let mut renderer = SplatRenderer::new(&gpu, 96, 80, cloud.len()).expect("renderer");
    renderer
        .forward(&gaussians, &cam, &settings)
        .expect("forward");
    let first = renderer.read_image().expect("read");
    renderer
        .forward(&gaussians, &cam, &settings)
        .expect("forward");
    let second = renderer.read_image().expect("read");
    let (third, _) = gpu_render(&gpu, &cloud, &cam, &settings);
    for other in [&second, &third] {
        assert_eq!(bits(&first.rgb), bits(&other.rgb));
        assert_eq!(bits(&first.alpha), bits(&other.alpha));
        assert_eq!(bits(&first.depth), bits(&other.depth));
    }
}

#[test]
fn hidden_gaussians_leave_the_image_bit_identical() {
    let gpu = gpu();
    let cam = camera(80, 64);
    let settings = RenderSettings::default();
    let base = scene(500, 3, 22);
    let (before, _) = gpu_render(&gpu, &base, &cam, &settings);
    let eye = [0.3, -0.4, -5.0];
    let mut more = base.clone();
    // Behind the camera (the camera looks towards +z from z = -5).
    more.push(
        &gaussian([eye[0], eye[1], eye[2] - 2.0], -1.0, 3.0, [1.0, 0.0, 0.0]),
        0u32,
    );
    // Far outside the frustum, to the side.
    more.push(
        &gaussian([40.0, 0.0, 0.0], -2.0, 3.0, [0.0, 1.0, 0.0]),
        0u32,
    );
    // In plain view but with (numerically) zero opacity.
    more.push(
        &gaussian([0.0, 0.0, 0.0], -1.0, -30.0, [0.0, 0.0, 1.0]),
        0u32,
    );
    let (after, stats) = gpu_render(&gpu, &more, &cam, &settings);
    assert_eq!(stats.dropped, 0);
    assert_eq!(bits(&before.rgb), bits(&after.rgb));
    assert_eq!(bits(&before.alpha), bits(&after.alpha));
    assert_eq!(bits(&before.depth), bits(&after.depth));
}

fn compare_with_cpu(
    gpu: &TestGpu,
    cloud: &GaussianCloud,
    cam: &PinholeCamera,
    what: &str,
) -> drape_engine::ops::splat::render::RenderedImage {
    let settings = RenderSettings::default();
    let (image, _) = gpu_render(gpu, cloud, cam, &settings);
    assert_finite(&format!("{what}: rgb"), &image.rgb);
    assert_finite(&format!("{what}: alpha"), &image.alpha);
    assert_finite(&format!("{what}: depth"), &image.depth);
    assert!(
        image.alpha.iter().all(|a| (0.0..=1.0).contains(a)),
        "{what}: alpha outside [0, 1]"
    );
    let frame = frame_params(cam, &settings, cloud.sh_degree, cloud.len());
    let gaussians = cloud.gaussians::<f32>();
    let cpu = reference::render(&gaussians, &frame);
    // The forward test's comparison (1e-5 on a CPU device; see assert_forward_close).
    assert_forward_close(gpu, &image, &gaussians, &frame, &cpu, 1, what);
    image
}

/// The backward at an extreme: finite everywhere, and equal to the f64 CPU reference
/// (the same shared functions in f64) wherever that reference is finite. Per parameter
/// group, ||gpu - f64|| <= 1e-3 ||f64|| + 1e-5 √len: f32 against f64 through exp, the
/// 0.3 px² dilation and sums of up to 100k splats per pixel; the absolute floor covers
/// groups whose f64 gradient is ~0.
fn backward_matches_reference(
    gpu: &TestGpu,
    cloud: &GaussianCloud,
    cam: &PinholeCamera,
    what: &str,
) {
    backward_matches_reference_with(gpu, cloud, cam, what, Accumulation::Auto);
}

/// [`backward_matches_reference`] with the backward accumulating its gradients by
/// `accumulation`.
fn backward_matches_reference_with(
    gpu: &TestGpu,
    cloud: &GaussianCloud,
    cam: &PinholeCamera,
    what: &str,
    accumulation: Accumulation,
) {
    let settings = RenderSettings::default();
    let gaussians = GaussianBuffers::upload(gpu, "g", cloud).expect("upload");
    let mut grads =
        GaussianBuffers::new(gpu, "grads", cloud.len(), cloud.sh_degree).expect("grads");
    let mut renderer =
        SplatRenderer::new(gpu, cam.width, cam.height, cloud.len()).expect("renderer");
    let saved = renderer
        .forward(&gaussians, cam, &settings)
        .expect("forward")
        .saved;
    let pixels = (cam.width * cam.height) as usize;
    let (g_rgb, g_alpha, g_depth) = (
        vec![1.0f32; 3 * pixels],
        vec![1.0f32; pixels],
        vec![0.01f32; pixels],
    );
    let ones = gpu.upload("grad rgb", &g_rgb).expect("upload");
    let alpha = gpu.upload("grad alpha", &g_alpha).expect("upload");
    let depth = gpu.upload("grad depth", &g_depth).expect("upload");
    renderer
        .backward(
            &saved,
            &gaussians,
            &ones,
            &alpha,
            &depth,
            &grads,
            accumulation,
        )
        .expect("backward");
    let g = grads.download(gpu, &cloud.groups).expect("download");
    let frame = frame_params(cam, &settings, cloud.sh_degree, cloud.len());
    let gs = cloud.gaussians::<f64>();
    let fwd = reference::render(&gs, &frame);
    let to64 = |v: &[f32]| v.iter().map(|&x| f64::from(x)).collect::<Vec<f64>>();
    let (cpu, _) = reference::backward(
        &gs,
        &frame,
        &fwd,
        &to64(&g_rgb),
        &to64(&g_alpha),
        &to64(&g_depth),
    );
    let k = drape_shared::splat::layout::sh_coeffs(cloud.sh_degree);
    let groups: [(&str, &Vec<f32>, Vec<f64>); 5] = [
        ("means", &g.means, cpu.iter().flat_map(|c| c.mean).collect()),
        (
            "log_scales",
            &g.log_scales,
            cpu.iter().flat_map(|c| c.log_scale).collect(),
        ),
        ("quats", &g.quats, cpu.iter().flat_map(|c| c.quat).collect()),
        (
            "opacity_logits",
            &g.opacity_logits,
            cpu.iter().map(|c| c.opacity_logit).collect(),
        ),
        (
            "sh",
            &g.sh,
            cpu.iter()
                .flat_map(|c| c.sh[..k].iter().flatten().copied().collect::<Vec<_>>())
                .collect(),
        ),
    ];
    for (name, gpu_values, reference) in groups {
        assert_finite(&format!("{what}: gradient of {name}"), gpu_values);
        let finite: Vec<usize> = (0..reference.len())
            .filter(|&i| reference[i].is_finite())
            .collect();
        let num: f64 = finite
            .iter()
            .map(|&i| (f64::from(gpu_values[i]) - reference[i]).powi(2))
            .sum::<f64>()
            .sqrt();
        let den: f64 = finite
            .iter()
            .map(|&i| reference[i].powi(2))
            .sum::<f64>()
            .sqrt();
        let bound = 1e-3 * den + 1e-5 * (finite.len() as f64).sqrt();
        eprintln!(
            "{what}: {name}: |gpu - f64| {num:.3e}, |f64| {den:.3e} over {} of {} finite",
            finite.len(),
            reference.len()
        );
        assert!(
            num <= bound,
            "{what}: gradient of {name}: |gpu - f64| = {num:e} > {bound:e} (|f64| = {den:e})"
        );
    }
}

#[test]
fn extreme_scales_from_1e_minus_7_to_1e7() {
    let gpu = gpu();
    let cam = camera(64, 64);
    let mut cloud = GaussianCloud::new(0);
    for (i, s) in [1e-7f32, 1e-4, 1e-2, 1.0, 1e3, 1e7].iter().enumerate() {
        let x = -0.8 + 0.3 * i as f32;
        cloud.push(&gaussian([x, 0.0, 0.0], s.ln(), 1.0, [0.9, 0.5, 0.1]), 0u32);
    }
    let image = compare_with_cpu(&gpu, &cloud, &cam, "extreme scales");
    // The 1e7 Gaussian covers the whole view: no pixel shows only the background.
    assert!(
        image.alpha.iter().all(|&a| a > 0.5),
        "a 1e7-scale splat must cover every pixel"
    );
    backward_matches_reference(&gpu, &cloud, &cam, "extreme scales");
}

#[test]
fn tiny_splat_still_shows_as_a_dot() {
    let gpu = gpu();
    let cam = camera(64, 64);
    let mut cloud = GaussianCloud::new(0);
    cloud.push(
        &gaussian([0.0, 0.0, 0.0], (1e-7f32).ln(), 5.0, [1.0, 1.0, 1.0]),
        0u32,
    );
    let image = compare_with_cpu(&gpu, &cloud, &cam, "tiny splat");
    let peak = image.alpha.iter().copied().fold(0.0, f32::max);
    assert!(
        peak > 0.3,
        "the dilation keeps a 1e-7 splat visible (peak alpha {peak})"
    );
    assert!(
        image.alpha.iter().filter(|&&a| a > 0.0).count() < 40,
        "and small"
    );
}

#[test]
fn gaussian_straddling_the_near_plane() {
    let gpu = gpu();
    let mut cam = camera(64, 64);
    cam.near = 0.5;
    // The camera is at distance ~5 from the origin along +z; a large splat whose centre
    // is just in front of the near plane, and one just behind it.
    let eye = [0.3f32, -0.4, -5.0];
    let mut cloud = GaussianCloud::new(0);
    cloud.push(
        &gaussian(
            [eye[0], eye[1], eye[2] + 0.51],
            (0.8f32).ln(),
            1.0,
            [0.2, 0.9, 0.2],
        ),
        0u32,
    );
    cloud.push(
        &gaussian(
            [eye[0], eye[1], eye[2] + 0.49],
            (0.8f32).ln(),
            1.0,
            [0.9, 0.2, 0.2],
        ),
        0u32,
    );
    let image = compare_with_cpu(&gpu, &cloud, &cam, "near plane");
    assert!(
        image.alpha.iter().any(|&a| a > 0.5),
        "the splat in front of the near plane is drawn"
    );
    backward_matches_reference(&gpu, &cloud, &cam, "near plane");
}

#[test]
fn hundred_thousand_gaussians_over_one_pixel() {
    let gpu = gpu();
    let cam = camera(64, 64);
    let mut cloud = GaussianCloud::new(0);
    // Project the image centre back to z = 0: the camera looks at the origin.
    for i in 0..100_000 {
        let jitter = (i % 7) as f32 * 1e-4;
        cloud.push(
            &gaussian(
                [jitter, 0.0, 0.01 * (i % 100) as f32],
                (0.004f32).ln(),
                2.0,
                [0.3, 0.6, 0.9],
            ),
            0u32,
        );
    }
    let image = compare_with_cpu(&gpu, &cloud, &cam, "100k on one pixel");
    let peak = image.alpha.iter().copied().fold(0.0, f32::max);
    // Blending stops once transmittance would drop to 1e-4.
    assert!(peak > 0.999 && peak <= 1.0, "peak alpha {peak}");
    backward_matches_reference(&gpu, &cloud, &cam, "100k on one pixel");
}

/// `n` tiny splats stacked in front of the image centre (depths 0 to 0.99), then one
/// large splat behind them at depth 1.5: pixels of the stack's blocks that the tiny
/// splats miss blend only the large one, behind `n` splats in their tile's list.
fn stack_ahead_of_a_large_splat(n: usize) -> GaussianCloud {
    let mut cloud = GaussianCloud::new(0);
    for i in 0..n {
        let jitter = (i % 7) as f32 * 1e-4;
        cloud.push(
            &gaussian(
                [jitter, 0.0, 0.99 * (i % 100) as f32 / 100.0],
                (0.004f32).ln(),
                2.0,
                [0.3, 0.6, 0.9],
            ),
            0u32,
        );
    }
    cloud.push(
        &gaussian([0.0, 0.0, 1.5], (0.6f32).ln(), 1.0, [0.9, 0.4, 0.1]),
        0u32,
    );
    cloud
}

/// A walk longer than the subgroup rasterizers take sparsely (`SPARSE_MAX_WALK`, 56,000
/// splats, llvmpipe's loop budget): 60,000 tiny splats in front at the image centre put
/// every other pixel of their tile's blocks behind 60,000 splats that miss it, before
/// the large splat behind that it blends. The forward walks that tile's list densely,
/// and so does the backward of those pixels (their last splat is the 60,001st).
#[test]
fn sixty_thousand_splats_ahead_of_the_one_a_pixel_blends() {
    let gpu = gpu();
    let cam = camera(64, 64);
    let cloud = stack_ahead_of_a_large_splat(60_000);
    let image = compare_with_cpu(&gpu, &cloud, &cam, "60k ahead");
    // The large splat shows around the stack.
    assert!(
        image.alpha.iter().filter(|&&a| a > 0.5).count() > 100,
        "the splat behind is blended"
    );
    backward_matches_reference(&gpu, &cloud, &cam, "60k ahead");
}

/// The compare-and-swap backward's sparse walk spends a loop iteration per round, per
/// visited splat and per add (each add is a loop), so it walks sparsely only up to
/// 24,000 splats (`SPARSE_MAX_WALK_CAS`), not the 56,000 of the other backwards: pixels
/// behind 40,000 tiny splats that miss them, before the large splat they blend, get
/// their gradient from a dense walk there and from a sparse one with float atomics.
#[test]
fn forty_thousand_splats_ahead_through_the_compare_and_swap_backward() {
    let gpu = gpu();
    let cam = camera(64, 64);
    let cloud = stack_ahead_of_a_large_splat(40_000);
    backward_matches_reference_with(
        &gpu,
        &cloud,
        &cam,
        "40k ahead, compare-and-swap",
        Accumulation::CompareAndSwap,
    );
    backward_matches_reference_with(
        &gpu,
        &cloud,
        &cam,
        "40k ahead, float atomics",
        Accumulation::Auto,
    );
}

#[test]
fn opacity_logits_of_plus_and_minus_50() {
    let gpu = gpu();
    let cam = camera(64, 64);
    let mut cloud = GaussianCloud::new(0);
    cloud.push(
        &gaussian([-0.5, 0.0, 0.0], (0.2f32).ln(), 50.0, [1.0, 0.0, 0.0]),
        0u32,
    );
    cloud.push(
        &gaussian([0.5, 0.0, 0.0], (0.2f32).ln(), -50.0, [0.0, 1.0, 0.0]),
        0u32,
    );
    let image = compare_with_cpu(&gpu, &cloud, &cam, "opacity +-50");
    let peak = image.alpha.iter().copied().fold(0.0, f32::max);
    // Opacity 1 (sigmoid(50) rounds to 1): alpha reaches the 0.99 clamp near the centre.
    assert!((0.95..=0.99).contains(&peak), "peak alpha {peak}");
    // Opacity sigmoid(-50) ~ 2e-22 is culled: the image is that of the first alone.
    let mut first = GaussianCloud::new(0);
    first.push(&cloud.gaussian(0), 0u32);
    let (alone, _) = gpu_render(&gpu, &first, &cam, &RenderSettings::default());
    assert_eq!(bits(&alone.rgb), bits(&image.rgb));
    backward_matches_reference(&gpu, &cloud, &cam, "opacity +-50");
}

#[test]
fn zero_quaternion_renders_as_identity() {
    let gpu = gpu();
    let cam = camera(64, 64);
    let mut with_zero = GaussianCloud::new(0);
    let mut g = gaussian([0.1, 0.0, 0.0], (0.3f32).ln(), 1.0, [0.5, 0.7, 0.2]);
    g.log_scale = [(0.3f32).ln(), (0.05f32).ln(), (0.1f32).ln()];
    let mut identity = with_zero.clone();
    identity.push(&g, 0u32);
    g.quat = [0.0; 4];
    with_zero.push(&g, 0u32);
    let a = compare_with_cpu(&gpu, &with_zero, &cam, "zero quaternion");
    let (b, _) = gpu_render(&gpu, &identity, &cam, &RenderSettings::default());
    assert_eq!(
        bits(&a.rgb),
        bits(&b.rgb),
        "a zero quaternion means no rotation"
    );
    backward_matches_reference(&gpu, &with_zero, &cam, "zero quaternion");
}

#[test]
fn nan_gaussian_is_dropped_and_counted() {
    let gpu = gpu();
    let cam = camera(64, 64);
    let base = scene(300, 1, 23);
    let (before, stats) = gpu_render(&gpu, &base, &cam, &RenderSettings::default());
    assert_eq!(stats.dropped, 0);
    let mut with_nan = base.clone();
    let mut bad = base.gaussian::<f32>(0);
    bad.mean[1] = f32::NAN;
    with_nan.push(&bad, 0u32);
    let mut bad_sh = base.gaussian::<f32>(1);
    bad_sh.sh[2][1] = f32::INFINITY;
    with_nan.push(&bad_sh, 0u32);
    let (after, stats) = gpu_render(&gpu, &with_nan, &cam, &RenderSettings::default());
    assert_eq!(stats.dropped, 2, "both non-finite Gaussians are counted");
    assert_eq!(
        bits(&before.rgb),
        bits(&after.rgb),
        "and the rest of the image is unchanged"
    );
    backward_matches_reference(&gpu, &with_nan, &cam, "NaN Gaussian");
}

#[test]
fn one_by_one_image() {
    let gpu = gpu();
    let cam = camera(1, 1);
    let image = compare_with_cpu(&gpu, &scene(200, 3, 24), &cam, "1x1");
    assert_eq!(image.rgb.len(), 3);
}

#[test]
fn image_of_2048_by_2048() {
    let gpu = gpu();
    let cam = camera(2048, 2048);
    let image = compare_with_cpu(&gpu, &scene(3000, 0, 25), &cam, "2048x2048");
    assert!(
        image.alpha.iter().filter(|&&a| a > 0.1).count() > 10_000,
        "the splats cover a good part of the image"
    );
}
