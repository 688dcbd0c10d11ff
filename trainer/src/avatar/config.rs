//! A training run's configuration: [`TrainConfig`] (the run directory's `config.json`),
//! its presets, the limits it is checked against, and JSON overrides laid onto a preset.

use std::path::{Path, PathBuf};

use drape_engine::ops::lpips::LpipsNet;

use crate::avatar::composite::Compositing;
use crate::avatar::densify::DensifyConfig;
use crate::avatar::layer::LayerConfig;
use crate::avatar::model::LayerChoice;
use crate::avatar::scene::SceneConfig;
use crate::error::TrainerError;
use crate::garment::GarmentFit;

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
