//! `drape demo` end to end (small), and its bad input.

use std::process::Command;

#[test]
fn demo_sorts_and_agrees_with_the_cpu() {
    let out = Command::new(env!("CARGO_BIN_EXE_drape"))
        .args(["--validation", "demo", "--n", "20000"])
        .output()
        .expect("drape runs");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        stdout.contains("identical to the CPU's stable sort: yes"),
        "{stdout}"
    );
}

#[test]
fn demo_rejects_a_negative_length_in_one_line() {
    let out = Command::new(env!("CARGO_BIN_EXE_drape"))
        .args(["demo", "--n", "-1"])
        .output()
        .expect("drape runs");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert_eq!(stderr.trim_end().lines().count(), 1, "{stderr}");
    assert!(stderr.contains("negative"), "{stderr}");
}
