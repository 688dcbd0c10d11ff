//! Workgroup-cooperative building blocks (barriers and workgroup memory).
//!
//! Every function here must be called by all invocations of the workgroup in uniform
//! control flow: each contains barriers.

use spirv_std::arch::workgroup_memory_barrier_with_group_sync as barrier;

/// Exclusive prefix sum (wrapping) of one value per invocation across a workgroup of
/// `N` invocations (Hillis-Steele over `scratch`). Returns (exclusive prefix, total).
/// `N` must be a power of two equal to the workgroup size.
pub fn exclusive_scan<const N: usize>(
    scratch: &mut [u32; N],
    lid: usize,
    value: u32,
) -> (u32, u32) {
    scratch[lid] = value;
    barrier();
    let mut offset = 1usize;
    while offset < N {
        let left = if lid >= offset {
            scratch[lid - offset]
        } else {
            0
        };
        barrier();
        scratch[lid] = scratch[lid].wrapping_add(left);
        barrier();
        offset <<= 1;
    }
    let inclusive = scratch[lid];
    let total = scratch[N - 1];
    // Everyone has read; the caller may reuse `scratch` right away.
    barrier();
    (inclusive.wrapping_sub(value), total)
}
