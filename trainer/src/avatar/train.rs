//! Training the avatar: load a sequence, build the layers the data requires, fit the
//! skinning weights, then step (sample a training frame → deform → render → losses →
//! backward → Adam) and evaluate on the held-out frames.
//!
//! The layers: the body and, where the data shows garments, the cloth (`model`:
//! triplane + decoders + learned skinning), rendered and composited as
//! [`TrainConfig::compositing`] says (`composite`); where the data has a scene, the
//! scene layer (`scene`) against the whole frame. The losses: 0.8 L1 + 0.2 (1 - SSIM)
//! against the person masked onto a random background colour each step (HUGS), LPIPS
//! where weights are given, and on the cloth layer the paper's cloth-LBS, simulation
//! (Chamfer + Geman–McClure to the garments simulated through the sequence's motion),
//! ARAP and cloth-mask losses (`cloth_losses`). Adam steps every layer, each training
//! frame's pose and translation are refined (`pose_refine`), and the layers are
//! densified and pruned on the schedule of [`TrainConfig::densify`] (`densify`).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use crate::ply;
use drape_engine::ops::splat::scene::RenderSettings;
use crate::avatar::groups::Layer;
use drape_engine::Context;

use crate::avatar::checkpoint;
use crate::avatar::eval::{evaluate, write_reports, EvalInputs};
pub use crate::avatar::eval::{mask_bbox, psnr, EvalMetrics};
use crate::avatar::scene::{scene_init, SceneConfig, SceneLayer};
use crate::dataset::colmap::ColmapModel;
use crate::avatar::cloth_losses::{ClothLossWeights, ClothLosses};
use crate::avatar::cloth_target;
use crate::garment::GarmentFit;
use drape_engine::ops::accumulate::Accumulation;
use drape_engine::ops::lpips::{Lpips, LpipsNet, LpipsWeights};
use crate::avatar::composite::{AvatarRenderer, Compositing};
use crate::avatar::densify::{self, DensifyConfig};
use crate::avatar::layer::LayerConfig;
use crate::avatar::model::{body_init, cloth_init, Avatar, LayerChoice};
use crate::error::TrainerError;
use crate::avatar::pose_refine::PoseRefiner;
use crate::avatar::losses::{ImageLossWeights, ImageLosses};
use crate::avatar::step::{self, HostWaits, Sample, Stages, StepBuffers, StepOutcome};
use crate::avatar::rig::Rig;
use crate::body::procedural::{default_body, BodyOptions};
use crate::body::SmplModel;
use crate::dataset::layout::{locate, SequenceFiles, Variant};
use crate::dataset::loader::{load_located, BodyParams, DatasetFrame};
use crate::dataset::error::DatasetError;
use crate::dataset::split::Split;

/// Everything a run is configured by (written to the run directory as `config.json`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    pub preset: Preset,
    /// Optimisation steps after the skinning-weight fit.
    pub steps: u32,
    pub seed: u64,
    /// Midpoint subdivisions of the body mesh for the body layer's Gaussians (0-2).
    pub subdivision: u32,
    /// Keep every n-th of the body's Gaussians (1: all), each widened by √n in the
    /// surface plane so the body stays covered: for tests and quick looks.
    pub decimate: u32,
    pub body: LayerConfig,
    /// `auto` (a cloth layer where the data has garment masks, a scene layer where it
    /// has scene points), or `body` joined by `+` with `cloth` and/or `scene`: `body`
    /// is the single-layer baseline (cloth folded into the body, as HUGS).
    pub layers: LayerChoice,
    pub cloth: LayerConfig,
    /// The scene layer (plain 3DGS from the sparse points), where there is one.
    pub scene: SceneConfig,
    /// Weight of the cloth-LBS loss `mean((W - W_gt)²)` on the cloth layer (paper: 1000).
    pub lambda_cloth_lbs: f32,
    /// Weight of the simulation loss (Chamfer + Geman–McClure to the frame's simulated
    /// garments, with the ½; paper: 1.0); 0 turns it off.
    pub lambda_sim: f32,
    /// Geman–McClure σ of the simulation loss (metres).
    pub gm_sigma: f32,
    /// Weight of ARAP (variance of the cloth graph's edge lengths; paper: 0.5).
    pub lambda_arap: f32,
    /// Weight of the cloth mask loss (MSE of the cloth alpha against the garment
    /// masks; paper: 1.0).
    pub lambda_mask: f32,
    /// Adam steps fitting the deformation decoder to the body's skinning weights.
    pub fit_steps: u32,
    pub fit_lr: f32,
    /// Steps between log lines (loss and training PSNR).
    pub log_every: u32,
    /// Steps between checkpoints (`checkpoint.npz`, replaced atomically); one is also
    /// written at the end (0: only that one).
    pub checkpoint_every: u32,
    /// A step with any non-finite gradient is skipped (counted and logged); this many
    /// in a row stop the run.
    pub max_skipped_steps: u32,
    /// Image loss `λ_l1 L1 + λ_ssim (1 - SSIM)` (paper: 0.8, 0.2).
    pub lambda_l1: f32,
    pub lambda_ssim: f32,
    /// ZJU-MoCap: the training camera's index.
    pub zju_train_camera: usize,
    /// LPIPS weights (a safetensors file from `scripts/lpips-to-safetensors.py`):
    /// with them LPIPS joins the image loss and the metrics; without, it is left out
    /// and reported as n/a.
    pub lpips_weights: Option<PathBuf>,
    /// `alex` (the metric HUGS reports) or `vgg`.
    pub lpips_net: LpipsNet,
    /// Weight of LPIPS in the image loss (paper: 1.0).
    pub lambda_lpips: f32,
    /// How the layers become one image where there is a cloth layer: `three-pass` (the
    /// paper's: body + scene, cloth and a matte in which only the scene hides the cloth,
    /// composited), `three-pass-occlusion` (the body hides the cloth in the matte too),
    /// `fused` / `fused-occlusion` (the same images and gradients from one sort and one
    /// walk of every layer) or `single-pass` (every layer in one depth-sorted pass).
    #[serde(default = "paper_compositing")]
    pub compositing: Compositing,
    /// Per-frame refinement of the training frames' pose and translation
    /// (`pose_refine`); HUGS refines the pose only.
    #[serde(default = "yes")]
    pub refine_pose: bool,
    /// Adam rate of the refined root and joint axis-angles (HUGS: 1e-4, on 6D).
    #[serde(default = "hugs_pose_rate")]
    pub lr_pose: f32,
    /// Adam rate of the refined translation (in the data's units; HUGS: none).
    #[serde(default = "hugs_pose_rate")]
    pub lr_translation: f32,
    /// Bit-identical runs: the splat and triplane backward passes accumulate in
    /// 64-bit fixed point instead of float atomics (whose order, and so last bits,
    /// changes from run to run), so a resumed run ends where an uninterrupted one does.
    /// Costs two integer atomics per value and gradients rounded to 2^-36.
    #[serde(default)]
    pub deterministic: bool,
    /// The T-shirt the cloth layer is made of and simulated with: `tight` or `loose`
    /// (`drape synth --fit`); on synthetic data, the one the data was made with.
    /// Missing from a config file: tight.
    #[serde(default)]
    pub cloth_fit: GarmentFit,
    /// Densification and pruning of every layer (`densify`; HUGS's schedule and
    /// thresholds in the paper preset). Missing from a config file: off.
    #[serde(default = "DensifyConfig::off")]
    pub densify: DensifyConfig,
}

fn paper_compositing() -> Compositing {
    Compositing::ThreePass(crate::avatar::composite::Matte::Paper)
}

fn yes() -> bool {
    true
}

fn hugs_pose_rate() -> f32 {
    1e-4
}

impl TrainConfig {
    /// Sized for lavapipe on a 2-core machine at the synthetic data's 128 × 128, with
    /// every layer and loss the data asks for (body, cloth and scene; cloth-LBS,
    /// simulation, ARAP and mask): every sixth vertex of the body mesh without
    /// subdivision (1,567 Gaussians) and of the garments (1,113), each widened to keep
    /// the surface covered, densified after 100 and 200 steps (at most 4,096 per
    /// layer); 64 × 64 × 16 triplanes; decoders at most 64 wide (HUGS: 128);
    /// 150 fitting and 400 training steps. The decoders dominate a step there (about two
    /// thirds of its GPU time, `drape train --profile`), hence the narrow decoders and
    /// the decimated meshes (docs/performance.md has the measurements).
    pub fn quick() -> Self {
        Self {
            preset: Preset::Quick,
            steps: 400,
            seed: 1,
            subdivision: 0,
            decimate: 6,
            body: LayerConfig { triplane_resolution: 64, triplane_channels: 16, decoder_width: 64, ..LayerConfig::default() },
            layers: LayerChoice::AUTO,
            cloth: LayerConfig { triplane_resolution: 64, triplane_channels: 16, decoder_width: 64, ..LayerConfig::default() },
            // SH degree 0 for the scene too: 3DGS raises its scene's degree one step
            // every 1,000 iterations, so within 400 it would still be at 0.
            scene: SceneConfig { sh_degree: 0, ..SceneConfig::default() },
            lambda_cloth_lbs: 1000.0,
            lambda_sim: 1.0,
            gm_sigma: drape_shared::cloth_loss::GM_SIGMA_DEFAULT,
            lambda_arap: 0.5,
            lambda_mask: 1.0,
            fit_steps: 150,
            fit_lr: 3e-3,
            log_every: 25,
            checkpoint_every: 200,
            max_skipped_steps: 10,
            lambda_l1: 0.8,
            lambda_ssim: 0.2,
            zju_train_camera: 0,
            lpips_weights: None,
            lpips_net: LpipsNet::Alex,
            lambda_lpips: 1.0,
            compositing: paper_compositing(),
            refine_pose: true,
            lr_pose: hugs_pose_rate(),
            lr_translation: hugs_pose_rate(),
            deterministic: false,
            cloth_fit: GarmentFit::Tight,
            // HUGS densifies every 600 steps from 15% to 75% of its 20k; here after 100
            // and 200 of 400, at most 4,096 per layer, to stay near 10 minutes (three
            // times, to 8,192, takes 860 s); no size prunes within the run (3DGS starts
            // them at 3,000 steps).
            densify: DensifyConfig { every: 100, from: 100, until: 200, max_gaussians: 4096, ..DensifyConfig::default() },
        }
    }

    /// The paper's setting (for a GPU): two subdivisions, 256 × 256 × 32 triplanes,
    /// 20k steps; SH degree 0 for the human layers (HUGS's code) and 3 for the scene
    /// (3DGS; here from the first step, without 3DGS's one-degree-per-1,000 ramp).
    pub fn paper() -> Self {
        Self {
            preset: Preset::Paper,
            steps: 20_000,
            subdivision: 2,
            decimate: 1,
            body: LayerConfig::default(),
            cloth: LayerConfig::default(),
            scene: SceneConfig::default(),
            fit_steps: 3000,
            fit_lr: 1e-3,
            log_every: 100,
            checkpoint_every: 1000,
            densify: DensifyConfig::default(),
            ..Self::quick()
        }
    }

    /// The preset's settings.
    pub fn preset(preset: Preset) -> Self {
        match preset {
            Preset::Quick => Self::quick(),
            Preset::Paper => Self::paper(),
        }
    }

    /// Reads a config from any serde format (a run's `config.json`, the merged TOML of
    /// `drape train --config`) and validates it. A bad value names its key (`body.
    /// triplane_resolution`, `compositing`) and, for a choice, the values it takes.
    pub fn from_deserializer<'de, D: serde::Deserializer<'de>>(d: D) -> crate::Result<Self> {
        let c: Self = serde_path_to_error::deserialize(d).map_err(|e| {
            let key = e.path().to_string();
            TrainerError::config(if key == "." { "(top level)".to_string() } else { key }, e.into_inner().to_string())
        })?;
        c.validate()?;
        Ok(c)
    }

    /// This config with the TOML document `text` (from `file`) laid over it: every key
    /// must be one of the config's (an optional one such as `lpips_weights` included)
    /// and keep its type (an integer may stand for a float); the result is validated.
    /// Errors name the file and the key.
    pub fn with_toml(&self, text: &str, file: &Path) -> crate::Result<Self> {
        let in_file = |e: TrainerError| match e {
            TrainerError::Config { key, problem } => TrainerError::Config { key: format!("{}: {key}", file.display()), problem },
            other => other,
        };
        let over: serde_json::Value = toml::from_str(text).map_err(|e| TrainerError::config(file.display().to_string(), e.message().to_string()))?;
        let mut base = serde_json::to_value(self).map_err(|e| TrainerError::config("(top level)", e.to_string()))?;
        merge_json(&mut base, &over, "").map_err(in_file)?;
        Self::from_deserializer(base).map_err(in_file)
    }

    /// Checks values a config file could get wrong, naming the field.
    pub fn validate(&self) -> crate::Result<()> {
        let bad = |key: &str, problem: String| Err(TrainerError::config(key, problem));
        // Each triplane is 3 x resolution² x channels f32 values, with Adam's two moments
        // beside it: bounded so that a typo cannot ask for terabytes.
        for (layer, t) in [("body", &self.body), ("cloth", &self.cloth)] {
            if !(2..=MAX_TRIPLANE_RESOLUTION).contains(&t.triplane_resolution) {
                return bad(&format!("{layer}.triplane_resolution"), format!("must be 2-{MAX_TRIPLANE_RESOLUTION} (HUGS: 128), got {}", t.triplane_resolution));
            }
            if !(1..=MAX_TRIPLANE_CHANNELS).contains(&t.triplane_channels) {
                return bad(&format!("{layer}.triplane_channels"), format!("must be 1-{MAX_TRIPLANE_CHANNELS} (HUGS: 32), got {}", t.triplane_channels));
            }
        }
        for (name, v, max) in [("steps", self.steps, MAX_STEPS), ("fit_steps", self.fit_steps, MAX_STEPS)] {
            if v > max {
                return bad(name, format!("must be at most {max}, got {v}"));
            }
        }
        let rates = [
            ("cloth.lr_position", self.cloth.lr_position),
            ("cloth.lr_triplane", self.cloth.lr_triplane),
            ("cloth.lr_decoders", self.cloth.lr_decoders),
            ("cloth.lr_deformation", self.cloth.lr_deformation),
            ("lambda_cloth_lbs", self.lambda_cloth_lbs),
            ("lambda_sim", self.lambda_sim),
            ("lambda_arap", self.lambda_arap),
            ("lambda_mask", self.lambda_mask),
            ("body.lr_position", self.body.lr_position),
            ("body.lr_triplane", self.body.lr_triplane),
            ("body.lr_decoders", self.body.lr_decoders),
            ("body.lr_deformation", self.body.lr_deformation),
            ("fit_lr", self.fit_lr),
            ("lambda_l1", self.lambda_l1),
            ("lambda_ssim", self.lambda_ssim),
            ("lambda_lpips", self.lambda_lpips),
            ("lr_pose", self.lr_pose),
            ("lr_translation", self.lr_translation),
            ("scene.lr_position", self.scene.lr_position),
            ("scene.lr_position_final", self.scene.lr_position_final),
            ("scene.lr_rotation", self.scene.lr_rotation),
            ("scene.lr_scale", self.scene.lr_scale),
            ("scene.lr_opacity", self.scene.lr_opacity),
            ("scene.lr_sh", self.scene.lr_sh),
        ];
        for (name, v) in rates {
            if !(v.is_finite() && v >= 0.0) {
                return bad(name, format!("must be a finite rate >= 0, got {v}"));
            }
        }
        self.densify.validate()?;
        if !(self.gm_sigma.is_finite() && self.gm_sigma > 0.0) {
            return bad("gm_sigma", format!("must be a finite length > 0, got {}", self.gm_sigma));
        }
        if self.decimate == 0 {
            return bad("decimate", "must be >= 1".into());
        }
        if self.log_every == 0 {
            return bad("log_every", "must be >= 1 (steps between log lines)".into());
        }
        if self.scene.max_points == 0 {
            return bad("scene.max_points", "must be >= 1".into());
        }
        if self.lpips_weights.as_ref().is_some_and(|p| p.as_os_str().is_empty()) {
            return bad("lpips_weights", "is empty; leave the key out to train without LPIPS".into());
        }
        if self.subdivision > 2 {
            return bad("subdivision", format!("must be 0, 1 or 2, got {}", self.subdivision));
        }
        for (name, degree) in [("body.sh_degree", self.body.sh_degree), ("cloth.sh_degree", self.cloth.sh_degree), ("scene.sh_degree", self.scene.sh_degree)] {
            if degree > 3 {
                return bad(name, format!("must be 0-3, got {degree}"));
            }
        }
        for (name, w) in [("body.decoder_width", self.body.decoder_width), ("cloth.decoder_width", self.cloth.decoder_width)] {
            if !(1..=1024).contains(&w) {
                return bad(name, format!("must be 1-1024 (HUGS: 128), got {w}"));
            }
        }
        Ok(())
    }
}

/// Largest triplane side and channel count a config may ask for (HUGS: 128 and 32).
pub const MAX_TRIPLANE_RESOLUTION: u32 = 1024;
pub const MAX_TRIPLANE_CHANNELS: u32 = 256;
/// Largest step counts (the paper trains 3,000 steps per sequence).
pub const MAX_STEPS: u32 = 10_000_000;

/// Lays `over` onto `base` (JSON values), naming the first key `base` lacks or whose
/// type `over` changes. A `null` in `base` (an unset option) takes any value.
fn merge_json(base: &mut serde_json::Value, over: &serde_json::Value, path: &str) -> crate::Result<()> {
    use serde_json::Value;
    match (base, over) {
        (Value::Object(b), Value::Object(o)) => {
            for (k, v) in o {
                let key = if path.is_empty() { k.clone() } else { format!("{path}.{k}") };
                match b.get_mut(k) {
                    Some(slot) => merge_json(slot, v, &key)?,
                    None => return Err(TrainerError::config(key, "unknown key (a run's config.json lists every key)")),
                }
            }
            Ok(())
        }
        (b @ Value::Null, o) => {
            *b = o.clone();
            Ok(())
        }
        (b, o) => {
            let kind = |v: &Value| match v {
                Value::Null => "nothing",
                Value::Bool(_) => "a boolean",
                Value::Number(_) => "a number",
                Value::String(_) => "a string",
                Value::Array(_) => "an array",
                Value::Object(_) => "a table",
            };
            // An integer may stand for a float, a float for an integer only if whole
            // (serde then says whether the number fits the field).
            if kind(b) != kind(o) {
                return Err(TrainerError::config(path, format!("must be {}, got {}", kind(b), kind(o))));
            }
            *b = o.clone();
            Ok(())
        }
    }
}

/// A named starting point for a config.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// Small sizes for lavapipe at 128 × 128 ([`TrainConfig::quick`]).
    Quick,
    /// The paper's setting, for a GPU ([`TrainConfig::paper`]).
    Paper,
}

impl Preset {
    /// `quick` or `paper`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Quick => "quick",
            Self::Paper => "paper",
        }
    }

    /// The preset named `name`; the error names the presets there are.
    pub fn parse(name: &str) -> crate::Result<Self> {
        match name {
            "quick" => Ok(Self::Quick),
            "paper" => Ok(Self::Paper),
            other => Err(TrainerError::config("preset", format!("unknown preset '{other}' (quick, paper)"))),
        }
    }
}

impl std::fmt::Display for Preset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

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
/// (`annots.npy`), or the root `drape synth` writes (its `neuman/`).
pub fn load_sequence(dir: &Path, zju_train_camera: usize) -> crate::Result<Sequence> {
    if !dir.join("sparse").is_dir() && !dir.join("annots.npy").is_file() && dir.join("neuman").join("sparse").is_dir() {
        return load_sequence(&dir.join("neuman"), zju_train_camera);
    }
    let files = locate(dir)?;
    let layout = match &files {
        SequenceFiles::Neuman(_) => Layout::NeuMan,
        SequenceFiles::Zju(_) => Layout::ZjuMocap,
    };
    let frames = load_located(&files, zju_train_camera)?;
    let variant = files.variant();
    Ok(Sequence { dir: dir.into(), layout, variant, frames })
}

impl TrainConfig {
    /// Reads a run's `config.json` (for `--resume`), naming the file on any problem.
    pub fn read_run(dir: &Path) -> crate::Result<Self> {
        let path = dir.join("config.json");
        let text = std::fs::read_to_string(&path).map_err(|e| TrainerError::io(&path, e))?;
        let mut json = serde_json::Deserializer::from_str(&text);
        Self::from_deserializer(&mut json).map_err(|e| match e {
            TrainerError::Config { key, problem } => TrainerError::Config { key: format!("{}: {key}", path.display()), problem },
            other => other,
        })
    }
}

/// What a run did.
#[derive(Clone, Debug, serde::Serialize)]
pub struct TrainReport {
    pub layout: Layout,
    pub gaussians: Vec<(String, u32)>,
    pub fit_steps: u32,
    pub fit_mse: f64,
    pub fit_seconds: f64,
    /// The step training started from (0, or the checkpoint's when resumed).
    pub start_step: u32,
    pub steps: u32,
    pub train_seconds: f64,
    pub iterations_per_second: f64,
    pub skipped_steps: u32,
    /// Host waits (fence waits) of the training steps.
    pub host_waits: HostWaits,
    pub initial: EvalMetrics,
    pub fin: EvalMetrics,
}

/// Progress of a run, for a progress line.
#[derive(Clone, Debug)]
pub enum Progress {
    Fit { layer: String, step: u32, total: u32, mse: f64 },
    Step { step: u32, total: u32, l1: f64, psnr: f64, it_per_s: f64 },
    Eval { done: usize, total: usize },
    /// Simulating the garments through the sequence (frames, settling ones included).
    Simulate { done: usize, total: usize },
    /// The layers were densified and pruned after `step` steps: (layer, before, after).
    Densify { step: u32, counts: Vec<(String, usize, usize)> },
}

/// The default body (the project's procedural one) or an SMPL file.
pub fn body_model(path: Option<&Path>) -> crate::Result<SmplModel> {
    match path {
        Some(p) => Ok(SmplModel::load_npz(p)?),
        None => Ok(default_body(&BodyOptions::default())),
    }
}

pub(crate) fn betas_of(f: &DatasetFrame) -> Vec<f64> {
    match &f.body {
        BodyParams::Smpl { betas, .. } => betas.clone(),
        BodyParams::Zju(p) => p.shapes.to_vec(),
    }
}


/// The optional layers a run builds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Layers {
    pub cloth: bool,
    pub scene: bool,
}

/// The sequence's sparse scene points (NeuMan's `sparse/`), if it has any.
pub fn scene_points(seq: &Sequence) -> crate::Result<Option<ColmapModel>> {
    if seq.layout != Layout::NeuMan {
        return Ok(None);
    }
    let m = ColmapModel::read_text(&seq.dir.join("sparse"))?;
    Ok((!m.points.is_empty()).then_some(m))
}

/// The layers the run builds, each forced by `config.layers` or else decided from the
/// data: a cloth layer where it has garment masks, a scene layer where it has scene
/// points (an unmasked capture; ZJU-MoCap's studio frames are masked and have none).
pub fn choose_layers(seq: &Sequence, config: &TrainConfig) -> crate::Result<Layers> {
    let choice = config.layers;
    let scene = match choice.scene {
        Some(true) if scene_points(seq)?.is_none() => {
            return Err(TrainerError::config("layers", format!("{choice}: {} has no scene points (NeuMan's sparse/points3D.txt) to build a scene layer from", seq.dir.display())))
        }
        Some(s) => s,
        None => scene_points(seq)?.is_some(),
    };
    Ok(Layers { cloth: choice.cloth.unwrap_or_else(|| seq.frames.iter().any(|f| f.garment_masks.is_some())), scene })
}

/// The avatar the data requires.
pub(crate) fn build_avatar(ctx: &Context, rig: &Rig, seq: &Sequence, config: &TrainConfig, layers: Layers) -> crate::Result<Avatar> {
    let cloth = layers.cloth;
    let mut inits = vec![body_init(rig, config.subdivision, config.decimate, config.body.sh_degree)];
    let mut configs = vec![config.body.clone()];
    let mut lbs = vec![0.0];
    if cloth {
        inits.push(cloth_init(rig, config.cloth_fit, config.decimate, config.cloth.sh_degree));
        configs.push(config.cloth.clone());
        lbs.push(config.lambda_cloth_lbs);
    }
    let scene = match (layers.scene, scene_points(seq)?) {
        (true, Some(colmap)) => {
            let (cloud, extent) = scene_init(&colmap, config.scene.sh_degree, config.scene.max_points);
            Some(SceneLayer::new(ctx, &cloud, extent, &config.scene, config.steps)?)
        }
        _ => None,
    };
    let mut avatar = Avatar::new(ctx, &inits, &configs, &lbs, scene, config.steps, config.seed)?;
    if config.deterministic {
        avatar.set_accumulation(ctx, Accumulation::Deterministic)?;
    }
    Ok(avatar)
}

/// Times host phases of a step into the context's profile (a no-op without one).
struct Lap<'c> {
    ctx: &'c Context,
    on: bool,
    since: Instant,
}

impl<'c> Lap<'c> {
    fn new(ctx: &'c Context, on: bool) -> Self {
        Self { ctx, on, since: Instant::now() }
    }

    fn reset(&mut self) {
        self.since = Instant::now();
    }

    /// Adds the time since the last reset or phase under `name`.
    fn host(&mut self, name: &str) {
        if self.on {
            self.ctx.profile_host(name, self.since.elapsed().as_secs_f64() * 1e3);
            self.since = Instant::now();
        }
    }
}

/// A log line's value: plain numbers and names, which always serialise.
fn json_value(value: &impl serde::Serialize) -> serde_json::Value {
    serde_json::to_value(value).expect("log values are numbers and names")
}

pub(crate) fn write_json(path: &Path, value: &impl serde::Serialize) -> crate::Result<()> {
    let text = serde_json::to_string_pretty(value).map_err(|e| TrainerError::io(path, e.into()))?;
    // Written whole to a temporary file, then renamed: never half a file.
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, text + "\n").map_err(|e| TrainerError::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| TrainerError::io(path, e))
}

/// Trains on `seq` into the run directory `out`: a new one (it must not exist, or be
/// empty), or with `resume` the run's last checkpoint (`out/checkpoint.npz`), continued
/// to `config.steps`. The step's frame and background come from `(seed, step)`, so a
/// resumed run samples what the uninterrupted one would have.
pub fn train(ctx: &Context, seq: &Sequence, model: SmplModel, config: &TrainConfig, out: &Path, resume: bool, progress: &mut dyn FnMut(Progress)) -> crate::Result<TrainReport> {
    train_until(ctx, seq, model, config, out, resume, config.steps, progress)
}

/// [`train`], stopping after step `stop_at` (at most `config.steps`) as if the run
/// had been interrupted there: the checkpoint is written, the schedules still run to
/// `config.steps`, and a later `resume` continues as the uninterrupted run would.
#[allow(clippy::too_many_arguments)]
pub fn train_until(ctx: &Context, seq: &Sequence, model: SmplModel, config: &TrainConfig, out: &Path, resume: bool, stop_at: u32, progress: &mut dyn FnMut(Progress)) -> crate::Result<TrainReport> {
    let never = AtomicBool::new(false);
    match run(ctx, seq, model, config, out, resume, stop_at, None, &never, progress)? {
        Outcome::Finished(report) => Ok(*report),
        Outcome::Interrupted { .. } => unreachable!("nothing sets the flag"),
    }
}

/// How a run that can be interrupted ended.
#[derive(Debug)]
pub enum Outcome {
    /// Every step ran; the model, metrics and `complete` marker are written.
    Finished(Box<TrainReport>),
    /// `interrupt` was set: the step in flight finished and the checkpoint holds the
    /// state after `step` steps; `--resume` continues it.
    Interrupted { step: u32 },
}

/// [`train`] that stops cleanly when `interrupt` becomes true (a signal handler sets
/// it): the step in flight finishes, the checkpoint is written atomically, and the run
/// directory stays resumable. `info` (the data and body) is written as `run.json` when
/// the run directory is made, so that `--resume` and the other commands find the data
/// of an unfinished run.
#[allow(clippy::too_many_arguments)]
pub fn train_interruptible(ctx: &Context, seq: &Sequence, model: SmplModel, config: &TrainConfig, out: &Path, resume: bool, info: Option<&crate::avatar::run::RunInfo>, interrupt: &AtomicBool, progress: &mut dyn FnMut(Progress)) -> crate::Result<Outcome> {
    run(ctx, seq, model, config, out, resume, config.steps, info, interrupt, progress)
}

/// The marker a finished run holds (its command run again has nothing to do).
pub const COMPLETE_MARKER: &str = "complete";
/// The note an unfinished run holds (how to continue it).
pub const INCOMPLETE_MARKER: &str = "incomplete";

/// What is in a run directory before a run starts in it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RunState {
    /// Missing or empty: a new run can start.
    Fresh,
    /// A finished run ([`COMPLETE_MARKER`]).
    Complete,
    /// A run with a checkpoint and no [`COMPLETE_MARKER`]: `--resume` continues it.
    Resumable,
    /// Something else (files that are no drape run, or a run without a checkpoint).
    Occupied,
}

/// Classifies `out` (see [`RunState`]).
pub fn run_state(out: &Path) -> crate::Result<RunState> {
    if !out.exists() {
        return Ok(RunState::Fresh);
    }
    if !out.is_dir() {
        return Ok(RunState::Occupied);
    }
    if std::fs::read_dir(out).map_err(|e| TrainerError::io(out, e))?.next().is_none() {
        return Ok(RunState::Fresh);
    }
    Ok(if out.join(COMPLETE_MARKER).is_file() {
        RunState::Complete
    } else if out.join("checkpoint.npz").is_file() && out.join("config.json").is_file() {
        RunState::Resumable
    } else {
        RunState::Occupied
    })
}

/// The preemption test's hook: with `DRAPE_FAILPOINT=wait-for-signal-before-step:K`,
/// the run says so on stderr before step K and waits (at most a minute) until a signal
/// sets `interrupt`, so that a test's SIGTERM lands at a known step. Unset (always,
/// outside that test), it does nothing.
fn wait_for_signal_if_asked(step: u32, interrupt: &AtomicBool) {
    let Ok(spec) = std::env::var("DRAPE_FAILPOINT") else { return };
    if spec.strip_prefix("wait-for-signal-before-step:").and_then(|k| k.parse::<u32>().ok()) != Some(step) {
        return;
    }
    eprintln!("\nfailpoint: waiting for a signal before step {step}");
    let t0 = Instant::now();
    while !interrupt.load(Ordering::SeqCst) && t0.elapsed().as_secs() < 60 {
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
}

/// Refuses to start a new run in `out` unless it is missing or empty, saying what is
/// there and what to do instead.
pub fn check_fresh(out: &Path) -> crate::Result<()> {
    match run_state(out)? {
        RunState::Fresh => Ok(()),
        RunState::Complete => Err(TrainerError::run(out, "holds a complete run (it has the 'complete' marker); --force trains it again")),
        RunState::Resumable => Err(TrainerError::run(out, format!("holds an unfinished run (see its '{INCOMPLETE_MARKER}'): `drape train --resume {}` continues it; --force starts it again", out.display()))),
        RunState::Occupied => Err(TrainerError::run(out, "exists and is not empty, and is no drape run to resume; choose another --out")),
    }
}

#[allow(clippy::too_many_arguments)]
/// The guard's bookkeeping: steps skipped for non-finite gradients, and the stop after
/// too many in a row.
struct SkipGuard {
    total: u32,
    in_a_row: u32,
    limit: u32,
}

impl SkipGuard {
    fn new(limit: u32) -> Self {
        Self { total: 0, in_a_row: 0, limit: limit.max(1) }
    }

    fn applied(&mut self) {
        self.in_a_row = 0;
    }

    /// Counts a skipped step; an error once `limit` steps in a row were skipped.
    fn skipped(&mut self, step: u32, nonfinite: u32, frame: usize, data: &Path, checkpoint: &Path) -> crate::Result<()> {
        self.total += 1;
        self.in_a_row += 1;
        if self.in_a_row < self.limit {
            return Ok(());
        }
        Err(TrainerError::numeric(
            "training",
            format!(
                "stopped at step {step}: {} steps in a row had non-finite gradients ({nonfinite} values in the last, frame {frame} of {}); the last checkpoint is {}",
                self.in_a_row,
                data.display(),
                checkpoint.display()
            ),
        ))
    }
}

/// The pose refiner's step on the frame of `s` from every human layer's share of
/// `∂L/∂A` (mapped memory: read after the step's wait with no other). A gradient
/// that the rig's chain rule makes non-finite is not applied: the log line says so.
fn refine_pose(ctx: &Context, avatar: &mut Avatar, rig: &Rig, refiner: &mut PoseRefiner, s: &Sample<'_>, step: u32) -> crate::Result<Option<serde_json::Value>> {
    let mut grad = vec![0.0f64; crate::avatar::rig::TRANSFORM_FLOATS];
    for l in &mut avatar.layers {
        for (g, v) in grad.iter_mut().zip(l.read_transform_grad(ctx)?) {
            *g += v;
        }
    }
    let g = rig.frame_gradient(&s.body, &grad);
    let bad = g.iter().filter(|v| !v.is_finite()).count();
    if bad > 0 {
        return Ok(Some(serde_json::json!({ "step": step, "frame": s.frame.frame, "pose_refinement_skipped": true, "nonfinite_pose_gradients": bad })));
    }
    refiner.step(s.index, &g);
    Ok(None)
}

/// A logging step's line (losses read back) with its L1 and PSNR.
/// `seconds`: since training started.
#[allow(clippy::too_many_arguments)]
fn log_line(ctx: &Context, image: &mut ImageLosses, cloth: Option<&mut ClothLosses>, avatar: &Avatar, refiner: Option<&PoseRefiner>, step: u32, frame: usize, seconds: f64) -> crate::Result<(serde_json::Value, f64, f64)> {
    let v = image.read_values(ctx)?;
    let mut line = serde_json::json!({ "step": step, "frame": frame, "l1": v.l1, "ssim": v.ssim, "loss": v.loss, "psnr_train": v.psnr, "lr_position": avatar.layers[0].groups.position.lr(), "seconds": seconds });
    if let Some(c) = cloth {
        line["cloth"] = json_value(&c.read_values(ctx)?);
    }
    if let Some(l) = v.lpips {
        line["lpips"] = l.into();
    }
    if let Some(r) = refiner {
        // Mean over training frames of the largest joint correction and of the
        // translation's.
        let (rot, tr) = r.summary();
        line["pose_correction_rad"] = rot.into();
        line["translation_correction"] = tr.into();
    }
    Ok((line, v.l1, v.psnr))
}

/// Densifies and prunes every layer after `step + 1` steps; everything sized by the
/// layers' counts follows them. Returns the log's summaries and (layer, before, after).
type DensifyCounts = Vec<(String, usize, usize)>;
fn densify_layers(ctx: &Context, avatar: &mut Avatar, config: &TrainConfig, step: u32, log_scale: f32) -> crate::Result<(serde_json::Map<String, serde_json::Value>, DensifyCounts)> {
    let dc = &config.densify;
    let mut counts = Vec::new();
    let mut summaries = serde_json::Map::new();
    let seed = config.seed ^ u64::from(step + 1).wrapping_mul(0xD1B5_4A32_D192_ED03);
    for l in avatar.layers.iter_mut() {
        let s = densify::apply_to_layer(ctx, l, dc, step + 1, log_scale)?;
        counts.push((l.name.clone(), s.before, s.after));
        summaries.insert(l.name.clone(), json_value(&s));
    }
    if let Some(sc) = avatar.scene.as_mut() {
        let s = densify::apply_to_scene(ctx, sc, dc, step + 1, seed.wrapping_add(1000))?;
        counts.push(("scene".into(), s.before, s.after));
        summaries.insert("scene".into(), json_value(&s));
    }
    avatar.resize_posed(ctx)?;
    Ok((summaries, counts))
}

fn run(ctx: &Context, seq: &Sequence, model: SmplModel, config: &TrainConfig, out: &Path, resume: bool, stop_at: u32, info: Option<&crate::avatar::run::RunInfo>, interrupt: &AtomicBool, progress: &mut dyn FnMut(Progress)) -> crate::Result<Outcome> {
    let stop_at = stop_at.min(config.steps);
    config.validate()?;
    let train_frames: Vec<&DatasetFrame> = seq.frames.iter().filter(|f| f.split == Split::Train).collect();
    if train_frames.is_empty() {
        return Err(DatasetError::layout(&seq.dir, "no training frames").into());
    }
    let (width, height) = (train_frames[0].width, train_frames[0].height);
    if let Some(f) = seq.frames.iter().find(|f| (f.width, f.height) != (width, height)) {
        return Err(DatasetError::image(&f.image_path, format!("{}x{}, but the sequence's first training image is {width}x{height}", f.width, f.height)).into());
    }
    // LPIPS where the run has weights: read before the run directory is made, so a
    // wrong path leaves nothing behind.
    let lpips_weights = match &config.lpips_weights {
        Some(path) => Some(LpipsWeights::load(path, config.lpips_net)?),
        None => None,
    };
    let checkpoint_path = out.join("checkpoint.npz");
    if resume {
        if !checkpoint_path.is_file() {
            return Err(TrainerError::run(&checkpoint_path, "no checkpoint to resume from"));
        }
        return train_in(ctx, seq, model, config, out, true, stop_at, interrupt, lpips_weights, progress);
    }
    check_fresh(out)?;
    let created = !out.exists();
    let made = (|| -> crate::Result<()> {
        std::fs::create_dir_all(out.join("eval")).map_err(|e| TrainerError::io(out, e))?;
        write_json(&out.join("config.json"), config)?;
        if let Some(info) = info {
            info.write(out)?;
        }
        let note = out.join(INCOMPLETE_MARKER);
        std::fs::write(&note, format!("this run has not finished; `drape train --resume {}` continues it from checkpoint.npz\n", out.display())).map_err(|e| TrainerError::io(&note, e))
    })();
    let result = made.and_then(|()| train_in(ctx, seq, model, config, out, false, stop_at, interrupt, lpips_weights, progress));
    // A run that failed before its first checkpoint leaves nothing (an empty directory
    // that was there before stays, empty); after it, the run stays resumable.
    if result.is_err() && !checkpoint_path.exists() {
        if created {
            let _ = std::fs::remove_dir_all(out);
        } else if let Ok(entries) = std::fs::read_dir(out) {
            for e in entries.flatten() {
                let p = e.path();
                let _ = if p.is_dir() { std::fs::remove_dir_all(&p) } else { std::fs::remove_file(&p) };
            }
        }
    }
    result
}

#[allow(clippy::too_many_arguments)]
fn train_in(ctx: &Context, seq: &Sequence, model: SmplModel, config: &TrainConfig, out: &Path, resume: bool, stop_at: u32, interrupt: &AtomicBool, lpips_weights: Option<LpipsWeights>, progress: &mut dyn FnMut(Progress)) -> crate::Result<Outcome> {
    let train_frames: Vec<&DatasetFrame> = seq.frames.iter().filter(|f| f.split == Split::Train).collect();
    let test_frames: Vec<&DatasetFrame> = seq.frames.iter().filter(|f| f.split == Split::Test).collect();
    let (width, height) = (train_frames[0].width, train_frames[0].height);
    let checkpoint_path = out.join("checkpoint.npz");
    let log_path = out.join("log.jsonl");
    let mut log = std::fs::OpenOptions::new().create(true).append(true).open(&log_path).map_err(|e| TrainerError::io(&log_path, e))?;

    let rig = Rig::new(model, &betas_of(train_frames[0]));
    let mut avatar = build_avatar(ctx, &rig, seq, config, choose_layers(seq, config)?)?;
    // With a scene layer the avatar is trained and judged on the whole image; without
    // one, on the person over a background colour.
    let whole_image = avatar.scene.is_some();
    let mut renderer = AvatarRenderer::new(ctx, &avatar, width, height, config.compositing)?;
    let ground_truth = cloth_target::ground_truth_dir(&seq.dir);
    // The cloth layer's physics targets: the garments simulated through the motion.
    let mut cloth_losses = match avatar.cloth() {
        Some(cloth) if config.lambda_sim > 0.0 || config.lambda_arap > 0.0 || config.lambda_mask > 0.0 => {
            let garments = cloth_target::simulate_sequence(&rig, config.cloth_fit, &seq.frames, &mut |done, total| progress(Progress::Simulate { done, total }))?;
            let weights = ClothLossWeights { sim: config.lambda_sim, gm_sigma: config.gm_sigma, arap: config.lambda_arap, mask: config.lambda_mask, target_stride: config.decimate };
            Some(ClothLosses::new(ctx, cloth, garments, weights, width, height)?)
        }
        _ => None,
    };

    // 1. The deformation decoder learns the body's skinning weights (or the run's
    //    checkpoint is loaded: its decoders have been fitted already).
    let t0 = Instant::now();
    let total_fit = config.fit_steps;
    let mut refiner = config.refine_pose.then(|| PoseRefiner::new(&train_frames.iter().map(|f| f.frame as u32).collect::<Vec<_>>(), f64::from(config.lr_pose), f64::from(config.lr_translation)));
    let (start_step, fit_mse) = if resume {
        let state = checkpoint::read(&checkpoint_path, &avatar.shapes(), avatar.scene_sh_degree())?;
        if state.step > config.steps {
            return Err(TrainerError::checkpoint(&checkpoint_path, "step", format!("the checkpoint is at step {}, past the run's {} steps (raise --steps)", state.step, config.steps)));
        }
        avatar.restore(ctx, &state)?;
        // The checkpoint's layers may have been densified to other counts.
        renderer = AvatarRenderer::new(ctx, &avatar, width, height, config.compositing)?;
        if let (Some(c), Some(cloth)) = (cloth_losses.as_mut(), avatar.cloth()) {
            c.resize(ctx, cloth)?;
        }
        if let (Some(r), Some(p)) = (refiner.as_mut(), state.poses) {
            r.restore(p).map_err(|e| TrainerError::checkpoint(&checkpoint_path, "poses", e.to_string()))?;
        }
        (state.step, f64::NAN)
    } else {
        let mut worst = 0.0f64;
        for l in &mut avatar.layers {
            let name = l.name.clone();
            let mse = l.fit_skinning_weights(ctx, total_fit, config.fit_lr, 25, |step, mse| progress(Progress::Fit { layer: name.clone(), step, total: total_fit, mse }))?;
            worst = worst.max(mse);
        }
        (0, worst)
    };
    let fit_seconds = t0.elapsed().as_secs_f64();
    if let (Some(c), true) = (cloth_losses.as_mut(), renderer.is_three_pass()) {
        c.set_mask_in_composite(true);
    }
    let lpips = match &lpips_weights {
        Some(w) if config.lambda_lpips > 0.0 => Some(Lpips::new(ctx, w, width, height)?),
        _ => None,
    };
    let eval_inputs = |sheets| EvalInputs { rig: &rig, frames: &test_frames, ground_truth: ground_truth.as_deref(), lpips: lpips_weights.as_ref(), sheets };
    let (initial, _) = evaluate(ctx, &mut avatar, &mut renderer, &eval_inputs(None), progress)?;

    // 2. The main loop: a step is one submission and one host wait (`step`).
    let mut buffers = StepBuffers::new(ctx, width, height)?;
    let weights = ImageLossWeights { l1: config.lambda_l1, ssim: config.lambda_ssim, lpips: config.lambda_lpips };
    let mut image_losses = ImageLosses::new(ctx, width, height, weights, lpips)?;
    let settings = RenderSettings::default();
    let t_train = Instant::now();
    let mut skips = SkipGuard::new(config.max_skipped_steps);
    let mut waits = HostWaits::default();
    let save = |avatar: &mut Avatar, refiner: &Option<PoseRefiner>, step: u32, path: &Path| -> crate::Result<()> {
        let mut state = avatar.state(ctx, step)?;
        state.poses = refiner.as_ref().map(|r| r.state().clone());
        checkpoint::write(path, &state)
    };
    // With a profile running (`drape train --profile`), it covers the steps alone.
    let profiling = ctx.profiling();
    if profiling {
        ctx.start_profile();
    }
    let mut lap = Lap::new(ctx, profiling);
    // Statistics are gathered from the step after one densification up to the next.
    let dc = &config.densify;
    let densifying = |step: u32| dc.every > 0 && step < dc.until.min(config.steps.saturating_sub(1));
    for step in start_step..stop_at {
        wait_for_signal_if_asked(step, interrupt);
        // A signal arrived during the step before: its state is complete, so it is
        // checkpointed here and the run stops, resumable.
        if interrupt.load(Ordering::SeqCst) {
            save(&mut avatar, &refiner, step, &checkpoint_path)?;
            return Ok(Outcome::Interrupted { step });
        }
        let waits_before = ctx.fence_waits();
        lap.reset();
        let s = step::sample(&train_frames, &rig, refiner.as_ref(), config.seed, step, whole_image);
        lap.host("host.frame_setup");
        let mut attempts = 0;
        let outcome = loop {
            attempts += 1;
            let mut st = Stages { avatar: &mut avatar, renderer: &mut renderer, cloth_losses: cloth_losses.as_mut(), image_losses: &mut image_losses, settings: &settings, pose_gradient: refiner.is_some(), screen_stats: densifying(step), masked: !whole_image };
            match step::run(ctx, &mut st, &mut buffers, &s)? {
                StepOutcome::Overflowed => continue,
                done => break done,
            }
        };
        lap.reset();
        if let StepOutcome::Skipped { nonfinite } = outcome {
            let line = serde_json::json!({ "step": step, "frame": s.frame.frame, "skipped": true, "nonfinite_gradients": nonfinite });
            writeln!(log, "{line}").map_err(|e| TrainerError::io(&log_path, e))?;
            skips.skipped(step, nonfinite, s.frame.frame, &seq.dir, &checkpoint_path)?;
            waits.add(ctx.fence_waits() - waits_before, attempts, false);
            continue;
        }
        skips.applied();
        if let Some(r) = refiner.as_mut() {
            if let Some(line) = refine_pose(ctx, &mut avatar, &rig, r, &s, step)? {
                writeln!(log, "{line}").map_err(|e| TrainerError::io(&log_path, e))?;
            }
        }
        lap.host("host.pose_gradient");
        let logging = step % config.log_every.max(1) == 0 || step + 1 == stop_at;
        if logging {
            let seconds = t_train.elapsed().as_secs_f64();
            let (line, l1, psnr) = log_line(ctx, &mut image_losses, cloth_losses.as_mut(), &avatar, refiner.as_ref(), step, s.frame.frame, seconds)?;
            writeln!(log, "{line}").map_err(|e| TrainerError::io(&log_path, e))?;
            let it_per_s = f64::from(step + 1 - start_step) / seconds.max(1e-9);
            progress(Progress::Step { step: step + 1, total: config.steps, l1, psnr, it_per_s });
        }
        lap.host("host.log");
        let densified = dc.due(step + 1) && step + 1 < config.steps;
        if densified {
            let (summaries, counts) = densify_layers(ctx, &mut avatar, config, step, s.transforms.log_scale)?;
            renderer = AvatarRenderer::new(ctx, &avatar, width, height, config.compositing)?;
            if let (Some(c), Some(cloth)) = (cloth_losses.as_mut(), avatar.cloth()) {
                c.resize(ctx, cloth)?;
                c.set_mask_in_composite(renderer.is_three_pass());
            }
            let line = serde_json::json!({ "step": step, "densify": summaries });
            writeln!(log, "{line}").map_err(|e| TrainerError::io(&log_path, e))?;
            progress(Progress::Densify { step: step + 1, counts });
            lap.host("host.densify");
        }
        let checkpointing = config.checkpoint_every > 0 && (step + 1) % config.checkpoint_every == 0 && step + 1 < stop_at;
        if checkpointing {
            save(&mut avatar, &refiner, step + 1, &checkpoint_path)?;
        }
        waits.add(ctx.fence_waits() - waits_before, attempts, !(logging || densified || checkpointing));
    }
    let loop_seconds = t_train.elapsed().as_secs_f64();
    let profile = if profiling { ctx.take_profile() } else { None };
    if let Some(p) = &profile {
        let steps = u64::from(stop_at.saturating_sub(start_step));
        let table = format!("{steps} steps in {loop_seconds:.2} s ({:.1} ms/step); shares are of that wall time\n{}\n{}", 1e3 * loop_seconds / steps.max(1) as f64, waits.summary(), p.table(1e3 * loop_seconds, steps, 25));
        let path = out.join("profile.txt");
        std::fs::write(&path, &table).map_err(|e| TrainerError::io(&path, e))?;
        write_json(&out.join("profile.json"), p)?;
    }
    let last = stop_at.max(start_step);
    save(&mut avatar, &refiner, last, &checkpoint_path)?;
    if interrupt.load(Ordering::SeqCst) {
        return Ok(Outcome::Interrupted { step: last });
    }
    save(&mut avatar, &refiner, last, &out.join("model.npz"))?;
    let train_seconds = t_train.elapsed().as_secs_f64();
    let eval_dir = out.join("eval");
    let (fin, per_frame) = evaluate(ctx, &mut avatar, &mut renderer, &eval_inputs(Some(&eval_dir)), progress)?;
    write_reports(&eval_dir, &format!("{} after {last} steps, {} held-out images of {}", out.display(), per_frame.len(), seq.dir.display()), &fin, &per_frame)?;
    // The posed body of the first held-out frame as a standard 3DGS PLY.
    if let Some(f) = test_frames.first() {
        let ft = rig.frame(&f.body);
        avatar.set_frame(ctx, &ft)?;
        {
            let mut rec = ctx.record("export forward")?;
            avatar.record_forward(&mut rec, ft.log_scale)?;
            rec.submit_and_wait()?;
        }
        let cloud = avatar.read_posed(ctx)?;
        // One standard 3DGS PLY per layer.
        for layer in [Layer::Body, Layer::Cloth] {
            let mut part = drape_engine::ops::splat::scene::GaussianCloud::new(cloud.sh_degree);
            for i in (0..cloud.len()).filter(|&i| cloud.groups[i] == layer.group()) {
                part.push(&cloud.gaussian::<f32>(i), layer);
            }
            if !part.is_empty() {
                let name = if layer == Layer::Body { "body" } else { "cloth" };
                let path = out.join(format!("{name}_frame{:04}.ply", f.frame));
                ply::write(&path, &part)?;
            }
        }
    }
    // A novel pose (the procedural raise-arms motion, halfway) on the first held-out
    // frame's root, translation and camera.
    if let Some(f) = test_frames.first() {
        let motion = crate::motion::procedural(crate::motion::MotionKind::RaiseArms, 30, 30.0, 1.0);
        let novel = &motion.poses[15];
        let body = match &f.body {
            BodyParams::Smpl { pose, betas, translation, scale } => {
                let mut p = *pose;
                p[1..].copy_from_slice(&novel[1..]);
                BodyParams::Smpl { pose: p, betas: betas.clone(), translation: *translation, scale: *scale }
            }
            BodyParams::Zju(z) => {
                let mut z = z.clone();
                for j in 1..24 {
                    z.poses[3 * j..3 * j + 3].copy_from_slice(&novel[j]);
                }
                BodyParams::Zju(z)
            }
        };
        let ft = rig.frame(&body);
        avatar.set_frame(ctx, &ft)?;
        {
            let mut rec = ctx.record("novel pose forward")?;
            avatar.record_forward(&mut rec, ft.log_scale)?;
            rec.submit_and_wait()?;
        }
        renderer.forward(ctx, &avatar, &f.camera.to_pinhole([0.0; 3]), &settings)?;
        let rgb = renderer.read_rgb(ctx)?;
        crate::dataset::image::write_rgb(&out.join("novel_pose.png"), width, height, &rgb)?;
    }
    let report = TrainReport {
        layout: seq.layout,
        gaussians: avatar.counts(),
        fit_steps: total_fit,
        fit_mse,
        fit_seconds,
        start_step,
        steps: stop_at,
        train_seconds,
        iterations_per_second: f64::from(stop_at.saturating_sub(start_step)) / train_seconds.max(1e-9),
        skipped_steps: skips.total,
        host_waits: waits,
        initial,
        fin,
    };
    write_json(&out.join("metrics.json"), &report)?;
    if stop_at == config.steps {
        let marker = out.join(COMPLETE_MARKER);
        std::fs::write(&marker, format!("finished {} steps\n", config.steps)).map_err(|e| TrainerError::io(&marker, e))?;
        let _ = std::fs::remove_file(out.join(INCOMPLETE_MARKER));
    }
    Ok(Outcome::Finished(Box::new(report)))
}
