//! What a run is built from before its first step: the sequence's checked image size,
//! the image losses, the renderer for the avatar's current counts, the cloth layer's
//! losses with their simulated targets, and the skinning-weight fit of every layer.

use drape_engine::ops::lpips::{Lpips, LpipsWeights};
use drape_engine::Context;

use crate::avatar::cloth_losses::{ClothLossWeights, ClothLosses};
use crate::avatar::cloth_target;
use crate::avatar::composite::AvatarRenderer;
use crate::avatar::config::TrainConfig;
use crate::avatar::inputs::Sequence;
use crate::avatar::losses::{ImageLossWeights, ImageLosses};
use crate::avatar::model::Avatar;
use crate::avatar::report::Progress;
use crate::avatar::rig::Rig;
use crate::dataset::error::DatasetError;
use crate::dataset::split::Split;

/// The size every image of `seq` has: an error where it has no training frames or an
/// image of another size than the first training image.
pub(super) fn image_size(seq: &Sequence) -> crate::Result<(u32, u32)> {
    let Some(first) = seq.frames.iter().find(|f| f.split == Split::Train) else {
        return Err(DatasetError::layout(&seq.dir, "no training frames").into());
    };
    let (width, height) = (first.width, first.height);
    if let Some(f) = seq
        .frames
        .iter()
        .find(|f| (f.width, f.height) != (width, height))
    {
        return Err(DatasetError::image(
            &f.image_path,
            format!(
                "{}x{}, but the sequence's first training image is {width}x{height}",
                f.width, f.height
            ),
        )
        .into());
    }
    Ok((width, height))
}

/// The image losses with the config's weights; LPIPS joins where there are weights and
/// `losses.lambda_lpips` is not 0.
pub(super) fn image_losses_of(
    ctx: &Context,
    config: &TrainConfig,
    lpips_weights: Option<&LpipsWeights>,
    (width, height): (u32, u32),
) -> crate::Result<ImageLosses> {
    let lpips = match lpips_weights {
        Some(w) if config.losses.lambda_lpips > 0.0 => Some(Lpips::new(ctx, w, width, height)?),
        _ => None,
    };
    let weights = ImageLossWeights {
        l1: config.losses.lambda_l1,
        ssim: config.losses.lambda_ssim,
        lpips: config.losses.lambda_lpips,
    };
    Ok(ImageLosses::new(ctx, width, height, weights, lpips)?)
}

/// The renderer for the avatar's current counts, and the cloth losses resized to them
/// (after a checkpoint or a densification changed the counts).
pub(super) fn renderer_for(
    ctx: &Context,
    avatar: &Avatar,
    cloth_losses: Option<&mut ClothLosses>,
    config: &TrainConfig,
    (width, height): (u32, u32),
) -> crate::Result<AvatarRenderer> {
    let renderer = AvatarRenderer::new(ctx, avatar, width, height, config.layers.compositing)?;
    if let (Some(c), Some(cloth)) = (cloth_losses, avatar.cloth()) {
        c.resize(ctx, cloth)?;
        c.set_mask_in_composite(renderer.is_three_pass());
    }
    Ok(renderer)
}

/// The cloth layer's losses, where the avatar has a cloth layer and the config weighs
/// them: their physics targets are the garments simulated through the sequence's motion.
pub(super) fn cloth_losses_of(
    ctx: &Context,
    avatar: &Avatar,
    rig: &Rig,
    seq: &Sequence,
    config: &TrainConfig,
    (width, height): (u32, u32),
    progress: &mut dyn FnMut(Progress),
) -> crate::Result<Option<ClothLosses>> {
    match avatar.cloth() {
        Some(cloth)
            if config.losses.lambda_sim > 0.0
                || config.losses.lambda_arap > 0.0
                || config.losses.lambda_mask > 0.0 =>
        {
            let garments = cloth_target::simulate_sequence(
                rig,
                config.layers.cloth_fit,
                &seq.frames,
                &mut |done, total| progress(Progress::Simulate { done, total }),
            )?;
            let weights = ClothLossWeights {
                sim: config.losses.lambda_sim,
                gm_sigma: config.losses.gm_sigma,
                arap: config.losses.lambda_arap,
                mask: config.losses.lambda_mask,
                target_stride: config.layers.decimate,
            };
            Ok(Some(ClothLosses::new(
                ctx, cloth, garments, weights, width, height,
            )?))
        }
        _ => Ok(None),
    }
}

/// Fits every layer's deformation decoder to the body's skinning weights; the worst
/// layer's final mean squared error.
pub(super) fn fit_skinning_weights(
    ctx: &Context,
    avatar: &mut Avatar,
    config: &TrainConfig,
    progress: &mut dyn FnMut(Progress),
) -> crate::Result<f64> {
    let total = config.schedule.fit_steps;
    let mut worst = 0.0f64;
    for l in &mut avatar.layers {
        let name = l.name.clone();
        let mse = l.fit_skinning_weights(ctx, total, config.schedule.fit_lr, 25, |step, mse| {
            progress(Progress::Fit {
                layer: name.clone(),
                step,
                total,
                mse,
            })
        })?;
        worst = worst.max(mse);
    }
    Ok(worst)
}
