//! LPIPS's frozen network and distance (`drape_shared::lpips` states the math): input
//! scaling, convolution (+ ReLU) forward and backward to the input, max-pooling
//! forward and backward, and the per-layer distance with its gradient. Every kernel
//! computes one output element per invocation (a gather: deterministic, no atomics),
//! 256 per workgroup on the engine's `flat_grid`.

use drape_shared::lpips::{
    conv_at, conv_input_grad_at, layer_distance_at, layer_distance_grad_at, pool_at,
    pool_input_grad_at, ConvParams, PoolParams, LPIPS_SCALE, LPIPS_SHIFT,
};
use spirv_std::glam::UVec3;
use spirv_std::spirv;

use crate::flat_index;

/// `out[c][y][x] = (2 rgb[y][x][c] - 1 - shift_c) / scale_c` (HWC in [0, 1] to the
/// network's CHW input); `p.c = 3`, `p.in_h`, `p.in_w`.
#[spirv(compute(threads(256)))]
pub fn scale_input(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &PoolParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] rgb: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] out: &mut [f32],
) {
    let i = flat_index(id, groups);
    let hw = p.in_h * p.in_w;
    if i >= 3 * hw {
        return;
    }
    let (c, pixel) = (i / hw, i % hw);
    out[i as usize] = (2.0 * rgb[(3 * pixel + c) as usize] - 1.0 - LPIPS_SHIFT[c as usize])
        / LPIPS_SCALE[c as usize];
}

/// `grad_rgb[y][x][c] += p.scale · 2 / scale_c · grad[c][y][x]`.
#[spirv(compute(threads(256)))]
pub fn scale_input_bwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &PoolParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] grad: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] grad_rgb: &mut [f32],
) {
    let i = flat_index(id, groups);
    let hw = p.in_h * p.in_w;
    if i >= 3 * hw {
        return;
    }
    let (pixel, c) = (i / 3, i % 3);
    grad_rgb[i as usize] +=
        p.scale * 2.0 / LPIPS_SCALE[c as usize] * grad[(c * hw + pixel) as usize];
}

#[spirv(compute(threads(256)))]
pub fn conv_fwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &ConvParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] input: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] weights: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] bias: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] output: &mut [f32],
) {
    let i = flat_index(id, groups);
    let hw = p.out_h * p.out_w;
    if i >= p.out_c * hw {
        return;
    }
    let (co, pixel) = (i / hw, i % hw);
    output[i as usize] = conv_at(
        p,
        input,
        weights,
        bias,
        co,
        pixel / p.out_w,
        pixel % p.out_w,
    );
}

/// `grad_in = ∂ / ∂ input` of the convolution (through its ReLU), written.
#[spirv(compute(threads(256)))]
pub fn conv_bwd_input(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &ConvParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] output: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] grad_out: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] weights: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] grad_in: &mut [f32],
) {
    let i = flat_index(id, groups);
    let hw = p.in_h * p.in_w;
    if i >= p.in_c * hw {
        return;
    }
    let (ci, pixel) = (i / hw, i % hw);
    grad_in[i as usize] = conv_input_grad_at(
        p,
        output,
        grad_out,
        weights,
        ci,
        pixel / p.in_w,
        pixel % p.in_w,
    );
}

#[spirv(compute(threads(256)))]
pub fn pool_fwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &PoolParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] input: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] output: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] argmax: &mut [u32],
) {
    let i = flat_index(id, groups);
    let hw = p.out_h * p.out_w;
    if i >= p.c * hw {
        return;
    }
    let (c, pixel) = (i / hw, i % hw);
    let (v, at) = pool_at(p, input, c, pixel / p.out_w, pixel % p.out_w);
    output[i as usize] = v;
    argmax[i as usize] = at;
}

#[spirv(compute(threads(256)))]
pub fn pool_bwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &PoolParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] argmax: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] grad_out: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] grad_in: &mut [f32],
) {
    let i = flat_index(id, groups);
    let hw = p.in_h * p.in_w;
    if i >= p.c * hw {
        return;
    }
    let (c, pixel) = (i / hw, i % hw);
    grad_in[i as usize] =
        pool_input_grad_at(p, argmax, grad_out, c, pixel / p.in_w, pixel % p.in_w);
}

/// Per pixel of a tapped layer (`p.c` channels of `p.in_h × p.in_w`): the weighted
/// squared distance of the normalised features.
#[spirv(compute(threads(256)))]
pub fn distance(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &PoolParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] f0: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] f1: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] lin: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] out: &mut [f32],
) {
    let i = flat_index(id, groups);
    let hw = p.in_h * p.in_w;
    if i >= hw {
        return;
    }
    out[i as usize] = layer_distance_at(p.c, hw, f0, f1, lin, i);
}

/// `grad[j][pixel] (+)= p.scale · ∂ distance(pixel) / ∂ f0[j][pixel]`; adds when
/// `p.kernel` is 1 (the flag: a layer that also feeds a deeper one already has the
/// deeper layers' gradient there).
#[spirv(compute(threads(256)))]
pub fn distance_grad(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &PoolParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] f0: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] f1: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] lin: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] grad: &mut [f32],
) {
    let i = flat_index(id, groups);
    let hw = p.in_h * p.in_w;
    if i >= p.c * hw {
        return;
    }
    let (j, pixel) = (i / hw, i % hw);
    let g = p.scale * layer_distance_grad_at(p.c, hw, f0, f1, lin, pixel, j);
    if p.kernel == 1 {
        grad[i as usize] += g;
    } else {
        grad[i as usize] = g;
    }
}
