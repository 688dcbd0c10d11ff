//! The GPU splatting renderer against the CPU reference (the same shared functions),
//! forward and backward, on lavapipe with validation.

use drape_engine::ops::splat::reference;
use drape_engine::ops::splat::render::{Accumulation, GaussianBuffers, SplatRenderer};
use drape_engine::ops::splat::scene::{frame_params, RenderSettings};
use drape_shared::splat::layout::sh_coeffs;
use drape_tests::splat::{camera, gpu_render, max_abs_diff, scene};
use drape_tests::{gpu, has_feature, Feature};
use rand::{Rng, SeedableRng};

/// RGB, alpha and depth (relative) within 1e-5: both sides run the same f32 code; only
/// the transcendental functions (exp, ln) may differ in their last bits.
const FORWARD_TOLERANCE: f32 = 1e-5;

fn check_forward(sizes: &[(u32, u32)], counts: &[usize]) {
    let gpu = gpu();
    for &(w, h) in sizes {
        for &n in counts {
            for degree in [0, 3] {
                for antialiased in [false, true] {
                    let cloud = scene(n, degree, n as u64 * 7 + u64::from(w));
                    let cam = camera(w, h);
                    let settings = RenderSettings { antialiased, ..RenderSettings::default() };
                    let (image, stats) = gpu_render(&gpu, &cloud, &cam, &settings);
                    let frame = frame_params(&cam, &settings, degree, cloud.len());
                    let cpu = reference::render(&cloud.gaussians::<f32>(), &frame);
                    let what = format!("{n} Gaussians, {w}x{h}, degree {degree}, antialiased {antialiased}");
                    // Equal on lavapipe; a GPU that fuses a * b + c may move a pair whose
                    // splat's bound falls on a tile edge: at most 0.1% + 2 pairs.
                    let d = (i64::from(stats.intersections) - cpu.intersections as i64).unsigned_abs();
                    assert!(d as f64 <= 1e-3 * cpu.intersections as f64 + 2.0, "intersections GPU {} vs CPU {}: {what}", stats.intersections, cpu.intersections);
                    let e_rgb = max_abs_diff(&image.rgb, &cpu.rgb);
                    let e_alpha = max_abs_diff(&image.alpha, &cpu.alpha);
                    assert!(e_rgb <= FORWARD_TOLERANCE, "rgb error {e_rgb:e}: {what}");
                    assert!(e_alpha <= FORWARD_TOLERANCE, "alpha error {e_alpha:e}: {what}");
                    // Depth is Σ wᵢ zᵢ with z near 5: the same 1e-5 relative to the depth.
                    let e_depth = image.depth.iter().zip(&cpu.depth).map(|(g, c)| (g - c).abs() / c.abs().max(1.0)).fold(0.0, f32::max);
                    assert!(e_depth <= FORWARD_TOLERANCE, "depth error {e_depth:e}: {what}");
                    assert!(cpu.depth.iter().any(|&z| z > 1.0) || n == 1, "depth is exercised: {what}");
                    assert!(image.alpha.iter().any(|&a| a > 0.1) || n == 1, "the scene must be visible: {what}");
                }
            }
        }
    }
}

#[test]
fn forward_matches_cpu_64x64() {
    check_forward(&[(64, 64)], &[1, 16, 1000, 10_000]);
}

#[test]
fn forward_matches_cpu_128x128() {
    check_forward(&[(128, 128)], &[1, 16, 1000, 10_000]);
}

#[test]
fn forward_matches_cpu_97x61() {
    check_forward(&[(97, 61)], &[1, 16, 1000, 10_000]);
}

/// ||a - b|| / ||b|| over one parameter group.
fn relative_error(gpu: &[f32], cpu: &[f32]) -> f64 {
    let num: f64 = gpu.iter().zip(cpu).map(|(a, b)| f64::from(a - b).powi(2)).sum();
    let den: f64 = cpu.iter().map(|b| f64::from(*b).powi(2)).sum();
    (num / den.max(1e-30)).sqrt()
}

/// Per-group relative error at most 1e-4: the GPU adds per-splat gradients in an
/// order the atomics choose, the CPU in pixel order; f32 sums of a few hundred terms
/// differ by ~1e-6 relative.
const BACKWARD_TOLERANCE: f64 = 1e-4;

/// Checks the GPU backward against the CPU reference; returns the gradients' bits.
fn check_backward(degree: u32, antialiased: bool, accumulation: Accumulation) -> Vec<u32> {
    let gpu = gpu();
    let (w, h) = (64, 48);
    let cloud = scene(300, degree, 11 + u64::from(degree));
    let cam = camera(w, h);
    let settings = RenderSettings { antialiased, ..RenderSettings::default() };
    let pixels = (w * h) as usize;
    let mut rng = rand::rngs::StdRng::seed_from_u64(5);
    let g_rgb: Vec<f32> = (0..3 * pixels).map(|_| rng.random_range(-1.0..1.0)).collect();
    let g_alpha: Vec<f32> = (0..pixels).map(|_| rng.random_range(-1.0..1.0)).collect();
    let g_depth: Vec<f32> = (0..pixels).map(|_| rng.random_range(-0.1..0.1)).collect();

    let gaussians = GaussianBuffers::upload(&gpu, "params", &cloud).expect("upload");
    let mut grads = GaussianBuffers::new(&gpu, "grads", cloud.len(), degree).expect("grads");
    let mut renderer = SplatRenderer::new(&gpu, w, h, cloud.len()).expect("renderer");
    renderer.forward(&gaussians, &cam, &settings).expect("forward");
    let b_rgb = gpu.upload("grad rgb", &g_rgb).expect("upload");
    let b_alpha = gpu.upload("grad alpha", &g_alpha).expect("upload");
    let b_depth = gpu.upload("grad depth", &g_depth).expect("upload");
    renderer.backward(&gaussians, &b_rgb, &b_alpha, &b_depth, &grads, accumulation).expect("backward");
    let gpu_grads = grads.download(&gpu, &cloud.layers).expect("download");

    let frame = frame_params(&cam, &settings, degree, cloud.len());
    let gs = cloud.gaussians::<f32>();
    let fwd = reference::render(&gs, &frame);
    let (cpu, _) = reference::backward(&gs, &frame, &fwd, &g_rgb, &g_alpha, &g_depth);
    let k = sh_coeffs(degree);
    let groups: [(&str, Vec<f32>, &Vec<f32>); 5] = [
        ("means", cpu.iter().flat_map(|g| g.mean).collect(), &gpu_grads.means),
        ("log_scales", cpu.iter().flat_map(|g| g.log_scale).collect(), &gpu_grads.log_scales),
        ("quats", cpu.iter().flat_map(|g| g.quat).collect(), &gpu_grads.quats),
        ("opacity_logits", cpu.iter().map(|g| g.opacity_logit).collect(), &gpu_grads.opacity_logits),
        ("sh", cpu.iter().flat_map(|g| g.sh[..k].iter().flatten().copied().collect::<Vec<_>>()).collect(), &gpu_grads.sh),
    ];
    for (name, c, g) in groups {
        assert!(c.iter().any(|v| *v != 0.0), "{name}: the CPU gradient is all zero; the check would be vacuous");
        let e = relative_error(g, &c);
        assert!(e <= BACKWARD_TOLERANCE, "{name}: relative error {e:e} (degree {degree}, antialiased {antialiased}, {accumulation:?})");
    }
    [&gpu_grads.means, &gpu_grads.log_scales, &gpu_grads.quats, &gpu_grads.opacity_logits, &gpu_grads.sh].into_iter().flatten().map(|v| v.to_bits()).collect()
}

/// Fixed-point accumulation matches the reference as the float paths do, and gives
/// the same bits on every run (float atomics need not: their order varies).
#[test]
fn backward_matches_cpu_deterministic_and_repeats_bit_for_bit() {
    let first = check_backward(3, false, Accumulation::Deterministic);
    check_backward(1, true, Accumulation::Deterministic);
    for repeat in 0..2 {
        let again = check_backward(3, false, Accumulation::Deterministic);
        let differing = first.iter().zip(&again).filter(|(a, b)| a != b).count();
        assert_eq!(differing, 0, "repeat {repeat}: {differing} of {} gradient values changed bits", first.len());
    }
}

#[test]
fn backward_matches_cpu_float_atomics() {
    if !has_feature(&gpu(), Feature::FloatAtomics, "backward_matches_cpu_float_atomics") {
        return;
    }
    check_backward(3, false, Accumulation::FloatAtomics);
    check_backward(0, true, Accumulation::FloatAtomics);
}

#[test]
fn backward_matches_cpu_compare_and_swap() {
    check_backward(3, false, Accumulation::CompareAndSwap);
    check_backward(1, true, Accumulation::CompareAndSwap);
}
