//! 3D Gaussian Splatting PLY files: binary little-endian, one `vertex` element with
//! `x y z [nx ny nz] f_dc_0..2 [f_rest_*] opacity scale_0..2 rot_0..3`, all `float`.
//! `f_rest` is channel-major (`f_rest_{c * (K - 1) + k - 1}` holds coefficient k of
//! channel c), as the reference implementation writes it; its count gives the SH
//! degree (0, 9, 24 or 45 for degrees 0-3). Opacity is a logit and scales are
//! logarithms, as in the cloud. Properties may come in any order; unknown `float`
//! properties are ignored. A file read holds the avatar's scene group (the format has
//! no groups).

use std::path::Path;

use drape_shared::splat::layout::sh_coeffs;

use drape_engine::ops::splat::scene::GaussianCloud;

use crate::avatar::groups::Layer;

/// Why a PLY file could not be read or written; every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum PlyError {
    // `error`, not `source`: the message already carries it, and a `source` would make
    // anyhow print the OS error twice.
    #[error("{path}: {error}")]
    Io { path: String, error: std::io::Error },
    #[error("{path}: {problem}")]
    Format { path: String, problem: String },
}

fn format_error(path: &Path, problem: impl Into<String>) -> PlyError {
    PlyError::Format {
        path: path.display().to_string(),
        problem: problem.into(),
    }
}

const REQUIRED: [&str; 14] = [
    "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
    "rot_0", "rot_1", "rot_2", "rot_3",
];

/// Property layout of the vertex element.
struct Header {
    vertices: usize,
    names: Vec<String>,
    data_start: usize,
}

fn parse_header(path: &Path, bytes: &[u8]) -> Result<Header, PlyError> {
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .ok_or_else(|| {
            format_error(
                path,
                "no 'end_header' line: not a PLY file, or the header is truncated",
            )
        })?;
    let text = std::str::from_utf8(&bytes[..end])
        .map_err(|_| format_error(path, "the header is not text"))?;
    let mut lines = text.lines();
    if lines.next().map(str::trim) != Some("ply") {
        return Err(format_error(path, "the first line is not 'ply'"));
    }
    let mut vertices = None;
    let mut names = Vec::new();
    let mut in_vertex = false;
    let mut format_seen = false;
    for line in lines {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            [] => {}
            ["comment", ..] | ["obj_info", ..] => {}
            ["format", f, _] => {
                if *f != "binary_little_endian" {
                    return Err(format_error(
                        path,
                        format!("format '{f}' is not supported (binary_little_endian only)"),
                    ));
                }
                format_seen = true;
            }
            ["element", "vertex", n] => {
                vertices = Some(n.parse::<usize>().map_err(|_| {
                    format_error(path, format!("vertex count '{n}' is not a number"))
                })?);
                in_vertex = true;
            }
            ["element", other, _] => {
                if vertices.is_some() {
                    return Err(format_error(
                        path,
                        format!("element '{other}' after 'vertex' is not supported"),
                    ));
                }
                return Err(format_error(
                    path,
                    format!("element '{other}' before 'vertex' is not supported"),
                ));
            }
            ["property", ty, name] if in_vertex => {
                if *ty != "float" && *ty != "float32" {
                    return Err(format_error(
                        path,
                        format!(
                            "property '{name}' has type '{ty}'; every property must be 'float'"
                        ),
                    ));
                }
                names.push(name.to_string());
            }
            ["property", "list", ..] => {
                return Err(format_error(path, "list properties are not supported"))
            }
            _ => {
                return Err(format_error(
                    path,
                    format!("unexpected header line '{line}'"),
                ))
            }
        }
    }
    if !format_seen {
        return Err(format_error(path, "no 'format' line"));
    }
    let vertices = vertices.ok_or_else(|| format_error(path, "no 'element vertex' line"))?;
    Ok(Header {
        vertices,
        names,
        data_start: end + 11,
    })
}

/// Reads a 3DGS PLY file.
pub fn read(path: &Path) -> Result<GaussianCloud, PlyError> {
    let bytes = std::fs::read(path).map_err(|error| PlyError::Io {
        path: path.display().to_string(),
        error,
    })?;
    let header = parse_header(path, &bytes)?;
    let index = |name: &str| header.names.iter().position(|n| n == name);
    for name in REQUIRED {
        if index(name).is_none() {
            return Err(format_error(path, format!("missing property '{name}'")));
        }
    }
    let rest = header
        .names
        .iter()
        .filter(|n| n.starts_with("f_rest_"))
        .count();
    let degree = match rest {
        0 => 0,
        9 => 1,
        24 => 2,
        45 => 3,
        n => {
            return Err(format_error(
                path,
                format!("{n} f_rest properties: not an SH degree (0, 9, 24 or 45 expected)"),
            ))
        }
    };
    let k = sh_coeffs(degree);
    let rest_index: Vec<usize> = (0..rest)
        .map(|i| {
            index(&format!("f_rest_{i}"))
                .ok_or_else(|| format_error(path, format!("missing property 'f_rest_{i}'")))
        })
        .collect::<Result<_, _>>()?;
    if header.vertices == 0 {
        return Err(format_error(
            path,
            "no vertices (element vertex 0): nothing to render",
        ));
    }
    let stride = header.names.len() * 4;
    let needed = header
        .vertices
        .checked_mul(stride)
        .ok_or_else(|| format_error(path, "vertex count overflows"))?;
    let data = &bytes[header.data_start..];
    if data.len() < needed {
        return Err(format_error(
            path,
            format!("{} vertices of {stride} bytes need {needed} bytes of data, the file has {} (truncated, or the vertex count is too large)", header.vertices, data.len()),
        ));
    }
    let [x, y, z, dc0, dc1, dc2, op, s0, s1, s2, r0, r1, r2, r3] =
        REQUIRED.map(|n| index(n).expect("checked above"));
    // Every value a Gaussian is made of must be a number: one NaN blanks the image.
    let used: Vec<usize> = [x, y, z, dc0, dc1, dc2, op, s0, s1, s2, r0, r1, r2, r3]
        .into_iter()
        .chain(rest_index.iter().copied())
        .collect();
    let mut cloud = GaussianCloud::new(degree);
    let n = header.vertices;
    cloud.means.reserve(3 * n);
    for v in 0..n {
        let row = &data[v * stride..(v + 1) * stride];
        let f = |i: usize| {
            f32::from_le_bytes([row[4 * i], row[4 * i + 1], row[4 * i + 2], row[4 * i + 3]])
        };
        if let Some(&i) = used.iter().find(|&&i| !f(i).is_finite()) {
            return Err(format_error(
                path,
                format!("vertex {v}: property '{}' is {}", header.names[i], f(i)),
            ));
        }
        if [r0, r1, r2, r3].iter().all(|&i| f(i) == 0.0) {
            return Err(format_error(
                path,
                format!("vertex {v}: the rotation (rot_0..rot_3) is the zero quaternion"),
            ));
        }
        cloud.means.extend([f(x), f(y), f(z)]);
        cloud.log_scales.extend([f(s0), f(s1), f(s2)]);
        cloud.quats.extend([f(r0), f(r1), f(r2), f(r3)]);
        cloud.opacity_logits.push(f(op));
        cloud.sh.extend([f(dc0), f(dc1), f(dc2)]);
        for coeff in 1..k {
            for ch in 0..3 {
                cloud.sh.push(f(rest_index[ch * (k - 1) + coeff - 1]));
            }
        }
        cloud.groups.push(Layer::Scene.into());
    }
    Ok(cloud)
}

/// Writes a 3DGS PLY file (normals written as 0, as the reference implementation does).
pub fn write(path: &Path, cloud: &GaussianCloud) -> Result<(), PlyError> {
    let io = |error| PlyError::Io {
        path: path.display().to_string(),
        error,
    };
    let k = cloud.sh_coeffs();
    let mut header = String::from("ply\nformat binary_little_endian 1.0\n");
    header += &format!("element vertex {}\n", cloud.len());
    for name in [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    ] {
        header += &format!("property float {name}\n");
    }
    for i in 0..3 * (k - 1) {
        header += &format!("property float f_rest_{i}\n");
    }
    for name in [
        "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
    ] {
        header += &format!("property float {name}\n");
    }
    header += "end_header\n";
    let mut out = Vec::with_capacity(header.len() + cloud.len() * (17 + 3 * k) * 4);
    out.extend_from_slice(header.as_bytes());
    for i in 0..cloud.len() {
        let mut row: Vec<f32> = Vec::with_capacity(17 + 3 * k);
        row.extend_from_slice(&cloud.means[3 * i..3 * i + 3]);
        row.extend([0.0; 3]);
        let sh = &cloud.sh[3 * k * i..3 * k * (i + 1)];
        row.extend_from_slice(&sh[..3]);
        for ch in 0..3 {
            for coeff in 1..k {
                row.push(sh[3 * coeff + ch]);
            }
        }
        row.push(cloud.opacity_logits[i]);
        row.extend_from_slice(&cloud.log_scales[3 * i..3 * i + 3]);
        row.extend_from_slice(&cloud.quats[4 * i..4 * i + 4]);
        for v in row {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    drape_io::write(path, &out).map_err(io)
}
