//! Differentiable Gaussian splatting on the GPU, its CPU reference, PLY files and the
//! optimizer. The math lives in `drape_shared::splat` and is shared by all of them.
//!
//! - [`scene`]: Gaussians on the host, cameras, render settings;
//! - [`reference`]: the CPU renderer, forward and backward, generic over f32/f64;
//! - [`render`]: the GPU renderer (project, depth sort, tile binning, tile sort,
//!   rasterize; and the backward passes);
//! - [`composite`]: depth-aware compositing of three passes (forward, backward);
//! - [`fused`]: the three passes in one sort, one binning and one rasterization;
//! - [`densify`]: the screen-space statistics densification reads;
//! - [`sh_copy`]: SH coefficients copied between layers of different degrees;
//! - [`ply`]: 3D Gaussian Splatting PLY files;
//! - [`adam`]: Adam over the Gaussian parameters on the GPU;
//! - [`fit`]: fitting Gaussians to an image.

pub mod adam;
pub mod composite;
pub mod densify;
pub mod fit;
pub mod fused;
pub mod ply;
pub mod reference;
pub mod render;
pub mod scene;
pub mod sh_copy;
