//! A training run's configuration: [`TrainConfig`] (the run directory's `config.json`)
//! in its groups (the layers, the losses, the schedule, densification), its presets, the
//! limits it is checked against, JSON overrides laid onto a preset, and the reading of
//! the flat layout that came before the groups ([`migrate_flat_layout`], [`FLAT_KEYS`]).

use std::path::{Path, PathBuf};

use drape_engine::ops::lpips::LpipsNet;

use crate::avatar::composite::Compositing;
use crate::avatar::densify::DensifyConfig;
use crate::avatar::layer::LayerConfig;
use crate::avatar::model::LayerChoice;
use crate::avatar::scene::SceneConfig;
use crate::dataset::split::CameraSplit;
use crate::error::TrainerError;
use crate::garment::GarmentFit;

/// Everything a run is configured by (written to the run directory as `config.json`), in
/// groups: the avatar's layers, the losses, the schedule and densification, beside the
/// few settings of the run as a whole. A `config.json` of the flat layout that came
/// before the groups still reads (see [`migrate_flat_layout`]).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    pub preset: Preset,
    /// Seeds the layers' initial networks and each step's frame and background.
    pub seed: u64,
    /// Bit-identical runs: the splat and triplane backward passes accumulate in
    /// 64-bit fixed point instead of float atomics (whose order, and so last bits,
    /// changes from run to run), so a resumed run ends where an uninterrupted one does.
    /// Costs two integer atomics per value and gradients rounded to 2^-36.
    #[serde(default)]
    pub deterministic: bool,
    /// ZJU-MoCap: the training camera's index (every other camera is held out).
    pub zju_train_camera: usize,
    /// ZJU-MoCap: several training cameras, e.g. `[0, 1, 2]` (replaces
    /// `zju_train_camera` when given).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub zju_train_cameras: Vec<usize>,
    /// ZJU-MoCap: the held-out cameras, e.g. `[3]`; empty: every camera that does not
    /// train. A camera in neither list is not loaded.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub zju_test_cameras: Vec<usize>,
    /// Which layers, their sizes and rates, and how they become one image.
    pub layers: LayersConfig,
    /// The losses' weights.
    pub losses: LossesConfig,
    /// How long, how fast and how often: steps, the skinning fit, logging,
    /// checkpoints, the non-finite guard and pose refinement.
    pub schedule: ScheduleConfig,
    /// Densification and pruning of every layer (`densify`; HUGS's schedule and
    /// thresholds in the paper preset). Missing from a config file: off.
    #[serde(default = "DensifyConfig::off")]
    pub densify: DensifyConfig,
}

/// The avatar's layers (`layers` in a config): which, each one's sizes and rates, the
/// meshes they start from, and their compositing.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LayersConfig {
    /// `auto` (a cloth layer where the data has garment masks, a scene layer where it
    /// has scene points), or `body` joined by `+` with `cloth` and/or `scene`: `body`
    /// is the single-layer baseline (cloth folded into the body, as HUGS).
    pub choice: LayerChoice,
    /// Midpoint subdivisions of the body mesh for the body layer's Gaussians (0-2).
    pub subdivision: u32,
    /// Keep every n-th of the body's (and the garments') Gaussians (1: all), each
    /// widened by √n in the surface plane so the body stays covered: for tests and
    /// quick looks. The simulation loss's targets are thinned the same.
    pub decimate: u32,
    pub body: LayerConfig,
    pub cloth: LayerConfig,
    /// The T-shirt the cloth layer is made of and simulated with: `tight` or `loose`
    /// (`drape synth --fit`); on synthetic data, the one the data was made with.
    /// Missing from a config file: tight.
    #[serde(default)]
    pub cloth_fit: GarmentFit,
    /// The scene layer (plain 3DGS from the sparse points), where there is one.
    pub scene: SceneConfig,
    /// How the layers become one image where there is a cloth layer: `three-pass` (the
    /// paper's: body + scene, cloth and a matte in which only the scene hides the cloth,
    /// composited), `three-pass-occlusion` (the body hides the cloth in the matte too),
    /// `fused` / `fused-occlusion` (the same images and gradients from one sort and one
    /// walk of every layer) or `single-pass` (every layer in one depth-sorted pass).
    #[serde(default = "paper_compositing")]
    pub compositing: Compositing,
}

/// The losses' weights (`losses` in a config).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LossesConfig {
    /// Image loss `λ_l1 L1 + λ_ssim (1 - SSIM)` (paper: 0.8, 0.2).
    pub lambda_l1: f32,
    pub lambda_ssim: f32,
    /// Weight of LPIPS in the image loss (paper: 1.0).
    pub lambda_lpips: f32,
    /// LPIPS weights (a safetensors file from `scripts/lpips-to-safetensors.py`):
    /// with them LPIPS joins the image loss and the metrics; without, it is left out
    /// and reported as n/a.
    pub lpips_weights: Option<PathBuf>,
    /// `alex` (the metric HUGS reports) or `vgg`.
    pub lpips_net: LpipsNet,
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
}

/// How long, how fast and how often (`schedule` in a config).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScheduleConfig {
    /// Optimisation steps after the skinning-weight fit.
    pub steps: u32,
    /// Adam steps fitting the deformation decoder to the body's skinning weights, and
    /// their rate.
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
        let human = LayerConfig {
            triplane_resolution: 64,
            triplane_channels: 16,
            decoder_width: 64,
            ..LayerConfig::default()
        };
        Self {
            preset: Preset::Quick,
            seed: 1,
            deterministic: false,
            zju_train_camera: 0,
            zju_train_cameras: Vec::new(),
            zju_test_cameras: Vec::new(),
            layers: LayersConfig {
                choice: LayerChoice::AUTO,
                subdivision: 0,
                decimate: 6,
                body: human.clone(),
                cloth: human,
                cloth_fit: GarmentFit::Tight,
                // SH degree 0 for the scene too: 3DGS raises its scene's degree one step
                // every 1,000 iterations, so within 400 it would still be at 0.
                scene: SceneConfig {
                    sh_degree: 0,
                    ..SceneConfig::default()
                },
                compositing: paper_compositing(),
            },
            losses: LossesConfig {
                lambda_l1: 0.8,
                lambda_ssim: 0.2,
                lambda_lpips: 1.0,
                lpips_weights: None,
                lpips_net: LpipsNet::Alex,
                lambda_cloth_lbs: 1000.0,
                lambda_sim: 1.0,
                gm_sigma: drape_shared::cloth_loss::GM_SIGMA_DEFAULT,
                lambda_arap: 0.5,
                lambda_mask: 1.0,
            },
            schedule: ScheduleConfig {
                steps: 400,
                fit_steps: 150,
                fit_lr: 3e-3,
                log_every: 25,
                checkpoint_every: 200,
                max_skipped_steps: 10,
                refine_pose: true,
                lr_pose: hugs_pose_rate(),
                lr_translation: hugs_pose_rate(),
            },
            // HUGS densifies every 600 steps from 15% to 75% of its 20k; here after 100
            // and 200 of 400, at most 4,096 per layer, to keep the quick run short on
            // lavapipe (docs/performance.md has its time with a third densification, to
            // 8,192); no size prunes within the run (3DGS starts them at 3,000 steps).
            densify: DensifyConfig {
                every: 100,
                from: 100,
                until: 200,
                max_gaussians: 4096,
                ..DensifyConfig::default()
            },
        }
    }

    /// The paper's setting (for a GPU): two subdivisions, 256 × 256 × 32 triplanes,
    /// 20k steps; SH degree 0 for the human layers (HUGS's code) and 3 for the scene
    /// (3DGS; here from the first step, without 3DGS's one-degree-per-1,000 ramp).
    pub fn paper() -> Self {
        let quick = Self::quick();
        Self {
            preset: Preset::Paper,
            layers: LayersConfig {
                subdivision: 2,
                decimate: 1,
                body: LayerConfig::default(),
                cloth: LayerConfig::default(),
                scene: SceneConfig::default(),
                ..quick.layers
            },
            schedule: ScheduleConfig {
                steps: 20_000,
                fit_steps: 3000,
                fit_lr: 1e-3,
                log_every: 100,
                checkpoint_every: 1000,
                ..quick.schedule
            },
            densify: DensifyConfig::default(),
            ..quick
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
    /// `drape train --config`), in the grouped layout or the flat one before it
    /// ([`migrate_flat_layout`]), and validates it. A bad value names its key in the
    /// grouped layout (`layers.body.triplane_resolution`, `layers.compositing`) and, for
    /// a choice, the values it takes; a key given twice in one table is refused.
    pub fn from_deserializer<'de, D: serde::Deserializer<'de>>(d: D) -> crate::Result<Self> {
        let keyed = |key: String, problem: String| {
            TrainerError::config(
                if key == "." {
                    "(top level)".to_string()
                } else {
                    key
                },
                problem,
            )
        };
        let StrictValue(mut json) = serde_path_to_error::deserialize(d)
            .map_err(|e| keyed(e.path().to_string(), e.into_inner().to_string()))?;
        migrate_flat_layout(&mut json)?;
        let c: Self = serde_path_to_error::deserialize(json)
            .map_err(|e| keyed(e.path().to_string(), e.into_inner().to_string()))?;
        c.validate()?;
        Ok(c)
    }

    /// This config with the TOML document `text` (from `file`) laid over it: every key
    /// must be one of the config's (an optional one such as `losses.lpips_weights`
    /// included) and keep its type (an integer may stand for a float); the result is
    /// validated. The keys of the flat layout (`steps`, `[body]`) still name theirs in
    /// the groups (`schedule.steps`, `[layers.body]`; [`migrate_flat_layout`]). Errors
    /// name the file and the key in the grouped layout.
    pub fn with_toml(&self, text: &str, file: &Path) -> crate::Result<Self> {
        let in_file = |e: TrainerError| match e {
            TrainerError::Config { key, problem } => TrainerError::Config {
                key: format!("{}: {key}", file.display()),
                problem,
            },
            other => other,
        };
        let mut over: serde_json::Value = toml::from_str(text).map_err(|e| {
            TrainerError::config(file.display().to_string(), e.message().to_string())
        })?;
        migrate_flat_layout(&mut over).map_err(in_file)?;
        let mut base = serde_json::to_value(self)
            .map_err(|e| TrainerError::config("(top level)", e.to_string()))?;
        // Left out of config.json while empty (so that older runs' files stay as they
        // were), but a file may set them.
        if let Some(top) = base.as_object_mut() {
            for key in ["zju_train_cameras", "zju_test_cameras"] {
                top.entry(key).or_insert_with(|| serde_json::json!([]));
            }
        }
        merge_json(&mut base, &over, "").map_err(in_file)?;
        Self::from_deserializer(base).map_err(in_file)
    }

    /// Checks values a config file could get wrong, naming the field.
    pub fn validate(&self) -> crate::Result<()> {
        let bad = |key: &str, problem: String| Err(TrainerError::config(key, problem));
        let (layers, losses, schedule) = (&self.layers, &self.losses, &self.schedule);
        // Each triplane is 3 x resolution² x channels f32 values, with Adam's two moments
        // beside it: bounded so that a typo cannot ask for terabytes.
        for (layer, t) in [
            ("layers.body", &layers.body),
            ("layers.cloth", &layers.cloth),
        ] {
            if !(2..=MAX_TRIPLANE_RESOLUTION).contains(&t.triplane_resolution) {
                return bad(
                    &format!("{layer}.triplane_resolution"),
                    format!(
                        "must be 2-{MAX_TRIPLANE_RESOLUTION} (HUGS: 128), got {}",
                        t.triplane_resolution
                    ),
                );
            }
            if !(1..=MAX_TRIPLANE_CHANNELS).contains(&t.triplane_channels) {
                return bad(
                    &format!("{layer}.triplane_channels"),
                    format!(
                        "must be 1-{MAX_TRIPLANE_CHANNELS} (HUGS: 32), got {}",
                        t.triplane_channels
                    ),
                );
            }
        }
        for (name, v, max) in [
            ("schedule.steps", schedule.steps, MAX_STEPS),
            ("schedule.fit_steps", schedule.fit_steps, MAX_STEPS),
        ] {
            if v > max {
                return bad(name, format!("must be at most {max}, got {v}"));
            }
        }
        let rates = [
            ("layers.cloth.lr_position", layers.cloth.lr_position),
            ("layers.cloth.lr_triplane", layers.cloth.lr_triplane),
            ("layers.cloth.lr_decoders", layers.cloth.lr_decoders),
            ("layers.cloth.lr_deformation", layers.cloth.lr_deformation),
            ("losses.lambda_cloth_lbs", losses.lambda_cloth_lbs),
            ("losses.lambda_sim", losses.lambda_sim),
            ("losses.lambda_arap", losses.lambda_arap),
            ("losses.lambda_mask", losses.lambda_mask),
            ("layers.body.lr_position", layers.body.lr_position),
            ("layers.body.lr_triplane", layers.body.lr_triplane),
            ("layers.body.lr_decoders", layers.body.lr_decoders),
            ("layers.body.lr_deformation", layers.body.lr_deformation),
            ("schedule.fit_lr", schedule.fit_lr),
            ("losses.lambda_l1", losses.lambda_l1),
            ("losses.lambda_ssim", losses.lambda_ssim),
            ("losses.lambda_lpips", losses.lambda_lpips),
            ("schedule.lr_pose", schedule.lr_pose),
            ("schedule.lr_translation", schedule.lr_translation),
            ("layers.scene.lr_position", layers.scene.lr_position),
            (
                "layers.scene.lr_position_final",
                layers.scene.lr_position_final,
            ),
            ("layers.scene.lr_rotation", layers.scene.lr_rotation),
            ("layers.scene.lr_scale", layers.scene.lr_scale),
            ("layers.scene.lr_opacity", layers.scene.lr_opacity),
            ("layers.scene.lr_sh", layers.scene.lr_sh),
        ];
        for (name, v) in rates {
            if !(v.is_finite() && v >= 0.0) {
                return bad(name, format!("must be a finite rate >= 0, got {v}"));
            }
        }
        self.densify.validate()?;
        if !(losses.gm_sigma.is_finite() && losses.gm_sigma > 0.0) {
            return bad(
                "losses.gm_sigma",
                format!("must be a finite length > 0, got {}", losses.gm_sigma),
            );
        }
        if layers.decimate == 0 {
            return bad("layers.decimate", "must be >= 1".into());
        }
        if schedule.log_every == 0 {
            return bad(
                "schedule.log_every",
                "must be >= 1 (steps between log lines)".into(),
            );
        }
        if layers.scene.max_points == 0 {
            return bad("layers.scene.max_points", "must be >= 1".into());
        }
        if losses
            .lpips_weights
            .as_ref()
            .is_some_and(|p| p.as_os_str().is_empty())
        {
            return bad(
                "losses.lpips_weights",
                "is empty; leave the key out to train without LPIPS".into(),
            );
        }
        if layers.subdivision > 2 {
            return bad(
                "layers.subdivision",
                format!("must be 0, 1 or 2, got {}", layers.subdivision),
            );
        }
        for (name, degree) in [
            ("layers.body.sh_degree", layers.body.sh_degree),
            ("layers.cloth.sh_degree", layers.cloth.sh_degree),
            ("layers.scene.sh_degree", layers.scene.sh_degree),
        ] {
            if degree > 3 {
                return bad(name, format!("must be 0-3, got {degree}"));
            }
        }
        for (name, w) in [
            ("layers.body.decoder_width", layers.body.decoder_width),
            ("layers.cloth.decoder_width", layers.cloth.decoder_width),
        ] {
            if !(1..=1024).contains(&w) {
                return bad(name, format!("must be 1-1024 (HUGS: 128), got {w}"));
            }
        }
        Ok(())
    }
}

/// Where each key of the flat layout lives in the grouped one: (flat key, group, key in
/// the group). Before the groups, `config.json` held every setting at its top level;
/// the keys not listed here (`preset`, `seed`, `deterministic`, `zju_train_camera`,
/// `densify`) are where they were. The flat `layers` (the layer choice, a string) is
/// `layers.choice`; the group `layers` is a table.
pub const FLAT_KEYS: [(&str, &str, &str); 27] = [
    ("layers", "layers", "choice"),
    ("subdivision", "layers", "subdivision"),
    ("decimate", "layers", "decimate"),
    ("body", "layers", "body"),
    ("cloth", "layers", "cloth"),
    ("cloth_fit", "layers", "cloth_fit"),
    ("scene", "layers", "scene"),
    ("compositing", "layers", "compositing"),
    ("lambda_l1", "losses", "lambda_l1"),
    ("lambda_ssim", "losses", "lambda_ssim"),
    ("lambda_lpips", "losses", "lambda_lpips"),
    ("lpips_weights", "losses", "lpips_weights"),
    ("lpips_net", "losses", "lpips_net"),
    ("lambda_cloth_lbs", "losses", "lambda_cloth_lbs"),
    ("lambda_sim", "losses", "lambda_sim"),
    ("gm_sigma", "losses", "gm_sigma"),
    ("lambda_arap", "losses", "lambda_arap"),
    ("lambda_mask", "losses", "lambda_mask"),
    ("steps", "schedule", "steps"),
    ("fit_steps", "schedule", "fit_steps"),
    ("fit_lr", "schedule", "fit_lr"),
    ("log_every", "schedule", "log_every"),
    ("checkpoint_every", "schedule", "checkpoint_every"),
    ("max_skipped_steps", "schedule", "max_skipped_steps"),
    ("refine_pose", "schedule", "refine_pose"),
    ("lr_pose", "schedule", "lr_pose"),
    ("lr_translation", "schedule", "lr_translation"),
];

/// Moves the keys of the flat layout in `config` (a whole config or an override, as
/// JSON) into their groups ([`FLAT_KEYS`]), so that a run's `config.json` written
/// before the groups, and a `--config` file written for it, read as they did. A
/// document already grouped is left as it is; one that mixes the layouts is moved
/// key by key, and a key given in both (`decimate` beside `layers.decimate`) is an
/// error naming both. Nothing is written back: a config is always saved grouped.
pub fn migrate_flat_layout(config: &mut serde_json::Value) -> crate::Result<()> {
    use serde_json::Value;
    // Not a table: deserialising it names the problem.
    let Some(top) = config.as_object_mut() else {
        return Ok(());
    };
    for (flat, group, key) in FLAT_KEYS {
        match top.get(flat) {
            None => continue,
            // The group `layers`, not the flat layer choice.
            Some(Value::Object(_)) if flat == group => continue,
            Some(_) => {}
        }
        let value = top.remove(flat).expect("the key is there");
        let slot = top
            .entry(group)
            .or_insert_with(|| Value::Object(serde_json::Map::new()));
        let Some(table) = slot.as_object_mut() else {
            return Err(TrainerError::config(
                group,
                format!("must be a table (it holds `{key}`, given as `{flat}` in the flat layout)"),
            ));
        };
        if table.contains_key(key) {
            return Err(TrainerError::config(format!("{group}.{key}"), format!("is given twice: as `{group}.{key}` and as `{flat}` (the flat layout before the groups)")));
        }
        table.insert(key.to_string(), value);
    }
    Ok(())
}

/// A JSON value read from any serde format that refuses a key given twice in one table,
/// as the config's structs do when read directly (a [`serde_json::Value`] would keep
/// the last). What [`TrainConfig::from_deserializer`] reads before moving flat keys
/// into their groups.
struct StrictValue(serde_json::Value);

impl<'de> serde::Deserialize<'de> for StrictValue {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        d.deserialize_any(StrictVisitor).map(StrictValue)
    }
}

struct StrictVisitor;

impl<'de> serde::de::Visitor<'de> for StrictVisitor {
    type Value = serde_json::Value;

    fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("a config value")
    }

    fn visit_bool<E>(self, v: bool) -> Result<Self::Value, E> {
        Ok(v.into())
    }

    fn visit_i64<E>(self, v: i64) -> Result<Self::Value, E> {
        Ok(v.into())
    }

    fn visit_u64<E>(self, v: u64) -> Result<Self::Value, E> {
        Ok(v.into())
    }

    fn visit_f64<E: serde::de::Error>(self, v: f64) -> Result<Self::Value, E> {
        serde_json::Number::from_f64(v)
            .map(serde_json::Value::Number)
            .ok_or_else(|| E::custom(format!("{v} is not a finite number")))
    }

    fn visit_str<E>(self, v: &str) -> Result<Self::Value, E> {
        Ok(v.into())
    }

    fn visit_none<E>(self) -> Result<Self::Value, E> {
        Ok(serde_json::Value::Null)
    }

    fn visit_unit<E>(self) -> Result<Self::Value, E> {
        Ok(serde_json::Value::Null)
    }

    fn visit_some<D: serde::Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
        d.deserialize_any(self)
    }

    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
        let mut items = Vec::new();
        while let Some(StrictValue(v)) = seq.next_element()? {
            items.push(v);
        }
        Ok(items.into())
    }

    fn visit_map<A: serde::de::MapAccess<'de>>(self, mut map: A) -> Result<Self::Value, A::Error> {
        let mut table = serde_json::Map::new();
        while let Some(key) = map.next_key::<String>()? {
            if table.contains_key(&key) {
                return Err(serde::de::Error::custom(format!("duplicate field `{key}`")));
            }
            let StrictValue(v) = map.next_value()?;
            table.insert(key, v);
        }
        Ok(table.into())
    }
}

/// Largest triplane side and channel count a config may ask for (HUGS: 128 and 32).
pub const MAX_TRIPLANE_RESOLUTION: u32 = 1024;
pub const MAX_TRIPLANE_CHANNELS: u32 = 256;
/// Largest step counts (the paper trains 3,000 steps per sequence).
pub const MAX_STEPS: u32 = 10_000_000;

/// Lays `over` onto `base` (JSON values), naming the first key `base` lacks or whose
/// type `over` changes. A `null` in `base` (an unset option) takes any value.
fn merge_json(
    base: &mut serde_json::Value,
    over: &serde_json::Value,
    path: &str,
) -> crate::Result<()> {
    use serde_json::Value;
    match (base, over) {
        (Value::Object(b), Value::Object(o)) => {
            for (k, v) in o {
                let key = if path.is_empty() {
                    k.clone()
                } else {
                    format!("{path}.{k}")
                };
                match b.get_mut(k) {
                    Some(slot) => merge_json(slot, v, &key)?,
                    None => {
                        return Err(TrainerError::config(
                            key,
                            "unknown key (a run's config.json lists every key but the empty zju_train_cameras and zju_test_cameras)",
                        ))
                    }
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
                return Err(TrainerError::config(
                    path,
                    format!("must be {}, got {}", kind(b), kind(o)),
                ));
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
            other => Err(TrainerError::config(
                "preset",
                format!("unknown preset '{other}' (quick, paper)"),
            )),
        }
    }
}

impl std::fmt::Display for Preset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl TrainConfig {
    /// A ZJU-MoCap sequence's training and held-out cameras: `zju_train_cameras` and
    /// `zju_test_cameras` where given, else `zju_train_camera` and every other.
    pub fn camera_split(&self) -> CameraSplit {
        CameraSplit {
            train: if self.zju_train_cameras.is_empty() {
                vec![self.zju_train_camera]
            } else {
                self.zju_train_cameras.clone()
            },
            test: (!self.zju_test_cameras.is_empty()).then(|| self.zju_test_cameras.clone()),
        }
    }

    /// Reads a run's `config.json` (for `--resume`), naming the file on any problem.
    pub fn read_run(dir: &Path) -> crate::Result<Self> {
        let path = dir.join("config.json");
        let text = std::fs::read_to_string(&path).map_err(|e| TrainerError::io(&path, e))?;
        let mut json = serde_json::Deserializer::from_str(&text);
        Self::from_deserializer(&mut json).map_err(|e| match e {
            TrainerError::Config { key, problem } => TrainerError::Config {
                key: format!("{}: {key}", path.display()),
                problem,
            },
            other => other,
        })
    }
}
