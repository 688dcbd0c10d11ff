//! The deterministic transcendentals of the shared math against f64 references.

use drape_shared::real::{exp_f32, ln_f32};

/// Relative error bound documented on the functions (a few ulps of f32).
const BOUND: f64 = 2e-7;

#[test]
fn exp_f32_is_accurate_over_its_range() {
    let mut worst = 0.0f64;
    let mut x = -86.9f32;
    while x < 88.5 {
        let got = f64::from(exp_f32(x));
        let want = f64::from(x).exp();
        worst = worst.max(((got - want) / want).abs());
        x += 0.0137;
    }
    assert!(worst <= BOUND, "worst relative error {worst:e}");
    assert_eq!(exp_f32(0.0), 1.0);
    assert_eq!(exp_f32(-1000.0), 0.0);
    assert_eq!(exp_f32(1000.0), f32::INFINITY);
    assert!(exp_f32(f32::NAN).is_nan());
}

#[test]
fn ln_f32_is_accurate_over_its_range() {
    let mut worst = 0.0f64;
    let mut x = 1.2e-38f32;
    while x < 3e38 {
        let got = f64::from(ln_f32(x));
        let want = f64::from(x).ln();
        // Near 1 the result is near 0: measure against max(|ln x|, 1e-3).
        worst = worst.max((got - want).abs() / want.abs().max(1e-3));
        x *= 1.013;
    }
    assert!(worst <= BOUND, "worst relative error {worst:e}");
    assert_eq!(ln_f32(1.0), 0.0);
    assert_eq!(ln_f32(0.0), f32::NEG_INFINITY);
    assert_eq!(ln_f32(f32::INFINITY), f32::INFINITY);
    assert!(ln_f32(-1.0).is_nan() && ln_f32(f32::NAN).is_nan());
}

/// `may_touch_rect` (the subgroup rasterizers' per-block cull) may only drop a splat
/// that `footprint` rejects at every pixel centre of the block: random splats, many of
/// them placed just outside the bounding box of their cut-off ellipse, thin ones up to
/// the cull's condition limit and past it, opacities near `alpha_min`.
#[test]
fn the_block_cull_drops_only_splats_that_miss_every_pixel() {
    use drape_shared::splat::raster::{footprint, may_touch_rect, BlendSettings, SplatView};
    use rand::{Rng, SeedableRng};
    let cfg = BlendSettings {
        alpha_min: 1.0 / 255.0,
        alpha_max: 0.99,
        transmittance_min: 1e-4,
    };
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    let (mut culled, mut kept) = (0u32, 0u32);
    for case in 0..200_000 {
        // A covariance with eigenvalues over six decades (plus the 0.3 dilation), turned.
        let l1 = 0.3 + 10f32.powf(rng.random_range(-2.0..4.0));
        let l2 = 0.3 + 10f32.powf(rng.random_range(-2.0..4.0));
        let th: f32 = rng.random_range(0.0..std::f32::consts::PI);
        let (cs, sn) = (th.cos(), th.sin());
        let (sxx, syy, sxy) = (
            l1 * cs * cs + l2 * sn * sn,
            l1 * sn * sn + l2 * cs * cs,
            (l1 - l2) * cs * sn,
        );
        let det = sxx * syy - sxy * sxy;
        let conic = [syy / det, -sxy / det, sxx / det];
        let opacity: f32 = if case % 4 == 0 {
            cfg.alpha_min * rng.random_range(0.9..1.2)
        } else {
            rng.random_range(0.0..1.0)
        };
        // The block: 8 x 4 pixels somewhere in a 2,000-pixel image.
        let bx = rng.random_range(0..250) as f32 * 8.0;
        let by = rng.random_range(0..500) as f32 * 4.0;
        let (lo, hi) = ([bx + 0.5, by + 0.5], [bx + 7.5, by + 3.5]);
        // Centre: half the cases just outside the exact box along a random axis.
        let t = (opacity / cfg.alpha_min).max(1.0).ln();
        let (hx, hy) = ((2.0 * t * sxx).sqrt(), (2.0 * t * syy).sqrt());
        let (x, y) = if case % 2 == 0 {
            let f = rng.random_range(0.97..1.08);
            if rng.random_bool(0.5) {
                (hi[0] + hx * f, rng.random_range(lo[1]..=hi[1]))
            } else {
                (rng.random_range(lo[0]..=hi[0]), lo[1] - hy * f)
            }
        } else {
            (
                bx + rng.random_range(-200.0f32..200.0),
                by + rng.random_range(-200.0f32..200.0),
            )
        };
        let s = SplatView {
            x,
            y,
            depth: 1.0,
            conic,
            opacity,
            color: [1.0; 3],
        };
        if may_touch_rect(&s, lo, hi, &cfg) {
            kept += 1;
            continue;
        }
        culled += 1;
        for py in 0..4 {
            for px in 0..8 {
                let (cx, cy) = (lo[0] + px as f32, lo[1] + py as f32);
                assert!(
                    footprint(&s, cx, cy, &cfg).is_none(),
                    "case {case}: culled {s:?} blends at ({cx}, {cy}) of the block at ({bx}, {by})"
                );
            }
        }
    }
    // The cull has to cull (the near misses alone are a quarter of the cases).
    assert!(
        culled > 50_000 && kept > 50_000,
        "culled {culled}, kept {kept}"
    );
    println!("culled {culled}, kept {kept}");
}
