//! Rig calibrations (`drape_trainer::dataset::calibration`) against what the real tools
//! wrote: Pose2Sim 0.10.49's own conversion (`calib_qca_fun`, `toml_write`) of the
//! Qualisys `Calib.qca.txt` shipped in its demo (`tests/fixtures/pose2sim/`: the
//! `.qca.txt` copied from the wheel with its BSD-3 licence, the TOML and JSON written
//! by `scripts/qca-reference.py`). Both readers must give Pose2Sim's numbers within
//! 1e-9 relative (each element; the references are 17-digit doubles, and the two paths
//! differ only by rounding: Pose2Sim's pi turn leaves sin(pi) = 1.2e-16 terms and its
//! rotation went through `cv2.Rodrigues` and back). Then hostile input: each damaged
//! file gives one error naming the file and the field.

use std::path::{Path, PathBuf};

use drape_trainer::dataset::calibration::{self, Calibration};

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/pose2sim")
}

/// Relative difference of two numbers, NaN when either is.
fn rel(a: f64, b: f64) -> f64 {
    if a == b {
        return 0.0;
    }
    (a - b).abs() / a.abs().max(b.abs())
}

fn assert_close(what: &str, got: f64, want: f64) {
    let r = rel(got, want);
    assert!(
        !(r > 1e-9) && r.is_finite(),
        "{what}: got {got}, Pose2Sim {want} (relative {r:e})"
    );
}

fn nums(v: &serde_json::Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

/// Every camera of `cal` against Pose2Sim's JSON, field by field.
fn check_against_pose2sim(cal: &Calibration, source: &str) {
    let text = std::fs::read_to_string(fixtures().join("Calib_qualisys.json")).unwrap();
    let json: serde_json::Value = serde_json::from_str(&text).unwrap();
    let want = json["cameras"].as_array().unwrap();
    let names: Vec<&str> = cal.cameras.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["cam01", "cam02", "cam03", "cam04"], "{source}");
    assert_eq!(want.len(), 4);
    for (c, w) in cal.cameras.iter().zip(want) {
        let n = format!("{source} {}", c.name);
        assert_eq!(w["name"], c.name.as_str());
        let size = nums(&w["size"]);
        assert_eq!(
            [c.camera.width, c.camera.height],
            [size[0] as u32, size[1] as u32],
            "{n} size"
        );
        let k = c.opencv_k();
        for (r, row) in w["K"].as_array().unwrap().iter().enumerate() {
            for (col, v) in nums(row).into_iter().enumerate() {
                assert_close(&format!("{n} K[{r}][{col}]"), k[r][col], v);
            }
        }
        let d = c.distortion;
        for (i, (got, v)) in [d.k1, d.k2, d.p1, d.p2]
            .into_iter()
            .zip(nums(&w["distortions"]))
            .enumerate()
        {
            assert_close(&format!("{n} distortion[{i}]"), got, v);
        }
        assert_eq!(d.k3, 0.0);
        for (r, row) in w["rotation_matrix"].as_array().unwrap().iter().enumerate() {
            for (col, v) in nums(row).into_iter().enumerate() {
                assert_close(&format!("{n} R[{r}][{col}]"), c.camera.rotation[r][col], v);
            }
        }
        for (i, v) in nums(&w["translation_m"]).into_iter().enumerate() {
            assert_close(&format!("{n} t[{i}]"), c.camera.translation[i], v);
        }
    }
}

#[test]
fn calibration_qca_matches_pose2sims_conversion() {
    let cal = calibration::read_qca(&fixtures().join("Calib.qca.txt"), 1).unwrap();
    assert_eq!(cal.format, "qualisys");
    check_against_pose2sim(&cal, "qca");
    // The format is told from the contents too.
    assert_eq!(
        calibration::read(&fixtures().join("Calib.qca.txt"), 1).unwrap(),
        cal
    );
    // The camera centres of docs/notes/prepare-footage.md (the .qca's x, y, z in mm).
    let centre = cal.cameras[0].camera.centre();
    assert!((centre - glam::DVec3::new(1.4602323709, -1.9091590482, 1.8965058524)).length() < 1e-9);
}

#[test]
fn calibration_qca_binning_halves_the_image() {
    let one = calibration::read_qca(&fixtures().join("Calib.qca.txt"), 1).unwrap();
    let two = calibration::read_qca(&fixtures().join("Calib.qca.txt"), 2).unwrap();
    for (a, b) in one.cameras.iter().zip(&two.cameras) {
        assert_eq!([b.camera.width, b.camera.height], [544, 960]);
        assert_close("fx", b.camera.fx, a.camera.fx / 2.0);
        // fov_video left/top are 0 here, so the OpenCV principal point halves.
        assert_close("cx", b.opencv_k()[0][2], a.opencv_k()[0][2] / 2.0);
        assert_close("k1", b.distortion.k1, a.distortion.k1 / 2.0);
        assert_eq!(a.camera.rotation, b.camera.rotation);
    }
}

#[test]
fn calibration_toml_matches_pose2sims_conversion() {
    let path = fixtures().join("Calib_qualisys.toml");
    let cal = calibration::read_toml(&path).unwrap();
    assert_eq!(cal.format, "pose2sim-toml");
    check_against_pose2sim(&cal, "toml");
    assert_eq!(calibration::read(&path, 1).unwrap(), cal);
}

/// Pixel convention: drape's camera has the file's principal point + 0.5.
#[test]
fn calibration_principal_point_moves_to_drapes_pixel_centres() {
    let cal = calibration::read_toml(&fixtures().join("Calib_qualisys.toml")).unwrap();
    assert_close("cx", cal.cameras[0].camera.cx, 532.97369384375 + 0.5);
    assert_close("cy", cal.cameras[0].camera.cy, 948.137390140625 + 0.5);
}

/// Writes `text` as `name` in a scratch directory and reads it; returns the error line.
fn read_error(name: &str, text: &str) -> (PathBuf, String) {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .join("calibration")
        .join(std::process::id().to_string());
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    drape_io::write(&path, text).unwrap();
    let err = match calibration::read(&path, 1) {
        Ok(c) => panic!("{name}: read, an error was expected: {c:?}"),
        Err(e) => e.to_string(),
    };
    (path, err)
}

fn qca() -> String {
    std::fs::read_to_string(fixtures().join("Calib.qca.txt")).unwrap()
}

fn toml() -> String {
    std::fs::read_to_string(fixtures().join("Calib_qualisys.toml")).unwrap()
}

/// Each damaged file: one line, naming the file and the field.
#[test]
fn calibration_hostile_files_name_file_and_field() {
    let cam03_nan = qca().replacen("focalLengthU=\"107622.296875\"", "focalLengthU=\"nan\"", 1);
    let not_rotation = qca().replacen("r11=\"0.2586331447643361\"", "r11=\"0.9\"", 1);
    let scaled = qca().replacen(
        "r11=\"0.5536380477336265\" r12=\"0.8046719867383512\" r13=\"0.2144479094331626\"",
        "r11=\"1.1072760954672530\" r12=\"1.6093439734767024\" r13=\"0.4288958188663252\"",
        1,
    );
    let no_attribute = qca().replacen(" centerPointV=\"61646.457031\"", "", 1);
    let text = qca();
    let truncated = &text[..text.len() / 2];
    let toml_nan = toml().replacen("1681.598388671875", "nan", 1);
    let toml_short = toml().replacen(
        "translation = [ -0.11152829000000014, 0.7766184800000001, 3.0675519599999994]",
        "translation = [ -0.11152829000000014, 0.7766184800000001]",
        1,
    );
    let toml_size = toml().replacen("size = [ 1088.0, 1920.0]", "size = [ 1088.5, 1920.0]", 1);
    let toml_no_matrix = toml().replacen(
        "matrix = [ [ 1681.244873046875, 0.0, 532.97369384375], [ 0.0, 1681.075439453125, 948.137390140625], [ 0.0, 0.0, 1.0]]\n",
        "",
        1,
    );
    let toml_broken = &toml()[..300];
    let cases: [(&str, &str, &str); 11] = [
        ("nan.qca.txt", &cam03_nan, "cam03: intrinsic focalLengthU"),
        (
            "rotation.qca.txt",
            &not_rotation,
            "cam04: transform r11..r33",
        ),
        ("scaled.qca.txt", &scaled, "cam01: transform r11..r33"),
        (
            "attribute.qca.txt",
            &no_attribute,
            "cam02: intrinsic centerPointV: missing",
        ),
        ("truncated.qca.txt", truncated, "XML: not well-formed"),
        ("nan.toml", &toml_nan, "[cam03] matrix[0][0]"),
        (
            "short.toml",
            &toml_short,
            "[cam02] translation: 2 values where 3 belong",
        ),
        ("size.toml", &toml_size, "[cam01] size[0]"),
        ("matrix.toml", &toml_no_matrix, "[cam01] matrix: missing"),
        ("broken.toml", toml_broken, "TOML"),
        ("empty.toml", "", "cameras: no camera table"),
    ];
    for (name, text, needle) in cases {
        assert_ne!(text, qca(), "{name}: the edit did not apply");
        assert_ne!(text, toml(), "{name}: the edit did not apply");
        let (path, err) = read_error(name, text);
        assert!(!err.contains('\n'), "{name}: more than one line: {err}");
        assert!(
            err.starts_with(&format!("{}: ", path.display())),
            "{name}: does not start with the file: {err}"
        );
        assert!(err.contains(needle), "{name}: '{needle}' not in: {err}");
    }
}
