//! Motion files as numpy and AMASS write them (`tests/python/write_motions.py`, real
//! numpy 2.1) through `Motion::load_npz`: what loads equals what numpy wrote or, for
//! AMASS, what AMASS users' conversion to a y-up SMPL motion gives; mistakes are
//! refused in one line naming the file and the field.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use drape_tests::reference_python::{case_dir, run};
use drape_trainer::motion::Motion;
use drape_trainer::npy::Npz;
use glam::DVec3;

/// The files, written once per test binary.
fn files() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = case_dir("motion_files", "numpy");
        run("write_motions.py", std::slice::from_ref(&dir));
        dir
    })
}

/// Whitespace-separated numbers as numpy's `savetxt('%.17g')` writes them: exact f64.
fn text_numbers(path: &Path) -> Vec<f64> {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    text.split_whitespace()
        .map(|v| {
            v.parse::<f64>()
                .unwrap_or_else(|e| panic!("{}: '{v}': {e}", path.display()))
        })
        .collect()
}

fn load(case: &str) -> Motion {
    let path = files().join(format!("{case}.npz"));
    Motion::load_npz(&path).unwrap_or_else(|e| panic!("{case}: {e}"))
}

/// Largest absolute difference between the loaded motion and the case's expectation.
fn worst_difference(case: &str, m: &Motion) -> (f64, f64) {
    let expected = files().join(format!("{case}.expected"));
    let poses = text_numbers(&expected.join("poses.txt"));
    let trans = text_numbers(&expected.join("trans.txt"));
    assert_eq!(m.len() * 72, poses.len(), "{case}: frames");
    assert_eq!(
        m.translations.len() * 3,
        trans.len(),
        "{case}: translation frames"
    );
    assert_eq!(
        m.fps,
        text_numbers(&expected.join("fps.txt"))[0],
        "{case}: fps"
    );
    let got_poses: Vec<f64> = m
        .poses
        .iter()
        .flatten()
        .flat_map(|r| r.to_array())
        .collect();
    let got_trans: Vec<f64> = m.translations.iter().flat_map(|t| t.to_array()).collect();
    (
        max_abs_diff(&got_poses, &poses),
        max_abs_diff(&got_trans, &trans),
    )
}

fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

#[test]
fn numpy_motions_load_exactly_as_written() {
    // Float64 values copied, not computed: exact.
    for case in ["smpl_0d_fps", "smpl_fortran", "body22"] {
        let m = load(case);
        assert_eq!(worst_difference(case, &m), (0.0, 0.0), "{case}");
    }
    let m = load("body22");
    assert!(
        m.poses
            .iter()
            .all(|p| p[22] == DVec3::ZERO && p[23] == DVec3::ZERO),
        "22-joint file: hands at rest"
    );
}

#[test]
fn amass_files_load_as_a_y_up_smpl_motion() {
    for case in [
        "amass",
        "amass_object_gender",
        "amass_bytes_gender",
        "amass_compressed",
        "amass_smplx",
    ] {
        let m = load(case);
        let (poses, trans) = worst_difference(case, &m);
        // Joints 1-21 and the hands are copied (exact); the root is composed with the
        // -90° x rotation here through quaternions and by scipy through its own route,
        // a few f64 roundings apart on angles below 1.2 rad.
        assert!(
            poses <= 1e-14,
            "{case}: poses differ from the AMASS conversion by {poses:e}"
        );
        // A permutation, a sign and one subtraction, as numpy does them: exact.
        assert_eq!(trans, 0.0, "{case}: translation");
        assert!(
            m.poses
                .iter()
                .all(|p| p[22] == DVec3::ZERO && p[23] == DVec3::ZERO),
            "{case}: SMPL's hand joints must be at rest"
        );
        assert_eq!(
            m.translations[0],
            DVec3::ZERO,
            "{case}: the motion starts where the body stands"
        );
    }
    // A subject standing upright in AMASS's z-up world stands upright here: the file's
    // roots are +90° about x composed with turns of at most 0.4 rad per axis.
    for p in &load("amass").poses {
        let angle = p[0].length();
        assert!(angle < 0.7, "root {:?} is not near upright", p[0]);
    }
}

#[test]
fn amass_body_joints_are_the_first_66_columns() {
    // Independently of the expectation files: joints 1..21 are the file's columns
    // 3..66 bit for bit (the `.npz` itself read as a plain archive).
    let npz = Npz::read(&files().join("amass.npz")).expect("read");
    let raw = npz.require("poses", &[None, Some(156)]).expect("poses");
    for (f, p) in load("amass").poses.iter().enumerate() {
        for (j, joint) in p.iter().enumerate().take(22).skip(1) {
            assert_eq!(
                &joint.to_array()[..],
                &raw.data[156 * f + 3 * j..156 * f + 3 * j + 3],
                "frame {f} joint {j}"
            );
        }
    }
}

#[test]
fn text_and_pickled_entries_do_not_stop_an_archive_but_asking_for_one_says_why() {
    for (case, descr) in [
        ("amass", "<U4"),
        ("amass_object_gender", "|O"),
        ("amass_bytes_gender", "|S6"),
    ] {
        let path = files().join(format!("{case}.npz"));
        let npz = Npz::read(&path).unwrap_or_else(|e| panic!("{case}: {e}"));
        assert!(
            npz.contains("gender") && !npz.arrays.contains_key("gender"),
            "{case}: gender kept aside"
        );
        let err = npz
            .require("gender", &[])
            .expect_err("text is not decoded")
            .to_string();
        assert!(
            err.contains(&path.display().to_string())
                && err.contains("['gender']")
                && err.contains(descr),
            "{case}: {err}"
        );
        assert_eq!(
            drape_trainer::npy::read_npz(&path).expect("read_npz").len(),
            5,
            "{case}: every numeric array"
        );
    }
    // The 0-d float numpy writes for mocap_framerate is a scalar; so is a (1) array.
    let npz = Npz::read(&files().join("amass.npz")).expect("read");
    assert_eq!(npz.scalar("mocap_framerate").expect("0-d"), 120.0);
    let err = npz
        .scalar("betas")
        .expect_err("16 values are no scalar")
        .to_string();
    assert!(err.contains("['betas']") && err.contains("[16]"), "{err}");
}

#[test]
fn bad_motion_files_are_refused_in_one_line_naming_the_file_and_field() {
    for (case, field, words) in [
        (
            "bad_width",
            "['poses']",
            &["100 values per frame", "72"][..],
        ),
        ("bad_nan", "['poses']", &["NaN"][..]),
        ("bad_no_poses", "['poses']", &["missing"][..]),
        ("bad_frames", "['trans']", &["5 frames", "6"][..]),
        ("bad_no_frames", "['poses']", &["no frames"][..]),
        ("bad_fps", "['fps']", &["positive"][..]),
        ("bad_no_fps", "['fps']", &["missing", "mocap_framerate"][..]),
        ("bad_text_poses", "['poses']", &["<U4", "not supported"][..]),
    ] {
        let path = files().join(format!("{case}.npz"));
        let err = match Motion::load_npz(&path) {
            Ok(m) => panic!("{case}: accepted, {} frames", m.len()),
            Err(e) => e.to_string(),
        };
        assert!(!err.contains('\n'), "{case}: one line: {err}");
        assert!(
            err.contains(&path.display().to_string()) && err.contains(field),
            "{case}: names the file and {field}: {err}"
        );
        for w in words {
            assert!(err.contains(w), "{case}: says '{w}': {err}");
        }
    }
}
