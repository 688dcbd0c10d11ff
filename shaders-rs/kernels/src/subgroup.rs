//! Subgroup broadcasts and reductions, the second `unsafe` of the kernels: spirv-std
//! exposes `OpGroupNonUniformBroadcast` as an `unsafe fn` because its result is
//! undefined when the source lane is inactive or outside the subgroup (its reduces,
//! votes and ballots are safe). Built only with the `subgroup-ballot` feature (the
//! shader builder's builds that declare the subgroup capabilities).
#![allow(unsafe_code)]

use spirv_std::arch::{subgroup_all, subgroup_ballot, subgroup_broadcast, subgroup_broadcast_const, subgroup_f_add, subgroup_u_max};

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

/// The value `v` of lane `lane` of this subgroup, to every lane: `lane` is the same in
/// every lane (dynamically uniform, which SPIR-V 1.5 allows for
/// OpGroupNonUniformBroadcast; llvmpipe 22.3 runs a loop over the lanes to find the
/// first active one, reads its index and extracts that element, as for a constant
/// lane). Same conditions as [`broadcast`], `lane < 8`.
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
    // OpGroupNonUniformBallot: one loop over the lanes on llvmpipe, where eight
    // broadcasts were eight loops (each looks for the first active lane).
    subgroup_ballot(v).x & 0xff
}

/// The sum over the 8 lanes of `v`, in every lane, every lane getting the same bits.
/// Same conditions as [`broadcast`], for lanes 0..8.
///
/// `OpGroupNonUniformFAdd` (reduce): llvmpipe 22.3 compiles it to one loop adding the
/// active lanes in lane order, while a broadcast is a loop of its own (it looks for the
/// first active lane before it extracts the one asked for), so this is one loop where
/// the eight broadcasts it replaces were eight. The order of the sum is the device's:
/// lane order there, a tree on others.
#[inline]
pub fn sum8(v: f32) -> f32 {
    subgroup_f_add(v)
}

/// The largest `v` over the 8 lanes, in every lane (same conditions as [`sum8`]; one
/// `OpGroupNonUniformUMax` reduce).
#[inline]
pub fn max8_u32(v: u32) -> u32 {
    subgroup_u_max(v)
}

/// Whether `v` holds in all 8 lanes (same conditions as [`sum8`]; one
/// `OpGroupNonUniformAll`).
#[inline]
pub fn all8(v: bool) -> bool {
    subgroup_all(v)
}
