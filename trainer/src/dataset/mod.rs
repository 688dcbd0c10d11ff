//! Datasets: the on-disk formats of NeuMan (COLMAP text model, the HUGS SMPL file)
//! and ZJU-MoCap (annotations, SMPL parameters, vertices), and the split protocols.
//! `synth` generates the project's own data in both layouts with the CPU rasterizer
//! (`raster`); `loader` reads either layout into the dataset type the trainer consumes.

pub mod colmap;
pub mod distortion;
pub mod error;
pub mod image;
pub mod inspect;
pub mod layout;
pub mod loader;
pub mod neuman;
pub mod raster;
pub mod split;
pub mod synth;
pub mod variants;
pub mod zju;
