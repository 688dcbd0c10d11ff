//! Exclusive prefix sum of `u32`: `scan::reduce` and `scan::downsweep` (blocks, for
//! GPUs), `scan::chunk_reduce`, `scan::chunk_sums` and `scan::chunk_downsweep` (long runs
//! walked by one invocation each, for CPU devices: `drape_shared::chunks`), and
//! `scan::chunk_serial` (short scans on CPU devices: one invocation, one dispatch).
//!
//! Buffers (blocks): `data` holds `params.len` elements at this level; `block_sums` /
//! `block_offsets` one element per block of `SCAN_BLOCK_LEN` (see
//! `drape_shared::scan` for the level structure). Chunks: `chunk_sums` /
//! `chunk_offsets` one element per chunk. Out-of-range elements read as 0 and
//! are never written, except that the chunk kernels write the last quad of `data` whole,
//! its elements past `len` as they read them. Sums wrap, like `u32::wrapping_add`.

use drape_shared::chunks::{chunk_range, CHUNK_WORKGROUP_SIZE};
use drape_shared::scan::{
    ChunkScanParams, ScanParams, SCAN_BLOCK_LEN, SCAN_ITEMS_PER_THREAD, SCAN_WORKGROUP_SIZE,
};
use spirv_std::glam::{UVec3, UVec4};
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

// The chunk kernels move four elements a load and a store, as one `UVec4`: on llvmpipe a
// storage-buffer access whose address is not uniform is one loop over the 8 lanes however
// many components it moves, so a quad costs the loop one element cost before. Chunks are
// cut in whole quads (`chunk_range` of `len.div_ceil(4)` quads), so no two invocations
// touch one quad. Buffers are made in whole 16-byte texels (the engine's `vk_bytes`), so
// the quad holding the last element is inside the buffer; the downsweep writes its lanes
// past `len` back as they were read.

/// The chunk's quads: `start..end` of `len.div_ceil(4)`.
#[inline]
fn chunk_quads(params: &ChunkScanParams, chunk: u32) -> (u32, u32) {
    chunk_range(params.len.div_ceil(4), params.chunks, chunk)
}

/// `quad` with its lanes from `valid` on (elements past the end) replaced by `past`'s.
#[inline]
fn keep_valid(quad: UVec4, past: UVec4, valid: u32) -> UVec4 {
    UVec4::new(
        quad.x,
        if valid > 1 { quad.y } else { past.y },
        if valid > 2 { quad.z } else { past.z },
        if valid > 3 { quad.w } else { past.w },
    )
}

/// `chunk_sums[chunk]` = the (wrapping) sum of chunk `chunk`'s elements; `chunks / 8`
/// workgroups, one chunk per invocation.
#[spirv(compute(threads(8)))]
pub fn chunk_reduce(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &ChunkScanParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] data: &[UVec4],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] chunk_sums: &mut [u32],
) {
    let chunk = group.x * CHUNK_WORKGROUP_SIZE + lid;
    let (start, end) = chunk_quads(params, chunk);
    // Four running sums, one per lane of the quad, added as vectors: a quad used whole
    // stays one `v4uint` load (taken apart lane by lane, the compiler makes it four
    // scalar loads, four lane loops on llvmpipe). Integer vector adds wrap, as the
    // scalar `wrapping_add`.
    let mut sums = UVec4::ZERO;
    let mut q = start;
    // The last quad's elements past `len` are summed too: that quad lies in the last
    // chunk that has elements, whose sum no element's offset includes.
    while q < end {
        sums += data[q as usize];
        q += 1;
    }
    chunk_sums[chunk as usize] = sums
        .x
        .wrapping_add(sums.y)
        .wrapping_add(sums.z)
        .wrapping_add(sums.w);
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
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] data: &mut [UVec4],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] chunk_offsets: &[u32],
) {
    let chunk = group.x * CHUNK_WORKGROUP_SIZE + lid;
    let (start, end) = chunk_quads(params, chunk);
    scan_quads(data, params.len, start, end, chunk_offsets[chunk as usize]);
}

/// Scans quads `start..end` of `data` in place from `running`, the quad holding element
/// `len - 1` written whole with its elements past `len` as they were read.
#[inline]
fn scan_quads(data: &mut [UVec4], len: u32, start: u32, end: u32, mut running: u32) {
    let mut q = start;
    while q < end {
        let v = data[q as usize];
        let a = running;
        let b = a.wrapping_add(v.x);
        let c = b.wrapping_add(v.y);
        let d = c.wrapping_add(v.z);
        running = d.wrapping_add(v.w);
        let mut scanned = UVec4::new(a, b, c, d);
        let valid = len - 4 * q;
        if valid < 4 {
            scanned = keep_valid(scanned, v, valid);
        }
        data[q as usize] = scanned;
        q += 1;
    }
}

/// The whole scan in one invocation, quad by quad, in place: for scans short enough
/// (`drape_shared::scan::SERIAL_SCAN_MAX_LEN`) that one walk costs less than the two
/// extra dispatches of `chunk_reduce` / `chunk_sums` / `chunk_downsweep` (on llvmpipe
/// each dispatch waits for its threads to start and finish; a radix sort's histogram is
/// 16K counters for 1M keys). One workgroup of one invocation.
#[spirv(compute(threads(1)))]
pub fn chunk_serial(
    #[spirv(push_constant)] params: &ChunkScanParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] data: &mut [UVec4],
) {
    scan_quads(data, params.len, 0, params.len.div_ceil(4), 0);
}
