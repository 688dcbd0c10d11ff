//! `engine-bench trade RUN`: the speed/accuracy trade of a trained avatar, measured.
//! For each knob the engine has, every held-out frame of the run is rendered
//! (posed as in that frame, from its camera) and compared with its ground truth and with
//! the default render (the run's own compositing at the data's size, every SH
//! coefficient, every Gaussian): PSNR, SSIM and, with weights, LPIPS; beside it the GPU
//! time of a frame (decoders, skinning, projection, binning and sorts, rasterization,
//! composite: the sum of the passes' timestamps), median over `--runs` × frames.
//!
//! Knobs measured:
//! - resolution: the frame's camera scaled (`--scales`); the render is resampled to the
//!   data's size (a 2 × 2 box per pixel when the scale is an integer, else bilinear) so
//!   that every setting is compared with the same ground truth;
//! - SH degree per layer: the coefficients above a degree zeroed after the decoders
//!   (where the appearance head's SH reaches the splatter: each layer's `posed.sh` and
//!   the gathered `avatar.posed.sh`; the scene's trained SH for the scene layer);
//! - Gaussians pruned by opacity (`--prune`): a pruned Gaussian's opacity logit is set to
//!   [`PRUNED_LOGIT`], which the projection culls (opacity below `alpha_min`), so it
//!   leaves no intersection, exactly as if removed;
//! - Gaussians pruned by contribution (`--prune-contribution`): each Gaussian's blend
//!   weight `α · T` summed over the pixels of `--contribution-frames` training frames
//!   (one depth-sorted render of every layer per frame, posed as in that frame,
//!   `SplatRenderer::contributions`: the backward rasterizer's colour gradient under
//!   an upstream of ones), and the given fraction with the least culled as above;
//! - compositing: three-pass, three-pass-occlusion, single-pass, fused;
//! - tile size: 8 (subgroup rasterizers only) and 32 against the default 16; the image
//!   is the same, the binning, sorts and walks are not;
//! - half-precision SH: the decoded SH packed to binary16 every frame (the packing's
//!   pass is in the time) and the projection reading half the words;
//! - half-precision projected splats: packed after binning (the pass is in the time),
//!   the forward rasterizers reading 6 words a splat instead of 10;
//! - pose-dependent offsets off, for runs whose layers were trained with them: the
//!   deformation reads the decoded offsets without the pose blend (which also saves
//!   the blend's pass).
//!
//! The edits are host reads and writes between the decoders and the render, outside the
//! GPU time. They change what is rendered, not how: the kernels still evaluate every SH
//! coefficient of the trained degree and project every Gaussian, so SH truncation saves
//! no time here and pruning (by opacity or contribution) saves binning, sorting and
//! rasterization but not the decoders or the projection (a compacted model would). Knobs
//! a run cannot measure (the subdivision level: another trained run) are listed under
//! `not_built`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use drape_cli_support::median;
use drape_engine::ops::lpips::{Lpips, LpipsWeights};
use drape_engine::ops::splat::render::subgroup_raster_supported;
use drape_engine::ops::splat::render::SplatRenderer;
use drape_engine::ops::splat::scene::{PinholeCamera, RenderSettings};
use drape_engine::Context;
use drape_shared::splat::layout::{sh_coeffs, DEFAULT_TILE_SIZE, RASTER_BLOCK, TILE_SIZES};
use drape_trainer::avatar::composite::{AvatarRenderer, Compositing};
use drape_trainer::avatar::eval::psnr;
use drape_trainer::avatar::model::Avatar;
use drape_trainer::avatar::run::OpenRun;
use drape_trainer::dataset::loader::DatasetFrame;
use drape_trainer::dataset::split::Split;
use serde_json::json;

/// The opacity logit of a pruned Gaussian: sigmoid(-30) ≈ 9e-14, far below the
/// projection's culling threshold (`alpha_min` = 1/255), and finite (a non-finite logit
/// would be counted as dropped rather than culled).
pub const PRUNED_LOGIT: f32 = -30.0;

/// The PSNR of identical images: `eval::psnr` floors the MSE at 1e-20 (JSON has no ∞).
pub const IDENTICAL_PSNR_DB: f64 = 200.0;

/// Options of `engine-bench trade`.
#[derive(Clone, Debug, clap::Args)]
pub struct TradeArgs {
    /// A finished `drape train` run directory (config.json, model.npz, run.json).
    pub run: PathBuf,
    /// The sequence the run was trained on, when run.json is missing or the data moved.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Timed renders of each held-out frame per setting; ms per frame is the median over
    /// runs × frames.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..))]
    pub runs: u32,
    /// Untimed warm-up renders (of the first held-out frame) before each setting (at least
    /// this many, and for at least --warm-seconds).
    #[arg(long, default_value_t = 1)]
    pub warmup: u32,
    /// LPIPS weights (safetensors, the run's `losses.lpips_net`; default: the run's config).
    /// Without any, the LPIPS columns are n/a.
    #[arg(long)]
    pub lpips_weights: Option<PathBuf>,
    /// Resolution knob: the data's size times each scale (1 is the default setting).
    #[arg(long, value_delimiter = ',', default_value = "0.5,1,2", value_parser = parse_scale)]
    pub scales: Vec<f64>,
    /// Pruning knob: Gaussians whose opacity is below each threshold are culled.
    #[arg(long, value_delimiter = ',', default_value = "0.005,0.02,0.05,0.1", value_parser = parse_threshold)]
    pub prune: Vec<f32>,
    /// Pruning by contribution: each fraction of the Gaussians with the least summed
    /// blend weight over training frames is culled.
    #[arg(long, value_delimiter = ',', default_value = "0.1,0.25,0.5", value_parser = parse_fraction)]
    pub prune_contribution: Vec<f64>,
    /// Training frames (spread evenly over the training split; 0: all) whose renders
    /// measure each Gaussian's contribution.
    #[arg(long, default_value_t = 8)]
    pub contribution_frames: usize,
    /// Use only the first N held-out frames (0: all of them).
    #[arg(long, default_value_t = 0)]
    pub max_frames: usize,
    /// Print the JSON table on stdout instead of the Markdown one.
    #[arg(long)]
    pub json: bool,
    /// Where trade.json, trade.md and trade.png go (default: RUN/trade).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

fn parse_scale(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if v > 0.0 && v <= 8.0 => Ok(v),
        _ => Err(format!("'{s}' is not a scale in (0, 8]")),
    }
}

fn parse_threshold(s: &str) -> Result<f32, String> {
    match s.trim().parse::<f32>() {
        Ok(v) if v > 0.0 && v < 1.0 => Ok(v),
        _ => Err(format!("'{s}' is not an opacity threshold in (0, 1)")),
    }
}

fn parse_fraction(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if v > 0.0 && v < 1.0 => Ok(v),
        _ => Err(format!(
            "'{s}' is not a fraction of the Gaussians in (0, 1)"
        )),
    }
}

/// One point of the trade: how the frame is rendered.
#[derive(Clone, Debug)]
struct Setting {
    knob: &'static str,
    label: String,
    scale: f64,
    compositing: String,
    /// SH degree kept per part (the human layers in order, then the scene); None: all.
    sh_keep: Vec<Option<u32>>,
    prune: Option<f32>,
    /// Gaussians culled by contribution (true), in the gathered order: the human layers,
    /// then the scene.
    prune_mask: Option<std::rc::Rc<Vec<bool>>>,
    /// The pose blend of layers trained with pose-dependent offsets.
    pose_offsets: bool,
    /// Tile side of binning and rasterization (`RenderSettings::tile_size`).
    tile_size: u32,
    /// Render from half-precision SH (`RenderSettings::half_sh`).
    half_sh: bool,
    /// Rasterize half-precision projected splats (`RenderSettings::half_splats`).
    half_splats: bool,
}

impl Setting {
    fn edits(&self) -> bool {
        self.prune.is_some()
            || self.prune_mask.is_some()
            || self.sh_keep.iter().any(Option::is_some)
    }
}

/// Zeroes the SH coefficients above degree `keep` of every Gaussian in `sh` (the
/// `[gaussian][k][channel]` layout of a cloud of degree `degree`).
pub fn truncate_sh(sh: &mut [f32], degree: u32, keep: u32) {
    let (k, kept) = (3 * sh_coeffs(degree), 3 * sh_coeffs(keep.min(degree)));
    for g in sh.chunks_exact_mut(k) {
        g[kept..].fill(0.0);
    }
}

/// Culls the Gaussians whose opacity (sigmoid of the logit) is below `threshold` by
/// setting their logit to [`PRUNED_LOGIT`]; returns how many are kept. Idempotent.
/// A NaN logit fails the `>=` test and is pruned.
pub fn prune_by_opacity(opacity_logits: &mut [f32], threshold: f32) -> usize {
    let mut kept = 0;
    for l in opacity_logits {
        if 1.0 / (1.0 + (-*l).exp()) >= threshold {
            kept += 1;
        } else {
            *l = PRUNED_LOGIT;
        }
    }
    kept
}

/// Culls the Gaussians marked in `pruned` (one flag per logit) by setting their logit to
/// [`PRUNED_LOGIT`]; returns how many are kept.
pub fn prune_masked(opacity_logits: &mut [f32], pruned: &[bool]) -> usize {
    assert_eq!(opacity_logits.len(), pruned.len(), "one flag per Gaussian");
    let mut kept = 0;
    for (l, &p) in opacity_logits.iter_mut().zip(pruned) {
        if p {
            *l = PRUNED_LOGIT;
        } else {
            kept += 1;
        }
    }
    kept
}

/// The `fraction` of the Gaussians with the least contribution (ties broken by index,
/// so the choice is the same on every run): true for each culled one.
pub fn least_contributing(contributions: &[f64], fraction: f64) -> Vec<bool> {
    let mut order: Vec<usize> = (0..contributions.len()).collect();
    order.sort_by(|&a, &b| {
        contributions[a]
            .total_cmp(&contributions[b])
            .then(a.cmp(&b))
    });
    let cut = (fraction * contributions.len() as f64).floor() as usize;
    let mut pruned = vec![false; contributions.len()];
    for &i in &order[..cut.min(order.len())] {
        pruned[i] = true;
    }
    pruned
}

/// Each Gaussian's contribution, in the gathered order (the human layers, then the
/// scene), summed over up to `max_frames` training frames spread evenly over the
/// training split (0: all): its blend weights `α · T` over the pixels of one
/// depth-sorted render of every layer, posed as in the frame, from its camera
/// (`SplatRenderer::contributions`). Returns the sums and the frames used.
fn contributions(
    ctx: &Context,
    run: &mut OpenRun,
    max_frames: usize,
) -> anyhow::Result<(Vec<f64>, usize)> {
    let train: Vec<DatasetFrame> = run
        .seq
        .frames
        .iter()
        .filter(|f| f.split == Split::Train)
        .cloned()
        .collect();
    anyhow::ensure!(
        !train.is_empty(),
        "{}: the run's data has no training frame to measure contributions on",
        run.seq.dir.display()
    );
    let picked: Vec<&DatasetFrame> = if max_frames == 0 || train.len() <= max_frames {
        train.iter().collect()
    } else {
        (0..max_frames)
            .map(|k| &train[k * train.len() / max_frames])
            .collect()
    };
    let total = run.avatar.posed.count;
    let mut sums = vec![0.0f64; total as usize];
    let mut renderers: BTreeMap<(u32, u32), SplatRenderer> = BTreeMap::new();
    for f in &picked {
        let cam = f.camera.to_pinhole([0.0; 3]);
        let transforms = run.rig.frame(&f.body);
        run.avatar.set_frame(ctx, &transforms)?;
        for l in &mut run.avatar.layers {
            l.deformer.set_pose_blend(true);
        }
        {
            let mut rec = ctx.record("trade contributions decode and skin")?;
            run.avatar.record_forward(&mut rec, transforms.log_scale)?;
            rec.submit_and_wait()?;
        }
        let renderer = match renderers.entry((cam.width, cam.height)) {
            std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::btree_map::Entry::Vacant(e) => e.insert(SplatRenderer::new(
                ctx,
                cam.width,
                cam.height,
                total as usize,
            )?),
        };
        let saved = renderer
            .forward(&run.avatar.posed, &cam, &RenderSettings::default())?
            .saved;
        for (s, c) in sums.iter_mut().zip(renderer.contributions(&saved)?) {
            *s += f64::from(c);
        }
    }
    Ok((sums, picked.len()))
}

/// Resamples an HWC RGB image: by box averaging when the source is an integer multiple
/// of the destination (supersampling), else bilinearly at pixel centres, edges clamped.
pub fn resample(rgb: &[f32], (sw, sh): (u32, u32), (dw, dh): (u32, u32)) -> Vec<f32> {
    if (sw, sh) == (dw, dh) {
        return rgb.to_vec();
    }
    let (sw, sh, dw, dh) = (sw as usize, sh as usize, dw as usize, dh as usize);
    let mut out = vec![0.0f32; 3 * dw * dh];
    if sw % dw == 0 && sh % dh == 0 {
        let (fx, fy) = (sw / dw, sh / dh);
        let norm = 1.0 / (fx * fy) as f32;
        for y in 0..dh {
            for x in 0..dw {
                for c in 0..3 {
                    let mut s = 0.0;
                    for j in 0..fy {
                        for i in 0..fx {
                            s += rgb[3 * ((y * fy + j) * sw + x * fx + i) + c];
                        }
                    }
                    out[3 * (y * dw + x) + c] = s * norm;
                }
            }
        }
        return out;
    }
    let at = |x: usize, y: usize, c: usize| rgb[3 * (y * sw + x) + c];
    for y in 0..dh {
        let v = ((y as f32 + 0.5) * sh as f32 / dh as f32 - 0.5).clamp(0.0, (sh - 1) as f32);
        let (y0, ty) = (v.floor() as usize, v - v.floor());
        let y1 = (y0 + 1).min(sh - 1);
        for x in 0..dw {
            let u = ((x as f32 + 0.5) * sw as f32 / dw as f32 - 0.5).clamp(0.0, (sw - 1) as f32);
            let (x0, tx) = (u.floor() as usize, u - u.floor());
            let x1 = (x0 + 1).min(sw - 1);
            for c in 0..3 {
                let top = at(x0, y0, c) * (1.0 - tx) + at(x1, y0, c) * tx;
                let bottom = at(x0, y1, c) * (1.0 - tx) + at(x1, y1, c) * tx;
                out[3 * (y * dw + x) + c] = top * (1.0 - ty) + bottom * ty;
            }
        }
    }
    out
}

/// Which points are on the Pareto frontier of (ms, lower is better; PSNR, higher is
/// better): no other point is at least as fast and at least as good, and better in one.
pub fn pareto(points: &[(f64, f64)]) -> Vec<bool> {
    points
        .iter()
        .map(|&(ms, q)| {
            !points
                .iter()
                .any(|&(m2, q2)| m2 <= ms && q2 >= q && (m2 < ms || q2 > q))
        })
        .collect()
}

/// The settings of every measured knob; the first is the default.
fn settings(
    ctx: &Context,
    args: &TradeArgs,
    run: &mut OpenRun,
) -> anyhow::Result<(Vec<Setting>, BTreeMap<&'static str, serde_json::Value>)> {
    let default_comp = run.config.layers.compositing.name().to_string();
    let parts = part_names(&run.avatar);
    let base = Setting {
        knob: "default",
        label: format!("{default_comp}, 1x, full SH, all Gaussians"),
        scale: 1.0,
        compositing: default_comp.clone(),
        sh_keep: vec![None; parts.len()],
        prune: None,
        prune_mask: None,
        pose_offsets: true,
        tile_size: DEFAULT_TILE_SIZE,
        half_sh: false,
        half_splats: false,
    };
    let mut out = vec![base.clone()];
    let mut knobs = BTreeMap::new();
    for &s in args.scales.iter().filter(|&&s| s != 1.0) {
        out.push(Setting {
            knob: "resolution",
            label: format!("{s}x"),
            scale: s,
            ..base.clone()
        });
    }
    knobs.insert(
        "resolution",
        json!(format!(
            "measured: scales {:?} of the data's size, resampled to it for the metrics",
            args.scales
        )),
    );
    let degrees = part_degrees(&run.avatar);
    let degree = run.avatar.sh_degree();
    if degree == 0 {
        knobs.insert(
            "sh_degree",
            json!("not applicable: the run was trained at SH degree 0 (nothing to truncate)"),
        );
    } else {
        for keep in 0..degree {
            for (k, name) in parts.iter().enumerate().filter(|&(k, _)| keep < degrees[k]) {
                let mut sh_keep = vec![None; parts.len()];
                sh_keep[k] = Some(keep);
                out.push(Setting {
                    knob: "sh_degree",
                    label: format!("{name} at degree {keep} (trained at {})", degrees[k]),
                    sh_keep,
                    ..base.clone()
                });
            }
            if parts.len() > 1 {
                out.push(Setting {
                    knob: "sh_degree",
                    label: format!("every layer at degree {keep} at most"),
                    sh_keep: vec![Some(keep); parts.len()],
                    ..base.clone()
                });
            }
        }
        let trained: Vec<String> = parts
            .iter()
            .zip(&degrees)
            .map(|(p, d)| format!("{p} {d}"))
            .collect();
        knobs.insert("sh_degree", json!(format!("measured: each layer below the degree it was trained at ({}), and every layer; time is the full degree's (the kernels evaluate every coefficient of the highest degree)", trained.join(", "))));
    }
    for &t in &args.prune {
        out.push(Setting {
            knob: "pruning",
            label: format!("opacity < {t}"),
            prune: Some(t),
            ..base.clone()
        });
    }
    knobs.insert("pruning", json!(format!("measured: opacity thresholds {:?}; pruned Gaussians are culled at projection (decoders and projection still run on all)", args.prune)));
    if !args.prune_contribution.is_empty() {
        let (sums, frames) = contributions(ctx, run, args.contribution_frames)?;
        for &q in &args.prune_contribution {
            let mask = least_contributing(&sums, q);
            // The least contribution kept, as pixels of weight per frame.
            let floor = sums
                .iter()
                .zip(&mask)
                .filter(|(_, &p)| !p)
                .map(|(&c, _)| c)
                .fold(f64::INFINITY, f64::min)
                / frames as f64;
            out.push(Setting {
                knob: "contribution pruning",
                label: format!(
                    "least-contributing {:.0}% (kept: at least {floor:.3} px of weight per frame)",
                    100.0 * q
                ),
                prune_mask: Some(std::rc::Rc::new(mask)),
                ..base.clone()
            });
        }
        let zero = sums.iter().filter(|&&c| c == 0.0).count();
        knobs.insert("contribution pruning", json!(format!("measured: the fractions {:?} of the Gaussians with the least contribution (blend weight summed over the pixels of {frames} training frames, a depth-sorted render of every layer each; {zero} of {} Gaussians contribute nothing) culled at projection", args.prune_contribution, sums.len())));
    }
    for c in ["three-pass", "three-pass-occlusion", "single-pass", "fused"]
        .into_iter()
        .filter(|&c| c != default_comp)
    {
        out.push(Setting {
            knob: "compositing",
            label: c.to_string(),
            compositing: c.to_string(),
            ..base.clone()
        });
    }
    knobs.insert("compositing", json!("measured: three-pass, three-pass-occlusion, single-pass, fused (the paper's matte from one sort and one walk of every layer)"));
    let blended: Vec<&str> = run
        .avatar
        .layers
        .iter()
        .filter(|l| l.deformer.has_pose_blend())
        .map(|l| l.name.as_str())
        .collect();
    if blended.is_empty() {
        knobs.insert("pose_offsets", json!("not applicable: no layer of this run was trained with pose-dependent offsets (config body.pose_offsets / cloth.pose_offsets)"));
    } else {
        out.push(Setting {
            knob: "pose_offsets",
            label: format!("off ({} without the pose blend)", blended.join(", ")),
            pose_offsets: false,
            ..base.clone()
        });
        knobs.insert(
            "pose_offsets",
            json!(format!(
                "measured: {} rendered without the pose blend (the decoded offsets alone)",
                blended.join(", ")
            )),
        );
    }
    let subgroup = subgroup_raster_supported(ctx.info());
    let tiles: Vec<u32> = TILE_SIZES
        .into_iter()
        .filter(|&t| t != DEFAULT_TILE_SIZE && (t >= RASTER_BLOCK || subgroup))
        .collect();
    for &t in &tiles {
        out.push(Setting {
            knob: "tile size",
            label: format!("{t} x {t} tiles"),
            tile_size: t,
            ..base.clone()
        });
    }
    let why8 = if subgroup {
        ""
    } else {
        "; 8 needs the subgroup rasterizers of CPU devices, not this device's"
    };
    knobs.insert("tile_size", json!(format!("measured: tiles of {tiles:?} against the default {DEFAULT_TILE_SIZE} (the same image: a tile only groups the splats that pixels walk){why8}")));
    out.push(Setting {
        knob: "half-precision SH",
        label: "SH packed to binary16 each frame".into(),
        half_sh: true,
        ..base.clone()
    });
    knobs.insert("half_sh", json!("measured: the SH the decoders wrote packed to binary16 (round to nearest even) every frame (splat.pack_sh_half, in the time) and the projection reading the halves"));
    out.push(Setting {
        knob: "half-precision splats",
        label: "projected splats packed to binary16 (centre f32)".into(),
        half_splats: true,
        ..base.clone()
    });
    knobs.insert("half_splats", json!("measured: the projected splats packed after binning (splat.pack_splats_half, in the time: centre f32, conic, opacity, colour and depth binary16) and the forward rasterizers reading 6 words a splat instead of 10"));
    Ok((out, knobs))
}

/// Knobs this run cannot measure (each needs another trained run): no numbers.
fn not_built(run: &OpenRun) -> Vec<serde_json::Value> {
    vec![
        json!({"knob": "subdivision level", "why": format!("fixed at training (this run: subdivision {}, decimate {}); another level needs another trained run", run.config.layers.subdivision, run.config.layers.decimate)}),
    ]
}

/// The avatar's parts in the gathered cloud's order: the human layers, then the scene.
fn part_names(avatar: &Avatar) -> Vec<String> {
    avatar.counts().into_iter().map(|(n, _)| n).collect()
}

/// The SH degree of each part (the human layers in order, then the scene).
fn part_degrees(avatar: &Avatar) -> Vec<u32> {
    avatar
        .layers
        .iter()
        .map(|l| l.deformer.posed.sh_degree)
        .chain(avatar.scene.iter().map(|s| s.params.sh_degree))
        .collect()
}

/// Applies a setting's SH truncation and pruning to the decoded Gaussians (each layer's
/// `posed`, the scene's parameters, each at its own SH degree) and gathers
/// `avatar.posed` from them again; returns the Gaussians kept per part. Host reads and
/// writes, then the GPU gather.
fn apply_edits(ctx: &Context, avatar: &mut Avatar, s: &Setting) -> anyhow::Result<Vec<usize>> {
    let mut kept = Vec::new();
    // `first`: the part's first Gaussian in the gathered order.
    let edit = |op: &mut Vec<f32>,
                sh: &mut Vec<f32>,
                degree: u32,
                keep: Option<u32>,
                first: usize|
     -> usize {
        if let Some(d) = keep {
            truncate_sh(sh, degree, d);
        }
        match (s.prune, &s.prune_mask) {
            (Some(t), _) => prune_by_opacity(op, t),
            (None, Some(mask)) => {
                let n = op.len();
                prune_masked(op, &mask[first..first + n])
            }
            (None, None) => op.len(),
        }
    };
    let (mut part, mut first) = (0, 0);
    for l in &mut avatar.layers {
        let n = l.count as usize;
        let degree = l.deformer.posed.sh_degree;
        let mut op = ctx.read_buffer::<f32>(&mut l.deformer.posed.opacity_logits, n)?;
        let mut sh = ctx.read_buffer::<f32>(&mut l.deformer.posed.sh, 3 * sh_coeffs(degree) * n)?;
        kept.push(edit(&mut op, &mut sh, degree, s.sh_keep[part], first));
        ctx.write_buffer(&mut l.deformer.posed.opacity_logits, &op)?;
        ctx.write_buffer(&mut l.deformer.posed.sh, &sh)?;
        part += 1;
        first += n;
    }
    if let Some(scene) = &mut avatar.scene {
        let n = scene.count as usize;
        let degree = scene.params.sh_degree;
        let mut op = ctx.read_buffer::<f32>(&mut scene.params.opacity_logits, n)?;
        let mut sh = ctx.read_buffer::<f32>(&mut scene.params.sh, 3 * sh_coeffs(degree) * n)?;
        kept.push(edit(&mut op, &mut sh, degree, s.sh_keep[part], first));
        ctx.write_buffer(&mut scene.params.opacity_logits, &op)?;
        ctx.write_buffer(&mut scene.params.sh, &sh)?;
    }
    let mut rec = ctx.record("trade gather")?;
    avatar.record_gather(&mut rec)?;
    rec.submit_and_wait()?;
    Ok(kept)
}

/// The scene layer's trained opacity and SH (the edits change them in place; they are
/// put back after each setting).
type SceneOriginal = Option<(Vec<f32>, Vec<f32>)>;

fn read_scene(ctx: &Context, avatar: &mut Avatar) -> anyhow::Result<SceneOriginal> {
    match &mut avatar.scene {
        Some(s) => {
            let n = s.count as usize;
            let k = 3 * sh_coeffs(s.params.sh_degree);
            Ok(Some((
                ctx.read_buffer(&mut s.params.opacity_logits, n)?,
                ctx.read_buffer(&mut s.params.sh, k * n)?,
            )))
        }
        None => Ok(None),
    }
}

fn restore_scene(
    ctx: &Context,
    avatar: &mut Avatar,
    original: &SceneOriginal,
) -> anyhow::Result<()> {
    if let (Some(s), Some((op, sh))) = (&mut avatar.scene, original) {
        ctx.write_buffer(&mut s.params.opacity_logits, op)?;
        ctx.write_buffer(&mut s.params.sh, sh)?;
    }
    Ok(())
}

/// The frame's camera at `scale` (each axis rounded to whole pixels, at least 1).
fn scaled_camera(cam: &PinholeCamera, scale: f64) -> PinholeCamera {
    let w = ((f64::from(cam.width) * scale).round() as u32).max(1);
    let h = ((f64::from(cam.height) * scale).round() as u32).max(1);
    let (sx, sy) = (
        (f64::from(w) / f64::from(cam.width)) as f32,
        (f64::from(h) / f64::from(cam.height)) as f32,
    );
    PinholeCamera {
        fx: cam.fx * sx,
        cx: cam.cx * sx,
        fy: cam.fy * sy,
        cy: cam.cy * sy,
        width: w,
        height: h,
        ..*cam
    }
}

/// One rendered frame: the image at the render's size and the GPU ms by stage.
struct Rendered {
    rgb: Vec<f32>,
    size: (u32, u32),
    gpu_ms: f64,
    stages: BTreeMap<String, f64>,
    kept: Vec<usize>,
}

/// Poses, decodes, edits and renders one frame with the profile on.
fn render_frame(
    ctx: &Context,
    run: &mut OpenRun,
    renderers: &mut BTreeMap<(u32, u32, String), AvatarRenderer>,
    f: &DatasetFrame,
    s: &Setting,
) -> anyhow::Result<Rendered> {
    let cam = scaled_camera(&f.camera.to_pinhole([0.0; 3]), s.scale);
    let key = (cam.width, cam.height, s.compositing.clone());
    let renderer = match renderers.entry(key) {
        std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
        std::collections::btree_map::Entry::Vacant(e) => {
            let c = Compositing::parse(&s.compositing)?;
            e.insert(AvatarRenderer::new(
                ctx,
                &run.avatar,
                cam.width,
                cam.height,
                c,
            )?)
        }
    };
    let transforms = run.rig.frame(&f.body);
    ctx.start_profile();
    let result = (|| -> anyhow::Result<Vec<usize>> {
        run.avatar.set_frame(ctx, &transforms)?;
        for l in &mut run.avatar.layers {
            l.deformer.set_pose_blend(s.pose_offsets);
        }
        {
            let mut rec = ctx.record("trade decode and skin")?;
            run.avatar.record_forward(&mut rec, transforms.log_scale)?;
            rec.submit_and_wait()?;
        }
        let kept = if s.edits() {
            apply_edits(ctx, &mut run.avatar, s)?
        } else {
            run.avatar.counts().iter().map(|c| c.1 as usize).collect()
        };
        renderer.forward(
            ctx,
            &run.avatar,
            &cam,
            &RenderSettings {
                tile_size: s.tile_size,
                half_sh: s.half_sh,
                half_splats: s.half_splats,
                ..RenderSettings::default()
            },
        )?;
        Ok(kept)
    })();
    let profile = ctx.take_profile().unwrap_or_default();
    let kept = result?;
    let stages = crate::avatar::by_stage(&profile);
    // Host work between passes is not GPU time; "other" (none expected) is reported but
    // not counted.
    let gpu_ms = stages
        .iter()
        .filter(|(k, _)| k.as_str() != "other")
        .map(|(_, v)| v)
        .sum();
    Ok(Rendered {
        rgb: renderer.read_rgb(ctx)?,
        size: (cam.width, cam.height),
        gpu_ms,
        stages,
        kept,
    })
}

/// Image metrics against one reference.
#[derive(Clone, Copy, Debug, Default)]
struct Metrics {
    psnr: f64,
    ssim: f64,
    lpips: Option<f64>,
}

/// LPIPS networks planned per image size.
struct LpipsCache<'w> {
    weights: Option<&'w LpipsWeights>,
    nets: BTreeMap<(u32, u32), Lpips>,
}

impl LpipsCache<'_> {
    fn measure(
        &mut self,
        ctx: &Context,
        a: &[f32],
        b: &[f32],
        (w, h): (u32, u32),
    ) -> anyhow::Result<Option<f64>> {
        let Some(weights) = self.weights else {
            return Ok(None);
        };
        let net = match self.nets.entry((w, h)) {
            std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::btree_map::Entry::Vacant(e) => {
                e.insert(Lpips::new(ctx, weights, w, h)?)
            }
        };
        let (pa, pb) = (
            ctx.upload("trade lpips a", a)?,
            ctx.upload("trade lpips b", b)?,
        );
        {
            let mut rec = ctx.record("trade lpips")?;
            net.record(&mut rec, &pa, &pb, None)?;
            rec.submit_and_wait()?;
        }
        Ok(Some(net.read_value(ctx)?))
    }
}

fn metrics(
    ctx: &Context,
    lpips: &mut LpipsCache,
    a: &[f32],
    b: &[f32],
    size: (u32, u32),
) -> anyhow::Result<Metrics> {
    let (fa, fb): (Vec<f64>, Vec<f64>) = (
        a.iter().map(|&v| f64::from(v)).collect(),
        b.iter().map(|&v| f64::from(v)).collect(),
    );
    let ssim = drape_engine::ops::ssim::reference(&fa, &fb, size.0 as usize, size.1 as usize).1;
    Ok(Metrics {
        psnr: psnr(a, b),
        ssim,
        lpips: lpips.measure(ctx, a, b, size)?,
    })
}

fn mean_metrics(v: &[Metrics]) -> serde_json::Value {
    let n = v.len().max(1) as f64;
    let lp: Vec<f64> = v.iter().filter_map(|m| m.lpips).collect();
    json!({
        "psnr": v.iter().map(|m| m.psnr).sum::<f64>() / n,
        "ssim": v.iter().map(|m| m.ssim).sum::<f64>() / n,
        "lpips": (!lp.is_empty()).then(|| lp.iter().sum::<f64>() / lp.len() as f64),
    })
}

/// The ground truth a render is compared with: the whole frame with a scene layer, else
/// the person on black (as `drape eval`).
fn target(f: &DatasetFrame, whole_image: bool) -> Vec<f32> {
    if whole_image {
        return f.rgb.clone();
    }
    f.mask
        .iter()
        .enumerate()
        .flat_map(|(i, &m)| {
            if m {
                [f.rgb[3 * i], f.rgb[3 * i + 1], f.rgb[3 * i + 2]]
            } else {
                [0.0; 3]
            }
        })
        .collect()
}

pub fn run(ctx: &Context, args: &TradeArgs) -> anyhow::Result<serde_json::Value> {
    let mut run = OpenRun::open(ctx, &args.run, args.data.as_deref(), None)?;
    let mut frames: Vec<DatasetFrame> = run.test_frames().into_iter().cloned().collect();
    anyhow::ensure!(
        !frames.is_empty(),
        "{}: the run's data has no held-out frame to render",
        run.seq.dir.display()
    );
    if args.max_frames > 0 {
        frames.truncate(args.max_frames);
    }
    let lpips_path = args
        .lpips_weights
        .clone()
        .or_else(|| run.config.losses.lpips_weights.clone());
    let weights = match &lpips_path {
        Some(p) => Some(LpipsWeights::load(p, run.config.losses.lpips_net)?),
        None => None,
    };
    let mut lpips = LpipsCache {
        weights: weights.as_ref(),
        nets: BTreeMap::new(),
    };
    let whole_image = run.avatar.scene.is_some();
    let targets: Vec<Vec<f32>> = frames.iter().map(|f| target(f, whole_image)).collect();
    let scene_original = read_scene(ctx, &mut run.avatar)?;
    let (settings, knobs) = settings(ctx, args, &mut run)?;
    let parts = part_names(&run.avatar);
    let degrees = part_degrees(&run.avatar);
    let mut renderers = BTreeMap::new();
    let mut defaults: Vec<Vec<f32>> = Vec::new();
    let mut rows = Vec::new();
    for s in &settings {
        eprintln!("trade: {} {} ...", s.knob, s.label);
        for _ in crate::schedule::Runs::new(args.warmup, 0) {
            render_frame(ctx, &mut run, &mut renderers, &frames[0], s)?;
        }
        let (mut times, mut render_times, mut stages, mut vs_gt, mut vs_default) = (
            Vec::new(),
            Vec::new(),
            BTreeMap::<String, Vec<f64>>::new(),
            Vec::new(),
            Vec::new(),
        );
        let (mut kept, mut size) = (Vec::new(), (0, 0));
        for r in 0..args.runs {
            for (i, f) in frames.iter().enumerate() {
                let out = render_frame(ctx, &mut run, &mut renderers, f, s)?;
                times.push(out.gpu_ms);
                // What the knobs act on: the frame without the decoders and skinning
                // (the same work in every setting, and the noisiest on a busy CPU).
                render_times.push(
                    out.stages
                        .iter()
                        .filter(|(k, _)| !matches!(k.as_str(), "decoders" | "skinning" | "other"))
                        .map(|(_, v)| v)
                        .sum::<f64>(),
                );
                for (k, v) in out.stages {
                    stages.entry(k).or_default().push(v);
                }
                if r > 0 {
                    continue;
                }
                // Renders are deterministic: the first run's images stand for all.
                let rgb = resample(&out.rgb, out.size, (f.width, f.height));
                if defaults.len() < frames.len() {
                    defaults.push(rgb.clone());
                }
                vs_gt.push(metrics(
                    ctx,
                    &mut lpips,
                    &rgb,
                    &targets[i],
                    (f.width, f.height),
                )?);
                vs_default.push(metrics(
                    ctx,
                    &mut lpips,
                    &rgb,
                    &defaults[i],
                    (f.width, f.height),
                )?);
                if i == 0 {
                    (kept, size) = (out.kept, out.size);
                }
            }
        }
        if s.edits() {
            restore_scene(ctx, &mut run.avatar, &scene_original)?;
        }
        let ms = median(&times);
        rows.push(json!({
            "knob": s.knob,
            "setting": s.label,
            "width": size.0,
            "height": size.1,
            "compositing": s.compositing,
            "sh_degree_kept": parts.iter().zip(&s.sh_keep).zip(&degrees).map(|((p, k), &d)| (p.clone(), k.map_or(d, |k| k.min(d)))).collect::<BTreeMap<_, _>>(),
            "gaussians_kept": kept.iter().sum::<usize>(),
            "gaussians_kept_per_layer": parts.iter().cloned().zip(kept.iter().copied()).collect::<BTreeMap<_, _>>(),
            "ms_per_frame": ms,
            "render_ms_per_frame": median(&render_times),
            "fps": 1e3 / ms.max(1e-9),
            "stages_gpu_ms": stages.into_iter().map(|(k, v)| (k, median(&v))).collect::<BTreeMap<_, _>>(),
            "vs_ground_truth": mean_metrics(&vs_gt),
            "vs_default": mean_metrics(&vs_default),
        }));
    }
    let points: Vec<(f64, f64)> = rows
        .iter()
        .map(|r| {
            (
                r["ms_per_frame"].as_f64().unwrap_or(0.0),
                r["vs_ground_truth"]["psnr"].as_f64().unwrap_or(0.0),
            )
        })
        .collect();
    for (r, on) in rows.iter_mut().zip(pareto(&points)) {
        r["pareto"] = json!(on);
    }
    let out_dir = args.out.clone().unwrap_or_else(|| args.run.join("trade"));
    let mut result = json!({
        "job": "trade",
        "device": ctx.info().name,
        "device_kind": format!("{:?}", ctx.info().kind),
        "run": args.run.display().to_string(),
        "data": run.seq.dir.display().to_string(),
        "step": run.step,
        "gaussians": run.avatar.counts(),
        "sh_degree": run.avatar.sh_degree(),
        "sh_degree_per_layer": parts.iter().cloned().zip(degrees.iter().copied()).collect::<BTreeMap<String, u32>>(),
        "frames": frames.len(),
        "frame_size": [frames[0].width, frames[0].height],
        "runs": args.runs,
        "warmup": args.warmup,
        "lpips": lpips_path.map_or_else(|| json!(null), |p| json!(p.display().to_string())),
        "compared_with": if whole_image { "the whole frame (the run has a scene layer)" } else { "the person on black (the masked frame), as drape eval" },
        "ms_per_frame_is": "GPU ms of the frame's passes (decoders, skinning, projection, binning and sorts, rasterization, composite) from timestamps, median over runs x frames; the host edits of the SH and pruning settings are not counted",
        "render_ms_per_frame_is": "the same without the decoders and skinning (projection, binning and sorts, rasterization, composite: what the knobs change), median over runs x frames",
        "identical_psnr_db": IDENTICAL_PSNR_DB,
        "knobs": knobs,
        "settings": rows,
        "not_built": not_built(&run),
    });
    std::fs::create_dir_all(&out_dir).map_err(|e| anyhow::anyhow!("{}: {e}", out_dir.display()))?;
    let (ranges, png) = plot(&result);
    png.save(out_dir.join("trade.png"))
        .map_err(|e| anyhow::anyhow!("{}: {e}", out_dir.join("trade.png").display()))?;
    result["plot"] = ranges;
    write(
        &out_dir.join("trade.json"),
        &serde_json::to_string_pretty(&result)?,
    )?;
    write(&out_dir.join("trade.md"), &markdown(&result))?;
    result["written"] = json!(out_dir.display().to_string());
    Ok(result)
}

fn write(path: &Path, text: &str) -> anyhow::Result<()> {
    drape_io::write(path, text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
}

fn num(v: &serde_json::Value, digits: usize) -> String {
    v.as_f64()
        .map_or_else(|| "n/a".to_string(), |x| format!("{x:.digits$}"))
}

/// The table as Markdown, with the knobs the run cannot measure and the plot's axis ranges.
pub fn markdown(r: &serde_json::Value) -> String {
    let mut s = format!(
        "`engine-bench trade {}` on {}: {} held-out frame(s) at {}x{}, step {}, Gaussians {}; compared with {}; ms/frame: {}; render ms: {}; LPIPS {}.\n\n",
        r["run"].as_str().unwrap_or("?"),
        r["device"].as_str().unwrap_or("?"),
        r["frames"],
        r["frame_size"][0],
        r["frame_size"][1],
        r["step"],
        r["gaussians"],
        r["compared_with"].as_str().unwrap_or("?"),
        r["ms_per_frame_is"].as_str().unwrap_or("?"),
        r["render_ms_per_frame_is"].as_str().unwrap_or("?"),
        r["lpips"].as_str().unwrap_or("n/a (no weights)")
    );
    s += "| knob | setting | render size | Gaussians kept | ms/frame | render ms | FPS | PSNR vs GT (dB) | SSIM vs GT | LPIPS vs GT | PSNR vs default (dB) | SSIM vs default | LPIPS vs default | Pareto |\n";
    s += "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n";
    for row in r["settings"].as_array().into_iter().flatten() {
        let (g, d) = (&row["vs_ground_truth"], &row["vs_default"]);
        s += &format!(
            "| {} | {} | {}x{} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            row["knob"].as_str().unwrap_or("?"),
            row["setting"].as_str().unwrap_or("?"),
            row["width"],
            row["height"],
            row["gaussians_kept"],
            num(&row["ms_per_frame"], 1),
            num(&row["render_ms_per_frame"], 1),
            num(&row["fps"], 2),
            num(&g["psnr"], 2),
            num(&g["ssim"], 4),
            num(&g["lpips"], 4),
            num(&d["psnr"], 2),
            num(&d["ssim"], 4),
            num(&d["lpips"], 4),
            if row["pareto"].as_bool() == Some(true) {
                "yes"
            } else {
                ""
            }
        );
    }
    s += &format!("\nPSNR {IDENTICAL_PSNR_DB} dB: identical images. At scales other than 1 the render is resampled to the data's size (box average for integer downsampling, else bilinear) before it is compared.\n\nKnobs:\n");
    for (k, v) in r["knobs"].as_object().into_iter().flatten() {
        s += &format!("- {k}: {}\n", v.as_str().unwrap_or("?"));
    }
    s += "\nNot built (no numbers):\n";
    for n in r["not_built"].as_array().into_iter().flatten() {
        s += &format!(
            "- {}: {}\n",
            n["knob"].as_str().unwrap_or("?"),
            n["why"].as_str().unwrap_or("?")
        );
    }
    let p = &r["plot"];
    s += &format!(
        "\n`trade.png`: ms per frame on x from {} to {}, PSNR vs ground truth on y from {} to {} dB (the axes' ends; no tick labels); the red line joins the Pareto frontier. Colours: {}.\n",
        num(&p["x_min_ms"], 1),
        num(&p["x_max_ms"], 1),
        num(&p["y_min_db"], 2),
        num(&p["y_max_db"], 2),
        KNOB_COLOURS.iter().map(|(k, c, _)| format!("{k} {c}")).collect::<Vec<_>>().join(", ")
    );
    s
}

/// Point colours per knob: (knob, colour name, RGB).
const KNOB_COLOURS: [(&str, &str, [u8; 3]); 10] = [
    ("default", "black", [0, 0, 0]),
    ("resolution", "blue", [30, 90, 220]),
    ("sh_degree", "green", [20, 150, 40]),
    ("pruning", "orange", [230, 130, 0]),
    ("compositing", "purple", [140, 40, 170]),
    ("pose_offsets", "teal", [0, 150, 150]),
    ("contribution pruning", "brown", [140, 80, 20]),
    ("tile size", "grey", [130, 130, 130]),
    ("half-precision SH", "pink", [230, 80, 160]),
    ("half-precision splats", "olive", [120, 130, 0]),
];

fn put(img: &mut image::RgbImage, x: i64, y: i64, c: [u8; 3]) {
    if x >= 0 && y >= 0 && x < i64::from(img.width()) && y < i64::from(img.height()) {
        img.put_pixel(x as u32, y as u32, image::Rgb(c));
    }
}

fn line(img: &mut image::RgbImage, (ax, ay): (i64, i64), (bx, by): (i64, i64), c: [u8; 3]) {
    let steps = (bx - ax).abs().max((by - ay).abs()).max(1);
    for i in 0..=steps {
        put(
            img,
            ax + (bx - ax) * i / steps,
            ay + (by - ay) * i / steps,
            c,
        );
    }
}

/// The Pareto plot: ms per frame (x) against PSNR vs ground truth (y), each setting a
/// square in its knob's colour, the frontier a red line. Returns the axis ranges (for
/// trade.md: the image has no text) and the image.
fn plot(r: &serde_json::Value) -> (serde_json::Value, image::RgbImage) {
    const W: u32 = 640;
    const H: u32 = 480;
    const M: i64 = 40;
    let rows: Vec<&serde_json::Value> = r["settings"].as_array().into_iter().flatten().collect();
    let pts: Vec<(f64, f64, [u8; 3], bool)> = rows
        .iter()
        .map(|row| {
            let colour = KNOB_COLOURS
                .iter()
                .find(|(k, _, _)| row["knob"].as_str() == Some(k))
                .map_or([0; 3], |c| c.2);
            (
                row["ms_per_frame"].as_f64().unwrap_or(0.0),
                row["vs_ground_truth"]["psnr"].as_f64().unwrap_or(0.0),
                colour,
                row["pareto"].as_bool() == Some(true),
            )
        })
        .collect();
    let (mut x0, mut x1, mut y0, mut y1) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    for &(x, y, _, _) in &pts {
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    if !x0.is_finite() {
        (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
    }
    // 5% headroom; a degenerate range is widened so every point lands inside.
    let pad = |lo: f64, hi: f64| {
        let d = if hi - lo > 1e-9 {
            0.05 * (hi - lo)
        } else {
            0.5f64.max(0.05 * hi.abs())
        };
        (lo - d, hi + d)
    };
    let ((x0, x1), (y0, y1)) = (pad(x0, x1), pad(y0, y1));
    let mut img = image::RgbImage::from_pixel(W, H, image::Rgb([255, 255, 255]));
    let to_px = |x: f64, y: f64| -> (i64, i64) {
        let px = M as f64 + (x - x0) / (x1 - x0) * (f64::from(W) - 2.0 * M as f64);
        let py = f64::from(H) - M as f64 - (y - y0) / (y1 - y0) * (f64::from(H) - 2.0 * M as f64);
        (px.round() as i64, py.round() as i64)
    };
    // Axes: x along the bottom, y along the left.
    line(
        &mut img,
        (M, i64::from(H) - M),
        (i64::from(W) - M, i64::from(H) - M),
        [0; 3],
    );
    line(&mut img, (M, M), (M, i64::from(H) - M), [0; 3]);
    let mut frontier: Vec<(f64, f64)> = pts.iter().filter(|p| p.3).map(|p| (p.0, p.1)).collect();
    frontier.sort_by(|a, b| a.0.total_cmp(&b.0));
    for w in frontier.windows(2) {
        line(
            &mut img,
            to_px(w[0].0, w[0].1),
            to_px(w[1].0, w[1].1),
            [220, 20, 20],
        );
    }
    for &(x, y, c, on) in &pts {
        let (px, py) = to_px(x, y);
        for dy in -3..=3 {
            for dx in -3..=3 {
                // Frontier points get a red ring.
                let edge = dx == -3 || dx == 3 || dy == -3 || dy == 3;
                put(
                    &mut img,
                    px + dx,
                    py + dy,
                    if on && edge { [220, 20, 20] } else { c },
                );
            }
        }
    }
    (
        json!({"x_min_ms": x0, "x_max_ms": x1, "y_min_db": y0, "y_max_db": y1}),
        img,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use drape_engine::ops::splat::reference;
    use drape_engine::ops::splat::render::render_image;
    use drape_engine::ops::splat::scene::{frame_params, GaussianCloud};
    use drape_engine::ContextDesc;

    fn camera(w: u32, h: u32) -> PinholeCamera {
        PinholeCamera::look_at([0.3, -0.4, -5.0], [0.0; 3], [0.0, -1.0, 0.0], 45.0, w, h)
            .expect("valid camera")
    }

    fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    }

    /// The CPU reference render of `cloud` at its own SH degree.
    fn cpu_render(cloud: &GaussianCloud, cam: &PinholeCamera) -> Vec<f32> {
        let frame = frame_params(
            cam,
            &RenderSettings::default(),
            cloud.sh_degree,
            cloud.len(),
        );
        reference::render(&cloud.gaussians::<f32>(), &frame).rgb
    }

    /// `cloud` at degree `d`: its first (d + 1)² coefficients per channel.
    fn at_degree(cloud: &GaussianCloud, d: u32) -> GaussianCloud {
        let (k, kept) = (3 * cloud.sh_coeffs(), 3 * sh_coeffs(d));
        GaussianCloud {
            sh_degree: d,
            sh: cloud
                .sh
                .chunks_exact(k)
                .flat_map(|g| g[..kept].to_vec())
                .collect(),
            ..cloud.clone()
        }
    }

    /// The GPU and the CPU reference run the same f32 code; only exp/ln may differ in
    /// their last bits (the splatter's own GPU-vs-CPU tolerance,
    /// tests/tests/engine/splat_gpu.rs).
    const TOLERANCE: f32 = 1e-5;

    #[test]
    fn truncated_sh_renders_as_the_lower_degree_cloud() {
        let ctx = Context::new(&ContextDesc::for_tests()).expect("test device");
        let cam = camera(64, 48);
        let cloud = GaussianCloud::random(300, 3, 1.5, (3.0, 7.0), 0.15, 7);
        let full = cpu_render(&cloud, &cam);
        for keep in 0..3 {
            let mut t = cloud.clone();
            truncate_sh(&mut t.sh, 3, keep);
            // Rendered at degree 3 on the GPU (what the trade does) against the CPU
            // reference of the same Gaussians stored at the lower degree.
            let (gpu, _) =
                render_image(&ctx, &t, &cam, &RenderSettings::default()).expect("render");
            let cpu = cpu_render(&at_degree(&cloud, keep), &cam);
            let e = max_abs_diff(&gpu.rgb, &cpu);
            assert!(e <= TOLERANCE, "degree {keep}: GPU vs CPU reference {e:e}");
            assert!(
                max_abs_diff(&cpu, &full) > 1e-2,
                "degree {keep}: truncation must change the image"
            );
        }
    }

    #[test]
    fn pruned_gaussians_render_as_if_removed() {
        let ctx = Context::new(&ContextDesc::for_tests()).expect("test device");
        let cam = camera(64, 48);
        let cloud = GaussianCloud::random(400, 1, 1.5, (3.0, 7.0), 0.15, 11);
        for threshold in [0.3f32, 0.6, 0.9] {
            let mut pruned = cloud.clone();
            let kept = prune_by_opacity(&mut pruned.opacity_logits, threshold);
            assert!(
                kept > 0 && kept < cloud.len(),
                "threshold {threshold}: {kept} of {} kept",
                cloud.len()
            );
            // The same cloud without the pruned Gaussians, on the CPU reference.
            let keep: Vec<usize> = (0..cloud.len())
                .filter(|&i| 1.0 / (1.0 + (-cloud.opacity_logits[i]).exp()) >= threshold)
                .collect();
            assert_eq!(keep.len(), kept);
            let mut removed = GaussianCloud::new(cloud.sh_degree);
            for &i in &keep {
                removed.push(&cloud.gaussian::<f32>(i), cloud.groups[i]);
            }
            let (gpu, _) =
                render_image(&ctx, &pruned, &cam, &RenderSettings::default()).expect("render");
            let e = max_abs_diff(&gpu.rgb, &cpu_render(&removed, &cam));
            assert!(
                e <= TOLERANCE,
                "threshold {threshold}: GPU vs CPU reference without the pruned {e:e}"
            );
        }
        // Idempotent: pruning twice keeps the same.
        let mut twice = cloud.opacity_logits.clone();
        let a = prune_by_opacity(&mut twice, 0.3);
        assert_eq!(prune_by_opacity(&mut twice, 0.3), a);
        let mut nan = vec![f32::NAN, 3.0];
        assert_eq!(
            prune_by_opacity(&mut nan, 0.01),
            1,
            "a NaN opacity is pruned"
        );
    }

    /// The knob's GPU-vs-CPU test: contributions measured on the GPU, the least
    /// contributing culled, rendered on the GPU as the CPU reference renders the cloud
    /// without them; the culled ones contribute no more than any kept one.
    #[test]
    fn least_contributing_are_culled_as_if_removed() {
        use drape_engine::ops::splat::render::{GaussianBuffers, SplatRenderer};
        let ctx = Context::new(&ContextDesc::for_tests()).expect("test device");
        let cam = camera(64, 48);
        let cloud = GaussianCloud::random(400, 1, 1.5, (3.0, 7.0), 0.15, 13);
        let buffers = GaussianBuffers::upload(&ctx, "contribution cloud", &cloud).expect("upload");
        let mut renderer =
            SplatRenderer::new(&ctx, cam.width, cam.height, cloud.len()).expect("renderer");
        let saved = renderer
            .forward(&buffers, &cam, &RenderSettings::default())
            .expect("forward")
            .saved;
        let sums: Vec<f64> = renderer
            .contributions(&saved)
            .expect("contributions")
            .into_iter()
            .map(f64::from)
            .collect();
        for fraction in [0.1, 0.3, 0.6] {
            let mask = least_contributing(&sums, fraction);
            let culled = mask.iter().filter(|&&m| m).count();
            assert_eq!(culled, (fraction * cloud.len() as f64).floor() as usize);
            let most_culled = sums
                .iter()
                .zip(&mask)
                .filter(|(_, &m)| m)
                .map(|(&c, _)| c)
                .fold(0.0, f64::max);
            let least_kept = sums
                .iter()
                .zip(&mask)
                .filter(|(_, &m)| !m)
                .map(|(&c, _)| c)
                .fold(f64::INFINITY, f64::min);
            assert!(
                most_culled <= least_kept,
                "fraction {fraction}: culled {most_culled} > kept {least_kept}"
            );
            let mut pruned = cloud.clone();
            assert_eq!(
                prune_masked(&mut pruned.opacity_logits, &mask),
                cloud.len() - culled
            );
            let mut removed = GaussianCloud::new(cloud.sh_degree);
            for i in (0..cloud.len()).filter(|&i| !mask[i]) {
                removed.push(&cloud.gaussian::<f32>(i), cloud.groups[i]);
            }
            let (gpu, _) =
                render_image(&ctx, &pruned, &cam, &RenderSettings::default()).expect("render");
            let e = max_abs_diff(&gpu.rgb, &cpu_render(&removed, &cam));
            assert!(
                e <= TOLERANCE,
                "fraction {fraction}: GPU vs CPU reference without the culled {e:e}"
            );
            if fraction > 0.5 {
                assert!(
                    max_abs_diff(&gpu.rgb, &cpu_render(&cloud, &cam)) > 1e-3,
                    "culling {culled} Gaussians must change the image"
                );
            }
        }
        // Ties go by index: the same choice on every run.
        assert_eq!(
            least_contributing(&[1.0, 0.0, 0.0, 2.0], 0.25),
            [false, true, false, false]
        );
    }

    #[test]
    fn resampling_keeps_what_it_should() {
        // A 2x box average of a 2x nearest upsampling is the identity (exact in f32 for
        // these dyadic values).
        let (w, h) = (5u32, 3u32);
        let img: Vec<f32> = (0..3 * w * h).map(|i| (i % 7) as f32 / 8.0).collect();
        let mut up = vec![0.0; 12 * (w * h) as usize];
        for y in 0..2 * h as usize {
            for x in 0..2 * w as usize {
                for c in 0..3 {
                    up[3 * (y * 2 * w as usize + x) + c] =
                        img[3 * ((y / 2) * w as usize + x / 2) + c];
                }
            }
        }
        assert_eq!(resample(&up, (2 * w, 2 * h), (w, h)), img);
        // Bilinear upsampling reproduces a linear ramp inside the image (edges clamp).
        let ramp: Vec<f32> = (0..8 * 4).flat_map(|i| [(i % 8) as f32; 3]).collect();
        let big = resample(&ramp, (8, 4), (16, 8));
        for x in 1..15 {
            let want = ((x as f32 + 0.5) / 2.0 - 0.5).clamp(0.0, 7.0);
            assert!(
                (big[3 * (3 * 16 + x)] - want).abs() < 1e-6,
                "x {x}: {} vs {want}",
                big[3 * (3 * 16 + x)]
            );
        }
        assert_eq!(resample(&img, (w, h), (w, h)), img);
    }

    #[test]
    fn the_frontier_is_the_undominated_points() {
        let pts = [
            (10.0, 30.0),
            (20.0, 32.0),
            (15.0, 29.0),
            (20.0, 31.0),
            (5.0, 20.0),
            (30.0, 32.0),
        ];
        assert_eq!(pareto(&pts), [true, true, false, false, true, false]);
    }

    #[test]
    fn truncation_keeps_the_lower_coefficients() {
        let mut sh: Vec<f32> = (0..2 * 3 * 16).map(|i| i as f32 + 1.0).collect();
        truncate_sh(&mut sh, 3, 1);
        for (g, chunk) in sh.chunks_exact(48).enumerate() {
            assert!(
                chunk[..12]
                    .iter()
                    .enumerate()
                    .all(|(i, &v)| v == (48 * g + i) as f32 + 1.0),
                "{chunk:?}"
            );
            assert!(chunk[12..].iter().all(|&v| v == 0.0), "{chunk:?}");
        }
    }
}
