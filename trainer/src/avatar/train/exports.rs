//! What a run writes besides its model and metrics: the training steps' profile
//! (`profile.txt`, `profile.json`), the avatar posed as a held-out frame as one 3DGS PLY
//! per layer, and `novel_pose.png`, the avatar in a pose the data never showed.

use std::path::Path;

use drape_engine::ops::splat::scene::RenderSettings;
use drape_engine::Context;

use crate::avatar::composite::AvatarRenderer;
use crate::avatar::groups::Layer;
use crate::avatar::model::Avatar;
use crate::avatar::report::write_json;
use crate::avatar::rig::Rig;
use crate::avatar::step::HostWaits;
use crate::dataset::loader::{BodyParams, DatasetFrame};
use crate::error::TrainerError;
use crate::ply;

/// Writes the training steps' profile (`drape train --profile`): `profile.txt`, a table
/// whose shares are of the loop's wall time, and `profile.json`.
pub(super) fn write_profile(
    out: &Path,
    profile: &drape_engine::Profile,
    waits: &HostWaits,
    steps: u64,
    loop_seconds: f64,
) -> crate::Result<()> {
    let table = format!("{steps} steps in {loop_seconds:.2} s ({:.1} ms/step); shares are of that wall time\n{}\n{}", 1e3 * loop_seconds / steps.max(1) as f64, waits.summary(), profile.table(1e3 * loop_seconds, steps, 25));
    let path = out.join("profile.txt");
    drape_io::write(&path, &table).map_err(|e| TrainerError::io(&path, e))?;
    write_json(&out.join("profile.json"), profile)
}

/// Exports the avatar posed as held-out frame `f`: one standard 3DGS PLY per layer
/// (`body_frameNNNN.ply`, `cloth_frameNNNN.ply`).
pub(super) fn export_posed_layers(
    ctx: &Context,
    avatar: &mut Avatar,
    rig: &Rig,
    f: &DatasetFrame,
    out: &Path,
) -> crate::Result<()> {
    let ft = rig.frame(&f.body);
    avatar.set_frame(ctx, &ft)?;
    {
        let mut rec = ctx.record("export forward")?;
        avatar.record_forward(&mut rec, ft.log_scale)?;
        rec.submit_and_wait()?;
    }
    let cloud = avatar.read_posed(ctx)?;
    for layer in [Layer::Body, Layer::Cloth] {
        let mut part = drape_engine::ops::splat::scene::GaussianCloud::new(cloud.sh_degree);
        for i in (0..cloud.len()).filter(|&i| cloud.groups[i] == layer.group()) {
            part.push(&cloud.gaussian::<f32>(i), layer);
        }
        if !part.is_empty() {
            let name = if layer == Layer::Body {
                "body"
            } else {
                "cloth"
            };
            let path = out.join(format!("{name}_frame{:04}.ply", f.frame));
            ply::write(&path, &part)?;
        }
    }
    Ok(())
}

/// Renders `novel_pose.png` at `f`'s size: the procedural raise-arms motion, halfway, on
/// held-out frame `f`'s root, translation and camera.
pub(super) fn render_novel_pose(
    ctx: &Context,
    avatar: &mut Avatar,
    renderer: &mut AvatarRenderer,
    rig: &Rig,
    f: &DatasetFrame,
    settings: &RenderSettings,
    out: &Path,
) -> crate::Result<()> {
    let motion = crate::motion::procedural(crate::motion::MotionKind::RaiseArms, 30, 30.0, 1.0);
    let novel = &motion.poses[15];
    let body = match &f.body {
        BodyParams::Smpl {
            pose,
            betas,
            translation,
            scale,
        } => {
            let mut p = *pose;
            p[1..].copy_from_slice(&novel[1..]);
            BodyParams::Smpl {
                pose: p,
                betas: betas.clone(),
                translation: *translation,
                scale: *scale,
            }
        }
        BodyParams::Zju(z) => {
            let mut z = z.clone();
            for (j, q) in novel.iter().enumerate().take(24).skip(1) {
                z.poses[3 * j..3 * j + 3].copy_from_slice(&q.to_array());
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
    renderer.forward(ctx, avatar, &f.camera.to_pinhole([0.0; 3]), settings)?;
    let rgb = renderer.read_rgb(ctx)?;
    crate::dataset::image::write_rgb(&out.join("novel_pose.png"), f.width, f.height, &rgb)?;
    Ok(())
}
