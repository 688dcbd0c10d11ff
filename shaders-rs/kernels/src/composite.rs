//! Depth-aware compositing of three rendered passes (`drape_shared::splat::composite`
//! is the math): `fwd` writes the composited image, `bwd` the gradients to the three
//! passes' outputs, `add_slice` adds one layer's slice of a pass's per-Gaussian
//! gradients into that layer's own.
//!
//! `fwd` bindings: base rgb, over rgb, over alpha, matte rgb (channel 0 is V), out rgb.
//! `bwd` bindings: grad out rgb, base rgb, over rgb, over alpha, matte rgb, then the
//! written gradients to base rgb, over rgb, over alpha and matte rgb (channels 1 and 2
//! zero: the matte pass's colour is V in every channel, and only one carries it).
//! With `matte_is_alpha` the matte is the over alpha: read from there, its gradient
//! joined to the alpha's, and the matte buffers neither read nor written.
//! `to_rgba` bindings: rgb, alpha a, alpha b (unread when `b_stride` is 0), out rgba.

use drape_shared::splat::composite::{
    composite, composite_grad, coverage, CompositeParams, RgbaParams, SliceParams,
};
use spirv_std::glam::UVec3;
use spirv_std::spirv;

#[inline]
fn rgb(b: &[f32], i: usize) -> [f32; 3] {
    [b[3 * i], b[3 * i + 1], b[3 * i + 2]]
}

#[spirv(compute(threads(256)))]
pub fn fwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &CompositeParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] base: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] over: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] over_alpha: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] matte: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] out: &mut [f32],
) {
    let i = crate::flat_index(id, groups);
    if i >= p.pixels {
        return;
    }
    let i = i as usize;
    let v = if p.matte_is_alpha != 0 {
        over_alpha[i]
    } else {
        matte[3 * i]
    };
    let c = composite(rgb(base, i), rgb(over, i), over_alpha[i], v);
    out[3 * i] = c[0];
    out[3 * i + 1] = c[1];
    out[3 * i + 2] = c[2];
}

/// A rendered image and its coverage as premultiplied RGBA (see [`RgbaParams`]).
#[spirv(compute(threads(256)))]
pub fn to_rgba(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &RgbaParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] rgb_in: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] alpha_a: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] alpha_b: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] rgba: &mut [f32],
) {
    let i = crate::flat_index(id, groups);
    if i >= p.pixels {
        return;
    }
    let i = i as usize;
    let a_raw = alpha_a[p.a_stride as usize * i];
    let a = if p.a_is_transmittance != 0 {
        1.0 - a_raw
    } else {
        a_raw
    };
    let b = if p.b_stride != 0 {
        alpha_b[p.b_stride as usize * i]
    } else {
        0.0
    };
    let c = rgb(rgb_in, i);
    rgba[4 * i] = c[0];
    rgba[4 * i + 1] = c[1];
    rgba[4 * i + 2] = c[2];
    rgba[4 * i + 3] = coverage(a, b);
}

#[spirv(compute(threads(256)))]
pub fn bwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &CompositeParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] grad: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] base: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] over: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] over_alpha: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] matte: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] grad_base: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] grad_over: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] grad_over_alpha: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] grad_matte: &mut [f32],
) {
    let i = crate::flat_index(id, groups);
    if i >= p.pixels {
        return;
    }
    let i = i as usize;
    let v = if p.matte_is_alpha != 0 {
        over_alpha[i]
    } else {
        matte[3 * i]
    };
    let (gb, go, ga, gm) =
        composite_grad(rgb(grad, i), rgb(base, i), rgb(over, i), over_alpha[i], v);
    drape_shared::each_index!(3, ch => {
        grad_base[3 * i + ch] = gb[ch];
        grad_over[3 * i + ch] = go[ch];
    });
    if p.matte_is_alpha != 0 {
        grad_over_alpha[i] = ga + gm;
    } else {
        grad_over_alpha[i] = ga;
        grad_matte[3 * i] = gm;
        grad_matte[3 * i + 1] = 0.0;
        grad_matte[3 * i + 2] = 0.0;
    }
}

#[spirv(compute(threads(256)))]
pub fn add_slice(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &SliceParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] src: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] dst: &mut [f32],
) {
    let i = crate::flat_index(id, groups);
    if i >= p.len {
        return;
    }
    dst[i as usize] += src[(p.src_offset + i) as usize];
}
