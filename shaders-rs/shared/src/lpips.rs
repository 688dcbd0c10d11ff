//! LPIPS v0.1 (Zhang et al. 2018, the `lpips` package): a frozen feature stack
//! (AlexNet or VGG16 convolutions with ReLU and max-pooling), each tapped layer's
//! features normalised to unit length over channels at every pixel, the squared
//! difference of the two images' normalised features weighted per channel by the
//! learned 1 × 1 "lin" layer, averaged over the pixels, summed over the layers.
//!
//! Tensors are channel-major (`C × H × W`), one image at a time. Inputs in [0, 1] are
//! mapped as the package does with `normalize=True`: `x' = 2x - 1`, then the scaling
//! layer `(x' - shift) / scale`. Only the gradient to the first image is computed
//! (LPIPS as a loss; the network is frozen).

use crate::real::Real;

/// The package's scaling layer (ImageNet statistics in [-1, 1] units).
pub const LPIPS_SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
pub const LPIPS_SCALE: [f32; 3] = [0.458, 0.448, 0.450];
/// The package's `normalize_tensor` epsilon.
pub const LPIPS_EPS: f32 = 1e-10;

/// Push constants of `lpips::conv_fwd` / `lpips::conv_bwd_input`: a 2-D convolution
/// (square kernel, same stride and zero padding in both axes), optionally followed by
/// ReLU.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct ConvParams {
    pub in_c: u32,
    pub in_h: u32,
    pub in_w: u32,
    pub out_c: u32,
    pub out_h: u32,
    pub out_w: u32,
    pub kernel: u32,
    pub stride: u32,
    pub pad: u32,
    /// 1: ReLU after the convolution.
    pub relu: u32,
    pub _pad: [u32; 2],
}

/// Push constants of `lpips::pool_*` (max-pooling, no padding, floor mode) and of the
/// layer-distance kernels (`c, h, w` of the features; `scale` multiplies the
/// gradient).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct PoolParams {
    pub c: u32,
    pub in_h: u32,
    pub in_w: u32,
    pub out_h: u32,
    pub out_w: u32,
    pub kernel: u32,
    pub stride: u32,
    pub scale: f32,
}

/// Output side of a convolution or pooling.
pub const fn out_size(input: u32, kernel: u32, stride: u32, pad: u32) -> u32 {
    (input + 2 * pad - kernel) / stride + 1
}

/// One output value of a convolution: `b + Σ w · x` over the window (weights
/// `out_c × in_c × k × k`), with ReLU when asked.
#[inline]
pub fn conv_at<F: Real>(
    p: &ConvParams,
    input: &[F],
    weights: &[F],
    bias: &[F],
    co: u32,
    oy: u32,
    ox: u32,
) -> F {
    let mut s = bias[co as usize];
    let k = p.kernel;
    let mut ci = 0;
    while ci < p.in_c {
        let mut ky = 0;
        while ky < k {
            let iy = (oy * p.stride + ky) as i32 - p.pad as i32;
            if iy >= 0 && (iy as u32) < p.in_h {
                let mut kx = 0;
                while kx < k {
                    let ix = (ox * p.stride + kx) as i32 - p.pad as i32;
                    if ix >= 0 && (ix as u32) < p.in_w {
                        let x = input[((ci * p.in_h + iy as u32) * p.in_w + ix as u32) as usize];
                        let w = weights[(((co * p.in_c + ci) * k + ky) * k + kx) as usize];
                        s += w * x;
                    }
                    kx += 1;
                }
            }
            ky += 1;
        }
        ci += 1;
    }
    if p.relu != 0 && s < F::zero() {
        F::zero()
    } else {
        s
    }
}

/// The gradient of one input value from the output gradient (`output` is the
/// forward's output, read for the ReLU's mask): a gather over every output whose
/// window holds the input.
#[inline]
pub fn conv_input_grad_at<F: Real>(
    p: &ConvParams,
    output: &[F],
    grad_out: &[F],
    weights: &[F],
    ci: u32,
    iy: u32,
    ix: u32,
) -> F {
    let k = p.kernel;
    let mut s = F::zero();
    let mut ky = 0;
    while ky < k {
        // oy * stride + ky - pad = iy.
        let ny = iy as i32 + p.pad as i32 - ky as i32;
        if ny >= 0 && ny as u32 % p.stride == 0 && (ny as u32 / p.stride) < p.out_h {
            let oy = ny as u32 / p.stride;
            let mut kx = 0;
            while kx < k {
                let nx = ix as i32 + p.pad as i32 - kx as i32;
                if nx >= 0 && nx as u32 % p.stride == 0 && (nx as u32 / p.stride) < p.out_w {
                    let ox = nx as u32 / p.stride;
                    let mut co = 0;
                    while co < p.out_c {
                        let o = ((co * p.out_h + oy) * p.out_w + ox) as usize;
                        if p.relu == 0 || output[o] > F::zero() {
                            s += weights[(((co * p.in_c + ci) * k + ky) * k + kx) as usize]
                                * grad_out[o];
                        }
                        co += 1;
                    }
                }
                kx += 1;
            }
        }
        ky += 1;
    }
    s
}

/// Max over one pooling window: (value, flat input index of the first maximum).
#[inline]
pub fn pool_at<F: Real>(p: &PoolParams, input: &[F], c: u32, oy: u32, ox: u32) -> (F, u32) {
    let mut best = F::neg_infinity();
    let mut at = 0u32;
    let mut ky = 0;
    while ky < p.kernel {
        let mut kx = 0;
        while kx < p.kernel {
            let i = (c * p.in_h + oy * p.stride + ky) * p.in_w + ox * p.stride + kx;
            let v = input[i as usize];
            if v > best {
                best = v;
                at = i;
            }
            kx += 1;
        }
        ky += 1;
    }
    (best, at)
}

/// The gradient of one pooling input: the sum of the output gradients of the windows
/// whose maximum it is.
#[inline]
pub fn pool_input_grad_at<F: Real>(
    p: &PoolParams,
    argmax: &[u32],
    grad_out: &[F],
    c: u32,
    iy: u32,
    ix: u32,
) -> F {
    let me = (c * p.in_h + iy) * p.in_w + ix;
    let mut s = F::zero();
    // Windows oy with oy·s ≤ iy < oy·s + k.
    let oy_lo = if iy + 1 > p.kernel {
        (iy + 1 - p.kernel).div_ceil(p.stride)
    } else {
        0
    };
    let ox_lo = if ix + 1 > p.kernel {
        (ix + 1 - p.kernel).div_ceil(p.stride)
    } else {
        0
    };
    let mut oy = oy_lo;
    while oy <= iy / p.stride && oy < p.out_h {
        let mut ox = ox_lo;
        while ox <= ix / p.stride && ox < p.out_w {
            let o = ((c * p.out_h + oy) * p.out_w + ox) as usize;
            if argmax[o] == me {
                s += grad_out[o];
            }
            ox += 1;
        }
        oy += 1;
    }
    s
}

/// Σ_c w_c (f0_c/(|f0|+ε) - f1_c/(|f1|+ε))² at one pixel of a tapped layer.
#[inline]
pub fn layer_distance_at<F: Real>(c: u32, hw: u32, f0: &[F], f1: &[F], lin: &[F], pixel: u32) -> F {
    let (n0, n1) = (
        channel_norm(c, hw, f0, pixel),
        channel_norm(c, hw, f1, pixel),
    );
    let eps = F::of(LPIPS_EPS);
    let mut s = F::zero();
    let mut k = 0;
    while k < c {
        let i = (k * hw + pixel) as usize;
        let d = f0[i] / (n0 + eps) - f1[i] / (n1 + eps);
        s += lin[k as usize] * d * d;
        k += 1;
    }
    s
}

/// `|f|` over channels at one pixel.
#[inline]
pub fn channel_norm<F: Real>(c: u32, hw: u32, f: &[F], pixel: u32) -> F {
    let mut s = F::zero();
    let mut k = 0;
    while k < c {
        let v = f[(k * hw + pixel) as usize];
        s += v * v;
        k += 1;
    }
    s.sqrt()
}

/// `∂ (layer distance at the pixel) / ∂ f0_j`: with `u = f0/(n+ε)`, `d = u - v`,
/// `g_c = 2 w_c d_c`: `g_j/(n+ε) - f0_j (Σ_c g_c f0_c) / ((n+ε)² n)` (the second term
/// 0 where n = 0).
#[inline]
pub fn layer_distance_grad_at<F: Real>(
    c: u32,
    hw: u32,
    f0: &[F],
    f1: &[F],
    lin: &[F],
    pixel: u32,
    j: u32,
) -> F {
    let (n0, n1) = (
        channel_norm(c, hw, f0, pixel),
        channel_norm(c, hw, f1, pixel),
    );
    let eps = F::of(LPIPS_EPS);
    let (a, b) = (n0 + eps, n1 + eps);
    let mut dot = F::zero();
    let mut gj = F::zero();
    let mut k = 0;
    while k < c {
        let i = (k * hw + pixel) as usize;
        let g = F::of(2.0) * lin[k as usize] * (f0[i] / a - f1[i] / b);
        dot += g * f0[i];
        if k == j {
            gj = g;
        }
        k += 1;
    }
    let fj = f0[(j * hw + pixel) as usize];
    let second = if n0 > F::zero() {
        fj * dot / (a * a * n0)
    } else {
        F::zero()
    };
    gj / a - second
}
