//! Per-element training kernels: Adam, the image loss gradients (MSE, L1), gradient
//! sums, SH copies between degrees and the non-finite count. All are dispatched on the
//! engine's `flat_grid` (index `id.y * num_workgroups.x * 256 + id.x`), so a parameter
//! group may pass 16.7M floats (6M Gaussians' SH is 288M).
//!
//! `adam_step`: `params`, `grads`, `m`, `v` of `len` floats; updates params, m, v in place
//! (`drape_shared::adam::adam_update` is the math). `mse_grad`: `pred`, `target` of
//! `len` floats; writes `grad = 2 (pred - target) * scale` and the squared error.
//! `l1_grad`: `pred`, `target` likewise; writes `grad = sign(pred - target) * scale` and
//! the absolute error. `add_into`: `src` (read), `dst` (added to).
//! `copy_sh`: `src`, `dst` SH buffers of two degrees (layers rendered together).
//! `count_nonfinite`: `values` (read), `counter` (added to: one per NaN or infinity).
//! `adam_step_guarded`: `adam_step` that does nothing while `guard[0]` is not 0 (the
//! step's guard: the non-finite count plus the renders' overflow flags).
//! `flag_exceeds`: `counter[0] += 1` when the 64-bit count in `value` is past the limit
//! (a render's intersection total past its capacity: that step's image is truncated).

use drape_shared::adam::{adam_update, exceeds, AdamParams, ExceedsParams, LossParams};
use drape_shared::splat::layout::{sh_copy_indices, ShCopyParams};
use spirv_std::glam::UVec3;
use spirv_std::spirv;

#[spirv(compute(threads(256)))]
pub fn adam_step(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &AdamParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] params: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] grads: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] m: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] v: &mut [f32],
) {
    adam_element(crate::flat_index(id, groups), p, params, grads, m, v);
}

/// [`adam_step`] unless the step's guard is raised (`guard[0] != 0`): a step with a
/// non-finite gradient or a truncated render is not applied, and the host learns of it
/// after the step's one wait instead of waiting for the count before Adam.
#[spirv(compute(threads(256)))]
pub fn adam_step_guarded(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &AdamParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] params: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] grads: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] m: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] v: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] guard: &[u32],
) {
    if guard[0] != 0 {
        return;
    }
    adam_element(crate::flat_index(id, groups), p, params, grads, m, v);
}

fn adam_element(
    index: u32,
    p: &AdamParams,
    params: &mut [f32],
    grads: &[f32],
    m: &mut [f32],
    v: &mut [f32],
) {
    if index >= p.len {
        return;
    }
    let i = index as usize;
    let (np, nm, nv) = adam_update(params[i], grads[i], m[i], v[i], p);
    params[i] = np;
    m[i] = nm;
    v[i] = nv;
}

#[spirv(compute(threads(256)))]
pub fn mse_grad(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &LossParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pred: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] target: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] grad: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] squared_error: &mut [f32],
) {
    let index = crate::flat_index(id, groups);
    if index >= p.len {
        return;
    }
    let i = index as usize;
    let d = pred[i] - target[i];
    grad[i] = 2.0 * d * p.scale;
    squared_error[i] = d * d;
}

/// L1 image loss: `grad = sign(pred - target) * scale` (0 where equal, as PyTorch's
/// `l1_loss`), and the absolute error per element.
#[spirv(compute(threads(256)))]
pub fn l1_grad(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &LossParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pred: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] target: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] grad: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] abs_error: &mut [f32],
) {
    let index = crate::flat_index(id, groups);
    if index >= p.len {
        return;
    }
    let i = index as usize;
    let d = pred[i] - target[i];
    grad[i] = if d > 0.0 {
        p.scale
    } else if d < 0.0 {
        -p.scale
    } else {
        0.0
    };
    abs_error[i] = d.abs();
}

/// `dst[i] += src[i]` (sums gradients that reach one parameter along two paths).
#[spirv(compute(threads(256)))]
pub fn add_into(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &LossParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] src: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] dst: &mut [f32],
) {
    let index = crate::flat_index(id, groups);
    if index >= p.len {
        return;
    }
    let i = index as usize;
    dst[i] += src[i];
}

/// Copies SH between buffers of different degrees (`drape_shared::splat::layout::
/// ShCopyParams`): one invocation per destination float; padded coefficients get 0.
#[spirv(compute(threads(256)))]
pub fn copy_sh(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &ShCopyParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] src: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] dst: &mut [f32],
) {
    let i = crate::flat_index(id, groups);
    if i >= p.floats() {
        return;
    }
    let (d, s) = sh_copy_indices(i, p);
    dst[d] = match s {
        Some(s) => src[s],
        None => 0.0,
    };
}

/// `counter[0] += 1` for every element of `values[..len]` that is NaN or infinite (the
/// training step's guard reads it before applying Adam).
#[spirv(compute(threads(256)))]
pub fn count_nonfinite(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &LossParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] values: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] counter: &mut [u32],
) {
    let i = crate::flat_index(id, groups);
    if i >= p.len {
        return;
    }
    if !values[i as usize].is_finite() {
        crate::atomics::add_u32(&mut counter[0], 1);
    }
}

/// `counter[0] += 1` when the 64-bit count `value` (low word, high word) is past the
/// limit: one invocation, recorded after the count is final.
#[spirv(compute(threads(1)))]
pub fn flag_exceeds(
    #[spirv(push_constant)] p: &ExceedsParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] value: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] counter: &mut [u32],
) {
    if exceeds(value[0], value[1], p) {
        crate::atomics::add_u32(&mut counter[0], 1);
    }
}
