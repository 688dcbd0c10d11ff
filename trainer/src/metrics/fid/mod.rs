//! FID (Fréchet Inception Distance) on the CPU: the FID Inception-v3 network as
//! pytorch-fid defines it, its weights file, and the Fréchet distance between two sets
//! of its features.
//!
//! - `network`: the Inception network (pytorch-fid's FID blocks, the input resize) and
//!   the reading of its weights: images to pool3 features ([`FidInception`]).
//! - `distance`: the Fréchet distance between two sets of features or two Gaussians
//!   ([`frechet_distance_of_features`], [`frechet_distance`], [`Statistics`]).
//! - `linalg`: the symmetric eigen-solver and the matrix products the distance is made
//!   of ([`symmetric_eigen`]).
//!
//! The weights file's format and its error are `metrics::fid_weights`'s
//! ([`FidWeightsError`] is re-exported here, where the network's loader returns it).
//! Everything public is reached through this module; the files are how it is kept, not
//! part of the paths.

mod distance;
mod linalg;
mod network;

pub use crate::metrics::fid_weights::FidWeightsError;
pub use distance::{frechet_distance, frechet_distance_of_features, Statistics};
pub use linalg::symmetric_eigen;
pub use network::{FidInception, ImageRef, BN_EPS, FEATURE_DIM, INPUT_SIDE};
