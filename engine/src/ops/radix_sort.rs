//! Stable LSD radix sort of `u32` keys with `u32` values (kernels `radix_sort::histogram`,
//! `radix_sort::scatter`, and the scan op for the histogram).
//!
//! One pass per `RADIX_BITS`-bit digit of the low `key_bits` bits: histogram, scan of
//! the digit-major histogram, scatter into the other buffer pair (the recorder derives
//! the barriers between them). Passes ping-pong between the caller's buffers and the
//! plan's scratch; an odd number of passes ends with a copy back, so the result is
//! always in the caller's buffers. No workgroup waits on another; no subgroup size is assumed.
//! CPU reference: a stable sort by `drape_shared::radix_sort::significant_bits`.

use drape_shared::radix_sort::{self, pass_count, pass_params, SortPassParams, RADIX_BUCKETS, SORT_BLOCK_LEN};

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::{EngineError, Result};
use crate::kernels::Kernel;
use crate::ops::scan::ExclusiveScan;
use crate::recorder::Recording;

/// A planned sort: scratch keys, values and histogram for lengths up to `max_len`.
pub struct RadixSort {
    max_len: u32,
    keys_scratch: Buffer,
    values_scratch: Buffer,
    histogram: Buffer,
    histogram_scan: ExclusiveScan,
}

impl RadixSort {
    /// Largest length one plan accepts (the workgroup-count limit of the sort kernels).
    pub const LIMIT: u32 = 65_535 * SORT_BLOCK_LEN;

    /// Plans sorts of up to `max_len` pairs.
    pub fn new(ctx: &Context, max_len: u32) -> Result<Self> {
        if max_len > Self::LIMIT {
            return Err(EngineError::too_large("keys to sort", max_len.into(), Self::LIMIT.into(), "the radix sort (65,535 workgroups of its block)"));
        }
        let bytes = u64::from(max_len) * 4;
        let histogram_len = RADIX_BUCKETS * radix_sort::block_count(max_len);
        Ok(Self {
            max_len,
            keys_scratch: ctx.create_buffer("radix_sort keys scratch", BufferDesc::gpu_only(bytes))?,
            values_scratch: ctx.create_buffer("radix_sort values scratch", BufferDesc::gpu_only(bytes))?,
            histogram: ctx.create_buffer("radix_sort histogram", BufferDesc::gpu_only(u64::from(histogram_len) * 4))?,
            histogram_scan: ExclusiveScan::new(ctx, "radix_sort.scan", histogram_len)?,
        })
    }

    pub fn max_len(&self) -> u32 {
        self.max_len
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
    /// recording. The passes are sized for `capacity`; workgroups past the count do
    /// nothing, so no host read of the count sits inside the frame.
    pub fn record_bounded<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        keys: &'a Buffer,
        values: &'a Buffer,
        capacity: u32,
        count_words: &'a Buffer,
        key_bits: u32,
    ) -> Result<()> {
        assert!(count_words.size >= 8, "the count of a bounded sort is two u32 words ('{}' has {} bytes)", count_words.name(), count_words.size);
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
        assert!(key_bits <= 32, "key_bits must be at most 32, got {key_bits}");
        if len > self.max_len {
            return Err(EngineError::too_large("keys to sort", len.into(), self.max_len.into(), "the sort's plan"));
        }
        let bytes = u64::from(len) * 4;
        assert!(bytes <= keys.size && bytes <= values.size, "sort of {len} pairs in buffers of {} and {} bytes", keys.size, values.size);
        if len <= 1 {
            return Ok(());
        }
        let passes = pass_count(key_bits);
        let blocks = radix_sort::block_count(len);
        let mut src = (keys, values);
        let mut dst = (&self.keys_scratch, &self.values_scratch);
        for pass in 0..passes {
            let params = SortPassParams { bounded: u32::from(count_words.is_some()), ..pass_params(len, key_bits, pass) };
            // Unread when unbounded; the keys stand in for the binding.
            let len_words = count_words.unwrap_or(src.0);
            rec.pass("radix_sort.histogram", Kernel::RadixSortHistogram)
                .read("keys", src.0)
                .write("histogram", &self.histogram)
                .read("len_words", len_words)
                .push(&params)
                .dispatch([blocks, 1, 1])?;
            self.histogram_scan.record(rec, &self.histogram, RADIX_BUCKETS * blocks)?;
            rec.pass("radix_sort.scatter", Kernel::RadixSortScatter)
                .read("keys_in", src.0)
                .read("values_in", src.1)
                .read("scanned_histogram", &self.histogram)
                .write("keys_out", dst.0)
                .write("values_out", dst.1)
                .read("len_words", len_words)
                .push(&params)
                .dispatch([blocks, 1, 1])?;
            std::mem::swap(&mut src, &mut dst);
        }
        if passes % 2 == 1 {
            rec.copy(src.0, keys, bytes);
            rec.copy(src.1, values, bytes);
        }
        Ok(())
    }
}

/// Sorts host data on the GPU in one submission: upload, sort, read back.
/// For embedding applications and tests; a frame loop keeps a plan and records.
pub fn sort_pairs_host(ctx: &Context, keys: &[u32], values: &[u32], key_bits: u32) -> Result<(Vec<u32>, Vec<u32>)> {
    assert_eq!(keys.len(), values.len(), "keys and values differ in length");
    let len = u32::try_from(keys.len()).map_err(|_| EngineError::too_large("keys to sort", keys.len() as u64, RadixSort::LIMIT.into(), "the radix sort (65,535 workgroups of its block)"))?;
    let mut key_buf = ctx.upload("sort keys", keys)?;
    let mut value_buf = ctx.upload("sort values", values)?;
    let plan = RadixSort::new(ctx, len)?;
    let mut rec = ctx.record("sort_pairs_host")?;
    plan.record(&mut rec, &key_buf, &value_buf, len, key_bits)?;
    rec.submit_and_wait()?;
    Ok((ctx.read_buffer(&mut key_buf, keys.len())?, ctx.read_buffer(&mut value_buf, values.len())?))
}
