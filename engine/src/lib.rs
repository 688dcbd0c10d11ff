//! The drape engine: a Vulkan runtime on `ash` and `gpu-allocator`, and the GPU ops
//! built on it. Kernels are rust-gpu SPIR-V modules committed in `shaders-rs/spirv`
//! and embedded at build time; [`Kernel`] is their typed handle.
//!
//! ```no_run
//! use drape_engine::{Context, ContextDesc, ops::radix_sort::RadixSort};
//! # fn main() -> drape_engine::Result<()> {
//! let ctx = Context::new(&ContextDesc::default())?;
//! let keys = ctx.upload("keys", &[3u32, 1, 2])?;
//! let values = ctx.upload("values", &[0u32, 1, 2])?;
//! let sort = RadixSort::new(&ctx, 3)?;
//! let mut rec = ctx.record("sort")?;
//! sort.record(&mut rec, &keys, &values, 3, 32)?;
//! let timings = rec.submit_and_wait()?;
//! # Ok(()) }
//! ```

#![warn(missing_docs)]

/// The `ash` the engine is built on, for the raw handles its embedding API takes.
pub use ash;

pub mod bindings;
pub mod buffer;
pub mod context;
pub mod error;
pub mod external;
pub mod kernels;
pub mod mirror;
pub mod ops;
mod pools;
pub mod profile;
pub mod recorder;
mod requirements;
mod retire;
pub mod submit;
pub mod validation;

pub use bindings::{Bindings, Read, Texel, Write};
pub use buffer::{Buffer, BufferDesc};
pub use context::{
    Context, ContextDesc, DeferredBuffers, DeviceInfo, DeviceKind, MemoryInUse, RecordedWork,
    POISON_WORD,
};
pub use error::{EngineError, Result};
pub use external::{
    device_requirements, DeviceFeatures, DeviceRequirements, ExternalOptions, ExternalVulkan,
};
pub use kernels::Kernel;
pub use mirror::Mirror;
pub use profile::{Profile, ProfileEntry};
pub use recorder::{ImageTarget, PassTimings, Recording};
pub use submit::{FramesInFlight, HostCommandBuffer, HostRecorded, Submission, SubmitSync};
