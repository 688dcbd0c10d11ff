//! The Cloth-HUGS avatar side of drape: the SMPL-format body (model, loader, the
//! project's procedural body, posing), garments and their cloth simulation (against the
//! body as a collider, `collider`), the dataset
//! readers (NeuMan, ZJU-MoCap, the synthetic sequences; NumPy, pickle and COLMAP files),
//! Gaussian PLY files (`ply`) and camera files (`camera_file`),
//! the layered avatar (`avatar`): training, densification, evaluation, animation and
//! editing, and the set-level metrics its evaluation reports (`metrics`: FID). Fallible functions return [`TrainerError`], or a file format's own error
//! (`npy::NpyError`, `dataset::error::DatasetError`, ...), which converts into it.
#![forbid(unsafe_code)]

pub mod avatar;
pub mod body;
pub mod camera;
pub mod camera_file;
pub mod cloth;
pub mod collider;
pub mod dataset;
pub mod error;
#[cfg(feature = "fuzzing")]
pub mod fuzzing;
pub mod garment;
pub mod grid;
pub mod mesh;
pub mod metrics;
pub mod motion;
pub mod npy;
pub mod pickle;
pub mod ply;
#[cfg(feature = "testing")]
pub mod testing;

pub use error::{Result, TrainerError};
