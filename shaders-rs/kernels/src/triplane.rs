//! Triplane sampling on the GPU, forward and backward (`drape_shared::triplane` is the
//! math and states the padding).
//!
//! `sample_fwd` bindings: `planes` 3·R·R·C, `points` n×3 (read), `features` n×3C
//! (written). `sample_bwd_{atomic,cas,fixed}`: `planes`, `points`, `grad_features` (read),
//! `grad_planes` 3·R·R·C (added to: the caller zeroes it), `grad_points` n×3 (written).
//! One invocation per point; the plane gradient is a scatter-add of four bilinear
//! weights per channel per plane, with float atomics, the compare-and-swap fallback,
//! or (deterministic) fixed-point integer atomics into a scratch buffer.

use drape_shared::triplane::{
    corners, footprint, inside, normalise, texel_index, TriplaneParams, PLANE_AXES,
};
use spirv_std::glam::UVec3;
use spirv_std::spirv;

#[cfg(feature = "float-atomics")]
use crate::atomics::FloatAtomics;
use crate::atomics::{CompareAndSwap, FixedPoint, GradAdd};

fn load_point(points: &[f32], i: usize) -> [f32; 3] {
    [points[3 * i], points[3 * i + 1], points[3 * i + 2]]
}

fn finite3(p: [f32; 3]) -> bool {
    p[0].is_finite() && p[1].is_finite() && p[2].is_finite()
}

/// Features of point `i`: 3C values.
#[spirv(compute(threads(256)))]
pub fn sample_fwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] p: &TriplaneParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] planes: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] points: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] features: &mut [f32],
) {
    let i = id.x as usize;
    if id.x >= p.count {
        return;
    }
    let ch = p.channels as usize;
    let pt = load_point(points, i);
    let ok = finite3(pt);
    let u = normalise(pt, p);
    let mut plane = 0;
    while plane < 3 {
        let out = i * 3 * ch + plane * ch;
        let mut c = 0;
        while c < ch {
            features[out + c] = 0.0;
            c += 1;
        }
        if ok {
            let fx = footprint(u[PLANE_AXES[plane].0], p.resolution);
            let fy = footprint(u[PLANE_AXES[plane].1], p.resolution);
            let cs = corners(&fx, &fy);
            let mut k = 0;
            while k < 4 {
                let (row, col, w, _, _) = cs[k];
                if inside(row, p.resolution) && inside(col, p.resolution) {
                    let t = texel_index(plane, row, col, p);
                    c = 0;
                    while c < ch {
                        features[out + c] += w * planes[t + c];
                        c += 1;
                    }
                }
                k += 1;
            }
        }
        plane += 1;
    }
}

/// The backward of [`sample_fwd`]: the plane gradient added by `A` (float atomics,
/// compare-and-swap or fixed point), the point gradient written. Entry points:
/// [`sample_bwd_atomic`], [`sample_bwd_cas`], [`sample_bwd_fixed`].
#[inline]
fn sample_bwd_in<A: GradAdd>(
    id: UVec3,
    p: &TriplaneParams,
    planes: &[f32],
    points: &[f32],
    grad_features: &[f32],
    grad_planes: &mut [A::Word],
    grad_points: &mut [f32],
) {
    let i = id.x as usize;
    if id.x >= p.count {
        return;
    }
    let ch = p.channels as usize;
    let pt = load_point(points, i);
    let mut gu = [0.0f32; 3];
    if finite3(pt) {
        let u = normalise(pt, p);
        let mut plane = 0;
        while plane < 3 {
            let (ax, ay) = PLANE_AXES[plane];
            let fx = footprint(u[ax], p.resolution);
            let fy = footprint(u[ay], p.resolution);
            let cs = corners(&fx, &fy);
            let g = i * 3 * ch + plane * ch;
            let mut k = 0;
            while k < 4 {
                let (row, col, w, dwx, dwy) = cs[k];
                if inside(row, p.resolution) && inside(col, p.resolution) {
                    let t = texel_index(plane, row, col, p);
                    let mut dot = 0.0f32;
                    let mut c = 0;
                    while c < ch {
                        let gc = grad_features[g + c];
                        dot += gc * planes[t + c];
                        A::add(grad_planes, t + c, w * gc);
                        c += 1;
                    }
                    gu[ax] += dwx * dot;
                    gu[ay] += dwy * dot;
                }
                k += 1;
            }
            plane += 1;
        }
    }
    grad_points[3 * i] = gu[0] * p.box_scale[0];
    grad_points[3 * i + 1] = gu[1] * p.box_scale[1];
    grad_points[3 * i + 2] = gu[2] * p.box_scale[2];
}

/// [`sample_bwd_in`] with float atomics (needs shaderBufferFloat32AtomicAdd).
#[cfg(feature = "float-atomics")]
#[spirv(compute(threads(256)))]
pub fn sample_bwd_atomic(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] p: &TriplaneParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] planes: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] points: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] grad_features: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] grad_planes: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] grad_points: &mut [f32],
) {
    sample_bwd_in::<FloatAtomics>(
        id,
        p,
        planes,
        points,
        grad_features,
        grad_planes,
        grad_points,
    );
}

/// [`sample_bwd_in`] with compare-and-swap on the bits of f32 (any device).
#[spirv(compute(threads(256)))]
pub fn sample_bwd_cas(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] p: &TriplaneParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] planes: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] points: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] grad_features: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] grad_planes: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] grad_points: &mut [f32],
) {
    sample_bwd_in::<CompareAndSwap>(
        id,
        p,
        planes,
        points,
        grad_features,
        grad_planes,
        grad_points,
    );
}

/// [`sample_bwd_in`], deterministic: the plane gradient in 64-bit fixed point (`fixed_point::resolve` turns it into f32).
#[spirv(compute(threads(256)))]
pub fn sample_bwd_fixed(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] p: &TriplaneParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] planes: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] points: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] grad_features: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] grad_planes: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] grad_points: &mut [f32],
) {
    sample_bwd_in::<FixedPoint>(
        id,
        p,
        planes,
        points,
        grad_features,
        grad_planes,
        grad_points,
    );
}
