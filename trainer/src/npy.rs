//! NumPy `.npy` arrays and `.npz` archives, as numpy writes and reads them (format
//! 1.0/2.0/3.0 headers; little-endian `f8`, `f4`, `i8`, `i4`, `u4`, `u1`, `b1`; C or
//! Fortran order, written in C order). Every error names the file and, inside an
//! archive, the key.
//!
//! Archives from the wild carry entries we have no use for and cannot decode: AMASS
//! stores `gender` as text (`<U4`, `|S6`) or as a pickled object (`|O`). Reading an
//! archive therefore never fails on an entry's dtype: [`Npz`] keeps such entries as
//! [`Undecoded`], and only asking for one ([`Npz::require`]) is an error, naming the
//! file, the key and the dtype. A corrupt or truncated entry still fails the read.
//! Scalars are accepted as numpy writes them (`np.savez(f, fps=30)` is a 0-d array) and
//! as 1-element arrays ([`scalar`]).

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::path::Path;

/// Element types this module reads and writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dtype {
    F64,
    F32,
    I64,
    I32,
    U32,
    U8,
    Bool,
}

impl Dtype {
    fn descr(self) -> &'static str {
        match self {
            Dtype::F64 => "<f8",
            Dtype::F32 => "<f4",
            Dtype::I64 => "<i8",
            Dtype::I32 => "<i4",
            Dtype::U32 => "<u4",
            Dtype::U8 => "|u1",
            Dtype::Bool => "|b1",
        }
    }

    fn size(self) -> usize {
        match self {
            Dtype::F64 | Dtype::I64 => 8,
            Dtype::F32 | Dtype::I32 | Dtype::U32 => 4,
            Dtype::U8 | Dtype::Bool => 1,
        }
    }

    fn parse(descr: &str) -> Option<Self> {
        Some(match descr {
            "<f8" | "f8" => Dtype::F64,
            "<f4" | "f4" => Dtype::F32,
            "<i8" | "i8" => Dtype::I64,
            "<i4" | "i4" => Dtype::I32,
            "<u4" | "u4" => Dtype::U32,
            "|u1" | "u1" | "<u1" => Dtype::U8,
            "|b1" | "b1" | "?" => Dtype::Bool,
            _ => return None,
        })
    }
}

/// An n-dimensional array with its values widened to f64 (all dtypes above are exact
/// in f64 except i64 beyond 2^53, which the loaders never need).
#[derive(Clone, Debug, PartialEq)]
pub struct Array {
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    pub data: Vec<f64>,
}

impl Array {
    pub fn new(dtype: Dtype, shape: Vec<usize>, data: Vec<f64>) -> Self {
        assert_eq!(
            shape.iter().product::<usize>(),
            data.len(),
            "shape {shape:?} does not hold {} values",
            data.len()
        );
        Self { dtype, shape, data }
    }

    pub fn f64(shape: Vec<usize>, data: Vec<f64>) -> Self {
        Self::new(Dtype::F64, shape, data)
    }
}

/// Why an array or archive could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum NpyError {
    // `error`, not `source`: the message carries it; a `source` would make anyhow
    // print the OS error twice.
    #[error("{file}: {error}")]
    Io { file: String, error: std::io::Error },
    #[error("{file}{}: {problem}", key.as_ref().map(|k| format!(" ['{k}']")).unwrap_or_default())]
    Format {
        file: String,
        key: Option<String>,
        problem: String,
    },
}

fn fmt_err(file: &str, key: Option<&str>, problem: impl Into<String>) -> NpyError {
    NpyError::Format {
        file: file.to_string(),
        key: key.map(str::to_string),
        problem: problem.into(),
    }
}

/// Encodes one array as `.npy` bytes (format 1.0).
pub fn encode(a: &Array) -> Vec<u8> {
    let shape = match a.shape.len() {
        1 => format!("({},)", a.shape[0]),
        _ => format!(
            "({})",
            a.shape
                .iter()
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut header = format!(
        "{{'descr': '{}', 'fortran_order': False, 'shape': {shape}, }}",
        a.dtype.descr()
    );
    // Pad so that the data starts at a multiple of 64 bytes, ending in '\n'.
    let total = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - total % 64) % 64));
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + a.data.len() * a.dtype.size());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for &v in &a.data {
        match a.dtype {
            Dtype::F64 => out.extend_from_slice(&v.to_le_bytes()),
            Dtype::F32 => out.extend_from_slice(&(v as f32).to_le_bytes()),
            Dtype::I64 => out.extend_from_slice(&(v as i64).to_le_bytes()),
            Dtype::I32 => out.extend_from_slice(&(v as i32).to_le_bytes()),
            Dtype::U32 => out.extend_from_slice(&(v as u32).to_le_bytes()),
            Dtype::U8 => out.push(v as u8),
            Dtype::Bool => out.push(u8::from(v != 0.0)),
        }
    }
    out
}

fn header_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let at = header.find(&format!("'{key}'"))? + key.len() + 2;
    let rest = header[at..].trim_start().strip_prefix(':')?.trim_start();
    if let Some(stripped) = rest.strip_prefix('(') {
        return stripped.find(')').map(|end| &stripped[..end]);
    }
    let end = rest.find([',', '}']).unwrap_or(rest.len());
    Some(rest[..end].trim().trim_matches('\''))
}

/// What a `.npy` header says.
struct Header {
    descr: String,
    fortran_order: bool,
    shape: Vec<usize>,
    /// Offset of the first data byte.
    data_start: usize,
}

fn parse_header(bytes: &[u8], err: &dyn Fn(String) -> NpyError) -> Result<Header, NpyError> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(err("not a .npy array (bad magic)".into()));
    }
    let (header_len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(err("truncated header".into()));
            }
            (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            )
        }
        v => return Err(err(format!("unsupported .npy version {v}"))),
    };
    let header_end = start + header_len;
    if bytes.len() < header_end {
        return Err(err("truncated header".into()));
    }
    let header = std::str::from_utf8(&bytes[start..header_end])
        .map_err(|_| err("header is not text".into()))?;
    let descr = header_value(header, "descr").ok_or_else(|| err("header has no 'descr'".into()))?;
    let shape_text =
        header_value(header, "shape").ok_or_else(|| err("header has no 'shape'".into()))?;
    let shape: Vec<usize> = shape_text
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<usize>()
                .map_err(|_| err(format!("shape '({shape_text})' is not a tuple of sizes")))
        })
        .collect::<Result<_, _>>()?;
    Ok(Header {
        descr: descr.to_string(),
        fortran_order: header_value(header, "fortran_order") == Some("True"),
        shape,
        data_start: header_end,
    })
}

/// Decodes `.npy` bytes; `file`/`key` name them in errors.
pub fn decode(bytes: &[u8], file: &str, key: Option<&str>) -> Result<Array, NpyError> {
    let err = |p: String| fmt_err(file, key, p);
    let header = parse_header(bytes, &err)?;
    let dtype = Dtype::parse(&header.descr).ok_or_else(|| err(unsupported_dtype(&header.descr)))?;
    decode_body(bytes, &header, dtype, &err)
}

fn unsupported_dtype(descr: &str) -> String {
    format!("dtype '{descr}' is not supported (need little-endian f8, f4, i8, i4, u4, u1 or b1; pickled objects are read by the ZJU loader)")
}

fn decode_body(
    bytes: &[u8],
    header: &Header,
    dtype: Dtype,
    err: &dyn Fn(String) -> NpyError,
) -> Result<Array, NpyError> {
    let shape = &header.shape;
    // Checked: a header may declare any shape, and the file's length bounds the data.
    let needed = shape
        .iter()
        .try_fold(dtype.size(), |a, &d| a.checked_mul(d))
        .ok_or_else(|| {
            err(format!(
                "shape {shape:?} of {}-byte values overflows",
                dtype.size()
            ))
        })?;
    let body = &bytes[header.data_start..];
    if body.len() < needed {
        return Err(err(format!(
            "truncated: shape {shape:?} needs {needed} bytes, found {}",
            body.len()
        )));
    }
    let data: Vec<f64> = body[..needed]
        .chunks_exact(dtype.size())
        .map(|c| match dtype {
            Dtype::F64 => f64::from_le_bytes(c.try_into().expect("8 bytes")),
            Dtype::F32 => f64::from(f32::from_le_bytes(c.try_into().expect("4 bytes"))),
            Dtype::I64 => i64::from_le_bytes(c.try_into().expect("8 bytes")) as f64,
            Dtype::I32 => f64::from(i32::from_le_bytes(c.try_into().expect("4 bytes"))),
            Dtype::U32 => f64::from(u32::from_le_bytes(c.try_into().expect("4 bytes"))),
            Dtype::U8 | Dtype::Bool => f64::from(c[0]),
        })
        .collect();
    // numpy saves an array that is Fortran- but not C-contiguous (a transpose, say) in
    // Fortran order; callers index in C order, so reorder.
    let data = if header.fortran_order && shape.len() > 1 {
        fortran_to_c(&data, shape)
    } else {
        data
    };
    Ok(Array {
        dtype,
        shape: shape.clone(),
        data,
    })
}

/// `data` laid out with the first index fastest, rewritten with the last fastest.
fn fortran_to_c(data: &[f64], shape: &[usize]) -> Vec<f64> {
    let mut out = Vec::with_capacity(data.len());
    let mut index = vec![0usize; shape.len()];
    for _ in 0..data.len() {
        let mut offset = 0;
        let mut stride = 1;
        for (i, &d) in index.iter().zip(shape) {
            offset += i * stride;
            stride *= d;
        }
        out.push(data[offset]);
        // Advance the C-order multi-index, last axis fastest.
        for axis in (0..shape.len()).rev() {
            index[axis] += 1;
            if index[axis] < shape[axis] {
                break;
            }
            index[axis] = 0;
        }
    }
    out
}

/// Writes arrays as an uncompressed `.npz` (what `numpy.savez` writes).
pub fn write_npz(path: &Path, arrays: &BTreeMap<String, Array>) -> Result<(), NpyError> {
    let file_name = path.display().to_string();
    let io = |error| NpyError::Io {
        file: file_name.clone(),
        error,
    };
    // The zip's own errors are carried out of the writer as I/O errors' payloads.
    let zip_err = |key: Option<&str>, e: zip::result::ZipError| {
        std::io::Error::other(fmt_err(&file_name, key, e.to_string()))
    };
    let written = drape_io::write_with(path, |file| {
        let mut zip = zip::ZipWriter::new(file);
        let options = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored);
        for (key, array) in arrays {
            zip.start_file(format!("{key}.npy"), options)
                .map_err(|e| zip_err(Some(key), e))?;
            zip.write_all(&encode(array))?;
        }
        zip.finish().map_err(|e| zip_err(None, e))?;
        Ok(())
    });
    written.map_err(|e| match e.downcast::<NpyError>() {
        Ok(npy) => npy,
        Err(e) => io(e),
    })
}

/// An archive entry whose dtype this module does not decode (text, bytes, pickled
/// objects, big-endian numbers): what it is, for the error if a caller asks for it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Undecoded {
    pub descr: String,
    pub shape: Vec<usize>,
}

/// An `.npz` archive as read: the arrays this module decodes, and the entries it does
/// not, kept so that asking for one says why it cannot be had.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Npz {
    /// The path as given, for errors.
    pub file: String,
    pub arrays: BTreeMap<String, Array>,
    pub undecoded: BTreeMap<String, Undecoded>,
}

impl Npz {
    /// Reads an archive (stored or deflated entries). Fails on an unreadable or corrupt
    /// archive or entry, not on an entry's dtype.
    pub fn read(path: &Path) -> Result<Self, NpyError> {
        let file_name = path.display().to_string();
        let file = std::fs::File::open(path).map_err(|error| NpyError::Io {
            file: file_name.clone(),
            error,
        })?;
        let file_len = file.metadata().map(|m| m.len()).unwrap_or(u64::MAX);
        let mut zip = zip::ZipArchive::new(file).map_err(|e| {
            fmt_err(
                &file_name,
                None,
                format!("not a readable .npz archive (truncated or corrupt?): {e}"),
            )
        })?;
        let mut out = Npz {
            file: file_name.clone(),
            ..Npz::default()
        };
        for i in 0..zip.len() {
            let mut entry = zip
                .by_index(i)
                .map_err(|e| fmt_err(&file_name, None, format!("entry {i}: {e}")))?;
            let name = entry.name().to_string();
            let key = name.strip_suffix(".npy").unwrap_or(&name).to_string();
            // An entry's declared size is only a claim: deflate expands at most about
            // 1032 times, and a stored entry holds what it occupies.
            // Its compressed size is a claim too: the file's length bounds it.
            let packed = entry.compressed_size().min(file_len);
            let most = if entry.compression() == zip::CompressionMethod::Stored {
                packed
            } else {
                packed.saturating_mul(1032).saturating_add(1024)
            };
            if entry.size() > most {
                return Err(fmt_err(
                    &file_name,
                    Some(&key),
                    format!(
                        "entry declares {} bytes, more than its {} compressed bytes can hold",
                        entry.size(),
                        entry.compressed_size()
                    ),
                ));
            }
            // Reserved up to 64 MiB; a larger entry grows as it is read (and so cannot
            // reserve memory its data does not fill).
            let mut bytes = Vec::with_capacity(entry.size().min(1 << 26) as usize);
            std::io::Read::take(&mut entry, most.saturating_add(1))
                .read_to_end(&mut bytes)
                .map_err(|e| {
                    fmt_err(
                        &file_name,
                        Some(&key),
                        format!("truncated or corrupt entry: {e}"),
                    )
                })?;
            let err = |p: String| fmt_err(&file_name, Some(&key), p);
            let header = parse_header(&bytes, &err)?;
            match Dtype::parse(&header.descr) {
                Some(dtype) => {
                    out.arrays
                        .insert(key.clone(), decode_body(&bytes, &header, dtype, &err)?);
                }
                None => {
                    out.undecoded.insert(
                        key.clone(),
                        Undecoded {
                            descr: header.descr,
                            shape: header.shape,
                        },
                    );
                }
            }
        }
        Ok(out)
    }

    /// Whether the archive has `key`, decoded or not.
    pub fn contains(&self, key: &str) -> bool {
        self.arrays.contains_key(key) || self.undecoded.contains_key(key)
    }

    /// [`require`] on this archive; an undecoded `key` is an error naming its dtype.
    pub fn require(&self, key: &str, shape: &[Option<usize>]) -> Result<&Array, NpyError> {
        self.check_decoded(key)?;
        require(&self.arrays, &self.file, key, shape)
    }

    /// [`scalar`] on this archive; an undecoded `key` is an error naming its dtype.
    pub fn scalar(&self, key: &str) -> Result<f64, NpyError> {
        self.check_decoded(key)?;
        scalar(&self.arrays, &self.file, key)
    }

    fn check_decoded(&self, key: &str) -> Result<(), NpyError> {
        match self.undecoded.get(key) {
            Some(u) => Err(fmt_err(
                &self.file,
                Some(key),
                format!("{} (shape {:?})", unsupported_dtype(&u.descr), u.shape),
            )),
            None => Ok(()),
        }
    }
}

/// Reads the arrays of an `.npz` archive that this module decodes, leaving out entries
/// of other dtypes (see [`Npz`] to learn which).
pub fn read_npz(path: &Path) -> Result<BTreeMap<String, Array>, NpyError> {
    Npz::read(path).map(|npz| npz.arrays)
}

/// Looks up `key` and checks its shape (`None` in `shape` matches any size) and that
/// every value is finite.
pub fn require<'a>(
    arrays: &'a BTreeMap<String, Array>,
    file: &str,
    key: &str,
    shape: &[Option<usize>],
) -> Result<&'a Array, NpyError> {
    let a = arrays
        .get(key)
        .ok_or_else(|| fmt_err(file, Some(key), "missing key"))?;
    let matches = a.shape.len() == shape.len()
        && a.shape
            .iter()
            .zip(shape)
            .all(|(&d, s)| s.is_none_or(|s| s == d));
    if !matches {
        let want: Vec<String> = shape
            .iter()
            .map(|s| s.map(|d| d.to_string()).unwrap_or("*".into()))
            .collect();
        return Err(fmt_err(
            file,
            Some(key),
            format!("shape {:?}, expected ({})", a.shape, want.join(", ")),
        ));
    }
    if let Some(i) = a.data.iter().position(|v| !v.is_finite()) {
        return Err(fmt_err(
            file,
            Some(key),
            format!("value {i} is {} (not finite)", a.data[i]),
        ));
    }
    Ok(a)
}

/// A finite scalar under `key`: a 0-d array (what `np.savez(f, fps=30)` writes) or a
/// 1-element one (shape `[1]`, what this module's writers use).
pub fn scalar(arrays: &BTreeMap<String, Array>, file: &str, key: &str) -> Result<f64, NpyError> {
    let a = arrays
        .get(key)
        .ok_or_else(|| fmt_err(file, Some(key), "missing key"))?;
    if !(a.shape.is_empty() || a.shape == [1]) {
        return Err(fmt_err(
            file,
            Some(key),
            format!("shape {:?}, expected a scalar (shape () or (1))", a.shape),
        ));
    }
    let v = a.data[0];
    if !v.is_finite() {
        return Err(fmt_err(file, Some(key), format!("{v} is not finite")));
    }
    Ok(v)
}
