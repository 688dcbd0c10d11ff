//! How the scatter-add backward kernels (the splat rasterizer's and the triplane's)
//! accumulate gradients, and the scratch that the deterministic way needs.
//!
//! Float atomics are fastest, and their sums depend on the order the GPU runs the
//! invocations in: two runs of the same step differ in the last bits. The
//! deterministic way (`*_fixed` kernels, `drape_shared::fixed_point`) adds 64-bit
//! fixed-point integers into a [`FixedPointScratch`] and then resolves it into the
//! f32 gradient, so the result is the same bits on every run of the same device
//! (for a run that resumes from a checkpoint and must match one that did not stop).

use drape_shared::fixed_point::{scratch_words, ResolveParams};

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::{EngineError, Result};
use crate::kernels;
use crate::recorder::{flat_grid, Recording};

/// How a backward kernel accumulates its scatter-added gradients.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Accumulation {
    /// Float atomics when the device has them, else compare-and-swap.
    #[default]
    Auto,
    /// Float atomic adds (`shaderBufferFloat32AtomicAdd`).
    FloatAtomics,
    /// Compare-and-swap loops on the float's bits: every device, slower under contention.
    CompareAndSwap,
    /// 64-bit fixed-point integer atomics: bit-identical from run to run; two atomics
    /// per value, and a resolution of 2^-36 (see `drape_shared::fixed_point`).
    Deterministic,
}

/// The kernel family an [`Accumulation`] comes to on a device.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Method {
    /// Float atomic adds.
    FloatAtomics,
    /// Compare-and-swap loops.
    CompareAndSwap,
    /// 64-bit fixed-point integer atomics, resolved to floats after the pass.
    FixedPoint,
}

impl Accumulation {
    /// The kernel family this choice comes to on `ctx`'s device.
    pub fn method(self, ctx: &Context) -> Method {
        match self {
            Accumulation::Auto if ctx.info().float_atomic_add => Method::FloatAtomics,
            Accumulation::Auto | Accumulation::CompareAndSwap => Method::CompareAndSwap,
            Accumulation::FloatAtomics => Method::FloatAtomics,
            Accumulation::Deterministic => Method::FixedPoint,
        }
    }

    /// Name for logs and benchmark reports.
    pub fn describe(self, ctx: &Context) -> &'static str {
        match self.method(ctx) {
            Method::FloatAtomics => "float atomics",
            Method::CompareAndSwap => "compare-and-swap",
            Method::FixedPoint => "deterministic (fixed point)",
        }
    }
}

/// A fixed-point accumulation buffer for up to `capacity` values: two u32 words each
/// and the non-finite flag word.
pub struct FixedPointScratch {
    buffer: Buffer,
    capacity: u32,
}

impl FixedPointScratch {
    /// Scratch for up to `capacity` values; refused beyond the device's storage-buffer range.
    pub fn new(ctx: &Context, label: &str, capacity: u32) -> Result<Self> {
        let bytes = 4 * scratch_words(capacity);
        let binding = ctx.info().max_storage_buffer_range;
        if bytes > binding {
            return Err(EngineError::too_large(
                format!("bytes of the fixed-point scratch of {label}"),
                bytes,
                binding,
                "the device's maxStorageBufferRange",
            ));
        }
        Ok(Self {
            buffer: ctx.create_buffer(
                &format!("{label} fixed-point scratch"),
                BufferDesc::gpu_only(bytes),
            )?,
            capacity,
        })
    }

    /// The most values it holds.
    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// The buffer a `*_fixed` kernel adds into (after [`record_clear`](Self::record_clear)).
    pub fn buffer(&self) -> &Buffer {
        &self.buffer
    }

    /// Zeroes the sums and the flag.
    pub fn record_clear<'a>(&'a self, rec: &mut Recording<'a>) {
        rec.fill(&self.buffer, 0);
    }

    /// Records `out[i] = value i` for the first `count` values (overwriting `out`), or
    /// NaN everywhere if a non-finite value was added.
    pub fn record_resolve<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        out: &'a Buffer,
        count: u32,
    ) -> Result<()> {
        assert!(
            count <= self.capacity,
            "resolving {count} values from a scratch of {}",
            self.capacity
        );
        rec.dispatch(
            "fixed_point.resolve",
            kernels::fixed_point::Resolve {
                scratch: self.buffer.read(),
                out: out.write(),
            },
            &ResolveParams {
                count,
                _pad: [0; 3],
            },
            flat_grid(count),
        )
    }
}
