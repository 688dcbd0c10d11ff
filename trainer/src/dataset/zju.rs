//! The ZJU-MoCap layout as public loaders read it: `annots.npy` (a pickled dict with
//! `cams` {K, D, R, T} per camera, T in millimetres, `p_c = R p_w + T`, and `ims`: per
//! frame the image path of every camera), `smpl_params/{i}.npy` (a pickled dict with
//! `poses` 1×72, `Rh` 1×3, `Th` 1×3, `shapes` 1×10) and `vertices/{i}.npy` (V×3).
//! Mask paths are image paths with `images` -> `mask` and `.jpg` -> `.png`.
//! [`ZjuCamera`] is the record `annots.npy` holds; it converts to and from the
//! trainer's [`Camera`].

use std::path::{Path, PathBuf};

use glam::DVec3;

use crate::camera::Camera;
use crate::dataset::distortion::Distortion;
use crate::dataset::error::DatasetError;
use crate::npy::{self, Array};
use crate::pickle::{decode_object_npy, encode_object_npy, PyValue};

/// One camera in metres.
#[derive(Clone, Debug, PartialEq)]
pub struct ZjuCamera {
    /// 3x3 intrinsics, rows.
    pub k: [[f64; 3]; 3],
    /// Distortion (k1 k2 p1 p2 k3).
    pub d: [f64; 5],
    /// World-to-camera rotation, rows.
    pub r: [[f64; 3]; 3],
    /// World-to-camera translation in metres (stored in millimetres on disk).
    pub t: [f64; 3],
}

impl ZjuCamera {
    /// The record of `camera`: no skew, no distortion. `K` is in OpenCV's pixel
    /// convention (pixel centres at integers), drape's camera in COLMAP's (centres at
    /// +0.5): the principal point moves by half a pixel.
    pub fn from_camera(camera: &Camera) -> Self {
        let c = camera;
        Self {
            k: [
                [c.fx, 0.0, c.cx - 0.5],
                [0.0, c.fy, c.cy - 0.5],
                [0.0, 0.0, 1.0],
            ],
            d: [0.0; 5],
            r: c.rotation,
            t: c.translation.to_array(),
        }
    }

    /// The pinhole camera for images of `width` x `height` (the annotations do not say),
    /// in drape's pixel convention (see [`Self::from_camera`]). Skew is dropped; the
    /// distortion is [`Self::distortion`], which the loader undoes on the images.
    pub fn camera(&self, width: u32, height: u32) -> Camera {
        let k = &self.k;
        Camera {
            fx: k[0][0],
            fy: k[1][1],
            cx: k[0][2] + 0.5,
            cy: k[1][2] + 0.5,
            width,
            height,
            rotation: self.r,
            translation: DVec3::from_array(self.t),
            near: Camera::NEAR,
        }
    }

    /// The lens distortion `D` (k1 k2 p1 p2 k3, OpenCV's model).
    pub fn distortion(&self) -> Distortion {
        Distortion::from_opencv(&self.d)
    }
}

/// Per-frame SMPL parameters in ZJU's convention.
#[derive(Clone, Debug, PartialEq)]
pub struct ZjuSmpl {
    pub poses: [f64; 72],
    pub rh: [f64; 3],
    pub th: [f64; 3],
    pub shapes: [f64; 10],
}

/// A sequence's annotations.
#[derive(Clone, Debug, PartialEq)]
pub struct ZjuAnnots {
    pub cameras: Vec<ZjuCamera>,
    /// `images[frame][camera]`, relative to the sequence directory.
    pub images: Vec<Vec<String>>,
}

fn arr(rows: usize, cols: usize, data: Vec<f64>) -> PyValue {
    PyValue::Array(Array::f64(vec![rows, cols], data))
}

/// The mask path of an image path, as ZJU loaders derive it.
pub fn mask_path(image: &str) -> String {
    image.replacen("images", "mask", 1).replace(".jpg", ".png")
}

impl ZjuAnnots {
    pub fn write(&self, dir: &Path) -> Result<(), DatasetError> {
        let cams = PyValue::dict(vec![
            (
                "K",
                PyValue::List(
                    self.cameras
                        .iter()
                        .map(|c| arr(3, 3, c.k.iter().flatten().copied().collect()))
                        .collect(),
                ),
            ),
            (
                "D",
                PyValue::List(
                    self.cameras
                        .iter()
                        .map(|c| arr(5, 1, c.d.to_vec()))
                        .collect(),
                ),
            ),
            (
                "R",
                PyValue::List(
                    self.cameras
                        .iter()
                        .map(|c| arr(3, 3, c.r.iter().flatten().copied().collect()))
                        .collect(),
                ),
            ),
            (
                "T",
                PyValue::List(
                    self.cameras
                        .iter()
                        .map(|c| arr(3, 1, c.t.iter().map(|v| v * 1000.0).collect()))
                        .collect(),
                ),
            ),
        ]);
        let ims = PyValue::List(
            self.images
                .iter()
                .map(|paths| {
                    PyValue::dict(vec![(
                        "ims",
                        PyValue::List(paths.iter().map(|p| PyValue::Str(p.clone())).collect()),
                    )])
                })
                .collect(),
        );
        let path = dir.join("annots.npy");
        std::fs::create_dir_all(dir).map_err(|e| DatasetError::io(dir, e))?;
        drape_io::write(
            &path,
            encode_object_npy(&PyValue::dict(vec![("cams", cams), ("ims", ims)])),
        )
        .map_err(|e| DatasetError::io(&path, e))
    }

    pub fn read(dir: &Path) -> Result<Self, DatasetError> {
        let path = dir.join("annots.npy");
        let name = path.display().to_string();
        let bytes = std::fs::read(&path).map_err(|e| DatasetError::io(&path, e))?;
        let v = decode_object_npy(&bytes, &name)?;
        let bad = |field: String, problem: &str| DatasetError::Field {
            file: name.clone(),
            field,
            problem: problem.to_string(),
        };
        let field = |key: &str| -> Result<Vec<Array>, DatasetError> {
            v.get("cams")
                .and_then(|c| c.get(key))
                .and_then(PyValue::as_list)
                .ok_or_else(|| bad(format!("cams['{key}']"), "missing or not a list"))?
                .iter()
                .enumerate()
                .map(|(i, a)| {
                    a.as_array()
                        .cloned()
                        .ok_or_else(|| bad(format!("cams['{key}'][{i}]"), "not an array"))
                })
                .collect()
        };
        let (ks, ds, rs, ts) = (field("K")?, field("D")?, field("R")?, field("T")?);
        if ks.len() != rs.len() || ks.len() != ts.len() || ks.len() != ds.len() {
            return Err(bad(
                "cams".into(),
                &format!(
                    "{} K, {} D, {} R and {} T",
                    ks.len(),
                    ds.len(),
                    rs.len(),
                    ts.len()
                ),
            ));
        }
        let mut cameras = Vec::new();
        for i in 0..ks.len() {
            let check = |a: &Array, key: &str, n: usize| -> Result<(), DatasetError> {
                if a.data.len() != n {
                    return Err(bad(
                        format!("cams['{key}'][{i}]"),
                        &format!("shape {:?}, expected {n} values", a.shape),
                    ));
                }
                if a.data.iter().any(|x| !x.is_finite()) {
                    return Err(bad(format!("cams['{key}'][{i}]"), "a non-finite value"));
                }
                Ok(())
            };
            check(&ks[i], "K", 9)?;
            check(&rs[i], "R", 9)?;
            check(&ts[i], "T", 3)?;
            let (fx, fy) = (ks[i].data[0], ks[i].data[4]);
            let (lo, hi) = (
                crate::dataset::colmap::MIN_FOCAL,
                crate::dataset::colmap::MAX_FOCAL,
            );
            if !(fx >= lo && fy >= lo && fx <= hi && fy <= hi) {
                return Err(bad(format!("cams['K'][{i}]"), &format!("focal length {fx} x {fy} pixels (fx = K[0][0], fy = K[1][1]); drape takes {lo} to {hi}")));
            }
            if ks[i].data[6..] != [0.0, 0.0, 1.0] {
                return Err(bad(
                    format!("cams['K'][{i}]"),
                    &format!(
                        "last row {:?}, a camera matrix's is [0, 0, 1]",
                        &ks[i].data[6..]
                    ),
                ));
            }
            if let Some(k) = ds[i].data.iter().position(|x| !x.is_finite()) {
                return Err(bad(
                    format!("cams['D'][{i}]"),
                    &format!("coefficient {k} is {} (not finite)", ds[i].data[k]),
                ));
            }
            if let Some(k) = ds[i].data.iter().skip(5).position(|&x| x != 0.0) {
                return Err(bad(format!("cams['D'][{i}]"), &format!("coefficient {} is {}: drape undistorts OpenCV's k1 k2 p1 p2 k3 (the rational and prism terms must be 0)", k + 5, ds[i].data[k + 5])));
            }
            if let Some(k) = ds[i].data.iter().position(|x| x.abs() > 1e3) {
                return Err(bad(
                    format!("cams['D'][{i}]"),
                    &format!(
                        "coefficient {k} is {}, beyond any lens (|D| <= 1000)",
                        ds[i].data[k]
                    ),
                ));
            }
            let m = |a: &Array| {
                [
                    [a.data[0], a.data[1], a.data[2]],
                    [a.data[3], a.data[4], a.data[5]],
                    [a.data[6], a.data[7], a.data[8]],
                ]
            };
            let r = m(&rs[i]);
            let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
                - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
                + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
            if (det - 1.0).abs() > 1e-3 {
                return Err(bad(
                    format!("cams['R'][{i}]"),
                    &format!("not a rotation (determinant {det})"),
                ));
            }
            for a in 0..3 {
                for b in 0..3 {
                    let dot: f64 = (0..3).map(|k| r[a][k] * r[b][k]).sum();
                    if (dot - if a == b { 1.0 } else { 0.0 }).abs() > 1e-3 {
                        return Err(bad(
                            format!("cams['R'][{i}]"),
                            &format!("not a rotation (row {a} . row {b} = {dot})"),
                        ));
                    }
                }
            }
            let mut d = [0.0; 5];
            for (k, x) in ds[i].data.iter().take(5).enumerate() {
                d[k] = *x;
            }
            cameras.push(ZjuCamera {
                k: m(&ks[i]),
                d,
                r,
                t: [0, 1, 2].map(|k| ts[i].data[k] / 1000.0),
            });
        }
        let images = v
            .get("ims")
            .and_then(PyValue::as_list)
            .ok_or_else(|| bad("ims".into(), "missing or not a list"))?
            .iter()
            .enumerate()
            .map(|(f, entry)| {
                entry
                    .get("ims")
                    .and_then(PyValue::as_list)
                    .ok_or_else(|| bad(format!("ims[{f}]['ims']"), "missing"))?
                    .iter()
                    .map(|p| {
                        p.as_str()
                            .map(str::to_string)
                            .ok_or_else(|| bad(format!("ims[{f}]"), "a non-string path"))
                    })
                    .collect::<Result<Vec<_>, _>>()
            })
            .collect::<Result<_, _>>()?;
        Ok(Self { cameras, images })
    }
}

impl ZjuSmpl {
    /// Writes `smpl_params/{frame}.npy`.
    pub fn write(&self, dir: &Path, frame: usize) -> Result<PathBuf, DatasetError> {
        let sub = dir.join("smpl_params");
        std::fs::create_dir_all(&sub).map_err(|e| DatasetError::io(&sub, e))?;
        let path = sub.join(format!("{frame}.npy"));
        let v = PyValue::dict(vec![
            ("poses", arr(1, 72, self.poses.to_vec())),
            ("Rh", arr(1, 3, self.rh.to_vec())),
            ("Th", arr(1, 3, self.th.to_vec())),
            ("shapes", arr(1, 10, self.shapes.to_vec())),
        ]);
        drape_io::write(&path, encode_object_npy(&v)).map_err(|e| DatasetError::io(&path, e))?;
        Ok(path)
    }

    /// Reads `smpl_params/{frame}.npy`, or `new_params/` or `params/` when that is what exists.
    pub fn read(dir: &Path, frame: usize) -> Result<Self, DatasetError> {
        let path = ["smpl_params", "new_params", "params"]
            .iter()
            .map(|d| dir.join(d).join(format!("{frame}.npy")))
            .find(|p| p.exists())
            .unwrap_or_else(|| dir.join("smpl_params").join(format!("{frame}.npy")));
        Self::read_file(&path)
    }

    /// Reads one parameter file (a pickled dict in a `.npy`).
    pub fn read_file(path: &Path) -> Result<Self, DatasetError> {
        let name = path.display().to_string();
        let bytes = std::fs::read(path).map_err(|e| DatasetError::io(path, e))?;
        let v = decode_object_npy(&bytes, &name)?;
        let bad = |key: &str, problem: String| DatasetError::Field {
            file: name.clone(),
            field: format!("'{key}'"),
            problem,
        };
        let get = |key: &str, n: usize| -> Result<Vec<f64>, DatasetError> {
            let a = v
                .get(key)
                .and_then(PyValue::as_array)
                .ok_or_else(|| bad(key, "missing or not an array".into()))?;
            if a.data.len() != n {
                return Err(bad(key, format!("shape {:?}, expected (1, {n})", a.shape)));
            }
            if let Some(i) = a.data.iter().position(|x| !x.is_finite()) {
                return Err(bad(key, format!("value {i} is {} (not finite)", a.data[i])));
            }
            Ok(a.data.clone())
        };
        Ok(Self {
            poses: get("poses", 72)?.try_into().expect("72"),
            rh: get("Rh", 3)?.try_into().expect("3"),
            th: get("Th", 3)?.try_into().expect("3"),
            shapes: {
                // SMPL files carry 10 or 300 shape coefficients; the body uses the first 10.
                let a = v
                    .get("shapes")
                    .and_then(PyValue::as_array)
                    .ok_or_else(|| bad("shapes", "missing or not an array".into()))?;
                if !(1..=300).contains(&a.data.len()) {
                    return Err(bad(
                        "shapes",
                        format!("shape {:?}, expected (1, 10) to (1, 300)", a.shape),
                    ));
                }
                if let Some(i) = a.data.iter().position(|x| !x.is_finite()) {
                    return Err(bad(
                        "shapes",
                        format!("value {i} is {} (not finite)", a.data[i]),
                    ));
                }
                std::array::from_fn(|k| a.data.get(k).copied().unwrap_or(0.0))
            },
        })
    }
}

/// Writes `vertices/{frame}.npy` (V×3 float64).
pub fn write_vertices(dir: &Path, frame: usize, vertices: &[[f64; 3]]) -> Result<(), DatasetError> {
    let sub = dir.join("vertices");
    std::fs::create_dir_all(&sub).map_err(|e| DatasetError::io(&sub, e))?;
    let path = sub.join(format!("{frame}.npy"));
    let a = Array::f64(
        vec![vertices.len(), 3],
        vertices.iter().flatten().copied().collect(),
    );
    drape_io::write(&path, npy::encode(&a)).map_err(|e| DatasetError::io(&path, e))
}

/// Reads `vertices/{frame}.npy`.
pub fn read_vertices(dir: &Path, frame: usize) -> Result<Vec<[f64; 3]>, DatasetError> {
    let path = dir.join("vertices").join(format!("{frame}.npy"));
    let name = path.display().to_string();
    let bytes = std::fs::read(&path).map_err(|e| DatasetError::io(&path, e))?;
    let a = npy::decode(&bytes, &name, None)?;
    if a.shape.len() != 2 || a.shape[1] != 3 {
        return Err(DatasetError::Field {
            file: name,
            field: "(array)".into(),
            problem: format!("shape {:?}, expected (V, 3)", a.shape),
        });
    }
    Ok(a.data.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
}
