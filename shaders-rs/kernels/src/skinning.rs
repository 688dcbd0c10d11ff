//! Linear blend skinning of points on the GPU, forward and backward
//! (`drape_shared::skinning` is the math).
//!
//! Buffers (V points, 24 joints): `transforms` 24×12 (3x4 row-major), `weights` V×24,
//! `points` V×3, `skinned`/`grad_skinned` V×3, `grad_points` V×3, `grad_weights` V×24,
//! `partials` groups×288 (per-workgroup sums of the transform gradient),
//! `grad_transforms` 288. The transform gradient is summed in two deterministic
//! steps (chunks, then chunks of chunks) instead of with atomics.

use drape_shared::skinning::{
    dot3, rotation_minus_identity_t, transform_delta, SkinParams, SKIN_JOINTS, TRANSFORM_FLOATS,
    TRANSFORM_GRAD_CHUNK,
};
use spirv_std::glam::UVec3;
use spirv_std::spirv;

const SLOTS: usize = SKIN_JOINTS * TRANSFORM_FLOATS;

fn transform(transforms: &[f32], j: usize) -> [f32; TRANSFORM_FLOATS] {
    let b = j * TRANSFORM_FLOATS;
    [
        transforms[b],
        transforms[b + 1],
        transforms[b + 2],
        transforms[b + 3],
        transforms[b + 4],
        transforms[b + 5],
        transforms[b + 6],
        transforms[b + 7],
        transforms[b + 8],
        transforms[b + 9],
        transforms[b + 10],
        transforms[b + 11],
    ]
}

/// `skinned[i] = points[i] + Σ_j w_ij (A_j x̂_i - x_i)`.
#[spirv(compute(threads(256)))]
pub fn skin_fwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] p: &SkinParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] transforms: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] weights: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] points: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] skinned: &mut [f32],
) {
    let i = id.x as usize;
    if id.x >= p.count {
        return;
    }
    let x = [points[3 * i], points[3 * i + 1], points[3 * i + 2]];
    let mut out = x;
    let mut j = 0;
    while j < SKIN_JOINTS {
        let w = weights[i * SKIN_JOINTS + j];
        if w != 0.0 {
            let d = transform_delta(&transform(transforms, j), x);
            out[0] += w * d[0];
            out[1] += w * d[1];
            out[2] += w * d[2];
        }
        j += 1;
    }
    skinned[3 * i] = out[0];
    skinned[3 * i + 1] = out[1];
    skinned[3 * i + 2] = out[2];
}

/// Gradients with respect to each point and its weights.
#[spirv(compute(threads(256)))]
pub fn skin_bwd_points(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] p: &SkinParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] transforms: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] weights: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] points: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] grad_skinned: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] grad_points: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] grad_weights: &mut [f32],
) {
    let i = id.x as usize;
    if id.x >= p.count {
        return;
    }
    let x = [points[3 * i], points[3 * i + 1], points[3 * i + 2]];
    let g = [
        grad_skinned[3 * i],
        grad_skinned[3 * i + 1],
        grad_skinned[3 * i + 2],
    ];
    let mut gx = g;
    let mut j = 0;
    while j < SKIN_JOINTS {
        let a = transform(transforms, j);
        let w = weights[i * SKIN_JOINTS + j];
        grad_weights[i * SKIN_JOINTS + j] = dot3(g, transform_delta(&a, x));
        let r = rotation_minus_identity_t(&a, g);
        gx[0] += w * r[0];
        gx[1] += w * r[1];
        gx[2] += w * r[2];
        j += 1;
    }
    grad_points[3 * i] = gx[0];
    grad_points[3 * i + 1] = gx[1];
    grad_points[3 * i + 2] = gx[2];
}

/// `partials[group][slot]` = this chunk's sum of `w_j g_r x̂_c` for slot (j, r, c).
#[spirv(compute(threads(256)))]
pub fn skin_bwd_transforms(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &SkinParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] weights: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] points: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] grad_skinned: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] partials: &mut [f32],
) {
    let begin = group.x * TRANSFORM_GRAD_CHUNK;
    let end = if begin + TRANSFORM_GRAD_CHUNK < p.count {
        begin + TRANSFORM_GRAD_CHUNK
    } else {
        p.count
    };
    let mut slot = lid as usize;
    while slot < SLOTS {
        let j = slot / TRANSFORM_FLOATS;
        let r = (slot % TRANSFORM_FLOATS) / 4;
        let c = slot % 4;
        let mut sum = 0.0f32;
        let mut i = begin as usize;
        while i < end as usize {
            let w = weights[i * SKIN_JOINTS + j];
            let xc = if c == 3 { 1.0 } else { points[3 * i + c] };
            sum += w * grad_skinned[3 * i + r] * xc;
            i += 1;
        }
        partials[group.x as usize * SLOTS + slot] = sum;
        slot += 256;
    }
}

/// `grad_transforms[slot]` = sum over groups of `partials[group][slot]`.
#[spirv(compute(threads(256)))]
pub fn sum_partials(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] p: &SkinParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] partials: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] grad_transforms: &mut [f32],
) {
    let slot = id.x as usize;
    if slot >= SLOTS {
        return;
    }
    let mut sum = 0.0f32;
    let mut g = 0;
    while g < p.groups as usize {
        sum += partials[g * SLOTS + slot];
        g += 1;
    }
    grad_transforms[slot] = sum;
}
