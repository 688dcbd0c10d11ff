//! `drape simulate --motion FILE.npz` on an AMASS file as AMASS writes it (written by
//! real numpy through `tests/python/write_motions.py`: 156 SMPL-H pose values, a 0-d
//! `mocap_framerate`, a text `gender`), end to end; and a bad motion file refused in
//! one line. `drape animate` reads `--motion` through the same `Motion::load_npz`.
//!
//! Python with numpy comes from `DRAPE_TORCH_PYTHON` or the project's
//! `target/torch-venv` (`scripts/torch-env.sh`); without it the test fails, it is not
//! skipped.

use std::path::{Path, PathBuf};
use std::process::Command;

fn python() -> PathBuf {
    if let Ok(p) = std::env::var("DRAPE_TORCH_PYTHON") {
        return p.into();
    }
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/torch-venv/bin/python");
    assert!(venv.exists(), "no Python with numpy: run scripts/torch-env.sh (the test command does) or set DRAPE_TORCH_PYTHON");
    venv
}

/// A fresh directory holding every file `write_motions.py` writes.
fn motion_files(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .join("motion-cli")
        .join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/python/write_motions.py");
    let out = Command::new(python())
        .arg(&script)
        .arg(&d)
        .output()
        .expect("python runs");
    assert!(
        out.status.success(),
        "write_motions.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    d
}

#[test]
fn simulate_takes_an_amass_file() {
    let d = motion_files("amass");
    let out = d.join("sim");
    let motion = d.join("amass.npz");
    // Two substeps: the 20 settling frames plus the file's 6 take seconds.
    let o = Command::new(env!("CARGO_BIN_EXE_drape"))
        .args([
            "simulate",
            "--substeps",
            "2",
            "--motion",
            motion.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .output()
        .expect("drape runs");
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(stdout.contains("simulated 6 frames"), "{stdout}");
    for garment in ["tshirt", "pants"] {
        for f in 0..6 {
            assert!(
                out.join(format!("{garment}_{f:04}.obj")).is_file(),
                "{garment} frame {f} missing: {stdout}"
            );
        }
    }
    // The cloth stays on the body. Loose bounds against an exploded simulation (a
    // misread pose): a 6-frame walk measures about 4 mm outside and 7% stretch, this
    // file 6 mm inside and 6%.
    let number_before = |tail: &str| -> f64 {
        let head = &stdout[..stdout
            .find(tail)
            .unwrap_or_else(|| panic!("no '{tail}' in: {stdout}"))];
        head.rsplit(' ')
            .find(|w| !w.is_empty())
            .and_then(|w| w.parse().ok())
            .unwrap_or_else(|| panic!("no number before '{tail}': {stdout}"))
    };
    let stretch = number_before("%; wrote");
    assert!(stretch < 30.0, "largest edge stretch {stretch}%: {stdout}");
    if stdout.contains("mm inside the body") {
        let depth = number_before(" mm inside the body");
        assert!(depth < 20.0, "cloth {depth} mm inside the body: {stdout}");
    }
}

#[test]
fn simulate_refuses_a_bad_motion_file_in_one_line() {
    let d = motion_files("bad");
    let motion = d.join("bad_width.npz");
    let o = Command::new(env!("CARGO_BIN_EXE_drape"))
        .args([
            "simulate",
            "--motion",
            motion.to_str().unwrap(),
            "--out",
            d.join("sim").to_str().unwrap(),
        ])
        .output()
        .expect("drape runs");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert_eq!(stderr.trim_end().lines().count(), 1, "{stderr}");
    assert!(
        stderr.contains(motion.to_str().unwrap())
            && stderr.contains("['poses']")
            && stderr.contains("100 values per frame"),
        "{stderr}"
    );
}

#[test]
fn simulate_refuses_an_obj_garment_without_faces_in_one_line_and_writes_nothing() {
    let d = std::env::temp_dir().join(format!("drape-obj-no-faces-{}", std::process::id()));
    std::fs::create_dir_all(&d).expect("temp dir");
    let obj = d.join("points_only.obj");
    drape_io::write(
        &obj,
        "# three vertices, no face\nv 0 1.2 0.1\nv 0.1 1.2 0.1\nv 0 1.3 0.1\n",
    )
    .expect("write obj");
    let out = d.join("sim");
    let o = Command::new(env!("CARGO_BIN_EXE_drape"))
        .args([
            "simulate",
            "--frames",
            "2",
            "--garment",
            obj.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .output()
        .expect("drape runs");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert_eq!(stderr.trim_end().lines().count(), 1, "{stderr}");
    assert!(
        stderr.contains(obj.to_str().unwrap()) && stderr.contains("no triangles"),
        "{stderr}"
    );
    assert!(!out.exists(), "the output directory was created");
}
