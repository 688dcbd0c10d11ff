//! Datasets: the on-disk formats of NeuMan (COLMAP text model, the HUGS SMPL file),
//! ZJU-MoCap (annotations, SMPL parameters, vertices) and rig calibrations (Qualisys,
//! Pose2Sim TOML: `calibration`), their published layout
//! variants (`layout`, checked before loading; `inspect` reports them), images and
//! masks (`image`), lens distortion removed at load (`distortion`), and the split
//! protocols. `synth` generates the project's own data in both layouts with the CPU
//! rasterizer (`raster`) and `variants` rewrites it into each published variant;
//! `loader` reads either layout into the dataset type the trainer consumes.

pub mod calibration;
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
