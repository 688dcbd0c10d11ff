//! The dataset type the trainer consumes, and the loaders that build it from the
//! NeuMan and ZJU-MoCap layouts (real sequences or `drape synth` output alike).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use glam::DVec3;

use crate::body::kinematics::Pose;
use crate::camera::Camera;
use crate::dataset::distortion::Undistorter;
use crate::dataset::error::DatasetError;
use crate::dataset::image::{read_mask, read_rgb, MaskRule};
use crate::dataset::layout::{locate, NeumanFiles, SequenceFiles, Variant, ZjuFiles};
use crate::dataset::neuman::SmplSequence;
use crate::dataset::split::{neuman_80_10_10, neuman_every_fifth, CameraSplit, Split};
use crate::dataset::zju::ZjuSmpl;

/// The body's parameters in a frame, in the convention of the layout it came from.
#[derive(Clone, Debug, PartialEq)]
pub enum BodyParams {
    /// NeuMan/HUGS: SMPL with root rotation, then `scale` and `translation`.
    Smpl {
        pose: Pose,
        betas: Vec<f64>,
        translation: DVec3,
        scale: f64,
    },
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

impl DatasetFrame {
    /// The person on a constant `background` colour (RGB, 3 floats per pixel).
    pub fn masked_rgb(&self, background: [f32; 3]) -> Vec<f32> {
        self.mask
            .iter()
            .enumerate()
            .flat_map(|(i, &m)| {
                if m {
                    [self.rgb[3 * i], self.rgb[3 * i + 1], self.rgb[3 * i + 2]]
                } else {
                    background
                }
            })
            .collect()
    }
}

/// NeuMan's split protocols.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NeumanSplit {
    /// Every 5th frame from offset 2 held out (HUGS).
    EveryFifth,
    /// The paper's 80/10/10.
    EightyTenTen,
}

fn size_mismatch(path: &Path, got: (u32, u32), want: (u32, u32), of: &str) -> DatasetError {
    DatasetError::image(
        path,
        format!("{}x{}, but its {of} is {}x{}", got.0, got.1, want.0, want.1),
    )
}

fn load_rgb(path: &Path, width: u32, height: u32) -> Result<Vec<f32>, DatasetError> {
    let img = read_rgb(path)?;
    if (img.width, img.height) != (width, height) {
        return Err(size_mismatch(
            path,
            (img.width, img.height),
            (width, height),
            "camera",
        ));
    }
    Ok(img.rgb)
}

/// Distortion is undone once, at load, with OpenCV's map (`cv2.undistort` with the
/// same K as the new camera, as the public ZJU-MoCap loaders do), because the splatter
/// and the rasterizer are pure pinholes and a per-step distortion would cost every step.
fn undistorted_rgb(undistort: &Option<Undistorter>, rgb: Vec<f32>) -> Vec<f32> {
    match undistort {
        Some(u) => u.rgb(&rgb),
        None => rgb,
    }
}

fn undistorted_mask(undistort: &Option<Undistorter>, mask: Vec<bool>) -> Vec<bool> {
    match undistort {
        Some(u) => u.mask(&mask),
        None => mask,
    }
}

/// NeuMan's Detectron2 masks mark the person black; a mask written the other way round
/// (the person white, as HUGS's SAM masks are) would train the background as the
/// person. Where the person would cover most of the frame, refuse, naming the file and
/// the two conventions.
pub fn check_not_inverted(
    variant: Variant,
    path: &Path,
    mask: &[bool],
) -> Result<(), DatasetError> {
    let person = mask.iter().filter(|&&m| m).count() as f64 / mask.len().max(1) as f64;
    if variant == Variant::Neuman && person > 0.6 {
        return Err(DatasetError::image(
            path,
            format!("{:.0}% of the frame is the person under NeuMan's rule (Detectron2: the person black); a mask with the person white belongs in 4d_humans/sam_segmentations/ (variant neuman+hugs)", 100.0 * person),
        ));
    }
    Ok(())
}

/// The union of an image's person masks.
/// `of` names what sets the size (the camera, or the image file).
fn load_masks(
    paths: &[PathBuf],
    rule: MaskRule,
    width: u32,
    height: u32,
    of: &str,
) -> Result<Vec<bool>, DatasetError> {
    let mut union = vec![false; width as usize * height as usize];
    for path in paths {
        let (w, h, m) = read_mask(path, rule)?;
        if (w, h) != (width, height) {
            return Err(size_mismatch(path, (w, h), (width, height), of));
        }
        union.iter_mut().zip(m).for_each(|(u, m)| *u |= m);
    }
    Ok(union)
}

/// Loads a located sequence of either layout, NeuMan with HUGS's split (every fifth
/// frame held out) and ZJU-MoCap with the cameras of `zju_cameras` (a camera index:
/// that one trains, the others are held out). Training and `drape inspect` both come
/// through here, so they report the same first problem.
pub fn load_located(
    files: &SequenceFiles,
    zju_cameras: impl Into<CameraSplit>,
) -> Result<Vec<DatasetFrame>, DatasetError> {
    match files {
        SequenceFiles::Neuman(n) => load_neuman_files(n, NeumanSplit::EveryFifth),
        SequenceFiles::Zju(z) => load_zju_files(z, zju_cameras),
    }
}

/// Loads a NeuMan-layout sequence (either variant, see [`crate::dataset::layout`]);
/// images in name order are frames.
pub fn load_neuman(dir: &Path, split: NeumanSplit) -> Result<Vec<DatasetFrame>, DatasetError> {
    match locate(dir)? {
        SequenceFiles::Neuman(files) => load_neuman_files(&files, split),
        SequenceFiles::Zju(z) => Err(DatasetError::layout(
            dir,
            format!("a ZJU-MoCap sequence ({}), not NeuMan", z.variant.name()),
        )),
    }
}

/// Loads a located NeuMan sequence.
pub fn load_neuman_files(
    files: &NeumanFiles,
    split: NeumanSplit,
) -> Result<Vec<DatasetFrame>, DatasetError> {
    let (dir, model) = (&files.dir, &files.model);
    let smpl = SmplSequence::read_npz(&files.smpl)?;
    if files.images.len() != smpl.len() {
        return Err(DatasetError::Field {
            file: files.smpl.display().to_string(),
            field: "global_orient".into(),
            problem: format!(
                "{} frames of SMPL parameters for {} registered images",
                smpl.len(),
                files.images.len()
            ),
        });
    }
    let splits = match split {
        NeumanSplit::EveryFifth => neuman_every_fifth(files.images.len()),
        NeumanSplit::EightyTenTen => neuman_80_10_10(files.images.len()),
    };
    let sparse = dir.join("sparse").join("images.txt");
    let rule = files.variant.mask_rule();
    // Undistortion maps, one per COLMAP camera (None for a pinhole).
    let mut undistorters: HashMap<u32, Option<Undistorter>> = HashMap::new();
    let mut out = Vec::with_capacity(files.images.len());
    for (f, (id, paths)) in files.images.iter().enumerate() {
        let img = &model.images[id];
        let cam = &model.cameras[&img.camera_id];
        let (camera, distortion) = img.camera_and_distortion(cam)?;
        let undistort = undistorters.entry(cam.id).or_insert_with(|| {
            (!distortion.is_identity()).then(|| Undistorter::new(&camera, distortion))
        });
        let qn = img.qvec.iter().map(|v| v * v).sum::<f64>().sqrt();
        let pose_problem = if img.qvec.iter().any(|v| !v.is_finite()) {
            Some(format!("QW QX QY QZ {:?} is not finite", img.qvec))
        } else if !(qn > 1e-9) {
            Some(format!("QW QX QY QZ {:?} is zero, no rotation", img.qvec))
        } else if img.tvec.iter().any(|v| !v.is_finite()) {
            Some(format!("TX TY TZ {:?} is not finite", img.tvec))
        } else {
            None
        };
        if let Some(problem) = pose_problem {
            return Err(DatasetError::Field {
                file: sparse.display().to_string(),
                field: format!("image {} ('{}')", img.id, img.name),
                problem,
            });
        }
        let rgb = undistorted_rgb(undistort, load_rgb(&paths.image, cam.width, cam.height)?);
        let mask = undistorted_mask(
            undistort,
            load_masks(
                &paths.masks,
                rule,
                cam.width,
                cam.height,
                "camera (cameras.txt)",
            )?,
        );
        check_not_inverted(files.variant, &paths.masks[0], &mask)?;
        let garment_masks = match &paths.garment_masks {
            Some((upper, lower)) => Some((
                undistorted_mask(
                    undistort,
                    load_masks(
                        std::slice::from_ref(upper),
                        MaskRule::AtLeastHalf,
                        cam.width,
                        cam.height,
                        "camera (cameras.txt)",
                    )?,
                ),
                undistorted_mask(
                    undistort,
                    load_masks(
                        std::slice::from_ref(lower),
                        MaskRule::AtLeastHalf,
                        cam.width,
                        cam.height,
                        "camera (cameras.txt)",
                    )?,
                ),
            )),
            None => None,
        };
        out.push(DatasetFrame {
            frame: f,
            view: 0,
            image_path: paths.image.clone(),
            width: cam.width,
            height: cam.height,
            rgb,
            mask,
            garment_masks,
            camera,
            body: BodyParams::Smpl {
                pose: smpl.poses[f],
                betas: smpl.betas[f].clone(),
                translation: smpl.translations[f],
                scale: smpl.scales[f],
            },
            split: splits[f],
        });
    }
    Ok(out)
}

/// Loads a ZJU-MoCap-layout sequence (any variant, see [`crate::dataset::layout`]);
/// `cameras`: which train and which are held out (a camera index: that one trains).
pub fn load_zju(
    dir: &Path,
    cameras: impl Into<CameraSplit>,
) -> Result<Vec<DatasetFrame>, DatasetError> {
    match locate(dir)? {
        SequenceFiles::Zju(files) => load_zju_files(&files, cameras),
        SequenceFiles::Neuman(n) => Err(DatasetError::layout(
            dir,
            format!("a NeuMan sequence ({}), not ZJU-MoCap", n.variant.name()),
        )),
    }
}

/// Loads a located ZJU-MoCap sequence.
pub fn load_zju_files(
    files: &ZjuFiles,
    cameras: impl Into<CameraSplit>,
) -> Result<Vec<DatasetFrame>, DatasetError> {
    let annots = &files.annots;
    let splits = cameras
        .into()
        .splits(annots.cameras.len())
        .map_err(|problem| DatasetError::Field {
            file: files.dir.join("annots.npy").display().to_string(),
            field: "cams".into(),
            problem: format!(
                "the training and held-out cameras (zju_train_camera, zju_train_cameras, zju_test_cameras): {problem}"
            ),
        })?;
    let rule = files.variant.mask_rule();
    // Undistortion maps per camera and image size (None for a pinhole).
    let mut undistorters: HashMap<(usize, u32, u32), Option<Undistorter>> = HashMap::new();
    let mut out = Vec::new();
    for (params, views) in &files.frames {
        let body = ZjuSmpl::read_file(params)?;
        for paths in views {
            let Some(split) = splits[paths.view] else {
                continue;
            };
            let cam = &annots.cameras[paths.view];
            let img = read_rgb(&paths.image)?;
            let (w, h) = (img.width, img.height);
            let camera = cam.camera(w, h);
            let undistort = undistorters.entry((paths.view, w, h)).or_insert_with(|| {
                (!cam.distortion().is_identity())
                    .then(|| Undistorter::new(&camera, cam.distortion()))
            });
            out.push(DatasetFrame {
                frame: paths.frame,
                view: paths.view,
                rgb: undistorted_rgb(undistort, img.rgb),
                mask: undistorted_mask(
                    undistort,
                    load_masks(
                        &paths.masks,
                        rule,
                        w,
                        h,
                        &format!("image {}", paths.image.display()),
                    )?,
                ),
                image_path: paths.image.clone(),
                width: w,
                height: h,
                garment_masks: None,
                camera,
                body: BodyParams::Zju(body.clone()),
                split,
            });
        }
    }
    Ok(out)
}
