//! Exclusive prefix sum of `u32`: `scan::reduce` and `scan::downsweep` (blocks, for
//! GPUs), `scan::chunk_reduce`, `scan::chunk_sums` and `scan::chunk_downsweep` (long runs
//! walked by one invocation each, for CPU devices: `drape_shared::chunks`).
//!
//! Buffers (blocks): `data` holds `params.len` elements at this level; `block_sums` /
//! `block_offsets` one element per block of `SCAN_BLOCK_LEN` (see
//! `drape_shared::scan` for the level structure). Chunks: `chunk_sums` /
//! `chunk_offsets` one element per chunk. Out-of-range elements read as 0 and
//! are never written. Sums wrap, like `u32::wrapping_add`.

use drape_shared::chunks::{chunk_range, CHUNK_WORKGROUP_SIZE};
use drape_shared::scan::{ChunkScanParams, ScanParams, SCAN_BLOCK_LEN, SCAN_ITEMS_PER_THREAD, SCAN_WORKGROUP_SIZE};
use spirv_std::glam::UVec3;
use spirv_std::spirv;

use crate::workgroup::exclusive_scan;

const WG: usize = SCAN_WORKGROUP_SIZE as usize;
// The `threads(..)` attributes below must be literals; keep them in step with the layout.
const _: () = assert!(SCAN_WORKGROUP_SIZE == 256);

/// Sum of the elements invocation `lid` of block `block` owns.
fn thread_sum(data: &[u32], len: u32, block: u32, lid: u32) -> u32 {
    let base = block * SCAN_BLOCK_LEN + lid * SCAN_ITEMS_PER_THREAD;
    let mut sum = 0u32;
    let mut i = 0;
    while i < SCAN_ITEMS_PER_THREAD {
        let idx = base + i;
        if idx < len {
            sum = sum.wrapping_add(data[idx as usize]);
        }
        i += 1;
    }
    sum
}

/// Writes the sum of each block to `block_sums[block]`.
#[spirv(compute(threads(256)))]
pub fn reduce(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] block: UVec3,
    #[spirv(push_constant)] params: &ScanParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] data: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] block_sums: &mut [u32],
    #[spirv(workgroup)] scratch: &mut [u32; WG],
) {
    let sum = thread_sum(data, params.len, block.x, lid);
    let (_, total) = exclusive_scan(scratch, lid as usize, sum);
    if lid == 0 {
        block_sums[block.x as usize] = total;
    }
}

/// Scans each block in place, adding `block_offsets[block]` when
/// `params.add_block_offsets` is 1 (a single-block scan binds `data` there, unread).
#[spirv(compute(threads(256)))]
pub fn downsweep(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] block: UVec3,
    #[spirv(push_constant)] params: &ScanParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] data: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] block_offsets: &[u32],
    #[spirv(workgroup)] scratch: &mut [u32; WG],
) {
    let sum = thread_sum(data, params.len, block.x, lid);
    let (prefix, _) = exclusive_scan(scratch, lid as usize, sum);
    let mut running = prefix;
    if params.add_block_offsets != 0 {
        running = running.wrapping_add(block_offsets[block.x as usize]);
    }
    let base = block.x * SCAN_BLOCK_LEN + lid * SCAN_ITEMS_PER_THREAD;
    let mut i = 0;
    while i < SCAN_ITEMS_PER_THREAD {
        let idx = base + i;
        if idx < params.len {
            let v = data[idx as usize];
            data[idx as usize] = running;
            running = running.wrapping_add(v);
        }
        i += 1;
    }
}

/// `chunk_sums[chunk]` = the (wrapping) sum of chunk `chunk`'s elements; `chunks / 8`
/// workgroups, one chunk per invocation.
#[spirv(compute(threads(8)))]
pub fn chunk_reduce(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &ChunkScanParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] data: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] chunk_sums: &mut [u32],
) {
    let chunk = group.x * CHUNK_WORKGROUP_SIZE + lid;
    let (start, end) = chunk_range(params.len, params.chunks, chunk);
    let mut sum = 0u32;
    let mut i = start;
    while i < end {
        sum = sum.wrapping_add(data[i as usize]);
        i += 1;
    }
    chunk_sums[chunk as usize] = sum;
}

/// Scans the `params.chunks` chunk sums in place, exclusively, in one invocation (a
/// few thousand at most, and its index is uniform, so each load is a scalar one).
#[spirv(compute(threads(1)))]
pub fn chunk_sums(
    #[spirv(push_constant)] params: &ChunkScanParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] chunk_sums: &mut [u32],
) {
    let mut running = 0u32;
    let mut c = 0;
    while c < params.chunks as usize {
        let v = chunk_sums[c];
        chunk_sums[c] = running;
        running = running.wrapping_add(v);
        c += 1;
    }
}

/// Scans each chunk in place starting from its offset in the scanned chunk sums.
#[spirv(compute(threads(8)))]
pub fn chunk_downsweep(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &ChunkScanParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] data: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] chunk_offsets: &[u32],
) {
    let chunk = group.x * CHUNK_WORKGROUP_SIZE + lid;
    let (start, end) = chunk_range(params.len, params.chunks, chunk);
    let mut running = chunk_offsets[chunk as usize];
    let mut i = start;
    while i < end {
        let v = data[i as usize];
        data[i as usize] = running;
        running = running.wrapping_add(v);
        i += 1;
    }
}
