//! Datasets: the on-disk formats of NeuMan (COLMAP text model, the HUGS SMPL file)
//! and ZJU-MoCap (annotations, SMPL parameters, vertices), and the split protocols.
//! The CPU mesh rasterizer the synthetic generator will use is here; not written
//! yet (see the datasets issue): the generator itself, image and mask files, and the
//! dataset type the trainer consumes.

pub mod colmap;
pub mod image;
pub mod neuman;
pub mod raster;
pub mod split;
pub mod synth;
pub mod zju;
