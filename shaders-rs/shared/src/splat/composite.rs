//! Depth-aware compositing of three rendered passes (Cloth-HUGS, Sec. 2.3), per pixel,
//! forward and backward.
//!
//! The passes: `base` (the layers under, e.g. body + scene, over the background), `over`
//! (the composited layer alone, e.g. cloth, over black: premultiplied colour `C` and
//! alpha `A`) and `matte` (the composited layer in colour 1 and its occluders in colour
//! 0, over black: the visibility `V`, read from channel 0). The paper writes
//! `I = I_over · V + I_base · (1 − V)` without saying what `I_over` is over; we take the
//! over pass's un-premultiplied colour `C / A`, which makes the formula exactly the
//! "over" operator `C + (1 − A) I_base` where nothing occludes the layer (`V = A`) and
//! keeps the background out of the layer's soft edges. Occluders only lower `V`, so
//! `V / A` lies in [0, 1]; it is clamped there (float rounding), and `A` is floored at
//! [`COMPOSITE_MIN_ALPHA`] so the ratio and its gradient stay bounded where the layer
//! is absent (there `V ≤ A` is tiny too).

use crate::real::Real;

/// Floor of the over pass's alpha in `V / A`: below it the layer is treated as absent.
pub const COMPOSITE_MIN_ALPHA: f32 = 1e-4;

/// Push constants of `composite::fwd` and `composite::bwd`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct CompositeParams {
    pub pixels: u32,
    /// 1: nothing can hide the layer, so the matte is the over pass's alpha (`V = A`)
    /// and no matte pass was rendered: the kernels read `over_alpha` for `V`, and the
    /// backward adds the matte's gradient into the alpha's (the matte buffer is unused).
    pub matte_is_alpha: u32,
    pub _pad: [u32; 2],
}

/// Push constants of `composite::add_slice`: `dst[i] += src[src_offset + i]` for
/// `i < len` (gathers one layer's gradients out of a pass that rendered several).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct SliceParams {
    pub len: u32,
    pub src_offset: u32,
    pub _pad: [u32; 2],
}

/// Push constants of `composite::to_rgba`: a rendered image (3 floats per pixel,
/// rendered over black, so its colour is premultiplied) and its coverage from one or two
/// alpha sources become premultiplied RGBA (4 floats per pixel, row-major from the top
/// row), the layout an embedder copies into an `R32G32B32A32_SFLOAT` image.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct RgbaParams {
    pub pixels: u32,
    /// Floats per pixel of the first alpha source (its value is the pixel's first float).
    pub a_stride: u32,
    /// 1: the first source holds a final transmittance `T`, so its alpha is `1 − T`.
    pub a_is_transmittance: u32,
    /// Floats per pixel of the second alpha source; 0: there is none.
    pub b_stride: u32,
}

/// The coverage of two layers over each other, alphas `a` and `b`: `1 − (1 − a)(1 − b)`.
/// For the composite `I = (C / A) · V + I_base · (1 − V)` over black it is the alpha that
/// makes `I` premultiplied: the layer covers `V`, the base `A_base` of the rest.
#[inline]
pub fn coverage<F: Real>(a: F, b: F) -> F {
    F::one() - (F::one() - a) * (F::one() - b)
}

/// `V / max(A, floor)` clamped to [0, 1], and whether the clamp left it free (its
/// derivative is zero otherwise).
#[inline]
fn ratio<F: Real>(alpha: F, matte: F) -> (F, F, bool, bool) {
    let floor = F::of(COMPOSITE_MIN_ALPHA);
    let alpha_free = alpha > floor;
    let a = if alpha_free { alpha } else { floor };
    let raw = matte / a;
    if raw <= F::zero() {
        (F::zero(), a, false, alpha_free)
    } else if raw >= F::one() {
        (F::one(), a, false, alpha_free)
    } else {
        (raw, a, true, alpha_free)
    }
}

/// The composited colour of one pixel.
#[inline]
pub fn composite<F: Real>(base: [F; 3], over: [F; 3], over_alpha: F, matte: F) -> [F; 3] {
    let (r, _, _, _) = ratio(over_alpha, matte);
    let keep = F::one() - matte;
    [
        over[0] * r + base[0] * keep,
        over[1] * r + base[1] * keep,
        over[2] * r + base[2] * keep,
    ]
}

/// Gradients of one pixel's composite given the loss gradient `grad` on its colour:
/// (to base, to over, to over_alpha, to matte).
#[inline]
pub fn composite_grad<F: Real>(
    grad: [F; 3],
    base: [F; 3],
    over: [F; 3],
    over_alpha: F,
    matte: F,
) -> ([F; 3], [F; 3], F, F) {
    let (r, a, ratio_free, alpha_free) = ratio(over_alpha, matte);
    let keep = F::one() - matte;
    let g_base = [grad[0] * keep, grad[1] * keep, grad[2] * keep];
    let g_over = [grad[0] * r, grad[1] * r, grad[2] * r];
    // ∂I/∂r = over; ∂r/∂V = 1 / a, ∂r/∂A = -V / a² where the ratio is free.
    let g_r = grad[0] * over[0] + grad[1] * over[1] + grad[2] * over[2];
    let g_base_dot = grad[0] * base[0] + grad[1] * base[1] + grad[2] * base[2];
    let mut g_matte = -g_base_dot;
    let mut g_alpha = F::zero();
    if ratio_free {
        g_matte += g_r / a;
        if alpha_free {
            g_alpha = -g_r * matte / (a * a);
        }
    }
    (g_base, g_over, g_alpha, g_matte)
}
