//! Editing a trained avatar's clothes (`drape edit`); each edit writes a new run
//! directory (`config.json`, `run.json` naming the edit, `model.npz`) that
//! `drape eval` and `drape animate` open like a trained one.
//!
//! - **Remove the cloth layer:** the body underneath shows what the body layer learned
//!   where the garments hid it (HUGS's single layer would have painted the shirt on).
//! - **Recolour the garments:** a hue rotation by θ about the grey axis, applied inside
//!   the cloth layer's appearance decoder: every SH coefficient's RGB triple of the SH
//!   head's weights and bias is multiplied by the rotation M. The splatter's colour is
//!   `0.5 + Σ Yₖ(d) shₖ` and M fixes grey (M · 0.5·𝟙 = 0.5·𝟙), so the new colour is
//!   exactly `M · colour` in every view direction (before the splatter's clamp at 0);
//!   luminance-preserving it is not, hue rotations about the grey axis never are.
//! - **Swap the cloth layer** for another run's: both runs must have cloth layers of
//!   the same shape (the same garments, decimation and layer configuration: runs made
//!   on the same body and data with the same preset). The body and scene stay.

use std::path::Path;

use drape_engine::Context;

use crate::avatar::checkpoint;
use crate::avatar::model::LayerChoice;
use crate::avatar::report::write_json;
use crate::avatar::run::{OpenRun, RunInfo};
use crate::avatar::state::{LayerState, ModelState};
use crate::TrainerError;

/// One edit.
#[derive(Clone, Debug, PartialEq)]
pub enum Edit {
    RemoveCloth,
    /// Hue rotation in degrees.
    Recolour {
        hue_degrees: f64,
    },
    /// The cloth layer of another (opened) run.
    SwapCloth,
}

/// The 3 × 3 rotation by `degrees` about the grey axis (1, 1, 1)/√3.
pub fn hue_rotation(degrees: f64) -> [[f32; 3]; 3] {
    let k = 1.0 / 3f64.sqrt();
    let (s, c) = degrees.to_radians().sin_cos();
    // M = c I + s [k]× + (1 - c) k kᵀ with k = (k, k, k).
    let a = c + (1.0 - c) * k * k;
    let b = (1.0 - c) * k * k - s * k;
    let d = (1.0 - c) * k * k + s * k;
    [[a, b, d], [d, a, b], [b, d, a]].map(|r| r.map(|v| v as f32))
}

/// Multiplies every RGB triple of the SH head (output rows 3k, 3k+1, 3k+2 of its
/// weight matrix and bias) of the decoder parameters `params` by `m`.
pub fn recolour_sh_head(
    params: &mut [f32],
    head_weight: usize,
    head_bias: usize,
    inputs: usize,
    outputs: usize,
    m: &[[f32; 3]; 3],
) {
    for k in 0..outputs / 3 {
        for col in 0..=inputs {
            // Column `inputs` stands for the bias.
            let at = |c: usize| {
                if col == inputs {
                    head_bias + 3 * k + c
                } else {
                    head_weight + (3 * k + c) * inputs + col
                }
            };
            let v = [params[at(0)], params[at(1)], params[at(2)]];
            for (c, row) in m.iter().enumerate() {
                params[at(c)] = row[0] * v[0] + row[1] * v[1] + row[2] * v[2];
            }
        }
    }
}

/// Applies `edit` to `run` (with `other`: the run whose cloth layer `SwapCloth` takes)
/// and writes the result into `out` (created; it must not exist or be empty).
/// Returns a line saying what was done.
pub fn edit(
    ctx: &Context,
    run: &mut OpenRun,
    edit: &Edit,
    other: Option<&mut OpenRun>,
    out: &Path,
) -> crate::Result<String> {
    if out.exists()
        && std::fs::read_dir(out)
            .map_err(|e| TrainerError::io(out, e))?
            .next()
            .is_some()
    {
        return Err(TrainerError::run(
            out,
            "the output directory exists and is not empty",
        ));
    }
    let Some(cloth_index) = run.avatar.layers.iter().position(|l| l.name == "cloth") else {
        return Err(TrainerError::run(
            &run.dir,
            "the model has no cloth layer to edit",
        ));
    };
    let mut state: ModelState = run.avatar.state(ctx, run.step)?;
    let mut config = run.config.clone();
    let what = match edit {
        Edit::RemoveCloth => {
            state.layers.retain(|(name, _)| name != "cloth");
            config.layers.choice = LayerChoice {
                cloth: Some(false),
                scene: Some(run.layers.scene),
            };
            format!("the cloth layer of {} removed", run.dir.display())
        }
        Edit::Recolour { hue_degrees } => {
            let desc = &run.avatar.layers[cloth_index].appearance.desc;
            let (offsets, _) = desc.layout();
            // The SH head is the second head, after opacity.
            let head = desc.hidden.len() + 1;
            let (w, b) = offsets[head];
            let inputs = desc.hidden.last().map_or(desc.input, |h| h.0);
            let outputs = desc.heads[1].width;
            recolour_sh_head(
                &mut state.layers[cloth_index].1.appearance,
                w,
                b,
                inputs,
                outputs,
                &hue_rotation(*hue_degrees),
            );
            format!(
                "the garments of {} recoloured by a hue rotation of {hue_degrees}°",
                run.dir.display()
            )
        }
        Edit::SwapCloth => {
            let other = other.ok_or_else(|| {
                TrainerError::invalid("swap", "no run to take the cloth layer from")
            })?;
            let theirs: ModelState = other.avatar.state(ctx, other.step)?;
            let Some((_, cloth)) = theirs.layers.into_iter().find(|(n, _)| n == "cloth") else {
                return Err(TrainerError::run(
                    &other.dir,
                    "the model has no cloth layer to swap in",
                ));
            };
            let mine = &state.layers[cloth_index].1;
            // The Gaussian counts may differ (densification); the networks may not.
            let shape = |l: &LayerState| {
                (
                    l.triplane_size,
                    l.appearance.len(),
                    l.geometry.len(),
                    l.deformation.len(),
                )
            };
            if shape(mine) != shape(&cloth) {
                return Err(TrainerError::run(
                    &other.dir,
                    format!(
                        "its cloth layer ({} Gaussians, triplane {:?}, decoders {}/{}/{} parameters) differs in shape from {}'s ({} Gaussians, triplane {:?}, decoders {}/{}/{}): swap needs runs made with the same garments and preset",
                        cloth.means.len() / 3,
                        cloth.triplane_size,
                        cloth.appearance.len(),
                        cloth.geometry.len(),
                        cloth.deformation.len(),
                        run.dir.display(),
                        mine.means.len() / 3,
                        mine.triplane_size,
                        mine.appearance.len(),
                        mine.geometry.len(),
                        mine.deformation.len()
                    ),
                ));
            }
            if other.rig.betas != run.rig.betas {
                return Err(TrainerError::run(&other.dir, format!("trained on a body of other shape (betas) than {}; the garments would not fit", run.dir.display())));
            }
            state.layers[cloth_index].1 = cloth;
            format!(
                "the cloth layer of {} put on {}",
                other.dir.display(),
                run.dir.display()
            )
        }
    };
    std::fs::create_dir_all(out).map_err(|e| TrainerError::io(out, e))?;
    write_json(&out.join("config.json"), &config)?;
    RunInfo {
        made_by: Some(format!("drape edit: {what}")),
        ..run.info.clone()
    }
    .write(out)?;
    checkpoint::write(&out.join("model.npz"), &state)?;
    Ok(what)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hue_rotation_fixes_grey_and_turns_red_towards_green() {
        let m = hue_rotation(120.0);
        let apply = |v: [f32; 3]| m.map(|r| r[0] * v[0] + r[1] * v[1] + r[2] * v[2]);
        // f32 rounding of the matrix entries.
        let close = |a: [f32; 3], b: [f32; 3]| a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-6);
        assert!(close(apply([0.5; 3]), [0.5; 3]), "{:?}", apply([0.5; 3]));
        // 120° about the grey axis permutes the primaries: red → green.
        assert!(
            close(apply([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0]),
            "{:?}",
            apply([1.0, 0.0, 0.0])
        );
    }

    #[test]
    fn recolouring_the_head_recolours_its_output() {
        // A head of 2 inputs and 6 outputs (two SH coefficients), weights then bias.
        let (inputs, outputs) = (2, 6);
        let mut params: Vec<f32> = (0..inputs * outputs + outputs)
            .map(|i| (i as f32 * 0.37).sin())
            .collect();
        let before = params.clone();
        let m = hue_rotation(50.0);
        recolour_sh_head(&mut params, 0, inputs * outputs, inputs, outputs, &m);
        let x = [0.3f32, -1.2];
        let eval = |p: &[f32]| -> Vec<f32> {
            (0..outputs)
                .map(|o| p[o * inputs] * x[0] + p[o * inputs + 1] * x[1] + p[inputs * outputs + o])
                .collect()
        };
        let (y0, y1) = (eval(&before), eval(&params));
        for k in 0..2 {
            for c in 0..3 {
                let want: f32 = (0..3).map(|d| m[c][d] * y0[3 * k + d]).sum();
                // A few f32 roundings of values of order 1.
                assert!(
                    (y1[3 * k + c] - want).abs() < 1e-5,
                    "coefficient {k} channel {c}: {} vs {want}",
                    y1[3 * k + c]
                );
            }
        }
    }
}
