//! `drape bench-cloth` end to end at a tiny size (32 px, 4 frames, 3 training steps, 2
//! skinning-weight fit steps; one loose walking sequence; the full row and the
//! single-layer baseline): the three reports are written and every row's held-out
//! metrics are finite numbers. The numbers themselves mean nothing at this size.

use std::path::PathBuf;
use std::process::Command;

fn drape(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_drape"))
        .args(args)
        .output()
        .expect("drape runs")
}

fn dir(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .join("bench-cloth-cli")
        .join(name);
    let _ = std::fs::remove_dir_all(&d);
    d
}

#[test]
fn tiny_benchmark_writes_finite_metrics_per_row() {
    let out = dir("tiny");
    let o = drape(&[
        "bench-cloth",
        "--out",
        out.to_str().unwrap(),
        "--size",
        "32",
        "--frames",
        "4",
        "--steps",
        "3",
        "--fit-steps",
        "2",
        "--fits",
        "loose",
        "--motions",
        "walk",
        "--rows",
        "full,single-layer",
    ]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "bench-cloth failed: {stdout}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    eprintln!("{stdout}");
    // A progress line per run.
    assert!(
        stdout.contains("[1/2] loose-walk full")
            && stdout.contains("[2/2] loose-walk single-layer"),
        "{stdout}"
    );
    for f in ["bench.json", "bench.md", "bench.png"] {
        assert!(out.join(f).is_file(), "{f} not written");
    }
    let png = std::fs::read(out.join("bench.png")).unwrap();
    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n"), "bench.png is a PNG");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("bench.json")).unwrap()).unwrap();
    let seqs = report["sequences"].as_array().unwrap();
    assert_eq!(seqs.len(), 1);
    assert_eq!(seqs[0]["sequence"], "loose-walk");
    let rows = seqs[0]["rows"].as_array().unwrap();
    assert_eq!(
        rows.iter()
            .map(|r| r["row"].as_str().unwrap())
            .collect::<Vec<_>>(),
        ["full", "single-layer"]
    );
    for r in rows {
        let m = &r["metrics"];
        for key in ["psnr_full", "psnr_crop", "ssim_full", "ssim_crop"] {
            // Non-finite values are written as null, so a number here is finite.
            let v = m[key]
                .as_f64()
                .unwrap_or_else(|| panic!("{} {key}: {}", r["row"], m[key]));
            assert!(v.is_finite() && v > 0.0, "{} {key} = {v}", r["row"]);
        }
        assert!(m["lpips_crop"].is_null(), "no LPIPS without weights");
        assert!(r["wall_s"].as_f64().unwrap() > 0.0 && r["it_per_s"].as_f64().unwrap() > 0.0);
        assert!(
            PathBuf::from(r["run"].as_str().unwrap())
                .join("model.npz")
                .is_file(),
            "each row is an ordinary run"
        );
    }
    let chamfer = |i: usize| rows[i]["metrics"]["cloth_chamfer_m"].clone();
    assert!(
        chamfer(0)
            .as_f64()
            .is_some_and(|c| c.is_finite() && c > 0.0),
        "the full model has cloth: {}",
        chamfer(0)
    );
    assert!(
        chamfer(1).is_null(),
        "the single layer has no cloth Gaussians"
    );
    // The claim is decided from the numbers, row by row.
    let claim = &report["claim"][0]["rows"][0];
    assert_eq!(claim["row"], "single-layer");
    let (f, s) = (
        rows[0]["metrics"]["psnr_crop"].as_f64().unwrap(),
        rows[1]["metrics"]["psnr_crop"].as_f64().unwrap(),
    );
    assert_eq!(claim["comparisons"]["psnr_crop"]["full_better"], f > s);
    let md = std::fs::read_to_string(out.join("bench.md")).unwrap();
    assert!(
        md.contains("## loose-walk")
            && md.contains("| full |")
            && md.contains("| single-layer |")
            && md.contains("full vs single-layer"),
        "{md}"
    );
}

#[test]
fn unknown_rows_fits_and_motions_are_one_line_and_write_nothing() {
    for (flag, value, expected) in [
        ("--rows", "full,ours", "'ours'"),
        ("--fits", "baggy", "'baggy'"),
        ("--motions", "swim", "'swim'"),
    ] {
        let out = dir(&format!("bad{flag}"));
        let o = drape(&["bench-cloth", "--out", out.to_str().unwrap(), flag, value]);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success());
        assert_eq!(
            stderr
                .trim()
                .lines()
                .filter(|l| l.starts_with("error"))
                .count(),
            1,
            "{stderr}"
        );
        assert!(stderr.contains(expected), "{stderr}");
        assert!(!out.exists(), "nothing written for {flag} {value}");
    }
}
