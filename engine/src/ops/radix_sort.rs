//! Stable LSD radix sort of `u32` keys with `u32` values, in two variants of the same
//! three steps ([`SortVariant`]): kernels `radix_sort::histogram` / `radix_sort::scatter`
//! (blocks ranked by a workgroup scan: GPUs) or `radix_sort::chunk_histogram` /
//! `radix_sort::chunk_scatter` (long runs walked by one invocation each: CPU devices),
//! and the scan op for the histogram.
//!
//! One pass per digit (4 bits in blocks, 8 in chunks) of the low `key_bits` bits:
//! histogram, scan of the digit-major histogram, scatter into the other buffers (the
//! recorder derives the barriers between them). Blocks ping-pong between the caller's
//! buffers and the plan's scratch, and an odd number of passes ends with a copy back.
//! Chunks of two passes or more keep the pairs interleaved between the first pass and
//! the last (`radix_sort::chunk_scatter_zip`, `chunk_scatter_pairs`,
//! `chunk_scatter_unzip`), which halves the loads and stores per pair on llvmpipe; a
//! chunked sort of one pass, or of more pairs than one binding of pairs holds, keeps
//! them apart as blocks do. Chunk passes read through texel views where the buffers
//! allow it (the `_texel` kernels, through 4-float views: four keys, or two interleaved
//! pairs, a fetch; a gather on llvmpipe, where a storage-buffer load is a loop over the
//! lanes per component) and, on devices with `shaderInt64`, store
//! each pair as one u64 (`_texel_u64`: one store loop instead of two). The result is always
//! in the caller's buffers. No workgroup waits on another; no subgroup size is assumed.
//! CPU reference: a stable sort by `drape_shared::radix_sort::significant_bits`.

use drape_shared::radix_sort::{
    self, chunk_count, chunk_pass_count, chunk_pass_params, pass_count, pass_params,
    SortPassParams, CHUNK_BUCKETS, CHUNK_WORKGROUP_SIZE, RADIX_BUCKETS, SORT_BLOCK_LEN,
};

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::{EngineError, Result};
use crate::kernels;
use crate::kernels::radix_sort::{
    ChunkHistogramKernel, ChunkHistogramPairsKernel, ChunkScatterPairsKernel,
    ChunkScatterUnzipKernel, ChunkScatterZipKernel, HistogramKernel, ScatterKernel,
};
use crate::ops::scan::{ExclusiveScan, ScanVariant};
use crate::recorder::Recording;

/// Which kernels a sort records; both give the same (exact, stable) result.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SortVariant {
    /// [`Chunks`](Self::Chunks) on CPU devices, [`Blocks`](Self::Blocks) elsewhere.
    #[default]
    Auto,
    /// Workgroups of 128 invocations rank blocks of 2,048 keys by 4-bit digits with a
    /// workgroup scan: the GPU kernels.
    Blocks,
    /// Each invocation walks one long run of the keys alone (64 runs from 64K keys,
    /// more past 2M, 8 or more below; `drape_shared::chunks`), by 8-bit
    /// digits, with no barriers (`drape_shared::radix_sort::CHUNK_RADIX_BITS` says why
    /// this suits llvmpipe; a GPU would sit mostly idle). Its scratch is two buffers of
    /// interleaved pairs, 16 bytes per key of the plan (blocks: 8), where one binding
    /// holds them.
    Chunks,
}

impl SortVariant {
    /// The variant `Auto` stands for on this device.
    pub fn resolve(self, ctx: &Context) -> Self {
        match self {
            Self::Auto if ctx.info().kind == crate::DeviceKind::Cpu => Self::Chunks,
            Self::Auto => Self::Blocks,
            chosen => chosen,
        }
    }
}

/// A planned sort: scratch and histogram for lengths up to `max_len`.
pub struct RadixSort {
    max_len: u32,
    variant: SortVariant,
    /// The scratch keys and values, or, where `interleaved`, two buffers of
    /// interleaved (key, value) pairs (`8 * max_len` bytes each) that the chunked
    /// passes between the first and the last ping-pong through (a sort of one pass
    /// uses them as keys and values).
    scratch: [Buffer; 2],
    /// Whether the chunked passes keep the pairs interleaved: chunks, and pair buffers
    /// that one binding can hold (lavapipe binds 128 MiB, 16.7M pairs; larger plans
    /// keep keys and values apart, as the block variant does).
    interleaved: bool,
    histogram: Buffer,
    histogram_scan: ExclusiveScan,
    /// Whether the chunked passes may read through texel views (always, but for tests
    /// of the storage-buffer kernels that buffers past the texel limits fall back to).
    texel_reads: bool,
    /// Whether the chunked passes may store pairs as one u64 each (where the device has
    /// `shaderInt64`; off for tests of the kernels other devices run).
    int64_stores: bool,
}

impl RadixSort {
    /// Largest length one plan accepts (the workgroup-count limit of the sort kernels).
    pub const LIMIT: u32 = 65_535 * SORT_BLOCK_LEN;

    /// Plans sorts of up to `max_len` pairs with the device's variant.
    pub fn new(ctx: &Context, max_len: u32) -> Result<Self> {
        Self::with_variant(ctx, max_len, SortVariant::Auto)
    }

    /// Plans sorts of up to `max_len` pairs with the given kernels.
    pub fn with_variant(ctx: &Context, max_len: u32, variant: SortVariant) -> Result<Self> {
        if max_len > Self::LIMIT {
            return Err(EngineError::too_large(
                "keys to sort",
                max_len.into(),
                Self::LIMIT.into(),
                "the radix sort (65,535 workgroups of its block)",
            ));
        }
        let variant = variant.resolve(ctx);
        let bytes = u64::from(max_len) * 4;
        let histogram_len = match variant {
            SortVariant::Chunks => CHUNK_BUCKETS * chunk_count(max_len),
            _ => RADIX_BUCKETS * radix_sort::block_count(max_len),
        };
        // Whole 16-byte texels, so that a 4-float texel view covers every pair.
        let pair_bytes = (2 * bytes).next_multiple_of(16);
        let interleaved =
            variant == SortVariant::Chunks && pair_bytes <= ctx.info().max_storage_buffer_range;
        let scratch = match interleaved {
            true => [
                ctx.create_buffer(
                    "radix_sort pairs scratch a",
                    BufferDesc::gpu_only(pair_bytes),
                )?,
                ctx.create_buffer(
                    "radix_sort pairs scratch b",
                    BufferDesc::gpu_only(pair_bytes),
                )?,
            ],
            false => [
                ctx.create_buffer("radix_sort keys scratch", BufferDesc::gpu_only(bytes))?,
                ctx.create_buffer("radix_sort values scratch", BufferDesc::gpu_only(bytes))?,
            ],
        };
        Ok(Self {
            max_len,
            variant,
            scratch,
            interleaved,
            histogram: ctx.create_buffer(
                "radix_sort histogram",
                BufferDesc::gpu_only(u64::from(histogram_len) * 4),
            )?,
            // The scan of the same family, so that each variant is the whole of itself.
            histogram_scan: ExclusiveScan::with_variant(
                ctx,
                "radix_sort.scan",
                histogram_len,
                if variant == SortVariant::Chunks {
                    ScanVariant::Chunks
                } else {
                    ScanVariant::Blocks
                },
            )?,
            texel_reads: true,
            int64_stores: ctx.info().shader_int64,
        })
    }

    /// The same plan reading only through storage buffers: the chunk kernels a sort
    /// falls back to where its buffers are past the device's texel-buffer limits (for
    /// tests; the result is the same).
    #[doc(hidden)]
    pub fn without_texel_reads(mut self) -> Self {
        self.texel_reads = false;
        self
    }

    /// The same plan storing each pair as two u32s, as on devices without `shaderInt64`
    /// (for tests; the result is the same).
    #[doc(hidden)]
    pub fn without_int64_stores(mut self) -> Self {
        self.int64_stores = false;
        self
    }

    /// The most pairs one sort may have.
    pub fn max_len(&self) -> u32 {
        self.max_len
    }

    /// The kernels this plan records (never `Auto`).
    pub fn variant(&self) -> SortVariant {
        self.variant
    }

    /// Records a stable sort of the first `len` (key, value) pairs by the low
    /// `key_bits` bits of the keys, in place.
    pub fn record<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        keys: &'a Buffer,
        values: &'a Buffer,
        len: u32,
        key_bits: u32,
    ) -> Result<()> {
        self.record_sort(rec, keys, values, len, None, key_bits)
    }

    /// Records a stable sort whose length the GPU computed: the first
    /// `min(count, capacity)` pairs, where `count` is the little-endian u64 in the
    /// first two words of `count_words`, written by an earlier command of the same
    /// recording. The passes are sized for `capacity`, so no host read of the count
    /// sits inside the frame: with blocks, workgroups past the count do nothing; with
    /// chunks, the kernels divide the count over the capacity's chunks. The pairs past the
    /// count are scratch afterwards (an odd number of passes copies the whole capacity back).
    pub fn record_bounded<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        keys: &'a Buffer,
        values: &'a Buffer,
        capacity: u32,
        count_words: &'a Buffer,
        key_bits: u32,
    ) -> Result<()> {
        assert!(
            count_words.size >= 8,
            "the count of a bounded sort is two u32 words ('{}' has {} bytes)",
            count_words.name(),
            count_words.size
        );
        self.record_sort(rec, keys, values, capacity, Some(count_words), key_bits)
    }

    fn record_sort<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        keys: &'a Buffer,
        values: &'a Buffer,
        len: u32,
        count_words: Option<&'a Buffer>,
        key_bits: u32,
    ) -> Result<()> {
        assert!(
            key_bits <= 32,
            "key_bits must be at most 32, got {key_bits}"
        );
        if len > self.max_len {
            return Err(EngineError::too_large(
                "keys to sort",
                len.into(),
                self.max_len.into(),
                "the sort's plan",
            ));
        }
        let bytes = u64::from(len) * 4;
        assert!(
            bytes <= keys.size && bytes <= values.size,
            "sort of {len} pairs in buffers of {} and {} bytes",
            keys.size,
            values.size
        );
        if len <= 1 {
            return Ok(());
        }
        let chunked = self.variant == SortVariant::Chunks;
        let passes = if chunked {
            chunk_pass_count(key_bits)
        } else {
            pass_count(key_bits)
        };
        if self.interleaved && passes >= 2 {
            return self.record_chunk_passes(rec, keys, values, len, count_words, key_bits, passes);
        }
        let (histogram, scatter, buckets, blocks, groups) = if chunked {
            let chunks = chunk_count(len);
            (
                HistogramKernel::RadixSortChunkHistogram,
                ScatterKernel::RadixSortChunkScatter,
                CHUNK_BUCKETS,
                chunks,
                chunks / CHUNK_WORKGROUP_SIZE,
            )
        } else {
            let blocks = radix_sort::block_count(len);
            (
                HistogramKernel::RadixSortHistogram,
                ScatterKernel::RadixSortScatter,
                RADIX_BUCKETS,
                blocks,
                blocks,
            )
        };
        let max_texels = rec.context().info().max_texel_buffer_elements;
        let mut src = (keys, values);
        let mut dst = (&self.scratch[0], &self.scratch[1]);
        for pass in 0..passes {
            let params = if chunked {
                chunk_pass_params(len, key_bits, pass)
            } else {
                pass_params(len, key_bits, pass)
            };
            let params = SortPassParams {
                bounded: u32::from(count_words.is_some()),
                ..params
            };
            // Unread when unbounded; the keys stand in for the binding.
            let len_words = count_words.unwrap_or(src.0);
            // A chunked sort of one pass reads through texel views where its inputs
            // allow them (as `record_chunk_passes` does); chunked sorts of several
            // passes land here only past one binding of pairs (16.7M on lavapipe), too
            // large for the tests, so they keep the storage kernels they were tested with.
            let texel = chunked
                && passes == 1
                && self.texel_reads
                && src.0.texel_readable(max_texels)
                && src.1.texel_readable(max_texels);
            let (histogram, scatter) = match texel {
                true => (
                    HistogramKernel::RadixSortChunkHistogramTexel,
                    ScatterKernel::RadixSortChunkScatterTexel,
                ),
                false => (histogram, scatter),
            };
            rec.dispatch_as(
                "radix_sort.histogram",
                histogram,
                kernels::radix_sort::Histogram {
                    keys: src.0.read(),
                    histogram: self.histogram.write(),
                    len_words: len_words.read(),
                },
                &params,
                [groups, 1, 1],
            )?;
            self.histogram_scan
                .record(rec, &self.histogram, buckets * blocks)?;
            rec.dispatch_as(
                "radix_sort.scatter",
                scatter,
                kernels::radix_sort::Scatter {
                    keys_in: src.0.read(),
                    values_in: src.1.read(),
                    scanned_histogram: self.histogram.read(),
                    keys_out: dst.0.write(),
                    values_out: dst.1.write(),
                    len_words: len_words.read(),
                },
                &params,
                [groups, 1, 1],
            )?;
            std::mem::swap(&mut src, &mut dst);
        }
        if passes % 2 == 1 {
            rec.copy(src.0, keys, bytes);
            rec.copy(src.1, values, bytes);
        }
        Ok(())
    }

    /// The chunked variant's sorts of two passes or more: the first pass zips the
    /// caller's keys and values into interleaved pairs, the middle ones move pairs
    /// between the two scratch buffers, and the last unzips into the caller's buffers
    /// (so no copy back). On llvmpipe a pair is then one load and one store instead of
    /// two of each, and the scatter writes one stream per digit instead of two.
    #[allow(clippy::too_many_arguments)]
    fn record_chunk_passes<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        keys: &'a Buffer,
        values: &'a Buffer,
        len: u32,
        count_words: Option<&'a Buffer>,
        key_bits: u32,
        passes: u32,
    ) -> Result<()> {
        let chunks = chunk_count(len);
        let groups = [chunks / CHUNK_WORKGROUP_SIZE, 1, 1];
        // Texel views where the buffers allow them (see `radix_sort::PairSource` in the
        // kernels): the caller's keys and values for the first pass, the scratch pairs
        // for the others.
        let max_texels = rec.context().info().max_texel_buffer_elements;
        let texel_inputs = self.texel_reads
            && keys.texel_readable(max_texels)
            && values.texel_readable(max_texels);
        let texel_pairs = self.texel_reads
            && self
                .scratch
                .iter()
                .all(|b| b.texel_readable(max_texels) && b.vk_size() % 16 == 0);
        let mut pairs = (&self.scratch[0], &self.scratch[1]);
        for pass in 0..passes {
            let params = SortPassParams {
                bounded: u32::from(count_words.is_some()),
                ..chunk_pass_params(len, key_bits, pass)
            };
            let (first, last) = (pass == 0, pass + 1 == passes);
            // Unread when unbounded; the pass's input stands in for the binding.
            let len_words = count_words.unwrap_or(if first { keys } else { pairs.0 });
            if first {
                let histogram = if texel_inputs {
                    ChunkHistogramKernel::RadixSortChunkHistogramTexel
                } else {
                    ChunkHistogramKernel::RadixSortChunkHistogram
                };
                let b = kernels::radix_sort::ChunkHistogram {
                    keys: keys.read(),
                    histogram: self.histogram.write(),
                    len_words: len_words.read(),
                };
                rec.dispatch_as("radix_sort.histogram", histogram, b, &params, groups)?;
            } else {
                let histogram = if texel_pairs {
                    ChunkHistogramPairsKernel::RadixSortChunkHistogramPairsTexel
                } else {
                    ChunkHistogramPairsKernel::RadixSortChunkHistogramPairs
                };
                let b = kernels::radix_sort::ChunkHistogramPairs {
                    pairs: pairs.0.read(),
                    histogram: self.histogram.write(),
                    len_words: len_words.read(),
                };
                rec.dispatch_as("radix_sort.histogram", histogram, b, &params, groups)?;
            }
            self.histogram_scan
                .record(rec, &self.histogram, CHUNK_BUCKETS * chunks)?;
            let scanned_histogram = self.histogram.read();
            if first {
                let kernel = match (texel_inputs, self.int64_stores) {
                    (true, true) => ChunkScatterZipKernel::RadixSortChunkScatterZipTexelU64,
                    (true, false) => ChunkScatterZipKernel::RadixSortChunkScatterZipTexel,
                    (false, _) => ChunkScatterZipKernel::RadixSortChunkScatterZip,
                };
                let b = kernels::radix_sort::ChunkScatterZip {
                    keys_in: keys.read(),
                    values_in: values.read(),
                    pairs_out: pairs.0.write(),
                    scanned_histogram,
                    len_words: len_words.read(),
                };
                rec.dispatch_as("radix_sort.scatter_zip", kernel, b, &params, groups)?;
            } else if last {
                let kernel = if texel_pairs {
                    ChunkScatterUnzipKernel::RadixSortChunkScatterUnzipTexel
                } else {
                    ChunkScatterUnzipKernel::RadixSortChunkScatterUnzip
                };
                let b = kernels::radix_sort::ChunkScatterUnzip {
                    pairs_in: pairs.0.read(),
                    keys_out: keys.write(),
                    values_out: values.write(),
                    scanned_histogram,
                    len_words: len_words.read(),
                };
                rec.dispatch_as("radix_sort.scatter_unzip", kernel, b, &params, groups)?;
            } else {
                let kernel = match (texel_pairs, self.int64_stores) {
                    (true, true) => ChunkScatterPairsKernel::RadixSortChunkScatterPairsTexelU64,
                    (true, false) => ChunkScatterPairsKernel::RadixSortChunkScatterPairsTexel,
                    (false, _) => ChunkScatterPairsKernel::RadixSortChunkScatterPairs,
                };
                let b = kernels::radix_sort::ChunkScatterPairs {
                    pairs_in: pairs.0.read(),
                    pairs_out: pairs.1.write(),
                    scanned_histogram,
                    len_words: len_words.read(),
                };
                rec.dispatch_as("radix_sort.scatter_pairs", kernel, b, &params, groups)?;
            }
            if !first {
                std::mem::swap(&mut pairs.0, &mut pairs.1);
            }
        }
        Ok(())
    }
}

/// Sorts host data on the GPU in one submission: upload, sort, read back.
/// For embedding applications and tests; a frame loop keeps a plan and records.
pub fn sort_pairs_host(
    ctx: &Context,
    keys: &[u32],
    values: &[u32],
    key_bits: u32,
) -> Result<(Vec<u32>, Vec<u32>)> {
    sort_pairs_host_with(ctx, SortVariant::Auto, keys, values, key_bits)
}

/// [`sort_pairs_host`] with the given kernels.
pub fn sort_pairs_host_with(
    ctx: &Context,
    variant: SortVariant,
    keys: &[u32],
    values: &[u32],
    key_bits: u32,
) -> Result<(Vec<u32>, Vec<u32>)> {
    assert_eq!(keys.len(), values.len(), "keys and values differ in length");
    let len = u32::try_from(keys.len()).map_err(|_| {
        EngineError::too_large(
            "keys to sort",
            keys.len() as u64,
            RadixSort::LIMIT.into(),
            "the radix sort (65,535 workgroups of its block)",
        )
    })?;
    let mut key_buf = ctx.upload("sort keys", keys)?;
    let mut value_buf = ctx.upload("sort values", values)?;
    let plan = RadixSort::with_variant(ctx, len, variant)?;
    let mut rec = ctx.record("sort_pairs_host")?;
    plan.record(&mut rec, &key_buf, &value_buf, len, key_bits)?;
    rec.submit_and_wait()?;
    Ok((
        ctx.read_buffer(&mut key_buf, keys.len())?,
        ctx.read_buffer(&mut value_buf, values.len())?,
    ))
}
