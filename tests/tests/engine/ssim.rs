//! SSIM on the GPU against the CPU reference (f64), the reference's gradient against
//! central differences, and the degenerate images (1 × 1, constant, identical).

use drape_engine::ops::ssim::{reference, Ssim};
use drape_engine::{BufferDesc, Context};
use drape_tests::gpu;
use drape_tests::num::rel_err;
use rand::{Rng, SeedableRng};

fn image(w: usize, h: usize, seed: u64) -> Vec<f64> {
    // Smooth structure plus noise, in [0, 1].
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    (0..w * h * 3)
        .map(|i| {
            let (p, c) = (i / 3, i % 3);
            let (x, y) = ((p % w) as f64, (p / w) as f64);
            (0.5 + 0.3 * ((x * 0.3 + c as f64).sin() * (y * 0.2).cos())
                + rng.random_range(-0.15..0.15))
            .clamp(0.0, 1.0)
        })
        .collect()
}

fn gpu_ssim(
    ctx: &Context,
    pred: &[f64],
    target: &[f64],
    w: u32,
    h: u32,
    scale: f32,
) -> (f64, Vec<f64>) {
    let f = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
    let p = ctx.upload("pred", &f(pred)).expect("upload");
    let t = ctx.upload("target", &f(target)).expect("upload");
    let mut g = ctx
        .create_buffer("grad", BufferDesc::gpu_only((pred.len() * 4) as u64))
        .expect("buffer");
    let mut s = Ssim::new(ctx, w, h).expect("ssim");
    {
        let mut rec = ctx.record("ssim test").expect("record");
        rec.fill(&g, 0);
        s.record(&mut rec, &p, &t, Some((&g, scale)))
            .expect("record");
        rec.submit_and_wait().expect("submit");
    }
    let grad = ctx
        .read_buffer::<f32>(&mut g, pred.len())
        .expect("read")
        .iter()
        .map(|&v| f64::from(v))
        .collect();
    (s.read_mean(ctx).expect("mean"), grad)
}

#[test]
fn ssim_gpu_matches_cpu_reference() {
    let ctx = gpu();
    for (w, h) in [(1usize, 1usize), (7, 5), (64, 64), (97, 61)] {
        let pred = image(w, h, 1);
        let target = image(w, h, 2);
        let (_, mean, grad) = reference(&pred, &target, w, h);
        let (gmean, ggrad) = gpu_ssim(&ctx, &pred, &target, w as u32, h as u32, 1.0);
        // f32 moments of values in [0, 1] through 121 taps: ~1e-6 absolute on SSIM.
        assert!(
            (gmean - mean).abs() < 1e-5,
            "{w}x{h}: mean SSIM {gmean} vs {mean}"
        );
        // The variance terms subtract nearly equal f32 moments: 1e-3 of the largest
        // gradient (measured ~1e-5).
        let e = rel_err(&ggrad, &grad, 1e-12);
        assert!(e < 1e-3, "{w}x{h}: gradient relative error {e:e}");
    }
}

#[test]
fn ssim_gradient_matches_central_differences() {
    let (w, h) = (9, 7);
    let pred = image(w, h, 3);
    let target = image(w, h, 4);
    let (_, _, grad) = reference(&pred, &target, w, h);
    let step = 1e-6;
    let numeric: Vec<f64> = (0..pred.len())
        .map(|i| {
            let (mut a, mut b) = (pred.clone(), pred.clone());
            a[i] += step;
            b[i] -= step;
            (reference(&a, &target, w, h).1 - reference(&b, &target, w, h).1) / (2.0 * step)
        })
        .collect();
    // Smooth in the prediction; f64 central differences agree to ~1e-9.
    let e = rel_err(&grad, &numeric, 1e-12);
    assert!(e < 1e-6, "relative error {e:e} against central differences");
}

#[test]
fn ssim_of_degenerate_images() {
    let ctx = gpu();
    // Identical images: SSIM 1 everywhere, zero gradient.
    let a = image(16, 12, 5);
    let (mean, grad) = gpu_ssim(&ctx, &a, &a, 16, 12, 1.0);
    assert!(
        (mean - 1.0).abs() < 1e-5,
        "SSIM of an image with itself: {mean}"
    );
    assert!(
        grad.iter().all(|g| g.abs() < 1e-4),
        "gradient at the optimum"
    );
    // Constant images: the variances vanish and C2 keeps the map finite.
    let c1 = vec![0.25; 8 * 8 * 3];
    let c2 = vec![0.75; 8 * 8 * 3];
    let (mean, grad) = gpu_ssim(&ctx, &c1, &c2, 8, 8, 1.0);
    let (_, rmean, _) = reference(&c1, &c2, 8, 8);
    assert!(
        mean.is_finite() && grad.iter().all(|g| g.is_finite()),
        "constant images: SSIM {mean}"
    );
    assert!(
        (mean - rmean).abs() < 1e-5,
        "constant images: {mean} vs {rmean}"
    );
    // 1 × 1: the window is one tap inside the image.
    let (mean, grad) = gpu_ssim(&ctx, &[0.2, 0.4, 0.6], &[0.3, 0.4, 0.5], 1, 1, 1.0);
    assert!(
        mean.is_finite() && grad.iter().all(|g| g.is_finite()),
        "1x1: SSIM {mean}"
    );
}
