//! Uniform texel buffers of `f32`, the kernels' other `unsafe` module (with `atomics`):
//! a texel fetch is `OpImageFetch` through inline SPIR-V (spirv-std's `fetch` adds an
//! explicit `Lod`, which a buffer image may not take, and `NonUniform` decorations that
//! would need another capability).
//!
//! Why kernels read through them at all: on llvmpipe a storage-buffer load whose index
//! the compiler cannot prove uniform (any index computed from a loop counter or the
//! workgroup id) becomes a loop over the 8 SIMD lanes with two branches per lane, while
//! a texel fetch is a call into the sampler code with one bounds compare and one
//! `vpgatherdd`, no branch (read off llvmpipe 22.3's machine code). Out-of-range
//! fetches return 0 (robust buffer access), so a fetch never ends the invocation. The
//! engine binds these through a buffer's `R32_SFLOAT` or `R32G32B32A32_SFLOAT` view
//! (`BindingDecl::texel`, `BindingDecl::texel4`). Every build declares `SampledBuffer`
//! (core Vulkan). The sort's chunk kernels read `u32`s through these views with
//! `f32::to_bits`: a fetch moves the 32 bits and nothing does arithmetic on them.
#![allow(unsafe_code)]

use core::arch::asm;
use spirv_std::glam::Vec4;
use spirv_std::Image;

/// A read-only buffer of `f32` bound as a uniform texel buffer (only the subgroup GEMMs
/// read one-float texels).
#[cfg(feature = "subgroup-ballot")]
pub type TexelBuffer = Image!(buffer, type=f32, sampled);

/// The same, read 4 floats a fetch: the image declares `Rgba32f`, which the engine
/// binds through the buffer's `R32G32B32A32_SFLOAT` view (`BindingDecl::texel4`).
pub type TexelBuffer4 = Image!(buffer, format = rgba32f, sampled);

/// Element `index` of `buffer` (0 past its end).
#[cfg(feature = "subgroup-ballot")]
#[inline]
pub fn fetch(buffer: &TexelBuffer, index: u32) -> f32 {
    let mut texel = Vec4::ZERO;
    let coordinate = index as i32;
    // SAFETY: OpImageFetch on a sampled buffer image with an integer coordinate and no
    // image operands is valid SPIR-V for any coordinate; Vulkan returns zeros for a
    // coordinate past the view instead of reading outside it.
    unsafe {
        asm! {
            "%image = OpLoad _ {buffer}",
            "%texel = OpImageFetch typeof*{texel} %image {coordinate}",
            "OpStore {texel} %texel",
            buffer = in(reg) buffer,
            coordinate = in(reg) coordinate,
            texel = in(reg) &mut texel,
        }
    }
    texel.x
}

/// Texel `index` of `buffer`: its elements `4 index .. 4 index + 4` (zeros past its end).
#[inline]
pub fn fetch4(buffer: &TexelBuffer4, index: u32) -> Vec4 {
    let mut texel = Vec4::ZERO;
    let coordinate = index as i32;
    // SAFETY: as in `fetch`.
    unsafe {
        asm! {
            "%image = OpLoad _ {buffer}",
            "%texel = OpImageFetch typeof*{texel} %image {coordinate}",
            "OpStore {texel} %texel",
            buffer = in(reg) buffer,
            coordinate = in(reg) coordinate,
            texel = in(reg) &mut texel,
        }
    }
    texel
}
