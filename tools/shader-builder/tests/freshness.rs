//! The freshness check on a temporary copy of `shaders-rs`: an untouched copy passes,
//! and a copy whose kernel source changed without rebuilding fails, naming the module;
//! `--baseline-only` without `--check` is refused.

use std::path::{Path, PathBuf};
use std::process::Command;

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let path = entry.path();
        if path.file_name().is_some_and(|n| n == "target") {
            continue;
        }
        let dest = to.join(entry.file_name());
        if path.is_dir() {
            copy_dir(&path, &dest);
        } else {
            std::fs::copy(&path, &dest).unwrap();
        }
    }
}

/// `--check --baseline-only`: the scan kernels live in the baseline build, and the
/// whole check of the repository itself is the test command's first step.
fn check(shaders: &Path) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_shader-builder"))
        .arg("--check")
        .arg("--baseline-only")
        .arg("--shaders")
        .arg(shaders)
        .output()
        .expect("shader-builder runs");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn changed_kernel_source_without_rebuild_fails_the_check() {
    let repo_shaders = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shaders-rs");
    let tmp: PathBuf = Path::new(env!("CARGO_TARGET_TMPDIR")).join("freshness-copy");
    let _ = std::fs::remove_dir_all(&tmp);
    copy_dir(&repo_shaders, &tmp);

    let (fresh, stderr) = check(&tmp);
    assert!(fresh, "an untouched copy must pass the check: {stderr}");

    let source = tmp.join("kernels/src/scan.rs");
    let text = std::fs::read_to_string(&source).unwrap();
    let edited = text.replace(
        "sum = sum.wrapping_add(data[idx as usize]);",
        "sum = sum.wrapping_add(data[idx as usize] ^ 1);",
    );
    assert_ne!(
        text, edited,
        "the edit must apply to the scan kernel source"
    );
    std::fs::write(&source, edited).unwrap();

    let (fresh, stderr) = check(&tmp);
    assert!(!fresh, "a changed kernel must fail the check");
    assert!(
        stderr.contains("module scan::reduce"),
        "the stale module is named: {stderr}"
    );
    assert!(
        !stderr.contains("module radix_sort::"),
        "untouched modules are not blamed: {stderr}"
    );
    let _ = std::fs::remove_dir_all(&tmp);
}

#[test]
fn baseline_only_is_a_check_not_a_write() {
    let out = Command::new(env!("CARGO_BIN_EXE_shader-builder"))
        .arg("--baseline-only")
        .output()
        .expect("shader-builder runs");
    assert_eq!(
        out.status.code(),
        Some(2),
        "a partial write must be refused"
    );
    assert!(String::from_utf8_lossy(&out.stderr).contains("--baseline-only needs --check"));
}
