//! Datasets: the on-disk formats of NeuMan (COLMAP text model, the HUGS SMPL file)
//! and ZJU-MoCap (annotations, SMPL parameters, vertices), and the split protocols.
//! Not written yet (see the datasets issue): the synthetic generator, images and
//! masks, and the dataset type the trainer consumes.

pub mod colmap;
pub mod neuman;
pub mod split;
pub mod zju;
