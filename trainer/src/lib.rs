//! The Cloth-HUGS avatar side of drape: the SMPL-format body (model, loader, the
//! project's procedural body, posing), NumPy file formats, and (in later issues)
//! garments, cloth simulation, datasets, training and evaluation.
#![forbid(unsafe_code)]

pub mod avatar;
pub mod body;
pub mod camera;
pub mod cloth;
pub mod dataset;
pub mod garment;
pub mod grid;
pub mod mesh;
pub mod motion;
pub mod npy;
pub mod pickle;
