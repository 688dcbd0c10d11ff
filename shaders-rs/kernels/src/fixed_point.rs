//! The second half of deterministic accumulation (`drape_shared::fixed_point` states
//! the representation): `resolve` turns a fixed-point scratch buffer, which a
//! `*_fixed` backward kernel added into, into f32 values.
//!
//! Bindings: `scratch` at least 2·count + 1 u32 words (read; its last word, wherever
//! the buffer ends, is the non-finite flag, as `atomics::add_fixed` finds it),
//! `out` count f32 (written: overwritten, not added to). One invocation per value.

use drape_shared::fixed_point::{decode, ResolveParams};
use spirv_std::glam::UVec3;
use spirv_std::spirv;

/// `out[i] = decode(scratch[2i], scratch[2i + 1])`, or NaN everywhere when a
/// non-finite value was added (so that the caller's non-finite guard sees it).
#[spirv(compute(threads(256)))]
pub fn resolve(
    #[spirv(global_invocation_id)] id: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(push_constant)] p: &ResolveParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] scratch: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] out: &mut [f32],
) {
    let index = crate::flat_index(id, groups);
    if index >= p.count {
        return;
    }
    let i = index as usize;
    out[i] = if scratch[scratch.len() - 1] != 0 {
        f32::NAN
    } else {
        decode([scratch[2 * i], scratch[2 * i + 1]])
    };
}
