//! Exclusive prefix sum of `u32` (wrapping), reduce-then-scan.
//!
//! Layout: one workgroup of [`SCAN_WORKGROUP_SIZE`] invocations owns a block of
//! [`SCAN_BLOCK_LEN`] consecutive elements; invocation `t` owns the
//! [`SCAN_ITEMS_PER_THREAD`] consecutive elements starting at `t * SCAN_ITEMS_PER_THREAD`.
//!
//! Levels: for `n > SCAN_BLOCK_LEN` a reduce pass writes one sum per block, the block
//! sums are scanned recursively, and a down-sweep pass scans each block again with its
//! block's offset. No workgroup ever waits on another one (no decoupled look-back):
//! Vulkan promises no forward progress between workgroups.
//!
//! Arithmetic is wrapping, like `u32::wrapping_add`, on both sides.

/// Invocations per workgroup of the block variant's scan kernels (the `threads(..)` of
/// their entry points; the chunk kernels run 8, and 1 for the chunk sums and the
/// one-invocation scan).
pub const SCAN_WORKGROUP_SIZE: u32 = 256;
/// Consecutive elements each invocation owns.
pub const SCAN_ITEMS_PER_THREAD: u32 = 4;
/// Elements one workgroup scans.
pub const SCAN_BLOCK_LEN: u32 = SCAN_WORKGROUP_SIZE * SCAN_ITEMS_PER_THREAD;

/// Push constants of the scan kernels.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct ScanParams {
    /// Number of elements at this level.
    pub len: u32,
    /// 1 when the down-sweep adds `block_offsets[workgroup]`, 0 for a single-block scan.
    pub add_block_offsets: u32,
    pub _pad: [u32; 2],
}

/// Push constants of the chunked scan kernels (`scan::chunk_*`, for CPU devices: each
/// invocation sums and then scans one of `chunks` runs of `len` elements, see
/// [`crate::chunks`]; one invocation scans the chunk sums in between; up to
/// [`SERIAL_SCAN_MAX_LEN`] one invocation scans all `len` elements, and `chunks` is
/// unread).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct ChunkScanParams {
    /// Number of elements.
    pub len: u32,
    /// Number of chunks ([`crate::chunks::chunk_count`] of `len`), a
    /// multiple of [`crate::chunks::CHUNK_WORKGROUP_SIZE`].
    pub chunks: u32,
    pub _pad: [u32; 2],
}

/// Number of blocks (workgroups) that cover `len` elements.
pub const fn block_count(len: u32) -> u32 {
    len.div_ceil(SCAN_BLOCK_LEN)
}

/// Exclusive scan of `data` in place; returns the (wrapping) total.
/// This is the CPU reference the GPU scan is checked against.
///
/// ```
/// let mut v = [3u32, 1, 4, 1, 5];
/// let total = drape_shared::scan::exclusive_scan_in_place(&mut v);
/// assert_eq!(v, [0, 3, 4, 8, 9]);
/// assert_eq!(total, 14);
/// ```
pub fn exclusive_scan_in_place(data: &mut [u32]) -> u32 {
    let mut running = 0u32;
    for x in data.iter_mut() {
        let v = *x;
        *x = running;
        running = running.wrapping_add(v);
    }
    running
}

/// Longest scan the chunked variant does in one invocation (`scan::chunk_serial`, one
/// dispatch instead of three): 16K quads, well inside llvmpipe's 65,535 loop iterations
/// an invocation, and the histogram of a chunked radix sort of up to 8M keys (256
/// chunks of 256 counters).
pub const SERIAL_SCAN_MAX_LEN: u32 = 65_536;
// The serial walk is one loop of a quad an iteration.
const _: () = assert!(SERIAL_SCAN_MAX_LEN.div_ceil(4) <= 65_535);
