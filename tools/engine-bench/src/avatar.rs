//! `engine-bench avatar RUN`: the frame rate of a trained avatar (a `drape train` run)
//! and where a frame goes. For each image size and compositing variant: the held-out
//! view's camera scaled to the size, the avatar posed as in that frame, and per frame
//! the decoders (triplane + MLPs), skinning, projection, binning and sorts,
//! rasterization and composite, each as GPU ms from the context's profile; median
//! frame time and FPS. Then, unless `--train-steps 0`, training it/s with the split of
//! a step: a fresh model from the run's configuration and data trained for that many
//! steps in a temporary directory (the run itself is not touched; the decoders' initial
//! fit is shortened to `--fit-steps`, which changes nothing about a step's cost).
//!
//! Then the library path (`drape_trainer::avatar::player`) with 1, 2 and 3 frames in
//! flight side by side (`--in-flight`): FPS and the host's fence waits.
//!
//! Every three-pass frame is one submission whose renders the recorder interleaves;
//! `fused` renders the same images from one sort and one rasterization. The training
//! measurement uses the run's own compositing or `--train-compositing` (`fused` trains
//! too, through its one-walk backward). It measures a trained run only: there is no
//! synthetic model of the paper's size to measure without one.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;

use drape_cli_support::median;
use drape_engine::ops::splat::scene::RenderSettings;
use drape_engine::{Context, Profile};
use drape_trainer::avatar::composite::{AvatarRenderer, Compositing};
use drape_trainer::avatar::run::OpenRun;
use drape_trainer::avatar::train::{body_model, Progress, TrainJob};
use serde_json::json;

/// Options of `engine-bench avatar`.
#[derive(Clone, Debug, clap::Args)]
pub struct AvatarArgs {
    /// A finished `drape train` run directory (config.json, model.npz, run.json).
    pub run: PathBuf,
    /// The sequence the run was trained on, when run.json is missing or the data moved.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Image sizes, WIDTHxHEIGHT, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "512x512,1920x1080", value_parser = crate::splat::parse_size)]
    pub sizes: Vec<(u32, u32)>,
    /// Compositing variants: three-pass (the paper's), three-pass-occlusion, single-pass,
    /// fused (the paper's three images from one sort and one rasterization),
    /// fused-occlusion.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "three-pass,three-pass-occlusion,fused,single-pass"
    )]
    pub compositing: Vec<String>,
    /// Timed frames per configuration (the median is reported).
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..))]
    pub runs: u32,
    /// Untimed warm-up frames first (at least this many, and for at least --warm-seconds).
    #[arg(long, default_value_t = 1)]
    pub warmup: u32,
    /// Training steps to time (0: skip the training measurement).
    #[arg(long, default_value_t = 10)]
    pub train_steps: u32,
    /// Untimed training steps before the timed ones (the first steps build pipelines and
    /// find a GPU at idle clocks; their time and GPU passes are left out).
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..))]
    pub train_warmup: u32,
    /// The compositing the training measurement trains through (default: the run's).
    #[arg(long)]
    pub train_compositing: Option<String>,
    /// Steps of the decoders' initial fit before the timed training steps.
    #[arg(long, default_value_t = 20)]
    pub fit_steps: u32,
    /// Frames in flight to compare (the library path, `drape_trainer::avatar::player`:
    /// one submission a frame, frame i waiting only for frame i - k), at the first size.
    #[arg(long, value_delimiter = ',', default_value = "1,2,3", value_parser = clap::value_parser!(u32).range(1..=8))]
    pub in_flight: Vec<u32>,
    /// Timed frames per frames-in-flight setting (after `--warmup` untimed ones).
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u32).range(1..))]
    pub flight_frames: u32,
    /// Print one JSON object on stdout instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// The stage a pass belongs to, by its name.
fn stage(pass: &str) -> &'static str {
    let starts = |p: &str| pass.starts_with(p);
    if starts("nn.") || starts("mlp.") || starts("triplane.") {
        "decoders"
    } else if starts("deform.") || starts("skinning.") || starts("layer.") {
        "skinning"
    } else if starts("splat.project") || starts("splat.pack_sh_half") {
        "projection"
    } else if starts("radix_sort.")
        || starts("splat.scan")
        || starts("splat.gather_counts")
        || starts("splat.emit_intersections")
        || starts("splat.tile_ranges")
    {
        "binning and sorts"
    } else if starts("splat.rasterize") || starts("splat.pack_splats_half") {
        "rasterization"
    } else if starts("composite.") {
        "composite"
    } else {
        "other"
    }
}

pub(crate) fn by_stage(profile: &Profile) -> BTreeMap<String, f64> {
    let mut stages = BTreeMap::new();
    for (name, e) in &profile.gpu_passes {
        *stages.entry(stage(name).to_string()).or_insert(0.0) += e.ms;
    }
    stages
}

fn render_variant(
    ctx: &Context,
    run: &mut OpenRun,
    args: &AvatarArgs,
    (w, h): (u32, u32),
    variant: &str,
) -> anyhow::Result<serde_json::Value> {
    let compositing = Compositing::parse(variant).context("--compositing")?;
    let frame = *run.test_frames().first().ok_or_else(|| {
        anyhow::anyhow!(
            "{}: the run's data has no held-out frame to pose the avatar in",
            run.dir.display()
        )
    })?;
    let (body, mut camera) = (frame.body.clone(), frame.camera);
    // The held-out view at the benchmark's size (each axis scaled on its own).
    let (sx, sy) = (
        f64::from(w) / f64::from(camera.width),
        f64::from(h) / f64::from(camera.height),
    );
    (
        camera.fx,
        camera.cx,
        camera.fy,
        camera.cy,
        camera.width,
        camera.height,
    ) = (
        camera.fx * sx,
        camera.cx * sx,
        camera.fy * sy,
        camera.cy * sy,
        w,
        h,
    );
    let pinhole = camera.to_pinhole([0.5; 3]);
    let transforms = run.rig.frame(&body);
    let mut renderer = AvatarRenderer::new(ctx, &run.avatar, w, h, compositing)?;
    let settings = RenderSettings::default();
    let mut totals: Vec<f64> = Vec::new();
    // Each stage's and GPU scope's times, one per timed run.
    let mut stages: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let mut scopes: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let mut work = drape_engine::RecordedWork::default();
    for timed in crate::schedule::Runs::new(args.warmup, args.runs) {
        ctx.start_profile();
        let work_before = ctx.recorded_work();
        let t0 = Instant::now();
        // A viewer poses the avatar every frame: the decoders and skinning run each time.
        run.avatar.set_frame(ctx, &transforms)?;
        {
            let mut rec = ctx.record("avatar decode and skin")?;
            run.avatar.record_forward(&mut rec, transforms.log_scale)?;
            rec.submit_and_wait()?;
        }
        renderer.forward(ctx, &run.avatar, &pinhole, &settings)?;
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        work = ctx.recorded_work() - work_before;
        let profile = ctx.take_profile().unwrap_or_default();
        if !timed {
            continue;
        }
        totals.push(ms);
        for (k, v) in by_stage(&profile) {
            stages.entry(k).or_default().push(v);
        }
        for (k, e) in &profile.gpu_scopes {
            scopes.entry(k.clone()).or_default().push(e.ms);
        }
    }
    let frame_ms = median(&totals);
    let stages: BTreeMap<String, f64> = stages.into_iter().map(|(k, v)| (k, median(&v))).collect();
    Ok(json!({
        "width": w,
        "height": h,
        "compositing": variant,
        "passes_rendered": if renderer.is_three_pass() && !renderer.is_fused() { 3 } else { 1 },
        "frame_median_ms": frame_ms,
        "fps": 1e3 / frame_ms,
        // The same every frame (the recordings do not depend on the data).
        "dispatches_per_frame": work.dispatches,
        "barriers_per_frame": work.barriers,
        "stages_gpu_ms": stages,
        // Per layer (its decoders and skinning) and per render of the composite.
        "scopes_gpu_ms": scopes.into_iter().map(|(k, v)| (k, median(&v))).collect::<BTreeMap<_, _>>(),
    }))
}

/// Frames in flight side by side: for each k, the player with k slots renders
/// `args.flight_frames` frames (the held-out frame's pose, its camera scaled to `size`)
/// without reading them back; FPS from the first submission to the last frame's
/// completion, and the host's fence waits (N - k).
fn frames_in_flight(
    ctx: &Context,
    args: &AvatarArgs,
    (w, h): (u32, u32),
) -> anyhow::Result<serde_json::Value> {
    use drape_engine::SubmitSync;
    use drape_trainer::avatar::player::{AvatarPlayer, ViewCamera};
    let mut rows = Vec::new();
    for &k in &args.in_flight {
        let before = ctx.memory_in_use();
        let mut player = AvatarPlayer::load(ctx, &args.run, k as usize)?;
        let loaded = ctx.memory_in_use();
        let c = player.default_camera();
        let (sx, sy) = (
            f64::from(w) / f64::from(c.width),
            f64::from(h) / f64::from(c.height),
        );
        let mut cam = ViewCamera::from_camera(c);
        (cam.fx, cam.cx, cam.fy, cam.cy) = (
            cam.fx * sx as f32,
            cam.cx * sx as f32,
            cam.fy * sy as f32,
            cam.cy * sy as f32,
        );
        // Warm-up: pipelines, and the renderers' intersection buffers grown to the frame.
        for _ in 0..args.warmup.max(1) + k {
            player.submit_frame(&cam, w, h, &SubmitSync::default(), None)?;
        }
        player.wait_idle()?;
        // What an app that embeds the avatar holds on the device: the player's weights
        // and Gaussians, then with its frames' buffers grown to this size.
        let warm = ctx.memory_in_use();
        let (waits, work, t0) = (ctx.fence_waits(), ctx.recorded_work(), Instant::now());
        for _ in 0..args.flight_frames {
            player.submit_frame(&cam, w, h, &SubmitSync::default(), None)?;
        }
        let waits_in_loop = ctx.fence_waits() - waits;
        let work = ctx.recorded_work() - work;
        player.wait_idle()?;
        let seconds = t0.elapsed().as_secs_f64();
        rows.push(json!({
            "frames_in_flight": k,
            "frames": args.flight_frames,
            "fps": f64::from(args.flight_frames) / seconds.max(1e-9),
            "ms_per_frame": 1e3 * seconds / f64::from(args.flight_frames),
            "fence_waits_while_submitting": waits_in_loop,
            "dispatches_per_frame": work.dispatches as f64 / f64::from(args.flight_frames),
            "barriers_per_frame": work.barriers as f64 / f64::from(args.flight_frames),
            "overflowed_frames": player.overflowed_frames(),
            "device_memory_loaded_bytes": loaded.allocated_bytes.saturating_sub(before.allocated_bytes),
            "device_memory_with_frames_bytes": warm.allocated_bytes.saturating_sub(before.allocated_bytes),
        }));
    }
    Ok(json!({ "width": w, "height": h, "settings": rows }))
}

/// Trains a fresh model from the run's configuration for `args.train_warmup +
/// args.train_steps` steps in a temporary directory, profiling the last
/// `args.train_steps`: it/s and the GPU split of one step.
fn train_steps(
    ctx: &Context,
    run: &OpenRun,
    args: &AvatarArgs,
) -> anyhow::Result<serde_json::Value> {
    let out = std::env::temp_dir().join(format!("engine-bench-avatar-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    std::fs::create_dir_all(&out)?;
    let mut config = run.config.clone();
    let total = args.train_warmup + args.train_steps;
    config.schedule.steps = total;
    config.schedule.fit_steps = args.fit_steps;
    config.schedule.checkpoint_every = 0;
    if let Some(c) = &args.train_compositing {
        config.layers.compositing = Compositing::parse(c).context("--train-compositing")?;
    }
    // A progress event after every step: the clock and the profile start after the
    // warm-up steps and stop after the last step (before the evaluation).
    config.schedule.log_every = 1;
    let model = body_model(run.info.body.as_deref())?;
    let (mut timed_from, mut timed_to, mut profile) = (None, None, None);
    let report = TrainJob::new(&run.seq, model, &config, &out)
        .progress(&mut |p| {
            if let Progress::Step { step, .. } = p {
                if step == args.train_warmup {
                    ctx.start_profile();
                    timed_from = Some(Instant::now());
                }
                if step == total {
                    timed_to = Some(Instant::now());
                    profile = ctx.take_profile();
                }
            }
        })
        .train(ctx);
    let _ = ctx.take_profile();
    let _ = std::fs::remove_dir_all(&out);
    let report = report?;
    let (Some(from), Some(to), Some(profile)) = (timed_from, timed_to, profile) else {
        anyhow::bail!("training stopped before its {total} steps");
    };
    let seconds = to.duration_since(from).as_secs_f64();
    let profile = serde_json::to_value(&profile)?;
    let steps = f64::from(args.train_steps.max(1));
    let mut stages: BTreeMap<String, f64> = BTreeMap::new();
    let mut passes: Vec<(String, f64)> = Vec::new();
    for (name, e) in profile["gpu_passes"].as_object().into_iter().flatten() {
        let ms = e["ms"].as_f64().unwrap_or(0.0) / steps;
        *stages.entry(train_stage(name).to_string()).or_insert(0.0) += ms;
        passes.push((name.clone(), ms));
    }
    passes.sort_by(|a, b| b.1.total_cmp(&a.1));
    let scopes: BTreeMap<String, f64> = profile["gpu_scopes"]
        .as_object()
        .into_iter()
        .flatten()
        .map(|(k, e)| (k.clone(), e["ms"].as_f64().unwrap_or(0.0) / steps))
        .collect();
    Ok(json!({
        "compositing": config.layers.compositing,
        "steps": args.train_steps,
        "warmup_steps": args.train_warmup,
        "iterations_per_second": steps / seconds.max(1e-9),
        "ms_per_step": 1e3 * seconds / steps,
        "stages_gpu_ms_per_step": stages,
        "scopes_gpu_ms_per_step": scopes,
        "top_passes_gpu_ms_per_step": passes.into_iter().take(8).collect::<BTreeMap<_, _>>(),
        "gaussians": report.gaussians,
    }))
}

/// A training step's stages: the render stages, the losses, and the optimiser.
fn train_stage(pass: &str) -> &'static str {
    match stage(pass) {
        "other" if pass.starts_with("adam") => "adam",
        "other"
            if pass.starts_with("ssim.")
                || pass.starts_with("loss.")
                || pass.starts_with("lpips.") =>
        {
            "image losses"
        }
        "other"
            if pass.starts_with("chamfer.")
                || pass.starts_with("arap.")
                || pass.starts_with("cloth.") =>
        {
            "cloth losses"
        }
        s => s,
    }
}

pub fn run(ctx: &Context, args: &AvatarArgs) -> anyhow::Result<serde_json::Value> {
    let mut run = OpenRun::open(ctx, &args.run, args.data.as_deref(), None)?;
    let mut results = Vec::new();
    for &size in &args.sizes {
        for variant in &args.compositing {
            eprintln!("avatar: {}x{} {variant} ...", size.0, size.1);
            results.push(render_variant(ctx, &mut run, args, size, variant)?);
        }
    }
    let in_flight = match args.sizes.first() {
        Some(&size) if !args.in_flight.is_empty() => {
            eprintln!(
                "avatar: frames in flight {:?} at {}x{} ...",
                args.in_flight, size.0, size.1
            );
            frames_in_flight(ctx, args, size)?
        }
        _ => json!("skipped (no --in-flight or --sizes)"),
    };
    let training = if args.train_steps > 0 {
        eprintln!(
            "avatar: training {} steps (fresh model, temporary directory) ...",
            args.train_steps
        );
        train_steps(ctx, &run, args)?
    } else {
        json!("skipped (--train-steps 0)")
    };
    Ok(json!({
        "job": "avatar",
        "device": ctx.info().name,
        "device_kind": format!("{:?}", ctx.info().kind),
        "run": args.run.display().to_string(),
        "gaussians": run.avatar.counts(),
        "runs": args.runs,
        "warmup": args.warmup,
        "render": results,
        "frames_in_flight": in_flight,
        "training": training,
        "not_built": ["a synthetic paper-size model without a run"],
    }))
}

pub fn print_table(r: &serde_json::Value) {
    println!(
        "avatar {} on {} ({} frames, median); Gaussians {}",
        r["run"].as_str().unwrap_or("?"),
        r["device"].as_str().unwrap_or("?"),
        r["runs"],
        r["gaussians"]
    );
    for c in r["render"].as_array().into_iter().flatten() {
        let stages: Vec<String> = c["stages_gpu_ms"]
            .as_object()
            .into_iter()
            .flatten()
            .map(|(k, v)| format!("{k} {:.1}", v.as_f64().unwrap_or(0.0)))
            .collect();
        println!(
            "  {}x{} {:<22} {:>9.1} ms {:>6.2} FPS | {} dispatches, {} barriers | GPU ms: {}",
            c["width"],
            c["height"],
            c["compositing"].as_str().unwrap_or("?"),
            c["frame_median_ms"].as_f64().unwrap_or(0.0),
            c["fps"].as_f64().unwrap_or(0.0),
            c["dispatches_per_frame"],
            c["barriers_per_frame"],
            stages.join(", ")
        );
    }
    let f = &r["frames_in_flight"];
    let flight: Vec<String> = f["settings"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|s| {
            format!(
                "{} in flight {:.2} FPS ({} waits, {:.1} MiB on the device)",
                s["frames_in_flight"],
                s["fps"].as_f64().unwrap_or(0.0),
                s["fence_waits_while_submitting"],
                s["device_memory_with_frames_bytes"].as_f64().unwrap_or(0.0) / (1024.0 * 1024.0)
            )
        })
        .collect();
    if !flight.is_empty() {
        println!(
            "  {}x{} library frames: {}",
            f["width"],
            f["height"],
            flight.join(" | ")
        );
    }
    let t = &r["training"];
    if let Some(its) = t["iterations_per_second"].as_f64() {
        let stages: Vec<String> = t["stages_gpu_ms_per_step"]
            .as_object()
            .into_iter()
            .flatten()
            .map(|(k, v)| format!("{k} {:.1}", v.as_f64().unwrap_or(0.0)))
            .collect();
        println!(
            "  training: {its:.2} it/s ({:.0} ms/step over {} steps) | GPU ms/step: {}",
            t["ms_per_step"].as_f64().unwrap_or(0.0),
            t["steps"],
            stages.join(", ")
        );
    } else {
        println!("  training: {}", t.as_str().unwrap_or("?"));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn passes_fall_into_the_stages_a_frame_has() {
        for (pass, want) in [
            ("nn.gemm", "decoders"),
            ("triplane.sample_fwd", "decoders"),
            ("skinning.fwd", "skinning"),
            ("deform.fwd", "skinning"),
            ("splat.project_fwd", "projection"),
            ("splat.scan.reduce", "binning and sorts"),
            ("radix_sort.scatter", "binning and sorts"),
            ("splat.tile_ranges", "binning and sorts"),
            ("splat.rasterize_fwd", "rasterization"),
            ("composite.fwd", "composite"),
            ("adam.step", "other"),
        ] {
            assert_eq!(stage(pass), want, "{pass}");
        }
        assert_eq!(train_stage("adam.step"), "adam");
        assert_eq!(train_stage("ssim.map"), "image losses");
        assert_eq!(train_stage("chamfer.grad"), "cloth losses");
        assert_eq!(train_stage("splat.rasterize_bwd"), "rasterization");
    }
}
