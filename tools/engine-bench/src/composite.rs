//! `engine-bench composite`: frame time of a layered scene of the avatar's size (body,
//! cloth and scene Gaussians) rendered as the paper's three passes and composited
//! (`ops::splat::composite`), beside the same layers in one depth-sorted pass; forward
//! and forward + backward, with per-pass GPU ms.
//!
//! Three variants of the paper's frame: serialised (each pass its own submission, the
//! composite a fourth: the passes cannot overlap), overlapped (the three renders and the
//! composite in one recording, which the recorder interleaves wave by wave: one
//! submission), fused (`ops::splat::fused`: one sort and binning of every layer, one
//! rasterization with three states per pixel, and the composite: one submission; the
//! paper's matte; forward, then the composite's backward and the fused one-walk
//! backward in a second submission), and one depth-sorted pass.

use std::collections::BTreeMap;
use std::time::Instant;

use drape_cli_support::median;
use drape_engine::ops::splat::composite::{
    matte_cloud, record_composite, record_composite_backward, CompositeGrads, CompositeInputs,
};
use drape_engine::ops::splat::fused::{FusedGrads, FusedRenderer};
use drape_engine::ops::splat::render::{Accumulation, GaussianBuffers, SplatRenderer};
use drape_engine::ops::splat::scene::{GaussianCloud, PinholeCamera, RenderSettings};
use drape_engine::{Buffer, BufferDesc, Context, PassTimings};
use drape_trainer::avatar::composite::layer_masks;
use drape_trainer::avatar::groups::Layer;
use serde_json::json;

/// Options of `engine-bench composite`.
#[derive(Clone, Debug, clap::Args)]
pub struct CompositeArgs {
    /// Image sizes, WIDTHxHEIGHT, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "512x512,1920x1080", value_parser = crate::splat::parse_size)]
    pub sizes: Vec<(u32, u32)>,
    /// Body Gaussians (the paper's body: about 110k-150k).
    #[arg(long, default_value_t = 150_000)]
    pub body: u32,
    /// Cloth Gaussians.
    #[arg(long, default_value_t = 30_000)]
    pub cloth: u32,
    /// Scene Gaussians.
    #[arg(long, default_value_t = 100_000)]
    pub scene: u32,
    /// Timed runs per configuration (the median is reported).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..))]
    pub runs: u32,
    /// Untimed warm-up runs first (at least this many, and for at least --warm-seconds).
    #[arg(long, default_value_t = 1)]
    pub warmup: u32,
    /// Print one JSON object on stdout instead of a table.
    #[arg(long)]
    pub json: bool,
}

fn with_layer(mut c: GaussianCloud, layer: Layer) -> GaussianCloud {
    c.groups = vec![layer.group(); c.len()];
    c
}

/// A person-sized body and cloth at the origin in front of a wider scene behind it.
fn layered(args: &CompositeArgs) -> [GaussianCloud; 3] {
    let small = |n: u32| 0.8 / (n.max(1) as f32).sqrt();
    [
        with_layer(
            GaussianCloud::random(
                args.body as usize,
                3,
                0.5,
                (-0.25, 0.25),
                small(args.body),
                1,
            ),
            Layer::Body,
        ),
        with_layer(
            GaussianCloud::random(
                args.cloth as usize,
                3,
                0.45,
                (-0.3, 0.3),
                small(args.cloth),
                2,
            ),
            Layer::Cloth,
        ),
        with_layer(
            GaussianCloud::random(
                args.scene as usize,
                3,
                3.0,
                (0.5, 4.0),
                4.0 / (args.scene.max(1) as f32).sqrt(),
                3,
            ),
            Layer::Scene,
        ),
    ]
}

struct Pass {
    gaussians: GaussianBuffers,
    grads: GaussianBuffers,
    renderer: SplatRenderer,
}

impl Pass {
    fn new(
        ctx: &Context,
        name: &str,
        cloud: &GaussianCloud,
        w: u32,
        h: u32,
    ) -> anyhow::Result<Self> {
        Ok(Self {
            gaussians: GaussianBuffers::upload(ctx, name, cloud)?,
            grads: GaussianBuffers::new(ctx, name, cloud.len(), cloud.sh_degree)?,
            renderer: SplatRenderer::new(ctx, w, h, cloud.len())?,
        })
    }
}

fn add(into: &mut BTreeMap<String, f64>, t: &PassTimings) {
    for (k, v) in t.by_name() {
        *into.entry(k).or_insert(0.0) += v;
    }
}

/// Medians of (forward ms, forward + backward ms) and per-pass GPU ms of `frame`.
fn time(
    args: &CompositeArgs,
    mut frame: impl FnMut(&mut BTreeMap<String, f64>) -> anyhow::Result<f64>,
) -> anyhow::Result<(f64, f64, BTreeMap<String, f64>)> {
    let (mut fwd, mut both) = (Vec::new(), Vec::new());
    let mut passes: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    for timed in crate::schedule::Runs::new(args.warmup, args.runs) {
        let mut p = BTreeMap::new();
        let t0 = Instant::now();
        let t_fwd = frame(&mut p)?;
        let t_both = t0.elapsed().as_secs_f64() * 1e3;
        if !timed {
            continue;
        }
        fwd.push(t_fwd);
        both.push(t_both);
        for (k, v) in p {
            passes.entry(k).or_default().push(v);
        }
    }
    Ok((
        median(&fwd),
        median(&both),
        passes.into_iter().map(|(k, v)| (k, median(&v))).collect(),
    ))
}

fn bench_size(
    ctx: &Context,
    args: &CompositeArgs,
    clouds: &[GaussianCloud; 3],
    w: u32,
    h: u32,
) -> anyhow::Result<serde_json::Value> {
    let [body, cloth, scene] = clouds;
    let settings = RenderSettings::default();
    let mut camera = PinholeCamera::look_at(
        [0.3, -0.4, -3.0],
        [0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
        45.0,
        w,
        h,
    )
    .expect("valid camera");
    camera.background = [0.5; 3];
    let black = PinholeCamera {
        background: [0.0; 3],
        ..camera
    };
    let pixels = (w * h) as usize;
    let image = |name: &str, floats: usize| {
        ctx.create_buffer(name, BufferDesc::gpu_only(4 * floats as u64))
    };
    let grad_rgb = ctx.upload("bench grad rgb", &vec![1e-3f32; 3 * pixels])?;
    let zeros = ctx.upload("bench zeros", &vec![0.0f32; pixels])?;

    // Three passes: body + scene, cloth, matte (scene 0, cloth 1), composited.
    let mut base_cloud = body.clone();
    base_cloud.extend(scene);
    let mut base = Pass::new(ctx, "bench base", &base_cloud, w, h)?;
    let mut over = Pass::new(ctx, "bench cloth", cloth, w, h)?;
    let mut matte = Pass::new(
        ctx,
        "bench matte",
        &matte_cloud(&[(scene, false), (cloth, true)]),
        w,
        h,
    )?;
    let out: Buffer = image("bench composite", 3 * pixels)?;
    let (g_base, g_over, g_alpha, g_matte) = (
        image("bench g base", 3 * pixels)?,
        image("bench g cloth", 3 * pixels)?,
        image("bench g alpha", pixels)?,
        image("bench g matte", 3 * pixels)?,
    );
    let three = time(args, |p| {
        let t0 = Instant::now();
        let mut saved = Vec::new();
        for (pass, cam) in [
            (&mut base, &camera),
            (&mut over, &black),
            (&mut matte, &black),
        ] {
            let stats = pass.renderer.forward(&pass.gaussians, cam, &settings)?;
            add(p, &stats.timings);
            saved.push(stats.saved);
        }
        let inputs = CompositeInputs {
            base_rgb: base.renderer.outputs().0,
            over_rgb: over.renderer.outputs().0,
            over_alpha: over.renderer.outputs().1,
            matte_rgb: Some(matte.renderer.outputs().0),
        };
        {
            let mut rec = ctx.record("composite")?;
            record_composite(&mut rec, inputs, &out, pixels as u32)?;
            add(p, &rec.submit_and_wait()?);
        }
        let t_fwd = t0.elapsed().as_secs_f64() * 1e3;
        {
            let grads = CompositeGrads {
                base_rgb: &g_base,
                over_rgb: &g_over,
                over_alpha: &g_alpha,
                matte_rgb: Some(&g_matte),
            };
            let mut rec = ctx.record("composite backward")?;
            record_composite_backward(&mut rec, &grad_rgb, inputs, grads, pixels as u32)?;
            add(p, &rec.submit_and_wait()?);
        }
        add(
            p,
            &base.renderer.backward(
                &saved[0],
                &base.gaussians,
                &g_base,
                &zeros,
                &zeros,
                &base.grads,
                Accumulation::Auto,
            )?,
        );
        add(
            p,
            &over.renderer.backward(
                &saved[1],
                &over.gaussians,
                &g_over,
                &g_alpha,
                &zeros,
                &over.grads,
                Accumulation::Auto,
            )?,
        );
        add(
            p,
            &matte.renderer.backward(
                &saved[2],
                &matte.gaussians,
                &g_matte,
                &zeros,
                &zeros,
                &matte.grads,
                Accumulation::Auto,
            )?,
        );
        Ok(t_fwd)
    })?;
    // The same three passes and composite recorded into one submission.
    let mut submissions = Vec::new();
    let overlapped = time(args, |p| {
        let t0 = Instant::now();
        let before = ctx.submission_count();
        base.renderer
            .prepare_forward(&base.gaussians, &camera, &settings)?;
        over.renderer
            .prepare_forward(&over.gaussians, &black, &settings)?;
        matte
            .renderer
            .prepare_forward(&matte.gaussians, &black, &settings)?;
        loop {
            {
                let inputs = CompositeInputs {
                    base_rgb: base.renderer.outputs().0,
                    over_rgb: over.renderer.outputs().0,
                    over_alpha: over.renderer.outputs().1,
                    matte_rgb: Some(matte.renderer.outputs().0),
                };
                let mut rec = ctx.record("composite frame")?;
                base.renderer.record_forward(&mut rec, &base.gaussians)?;
                over.renderer.record_forward(&mut rec, &over.gaussians)?;
                matte.renderer.record_forward(&mut rec, &matte.gaussians)?;
                record_composite(&mut rec, inputs, &out, pixels as u32)?;
                add(p, &rec.submit_and_wait()?);
            }
            let again = [
                base.renderer.finish_forward()?,
                over.renderer.finish_forward()?,
                matte.renderer.finish_forward()?,
            ]
            .iter()
            .any(|s| s.rerendered);
            if !again {
                break;
            }
        }
        submissions.push(ctx.submission_count() - before);
        Ok(t0.elapsed().as_secs_f64() * 1e3)
    })?;
    drop((base, over, matte));

    // Fused: one sort and binning of every layer, one rasterization with three states
    // per pixel, and the composite, in one submission (the paper's matte).
    let mut all_cloud = base_cloud;
    all_cloud.extend(cloth);
    let layers: Vec<Layer> = [
        (Layer::Body, body.len()),
        (Layer::Scene, scene.len()),
        (Layer::Cloth, cloth.len()),
    ]
    .iter()
    .flat_map(|&(l, n)| std::iter::repeat_n(l, n))
    .collect();
    let fused_gaussians = GaussianBuffers::upload(ctx, "bench fused", &all_cloud)?;
    let fused_grads = GaussianBuffers::new(
        ctx,
        "bench fused grads",
        all_cloud.len(),
        all_cloud.sh_degree,
    )?;
    let mut fused = FusedRenderer::new(ctx, w, h, all_cloud.len())?;
    fused.set_masks(ctx, &layer_masks(&layers, false))?;
    let fused_time = time(args, |p| {
        let t0 = Instant::now();
        fused.prepare_forward(&fused_gaussians, &camera, &settings)?;
        let saved = loop {
            {
                let mut rec = ctx.record("fused frame")?;
                fused.record_forward(&mut rec, &fused_gaussians)?;
                record_composite(&mut rec, fused.outputs(), &out, pixels as u32)?;
                add(p, &rec.submit_and_wait()?);
            }
            let stats = fused.finish_forward()?;
            if !stats.rerendered {
                break stats.saved;
            }
        };
        let t_fwd = t0.elapsed().as_secs_f64() * 1e3;
        // The composite's backward and the one-walk backward, in one submission.
        fused.prepare_backward(Accumulation::Auto)?;
        let grads = CompositeGrads {
            base_rgb: &g_base,
            over_rgb: &g_over,
            over_alpha: &g_alpha,
            matte_rgb: Some(&g_matte),
        };
        let upstream = FusedGrads {
            base_rgb: &g_base,
            over_rgb: &g_over,
            over_alpha: &g_alpha,
            matte_rgb: &g_matte,
        };
        let mut rec = ctx.record("fused backward")?;
        record_composite_backward(&mut rec, &grad_rgb, fused.outputs(), grads, pixels as u32)?;
        fused.record_backward(
            &mut rec,
            &saved,
            &fused_gaussians,
            upstream,
            &fused_grads,
            Accumulation::Auto,
        )?;
        add(p, &rec.submit_and_wait()?);
        Ok(t_fwd)
    })?;
    drop((fused, fused_gaussians, fused_grads));

    // One depth-sorted pass of every layer.
    let mut all = Pass::new(ctx, "bench one pass", &all_cloud, w, h)?;
    let one = time(args, |p| {
        let t0 = Instant::now();
        let stats = all.renderer.forward(&all.gaussians, &camera, &settings)?;
        add(p, &stats.timings);
        let t_fwd = t0.elapsed().as_secs_f64() * 1e3;
        add(
            p,
            &all.renderer.backward(
                &stats.saved,
                &all.gaussians,
                &grad_rgb,
                &zeros,
                &zeros,
                &all.grads,
                Accumulation::Auto,
            )?,
        );
        Ok(t_fwd)
    })?;
    let three_fwd = three.0;
    let three_both = three.1;
    let variant = |(fwd, both, passes): (f64, f64, BTreeMap<String, f64>)| json!({ "forward_median_ms": fwd, "forward_fps": 1e3 / fwd, "forward_backward_median_ms": both, "passes_gpu_ms": passes });
    Ok(json!({
        "width": w,
        "height": h,
        "three_pass_serialised": variant(three),
        "one_pass": variant(one),
        "three_pass_overlapped": json!({
            "forward_median_ms": overlapped.0,
            "forward_fps": 1e3 / overlapped.0,
            "passes_gpu_ms": overlapped.2,
            "forward_submissions": submissions.last().copied().unwrap_or(0),
        }),
        "fused": json!({
            "forward_median_ms": fused_time.0,
            "forward_fps": 1e3 / fused_time.0,
            "forward_backward_median_ms": fused_time.1,
            "passes_gpu_ms": fused_time.2,
            "speedup_over_serialised": three_fwd / fused_time.0,
            "forward_backward_speedup_over_serialised": three_both / fused_time.1,
        }),
    }))
}

pub fn run(ctx: &Context, args: &CompositeArgs) -> anyhow::Result<serde_json::Value> {
    let clouds = layered(args);
    let mut results = Vec::new();
    for &(w, h) in &args.sizes {
        eprintln!("composite: {w}x{h} ...");
        results.push(bench_size(ctx, args, &clouds, w, h)?);
    }
    Ok(json!({
        "job": "composite",
        "device": ctx.info().name,
        "device_kind": format!("{:?}", ctx.info().kind),
        "gaussians": { "body": args.body, "cloth": args.cloth, "scene": args.scene },
        "runs": args.runs,
        "warmup": args.warmup,
        "results": results,
    }))
}

pub fn print_table(r: &serde_json::Value) {
    let g = &r["gaussians"];
    println!(
        "composite on {} ({} body + {} cloth + {} scene Gaussians; {} runs, median)",
        r["device"].as_str().unwrap_or("?"),
        g["body"],
        g["cloth"],
        g["scene"],
        r["runs"]
    );
    for c in r["results"].as_array().into_iter().flatten() {
        for (key, label) in [
            ("three_pass_serialised", "three passes, serialised"),
            ("three_pass_overlapped", "three passes, overlapped"),
            ("fused", "fused (one sort, one walk)"),
            ("one_pass", "one depth-sorted pass"),
        ] {
            let v = &c[key];
            let both = match v["forward_backward_median_ms"].as_f64() {
                Some(ms) => format!("{ms:>9.1} ms"),
                None => format!("{:>9}", "-"),
            };
            println!(
                "  {}x{} {:<26} fwd {:>9.1} ms {:>6.2} FPS | fwd+bwd {both}",
                c["width"],
                c["height"],
                label,
                v["forward_median_ms"].as_f64().unwrap_or(0.0),
                v["forward_fps"].as_f64().unwrap_or(0.0),
            );
            if let Some(passes) = v["passes_gpu_ms"].as_object() {
                let mut top: Vec<(&String, f64)> = passes
                    .iter()
                    .map(|(k, v)| (k, v.as_f64().unwrap_or(0.0)))
                    .collect();
                top.sort_by(|a, b| b.1.total_cmp(&a.1));
                let line: Vec<String> = top
                    .iter()
                    .take(6)
                    .map(|(k, v)| format!("{k} {v:.1}"))
                    .collect();
                println!("      GPU ms: {}", line.join(", "));
            }
        }
        println!(
            "  {}x{} fused forward {:.2}x faster than three serialised passes, forward + backward {:.2}x",
            c["width"],
            c["height"],
            c["fused"]["speedup_over_serialised"].as_f64().unwrap_or(0.0),
            c["fused"]["forward_backward_speedup_over_serialised"].as_f64().unwrap_or(0.0)
        );
    }
}
