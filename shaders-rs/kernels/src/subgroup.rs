//! Subgroup broadcasts, the second `unsafe` of the kernels: spirv-std exposes
//! `OpGroupNonUniformBroadcast` as an `unsafe fn` because its result is undefined when
//! the source lane is inactive or outside the subgroup. Built only with the
//! `subgroup-ballot` feature (the shader builder's build that declares the capability).
#![allow(unsafe_code)]

use spirv_std::arch::{subgroup_broadcast, subgroup_broadcast_const};

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

/// [`broadcast`] for a `u32`.
#[inline]
pub fn broadcast_u32<const LANE: u32>(v: u32) -> u32 {
    // SAFETY: as in `broadcast`.
    unsafe { subgroup_broadcast_const::<u32, LANE>(v) }
}

/// The value `v` of lane `lane` of this subgroup, to every lane: `lane` is the same in
/// every lane (dynamically uniform, which SPIR-V 1.5 allows for
/// OpGroupNonUniformBroadcast; llvmpipe reads lane 0's index and extracts that element,
/// one shuffle, as for a constant lane). Same conditions as [`broadcast`], `lane < 8`.
#[inline]
pub fn broadcast_at(v: f32, lane: u32) -> f32 {
    // SAFETY: `lane` is uniform, inside the subgroup and active (see above).
    unsafe { subgroup_broadcast(v, lane) }
}

/// [`broadcast_at`] for a `u32`.
#[inline]
pub fn broadcast_u32_at(v: u32, lane: u32) -> u32 {
    // SAFETY: as in `broadcast_at`.
    unsafe { subgroup_broadcast(v, lane) }
}

/// Bit `l` set where `v` holds in lane `l`, in every lane (same conditions as [`sum8`]).
#[inline]
pub fn ballot8(v: bool) -> u32 {
    let x = if v { 1u32 } else { 0 };
    broadcast_u32::<0>(x)
        | (broadcast_u32::<1>(x) << 1)
        | (broadcast_u32::<2>(x) << 2)
        | (broadcast_u32::<3>(x) << 3)
        | (broadcast_u32::<4>(x) << 4)
        | (broadcast_u32::<5>(x) << 5)
        | (broadcast_u32::<6>(x) << 6)
        | (broadcast_u32::<7>(x) << 7)
}

/// The sum over the 8 lanes of `v`, in every lane (lane order, so every lane gets the
/// same bits). Same conditions as [`broadcast`], for lanes 0..8.
#[inline]
pub fn sum8(v: f32) -> f32 {
    ((broadcast::<0>(v) + broadcast::<1>(v)) + (broadcast::<2>(v) + broadcast::<3>(v)))
        + ((broadcast::<4>(v) + broadcast::<5>(v)) + (broadcast::<6>(v) + broadcast::<7>(v)))
}

/// The largest `v` over the 8 lanes, in every lane (same conditions as [`sum8`]).
#[inline]
pub fn max8_u32(v: u32) -> u32 {
    let a = broadcast_u32::<0>(v).max(broadcast_u32::<1>(v)).max(broadcast_u32::<2>(v).max(broadcast_u32::<3>(v)));
    let b = broadcast_u32::<4>(v).max(broadcast_u32::<5>(v)).max(broadcast_u32::<6>(v).max(broadcast_u32::<7>(v)));
    a.max(b)
}

/// Whether `v` holds in all 8 lanes (same conditions as [`sum8`]).
#[inline]
pub fn all8(v: bool) -> bool {
    let x = if v { 1u32 } else { 0 };
    (broadcast_u32::<0>(x) & broadcast_u32::<1>(x) & broadcast_u32::<2>(x) & broadcast_u32::<3>(x)
        & broadcast_u32::<4>(x) & broadcast_u32::<5>(x) & broadcast_u32::<6>(x) & broadcast_u32::<7>(x))
        != 0
}
