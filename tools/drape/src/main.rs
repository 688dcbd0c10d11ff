//! `drape`: the product's command line: `demo` (GPU sort checked against the CPU),
//! `render` (a 3DGS PLY to PNG, .npy or OpenEXR), `fit` (Gaussians fitted to an image),
//! `body` (the default body as SMPL .npz), `simulate` (garments on a motion), `synth`
//! (the synthetic data), `inspect` (a sequence's layout and problems), `prepare` (a
//! person's videos towards a sequence: frames, cameras, landmarks), `train` (the
//! avatar), `eval`, `animate` and `edit` (a trained run), `export` (a trained run as one
//! `.avatar` file), `bench-cloth` (the synthetic
//! cloth benchmark), `view` (a real-time viewer of a trained run or an avatar file).
// `deny`, not `forbid`: `view`'s Vulkan host code (its `device`, `swapchain` and `frame`
// files) allows it for itself (with a SAFETY comment on every block); every other module
// stays free of unsafe.
#![deny(unsafe_code)]

use std::process::ExitCode;
use std::time::Instant;

use clap::{Parser, Subcommand};
use drape_cli_support::{parse_len, DeviceArgs};
use drape_engine::ops::radix_sort::sort_pairs_host;
use rand::{Rng, SeedableRng};

mod animate;
mod bench_cloth;
mod body;
mod edit;
mod eval;
mod export;
mod fit;
mod fitting;
mod image_io;
mod inspect;
mod prepare;
mod render;
mod train;
mod view;

/// Cloth-aware human Gaussian-splat avatars on Vulkan.
#[derive(Parser, Debug)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(flatten)]
    device: DeviceArgs,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug, Clone)]
enum Command {
    /// Sort random (key, value) pairs with the GPU radix sort, check the result
    /// against the CPU's stable sort, and print a summary.
    Demo {
        /// Number of pairs.
        #[arg(long, value_parser = parse_len, allow_negative_numbers = true, default_value = "1000000")]
        n: u32,
        /// Seed of the random keys.
        #[arg(long, default_value_t = 7)]
        seed: u64,
    },
    /// Render a 3D Gaussian Splatting PLY file to a PNG, a NumPy .npy (colour, alpha,
    /// depth) or an OpenEXR, from a look-at camera or a JSON camera file.
    Render(render::RenderArgs),
    /// Fit random Gaussians to an image with the GPU optimizer and save them as PLY.
    Fit(fit::FitArgs),
    /// Write the project's default body (SMPL format, smplx .npz layout).
    Body(body::BodyArgs),
    /// Simulate the T-shirt and pants (and any OBJ garments) on the default body
    /// through a motion; writes one OBJ per frame per garment.
    Simulate(body::SimulateArgs),
    /// Generate the synthetic dataset: a clothed person walking in a room, rendered
    /// for a moving camera (NeuMan layout) and a ring of cameras (ZJU-MoCap layout),
    /// with masks, depth and ground-truth body and cloth.
    Synth(body::SynthArgs),
    /// Say which layout and variant a sequence directory is in, its frames, cameras,
    /// image size, masks, parameters and split, and the first problem found.
    Inspect(inspect::InspectArgs),
    /// From a person's videos (a calibrated rig of two views or more) to a sequence to
    /// train on: frames (ffmpeg), cameras from the calibration, mediapipe's person masks
    /// and landmarks, the body fitted to them, all written as a ZJU-MoCap sequence (one
    /// video stops before the body fit: not built yet).
    Prepare(prepare::PrepareArgs),
    /// Train the avatar on a sequence (NeuMan or ZJU-MoCap layout, or `drape synth`
    /// output) and evaluate it on the held-out frames.
    Train(train::TrainArgs),
    /// Measure a trained run on its held-out frames: PSNR, SSIM, LPIPS (full image and
    /// human crop), cloth Chamfer; a table, JSON, Markdown and a sheet per frame.
    Eval(eval::EvalArgs),
    /// Render a trained run in a new motion from an orbiting camera: PNG frames and a GIF.
    Animate(animate::AnimateArgs),
    Export(export::ExportArgs),
    /// Change a trained run's clothes (remove, recolour, swap) into a new run.
    Edit(edit::EditArgs),
    /// The synthetic cloth benchmark: synthesise loose / tight garment sequences, train
    /// the full model, the paper's ablation rows and the single-layer baseline on each,
    /// and write bench.json, bench.md (with the paper's claim checked) and bench.png.
    BenchCloth(bench_cloth::BenchClothArgs),
    /// Show a trained run in a window in real time (winit + a Vulkan swapchain, the
    /// engine on the viewer's own device): space plays/pauses, arrows step, drag orbits.
    View(view::ViewArgs),
}

fn demo(device: &DeviceArgs, n: u32, seed: u64) -> anyhow::Result<()> {
    // Keys and values, their sorted copies and the CPU's pairs: about 24 bytes a pair.
    drape_cli_support::ensure_memory(24 * u64::from(n), &format!("sorting {n} pairs"), "--n")?;
    let ctx = device.open()?;
    let limit = ctx.info().max_storage_buffer_range / 8;
    anyhow::ensure!(u64::from(n) <= limit, "--n: {n} pairs do not fit one storage buffer of this device (at most {limit}: maxStorageBufferRange / 8 bytes a pair)");
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let keys: Vec<u32> = (0..n).map(|_| rng.random()).collect();
    let values: Vec<u32> = (0..n).collect();
    let t0 = Instant::now();
    let (gpu_keys, gpu_values) = sort_pairs_host(&ctx, &keys, &values, 32)?;
    let gpu_ms = t0.elapsed().as_secs_f64() * 1e3;
    let mut expected: Vec<(u32, u32)> = keys.iter().copied().zip(values.iter().copied()).collect();
    let t0 = Instant::now();
    expected.sort_by_key(|&(k, _)| k);
    let cpu_ms = t0.elapsed().as_secs_f64() * 1e3;
    let matches = expected
        .iter()
        .zip(gpu_keys.iter().zip(&gpu_values))
        .all(|(&(k, v), (&gk, &gv))| k == gk && v == gv);
    anyhow::ensure!(matches, "the GPU sort differs from the CPU's stable sort");
    device.check_validation(&ctx)?;
    println!(
        "sorted {n} random u32 keys with their indices on {}",
        ctx.info().name
    );
    println!("  GPU (upload + sort + readback): {gpu_ms:.1} ms; CPU stable sort: {cpu_ms:.1} ms");
    println!("  identical to the CPU's stable sort: yes");
    let show = gpu_keys.len().min(5);
    println!(
        "  first {show} (key, original index): {:?}",
        gpu_keys
            .iter()
            .zip(&gpu_values)
            .take(show)
            .collect::<Vec<_>>()
    );
    Ok(())
}

fn main() -> ExitCode {
    let cli: Cli = match drape_cli_support::parse_args() {
        Ok(c) => c,
        Err(code) => return code,
    };
    drape_cli_support::run(|| match cli.command.clone() {
        Command::Demo { n, seed } => demo(&cli.device, n, seed),
        Command::Render(args) => render::run(&cli.device, &args),
        Command::Fit(args) => fit::run(&cli.device, &args),
        Command::Body(args) => body::run_body(&args),
        Command::Simulate(args) => body::run_simulate(&args),
        Command::Synth(args) => body::run_synth(&args),
        Command::Inspect(args) => inspect::run(&args),
        Command::Prepare(args) => prepare::run(&args),
        Command::Train(args) => train::run(&cli.device, &args),
        Command::Eval(args) => eval::run(&cli.device, &args),
        Command::Animate(args) => animate::run(&cli.device, &args),
        Command::Export(args) => export::run(&cli.device, &args),
        Command::Edit(args) => edit::run(&cli.device, &args),
        Command::BenchCloth(args) => bench_cloth::run(&cli.device, &args),
        Command::View(args) => view::run(&cli.device, &args),
    })
}
