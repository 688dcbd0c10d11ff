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
        ("zero-width.toml", "[cloth]\ndecoder_width = 0\n", "cloth.decoder_width"),
        ("compositing.toml", "compositing = \"blended\"\n", "compositing"),
        ("sh.toml", "[scene]\nsh_degree = 4\n", "scene.sh_degree"),
        ("fit.toml", "cloth_fit = \"baggy\"\n", "cloth_fit"),
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

/// A run SIGKILLed in the middle of writing a checkpoint resumes from the one before:
/// the half-written temporary file never replaces it.
#[test]
fn a_run_killed_during_a_checkpoint_write_resumes_from_the_previous_one() {
    use std::io::{BufRead, BufReader};
    let d = dir("sigkill");
    let data = d.join("data");
    let o = drape(&["synth", "--out", data.to_str().unwrap(), "--size", "64", "--frames", "8", "--cameras", "1", "--samples", "1"]);
    assert!(o.status.success(), "synth: {}", String::from_utf8_lossy(&o.stderr));
    let config = d.join("tiny.toml");
    std::fs::write(&config, "steps = 12\nfit_steps = 10\ndecimate = 6\ncheckpoint_every = 4\nlog_every = 4\nlayers = \"body\"\n[body]\ntriplane_resolution = 16\ntriplane_channels = 4\n").unwrap();
    let run = d.join("run");
    let mut child = Command::new(env!("CARGO_BIN_EXE_drape"))
        .args(["train", "--data", data.to_str().unwrap(), "--out", run.to_str().unwrap(), "--config", config.to_str().unwrap()])
        .env("DRAPE_FAILPOINT", "stall-in-checkpoint-write:2")
        .stderr(std::process::Stdio::piped())
        .stdout(std::process::Stdio::null())
        .spawn()
        .expect("drape train starts");
    // Wait for the second checkpoint write (step 8) to stall half written, then SIGKILL.
    let stderr = child.stderr.take().unwrap();
    let mut seen = String::new();
    for line in BufReader::new(stderr).split(b'\n').map_while(Result::ok) {
        let line = String::from_utf8_lossy(&line).to_string();
        seen.push_str(&line);
        seen.push('\n');
        if line.contains("failpoint: stalled writing") {
            break;
        }
    }
    assert!(seen.contains("failpoint: stalled writing"), "the run ended before the failpoint: {seen}");
    child.kill().expect("SIGKILL");
    child.wait().expect("reaped");
    let tmp = run.join("checkpoint.npz.tmp");
    assert!(tmp.is_file(), "the half-written temporary file is what the kill left");
    let ckpt = drape_trainer::npy::read_npz(&run.join("checkpoint.npz")).expect("the previous checkpoint is intact");
    assert_eq!(ckpt["step"].data, vec![4.0], "the checkpoint on disk is the first one (step 4)");
    let o = drape(&["train", "--data", data.to_str().unwrap(), "--resume", run.to_str().unwrap()]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "resume failed: {}", String::from_utf8_lossy(&o.stderr));
    assert!(stdout.contains("resumed at step 4"), "{stdout}");
    let done = drape_trainer::npy::read_npz(&run.join("model.npz")).expect("model written");
    assert_eq!(done["step"].data, vec![12.0], "the resumed run finished all steps");
}

/// `drape eval`, `animate` and `edit` on bad input: one error line naming the problem,
/// a non-zero exit, nothing written.
#[test]
fn eval_animate_and_edit_name_bad_input() {
    let d = dir("run-tools");
    let check = |args: &[&str], want: &[&str]| {
        let o = drape(args);
        let stderr = String::from_utf8_lossy(&o.stderr).to_string();
        assert!(!o.status.success(), "{args:?}: expected failure, got success");
        assert_eq!(stderr.trim().lines().filter(|l| l.starts_with("error")).count(), 1, "{args:?}: one error line expected: {stderr}");
        for w in want {
            assert!(stderr.contains(w), "{args:?}: '{w}' missing from: {stderr}");
        }
    };
    let missing = d.join("no-run");
    let m = missing.to_str().unwrap();
    check(&["eval", m], &["no-run", "no such run directory"]);
    // A directory without a model.
    let empty = d.join("empty-run");
    std::fs::create_dir_all(&empty).unwrap();
    check(&["eval", empty.to_str().unwrap()], &["no model.npz"]);
    // A motion that is neither a name nor a file is refused before any run is opened.
    check(&["animate", m, "--motion", "moonwalk"], &["moonwalk", "walk, jog"]);
    // A motion file with 23 joints (69 pose values) names the file and the array.
    let motion = d.join("bad-motion.npz");
    std::fs::write(&motion, b"not a zip").unwrap();
    check(&["animate", m, "--motion", motion.to_str().unwrap()], &["bad-motion.npz"]);
    check(&["animate", m, "--background", "2,0,0"], &["--background"]);
    // edit needs exactly one edit and refuses a non-empty output.
    let out = d.join("edited");
    check(&["edit", m, "--out", out.to_str().unwrap()], &["--remove-cloth"]);
    check(&["edit", m, "--out", empty.parent().unwrap().to_str().unwrap(), "--remove-cloth"], &["not empty"]);
    assert!(!out.exists(), "nothing written");
}
