//! SSIM as 3DGS computes it, and its gradient, for images of `height × width × 3`
//! (interleaved RGB, each channel on its own): an 11 × 11 Gaussian window (σ = 1.5,
//! normalised), "same" convolution with zero padding, C1 = 0.01², C2 = 0.03², the
//! mean of the map over every pixel and channel.
//!
//! Forward: five moment images `x, y, x², y², xy` blurred (two separable passes) into
//! `μx, μy, E[x²], E[y²], E[xy]`, then per pixel
//! `S = (2 μx μy + C1)(2 σxy + C2) / ((μx² + μy² + C1)(σx² + σy² + C2))` with
//! `σx² = E[x²] - μx²`, `σxy = E[xy] - μx μy`.
//! Backward (to `x` only): with `P_m, P_xx, P_xy` the partial derivatives of `S` with
//! respect to `μx, E[x²], E[xy]`, `∂ mean(S) / ∂x = (blur(P_m) + 2 x blur(P_xx) +
//! y blur(P_xy)) / N`: the window is symmetric, so the adjoint of the zero-padded
//! blur is the same blur.

use crate::real::Real;

/// Window side.
pub const SSIM_WINDOW: usize = 11;
/// Window standard deviation (pixels).
pub const SSIM_SIGMA: f32 = 1.5;
pub const SSIM_C1: f32 = 0.01 * 0.01;
pub const SSIM_C2: f32 = 0.03 * 0.03;
/// Moment images of the forward pass.
pub const SSIM_MOMENTS: u32 = 5;
/// Derivative images of the backward pass.
pub const SSIM_PARTIALS: u32 = 3;

/// Outputs of one invocation of the `ssim::blur` kernel: a run of consecutive pixels
/// along the blur's axis, one channel of one plane. Its 11-tap window over the run is
/// 26 loads (`SSIM_BLUR_RUN + SSIM_WINDOW - 1`) for 16 outputs, where one output an
/// invocation takes 11; on llvmpipe each load whose address is not uniform is a loop
/// over the lanes, so this is a quarter of the loops.
pub const SSIM_BLUR_RUN: u32 = 16;

/// Invocations of one `ssim::blur` pass over `planes` images of `width × height × 3`:
/// one per run of [`SSIM_BLUR_RUN`] pixels along the axis, per line across it, per
/// channel and plane.
///
/// ```
/// use drape_shared::ssim::blur_invocations;
/// assert_eq!(blur_invocations(64, 48, 5, false), 5 * 48 * 3 * 4);
/// assert_eq!(blur_invocations(61, 45, 1, true), 61 * 3 * 3);
/// ```
pub const fn blur_invocations(width: u32, height: u32, planes: u32, vertical: bool) -> u32 {
    let (along, across) = if vertical {
        (height, width)
    } else {
        (width, height)
    };
    planes * across * 3 * along.div_ceil(SSIM_BLUR_RUN)
}

/// Push constants of the `ssim::*` kernels.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct SsimParams {
    pub width: u32,
    pub height: u32,
    /// Images in the buffer being blurred (5 moments or 3 partials).
    pub planes: u32,
    /// Blur direction: 0 horizontal, 1 vertical.
    pub vertical: u32,
    /// Multiplies the gradient (e.g. `-λ / N` for a loss `λ (1 - SSIM)`).
    pub scale: f32,
    pub _pad: [u32; 3],
    /// The window's taps ([`window_taps`]), so every invocation uses the same bits.
    pub taps: [f32; SSIM_WINDOW],
    pub _pad2: u32,
}

/// The normalised 1-D Gaussian window (the 2-D window is its outer product).
#[inline]
pub fn window_taps<F: Real>() -> [F; SSIM_WINDOW] {
    let half = (SSIM_WINDOW / 2) as f32;
    let denom = 2.0 * SSIM_SIGMA * SSIM_SIGMA;
    let mut taps = [F::zero(); SSIM_WINDOW];
    let mut sum = F::zero();
    let mut k = 0;
    while k < SSIM_WINDOW {
        let d = k as f32 - half;
        taps[k] = F::of(-d * d / denom).exp_k();
        sum += taps[k];
        k += 1;
    }
    k = 0;
    while k < SSIM_WINDOW {
        taps[k] /= sum;
        k += 1;
    }
    taps
}

/// The SSIM of one pixel-channel from its moments, and the partial derivatives with
/// respect to `μx`, `E[x²]` and `E[xy]`: (S, P_m, P_xx, P_xy).
#[inline]
pub fn ssim_pointwise<F: Real>(mx: F, my: F, exx: F, eyy: F, exy: F) -> (F, F, F, F) {
    let c1 = F::of(SSIM_C1);
    let c2 = F::of(SSIM_C2);
    let two = F::of(2.0);
    let sxx = exx - mx * mx;
    let syy = eyy - my * my;
    let sxy = exy - mx * my;
    let a1 = two * mx * my + c1;
    let a2 = two * sxy + c2;
    let b1 = mx * mx + my * my + c1;
    let b2 = sxx + syy + c2;
    let s = a1 * a2 / (b1 * b2);
    let p_m = s * (two * my / a1 - two * my / a2 - two * mx / b1 + two * mx / b2);
    let p_xx = -s / b2;
    let p_xy = s * two / a2;
    (s, p_m, p_xx, p_xy)
}
