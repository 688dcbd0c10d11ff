//! `drape render` and `drape fit` end to end (small), and their bad input.

use std::path::PathBuf;
use std::process::Command;

fn drape(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_drape"))
        .args(args)
        .output()
        .expect("drape runs")
}

fn temp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("drape-cli-tests-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// A 16x16 PNG: a red square on blue, written with the same `image` crate.
fn write_target(path: &PathBuf) {
    let data: Vec<u8> = (0..256)
        .flat_map(|i| {
            if (i % 16 > 4) && (i / 16 > 4) {
                [220, 40, 30]
            } else {
                [20, 40, 200]
            }
        })
        .collect();
    image::RgbImage::from_raw(16, 16, data)
        .unwrap()
        .save_with_format(path, image::ImageFormat::Png)
        .unwrap();
}

#[test]
fn fit_then_render_round_trip() {
    let target = temp("target.png");
    write_target(&target);
    let ply = temp("fit.ply");
    let out = drape(&[
        "--validation",
        "fit",
        "--target",
        target.to_str().unwrap(),
        "--n",
        "300",
        "--iters",
        "60",
        "--out",
        ply.to_str().unwrap(),
    ]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "fit failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("PSNR"), "{stdout}");

    let image = temp("render.png");
    let out = drape(&[
        "--validation",
        "render",
        "--ply",
        ply.to_str().unwrap(),
        "--eye",
        "0,0,0",
        "--look-at",
        "0,0,3",
        "--width",
        "40",
        "--height",
        "30",
        "--out",
        image.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "render failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(image::image_dimensions(&image).unwrap(), (40, 30));
}

fn assert_one_line_error(out: &std::process::Output, needle: &str) {
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(stderr.trim_end().lines().count(), 1, "{stderr}");
    assert!(stderr.contains(needle), "'{needle}' not in {stderr}");
}

#[test]
fn render_reports_a_missing_ply_in_one_line() {
    let out = drape(&[
        "render",
        "--ply",
        "/nonexistent/scene.ply",
        "--out",
        "/tmp/x.png",
    ]);
    assert_one_line_error(&out, "/nonexistent/scene.ply");
    // The OS's reason once, not once from the message and again from its source.
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        stderr.matches("No such file or directory").count(),
        1,
        "{stderr}"
    );
}

/// Sizes are named: a zero width by its option, an image too large for one binding by
/// its size in pixels and bytes and the device limit (it said "0 bytes" before).
#[test]
fn render_names_bad_image_sizes() {
    let target = temp("size-target.png");
    write_target(&target);
    let ply = temp("size.ply");
    let out = drape(&[
        "fit",
        "--target",
        target.to_str().unwrap(),
        "--n",
        "50",
        "--iters",
        "1",
        "--out",
        ply.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "fit failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = drape(&[
        "render",
        "--ply",
        ply.to_str().unwrap(),
        "--width",
        "0",
        "--out",
        "/tmp/x.png",
    ]);
    assert_one_line_error(&out, "'--width <WIDTH>'");
    let image = temp("huge.png");
    let out = drape(&[
        "render",
        "--ply",
        ply.to_str().unwrap(),
        "--width",
        "100000",
        "--height",
        "100000",
        "--out",
        image.to_str().unwrap(),
    ]);
    assert_one_line_error(&out, "'--width <WIDTH>'");
    // Within the side limit but beyond what one storage buffer of the device holds: the
    // options are named with the size and the limit.
    let out = drape(&[
        "render",
        "--ply",
        ply.to_str().unwrap(),
        "--width",
        "16384",
        "--height",
        "16384",
        "--out",
        image.to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    let error: Vec<&str> = stderr
        .lines()
        .filter(|l| !l.starts_with("device:"))
        .collect();
    assert!(!out.status.success() && error.len() == 1, "{stderr}");
    assert!(
        error[0].contains("--width")
            && error[0].contains("16384x16384")
            && error[0].contains("maxStorageBufferRange"),
        "{stderr}"
    );
    assert!(!image.exists(), "nothing written");
}

#[test]
fn render_reports_a_bad_camera_file_naming_it() {
    let cam = temp("camera.json");
    drape_io::write(&cam, r#"{"fx": -1, "fy": 100, "cx": 8, "cy": 8, "width": 16, "height": 16, "rotation": [[1,0,0],[0,1,0],[0,0,1]], "translation": [0,0,0]}"#).unwrap();
    let ply = temp("any.ply");
    drape_io::write(&ply, b"not a ply").unwrap();
    let out = drape(&[
        "render",
        "--ply",
        ply.to_str().unwrap(),
        "--camera",
        cam.to_str().unwrap(),
        "--out",
        "/tmp/x.png",
    ]);
    assert_one_line_error(&out, "fx and fy must be positive");
}

#[test]
fn fit_reports_a_truncated_png() {
    let target = temp("truncated.png");
    write_target(&target);
    let bytes = std::fs::read(&target).unwrap();
    drape_io::write(&target, &bytes[..bytes.len() / 2]).unwrap();
    let out = drape(&[
        "fit",
        "--target",
        target.to_str().unwrap(),
        "--out",
        "/tmp/x.ply",
    ]);
    assert_one_line_error(&out, "truncated.png");
}
