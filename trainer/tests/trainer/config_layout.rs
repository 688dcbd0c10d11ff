//! The run configuration's grouped layout (`layers`, `losses`, `schedule`, `densify`) and
//! the flat one before it: a `config.json` that `drape train` wrote before the groups
//! (`trainer/tests/fixtures/flat-config-*`, written at 860a1e7) reads with each value
//! where the groups put it (`TrainConfig::read_run`, what `drape train --resume`,
//! `eval`, `animate` and `edit` call), is written back grouped only, and `--config`
//! overrides in either layout give the same config.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use drape_engine::ops::lpips::LpipsNet;
use drape_trainer::avatar::composite::Compositing;
use drape_trainer::avatar::config::{LossesConfig, Preset, ScheduleConfig, TrainConfig, FLAT_KEYS};
use drape_trainer::avatar::densify::DensifyConfig;
use drape_trainer::avatar::layer::LayerConfig;
use drape_trainer::avatar::model::LayerChoice;
use drape_trainer::avatar::scene::SceneConfig;
use drape_trainer::garment::GarmentFit;
use drape_trainer::TrainerError;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn config_error(e: TrainerError) -> (String, String) {
    match e {
        TrainerError::Config { key, problem } => (key, problem),
        other => panic!("expected a config error, got {other:?}"),
    }
}

#[test]
fn a_flat_config_json_written_before_the_groups_reads_with_its_values_in_the_groups() {
    let dir = fixture("flat-config-tiny");
    let text = std::fs::read_to_string(dir.join("config.json")).unwrap();
    assert!(
        text.contains("\"lambda_sim\": 0.5") && !text.contains("\"schedule\""),
        "the fixture is of the flat layout"
    );
    let c = TrainConfig::read_run(&dir).expect("a flat config.json reads");
    // The values of the fixture's train.toml (and --deterministic), key by key.
    assert_eq!(c.preset, Preset::Quick);
    assert_eq!(c.seed, 7);
    assert!(c.deterministic);
    assert_eq!(c.zju_train_camera, 1);
    assert_eq!(c.layers.choice, LayerChoice::parse("body+cloth").unwrap());
    assert_eq!((c.layers.subdivision, c.layers.decimate), (0, 8));
    let body = LayerConfig {
        triplane_resolution: 8,
        triplane_channels: 2,
        sh_degree: 0,
        lr_position: 1.6e-4,
        lr_triplane: 2e-3,
        lr_decoders: 1e-3,
        lr_deformation: 1e-4,
        decoder_width: 16,
        pose_offsets: false,
        weight_norm: true,
    };
    assert_eq!(c.layers.body, body);
    let cloth = LayerConfig {
        triplane_resolution: 12,
        triplane_channels: 3,
        sh_degree: 1,
        lr_position: 1.6e-4,
        lr_triplane: 1e-3,
        lr_decoders: 1e-3,
        lr_deformation: 3e-4,
        decoder_width: 24,
        pose_offsets: true,
        weight_norm: true,
    };
    assert_eq!(c.layers.cloth, cloth);
    assert_eq!(c.layers.cloth_fit, GarmentFit::Loose);
    let scene = SceneConfig {
        lr_position: 1.6e-4,
        lr_position_final: 1.6e-6,
        lr_rotation: 1e-3,
        lr_scale: 5e-3,
        lr_opacity: 5e-2,
        lr_sh: 1e-3,
        max_points: 500,
        sh_degree: 0,
    };
    assert_eq!(c.layers.scene, scene);
    assert_eq!(c.layers.compositing, Compositing::parse("fused").unwrap());
    let losses = LossesConfig {
        lambda_l1: 0.7,
        lambda_ssim: 0.3,
        lambda_lpips: 0.5,
        lpips_weights: None,
        lpips_net: LpipsNet::Vgg16,
        lambda_cloth_lbs: 500.0,
        lambda_sim: 0.5,
        gm_sigma: 0.03,
        lambda_arap: 0.25,
        lambda_mask: 0.75,
    };
    assert_eq!(c.losses, losses);
    let schedule = ScheduleConfig {
        steps: 4,
        fit_steps: 2,
        fit_lr: 2e-3,
        log_every: 2,
        checkpoint_every: 3,
        max_skipped_steps: 5,
        refine_pose: false,
        lr_pose: 2e-4,
        lr_translation: 3e-4,
    };
    assert_eq!(c.schedule, schedule);
    assert_eq!(
        c.densify,
        DensifyConfig {
            every: 2,
            from: 2,
            until: 3,
            max_gaussians: 3000,
            ..DensifyConfig::default()
        }
    );

    // Written again (as `drape edit` and a new run write it), it is grouped only, and
    // reads back the same.
    let json = serde_json::to_value(&c).unwrap();
    let top: BTreeSet<&str> = json
        .as_object()
        .unwrap()
        .keys()
        .map(String::as_str)
        .collect();
    assert_eq!(
        top,
        BTreeSet::from([
            "deterministic",
            "densify",
            "layers",
            "losses",
            "preset",
            "schedule",
            "seed",
            "zju_train_camera"
        ])
    );
    assert_eq!(TrainConfig::from_deserializer(json).unwrap(), c);
}

#[test]
fn the_quick_presets_flat_config_json_reads_as_the_quick_preset() {
    // Every one of the flat layout's 32 keys, as the quick preset had them.
    let c = TrainConfig::read_run(&fixture("flat-config-quick")).expect("a flat config.json reads");
    let mut quick = TrainConfig::quick();
    quick.schedule.steps = 1; // `--steps 1`
    assert_eq!(c, quick);
    let flat: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(fixture("flat-config-quick/config.json")).unwrap(),
    )
    .unwrap();
    let keys: BTreeSet<&str> = flat
        .as_object()
        .unwrap()
        .keys()
        .map(String::as_str)
        .collect();
    let moved: BTreeSet<&str> = FLAT_KEYS.iter().map(|&(k, _, _)| k).collect();
    let stayed = BTreeSet::from([
        "preset",
        "seed",
        "deterministic",
        "zju_train_camera",
        "densify",
    ]);
    assert_eq!(keys.len(), 32);
    assert_eq!(
        keys,
        &moved | &stayed,
        "FLAT_KEYS names every key of the flat layout that moved"
    );
}

#[test]
fn a_flat_config_json_without_the_later_keys_gets_their_defaults() {
    // Runs older than `compositing`, pose refinement, `deterministic`, `cloth_fit` and
    // `densify` lack those keys; they read as those runs trained.
    let mut flat: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(fixture("flat-config-tiny/config.json")).unwrap(),
    )
    .unwrap();
    for key in [
        "compositing",
        "refine_pose",
        "lr_pose",
        "lr_translation",
        "deterministic",
        "cloth_fit",
        "densify",
    ] {
        flat.as_object_mut().unwrap().remove(key).expect(key);
    }
    let c = TrainConfig::from_deserializer(flat).expect("an older flat config reads");
    assert_eq!(
        c.layers.compositing,
        Compositing::parse("three-pass").unwrap()
    );
    assert!(c.schedule.refine_pose);
    assert_eq!(
        (c.schedule.lr_pose, c.schedule.lr_translation),
        (1e-4, 1e-4)
    );
    assert!(!c.deterministic);
    assert_eq!(c.layers.cloth_fit, GarmentFit::Tight);
    assert_eq!(c.densify, DensifyConfig::off());
    assert_eq!(c.losses.lambda_sim, 0.5, "the other keys keep their values");
}

#[test]
fn overrides_in_the_flat_layout_give_what_the_grouped_keys_give() {
    let quick = TrainConfig::quick();
    let file = Path::new("c.toml");
    let flat = "steps = 12\nlambda_sim = 0.25\nlpips_weights = \"w.safetensors\"\nlayers = \"body+cloth\"\ncompositing = \"fused\"\ndecimate = 3\n[body]\ntriplane_resolution = 16\n[densify]\nevery = 3\n";
    let grouped = "[schedule]\nsteps = 12\n[losses]\nlambda_sim = 0.25\nlpips_weights = \"w.safetensors\"\n[layers]\nchoice = \"body+cloth\"\ncompositing = \"fused\"\ndecimate = 3\n[layers.body]\ntriplane_resolution = 16\n[densify]\nevery = 3\n";
    let a = quick.with_toml(flat, file).expect("flat keys");
    let b = quick.with_toml(grouped, file).expect("grouped keys");
    assert_eq!(a, b);
    assert_eq!(
        (
            b.schedule.steps,
            b.losses.lambda_sim,
            b.layers.decimate,
            b.layers.body.triplane_resolution,
            b.densify.every
        ),
        (12, 0.25, 3, 16, 3)
    );
    assert_eq!(
        b.losses.lpips_weights.as_deref(),
        Some(Path::new("w.safetensors"))
    );
    assert_eq!(b.layers.choice, LayerChoice::parse("body+cloth").unwrap());
    assert_eq!(b.layers.compositing, Compositing::parse("fused").unwrap());
    assert_eq!(
        b.layers.cloth, quick.layers.cloth,
        "what the file leaves out is the preset's"
    );

    // A key in both layouts, and a flat key whose group is not a table, name the grouped key.
    let (key, problem) = config_error(
        quick
            .with_toml("decimate = 2\n[layers]\ndecimate = 3\n", file)
            .unwrap_err(),
    );
    assert_eq!(key, "c.toml: layers.decimate");
    assert!(
        problem.contains("twice") && problem.contains("`decimate`"),
        "{problem}"
    );
    let (key, _) = config_error(
        quick
            .with_toml("losses = 3\nlambda_sim = 1.0\n", file)
            .unwrap_err(),
    );
    assert_eq!(key, "c.toml: losses");
    // A bad value of the flat layout is named by its grouped key.
    let (key, _) = config_error(
        quick
            .with_toml("[body]\ntriplane_resolution = 1\n", file)
            .unwrap_err(),
    );
    assert_eq!(key, "c.toml: layers.body.triplane_resolution");
}

#[test]
fn a_key_given_twice_in_a_config_json_is_refused() {
    // Read through a generic value first (to move the flat keys), a config.json still
    // refuses a duplicate key as the config's own structs do, naming where it is.
    let text = serde_json::to_string_pretty(&TrainConfig::quick()).unwrap();
    // (the key given twice, the table it is in, the text)
    let cases = [
        (
            "seed",
            "(top level)",
            text.replacen('{', "{\"seed\": 5,", 1),
        ),
        (
            "decimate",
            "layers",
            text.replacen("\"decimate\"", "\"decimate\": 2, \"decimate\"", 1),
        ),
    ];
    for (field, table, twice) in cases {
        let (key, problem) = config_error(
            TrainConfig::from_deserializer(&mut serde_json::Deserializer::from_str(&twice))
                .unwrap_err(),
        );
        assert_eq!(key, table, "{field}: {problem}");
        assert!(
            problem.contains(&format!("duplicate field `{field}`")),
            "{field}: {problem}"
        );
    }
    // The quick preset itself reads back.
    assert_eq!(
        TrainConfig::from_deserializer(&mut serde_json::Deserializer::from_str(&text)).unwrap(),
        TrainConfig::quick()
    );
}

/// Several training cameras and named held-out ones come from a config file; unset,
/// they are not written to `config.json` (older runs' files stay as they were) and the
/// split is `zju_train_camera` against every other camera.
#[test]
fn training_and_held_out_cameras_from_a_config_file() {
    use drape_trainer::dataset::split::CameraSplit;
    let quick = TrainConfig::preset(Preset::Quick);
    assert_eq!(quick.camera_split(), CameraSplit::from(0));
    let json = serde_json::to_string(&quick).unwrap();
    assert!(
        !json.contains("zju_train_cameras") && !json.contains("zju_test_cameras"),
        "{json}"
    );
    let c = quick
        .with_toml(
            "zju_train_cameras = [0, 2]\nzju_test_cameras = [1]\n",
            Path::new("t.toml"),
        )
        .expect("the keys are known");
    assert_eq!(
        c.camera_split(),
        CameraSplit {
            train: vec![0, 2],
            test: Some(vec![1])
        }
    );
    let json = serde_json::to_string(&c).unwrap();
    assert!(json.contains("\"zju_train_cameras\":[0,2]"), "{json}");
}
