//! Held-out evaluation of an avatar (training's end, and `drape eval`): every held-out
//! frame rendered and compared with its ground truth, per frame and as means: PSNR and
//! SSIM on the whole image and on the human crop (the person mask's bounding box, as
//! HUGS), LPIPS where weights are given, and the cloth Gaussians' Chamfer distance to
//! the ground-truth garments where the data has them; FID (a set-level metric: renders
//! against ground truths, whole and cropped, every image resized to 299) where
//! Inception weights are given ([`evaluate_with_fid`]; `drape eval --fid-weights`;
//! training's own final evaluation does not compute it). With an output directory, one
//! sheet per frame (ground truth | render | error ×4, then the base, cloth and matte
//! passes where the frame was rendered in three) and the tables `eval.json` and
//! `eval.md`.

use std::path::Path;

use drape_engine::ops::cloth_loss::Chamfer;
use drape_engine::ops::lpips::{Lpips, LpipsWeights};
use drape_engine::ops::splat::scene::RenderSettings;
use drape_engine::{BufferDesc, Context};

use crate::avatar::cloth_target;
use crate::avatar::composite::AvatarRenderer;
use crate::avatar::model::Avatar;
use crate::avatar::report::{write_json, Progress};
use crate::avatar::rig::Rig;
use crate::dataset::loader::DatasetFrame;
use crate::garment::GarmentFit;
use crate::metrics::fid::{frechet_distance_of_features, FidInception, ImageRef};
use crate::TrainerError;

/// How much the error panel of a sheet amplifies `|render - truth|` (mean over RGB).
pub const ERROR_GAIN: f32 = 4.0;

/// Peak signal-to-noise ratio (dB) of images in [0, 1].
pub fn psnr(a: &[f32], b: &[f32]) -> f64 {
    let mse = a
        .iter()
        .zip(b)
        .map(|(x, y)| f64::from(x - y).powi(2))
        .sum::<f64>()
        / a.len().max(1) as f64;
    -10.0 * mse.max(1e-20).log10()
}

/// The bounding box of a mask: (x0, y0, x1, y1), exclusive ends; None when empty.
pub fn mask_bbox(mask: &[bool], width: u32) -> Option<(u32, u32, u32, u32)> {
    let mut b: Option<(u32, u32, u32, u32)> = None;
    for (i, _) in mask.iter().enumerate().filter(|(_, &m)| m) {
        let (x, y) = (i as u32 % width, i as u32 / width);
        b = Some(match b {
            None => (x, y, x + 1, y + 1),
            Some((x0, y0, x1, y1)) => (x0.min(x), y0.min(y), x1.max(x + 1), y1.max(y + 1)),
        });
    }
    b
}

/// The pixels of an HWC RGB image inside `(x0, y0, x1, y1)` (exclusive ends).
pub fn crop(rgb: &[f32], width: u32, (x0, y0, x1, y1): (u32, u32, u32, u32)) -> Vec<f32> {
    let mut out = Vec::new();
    for y in y0..y1 {
        let row = 3 * (y * width) as usize;
        out.extend_from_slice(&rgb[row + 3 * x0 as usize..row + 3 * x1 as usize]);
    }
    out
}

/// Held-out metrics: means over the evaluated frames.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct EvalMetrics {
    pub frames: usize,
    /// Whole image: the frame itself with a scene layer, else the person on black.
    pub psnr_full: f64,
    /// The person mask's bounding box (HUGS's human crop).
    pub psnr_crop: f64,
    /// SSIM (11 × 11 Gaussian window, zero padding, as the loss) on the same images.
    pub ssim_full: f64,
    pub ssim_crop: f64,
    /// The cloth Gaussians' Chamfer distance to the ground-truth garments (metres,
    /// `½ (mean d(p, Q) + mean d(q, P))`), over the held-out frames that have them
    /// (synthetic data); None without a cloth layer or ground truth.
    pub cloth_chamfer: Option<f64>,
    /// LPIPS (the configured network) on the same images; None (n/a) without weights.
    pub lpips_full: Option<f64>,
    pub lpips_crop: Option<f64>,
    /// FID of the renders against the ground truths over all evaluated frames (whole
    /// image, and human crops); None (n/a) without Inception weights or with fewer
    /// than two images.
    pub fid_full: Option<f64>,
    pub fid_crop: Option<f64>,
}

/// One held-out frame's metrics (the fields as in [`EvalMetrics`]; a frame with an
/// empty person mask has no crop: its crop values are None).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct FrameMetrics {
    pub frame: usize,
    pub view: usize,
    pub psnr_full: f64,
    pub psnr_crop: Option<f64>,
    pub ssim_full: f64,
    pub ssim_crop: Option<f64>,
    pub lpips_full: Option<f64>,
    pub lpips_crop: Option<f64>,
    pub cloth_chamfer: Option<f64>,
}

/// What [`evaluate`] needs besides the avatar.
pub struct EvalInputs<'a> {
    pub rig: &'a Rig,
    pub frames: &'a [&'a DatasetFrame],
    /// The ground-truth garments (`gt/garments` of synthetic data), if any.
    pub ground_truth: Option<&'a Path>,
    pub lpips: Option<&'a LpipsWeights>,
    /// Where the sheets go (one PNG per frame); None writes nothing.
    pub sheets: Option<&'a Path>,
}

/// Renders every held-out frame (on black without a scene layer, compared with the
/// masked ground truth; with one, the whole frame) and measures it.
pub fn evaluate(
    ctx: &Context,
    avatar: &mut Avatar,
    renderer: &mut AvatarRenderer,
    inputs: &EvalInputs,
    progress: &mut dyn FnMut(Progress),
) -> crate::Result<(EvalMetrics, Vec<FrameMetrics>)> {
    evaluate_with_fid(ctx, avatar, renderer, inputs, None, progress)
}

/// [`evaluate`], and with `fid` the FID of the renders against the ground truths, on
/// the whole images and on the human crops (the mask's bounding box, unwidened), on the
/// CPU (four Inception passes per frame, about 5.7 GFLOP each).
pub fn evaluate_with_fid(
    ctx: &Context,
    avatar: &mut Avatar,
    renderer: &mut AvatarRenderer,
    inputs: &EvalInputs,
    fid: Option<&FidInception>,
    progress: &mut dyn FnMut(Progress),
) -> crate::Result<(EvalMetrics, Vec<FrameMetrics>)> {
    let whole_image = avatar.scene.is_some();
    let settings = RenderSettings::default();
    // Both fits' T-shirts are named `tshirt`: the names do not depend on the fit.
    let names: Vec<String> = cloth_target::garments(inputs.rig, GarmentFit::Tight)
        .iter()
        .map(|g| g.name.clone())
        .collect();
    let names: Vec<&str> = names.iter().map(String::as_str).collect();
    let mut per_frame = Vec::with_capacity(inputs.frames.len());
    // Features of (render, truth) on the whole image and on the crop, frame by frame.
    let mut features: [[Vec<Vec<f32>>; 2]; 2] = Default::default();
    for (k, f) in inputs.frames.iter().enumerate() {
        progress(Progress::Eval {
            done: k,
            total: inputs.frames.len(),
        });
        let mut m = FrameMetrics {
            frame: f.frame,
            view: f.view,
            ..FrameMetrics::default()
        };
        let ft = inputs.rig.frame(&f.body);
        avatar.set_frame(ctx, &ft)?;
        {
            let mut rec = ctx.record("eval forward")?;
            avatar.record_forward(&mut rec, ft.log_scale)?;
            rec.submit_and_wait()?;
        }
        if let (Some(dir), Some(cloth)) = (inputs.ground_truth, avatar.cloth()) {
            if let Some(points) = cloth_target::ground_truth(dir, &names, f.frame)? {
                m.cloth_chamfer = Some(cloth_chamfer(ctx, cloth, &points)?);
            }
        }
        renderer.forward(ctx, avatar, &f.camera.to_pinhole([0.0; 3]), &settings)?;
        let rgb = renderer.read_rgb(ctx)?;
        let target = if whole_image {
            f.rgb.clone()
        } else {
            f.masked_rgb([0.0; 3])
        };
        m.psnr_full = psnr(&rgb, &target);
        m.ssim_full = ssim_of(&rgb, &target, f.width, f.height);
        if let Some(w) = inputs.lpips {
            m.lpips_full = Some(lpips_of(ctx, w, &rgb, &target, f.width, f.height)?);
        }
        if let Some(b) = mask_bbox(&f.mask, f.width) {
            let (cr, ct) = (crop(&rgb, f.width, b), crop(&target, f.width, b));
            m.psnr_crop = Some(psnr(&cr, &ct));
            m.ssim_crop = Some(ssim_of(&cr, &ct, b.2 - b.0, b.3 - b.1));
            if let Some(net) = fid {
                let (w, h) = (b.2 - b.0, b.3 - b.1);
                let pair = net.features_of_images(&[
                    ImageRef {
                        rgb: &cr,
                        width: w,
                        height: h,
                    },
                    ImageRef {
                        rgb: &ct,
                        width: w,
                        height: h,
                    },
                ])?;
                let [fr, ft] =
                    <[Vec<f32>; 2]>::try_from(pair).expect("one feature vector per image");
                features[1][0].push(fr);
                features[1][1].push(ft);
            }
            if let Some(w) = inputs.lpips {
                // A crop below the network's minimum is widened to it (centred, clamped).
                let min = LpipsWeights::min_side(w.net);
                let grow = |lo: u32, hi: u32, size: u32| -> (u32, u32) {
                    let want = (hi - lo).max(min.min(size));
                    let lo = (lo + hi).saturating_sub(want) / 2;
                    let lo = lo.min(size - want);
                    (lo, lo + want)
                };
                let (x0, x1) = grow(b.0, b.2, f.width);
                let (y0, y1) = grow(b.1, b.3, f.height);
                let bb = (x0, y0, x1, y1);
                m.lpips_crop = Some(lpips_of(
                    ctx,
                    w,
                    &crop(&rgb, f.width, bb),
                    &crop(&target, f.width, bb),
                    x1 - x0,
                    y1 - y0,
                )?);
            }
        }
        if let Some(net) = fid {
            let pair = net.features_of_images(&[
                ImageRef {
                    rgb: &rgb,
                    width: f.width,
                    height: f.height,
                },
                ImageRef {
                    rgb: &target,
                    width: f.width,
                    height: f.height,
                },
            ])?;
            let [fr, ft] = <[Vec<f32>; 2]>::try_from(pair).expect("one feature vector per image");
            features[0][0].push(fr);
            features[0][1].push(ft);
        }
        if let Some(dir) = inputs.sheets {
            let mut panels = vec![target.clone(), rgb.clone(), error_panel(&rgb, &target)];
            if let Some(passes) = renderer.read_passes()? {
                panels.extend(passes);
            }
            let sheet = side_by_side(&panels, f.width as usize, f.height as usize);
            crate::dataset::image::write_rgb(
                &dir.join(format!("frame{:04}_view{}.png", f.frame, f.view)),
                panels.len() as u32 * f.width,
                f.height,
                &sheet,
            )?;
        }
        per_frame.push(m);
    }
    let mut mean = mean_metrics(&per_frame);
    // Fewer than two images leave no covariance: n/a, as without weights.
    let fid_of = |[renders, truths]: &[Vec<Vec<f32>>; 2]| -> crate::Result<Option<f64>> {
        if renders.len() < 2 {
            return Ok(None);
        }
        frechet_distance_of_features(renders, truths).map(Some)
    };
    mean.fid_full = fid_of(&features[0])?;
    mean.fid_crop = fid_of(&features[1])?;
    Ok((mean, per_frame))
}

/// Means over frames; crop and LPIPS means over the frames that have them.
pub fn mean_metrics(frames: &[FrameMetrics]) -> EvalMetrics {
    let n = frames.len().max(1) as f64;
    let mean_of = |get: &dyn Fn(&FrameMetrics) -> Option<f64>| -> Option<f64> {
        let v: Vec<f64> = frames.iter().filter_map(get).collect();
        (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    };
    EvalMetrics {
        frames: frames.len(),
        psnr_full: frames.iter().map(|f| f.psnr_full).sum::<f64>() / n,
        psnr_crop: mean_of(&|f| f.psnr_crop).unwrap_or(0.0),
        ssim_full: frames.iter().map(|f| f.ssim_full).sum::<f64>() / n,
        ssim_crop: mean_of(&|f| f.ssim_crop).unwrap_or(0.0),
        cloth_chamfer: mean_of(&|f| f.cloth_chamfer),
        lpips_full: mean_of(&|f| f.lpips_full),
        lpips_crop: mean_of(&|f| f.lpips_crop),
        fid_full: None,
        fid_crop: None,
    }
}

/// `|a - b|` averaged over RGB, times [`ERROR_GAIN`], as grey.
fn error_panel(a: &[f32], b: &[f32]) -> Vec<f32> {
    a.chunks_exact(3)
        .zip(b.chunks_exact(3))
        .flat_map(|(p, q)| {
            [ERROR_GAIN * ((p[0] - q[0]).abs() + (p[1] - q[1]).abs() + (p[2] - q[2]).abs()) / 3.0;
                3]
        })
        .collect()
}

/// HWC images of one size placed left to right.
fn side_by_side(panels: &[Vec<f32>], width: usize, height: usize) -> Vec<f32> {
    let mut sheet = Vec::with_capacity(panels.len() * 3 * width * height);
    for y in 0..height {
        for p in panels {
            sheet.extend_from_slice(&p[3 * y * width..3 * (y + 1) * width]);
        }
    }
    sheet
}

/// Writes `eval.json` (means and per-frame values) and `eval.md` (the same as a
/// Markdown table) into `dir`; `header` is a line saying what was evaluated.
pub fn write_reports(
    dir: &Path,
    header: &str,
    mean: &EvalMetrics,
    frames: &[FrameMetrics],
) -> crate::Result<()> {
    write_json(
        &dir.join("eval.json"),
        &serde_json::json!({ "evaluated": header, "mean": mean, "frames": frames }),
    )?;
    let path = dir.join("eval.md");
    drape_io::write(&path, markdown_table(header, mean, frames))
        .map_err(|e| TrainerError::io(&path, e))
}

fn fmt(v: Option<f64>, digits: usize, scale: f64) -> String {
    v.map_or_else(
        || "n/a".to_string(),
        |v| format!("{:.*}", digits, v * scale),
    )
}

/// The metrics as a Markdown table: one row per frame, then the mean.
pub fn markdown_table(header: &str, mean: &EvalMetrics, frames: &[FrameMetrics]) -> String {
    let mut s = format!("{header}\n\n| frame | view | PSNR full (dB) | PSNR crop (dB) | SSIM full | SSIM crop | LPIPS full | LPIPS crop | cloth Chamfer (mm) |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n");
    for f in frames {
        s += &format!(
            "| {} | {} | {:.2} | {} | {:.4} | {} | {} | {} | {} |\n",
            f.frame,
            f.view,
            f.psnr_full,
            fmt(f.psnr_crop, 2, 1.0),
            f.ssim_full,
            fmt(f.ssim_crop, 4, 1.0),
            fmt(f.lpips_full, 4, 1.0),
            fmt(f.lpips_crop, 4, 1.0),
            fmt(f.cloth_chamfer, 2, 1e3)
        );
    }
    s += &format!(
        "| **mean of {}** | | **{:.2}** | **{:.2}** | **{:.4}** | **{:.4}** | **{}** | **{}** | **{}** |\n",
        mean.frames,
        mean.psnr_full,
        mean.psnr_crop,
        mean.ssim_full,
        mean.ssim_crop,
        fmt(mean.lpips_full, 4, 1.0),
        fmt(mean.lpips_crop, 4, 1.0),
        fmt(mean.cloth_chamfer, 2, 1e3)
    );
    // FID is one number per set, not per frame; with tens of images it is biased upward
    // (a 2048-d covariance from so few), so it compares runs on the same frames only.
    s += &format!(
        "\nFID (the {} renders against their ground truths, pytorch-fid's 2048-d pool3; compare only on the same frames): full **{}**, human crop **{}**\n",
        mean.frames,
        fmt(mean.fid_full, 2, 1.0),
        fmt(mean.fid_crop, 2, 1.0)
    );
    s
}

/// LPIPS of two HWC images on the GPU (a network planned for their size).
fn lpips_of(
    ctx: &Context,
    weights: &LpipsWeights,
    a: &[f32],
    b: &[f32],
    width: u32,
    height: u32,
) -> crate::Result<f64> {
    let mut l = Lpips::new(ctx, weights, width, height)?;
    let pa = ctx.upload("eval lpips a", a)?;
    let pb = ctx.upload("eval lpips b", b)?;
    {
        let mut rec = ctx.record("eval lpips")?;
        l.record(&mut rec, &pa, &pb, None)?;
        rec.submit_and_wait()?;
    }
    Ok(l.read_value(ctx)?)
}

/// The plain Chamfer distance between the cloth layer's posed centres (of the last
/// forward pass) and `points`, on the GPU.
fn cloth_chamfer(
    ctx: &Context,
    cloth: &crate::avatar::layer::HumanLayer,
    points: &[[f32; 3]],
) -> drape_engine::Result<f64> {
    let m = points.len() as u32;
    let chamfer = Chamfer::new(ctx, cloth.count, m)?;
    let mut target = ctx.create_buffer(
        "eval garment points",
        BufferDesc::gpu_only(12 * u64::from(m.max(1))),
    )?;
    ctx.write_buffer(
        &mut target,
        &points.iter().flatten().copied().collect::<Vec<f32>>(),
    )?;
    {
        let mut rec = ctx.record("eval cloth chamfer")?;
        chamfer.record(
            &mut rec,
            &cloth.deformer.posed.means,
            cloth.count,
            &target,
            m,
            1.0,
            None,
        )?;
        rec.submit_and_wait()?;
    }
    let mut chamfer = chamfer;
    Ok(chamfer.read_value(ctx)?.distance)
}

/// Mean SSIM (the training loss's form, `ops::ssim`) computed on the CPU in f64.
fn ssim_of(a: &[f32], b: &[f32], width: u32, height: u32) -> f64 {
    let (a, b): (Vec<f64>, Vec<f64>) = (
        a.iter().map(|&v| f64::from(v)).collect(),
        b.iter().map(|&v| f64::from(v)).collect(),
    );
    drape_engine::ops::ssim::reference(&a, &b, width as usize, height as usize).1
}
