//! Linear blend skinning of points, forward and backward, per joint term.
//!
//! `x' = x + Σ_j w_j (A_j x̂ - x)` with `x̂ = (x, 1)` and `A_j` the 3x4 row-major
//! skinning transform of joint j: equal to `Σ_j w_j A_j x̂` when the weights sum to 1,
//! and exactly `x` when every transform is the identity.
//! Backward, for an upstream gradient g on x': `dx = g + Σ_j w_j (R_j - I)ᵀ g`,
//! `dw_j = g · (A_j x̂ - x)`, `dA_j[r][c] = w_j g_r x̂_c`.

use crate::real::{Real, V3};

/// Joints of the SMPL skeleton.
pub const SKIN_JOINTS: usize = 24;
/// Floats per transform (3x4).
pub const TRANSFORM_FLOATS: usize = 12;
/// Vertices one workgroup of the transform-gradient kernel sums.
pub const TRANSFORM_GRAD_CHUNK: u32 = 1024;

/// Push constants of the skinning kernels.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct SkinParams {
    /// Points.
    pub count: u32,
    /// Workgroups of partial transform gradients.
    pub groups: u32,
    pub _pad: [u32; 2],
}

/// `A x̂ - x` for one transform.
#[inline]
pub fn transform_delta<F: Real>(a: &[F; TRANSFORM_FLOATS], x: V3<F>) -> V3<F> {
    [
        a[0] * x[0] + a[1] * x[1] + a[2] * x[2] + a[3] - x[0],
        a[4] * x[0] + a[5] * x[1] + a[6] * x[2] + a[7] - x[1],
        a[8] * x[0] + a[9] * x[1] + a[10] * x[2] + a[11] - x[2],
    ]
}

/// `(R - I)ᵀ g` for one transform.
#[inline]
pub fn rotation_minus_identity_t<F: Real>(a: &[F; TRANSFORM_FLOATS], g: V3<F>) -> V3<F> {
    [
        (a[0] - F::one()) * g[0] + a[4] * g[1] + a[8] * g[2],
        a[1] * g[0] + (a[5] - F::one()) * g[1] + a[9] * g[2],
        a[2] * g[0] + a[6] * g[1] + (a[10] - F::one()) * g[2],
    ]
}

#[inline]
pub fn dot3<F: Real>(a: V3<F>, b: V3<F>) -> F {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
