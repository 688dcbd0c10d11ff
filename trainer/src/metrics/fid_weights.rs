//! The FID Inception weights file: a safetensors file (an 8-byte little-endian header
//! length, a JSON header naming each tensor's dtype, shape and byte range, then the
//! data), read as float32 tensors of the shapes the network asks for, and its error,
//! which names the file and the tensor.

use std::path::{Path, PathBuf};

/// A problem with a weights file, naming the file and the tensor.
#[derive(Debug, thiserror::Error)]
pub enum FidWeightsError {
    // `error`, not `source`: the message already carries it (anyhow would print it twice).
    #[error("{path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("{path}: not a safetensors file: {detail}")]
    Format { path: PathBuf, detail: String },
    #[error("{path}: tensor '{tensor}' is missing (is this pytorch-fid's FID Inception, from scripts/fid-to-safetensors.py?)")]
    Missing { path: PathBuf, tensor: String },
    #[error("{path}: tensor '{tensor}' has {detail}")]
    Bad {
        path: PathBuf,
        tensor: String,
        detail: String,
    },
}

/// A parsed safetensors file: its header and data.
pub(crate) struct SafeTensors<'a> {
    pub(crate) path: &'a Path,
    header: serde_json::Map<String, serde_json::Value>,
    body: &'a [u8],
}

impl<'a> SafeTensors<'a> {
    pub(crate) fn parse(path: &'a Path, bytes: &'a [u8]) -> Result<Self, FidWeightsError> {
        let format = |detail: String| FidWeightsError::Format {
            path: path.into(),
            detail,
        };
        if bytes.len() < 8 {
            return Err(format(format!(
                "{} bytes, shorter than the 8-byte header length",
                bytes.len()
            )));
        }
        let header_len = u64::from_le_bytes([
            bytes[0], bytes[1], bytes[2], bytes[3], bytes[4], bytes[5], bytes[6], bytes[7],
        ]);
        let header_len = usize::try_from(header_len).unwrap_or(usize::MAX);
        if header_len > bytes.len() - 8 {
            return Err(format(format!(
                "header of {header_len} bytes, but the file has {} after the length",
                bytes.len() - 8
            )));
        }
        let header = serde_json::from_slice(&bytes[8..8 + header_len])
            .map_err(|e| format(format!("header: {e}")))?;
        Ok(Self {
            path,
            header,
            body: &bytes[8 + header_len..],
        })
    }

    /// The float32 tensor `name`, which must have `shape` and finite values.
    pub(crate) fn tensor(&self, name: &str, shape: &[usize]) -> Result<Vec<f32>, FidWeightsError> {
        let bad = |detail: String| FidWeightsError::Bad {
            path: self.path.into(),
            tensor: name.into(),
            detail,
        };
        let entry = self
            .header
            .get(name)
            .ok_or_else(|| FidWeightsError::Missing {
                path: self.path.into(),
                tensor: name.into(),
            })?;
        let dtype = entry.get("dtype").and_then(|d| d.as_str()).unwrap_or("?");
        if dtype != "F32" {
            return Err(bad(format!("dtype {dtype}, expected F32")));
        }
        let numbers = |key: &str| -> Vec<usize> {
            entry
                .get(key)
                .and_then(|s| s.as_array())
                .map(|a| {
                    a.iter()
                        .filter_map(|v| v.as_u64().map(|v| v as usize))
                        .collect()
                })
                .unwrap_or_default()
        };
        let got = numbers("shape");
        if got != shape {
            return Err(bad(format!("shape {got:?}, expected {shape:?}")));
        }
        let offsets = numbers("data_offsets");
        let n: usize = shape.iter().product();
        if offsets.len() != 2 || offsets[1] < offsets[0] || offsets[1] - offsets[0] != 4 * n {
            return Err(bad(format!(
                "data offsets {offsets:?}, expected a range of {} bytes",
                4 * n
            )));
        }
        if offsets[1] > self.body.len() {
            return Err(bad(format!(
                "bytes {}..{}, but the file's data ends at {} (truncated?)",
                offsets[0],
                offsets[1],
                self.body.len()
            )));
        }
        let data: Vec<f32> = self.body[offsets[0]..offsets[1]]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        if data.iter().any(|v| !v.is_finite()) {
            return Err(bad("a non-finite value".into()));
        }
        Ok(data)
    }
}
