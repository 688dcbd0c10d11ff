//! Exclusive prefix sum of `u32` on the GPU (kernels `scan::reduce`, `scan::downsweep`).
//!
//! Reduce-then-scan over levels of `SCAN_BLOCK_LEN`-element blocks: reduce each block
//! to a sum, scan the sums (recursively), then scan each block again starting from its
//! block's offset. Two dispatches per level and one for the top; no workgroup waits on
//! another. In place; wrapping arithmetic; any length up to [`ExclusiveScan::max_len`].
//! CPU reference: `drape_shared::scan::exclusive_scan_in_place`.

use drape_shared::scan::{block_count, ScanParams, SCAN_BLOCK_LEN};

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::{EngineError, Result};
use crate::kernels::Kernel;
use crate::recorder::Recording;

/// A planned scan: the block-sum buffers of every level for lengths up to `max_len`.
pub struct ExclusiveScan {
    max_len: u32,
    /// Block sums of level 1, 2, ... (level 0 is the caller's data).
    level_sums: Vec<Buffer>,
    pass_reduce: String,
    pass_downsweep: String,
}

impl ExclusiveScan {
    /// Largest length one plan accepts: the level-0 dispatch must fit the
    /// 65,535-workgroup limit every Vulkan device guarantees.
    pub const LIMIT: u32 = 65_535 * SCAN_BLOCK_LEN;

    /// Plans scans of up to `max_len` elements; `label` prefixes pass names.
    pub fn new(ctx: &Context, label: &str, max_len: u32) -> Result<Self> {
        if max_len > Self::LIMIT {
            return Err(EngineError::too_large("elements to scan", max_len.into(), Self::LIMIT.into(), "the scan (65,535 workgroups of its block)"));
        }
        let mut level_sums = Vec::new();
        let mut len = max_len;
        while len > SCAN_BLOCK_LEN {
            len = block_count(len);
            let name = format!("{label} level {} sums", level_sums.len() + 1);
            level_sums.push(ctx.create_buffer(&name, BufferDesc::gpu_only(u64::from(len) * 4))?);
        }
        Ok(Self {
            max_len,
            level_sums,
            pass_reduce: format!("{label}.reduce"),
            pass_downsweep: format!("{label}.downsweep"),
        })
    }

    pub fn max_len(&self) -> u32 {
        self.max_len
    }

    /// Records an in-place exclusive scan of the first `len` elements of `data`.
    pub fn record<'a>(&'a self, rec: &mut Recording<'a>, data: &'a Buffer, len: u32) -> Result<()> {
        if len > self.max_len {
            return Err(EngineError::too_large("elements to scan", len.into(), self.max_len.into(), "the scan's plan"));
        }
        assert!(u64::from(len) * 4 <= data.size, "scan of {len} elements in '{}' of {} bytes", data.name(), data.size);
        self.record_level(rec, data, len, 0)
    }

    fn record_level<'a>(&'a self, rec: &mut Recording<'a>, data: &'a Buffer, len: u32, level: usize) -> Result<()> {
        if len == 0 {
            return Ok(());
        }
        if len <= SCAN_BLOCK_LEN {
            let params = ScanParams { len, add_block_offsets: 0, _pad: [0; 2] };
            // Single block: `block_offsets` is unread; bind `data` to satisfy the layout.
            return rec
                .pass(&self.pass_downsweep, Kernel::ScanDownsweep)
                .write("data", data)
                .read("block_offsets", data)
                .push(&params)
                .dispatch([1, 1, 1]);
        }
        let blocks = block_count(len);
        let sums = &self.level_sums[level];
        let params = ScanParams { len, add_block_offsets: 1, _pad: [0; 2] };
        rec.pass(&self.pass_reduce, Kernel::ScanReduce)
            .read("data", data)
            .write("block_sums", sums)
            .push(&params)
            .dispatch([blocks, 1, 1])?;
        self.record_level(rec, sums, blocks, level + 1)?;
        rec.pass(&self.pass_downsweep, Kernel::ScanDownsweep)
            .write("data", data)
            .read("block_offsets", sums)
            .push(&params)
            .dispatch([blocks, 1, 1])
    }
}

/// Scans host data on the GPU in one submission: upload, scan, read back.
/// For embedding applications and tests; a frame loop keeps a plan and records.
pub fn exclusive_scan_host(ctx: &Context, data: &[u32]) -> Result<Vec<u32>> {
    let len = u32::try_from(data.len()).map_err(|_| EngineError::too_large("elements to scan", data.len() as u64, ExclusiveScan::LIMIT.into(), "the scan (65,535 workgroups of its block)"))?;
    let mut buf = ctx.upload("scan data", data)?;
    let plan = ExclusiveScan::new(ctx, "scan", len)?;
    let mut rec = ctx.record("exclusive_scan_host")?;
    plan.record(&mut rec, &buf, len)?;
    rec.submit_and_wait()?;
    ctx.read_buffer(&mut buf, data.len())
}
