//! The error every dataset reader and writer returns: one line that names the file (and
//! the field, or the layout variant that was assumed), never a panic or a debug dump.

use std::path::Path;

/// What went wrong reading or writing a sequence.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// The file could not be opened, read or written.
    #[error("{file}: {source}")]
    Io { file: String, source: std::io::Error },
    /// The file is there but is not an image we can decode (corrupt, truncated, an
    /// unsupported encoding), or its size does not match its camera.
    #[error("{file}: {problem}")]
    Image { file: String, problem: String },
    /// A value in a file is wrong: the file, the field, and what is wrong with it.
    #[error("{file}: {field}: {problem}")]
    Field { file: String, field: String, problem: String },
    /// A file the detected layout variant needs does not exist.
    #[error("{file}: missing ({what}; the layout was read as {variant})")]
    Missing { file: String, what: String, variant: &'static str },
    /// The directory is no layout we know.
    #[error("{dir}: {problem}")]
    Layout { dir: String, problem: String },
    /// A message from a format reader that already names its file and field (COLMAP
    /// text, pickled annotations), carried as it is.
    #[error("{0}")]
    Format(String),
}

impl DatasetError {
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io { file: path.display().to_string(), source }
    }

    pub fn image(path: &Path, problem: impl Into<String>) -> Self {
        Self::Image { file: path.display().to_string(), problem: problem.into() }
    }

    pub fn missing(path: &Path, what: impl Into<String>, variant: &'static str) -> Self {
        Self::Missing { file: path.display().to_string(), what: what.into(), variant }
    }

    pub fn layout(dir: &Path, problem: impl Into<String>) -> Self {
        Self::Layout { dir: dir.display().to_string(), problem: problem.into() }
    }
}

impl From<String> for DatasetError {
    fn from(message: String) -> Self {
        Self::Format(message)
    }
}

impl From<crate::npy::NpyError> for DatasetError {
    fn from(e: crate::npy::NpyError) -> Self {
        Self::Format(e.to_string())
    }
}

/// The binaries and the older `String`-error callers take the one-line message.
impl From<DatasetError> for String {
    fn from(e: DatasetError) -> Self {
        e.to_string()
    }
}
