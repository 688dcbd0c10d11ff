//! Subgroup broadcasts and reductions for the kernels of CPU devices. Built only with
//! the `subgroup-ballot` feature (the shader builder's builds that declare the
//! subgroup capabilities, shuffles among them).
//!
//! Lanes move between each other by shuffles (`OpGroupNonUniformShuffle`,
//! `ShuffleXor`), not by `OpGroupNonUniformBroadcast` or reduces: llvmpipe 22.3
//! compiles a shuffle of 32-bit values in a subgroup of 8 to one AVX2 `vpermd`, while a
//! broadcast (constant lane or not) is a loop over the lanes looking for the first
//! active one before it extracts the lane asked for, and a reduce a loop adding the
//! lanes one by one. With shuffles the subgroup rasterizers run 24-31% faster forward
//! and backward on lavapipe than with broadcasts (100k Gaussians, 512 x 512, tiles of 8
//! and 16).
//!
//! Every function here needs all 8 lanes of the subgroup active (no lane has returned
//! or branched away when it runs): the engine dispatches these kernels only on devices
//! whose subgroup size is 8, in workgroups of 8, and their loops are uniform.

use spirv_std::arch::{subgroup_ballot, subgroup_shuffle, subgroup_shuffle_xor};
use spirv_std::glam::Vec4;

/// The value `v` of lane `lane` (< 8) of this subgroup, to every lane: `lane` may differ
/// between lanes (a shuffle), though the rasterizers pass a uniform one and the GEMMs
/// a constant.
#[inline]
pub fn broadcast_at(v: f32, lane: u32) -> f32 {
    subgroup_shuffle(v, lane)
}

/// [`broadcast_at`] for a `u32`.
#[inline]
pub fn broadcast_u32_at(v: u32, lane: u32) -> u32 {
    subgroup_shuffle(v, lane)
}

/// [`broadcast_at`] for a `Vec4`: one shuffle of the whole vector (a `Vec4` loaded from
/// a storage buffer and used whole stays one load; see `splat::SplatRows`).
#[inline]
pub fn broadcast_vec4_at(v: Vec4, lane: u32) -> Vec4 {
    subgroup_shuffle(v, lane)
}

/// Bit `l` set where `v` holds in lane `l`, in every lane.
#[inline]
pub fn ballot8(v: bool) -> u32 {
    // OpGroupNonUniformBallot: one loop over the lanes on llvmpipe (once a round of
    // the rasterizers' walks, not once a splat).
    subgroup_ballot(v).x & 0xff
}

/// The sum over the 8 lanes of `v`, in every lane, every lane getting the same bits.
///
/// A butterfly of three shuffles: lane `l` adds lane `l ^ 1`, then `l ^ 2`, then
/// `l ^ 4`. Float addition is commutative, so a lane and its partner compute the same
/// bits at every step and all 8 end equal; the order is fixed, so the sum is the same
/// on every run (the deterministic backward relies on that). Three `vpermd` and three
/// adds on llvmpipe, where `OpGroupNonUniformFAdd` is a loop over the lanes.
#[inline]
pub fn sum8(v: f32) -> f32 {
    let v = v + subgroup_shuffle_xor(v, 1);
    let v = v + subgroup_shuffle_xor(v, 2);
    v + subgroup_shuffle_xor(v, 4)
}

/// The largest `v` over the 8 lanes, in every lane (a butterfly, as [`sum8`]).
#[inline]
pub fn max8_u32(v: u32) -> u32 {
    let v = v.max(subgroup_shuffle_xor(v, 1));
    let v = v.max(subgroup_shuffle_xor(v, 2));
    v.max(subgroup_shuffle_xor(v, 4))
}

/// Whether `v` holds in all 8 lanes (a butterfly, as [`sum8`]).
#[inline]
pub fn all8(v: bool) -> bool {
    let x = u32::from(v);
    let x = x & subgroup_shuffle_xor(x, 1);
    let x = x & subgroup_shuffle_xor(x, 2);
    (x & subgroup_shuffle_xor(x, 4)) != 0
}
