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
    assert!(!stderr.contains("panicked") && !stderr.contains("RUST_BACKTRACE"), "panic trace: {stderr}");
    assert_eq!(stderr.trim_end().lines().count(), 1, "one line expected, got: {stderr}");
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
    let out = bench(&["sort", "--n", "10"], &[("DRAPE_VULKAN_LOADER", "/nonexistent/libvulkan.so.1")]);
    assert_one_line_error(&out, "Vulkan loader");
}

#[test]
fn too_few_runs_are_rejected() {
    let out = bench(&["scan", "--n", "10", "--runs", "3"], &[]);
    assert_one_line_error(&out, "--runs");
}

fn json_of(args: &[&str]) -> serde_json::Value {
    let out = bench(args, &[]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{args:?} failed: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_str(stdout.trim()).unwrap_or_else(|e| panic!("stdout is not one JSON object ({e}): {stdout}"))
}

#[test]
fn sort_json_has_the_documented_fields() {
    let j = json_of(&["--validation", "sort", "--n", "5000", "--bits", "12", "--json"]);
    for key in ["device", "n", "median_ms", "gpu_median_ms", "keys_per_s", "cpu_median_ms", "passes"] {
        assert!(j.get(key).is_some(), "missing '{key}' in {j}");
    }
    assert_eq!(j["n"], 5000);
    assert_eq!(j["key_bits"], 12);
    assert!(j["median_ms"].as_f64().is_some_and(|v| v > 0.0));
    assert!(j["passes"].get("radix_sort.scatter").is_some(), "{j}");
}

#[test]
fn scan_json_has_the_documented_fields() {
    let j = json_of(&["--validation", "scan", "--n", "5000", "--json"]);
    for key in ["device", "n", "median_ms", "elems_per_s", "cpu_median_ms", "passes"] {
        assert!(j.get(key).is_some(), "missing '{key}' in {j}");
    }
    assert!(j["passes"].get("scan.reduce").is_some(), "{j}");
}

#[test]
fn avatar_names_a_missing_run_in_one_line() {
    let out = bench(&["avatar", "/nonexistent/run"], &[]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    // The device line comes first (the run is opened on the device).
    let lines: Vec<&str> = stderr.lines().filter(|l| !l.starts_with("device:")).collect();
    assert!(!out.status.success() && !stderr.contains("panicked"), "{stderr}");
    assert_eq!(lines.len(), 1, "{stderr}");
    assert!(lines[0].contains("/nonexistent/run") && lines[0].contains("no such run directory"), "{stderr}");
}
