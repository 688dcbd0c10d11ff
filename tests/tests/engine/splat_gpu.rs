//! The GPU splatting renderer against the CPU reference (the same shared functions),
//! forward and backward, on lavapipe with validation.

use drape_engine::error::EngineError;
use drape_engine::ops::splat::reference;
use drape_engine::ops::splat::render::{
    Accumulation, GaussianBuffers, RasterVariant, SplatRenderer,
};
use drape_engine::ops::splat::scene::{frame_params, RenderSettings};
use drape_shared::half::round_to_f16;
use drape_shared::splat::layout::{sh_coeffs, DEFAULT_TILE_SIZE, RASTER_BLOCK};
use drape_tests::splat::{
    assert_forward_close, assert_forward_close_to, camera, gpu_render_with, raster_variants, scene,
};
use drape_tests::{gpu, has_feature, Feature};
use rand::{Rng, SeedableRng};

fn check_forward(sizes: &[(u32, u32)], counts: &[usize], test: &str) {
    check_forward_tiles(sizes, counts, DEFAULT_TILE_SIZE, test);
}

/// [`check_forward`] with tiles of `tile_size`, on every rasterizer that takes them.
fn check_forward_tiles(sizes: &[(u32, u32)], counts: &[usize], tile_size: u32, test: &str) {
    let gpu = gpu();
    let variants: Vec<RasterVariant> = raster_variants(&gpu, test)
        .into_iter()
        .filter(|&v| tile_size >= RASTER_BLOCK || v == RasterVariant::Subgroup)
        .collect();
    let (mut worst, mut near_threshold) = (0.0f32, 0);
    for &(w, h) in sizes {
        for &n in counts {
            for degree in [0, 3] {
                for (antialiased, &variant) in [false, true]
                    .into_iter()
                    .flat_map(|a| variants.iter().map(move |v| (a, v)))
                {
                    let cloud = scene(n, degree, n as u64 * 7 + u64::from(w));
                    let cam = camera(w, h);
                    let settings = RenderSettings {
                        antialiased,
                        tile_size,
                        ..RenderSettings::default()
                    };
                    let (image, stats) = gpu_render_with(&gpu, &cloud, &cam, &settings, variant);
                    let frame = frame_params(&cam, &settings, degree, cloud.len());
                    let gaussians = cloud.gaussians::<f32>();
                    let cpu = reference::render(&gaussians, &frame);
                    let what = format!("{n} Gaussians, {w}x{h}, degree {degree}, antialiased {antialiased}, {variant:?} rasterizer, tiles of {tile_size}");
                    // Equal on lavapipe; a GPU that fuses a * b + c may move a pair whose
                    // splat's bound falls on a tile edge: at most 0.1% + 2 pairs.
                    let d =
                        (i64::from(stats.intersections) - cpu.intersections as i64).unsigned_abs();
                    assert!(
                        d as f64 <= 1e-3 * cpu.intersections as f64 + 2.0,
                        "intersections GPU {} vs CPU {}: {what}",
                        stats.intersections,
                        cpu.intersections
                    );
                    // Every pixel: 1e-5 on a CPU device, the GPU allowance elsewhere
                    // (see assert_forward_close).
                    let seen =
                        assert_forward_close(&gpu, &image, &gaussians, &frame, &cpu, 1, &what);
                    worst = worst.max(seen.max_error);
                    near_threshold += seen.near_threshold;
                    assert!(
                        cpu.depth.iter().any(|&z| z > 1.0) || n == 1,
                        "depth is exercised: {what}"
                    );
                    assert!(
                        image.alpha.iter().any(|&a| a > 0.1) || n == 1,
                        "the scene must be visible: {what}"
                    );
                }
            }
        }
    }
    eprintln!(
        "{test} on {}: largest error {worst:e}, {near_threshold} pixels near a threshold",
        gpu.info().name
    );
}

#[test]
fn forward_matches_cpu_64x64() {
    check_forward(
        &[(64, 64)],
        &[1, 16, 1000, 10_000],
        "forward_matches_cpu_64x64",
    );
}

#[test]
fn forward_matches_cpu_128x128() {
    check_forward(
        &[(128, 128)],
        &[1, 16, 1000, 10_000],
        "forward_matches_cpu_128x128",
    );
}

#[test]
fn forward_matches_cpu_97x61() {
    check_forward(
        &[(97, 61)],
        &[1, 16, 1000, 10_000],
        "forward_matches_cpu_97x61",
    );
}

/// ||a - b|| / ||b|| over one parameter group.
fn relative_error(gpu: &[f32], cpu: &[f32]) -> f64 {
    let num: f64 = gpu
        .iter()
        .zip(cpu)
        .map(|(a, b)| f64::from(a - b).powi(2))
        .sum();
    let den: f64 = cpu.iter().map(|b| f64::from(*b).powi(2)).sum();
    (num / den.max(1e-30)).sqrt()
}

/// Per-group relative error at most 1e-4: the GPU adds per-splat gradients in an
/// order the atomics choose, the CPU in pixel order; f32 sums of a few hundred terms
/// differ by ~1e-6 relative.
const BACKWARD_TOLERANCE: f64 = 1e-4;

/// Checks the GPU backward against the CPU reference; returns the gradients' bits.
fn check_backward(
    degree: u32,
    antialiased: bool,
    accumulation: Accumulation,
    variant: RasterVariant,
) -> Vec<u32> {
    check_backward_tiles(
        degree,
        antialiased,
        accumulation,
        variant,
        DEFAULT_TILE_SIZE,
    )
}

/// [`check_backward`] with tiles of `tile_size`.
fn check_backward_tiles(
    degree: u32,
    antialiased: bool,
    accumulation: Accumulation,
    variant: RasterVariant,
    tile_size: u32,
) -> Vec<u32> {
    let gpu = gpu();
    // Not multiples of 16 (nor of the subgroup kernels' 8 x 4 blocks): edge tiles and
    // blocks with lanes and rows outside the image.
    let (w, h) = (61, 45);
    let cloud = scene(300, degree, 11 + u64::from(degree));
    let cam = camera(w, h);
    let settings = RenderSettings {
        antialiased,
        tile_size,
        ..RenderSettings::default()
    };
    let pixels = (w * h) as usize;
    let mut rng = rand::rngs::StdRng::seed_from_u64(5);
    let g_rgb: Vec<f32> = (0..3 * pixels)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    let g_alpha: Vec<f32> = (0..pixels).map(|_| rng.random_range(-1.0..1.0)).collect();
    let g_depth: Vec<f32> = (0..pixels).map(|_| rng.random_range(-0.1..0.1)).collect();

    let gaussians = GaussianBuffers::upload(&gpu, "params", &cloud).expect("upload");
    let mut grads = GaussianBuffers::new(&gpu, "grads", cloud.len(), degree).expect("grads");
    let mut renderer = SplatRenderer::new(&gpu, w, h, cloud.len()).expect("renderer");
    renderer
        .set_raster_variant(variant)
        .expect("raster variant");
    let saved = renderer
        .forward(&gaussians, &cam, &settings)
        .expect("forward")
        .saved;
    let b_rgb = gpu.upload("grad rgb", &g_rgb).expect("upload");
    let b_alpha = gpu.upload("grad alpha", &g_alpha).expect("upload");
    let b_depth = gpu.upload("grad depth", &g_depth).expect("upload");
    renderer
        .backward(
            &saved,
            &gaussians,
            &b_rgb,
            &b_alpha,
            &b_depth,
            &grads,
            accumulation,
        )
        .expect("backward");
    let gpu_grads = grads.download(&gpu, &cloud.groups).expect("download");

    let frame = frame_params(&cam, &settings, degree, cloud.len());
    let gs = cloud.gaussians::<f32>();
    let fwd = reference::render(&gs, &frame);
    let (cpu, _) = reference::backward(&gs, &frame, &fwd, &g_rgb, &g_alpha, &g_depth);
    let k = sh_coeffs(degree);
    let groups: [(&str, Vec<f32>, &Vec<f32>); 5] = [
        (
            "means",
            cpu.iter().flat_map(|g| g.mean).collect(),
            &gpu_grads.means,
        ),
        (
            "log_scales",
            cpu.iter().flat_map(|g| g.log_scale).collect(),
            &gpu_grads.log_scales,
        ),
        (
            "quats",
            cpu.iter().flat_map(|g| g.quat).collect(),
            &gpu_grads.quats,
        ),
        (
            "opacity_logits",
            cpu.iter().map(|g| g.opacity_logit).collect(),
            &gpu_grads.opacity_logits,
        ),
        (
            "sh",
            cpu.iter()
                .flat_map(|g| g.sh[..k].iter().flatten().copied().collect::<Vec<_>>())
                .collect(),
            &gpu_grads.sh,
        ),
    ];
    for (name, c, g) in groups {
        assert!(
            c.iter().any(|v| *v != 0.0),
            "{name}: the CPU gradient is all zero; the check would be vacuous"
        );
        let e = relative_error(g, &c);
        assert!(e <= BACKWARD_TOLERANCE, "{name}: relative error {e:e} (degree {degree}, antialiased {antialiased}, {accumulation:?}, {variant:?} rasterizer, tiles of {tile_size})");
    }
    [
        &gpu_grads.means,
        &gpu_grads.log_scales,
        &gpu_grads.quats,
        &gpu_grads.opacity_logits,
        &gpu_grads.sh,
    ]
    .into_iter()
    .flatten()
    .map(|v| v.to_bits())
    .collect()
}

/// Fixed-point accumulation matches the reference as the float paths do, and gives
/// the same bits on every run (float atomics need not: their order varies), with each
/// rasterizer.
#[test]
fn backward_matches_cpu_deterministic_and_repeats_bit_for_bit() {
    for variant in raster_variants(
        &gpu(),
        "backward_matches_cpu_deterministic_and_repeats_bit_for_bit",
    ) {
        let first = check_backward(3, false, Accumulation::Deterministic, variant);
        check_backward(1, true, Accumulation::Deterministic, variant);
        for repeat in 0..2 {
            let again = check_backward(3, false, Accumulation::Deterministic, variant);
            let differing = first.iter().zip(&again).filter(|(a, b)| a != b).count();
            assert_eq!(differing, 0, "{variant:?} rasterizer, repeat {repeat}: {differing} of {} gradient values changed bits", first.len());
        }
    }
}

#[test]
fn backward_matches_cpu_float_atomics() {
    if !has_feature(
        &gpu(),
        Feature::FloatAtomics,
        "backward_matches_cpu_float_atomics",
    ) {
        return;
    }
    for variant in raster_variants(&gpu(), "backward_matches_cpu_float_atomics") {
        check_backward(3, false, Accumulation::FloatAtomics, variant);
        check_backward(0, true, Accumulation::FloatAtomics, variant);
    }
}

#[test]
fn backward_matches_cpu_compare_and_swap() {
    for variant in raster_variants(&gpu(), "backward_matches_cpu_compare_and_swap") {
        check_backward(3, false, Accumulation::CompareAndSwap, variant);
        check_backward(1, true, Accumulation::CompareAndSwap, variant);
    }
}

/// Each Gaussian's contribution to a frame (`SplatRenderer::contributions`, the sum of
/// its blend weights `α · T` over the pixels, for pruning by contribution) matches the
/// reference's colour gradient under a red-only upstream of ones, and, checked without
/// the backward's code, the contributions sum to the sum of the forward's alpha image
/// (per pixel the weights add up to `1 - T`).
#[test]
fn contributions_match_the_reference_and_sum_to_the_alpha_image() {
    let gpu = gpu();
    for variant in raster_variants(
        &gpu,
        "contributions_match_the_reference_and_sum_to_the_alpha_image",
    ) {
        for &((w, h), n) in &[((64u32, 64u32), 1000usize), ((97, 61), 300)] {
            let cloud = scene(n, 0, 23 + n as u64);
            let cam = camera(w, h);
            let settings = RenderSettings::default();
            let gaussians =
                GaussianBuffers::upload(&gpu, "contribution scene", &cloud).expect("upload");
            let mut renderer = SplatRenderer::new(&gpu, w, h, cloud.len()).expect("renderer");
            renderer
                .set_raster_variant(variant)
                .expect("raster variant");
            let saved = renderer
                .forward(&gaussians, &cam, &settings)
                .expect("forward")
                .saved;
            let image = renderer.read_image().expect("read");
            let got = renderer.contributions(&saved).expect("contributions");
            assert_eq!(got.len(), n);

            let frame = frame_params(&cam, &settings, 0, n);
            let gs = cloud.gaussians::<f32>();
            let fwd = reference::render(&gs, &frame);
            let pixels = (w * h) as usize;
            let red: Vec<f32> = (0..pixels).flat_map(|_| [1.0f32, 0.0, 0.0]).collect();
            let zeros = vec![0.0f32; pixels];
            let (_, splat_grads) = reference::backward(&gs, &frame, &fwd, &red, &zeros, &zeros);
            let what = format!("{n} Gaussians, {w}x{h}, {variant:?} rasterizer");
            assert!(
                splat_grads.iter().filter(|g| g.color[0] > 1.0).count() > n / 10,
                "most Gaussians must cover a pixel or more: {what}"
            );
            let mut worst = 0.0f32;
            for (i, (g, c)) in got.iter().zip(&splat_grads).enumerate() {
                let want = c.color[0];
                // The reference adds its weights in f32 pixel by pixel, the GPU in
                // 64-bit fixed point in the atomics' order: f32 sums of up to a few
                // thousand weights differ by ~1e-6 relative; 1e-4 leaves room and still
                // catches a dropped pixel or splat (at least 1/pixels relative).
                let err = (g - want).abs() / want.max(1.0);
                worst = worst.max(err);
                assert!(
                    err <= 1e-4,
                    "Gaussian {i}: contribution {g} vs reference {want}: {what}"
                );
            }
            let total: f64 = got.iter().map(|&c| f64::from(c)).sum();
            let alpha: f64 = image.alpha.iter().map(|&a| f64::from(a)).sum();
            // Per pixel Σ α·T = 1 - T_final exactly; in f32 the backward's T (recovered
            // by division) drifts ~n·ε relative from the forward's product.
            assert!(
                (total - alpha).abs() <= 1e-4 * alpha,
                "contributions sum to {total}, the alpha image to {alpha}: {what}"
            );
            eprintln!("contributions, {what}: largest relative error {worst:e}; sum {total:.4} vs alpha {alpha:.4}");
        }
    }
}

/// The backward takes what its forward returned (`SavedForward`) and refuses, naming
/// why, the state of a forward the renderer has since overwritten, another renderer's,
/// a default value, and a forward of another number of Gaussians; the last forward's
/// own is accepted.
#[test]
fn a_backward_refuses_the_saved_state_of_another_forward() {
    use drape_engine::ops::splat::render::SavedForward;
    let gpu = gpu();
    let (w, h) = (32u32, 32u32);
    let (a, b) = (scene(50, 0, 1), scene(40, 0, 2));
    let (ga, gb) = (
        GaussianBuffers::upload(&gpu, "a", &a).expect("upload"),
        GaussianBuffers::upload(&gpu, "b", &b).expect("upload"),
    );
    let grads_b = GaussianBuffers::new(&gpu, "grads b", b.len(), 0).expect("grads");
    let mut renderer = SplatRenderer::new(&gpu, w, h, 50).expect("renderer");
    let mut other = SplatRenderer::new(&gpu, w, h, 50).expect("renderer");
    let cam = camera(w, h);
    let settings = RenderSettings::default();
    let pixels = (w * h) as usize;
    let g_rgb = gpu
        .upload("grad rgb", &vec![1.0f32; 3 * pixels])
        .expect("upload");
    let zeros = gpu.upload("zeros", &vec![0.0f32; pixels]).expect("upload");
    let first = renderer
        .forward(&ga, &cam, &settings)
        .expect("forward")
        .saved;
    let second = renderer
        .forward(&gb, &cam, &settings)
        .expect("forward")
        .saved;
    let from_other = other.forward(&gb, &cam, &settings).expect("forward").saved;
    renderer
        .backward(
            &second,
            &gb,
            &g_rgb,
            &zeros,
            &zeros,
            &grads_b,
            Accumulation::Auto,
        )
        .expect("the last forward's own state");
    for (saved, why) in [
        (first, "earlier forward"),
        (from_other, "another renderer"),
        (SavedForward::default(), "no complete forward"),
    ] {
        let e = renderer
            .backward(
                &saved,
                &gb,
                &g_rgb,
                &zeros,
                &zeros,
                &grads_b,
                Accumulation::Auto,
            )
            .expect_err(why);
        let text = e.to_string();
        eprintln!("{text}");
        assert!(
            text.contains("splat backward") && text.contains(why),
            "{why}: {text}"
        );
    }
    // The state of a forward of 50 Gaussians, for a cloud of 40.
    let third = renderer
        .forward(&ga, &cam, &settings)
        .expect("forward")
        .saved;
    let e = renderer
        .backward(
            &third,
            &gb,
            &g_rgb,
            &zeros,
            &zeros,
            &grads_b,
            Accumulation::Auto,
        )
        .expect_err("another count");
    assert!(e.to_string().contains("50 Gaussians, but 40"), "{e}");
    assert!(
        renderer.contributions(&second).is_err(),
        "contributions take the last forward's state too"
    );
}

/// Densification statistics (`ops::splat::densify`) of two frames of one render, for a
/// slice of the Gaussians written at an offset, match the CPU reference: the visible
/// counts exactly, the gradient-norm sums to 1e-6 relative (the same f32 operations
/// in the same order; only `sqrt` may differ in the last bit), the radii to within the
/// one pixel that a last-bit `sqrt` difference can move a `ceil`.
#[test]
fn screen_stats_match_the_reference() {
    use drape_engine::ops::splat::densify::{
        record_screen_stats, reference, ScreenStatsParams, SCREEN_STATS_FLOATS,
    };
    let ctx = gpu();
    let (w, h) = (64, 48);
    let cloud = scene(300, 0, 21);
    let cam = camera(w, h);
    let settings = RenderSettings::default();
    let pixels = (w * h) as usize;
    let mut rng = rand::rngs::StdRng::seed_from_u64(8);
    let g_rgb: Vec<f32> = (0..3 * pixels)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    let gaussians = GaussianBuffers::upload(&ctx, "params", &cloud).expect("upload");
    let grads = GaussianBuffers::new(&ctx, "grads", cloud.len(), 0).expect("grads");
    let mut renderer = SplatRenderer::new(&ctx, w, h, cloud.len()).expect("renderer");
    let saved = renderer
        .forward(&gaussians, &cam, &settings)
        .expect("forward")
        .saved;
    let b_rgb = ctx.upload("grad rgb", &g_rgb).expect("upload");
    let zeros = ctx.upload("zeros", &vec![0.0f32; pixels]).expect("upload");
    renderer
        .backward(
            &saved,
            &gaussians,
            &b_rgb,
            &zeros,
            &zeros,
            &grads,
            Accumulation::Deterministic,
        )
        .expect("backward");
    let (first, count, out_first) = (40u32, 200u32, 7u32);
    let len = SCREEN_STATS_FLOATS * (out_first + count + 3) as usize;
    let mut stats = ctx.upload("stats", &vec![0.0f32; len]).expect("upload");
    for _ in 0..2 {
        let mut rec = ctx.record("stats").expect("record");
        record_screen_stats(&mut rec, &renderer, first, count, &stats, out_first).expect("stats");
        rec.submit_and_wait().expect("submit");
    }
    let got = ctx.read_buffer::<f32>(&mut stats, len).expect("read");
    let splats = renderer.read_splats(cloud.len()).expect("splats");
    let splat_grads = renderer.read_splat_grads(cloud.len()).expect("splat grads");
    let mut want = vec![0.0f32; len];
    let p = ScreenStatsParams {
        first,
        count,
        out_first,
        width: w,
        height: h,
        _pad: [0; 3],
    };
    reference::screen_stats(&splats, &splat_grads, p, &mut want);
    reference::screen_stats(&splats, &splat_grads, p, &mut want);
    let visible = want.chunks_exact(3).filter(|s| s[1] > 0.0).count();
    assert!(
        visible > 50,
        "{visible} of {count} visible: too few for the check to mean much"
    );
    for (k, (g, c)) in got.chunks_exact(3).zip(want.chunks_exact(3)).enumerate() {
        assert_eq!(g[1], c[1], "Gaussian slot {k}: visible frames");
        assert!(
            (g[0] - c[0]).abs() <= 1e-6 * c[0].abs() + 1e-12,
            "Gaussian slot {k}: gradient-norm sum {} vs {}",
            g[0],
            c[0]
        );
        assert!(
            (g[2] - c[2]).abs() <= 1.0,
            "Gaussian slot {k}: radius {} vs {}",
            g[2],
            c[2]
        );
        let inside = k >= out_first as usize && k < (out_first + count) as usize;
        if !inside {
            assert_eq!(
                g, [0.0; 3],
                "slot {k} is outside the slice and must stay zero"
            );
        }
        if inside && c[1] > 0.0 {
            assert_eq!(c[1], 2.0, "two frames added");
        }
    }
}

/// The statistics are in 3DGS's units, checked independently of the shared code: one
/// Gaussian on a camera looking down +z; its gradient-norm statistic equals the
/// gradient of the loss `Σ g·rgb` with respect to its centre in normalised device
/// coordinates, measured by central differences of the f64 reference renderer
/// (moving the mean by δ moves the centre by `fx δ / z` pixels, `W / 2` pixels per NDC
/// unit); its radius is `ceil(3 √λ)` with `λ = (fx s / z)² + 0.3` (isotropic, dilated).
#[test]
fn screen_stats_are_in_3dgs_units() {
    use drape_engine::ops::splat::densify::{record_screen_stats, SCREEN_STATS_FLOATS};
    use drape_engine::ops::splat::scene::{GaussianCloud, PinholeCamera};
    use drape_shared::splat::project::Gaussian;
    let ctx = gpu();
    let (w, h) = (64u32, 48u32);
    let (f, z, s) = (50.0f32, 3.0f32, 0.1f32);
    let cam = PinholeCamera {
        fx: f,
        fy: f,
        cx: 30.0,
        cy: 22.0,
        width: w,
        height: h,
        rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        translation: [0.0; 3],
        near: 0.01,
        far: 100.0,
        background: [0.0; 3],
    };
    let settings = RenderSettings::default();
    let make = |dx: f32, dy: f32| {
        let mut c = GaussianCloud::new(0);
        let mut sh = [[0.0f32; 3]; drape_shared::splat::layout::MAX_SH_COEFFS];
        sh[0] = [1.0, 0.5, -0.5];
        c.push(
            &Gaussian {
                mean: [dx, dy, z],
                log_scale: [s.ln(); 3],
                quat: [1.0, 0.0, 0.0, 0.0],
                opacity_logit: 1.0,
                sh,
            },
            0u32,
        );
        c
    };
    let pixels = (w * h) as usize;
    // A smooth weighting that varies across the image, so the gradient is not zero.
    let g_rgb: Vec<f32> = (0..pixels)
        .flat_map(|p| {
            let (x, y) = ((p % w as usize) as f32, (p / w as usize) as f32);
            [
                x / w as f32,
                0.5 - y / h as f32,
                0.3 * x * y / pixels as f32,
            ]
        })
        .collect();
    let loss = |cloud: &GaussianCloud| -> f64 {
        let frame = frame_params(&cam, &settings, 0, 1);
        let r = reference::render(&cloud.gaussians::<f64>(), &frame);
        r.rgb
            .iter()
            .zip(&g_rgb)
            .map(|(c, g)| c * f64::from(*g))
            .sum()
    };
    let d = 1e-4f32;
    let per_pixel = f64::from(f) * f64::from(d) / f64::from(z);
    let gx = (loss(&make(d, 0.0)) - loss(&make(-d, 0.0))) / (2.0 * per_pixel);
    let gy = (loss(&make(0.0, d)) - loss(&make(0.0, -d))) / (2.0 * per_pixel);
    let want_norm = ((gx * f64::from(w) / 2.0).powi(2) + (gy * f64::from(h) / 2.0).powi(2)).sqrt();
    let want_radius = (3.0 * ((f * s / z).powi(2) + 0.3).sqrt()).ceil();

    let cloud = make(0.0, 0.0);
    let gaussians = GaussianBuffers::upload(&ctx, "one", &cloud).expect("upload");
    let grads = GaussianBuffers::new(&ctx, "grads", 1, 0).expect("grads");
    let mut renderer = SplatRenderer::new(&ctx, w, h, 1).expect("renderer");
    let saved = renderer
        .forward(&gaussians, &cam, &settings)
        .expect("forward")
        .saved;
    let b_rgb = ctx.upload("grad rgb", &g_rgb).expect("upload");
    let zeros = ctx.upload("zeros", &vec![0.0f32; pixels]).expect("upload");
    renderer
        .backward(
            &saved,
            &gaussians,
            &b_rgb,
            &zeros,
            &zeros,
            &grads,
            Accumulation::CompareAndSwap,
        )
        .expect("backward");
    let mut stats = ctx
        .upload("stats", &[0.0f32; SCREEN_STATS_FLOATS])
        .expect("upload");
    let mut rec = ctx.record("stats").expect("record");
    record_screen_stats(&mut rec, &renderer, 0, 1, &stats, 0).expect("stats");
    rec.submit_and_wait().expect("submit");
    let got = ctx.read_buffer::<f32>(&mut stats, 3).expect("read");
    eprintln!("gradient norm (NDC): GPU {} vs central differences {want_norm}; radius {} vs {want_radius}", got[0], got[2]);
    assert_eq!(got[1], 1.0, "visible in the one frame");
    assert!(
        want_norm > 1e-3,
        "the check would be vacuous: gradient norm {want_norm}"
    );
    // 1%: central differences of an f64 render at δ = 1e-4 are accurate to ~1e-6; the
    // rest is the GPU's f32 blending (~1e-5 relative).
    assert!(
        (f64::from(got[0]) - want_norm).abs() <= 1e-2 * want_norm,
        "gradient norm {} vs {want_norm}",
        got[0]
    );
    assert_eq!(got[2], want_radius, "screen radius");
}

/// A forward frame is one `vkQueueSubmit` with no host read inside it; a frame whose
/// tile intersections overflow the capacity it was recorded with (forced tiny here)
/// grows its buffers and renders again, and its image is the CPU reference's, not one
/// drawn from a truncated list.
#[test]
fn a_frame_is_one_submission_and_an_intersection_overflow_still_renders_correctly() {
    let gpu = gpu();
    let cloud = scene(1000, 3, 41);
    let cam = camera(96, 64);
    let settings = RenderSettings::default();
    let frame = frame_params(&cam, &settings, 3, cloud.len());
    let host_gaussians = cloud.gaussians::<f32>();
    let cpu = reference::render(&host_gaussians, &frame);
    assert!(
        cpu.intersections > 1000,
        "the scene must have many intersections ({})",
        cpu.intersections
    );
    let gaussians = GaussianBuffers::upload(&gpu, "frame test", &cloud).expect("upload");
    let mut renderer =
        SplatRenderer::new(&gpu, cam.width, cam.height, cloud.len()).expect("renderer");
    renderer
        .set_intersection_capacity(cpu.intersections as u32 + 100)
        .expect("capacity");

    let before = gpu.submission_count();
    let stats = renderer
        .forward(&gaussians, &cam, &settings)
        .expect("forward");
    assert_eq!(
        gpu.submission_count() - before,
        1,
        "a frame with room for its intersections is one submission"
    );
    assert!(!stats.rerendered);
    let ample = renderer.read_image().expect("read");

    for capacity in [1, 7, cpu.intersections as u32 / 2] {
        renderer
            .set_intersection_capacity(capacity)
            .expect("capacity");
        // (Not counted: growing makes new buffers, which tests poison, through
        // submissions of their own where device buffers are not mapped.)
        let stats = renderer
            .forward(&gaussians, &cam, &settings)
            .expect("forward");
        assert!(
            stats.rerendered,
            "capacity {capacity}: the overflow is reported"
        );
        assert_eq!(
            u64::from(stats.intersections),
            cpu.intersections,
            "capacity {capacity}"
        );
        assert!(
            u64::from(renderer.intersection_capacity()) >= cpu.intersections,
            "capacity {capacity}: the buffers grew"
        );
        let image = renderer.read_image().expect("read");
        // The same frame as with room to spare, bit for bit, and the CPU reference's.
        let differ = image
            .rgb
            .iter()
            .zip(&ample.rgb)
            .chain(image.alpha.iter().zip(&ample.alpha))
            .filter(|(a, b)| a != b)
            .count();
        assert_eq!(
            differ, 0,
            "capacity {capacity}: values that differ from the frame with room to spare"
        );
        assert_forward_close(
            &gpu,
            &image,
            &host_gaussians,
            &frame,
            &cpu,
            1,
            &format!("capacity {capacity}"),
        );
        // The next frame fits: one submission again.
        let before = gpu.submission_count();
        let again = renderer
            .forward(&gaussians, &cam, &settings)
            .expect("forward");
        assert_eq!(gpu.submission_count() - before, 1);
        assert!(!again.rerendered);
    }
}

/// The tile-size knob (`engine-bench trade`): tiles of 8 and 32 render what the CPU
/// reference renders at that size, forward (sizes no multiple of 32, so edge tiles and
/// blocks are partial) and backward, on every rasterizer that takes the size; the
/// image is the one tiles of 16 give, and the intersections move the way tile size
/// says they must.
#[test]
fn tile_sizes_8_and_32_match_cpu() {
    let test = "tile_sizes_8_and_32_match_cpu";
    for tile_size in [8, 32] {
        check_forward_tiles(&[(97, 61)], &[16, 3000], tile_size, test);
        for variant in raster_variants(&gpu(), test) {
            if tile_size >= RASTER_BLOCK || variant == RasterVariant::Subgroup {
                check_backward_tiles(3, false, Accumulation::Deterministic, variant, tile_size);
            }
        }
    }
    let gpu = gpu();
    let cloud = scene(3000, 3, 17);
    let cam = camera(97, 61);
    let variant = *raster_variants(&gpu, test).last().expect("a rasterizer");
    let render = |tile_size| {
        gpu_render_with(
            &gpu,
            &cloud,
            &cam,
            &RenderSettings {
                tile_size,
                ..RenderSettings::default()
            },
            variant,
        )
    };
    let (image16, stats16) = render(16);
    // Tiles of 8 need the subgroup rasterizer; without it (a GPU) raster_variants has
    // printed SKIPPED for it, and only 32 is compared with 16.
    let smaller_tiles = variant == RasterVariant::Subgroup;
    let mut intersections = vec![];
    for tile_size in if smaller_tiles { vec![8, 32] } else { vec![32] } {
        let (image, stats) = render(tile_size);
        // The same splats blend in the same order at every pixel; only the entries a
        // pixel skips differ, so the colours agree to the last bits (1e-6: a GPU may
        // contract the blend differently per kernel build).
        let d = drape_tests::splat::max_abs_diff(&image.rgb, &image16.rgb).max(
            drape_tests::splat::max_abs_diff(&image.alpha, &image16.alpha),
        );
        assert!(
            d <= 1e-6,
            "tiles of {tile_size} vs 16: colour differs by {d} ({variant:?})"
        );
        intersections.push(stats.intersections);
    }
    // A splat's extent covers more small tiles than large ones.
    let n32 = *intersections.last().expect("tiles of 32");
    assert!(
        stats16.intersections > n32,
        "intersections at tiles of 16, 32: {}, {n32}",
        stats16.intersections
    );
    if smaller_tiles {
        assert!(
            intersections[0] > stats16.intersections,
            "intersections at tiles of 8, 16: {}, {}",
            intersections[0],
            stats16.intersections
        );
    }

    // What the kernels cannot take is refused before anything is recorded.
    let gaussians = GaussianBuffers::upload(&gpu, "params", &cloud).expect("upload");
    let mut renderer = SplatRenderer::new(&gpu, 97, 61, cloud.len()).expect("renderer");
    let err = renderer
        .forward(
            &gaussians,
            &cam,
            &RenderSettings {
                tile_size: 12,
                ..RenderSettings::default()
            },
        )
        .expect_err("tile size 12");
    assert!(
        matches!(err, EngineError::InvalidSetting { .. })
            && err.to_string().contains("tile size 12"),
        "{err}"
    );
    renderer
        .set_raster_variant(RasterVariant::Workgroup)
        .expect("workgroup rasterizer");
    let err = renderer
        .forward(
            &gaussians,
            &cam,
            &RenderSettings {
                tile_size: 8,
                ..RenderSettings::default()
            },
        )
        .expect_err("tiles of 8 on the workgroup rasterizer");
    assert!(
        matches!(err, EngineError::MissingFeature { .. }) && err.to_string().contains("tiles of 8"),
        "{err}"
    );
}

/// The half-precision SH knob (`RenderSettings::half_sh`): the GPU render from packed
/// halves equals the CPU reference rendered from the same SH rounded on the host
/// (`drape_shared::half`, the same rounding bit for bit), and differs from the
/// full-precision reference by no more than half precision allows; its backward is
/// refused.
#[test]
fn half_precision_sh_matches_cpu() {
    let test = "half_precision_sh_matches_cpu";
    let gpu = gpu();
    // Degrees 0 and 2 pack an odd count of halves (a padded word per Gaussian).
    for degree in [0, 2, 3] {
        for &variant in &raster_variants(&gpu, test) {
            let cloud = scene(3000, degree, 23 + u64::from(degree));
            let cam = camera(97, 61);
            let settings = RenderSettings {
                half_sh: true,
                ..RenderSettings::default()
            };
            let (image, _) = gpu_render_with(&gpu, &cloud, &cam, &settings, variant);
            let frame = frame_params(&cam, &settings, degree, cloud.len());
            let full = cloud.gaussians::<f32>();
            let mut rounded = full.clone();
            // Per Gaussian and channel, the colour can move by at most Σ_k |Y_k| |δ_k|
            // ≤ Σ_k |δ_k| (every real SH basis function up to degree 3 is at most 1 in
            // magnitude on the sphere; the clamp at 0 cannot add to it).
            let mut colour_bound = 0.0f32;
            for g in &mut rounded {
                let mut moved = [0.0f32; 3];
                for k in g.sh.iter_mut() {
                    for (c, v) in k.iter_mut().enumerate() {
                        let r = round_to_f16(*v);
                        moved[c] += (r - *v).abs();
                        *v = r;
                    }
                }
                colour_bound = colour_bound.max(moved[0]).max(moved[1]).max(moved[2]);
            }
            let what = format!("half-precision SH, degree {degree}, {variant:?} rasterizer");
            let cpu = reference::render(&rounded, &frame);
            assert_forward_close(&gpu, &image, &rounded, &frame, &cpu, 1, &what);
            // A pixel's colour is a convex combination of its splats' colours (alpha is
            // untouched by SH): it moves by at most the largest splat's move, plus the
            // forward tolerance of the comparison (1e-4 covers a GPU's:
            // `drape_tests::splat::GPU_FORWARD_TOLERANCE`).
            let reference_full = reference::render(&full, &frame);
            let d = drape_tests::splat::max_abs_diff(&image.rgb, &reference_full.rgb);
            assert!(
                d <= colour_bound + 1e-4,
                "{what}: {d} from the full-precision reference, bound {colour_bound}"
            );
            assert!(
                d > 0.0 || degree == 0,
                "{what}: rounding to half changed nothing; the knob is not in effect"
            );
        }
    }
    let cloud = scene(300, 3, 5);
    let cam = camera(61, 45);
    let gaussians = GaussianBuffers::upload(&gpu, "params", &cloud).expect("upload");
    let grads = GaussianBuffers::new(&gpu, "grads", cloud.len(), 3).expect("grads");
    let mut renderer = SplatRenderer::new(&gpu, 61, 45, cloud.len()).expect("renderer");
    let saved = renderer
        .forward(
            &gaussians,
            &cam,
            &RenderSettings {
                half_sh: true,
                ..RenderSettings::default()
            },
        )
        .expect("forward")
        .saved;
    let zeros = gpu
        .upload("zeros", &vec![0.0f32; 3 * 61 * 45])
        .expect("upload");
    let err = renderer
        .backward(
            &saved,
            &gaussians,
            &zeros,
            &zeros,
            &zeros,
            &grads,
            Accumulation::Deterministic,
        )
        .expect_err("a half-precision frame has no backward");
    assert!(
        matches!(err, EngineError::InvalidSetting { .. }) && err.to_string().contains("half"),
        "{err}"
    );
}

/// The half-precision splat knob (`RenderSettings::half_splats`): the GPU render from
/// packed splats equals the CPU reference that packs the same way
/// (`reference::render_half_splats`), on every rasterizer, and stays near the
/// full-precision reference; its backward is refused.
#[test]
fn half_precision_splats_match_cpu() {
    let test = "half_precision_splats_match_cpu";
    let gpu = gpu();
    let mut worst = 0.0f32;
    for (w, h, n) in [(97, 61, 3000), (128, 128, 10_000)] {
        for &variant in &raster_variants(&gpu, test) {
            let cloud = scene(n, 3, 31 + n as u64);
            let cam = camera(w, h);
            let settings = RenderSettings {
                half_splats: true,
                ..RenderSettings::default()
            };
            let (image, _) = gpu_render_with(&gpu, &cloud, &cam, &settings, variant);
            let frame = frame_params(&cam, &settings, 3, cloud.len());
            let gaussians = cloud.gaussians::<f32>();
            let what =
                format!("half-precision splats, {n} Gaussians, {w}x{h}, {variant:?} rasterizer");
            let cpu = reference::render_half_splats(&gaussians, &frame);
            assert_forward_close_to(
                &gpu,
                &image,
                &gaussians,
                &frame,
                &cpu,
                reference::render_half_splats,
                HALF_PACK_GPU_TOLERANCE,
                1,
                &what,
            );
            let full = reference::render(&gaussians, &frame);
            let d = drape_tests::splat::max_abs_diff(&image.rgb, &full.rgb)
                .max(drape_tests::splat::max_abs_diff(&image.alpha, &full.alpha));
            let mse = image
                .rgb
                .iter()
                .zip(&full.rgb)
                .map(|(a, b)| f64::from(a - b).powi(2))
                .sum::<f64>()
                / image.rgb.len() as f64;
            // The render follows the halves, not the f32 splats: of the values where the
            // two references differ, the render is nearer the half-precision one in far
            // more. HALF_PACK_GPU_TOLERANCE alone could not tell on a GPU (it is of the
            // size of the halves' whole effect); a count can, and the few values a
            // rounding or threshold flip moves cannot swing it (a factor of 4 leaves them
            // a fifth of the values).
            let (mut nearer_half, mut nearer_f32) = (0usize, 0usize);
            let values = |r: &[f32], a: &[f32]| r.iter().chain(a).copied().collect::<Vec<f32>>();
            let (g, h, f) = (
                values(&image.rgb, &image.alpha),
                values(&cpu.rgb, &cpu.alpha),
                values(&full.rgb, &full.alpha),
            );
            for ((g, h), f) in g.iter().zip(&h).zip(&f) {
                let (to_half, to_f32) = ((g - h).abs(), (g - f).abs());
                if to_half < to_f32 {
                    nearer_half += 1;
                } else if to_f32 < to_half {
                    nearer_f32 += 1;
                }
            }
            eprintln!("{what}: largest difference from the f32 reference {d:e}, PSNR {:.1} dB; values nearer the half-precision reference {nearer_half}, nearer the f32 one {nearer_f32}", -10.0 * mse.max(1e-20).log10());
            assert!(
                d > 0.0,
                "{what}: packing changed nothing; the knob is not in effect"
            );
            assert!(nearer_half > 4 * nearer_f32, "{what}: {nearer_half} values nearer the half-precision reference, {nearer_f32} nearer the f32 one: the knob looks not in effect");
            worst = worst.max(d);
        }
    }
    assert!(
        worst <= HALF_SPLAT_TOLERANCE,
        "half-precision splats differ from the f32 reference by {worst}"
    );
    let cloud = scene(300, 3, 5);
    let cam = camera(61, 45);
    let gaussians = GaussianBuffers::upload(&gpu, "params", &cloud).expect("upload");
    let grads = GaussianBuffers::new(&gpu, "grads", cloud.len(), 3).expect("grads");
    let mut renderer = SplatRenderer::new(&gpu, 61, 45, cloud.len()).expect("renderer");
    let saved = renderer
        .forward(
            &gaussians,
            &cam,
            &RenderSettings {
                half_splats: true,
                ..RenderSettings::default()
            },
        )
        .expect("forward")
        .saved;
    let zeros = gpu
        .upload("zeros", &vec![0.0f32; 3 * 61 * 45])
        .expect("upload");
    let err = renderer
        .backward(
            &saved,
            &gaussians,
            &zeros,
            &zeros,
            &zeros,
            &grads,
            Accumulation::Deterministic,
        )
        .expect_err("a half-precision frame has no backward");
    assert!(
        matches!(err, EngineError::InvalidSetting { .. }) && err.to_string().contains("half"),
        "{err}"
    );
}

/// How far a GPU's render from half-precision splats may be from the CPU reference's
/// render from half-precision splats. Both pack with the same round-to-nearest-even
/// integer code, but the GPU packs what it projected, with its own exp and fused
/// multiply-adds; where a value lies within those last bits of a half rounding boundary,
/// the two packed halves are one binary16 ulp apart (at most 2^-10 of a normal half's
/// value). For a splat one ulp off in every value: its colour moves the pixel by at most
/// w · 2^-10, its opacity its alpha by α · 2^-10, its conic the exponent σ by σ · 2^-10
/// and so its alpha by α σ 2^-10 ≤ o e^-1 2^-10 (σ e^-σ ≤ 1/e), depth relative 2^-10:
/// about 2.4 · 2^-10 for a pixel whose splats all sat on boundaries (Σ w ≤ 1), which
/// rounding makes rare. An estimate, not a bound (a very elongated conic amplifies its
/// rounding; subnormal halves are coarser), on top of the f32 forward's GPU tolerance;
/// the test also counts that the render is nearer the half-precision reference than the
/// f32 one. An H200 gave 1.09e-4 (a depth, relative). CPU devices project as the host
/// does and are held to 1e-5.
const HALF_PACK_GPU_TOLERANCE: f32 = drape_tests::splat::GPU_FORWARD_TOLERANCE + 2.5 / 1024.0;

/// How far a render from half-precision splats may be from the f32 one, per pixel and
/// channel: the halves' relative rounding (2^-11) moves each splat's alpha by at most
/// about 2^-11 (opacity) + σ · 2^-11 (the conic, σ up to max_sigmas² / 2 ≈ 5.5), ~3e-3
/// relative, and its colour by 2^-11, and a pixel sums its splats' moves through
/// transmittance. Measured here: 3.5e-3 at most (10,000 Gaussians at 128x128); 1e-2
/// leaves room for denser pixels.
const HALF_SPLAT_TOLERANCE: f32 = 1e-2;
