//! The error the sequence readers and writers return (layouts, images, ZJU-MoCap files,
//! the loaders), wrapping the errors of the formats below them (pickle, COLMAP, NumPy):
//! one line that names the file (and the field, or the layout variant that was
//! assumed), never a panic or a debug dump.

use std::path::Path;

use crate::dataset::colmap::ColmapError;
use crate::npy::NpyError;
use crate::pickle::PickleError;

/// What went wrong reading or writing a sequence.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// The file could not be opened, read or written.
    // `error`, not `source`: the message carries it; a `source` would make anyhow
    // print the OS error twice.
    #[error("{file}: {error}")]
    Io { file: String, error: std::io::Error },
    /// The file is there but is not an image we can decode (corrupt, truncated, an
    /// unsupported encoding), or its size does not match its camera.
    #[error("{file}: {problem}")]
    Image { file: String, problem: String },
    /// A value in a file is wrong: the file, the field, and what is wrong with it.
    #[error("{file}: {field}: {problem}")]
    Field {
        file: String,
        field: String,
        problem: String,
    },
    /// A file the detected layout variant needs does not exist.
    #[error("{file}: missing ({what}; the layout was read as {variant})")]
    Missing {
        file: String,
        what: String,
        variant: &'static str,
    },
    /// The directory is no layout we know.
    #[error("{dir}: {problem}")]
    Layout { dir: String, problem: String },
    /// A pickled file (ZJU-MoCap's `annots.npy`, `smpl_params/*.npy`) that cannot be
    /// read; the error names the file and the byte.
    #[error(transparent)]
    Pickle(#[from] PickleError),
    /// COLMAP text (NeuMan's `sparse/`) that cannot be read, or a camera in it drape
    /// does not undistort; the error names the file and the line or camera.
    #[error(transparent)]
    Colmap(#[from] ColmapError),
    /// A NumPy `.npy` / `.npz` file (SMPL parameters, vertices) that cannot be read;
    /// the error names the file and the array.
    #[error(transparent)]
    Npy(#[from] NpyError),
}

impl DatasetError {
    pub fn io(path: &Path, error: std::io::Error) -> Self {
        Self::Io {
            file: path.display().to_string(),
            error,
        }
    }

    pub fn image(path: &Path, problem: impl Into<String>) -> Self {
        Self::Image {
            file: path.display().to_string(),
            problem: problem.into(),
        }
    }

    pub fn missing(path: &Path, what: impl Into<String>, variant: &'static str) -> Self {
        Self::Missing {
            file: path.display().to_string(),
            what: what.into(),
            variant,
        }
    }

    pub fn layout(dir: &Path, problem: impl Into<String>) -> Self {
        Self::Layout {
            dir: dir.display().to_string(),
            problem: problem.into(),
        }
    }
}
