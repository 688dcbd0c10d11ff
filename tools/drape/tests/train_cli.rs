//! `drape train`'s bad input: each case ends in one line on stderr that names the file
//! or field, a non-zero exit, and no run directory left behind.

use std::path::{Path, PathBuf};
use std::process::Command;

fn drape(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_drape")).args(args).output().expect("drape runs")
}

fn dir(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("train-cli").join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Runs `drape train` expecting failure; returns stderr after checking that the run
/// directory was not created.
fn fails(data: &Path, extra: &[&str], out: &Path) -> String {
    let mut args = vec!["train", "--data", data.to_str().unwrap(), "--out", out.to_str().unwrap()];
    args.extend_from_slice(extra);
    let o = drape(&args);
    let stderr = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!o.status.success(), "expected failure, got success: {}", String::from_utf8_lossy(&o.stdout));
    assert!(!out.exists(), "a run directory was left behind for: {stderr}");
    assert_eq!(stderr.trim().lines().filter(|l| l.starts_with("error")).count(), 1, "one error line expected: {stderr}");
    stderr
}

#[test]
fn bad_data_directories_are_named() {
    let d = dir("bad-data");
    let out = d.join("run");
    let e = fails(&d.join("nonexistent"), &[], &out);
    assert!(e.contains("nonexistent") && e.contains("no such directory"), "{e}");
    let empty = d.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let e = fails(&empty, &[], &out);
    assert!(e.contains("empty") && e.contains("neither a NeuMan"), "{e}");
    // A NeuMan layout whose SMPL file is missing.
    let neuman = d.join("neuman");
    std::fs::create_dir_all(neuman.join("sparse")).unwrap();
    for f in ["cameras.txt", "images.txt", "points3D.txt"] {
        std::fs::write(neuman.join("sparse").join(f), "# empty\n").unwrap();
    }
    let e = fails(&neuman, &[], &out);
    assert!(e.contains("smpl_optimized_aligned_scale.npz"), "{e}");
}

#[test]
fn bad_configs_name_the_file_and_field() {
    let d = dir("bad-config");
    // The data is never read: the config is checked first.
    let data = d.join("data");
    let out = d.join("run");
    let cases = [
        ("typo.toml", "steps = 10\n[body]\nlr_positon = 1e-4\n", "body.lr_positon"),
        ("negative.toml", "[body]\nlr_triplane = -1e-3\n", "body.lr_triplane"),
        ("wrong-type.toml", "steps = \"many\"\n", "steps"),
        ("broken.toml", "steps = \n", "broken.toml"),
    ];
    for (name, text, field) in cases {
        let path = d.join(name);
        std::fs::write(&path, text).unwrap();
        let e = fails(&data, &["--config", path.to_str().unwrap()], &out);
        assert!(e.contains(name) || e.contains(field), "{name}: {e}");
        assert!(e.contains(field), "{name}: the field '{field}' is not named: {e}");
    }
    let e = fails(&data, &["--preset", "fast"], &out);
    assert!(e.contains("unknown preset 'fast'"), "{e}");
    let e = fails(&data, &["--config", d.join("missing.toml").to_str().unwrap()], &out);
    assert!(e.contains("missing.toml"), "{e}");
}
