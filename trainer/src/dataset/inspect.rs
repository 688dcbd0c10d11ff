//! `drape inspect DIR`: what a sequence directory is before anything trains on it:
//! the layout and variant, frame and camera counts, the image size, which masks and
//! parameters were found, the split training would use, and the first problem found.
//!
//! The problem is what the loader training uses reports (one code path): every camera,
//! parameter file, image and mask is read and checked as `drape train` reads them, so
//! inspecting a real capture takes as long as loading it for training.

use std::path::{Path, PathBuf};

use crate::dataset::image::dimensions;
use crate::dataset::layout::{detect, locate, sequence_root, SequenceFiles, Variant};

/// What `inspect` found.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Inspection {
    pub dir: PathBuf,
    /// `None` when the directory is no layout we know (then `problem` says why).
    pub variant: Option<&'static str>,
    pub description: Option<&'static str>,
    pub frames: usize,
    pub cameras: usize,
    pub image_size: Option<(u32, u32)>,
    /// Where the person masks come from, and the rule that reads them.
    pub masks: String,
    /// Where the body parameters come from.
    pub params: String,
    /// The split training would use.
    pub split: String,
    /// Folders of the layout that exist and that drape does not read.
    pub unused: Vec<String>,
    /// The first problem found, in one line.
    pub problem: Option<String>,
}

fn rel(dir: &Path, p: &Path) -> String {
    p.strip_prefix(dir).unwrap_or(p).display().to_string()
}

fn parent_folder(dir: &Path, p: &Path) -> String {
    let r = rel(dir, p);
    r.split('/').next().map(|s| format!("{s}/")).unwrap_or(r)
}

/// Inspects `dir` (a `drape synth` or `drape prepare` output through the sequence in it
/// that `drape train` would read: [`sequence_root`]).
pub fn inspect(dir: &Path) -> Inspection {
    let dir = sequence_root(dir);
    let mut out = Inspection {
        dir: dir.clone(),
        variant: None,
        description: None,
        frames: 0,
        cameras: 0,
        image_size: None,
        masks: "-".into(),
        params: "-".into(),
        split: "-".into(),
        unused: vec![],
        problem: None,
    };
    let variant = match detect(&dir) {
        Ok(v) => v,
        Err(e) => {
            out.problem = Some(if dir.exists() {
                e.to_string()
            } else {
                format!("{}: no such directory", dir.display())
            });
            return out;
        }
    };
    out.variant = Some(variant.name());
    out.description = Some(variant.describe());
    out.masks = format!(
        "{} ({})",
        match variant {
            Variant::Neuman => "segmentations/",
            Variant::NeumanHugs => "4d_humans/sam_segmentations/",
            _ => "mask/ and/or mask_cihp/ beside each image",
        },
        variant.mask_rule().name()
    );
    let files = match locate(&dir) {
        Ok(f) => f,
        Err(e) => {
            out.problem = Some(e.to_string());
            return out;
        }
    };
    let images = files.images();
    // The loader itself, as training runs it (camera 0 training), so that inspect and
    // `drape train` report the same first problem.
    out.problem = crate::dataset::loader::load_located(&files, 0)
        .err()
        .map(|e| e.to_string());
    match &files {
        SequenceFiles::Neuman(n) => {
            out.frames = n.images.len();
            out.cameras = 1;
            out.params = format!("{} (HUGS's SMPL fit)", rel(&dir, &n.smpl));
            let test = crate::dataset::split::neuman_every_fifth(n.images.len())
                .iter()
                .filter(|s| **s == crate::dataset::split::Split::Test)
                .count();
            out.split = format!(
                "every fifth frame from the third held out (HUGS): {} train, {test} test",
                n.images.len() - test
            );
            out.unused = n.unused.clone();
            if n.images
                .first()
                .is_some_and(|(_, f)| f.garment_masks.is_some())
            {
                out.masks
                    .push_str("; garment masks in masks_upper/ and masks_lower/");
            }
        }
        SequenceFiles::Zju(z) => {
            out.frames = z.frames.len();
            out.cameras = z.annots.cameras.len();
            if let Some((p, _)) = z.frames.first() {
                out.params = format!(
                    "{}{}",
                    parent_folder(&dir, p),
                    if variant == Variant::ZjuCoreView313 {
                        " (1-based, from the frame number in each image's name)"
                    } else {
                        " (numbered by each image's name)"
                    }
                );
            }
            let folders: std::collections::BTreeSet<String> = images
                .iter()
                .flat_map(|f| f.masks.iter().map(|m| parent_folder(&dir, m)))
                .collect();
            out.masks = format!(
                "{} ({})",
                folders.into_iter().collect::<Vec<_>>().join(" + "),
                variant.mask_rule().name()
            );
            out.split = format!(
                "camera 0 trains ({} images), the other {} test ({} images)",
                z.frames.len(),
                out.cameras.saturating_sub(1),
                z.frames.len() * out.cameras.saturating_sub(1)
            );
        }
    }
    out.image_size = images.first().and_then(|f| dimensions(&f.image).ok());
    out
}
