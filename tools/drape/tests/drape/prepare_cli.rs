//! `drape prepare` on real footage: two views of Pose2Sim 0.10.49's Demo_SinglePerson
//! (cam01, 1080 wide against its calibration's 1088, and cam03, 1088), frames 0:6
//! every 3rd at height 128, with the demo's Qualisys calibration: the frames' names and
//! sizes, the frame named 000003 being source frame 3 (against ffmpeg's own decode of
//! it), `cameras.json` against Pose2Sim's own conversion of the calibration
//! (`tests/fixtures/pose2sim/Calib_qualisys.json`) moved and scaled as documented, the
//! principal point warning for cam01 only, and the stage stamps on a rerun. Then a
//! phone video (rotation in the container), and the one-line errors: an unreadable
//! video, a calibration for another number of cameras, ffmpeg missing.
//!
//! The footage: `$DRAPE_POSE2SIM` (the root `scripts/pose2sim-footage.sh` prints), else
//! this test runs that script itself (downloads the 51 MB wheel once into `target/`,
//! sha256-checked). It is never skipped: without the footage it fails.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Demo_SinglePerson's directory (module header).
fn footage() -> &'static Path {
    static ROOT: OnceLock<PathBuf> = OnceLock::new();
    ROOT.get_or_init(|| {
        let root = match std::env::var_os("DRAPE_POSE2SIM") {
            Some(r) => PathBuf::from(r),
            None => {
                let o = Command::new(repo().join("scripts/pose2sim-footage.sh"))
                    .output()
                    .expect("scripts/pose2sim-footage.sh runs");
                assert!(
                    o.status.success(),
                    "scripts/pose2sim-footage.sh (set DRAPE_POSE2SIM to skip the download): {}",
                    String::from_utf8_lossy(&o.stderr)
                );
                let out = String::from_utf8_lossy(&o.stdout);
                PathBuf::from(
                    out.lines()
                        .last()
                        .expect("the script prints the root")
                        .trim(),
                )
            }
        };
        let demo = root.join("Pose2Sim/Demo_SinglePerson");
        assert!(
            demo.join("videos/cam01.mp4").is_file(),
            "{}: no Pose2Sim footage there",
            demo.display()
        );
        demo
    })
}

fn scratch(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .join("prepare-cli")
        .join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn drape(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_drape"))
        .args(args)
        .env("RUST_BACKTRACE", "0")
        .output()
        .expect("drape runs")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The single `error:` line of a failed run.
fn one_error(o: &Output) -> String {
    let err = stderr(o);
    assert!(!o.status.success(), "exit 0, an error was expected: {err}");
    assert!(!err.contains("panicked"), "{err}");
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("error")).collect();
    assert_eq!(lines.len(), 1, "one error line expected: {err}");
    lines[0].to_string()
}

fn rgb(path: &Path) -> image::RgbImage {
    image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgb8()
}

/// ffmpeg's own decode of `video`'s source frame `n`, with `filter` after the choice.
fn ffmpeg_frame(video: &Path, n: u64, filter: &str, out: &Path) -> image::RgbImage {
    let vf = format!("select=eq(n\\,{n}){filter}");
    let o = Command::new("ffmpeg")
        .args(["-nostdin", "-v", "error", "-y", "-i"])
        .arg(video)
        .args(["-vf", &vf, "-frames:v", "1"])
        .arg(out)
        .output()
        .expect("ffmpeg runs");
    assert!(o.status.success(), "ffmpeg: {}", stderr(&o));
    rgb(out)
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-9 * b.abs().max(1.0)
}

#[test]
fn prepare_two_pose2sim_views_frames_and_cameras() {
    let demo = footage();
    let d = scratch("pose2sim");
    let out = d.join("out");
    let args = |extra: &[&str]| -> Vec<std::ffi::OsString> {
        let mut a: Vec<std::ffi::OsString> = vec![
            "prepare".into(),
            demo.join("videos/cam01.mp4").into(),
            demo.join("videos/cam03.mp4").into(),
            "--calibration".into(),
            demo.join("calibration/Calib.qca.txt").into(),
            "--frames".into(),
            "0:6".into(),
            "--every".into(),
            "3".into(),
            "--height".into(),
            "128".into(),
            "--until".into(),
            "cameras".into(),
            "--out".into(),
            out.clone().into(),
        ];
        a.extend(extra.iter().map(Into::into));
        a
    };
    let run = |extra: &[&str]| {
        let a = args(extra);
        let o = drape(&a.iter().map(|s| s.as_os_str()).collect::<Vec<_>>());
        assert!(o.status.success(), "drape prepare: {}", stderr(&o));
        stderr(&o)
    };
    let err = run(&[]);

    // Frames: the source indices 0 and 3, at 72x128 (1080 and 1088 wide both round to 72).
    for cam in ["cam01", "cam03"] {
        let mut pngs: Vec<String> = std::fs::read_dir(out.join("frames").join(cam))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".png"))
            .collect();
        pngs.sort();
        assert_eq!(pngs, ["000000.png", "000003.png"], "{cam}");
        for p in &pngs {
            let img = rgb(&out.join("frames").join(cam).join(p));
            assert_eq!(img.dimensions(), (72, 128), "{cam}/{p}");
        }
    }
    // The file named 000003 is source frame 3, decoded and scaled as ffmpeg does alone.
    let want = ffmpeg_frame(
        &demo.join("videos/cam01.mp4"),
        3,
        ",scale=72:128:flags=area",
        &d.join("ffmpeg-3.png"),
    );
    assert!(
        rgb(&out.join("frames/cam01/000003.png")) == want,
        "frame 3 differs from ffmpeg's"
    );
    let other = ffmpeg_frame(
        &demo.join("videos/cam01.mp4"),
        4,
        ",scale=72:128:flags=area",
        &d.join("ffmpeg-4.png"),
    );
    assert!(
        other != want,
        "frames 3 and 4 are alike: the check above proves nothing"
    );

    // The warning for cam01 (1080 against 1088), none for cam03.
    let warnings: Vec<&str> = err.lines().filter(|l| l.starts_with("warning")).collect();
    assert_eq!(warnings.len(), 1, "{err}");
    assert!(
        warnings[0].contains("cam01.mp4")
            && warnings[0].contains("principal point moved by (-4, 0)"),
        "{err}"
    );

    // cameras.json against Pose2Sim's conversion: shifted by half the width difference,
    // then scaled per axis, in drape's pixel convention (centres at +0.5).
    let doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("cameras.json")).unwrap()).unwrap();
    let reference: serde_json::Value = serde_json::from_slice(
        &std::fs::read(repo().join("tests/fixtures/pose2sim/Calib_qualisys.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(doc["format"], "drape-prepare-cameras");
    assert_eq!(doc["calibration"]["format"], "qualisys");
    let cams = doc["cameras"].as_array().unwrap();
    assert_eq!(cams.len(), 2);
    for (cam, ref_index, video_width, shift) in
        [(&cams[0], 0, 1080.0, -4.0), (&cams[1], 2, 1088.0, 0.0)]
    {
        let r = &reference["cameras"][ref_index];
        assert_eq!(cam["name"], r["name"]);
        assert_eq!(
            (cam["width"].as_u64(), cam["height"].as_u64()),
            (Some(72), Some(128))
        );
        let (sx, sy) = (72.0 / video_width, 128.0 / 1920.0);
        let k = |i: usize, j: usize| r["K"][i][j].as_f64().unwrap();
        let got = |key: &str| cam[key].as_f64().unwrap();
        assert!(
            close(got("fx"), k(0, 0) * sx),
            "{} fx {}",
            cam["name"],
            got("fx")
        );
        assert!(
            close(got("fy"), k(1, 1) * sy),
            "{} fy {}",
            cam["name"],
            got("fy")
        );
        assert!(
            close(got("cx"), (k(0, 2) + 0.5 + shift) * sx),
            "{} cx {}",
            cam["name"],
            got("cx")
        );
        assert!(
            close(got("cy"), (k(1, 2) + 0.5) * sy),
            "{} cy {}",
            cam["name"],
            got("cy")
        );
        assert_eq!(cam["principal_point_shift"][0].as_f64(), Some(shift));
        for i in 0..3 {
            let t = cam["translation"][i].as_f64().unwrap();
            assert!(
                close(t, r["translation_m"][i].as_f64().unwrap()),
                "t[{i}] {t}"
            );
            for j in 0..3 {
                let v = cam["rotation"][i][j].as_f64().unwrap();
                assert!(
                    close(v, r["rotation_matrix"][i][j].as_f64().unwrap()),
                    "R {v}"
                );
            }
        }
        for i in 0..4 {
            let v = cam["distortion"][i].as_f64().unwrap();
            assert!(
                close(v, r["distortions"][i].as_f64().unwrap()),
                "distortion {v}"
            );
        }
    }

    // A rerun skips both stages and leaves the frames as they were; --redo frames
    // decodes again.
    let frame = out.join("frames/cam01/000000.png");
    let modified = std::fs::metadata(&frame).unwrap().modified().unwrap();
    let again = run(&[]);
    assert!(
        again.contains("frames: cam01: 2 frames up to date (skipped)"),
        "{again}"
    );
    assert!(
        again.contains("cameras.json is up to date (skipped)"),
        "{again}"
    );
    assert_eq!(
        std::fs::metadata(&frame).unwrap().modified().unwrap(),
        modified
    );
    let redo = run(&["--redo", "frames"]);
    assert!(!redo.contains("skipped"), "{redo}");
    assert!(
        redo.contains("frames: cam03: 2 frames (0..3) at 72x128"),
        "{redo}"
    );
}

/// A phone video: stored 64x32 with a quarter turn in the container, decoded upright.
#[test]
fn prepare_applies_a_phone_videos_rotation() {
    let d = scratch("phone");
    let plain = d.join("plain.mp4");
    let phone = d.join("phone.mp4");
    let ff = |args: &[&str]| {
        let o = Command::new("ffmpeg")
            .args(["-nostdin", "-v", "error", "-y"])
            .args(args)
            .output()
            .expect("ffmpeg runs");
        assert!(o.status.success(), "ffmpeg {args:?}: {}", stderr(&o));
    };
    ff(&[
        "-f",
        "lavfi",
        "-i",
        "testsrc=size=64x32:rate=10",
        "-frames:v",
        "6",
        "-c:v",
        "libx264",
        "-pix_fmt",
        "yuv444p",
        plain.to_str().unwrap(),
    ]);
    // ffmpeg 5.1 writes the rotation into the display matrix when stream-copying.
    ff(&[
        "-i",
        plain.to_str().unwrap(),
        "-c",
        "copy",
        "-metadata:s:v:0",
        "rotate=90",
        phone.to_str().unwrap(),
    ]);
    let out = d.join("out");
    let o = drape(&[
        "prepare".as_ref(),
        phone.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
        "--until".as_ref(),
        "frames".as_ref(),
    ]);
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("32x64, 6 frames at 10.00 fps, h264, rotated 90 degrees"),
        "{err}"
    );
    let ours = rgb(&out.join("frames/phone/000000.png"));
    assert_eq!(ours.dimensions(), (32, 64));
    // The stored frame turned as the display matrix says: ffprobe's "rotation": 90 is
    // a quarter turn counter-clockwise (ffmpeg's convention, which its autorotation and
    // players follow).
    let stored = ffmpeg_frame(&plain, 0, "", &d.join("stored.png"));
    let diff = |a: &image::RgbImage, b: &image::RgbImage| -> f64 {
        a.as_raw()
            .iter()
            .zip(b.as_raw())
            .map(|(x, y)| f64::from(x.abs_diff(*y)))
            .sum::<f64>()
            / a.as_raw().len() as f64
    };
    let clockwise = image::imageops::rotate90(&stored);
    let anticlockwise = image::imageops::rotate270(&stored);
    let (cw, acw) = (diff(&ours, &clockwise), diff(&ours, &anticlockwise));
    // Both come from one decoded frame (4:4:4, so no chroma siting to differ by):
    // within rounding of the colour conversion; the wrong turn is far off.
    assert!(
        acw < 1.0 && cw > 20.0,
        "mean difference clockwise {cw}, anticlockwise {acw}"
    );
}

#[test]
fn prepare_errors_name_the_file_and_write_nothing() {
    let d = scratch("errors");
    let out = d.join("out");
    // An unreadable video.
    let bad = d.join("broken.mp4");
    drape_io::write(&bad, "not a video").unwrap();
    let o = drape(&[
        "prepare".as_ref(),
        bad.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    let line = one_error(&o);
    assert!(
        line.contains("broken.mp4") && line.contains("not a video ffmpeg can read"),
        "{line}"
    );
    assert!(!out.exists(), "--out was created");

    // Four cameras for two videos that are not named after them.
    let demo = footage();
    let a = d.join("a.mp4");
    std::fs::copy(demo.join("videos/cam03.mp4"), &a).unwrap();
    let o = drape(&[
        "prepare".as_ref(),
        a.as_os_str(),
        demo.join("videos/cam04.mp4").as_os_str(),
        "--calibration".as_ref(),
        demo.join("calibration/Calib.qca.txt").as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    let line = one_error(&o);
    assert!(
        line.contains("Calib.qca.txt: 4 cameras (cam01, cam02, cam03, cam04) for 2 videos"),
        "{line}"
    );
    assert!(!out.exists(), "--out was created");

    // ffmpeg missing: one line saying what to install.
    let o = Command::new(env!("CARGO_BIN_EXE_drape"))
        .args([
            "prepare".as_ref(),
            a.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
        ])
        .env("PATH", d.join("no-bin"))
        .output()
        .unwrap();
    let line = one_error(&o);
    assert!(
        line.contains("ffprobe was not found") && line.contains("apt-get install ffmpeg"),
        "{line}"
    );
    assert!(!out.exists(), "--out was created");
}

/// The whole path on real footage, small: cam01 and cam03 (1080 and 1088 wide, so the
/// sequence stage crops one: 146 wide to 144), frames 0:20 every 4th at height 256 → mediapipe's
/// landmarks and masks → the body fit → a zju-refined sequence that `drape inspect`
/// accepts → a few training steps on cam01 with cam03 held out.
#[test]
fn prepare_to_training_on_two_pose2sim_views() {
    let demo = footage();
    let d = scratch("end-to-end");
    let out = d.join("out");
    let o = drape(&[
        "prepare".as_ref(),
        demo.join("videos/cam01.mp4").as_os_str(),
        demo.join("videos/cam03.mp4").as_os_str(),
        "--calibration".as_ref(),
        demo.join("calibration/Calib.qca.txt").as_os_str(),
        "--frames".as_ref(),
        "0:20".as_ref(),
        "--every".as_ref(),
        "4".as_ref(),
        "--height".as_ref(),
        "256".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    let err = stderr(&o);
    assert!(o.status.success(), "drape prepare: {err}");
    assert!(err.contains("cropped about their centre"), "{err}");

    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("body/report.json")).unwrap()).unwrap();
    for v in report["views"].as_array().unwrap() {
        assert_eq!(v["detection_rate"].as_f64(), Some(1.0), "{v}");
    }
    // The bounds on the full footage are 1% (triangulated) and 1.5% (fitted
    // body); two views of five frames have less to average, so 2x those.
    let tri = report["triangulation_median_percent_of_height"]
        .as_f64()
        .unwrap();
    let fit = report["fitted_body_median_percent_of_height"]
        .as_f64()
        .unwrap();
    assert!(tri <= 2.0, "triangulated landmarks: {tri}% of the height");
    assert!(fit <= 3.0, "fitted body: {fit}% of the height");

    let o = drape(&["inspect".as_ref(), out.as_os_str()]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "drape inspect: {text}{}", stderr(&o));
    assert!(text.contains("zju-refined"), "{text}");
    assert!(text.contains("x 2 cameras, 144x256"), "{text}");

    let run = d.join("run");
    let o = drape(&[
        "train".as_ref(),
        "--data".as_ref(),
        out.as_os_str(),
        "--config".as_ref(),
        repo().join("tests/fixtures/tiny-run.toml").as_os_str(),
        "--layers".as_ref(),
        "auto".as_ref(),
        "--steps".as_ref(),
        "5".as_ref(),
        "--train-cameras".as_ref(),
        "0".as_ref(),
        "--test-cameras".as_ref(),
        "1".as_ref(),
        "--out".as_ref(),
        run.as_os_str(),
    ]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "drape train: {text}{}", stderr(&o));
    assert!(
        text.contains("body: ") && text.contains("sequence/body_model.npz"),
        "{text}"
    );
    assert!(
        text.contains("no cloth layer: the data has no garment masks"),
        "{text}"
    );
    assert!(text.contains(" held-out images at "), "{text}");
    let metrics: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("metrics.json")).unwrap()).unwrap();
    let psnr = metrics["fin"]["psnr_crop"].as_f64();
    assert!(psnr.is_some_and(f64::is_finite), "{metrics}");
}
