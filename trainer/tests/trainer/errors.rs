//! The trainer's typed errors: a caller tells a GPU failure from a bad setting by
//! matching on `TrainerError`, and a config value's error names its key and the values
//! a choice takes.

use drape_engine::EngineError;
use drape_tests::gpu;
use drape_trainer::avatar::composite::{AvatarRenderer, Compositing};
use drape_trainer::avatar::layer::LayerConfig;
use drape_trainer::avatar::model::{body_init, Avatar};
use drape_trainer::avatar::rig::Rig;
use drape_trainer::avatar::train::TrainConfig;
use drape_trainer::body::procedural::{default_body, BodyOptions};
use drape_trainer::TrainerError;

/// What an application embedding the trainer does with an error: retry elsewhere on a
/// lost or exhausted device, report a size past the device's limits, ask the user to
/// fix a setting.
fn action(e: &TrainerError) -> &'static str {
    match e {
        TrainerError::Engine(
            EngineError::DeviceLost { .. } | EngineError::OutOfDeviceMemory { .. },
        ) => "retry on another device",
        TrainerError::Engine(EngineError::TooLarge { .. }) => "choose a smaller size",
        TrainerError::Engine(_) => "report a GPU failure",
        TrainerError::Config { .. } => "fix the setting",
        _ => "report",
    }
}

/// The quick preset with the value at `key` (dotted: `layers.compositing`) replaced.
fn config_with(key: &str, value: serde_json::Value) -> drape_trainer::Result<TrainConfig> {
    let mut json = serde_json::to_value(TrainConfig::quick()).expect("a config serialises");
    let slot = key.split('.').fold(&mut json, |v, k| &mut v[k]);
    assert!(!slot.is_null(), "{key} is a key of the config");
    *slot = value;
    TrainConfig::from_deserializer(json)
}

#[test]
fn a_config_choice_error_names_the_key_and_the_values_it_takes() {
    for (key, value, allowed) in [
        (
            "layers.compositing",
            "blended",
            "three-pass, three-pass-occlusion, single-pass, fused or fused-occlusion",
        ),
        ("layers.choice", "cloth+body", "body+cloth+scene"),
        ("layers.cloth_fit", "baggy", "`tight`"),
        ("losses.lpips_net", "squeeze", "`alex`"),
        ("preset", "fast", "`quick`"),
    ] {
        let e = config_with(key, value.into()).expect_err(key);
        match &e {
            TrainerError::Config { key: k, problem } => {
                assert_eq!(k, key, "{e}");
                assert!(
                    problem.contains(value) && problem.contains(allowed),
                    "{key}: the value and the allowed ones: {e}"
                );
            }
            other => panic!("{key}: expected a config error, got {other:?}"),
        }
        assert_eq!(action(&e), "fix the setting");
    }
    // A range checked after deserialising names its key too.
    let e = config_with("layers.decimate", 0.into()).expect_err("decimate 0");
    assert!(
        matches!(&e, TrainerError::Config { key, .. } if key == "layers.decimate"),
        "{e:?}"
    );
    // Each choice round-trips through its serde form.
    for c in Compositing::ALL {
        let back = config_with("layers.compositing", c.name().into()).expect("a named compositing");
        assert_eq!(back.layers.compositing, c);
    }
}

#[test]
fn a_gpu_failure_is_told_apart_from_a_config_error() {
    // A real failure from the engine, through the trainer's renderer: a frame whose
    // buffers are past the device's maxMemoryAllocationSize.
    let ctx = gpu();
    let rig = Rig::new(default_body(&BodyOptions::default()), &[]);
    let layer = LayerConfig {
        triplane_resolution: 8,
        triplane_channels: 4,
        decoder_width: 16,
        ..LayerConfig::default()
    };
    let avatar = Avatar::new(
        &ctx,
        &[body_init(&rig, 0, 16, 0)],
        &[layer],
        &[0.0],
        None,
        10,
        1,
    )
    .expect("a small avatar");
    let side = 1 << 16;
    let e: TrainerError =
        match AvatarRenderer::new(&ctx, &avatar, side, side, Compositing::SinglePass) {
            Ok(_) => panic!("a {side}x{side} frame should be past the device's limits"),
            Err(e) => e.into(),
        };
    assert!(
        matches!(e.engine(), Some(EngineError::TooLarge { .. })),
        "{e:?}"
    );
    assert_eq!(action(&e), "choose a smaller size");

    // A lost device or exhausted memory, as the engine reports them, reaches the caller
    // as the engine's own variant through `?`, not as prose.
    fn step(fail: EngineError) -> drape_trainer::Result<()> {
        Err(fail)?;
        Ok(())
    }
    let lost = step(EngineError::DeviceLost {
        pass: "splat.raster_fwd".into(),
    })
    .unwrap_err();
    let oom = step(EngineError::OutOfDeviceMemory {
        what: "triplane".into(),
        bytes: 1 << 40,
    })
    .unwrap_err();
    for e in [&lost, &oom] {
        assert_eq!(action(e), "retry on another device", "{e:?}");
    }
    assert!(
        matches!(lost.engine(), Some(EngineError::DeviceLost { pass }) if pass == "splat.raster_fwd")
    );
    let config = config_with("layers.compositing", "blended".into()).unwrap_err();
    assert!(config.engine().is_none());
    assert_ne!(action(&config), action(&lost));
}
