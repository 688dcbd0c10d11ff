//! `drape inspect` on a synthetic sequence, on the same sequence with a mask removed,
//! and on a directory that is no sequence.

use std::path::PathBuf;
use std::process::{Command, Output};

fn drape(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_drape"))
        .args(args)
        .output()
        .expect("drape runs")
}

fn text(o: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

#[test]
fn inspect_names_the_variant_and_a_missing_mask() {
    let root = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("inspect-cli");
    let _ = std::fs::remove_dir_all(&root);
    let data = root.join("data");
    let o = drape(&[
        "synth",
        "--out",
        data.to_str().unwrap(),
        "--size",
        "32",
        "--frames",
        "3",
        "--cameras",
        "2",
        "--samples",
        "1",
    ]);
    assert!(o.status.success(), "synth: {}", text(&o).1);

    let o = drape(&["inspect", data.join("zju").to_str().unwrap()]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}\n{err}");
    assert!(
        out.contains("zju-refined")
            && out.contains("3 frames x 2 cameras, 32x32")
            && out.contains("problem: none"),
        "{out}"
    );
    // The synth root is inspected through its neuman/ (what `drape train` reads).
    let o = drape(&["inspect", data.to_str().unwrap()]);
    let (out, _) = text(&o);
    assert!(
        o.status.success() && out.contains("neuman+hugs") && out.contains("3 frames x 1 cameras"),
        "{out}"
    );

    let gone = data.join("zju/mask/Camera_B2/000001.png");
    std::fs::remove_file(&gone).unwrap();
    let o = drape(&["inspect", data.join("zju").to_str().unwrap()]);
    let (out, err) = text(&o);
    assert!(!o.status.success(), "a missing mask must fail: {out}");
    let problem = out
        .lines()
        .find(|l| l.trim_start().starts_with("problem:"))
        .expect("a problem line");
    assert!(
        problem.contains(&gone.display().to_string()) && problem.contains("zju-refined"),
        "{problem}"
    );
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");

    let o = drape(&["inspect", root.join("nothing").to_str().unwrap()]);
    let (out, _) = text(&o);
    assert!(
        !o.status.success() && out.contains("no such directory"),
        "{out}"
    );
}
