//! Long runs walked by one invocation each: the layout of the chunked kernels for CPU
//! devices (`radix_sort::chunk_*`, `scan::chunk_*`).
//!
//! A length is cut into [`chunk_count`] runs of equal length ([`chunk_range`]); each
//! invocation of a workgroup of [`CHUNK_WORKGROUP_SIZE`] walks one run alone, in order.
//! On llvmpipe a workgroup of 8 is one SIMD vector: no barriers, no coroutine switches,
//! and nothing but the walk itself; on a GPU so few invocations would leave most of it
//! idle, so the GPU kernels stay the block-wise ones.

/// Invocations per workgroup of the chunked kernels (one chunk each: a subgroup of 8 on
/// llvmpipe).
pub const CHUNK_WORKGROUP_SIZE: u32 = 8;
/// Longest run one invocation walks. llvmpipe stops a shader's loops after 65,535
/// iterations in all (its loop limiter); a walk plus the two 256-counter loops stays
/// well inside that.
pub const CHUNK_MAX_LEN: u32 = 32_768;
/// Chunks wanted when there are elements enough: 8 workgroups, so both of a small CPU's
/// cores get work, and what is kept per chunk (the sort's 256 counters) stays short.
pub const CHUNK_TARGET_COUNT: u32 = 64;
/// The run length [`chunk_count`] aims at for lengths short of the target count of
/// chunks (before it rounds the count up to whole workgroups, which shortens them).
pub const CHUNK_MIN_LEN: u32 = 1024;
/// The budget [`CHUNK_MAX_LEN`] keeps within: a walk plus two loops over the sort's 256
/// counters (`radix_sort::CHUNK_BUCKETS`), under llvmpipe's 65,535 loop iterations.
const _: () = assert!(CHUNK_MAX_LEN + 2 * 256 <= 65_535);

/// Number of chunks a length of up to `capacity` is cut into: a
/// multiple of [`CHUNK_WORKGROUP_SIZE`], at least one workgroup's, enough that no chunk
/// exceeds [`CHUNK_MAX_LEN`]. Fixed by the capacity, so a bounded sort (whose count the
/// GPU computes) is dispatched without reading the count; the kernels then divide the
/// actual count over these chunks ([`chunk_len`]), so a short list is still shared by all.
///
/// ```
/// use drape_shared::chunks::chunk_count;
/// assert_eq!(chunk_count(0), 8);
/// assert_eq!(chunk_count(10_000), 16);
/// assert_eq!(chunk_count(1 << 20), 64);
/// assert_eq!(chunk_count(16 << 20), 512);
/// ```
pub const fn chunk_count(capacity: u32) -> u32 {
    let by_min_len = capacity.div_ceil(CHUNK_MIN_LEN);
    let wanted = if by_min_len < CHUNK_TARGET_COUNT {
        by_min_len
    } else {
        CHUNK_TARGET_COUNT
    };
    let needed = capacity.div_ceil(CHUNK_MAX_LEN);
    let chunks = if wanted > needed { wanted } else { needed };
    let rounded = chunks.div_ceil(CHUNK_WORKGROUP_SIZE) * CHUNK_WORKGROUP_SIZE;
    if rounded == 0 {
        CHUNK_WORKGROUP_SIZE
    } else {
        rounded
    }
}

/// Elements per chunk when `len` keys are cut into `chunks` runs (the last ones may be
/// shorter or empty).
#[inline]
pub const fn chunk_len(len: u32, chunks: u32) -> u32 {
    len.div_ceil(chunks)
}

/// The elements of chunk `chunk`: `start..end` of `len` keys cut into `chunks` runs.
#[inline]
pub const fn chunk_range(len: u32, chunks: u32, chunk: u32) -> (u32, u32) {
    let run = chunk_len(len, chunks);
    // chunk < chunks, so chunk * run < len + chunks: no overflow below 2^32 - 2^16.
    let start = chunk * run;
    let start = if start < len { start } else { len };
    let end = if len - start < run { len } else { start + run };
    (start, end)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chunks_cover_every_key_once_in_order() {
        // Up to the sort's and the scan's limits (65,535 workgroups of their blocks).
        for len in [
            0u32,
            1,
            7,
            8,
            9,
            1000,
            1023,
            1025,
            65_537,
            1 << 20,
            (1 << 21) + 3,
            16 << 20,
            65_535 * 1024,
            65_535 * 2048,
        ] {
            let chunks = chunk_count(len);
            assert_eq!(chunks % CHUNK_WORKGROUP_SIZE, 0);
            // A bounded sort divides any count up to its capacity over the same chunks.
            for count in [len, len / 3, len.saturating_sub(1)] {
                let mut next = 0;
                for c in 0..chunks {
                    let (start, end) = chunk_range(count, chunks, c);
                    assert!(
                        start <= end && end - start <= CHUNK_MAX_LEN,
                        "len {len} count {count} chunk {c}: {start}..{end}"
                    );
                    assert_eq!(start, next.min(count), "len {len} count {count} chunk {c}");
                    next = end.max(next);
                }
                assert_eq!(next, count, "len {len} count {count}: chunks end at {next}");
            }
        }
    }
}
