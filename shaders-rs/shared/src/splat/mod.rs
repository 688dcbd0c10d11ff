//! Differentiable 3D Gaussian splatting: layouts shared by kernels and host, and the
//! math of every stage (projection, spherical harmonics, per-pixel blending), forward
//! and backward, generic over [`Real`](crate::real::Real) so that the same code is the
//! GPU kernel, the CPU reference and the f64 gradient-check reference.
//!
//! Conventions (follow gsplat so renders agree with it): camera looks down +z,
//! world-to-camera `p_c = R p_w + t`; pixel `(i, j)` has its centre at `(i + 0.5, j + 0.5)`;
//! quaternions are `(w, x, y, z)`, unnormalized; scales are stored as logarithms and
//! opacities as logits. NaN policy: guards are written so that NaN fails them, and a
//! Gaussian with any non-finite parameter is dropped (and counted) before projection.

pub mod composite;
pub mod densify;
pub mod layout;
pub mod project;
pub mod raster;
pub mod sh;

pub use layout::*;
