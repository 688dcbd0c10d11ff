//! The sequence stage: the frames, masks, cameras and fitted body written as one
//! ZJU-MoCap sequence in the refined layout (`zju-refined`, as GauHuman, GART and
//! instant-nvr read it), `DIR/sequence/`, which `drape inspect DIR` and `drape train
//! --data DIR` read (`dataset::layout::sequence_root`):
//!
//! - `annots.npy`: `cams` (K in OpenCV's pixel convention, D = k1 k2 p1 p2 0, R, T in
//!   millimetres) from `cameras.json`, and per frame `ims`: `images/<camera>/<name>`.
//! - `images/<camera>/<name>.png`: the frames stage's images (hard links where the file
//!   system allows, else copies), not undistorted (the loader undoes D, as it does for
//!   ZJU-MoCap's own images).
//! - `mask/<camera>/<name>.png`: mediapipe's person mask at one half, 0 or 255 (the
//!   layout's rule takes any non-zero pixel as the person; mediapipe's soft edge would
//!   otherwise grow it).
//! - `smpl_params/<n>.npy`: the fitted body per frame in ZJU's convention (`poses` with
//!   a zero root, `Rh` the root's turn, `Th` so that the pelvis, which SMPL turns about,
//!   stays where the fit put it; `shapes` the fitted betas), `n` the first camera's
//!   frame name.
//! - `body_model.npz`: the body those betas shape (limb lengths in betas 2..9), which
//!   `drape train` uses when no `--body` is given.
//!
//! Sizes: the trainer takes one image size. Views whose frames differ (Pose2Sim's cam03
//! and cam04 are 1088 wide where cam01 and cam02 are 1080, so 146 against 144 at
//! `--height 256`) are
//! cropped about their centre to the smallest width and height, and their principal
//! point moves with the crop (a warning where more than 2% of a side goes).
//!
//! Time offsets: the body stage found each view's offset against the first (Pose2Sim's
//! cam03: 5 frames); a body frame `f` is paired with view `v`'s frame `f + offset_v`
//! (rounded half up), and a frame that some view does not have is left out.

use std::path::Path;

use anyhow::{bail, Context as _};
use drape_trainer::body::kinematics::{regress_joints, shaped_vertices};
use drape_trainer::body::SmplModel;
use drape_trainer::camera::Camera;
use drape_trainer::dataset::image::{read_mask, read_rgb, write_mask, write_rgb, MaskRule};
use drape_trainer::dataset::neuman::SmplSequence;
use drape_trainer::dataset::synth::to_zju;
use drape_trainer::dataset::zju::{ZjuAnnots, ZjuCamera};
use serde_json::json;

use super::body::{read_cameras, read_track};
use super::{commit_stage, progress, read_stamp};

/// Bumped when the stage's method changes, so that a rerun redoes it.
const METHOD: &str =
    "sequence v3: zju-refined, masks at one half, offsets rounded half up, one size";

/// Each view's time offset in frames, from the body stage's `report.json`.
fn time_offsets(out: &Path, names: &[String]) -> anyhow::Result<Vec<f64>> {
    let path = out.join("body").join("report.json");
    let text = std::fs::read_to_string(&path).with_context(|| format!("{}", path.display()))?;
    let doc: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}", path.display()))?;
    names
        .iter()
        .map(|n| {
            doc["views"]
                .as_array()
                .and_then(|vs| vs.iter().find(|v| v["name"].as_str() == Some(n)))
                .and_then(|v| v["time_offset_frames"].as_f64())
                .with_context(|| format!("{}: no time offset for view {n}", path.display()))
        })
        .collect()
}

/// Which frame of each view shows body frame `f`, or None where one view has none.
pub(super) fn paired_frames(
    body_frames: usize,
    offsets: &[f64],
    view_frames: &[usize],
) -> Vec<Option<Vec<usize>>> {
    (0..body_frames)
        .map(|f| {
            offsets
                .iter()
                .zip(view_frames)
                .map(|(d, &n)| {
                    // Half up, the same way for every frame.
                    let i = (f as f64 + d + 0.5).floor();
                    (i >= 0.0 && (i as usize) < n).then_some(i as usize)
                })
                .collect()
        })
        .collect()
}

/// A file of the frames stage in the sequence: a hard link, else a copy.
fn link_or_copy(from: &Path, to: &Path) -> anyhow::Result<()> {
    if std::fs::hard_link(from, to).is_err() {
        std::fs::copy(from, to)
            .with_context(|| format!("copying {} to {}", from.display(), to.display()))?;
    }
    Ok(())
}

/// The sequence stage (module header).
pub fn stage(out: &Path, names: &[String], redo: bool) -> anyhow::Result<()> {
    let dir = out.join("sequence");
    let body_dir = out.join("body");
    let stamp_of = |d: &Path| read_stamp(d).unwrap_or(serde_json::Value::Null);
    let key = json!({
        "method": METHOD,
        "body": stamp_of(&body_dir),
        "frames": names.iter().map(|n| stamp_of(&out.join("frames").join(n))).collect::<Vec<_>>(),
        "landmarks": names.iter().map(|n| stamp_of(&out.join("landmarks").join(n))).collect::<Vec<_>>(),
    });
    if !redo && read_stamp(&dir).is_some_and(|s| s == key) {
        progress("sequence: up to date (skipped)");
        return Ok(());
    }
    let t0 = std::time::Instant::now();
    let (cameras_doc, all_views) = read_cameras(out)?;
    let params_path = body_dir.join("smpl_params.npz");
    let fitted = SmplSequence::read_npz(&params_path)
        .with_context(|| format!("{}", params_path.display()))?;
    let model_path = body_dir.join("body_model.npz");
    let model =
        SmplModel::load_npz(&model_path).with_context(|| format!("{}", model_path.display()))?;
    let offsets = time_offsets(out, names)?;
    let mut cameras = Vec::new();
    let mut frame_names = Vec::new();
    for n in names {
        let i = all_views
            .iter()
            .position(|v| &v.name == n)
            .with_context(|| format!("{}: no camera {n}", out.join("cameras.json").display()))?;
        let d = &cameras_doc["cameras"][i]["distortion"];
        let k: Vec<f64> = (0..4).map(|j| d[j].as_f64().unwrap_or(0.0)).collect();
        cameras.push(([k[0], k[1], k[2], k[3]], all_views[i].camera));
        frame_names.push(read_track(&out.join("landmarks").join(n))?.1);
    }
    let counts: Vec<usize> = frame_names.iter().map(Vec::len).collect();
    let size = (
        cameras.iter().map(|c| c.1.width).min().unwrap_or(0),
        cameras.iter().map(|c| c.1.height).min().unwrap_or(0),
    );
    let crops: Vec<Crop> = cameras
        .iter()
        .map(|(_, c)| Crop {
            x: (c.width - size.0) / 2,
            y: (c.height - size.1) / 2,
            width: size.0,
            height: size.1,
            from: (c.width, c.height),
        })
        .collect();
    for (n, crop) in names.iter().zip(&crops) {
        let (w, h) = crop.from;
        if crop.is_some() {
            progress(&format!(
                "sequence: {n}'s {w}x{h} frames cropped about their centre to {}x{} (the trainer takes one size)",
                size.0, size.1
            ));
            if f64::from(w - size.0) > 0.02 * f64::from(w)
                || f64::from(h - size.1) > 0.02 * f64::from(h)
            {
                progress(&format!(
                    "sequence: warning: the crop takes more than 2% of {n}'s frames"
                ));
            }
        }
    }
    let cameras: Vec<ZjuCamera> = cameras
        .iter()
        .zip(&crops)
        .map(|((d, c), crop)| {
            let mut c = *c;
            c.cx -= f64::from(crop.x);
            c.cy -= f64::from(crop.y);
            c.width = crop.width;
            c.height = crop.height;
            zju_camera(&c, *d)
        })
        .collect();
    let pairs = paired_frames(fitted.len(), &offsets, &counts);

    let staged = drape_io::StagedDir::new(&dir).with_context(|| format!("{}", dir.display()))?;
    let root = staged.path();
    for n in names {
        for sub in ["images", "mask"] {
            let d = root.join(sub).join(n);
            std::fs::create_dir_all(&d).with_context(|| format!("{}", d.display()))?;
        }
    }
    let mut images = Vec::new();
    let mut dropped = 0usize;
    let mut mask_pixels = vec![0usize; names.len()];
    for (f, pair) in pairs.iter().enumerate() {
        let Some(pair) = pair else {
            dropped += 1;
            continue;
        };
        let mut row = Vec::with_capacity(names.len());
        for (v, (&i, n)) in pair.iter().zip(names).enumerate() {
            let name = &frame_names[v][i];
            let rel = format!("images/{n}/{name}");
            let crop = &crops[v];
            let frame = out.join("frames").join(n).join(name);
            if crop.is_some() {
                let img = read_rgb(&frame)?;
                crop.check(&frame, (img.width, img.height))?;
                write_rgb(
                    &root.join(&rel),
                    crop.width,
                    crop.height,
                    &crop.apply(&img.rgb, 3),
                )?;
            } else {
                link_or_copy(&frame, &root.join(&rel))?;
            }
            let stem = name.rsplit_once('.').map_or(name.as_str(), |(s, _)| s);
            let soft = out
                .join("landmarks")
                .join(n)
                .join("masks")
                .join(format!("{stem}.png"));
            let (w, h, mask) = read_mask(&soft, MaskRule::AtLeastHalf)?;
            crop.check(&soft, (w, h))?;
            let mask = crop.apply(&mask, 1);
            mask_pixels[v] += mask.iter().filter(|&&m| m).count();
            write_mask(
                &root.join(format!("mask/{n}/{stem}.png")),
                crop.width,
                crop.height,
                &mask,
            )?;
            row.push(rel);
        }
        let number: usize = {
            let first = &frame_names[0][pair[0]];
            let stem = first.rsplit_once('.').map_or(first.as_str(), |(s, _)| s);
            stem.parse().with_context(|| {
                format!(
                    "{}: frame name {first} is not a number",
                    out.join("frames").display()
                )
            })?
        };
        let betas = &fitted.betas[f];
        let pelvis = regress_joints(&model, &shaped_vertices(&model, betas))[0];
        let mut zju = to_zju(
            &fitted.poses[f],
            fitted.translations[f] / fitted.scales[f],
            pelvis,
        );
        for (s, b) in zju.shapes.iter_mut().zip(betas) {
            *s = *b;
        }
        if (fitted.scales[f] - 1.0).abs() > 1e-12 {
            bail!(
                "{}: frame {f} has scale {} (the fit writes 1; ZJU-MoCap has no scale)",
                params_path.display(),
                fitted.scales[f]
            );
        }
        zju.write(root, number)?;
        images.push(row);
    }
    if images.is_empty() {
        bail!(
            "{}: no frame is seen by every view at the time offsets {offsets:?}",
            body_dir.display()
        );
    }
    model.write_npz(&root.join("body_model.npz"))?;
    // Last: annots.npy is what makes the directory a sequence.
    ZjuAnnots {
        cameras,
        images: images.clone(),
    }
    .write(root)?;
    commit_stage(staged, &dir, &key)?;
    progress(&format!(
        "sequence: {} frames x {} cameras (zju-refined) to {} in {:.1} s{}",
        images.len(),
        names.len(),
        dir.display(),
        t0.elapsed().as_secs_f64(),
        if dropped > 0 {
            format!("; {dropped} frames left out, not in every view at its time offset")
        } else {
            String::new()
        }
    ));
    for (n, px) in names.iter().zip(&mask_pixels) {
        if *px == 0 {
            progress(&format!(
                "sequence: warning: {n}'s masks are empty in every frame"
            ));
        }
    }
    Ok(())
}

/// A view's frames cut to the sequence's one size, about their centre.
struct Crop {
    x: u32,
    y: u32,
    width: u32,
    height: u32,
    /// The frames' size before.
    from: (u32, u32),
}

impl Crop {
    fn is_some(&self) -> bool {
        self.from != (self.width, self.height)
    }

    /// A frame must have the size `cameras.json` gives its view.
    fn check(&self, path: &Path, size: (u32, u32)) -> anyhow::Result<()> {
        if size != self.from {
            bail!(
                "{}: {}x{}, but cameras.json gives its view {}x{} (rerun with --redo frames)",
                path.display(),
                size.0,
                size.1,
                self.from.0,
                self.from.1
            );
        }
        Ok(())
    }

    /// The cropped pixels of a row-major image of `channels` values a pixel.
    fn apply<T: Copy>(&self, pixels: &[T], channels: usize) -> Vec<T> {
        let row = self.from.0 as usize * channels;
        (self.y..self.y + self.height)
            .flat_map(|y| {
                let start = y as usize * row + self.x as usize * channels;
                pixels[start..start + self.width as usize * channels]
                    .iter()
                    .copied()
            })
            .collect()
    }
}

/// `annots.npy`'s record of a camera of `cameras.json` (drape's pixel convention, the
/// distortion k1 k2 p1 p2).
fn zju_camera(camera: &Camera, distortion: [f64; 4]) -> ZjuCamera {
    let mut c = ZjuCamera::from_camera(camera);
    c.d = [
        distortion[0],
        distortion[1],
        distortion[2],
        distortion[3],
        0.0,
    ];
    c
}

#[cfg(test)]
mod tests {
    use super::*;
    use drape_trainer::body::kinematics::pose_body;
    use drape_trainer::body::procedural::{default_body, BodyOptions};
    use drape_trainer::dataset::synth::posed_from_zju;
    use glam::DVec3;

    /// A body frame pairs with each view's frame at its offset, and a frame some view
    /// lacks is left out.
    #[test]
    fn frames_pair_at_the_time_offsets() {
        let pairs = paired_frames(4, &[0.0, 2.0, -0.5], &[4, 5, 4]);
        // View 2 at -0.5 rounds half up: frame 0 -> 0, 1 -> 1.
        assert_eq!(pairs[0], Some(vec![0, 2, 0]));
        assert_eq!(pairs[1], Some(vec![1, 3, 1]));
        assert_eq!(pairs[2], Some(vec![2, 4, 2]));
        // View 1 has 5 frames: 3 + 2 = 5 is past its end.
        assert_eq!(pairs[3], None);
    }

    /// ZJU's parameters pose the same vertices as the fit's (root about the shaped
    /// pelvis, then the translation), with limb betas that move the pelvis.
    #[test]
    fn zju_parameters_pose_the_fitted_body() {
        let model =
            drape_trainer::body::fit::with_limb_lengths(&default_body(&BodyOptions::default()));
        let betas = vec![0.3, -0.2, 0.8, -0.5, 0.4, 0.0, 0.2, -0.3, 0.6, 0.1];
        let mut pose = [DVec3::ZERO; 24];
        pose[0] = DVec3::new(1.2, -0.4, 0.3);
        pose[1] = DVec3::new(0.3, 0.1, 0.0);
        pose[18] = DVec3::new(0.0, 0.0, -0.7);
        let translation = DVec3::new(0.4, -1.1, 2.0);
        let want = pose_body(&model, &betas, &pose, translation).vertices;
        let pelvis = regress_joints(&model, &shaped_vertices(&model, &betas))[0];
        let mut zju = to_zju(&pose, translation, pelvis);
        zju.shapes.copy_from_slice(&betas);
        let got = posed_from_zju(&model, &zju);
        let worst = want
            .iter()
            .zip(&got)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max);
        // Two orders of the same rigid transform in f64: rounding only.
        assert!(worst < 1e-9, "{worst} m");
    }
}
