//! COLMAP's text model (`cameras.txt`, `images.txt`, `points3D.txt`), written and
//! parsed exactly as COLMAP does: `images.txt` has two lines per image (pose and
//! name, then its 2D points as `X Y POINT3D_ID` triples, -1 for none), quaternions
//! are (w, x, y, z) world-to-camera, `p_c = R(q) p_w + t`. Errors name the file and line.
//! The records are what the files hold; [`ColmapImage::camera_and_distortion`] (or
//! [`ColmapImage::camera`], which drops the lens) and the `from_camera` constructors
//! convert to and from the trainer's [`Camera`] and [`Distortion`].

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use glam::DVec3;

use crate::camera::Camera;
use crate::dataset::distortion::Distortion;

/// COLMAP's quaternions come from the shared conversion (w kept >= 0, as COLMAP does).
pub use crate::mesh::rotation_to_quaternion;

/// A camera: COLMAP model name and its parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapCamera {
    pub id: u32,
    /// PINHOLE (fx fy cx cy), SIMPLE_PINHOLE (f cx cy), SIMPLE_RADIAL (f cx cy k),
    /// OPENCV (fx fy cx cy k1 k2 p1 p2), ...
    pub model: String,
    pub width: u32,
    pub height: u32,
    pub params: Vec<f64>,
}

impl ColmapCamera {
    /// A PINHOLE record of `camera`'s intrinsics and image size.
    pub fn from_camera(id: u32, camera: &Camera) -> Self {
        Self {
            id,
            model: "PINHOLE".into(),
            width: camera.width,
            height: camera.height,
            params: vec![camera.fx, camera.fy, camera.cx, camera.cy],
        }
    }

    /// A record of `camera`'s intrinsics and image size with lens `distortion`: PINHOLE
    /// without one, OPENCV when k3 is zero, else FULL_OPENCV with k4 = k5 = k6 = 0
    /// (COLMAP's OPENCV has no k3). [`Self::intrinsics`] reads each back.
    pub fn from_camera_and_distortion(id: u32, camera: &Camera, distortion: &Distortion) -> Self {
        let d = distortion;
        if d.is_identity() {
            return Self::from_camera(id, camera);
        }
        let mut params = vec![
            camera.fx, camera.fy, camera.cx, camera.cy, d.k1, d.k2, d.p1, d.p2,
        ];
        let model = if d.k3 == 0.0 {
            "OPENCV"
        } else {
            params.extend([d.k3, 0.0, 0.0, 0.0]);
            "FULL_OPENCV"
        };
        Self {
            id,
            model: model.into(),
            width: camera.width,
            height: camera.height,
            params,
        }
    }

    /// The pinhole intrinsics `[fx, fy, cx, cy]` and the lens of this record, for the
    /// models drape undistorts: SIMPLE_PINHOLE (f cx cy), PINHOLE (fx fy cx cy),
    /// SIMPLE_RADIAL (f cx cy k), RADIAL (f cx cy k1 k2), OPENCV (fx fy cx cy k1 k2 p1
    /// p2) and FULL_OPENCV (fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6) when its rational
    /// terms k4..k6 are zero. The error names `cameras.txt`, the camera and the field.
    pub fn intrinsics(&self) -> Result<([f64; 4], Distortion), ColmapError> {
        let err = |problem: CameraProblem| ColmapError::Camera {
            camera: self.id,
            model: self.model.clone(),
            problem,
        };
        let (names, simple): (&[&str], bool) = match self.model.as_str() {
            "SIMPLE_PINHOLE" => (&["f", "cx", "cy"], true),
            "PINHOLE" => (&["fx", "fy", "cx", "cy"], false),
            "SIMPLE_RADIAL" => (&["f", "cx", "cy", "k"], true),
            "RADIAL" => (&["f", "cx", "cy", "k1", "k2"], true),
            "OPENCV" => (&["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"], false),
            "FULL_OPENCV" => (
                &[
                    "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
                ],
                false,
            ),
            _ => return Err(err(CameraProblem::UnsupportedModel)),
        };
        if self.width == 0 || self.height == 0 {
            return Err(err(CameraProblem::Size {
                width: self.width,
                height: self.height,
            }));
        }
        let p = &self.params;
        if p.len() != names.len() {
            return Err(err(CameraProblem::ParamCount {
                got: p.len(),
                expected: names,
            }));
        }
        if let Some(i) = p.iter().position(|v| !v.is_finite()) {
            return Err(err(CameraProblem::NotFinite {
                param: names[i],
                value: p[i],
            }));
        }
        let (k, rest) = if simple {
            ([p[0], p[0], p[1], p[2]], &p[3..])
        } else {
            ([p[0], p[1], p[2], p[3]], &p[4..])
        };
        if !(k[0] >= MIN_FOCAL && k[1] >= MIN_FOCAL && k[0] <= MAX_FOCAL && k[1] <= MAX_FOCAL) {
            return Err(err(CameraProblem::FocalLength { fx: k[0], fy: k[1] }));
        }
        let c = |i: usize| rest.get(i).copied().unwrap_or(0.0);
        let distortion = match self.model.as_str() {
            "SIMPLE_RADIAL" | "RADIAL" => Distortion {
                k1: c(0),
                k2: c(1),
                ..Distortion::NONE
            },
            "OPENCV" | "FULL_OPENCV" => {
                // FULL_OPENCV's k4..k6 (rest[5..8]) divide by a second polynomial, which
                // `Distortion` does not model.
                if let Some(i) = (5..rest.len()).find(|&i| rest[i] != 0.0) {
                    return Err(err(CameraProblem::RationalModel {
                        param: names[i + 4],
                        value: rest[i],
                    }));
                }
                Distortion {
                    k1: c(0),
                    k2: c(1),
                    p1: c(2),
                    p2: c(3),
                    k3: c(4),
                }
            }
            _ => Distortion::NONE,
        };
        Ok((k, distortion))
    }

    /// (fx, fy, cx, cy) for the pinhole part of any supported model.
    pub fn pinhole(&self) -> Option<(f64, f64, f64, f64)> {
        let p = &self.params;
        match self.model.as_str() {
            "PINHOLE" | "OPENCV" | "FULL_OPENCV" if p.len() >= 4 => Some((p[0], p[1], p[2], p[3])),
            "SIMPLE_PINHOLE" | "SIMPLE_RADIAL" | "RADIAL" if p.len() >= 3 => {
                Some((p[0], p[0], p[1], p[2]))
            }
            _ => None,
        }
    }
}

/// A registered image.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapImage {
    pub id: u32,
    /// (w, x, y, z), world to camera.
    pub qvec: [f64; 4],
    pub tvec: [f64; 3],
    pub camera_id: u32,
    pub name: String,
    /// (x, y, point3D id or -1).
    pub points2d: Vec<(f64, f64, i64)>,
}

impl ColmapImage {
    /// The record of an image `name` taken by `camera` (COLMAP camera `camera_id`).
    pub fn from_camera(id: u32, camera_id: u32, name: String, camera: &Camera) -> Self {
        Self {
            id,
            qvec: rotation_to_quaternion(&camera.rotation),
            tvec: camera.translation.to_array(),
            camera_id,
            name,
            points2d: vec![],
        }
    }

    /// The camera that took this image with intrinsics from `camera` (its record in
    /// `cameras.txt`); None for a model without a pinhole part. Distortion is dropped:
    /// [`Self::camera_and_distortion`] keeps it, for loaders that undistort.
    pub fn camera(&self, camera: &ColmapCamera) -> Option<Camera> {
        let (fx, fy, cx, cy) = camera.pinhole()?;
        Some(Camera {
            fx,
            fy,
            cx,
            cy,
            width: camera.width,
            height: camera.height,
            rotation: self.rotation(),
            translation: DVec3::from_array(self.tvec),
            near: Camera::NEAR,
        })
    }

    /// The pinhole camera that took this image, with intrinsics from `camera` (its
    /// record in `cameras.txt`), and its lens: the images are this camera's after
    /// [`crate::dataset::distortion::Undistorter`]. An error for a model drape does not
    /// undistort (the fisheye models, FOV, THIN_PRISM_FISHEYE) or a malformed record;
    /// see [`ColmapCamera::intrinsics`].
    pub fn camera_and_distortion(
        &self,
        camera: &ColmapCamera,
    ) -> Result<(Camera, Distortion), ColmapError> {
        let ([fx, fy, cx, cy], distortion) = camera.intrinsics()?;
        Ok((
            Camera {
                fx,
                fy,
                cx,
                cy,
                width: camera.width,
                height: camera.height,
                rotation: self.rotation(),
                translation: DVec3::from_array(self.tvec),
                near: Camera::NEAR,
            },
            distortion,
        ))
    }

    /// World-to-camera rotation (rows), from the normalized quaternion.
    pub fn rotation(&self) -> [[f64; 3]; 3] {
        let (q, _) = drape_shared::splat::project::normalize_quat(self.qvec);
        drape_shared::splat::project::quat_to_mat(q)
    }
}

/// A 3D point with its colour, error and track.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapPoint {
    pub id: u64,
    pub xyz: [f64; 3],
    pub rgb: [u8; 3],
    pub error: f64,
    /// (image id, index of the 2D point in that image).
    pub track: Vec<(u32, u32)>,
}

/// A whole text model.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ColmapModel {
    pub cameras: BTreeMap<u32, ColmapCamera>,
    pub images: BTreeMap<u32, ColmapImage>,
    pub points: BTreeMap<u64, ColmapPoint>,
}

/// Why a model could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum ColmapError {
    // `error`, not `source`: the message carries it; a `source` would make anyhow
    // print the OS error twice.
    #[error("{path}: {error}")]
    Io { path: String, error: std::io::Error },
    /// A data line that is not the record its file holds: the file, the line and what
    /// is wrong with it.
    #[error("{path}:{line}: {problem}")]
    Parse {
        path: String,
        line: usize,
        problem: String,
    },
    /// A column of a data line that is not a number of its type: the file, the line,
    /// the column (as COLMAP's header names it) and its text.
    #[error("{path}: {problem}")]
    Model { path: String, problem: String },
    #[error("{path}:{line}: {field} '{text}' is not a valid number")]
    Number {
        path: String,
        line: usize,
        field: &'static str,
        text: String,
    },
    /// A camera record that is no pinhole camera and lens drape undistorts: the
    /// camera's id and model and what is wrong with it.
    #[error("cameras.txt: camera {camera} {}", problem.describe(model))]
    Camera {
        camera: u32,
        model: String,
        problem: CameraProblem,
    },
}

/// What is wrong with a camera record ([`ColmapError::Camera`]).
#[derive(Clone, Debug, PartialEq)]
pub enum CameraProblem {
    /// A model drape does not undistort (the fisheye models, FOV, THIN_PRISM_FISHEYE).
    UnsupportedModel,
    /// PARAMS has `got` values; the model has `expected` (their names).
    ParamCount {
        got: usize,
        expected: &'static [&'static str],
    },
    /// A parameter is NaN or infinite.
    NotFinite { param: &'static str, value: f64 },
    /// A focal length is zero or negative.
    FocalLength { fx: f64, fy: f64 },
    /// WIDTH or HEIGHT is zero.
    Size { width: u32, height: u32 },
    /// FULL_OPENCV with a non-zero rational term (k4, k5 or k6), which `Distortion`
    /// does not model.
    RationalModel { param: &'static str, value: f64 },
}

impl CameraProblem {
    /// The message after "camera ID", for a camera of `model`.
    fn describe(&self, model: &str) -> String {
        match self {
            Self::UnsupportedModel => format!("has model {model}, which drape does not undistort (it reads SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV and FULL_OPENCV)"),
            Self::ParamCount { got, expected } => format!("({model}) has {got} PARAMS, expected {} ({})", expected.len(), expected.join(" ")),
            Self::NotFinite { param, value } => format!("({model}) has {param} = {value}, which is not finite"),
            Self::FocalLength { fx, fy } => format!("({model}) has focal length {fx} x {fy} pixels; drape takes {MIN_FOCAL} to {MAX_FOCAL}"),
            Self::Size { width, height } => format!("({model}) has WIDTH x HEIGHT {width} x {height}; both must be at least 1"),
            Self::RationalModel { param, value } => format!("({model}) has {param} = {value}: drape does not undistort the rational model (k4, k5, k6 must be 0)"),
        }
    }
}

/// The focal lengths (pixels) a camera may have: below one pixel the field of view is
/// nearly 180°, above ten million a telescope's.
pub const MIN_FOCAL: f64 = 1.0;
pub const MAX_FOCAL: f64 = 1e7;

/// Formats a float the way Python's `repr` would for round-tripping: shortest exact.
fn num(v: f64) -> String {
    let s = format!("{v}");
    if s.contains('.') || s.contains('e') || s.contains("inf") || s.contains("NaN") {
        s
    } else {
        format!("{s}.0")
    }
}

impl ColmapModel {
    /// Writes `cameras.txt`, `images.txt` and `points3D.txt` into `dir`.
    pub fn write_text(&self, dir: &Path) -> Result<(), ColmapError> {
        let io = |path: &Path| {
            let p = path.display().to_string();
            move |error| ColmapError::Io {
                path: p.clone(),
                error,
            }
        };
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let mut cams = String::from("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
        let _ = writeln!(cams, "# Number of cameras: {}", self.cameras.len());
        for c in self.cameras.values() {
            let params: Vec<String> = c.params.iter().map(|&p| num(p)).collect();
            let _ = writeln!(
                cams,
                "{} {} {} {} {}",
                c.id,
                c.model,
                c.width,
                c.height,
                params.join(" ")
            );
        }
        let mut imgs = String::from("# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n");
        let _ = writeln!(imgs, "# Number of images: {}", self.images.len());
        for i in self.images.values() {
            let q: Vec<String> = i.qvec.iter().chain(&i.tvec).map(|&v| num(v)).collect();
            let _ = writeln!(imgs, "{} {} {} {}", i.id, q.join(" "), i.camera_id, i.name);
            let pts: Vec<String> = i
                .points2d
                .iter()
                .map(|(x, y, id)| format!("{} {} {id}", num(*x), num(*y)))
                .collect();
            let _ = writeln!(imgs, "{}", pts.join(" "));
        }
        let mut pts = String::from("# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n");
        let _ = writeln!(pts, "# Number of points: {}", self.points.len());
        for p in self.points.values() {
            let track: Vec<String> = p.track.iter().map(|(i, k)| format!("{i} {k}")).collect();
            let _ = writeln!(
                pts,
                "{} {} {} {} {} {} {} {} {}",
                p.id,
                num(p.xyz[0]),
                num(p.xyz[1]),
                num(p.xyz[2]),
                p.rgb[0],
                p.rgb[1],
                p.rgb[2],
                num(p.error),
                track.join(" ")
            );
        }
        for (name, text) in [
            ("cameras.txt", cams),
            ("images.txt", imgs),
            ("points3D.txt", pts),
        ] {
            let path = dir.join(name);
            drape_io::write(&path, text).map_err(io(&path))?;
        }
        Ok(())
    }

    /// Reads the three files from `dir`.
    pub fn read_text(dir: &Path) -> Result<Self, ColmapError> {
        let read = |name: &str| {
            let path = dir.join(name);
            std::fs::read_to_string(&path)
                .map(|t| (path.display().to_string(), t))
                .map_err(|error| ColmapError::Io {
                    path: path.display().to_string(),
                    error,
                })
        };
        let mut model = ColmapModel::default();

        let (path, text) = read("cameras.txt")?;
        for (n, line) in data_lines(&text) {
            let at = At {
                path: &path,
                line: n,
            };
            let w: Vec<&str> = line.split_whitespace().collect();
            if w.len() < 5 {
                return Err(at.err(format!(
                    "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., got '{line}'"
                )));
            }
            let cam = ColmapCamera {
                id: at.num(w[0], "CAMERA_ID")?,
                model: w[1].to_string(),
                width: at.num(w[2], "WIDTH")?,
                height: at.num(w[3], "HEIGHT")?,
                params: w[4..]
                    .iter()
                    .map(|v| at.num::<f64>(v, "PARAMS"))
                    .collect::<Result<_, _>>()?,
            };
            if model.cameras.contains_key(&cam.id) {
                return Err(at.err(format!("camera {} is listed twice", cam.id)));
            }
            model.cameras.insert(cam.id, cam);
        }

        let (path, text) = read("images.txt")?;
        let lines: Vec<(usize, &str)> = text
            .lines()
            .enumerate()
            .map(|(i, l)| (i + 1, l))
            .filter(|(_, l)| !l.starts_with('#'))
            .collect();
        let mut k = 0;
        while k < lines.len() {
            let (n, line) = lines[k];
            if line.trim().is_empty() {
                k += 1;
                continue;
            }
            let at = At {
                path: &path,
                line: n,
            };
            let w: Vec<&str> = line.split_whitespace().collect();
            if w.len() < 10 {
                return Err(at.err(format!(
                    "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got '{line}'"
                )));
            }
            let f = |i: usize, field: &'static str| at.num::<f64>(w[i], field);
            let qvec = [f(1, "QW")?, f(2, "QX")?, f(3, "QY")?, f(4, "QZ")?];
            let tvec = [f(5, "TX")?, f(6, "TY")?, f(7, "TZ")?];
            let id: u32 = at.num(w[0], "IMAGE_ID")?;
            let camera_id: u32 = at.num(w[8], "CAMERA_ID")?;
            if !model.cameras.contains_key(&camera_id) {
                return Err(at.err(format!(
                    "image {id} uses camera {camera_id}, which cameras.txt does not list"
                )));
            }
            let name = w[9..].join(" ");
            let (n2, points_line) = lines.get(k + 1).copied().unwrap_or((n + 1, ""));
            let at2 = At {
                path: &path,
                line: n2,
            };
            let v: Vec<&str> = points_line.split_whitespace().collect();
            if v.len() % 3 != 0 {
                return Err(at2.err("POINTS2D is not a list of X Y POINT3D_ID triples".into()));
            }
            let mut points2d = Vec::with_capacity(v.len() / 3);
            for c in v.chunks_exact(3) {
                points2d.push((
                    at2.num(c[0], "X")?,
                    at2.num(c[1], "Y")?,
                    at2.num(c[2], "POINT3D_ID")?,
                ));
            }
            if model.images.contains_key(&id) {
                return Err(at.err(format!("image {id} is listed twice")));
            }
            if let Some(other) = model.images.values().find(|i| i.name == name) {
                return Err(at.err(format!(
                    "image {id} is named '{name}', as image {} is",
                    other.id
                )));
            }
            model.images.insert(
                id,
                ColmapImage {
                    id,
                    qvec,
                    tvec,
                    camera_id,
                    name,
                    points2d,
                },
            );
            k += 2;
        }

        let (path, text) = read("points3D.txt")?;
        for (n, line) in data_lines(&text) {
            let at = At {
                path: &path,
                line: n,
            };
            let w: Vec<&str> = line.split_whitespace().collect();
            if w.len() < 8 || (w.len() - 8) % 2 != 0 {
                return Err(at.err(format!(
                    "expected POINT3D_ID X Y Z R G B ERROR TRACK..., got '{line}'"
                )));
            }
            let p = ColmapPoint {
                id: at.num(w[0], "POINT3D_ID")?,
                xyz: [at.num(w[1], "X")?, at.num(w[2], "Y")?, at.num(w[3], "Z")?],
                rgb: [at.num(w[4], "R")?, at.num(w[5], "G")?, at.num(w[6], "B")?],
                error: at.num(w[7], "ERROR")?,
                track: w[8..]
                    .chunks_exact(2)
                    .map(|c| Ok((at.num(c[0], "IMAGE_ID")?, at.num(c[1], "POINT2D_IDX")?)))
                    .collect::<Result<_, ColmapError>>()?,
            };
            if let Some(v) = p.xyz.iter().chain([&p.error]).find(|v| !v.is_finite()) {
                return Err(at.err(format!("point {} has {v} among X Y Z ERROR", p.id)));
            }
            if model.points.contains_key(&p.id) {
                return Err(at.err(format!("point {} is listed twice", p.id)));
            }
            model.points.insert(p.id, p);
        }
        if model.images.is_empty() {
            return Err(ColmapError::Model {
                path: dir.join("images.txt").display().to_string(),
                problem: "no images: a model needs at least one registered image".into(),
            });
        }
        Ok(model)
    }
}

fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

/// A data line of a file, for its errors.
#[derive(Clone, Copy)]
struct At<'a> {
    path: &'a str,
    line: usize,
}

impl At<'_> {
    /// [`ColmapError::Parse`] at this line.
    fn err(self, problem: String) -> ColmapError {
        ColmapError::Parse {
            path: self.path.to_string(),
            line: self.line,
            problem,
        }
    }

    /// Column `field` of this line as a number, or [`ColmapError::Number`].
    fn num<T: std::str::FromStr>(self, text: &str, field: &'static str) -> Result<T, ColmapError> {
        text.parse::<T>().map_err(|_| ColmapError::Number {
            path: self.path.to_string(),
            line: self.line,
            field,
            text: text.to_string(),
        })
    }
}
