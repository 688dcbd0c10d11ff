//! The trainer's error type. Every fallible function of the crate returns
//! [`TrainerError`], or, for a file format's reader or writer, that format's own error
//! (`NpyError`, `DatasetError`, `PickleError`, `ColmapError`, `GarmentError`, `PlyError`,
//! `FidWeightsError`), which `?` converts into it. A caller tells a lost device or an
//! exhausted GPU (`Engine`) from a bad file (`Dataset`, `Npy`, `Pickle`, ...) or a bad
//! setting (`Config`) by matching, not by reading prose. Each variant's message is one
//! line that names the file, key or stage; the binaries print it as it is.

use std::path::{Path, PathBuf};

use drape_engine::EngineError;

/// What went wrong in the trainer.
#[derive(Debug, thiserror::Error)]
pub enum TrainerError {
    /// A GPU failure: a lost device, device memory exhausted, a missing feature, a size
    /// past a device limit.
    #[error(transparent)]
    Engine(#[from] EngineError),
    /// A sequence's files (NeuMan, ZJU-MoCap, synthetic) could not be read or written.
    #[error(transparent)]
    Dataset(#[from] crate::dataset::error::DatasetError),
    /// A NumPy `.npy` / `.npz` file (a body model, a checkpoint, a motion).
    #[error(transparent)]
    Npy(#[from] crate::npy::NpyError),
    /// A pickle (ZJU-MoCap's `annots.npy`).
    #[error(transparent)]
    Pickle(#[from] crate::pickle::PickleError),
    /// COLMAP text (NeuMan's `sparse/`).
    #[error(transparent)]
    Colmap(#[from] crate::dataset::colmap::ColmapError),
    /// A garment file.
    #[error(transparent)]
    Garment(#[from] crate::garment::GarmentError),
    /// A Gaussian PLY file.
    #[error(transparent)]
    Ply(#[from] crate::ply::PlyError),
    /// An LPIPS weights file.
    #[error(transparent)]
    LpipsWeights(#[from] drape_engine::ops::lpips::WeightsError),
    /// An FID Inception weights file.
    #[error(transparent)]
    FidWeights(#[from] crate::metrics::fid_weights::FidWeightsError),
    /// A file or directory could not be read, written, created or renamed.
    #[error("{}: {error}", path.display())]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    /// A configuration value out of range or of the wrong kind: the key (as in
    /// `config.json`) and what is wrong with it.
    #[error("config: {key}: {problem}")]
    Config { key: String, problem: String },
    /// A checkpoint that cannot be loaded into the model: the file, the array and why.
    #[error("{}: '{key}': {problem}", path.display())]
    Checkpoint {
        path: PathBuf,
        key: String,
        problem: String,
    },
    /// A run directory that cannot be used as asked: the directory and why.
    #[error("{}: {problem}", dir.display())]
    Run { dir: PathBuf, problem: String },
    /// An avatar file (`.avatar`) that cannot be read or written: the file and why.
    #[error("{}: {problem}", path.display())]
    AvatarFile { path: PathBuf, problem: String },
    /// Values became non-finite or left their range (a simulation, a training run, a
    /// metric): the stage and what was seen.
    #[error("{stage}: {problem}")]
    Numeric {
        stage: &'static str,
        problem: String,
    },
    /// Arguments an operation cannot use (sizes that disagree, an empty set): the
    /// argument and why.
    #[error("{what}: {problem}")]
    InvalidInput { what: &'static str, problem: String },
}

/// A config choice given a value it does not take; what a choice's `TryFrom<String>`
/// (its serde form) returns, so that the deserialiser names the key around it.
#[derive(Debug, thiserror::Error)]
#[error("must be {allowed}, got '{value}'")]
pub struct BadChoice {
    /// The value given.
    pub value: String,
    /// The values the choice takes, as a phrase ("tight or loose").
    pub allowed: &'static str,
}

/// The trainer's result type.
pub type Result<T, E = TrainerError> = std::result::Result<T, E>;

impl TrainerError {
    /// [`TrainerError::Io`] for `path`.
    pub fn io(path: &Path, error: std::io::Error) -> Self {
        Self::Io {
            path: path.to_path_buf(),
            error,
        }
    }

    /// [`TrainerError::Config`] for `key`.
    pub fn config(key: impl Into<String>, problem: impl Into<String>) -> Self {
        Self::Config {
            key: key.into(),
            problem: problem.into(),
        }
    }

    /// [`TrainerError::Checkpoint`] for `key` of the checkpoint at `path`.
    pub fn checkpoint(path: &Path, key: impl Into<String>, problem: impl Into<String>) -> Self {
        Self::Checkpoint {
            path: path.to_path_buf(),
            key: key.into(),
            problem: problem.into(),
        }
    }

    /// [`TrainerError::AvatarFile`] for the avatar file at `path`.
    pub fn avatar_file(path: &Path, problem: impl Into<String>) -> Self {
        Self::AvatarFile {
            path: path.to_path_buf(),
            problem: problem.into(),
        }
    }

    /// [`TrainerError::Run`] for the run directory `dir`.
    pub fn run(dir: &Path, problem: impl Into<String>) -> Self {
        Self::Run {
            dir: dir.to_path_buf(),
            problem: problem.into(),
        }
    }

    /// [`TrainerError::Numeric`] at `stage`.
    pub fn numeric(stage: &'static str, problem: impl Into<String>) -> Self {
        Self::Numeric {
            stage,
            problem: problem.into(),
        }
    }

    /// [`TrainerError::InvalidInput`] for the argument `what`.
    pub fn invalid(what: &'static str, problem: impl Into<String>) -> Self {
        Self::InvalidInput {
            what,
            problem: problem.into(),
        }
    }

    /// The engine's error, where this is one: a caller that retries on another device
    /// or reports a lost GPU differently from bad input asks this.
    pub fn engine(&self) -> Option<&EngineError> {
        match self {
            Self::Engine(e) => Some(e),
            _ => None,
        }
    }
}
