//! Exclusive prefix sum of `u32` on the GPU, in two variants ([`ScanVariant`]).
//!
//! Blocks (GPUs; kernels `scan::reduce`, `scan::downsweep`): reduce-then-scan over
//! levels of `SCAN_BLOCK_LEN`-element blocks: reduce each block to a sum, scan the sums
//! (recursively), then scan each block again starting from its block's offset. Two
//! dispatches per level and one for the top.
//! Chunks (CPU devices; `scan::chunk_reduce`, `scan::chunk_sums`,
//! `scan::chunk_downsweep`): each invocation sums one of up to 64 long runs (more past
//! 2M elements; runs of whole quads of 4 elements, each read and written as one `UVec4`,
//! which on llvmpipe costs one lane loop where an element cost one)
//! (`drape_shared::chunks`), one invocation scans those sums, and each run is scanned
//! from its offset: three dispatches, no barriers. Up to `SERIAL_SCAN_MAX_LEN` elements
//! (a chunked radix sort's histogram up to 8M keys) one invocation scans them all
//! instead (`scan::chunk_serial`): on lavapipe each dispatch costs its threads' start and
//! finish, more than that walk (docs/performance.md, "What llvmpipe 22.3 makes of a
//! kernel"). The quad holding the last element is
//! written whole, its elements past `len` as they were (buffers are whole 16-byte texels).
//! No workgroup waits on another. In place; wrapping arithmetic; any length up to
//! [`ExclusiveScan::max_len`]. CPU reference: `drape_shared::scan::exclusive_scan_in_place`.

use drape_shared::chunks::{chunk_count, CHUNK_WORKGROUP_SIZE};
use drape_shared::scan::{
    block_count, ChunkScanParams, ScanParams, SCAN_BLOCK_LEN, SERIAL_SCAN_MAX_LEN,
};

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::{EngineError, Result};
use crate::kernels;
use crate::recorder::Recording;

/// Which kernels a scan records; both give the same (exact) result.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ScanVariant {
    /// [`Chunks`](Self::Chunks) on CPU devices, [`Blocks`](Self::Blocks) elsewhere.
    #[default]
    Auto,
    /// Workgroups of 256 invocations scan blocks of 1,024 elements, level by level: the
    /// GPU kernels.
    Blocks,
    /// One invocation per long run, no barriers: for llvmpipe, where a workgroup scan's
    /// barriers are coroutine switches (docs/performance.md, "Sort and scan on lavapipe",
    /// compares the two variants).
    Chunks,
}

impl ScanVariant {
    /// The variant `Auto` stands for on this device.
    pub fn resolve(self, ctx: &Context) -> Self {
        match self {
            Self::Auto if ctx.info().kind == crate::DeviceKind::Cpu => Self::Chunks,
            Self::Auto => Self::Blocks,
            chosen => chosen,
        }
    }
}

/// A planned scan: the block-sum buffers of every level (blocks) or the chunk sums
/// (chunks) for lengths up to `max_len`.
pub struct ExclusiveScan {
    max_len: u32,
    variant: ScanVariant,
    /// Blocks: sums of level 1, 2, ... (level 0 is the caller's data). Chunks: one
    /// buffer, the chunk sums.
    level_sums: Vec<Buffer>,
    pass_reduce: String,
    pass_sums: String,
    pass_downsweep: String,
    pass_serial: String,
    /// Whether chunked scans of up to `SERIAL_SCAN_MAX_LEN` run in one invocation
    /// (off for tests of the three-dispatch kernels at those lengths).
    serial: bool,
}

impl ExclusiveScan {
    /// Largest length one plan accepts: the level-0 dispatch must fit the
    /// 65,535-workgroup limit every Vulkan device guarantees.
    pub const LIMIT: u32 = 65_535 * SCAN_BLOCK_LEN;

    /// Plans scans of up to `max_len` elements with the device's variant; `label`
    /// prefixes pass names.
    pub fn new(ctx: &Context, label: &str, max_len: u32) -> Result<Self> {
        Self::with_variant(ctx, label, max_len, ScanVariant::Auto)
    }

    /// Plans scans of up to `max_len` elements with the given kernels.
    pub fn with_variant(
        ctx: &Context,
        label: &str,
        max_len: u32,
        variant: ScanVariant,
    ) -> Result<Self> {
        if max_len > Self::LIMIT {
            return Err(EngineError::too_large(
                "elements to scan",
                max_len.into(),
                Self::LIMIT.into(),
                "the scan (65,535 workgroups of its block)",
            ));
        }
        let variant = variant.resolve(ctx);
        let mut level_sums = Vec::new();
        if variant == ScanVariant::Chunks {
            let chunks = chunk_count(max_len);
            level_sums.push(ctx.create_buffer(
                &format!("{label} chunk sums"),
                BufferDesc::gpu_only(u64::from(chunks) * 4),
            )?);
        } else {
            let mut len = max_len;
            while len > SCAN_BLOCK_LEN {
                len = block_count(len);
                let name = format!("{label} level {} sums", level_sums.len() + 1);
                level_sums
                    .push(ctx.create_buffer(&name, BufferDesc::gpu_only(u64::from(len) * 4))?);
            }
        }
        Ok(Self {
            max_len,
            variant,
            level_sums,
            pass_reduce: format!("{label}.reduce"),
            pass_sums: format!("{label}.chunk_sums"),
            pass_downsweep: format!("{label}.downsweep"),
            pass_serial: format!("{label}.serial"),
            serial: true,
        })
    }

    /// The most elements one scan may have.
    pub fn max_len(&self) -> u32 {
        self.max_len
    }

    /// The same plan scanning every length with the three-dispatch chunk kernels (for
    /// tests; the result is the same).
    #[doc(hidden)]
    pub fn without_serial(mut self) -> Self {
        self.serial = false;
        self
    }

    /// The kernels this plan records (never `Auto`).
    pub fn variant(&self) -> ScanVariant {
        self.variant
    }

    /// Records an in-place exclusive scan of the first `len` elements of `data`.
    pub fn record<'a>(&'a self, rec: &mut Recording<'a>, data: &'a Buffer, len: u32) -> Result<()> {
        if len > self.max_len {
            return Err(EngineError::too_large(
                "elements to scan",
                len.into(),
                self.max_len.into(),
                "the scan's plan",
            ));
        }
        assert!(
            u64::from(len) * 4 <= data.size,
            "scan of {len} elements in '{}' of {} bytes",
            data.name(),
            data.size
        );
        if self.variant == ScanVariant::Chunks {
            return self.record_chunks(rec, data, len);
        }
        self.record_level(rec, data, len, 0)
    }

    fn record_chunks<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        data: &'a Buffer,
        len: u32,
    ) -> Result<()> {
        if len == 0 {
            return Ok(());
        }
        let params = ChunkScanParams {
            len,
            chunks: chunk_count(len),
            _pad: [0; 2],
        };
        if len <= SERIAL_SCAN_MAX_LEN && self.serial {
            return rec.dispatch(
                &self.pass_serial,
                kernels::scan::ChunkSerial { data: data.write() },
                &params,
                [1, 1, 1],
            );
        }
        let sums = &self.level_sums[0];
        let groups = params.chunks / CHUNK_WORKGROUP_SIZE;
        rec.dispatch(
            &self.pass_reduce,
            kernels::scan::ChunkReduce {
                data: data.read(),
                chunk_sums: sums.write(),
            },
            &params,
            [groups, 1, 1],
        )?;
        rec.dispatch(
            &self.pass_sums,
            kernels::scan::ChunkSums {
                chunk_sums: sums.write(),
            },
            &params,
            [1, 1, 1],
        )?;
        rec.dispatch(
            &self.pass_downsweep,
            kernels::scan::ChunkDownsweep {
                data: data.write(),
                chunk_offsets: sums.read(),
            },
            &params,
            [groups, 1, 1],
        )
    }

    fn record_level<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        data: &'a Buffer,
        len: u32,
        level: usize,
    ) -> Result<()> {
        if len == 0 {
            return Ok(());
        }
        if len <= SCAN_BLOCK_LEN {
            let params = ScanParams {
                len,
                add_block_offsets: 0,
                _pad: [0; 2],
            };
            // Single block: `block_offsets` is unread; bind `data` to satisfy the layout.
            return rec.dispatch(
                &self.pass_downsweep,
                kernels::scan::Downsweep {
                    data: data.write(),
                    block_offsets: data.read(),
                },
                &params,
                [1, 1, 1],
            );
        }
        let blocks = block_count(len);
        let sums = &self.level_sums[level];
        let params = ScanParams {
            len,
            add_block_offsets: 1,
            _pad: [0; 2],
        };
        rec.dispatch(
            &self.pass_reduce,
            kernels::scan::Reduce {
                data: data.read(),
                block_sums: sums.write(),
            },
            &params,
            [blocks, 1, 1],
        )?;
        self.record_level(rec, sums, blocks, level + 1)?;
        rec.dispatch(
            &self.pass_downsweep,
            kernels::scan::Downsweep {
                data: data.write(),
                block_offsets: sums.read(),
            },
            &params,
            [blocks, 1, 1],
        )
    }
}

/// Scans host data on the GPU in one submission: upload, scan, read back.
/// For embedding applications and tests; a frame loop keeps a plan and records.
pub fn exclusive_scan_host(ctx: &Context, data: &[u32]) -> Result<Vec<u32>> {
    exclusive_scan_host_with(ctx, ScanVariant::Auto, data)
}

/// [`exclusive_scan_host`] with the given kernels.
pub fn exclusive_scan_host_with(
    ctx: &Context,
    variant: ScanVariant,
    data: &[u32],
) -> Result<Vec<u32>> {
    let len = u32::try_from(data.len()).map_err(|_| {
        EngineError::too_large(
            "elements to scan",
            data.len() as u64,
            ExclusiveScan::LIMIT.into(),
            "the scan (65,535 workgroups of its block)",
        )
    })?;
    let mut buf = ctx.upload("scan data", data)?;
    let plan = ExclusiveScan::with_variant(ctx, "scan", len, variant)?;
    let mut rec = ctx.record("exclusive_scan_host")?;
    plan.record(&mut rec, &buf, len)?;
    rec.submit_and_wait()?;
    ctx.read_buffer(&mut buf, data.len())
}
