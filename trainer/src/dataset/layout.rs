//! Which published layout and variant a sequence directory is in, and where each of
//! its files is: detected from the directory, named at load time, and checked for
//! every frame before a pixel is decoded (so a missing file is named at once, and
//! `drape inspect` can say so without loading the sequence).
//!
//! The variants (each has a fixture the tests generate: `variants::write_zju_variant`,
//! `variants::write_neuman_variant`):
//! - `neuman`: NeuMan as released: `images/`, `segmentations/` (Detectron2, the person
//!   black on white), `sparse/` (COLMAP text), optional `depth_maps/` and
//!   `mono_depth/` (not used), plus HUGS's `4d_humans/smpl_optimized_aligned_scale.npz`,
//!   which drape needs: it reads the SMPL fit from HUGS's file, not from NeuMan's
//!   `smpl_output_optimized.pkl` + `alignments.npy`.
//! - `neuman+hugs`: the same with HUGS's SAM masks `4d_humans/sam_segmentations/`
//!   (the person white), which HUGS trains on and which then replace `segmentations/`.
//! - `zju-neuralbody`: ZJU-MoCap as released for Neural Body: `annots.npy`, images at
//!   `Camera_B*/NNNNNN.jpg` under the root, masks `mask/<image>.png` and/or
//!   `mask_cihp/<image>.png` (the union of those present, as Neural Body reads them),
//!   parameters `new_params/` or `params/`, the frame number from the file name.
//! - `zju-coreview313`: CoreView_313 and CoreView_315 of that release, whose frames are
//!   `Camera (1)/CoreView_313_Camera_(1)_0001_<date>.jpg`: the frame number is the
//!   fifth `_` field, 1-based, and names the parameter file as it is (`params/1.npy`
//!   is the first frame), as Neural Body reads it.
//! - `zju-refined`: the refined release GauHuman, GART and instant-nvr read (`my_377`),
//!   and `drape synth`'s: images under `images/<camera>/`, masks at the image path with
//!   `images` -> `mask`, parameters in `smpl_params/`.
//!
//! Parameter folders are taken in the order `smpl_params/`, `new_params/`, `params/`
//! (the first that exists): the refined fits before the original ones.

use std::path::{Path, PathBuf};

use crate::dataset::colmap::ColmapModel;
use crate::dataset::error::DatasetError;
use crate::dataset::image::MaskRule;
use crate::dataset::zju::ZjuAnnots;

/// The sequence a directory holds: the directory itself, or the one inside a `drape
/// synth` output (its `neuman/`) or a `drape prepare` output (its `sequence/`).
pub fn sequence_root(dir: &Path) -> PathBuf {
    if dir.join("sparse").is_dir() || dir.join("annots.npy").is_file() {
        return dir.to_path_buf();
    }
    if dir.join("neuman").join("sparse").is_dir() {
        return dir.join("neuman");
    }
    if dir.join("prepare.json").is_file() && dir.join("sequence").join("annots.npy").is_file() {
        return dir.join("sequence");
    }
    dir.to_path_buf()
}

/// A published layout variant.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Variant {
    Neuman,
    NeumanHugs,
    ZjuNeuralBody,
    ZjuCoreView313,
    ZjuRefined,
}

impl Variant {
    pub const ALL: [Variant; 5] = [
        Variant::Neuman,
        Variant::NeumanHugs,
        Variant::ZjuNeuralBody,
        Variant::ZjuCoreView313,
        Variant::ZjuRefined,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Variant::Neuman => "neuman",
            Variant::NeumanHugs => "neuman+hugs",
            Variant::ZjuNeuralBody => "zju-neuralbody",
            Variant::ZjuCoreView313 => "zju-coreview313",
            Variant::ZjuRefined => "zju-refined",
        }
    }

    /// One line on what the variant is, for `drape inspect`.
    pub fn describe(self) -> &'static str {
        match self {
            Variant::Neuman => {
                "NeuMan as released (Detectron2 masks in segmentations/) with HUGS's SMPL file"
            }
            Variant::NeumanHugs => "NeuMan with HUGS's 4d_humans/ (SAM masks and SMPL file)",
            Variant::ZjuNeuralBody => {
                "ZJU-MoCap as released for Neural Body (Camera_B*/ at the root)"
            }
            Variant::ZjuCoreView313 => {
                "ZJU-MoCap CoreView_313/315 naming (1-based frame in the file name)"
            }
            Variant::ZjuRefined => {
                "ZJU-MoCap refined (GauHuman, GART, instant-nvr; drape synth): images/<camera>/"
            }
        }
    }

    pub fn is_zju(self) -> bool {
        matches!(
            self,
            Variant::ZjuNeuralBody | Variant::ZjuCoreView313 | Variant::ZjuRefined
        )
    }

    /// The rule that reads the variant's person masks.
    pub fn mask_rule(self) -> MaskRule {
        match self {
            Variant::Neuman => MaskRule::BelowHalf,
            Variant::NeumanHugs => MaskRule::AtLeastHalf,
            _ => MaskRule::NonZero,
        }
    }
}

/// The files of one image of a sequence.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageFiles {
    pub frame: usize,
    pub view: usize,
    pub image: PathBuf,
    /// The person masks (their union is the person; one file except ZJU's
    /// `mask/` + `mask_cihp/`).
    pub masks: Vec<PathBuf>,
    /// Upper and lower garment masks (`masks_upper/`, `masks_lower/`: the synthetic
    /// data's; no published layout has them).
    pub garment_masks: Option<(PathBuf, PathBuf)>,
}

/// A NeuMan sequence's files.
#[derive(Clone, Debug)]
pub struct NeumanFiles {
    pub dir: PathBuf,
    pub variant: Variant,
    pub model: ColmapModel,
    pub smpl: PathBuf,
    /// COLMAP image ids in frame order (image names sorted), with their files.
    pub images: Vec<(u32, ImageFiles)>,
    /// Optional folders that exist and are not read (`depth_maps/`, `mono_depth/`, ...).
    pub unused: Vec<String>,
}

/// A ZJU-MoCap sequence's files.
#[derive(Clone, Debug)]
pub struct ZjuFiles {
    pub dir: PathBuf,
    pub variant: Variant,
    pub annots: ZjuAnnots,
    /// Per frame: the parameter file and the files of every camera's image.
    pub frames: Vec<(PathBuf, Vec<ImageFiles>)>,
}

/// A sequence's files in whichever layout it is.
#[derive(Clone, Debug)]
pub enum SequenceFiles {
    Neuman(NeumanFiles),
    Zju(ZjuFiles),
}

impl SequenceFiles {
    pub fn variant(&self) -> Variant {
        match self {
            SequenceFiles::Neuman(n) => n.variant,
            SequenceFiles::Zju(z) => z.variant,
        }
    }

    /// Every image's files, frame-major.
    pub fn images(&self) -> Vec<&ImageFiles> {
        match self {
            SequenceFiles::Neuman(n) => n.images.iter().map(|(_, f)| f).collect(),
            SequenceFiles::Zju(z) => z.frames.iter().flat_map(|(_, v)| v).collect(),
        }
    }
}

fn exists_or_missing(path: PathBuf, what: &str, variant: Variant) -> Result<PathBuf, DatasetError> {
    if path.is_file() {
        Ok(path)
    } else {
        Err(DatasetError::missing(&path, what, variant.name()))
    }
}

/// The variant of `dir` from its cheapest evidence (of its files only `annots.npy` is
/// read).
pub fn detect(dir: &Path) -> Result<Variant, DatasetError> {
    if dir.join("sparse").is_dir() {
        return Ok(
            if dir.join("4d_humans").join("sam_segmentations").is_dir() {
                Variant::NeumanHugs
            } else {
                Variant::Neuman
            },
        );
    }
    if dir.join("annots.npy").is_file() {
        let annots = ZjuAnnots::read(dir)?;
        return Ok(annots
            .images
            .first()
            .and_then(|v| v.first())
            .map_or(Variant::ZjuNeuralBody, |rel| zju_variant(rel)));
    }
    Err(DatasetError::layout(dir, "neither a NeuMan sequence (sparse/) nor a ZJU-MoCap one (annots.npy), nor a `drape synth` output (neuman/)"))
}

/// Locates every file of a sequence directory, NeuMan (`sparse/`) or ZJU-MoCap
/// (`annots.npy`), naming the first one missing.
pub fn locate(dir: &Path) -> Result<SequenceFiles, DatasetError> {
    if dir.join("sparse").is_dir() {
        return locate_neuman(dir).map(SequenceFiles::Neuman);
    }
    if dir.join("annots.npy").is_file() {
        return locate_zju(dir).map(SequenceFiles::Zju);
    }
    if !dir.exists() {
        return Err(DatasetError::layout(dir, "no such directory"));
    }
    Err(DatasetError::layout(dir, "neither a NeuMan sequence (sparse/) nor a ZJU-MoCap one (annots.npy), nor a `drape synth` output (neuman/)"))
}

fn locate_neuman(dir: &Path) -> Result<NeumanFiles, DatasetError> {
    let sam = dir.join("4d_humans").join("sam_segmentations");
    let variant = if sam.is_dir() {
        Variant::NeumanHugs
    } else {
        Variant::Neuman
    };
    let model = ColmapModel::read_text(&dir.join("sparse"))?;
    let smpl = exists_or_missing(
        dir.join("4d_humans")
            .join("smpl_optimized_aligned_scale.npz"),
        "HUGS's SMPL fit, which drape reads instead of NeuMan's smpl_output_optimized.pkl",
        variant,
    )?;
    let mut ids: Vec<(u32, String)> = model
        .images
        .values()
        .map(|i| (i.id, i.name.clone()))
        .collect();
    ids.sort_by(|a, b| a.1.cmp(&b.1));
    let mask_dir = if variant == Variant::NeumanHugs {
        sam
    } else {
        dir.join("segmentations")
    };
    let upper = dir.join("masks_upper");
    let mut images = Vec::with_capacity(ids.len());
    for (frame, (id, name)) in ids.into_iter().enumerate() {
        let image =
            exists_or_missing(dir.join("images").join(&name), "the frame's image", variant)?;
        let mask = exists_or_missing(mask_dir.join(&name), "the frame's person mask", variant)?;
        let garment_masks = if upper.is_dir() {
            Some((
                exists_or_missing(upper.join(&name), "the upper garment mask", variant)?,
                exists_or_missing(
                    dir.join("masks_lower").join(&name),
                    "the lower garment mask",
                    variant,
                )?,
            ))
        } else {
            None
        };
        images.push((
            id,
            ImageFiles {
                frame,
                view: 0,
                image,
                masks: vec![mask],
                garment_masks,
            },
        ));
    }
    let unused = [
        "depth_maps",
        "mono_depth",
        "monocular_depth",
        "keypoints",
        "densepose",
    ]
    .iter()
    .filter(|d| dir.join(d).is_dir())
    .map(|d| format!("{d}/"))
    .collect();
    Ok(NeumanFiles {
        dir: dir.into(),
        variant,
        model,
        smpl,
        images,
        unused,
    })
}

/// The variant an `annots.npy` image path belongs to.
fn zju_variant(rel: &str) -> Variant {
    let name = rel.rsplit('/').next().unwrap_or(rel);
    if rel.starts_with("images/") {
        Variant::ZjuRefined
    } else if name.starts_with("CoreView_") && name.split('_').count() >= 5 {
        Variant::ZjuCoreView313
    } else {
        Variant::ZjuNeuralBody
    }
}

/// The number that names a frame's parameter file, from its image's name.
fn zju_frame_number(rel: &str, annots: &Path) -> Result<usize, DatasetError> {
    let name = rel.rsplit('/').next().unwrap_or(rel);
    let field = if name.starts_with("CoreView_") {
        name.split('_').nth(4).unwrap_or("")
    } else {
        name.rsplit_once('.').map_or(name, |(stem, _)| stem)
    };
    field.parse().map_err(|_| DatasetError::Field {
        file: annots.display().to_string(),
        field: format!("ims: '{rel}'"),
        problem: "no frame number in the image's name (expected NNNNNN.jpg or CoreView_3xx_Camera_(c)_NNNN_<date>.jpg)".into(),
    })
}

fn without_extension(rel: &str) -> &str {
    match rel.rsplit_once('.') {
        Some((stem, ext)) if !ext.contains('/') => stem,
        _ => rel,
    }
}

/// Where ZJU-MoCap loaders look for an image's masks.
fn zju_mask_candidates(rel: &str, variant: Variant) -> [String; 2] {
    let stem = without_extension(rel);
    if variant == Variant::ZjuRefined {
        [
            format!("{}.png", stem.replacen("images", "mask", 1)),
            format!("{}.png", stem.replacen("images", "mask_cihp", 1)),
        ]
    } else {
        [format!("mask/{stem}.png"), format!("mask_cihp/{stem}.png")]
    }
}

fn locate_zju(dir: &Path) -> Result<ZjuFiles, DatasetError> {
    let annots = ZjuAnnots::read(dir)?;
    let annots_path = dir.join("annots.npy");
    let first = annots
        .images
        .first()
        .and_then(|v| v.first())
        .ok_or_else(|| DatasetError::Field {
            file: annots_path.display().to_string(),
            field: "ims".into(),
            problem: "no frames".into(),
        })?;
    let variant = zju_variant(first);
    let params_dir = ["smpl_params", "new_params", "params"]
        .iter()
        .map(|d| dir.join(d))
        .find(|d| d.is_dir());
    let params_dir = params_dir.ok_or_else(|| {
        DatasetError::missing(
            &dir.join("smpl_params"),
            "the SMPL parameters (smpl_params/, new_params/ or params/)",
            variant.name(),
        )
    })?;
    let mut frames = Vec::with_capacity(annots.images.len());
    for (f, paths) in annots.images.iter().enumerate() {
        if paths.len() != annots.cameras.len() {
            return Err(DatasetError::Field {
                file: annots_path.display().to_string(),
                field: format!("ims[{f}]"),
                problem: format!(
                    "{} images for {} cameras",
                    paths.len(),
                    annots.cameras.len()
                ),
            });
        }
        let number = zju_frame_number(&paths[0], &annots_path)?;
        let params = exists_or_missing(
            params_dir.join(format!("{number}.npy")),
            "the frame's SMPL parameters",
            variant,
        )?;
        let mut views = Vec::with_capacity(paths.len());
        for (c, rel) in paths.iter().enumerate() {
            let image = exists_or_missing(dir.join(rel), "the image annots.npy lists", variant)?;
            let candidates = zju_mask_candidates(rel, variant);
            let masks: Vec<PathBuf> = candidates
                .iter()
                .map(|m| dir.join(m))
                .filter(|p| p.is_file())
                .collect();
            if masks.is_empty() {
                // Name the one whose folder exists: that is where the masks are.
                let top = |c: &String| dir.join(c.split('/').next().unwrap_or(c)).is_dir();
                let (named, other) = if !top(&candidates[0]) && top(&candidates[1]) {
                    (&candidates[1], &candidates[0])
                } else {
                    (&candidates[0], &candidates[1])
                };
                return Err(DatasetError::missing(
                    &dir.join(named),
                    format!("the person mask; nor is there {other}"),
                    variant.name(),
                ));
            }
            views.push(ImageFiles {
                frame: f,
                view: c,
                image,
                masks,
                garment_masks: None,
            });
        }
        frames.push((params, views));
    }
    Ok(ZjuFiles {
        dir: dir.into(),
        variant,
        annots,
        frames,
    })
}
