//! The body stage: the landmarks of every view triangulated ([`super::triangulate`])
//! and drape's SMPL-format body fitted to them (`drape_trainer::body::fit`), written to
//! `DIR/body/`:
//!
//! - `landmarks3d.npy`: float32 [frames, 33, 5], per mediapipe landmark x, y, z in the
//!   calibration's world (metres; NaN where no two views solved it), the number of
//!   views it was solved from, the number of views rejected (the one-bad-view rule).
//! - `smpl_params.npz`: the fitted sequence in NeuMan's layout as the trainer reads it
//!   (`global_orient` F×3, `body_pose` F×69, `betas` F×10, `transl` F×3, `scale` F, all
//!   ones): the body posed straight into the calibration's world (z-up for a Qualisys
//!   rig: the root's rotation carries the turn from the body's y-up).
//! - `body_model.npz`: the procedural body with its limb-length shape directions in
//!   betas 2..9 (smplx's layout), the model those parameters pose.
//! - `report.json`: per view the detection rate, the time offset found, the median
//!   reprojection error of the triangulated landmarks (pixels of the frames and % of
//!   the image height: of the views each point was solved from, and of every view that
//!   saw it) and of the fitted body's landmarks; the fitted limb lengths; timings.
//! - `sheet.png`: the fitted body drawn over frames of every view ([`super::sheet`]).
//!
//! It needs `cameras.json` (a calibrated rig) and two views or more; one view (a
//! monocular fit) is not built yet and the stage says so.

use std::path::Path;
use std::time::Instant;

use anyhow::{bail, Context as _};
use drape_trainer::body::fit::{self, FitBody, FitOptions, Marker, MEDIAPIPE_MARKERS};
use drape_trainer::body::procedural::{default_body, BodyOptions};
use drape_trainer::camera::Camera;
use drape_trainer::dataset::distortion::{self, Distortion};
use drape_trainer::dataset::neuman::SmplSequence;
use drape_trainer::npy::{self, Array, Dtype};
use glam::DVec3;
use serde_json::json;

use super::sheet;
use super::triangulate::{self, median_of, Options, Track, Triangulation, LANDMARKS};
use super::{commit_stage, progress, read_stamp};

/// Bumped when the stage's method changes, so that a rerun redoes it.
const METHOD: &str =
    "body v1: DLT + one-bad-view rejection + time offsets; limb-length fit; sheet.png";

/// The views of `cameras.json`.
pub(super) fn read_cameras(
    out: &Path,
) -> anyhow::Result<(serde_json::Value, Vec<triangulate::View>)> {
    let path = out.join("cameras.json");
    let text = std::fs::read_to_string(&path).with_context(|| format!("{}", path.display()))?;
    let doc: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}", path.display()))?;
    let bad = || anyhow::anyhow!("{}: not a drape prepare cameras.json", path.display());
    let mut views = Vec::new();
    for c in doc["cameras"].as_array().ok_or_else(bad)? {
        let num = |k: &str| c[k].as_f64().ok_or_else(bad);
        let arr = |v: &serde_json::Value, n: usize| -> anyhow::Result<Vec<f64>> {
            let a = v.as_array().ok_or_else(bad)?;
            if a.len() != n {
                return Err(bad());
            }
            a.iter().map(|x| x.as_f64().ok_or_else(bad)).collect()
        };
        let rows = c["rotation"].as_array().ok_or_else(bad)?;
        if rows.len() != 3 {
            return Err(bad());
        }
        let mut rotation = [[0.0; 3]; 3];
        for (r, row) in rotation.iter_mut().zip(rows) {
            r.copy_from_slice(&arr(row, 3)?);
        }
        let t = arr(&c["translation"], 3)?;
        let d = arr(&c["distortion"], 4)?;
        views.push(triangulate::View {
            name: c["name"].as_str().ok_or_else(bad)?.to_string(),
            camera: Camera {
                fx: num("fx")?,
                fy: num("fy")?,
                cx: num("cx")?,
                cy: num("cy")?,
                width: num("width")? as u32,
                height: num("height")? as u32,
                rotation,
                translation: DVec3::new(t[0], t[1], t[2]),
                near: Camera::NEAR,
            },
            distortion: Distortion {
                k1: d[0],
                k2: d[1],
                p1: d[2],
                p2: d[3],
                k3: 0.0,
            },
        });
    }
    Ok((doc, views))
}

/// One view's landmarks (x, y, visibility) and frame names.
pub(super) fn read_track(dir: &Path) -> anyhow::Result<(Track, Vec<String>)> {
    let path = dir.join("landmarks.npy");
    let bytes = std::fs::read(&path).with_context(|| format!("{}", path.display()))?;
    let a = npy::decode(&bytes, &path.display().to_string(), None)?;
    if a.shape.len() != 3 || a.shape[1] != LANDMARKS || a.shape[2] != 5 {
        bail!(
            "{}: shape {:?}, want [frames, {LANDMARKS}, 5]",
            path.display(),
            a.shape
        );
    }
    let track = a
        .data
        .chunks_exact(LANDMARKS * 5)
        .map(|f| std::array::from_fn(|l| [f[5 * l], f[5 * l + 1], f[5 * l + 3]]))
        .collect();
    let names_path = dir.join("frames.txt");
    let names = std::fs::read_to_string(&names_path)
        .with_context(|| format!("{}", names_path.display()))?
        .lines()
        .map(str::to_string)
        .collect();
    Ok((track, names))
}

/// Per view `(median px, % of height)` of `errors`.
fn figures(errors: &[f64], height: u32) -> serde_json::Value {
    let m = median_of(errors.to_vec());
    json!({
        "median_px": m,
        "median_percent_of_height": 100.0 * m / f64::from(height),
        "count": errors.len(),
    })
}

/// The fitted body's landmark errors per view (pixels), against each view's
/// observations at its time offset.
pub fn body_errors(
    views: &[triangulate::View],
    tracks: &[Track],
    offsets: &[f64],
    markers_by_frame: &[Vec<DVec3>],
    options: &Options,
) -> Vec<Vec<f64>> {
    views
        .iter()
        .zip(tracks)
        .zip(offsets)
        .map(|((view, track), d)| {
            let mut e = Vec::new();
            for (f, markers) in markers_by_frame.iter().enumerate() {
                for ((l, _), p) in MEDIAPIPE_MARKERS.iter().zip(markers) {
                    let fr = f as f64 + d;
                    let (i0, s) = (fr.floor(), fr - fr.floor());
                    if !(i0 >= 0.0) {
                        continue;
                    }
                    let i0 = i0 as usize;
                    let (Some(a), Some(b)) = (track.get(i0), track.get(i0 + usize::from(s > 0.0)))
                    else {
                        continue;
                    };
                    let (a, b) = (a[*l], b[*l]);
                    if !(a[2] >= options.min_visibility && b[2] >= options.min_visibility) {
                        continue;
                    }
                    let obs = [a[0] + s * (b[0] - a[0]), a[1] + s * (b[1] - a[1])];
                    let q = distortion::project(&view.camera, &view.distortion, *p);
                    e.push((q[0] - obs[0]).hypot(q[1] - obs[1]));
                }
            }
            e
        })
        .collect()
}

/// The fit's targets from a triangulation: each marker's landmark, confidence 1 where
/// solved.
pub fn targets(t: &Triangulation) -> fit::Targets {
    t.points
        .iter()
        .map(|row| {
            MEDIAPIPE_MARKERS
                .iter()
                .map(|(l, _)| match row[*l] {
                    Some(s) => (s.point, 1.0),
                    None => (DVec3::ZERO, 0.0),
                })
                .collect()
        })
        .collect()
}

pub fn markers() -> Vec<Marker> {
    MEDIAPIPE_MARKERS.iter().map(|(_, m)| *m).collect()
}

/// The body stage (module header); `landmark_keys` are the landmark stage's stamps.
pub fn stage(out: &Path, names: &[String], redo: bool) -> anyhow::Result<()> {
    let cameras_path = out.join("cameras.json");
    if !cameras_path.is_file() {
        bail!("the body fit needs a calibrated rig (--calibration; {} is missing): fitting one view's landmarks is not built yet", cameras_path.display());
    }
    if names.len() < 2 {
        bail!(
            "the body fit needs two views or more: fitting one view's landmarks is not built yet"
        );
    }
    // The triangulation keeps each point's views as bits of a u32.
    if names.len() > 32 {
        bail!(
            "the body fit takes at most 32 views ({} given): more is not built yet",
            names.len()
        );
    }
    let (cameras_doc, all_views) = read_cameras(out)?;
    let views: Vec<triangulate::View> = names
        .iter()
        .map(|n| {
            all_views
                .iter()
                .find(|v| &v.name == n)
                .cloned()
                .with_context(|| format!("{}: no camera {n}", cameras_path.display()))
        })
        .collect::<anyhow::Result<_>>()?;
    let landmark_stamps: Vec<serde_json::Value> = names
        .iter()
        .map(|n| read_stamp(&out.join("landmarks").join(n)).unwrap_or(serde_json::Value::Null))
        .collect();
    let options = Options::default();
    let fit_options = FitOptions::default();
    let dir = out.join("body");
    let key = json!({
        "method": METHOD,
        "cameras": cameras_doc,
        "landmarks": landmark_stamps,
        "triangulation": format!("{options:?}"),
        "fit": format!("{fit_options:?}"),
    });
    if !redo && read_stamp(&dir).is_some_and(|s| s == key) {
        progress("body: up to date (skipped)");
        return Ok(());
    }
    let t0 = Instant::now();
    let mut tracks = Vec::new();
    let mut frame_names = Vec::new();
    for n in names {
        let (track, fr) = read_track(&out.join("landmarks").join(n))?;
        tracks.push(track);
        frame_names.push(fr);
    }
    let frames = tracks[0].len();
    for (n, t) in names.iter().zip(&tracks) {
        if t.len() != frames {
            progress(&format!(
                "body: warning: {n} has {} frames against {}'s {frames}; the frames are matched by position",
                t.len(),
                names[0]
            ));
        }
    }

    let tri = triangulate::triangulate(&views, &tracks, &options);
    let t_tri = t0.elapsed().as_secs_f64();
    if tri.points.iter().flatten().all(|s| s.is_none()) {
        bail!(
            "{}: no landmark was seen in two views at once in any frame, so there is no body to fit (is the person in view of at least two cameras?)",
            out.join("landmarks").display()
        );
    }
    let tri_errors = triangulate::view_errors(&views, &tracks, &tri, &options);
    let mut all_inlier = Vec::new();
    for ((inl, _), v) in tri_errors.iter().zip(&views) {
        all_inlier.extend(inl.iter().map(|e| e / f64::from(v.camera.height)));
    }
    progress(&format!(
        "body: triangulated {frames} frames x {LANDMARKS} landmarks in {t_tri:.1} s; time offsets {:?} frames; median reprojection {:.2}% of the image height",
        tri.offsets,
        100.0 * median_of(all_inlier.clone())
    ));

    let t1 = Instant::now();
    let model = fit::with_limb_lengths(&default_body(&BodyOptions::default()));
    let body = FitBody::new(&model);
    let markers = markers();
    let fitted = fit::fit_sequence(&body, &markers, &targets(&tri), &fit_options);
    let t_fit = t1.elapsed().as_secs_f64();
    let posed = fitted.posed(&body, &markers);
    let marker_positions: Vec<Vec<DVec3>> = posed.iter().map(|(_, m)| m.clone()).collect();
    let fit_errors = body_errors(&views, &tracks, &tri.offsets, &marker_positions, &options);
    let mut all_fit = Vec::new();
    for (e, v) in fit_errors.iter().zip(&views) {
        all_fit.extend(e.iter().map(|x| x / f64::from(v.camera.height)));
    }
    progress(&format!(
        "body: fitted in {t_fit:.1} s; the body's landmarks reproject at a median {:.2}% of the image height",
        100.0 * median_of(all_fit.clone())
    ));

    let staged = drape_io::StagedDir::new(&dir).with_context(|| format!("{}", dir.display()))?;
    let mut data = Vec::with_capacity(frames * LANDMARKS * 5);
    for row in &tri.points {
        for s in row {
            match s {
                Some(s) => data.extend([
                    s.point.x,
                    s.point.y,
                    s.point.z,
                    f64::from(s.used.count_ones()),
                    f64::from(s.rejected.count_ones()),
                ]),
                None => data.extend([f64::NAN, f64::NAN, f64::NAN, 0.0, 0.0]),
            }
        }
    }
    let lm_path = staged.path().join("landmarks3d.npy");
    drape_io::write(
        &lm_path,
        npy::encode(&Array::new(Dtype::F32, vec![frames, LANDMARKS, 5], data)),
    )
    .with_context(|| format!("{}", lm_path.display()))?;
    SmplSequence {
        poses: fitted.poses.clone(),
        betas: vec![fitted.betas.clone(); frames],
        translations: fitted.translations.clone(),
        scales: vec![1.0; frames],
    }
    .write_npz(&staged.path().join("smpl_params.npz"))?;
    model.write_npz(&staged.path().join("body_model.npz"))?;
    let t_sheet = Instant::now();
    let sheet_frames: Vec<sheet::SheetFrame<'_>> = fitted
        .poses
        .iter()
        .zip(&fitted.translations)
        .map(|(pose, t)| sheet::SheetFrame {
            pose,
            translation: *t,
        })
        .collect();
    sheet::write(
        &staged.path().join("sheet.png"),
        &sheet::Sheet {
            frames_dir: &out.join("frames"),
            views: &views,
            frame_names: &frame_names,
            offsets: &tri.offsets,
            model: &model,
            betas: &fitted.betas,
            fitted: &sheet_frames,
        },
    )?;
    let t_sheet = t_sheet.elapsed().as_secs_f64();

    let per_view: Vec<serde_json::Value> = views
        .iter()
        .enumerate()
        .map(|(v, view)| {
            let h = view.camera.height;
            let detected = tracks[v]
                .iter()
                .filter(|f| f.iter().any(|l| l[0].is_finite()))
                .count();
            let rejected = tri
                .points
                .iter()
                .flatten()
                .flatten()
                .filter(|s| s.rejected & (1 << v) != 0)
                .count();
            json!({
                "name": view.name,
                "frames": tracks[v].len(),
                "detected_frames": detected,
                "detection_rate": detected as f64 / tracks[v].len().max(1) as f64,
                "time_offset_frames": tri.offsets[v],
                "rejected_observations": rejected,
                "triangulation_inliers": figures(&tri_errors[v].0, h),
                "triangulation_all": figures(&tri_errors[v].1, h),
                "fitted_body": figures(&fit_errors[v], h),
            })
        })
        .collect();
    let solved = tri.points.iter().flatten().filter(|s| s.is_some()).count();
    let report = json!({
        "frames": frames,
        "first_frame": frame_names[0].first(),
        "landmarks_solved": solved,
        "landmarks_total": frames * LANDMARKS,
        "triangulation_median_percent_of_height": 100.0 * median_of(all_inlier),
        "fitted_body_median_percent_of_height": 100.0 * median_of(all_fit),
        "views": per_view,
        "betas": fitted.betas,
        "limb_lengths": fit::LIMBS.iter().enumerate().map(|(k, (name, _))| {
            json!({"limb": name, "beta": fitted.betas[fit::LIMB_BETAS.start + k], "scale": 1.0 + 0.1 * fitted.betas[fit::LIMB_BETAS.start + k]})
        }).collect::<Vec<_>>(),
        "seconds": {"triangulation": t_tri, "fit": t_fit, "sheet": t_sheet},
        "sheet": "sheet.png",
        "rules": {
            "observation": format!("visibility >= {}, weighted by visibility", options.min_visibility),
            "rejection": format!("with 3+ views, the worst view is dropped when its error > {} x the others' median and > {}% of the image height", options.reject_ratio, 100.0 * options.reject_floor),
            "time_offsets": format!("per view but the first, -{0}..{0} frames in halves, minimising the median reprojection error", options.max_offset),
            "fitted_body": "errors over the 23 fitted landmarks (MEDIAPIPE_MARKERS) only",
        },
    });
    drape_io::write(
        staged.path().join("report.json"),
        serde_json::to_string_pretty(&report)? + "\n",
    )?;
    commit_stage(staged, &dir, &key)?;
    progress(&format!(
        "body: written to {} in {:.1} s",
        dir.display(),
        t0.elapsed().as_secs_f64()
    ));
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use drape_trainer::body::kinematics::Pose;
    use drape_trainer::body::NUM_JOINTS;
    use glam::DMat3;
    use rand::{Rng as _, SeedableRng as _};

    /// Pixel noise per axis of the synthetic observations: mediapipe's cross-view
    /// disagreement on Pose2Sim's demo, where the triangulated landmarks reproject at a
    /// median of about 1% of the image height (19 px of 1920) at 3-4 m; Gaussian noise
    /// of 10 px per axis gives a median 2D error of 11.8 px before triangulation.
    const NOISE_PX: f64 = 10.0;

    /// A walking-like sequence posed in a z-up world: the root turned from the body's
    /// y-up and yawing, legs and arms swinging, knees and elbows bending.
    fn sequence(frames: usize, rng: &mut rand::rngs::StdRng) -> (Vec<Pose>, Vec<DVec3>) {
        let turn = DMat3::from_rotation_x(std::f64::consts::FRAC_PI_2);
        let phase: f64 = rng.random_range(0.0..1.0);
        let mut poses = Vec::new();
        let mut translations = Vec::new();
        for f in 0..frames {
            let s = 0.3 * f as f64 + phase;
            let yaw = DMat3::from_rotation_y(0.4 + 0.3 * (0.1 * f as f64).sin());
            let mut p = [DVec3::ZERO; NUM_JOINTS];
            p[0] = fit::log_rotation(turn * yaw);
            p[1] = DVec3::new(0.5 * s.sin(), 0.0, 0.1);
            p[2] = DVec3::new(-0.5 * s.sin(), 0.0, -0.1);
            p[4] = DVec3::new(0.6 + 0.5 * s.cos(), 0.0, 0.0);
            p[5] = DVec3::new(0.6 - 0.5 * s.cos(), 0.0, 0.0);
            p[16] = DVec3::new(0.2 * s.sin(), 0.3, -1.1);
            p[17] = DVec3::new(-0.2 * s.sin(), -0.3, 1.1);
            p[18] = DVec3::new(0.0, -0.5 - 0.3 * s.sin(), 0.0);
            p[19] = DVec3::new(0.0, 0.5 - 0.3 * s.sin(), 0.0);
            p[3] = DVec3::new(0.1, 0.1 * s.sin(), 0.0);
            p[15] = DVec3::new(0.1, 0.2 * s.cos(), 0.0);
            poses.push(p);
            translations.push(DVec3::new(0.02 * f as f64 - 0.2, 0.1, -0.9));
        }
        (poses, translations)
    }

    /// The fit recovers a body with random limb lengths (+-15%) from its landmarks
    /// projected into four cameras with mediapipe-sized noise and triangulated: mean
    /// joint error over the 24 joints and all frames under 3 cm. (The markers' offsets
    /// are the fit's own: this tests the fit, not the mapping from mediapipe's
    /// landmarks to the body.)
    #[test]
    fn fit_recovers_a_synthetic_body_within_3_cm() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let model = fit::with_limb_lengths(&default_body(&BodyOptions {
            cell: 0.05,
            num_betas: 10,
        }));
        let body = FitBody::new(&model);
        let markers = markers();
        let mut betas = vec![0.0; 10];
        for b in &mut betas[fit::LIMB_BETAS] {
            *b = rng.random_range(-1.5..1.5);
        }
        let frames = 24;
        let (poses, translations) = sequence(frames, &mut rng);
        let truth = fit::Fit {
            betas: betas.clone(),
            poses,
            translations,
        };
        let posed = truth.posed(&body, &markers);
        let views = triangulate::test_rig();
        let tracks: Vec<Track> = views
            .iter()
            .map(|view| {
                posed
                    .iter()
                    .map(|(_, m)| {
                        let mut row = [[f64::NAN; 3]; LANDMARKS];
                        for ((l, _), p) in MEDIAPIPE_MARKERS.iter().zip(m) {
                            let [x, y] = distortion::project(&view.camera, &view.distortion, *p);
                            let mut n = [0.0; 2];
                            for k in &mut n {
                                let (a, b): (f64, f64) =
                                    (rng.random_range(1e-12..1.0), rng.random());
                                *k = NOISE_PX
                                    * (-2.0 * a.ln()).sqrt()
                                    * (std::f64::consts::TAU * b).cos();
                            }
                            row[*l] = [x + n[0], y + n[1], 0.9];
                        }
                        row
                    })
                    .collect()
            })
            .collect();
        let options = Options {
            max_offset: 0.0,
            ..Options::default()
        };
        let tri = triangulate::triangulate(&views, &tracks, &options);
        let fitted = fit::fit_sequence(&body, &markers, &targets(&tri), &FitOptions::default());
        let got = fitted.posed(&body, &markers);
        let mut sum = 0.0;
        for ((j_fit, _), (j_true, _)) in got.iter().zip(&posed) {
            for (a, b) in j_fit.iter().zip(j_true) {
                sum += (*a - *b).length();
            }
        }
        let mean = sum / (frames * NUM_JOINTS) as f64;
        eprintln!(
            "mean joint error {:.2} cm; betas true {:?} fitted {:?}",
            100.0 * mean,
            &betas[fit::LIMB_BETAS],
            &fitted.betas[fit::LIMB_BETAS]
        );
        assert!(mean < 0.03, "mean joint error {mean} m");
        // The limb lengths themselves: every bone's rest length within 1 cm. (Without
        // them the poses still place the joints near the landmarks: a fit that kept the
        // procedural body's proportions gave a mean joint error of 2.2 cm, under the
        // bound above.)
        let (rest_true, rest_fit) = (body.rest(&betas), body.rest(&fitted.betas));
        let worst = (1..NUM_JOINTS)
            .map(|j| {
                let p = drape_trainer::body::PARENTS[j] as usize;
                ((rest_true[j] - rest_true[p]).length() - (rest_fit[j] - rest_fit[p]).length())
                    .abs()
            })
            .fold(0.0, f64::max);
        eprintln!("largest bone length error {:.2} cm", 100.0 * worst);
        assert!(worst < 0.01, "largest bone length error {worst} m");
    }
}
