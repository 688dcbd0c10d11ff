//! `engine-bench ops`: the neural ops the avatar runs every step. GEMM throughput of
//! the HUGS decoder layer shapes at `--rows` rows (forward `y = x Wᵀ + b` and the
//! backward pair dW, dx), with a CPU GEMM from the `matrixmultiply` crate (through
//! ndarray, all cores) on the same matrices in the same run; the three decoders'
//! forward + backward; triplane sampling forward + backward in points per second; SSIM
//! (map and gradient) and LPIPS (value and gradient, seeded random AlexNet weights) at
//! 512 × 512; the cloth Chamfer loss with its gradient through the uniform grid at
//! `--chamfer-points` per side, and grid against brute force at `--chamfer-compare`.

use std::time::Instant;

use drape_cli_support::{median, parse_len};
use drape_engine::ops::accumulate::Accumulation;
use drape_engine::ops::nn::{Activation, GemmVariant, HeadDesc, Mlp, MlpDesc};
use drape_engine::ops::triplane::{Triplane, TriplaneDesc, TriplaneInit};
use drape_engine::{BufferDesc, Context, PassTimings};
use rand::{Rng, SeedableRng};
use serde_json::json;

/// Options of `engine-bench ops`.
#[derive(Clone, Debug, clap::Args)]
pub struct OpsArgs {
    /// Rows (Gaussians) per op.
    #[arg(long, value_parser = parse_len, allow_negative_numbers = true, default_value = "150000")]
    pub rows: u32,
    /// Timed runs (the median is reported).
    #[arg(long, default_value_t = 5)]
    pub runs: u32,
    /// Untimed warm-up runs first (at least this many, and for at least --warm-seconds).
    #[arg(long, default_value_t = 1)]
    pub warmup: u32,
    /// Triplane side and channels.
    #[arg(long, default_value_t = 256)]
    pub triplane_resolution: u32,
    #[arg(long, default_value_t = 32)]
    pub triplane_channels: u32,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Run only these parts (comma-separated): gemm, decoders, triplane, ssim, lpips,
    /// chamfer. Default: all. LPIPS at 512 x 512 takes minutes on lavapipe.
    #[arg(long, value_delimiter = ',', value_parser = ["gemm", "decoders", "triplane", "ssim", "lpips", "chamfer"])]
    pub only: Vec<String>,
    /// Points on each side of the Chamfer loss timed through the uniform grid (two
    /// samplings of a garment-like surface).
    #[arg(long, value_parser = parse_len, default_value = "1000000")]
    pub chamfer_points: u32,
    /// Points on each side where grid and brute force are timed side by side.
    #[arg(long, value_parser = parse_len, default_value = "32768")]
    pub chamfer_compare: u32,
    /// GEMM kernel: auto (on CPU devices texel4 where subgroups are 8 lanes,
    /// register-blocked for narrow outputs; tiled on GPUs), tiled, blocked, subgroup
    /// (64 x 32 tiles of a subgroup, B shared by broadcasts, storage-buffer reads), texel
    /// (the same reading texel buffers) or texel4 (the texel tiles reading 4 floats a
    /// fetch, B fetched by every lane instead of broadcast, where the operands' layout
    /// allows).
    #[arg(long, default_value = "auto", value_parser = ["auto", "tiled", "blocked", "subgroup", "texel", "texel4"])]
    pub gemm: String,
    /// Triplane backward: accumulate the plane gradient deterministically (64-bit
    /// fixed-point integer atomics) instead of with float atomics.
    #[arg(long)]
    pub deterministic: bool,
    /// GEMM layers to time, as IN x OUT (comma-separated, e.g. "128x128,64x49").
    /// Default: the HUGS decoder shapes.
    #[arg(long, value_delimiter = ',', value_parser = parse_layer)]
    pub layers: Vec<(usize, usize)>,
}

/// `IN x OUT` (e.g. "128x128"), both from 1 to 1,024.
fn parse_layer(s: &str) -> Result<(usize, usize), String> {
    let (i, o) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("'{s}': expected IN x OUT, e.g. 128x128"))?;
    let width = |w: &str| {
        w.trim()
            .parse::<usize>()
            .ok()
            .filter(|w| (1..=1024).contains(w))
            .ok_or_else(|| format!("'{s}': '{w}' is not a width from 1 to 1024"))
    };
    Ok((width(i)?, width(o)?))
}

impl OpsArgs {
    fn variant(&self) -> GemmVariant {
        match self.gemm.as_str() {
            "tiled" => GemmVariant::Tiled,
            "blocked" => GemmVariant::Blocked,
            "subgroup" => GemmVariant::Subgroup,
            "texel" => GemmVariant::Texel,
            "texel4" => GemmVariant::Texel4,
            _ => GemmVariant::Auto,
        }
    }

    fn wants(&self, part: &str) -> bool {
        self.only.is_empty() || self.only.iter().any(|p| p == part)
    }
}

fn timed(
    ctx: &Context,
    args: &OpsArgs,
    mut record: impl FnMut() -> anyhow::Result<PassTimings>,
) -> anyhow::Result<(f64, f64)> {
    let _ = ctx;
    let mut walls = Vec::new();
    let mut gpus = Vec::new();
    for timed in crate::schedule::Runs::new(args.warmup, args.runs) {
        let t0 = Instant::now();
        let timings = record()?;
        if timed {
            walls.push(t0.elapsed().as_secs_f64() * 1e3);
            gpus.push(timings.busy_ms());
        }
    }
    Ok((median(&walls), median(&gpus)))
}

fn random(len: usize, seed: u64) -> Vec<f32> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    (0..len).map(|_| rng.random_range(-1.0..1.0)).collect()
}

/// The linear layers of HUGS's three decoders on a 96-wide feature, each shape once:
/// (in, out). Appearance 96-64-64 with heads opacity (1) and SH (48); geometry
/// 96-128-128 with heads offset (3), 6D rotation (6), log-scale delta (3);
/// deformation 96-128-128-128-128 with 24 skinning logits. Each head is its own
/// layer, as `Mlp` runs it (and HUGS does).
const SHAPES: [(usize, usize); 9] = [
    (96, 64),
    (64, 64),
    (64, 1),
    (64, 48),
    (96, 128),
    (128, 128),
    (128, 3),
    (128, 6),
    (128, 24),
];

fn cpu_gemm_ms(args: &OpsArgs, rows: usize, i: usize, o: usize, x: &[f32], w: &[f32]) -> f64 {
    let mut y = vec![0.0f32; rows * o];
    let mut times = Vec::new();
    for timed in crate::schedule::Runs::new(args.warmup, args.runs) {
        let t0 = Instant::now();
        gemm_cpu(rows, i, o, x, w, &mut y);
        if timed {
            times.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        std::hint::black_box(&y);
    }
    median(&times)
}

/// `y = x Wᵀ` on the CPU (x rows×i, W o×i, y rows×o, all row-major) through
/// ndarray's `general_mat_mul`, which is `matrixmultiply`'s packed, multithreaded
/// sgemm behind a safe API.
fn gemm_cpu(rows: usize, i: usize, o: usize, x: &[f32], w: &[f32], y: &mut [f32]) {
    use ndarray::{linalg::general_mat_mul, ArrayView2, ArrayViewMut2};
    let a = ArrayView2::from_shape((rows, i), &x[..rows * i]).expect("x is rows × in");
    let b = ArrayView2::from_shape((o, i), &w[..o * i]).expect("W is out × in");
    let mut c = ArrayViewMut2::from_shape((rows, o), &mut y[..rows * o]).expect("y is rows × out");
    general_mat_mul(1.0, &a, &b.t(), 0.0, &mut c);
}

pub fn run(ctx: &Context, args: &OpsArgs) -> anyhow::Result<serde_json::Value> {
    let rows = args.rows as usize;
    let mut out = json!({ "job": "ops", "device": ctx.info().name, "rows": rows, "runs": args.runs, "gemm_kernel": args.gemm });
    let mut gemms = Vec::new();
    let layers = if args.layers.is_empty() {
        SHAPES.to_vec()
    } else {
        args.layers.clone()
    };
    for &(i, o) in layers.iter().filter(|_| args.wants("gemm")) {
        let desc = MlpDesc {
            input: i,
            hidden: vec![],
            heads: vec![HeadDesc::new("y", o, Activation::Identity)],
            weight_norm: vec![],
        };
        let mut mlp = Mlp::new(ctx, "bench linear", desc.clone(), rows, 1)?;
        mlp.variant = args.variant();
        let x_host = random(rows * i, 2);
        let x = ctx.upload("bench x", &x_host)?;
        let gx = ctx.create_buffer("bench gx", BufferDesc::gpu_only((rows * i * 4) as u64))?;
        let (fwd_wall, fwd_gpu) = timed(ctx, args, || {
            let mut rec = ctx.record("bench linear fwd")?;
            mlp.record_forward(&mut rec, &x, rows as u32)?;
            Ok(rec.submit_and_wait()?)
        })?;
        let (bwd_wall, bwd_gpu) = timed(ctx, args, || {
            let mut rec = ctx.record("bench linear bwd")?;
            mlp.record_backward(&mut rec, &x, rows as u32, Some(&gx), false)?;
            Ok(rec.submit_and_wait()?)
        })?;
        // Where the backward's time goes (one more run): dW, dx, the split sums.
        let bwd_passes = {
            let mut rec = ctx.record("bench linear bwd")?;
            mlp.record_backward(&mut rec, &x, rows as u32, Some(&gx), false)?;
            rec.submit_and_wait()?.by_name()
        };
        let w_host = desc.init_params(1);
        let cpu_ms = cpu_gemm_ms(args, rows, i, o, &x_host, &w_host[..i * o]);
        let flops = 2.0 * rows as f64 * i as f64 * o as f64;
        gemms.push(json!({
            "in": i, "out": o, "rows": rows,
            "forward_ms": fwd_wall, "forward_gpu_ms": fwd_gpu, "forward_gflops": flops / fwd_gpu.max(1e-9) / 1e6,
            "backward_ms": bwd_wall, "backward_gpu_ms": bwd_gpu, "backward_gflops": 2.0 * flops / bwd_gpu.max(1e-9) / 1e6,
            "backward_passes_gpu_ms": bwd_passes,
            "cpu_forward_ms": cpu_ms, "cpu_gflops": flops / cpu_ms.max(1e-9) / 1e6,
            "gpu_over_cpu_throughput": cpu_ms / fwd_gpu.max(1e-9),
        }));
    }
    if args.wants("gemm") {
        out["gemm"] = gemms.into();
    }
    let width = 3 * args.triplane_channels as usize;
    let feats = ctx.upload("bench features", &random(rows * width, 3))?;
    if args.wants("decoders") {
        decoders(ctx, args, &mut out, &feats, width)?;
    }
    if args.wants("triplane") {
        triplane(ctx, args, &mut out, &feats)?;
    }
    if args.wants("ssim") || args.wants("lpips") {
        images(ctx, args, &mut out)?;
    }
    if args.wants("chamfer") {
        chamfer(ctx, args, &mut out)?;
    }
    Ok(out)
}

/// `n` points on a wavy cylinder 0.3 m across and 0.6 m tall (a garment's size),
/// pushed off it by up to `jitter / 2`: flat xyz.
fn garment_like(n: usize, seed: u64, jitter: f64) -> Vec<f32> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let mut v = Vec::with_capacity(3 * n);
    for _ in 0..n {
        let (a, h, j): (f64, f64, f64) = (
            rng.random_range(0.0..std::f64::consts::TAU),
            rng.random_range(0.0..0.6),
            rng.random_range(-0.5..0.5) * jitter,
        );
        let r = 0.15 + 0.01 * (5.0 * a).sin() * (10.0 * h).cos() + j;
        v.extend([(r * a.cos()) as f32, h as f32, (r * a.sin()) as f32]);
    }
    v
}

/// The Chamfer loss and its gradient (both directions): the grid at
/// `--chamfer-points`, then grid and brute force side by side at `--chamfer-compare`
/// points each.
fn chamfer(ctx: &Context, args: &OpsArgs, out: &mut serde_json::Value) -> anyhow::Result<()> {
    use drape_engine::ops::cloth_loss::{Chamfer, NearestSearch};
    let mut rows = Vec::new();
    let k = args.chamfer_compare;
    for (label, n, search) in [
        ("grid", args.chamfer_points, NearestSearch::Grid),
        ("grid", k, NearestSearch::Grid),
        ("brute force", k, NearestSearch::BruteForce),
    ] {
        let pred = ctx.upload("bench chamfer pred", &garment_like(n as usize, 9, 0.006))?;
        let target = ctx.upload("bench chamfer target", &garment_like(n as usize, 10, 0.0))?;
        let grad = ctx.create_buffer(
            "bench chamfer grad",
            BufferDesc::gpu_only(12 * u64::from(n.max(1))),
        )?;
        let c = Chamfer::with_search(ctx, n, n, search)?;
        let (wall, gpu) = timed(ctx, args, || {
            let mut rec = ctx.record("bench chamfer")?;
            rec.fill(&grad, 0);
            c.record(&mut rec, &pred, n, &target, n, 0.02, Some((&grad, 1.0)))?;
            Ok(rec.submit_and_wait()?)
        })?;
        rows.push(
            json!({ "search": label, "points": n, "fwd_bwd_ms": wall, "fwd_bwd_gpu_ms": gpu }),
        );
    }
    out["chamfer"] = rows.into();
    Ok(())
}

/// The three decoders together, forward and backward.
fn decoders(
    ctx: &Context,
    args: &OpsArgs,
    out: &mut serde_json::Value,
    feats: &drape_engine::Buffer,
    width: usize,
) -> anyhow::Result<()> {
    let rows = args.rows as usize;
    let decoders = [
        MlpDesc::hugs_appearance(width, 3),
        MlpDesc::hugs_geometry(width),
        MlpDesc::hugs_deformation(width),
    ];
    let mut mlps: Vec<Mlp> = decoders
        .iter()
        .enumerate()
        .map(|(k, d)| Mlp::new(ctx, "bench decoder", d.clone(), rows, k as u64))
        .collect::<Result<_, _>>()?;
    for m in &mut mlps {
        m.variant = args.variant();
    }
    let gfeats = ctx.create_buffer(
        "bench feature grads",
        BufferDesc::gpu_only((rows * width * 4) as u64),
    )?;
    let (dec_wall, dec_gpu) = timed(ctx, args, || {
        let mut rec = ctx.record("bench decoders")?;
        for m in &mlps {
            m.record_forward(&mut rec, feats, rows as u32)?;
        }
        for (k, m) in mlps.iter().enumerate() {
            m.record_backward(&mut rec, feats, rows as u32, Some(&gfeats), k > 0)?;
        }
        Ok(rec.submit_and_wait()?)
    })?;
    out["decoders_fwd_bwd_ms"] = dec_wall.into();
    out["decoders_fwd_bwd_gpu_ms"] = dec_gpu.into();
    Ok(())
}

/// Triplane sample + backward.
fn triplane(
    ctx: &Context,
    args: &OpsArgs,
    out: &mut serde_json::Value,
    feats: &drape_engine::Buffer,
) -> anyhow::Result<()> {
    let rows = args.rows as usize;
    let mut rng = rand::rngs::StdRng::seed_from_u64(4);
    let pts: Vec<f32> = (0..3 * rows).map(|_| rng.random_range(-0.9..0.9)).collect();
    let tdesc = TriplaneDesc {
        resolution: args.triplane_resolution,
        channels: args.triplane_channels,
        box_min: [-1.0; 3],
        box_max: [1.0; 3],
    };
    let mut tp = Triplane::new(
        ctx,
        "bench triplane",
        tdesc,
        TriplaneInit::Normal { seed: 5 },
    )?;
    let accumulation = if args.deterministic {
        Accumulation::Deterministic
    } else {
        Accumulation::Auto
    };
    tp.prepare(ctx, accumulation)?;
    let points = ctx.upload("bench points", &pts)?;
    let gpoints = ctx.create_buffer(
        "bench point grads",
        BufferDesc::gpu_only((rows * 12) as u64),
    )?;
    let (tp_wall, tp_gpu) = timed(ctx, args, || {
        let mut rec = ctx.record("bench triplane")?;
        tp.record_forward(&mut rec, &points, feats, rows as u32)?;
        tp.record_backward(
            &mut rec,
            &points,
            feats,
            &gpoints,
            rows as u32,
            accumulation,
        )?;
        Ok(rec.submit_and_wait()?)
    })?;
    out["triplane"] = json!({ "resolution": args.triplane_resolution, "channels": args.triplane_channels, "fwd_bwd_ms": tp_wall, "fwd_bwd_gpu_ms": tp_gpu, "points_per_s": rows as f64 / (tp_gpu.max(1e-9) / 1e3), "accumulation": accumulation.describe(ctx) });
    Ok(())
}

/// SSIM (map + gradient) and LPIPS (value + gradient) at 512 x 512.
fn images(ctx: &Context, args: &OpsArgs, out: &mut serde_json::Value) -> anyhow::Result<()> {
    let side = 512u32;
    let px = (side * side * 3) as usize;
    let img_a = ctx.upload(
        "bench ssim a",
        &random(px, 6)
            .iter()
            .map(|v| 0.5 + 0.5 * v)
            .collect::<Vec<f32>>(),
    )?;
    let img_b = ctx.upload(
        "bench ssim b",
        &random(px, 7)
            .iter()
            .map(|v| 0.5 + 0.5 * v)
            .collect::<Vec<f32>>(),
    )?;
    if args.wants("ssim") {
        let ssim_grad =
            ctx.create_buffer("bench ssim grad", BufferDesc::gpu_only((px * 4) as u64))?;
        let ssim = drape_engine::ops::ssim::Ssim::new(ctx, side, side)?;
        let (ssim_wall, ssim_gpu) = timed(ctx, args, || {
            let mut rec = ctx.record("bench ssim")?;
            ssim.record(&mut rec, &img_a, &img_b, Some((&ssim_grad, -1.0)))?;
            Ok(rec.submit_and_wait()?)
        })?;
        out["ssim_512"] = json!({ "fwd_bwd_ms": ssim_wall, "fwd_bwd_gpu_ms": ssim_gpu });
    }
    if !args.wants("lpips") {
        return Ok(());
    }
    // LPIPS (AlexNet, value + gradient to the first image) at 512 x 512, with seeded
    // random weights: the cost does not depend on the values.
    let net = drape_engine::ops::lpips::LpipsNet::Alex;
    let mut rng = rand::rngs::StdRng::seed_from_u64(8);
    let tensors = net.tensors().into_iter().map(|(name, shape)| {
        let n: usize = shape.iter().product();
        (
            name,
            (0..n)
                .map(|_| rng.random_range(-0.05f32..0.05).abs())
                .collect::<Vec<f32>>(),
        )
    });
    let weights = drape_engine::ops::lpips::LpipsWeights {
        net,
        tensors: tensors.collect(),
    };
    let lpips = drape_engine::ops::lpips::Lpips::new(ctx, &weights, side, side)?;
    let lpips_grad =
        ctx.create_buffer("bench lpips grad", BufferDesc::gpu_only((px * 4) as u64))?;
    let (lpips_wall, lpips_gpu) = timed(ctx, args, || {
        let mut rec = ctx.record("bench lpips")?;
        lpips.record(&mut rec, &img_a, &img_b, Some((&lpips_grad, 1.0)))?;
        Ok(rec.submit_and_wait()?)
    })?;
    out["lpips_alex_512"] = json!({ "fwd_bwd_ms": lpips_wall, "fwd_bwd_gpu_ms": lpips_gpu, "weights": "random (timing only)" });
    Ok(())
}

pub fn print_table(r: &serde_json::Value) {
    println!(
        "neural ops at {} rows on {} (median of {} runs)",
        r["rows"],
        r["device"].as_str().unwrap_or("?"),
        r["runs"]
    );
    println!(
        "  {:>9} {:>11} {:>10} {:>11} {:>10} {:>11} {:>8}",
        "layer", "fwd GPU ms", "GFLOP/s", "bwd GPU ms", "GFLOP/s", "CPU GFLOP/s", "GPU/CPU"
    );
    for g in r["gemm"].as_array().into_iter().flatten() {
        println!(
            "  {:>4}->{:<4} {:>11.2} {:>10.2} {:>11.2} {:>10.2} {:>11.2} {:>8.2}",
            g["in"],
            g["out"],
            g["forward_gpu_ms"].as_f64().unwrap_or(0.0),
            g["forward_gflops"].as_f64().unwrap_or(0.0),
            g["backward_gpu_ms"].as_f64().unwrap_or(0.0),
            g["backward_gflops"].as_f64().unwrap_or(0.0),
            g["cpu_gflops"].as_f64().unwrap_or(0.0),
            g["gpu_over_cpu_throughput"].as_f64().unwrap_or(0.0)
        );
    }
    let splits: Vec<String> = r["gemm"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|g| {
            let passes = g["backward_passes_gpu_ms"]
                .as_object()
                .map(|m| {
                    m.iter()
                        .map(|(k, v)| {
                            format!(
                                "{} {:.1}",
                                k.trim_start_matches("mlp."),
                                v.as_f64().unwrap_or(0.0)
                            )
                        })
                        .collect::<Vec<_>>()
                        .join(", ")
                })
                .unwrap_or_default();
            format!("{}->{}: {passes}", g["in"], g["out"])
        })
        .collect();
    if !splits.is_empty() {
        println!(
            "  backward by pass (GPU ms, one run): {}",
            splits.join("; ")
        );
    }
    if let Some(ms) = r["decoders_fwd_bwd_gpu_ms"].as_f64() {
        println!("  three HUGS decoders, forward + backward: {ms:.1} ms GPU");
    }
    if let Some(ms) = r["ssim_512"]["fwd_bwd_gpu_ms"].as_f64() {
        println!("  SSIM 512x512, map + gradient: {ms:.1} ms GPU");
    }
    if let Some(ms) = r["lpips_alex_512"]["fwd_bwd_gpu_ms"].as_f64() {
        println!("  LPIPS (AlexNet) 512x512, value + gradient: {ms:.1} ms GPU");
    }
    for c in r["chamfer"].as_array().into_iter().flatten() {
        println!(
            "  Chamfer {} x {} points ({}), both directions + gradient: {:.1} ms GPU",
            c["points"],
            c["points"],
            c["search"].as_str().unwrap_or("?"),
            c["fwd_bwd_gpu_ms"].as_f64().unwrap_or(0.0)
        );
    }
    let t = &r["triplane"];
    if t.is_null() {
        return;
    }
    println!(
        "  triplane {}x{}x{} sample + backward: {:.1} ms GPU ({:.2} M points/s)",
        t["resolution"],
        t["resolution"],
        t["channels"],
        t["fwd_bwd_gpu_ms"].as_f64().unwrap_or(0.0),
        t["points_per_s"].as_f64().unwrap_or(0.0) / 1e6
    );
}
