//! One pass of the stable LSD radix sort: `radix_sort::histogram` and `radix_sort::scatter`
//! (the block variant, for GPUs), `radix_sort::chunk_histogram[_pairs][_texel]` and
//! `radix_sort::chunk_scatter[_zip|_pairs|_unzip][_texel]` (the chunked variant, for CPU
//! devices; see `drape_shared::radix_sort::CHUNK_RADIX_BITS`; `_zip`/`_pairs`/`_unzip` say
//! which side holds interleaved (key, value) pairs instead of separate buffers, and
//! `_texel` that the kernel reads its input through texel views, see `PairSource`;
//! `chunk_scatter_zip_texel_u64` and `chunk_scatter_pairs_texel_u64` store each pair as
//! one u64, on devices with `shaderInt64`).
//!
//! Buffers: `keys_in`/`values_in` hold `params.len` elements; `histogram` holds
//! `RADIX_BUCKETS * params.block_count` counters (blocks; chunks: `CHUNK_BUCKETS` per
//! chunk), digit-major (see `drape_shared::radix_sort`); the scatter reads it after the
//! exclusive scan. Blocks: workgroup memory `counters[digit * WG + invocation]` gives
//! each invocation its own column, so counting needs no atomics; chunks: each
//! invocation keeps its chunk's counters in a local array. `len_words` holds a
//! GPU-computed 64-bit count when `params.bounded` is 1 (read only then; unbounded
//! sorts bind the keys there).

use drape_shared::radix_sort::{
    bounded_len, chunk_range, digit, SortPassParams, CHUNK_BUCKETS, CHUNK_WORKGROUP_SIZE,
    RADIX_BUCKETS, SORT_BLOCK_LEN, SORT_ITEMS_PER_THREAD, SORT_SHARED_COUNTERS,
    SORT_WORKGROUP_SIZE,
};
use spirv_std::arch::workgroup_memory_barrier_with_group_sync as barrier;
use spirv_std::glam::{UVec2, UVec3, UVec4, Vec4};
use spirv_std::spirv;

use crate::texel::{fetch4, TexelBuffer4};
use crate::workgroup::exclusive_scan;

const WG: usize = SORT_WORKGROUP_SIZE as usize;
const BUCKETS: usize = RADIX_BUCKETS as usize;
const _: () = assert!(SORT_WORKGROUP_SIZE == 128);
// The flattened counter scan gives each invocation one whole run of counters.
const COUNTERS_PER_THREAD: usize = SORT_SHARED_COUNTERS / WG;

/// Zeroes this invocation's column and counts the digits of its keys into it.
fn count_digits(
    counters: &mut [u32; SORT_SHARED_COUNTERS],
    keys: &[u32],
    params: &SortPassParams,
    len: u32,
    block: u32,
    lid: u32,
) {
    let column = lid as usize;
    let mut d = 0;
    while d < BUCKETS {
        counters[d * WG + column] = 0;
        d += 1;
    }
    let base = block * SORT_BLOCK_LEN + lid * SORT_ITEMS_PER_THREAD;
    let mut i = 0;
    while i < SORT_ITEMS_PER_THREAD {
        let idx = base + i;
        if idx < len {
            let slot = digit(keys[idx as usize], params) as usize * WG + column;
            counters[slot] += 1;
        }
        i += 1;
    }
}

/// The number of keys this pass sorts.
fn keys_to_sort(params: &SortPassParams, len_words: &[u32]) -> u32 {
    if params.bounded != 0 {
        bounded_len(params.len, len_words[0], len_words[1])
    } else {
        params.len
    }
}

/// `histogram[digit * block_count + block]` = how many keys of this block have `digit`.
#[spirv(compute(threads(128)))]
pub fn histogram(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] block: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] keys: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] histogram: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] len_words: &[u32],
    #[spirv(workgroup)] counters: &mut [u32; SORT_SHARED_COUNTERS],
) {
    let len = keys_to_sort(params, len_words);
    count_digits(counters, keys, params, len, block.x, lid);
    barrier();
    if (lid as usize) < BUCKETS {
        let row = lid as usize * WG;
        let mut total = 0u32;
        let mut t = 0;
        while t < WG {
            total += counters[row + t];
            t += 1;
        }
        histogram[(lid * params.block_count + block.x) as usize] = total;
    }
}

/// Moves every key (and its value) to its place for this digit, stably.
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(128)))]
pub fn scatter(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] block: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] keys_in: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] values_in: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] scanned_histogram: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] keys_out: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] values_out: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] len_words: &[u32],
    #[spirv(workgroup)] counters: &mut [u32; SORT_SHARED_COUNTERS],
    #[spirv(workgroup)] scratch: &mut [u32; WG],
    #[spirv(workgroup)] digit_base: &mut [u32; BUCKETS],
) {
    let len = keys_to_sort(params, len_words);
    count_digits(counters, keys_in, params, len, block.x, lid);
    barrier();

    // Exclusive scan of the counters in digit-major order: afterwards
    // counters[d * WG + t] = keys of this block with a smaller digit, plus keys with
    // digit d owned by invocations before t.
    let run = lid as usize * COUNTERS_PER_THREAD;
    let mut run_total = 0u32;
    let mut k = 0;
    while k < COUNTERS_PER_THREAD {
        run_total += counters[run + k];
        k += 1;
    }
    let (mut running, _) = exclusive_scan(scratch, lid as usize, run_total);
    k = 0;
    while k < COUNTERS_PER_THREAD {
        let c = counters[run + k];
        counters[run + k] = running;
        running += c;
        k += 1;
    }
    barrier();

    // Turn block-local positions into global ones: the scanned histogram gives the
    // first slot of (digit, block); subtract where the digit starts inside the block.
    if (lid as usize) < BUCKETS {
        let global = scanned_histogram[(lid * params.block_count + block.x) as usize];
        digit_base[lid as usize] = global.wrapping_sub(counters[lid as usize * WG]);
    }
    barrier();

    let column = lid as usize;
    let base = block.x * SORT_BLOCK_LEN + lid * SORT_ITEMS_PER_THREAD;
    let mut i = 0;
    while i < SORT_ITEMS_PER_THREAD {
        let idx = base + i;
        if idx < len {
            let key = keys_in[idx as usize];
            let d = digit(key, params) as usize;
            let slot = d * WG + column;
            let dst = digit_base[d].wrapping_add(counters[slot]) as usize;
            counters[slot] += 1;
            keys_out[dst] = key;
            values_out[dst] = values_in[idx as usize];
        }
        i += 1;
    }
}

const _: () = assert!(CHUNK_WORKGROUP_SIZE == 8);

/// Invocation `lid`'s chunk of this pass: its number and the keys `start..end` it walks.
fn own_chunk(
    params: &SortPassParams,
    len_words: &[u32],
    group: UVec3,
    lid: u32,
) -> (u32, u32, u32) {
    let chunk = group.x * CHUNK_WORKGROUP_SIZE + lid;
    let (start, end) = chunk_range(keys_to_sort(params, len_words), params.block_count, chunk);
    (chunk, start, end)
}

/// Where a chunk pass reads its pairs: the caller's separate key and value buffers, or
/// the sort's scratch of interleaved (key, value) pairs, each as storage buffers or
/// through texel views. On llvmpipe every storage-buffer load or store whose address is
/// not uniform is a loop over the lanes, one loop per 32-bit component, where a texel
/// fetch is a branch-free gather; so the kernels read through texel views wherever the
/// engine can bind them, and interleaved pairs make the scatter's stores go to one
/// stream of cache lines per digit instead of two.
trait PairSource {
    fn key(&self, i: u32) -> u32;
    fn pair(&self, i: u32) -> UVec2;
    /// The keys `i .. i + 4`, `i` a multiple of 4 (one or two fetches where texels hold
    /// them together).
    #[inline]
    fn four_keys(&self, i: u32) -> UVec4 {
        UVec4::new(
            self.key(i),
            self.key(i + 1),
            self.key(i + 2),
            self.key(i + 3),
        )
    }
    /// The pairs `i .. i + 4`, `i` a multiple of 4: their keys and their values (see
    /// [`four_keys`](Self::four_keys)).
    #[inline]
    fn four_pairs(&self, i: u32) -> (UVec4, UVec4) {
        let (a, b, c, d) = (
            self.pair(i),
            self.pair(i + 1),
            self.pair(i + 2),
            self.pair(i + 3),
        );
        (
            UVec4::new(a.x, b.x, c.x, d.x),
            UVec4::new(a.y, b.y, c.y, d.y),
        )
    }
}

/// Where a chunk scatter writes its pairs (see [`PairSource`]).
trait PairSink {
    fn put(&mut self, i: u32, pair: UVec2);
}

/// Separate key and value buffers.
struct Split<'a> {
    keys: &'a [u32],
    values: &'a [u32],
}

/// Separate key and value buffers, written.
struct SplitMut<'a> {
    keys: &'a mut [u32],
    values: &'a mut [u32],
}

/// Interleaved pairs.
struct Pairs<'a>(&'a [UVec2]);

/// Interleaved pairs, written.
struct PairsMut<'a>(&'a mut [UVec2]);

/// Separate key and value buffers read through their `R32G32B32A32_SFLOAT` views, four
/// elements a fetch, bit for bit (a fetch moves the bits; nothing does arithmetic on
/// them). The engine makes every buffer in whole 16-byte texels, so the view reaches
/// the last element.
struct TexelSplit<'a> {
    keys: &'a TexelBuffer4,
    values: &'a TexelBuffer4,
}

/// Component `k` (0-3) of `texel`'s bits.
#[inline]
fn component_bits(texel: Vec4, k: u32) -> u32 {
    let bits = if k == 0 {
        texel.x
    } else if k == 1 {
        texel.y
    } else if k == 2 {
        texel.z
    } else {
        texel.w
    };
    bits.to_bits()
}

/// All four components' bits.
#[inline]
fn texel_bits(texel: Vec4) -> UVec4 {
    UVec4::new(
        texel.x.to_bits(),
        texel.y.to_bits(),
        texel.z.to_bits(),
        texel.w.to_bits(),
    )
}

/// Interleaved pairs read through their `R32G32B32A32_SFLOAT` view: two pairs a texel.
struct TexelPairs<'a>(&'a TexelBuffer4);

impl PairSource for Split<'_> {
    #[inline]
    fn key(&self, i: u32) -> u32 {
        self.keys[i as usize]
    }
    #[inline]
    fn pair(&self, i: u32) -> UVec2 {
        UVec2::new(self.keys[i as usize], self.values[i as usize])
    }
}

impl PairSource for Pairs<'_> {
    #[inline]
    fn key(&self, i: u32) -> u32 {
        self.0[i as usize].x
    }
    #[inline]
    fn pair(&self, i: u32) -> UVec2 {
        self.0[i as usize]
    }
}

impl PairSource for TexelSplit<'_> {
    #[inline]
    fn key(&self, i: u32) -> u32 {
        component_bits(fetch4(self.keys, i >> 2), i & 3)
    }
    #[inline]
    fn pair(&self, i: u32) -> UVec2 {
        UVec2::new(
            self.key(i),
            component_bits(fetch4(self.values, i >> 2), i & 3),
        )
    }
    #[inline]
    fn four_keys(&self, i: u32) -> UVec4 {
        texel_bits(fetch4(self.keys, i >> 2))
    }
    #[inline]
    fn four_pairs(&self, i: u32) -> (UVec4, UVec4) {
        (
            texel_bits(fetch4(self.keys, i >> 2)),
            texel_bits(fetch4(self.values, i >> 2)),
        )
    }
}

impl PairSource for TexelPairs<'_> {
    #[inline]
    fn key(&self, i: u32) -> u32 {
        self.pair(i).x
    }
    #[inline]
    fn pair(&self, i: u32) -> UVec2 {
        let texel = fetch4(self.0, i >> 1);
        if i & 1 == 0 {
            UVec2::new(texel.x.to_bits(), texel.y.to_bits())
        } else {
            UVec2::new(texel.z.to_bits(), texel.w.to_bits())
        }
    }
    #[inline]
    fn four_keys(&self, i: u32) -> UVec4 {
        let (a, b) = (fetch4(self.0, i >> 1), fetch4(self.0, (i >> 1) + 1));
        UVec4::new(a.x.to_bits(), a.z.to_bits(), b.x.to_bits(), b.z.to_bits())
    }
    #[inline]
    fn four_pairs(&self, i: u32) -> (UVec4, UVec4) {
        let (a, b) = (fetch4(self.0, i >> 1), fetch4(self.0, (i >> 1) + 1));
        (
            UVec4::new(a.x.to_bits(), a.z.to_bits(), b.x.to_bits(), b.z.to_bits()),
            UVec4::new(a.y.to_bits(), a.w.to_bits(), b.y.to_bits(), b.w.to_bits()),
        )
    }
}

impl PairSink for SplitMut<'_> {
    #[inline]
    fn put(&mut self, i: u32, pair: UVec2) {
        self.keys[i as usize] = pair.x;
        self.values[i as usize] = pair.y;
    }
}

impl PairSink for PairsMut<'_> {
    #[inline]
    fn put(&mut self, i: u32, pair: UVec2) {
        self.0[i as usize] = pair;
    }
}

// The counters of a chunk walk live in a function-local array, not workgroup memory:
// llvmpipe keeps such an array per lane on the stack and reads and writes it with
// unrolled per-lane moves, where a workgroup-memory access with a non-uniform index is a
// loop over the lanes with a branch per lane. Each invocation owns its chunk's counters
// either way, so nothing is shared and there are no barriers.

/// Counts invocation `lid`'s chunk of `src` and writes `histogram[digit * chunks + chunk]`.
#[inline]
fn count_chunk<S: PairSource>(
    params: &SortPassParams,
    len_words: &[u32],
    group: UVec3,
    lid: u32,
    src: &S,
    histogram: &mut [u32],
) {
    let (chunk, start, end) = own_chunk(params, len_words, group, lid);
    let chunks = params.block_count as usize;
    // The digit's shift and mask copied once per walk: read through the push-constant
    // pointer, llvmpipe's code loads them for every key (seen in its disassembly; the
    // time saved is within this machine's noise).
    let pass = SortPassParams { ..*params };
    let mut counts = [0u32; CHUNK_BUCKETS as usize];
    // Four keys a step from positions that are multiples of 4, so that texels are
    // fetched whole (`four_keys`); the keys before the first such position and after the
    // last whole four go one at a time.
    let mut i = start;
    while i < end && i & 3 != 0 {
        counts[digit(src.key(i), &pass) as usize] += 1;
        i += 1;
    }
    while i + 3 < end {
        let k = src.four_keys(i);
        counts[digit(k.x, &pass) as usize] += 1;
        counts[digit(k.y, &pass) as usize] += 1;
        counts[digit(k.z, &pass) as usize] += 1;
        counts[digit(k.w, &pass) as usize] += 1;
        i += 4;
    }
    while i < end {
        counts[digit(src.key(i), &pass) as usize] += 1;
        i += 1;
    }
    let mut d = 0;
    while d < CHUNK_BUCKETS as usize {
        histogram[d * chunks + chunk as usize] = counts[d];
        d += 1;
    }
}

/// Moves every pair of invocation `lid`'s chunk of `src` to its place in `dst` for
/// this digit, in order: the scanned histogram gives the chunk's first slot per digit,
/// and the chunk's own counters count on from there.
#[inline]
#[allow(clippy::too_many_arguments)]
fn scatter_chunk<S: PairSource, D: PairSink>(
    params: &SortPassParams,
    len_words: &[u32],
    group: UVec3,
    lid: u32,
    scanned_histogram: &[u32],
    src: &S,
    dst: &mut D,
) {
    let (chunk, start, end) = own_chunk(params, len_words, group, lid);
    let chunks = params.block_count as usize;
    let mut next = [0u32; CHUNK_BUCKETS as usize];
    let mut d = 0;
    while d < CHUNK_BUCKETS as usize {
        next[d] = scanned_histogram[d * chunks + chunk as usize];
        d += 1;
    }
    let pass = SortPassParams { ..*params }; // see `count_chunk`
    macro_rules! place {
        ($pair:expr) => {{
            let pair = $pair;
            let d = digit(pair.x, &pass) as usize;
            let at = next[d];
            next[d] = at + 1;
            dst.put(at, pair);
        }};
    }
    // Four pairs a step, as `count_chunk` walks.
    let mut i = start;
    while i < end && i & 3 != 0 {
        place!(src.pair(i));
        i += 1;
    }
    while i + 3 < end {
        let (k, v) = src.four_pairs(i);
        place!(UVec2::new(k.x, v.x));
        place!(UVec2::new(k.y, v.y));
        place!(UVec2::new(k.z, v.z));
        place!(UVec2::new(k.w, v.w));
        i += 4;
    }
    while i < end {
        place!(src.pair(i));
        i += 1;
    }
}

/// `histogram[digit * chunks + chunk]` = how many keys of chunk `chunk` have `digit`;
/// `params.block_count` is the chunk count, a multiple of 8, dispatched as
/// `chunks / 8` workgroups. Each invocation counts its own chunk.
#[spirv(compute(threads(8)))]
pub fn chunk_histogram(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] keys: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] histogram: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] len_words: &[u32],
) {
    count_chunk(
        params,
        len_words,
        group,
        lid,
        &Split { keys, values: keys },
        histogram,
    );
}

/// [`chunk_histogram`] reading the keys through a texel view.
#[spirv(compute(threads(8)))]
pub fn chunk_histogram_texel(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(descriptor_set = 0, binding = 0)] keys: &TexelBuffer4,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] histogram: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] len_words: &[u32],
) {
    count_chunk(
        params,
        len_words,
        group,
        lid,
        &TexelSplit { keys, values: keys },
        histogram,
    );
}

/// [`chunk_histogram`] of interleaved pairs (the passes after the first).
#[spirv(compute(threads(8)))]
pub fn chunk_histogram_pairs(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pairs: &[UVec2],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] histogram: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] len_words: &[u32],
) {
    count_chunk(params, len_words, group, lid, &Pairs(pairs), histogram);
}

/// [`chunk_histogram_pairs`] reading through a texel view.
#[spirv(compute(threads(8)))]
pub fn chunk_histogram_pairs_texel(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(descriptor_set = 0, binding = 0)] pairs: &TexelBuffer4,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] histogram: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] len_words: &[u32],
) {
    count_chunk(params, len_words, group, lid, &TexelPairs(pairs), histogram);
}

/// One pass from separate buffers to separate buffers (a sort of one pass).
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(8)))]
pub fn chunk_scatter(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] keys_in: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] values_in: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] scanned_histogram: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] keys_out: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] values_out: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] len_words: &[u32],
) {
    let src = Split {
        keys: keys_in,
        values: values_in,
    };
    let mut dst = SplitMut {
        keys: keys_out,
        values: values_out,
    };
    scatter_chunk(
        params,
        len_words,
        group,
        lid,
        scanned_histogram,
        &src,
        &mut dst,
    );
}

/// [`chunk_scatter`] reading keys and values through texel views (a sort of one pass:
/// on llvmpipe two gathers a step of four pairs where storage loads are two loops over
/// the lanes a pair).
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(8)))]
pub fn chunk_scatter_texel(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(descriptor_set = 0, binding = 0)] keys_in: &TexelBuffer4,
    #[spirv(descriptor_set = 0, binding = 1)] values_in: &TexelBuffer4,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] scanned_histogram: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] keys_out: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] values_out: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] len_words: &[u32],
) {
    let src = TexelSplit {
        keys: keys_in,
        values: values_in,
    };
    let mut dst = SplitMut {
        keys: keys_out,
        values: values_out,
    };
    scatter_chunk(
        params,
        len_words,
        group,
        lid,
        scanned_histogram,
        &src,
        &mut dst,
    );
}

/// The first pass of a longer sort: separate buffers in, interleaved pairs out.
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(8)))]
pub fn chunk_scatter_zip(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] keys_in: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] values_in: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] scanned_histogram: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] pairs_out: &mut [UVec2],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] len_words: &[u32],
) {
    let src = Split {
        keys: keys_in,
        values: values_in,
    };
    scatter_chunk(
        params,
        len_words,
        group,
        lid,
        scanned_histogram,
        &src,
        &mut PairsMut(pairs_out),
    );
}

/// [`chunk_scatter_zip`] reading keys and values through texel views.
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(8)))]
pub fn chunk_scatter_zip_texel(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(descriptor_set = 0, binding = 0)] keys_in: &TexelBuffer4,
    #[spirv(descriptor_set = 0, binding = 1)] values_in: &TexelBuffer4,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] scanned_histogram: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] pairs_out: &mut [UVec2],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] len_words: &[u32],
) {
    let src = TexelSplit {
        keys: keys_in,
        values: values_in,
    };
    scatter_chunk(
        params,
        len_words,
        group,
        lid,
        scanned_histogram,
        &src,
        &mut PairsMut(pairs_out),
    );
}

/// A middle pass: interleaved pairs in and out.
#[spirv(compute(threads(8)))]
pub fn chunk_scatter_pairs(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pairs_in: &[UVec2],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] scanned_histogram: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] pairs_out: &mut [UVec2],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] len_words: &[u32],
) {
    scatter_chunk(
        params,
        len_words,
        group,
        lid,
        scanned_histogram,
        &Pairs(pairs_in),
        &mut PairsMut(pairs_out),
    );
}

/// [`chunk_scatter_pairs`] reading through a texel view.
#[spirv(compute(threads(8)))]
pub fn chunk_scatter_pairs_texel(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(descriptor_set = 0, binding = 0)] pairs_in: &TexelBuffer4,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] scanned_histogram: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] pairs_out: &mut [UVec2],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] len_words: &[u32],
) {
    scatter_chunk(
        params,
        len_words,
        group,
        lid,
        scanned_histogram,
        &TexelPairs(pairs_in),
        &mut PairsMut(pairs_out),
    );
}

/// The last pass of a longer sort: interleaved pairs in, the caller's separate buffers out.
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(8)))]
pub fn chunk_scatter_unzip(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pairs_in: &[UVec2],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] scanned_histogram: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] keys_out: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] values_out: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] len_words: &[u32],
) {
    let mut dst = SplitMut {
        keys: keys_out,
        values: values_out,
    };
    scatter_chunk(
        params,
        len_words,
        group,
        lid,
        scanned_histogram,
        &Pairs(pairs_in),
        &mut dst,
    );
}

/// [`chunk_scatter_unzip`] reading through a texel view.
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(8)))]
pub fn chunk_scatter_unzip_texel(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(descriptor_set = 0, binding = 0)] pairs_in: &TexelBuffer4,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] scanned_histogram: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] keys_out: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] values_out: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] len_words: &[u32],
) {
    let mut dst = SplitMut {
        keys: keys_out,
        values: values_out,
    };
    scatter_chunk(
        params,
        len_words,
        group,
        lid,
        scanned_histogram,
        &TexelPairs(pairs_in),
        &mut dst,
    );
}

/// Interleaved pairs written as one `u64` each (key in the low half: the same bytes as
/// a `UVec2`), so that llvmpipe runs one loop over the lanes per store instead of two.
#[cfg(feature = "int64")]
struct Pairs64Mut<'a>(&'a mut [u64]);

#[cfg(feature = "int64")]
impl PairSink for Pairs64Mut<'_> {
    #[inline]
    fn put(&mut self, i: u32, pair: UVec2) {
        self.0[i as usize] = (u64::from(pair.y) << 32) | u64::from(pair.x);
    }
}

/// [`chunk_scatter_zip_texel`] storing each pair as one `u64`.
#[cfg(feature = "int64")]
#[allow(clippy::too_many_arguments)]
#[spirv(compute(threads(8)))]
pub fn chunk_scatter_zip_texel_u64(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(descriptor_set = 0, binding = 0)] keys_in: &TexelBuffer4,
    #[spirv(descriptor_set = 0, binding = 1)] values_in: &TexelBuffer4,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] scanned_histogram: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] pairs_out: &mut [u64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] len_words: &[u32],
) {
    let src = TexelSplit {
        keys: keys_in,
        values: values_in,
    };
    scatter_chunk(
        params,
        len_words,
        group,
        lid,
        scanned_histogram,
        &src,
        &mut Pairs64Mut(pairs_out),
    );
}

/// [`chunk_scatter_pairs_texel`] storing each pair as one `u64`.
#[cfg(feature = "int64")]
#[spirv(compute(threads(8)))]
pub fn chunk_scatter_pairs_texel_u64(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(push_constant)] params: &SortPassParams,
    #[spirv(descriptor_set = 0, binding = 0)] pairs_in: &TexelBuffer4,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] scanned_histogram: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] pairs_out: &mut [u64],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] len_words: &[u32],
) {
    scatter_chunk(
        params,
        len_words,
        group,
        lid,
        scanned_histogram,
        &TexelPairs(pairs_in),
        &mut Pairs64Mut(pairs_out),
    );
}
