//! The cameras stage: a rig calibration's cameras matched to the videos and brought
//! to the frames' size, written as `cameras.json`.
//!
//! Matching: by name when every video's file stem names a camera of the calibration
//! (Pose2Sim's rigs: `videos/cam01.mp4` is `[cam01]`; a subset of the rig is then
//! fine), otherwise in order, and then the counts must be equal.
//!
//! Sizes: a video whose displayed size differs from its camera's by more than 1% on
//! either side is an error (another camera, or another resolution). A smaller
//! difference (Pose2Sim's cam01 and cam02 decode 1080 wide against a calibration of
//! 1088) is taken as a centred crop: the principal point moves by half the difference,
//! with a warning. (On that footage the data cannot tell a centred crop from a
//! left-aligned one: docs/notes/prepare-footage.md.) Then K scales from the video's
//! size to the frames' per axis, the widths being rounded (`sx = w'/W`, `sy = h'/H`),
//! in drape's pixel convention (centres at +0.5, so `cx' = sx cx`).
//!
//! `cameras.json` (version 1):
//!
//! ```text
//! { "format": "drape-prepare-cameras", "version": 1,
//!   "convention": "...",            # the sentence below, for a reader of the file
//!   "calibration": { "file": PATH, "format": "qualisys" | "pose2sim-toml" },
//!   "cameras": [ { "name": "cam01", "video": PATH,
//!       "width": W', "height": H',   # the frames' size (frames/<name>/*.png)
//!       "fx", "fy", "cx", "cy",      # pixels of the frames, centres at +0.5
//!       "distortion": [k1, k2, p1, p2],   # OpenCV's, on normalised coordinates
//!       "rotation": [[3], [3], [3]], "translation": [3],   # world to camera, metres
//!       "calibration_size": [W, H], "video_size": [W, H],
//!       "principal_point_shift": [dx, dy] }, ... ] }   # pixels of the video, <= 1%
//! ```
//!
//! Convention: `x_cam = R X_world + t`, x right, y down, z forward, metres; a pixel's
//! centre is at +0.5 (OpenCV's principal point is `cx - 0.5`).

use std::path::Path;

use anyhow::bail;
use drape_trainer::camera::Camera;
use drape_trainer::dataset::calibration::{Calibration, RigCamera};
use serde_json::json;

use super::frames::VideoInfo;

/// How far a video's size may be from its camera's and still be that camera.
const SIZE_TOLERANCE: f64 = 0.01;

/// The calibration's camera for each video, in the videos' order.
pub fn match_videos<'c>(
    calibration: &'c Calibration,
    file: &Path,
    videos: &[VideoInfo],
) -> anyhow::Result<Vec<&'c RigCamera>> {
    let by_name: Option<Vec<&RigCamera>> = videos
        .iter()
        .map(|v| {
            let stem = v.path.file_stem()?.to_str()?;
            calibration.cameras.iter().find(|c| c.name == stem)
        })
        .collect();
    if let Some(m) = by_name {
        let mut names: Vec<&str> = m.iter().map(|c| c.name.as_str()).collect();
        names.sort_unstable();
        names.dedup();
        if names.len() == m.len() {
            return Ok(m);
        }
    }
    if calibration.cameras.len() != videos.len() {
        bail!(
            "{}: {} cameras ({}) for {} videos; give one video per camera, in the calibration's order, or name each video after its camera (cam01.mp4)",
            file.display(),
            calibration.cameras.len(),
            calibration
                .cameras
                .iter()
                .map(|c| c.name.as_str())
                .collect::<Vec<_>>()
                .join(", "),
            videos.len()
        );
    }
    Ok(calibration.cameras.iter().collect())
}

/// A camera fitted to its video and scaled to the frames: the camera, the shift of the
/// principal point (video pixels) and the warning to print, if any.
pub struct Fitted {
    pub camera: Camera,
    pub shift: [f64; 2],
    pub warning: Option<String>,
}

/// `rig`'s camera for `video`, checked and moved for its size, scaled to `frames`.
pub fn fit(
    rig: &RigCamera,
    file: &Path,
    video: &VideoInfo,
    frames: (u32, u32),
) -> anyhow::Result<Fitted> {
    let c = rig.camera;
    let (cw, ch) = (f64::from(c.width), f64::from(c.height));
    let (vw, vh) = (f64::from(video.width), f64::from(video.height));
    let off = ((vw - cw) / cw).abs().max(((vh - ch) / ch).abs());
    if !(off <= SIZE_TOLERANCE) {
        bail!(
            "{}: camera {} is {}x{} but {} is {}x{} (displayed), more than 1% apart: another camera or another resolution",
            file.display(),
            rig.name,
            c.width,
            c.height,
            video.path.display(),
            video.width,
            video.height
        );
    }
    let shift = [(vw - cw) / 2.0, (vh - ch) / 2.0];
    let warning = (shift != [0.0, 0.0]).then(|| {
        format!(
            "warning: {}: {}x{} against camera {}'s {}x{}: taken as a centred crop, the principal point moved by ({}, {}) px",
            video.path.display(),
            video.width,
            video.height,
            rig.name,
            c.width,
            c.height,
            shift[0],
            shift[1]
        )
    });
    let (sx, sy) = (f64::from(frames.0) / vw, f64::from(frames.1) / vh);
    let camera = Camera {
        fx: c.fx * sx,
        fy: c.fy * sy,
        cx: (c.cx + shift[0]) * sx,
        cy: (c.cy + shift[1]) * sy,
        width: frames.0,
        height: frames.1,
        ..c
    };
    Ok(Fitted {
        camera,
        shift,
        warning,
    })
}

/// A path as the document records it: absolute where it can be made so.
fn absolute(p: &Path) -> String {
    p.canonicalize()
        .unwrap_or_else(|_| p.to_path_buf())
        .display()
        .to_string()
}

/// The `cameras.json` document (module header).
pub fn document(
    calibration: &Calibration,
    file: &Path,
    cameras: &[(&RigCamera, &VideoInfo, &Fitted)],
) -> serde_json::Value {
    let list: Vec<serde_json::Value> = cameras
        .iter()
        .map(|(rig, video, fitted)| {
            let c = &fitted.camera;
            let d = rig.distortion;
            json!({
                "name": rig.name,
                "video": absolute(&video.path),
                "width": c.width,
                "height": c.height,
                "fx": c.fx,
                "fy": c.fy,
                "cx": c.cx,
                "cy": c.cy,
                "distortion": [d.k1, d.k2, d.p1, d.p2],
                "rotation": c.rotation,
                "translation": c.translation.to_array(),
                "calibration_size": [rig.camera.width, rig.camera.height],
                "video_size": [video.width, video.height],
                "principal_point_shift": fitted.shift,
            })
        })
        .collect();
    json!({
        "format": "drape-prepare-cameras",
        "version": 1,
        "convention": "x_cam = R X_world + t (world to camera; x right, y down, z forward; metres); K in pixels of the frames with pixel centres at +0.5 (OpenCV's principal point is cx - 0.5, cy - 0.5); distortion OpenCV's k1 k2 p1 p2",
        "calibration": {"file": absolute(file), "format": calibration.format},
        "cameras": list,
    })
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use drape_trainer::dataset::distortion::Distortion;

    use super::*;

    fn rig(name: &str, width: u32) -> RigCamera {
        RigCamera {
            name: name.into(),
            camera: Camera {
                fx: 1680.0,
                fy: 1681.0,
                cx: 533.5,
                cy: 948.5,
                width,
                height: 1920,
                rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                translation: glam::DVec3::ZERO,
                near: Camera::NEAR,
            },
            distortion: Distortion::NONE,
        }
    }

    fn video(name: &str, width: u32) -> VideoInfo {
        VideoInfo {
            path: PathBuf::from(format!("/v/{name}.mp4")),
            width,
            height: 1920,
            frames: 100,
            fps: 60.0,
            rotation: 0,
            codec: "h264".into(),
        }
    }

    #[test]
    fn a_narrower_video_shifts_then_scales_k() {
        let f = fit(
            &rig("cam01", 1088),
            Path::new("c.toml"),
            &video("cam01", 1080),
            (72, 128),
        )
        .unwrap();
        assert_eq!(f.shift, [-4.0, 0.0]);
        assert!(f
            .warning
            .as_deref()
            .unwrap()
            .contains("principal point moved by (-4, 0)"));
        let (sx, sy) = (72.0 / 1080.0, 128.0 / 1920.0);
        assert_eq!((f.camera.width, f.camera.height), (72, 128));
        assert!((f.camera.fx - 1680.0 * sx).abs() < 1e-12);
        assert!((f.camera.fy - 1681.0 * sy).abs() < 1e-12);
        assert!((f.camera.cx - (533.5 - 4.0) * sx).abs() < 1e-12);
        assert!((f.camera.cy - 948.5 * sy).abs() < 1e-12);
        let same = fit(
            &rig("cam03", 1088),
            Path::new("c.toml"),
            &video("cam03", 1088),
            (72, 128),
        )
        .unwrap();
        assert!(same.warning.is_none());
    }

    #[test]
    fn more_than_one_percent_off_is_an_error() {
        let e = fit(
            &rig("cam01", 1088),
            Path::new("c.toml"),
            &video("cam01", 1072),
            (72, 128),
        )
        .err()
        .unwrap()
        .to_string();
        assert!(
            e.starts_with("c.toml: camera cam01 is 1088x1920") && e.contains("1072x1920"),
            "{e}"
        );
        // 1077 is 1.01% narrower than 1088; 1078 is 0.92%.
        assert!(fit(
            &rig("c", 1088),
            Path::new("c"),
            &video("c", 1077),
            (72, 128)
        )
        .is_err());
        assert!(fit(
            &rig("c", 1088),
            Path::new("c"),
            &video("c", 1078),
            (72, 128)
        )
        .is_ok());
    }

    #[test]
    fn videos_match_by_name_else_in_order_with_equal_counts() {
        let cal = Calibration {
            cameras: vec![rig("cam01", 1088), rig("cam02", 1088), rig("cam03", 1088)],
            format: "pose2sim-toml",
        };
        let file = Path::new("calib.toml");
        let m = match_videos(&cal, file, &[video("cam03", 1088), video("cam01", 1080)]).unwrap();
        assert_eq!(
            m.iter().map(|c| c.name.as_str()).collect::<Vec<_>>(),
            ["cam03", "cam01"]
        );
        let m = match_videos(
            &cal,
            file,
            &[video("a", 1088), video("b", 1088), video("c", 1088)],
        )
        .unwrap();
        assert_eq!(m[2].name, "cam03");
        let e = match_videos(&cal, file, &[video("a", 1088), video("b", 1088)])
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.starts_with("calib.toml: 3 cameras (cam01, cam02, cam03) for 2 videos"),
            "{e}"
        );
        // The same camera twice by name falls back to order (and its count check).
        assert!(match_videos(&cal, file, &[video("cam01", 1088), video("cam01", 1088)]).is_err());
    }
}
