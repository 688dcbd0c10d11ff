//! `drape eval RUN`: measures a trained run on the held-out frames of its protocol
//! (NeuMan: every fifth frame from the second; ZJU-MoCap: the cameras not trained on):
//! PSNR, SSIM and LPIPS (with weights; n/a without) on the whole image and the human
//! crop, FID over all held-out renders against their ground truths (whole and crop;
//! with `--fid-weights`, n/a without; computed on the CPU), the cloth Gaussians'
//! Chamfer distance to the ground-truth garments where the data has them; per frame and
//! as means, printed as a table and written to
//! `OUT/eval.json` and `OUT/eval.md`, with a sheet per frame (`OUT/frameNNNN_viewV.png`:
//! ground truth | render | error ×4 | base pass | cloth pass | matte).

use std::io::Write;
use std::path::PathBuf;

use drape_cli_support::DeviceArgs;
use drape_engine::ops::lpips::LpipsWeights;
use drape_trainer::avatar::cloth_target::ground_truth_dir;
use drape_trainer::avatar::eval::{
    evaluate_with_fid, markdown_table, write_reports, EvalInputs, ERROR_GAIN,
};
use drape_trainer::avatar::run::OpenRun;
use drape_trainer::avatar::train::Progress;
use drape_trainer::metrics::fid::FidInception;

/// Options of `drape eval`.
#[derive(Clone, Debug, clap::Args)]
pub struct EvalArgs {
    /// The run directory (`drape train --out`, or `drape edit --out`).
    pub run: PathBuf,
    /// The sequence to evaluate on (default: the one the run was trained on, from its
    /// run.json; needed for a run without run.json).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// An SMPL-format body (default: the run's).
    #[arg(long)]
    pub body: Option<PathBuf>,
    /// LPIPS weights (safetensors; default: the run's config); without any, LPIPS is n/a.
    #[arg(long)]
    pub lpips_weights: Option<PathBuf>,
    /// FID Inception weights (safetensors from `scripts/fid-to-safetensors.py`, pytorch-fid's
    /// network); without them, FID is n/a.
    #[arg(long)]
    pub fid_weights: Option<PathBuf>,
    /// Where the tables and sheets go (default: RUN/eval).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

pub fn run(device: &DeviceArgs, args: &EvalArgs) -> anyhow::Result<()> {
    let ctx = device.open()?;
    let mut run = OpenRun::open(&ctx, &args.run, args.data.as_deref(), args.body.as_deref())?;
    let lpips_path = args
        .lpips_weights
        .clone()
        .or_else(|| run.config.losses.lpips_weights.clone());
    let lpips = match &lpips_path {
        Some(p) => Some(LpipsWeights::load(p, run.config.losses.lpips_net)?),
        None => None,
    };
    let fid = match &args.fid_weights {
        Some(p) => Some(FidInception::load(p)?),
        None => None,
    };
    let ground_truth = ground_truth_dir(&run.seq.dir);
    let frames: Vec<_> = run.test_frames().into_iter().cloned().collect();
    anyhow::ensure!(
        !frames.is_empty(),
        "{}: no held-out frames in this sequence's protocol",
        run.seq.dir.display()
    );
    let frame_refs: Vec<_> = frames.iter().collect();
    let staged = match &args.out {
        Some(o) => drape_cli_support::output::StagedDir::new(o, "--out", false)?,
        None => drape_cli_support::output::StagedDir::new(
            &run.dir.join("eval"),
            "the default output RUN/eval",
            true,
        )?,
    };
    let out = staged.path().to_path_buf();
    let inputs = EvalInputs {
        rig: &run.rig,
        frames: &frame_refs,
        ground_truth: ground_truth.as_deref(),
        lpips: lpips.as_ref(),
        sheets: Some(&out),
    };
    let t0 = std::time::Instant::now();
    let (mean, per_frame) = evaluate_with_fid(
        &ctx,
        &mut run.avatar,
        &mut run.renderer,
        &inputs,
        fid.as_ref(),
        &mut |p| {
            if let Progress::Eval { done, total } = p {
                eprint!("\revaluating {}/{total}   ", done + 1);
                let _ = std::io::stderr().flush();
            }
        },
    )?;
    eprintln!();
    device.check_validation(&ctx)?;
    let layers = format!(
        "body{}{}",
        if run.layers.cloth { " + cloth" } else { "" },
        if run.layers.scene { " + scene" } else { "" }
    );
    let header = format!(
        "{} ({layers}, step {}) on {}: {} held-out images, {}; LPIPS {}; FID {}",
        run.dir.display(),
        run.step,
        run.seq.dir.display(),
        per_frame.len(),
        if run.layers.scene {
            "whole frame"
        } else {
            "person on black"
        },
        match &lpips_path {
            Some(p) => format!("{} from {}", run.config.losses.lpips_net, p.display()),
            None => "n/a (no --lpips-weights)".into(),
        },
        match &args.fid_weights {
            Some(_) if per_frame.len() < 2 =>
                "n/a (fewer than 2 held-out images: no covariance)".into(),
            Some(p) => format!("pytorch-fid Inception from {}", p.display()),
            None => "n/a (no --fid-weights)".into(),
        }
    );
    write_reports(&out, &header, &mean, &per_frame)?;
    let out = staged.target().to_path_buf();
    staged.commit()?;
    println!("{}", markdown_table(&header, &mean, &per_frame));
    println!(
        "wrote {}/eval.json, eval.md and {} sheets (ground truth | render | error x{ERROR_GAIN}{}) in {:.1} s",
        out.display(),
        per_frame.len(),
        if run.renderer.is_three_pass() { " | base pass | cloth pass | matte" } else { "" },
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}
