//! Rewrites `drape synth`'s sequences into each published layout variant (see
//! [`crate::dataset::layout`]): the fixtures the loader tests and `drape inspect`'s
//! tests read, made from data whose truth is known. Files are copied byte for byte;
//! only their names, folders and `annots.npy`'s paths change.

use std::path::Path;

use crate::dataset::error::DatasetError;
use crate::dataset::layout::Variant;
use crate::dataset::zju::{mask_path, ZjuAnnots};

fn copy(from: &Path, to: &Path) -> Result<(), DatasetError> {
    if let Some(dir) = to.parent() {
        std::fs::create_dir_all(dir).map_err(|e| DatasetError::io(dir, e))?;
    }
    std::fs::copy(from, to)
        .map(|_| ())
        .map_err(|e| DatasetError::io(from, e))
}

fn copy_tree(from: &Path, to: &Path) -> Result<(), DatasetError> {
    std::fs::create_dir_all(to).map_err(|e| DatasetError::io(to, e))?;
    for entry in std::fs::read_dir(from).map_err(|e| DatasetError::io(from, e))? {
        let entry = entry.map_err(|e| DatasetError::io(from, e))?;
        let (src, dst) = (entry.path(), to.join(entry.file_name()));
        if src.is_dir() {
            copy_tree(&src, &dst)?;
        } else {
            copy(&src, &dst)?;
        }
    }
    Ok(())
}

/// Writes `drape synth`'s NeuMan sequence `src` (its `neuman/`) into `dst` as `variant`
/// (`Neuman`: without HUGS's SAM masks, so Detectron2's `segmentations/` are read;
/// `NeumanHugs`: as generated).
pub fn write_neuman_variant(src: &Path, dst: &Path, variant: Variant) -> Result<(), DatasetError> {
    copy_tree(src, dst)?;
    match variant {
        Variant::NeumanHugs => Ok(()),
        Variant::Neuman => {
            let sam = dst.join("4d_humans").join("sam_segmentations");
            std::fs::remove_dir_all(&sam).map_err(|e| DatasetError::io(&sam, e))
        }
        other => Err(DatasetError::layout(
            dst,
            format!("{} is not a NeuMan variant", other.name()),
        )),
    }
}

/// Writes `drape synth`'s ZJU-MoCap sequence `src` (its `zju/`) into `dst` as `variant`:
/// - `ZjuRefined`: `images/NN/NNNNNN.jpg` (two-digit camera folders as `my_377`),
///   `mask/NN/`, `smpl_params/`, `smpl_vertices/` (GauHuman's name);
/// - `ZjuNeuralBody`: `Camera_B<c>/NNNNNN.jpg` at the root, both `mask/` and
///   `mask_cihp/`, `new_params/` and `new_vertices/`;
/// - `ZjuCoreView313`: `Camera (<c>)/CoreView_313_Camera_(<c>)_<f+1:04>_<date>.jpg`,
///   masks only in `mask_cihp/`, 1-based `params/` and `vertices/`.
pub fn write_zju_variant(src: &Path, dst: &Path, variant: Variant) -> Result<(), DatasetError> {
    let annots = ZjuAnnots::read(src)?;
    let (params_dir, vertices_dir, first) = match variant {
        Variant::ZjuRefined => ("smpl_params", "smpl_vertices", 0),
        Variant::ZjuNeuralBody => ("new_params", "new_vertices", 0),
        Variant::ZjuCoreView313 => ("params", "vertices", 1),
        other => {
            return Err(DatasetError::layout(
                dst,
                format!("{} is not a ZJU-MoCap variant", other.name()),
            ))
        }
    };
    let mut images = Vec::with_capacity(annots.images.len());
    for (f, paths) in annots.images.iter().enumerate() {
        let number = f + first;
        let mut renamed = Vec::with_capacity(paths.len());
        for (c, rel) in paths.iter().enumerate() {
            let ext = rel.rsplit_once('.').map_or("jpg", |(_, e)| e);
            let new = match variant {
                Variant::ZjuRefined => format!("images/{c:02}/{number:06}.{ext}"),
                Variant::ZjuNeuralBody => format!("Camera_B{}/{number:06}.{ext}", c + 1),
                _ => format!("Camera ({c1})/CoreView_313_Camera_({c1})_{number:04}_2019-08-23_16-08-50.592.{ext}", c1 = c + 1),
            };
            copy(&src.join(rel), &dst.join(&new))?;
            let mask = src.join(mask_path(rel));
            let stem = new.rsplit_once('.').map_or(new.as_str(), |(s, _)| s);
            match variant {
                Variant::ZjuRefined => copy(&mask, &dst.join(mask_path(&new)))?,
                Variant::ZjuNeuralBody => {
                    copy(&mask, &dst.join(format!("mask/{stem}.png")))?;
                    copy(&mask, &dst.join(format!("mask_cihp/{stem}.png")))?;
                }
                _ => copy(&mask, &dst.join(format!("mask_cihp/{stem}.png")))?,
            }
            renamed.push(new);
        }
        images.push(renamed);
        copy(
            &src.join("smpl_params").join(format!("{f}.npy")),
            &dst.join(params_dir).join(format!("{number}.npy")),
        )?;
        copy(
            &src.join("vertices").join(format!("{f}.npy")),
            &dst.join(vertices_dir).join(format!("{number}.npy")),
        )?;
    }
    ZjuAnnots {
        cameras: annots.cameras,
        images,
    }
    .write(dst)?;
    Ok(())
}

/// Writes `drape synth`'s ZJU-MoCap sequence `src` into `dst` as if seen through a lens
/// with `distortion` (OpenCV's k1 k2 p1 p2 k3): every image and mask is distorted from
/// the pinhole render, and `annots.npy` carries the coefficients as the release does.
/// Loading it must give back the pinhole frames (up to resampling and JPEG).
pub fn write_zju_distorted(
    src: &Path,
    dst: &Path,
    distortion: &[f64; 5],
) -> Result<(), DatasetError> {
    use crate::dataset::distortion::{distort_mask, distort_rgb, Distortion};
    use crate::dataset::image::{read_mask, read_rgb, write_mask, write_rgb, MaskRule};
    let mut annots = ZjuAnnots::read(src)?;
    let d = Distortion::from_opencv(distortion);
    for (f, paths) in annots.images.iter().enumerate() {
        for (c, rel) in paths.iter().enumerate() {
            let img = read_rgb(&src.join(rel))?;
            let camera = annots.cameras[c].camera(img.width, img.height);
            write_rgb(
                &dst.join(rel),
                img.width,
                img.height,
                &distort_rgb(&camera, d, &img.rgb),
            )?;
            let (w, h, mask) = read_mask(&src.join(mask_path(rel)), MaskRule::NonZero)?;
            write_mask(
                &dst.join(mask_path(rel)),
                w,
                h,
                &distort_mask(&camera, d, &mask),
            )?;
        }
        copy(
            &src.join("smpl_params").join(format!("{f}.npy")),
            &dst.join("smpl_params").join(format!("{f}.npy")),
        )?;
        copy(
            &src.join("vertices").join(format!("{f}.npy")),
            &dst.join("vertices").join(format!("{f}.npy")),
        )?;
    }
    for cam in &mut annots.cameras {
        cam.d = *distortion;
    }
    annots.write(dst)
}
