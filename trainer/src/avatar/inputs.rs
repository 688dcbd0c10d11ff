//! A run's inputs: the sequence in whichever on-disk layout it came (its frames and
//! sparse scene points), the body model, and a frame's body shape.

use std::path::{Path, PathBuf};

use crate::body::procedural::{default_body, BodyOptions};
use crate::body::SmplModel;
use crate::dataset::colmap::ColmapModel;
use crate::dataset::layout::{locate, sequence_root, SequenceFiles, Variant};
use crate::dataset::loader::{load_located, BodyParams, DatasetFrame};
use crate::dataset::split::CameraSplit;

/// The on-disk layout a sequence came in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum Layout {
    NeuMan,
    ZjuMocap,
}

/// A loaded sequence.
pub struct Sequence {
    pub dir: PathBuf,
    pub layout: Layout,
    /// The published variant the files were read as (see `dataset::layout`).
    pub variant: Variant,
    pub frames: Vec<DatasetFrame>,
}

/// Loads `dir` in whichever layout and variant it is: NeuMan (`sparse/`), ZJU-MoCap
/// (`annots.npy`), the root `drape synth` writes (its `neuman/`), or the directory
/// `drape prepare` writes (its `sequence/`). `zju_cameras`:
/// a ZJU-MoCap sequence's training and held-out cameras (a camera index: that one
/// trains, the others are held out; [`TrainConfig::camera_split`]).
///
/// [`TrainConfig::camera_split`]: crate::avatar::config::TrainConfig::camera_split
pub fn load_sequence(dir: &Path, zju_cameras: impl Into<CameraSplit>) -> crate::Result<Sequence> {
    let dir = &sequence_root(dir);
    let files = locate(dir)?;
    let layout = match &files {
        SequenceFiles::Neuman(_) => Layout::NeuMan,
        SequenceFiles::Zju(_) => Layout::ZjuMocap,
    };
    let frames = load_located(&files, zju_cameras)?;
    let variant = files.variant();
    Ok(Sequence {
        dir: dir.into(),
        layout,
        variant,
        frames,
    })
}

/// The default body (the project's procedural one) or an SMPL file.
pub fn body_model(path: Option<&Path>) -> crate::Result<SmplModel> {
    match path {
        Some(p) => Ok(SmplModel::load_npz(p)?),
        None => Ok(default_body(&BodyOptions::default())),
    }
}

/// The body shape (betas) a frame was captured with.
pub(crate) fn betas_of(f: &DatasetFrame) -> Vec<f64> {
    match &f.body {
        BodyParams::Smpl { betas, .. } => betas.clone(),
        BodyParams::Zju(p) => p.shapes.to_vec(),
    }
}

/// The sequence's sparse scene points (NeuMan's `sparse/`), if it has any.
pub fn scene_points(seq: &Sequence) -> crate::Result<Option<ColmapModel>> {
    if seq.layout != Layout::NeuMan {
        return Ok(None);
    }
    let m = ColmapModel::read_text(&seq.dir.join("sparse"))?;
    Ok((!m.points.is_empty()).then_some(m))
}
