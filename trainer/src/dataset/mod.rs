//! Datasets: the on-disk formats of NeuMan (COLMAP text model, masks, the HUGS SMPL
//! file) and ZJU-MoCap, and their split protocols. (The synthetic generator and the
//! ZJU-MoCap `annots.npy` pickle are not written yet; see the datasets issue.)

pub mod colmap;
pub mod neuman;
pub mod split;
pub mod zju;
