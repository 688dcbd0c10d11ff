//! Host mirrors: a device buffer's values copied into host-visible memory by the
//! submission that computes them, so the host reads them after that submission's own
//! wait rather than with a submission and a wait of their own.
//!
//! A read-back through [`Context::read_buffer`] of a device-local buffer is a copy, a
//! submission and a fence wait. An op whose values a host reads often (a training
//! step's logged losses) keeps a [`Mirror`] of each value buffer instead: the caller
//! records [`Mirror::record_copy`] into the step's recording, and after the step's one
//! wait [`Mirror::read`] is a copy out of mapped memory.

use std::sync::atomic::{AtomicBool, Ordering};

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::Result;
use crate::recorder::Recording;

/// A host-visible copy of one device buffer (the same size), with whether it holds the
/// buffer's current values.
pub struct Mirror {
    host: Buffer,
    /// Set when a copy is recorded; cleared ([`Mirror::mark_stale`]) when a recording
    /// recomputes the source without copying it.
    fresh: AtomicBool,
}

impl Mirror {
    /// A mirror of `source`, named after it.
    pub fn new(ctx: &Context, source: &Buffer) -> Result<Self> {
        let host = ctx.create_buffer(
            &format!("{} (mirror)", source.name()),
            BufferDesc::readback(source.size),
        )?;
        Ok(Self {
            host,
            fresh: AtomicBool::new(false),
        })
    }

    /// Records the copy of `source`'s first `bytes` into the mirror, after whatever the
    /// recording wrote to `source` before (the recorder orders the two). Its values are
    /// the host's to read once this recording's submission has completed.
    pub fn record_copy<'a>(&'a self, rec: &mut Recording<'a>, source: &'a Buffer, bytes: u64) {
        rec.copy(source, &self.host, bytes);
        self.fresh.store(true, Ordering::Relaxed);
    }

    /// The source is being recomputed by a recording that does not copy it: reads go
    /// to the source again until the next [`Mirror::record_copy`].
    pub fn mark_stale(&self) {
        self.fresh.store(false, Ordering::Relaxed);
    }

    /// Whether the last recording that recomputed the source also copied it here.
    pub fn is_fresh(&self) -> bool {
        self.fresh.load(Ordering::Relaxed)
    }

    /// The first `count` elements of `source`: out of the mirror's mapped memory where
    /// it is fresh (no submission, no wait), otherwise read from `source` itself.
    /// Call it after the submission that recorded the copy has completed.
    pub fn read<T: bytemuck::Pod>(
        &mut self,
        ctx: &Context,
        source: &mut Buffer,
        count: usize,
    ) -> Result<Vec<T>> {
        if self.is_fresh() {
            ctx.read_buffer(&mut self.host, count)
        } else {
            ctx.read_buffer(source, count)
        }
    }
}

/// Reads `count` elements of `source` through `mirror` where there is one (see
/// [`Mirror::read`]), otherwise straight from `source`.
pub fn read_through<T: bytemuck::Pod>(
    ctx: &Context,
    mirror: Option<&mut Mirror>,
    source: &mut Buffer,
    count: usize,
) -> Result<Vec<T>> {
    match mirror {
        Some(m) => m.read(ctx, source, count),
        None => ctx.read_buffer(source, count),
    }
}
