//! A finished run opened again (`drape eval`, `drape animate`, `drape edit`): its
//! `config.json`, the data and body it was trained on (`run.json`, written by
//! `drape train`), the body rig, and the trained avatar loaded from `model.npz` onto
//! the GPU with its renderer, ready to pose and render.
//!
//! Which layers the avatar has is read from `model.npz` itself (the arrays it holds),
//! so an edited run (the cloth removed) opens as what it is.

use std::path::{Path, PathBuf};

use drape_engine::Context;

use crate::avatar::assemble::{build_avatar, Layers};
use crate::avatar::checkpoint;
use crate::avatar::composite::AvatarRenderer;
use crate::avatar::config::TrainConfig;
use crate::avatar::inputs::{betas_of, body_model, load_sequence, scene_points, Sequence};
use crate::avatar::model::Avatar;
use crate::avatar::report::write_json;
use crate::avatar::rig::Rig;
use crate::dataset::error::DatasetError;
use crate::dataset::split::Split;
use crate::npy::read_npz;
use crate::TrainerError;

/// Version of `run.json`.
pub const RUN_INFO_VERSION: u32 = 1;

/// Where a run's inputs came from (`run.json`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunInfo {
    pub format_version: u32,
    /// The sequence (absolute path when it was written).
    pub data: PathBuf,
    /// The SMPL-format body file; None: the project's procedural body.
    pub body: Option<PathBuf>,
    /// What made the run when it was not `drape train` (e.g. "edit: cloth removed").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub made_by: Option<String>,
}

impl RunInfo {
    pub fn new(data: &Path, body: Option<&Path>) -> Self {
        let abs = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
        Self {
            format_version: RUN_INFO_VERSION,
            data: abs(data),
            body: body.map(abs),
            made_by: None,
        }
    }

    pub fn write(&self, run: &Path) -> crate::Result<()> {
        write_json(&run.join("run.json"), self)
    }

    /// Reads `run/run.json`; Ok(None) when the run has none.
    pub fn read(run: &Path) -> crate::Result<Option<Self>> {
        let path = run.join("run.json");
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&path).map_err(|e| TrainerError::io(&path, e))?;
        let info: Self =
            serde_json::from_str(&text).map_err(|e| TrainerError::run(&path, e.to_string()))?;
        if info.format_version != RUN_INFO_VERSION {
            return Err(TrainerError::run(
                &path,
                format!(
                    "format_version {}, this drape reads version {RUN_INFO_VERSION}",
                    info.format_version
                ),
            ));
        }
        Ok(Some(info))
    }
}

/// A run ready to render.
pub struct OpenRun {
    pub dir: PathBuf,
    pub config: TrainConfig,
    pub info: RunInfo,
    pub seq: Sequence,
    pub rig: Rig,
    pub avatar: Avatar,
    pub renderer: AvatarRenderer,
    pub layers: Layers,
    /// Training steps the model had taken.
    pub step: u32,
}

/// The layers a model file holds (beyond the body, which every model has).
pub fn model_layers(path: &Path) -> crate::Result<Layers> {
    let a = read_npz(path)?;
    if !a.contains_key("body.means") {
        return Err(TrainerError::checkpoint(
            path,
            "body.means",
            "array is missing (not a drape model?)",
        ));
    }
    Ok(Layers {
        cloth: a.contains_key("cloth.means"),
        scene: a.contains_key("scene.means"),
    })
}

impl OpenRun {
    /// Opens `dir` (a run directory with `config.json` and `model.npz`). `data` and
    /// `body` override `run.json`'s; a run without `run.json` needs `data`.
    pub fn open(
        ctx: &Context,
        dir: &Path,
        data: Option<&Path>,
        body: Option<&Path>,
    ) -> crate::Result<Self> {
        if !dir.is_dir() {
            return Err(TrainerError::run(dir, "no such run directory"));
        }
        let model_path = dir.join("model.npz");
        if !model_path.is_file() {
            return Err(TrainerError::run(
                dir,
                "no model.npz (the run has not finished training?)",
            ));
        }
        let config = TrainConfig::read_run(dir)?;
        let info = match (RunInfo::read(dir)?, data) {
            (Some(mut i), Some(d)) => {
                i.data = d.to_path_buf();
                i
            }
            (Some(i), None) => i,
            (None, Some(d)) => RunInfo::new(d, body),
            (None, None) => {
                return Err(TrainerError::run(
                    dir,
                    "no run.json saying which data the run was trained on; give --data DIR",
                ))
            }
        };
        let body = body.map(Path::to_path_buf).or_else(|| info.body.clone());
        let seq = load_sequence(&info.data, config.camera_split())?;
        let first = seq
            .frames
            .iter()
            .find(|f| f.split == Split::Train)
            .ok_or_else(|| DatasetError::layout(&seq.dir, "no training frames"))?;
        let (width, height) = (first.width, first.height);
        let rig = Rig::new(body_model(body.as_deref())?, &betas_of(first));
        let layers = model_layers(&model_path)?;
        if layers.scene && scene_points(&seq)?.is_none() {
            return Err(TrainerError::run(&model_path, format!("the model has a scene layer, but {} has no scene points to build it on (another sequence?)", seq.dir.display())));
        }
        let mut avatar = build_avatar(ctx, &rig, &seq, &config, layers)?;
        let state = checkpoint::read(&model_path, &avatar.shapes(), avatar.scene_sh_degree())?;
        avatar.restore(ctx, &state)?;
        // Held-out images of trained instants (another camera, the same frame) take
        // the instants' refined poses, as training's own evaluation rendered them.
        let mut seq = seq;
        if let Some(poses) = &state.poses {
            for f in seq.frames.iter_mut().filter(|f| f.split == Split::Test) {
                f.body = poses.body_of_frame(f.frame as u32, &f.body);
            }
        }
        let renderer = AvatarRenderer::new(ctx, &avatar, width, height, config.layers.compositing)?;
        Ok(Self {
            dir: dir.to_path_buf(),
            config,
            info,
            seq,
            rig,
            avatar,
            renderer,
            layers,
            step: state.step,
        })
    }

    /// The held-out frames of the run's protocol.
    pub fn test_frames(&self) -> Vec<&crate::dataset::loader::DatasetFrame> {
        self.seq
            .frames
            .iter()
            .filter(|f| f.split == Split::Test)
            .collect()
    }
}
