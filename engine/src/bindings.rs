//! Typed bindings: what a compute pass binds, checked by the compiler.
//!
//! For every kernel of the manifest, `build.rs` generates a struct in
//! [`crate::kernels`], in a module named after the kernel's Rust module
//! (`kernels::splat::ProjectFwd` for the entry point `splat::project_fwd`), with one
//! public field per binding, named after the kernel parameter and typed by the access
//! the SPIR-V declares:
//!
//! - [`Read`] for a storage buffer the kernel only reads (`NonWritable`): made by
//!   [`Buffer::read`] or [`Buffer::read_range`];
//! - [`Write`] for a storage buffer the kernel writes (and may read): made by
//!   [`Buffer::write`] or [`Buffer::write_range`];
//! - [`Texel`] for a uniform texel buffer (read through the buffer's view, so always
//!   the whole buffer): made by [`Buffer::texel`].
//!
//! The struct implements [`Bindings`], which names its kernel and its push-constant
//! type (the one the kernel's source declares, recorded in the manifest by the shader
//! builder), and [`Recording::dispatch`](crate::Recording::dispatch) records it:
//!
//! ```text
//! rec.dispatch("sort.scatter", kernels::radix_sort::Scatter {
//!     keys_in: keys.read(),
//!     keys_out: out.write(),
//!     // ...every other binding
//! }, &params, [groups, 1, 1])?;
//! ```
//!
//! The structs have no `Default`, so a binding left out, a binding the kernel lacks, a
//! read-only buffer passed where the kernel writes (or the reverse) and push constants
//! of another type each fail to compile (the examples below). What is left to run time
//! are the device's limits: a range's offset alignment, `maxStorageBufferRange`, the
//! workgroup counts, a texel buffer's usage and size. Barriers are still derived from
//! the kernel's declared accesses (see [`crate::recorder`]).
//!
//! A kernel chosen at run time among variants with the same bindings and push
//! constants (the atomic, compare-and-swap and fixed-point accumulations, the texel
//! and storage reads of one kernel...) shares one struct:
//! [`Recording::dispatch_as`](crate::Recording::dispatch_as) takes the kernel as well,
//! as a value of the enum generated beside the struct (`kernels::radix_sort::ScatterKernel`
//! for `Scatter`), which lists exactly the kernels the struct fits: another kernel
//! does not compile.
//!
//! ```compile_fail,E0063
//! // A binding left out (`values_out`) does not compile.
//! use drape_engine::{kernels, Buffer, Recording};
//! fn pass<'a>(rec: &mut Recording<'a>, b: &'a Buffer, p: &drape_shared::radix_sort::SortPassParams) {
//!     rec.dispatch("scatter", kernels::radix_sort::Scatter {
//!         keys_in: b.read(),
//!         values_in: b.read(),
//!         scanned_histogram: b.read(),
//!         keys_out: b.write(),
//!         len_words: b.read(),
//!     }, p, [1, 1, 1]).unwrap();
//! }
//! ```
//!
//! ```compile_fail,E0560
//! // A binding the kernel lacks (`vals_out`) does not compile.
//! use drape_engine::{kernels, Buffer, Recording};
//! fn pass<'a>(rec: &mut Recording<'a>, b: &'a Buffer, p: &drape_shared::radix_sort::SortPassParams) {
//!     rec.dispatch("scatter", kernels::radix_sort::Scatter {
//!         keys_in: b.read(),
//!         values_in: b.read(),
//!         scanned_histogram: b.read(),
//!         keys_out: b.write(),
//!         values_out: b.write(),
//!         vals_out: b.write(),
//!         len_words: b.read(),
//!     }, p, [1, 1, 1]).unwrap();
//! }
//! ```
//!
//! ```compile_fail,E0308
//! // A read-only buffer where the kernel writes (`keys_out`) does not compile.
//! use drape_engine::{kernels, Buffer, Recording};
//! fn pass<'a>(rec: &mut Recording<'a>, b: &'a Buffer, p: &drape_shared::radix_sort::SortPassParams) {
//!     rec.dispatch("scatter", kernels::radix_sort::Scatter {
//!         keys_in: b.read(),
//!         values_in: b.read(),
//!         scanned_histogram: b.read(),
//!         keys_out: b.read(),
//!         values_out: b.write(),
//!         len_words: b.read(),
//!     }, p, [1, 1, 1]).unwrap();
//! }
//! ```
//!
//! ```compile_fail,E0308
//! // Push constants of another type than the kernel's do not compile.
//! use drape_engine::{kernels, Buffer, Recording};
//! fn pass<'a>(rec: &mut Recording<'a>, b: &'a Buffer, p: &drape_shared::scan::ScanParams) {
//!     rec.dispatch("scatter", kernels::radix_sort::Scatter {
//!         keys_in: b.read(),
//!         values_in: b.read(),
//!         scanned_histogram: b.read(),
//!         keys_out: b.write(),
//!         values_out: b.write(),
//!         len_words: b.read(),
//!     }, p, [1, 1, 1]).unwrap();
//! }
//! ```
//!
//! ```
//! // The same pass, complete and right, compiles.
//! use drape_engine::{kernels, Buffer, Recording};
//! fn pass<'a>(rec: &mut Recording<'a>, b: &'a Buffer, p: &drape_shared::radix_sort::SortPassParams) {
//!     rec.dispatch("scatter", kernels::radix_sort::Scatter {
//!         keys_in: b.read(),
//!         values_in: b.read(),
//!         scanned_histogram: b.read(),
//!         keys_out: b.write(),
//!         values_out: b.write(),
//!         len_words: b.read(),
//!     }, p, [1, 1, 1]).unwrap();
//! }
//! ```
//!
//! ```
//! // A variant chosen at run time among the struct's kernels compiles.
//! use drape_engine::{kernels, Buffer, Recording};
//! use kernels::radix_sort::ScatterKernel;
//! fn pass<'a>(rec: &mut Recording<'a>, b: &'a Buffer, p: &drape_shared::radix_sort::SortPassParams, texel: bool) {
//!     let kernel = if texel { ScatterKernel::RadixSortChunkScatterTexel } else { ScatterKernel::RadixSortChunkScatter };
//!     rec.dispatch_as("scatter", kernel, kernels::radix_sort::Scatter {
//!         keys_in: b.read(),
//!         values_in: b.read(),
//!         scanned_histogram: b.read(),
//!         keys_out: b.write(),
//!         values_out: b.write(),
//!         len_words: b.read(),
//!     }, p, [1, 1, 1]).unwrap();
//! }
//! ```
//!
//! ```compile_fail,E0308
//! // A kernel with other bindings (`nn::act_fwd` for `train::add_into`) does not compile.
//! use drape_engine::{kernels, Buffer, Recording};
//! fn pass<'a>(rec: &mut Recording<'a>, b: &'a Buffer, p: &drape_shared::adam::LossParams) {
//!     rec.dispatch_as("add", kernels::nn::ActFwdKernel::NnActFwd, kernels::train::AddInto {
//!         src: b.read(),
//!         dst: b.write(),
//!     }, p, [1, 1, 1]).unwrap();
//! }
//! ```

use crate::buffer::Buffer;
use crate::kernels::Kernel;

/// One binding of a pass: a buffer, or a byte range of one.
#[derive(Clone, Copy)]
pub struct Bound<'a> {
    pub(crate) buffer: &'a Buffer,
    pub(crate) offset: u64,
    pub(crate) range: u64,
}

impl<'a> Bound<'a> {
    fn whole(buffer: &'a Buffer) -> Self {
        Bound {
            buffer,
            offset: 0,
            range: buffer.vk_size(),
        }
    }

    fn range(buffer: &'a Buffer, offset: u64, bytes: u64) -> Self {
        // The offset's alignment (a device limit) is checked when the pass is recorded.
        assert!(
            offset
                .checked_add(bytes)
                .is_some_and(|end| end <= buffer.vk_size())
                && bytes > 0,
            "binding bytes {offset}..{} of '{}' ({} bytes)",
            offset.saturating_add(bytes),
            buffer.name(),
            buffer.size
        );
        Bound {
            buffer,
            offset,
            range: bytes,
        }
    }

    /// Whether the binding covers the whole buffer.
    pub(crate) fn is_whole(&self) -> bool {
        self.offset == 0 && self.range == self.buffer.vk_size()
    }
}

/// A buffer (or range) bound where the kernel only reads ([`Buffer::read`]).
#[derive(Clone, Copy)]
pub struct Read<'a>(pub(crate) Bound<'a>);

/// A buffer (or range) bound where the kernel writes, and may read ([`Buffer::write`]).
#[derive(Clone, Copy)]
pub struct Write<'a>(pub(crate) Bound<'a>);

/// A whole buffer bound as a uniform texel buffer ([`Buffer::texel`]).
#[derive(Clone, Copy)]
pub struct Texel<'a>(pub(crate) Bound<'a>);

impl Buffer {
    /// The whole buffer, for a binding the kernel only reads.
    pub fn read(&self) -> Read<'_> {
        Read(Bound::whole(self))
    }

    /// The whole buffer, for a binding the kernel writes (and may read).
    pub fn write(&self) -> Write<'_> {
        Write(Bound::whole(self))
    }

    /// `bytes` bytes from `offset` (a multiple of the device's
    /// `minStorageBufferOffsetAlignment`, checked when the pass is recorded), for a
    /// binding the kernel only reads: for a buffer larger than one binding may cover,
    /// processed in chunks.
    pub fn read_range(&self, offset: u64, bytes: u64) -> Read<'_> {
        Read(Bound::range(self, offset, bytes))
    }

    /// `bytes` bytes from `offset`, for a binding the kernel writes (see
    /// [`read_range`](Self::read_range)).
    pub fn write_range(&self, offset: u64, bytes: u64) -> Write<'_> {
        Write(Bound::range(self, offset, bytes))
    }

    /// The whole buffer, for a uniform texel binding (read through the buffer's
    /// `R32_SFLOAT` or `R32G32B32A32_SFLOAT` view; the buffer needs texel usage, see
    /// [`Buffer::texel_readable`]).
    pub fn texel(&self) -> Texel<'_> {
        Texel(Bound::whole(self))
    }
}

/// The bindings of one kernel (generated per kernel in [`crate::kernels`]), with its
/// push-constant type.
pub trait Bindings<'a> {
    /// The kernel the struct was generated for.
    const KERNEL: Kernel;
    /// The kernels that run with this struct (generated as `<Struct>Kernel`): the same
    /// bindings in the same order, each with the same name and read-only or writable
    /// alike (a texel and a storage read of one binding are alike: the recorder checks
    /// at run time that a texel binding gets a whole buffer), and the same push-constant
    /// type. [`Recording::dispatch_as`](crate::Recording::dispatch_as) takes one.
    type Kernels: Copy + Into<Kernel>;
    /// The push constants the kernel declares (`()` for none).
    type Params: bytemuck::Pod;
    /// The bindings in binding order (an array: no allocation).
    type List: AsRef<[Bound<'a>]>;
    /// The bindings in binding order.
    fn into_list(self) -> Self::List;
}
