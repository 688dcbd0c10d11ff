//! Code shared by the GPU kernels (compiled to SPIR-V by rust-gpu) and the host.
//!
//! Everything here is `no_std`, allocation-free and deterministic, so the very same
//! functions run inside a compute shader and inside a CPU reference on the host.
//! Parameter structs are `#[repr(C)]`; on the host they are also `bytemuck::Pod` so
//! they can be pushed as push constants byte for byte.
#![no_std]
#![forbid(unsafe_code)]

pub mod adam;
pub mod cloth_loss;
pub mod deform;
pub mod fixed_point;
pub mod half;
pub mod lpips;
pub mod nn;
pub mod radix_sort;
pub mod real;
pub mod scan;
pub mod skinning;
pub mod splat;
pub mod ssim;
pub mod triplane;
#[cfg(not(target_arch = "spirv"))]
pub mod spirv_module;
