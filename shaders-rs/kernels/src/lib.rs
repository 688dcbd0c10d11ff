//! rust-gpu compute entry points of the drape engine.
//!
//! Each entry point only computes indices, moves data between buffers and workgroup
//! memory, and calls into `drape-shared`, where the math lives (and where the host's
//! CPU references call the same functions). Modules group the kernels of one op.
//!
//! Conventions: bindings are `descriptor_set = 0`, numbered in the order the op's host
//! code names them; parameters arrive as push constants (`#[repr(C)]` structs from
//! `drape-shared`); read-only buffers are `&[T]`, written ones `&mut [T]`.
#![cfg_attr(target_arch = "spirv", no_std)]
// Inline SPIR-V, for the texel fetches of `texel`.
#![cfg_attr(target_arch = "spirv", feature(asm_experimental_arch))]
// Only `atomics` and `texel` may use unsafe (spirv-std's atomics are unsafe fns; a
// texel fetch is inline SPIR-V).
#![deny(unsafe_code)]

mod atomics;
pub mod cloth_loss;
pub mod composite;
pub mod deform;
pub mod fixed_point;
pub mod lpips;
pub mod nn;
pub mod nn_lavapipe;
pub mod radix_sort;
pub mod scan;
pub mod skinning;
pub mod splat;
#[cfg(feature = "subgroup-ballot")]
pub mod splat_lavapipe;
pub mod ssim;
#[cfg(feature = "subgroup-ballot")]
mod subgroup;
mod texel;
pub mod train;
pub mod triplane;
mod workgroup;

/// Index of an invocation of a one-element-per-invocation kernel (256 per workgroup),
/// which the engine dispatches on `recorder::flat_grid`: a row of up to 65,535
/// workgroups, then more rows, so counts past 16.7M fit the limit every device has.
#[inline]
pub(crate) fn flat_index(id: spirv_std::glam::UVec3, groups: spirv_std::glam::UVec3) -> u32 {
    id.y * groups.x * 256 + id.x
}
