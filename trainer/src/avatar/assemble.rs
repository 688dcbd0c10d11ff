//! The avatar a run trains: which optional layers (cloth, scene) it builds, from its
//! config or else from the data, and the avatar built with them.

use drape_engine::ops::accumulate::Accumulation;
use drape_engine::Context;

use crate::avatar::config::TrainConfig;
use crate::avatar::inputs::{scene_points, Sequence};
use crate::avatar::model::{body_init, cloth_init, Avatar};
use crate::avatar::rig::Rig;
use crate::avatar::scene::{scene_init, SceneLayer};
use crate::error::TrainerError;

/// The optional layers a run builds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Layers {
    pub cloth: bool,
    pub scene: bool,
}

/// The layers the run builds, each forced by `config.layers.choice` or else decided from the
/// data: a cloth layer where it has garment masks, a scene layer where it has scene
/// points (an unmasked capture; ZJU-MoCap's studio frames are masked and have none).
pub fn choose_layers(seq: &Sequence, config: &TrainConfig) -> crate::Result<Layers> {
    let choice = config.layers.choice;
    let scene = match choice.scene {
        Some(true) if scene_points(seq)?.is_none() => {
            return Err(TrainerError::config("layers", format!("{choice}: {} has no scene points (NeuMan's sparse/points3D.txt) to build a scene layer from", seq.dir.display())))
        }
        Some(s) => s,
        None => scene_points(seq)?.is_some(),
    };
    Ok(Layers {
        cloth: choice
            .cloth
            .unwrap_or_else(|| seq.frames.iter().any(|f| f.garment_masks.is_some())),
        scene,
    })
}

/// The avatar the data requires.
pub(crate) fn build_avatar(
    ctx: &Context,
    rig: &Rig,
    seq: &Sequence,
    config: &TrainConfig,
    layers: Layers,
) -> crate::Result<Avatar> {
    let cloth = layers.cloth;
    let mut inits = vec![body_init(
        rig,
        config.layers.subdivision,
        config.layers.decimate,
        config.layers.body.sh_degree,
    )];
    let mut configs = vec![config.layers.body.clone()];
    let mut lbs = vec![0.0];
    if cloth {
        inits.push(cloth_init(
            rig,
            config.layers.cloth_fit,
            config.layers.decimate,
            config.layers.cloth.sh_degree,
        ));
        configs.push(config.layers.cloth.clone());
        lbs.push(config.losses.lambda_cloth_lbs);
    }
    let scene = match (layers.scene, scene_points(seq)?) {
        (true, Some(colmap)) => {
            let (cloud, extent) = scene_init(
                &colmap,
                config.layers.scene.sh_degree,
                config.layers.scene.max_points,
            );
            Some(SceneLayer::new(
                ctx,
                &cloud,
                extent,
                &config.layers.scene,
                config.schedule.steps,
            )?)
        }
        _ => None,
    };
    let mut avatar = Avatar::new(
        ctx,
        &inits,
        &configs,
        &lbs,
        scene,
        config.schedule.steps,
        config.seed,
    )?;
    if config.deterministic {
        avatar.set_accumulation(ctx, Accumulation::Deterministic)?;
    }
    Ok(avatar)
}
