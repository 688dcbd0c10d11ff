//! `engine-bench`: times the engine's GPU work on the chosen device (sort, scan,
//! splatting, the neural ops, the composite, a trained avatar's frame and training step,
//! and the avatar's speed/accuracy trade), with per-pass GPU times from timestamp
//! queries and, where there is one, a CPU baseline of the same job in the same run.
//!
//! Every figure is a median over `--runs` timed runs after untimed ones: at least
//! `--warmup` of them, for at least `--warm-seconds` (1 s on a GPU, whose clocks ramp up
//! from idle; see `schedule`).
//! `median_ms` is wall time from submit to fence (what an application waits);
//! `gpu_median_ms` is the sum of the passes' timestamps.
#![forbid(unsafe_code)]

use std::collections::BTreeMap;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Context as _;
use clap::{Parser, Subcommand};
use drape_cli_support::{median, parse_len, DeviceArgs};
use drape_engine::ops::{
    radix_sort::{RadixSort, SortVariant},
    scan::{ExclusiveScan, ScanVariant},
};
use drape_engine::{BufferDesc, Context, PassTimings};
use drape_shared::radix_sort::significant_bits;
use rand::{Rng, SeedableRng};
use serde_json::json;

mod avatar;
mod composite;
mod ops;
mod schedule;
mod splat;
mod trade;

/// Benchmarks of the drape engine's GPU ops.
#[derive(Parser, Debug)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(flatten)]
    device: DeviceArgs,
    /// Least warm-up time of every timed loop, in seconds: warm-up runs go on until
    /// `--warmup` runs are done and this much time has passed, so that a GPU's clocks
    /// have ramped up from idle. Default: 1 on a GPU, 0 on a CPU device.
    #[arg(long, global = true, value_name = "SECONDS", value_parser = parse_seconds, allow_negative_numbers = true)]
    warm_seconds: Option<f64>,
    #[command(subcommand)]
    job: Job,
}

#[derive(Clone, Debug, clap::Args)]
struct Common {
    /// Number of elements.
    #[arg(long, value_parser = parse_len, allow_negative_numbers = true, default_value = "1000000")]
    n: u32,
    /// Timed runs (the median is reported); at least 10.
    #[arg(long, allow_negative_numbers = true, default_value_t = 10, value_parser = clap::value_parser!(u32).range(10..))]
    runs: u32,
    /// Untimed warm-up runs first (at least this many, and for at least --warm-seconds).
    #[arg(long, default_value_t = 2)]
    warmup: u32,
    /// Seed of the random input.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Print one JSON object on stdout instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Subcommand, Debug)]
enum Job {
    /// Stable radix sort of random u32 keys with u32 values; CPU baseline: the standard
    /// library's sort_unstable_by_key on the same (key, value) pairs.
    Sort {
        #[command(flatten)]
        common: Common,
        /// Significant key bits (1-32); keys are random in 0..2^bits.
        #[arg(long, allow_negative_numbers = true, default_value_t = 32, value_parser = clap::value_parser!(u32).range(1..=32))]
        bits: u32,
        /// Sort kernels: auto (chunks on CPU devices, blocks on GPUs), blocks (workgroups
        /// rank blocks of 2,048 keys by 4-bit digits) or chunks (one invocation walks each
        /// long run by 8-bit digits).
        #[arg(long, value_enum, default_value_t = SortKernels::Auto)]
        variant: SortKernels,
    },
    /// Exclusive prefix sum of random u32; CPU baseline: a sequential scan.
    Scan {
        #[command(flatten)]
        common: Common,
        /// Scan kernels: auto (chunks on CPU devices, blocks on GPUs), blocks (workgroups
        /// scan blocks of 1,024, level by level) or chunks (one invocation per long run).
        #[arg(long, value_enum, default_value_t = SortKernels::Auto)]
        variant: SortKernels,
    },
    /// Gaussian splatting: forward and forward+backward FPS, per-pass GPU ms and
    /// blend steps per second, at 512x512 and 1920x1080 with 10k, 100k and 1M random
    /// Gaussians by default, or on a PLY file.
    Splat(splat::SplatArgs),
    /// Neural ops: GEMM GFLOP/s of the HUGS decoder layers (forward, backward) beside
    /// a CPU GEMM (matrixmultiply) on the same matrices, the decoders' forward +
    /// backward, triplane sampling points/s.
    Ops(ops::OpsArgs),
    /// Layered avatar-sized scene (150k body, 30k cloth, 100k scene Gaussians by
    /// default): the paper's three passes composited, against one depth-sorted pass of
    /// every layer; forward and forward + backward frame time, per-pass GPU ms.
    Composite(composite::CompositeArgs),
    /// A trained avatar (a `drape train` run): frame time and FPS at 512x512 and
    /// 1920x1080 through each compositing variant with the GPU split (decoders,
    /// skinning, projection, sorts, rasterization, composite), and training it/s with
    /// the split of a step.
    Avatar(avatar::AvatarArgs),
    /// The speed/accuracy trade of a trained avatar: for each knob (resolution, SH degree
    /// per layer, pruning by opacity or contribution, compositing, tile size,
    /// half-precision SH and splats, pose-dependent offsets off where the run has them)
    /// the held-out frames rendered and compared with the ground truth and with the
    /// default render (PSNR, SSIM, LPIPS with weights) beside the GPU ms per frame; writes
    /// trade.json, trade.md and a Pareto plot trade.png; lists the knobs a run cannot
    /// measure.
    Trade(trade::TradeArgs),
}

/// Medians over the timed runs.
struct Measured {
    wall_ms: f64,
    gpu_ms: f64,
    passes: BTreeMap<String, f64>,
}

fn measure(
    ctx: &Context,
    common: &Common,
    mut run_once: impl FnMut() -> anyhow::Result<(f64, PassTimings)>,
) -> anyhow::Result<Measured> {
    let _ = ctx;
    let mut walls = Vec::new();
    let mut gpus = Vec::new();
    let mut per_pass: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    for timed in schedule::Runs::new(common.warmup, common.runs) {
        let (wall, timings) = run_once()?;
        if !timed {
            continue;
        }
        walls.push(wall);
        gpus.push(timings.busy_ms());
        for (name, ms) in timings.by_name() {
            per_pass.entry(name).or_default().push(ms);
        }
    }
    Ok(Measured {
        wall_ms: median(&walls),
        gpu_ms: median(&gpus),
        passes: per_pass.into_iter().map(|(k, v)| (k, median(&v))).collect(),
    })
}

fn cpu_median(runs: u32, mut job: impl FnMut() -> f64) -> f64 {
    let _ = job(); // warm caches and the allocator
    let times: Vec<f64> = (0..runs).map(|_| job()).collect();
    median(&times)
}

/// `--variant` of `engine-bench sort` and `scan`.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum SortKernels {
    Auto,
    Blocks,
    Chunks,
}

fn bench_sort(
    ctx: &Context,
    common: &Common,
    bits: u32,
    variant: SortKernels,
) -> anyhow::Result<serde_json::Value> {
    let n = common.n;
    anyhow::ensure!(
        n <= RadixSort::LIMIT,
        "--n {n} exceeds the sort's limit of {}",
        RadixSort::LIMIT
    );
    let mut rng = rand::rngs::StdRng::seed_from_u64(common.seed);
    let keys: Vec<u32> = (0..n)
        .map(|_| significant_bits(rng.random(), bits))
        .collect();
    let values: Vec<u32> = (0..n).collect();
    let pristine_keys = ctx.upload("bench pristine keys", &keys)?;
    let pristine_values = ctx.upload("bench pristine values", &values)?;
    let bytes = u64::from(n) * 4;
    let mut key_buf = ctx.create_buffer("bench keys", BufferDesc::gpu_only(bytes))?;
    let value_buf = ctx.create_buffer("bench values", BufferDesc::gpu_only(bytes))?;
    let variant = match variant {
        SortKernels::Auto => SortVariant::Auto,
        SortKernels::Blocks => SortVariant::Blocks,
        SortKernels::Chunks => SortVariant::Chunks,
    };
    let plan = RadixSort::with_variant(ctx, n, variant)?;

    let measured = measure(ctx, common, || {
        let mut restore = ctx.record("restore input")?;
        restore.copy(&pristine_keys, &key_buf, bytes);
        restore.copy(&pristine_values, &value_buf, bytes);
        restore.submit_and_wait()?;
        let mut rec = ctx.record("radix_sort")?;
        plan.record(&mut rec, &key_buf, &value_buf, n, bits)?;
        let t0 = Instant::now();
        let timings = rec.submit_and_wait()?;
        Ok((t0.elapsed().as_secs_f64() * 1e3, timings))
    })?;
    let sorted = ctx.read_buffer::<u32>(&mut key_buf, n as usize)?;
    anyhow::ensure!(
        sorted.windows(2).all(|w| w[0] <= w[1]),
        "the GPU sort's output is not sorted"
    );

    let pairs: Vec<(u32, u32)> = keys.iter().copied().zip(values.iter().copied()).collect();
    let cpu_ms = cpu_median(common.runs, || {
        let mut p = pairs.clone();
        let t0 = Instant::now();
        p.sort_unstable_by_key(|&(k, _)| k);
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        std::hint::black_box(&p);
        ms
    });
    Ok(report(
        ctx,
        "sort",
        common,
        &measured,
        cpu_ms,
        "keys_per_s",
        json!({ "key_bits": bits, "variant": format!("{:?}", plan.variant()).to_lowercase() }),
    ))
}

fn bench_scan(
    ctx: &Context,
    common: &Common,
    variant: SortKernels,
) -> anyhow::Result<serde_json::Value> {
    let n = common.n;
    anyhow::ensure!(
        n <= ExclusiveScan::LIMIT,
        "--n {n} exceeds the scan's limit of {}",
        ExclusiveScan::LIMIT
    );
    let mut rng = rand::rngs::StdRng::seed_from_u64(common.seed);
    let data: Vec<u32> = (0..n).map(|_| rng.random_range(0..1024)).collect();
    let pristine = ctx.upload("bench pristine data", &data)?;
    let bytes = u64::from(n) * 4;
    let mut buf = ctx.create_buffer("bench data", BufferDesc::gpu_only(bytes))?;
    let variant = match variant {
        SortKernels::Auto => ScanVariant::Auto,
        SortKernels::Blocks => ScanVariant::Blocks,
        SortKernels::Chunks => ScanVariant::Chunks,
    };
    let plan = ExclusiveScan::with_variant(ctx, "scan", n, variant)?;
    let measured = measure(ctx, common, || {
        let mut restore = ctx.record("restore input")?;
        restore.copy(&pristine, &buf, bytes);
        restore.submit_and_wait()?;
        let mut rec = ctx.record("scan")?;
        plan.record(&mut rec, &buf, n)?;
        let t0 = Instant::now();
        let timings = rec.submit_and_wait()?;
        Ok((t0.elapsed().as_secs_f64() * 1e3, timings))
    })?;
    let gpu = ctx.read_buffer::<u32>(&mut buf, n as usize)?;
    let mut expected = data.clone();
    drape_shared::scan::exclusive_scan_in_place(&mut expected);
    anyhow::ensure!(
        gpu == expected,
        "the GPU scan's output differs from the CPU scan"
    );
    let cpu_ms = cpu_median(common.runs, || {
        let mut d = data.clone();
        let t0 = Instant::now();
        drape_shared::scan::exclusive_scan_in_place(&mut d);
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        std::hint::black_box(&d);
        ms
    });
    Ok(report(
        ctx,
        "scan",
        common,
        &measured,
        cpu_ms,
        "elems_per_s",
        json!({ "variant": format!("{:?}", plan.variant()).to_lowercase() }),
    ))
}

fn report(
    ctx: &Context,
    job: &str,
    common: &Common,
    m: &Measured,
    cpu_ms: f64,
    rate_key: &str,
    extra: serde_json::Value,
) -> serde_json::Value {
    let mut out = json!({
        "job": job,
        "device": ctx.info().name,
        "device_kind": format!("{:?}", ctx.info().kind),
        "n": common.n,
        "runs": common.runs,
        "warmup": common.warmup,
        "median_ms": m.wall_ms,
        "gpu_median_ms": m.gpu_ms,
        "cpu_median_ms": cpu_ms,
        "cpu_over_gpu": cpu_ms / m.wall_ms,
        "passes": m.passes,
        "verified": true,
    });
    out[rate_key] = json!(f64::from(common.n) / (m.wall_ms / 1e3));
    out["cpu_".to_string() + rate_key] = json!(f64::from(common.n) / (cpu_ms / 1e3));
    if let (Some(o), Some(e)) = (out.as_object_mut(), extra.as_object()) {
        o.extend(e.clone());
    }
    out
}

fn print_table(r: &serde_json::Value) {
    let rate_key = if r.get("keys_per_s").is_some() {
        "keys_per_s"
    } else {
        "elems_per_s"
    };
    let kernels = r["variant"]
        .as_str()
        .map(|v| format!(", {v} kernels"))
        .unwrap_or_default();
    println!(
        "{} of {} elements on {} ({} runs, median{kernels})",
        r["job"].as_str().unwrap_or("?"),
        r["n"],
        r["device"].as_str().unwrap_or("?"),
        r["runs"]
    );
    println!(
        "  wall (submit to fence)  {:>10.3} ms   {:>8.2} M/s",
        r["median_ms"].as_f64().unwrap_or(0.0),
        r[rate_key].as_f64().unwrap_or(0.0) / 1e6
    );
    println!(
        "  GPU (timestamps)        {:>10.3} ms",
        r["gpu_median_ms"].as_f64().unwrap_or(0.0)
    );
    if let Some(passes) = r["passes"].as_object() {
        for (name, ms) in passes {
            println!("    {name:<28}{:>10.3} ms", ms.as_f64().unwrap_or(0.0));
        }
    }
    println!(
        "  CPU baseline            {:>10.3} ms   {:>8.2} M/s",
        r["cpu_median_ms"].as_f64().unwrap_or(0.0),
        r[format!("cpu_{rate_key}")].as_f64().unwrap_or(0.0) / 1e6
    );
    println!(
        "  CPU time / GPU time     {:>10.2}x",
        r["cpu_over_gpu"].as_f64().unwrap_or(0.0)
    );
}

/// A number of seconds, at least 0.
fn parse_seconds(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("'{s}' is not a number of seconds (0 or more)")),
    }
}

fn main() -> ExitCode {
    let cli: Cli = match drape_cli_support::parse_args() {
        Ok(c) => c,
        Err(code) => return code,
    };
    drape_cli_support::run(|| {
        // The splat scenes first: a bad PLY is reported before the device is opened.
        let mut splat_configs = match &cli.job {
            Job::Splat(args) => Some(splat::configs(args)?),
            _ => None,
        };
        let ctx = cli.device.open()?;
        let on_gpu = ctx.info().kind != drape_engine::DeviceKind::Cpu;
        schedule::set_warm_seconds(cli.warm_seconds.unwrap_or(if on_gpu { 1.0 } else { 0.0 }));
        // Each job gives its JSON, whether to print it as JSON, and its table printer.
        let (mut result, json_out, table): (serde_json::Value, bool, fn(&serde_json::Value)) =
            match &cli.job {
                Job::Sort {
                    common,
                    bits,
                    variant,
                } => (
                    bench_sort(&ctx, common, *bits, *variant).context("sort benchmark")?,
                    common.json,
                    print_table,
                ),
                Job::Scan { common, variant } => (
                    bench_scan(&ctx, common, *variant).context("scan benchmark")?,
                    common.json,
                    print_table,
                ),
                Job::Ops(args) => (ops::run(&ctx, args)?, args.json, ops::print_table),
                Job::Avatar(args) => (avatar::run(&ctx, args)?, args.json, avatar::print_table),
                Job::Composite(args) => (
                    composite::run(&ctx, args)?,
                    args.json,
                    composite::print_table,
                ),
                Job::Splat(args) => (
                    splat::run(&ctx, args, splat_configs.take().expect("made above"))?,
                    args.json,
                    splat::print_table,
                ),
                Job::Trade(args) => (trade::run(&ctx, args)?, args.json, |r| {
                    print!("{}", trade::markdown(r))
                }),
            };
        cli.device.check_validation(&ctx)?;
        if let Some(object) = result.as_object_mut() {
            object.insert("warm_seconds".into(), json!(schedule::warm_seconds()));
        }
        if json_out {
            println!("{result}");
        } else {
            table(&result);
        }
        Ok(())
    })
}
