//! Finite-difference checks, in f64, of the CPU reference's backward pass (the same
//! shared functions the GPU kernels run) for every parameter group.
//!
//! The function is made differentiable for the check: `alpha_min` = 0 (the test-only
//! smooth cutoff: no threshold at all), opacities below the 0.99 clamp, few enough
//! splats that transmittance never reaches its floor, and an extent of 8 standard
//! deviations so what lies outside a splat's tile rectangle weighs under e^-32.
//! Tolerance: central differences with h = 1e-6 in f64 have truncation error
//! ~h² and rounding error ~1e-16/h, far below the 1e-5 relative bound used.

use drape_engine::ops::splat::reference::{backward, render};
use drape_engine::ops::splat::scene::{frame_params, GaussianCloud, PinholeCamera, RenderSettings};
use drape_shared::splat::layout::{sh_coeffs, FrameParams};
use drape_shared::splat::project::{Gaussian, GaussianGrad};
use rand::{Rng, SeedableRng};

const H: f64 = 1e-6;
const TOLERANCE: f64 = 1e-5;

struct Case {
    gaussians: Vec<Gaussian<f64>>,
    frame: FrameParams,
    w_rgb: Vec<f64>,
    w_alpha: Vec<f64>,
    w_depth: Vec<f64>,
}

fn case(sh_degree: u32, antialiased: bool, seed: u64) -> Case {
    let cam = PinholeCamera::look_at(
        [0.4, -0.3, -4.0],
        [0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
        40.0,
        40,
        24,
    )
    .expect("camera");
    let mut cam = cam;
    cam.background = [0.2, 0.4, 0.6];
    let settings = RenderSettings {
        antialiased,
        alpha_min: 0.0,
        max_sigmas: 8.0,
        ..RenderSettings::default()
    };
    let mut cloud = GaussianCloud::random(6, sh_degree, 0.9, (-0.5, 0.5), 0.25, seed);
    for l in &mut cloud.opacity_logits {
        *l = l.clamp(-1.5, 1.5);
    }
    let frame = frame_params(&cam, &settings, sh_degree, cloud.len());
    let pixels = (cam.width * cam.height) as usize;
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed + 100);
    Case {
        gaussians: cloud.gaussians::<f64>(),
        frame,
        w_rgb: (0..3 * pixels)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect(),
        w_alpha: (0..pixels).map(|_| rng.random_range(-1.0..1.0)).collect(),
        w_depth: (0..pixels).map(|_| rng.random_range(-0.2..0.2)).collect(),
    }
}

fn loss(c: &Case, gaussians: &[Gaussian<f64>]) -> f64 {
    let r = render(gaussians, &c.frame);
    let mut l = 0.0;
    for (v, w) in r.rgb.iter().zip(&c.w_rgb) {
        l += v * w;
    }
    for (v, w) in r.alpha.iter().zip(&c.w_alpha) {
        l += v * w;
    }
    for (v, w) in r.depth.iter().zip(&c.w_depth) {
        l += v * w;
    }
    l
}

/// One parameter: its group, where it sits in a Gaussian, and its gradient.
type Parameter = (
    &'static str,
    Box<dyn Fn(&mut Gaussian<f64>) -> &mut f64>,
    Box<dyn Fn(&GaussianGrad<f64>) -> f64>,
);

/// Every parameter as (group, accessor) so one loop perturbs them all.
fn parameters(k_count: usize) -> Vec<Parameter> {
    let mut out: Vec<Parameter> = Vec::new();
    for a in 0..3 {
        out.push((
            "means",
            Box::new(move |g| &mut g.mean[a]),
            Box::new(move |d| d.mean[a]),
        ));
        out.push((
            "log_scales",
            Box::new(move |g| &mut g.log_scale[a]),
            Box::new(move |d| d.log_scale[a]),
        ));
    }
    for a in 0..4 {
        out.push((
            "quats",
            Box::new(move |g| &mut g.quat[a]),
            Box::new(move |d| d.quat[a]),
        ));
    }
    out.push((
        "opacity_logits",
        Box::new(|g| &mut g.opacity_logit),
        Box::new(|d| d.opacity_logit),
    ));
    for k in 0..k_count {
        for ch in 0..3 {
            out.push((
                "sh",
                Box::new(move |g| &mut g.sh[k][ch]),
                Box::new(move |d| d.sh[k][ch]),
            ));
        }
    }
    out
}

fn check(sh_degree: u32, antialiased: bool, seed: u64) {
    let c = case(sh_degree, antialiased, seed);
    let fwd = render(&c.gaussians, &c.frame);
    assert!(
        fwd.projections.iter().filter(|p| p.visible).count() >= 4,
        "the scene must show most splats"
    );
    let (grads, _) = backward(
        &c.gaussians,
        &c.frame,
        &fwd,
        &c.w_rgb,
        &c.w_alpha,
        &c.w_depth,
    );
    let mut worst: std::collections::BTreeMap<&str, (f64, f64)> = Default::default();
    for (i, _) in c.gaussians.iter().enumerate() {
        for (group, param, analytic) in parameters(sh_coeffs(sh_degree)) {
            let mut plus = c.gaussians.clone();
            *param(&mut plus[i]) += H;
            let mut minus = c.gaussians.clone();
            *param(&mut minus[i]) -= H;
            let numeric = (loss(&c, &plus) - loss(&c, &minus)) / (2.0 * H);
            let a = analytic(&grads[i]);
            let e = worst.entry(group).or_insert((0.0, 0.0));
            e.0 = e.0.max((a - numeric).abs());
            e.1 = e.1.max(numeric.abs());
        }
    }
    for (group, (err, scale)) in worst {
        assert!(
            scale > 0.0,
            "{group}: all gradients are zero; the check would be vacuous"
        );
        let rel = err / scale;
        assert!(rel <= TOLERANCE, "{group}: max |analytic - numeric| = {err:e}, relative {rel:e} (degree {sh_degree}, antialiased {antialiased})");
    }
}

#[test]
fn finite_differences_sh_degree_0() {
    check(0, false, 1);
}

#[test]
fn finite_differences_sh_degree_3() {
    check(3, false, 2);
}

#[test]
fn finite_differences_antialiased_sh_degree_1() {
    check(1, true, 3);
}

#[test]
fn finite_differences_antialiased_sh_degree_3() {
    check(3, true, 4);
}
