//! `engine-bench` as a user runs it: JSON output, and bad input that must end in one
//! line on stderr, a non-zero exit code and no panic trace.

use std::process::{Command, Output};

fn bench(args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_engine-bench"));
    cmd.args(args);
    for (k, v) in env {
        cmd.env(k, v);
    }
    cmd.output().expect("engine-bench runs")
}

/// Asserts a failure reported in exactly one line that contains `needle`.
fn assert_one_line_error(out: &Output, needle: &str) {
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "expected failure, stderr: {stderr}");
    assert!(
        !stderr.contains("panicked") && !stderr.contains("RUST_BACKTRACE"),
        "panic trace: {stderr}"
    );
    assert_eq!(
        stderr.trim_end().lines().count(),
        1,
        "one line expected, got: {stderr}"
    );
    assert!(stderr.contains(needle), "'{needle}' not in: {stderr}");
}

#[test]
fn negative_length_is_rejected_in_one_line() {
    let out = bench(&["sort", "--n", "-5"], &[]);
    assert_one_line_error(&out, "-5");
    assert_eq!(out.status.code(), Some(2), "usage errors exit with 2");
}

#[test]
fn unknown_device_is_rejected_in_one_line() {
    let out = bench(&["--device", "nosuch", "sort", "--n", "10"], &[]);
    assert_one_line_error(&out, "no Vulkan device matches 'nosuch'");
}

#[test]
fn missing_vulkan_loader_is_reported_in_one_line() {
    let out = bench(
        &["sort", "--n", "10"],
        &[("DRAPE_VULKAN_LOADER", "/nonexistent/libvulkan.so.1")],
    );
    assert_one_line_error(&out, "Vulkan loader");
}

#[test]
fn a_negative_warm_time_is_rejected_in_one_line() {
    let out = bench(&["--warm-seconds", "-1", "sort", "--n", "10"], &[]);
    assert_one_line_error(&out, "not a number of seconds");
}

#[test]
fn too_few_runs_are_rejected() {
    let out = bench(&["scan", "--n", "10", "--runs", "3"], &[]);
    assert_one_line_error(&out, "--runs");
}

fn json_of(args: &[&str]) -> serde_json::Value {
    let out = bench(args, &[]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_str(stdout.trim())
        .unwrap_or_else(|e| panic!("stdout is not one JSON object ({e}): {stdout}"))
}

#[test]
fn sort_json_has_the_documented_fields() {
    let j = json_of(&[
        "--validation",
        "sort",
        "--n",
        "5000",
        "--bits",
        "12",
        "--json",
    ]);
    for key in [
        "device",
        "n",
        "median_ms",
        "gpu_median_ms",
        "keys_per_s",
        "cpu_median_ms",
        "passes",
    ] {
        assert!(j.get(key).is_some(), "missing '{key}' in {j}");
    }
    assert_eq!(j["n"], 5000);
    assert_eq!(j["key_bits"], 12);
    assert!(j["median_ms"].as_f64().is_some_and(|v| v > 0.0));
    // The chunk variant (CPU devices) names its scatters by layout (scatter_zip, ...).
    assert!(
        j["passes"]
            .as_object()
            .is_some_and(|p| p.keys().any(|k| k.starts_with("radix_sort.scatter"))),
        "{j}"
    );
}

#[test]
fn scan_json_has_the_documented_fields() {
    let j = json_of(&["--validation", "scan", "--n", "5000", "--json"]);
    for key in [
        "device",
        "n",
        "median_ms",
        "elems_per_s",
        "cpu_median_ms",
        "passes",
    ] {
        assert!(j.get(key).is_some(), "missing '{key}' in {j}");
    }
    // The block kernels (GPUs) reduce then sweep; the chunk kernels (CPU devices) scan
    // 5,000 elements in one invocation (`scan::chunk_serial`).
    let pass = if j["device_kind"] == "Cpu" {
        "scan.serial"
    } else {
        "scan.reduce"
    };
    assert!(j["passes"].get(pass).is_some(), "{j}");
    // By default a CPU device warms up for no minimum time, a GPU for 1 s; asked, the
    // JSON says what was asked.
    let default = if j["device_kind"] == "Cpu" { 0.0 } else { 1.0 };
    assert_eq!(j["warm_seconds"], default, "{j}");
    let j = json_of(&["--warm-seconds", "0.25", "scan", "--n", "5000", "--json"]);
    assert_eq!(j["warm_seconds"], 0.25, "{j}");
}

#[test]
fn avatar_names_a_missing_run_in_one_line() {
    let out = bench(&["avatar", "/nonexistent/run"], &[]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    // The device line comes first (the run is opened on the device).
    let lines: Vec<&str> = stderr
        .lines()
        .filter(|l| !l.starts_with("device:"))
        .collect();
    assert!(
        !out.status.success() && !stderr.contains("panicked"),
        "{stderr}"
    );
    assert_eq!(lines.len(), 1, "{stderr}");
    assert!(
        lines[0].contains("/nonexistent/run") && lines[0].contains("no such run directory"),
        "{stderr}"
    );
}

/// The shared tiny run (body + cloth at SH degree 1, the cloth with pose-dependent
/// offsets: `tests/fixtures/tiny-run.toml`), made once by the test command
/// (`DRAPE_TEST_RUN`) or trained here: enough for `engine-bench trade` to have every knob.
fn tiny_run() -> std::path::PathBuf {
    let ctx =
        drape_engine::Context::new(&drape_engine::ContextDesc::for_tests()).expect("test device");
    drape_trainer::testing::tiny_run(&ctx).to_path_buf()
}

#[test]
fn trade_measures_every_knob_and_the_default_matches_itself() {
    let run = tiny_run();
    let out = std::path::PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .join(format!("trade-out-{}", std::process::id()));
    let j = json_of(&[
        "--validation",
        "trade",
        run.to_str().unwrap(),
        "--runs",
        "1",
        "--warmup",
        "0",
        "--max-frames",
        "2",
        "--json",
        "--out",
        out.to_str().unwrap(),
    ]);
    let settings = j["settings"].as_array().expect("settings");
    let of = |knob: &str| {
        settings
            .iter()
            .filter(|s| s["knob"] == knob)
            .collect::<Vec<_>>()
    };
    for knob in [
        "resolution",
        "sh_degree",
        "pruning",
        "contribution pruning",
        "compositing",
        "pose_offsets",
        "tile_size",
        "half_sh",
        "half_splats",
    ] {
        assert!(
            j["knobs"][knob]
                .as_str()
                .is_some_and(|s| s.starts_with("measured")),
            "knob '{knob}': {}",
            j["knobs"]
        );
    }
    // 0.5x and 2x; degree 0 for the body, the cloth and both; four thresholds; the two
    // other compositing variants.
    assert_eq!(of("resolution").len(), 2, "{j}");
    assert_eq!(of("sh_degree").len(), 3, "{j}");
    assert_eq!(of("pruning").len(), 4, "{j}");
    assert_eq!(of("compositing").len(), 3, "{j}");
    // 10%, 25% and 50% of the Gaussians with the least contribution culled: exactly
    // those counts.
    let by_contribution = of("contribution pruning");
    assert_eq!(by_contribution.len(), 3, "{j}");
    let all: u64 = j["gaussians"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|p| p[1].as_u64().unwrap())
        .sum();
    for (s, q) in by_contribution.iter().zip([0.1, 0.25, 0.5]) {
        assert_eq!(
            s["gaussians_kept"].as_u64(),
            Some(all - (q * all as f64).floor() as u64),
            "{s}"
        );
        assert!(
            s["vs_default"]["psnr"].as_f64().is_some_and(|p| p < 199.0),
            "culling changes the render: {s}"
        );
    }
    // The fused frame renders the default three-pass frame's image (same sums, same
    // order): within float rounding of it.
    let fused: Vec<_> = of("compositing")
        .into_iter()
        .filter(|s| s["setting"] == "fused")
        .collect();
    assert_eq!(fused.len(), 1, "{j}");
    assert!(
        fused[0]["vs_default"]["psnr"]
            .as_f64()
            .is_some_and(|p| p > 80.0),
        "{}",
        fused[0]
    );
    // The cloth's pose blend off: one setting, and ten steps moved the blend head off
    // its zero init, so the render differs from the default.
    let pose = of("pose_offsets");
    assert_eq!(pose.len(), 1, "{j}");
    assert!(
        pose[0]["setting"]
            .as_str()
            .is_some_and(|l| l.contains("cloth") && !l.contains("body")),
        "{}",
        pose[0]
    );
    assert!(
        pose[0]["vs_default"]["psnr"]
            .as_f64()
            .is_some_and(|p| p < 199.0),
        "{}",
        pose[0]
    );
    let default = of("default");
    assert_eq!(default.len(), 1, "{j}");
    // The default render against itself: identical (PSNR at its 200 dB floor, SSIM 1).
    assert!(
        default[0]["vs_default"]["psnr"]
            .as_f64()
            .is_some_and(|p| p >= 199.0),
        "{}",
        default[0]
    );
    assert!(
        default[0]["vs_default"]["ssim"]
            .as_f64()
            .is_some_and(|s| (s - 1.0).abs() < 1e-9),
        "{}",
        default[0]
    );
    let total: u64 = j["gaussians"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|p| p[1].as_u64().unwrap())
        .sum();
    let mut last = total;
    for s in settings {
        assert!(s["ms_per_frame"].as_f64().is_some_and(|v| v > 0.0), "{s}");
        // The render alone is part of the frame.
        assert!(
            s["render_ms_per_frame"]
                .as_f64()
                .is_some_and(|v| v > 0.0 && v < s["ms_per_frame"].as_f64().unwrap()),
            "{s}"
        );
        assert!(
            s["vs_ground_truth"]["psnr"]
                .as_f64()
                .is_some_and(|v| v.is_finite() && v > 5.0),
            "{s}"
        );
        assert!(
            s["vs_default"]["lpips"].is_null(),
            "no weights: LPIPS n/a, {s}"
        );
    }
    for s in of("pruning") {
        // Higher thresholds keep no more Gaussians.
        let kept = s["gaussians_kept"].as_u64().unwrap();
        assert!(kept <= last, "{s}");
        last = kept;
    }
    // Zeroing a layer's degree-1 coefficients changes its render, not to the default's.
    for s in of("sh_degree") {
        assert!(s["vs_default"]["psnr"].as_f64().unwrap() < 199.0, "{s}");
    }
    // Tile size: 32 everywhere, 8 with the subgroup rasterizers (lavapipe); a tile
    // groups the splats a pixel walks and changes nothing of the image.
    let tiles = of("tile size");
    assert!(
        !tiles.is_empty()
            && tiles
                .iter()
                .any(|s| s["setting"].as_str().is_some_and(|l| l.starts_with("32"))),
        "{j}"
    );
    for s in &tiles {
        assert!(
            s["vs_default"]["psnr"].as_f64().is_some_and(|p| p >= 199.0),
            "the same image: {s}"
        );
    }
    // The half-precision knobs round what they store: near the default, not identical.
    for knob in ["half-precision SH", "half-precision splats"] {
        let rows = of(knob);
        assert_eq!(rows.len(), 1, "{knob}: {j}");
        assert!(
            rows[0]["vs_default"]["psnr"]
                .as_f64()
                .is_some_and(|p| p > 50.0 && p < 199.0),
            "{}",
            rows[0]
        );
    }
    let not_built: Vec<&str> = j["not_built"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|n| n["knob"].as_str().unwrap())
        .collect();
    assert_eq!(not_built, ["subdivision level"], "{j}");
    // The deterministic backward is built (`drape train --deterministic`); it is a
    // training knob, with no render to trade.
    assert!(
        !not_built.iter().any(|k| k.contains("deterministic")),
        "{not_built:?}"
    );
    assert!(settings.iter().any(|s| s["pareto"] == true), "{j}");
    // The files: the same JSON, a Markdown row per setting, a decodable plot.
    let written: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("trade.json")).expect("trade.json"))
            .expect("JSON");
    assert_eq!(written["settings"], j["settings"]);
    let md = std::fs::read_to_string(out.join("trade.md")).expect("trade.md");
    assert_eq!(
        md.lines()
            .filter(|l| l.starts_with("| ") && !l.starts_with("| knob") && !l.starts_with("| ---"))
            .count(),
        settings.len(),
        "{md}"
    );
    assert!(md.contains("not built") || md.contains("Not built"), "{md}");
    let png = image::open(out.join("trade.png")).expect("trade.png decodes");
    assert_eq!((png.width(), png.height()), (640, 480));
}

#[test]
fn ops_times_chamfer_through_the_grid_and_by_brute_force() {
    let j = json_of(&[
        "--validation",
        "ops",
        "--only",
        "chamfer",
        "--chamfer-points",
        "5000",
        // Brute force is quadratic: at the default 32,768 a side it took a minute here.
        "--chamfer-compare",
        "2000",
        "--runs",
        "1",
        "--warmup",
        "0",
        "--json",
    ]);
    let rows = j["chamfer"].as_array().expect("chamfer rows");
    let got: Vec<(String, u64)> = rows
        .iter()
        .map(|r| {
            (
                r["search"].as_str().unwrap().to_string(),
                r["points"].as_u64().unwrap(),
            )
        })
        .collect();
    assert_eq!(
        got,
        [
            ("grid".to_string(), 5000),
            ("grid".to_string(), 2000),
            ("brute force".to_string(), 2000)
        ],
        "{j}"
    );
    for r in rows {
        assert!(r["fwd_bwd_gpu_ms"].as_f64().is_some_and(|v| v > 0.0), "{r}");
    }
    assert!(
        j.get("gemm")
            .is_none_or(|g| g.as_array().is_none_or(|a| a.is_empty())),
        "--only chamfer ran the GEMMs: {j}"
    );
}

#[test]
fn composite_times_the_three_passes_serialised_in_one_submission_and_fused() {
    let j = json_of(&[
        "composite",
        "--sizes",
        "64x48",
        "--body",
        "300",
        "--cloth",
        "100",
        "--scene",
        "200",
        "--runs",
        "1",
        "--warmup",
        "1",
        "--json",
    ]);
    let r = &j["results"][0];
    assert_eq!(
        (r["width"].as_u64(), r["height"].as_u64()),
        (Some(64), Some(48)),
        "{r}"
    );
    for key in ["three_pass_serialised", "three_pass_overlapped", "one_pass"] {
        assert!(
            r[key]["forward_median_ms"]
                .as_f64()
                .is_some_and(|ms| ms > 0.0),
            "{key}: {r}"
        );
        assert!(
            r[key]["passes_gpu_ms"]["splat.rasterize_fwd"]
                .as_f64()
                .is_some_and(|ms| ms >= 0.0),
            "{key}: {r}"
        );
    }
    // After the warm-up frame grew the intersection buffers, the overlapped frame is
    // one vkQueueSubmit: three renders and the composite.
    assert_eq!(
        r["three_pass_overlapped"]["forward_submissions"].as_u64(),
        Some(1),
        "{r}"
    );
    assert!(
        r["three_pass_overlapped"]["passes_gpu_ms"]["composite.fwd"]
            .as_f64()
            .is_some(),
        "{r}"
    );
    assert!(
        r["fused"]["forward_median_ms"]
            .as_f64()
            .is_some_and(|ms| ms > 0.0),
        "{r}"
    );
    assert!(
        r["fused"]["passes_gpu_ms"]["splat.rasterize_fused_fwd"]
            .as_f64()
            .is_some(),
        "{r}"
    );
    assert!(
        r["fused"]["passes_gpu_ms"]["splat.rasterize_fwd"].is_null(),
        "the fused frame rasterizes once: {r}"
    );
    // And back-propagates in one walk.
    assert!(
        r["fused"]["forward_backward_median_ms"]
            .as_f64()
            .is_some_and(|ms| ms > r["fused"]["forward_median_ms"].as_f64().unwrap()),
        "{r}"
    );
    assert!(
        r["fused"]["passes_gpu_ms"]["splat.rasterize_fused_bwd"]
            .as_f64()
            .is_some(),
        "{r}"
    );
    assert!(
        r["fused"]["passes_gpu_ms"]["splat.rasterize_bwd"].is_null(),
        "{r}"
    );
}

/// Counts near 2^32 are refused by name before anything is allocated (they aborted on
/// allocation), and a PLY whose Gaussians are not finite is refused naming the file and
/// the property (it panicked in the camera set-up).
#[test]
fn huge_counts_and_non_finite_plys_are_refused_in_one_line() {
    assert_one_line_error(
        &bench(&["splat", "--counts", "4294967295"], &[]),
        "--counts",
    );
    assert_one_line_error(&bench(&["splat", "--counts", "0"], &[]), "--counts");
    let dir = std::path::PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("engine-bench-cli");
    std::fs::create_dir_all(&dir).unwrap();
    let ply = dir.join("nan.ply");
    let props = [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3",
    ];
    let mut bytes = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex 2\n{}end_header\n",
        props
            .iter()
            .map(|p| format!("property float {p}\n"))
            .collect::<String>()
    )
    .into_bytes();
    for v in 0..2 {
        for (i, _) in props.iter().enumerate() {
            let value: f32 = if v == 1 && i == 0 {
                f32::NAN
            } else if i == 10 {
                1.0
            } else {
                0.0
            };
            bytes.extend(value.to_le_bytes());
        }
    }
    drape_io::write(&ply, bytes).unwrap();
    assert_one_line_error(
        &bench(
            &["splat", "--ply", ply.to_str().unwrap(), "--sizes", "32x32"],
            &[],
        ),
        "nan.ply",
    );
}

/// A three-pass frame of the tiny run at 32x32 (decoders, skinning, three renders, the
/// composite), as `engine-bench avatar` counted it on lavapipe at `d2709f9`: the
/// benchmark's frame (pose, then render: two recordings) and the library's (one). A
/// change that merges passes lowers these; one that adds launches to a frame fails here
/// until it says so by raising them.
const FRAME_DISPATCHES_AT_MOST: u64 = 102;
const FRAME_BARRIERS_AT_MOST: u64 = 40;
const PLAYER_DISPATCHES_AT_MOST: f64 = 103.0;
const PLAYER_BARRIERS_AT_MOST: f64 = 39.0;

#[test]
fn avatar_compares_one_two_and_three_frames_in_flight_in_one_run() {
    let run = tiny_run();
    let frames = 6u64;
    let j = json_of(&[
        "--validation",
        "avatar",
        run.to_str().unwrap(),
        "--sizes",
        "32x32",
        "--compositing",
        "three-pass",
        "--runs",
        "1",
        "--warmup",
        "0",
        "--train-steps",
        "0",
        "--flight-frames",
        &frames.to_string(),
        "--json",
    ]);
    let settings = j["frames_in_flight"]["settings"]
        .as_array()
        .expect("frames_in_flight settings");
    assert_eq!(settings.len(), 3, "{j}");
    let frame = &j["render"][0];
    let counted = |v: &serde_json::Value, key: &str| v[key].as_f64().expect(key);
    assert!(
        counted(frame, "dispatches_per_frame") <= FRAME_DISPATCHES_AT_MOST as f64
            && counted(frame, "barriers_per_frame") <= FRAME_BARRIERS_AT_MOST as f64,
        "a frame's launches grew past {FRAME_DISPATCHES_AT_MOST} dispatches / \
         {FRAME_BARRIERS_AT_MOST} barriers: {frame}"
    );
    for (s, k) in settings.iter().zip(1u64..) {
        assert!(
            counted(s, "dispatches_per_frame") <= PLAYER_DISPATCHES_AT_MOST
                && counted(s, "barriers_per_frame") <= PLAYER_BARRIERS_AT_MOST,
            "the library frame's launches grew past {PLAYER_DISPATCHES_AT_MOST} dispatches / \
             {PLAYER_BARRIERS_AT_MOST} barriers: {s}"
        );
        assert_eq!(s["frames_in_flight"].as_u64(), Some(k), "{s}");
        assert!(s["fps"].as_f64().is_some_and(|f| f > 0.0), "{s}");
        // Frame i waits for frame i - k only: N - k waits while submitting N frames.
        assert_eq!(
            s["fence_waits_while_submitting"].as_u64(),
            Some(frames - k),
            "{s}"
        );
    }
}
