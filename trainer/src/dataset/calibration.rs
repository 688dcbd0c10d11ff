//! Calibrations of a static rig of cameras, as the capture tools write them: a
//! Qualisys `.qca.txt` (XML) converted exactly as Pose2Sim's `calib_qca_fun` does, and
//! a Pose2Sim / Sports2D `Calib*.toml`. Each reads into one [`RigCamera`] a camera: its
//! name, the trainer's [`Camera`] (image size, intrinsics, world-to-camera pose in
//! metres) and its lens [`Distortion`] (k1, k2, p1, p2; k3 = 0).
//!
//! Conventions. Both files describe OpenCV cameras: `x_cam = R X_world + t`, x right,
//! y down, z forward, t in metres, and a principal point in OpenCV's pixel convention
//! (pixel centres at integers). drape's [`Camera`] puts pixel centres at +0.5, so
//! `camera.cx = file cx + 0.5` (and `cy`); [`RigCamera::opencv_k`] gives the file's K
//! back.
//!
//! Qualisys (`read_qca`, Pose2Sim 0.10.49's `read_qca` + `calib_qca_fun`, checked
//! against its own output in `tests/fixtures/pose2sim/`): only `<camera>`s whose
//! `model` contains "video" or "none" (Qualisys video cameras; marker-only cameras are
//! left out, as Pose2Sim does), in the natural order of their `serial`. With the binning
//! factor b (1 unless the video was filmed binned, e.g. 2 for 540p from a 1080p sensor):
//! - size: W = (fov_video.right - fov_video.left + 1) / b, H = (bottom - top + 1) / b;
//! - K: the `intrinsic` focal lengths and principal point are in 1/64 px:
//!   fx = focalLengthU / 64 / b, cx = centerPointU / 64 / b - fov_video.left (the offset
//!   is not binned, as Pose2Sim has it), fy, cy likewise with V and top; skew ignored;
//! - distortion: [radialDistortion1, radialDistortion2, tangentalDistortion1,
//!   tangentalDistortion2] / 64 / b (radialDistortion3 is ignored, as Pose2Sim does);
//! - pose: the `transform` M (rows r11 r12 r13, ...) and camera centre p = (x, y, z)
//!   in mm: R = diag(1, -1, -1) M, t = -R p / 1000 (Pose2Sim inverts the transform, then
//!   turns the camera by pi about its x axis; M must be a rotation).
//!
//! Pose2Sim TOML (`read_toml`): one table per camera with `size = [W, H]`, `matrix`
//! (3x3 K), `distortions` (4), `rotation` (a Rodrigues vector), `translation` (metres)
//! and `fisheye` (only `false` is read); the name is the table's `name` (else its key);
//! the tables `metadata`, `capture_volume`, `charuco` and `checkerboard` are not
//! cameras (Pose2Sim's `retrieve_calib_params` skips the same); cameras keep the file's
//! order.
//!
//! Errors: one [`DatasetError`] naming the file and the field (`cam03: intrinsic
//! focalLengthU`, `[cam02] matrix[0][0]`): a value that is missing, not a number, NaN
//! or infinite, a non-positive focal length or image size, a size that is not a whole
//! number of pixels, a transform that is not a rotation. Nothing here panics on input.

use std::path::Path;

use glam::DVec3;

use crate::camera::Camera;
use crate::dataset::distortion::Distortion;
use crate::dataset::error::DatasetError;

/// The largest image side read (pixels): far past any camera, small enough that
/// `width * height` pixels of RGB fit in memory arithmetic.
const MAX_SIDE: f64 = 65_536.0;

/// How far from a rotation a Qualisys `transform` may be (largest element of
/// `MᵀM - I`, and `det M` from 1): the files hold 16 significant digits, so a real
/// rotation is within 1e-12; 1e-6 admits one written with 7 digits.
const ROTATION_TOLERANCE: f64 = 1e-6;

/// One calibrated camera of a rig.
#[derive(Clone, Debug, PartialEq)]
pub struct RigCamera {
    /// The calibration's name for it (Qualisys `serial`, the TOML table's `name`).
    pub name: String,
    /// Image size, intrinsics (drape's pixel convention: centres at +0.5) and the
    /// world-to-camera pose in metres.
    pub camera: Camera,
    /// The lens (k1, k2, p1, p2; k3 = 0).
    pub distortion: Distortion,
}

impl RigCamera {
    /// K as the calibration file holds it (OpenCV's pixel convention: centres at
    /// integers).
    pub fn opencv_k(&self) -> [[f64; 3]; 3] {
        let c = &self.camera;
        [
            [c.fx, 0.0, c.cx - 0.5],
            [0.0, c.fy, c.cy - 0.5],
            [0.0, 0.0, 1.0],
        ]
    }
}

/// A rig calibration: its cameras in the file's order (Qualisys: natural order of
/// their names).
#[derive(Clone, Debug, PartialEq)]
pub struct Calibration {
    pub cameras: Vec<RigCamera>,
    /// The format it was read from: "qualisys" or "pose2sim-toml".
    pub format: &'static str,
}

/// The formats [`read`] tells apart, as a phrase for messages.
pub const FORMATS: &str = "a Qualisys .qca.txt (XML) or a Pose2Sim / Sports2D Calib*.toml";

/// Reads a calibration, telling the format by the file's first non-blank character
/// (`<`: Qualisys XML; anything else: TOML). `binning` is the Qualisys binning factor
/// (1 unless the video was filmed binned); a TOML ignores it.
pub fn read(path: &Path, binning: u32) -> Result<Calibration, DatasetError> {
    let text = read_text(path)?;
    if text.trim_start().starts_with('<') {
        parse_qca(path, &text, binning)
    } else {
        parse_toml(path, &text)
    }
}

/// Reads a Qualisys `.qca.txt` as Pose2Sim converts it (module header).
pub fn read_qca(path: &Path, binning: u32) -> Result<Calibration, DatasetError> {
    parse_qca(path, &read_text(path)?, binning)
}

/// Reads a Pose2Sim / Sports2D calibration TOML (module header).
pub fn read_toml(path: &Path) -> Result<Calibration, DatasetError> {
    parse_toml(path, &read_text(path)?)
}

fn read_text(path: &Path) -> Result<String, DatasetError> {
    let bytes = std::fs::read(path).map_err(|e| DatasetError::io(path, e))?;
    String::from_utf8(bytes).map_err(|e| {
        field(
            path,
            "text",
            format!("not UTF-8 text (byte {})", e.utf8_error().valid_up_to()),
        )
    })
}

fn field(path: &Path, name: impl Into<String>, problem: impl Into<String>) -> DatasetError {
    DatasetError::Field {
        file: path.display().to_string(),
        field: name.into(),
        problem: problem.into(),
    }
}

/// Pose2Sim's `natural_sort_key`: digit runs compare as numbers ("cam2" < "cam10").
fn natural_key(s: &str) -> Vec<(u8, u128, String)> {
    let mut out = Vec::new();
    let mut rest = s;
    while !rest.is_empty() {
        let digits = rest.chars().take_while(char::is_ascii_digit).count();
        if digits > 0 {
            let (d, r) = rest.split_at(digits);
            out.push((0, d.parse().unwrap_or(u128::MAX), String::new()));
            rest = r;
        } else {
            let n = rest
                .char_indices()
                .find(|(_, c)| c.is_ascii_digit())
                .map_or(rest.len(), |(i, _)| i);
            let (t, r) = rest.split_at(n);
            out.push((1, 0, t.to_lowercase()));
            rest = r;
        }
    }
    out
}

fn parse_qca(path: &Path, text: &str, binning: u32) -> Result<Calibration, DatasetError> {
    if binning == 0 {
        return Err(field(path, "binning factor", "must be at least 1"));
    }
    let b = f64::from(binning);
    let doc = roxmltree::Document::parse(text)
        .map_err(|e| field(path, "XML", format!("not well-formed: {e}")))?;
    let root = doc.root_element();
    if root.tag_name().name() != "calibration" {
        return Err(field(
            path,
            "XML",
            format!(
                "the root element is <{}>, not a Qualisys <calibration>",
                root.tag_name().name()
            ),
        ));
    }
    let cameras_el = child(path, root, "cameras", "calibration")?;
    let mut cameras = Vec::new();
    for (i, cam) in cameras_el
        .children()
        .filter(|n| n.has_tag_name("camera"))
        .enumerate()
    {
        let video = cam.attribute("model").is_some_and(|m| {
            let m = m.to_lowercase();
            m.contains("video") || m.contains("none")
        });
        if !video {
            continue;
        }
        let name = match cam.attribute("serial") {
            Some(s) if !s.trim().is_empty() => s.trim().to_string(),
            _ => {
                return Err(field(
                    path,
                    format!("camera {}: serial", i + 1),
                    "missing (the camera's name)",
                ))
            }
        };
        let at = |el: &str, attr: &str| -> Result<f64, DatasetError> {
            let node = child(path, cam, el, &name)?;
            let what = format!("{name}: {el} {attr}");
            let raw = node
                .attribute(attr)
                .ok_or_else(|| field(path, &what, "missing"))?;
            let v: f64 = raw
                .trim()
                .parse()
                .map_err(|_| field(path, &what, format!("'{raw}' is not a number")))?;
            if !v.is_finite() {
                return Err(field(path, &what, format!("{raw} is not finite")));
            }
            Ok(v)
        };
        let (left, right) = (at("fov_video", "left")?, at("fov_video", "right")?);
        let (top, bottom) = (at("fov_video", "top")?, at("fov_video", "bottom")?);
        let width = pixels(
            path,
            &format!("{name}: fov_video width"),
            (right - left + 1.0) / b,
        )?;
        let height = pixels(
            path,
            &format!("{name}: fov_video height"),
            (bottom - top + 1.0) / b,
        )?;
        let focal = |attr: &str| -> Result<f64, DatasetError> {
            let f = at("intrinsic", attr)? / 64.0 / b;
            if !(f > 0.0) {
                return Err(field(
                    path,
                    format!("{name}: intrinsic {attr}"),
                    format!("{f} px is not a positive focal length"),
                ));
            }
            Ok(f)
        };
        let fx = focal("focalLengthU")?;
        let fy = focal("focalLengthV")?;
        let cx = at("intrinsic", "centerPointU")? / 64.0 / b - left;
        let cy = at("intrinsic", "centerPointV")? / 64.0 / b - top;
        let distortion = Distortion {
            k1: at("intrinsic", "radialDistortion1")? / 64.0 / b,
            k2: at("intrinsic", "radialDistortion2")? / 64.0 / b,
            p1: at("intrinsic", "tangentalDistortion1")? / 64.0 / b,
            p2: at("intrinsic", "tangentalDistortion2")? / 64.0 / b,
            k3: 0.0,
        };
        let mut m = [[0.0; 3]; 3];
        for (r, row) in m.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = at("transform", &format!("r{}{}", r + 1, c + 1))?;
            }
        }
        check_rotation(path, &format!("{name}: transform r11..r33"), &m)?;
        let centre = DVec3::new(
            at("transform", "x")?,
            at("transform", "y")?,
            at("transform", "z")?,
        ) / 1000.0;
        // R = diag(1, -1, -1) M: Pose2Sim's inversion of the transform, then its turn
        // of the camera by pi about x.
        let rotation = [m[0], m[1].map(|v| -v), m[2].map(|v| -v)];
        let translation = -mat_vec(&rotation, centre);
        cameras.push(RigCamera {
            name,
            camera: Camera {
                fx,
                fy,
                cx: cx + 0.5,
                cy: cy + 0.5,
                width,
                height,
                rotation,
                translation,
                near: Camera::NEAR,
            },
            distortion,
        });
    }
    if cameras.is_empty() {
        return Err(field(
            path,
            "cameras",
            "no video camera (a <camera> whose model says video or none)",
        ));
    }
    cameras.sort_by_key(|c| natural_key(&c.name));
    check_unique(path, &cameras)?;
    Ok(Calibration {
        cameras,
        format: "qualisys",
    })
}

fn child<'a, 'i>(
    path: &Path,
    node: roxmltree::Node<'a, 'i>,
    name: &str,
    parent: &str,
) -> Result<roxmltree::Node<'a, 'i>, DatasetError> {
    node.children()
        .find(|n| n.has_tag_name(name))
        .ok_or_else(|| field(path, format!("{parent}: {name}"), "missing element"))
}

/// A whole positive number of pixels, at most [`MAX_SIDE`].
fn pixels(path: &Path, what: &str, v: f64) -> Result<u32, DatasetError> {
    if !((1.0..=MAX_SIDE).contains(&v) && v.fract() == 0.0) {
        return Err(field(
            path,
            what,
            format!("{v} is not a whole number of pixels from 1 to {MAX_SIDE}"),
        ));
    }
    Ok(v as u32)
}

fn check_rotation(path: &Path, what: &str, m: &[[f64; 3]; 3]) -> Result<(), DatasetError> {
    let mut worst: f64 = 0.0;
    for i in 0..3 {
        for j in 0..3 {
            let dot: f64 = (0..3).map(|k| m[k][i] * m[k][j]).sum();
            let want = if i == j { 1.0 } else { 0.0 };
            worst = worst.max((dot - want).abs());
        }
    }
    let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    if !(worst <= ROTATION_TOLERANCE && (det - 1.0).abs() <= ROTATION_TOLERANCE) {
        return Err(field(
            path,
            what,
            format!(
                "not a rotation (MᵀM differs from I by {worst:.3e}, det {det:.6}; tolerance {ROTATION_TOLERANCE:e})"
            ),
        ));
    }
    Ok(())
}

fn mat_vec(m: &[[f64; 3]; 3], v: DVec3) -> DVec3 {
    DVec3::new(
        m[0][0] * v.x + m[0][1] * v.y + m[0][2] * v.z,
        m[1][0] * v.x + m[1][1] * v.y + m[1][2] * v.z,
        m[2][0] * v.x + m[2][1] * v.y + m[2][2] * v.z,
    )
}

fn check_unique(path: &Path, cameras: &[RigCamera]) -> Result<(), DatasetError> {
    for (i, c) in cameras.iter().enumerate() {
        if cameras[..i].iter().any(|o| o.name == c.name) {
            return Err(field(path, &c.name, "two cameras have this name"));
        }
    }
    Ok(())
}

/// The rotation matrix (rows) of a Rodrigues vector, term for term as OpenCV's
/// `cv2.Rodrigues`: `R = cos θ I + (1 - cos θ) k kᵀ + sin θ [k]ₓ` with `k = r / θ`,
/// the identity where θ is below machine epsilon (as OpenCV).
pub fn rodrigues(r: [f64; 3]) -> [[f64; 3]; 3] {
    let theta = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
    if theta < f64::EPSILON {
        return [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    }
    let k = r.map(|v| v / theta);
    let (s, c) = theta.sin_cos();
    let c1 = 1.0 - c;
    [
        [
            c + c1 * k[0] * k[0],
            c1 * k[0] * k[1] - s * k[2],
            c1 * k[0] * k[2] + s * k[1],
        ],
        [
            c1 * k[1] * k[0] + s * k[2],
            c + c1 * k[1] * k[1],
            c1 * k[1] * k[2] - s * k[0],
        ],
        [
            c1 * k[2] * k[0] - s * k[1],
            c1 * k[2] * k[1] + s * k[0],
            c + c1 * k[2] * k[2],
        ],
    ]
}

/// Tables of a Pose2Sim calibration that are not cameras.
const NOT_CAMERAS: [&str; 4] = ["metadata", "capture_volume", "charuco", "checkerboard"];

fn parse_toml(path: &Path, text: &str) -> Result<Calibration, DatasetError> {
    use std::collections::BTreeMap;
    use toml::{Spanned, Value};
    let tables: BTreeMap<String, Spanned<Value>> =
        toml::from_str(text).map_err(|e| field(path, "TOML", one_line(&e.to_string())))?;
    // The file's order (the map is sorted by key): by where each table starts.
    let mut keyed: Vec<(&String, &Spanned<Value>)> = tables
        .iter()
        .filter(|(k, v)| !NOT_CAMERAS.contains(&k.as_str()) && v.get_ref().is_table())
        .collect();
    keyed.sort_by_key(|(_, v)| v.span().start);
    let mut cameras = Vec::new();
    for (key, value) in keyed {
        let Value::Table(t) = value.get_ref() else {
            continue;
        };
        let what = |f: &str| format!("[{key}] {f}");
        let get = |f: &str| t.get(f).ok_or_else(|| field(path, what(f), "missing"));
        let number = |v: &Value, name: String| -> Result<f64, DatasetError> {
            let x = match v {
                Value::Float(x) => *x,
                Value::Integer(i) => *i as f64,
                other => {
                    return Err(field(
                        path,
                        name,
                        format!("a {} where a number belongs", other.type_str()),
                    ))
                }
            };
            if !x.is_finite() {
                return Err(field(path, name, format!("{x} is not finite")));
            }
            Ok(x)
        };
        let list = |f: &str, n: usize| -> Result<Vec<f64>, DatasetError> {
            let arr = get(f)?
                .as_array()
                .ok_or_else(|| field(path, what(f), format!("not a list of {n} numbers")))?;
            if arr.len() != n {
                return Err(field(
                    path,
                    what(f),
                    format!("{} values where {n} belong", arr.len()),
                ));
            }
            arr.iter()
                .enumerate()
                .map(|(i, v)| number(v, format!("{}[{i}]", what(f))))
                .collect()
        };
        let name = match t.get("name") {
            None => key.clone(),
            Some(Value::String(s)) if !s.trim().is_empty() => s.trim().to_string(),
            Some(_) => return Err(field(path, what("name"), "not a camera name")),
        };
        if let Some(f) = t.get("fisheye") {
            match f {
                Value::Boolean(false) => {}
                Value::Boolean(true) => {
                    return Err(field(
                        path,
                        what("fisheye"),
                        "a fisheye lens, which drape does not read (only the pinhole model with k1 k2 p1 p2)",
                    ))
                }
                _ => return Err(field(path, what("fisheye"), "not true or false")),
            }
        }
        let size = list("size", 2)?;
        let width = pixels(path, &what("size[0]"), size[0])?;
        let height = pixels(path, &what("size[1]"), size[1])?;
        let rows = get("matrix")?
            .as_array()
            .filter(|a| a.len() == 3)
            .ok_or_else(|| field(path, what("matrix"), "not a 3x3 matrix"))?;
        let mut k = [[0.0; 3]; 3];
        for (r, row) in rows.iter().enumerate() {
            let row = row.as_array().filter(|a| a.len() == 3).ok_or_else(|| {
                field(
                    path,
                    format!("{}[{r}]", what("matrix")),
                    "not a row of 3 numbers",
                )
            })?;
            for (c, v) in row.iter().enumerate() {
                k[r][c] = number(v, format!("{}[{r}][{c}]", what("matrix")))?;
            }
        }
        for (r, c) in [(0, 0), (1, 1)] {
            if !(k[r][c] > 0.0) {
                return Err(field(
                    path,
                    format!("{}[{r}][{c}]", what("matrix")),
                    format!("{} is not a positive focal length", k[r][c]),
                ));
            }
        }
        if k[2] != [0.0, 0.0, 1.0] || k[1][0] != 0.0 {
            return Err(field(
                path,
                what("matrix"),
                "not a camera matrix (the last row must be 0 0 1, and [1][0] 0)",
            ));
        }
        let d = list("distortions", 4)?;
        let r = list("rotation", 3)?;
        let rotation = rodrigues([r[0], r[1], r[2]]);
        let t = list("translation", 3)?;
        cameras.push(RigCamera {
            name,
            camera: Camera {
                fx: k[0][0],
                fy: k[1][1],
                cx: k[0][2] + 0.5,
                cy: k[1][2] + 0.5,
                width,
                height,
                rotation,
                translation: DVec3::new(t[0], t[1], t[2]),
                near: Camera::NEAR,
            },
            distortion: Distortion {
                k1: d[0],
                k2: d[1],
                p1: d[2],
                p2: d[3],
                k3: 0.0,
            },
        });
    }
    if cameras.is_empty() {
        return Err(field(
            path,
            "cameras",
            "no camera table (one [name] table a camera, with size, matrix, distortions, rotation, translation)",
        ));
    }
    check_unique(path, &cameras)?;
    Ok(Calibration {
        cameras,
        format: "pose2sim-toml",
    })
}

/// The TOML parser's message folded onto one line (it spans several, with a caret).
fn one_line(s: &str) -> String {
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn natural_order_compares_numbers() {
        let mut names = vec!["cam10", "cam2", "Cam1"];
        names.sort_by_key(|n| natural_key(n));
        assert_eq!(names, ["Cam1", "cam2", "cam10"]);
    }

    #[test]
    fn rodrigues_is_a_rotation_about_its_axis() {
        // A quarter turn about z takes x to y.
        let r = rodrigues([0.0, 0.0, std::f64::consts::FRAC_PI_2]);
        let x = mat_vec(&r, DVec3::X);
        assert!((x - DVec3::Y).length() < 1e-15, "{x}");
        assert_eq!(rodrigues([0.0; 3])[1], [0.0, 1.0, 0.0]);
    }
}
