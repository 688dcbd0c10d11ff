//! `drape train`'s bad input: each case ends in one line on stderr that names the file
//! or field, a non-zero exit, and no run directory left behind.

use std::path::{Path, PathBuf};
use std::process::Command;

fn drape(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_drape"))
        .args(args)
        .output()
        .expect("drape runs")
}

fn dir(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .join("train-cli")
        .join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A small synthetic sequence (`drape synth`, one moving camera) in `d/data`.
fn synth_sequence(d: &Path, size: &str, frames: &str) -> PathBuf {
    let data = d.join("data");
    let o = drape(&[
        "synth",
        "--out",
        data.to_str().unwrap(),
        "--size",
        size,
        "--frames",
        frames,
        "--cameras",
        "1",
        "--samples",
        "1",
    ]);
    assert!(
        o.status.success(),
        "synth: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    data
}

/// Reads `stderr` until it has printed `needle`; returns what it printed.
fn read_until(stderr: &mut impl std::io::Read, needle: &str) -> Vec<u8> {
    let mut seen = Vec::new();
    let mut buf = [0u8; 4096];
    while !String::from_utf8_lossy(&seen).contains(needle) {
        let n = stderr.read(&mut buf).unwrap();
        assert!(
            n > 0,
            "the run ended before printing '{needle}': {}",
            String::from_utf8_lossy(&seen)
        );
        seen.extend_from_slice(&buf[..n]);
    }
    seen
}

/// Runs `drape train` expecting failure; returns stderr after checking that the run
/// directory was not created.
fn fails(data: &Path, extra: &[&str], out: &Path) -> String {
    let mut args = vec![
        "train",
        "--data",
        data.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    let o = drape(&args);
    let stderr = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(
        !o.status.success(),
        "expected failure, got success: {}",
        String::from_utf8_lossy(&o.stdout)
    );
    assert!(
        !out.exists(),
        "a run directory was left behind for: {stderr}"
    );
    assert_eq!(
        stderr
            .trim()
            .lines()
            .filter(|l| l.starts_with("error"))
            .count(),
        1,
        "one error line expected: {stderr}"
    );
    stderr
}

#[test]
fn bad_data_directories_are_named() {
    let d = dir("bad-data");
    let out = d.join("run");
    let e = fails(&d.join("nonexistent"), &[], &out);
    assert!(
        e.contains("nonexistent") && e.contains("no such directory"),
        "{e}"
    );
    let empty = d.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let e = fails(&empty, &[], &out);
    assert!(e.contains("empty") && e.contains("neither a NeuMan"), "{e}");
    // A NeuMan layout whose SMPL file is missing.
    let neuman = d.join("neuman");
    std::fs::create_dir_all(neuman.join("sparse")).unwrap();
    for (f, text) in [
        ("cameras.txt", "1 PINHOLE 32 32 40 40 16 16\n"),
        ("images.txt", "1 1 0 0 0 0 0 3 1 00000.png\n\n"),
        ("points3D.txt", "# empty\n"),
    ] {
        drape_io::write(neuman.join("sparse").join(f), text).unwrap();
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
        (
            "typo.toml",
            "[schedule]\nsteps = 10\n[layers.body]\nlr_positon = 1e-4\n",
            "layers.body.lr_positon",
        ),
        (
            "negative.toml",
            "[layers.body]\nlr_triplane = -1e-3\n",
            "layers.body.lr_triplane",
        ),
        (
            "wrong-type.toml",
            "[schedule]\nsteps = \"many\"\n",
            "schedule.steps",
        ),
        (
            "zero-width.toml",
            "[layers.cloth]\ndecoder_width = 0\n",
            "layers.cloth.decoder_width",
        ),
        (
            "compositing.toml",
            "[layers]\ncompositing = \"blended\"\n",
            "layers.compositing",
        ),
        (
            "sh.toml",
            "[layers.scene]\nsh_degree = 4\n",
            "layers.scene.sh_degree",
        ),
        (
            "fit.toml",
            "[layers]\ncloth_fit = \"baggy\"\n",
            "layers.cloth_fit",
        ),
        ("broken.toml", "[schedule]\nsteps = \n", "broken.toml"),
        ("group.toml", "[loss]\nlambda_l1 = 1\n", "loss"),
        // A file of the flat layout (before the groups) still reads; its errors name the
        // grouped key, and a key given in both layouts is refused.
        (
            "flat-typo.toml",
            "steps = 10\n[body]\nlr_positon = 1e-4\n",
            "layers.body.lr_positon",
        ),
        (
            "flat-wrong-type.toml",
            "steps = \"many\"\n",
            "schedule.steps",
        ),
        (
            "flat-compositing.toml",
            "compositing = \"blended\"\n",
            "layers.compositing",
        ),
        (
            "twice.toml",
            "decimate = 2\n[layers]\ndecimate = 3\n",
            "layers.decimate",
        ),
    ];
    for (name, text, field) in cases {
        let path = d.join(name);
        drape_io::write(&path, text).unwrap();
        let e = fails(&data, &["--config", path.to_str().unwrap()], &out);
        assert!(e.contains(name) || e.contains(field), "{name}: {e}");
        assert!(
            e.contains(field),
            "{name}: the field '{field}' is not named: {e}"
        );
    }
    let e = fails(&data, &["--preset", "fast"], &out);
    assert!(e.contains("unknown preset 'fast'"), "{e}");
    let e = fails(
        &data,
        &["--config", d.join("missing.toml").to_str().unwrap()],
        &out,
    );
    assert!(e.contains("missing.toml"), "{e}");
}

/// A run directory whose `config.json` is of the flat layout before the config's groups
/// (`trainer/tests/fixtures/flat-config-tiny`, written by `drape train` at 860a1e7 with
/// the `train.toml` beside it) resumes with the same bits as the same run with its
/// grouped `config.json`, and `drape eval` opens it.
#[test]
fn a_run_whose_config_json_is_of_the_flat_layout_resumes_and_evaluates_as_a_grouped_one() {
    let d = dir("flat-config");
    let fixture =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../trainer/tests/fixtures/flat-config-tiny");
    let data = d.join("data");
    let o = drape(&[
        "synth",
        "--out",
        data.to_str().unwrap(),
        "--size",
        "32",
        "--frames",
        "4",
        "--cameras",
        "1",
        "--samples",
        "1",
        "--fit",
        "loose",
    ]);
    assert!(
        o.status.success(),
        "synth: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let grouped = d.join("grouped");
    let o = drape(&[
        "train",
        "--data",
        data.to_str().unwrap(),
        "--out",
        grouped.to_str().unwrap(),
        "--config",
        fixture.join("train.toml").to_str().unwrap(),
        "--deterministic",
    ]);
    assert!(
        o.status.success(),
        "train: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let written: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(grouped.join("config.json")).unwrap())
            .unwrap();
    assert!(
        written.get("steps").is_none() && written["schedule"]["steps"] == 4,
        "a run writes the grouped layout: {written}"
    );
    // The same run, its config.json replaced by the one the flat layout's code wrote.
    let flat = d.join("flat");
    std::fs::create_dir_all(&flat).unwrap();
    for entry in std::fs::read_dir(&grouped).unwrap() {
        let path = entry.unwrap().path();
        if path.is_file() {
            std::fs::copy(&path, flat.join(path.file_name().unwrap())).unwrap();
        }
    }
    std::fs::copy(fixture.join("config.json"), flat.join("config.json")).unwrap();
    for run in [&grouped, &flat] {
        let o = drape(&[
            "train",
            "--data",
            data.to_str().unwrap(),
            "--resume",
            run.to_str().unwrap(),
            "--steps",
            "6",
        ]);
        assert!(
            o.status.success(),
            "resume {}: {}",
            run.display(),
            String::from_utf8_lossy(&o.stderr)
        );
        assert!(
            String::from_utf8_lossy(&o.stdout).contains("resumed at step 4"),
            "{}",
            String::from_utf8_lossy(&o.stdout)
        );
    }
    let (a, b) = (
        std::fs::read(grouped.join("model.npz")).unwrap(),
        std::fs::read(flat.join("model.npz")).unwrap(),
    );
    assert!(
        a == b,
        "the run resumed from the flat config.json differs from the grouped one's"
    );
    assert_eq!(
        drape_trainer::npy::read_npz(&flat.join("model.npz")).unwrap()["step"].data,
        vec![6.0]
    );
    let o = drape(&[
        "eval",
        flat.to_str().unwrap(),
        "--out",
        d.join("eval").to_str().unwrap(),
    ]);
    assert!(
        o.status.success(),
        "eval of the flat run: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(d.join("eval/eval.json").is_file());
}

/// A run SIGKILLed in the middle of writing a checkpoint resumes from the one before:
/// the half-written temporary file never replaces it.
#[test]
fn a_run_killed_during_a_checkpoint_write_resumes_from_the_previous_one() {
    use std::io::{BufRead, BufReader};
    let d = dir("sigkill");
    let data = synth_sequence(&d, "64", "8");
    let config = d.join("tiny.toml");
    drape_io::write(
        &config,
        crate::fixtures::tiny_body_config(
            "[schedule]\nsteps = 12\nfit_steps = 10\ncheckpoint_every = 4\nlog_every = 4\n",
        ),
    )
    .unwrap();
    let run = d.join("run");
    let mut child = Command::new(env!("CARGO_BIN_EXE_drape"))
        .args([
            "train",
            "--data",
            data.to_str().unwrap(),
            "--out",
            run.to_str().unwrap(),
            "--config",
            config.to_str().unwrap(),
        ])
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
    assert!(
        seen.contains("failpoint: stalled writing"),
        "the run ended before the failpoint: {seen}"
    );
    child.kill().expect("SIGKILL");
    child.wait().expect("reaped");
    let staged: Vec<_> = std::fs::read_dir(&run)
        .expect("the run directory")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(".checkpoint.partial-") && n.ends_with(".npz"))
        .collect();
    assert_eq!(
        staged.len(),
        1,
        "the half-written staged checkpoint is what the kill left: {staged:?}"
    );
    let ckpt = drape_trainer::npy::read_npz(&run.join("checkpoint.npz"))
        .expect("the previous checkpoint is intact");
    assert_eq!(
        ckpt["step"].data,
        vec![4.0],
        "the checkpoint on disk is the first one (step 4)"
    );
    let o = drape(&[
        "train",
        "--data",
        data.to_str().unwrap(),
        "--resume",
        run.to_str().unwrap(),
    ]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "resume failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(stdout.contains("resumed at step 4"), "{stdout}");
    let done = drape_trainer::npy::read_npz(&run.join("model.npz")).expect("model written");
    assert_eq!(
        done["step"].data,
        vec![12.0],
        "the resumed run finished all steps"
    );
}

/// `drape eval`, `animate` and `edit` on bad input: one error line naming the problem,
/// a non-zero exit, nothing written.
#[test]
fn eval_animate_and_edit_name_bad_input() {
    let d = dir("run-tools");
    let check = |args: &[&str], want: &[&str]| {
        let o = drape(args);
        let stderr = String::from_utf8_lossy(&o.stderr).to_string();
        assert!(
            !o.status.success(),
            "{args:?}: expected failure, got success"
        );
        assert_eq!(
            stderr
                .trim()
                .lines()
                .filter(|l| l.starts_with("error"))
                .count(),
            1,
            "{args:?}: one error line expected: {stderr}"
        );
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
    check(
        &["animate", m, "--motion", "moonwalk"],
        &["moonwalk", "walk, jog"],
    );
    // A motion file with 23 joints (69 pose values) names the file and the array.
    let motion = d.join("bad-motion.npz");
    drape_io::write(&motion, b"not a zip").unwrap();
    check(
        &["animate", m, "--motion", motion.to_str().unwrap()],
        &["bad-motion.npz"],
    );
    check(&["animate", m, "--background", "2,0,0"], &["--background"]);
    // edit needs exactly one edit and refuses a non-empty output.
    let out = d.join("edited");
    check(
        &["edit", m, "--out", out.to_str().unwrap()],
        &["--remove-cloth"],
    );
    check(
        &[
            "edit",
            m,
            "--out",
            empty.parent().unwrap().to_str().unwrap(),
            "--remove-cloth",
        ],
        &["not empty"],
    );
    assert!(!out.exists(), "nothing written");
}

/// Preemption: SIGTERM during a `--deterministic` run finishes the step in flight,
/// writes the checkpoint, and exits 75; running the command again says how to resume;
/// `--resume` ends with the same bits as a run that was never interrupted; a complete
/// run's command run again does nothing. The signal is sent from outside, at a step
/// drawn from a printed seed and at a step between two densifications.
#[test]
fn sigterm_checkpoints_exits_75_and_the_resumed_run_is_bit_identical() {
    use std::io::Read;
    let d = dir("sigterm");
    let data = synth_sequence(&d, "32", "8");
    let config = d.join("tiny.toml");
    // Densified after steps 6, 12 and 18.
    drape_io::write(
        &config,
        crate::fixtures::tiny_body_config(
            "[schedule]\nsteps = 20\nfit_steps = 3\ncheckpoint_every = 100\nlog_every = 1\n[densify]\nevery = 6\nfrom = 6\nuntil = 18\n",
        ),
    )
    .unwrap();
    let train = |out: &Path| -> Vec<String> {
        [
            "train",
            "--data",
            data.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--config",
            config.to_str().unwrap(),
            "--deterministic",
        ]
        .map(String::from)
        .to_vec()
    };
    let whole = d.join("whole");
    let o = Command::new(env!("CARGO_BIN_EXE_drape"))
        .args(train(&whole))
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "uninterrupted run: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(
        whole.join("complete").is_file() && !whole.join("incomplete").exists(),
        "a finished run is marked complete"
    );
    // Its command run again does nothing.
    let before = std::fs::read(whole.join("model.npz")).unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_drape"))
        .args(train(&whole))
        .output()
        .unwrap();
    assert!(
        o.status.success() && String::from_utf8_lossy(&o.stdout).contains("complete run"),
        "rerun of a complete run: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert_eq!(
        std::fs::read(whole.join("model.npz")).unwrap(),
        before,
        "a complete run is not retrained"
    );
    let reference = drape_trainer::npy::read_npz(&whole.join("model.npz")).unwrap();

    let seed = 0x5EED_u64;
    let seeded_step = 1 + (seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 60) as u32 % 18;
    eprintln!("SIGTERM before step {seeded_step} (drawn from seed {seed:#x}), then before step 9 (between the densifications after steps 6 and 12)");
    for (name, step) in [("seeded", seeded_step), ("between-densifications", 9)] {
        let run = d.join(name);
        let mut child = Command::new(env!("CARGO_BIN_EXE_drape"))
            .args(train(&run))
            .env(
                "DRAPE_FAILPOINT",
                format!("wait-for-signal-before-step:{step}"),
            )
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let mut stderr = child.stderr.take().unwrap();
        let mut seen = read_until(&mut stderr, "failpoint: waiting");
        let kill = Command::new("kill")
            .args(["-TERM", &child.id().to_string()])
            .status()
            .unwrap();
        assert!(kill.success());
        stderr.read_to_end(&mut seen).unwrap();
        let status = child.wait().unwrap();
        let text = String::from_utf8_lossy(&seen).to_string();
        assert_eq!(
            status.code(),
            Some(75),
            "{name}: exit status after SIGTERM: {text}"
        );
        assert!(
            !text.contains("panicked") && text.contains("--resume"),
            "{name}: {text}"
        );
        let ckpt =
            drape_trainer::npy::read_npz(&run.join("checkpoint.npz")).expect("a valid checkpoint");
        assert_eq!(
            ckpt["step"].data,
            vec![f64::from(step)],
            "{name}: the checkpoint holds the steps before the signal"
        );
        assert!(
            run.join("incomplete").is_file() && !run.join("complete").exists(),
            "{name}: the run says it is incomplete"
        );
        assert!(
            !run.join("model.npz").exists(),
            "{name}: no model from an interrupted run"
        );
        // The same command again says how to resume instead of training over it.
        let o = Command::new(env!("CARGO_BIN_EXE_drape"))
            .args(train(&run))
            .output()
            .unwrap();
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && e.contains(&format!("--resume {}", run.display())),
            "{name}: rerun of an unfinished run: {e}"
        );
        let o = drape(&[
            "train",
            "--data",
            data.to_str().unwrap(),
            "--resume",
            run.to_str().unwrap(),
        ]);
        assert!(
            o.status.success(),
            "{name}: resume: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        assert!(
            String::from_utf8_lossy(&o.stdout).contains(&format!("resumed at step {step}")),
            "{name}: {}",
            String::from_utf8_lossy(&o.stdout)
        );
        assert!(
            run.join("complete").is_file(),
            "{name}: the resumed run is complete"
        );
        let resumed = drape_trainer::npy::read_npz(&run.join("model.npz")).unwrap();
        assert_eq!(
            resumed.keys().collect::<Vec<_>>(),
            reference.keys().collect::<Vec<_>>(),
            "{name}: the same arrays"
        );
        for (k, a) in &reference {
            let b = &resumed[k];
            assert_eq!(a.shape, b.shape, "{name}: {k}");
            let differ = a
                .data
                .iter()
                .zip(&b.data)
                .filter(|(x, y)| x.to_bits() != y.to_bits())
                .count();
            assert_eq!(
                differ,
                0,
                "{name}: {k}: {differ} of {} values differ from the uninterrupted run's bits",
                a.data.len()
            );
        }
    }
}

/// A second signal does not wait for the step: the process exits at once with 128 +
/// the signal's number. The first SIGTERM lands while the skinning weights are fitted
/// (long here), before any step, so the flag is set and nothing has reacted to it yet.
#[test]
fn a_second_sigterm_exits_at_once() {
    let d = dir("second-signal");
    let data = synth_sequence(&d, "32", "5");
    let config = d.join("slow-fit.toml");
    drape_io::write(
        &config,
        crate::fixtures::tiny_body_config("[schedule]\nsteps = 5\nfit_steps = 100000\n"),
    )
    .unwrap();
    let run = d.join("run");
    let mut child = Command::new(env!("CARGO_BIN_EXE_drape"))
        .args([
            "train",
            "--data",
            data.to_str().unwrap(),
            "--out",
            run.to_str().unwrap(),
            "--config",
            config.to_str().unwrap(),
        ])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = child.stderr.take().unwrap();
    read_until(&mut stderr, "fitting");
    let term = || {
        assert!(Command::new("kill")
            .args(["-TERM", &child.id().to_string()])
            .status()
            .unwrap()
            .success())
    };
    term();
    std::thread::sleep(std::time::Duration::from_millis(300));
    term();
    let started = std::time::Instant::now();
    let status = child.wait().unwrap();
    assert_eq!(
        status.code(),
        Some(128 + 15),
        "a second SIGTERM exits at once with 143"
    );
    assert!(
        started.elapsed().as_secs() < 10,
        "the second signal did not wait for the fit"
    );
    assert!(
        !run.join("checkpoint.npz").exists(),
        "no step ran, so no checkpoint"
    );
}
