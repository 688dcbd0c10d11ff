//! The dataset type the trainer consumes, and the loaders that build it from the
//! NeuMan and ZJU-MoCap layouts (real sequences or `drape synth` output alike).

use std::path::{Path, PathBuf};

use crate::body::kinematics::Pose;
use crate::camera::Camera;
use crate::dataset::colmap::ColmapModel;
use crate::dataset::image::{read, read_mask};
use crate::dataset::neuman::SmplSequence;
use crate::dataset::split::{neuman_80_10_10, neuman_every_fifth, zju_by_camera, Split};
use crate::dataset::zju::{mask_path, ZjuAnnots, ZjuSmpl};
use crate::mesh::V3;

/// The body's parameters in a frame, in the convention of the layout it came from.
#[derive(Clone, Debug, PartialEq)]
pub enum BodyParams {
    /// NeuMan/HUGS: SMPL with root rotation, then `scale` and `translation`.
    Smpl { pose: Pose, betas: Vec<f64>, translation: V3, scale: f64 },
    /// ZJU-MoCap: root-free SMPL, then `R(Rh)` and `Th`.
    Zju(ZjuSmpl),
}

/// One image of a sequence with everything the trainer needs.
#[derive(Clone, Debug)]
pub struct DatasetFrame {
    pub frame: usize,
    /// Camera index (0 for a monocular sequence).
    pub view: usize,
    pub image_path: PathBuf,
    pub width: u32,
    pub height: u32,
    /// RGB in [0, 1].
    pub rgb: Vec<f32>,
    /// The person.
    pub mask: Vec<bool>,
    /// Upper and lower garment masks when the sequence has them (synthetic data).
    pub garment_masks: Option<(Vec<bool>, Vec<bool>)>,
    pub camera: Camera,
    pub body: BodyParams,
    pub split: Split,
}

/// NeuMan's split protocols.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NeumanSplit {
    /// Every 5th frame from offset 2 held out (HUGS).
    EveryFifth,
    /// The paper's 80/10/10.
    EightyTenTen,
}

fn load_rgb(path: &Path, width: u32, height: u32) -> Result<Vec<f32>, String> {
    let (w, h, c, bytes) = read(path)?;
    if (w, h) != (width, height) {
        return Err(format!("{}: {w}x{h}, but its camera is {width}x{height}", path.display()));
    }
    Ok(bytes.chunks_exact(c).flat_map(|p| if c >= 3 { [p[0], p[1], p[2]] } else { [p[0]; 3] }).map(|v| f32::from(v) / 255.0).collect())
}

fn load_mask(path: &Path, width: u32, height: u32) -> Result<Vec<bool>, String> {
    let (w, h, m) = read_mask(path)?;
    if (w, h) != (width, height) {
        return Err(format!("{}: {w}x{h}, but its image is {width}x{height}", path.display()));
    }
    Ok(m)
}

/// Loads a NeuMan-layout sequence: `images/`, `segmentations/`, `sparse/` and
/// `4d_humans/smpl_optimized_aligned_scale.npz` (images in name order are frames).
pub fn load_neuman(dir: &Path, split: NeumanSplit) -> Result<Vec<DatasetFrame>, String> {
    let model = ColmapModel::read_text(&dir.join("sparse")).map_err(|e| e.to_string())?;
    let smpl_path = dir.join("4d_humans").join("smpl_optimized_aligned_scale.npz");
    let smpl = SmplSequence::read_npz(&smpl_path).map_err(|e| e.to_string())?;
    let mut images: Vec<_> = model.images.values().collect();
    images.sort_by(|a, b| a.name.cmp(&b.name));
    if images.len() != smpl.len() {
        return Err(format!("{}: {} frames of SMPL parameters for {} registered images", smpl_path.display(), smpl.len(), images.len()));
    }
    let splits = match split {
        NeumanSplit::EveryFifth => neuman_every_fifth(images.len()),
        NeumanSplit::EightyTenTen => neuman_80_10_10(images.len()),
    };
    let sparse = dir.join("sparse").join("images.txt");
    let mut out = Vec::with_capacity(images.len());
    for (f, img) in images.iter().enumerate() {
        let cam = &model.cameras[&img.camera_id];
        let camera = img.camera(cam).ok_or_else(|| format!("{}: camera {} has model {}, which is not a pinhole model", dir.join("sparse/cameras.txt").display(), cam.id, cam.model))?;
        let qn = img.qvec.iter().map(|v| v * v).sum::<f64>().sqrt();
        if !(qn > 1e-9) || img.qvec.iter().chain(&img.tvec).any(|v| !v.is_finite()) {
            return Err(format!("{}: image {} ('{}') has a singular rotation (qvec {:?})", sparse.display(), img.id, img.name, img.qvec));
        }
        let image_path = dir.join("images").join(&img.name);
        let rgb = load_rgb(&image_path, cam.width, cam.height)?;
        let mask = load_mask(&dir.join("segmentations").join(&img.name), cam.width, cam.height)?;
        let upper = dir.join("masks_upper").join(&img.name);
        let garment_masks = if upper.exists() {
            Some((load_mask(&upper, cam.width, cam.height)?, load_mask(&dir.join("masks_lower").join(&img.name), cam.width, cam.height)?))
        } else {
            None
        };
        out.push(DatasetFrame {
            frame: f,
            view: 0,
            image_path,
            width: cam.width,
            height: cam.height,
            rgb,
            mask,
            garment_masks,
            camera,
            body: BodyParams::Smpl { pose: smpl.poses[f], betas: smpl.betas[f].clone(), translation: smpl.translations[f], scale: smpl.scales[f] },
            split: splits[f],
        });
    }
    Ok(out)
}

/// Loads a ZJU-MoCap-layout sequence: `annots.npy`, images and masks per camera,
/// `smpl_params/` (or `params/`); `train_camera` is the training view.
pub fn load_zju(dir: &Path, train_camera: usize) -> Result<Vec<DatasetFrame>, String> {
    let annots = ZjuAnnots::read(dir)?;
    let splits = zju_by_camera(annots.cameras.len(), train_camera);
    let mut out = Vec::new();
    for (f, paths) in annots.images.iter().enumerate() {
        if paths.len() != annots.cameras.len() {
            return Err(format!("{}: ims[{f}] lists {} images for {} cameras", dir.join("annots.npy").display(), paths.len(), annots.cameras.len()));
        }
        let body = ZjuSmpl::read(dir, f)?;
        for (c, rel) in paths.iter().enumerate() {
            let cam = &annots.cameras[c];
            let image_path = dir.join(rel);
            let (w, h, _, _) = read(&image_path)?;
            let camera = cam.camera(w, h);
            out.push(DatasetFrame {
                frame: f,
                view: c,
                rgb: load_rgb(&image_path, w, h)?,
                mask: load_mask(&dir.join(mask_path(rel)), w, h)?,
                image_path,
                width: w,
                height: h,
                garment_masks: None,
                camera,
                body: BodyParams::Zju(body.clone()),
                split: splits[c],
            });
        }
    }
    Ok(out)
}
