//! Per-Gaussian deformation and skinning with learned weights, forward and backward
//! (`drape_shared::deform` is the math and says what happens to the rotation).
//!
//! `deform_fwd` bindings (n Gaussians): `transforms` 24×12, `means` n×3, `quats` n×4,
//! `log_scales` n×3, `offsets` n×3, `rot6d` n×6, `log_scale_deltas` n×3, `weights`
//! n×24 (read); `posed_means` n×3, `posed_quats` n×4, `posed_log_scales` n×3 (written).
//! `deform_bwd`: the inputs less `log_scales` and `log_scale_deltas` (its gradients do
//! not depend on them), then `grad_posed_means`, `grad_posed_quats`,
//! `grad_posed_log_scales` (read); `grad_means`, `grad_offsets`, `grad_rot6d`,
//! `grad_log_scale_deltas`, `grad_weights`, `grad_transform_terms` n×15 (written).
//! `deform_transform_grad`: `weights` n×24, `terms` n×15 (read); `partials`
//! ceil(n / 1024)×24×12 (written): workgroup (chunk, joint) sums its chunk's share of
//! `∂L/∂A_joint` in an order fixed by the invocation indices, so the result does not
//! depend on scheduling.
//! `pose_blend_fwd`: `basis` n×621, `features` 207, `decoded` n×3 (read); `offsets` n×3
//! (written: `decoded` plus the pose blend, the offsets `deform_fwd` then reads).
//! `pose_blend_bwd`: `features`, `grad_offsets` n×3 (read); `grad_basis` n×621 (written).

use drape_shared::deform::{
    deform_bwd as bwd_math, deform_fwd as fwd_math, transform_grad_add, DeformInput, DeformOutput,
    DeformParams, TRANSFORM_GRAD_CHUNK, TRANSFORM_TERMS,
};
use drape_shared::skinning::{SKIN_JOINTS, TRANSFORM_FLOATS};
use spirv_std::arch::workgroup_memory_barrier_with_group_sync as barrier;
use spirv_std::glam::UVec3;
use spirv_std::spirv;

fn v3(b: &[f32], i: usize) -> [f32; 3] {
    [b[3 * i], b[3 * i + 1], b[3 * i + 2]]
}

/// Gaussian `i`'s inputs, the log-scales left at zero (the backward does not read
/// them; the forward fills them in).
fn load(
    i: usize,
    means: &[f32],
    quats: &[f32],
    offsets: &[f32],
    rot6d: &[f32],
    weights: &[f32],
) -> DeformInput<f32> {
    let mut w = [0.0f32; SKIN_JOINTS];
    let mut j = 0;
    while j < SKIN_JOINTS {
        w[j] = weights[i * SKIN_JOINTS + j];
        j += 1;
    }
    DeformInput {
        mean: v3(means, i),
        quat: [
            quats[4 * i],
            quats[4 * i + 1],
            quats[4 * i + 2],
            quats[4 * i + 3],
        ],
        log_scale: [0.0; 3],
        offset: v3(offsets, i),
        rot6d: [
            rot6d[6 * i],
            rot6d[6 * i + 1],
            rot6d[6 * i + 2],
            rot6d[6 * i + 3],
            rot6d[6 * i + 4],
            rot6d[6 * i + 5],
        ],
        log_scale_delta: [0.0; 3],
        weights: w,
    }
}

fn store3(b: &mut [f32], i: usize, v: [f32; 3]) {
    b[3 * i] = v[0];
    b[3 * i + 1] = v[1];
    b[3 * i + 2] = v[2];
}

#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(256)))]
pub fn deform_fwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] p: &DeformParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] transforms: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] means: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] quats: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] log_scales: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] offsets: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] rot6d: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] deltas: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] weights: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] posed_means: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] posed_quats: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 10)] posed_log_scales: &mut [f32],
) {
    let i = id.x as usize;
    if id.x >= p.count {
        return;
    }
    let mut g = load(i, means, quats, offsets, rot6d, weights);
    g.log_scale = v3(log_scales, i);
    g.log_scale_delta = v3(deltas, i);
    let out = fwd_math(&g, transforms);
    store3(posed_means, i, out.mean);
    drape_shared::each_index!(4, k => {
        posed_quats[4 * i + k] = out.quat[k];
    });
    let o = p.log_scale_offset;
    store3(
        posed_log_scales,
        i,
        [
            out.log_scale[0] + o,
            out.log_scale[1] + o,
            out.log_scale[2] + o,
        ],
    );
}

#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(256)))]
pub fn deform_bwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(push_constant)] p: &DeformParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] transforms: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] means: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] quats: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] offsets: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] rot6d: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] weights: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] grad_posed_means: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] grad_posed_quats: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 8)] grad_posed_log_scales: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 9)] grad_means: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 10)] grad_offsets: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 11)] grad_rot6d: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 12)] grad_deltas: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 13)] grad_weights: &mut [f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 14)] grad_transform_terms: &mut [f32],
) {
    let i = id.x as usize;
    if id.x >= p.count {
        return;
    }
    let g = load(i, means, quats, offsets, rot6d, weights);
    let up = DeformOutput {
        mean: v3(grad_posed_means, i),
        quat: [
            grad_posed_quats[4 * i],
            grad_posed_quats[4 * i + 1],
            grad_posed_quats[4 * i + 2],
            grad_posed_quats[4 * i + 3],
        ],
        log_scale: v3(grad_posed_log_scales, i),
    };
    let out = bwd_math(&g, transforms, &up);
    store3(grad_means, i, out.mean);
    store3(grad_offsets, i, out.offset);
    let mut k = 0;
    while k < 6 {
        grad_rot6d[6 * i + k] = out.rot6d[k];
        k += 1;
    }
    store3(grad_deltas, i, out.log_scale_delta);
    k = 0;
    while k < SKIN_JOINTS {
        grad_weights[i * SKIN_JOINTS + k] = out.weights[k];
        k += 1;
    }
    k = 0;
    while k < TRANSFORM_TERMS {
        grad_transform_terms[i * TRANSFORM_TERMS + k] = out.transform_terms[k];
        k += 1;
    }
}

/// Invocations of one `deform_transform_grad` workgroup.
const TRANSFORM_GRAD_GROUP: usize = 256;

/// Workgroup (chunk, joint) sums the chunk's share of `∂L/∂A_joint`: each invocation
/// adds every 256th Gaussian of the chunk, then a tree over the workgroup adds the 256
/// sums, in an order fixed by the invocation indices (deterministic). A workgroup, not
/// one invocation, per (chunk, joint): at the avatar's few thousand Gaussians per layer
/// there are only tens of (chunk, joint) pairs (72 for 3,000), too few invocations to
/// fill a GPU if each walked its 1,024 Gaussians alone (docs/performance.md, H100
/// "Training").
#[spirv(compute(threads(256)))]
pub fn deform_transform_grad(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &DeformParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] weights: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] terms: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] partials: &mut [f32],
    #[spirv(workgroup)] sums: &mut [[f32; TRANSFORM_FLOATS]; TRANSFORM_GRAD_GROUP],
) {
    // Dispatched as [chunks, 24, 1]: every invocation of a workgroup reaches every
    // barrier below (the chunk and joint are the workgroup's).
    let chunk = group.x;
    let joint = group.y as usize;
    let start = chunk * TRANSFORM_GRAD_CHUNK;
    let end = if start + TRANSFORM_GRAD_CHUNK < p.count {
        start + TRANSFORM_GRAD_CHUNK
    } else {
        p.count
    };
    let mut sum = [0.0f32; TRANSFORM_FLOATS];
    let mut i = (start + lid) as usize;
    while i < end as usize {
        let mut t = [0.0f32; TRANSFORM_TERMS];
        let mut k = 0;
        while k < TRANSFORM_TERMS {
            t[k] = terms[i * TRANSFORM_TERMS + k];
            k += 1;
        }
        transform_grad_add(&t, weights[i * SKIN_JOINTS + joint], &mut sum);
        i += TRANSFORM_GRAD_GROUP;
    }
    let l = lid as usize;
    sums[l] = sum;
    barrier();
    let mut half = TRANSFORM_GRAD_GROUP / 2;
    while half > 0 {
        if l < half {
            let mut k = 0;
            while k < TRANSFORM_FLOATS {
                sums[l][k] += sums[l + half][k];
                k += 1;
            }
        }
        barrier();
        half /= 2;
    }
    if l < TRANSFORM_FLOATS {
        partials[(chunk as usize * SKIN_JOINTS + joint) * TRANSFORM_FLOATS + l] = sums[0][l];
    }
}

/// Pose-dependent offsets (`drape_shared::deform::pose_blend_offset`): `offsets` n×3 =
/// `decoded` n×3 (the geometry decoder's offsets) + the pose blend of `basis` n×621 by
/// `features` 207.
#[spirv(compute(threads(256)))]
pub fn pose_blend_fwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &drape_shared::deform::PoseBlendParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] basis: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] features: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] decoded: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] offsets: &mut [f32],
) {
    let i = crate::flat_index(id, groups);
    if i >= p.count {
        return;
    }
    let i = i as usize;
    let o = drape_shared::deform::pose_blend_offset(basis, i, features);
    offsets[3 * i] = decoded[3 * i] + o[0];
    offsets[3 * i + 1] = decoded[3 * i + 1] + o[1];
    offsets[3 * i + 2] = decoded[3 * i + 2] + o[2];
}

/// The basis's gradient (`drape_shared::deform::pose_blend_basis_grad`): one invocation
/// per float of `grad_basis` n×621, from `features` 207 and `grad_offsets` n×3.
#[spirv(compute(threads(256)))]
pub fn pose_blend_bwd(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &drape_shared::deform::PoseBlendParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] features: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] grad_offsets: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] grad_basis: &mut [f32],
) {
    let j = crate::flat_index(id, groups);
    if j >= p.count * drape_shared::deform::POSE_BLEND_FLOATS as u32 {
        return;
    }
    grad_basis[j as usize] =
        drape_shared::deform::pose_blend_basis_grad(j as usize, features, grad_offsets);
}
