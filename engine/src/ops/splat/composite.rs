//! Depth-aware compositing of three rendered passes (Cloth-HUGS, Sec. 2.3): a base pass,
//! an over pass (the composited layer alone, over black) and a matte pass (that layer
//! in colour 1 and its occluders in colour 0, over black) give
//! `I = (C / A) · V + I_base · (1 − V)` per pixel; see
//! `drape_shared::splat::composite` for the math and why `C / A`.
//!
//! The engine speaks of passes; which clouds go into which pass is the caller's choice
//! (the trainer's `avatar::composite` renders body + scene, cloth, and cloth + scene).
//! Both kernels are per pixel and record into the caller's recording; the CPU
//! reference runs the same shared functions.

use drape_shared::splat::composite::{composite, composite_grad, CompositeParams, SliceParams};

use drape_shared::splat::layout::MAX_SH_COEFFS;
use drape_shared::splat::sh::C0;

use crate::buffer::Buffer;
use crate::error::Result;
use crate::kernels;
use crate::ops::splat::scene::GaussianCloud;
use crate::recorder::{flat_grid, Recording};

/// The inputs of one composite: each pass's rgb (3 floats per pixel), the over pass's
/// alpha, and the matte pass's rgb (channel 0 is the visibility `V`); no matte where
/// nothing can hide the layer (then `V` is the over pass's alpha, and the matte pass
/// need not be rendered).
#[derive(Clone, Copy)]
pub struct CompositeInputs<'a> {
    /// The base pass's rgb.
    pub base_rgb: &'a Buffer,
    /// The over pass's rgb.
    pub over_rgb: &'a Buffer,
    /// The over pass's alpha.
    pub over_alpha: &'a Buffer,
    /// The matte pass's rgb, if rendered.
    pub matte_rgb: Option<&'a Buffer>,
}

/// Where the composite's backward writes: gradients to the three passes' outputs
/// (`matte_rgb` gets the visibility's gradient in channel 0 and zeros in 1 and 2;
/// without a matte, that gradient joins `over_alpha`'s).
#[derive(Clone, Copy)]
pub struct CompositeGrads<'a> {
    /// Gradient on the base pass's rgb.
    pub base_rgb: &'a Buffer,
    /// Gradient on the over pass's rgb.
    pub over_rgb: &'a Buffer,
    /// Gradient on the over pass's alpha.
    pub over_alpha: &'a Buffer,
    /// Gradient on the matte pass's rgb, with a matte.
    pub matte_rgb: Option<&'a Buffer>,
}

fn params(pixels: u32, matte: Option<&Buffer>) -> CompositeParams {
    CompositeParams {
        pixels,
        matte_is_alpha: u32::from(matte.is_none()),
        _pad: [0; 2],
    }
}

/// Records the composite of `pixels` pixels into `out` (3 floats per pixel).
pub fn record_composite<'a>(
    rec: &mut Recording<'a>,
    inputs: CompositeInputs<'a>,
    out: &'a Buffer,
    pixels: u32,
) -> Result<()> {
    let p = params(pixels, inputs.matte_rgb);
    // Without a matte the kernel reads V from the alpha; the binding still needs a buffer.
    rec.dispatch(
        "composite.fwd",
        kernels::composite::Fwd {
            base: inputs.base_rgb.read(),
            over: inputs.over_rgb.read(),
            over_alpha: inputs.over_alpha.read(),
            matte: inputs.matte_rgb.unwrap_or(inputs.over_alpha).read(),
            out: out.write(),
        },
        &p,
        flat_grid(pixels),
    )
}

/// Records the composite's backward from `grad` (the loss's gradient on the
/// composited rgb); every output of `grads` is written, none accumulated.
pub fn record_composite_backward<'a>(
    rec: &mut Recording<'a>,
    grad: &'a Buffer,
    inputs: CompositeInputs<'a>,
    grads: CompositeGrads<'a>,
    pixels: u32,
) -> Result<()> {
    assert_eq!(
        inputs.matte_rgb.is_some(),
        grads.matte_rgb.is_some(),
        "a matte's gradient goes with a matte"
    );
    let p = params(pixels, inputs.matte_rgb);
    // Without a matte neither matte binding is touched; they still need buffers.
    rec.dispatch(
        "composite.bwd",
        kernels::composite::Bwd {
            grad: grad.read(),
            base: inputs.base_rgb.read(),
            over: inputs.over_rgb.read(),
            over_alpha: inputs.over_alpha.read(),
            matte: inputs.matte_rgb.unwrap_or(inputs.over_alpha).read(),
            grad_base: grads.base_rgb.write(),
            grad_over: grads.over_rgb.write(),
            grad_over_alpha: grads.over_alpha.write(),
            grad_matte: grads.matte_rgb.unwrap_or(grads.over_rgb).write(),
        },
        &p,
        flat_grid(pixels),
    )
}

/// Records `dst[i] += src[src_offset + i]` for `i < len` (floats): one cloud's slice of
/// a pass's per-Gaussian gradients added into that cloud's own.
pub fn record_add_slice<'a>(
    rec: &mut Recording<'a>,
    src: &'a Buffer,
    src_offset: u32,
    dst: &'a Buffer,
    len: u32,
) -> Result<()> {
    if len == 0 {
        return Ok(());
    }
    let p = SliceParams {
        len,
        src_offset,
        _pad: [0; 2],
    };
    rec.dispatch(
        "composite.add_slice",
        kernels::composite::AddSlice {
            src: src.read(),
            dst: dst.write(),
        },
        &p,
        flat_grid(len),
    )
}

/// The degree-0 SH coefficient (all three channels) of a Gaussian in the matte pass:
/// colour `0.5 + C0 · dc` is 1 for the composited layer and -0.5, clamped to 0 by the
/// splatter, for an occluder.
pub fn matte_sh_dc(composited: bool) -> f32 {
    if composited {
        0.5 / C0
    } else {
        -1.0 / C0
    }
}

/// The matte pass's cloud built on the host: each part's Gaussians at SH degree 0 in its
/// binary colour (`true`: the composited layer).
pub fn matte_cloud(parts: &[(&GaussianCloud, bool)]) -> GaussianCloud {
    let mut out = GaussianCloud::new(0);
    for (cloud, composited) in parts {
        for i in 0..cloud.len() {
            let mut g = cloud.gaussian::<f32>(i);
            g.sh = [[0.0; 3]; MAX_SH_COEFFS];
            g.sh[0] = [matte_sh_dc(*composited); 3];
            out.push(&g, cloud.groups[i]);
        }
    }
    out
}

fn rgb(b: &[f32], i: usize) -> [f32; 3] {
    [b[3 * i], b[3 * i + 1], b[3 * i + 2]]
}

fn visibility(over_alpha: &[f32], matte_rgb: Option<&[f32]>, i: usize) -> f32 {
    matte_rgb.map_or(over_alpha[i], |m| m[3 * i])
}

/// CPU references of the composite kernels, on the same shared functions.
pub mod reference {
    use super::*;

    /// CPU reference of [`record_composite`] (host slices in the same layout).
    pub fn forward(
        base_rgb: &[f32],
        over_rgb: &[f32],
        over_alpha: &[f32],
        matte_rgb: Option<&[f32]>,
    ) -> Vec<f32> {
        (0..over_alpha.len())
            .flat_map(|i| {
                composite(
                    rgb(base_rgb, i),
                    rgb(over_rgb, i),
                    over_alpha[i],
                    visibility(over_alpha, matte_rgb, i),
                )
            })
            .collect()
    }

    /// CPU reference of [`record_composite_backward`]: (base rgb, over rgb, over alpha,
    /// matte rgb) gradients (the last empty without a matte).
    pub fn backward(
        grad: &[f32],
        base_rgb: &[f32],
        over_rgb: &[f32],
        over_alpha: &[f32],
        matte_rgb: Option<&[f32]>,
    ) -> [Vec<f32>; 4] {
        let n = over_alpha.len();
        let mut out = [
            vec![0.0; 3 * n],
            vec![0.0; 3 * n],
            vec![0.0; n],
            vec![0.0; if matte_rgb.is_some() { 3 * n } else { 0 }],
        ];
        for i in 0..n {
            let (gb, go, ga, gm) = composite_grad(
                rgb(grad, i),
                rgb(base_rgb, i),
                rgb(over_rgb, i),
                over_alpha[i],
                visibility(over_alpha, matte_rgb, i),
            );
            out[0][3 * i..3 * i + 3].copy_from_slice(&gb);
            out[1][3 * i..3 * i + 3].copy_from_slice(&go);
            if matte_rgb.is_some() {
                out[2][i] = ga;
                out[3][3 * i] = gm;
            } else {
                out[2][i] = ga + gm;
            }
        }
        out
    }

    /// CPU reference of [`record_to_rgba`] (same shared function).
    pub fn to_rgba(
        rgb: &[f32],
        a: &[f32],
        a_stride: usize,
        a_is_transmittance: bool,
        b: Option<(&[f32], usize)>,
    ) -> Vec<f32> {
        let pixels = rgb.len() / 3;
        let mut out = Vec::with_capacity(4 * pixels);
        for i in 0..pixels {
            let a = if a_is_transmittance {
                1.0 - a[a_stride * i]
            } else {
                a[a_stride * i]
            };
            let b = b.map_or(0.0, |(b, s)| b[s * i]);
            out.extend_from_slice(&rgb[3 * i..3 * i + 3]);
            out.push(drape_shared::splat::composite::coverage(a, b));
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use drape_shared::splat::composite::{composite, composite_grad, COMPOSITE_MIN_ALPHA};

    /// The composite's gradient against central differences in f64 at random pixels,
    /// away from the clamps (where the derivative jumps).
    #[test]
    fn gradient_matches_central_differences() {
        let mut seed = 7u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            ((seed >> 11) as f64) / ((1u64 << 53) as f64)
        };
        for _ in 0..200 {
            let base = [next(), next(), next()];
            let a = 0.05 + 0.9 * next();
            let over = [a * next(), a * next(), a * next()];
            let v = a * (0.05 + 0.9 * next());
            let g = [next() - 0.5, next() - 0.5, next() - 0.5];
            let loss = |b: [f64; 3], o: [f64; 3], a: f64, v: f64| {
                let c = composite(b, o, a, v);
                g[0] * c[0] + g[1] * c[1] + g[2] * c[2]
            };
            let (gb, go, ga, gv) = composite_grad(g, base, over, a, v);
            let h = 1e-6;
            // Central differences are exact to O(h²) on this smooth piece; 1e-7 absolute
            // leaves room for the f64 rounding of h-sized differences.
            for k in 0..3 {
                let (mut bp, mut bm) = (base, base);
                bp[k] += h;
                bm[k] -= h;
                assert!(
                    ((loss(bp, over, a, v) - loss(bm, over, a, v)) / (2.0 * h) - gb[k]).abs()
                        < 1e-7
                );
                let (mut op, mut om) = (over, over);
                op[k] += h;
                om[k] -= h;
                assert!(
                    ((loss(base, op, a, v) - loss(base, om, a, v)) / (2.0 * h) - go[k]).abs()
                        < 1e-7
                );
            }
            assert!(
                ((loss(base, over, a + h, v) - loss(base, over, a - h, v)) / (2.0 * h) - ga).abs()
                    < 1e-6,
                "alpha"
            );
            assert!(
                ((loss(base, over, a, v + h) - loss(base, over, a, v - h)) / (2.0 * h) - gv).abs()
                    < 1e-6,
                "matte"
            );
        }
        // Where nothing occludes the layer (V = A) the composite is the "over" operator.
        let c = composite([0.2f64, 0.4, 0.6], [0.3, 0.1, 0.05], 0.5, 0.5);
        for k in 0..3 {
            let over = [0.3, 0.1, 0.05][k] + 0.5 * [0.2, 0.4, 0.6][k];
            assert!((c[k] - over).abs() < 1e-12, "{c:?}");
        }
        // An absent layer leaves the base untouched, with bounded gradients.
        let (_, go, ga, _) = composite_grad([1.0f64; 3], [0.5; 3], [0.0; 3], 0.0, 0.0);
        assert_eq!(composite([0.5f64; 3], [0.0; 3], 0.0, 0.0), [0.5; 3]);
        assert!(go == [0.0; 3] && ga == 0.0 && COMPOSITE_MIN_ALPHA > 0.0);
    }
}

/// Where a frame's coverage comes from, for [`record_to_rgba`].
#[derive(Clone, Copy)]
pub enum Coverage<'a> {
    /// One alpha per pixel (a single render's).
    Alpha(&'a Buffer),
    /// A base alpha and a layer's visibility over it: each (buffer, floats per pixel,
    /// whether it holds the final transmittance `T` rather than the alpha `1 − T`).
    Two {
        /// The base: (buffer, floats per pixel, whether it holds `T`).
        base: (&'a Buffer, u32, bool),
        /// The layer's visibility: (buffer, floats per pixel).
        layer: (&'a Buffer, u32),
    },
}

/// Records `rgb` (3 floats per pixel, rendered over black) and its coverage as
/// premultiplied RGBA into `out` (4 floats per pixel, row-major from the top row: what
/// an `R32G32B32A32_SFLOAT` image takes by `Recording::copy_to_image`). The coverage of
/// a composite is `1 − (1 − A_base)(1 − V)` (`drape_shared::splat::composite::coverage`).
pub fn record_to_rgba<'a>(
    rec: &mut Recording<'a>,
    rgb: &'a Buffer,
    coverage: Coverage<'a>,
    out: &'a Buffer,
    pixels: u32,
) -> Result<()> {
    use drape_shared::splat::composite::RgbaParams;
    let (a, b, p) = match coverage {
        Coverage::Alpha(alpha) => (
            alpha,
            alpha,
            RgbaParams {
                pixels,
                a_stride: 1,
                a_is_transmittance: 0,
                b_stride: 0,
            },
        ),
        Coverage::Two {
            base: (a, a_stride, t),
            layer: (b, b_stride),
        } => (
            a,
            b,
            RgbaParams {
                pixels,
                a_stride,
                a_is_transmittance: u32::from(t),
                b_stride,
            },
        ),
    };
    rec.dispatch(
        "composite.to_rgba",
        kernels::composite::ToRgba {
            rgb_in: rgb.read(),
            alpha_a: a.read(),
            alpha_b: b.read(),
            rgba: out.write(),
        },
        &p,
        flat_grid(pixels),
    )
}
