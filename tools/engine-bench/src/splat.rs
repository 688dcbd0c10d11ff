//! `engine-bench splat`: frames per second of the splatting renderer, forward and
//! forward + backward, with per-pass GPU times and blend steps per second, over a grid
//! of image sizes and random scenes (or one PLY file).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use drape_cli_support::median;
use drape_engine::ops::splat::render::{
    Accumulation, GaussianBuffers, RasterVariant, SplatRenderer,
};
use drape_engine::ops::splat::scene::{GaussianCloud, PinholeCamera, RenderSettings};
use drape_engine::Context;
use drape_shared::splat::layout::TILE_SIZES;
use drape_trainer::ply;
use serde_json::json;

/// Options of `engine-bench splat`.
#[derive(Clone, Debug, clap::Args)]
pub struct SplatArgs {
    /// Image sizes, WIDTHxHEIGHT, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "512x512,1920x1080", value_parser = parse_size)]
    pub sizes: Vec<(u32, u32)>,
    /// Random scenes of these many Gaussians (SH degree 3), comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "10000,100000,1000000", allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=100_000_000))]
    pub counts: Vec<u32>,
    /// Benchmark this PLY file instead of random scenes (camera looks at its centroid).
    #[arg(long)]
    pub ply: Option<PathBuf>,
    /// Timed runs per configuration (the median is reported); at least 10.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(10..))]
    pub runs: u32,
    /// Untimed warm-up runs first (at least this many, and for at least --warm-seconds).
    #[arg(long, default_value_t = 2)]
    pub warmup: u32,
    /// Accumulate gradients with compare-and-swap instead of float atomics.
    #[arg(long, conflicts_with = "deterministic")]
    pub cas: bool,
    /// Accumulate gradients deterministically (64-bit fixed-point integer atomics):
    /// the same bits on every run.
    #[arg(long)]
    pub deterministic: bool,
    /// Rasterizer kernels, comma-separated to measure several side by side: auto
    /// (subgroup on a CPU device with subgroups of 8, else workgroup), workgroup
    /// (16x16 invocations per tile, batches in workgroup memory: the GPU kernels) or
    /// subgroup (one subgroup of 8 per 8x4 block, broadcasts instead of workgroup
    /// memory: for lavapipe).
    #[arg(long, value_delimiter = ',', default_value = "auto")]
    pub raster: Vec<RasterChoice>,
    /// Tile sides in pixels (8, 16 or 32), comma-separated to measure several side by
    /// side: the same image, with more intersections to sort and shorter lists to walk
    /// as tiles shrink. 8 needs the subgroup rasterizer.
    #[arg(long, value_delimiter = ',', default_value = "16", value_parser = parse_tile_size)]
    pub tile_sizes: Vec<u32>,
    /// Also time each configuration forward-only from half-precision SH
    /// (RenderSettings::half_sh: packed every frame) and from half-precision projected
    /// splats (half_splats), beside the f32 forward.
    #[arg(long)]
    pub half: bool,
    /// Print one JSON object on stdout instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// `--raster` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum RasterChoice {
    Auto,
    Workgroup,
    Subgroup,
}

impl RasterChoice {
    pub fn variant(self) -> RasterVariant {
        match self {
            RasterChoice::Auto => RasterVariant::Auto,
            RasterChoice::Workgroup => RasterVariant::Workgroup,
            RasterChoice::Subgroup => RasterVariant::Subgroup,
        }
    }
}

fn accumulation(args: &SplatArgs) -> Accumulation {
    if args.cas {
        Accumulation::CompareAndSwap
    } else if args.deterministic {
        Accumulation::Deterministic
    } else {
        Accumulation::Auto
    }
}

fn parse_tile_size(s: &str) -> Result<u32, String> {
    match s.trim().parse::<u32>() {
        Ok(t) if TILE_SIZES.contains(&t) => Ok(t),
        _ => Err(format!("'{s}' is not a tile size ({TILE_SIZES:?})")),
    }
}

pub(crate) fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once('x')
        .ok_or_else(|| format!("'{s}' is not WIDTHxHEIGHT"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .ok()
            .filter(|&v| v > 0 && v <= 16384)
    };
    match (parse(w), parse(h)) {
        (Some(w), Some(h)) => Ok((w, h)),
        _ => Err(format!(
            "'{s}' is not WIDTHxHEIGHT with sides from 1 to 16384"
        )),
    }
}

/// The camera of the random scenes: 5 units from the origin, 45 degrees vertical.
fn bench_camera(width: u32, height: u32, target: [f32; 3], distance: f32) -> PinholeCamera {
    let eye = [target[0] + 0.3, target[1] - 0.4, target[2] - distance];
    PinholeCamera::look_at(eye, target, [0.0, -1.0, 0.0], 45.0, width, height)
        .expect("valid camera")
}

pub(crate) struct Config {
    label: String,
    cloud: GaussianCloud,
    camera: PinholeCamera,
}

pub(crate) fn configs(args: &SplatArgs) -> anyhow::Result<Vec<Config>> {
    let mut out = Vec::new();
    if let Some(path) = &args.ply {
        let cloud = ply::read(path)?;
        anyhow::ensure!(!cloud.is_empty(), "{}: no Gaussians", path.display());
        let n = cloud.len() as f32;
        let mut c = [0.0f32; 3];
        for i in 0..cloud.len() {
            for a in 0..3 {
                c[a] += cloud.means[3 * i + a] / n;
            }
        }
        let radius = (0..cloud.len())
            .map(|i| {
                (0..3)
                    .map(|a| (cloud.means[3 * i + a] - c[a]).powi(2))
                    .sum::<f32>()
                    .sqrt()
            })
            .fold(0.0f32, f32::max)
            .max(1e-3);
        for &(w, h) in &args.sizes {
            out.push(Config {
                label: format!("{} {w}x{h}", path.display()),
                cloud: cloud.clone(),
                camera: bench_camera(w, h, c, 2.5 * radius),
            });
        }
        return Ok(out);
    }
    for &(w, h) in &args.sizes {
        for &n in &args.counts {
            // 59 floats a Gaussian at SH degree 3, held by the cloud, its copy and the device.
            drape_cli_support::ensure_memory(
                3 * 236 * u64::from(n),
                &format!("a scene of {n} Gaussians"),
                "--counts",
            )?;
            // Splat size falls with the count so that coverage stays comparable.
            let scale = 2.0 / (n as f32).sqrt();
            let cloud = GaussianCloud::random(n as usize, 3, 1.6, (-1.0, 1.0), scale, u64::from(n));
            out.push(Config {
                label: format!("{n} random {w}x{h}"),
                cloud,
                camera: bench_camera(w, h, [0.0; 3], 5.0),
            });
        }
    }
    Ok(out)
}

fn bench_one(
    ctx: &Context,
    cfg: &Config,
    args: &SplatArgs,
    raster: RasterChoice,
    tile_size: u32,
) -> anyhow::Result<serde_json::Value> {
    let (w, h) = (cfg.camera.width, cfg.camera.height);
    let n = cfg.cloud.len();
    let settings = RenderSettings {
        tile_size,
        ..RenderSettings::default()
    };
    let gaussians = GaussianBuffers::upload(ctx, "bench params", &cfg.cloud)?;
    let grads = GaussianBuffers::new(ctx, "bench grads", n, cfg.cloud.sh_degree)?;
    let mut renderer = SplatRenderer::new(ctx, w, h, n)?;
    renderer.set_raster_variant(raster.variant())?;
    let pixels = (w * h) as usize;
    let grad_rgb = ctx.upload("bench grad rgb", &vec![1e-3f32; 3 * pixels])?;
    let grad_alpha = ctx.upload("bench grad alpha", &vec![1e-3f32; pixels])?;
    let grad_depth = ctx.upload("bench grad depth", &vec![0.0f32; pixels])?;
    let accumulation = accumulation(args);

    let mut fwd_ms = Vec::new();
    let mut both_ms = Vec::new();
    let mut passes: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let mut intersections = 0;
    for timed in crate::schedule::Runs::new(args.warmup, args.runs) {
        let t0 = Instant::now();
        let stats = renderer.forward(&gaussians, &cfg.camera, &settings)?;
        let t_fwd = t0.elapsed().as_secs_f64() * 1e3;
        let bwd = renderer.backward(
            &stats.saved,
            &gaussians,
            &grad_rgb,
            &grad_alpha,
            &grad_depth,
            &grads,
            accumulation,
        )?;
        let t_both = t0.elapsed().as_secs_f64() * 1e3;
        if !timed {
            continue;
        }
        intersections = stats.intersections;
        fwd_ms.push(t_fwd);
        both_ms.push(t_both);
        let mut by_name = stats.timings.by_name();
        for (k, v) in bwd.by_name() {
            *by_name.entry(k).or_insert(0.0) += v;
        }
        for (k, v) in by_name {
            passes.entry(k).or_default().push(v);
        }
    }
    // Forward-only times of the render-only knobs (they have no backward).
    let mut half = serde_json::Map::new();
    if args.half {
        for (name, knob) in [
            (
                "half_sh",
                RenderSettings {
                    half_sh: true,
                    ..settings
                },
            ),
            (
                "half_splats",
                RenderSettings {
                    half_splats: true,
                    ..settings
                },
            ),
        ] {
            let mut ms = Vec::new();
            let mut knob_passes: BTreeMap<String, Vec<f64>> = BTreeMap::new();
            for timed in crate::schedule::Runs::new(args.warmup, args.runs) {
                let t0 = Instant::now();
                let stats = renderer.forward(&gaussians, &cfg.camera, &knob)?;
                if timed {
                    ms.push(t0.elapsed().as_secs_f64() * 1e3);
                    for (k, v) in stats.timings.by_name() {
                        knob_passes.entry(k).or_default().push(v);
                    }
                }
            }
            half.insert(name.into(), json!({"forward_median_ms": median(&ms), "passes": knob_passes.into_iter().map(|(k, v)| (k, median(&v))).collect::<BTreeMap<_, _>>()}));
        }
    }
    renderer.forward(&gaussians, &cfg.camera, &settings)?;
    let image = renderer.read_image()?;
    let fwd = median(&fwd_ms);
    let both = median(&both_ms);
    Ok(json!({
        "config": cfg.label,
        "gaussians": n,
        "width": w,
        "height": h,
        "tile_size": tile_size,
        "intersections": intersections,
        "forward_median_ms": fwd,
        "forward_fps": 1e3 / fwd,
        "forward_backward_median_ms": both,
        "forward_backward_fps": 1e3 / both,
        "raster": format!("{:?}", renderer.raster_variant()).to_lowercase(),
        "blend_steps": image.blend_steps,
        "blend_steps_per_s": image.blend_steps as f64 / (fwd / 1e3),
        "passes": passes.into_iter().map(|(k, v)| (k, median(&v))).collect::<BTreeMap<_, _>>(),
        "half": half,
    }))
}

/// `configs` come from [`configs`], made before the device is opened (a bad PLY costs
/// nothing).
pub(crate) fn run(
    ctx: &Context,
    args: &SplatArgs,
    configs: Vec<Config>,
) -> anyhow::Result<serde_json::Value> {
    let mut results = Vec::new();
    for cfg in configs {
        for &raster in &args.raster {
            for &tile in &args.tile_sizes {
                eprintln!(
                    "splat: {} ({raster:?} rasterizer, tiles of {tile}) ...",
                    cfg.label
                );
                results.push(bench_one(ctx, &cfg, args, raster, tile).with_context(|| {
                    format!(
                        "splat benchmark '{}' ({raster:?} rasterizer, tiles of {tile})",
                        cfg.label
                    )
                })?);
            }
        }
    }
    Ok(json!({
        "job": "splat",
        "device": ctx.info().name,
        "device_kind": format!("{:?}", ctx.info().kind),
        "runs": args.runs,
        "warmup": args.warmup,
        "accumulation": accumulation(args).describe(ctx),
        "results": results,
    }))
}

pub fn print_table(r: &serde_json::Value) {
    println!(
        "splat on {} ({} runs, median)",
        r["device"].as_str().unwrap_or("?"),
        r["runs"]
    );
    for c in r["results"].as_array().into_iter().flatten() {
        println!(
            "  {:<28} {:<9} {:>2}px fwd {:>9.2} ms {:>7.2} FPS | fwd+bwd {:>9.2} ms {:>7.2} FPS | {:>10} isect | {:>7.1} M blend/s",
            c["config"].as_str().unwrap_or("?"),
            c["raster"].as_str().unwrap_or("?"),
            c["tile_size"],
            c["forward_median_ms"].as_f64().unwrap_or(0.0),
            c["forward_fps"].as_f64().unwrap_or(0.0),
            c["forward_backward_median_ms"].as_f64().unwrap_or(0.0),
            c["forward_backward_fps"].as_f64().unwrap_or(0.0),
            c["intersections"],
            c["blend_steps_per_s"].as_f64().unwrap_or(0.0) / 1e6,
        );
        if let Some(passes) = c["passes"].as_object() {
            let line: Vec<String> = passes
                .iter()
                .map(|(k, v)| format!("{k} {:.2}", v.as_f64().unwrap_or(0.0)))
                .collect();
            println!("      GPU ms: {}", line.join(", "));
        }
        for (k, v) in c["half"].as_object().into_iter().flatten() {
            let line: Vec<String> = v["passes"]
                .as_object()
                .into_iter()
                .flatten()
                .map(|(k, v)| format!("{k} {:.2}", v.as_f64().unwrap_or(0.0)))
                .collect();
            println!(
                "      {k}: fwd {:.2} ms; GPU ms: {}",
                v["forward_median_ms"].as_f64().unwrap_or(0.0),
                line.join(", ")
            );
        }
    }
}
