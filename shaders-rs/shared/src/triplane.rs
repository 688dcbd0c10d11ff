//! Triplane feature sampling: three planes (XY, XZ, YZ), each `R × R × C`, stored
//! channels-last (`planes[p][row][col][c]`); a point is mapped through its layer's box
//! into `[-1, 1]³` and each plane is sampled bilinearly with PyTorch's
//! `grid_sample(mode="bilinear", align_corners=True)` semantics: grid x picks the column,
//! grid y the row, `-1` and `1` are the centres of the first and last texels.
//!
//! Padding: zeros (as HUGS). A corner texel outside the plane contributes 0, so a
//! point up to one texel outside the box fades out and a point further out gets a
//! zero feature and zero gradients. Non-finite points get zero features.
//!
//! Plane p samples the normalised coordinates `(u[PLANE_AXES[p].0], u[PLANE_AXES[p].1])`
//! as (grid x, grid y); the feature vector is the three planes' C features in plane
//! order (3C).

use crate::real::Real;

/// Normalised axes each plane samples, as (grid x, grid y).
pub const PLANE_AXES: [(usize, usize); 3] = [(0, 1), (0, 2), (1, 2)];

/// Push constants of the `triplane::*` kernels.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct TriplaneParams {
    pub count: u32,
    /// Plane side R.
    pub resolution: u32,
    /// Channels C per plane.
    pub channels: u32,
    pub _pad0: u32,
    pub box_min: [f32; 4],
    /// `2 / (box_max - box_min)` per axis (w unused).
    pub box_scale: [f32; 4],
}

/// The bilinear footprint of one grid coordinate along one axis: the lower texel
/// index, its weight and the upper one's, and `d(upper weight) / d(grid coordinate)`.
#[derive(Clone, Copy, Debug)]
pub struct Footprint<F> {
    pub i0: i32,
    pub w0: F,
    pub w1: F,
    pub dw1_dg: F,
}

/// Footprint of grid coordinate `g ∈ [-1, 1]` on an axis of `size` texels
/// (`align_corners=True`: texel position `(g + 1) / 2 (size - 1)`).
#[inline]
pub fn footprint<F: Real>(g: F, size: u32) -> Footprint<F> {
    let half = F::of(0.5) * F::of((size - 1) as f32);
    let x = (g + F::one()) * half;
    let x0 = x.floor();
    let w1 = x - x0;
    // Far outside (or huge): clamp the index so the cast stays defined; every corner
    // is then out of range and contributes nothing.
    let limit = F::of(1.0e6);
    let i0 = if x0 < -limit {
        -1_000_000
    } else if x0 > limit {
        1_000_000
    } else {
        x0.to_f32() as i32
    };
    Footprint {
        i0,
        w0: F::one() - w1,
        w1,
        dw1_dg: half,
    }
}

/// Whether texel index `i` lies in a plane of side `size`.
#[inline]
pub fn inside(i: i32, size: u32) -> bool {
    i >= 0 && i < size as i32
}

/// Normalised coordinates of point `p` (`u = (p - box_min) * box_scale - 1`).
#[inline]
pub fn normalise<F: Real>(p: [F; 3], params: &TriplaneParams) -> [F; 3] {
    [
        (p[0] - F::of(params.box_min[0])) * F::of(params.box_scale[0]) - F::one(),
        (p[1] - F::of(params.box_min[1])) * F::of(params.box_scale[1]) - F::one(),
        (p[2] - F::of(params.box_min[2])) * F::of(params.box_scale[2]) - F::one(),
    ]
}

/// Index of texel (plane, row, col, channel 0) in the channels-last layout.
#[inline]
pub fn texel_index(plane: usize, row: i32, col: i32, params: &TriplaneParams) -> usize {
    let r = params.resolution as usize;
    ((plane * r + row as usize) * r + col as usize) * params.channels as usize
}

/// The four corners of a bilinear sample: (row, col, weight, d weight / d gx,
/// d weight / d gy), in the order (y0 x0), (y0 x1), (y1 x0), (y1 x1).
#[inline]
pub fn corners<F: Real>(fx: &Footprint<F>, fy: &Footprint<F>) -> [(i32, i32, F, F, F); 4] {
    [
        (
            fy.i0,
            fx.i0,
            fy.w0 * fx.w0,
            -fx.dw1_dg * fy.w0,
            -fy.dw1_dg * fx.w0,
        ),
        (
            fy.i0,
            fx.i0 + 1,
            fy.w0 * fx.w1,
            fx.dw1_dg * fy.w0,
            -fy.dw1_dg * fx.w1,
        ),
        (
            fy.i0 + 1,
            fx.i0,
            fy.w1 * fx.w0,
            -fx.dw1_dg * fy.w1,
            fy.dw1_dg * fx.w0,
        ),
        (
            fy.i0 + 1,
            fx.i0 + 1,
            fy.w1 * fx.w1,
            fx.dw1_dg * fy.w1,
            fy.dw1_dg * fx.w1,
        ),
    ]
}
