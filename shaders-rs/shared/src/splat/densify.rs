//! Screen-space statistics for densification (3DGS's `add_densification_stats`): per
//! Gaussian, the sum over the frames it was visible in of the norm of its projected
//! centre's gradient, the number of those frames, and the largest screen radius it had.
//! The trainer divides the sum by the count and compares it with the threshold (HUGS
//! and 3DGS: 2e-4), and prunes by the radius (HUGS: 20 px).
//!
//! Units follow 3DGS so its thresholds carry over: its gradient is taken with respect
//! to the centre in normalised device coordinates, `pixel = ((ndc + 1) W − 1) / 2`, so
//! `∂L/∂ndc_x = ∂L/∂x · W / 2` (and `H / 2` for y). Its radius is
//! `ceil(3 √λ_max)` of the (dilated) 2D covariance, here recovered from the conic.
//! A non-finite gradient adds nothing (the training step that made it is skipped).

use crate::real::{Float, Real};
use crate::splat::layout::ProjectedSplat;

/// Floats of statistics per Gaussian: gradient-norm sum, visible frames, largest radius.
pub const SCREEN_STATS_FLOATS: usize = 3;

/// Push constants of `splat::screen_stats`: Gaussians `[first, first + count)` of a
/// render add into statistics `[out_first, out_first + count)` of a layer's buffer.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct ScreenStatsParams {
    pub first: u32,
    pub count: u32,
    pub out_first: u32,
    pub width: u32,
    pub height: u32,
    pub _pad: [u32; 3],
}

/// 3DGS's screen radius of a splat from its conic (the inverse of the dilated 2D
/// covariance): `ceil(3 √λ_max)` pixels.
pub fn screen_radius<F: Real>(conic: [F; 3]) -> F {
    let [a, b, c] = conic;
    let det = a * c - b * b;
    // The covariance is the conic's inverse: [[c, -b], [-b, a]] / det.
    let (s00, s01, s11) = (c / det, -b / det, a / det);
    let mid = F::of(0.5) * (s00 + s11);
    let d = s00 * s11 - s01 * s01;
    let lambda = mid + (mid * mid - d).max(F::of(0.1)).sqrt();
    (F::of(3.0) * lambda.sqrt()).ceil()
}

/// One frame's contribution to a Gaussian's statistics `stats` (gradient-norm sum,
/// visible frames, largest radius), from its splat and the splat's gradient on the
/// pixel centre `(gx, gy)`.
pub fn accumulate(
    stats: [f32; 3],
    splat: &ProjectedSplat,
    gx: f32,
    gy: f32,
    width: u32,
    height: u32,
) -> [f32; 3] {
    if splat.tiles == 0 {
        return stats;
    }
    let nx = gx * 0.5 * width as f32;
    let ny = gy * 0.5 * height as f32;
    let norm = Float::sqrt(nx * nx + ny * ny);
    if !Float::is_finite(norm) {
        return stats;
    }
    let radius = screen_radius([splat.conic_a, splat.conic_b, splat.conic_c]);
    [stats[0] + norm, stats[1] + 1.0, stats[2].max(radius)]
}
