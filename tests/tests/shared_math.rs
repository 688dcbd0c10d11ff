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
