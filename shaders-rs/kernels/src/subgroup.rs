//! Subgroup broadcasts, the second `unsafe` of the kernels: spirv-std exposes
//! `OpGroupNonUniformBroadcast` as an `unsafe fn` because its result is undefined when
//! the source lane is inactive or outside the subgroup. Built only with the
//! `subgroup-ballot` feature (the shader builder's build that declares the capability).
#![allow(unsafe_code)]

use spirv_std::arch::subgroup_broadcast_const;

/// The value `v` of lane `LANE` of this subgroup, to every lane.
///
/// Callers keep lanes `0..=LANE` active (no lane of the subgroup has returned or
/// branched away when this runs) and run only where the subgroup has more than `LANE`
/// lanes: the engine dispatches such kernels only on devices whose subgroup size is 8,
/// and uses `LANE < 8`.
#[inline]
pub fn broadcast<const LANE: u32>(v: f32) -> f32 {
    // SAFETY: the lane is constant, inside the subgroup and active (see above), which
    // is all OpGroupNonUniformBroadcast requires for a defined result.
    unsafe { subgroup_broadcast_const::<f32, LANE>(v) }
}
