//! Differentiable Gaussian splatting on the GPU and its CPU reference. The math lives in
//! `drape_shared::splat` and is shared by both. The optimizer is `ops::adam`.
//!
//! - [`scene`]: Gaussians on the host, cameras, render settings;
//! - [`mod@reference`]: the CPU renderer, forward and backward, generic over f32/f64;
//! - [`render`]: the GPU renderer (project, depth sort, tile binning, tile sort,
//!   rasterize; and the backward passes);
//! - [`composite`]: depth-aware compositing of three passes (forward, backward);
//! - [`fused`]: the three passes in one sort, one binning and one rasterization;
//! - [`densify`]: the screen-space statistics densification reads;
//! - [`sh_copy`]: SH coefficients copied between clouds of different degrees.

pub mod composite;
pub mod densify;
pub mod fused;
pub mod reference;
pub mod render;
pub mod scene;
pub mod sh_copy;
