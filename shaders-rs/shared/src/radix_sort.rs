//! Stable least-significant-digit radix sort of `u32` keys carrying `u32` values, in
//! two variants of the same three steps: blocks (below; the GPU kernels) and chunks
//! ([`CHUNK_RADIX_BITS`]; for CPU devices).
//!
//! In the block variant each pass sorts by one [`RADIX_BITS`]-bit digit and is three steps:
//! 1. histogram: each workgroup counts the digits of its block of [`SORT_BLOCK_LEN`]
//!    keys and writes `histogram[digit * block_count + block]` (digit-major, so that
//!    an exclusive scan of the whole array gives every (digit, block) its first output
//!    slot, in stable order);
//! 2. an exclusive scan of the histogram (the scan kernels);
//! 3. scatter: each workgroup recounts, ranks each key among the equal digits of the
//!    invocations before it (a scan across invocations in workgroup memory), and writes
//!    key and value to `scanned[digit * block_count + block] + rank`.
//!
//! Invocation `t` of a workgroup owns the [`SORT_ITEMS_PER_THREAD`] consecutive keys
//! starting at `t * SORT_ITEMS_PER_THREAD` and walks them in order, so keys with equal
//! digits keep their input order: the sort is stable. Nothing assumes a subgroup size
//! and no workgroup waits on another one.
//!
//! Only the low `key_bits` bits of each key take part: a tile-id sort passes the bits
//! it needs and skips the passes it does not.

/// Bits per digit (one pass per digit).
pub const RADIX_BITS: u32 = 4;
/// Distinct digit values.
pub const RADIX_BUCKETS: u32 = 1 << RADIX_BITS;
/// Invocations per workgroup of the block variant's kernels (the `threads(..)` of their
/// entry points; the chunk kernels' is [`CHUNK_WORKGROUP_SIZE`]).
pub const SORT_WORKGROUP_SIZE: u32 = 128;
/// Consecutive keys each invocation owns.
pub const SORT_ITEMS_PER_THREAD: u32 = 16;
/// Keys one workgroup handles per pass.
pub const SORT_BLOCK_LEN: u32 = SORT_WORKGROUP_SIZE * SORT_ITEMS_PER_THREAD;
/// Workgroup-memory counters: one per (digit, invocation), digit-major.
pub const SORT_SHARED_COUNTERS: usize = (RADIX_BUCKETS * SORT_WORKGROUP_SIZE) as usize;

/// Push constants of the sort kernels.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct SortPassParams {
    /// Number of keys.
    pub len: u32,
    /// Bit position of this pass's digit.
    pub shift: u32,
    /// Mask applied after the shift (narrower than [`RADIX_BUCKETS`] - 1 on a last,
    /// partial digit).
    pub digit_mask: u32,
    /// Blocks: workgroups (blocks) covering `len` keys. Chunks: the chunk count
    /// ([`chunk_count`] of `len`), dispatched as `chunks / CHUNK_WORKGROUP_SIZE` workgroups.
    pub block_count: u32,
    /// 1: `len` is a capacity and the keys to sort are [`bounded_len`] of it and the
    /// 64-bit count in the kernels' `len_words` (a count the GPU computed, so no host
    /// read sits between the pass that counts and the sort); 0: `len` keys.
    pub bounded: u32,
    pub _pad: [u32; 3],
}

/// Number of passes for `key_bits` significant bits (0 bits: nothing to do).
pub const fn pass_count(key_bits: u32) -> u32 {
    key_bits.div_ceil(RADIX_BITS)
}

/// Number of blocks (workgroups) covering `len` keys.
pub const fn block_count(len: u32) -> u32 {
    len.div_ceil(SORT_BLOCK_LEN)
}

/// The parameters of pass `pass` when sorting `len` keys by their low `key_bits` bits.
pub const fn pass_params(len: u32, key_bits: u32, pass: u32) -> SortPassParams {
    digit_pass(len, key_bits, pass, RADIX_BITS, block_count(len))
}

/// Pass `pass` of digits `digit_bits` wide (the last one narrower where `key_bits` ends
/// inside it) over `len` keys in `blocks` blocks or chunks.
const fn digit_pass(
    len: u32,
    key_bits: u32,
    pass: u32,
    digit_bits: u32,
    blocks: u32,
) -> SortPassParams {
    let shift = pass * digit_bits;
    let remaining = key_bits - shift;
    let bits = if remaining < digit_bits {
        remaining
    } else {
        digit_bits
    };
    SortPassParams {
        len,
        shift,
        digit_mask: (1u32 << bits) - 1,
        block_count: blocks,
        bounded: 0,
        _pad: [0; 3],
    }
}

/// The number of elements to process when a GPU-computed 64-bit count (`lo`, `hi`)
/// meets a buffer of `capacity` elements: the count, or the capacity where the count
/// exceeds it (the caller then sees the overflow in the count and runs again larger).
///
/// ```
/// use drape_shared::radix_sort::bounded_len;
/// assert_eq!(bounded_len(100, 7, 0), 7);
/// assert_eq!(bounded_len(100, 700, 0), 100);
/// assert_eq!(bounded_len(100, 7, 1), 100);
/// ```
#[inline]
pub const fn bounded_len(capacity: u32, lo: u32, hi: u32) -> u32 {
    if hi != 0 || lo > capacity {
        capacity
    } else {
        lo
    }
}

/// The digit of `key` in the pass described by `params`.
#[inline]
pub fn digit(key: u32, params: &SortPassParams) -> u32 {
    (key >> params.shift) & params.digit_mask
}

/// The key the sort orders by: the low `key_bits` bits (all of them for 32).
#[inline]
pub const fn significant_bits(key: u32, key_bits: u32) -> u32 {
    if key_bits >= 32 {
        key
    } else {
        key & ((1u32 << key_bits) - 1)
    }
}

pub use crate::chunks::{chunk_count, chunk_len, chunk_range, CHUNK_MAX_LEN, CHUNK_WORKGROUP_SIZE};

/// The chunked variant, for CPU devices (`radix_sort::chunk_histogram`,
/// `radix_sort::chunk_scatter`): the keys are cut into [`chunk_count`] equal runs and
/// each invocation walks one run alone, in order, counting and then placing its keys
/// with its own [`CHUNK_BUCKETS`] counters in a local array. No invocation reads
/// another's counters, so there are no barriers; the per-(digit, chunk) histogram
/// is digit-major like the block variant's, so the same exclusive scan gives each
/// (digit, chunk) its first slot and the sort stays stable. Digits of
/// [`CHUNK_RADIX_BITS`] bits halve the passes of the block variant's; its counters
/// would not fit workgroup memory at this width (one column per invocation of 128).
///
/// Why for CPUs: llvmpipe runs a workgroup's invocations as SIMD lanes and turns every
/// storage-buffer or workgroup-memory load or store whose address is not uniform into a
/// loop over the lanes (one per 32-bit component), and every barrier into a coroutine
/// switch. The block variant's ranking (a workgroup scan of every counter, per pass,
/// with barriers) then costs more than the keys' own traffic; here each key costs its
/// load (a texel fetch: a gather), one counter update (a local array: unrolled moves)
/// and its store (the only loop). On a GPU a few long
/// serial walks would leave most of the machine idle, so GPUs keep the block variant.
pub const CHUNK_RADIX_BITS: u32 = 8;
/// Distinct digit values of the chunked variant.
pub const CHUNK_BUCKETS: u32 = 1 << CHUNK_RADIX_BITS;
/// Number of passes of the chunked variant for `key_bits` significant bits.
pub const fn chunk_pass_count(key_bits: u32) -> u32 {
    key_bits.div_ceil(CHUNK_RADIX_BITS)
}

/// The parameters of the chunked variant's pass `pass` over up to `capacity` keys by
/// their low `key_bits` bits; `block_count` is the chunk count.
pub const fn chunk_pass_params(capacity: u32, key_bits: u32, pass: u32) -> SortPassParams {
    digit_pass(
        capacity,
        key_bits,
        pass,
        CHUNK_RADIX_BITS,
        chunk_count(capacity),
    )
}
