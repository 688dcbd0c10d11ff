//! `drape bench-cloth`: the synthetic cloth benchmark. For each
//! garment fit × motion it synthesises a sequence (`drape synth`, NeuMan layout, ground
//! truth garments), trains the full model, the paper's ablation rows and the
//! single-layer baseline on it, evaluates each on the held-out frames (every fifth from
//! the second), and writes `bench.json`, `bench.md` (a table per sequence and, row by
//! row, whether the full model beats it as the paper claims: measured, never assumed)
//! and `bench.png` (human-crop PSNR per row per sequence).
//!
//! Layout of `--out`: `data/<fit>-<motion>/` (the sequences), `runs/<fit>-<motion>/<row>/`
//! (ordinary `drape train` run directories: `drape eval` and `drape animate` open them).
//!
//! Rows (Table "Ablation study" of the paper; names as there):
//! - `full` ("Ours"): every loss at the preset's weights.
//! - `no-physics` ("w/o Phys. losses"): simulation, ARAP and mask losses off, cloth-LBS on.
//!   The paper lists "Mask loss only" as a separate row, so "physics" there cannot be
//!   just simulation + ARAP (that would be the same run as "Mask loss only"); we read
//!   it as all three cloth losses the paper adds on top of the layering.
//! - `no-lbs` ("w/o Cloth LBS Reg."): cloth-LBS weight 0.
//! - `arap-only`, `sim-only`, `mask-only` ("ARAP loss only", "Simulation loss only",
//!   "Mask loss only"): one of the three cloth losses kept, the other two 0; cloth-LBS on.
//! - `single-layer` (HUGS: the cloth folded into the body; `--layers body+scene`): has
//!   no cloth Gaussians, so its cloth Chamfer is n/a.
//!
//! Every row's cloth layer and simulation target are made from the T-shirt of the
//! sequence's fit (config `layers.cloth_fit`), as the paper's synthetic setting has the
//! garment template that was simulated.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context as _;
use drape_cli_support::DeviceArgs;
use drape_trainer::avatar::eval::EvalMetrics;
use drape_trainer::avatar::model::LayerChoice;
use drape_trainer::avatar::train::{
    body_model, load_sequence, Preset, Progress, TrainConfig, TrainJob,
};
use drape_trainer::dataset::synth::{generate, SynthOptions};
use drape_trainer::garment::GarmentFit;
use drape_trainer::motion::MotionKind;
use serde_json::json;

/// Options of `drape bench-cloth`.
#[derive(Clone, Debug, clap::Args)]
pub struct BenchClothArgs {
    /// Output directory (new or empty): data/, runs/, bench.json, bench.md, bench.png.
    #[arg(long)]
    pub out: PathBuf,
    /// T-shirt fits to synthesise, comma-separated: loose (4.5 cm of ease, longer hem),
    /// tight (1.5 cm, `drape synth`'s default).
    #[arg(long, default_value = "loose,tight")]
    pub fits: String,
    /// Motions to synthesise, comma-separated: walk, jog, raise-arms, turn.
    #[arg(long, default_value = "walk,jog")]
    pub motions: String,
    /// Rows to train, comma-separated: full (every loss), no-physics (simulation, ARAP
    /// and mask losses off), no-lbs (cloth-LBS off), arap-only, sim-only, mask-only (one
    /// cloth loss kept), single-layer (HUGS: --layers body+scene, no cloth layer).
    #[arg(
        long,
        default_value = "full,no-physics,no-lbs,arap-only,sim-only,mask-only,single-layer"
    )]
    pub rows: String,
    /// Training preset of every row (quick: sized for lavapipe; paper: for a GPU).
    #[arg(long, default_value = "quick")]
    pub preset: String,
    /// Training steps of every row (default: the preset's).
    #[arg(long)]
    pub steps: Option<u32>,
    /// Skinning-weight fitting steps before training (default: the preset's); fewer
    /// for smoke tests.
    #[arg(long)]
    pub fit_steps: Option<u32>,
    /// Image width and height of the synthetic sequences in pixels.
    #[arg(long, allow_negative_numbers = true, default_value_t = 128, value_parser = clap::value_parser!(u32).range(16..=2048))]
    pub size: u32,
    /// Frames per sequence at 30 fps (every fifth, from the second, is held out).
    #[arg(long, allow_negative_numbers = true, default_value_t = 30, value_parser = clap::value_parser!(u32).range(3..=3000))]
    pub frames: u32,
    /// Seed of the sequences' handheld camera and of training.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// LPIPS weights (safetensors, scripts/lpips-to-safetensors.py): LPIPS joins every
    /// row's loss and the metrics; without it LPIPS is n/a.
    #[arg(long)]
    pub lpips_weights: Option<PathBuf>,
}

/// One row of the ablation: its key, the paper's name and how it changes the config.
#[derive(Clone, Copy, Debug)]
struct Row {
    key: &'static str,
    paper: &'static str,
    apply: fn(&mut TrainConfig),
}

const ROWS: [Row; 7] = [
    Row {
        key: "full",
        paper: "Ours (full)",
        apply: |_| {},
    },
    Row {
        key: "no-physics",
        paper: "w/o Phys. losses",
        apply: |c| {
            c.losses.lambda_sim = 0.0;
            c.losses.lambda_arap = 0.0;
            c.losses.lambda_mask = 0.0;
        },
    },
    Row {
        key: "no-lbs",
        paper: "w/o Cloth LBS Reg.",
        apply: |c| c.losses.lambda_cloth_lbs = 0.0,
    },
    Row {
        key: "arap-only",
        paper: "ARAP loss only",
        apply: |c| {
            c.losses.lambda_sim = 0.0;
            c.losses.lambda_mask = 0.0;
        },
    },
    Row {
        key: "sim-only",
        paper: "Simulation loss only",
        apply: |c| {
            c.losses.lambda_arap = 0.0;
            c.losses.lambda_mask = 0.0;
        },
    },
    Row {
        key: "mask-only",
        paper: "Mask loss only",
        apply: |c| {
            c.losses.lambda_sim = 0.0;
            c.losses.lambda_arap = 0.0;
        },
    },
    Row {
        key: "single-layer",
        paper: "Single layer (HUGS)",
        apply: |c| {
            c.layers.choice = LayerChoice {
                cloth: Some(false),
                scene: Some(true),
            }
        },
    },
];

fn list<T>(
    s: &str,
    what: &str,
    choices: &str,
    parse: impl Fn(&str) -> Option<T>,
) -> anyhow::Result<Vec<T>> {
    let items: Vec<T> = s
        .split(',')
        .map(str::trim)
        .filter(|x| !x.is_empty())
        .map(|x| parse(x).ok_or_else(|| anyhow::anyhow!("--{what}: '{x}' is not one of {choices}")))
        .collect::<anyhow::Result<_>>()?;
    anyhow::ensure!(!items.is_empty(), "--{what} is empty");
    Ok(items)
}

/// A finite number as JSON, anything else as null (JSON has no NaN or infinity).
fn num(v: f64) -> serde_json::Value {
    if v.is_finite() {
        json!(v)
    } else {
        serde_json::Value::Null
    }
}

fn metrics_json(m: &EvalMetrics) -> serde_json::Value {
    let opt = |v: Option<f64>| v.map_or(serde_json::Value::Null, num);
    json!({
        "frames": m.frames,
        "psnr_full": num(m.psnr_full), "psnr_crop": num(m.psnr_crop),
        "ssim_full": num(m.ssim_full), "ssim_crop": num(m.ssim_crop),
        "lpips_full": opt(m.lpips_full), "lpips_crop": opt(m.lpips_crop),
        "cloth_chamfer_m": opt(m.cloth_chamfer),
    })
}

pub fn run(device: &DeviceArgs, args: &BenchClothArgs) -> anyhow::Result<()> {
    let fits = list(&args.fits, "fits", "loose, tight", GarmentFit::parse)?;
    let motions = list(
        &args.motions,
        "motions",
        "walk, jog, raise-arms, turn",
        MotionKind::parse,
    )?;
    let rows = list(&args.rows, "rows", &ROWS.map(|r| r.key).join(", "), |k| {
        ROWS.iter().find(|r| r.key == k).copied()
    })?;
    let mut base = TrainConfig::preset(Preset::parse(&args.preset).context("--preset")?);
    if let Some(s) = args.steps {
        base.schedule.steps = s;
    }
    if let Some(s) = args.fit_steps {
        base.schedule.fit_steps = s;
    }
    base.seed = args.seed;
    base.losses.lpips_weights = args.lpips_weights.clone();
    base.validate()?;
    // Runs are never overwritten: a finished benchmark stays as it was measured.
    if args.out.exists() {
        let mut entries = std::fs::read_dir(&args.out)
            .with_context(|| format!("--out {}: cannot read", args.out.display()))?;
        anyhow::ensure!(
            entries.next().is_none(),
            "--out {}: not empty (bench-cloth writes a new directory)",
            args.out.display()
        );
    }
    if let Some(path) = &base.losses.lpips_weights {
        drape_engine::ops::lpips::LpipsWeights::load(path, base.losses.lpips_net)?;
    }
    // All or nothing: a benchmark that fails leaves no directory behind (an empty one
    // that was there stays, empty).
    let created = !args.out.exists();
    let result = measure(device, args, &fits, &motions, &rows, &base);
    if result.is_err() {
        if created {
            let _ = std::fs::remove_dir_all(&args.out);
        } else if let Ok(entries) = std::fs::read_dir(&args.out) {
            for e in entries.flatten() {
                let _ = if e.path().is_dir() {
                    std::fs::remove_dir_all(e.path())
                } else {
                    std::fs::remove_file(e.path())
                };
            }
        }
    }
    result
}

fn measure(
    device: &DeviceArgs,
    args: &BenchClothArgs,
    fits: &[GarmentFit],
    motions: &[MotionKind],
    rows: &[Row],
    base: &TrainConfig,
) -> anyhow::Result<()> {
    let ctx = device.open()?;
    let total = fits.len() * motions.len() * rows.len();
    let mut done = 0;
    let mut sequences = Vec::new();
    let t_all = Instant::now();
    for &fit in fits {
        for &motion in motions {
            let name = format!("{}-{}", fit.name(), motion_name(motion));
            let data = args.out.join("data").join(&name);
            let options = SynthOptions {
                width: args.size,
                height: args.size,
                frames: args.frames as usize,
                cameras: 1,
                motion,
                seed: args.seed,
                samples: 2,
                garment: fit,
            };
            let t0 = Instant::now();
            generate(&data, &options, &mut |stage, d, n| {
                eprint!("\r[{name}] synth: {stage:<18} {d:>4}/{n}   ");
                let _ = std::io::stderr().flush();
            })
            .map_err(|e| anyhow::anyhow!("{}: {e}", data.display()))?;
            eprintln!();
            println!(
                "[{name}] synthesised {} frames at {}x{} in {:.1} s",
                args.frames,
                args.size,
                args.size,
                t0.elapsed().as_secs_f64()
            );
            let seq = load_sequence(&data, 0)?;
            let mut results = Vec::new();
            for row in rows {
                done += 1;
                let mut config = base.clone();
                config.layers.cloth_fit = fit;
                (row.apply)(&mut config);
                let out = args.out.join("runs").join(&name).join(row.key);
                let model = body_model(None)?;
                let t0 = Instant::now();
                let report = TrainJob::new(&seq, model, &config, &out)
                    .progress(&mut |p| {
                        match p {
                            Progress::Fit {
                                layer, step, total, ..
                            } => {
                                eprint!("\r  fitting {layer} skinning weights {step:>5}/{total}   ")
                            }
                            Progress::Step {
                                step,
                                total,
                                psnr,
                                it_per_s,
                                ..
                            } => eprint!(
                            "\r  step {step:>6}/{total}  PSNR {psnr:5.2} dB  {it_per_s:.2} it/s   "
                        ),
                            Progress::Simulate { done, total } => {
                                eprint!("\r  simulating the garments {done:>4}/{total}   ")
                            }
                            Progress::Densify { .. } => {}
                            Progress::Eval { done, total } => {
                                eprint!("\r  evaluating {}/{total}   ", done + 1)
                            }
                        }
                        let _ = std::io::stderr().flush();
                    })
                    .train(&ctx)
                    .map_err(|e| anyhow::anyhow!("{name} {}: {e}", row.key))?;
                eprint!("\r{:80}\r", "");
                let wall = t0.elapsed().as_secs_f64();
                let m = &report.fin;
                let chamfer = m
                    .cloth_chamfer
                    .map_or("n/a".to_string(), |c| format!("{:.2} mm", 1e3 * c));
                println!(
                    "[{done}/{total}] {name} {:<12} crop PSNR {:.2} dB, SSIM {:.4}; full PSNR {:.2} dB; cloth Chamfer {chamfer}; {:.1} s ({:.2} it/s)",
                    row.key, m.psnr_crop, m.ssim_crop, m.psnr_full, wall, report.iterations_per_second
                );
                results.push(json!({
                    "row": row.key, "paper": row.paper, "run": out.display().to_string(),
                    "lambda_cloth_lbs": config.losses.lambda_cloth_lbs, "lambda_sim": config.losses.lambda_sim, "lambda_arap": config.losses.lambda_arap, "lambda_mask": config.losses.lambda_mask, "layers": config.layers.choice,
                    "metrics": metrics_json(m),
                    "wall_s": wall, "train_s": report.train_seconds, "it_per_s": num(report.iterations_per_second), "steps": report.steps,
                }));
            }
            sequences.push(json!({ "sequence": name, "fit": fit.name(), "motion": motion_name(motion), "data": data.display().to_string(), "rows": results }));
        }
    }
    let command = std::env::args().collect::<Vec<_>>().join(" ");
    let mut report = json!({
        "command": command,
        "preset": args.preset, "steps": base.schedule.steps, "fit_steps": base.schedule.fit_steps, "size": args.size, "frames": args.frames, "seed": args.seed,
        "device": ctx.info().name,
        "lpips": args.lpips_weights.is_some(),
        "seconds": t_all.elapsed().as_secs_f64(),
        "sequences": sequences,
    });
    let claims: Vec<serde_json::Value> = report["sequences"]
        .as_array()
        .map(|s| s.iter().map(claim).collect())
        .unwrap_or_default();
    report["claim"] = claims.into();
    device.check_validation(&ctx)?;
    write(
        &args.out.join("bench.json"),
        &serde_json::to_string_pretty(&report)?,
    )?;
    write(&args.out.join("bench.md"), &markdown(&report))?;
    let png = args.out.join("bench.png");
    plot(&report)
        .save(&png)
        .with_context(|| format!("{}: cannot write", png.display()))?;
    println!(
        "wrote {} (bench.json, bench.md, bench.png) in {:.1} s",
        args.out.display(),
        t_all.elapsed().as_secs_f64()
    );
    Ok(())
}

fn motion_name(m: MotionKind) -> &'static str {
    ["walk", "jog", "raise-arms", "turn"]
        .into_iter()
        .find(|n| MotionKind::parse(n) == Some(m))
        .unwrap_or("motion")
}

fn write(path: &Path, text: &str) -> anyhow::Result<()> {
    drape_io::write(path, text).with_context(|| format!("{}: cannot write", path.display()))
}

/// One comparison of the full model with a row: which is better on a metric, or why it
/// cannot be said.
fn compare(
    full: &serde_json::Value,
    other: &serde_json::Value,
    key: &str,
    higher_is_better: bool,
) -> serde_json::Value {
    match (full[key].as_f64(), other[key].as_f64()) {
        (Some(f), Some(o)) => {
            json!({ "full": f, "row": o, "full_better": if higher_is_better { f > o } else { f < o } })
        }
        _ => json!({ "full_better": null, "why": "not measured for one of the two" }),
    }
}

/// The paper's claim on one sequence, row by row: the full model beats the row on the
/// human crop (PSNR, SSIM; LPIPS where measured) and on cloth geometry (Chamfer, where
/// the row has a cloth layer). A row "holds" when every measured comparison does.
fn claim(seq: &serde_json::Value) -> serde_json::Value {
    let rows = seq["rows"].as_array().cloned().unwrap_or_default();
    let Some(full) = rows.iter().find(|r| r["row"] == "full") else {
        return json!({ "sequence": seq["sequence"], "holds": null, "why": "no full row was trained", "rows": [] });
    };
    let fm = &full["metrics"];
    let per_row: Vec<serde_json::Value> = rows
        .iter()
        .filter(|r| r["row"] != "full")
        .map(|r| {
            let m = &r["metrics"];
            let c = json!({
                "psnr_crop": compare(fm, m, "psnr_crop", true),
                "ssim_crop": compare(fm, m, "ssim_crop", true),
                "lpips_crop": compare(fm, m, "lpips_crop", false),
                "cloth_chamfer_m": compare(fm, m, "cloth_chamfer_m", false),
            });
            let measured: Vec<bool> = ["psnr_crop", "ssim_crop", "lpips_crop", "cloth_chamfer_m"].iter().filter_map(|k| c[*k]["full_better"].as_bool()).collect();
            json!({ "row": r["row"], "holds": !measured.is_empty() && measured.iter().all(|&b| b), "comparisons": c })
        })
        .collect();
    let holds = if per_row.is_empty() {
        serde_json::Value::Null
    } else {
        per_row.iter().all(|r| r["holds"] == true).into()
    };
    json!({ "sequence": seq["sequence"], "holds": holds, "rows": per_row })
}

fn fmt(v: &serde_json::Value, digits: usize, scale: f64) -> String {
    v.as_f64()
        .map_or("n/a".into(), |x| format!("{:.*}", digits, x * scale))
}

pub fn markdown(r: &serde_json::Value) -> String {
    let mut s = String::new();
    s.push_str("# Synthetic cloth benchmark (`drape bench-cloth`)\n\n");
    s.push_str(&format!(
        "Command: `{}`\n\n",
        r["command"].as_str().unwrap_or("")
    ));
    s.push_str(&format!(
        "Preset {}, {} training steps ({} skinning-weight fit steps), {}x{} px, {} frames per sequence (every fifth from the second held out), seed {}, on {}; {:.0} s in all. LPIPS: {}.\n\n",
        r["preset"].as_str().unwrap_or(""), r["steps"], r["fit_steps"], r["size"], r["size"], r["frames"], r["seed"], r["device"].as_str().unwrap_or(""), r["seconds"].as_f64().unwrap_or(0.0),
        if r["lpips"] == true { "AlexNet weights given" } else { "n/a (no --lpips-weights)" }
    ));
    s.push_str("Metrics on the held-out frames: PSNR (dB) and SSIM on the whole frame and on the human crop (the person mask's bounding box); cloth Chamfer (mm) between the cloth Gaussians and the ground-truth garments; wall time of the whole run (fit, simulation, training, evaluation) and training iterations per second.\n\n");
    for (seq, claim) in r["sequences"]
        .as_array()
        .into_iter()
        .flatten()
        .zip(r["claim"].as_array().into_iter().flatten())
    {
        s.push_str(&format!(
            "## {}\n\n",
            seq["sequence"].as_str().unwrap_or("")
        ));
        s.push_str("| row | paper | PSNR full | SSIM full | LPIPS full | PSNR crop | SSIM crop | LPIPS crop | cloth Chamfer (mm) | wall (s) | it/s |\n");
        s.push_str("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n");
        for row in seq["rows"].as_array().into_iter().flatten() {
            let m = &row["metrics"];
            s.push_str(&format!(
                "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
                row["row"].as_str().unwrap_or(""),
                row["paper"].as_str().unwrap_or(""),
                fmt(&m["psnr_full"], 2, 1.0),
                fmt(&m["ssim_full"], 4, 1.0),
                fmt(&m["lpips_full"], 4, 1.0),
                fmt(&m["psnr_crop"], 2, 1.0),
                fmt(&m["ssim_crop"], 4, 1.0),
                fmt(&m["lpips_crop"], 4, 1.0),
                fmt(&m["cloth_chamfer_m"], 2, 1e3),
                fmt(&row["wall_s"], 1, 1.0),
                fmt(&row["it_per_s"], 2, 1.0)
            ));
        }
        s.push_str("\nThe paper's claim (the full model beats the single layer and every ablation on the human crop and on cloth geometry), as measured here (one digit more than the table, so that a tie shows; a row holds when the full model is strictly better on every metric measured for both):\n\n");
        let rows = claim["rows"].as_array().cloned().unwrap_or_default();
        if rows.is_empty() {
            s.push_str(
                "- not testable: the benchmark needs the full row and at least one other.\n",
            );
        }
        for c in &rows {
            let part = |key: &str, label: &str, digits: usize, scale: f64| {
                let x = &c["comparisons"][key];
                match x["full_better"].as_bool() {
                    Some(b) => format!(
                        "{label} {} ({} vs {})",
                        if b { "better" } else { "not better" },
                        fmt(&x["full"], digits, scale),
                        fmt(&x["row"], digits, scale)
                    ),
                    None => format!("{label} n/a"),
                }
            };
            s.push_str(&format!(
                "- full vs {}: {}; {}; {}; {} → claim {}\n",
                c["row"].as_str().unwrap_or(""),
                part("psnr_crop", "crop PSNR", 3, 1.0),
                part("ssim_crop", "crop SSIM", 5, 1.0),
                part("lpips_crop", "crop LPIPS", 5, 1.0),
                part("cloth_chamfer_m", "cloth Chamfer (mm)", 3, 1e3),
                if c["holds"] == true {
                    "holds"
                } else {
                    "does not hold"
                }
            ));
        }
        match claim["holds"].as_bool() {
            Some(true) => s.push_str("\nOn this sequence the claim holds against every row trained.\n\n"),
            Some(false) => s.push_str("\nOn this sequence the claim does not hold against every row trained (see the rows marked \"does not hold\").\n\n"),
            None => s.push('\n'),
        }
    }
    s.push_str("bench.png: human-crop PSNR, one group of bars per sequence in the order above, one bar per row in the order of the tables; colours: full blue, no-physics orange, no-lbs green, arap-only red, sim-only purple, mask-only brown, single-layer grey (the swatches on the right); grey lines every dB.\n\n");
    s.push_str("Rows: full = every loss; no-physics = simulation, ARAP and mask losses 0; no-lbs = cloth-LBS 0; arap-only / sim-only / mask-only = that cloth loss alone of the three (cloth-LBS on); single-layer = `--layers body+scene` (HUGS), no cloth layer, so no cloth Chamfer. The trainer's cloth layer and its simulation target use the tight T-shirt template on every sequence.\n");
    s
}

/// Grouped bars: human-crop PSNR per row (colour) per sequence (group), on an axis from
/// just below the lowest value, with a tick every dB; drawn with `image` alone.
fn plot(r: &serde_json::Value) -> image::RgbImage {
    const PALETTE: [[u8; 3]; 7] = [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [127, 127, 127],
    ];
    let seqs: Vec<&serde_json::Value> = r["sequences"]
        .as_array()
        .map(|v| v.iter().collect())
        .unwrap_or_default();
    let keys: Vec<&str> = ROWS
        .iter()
        .map(|r| r.key)
        .filter(|k| {
            seqs.iter().any(|s| {
                s["rows"]
                    .as_array()
                    .is_some_and(|rows| rows.iter().any(|x| x["row"] == *k))
            })
        })
        .collect();
    let value = |s: &serde_json::Value, k: &str| {
        s["rows"]
            .as_array()
            .and_then(|rows| rows.iter().find(|x| x["row"] == k))
            .and_then(|x| x["metrics"]["psnr_crop"].as_f64())
    };
    let values: Vec<f64> = seqs
        .iter()
        .flat_map(|s| keys.iter().filter_map(|k| value(s, k)))
        .collect();
    let lo = values.iter().cloned().fold(f64::INFINITY, f64::min).floor() - 1.0;
    let hi = values
        .iter()
        .cloned()
        .fold(f64::NEG_INFINITY, f64::max)
        .ceil()
        + 0.5;
    let (lo, hi) = if lo.is_finite() && hi > lo {
        (lo, hi)
    } else {
        (0.0, 1.0)
    };
    let (bar, gap, margin, height) = (14u32, 20u32, 40u32, 300u32);
    let group = bar * keys.len().max(1) as u32 + gap;
    let width = 2 * margin + group * seqs.len().max(1) as u32 + 20 + 16 * 2;
    let mut img =
        image::RgbImage::from_pixel(width, height + 2 * margin, image::Rgb([255, 255, 255]));
    let y_of = |v: f64| {
        margin + height
            - ((v - lo) / (hi - lo) * f64::from(height)).clamp(0.0, f64::from(height)) as u32
    };
    // Axis and a grey tick line every dB.
    let mut t = lo.ceil();
    while t <= hi {
        let y = y_of(t);
        for x in margin - 6..width - margin {
            let c = if x < margin {
                [0, 0, 0]
            } else {
                [225, 225, 225]
            };
            img.put_pixel(x, y, image::Rgb(c));
        }
        t += 1.0;
    }
    for y in margin..=margin + height {
        img.put_pixel(margin, y, image::Rgb([0, 0, 0]));
    }
    for (g, s) in seqs.iter().enumerate() {
        let x0 = margin + 10 + g as u32 * group;
        for (k, key) in keys.iter().enumerate() {
            let Some(v) = value(s, key) else { continue };
            let top = y_of(v);
            let c = PALETTE[ROWS.iter().position(|r| r.key == *key).unwrap_or(0) % PALETTE.len()];
            for x in x0 + k as u32 * bar..x0 + (k as u32 + 1) * bar - 2 {
                for y in top..=margin + height {
                    img.put_pixel(x, y, image::Rgb(c));
                }
            }
        }
    }
    // A legend: one swatch per row, in the order of the bars.
    for (k, key) in keys.iter().enumerate() {
        let c = PALETTE[ROWS.iter().position(|r| r.key == *key).unwrap_or(0) % PALETTE.len()];
        let x = width - 30;
        let y = margin + 4 + 16 * k as u32;
        for dx in 0..12 {
            for dy in 0..12 {
                img.put_pixel(x + dx, y + dy, image::Rgb(c));
            }
        }
    }
    img
}
