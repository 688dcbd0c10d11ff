//! `drape body`, `drape simulate` and `drape synth`: the default body, garments on a
//! motion, and the synthetic data.

use std::path::PathBuf;

use anyhow::Context as _;
use drape_trainer::body::procedural::{default_body, BodyOptions};
use drape_trainer::body::SmplModel;
use drape_trainer::cloth::{simulate_with_progress, ClothParams};
use drape_trainer::garment::{load_obj, pants, tshirt, write_obj, GarmentFit};
use drape_trainer::motion::{procedural, Motion, MotionKind};

/// Options of `drape body`.
#[derive(Clone, Debug, clap::Args)]
pub struct BodyArgs {
    /// Output .npz (v_template, shapedirs, posedirs, J_regressor, weights, kintree_table, f).
    #[arg(long)]
    pub out: PathBuf,
    /// Surface extraction cell size in metres (smaller: more vertices).
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.028, value_parser = drape_cli_support::number_in::<f64>(0.01, 0.1))]
    pub cell: f64,
}

pub fn run_body(args: &BodyArgs) -> anyhow::Result<()> {
    let body = default_body(&BodyOptions {
        cell: args.cell,
        ..BodyOptions::default()
    });
    let out = drape_cli_support::output::StagedFile::new(&args.out, "--out")?;
    body.write_npz(out.path())?;
    out.commit()?;
    // Read back through the loader, as a user's SMPL file would be.
    let back = SmplModel::load_npz(&args.out)?;
    println!(
        "wrote {}: {} vertices, {} faces, 24 joints, {} shape coefficients",
        args.out.display(),
        back.num_vertices(),
        back.faces.len(),
        back.num_betas
    );
    Ok(())
}

/// Options of `drape simulate`.
#[derive(Clone, Debug, clap::Args)]
pub struct SimulateArgs {
    /// Motion: walk, jog, raise-arms, turn; or an .npz: drape's (poses F x 72 or F x 66,
    /// trans F x 3, fps as a scalar) or an AMASS file (SMPL-H or SMPL-X poses, trans,
    /// mocap_framerate; z-up turned to y-up, started at the origin, hands at rest).
    #[arg(long, default_value = "walk")]
    pub motion: String,
    /// Frames of a procedural motion.
    #[arg(long, allow_negative_numbers = true, default_value_t = 90, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    pub frames: u32,
    /// Playback speed of a procedural motion (2 = twice as fast).
    #[arg(long, allow_negative_numbers = true, default_value_t = 1.0, value_parser = drape_cli_support::number_in::<f64>(0.01, 100.0))]
    pub speed: f64,
    /// Substeps per frame (below 8, the iterations per substep grow so that a frame
    /// still gets about 16 rounds of collisions and strain limiting).
    #[arg(long, allow_negative_numbers = true, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub substeps: u32,
    /// Body model .npz (default: the project's body).
    #[arg(long)]
    pub body: Option<PathBuf>,
    /// Extra OBJ garments to simulate besides the T-shirt and pants, made on the body
    /// in its rest pose (the T-pose, arms out).
    #[arg(long)]
    pub garment: Vec<PathBuf>,
    /// Frames simulated before the motion starts (not written), blending from the pose
    /// the garments were made in into the motion's first pose, so that the cloth has
    /// settled under gravity by frame 0. Fewer is faster; 0 starts the motion at once.
    #[arg(long, allow_negative_numbers = true, default_value_t = 20, value_parser = clap::value_parser!(u32).range(0..=1000))]
    pub settle: u32,
    /// Output directory for <garment>_<frame>.obj.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run_simulate(args: &SimulateArgs) -> anyhow::Result<()> {
    let body = match &args.body {
        Some(path) => SmplModel::load_npz(path)?,
        None => default_body(&BodyOptions::default()),
    };
    let motion = match MotionKind::parse(&args.motion) {
        Some(kind) => {
            anyhow::ensure!(args.frames > 0, "--frames must be positive");
            anyhow::ensure!(
                args.speed > 0.0 && args.speed.is_finite(),
                "--speed must be a positive number"
            );
            procedural(kind, args.frames as usize, 30.0, args.speed)
        }
        None => Motion::load_npz(std::path::Path::new(&args.motion)).with_context(|| {
            format!(
                "--motion '{}' is neither walk, jog, raise-arms, turn nor a readable motion .npz",
                args.motion
            )
        })?,
    };
    let mut garments = vec![tshirt(&body), pants(&body)];
    for path in &args.garment {
        let mut g = load_obj(path, &body)?;
        // A user's garment named like a built-in (or like another) keeps its own files.
        if garments.iter().any(|o| o.name == g.name) {
            let base = g.name.clone();
            g.name = (2..)
                .map(|k| format!("{base}-{k}"))
                .find(|n| garments.iter().all(|o| &o.name != n))
                .expect("a free name");
            eprintln!(
                "{}: written as {}_NNNN.obj ('{base}' is taken)",
                path.display(),
                g.name
            );
        }
        garments.push(g);
    }
    let out = drape_cli_support::output::StagedDir::new(&args.out, "--out", false)?;
    let params = ClothParams::with_substeps(args.substeps);
    eprintln!(
        "simulating {} garments ({} vertices) over {} frames...",
        garments.len(),
        garments.iter().map(|g| g.vertices.len()).sum::<usize>(),
        motion.len()
    );
    let t0 = std::time::Instant::now();
    let settle = args.settle as usize;
    let result = simulate_with_progress(
        &body,
        &garments,
        &motion,
        params,
        settle,
        &mut |done, total| eprint!("\rframe {done:>5}/{total} ({settle} settling)   "),
    );
    eprintln!();
    let seconds = t0.elapsed().as_secs_f64();
    anyhow::ensure!(
        !result.any_nan,
        "the simulation produced non-finite positions"
    );
    for (f, frame) in result.frames.iter().enumerate() {
        for (g, positions) in garments.iter().zip(frame) {
            let path = out.path().join(format!("{}_{f:04}.obj", g.name));
            write_obj(&path, positions, &g.faces, Some(&g.uvs))
                .with_context(|| format!("{}: cannot write", path.display()))?;
        }
    }
    out.commit()?;
    println!(
        "simulated {} frames in {seconds:.1} s ({:.2} frames/s, {settle} settling frames included): deepest cloth vertex {:.1} mm {} the body (margin {:.1} mm), largest edge stretch {:.1}%; wrote {}",
        result.frames.len(),
        (result.frames.len() + settle) as f64 / seconds,
        result.max_penetration.abs() * 1e3,
        if result.max_penetration > 0.0 { "inside" } else { "outside" },
        params.margin * 1e3,
        (result.max_strain - 1.0) * 100.0,
        args.out.display()
    );
    Ok(())
}

/// Options of `drape synth`.
#[derive(Clone, Debug, clap::Args)]
pub struct SynthArgs {
    /// Output directory (gets neuman/, zju/ and gt/).
    #[arg(long)]
    pub out: PathBuf,
    /// Image width and height in pixels (the full size is 512).
    #[arg(long, allow_negative_numbers = true, default_value_t = 128, value_parser = clap::value_parser!(u32).range(16..=2048))]
    pub size: u32,
    /// Frames at 30 fps.
    #[arg(long, allow_negative_numbers = true, default_value_t = 30, value_parser = clap::value_parser!(u32).range(1..=3000))]
    pub frames: u32,
    /// Static cameras of the ring (ZJU-MoCap layout).
    #[arg(long, allow_negative_numbers = true, default_value_t = 4, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub cameras: u32,
    /// Motion: walk, jog, raise-arms, turn.
    #[arg(long, default_value = "walk")]
    pub motion: String,
    /// Seed of the handheld camera's path.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Supersampling per axis (antialiasing).
    #[arg(long, allow_negative_numbers = true, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=8))]
    pub samples: u32,
    /// The T-shirt's fit: tight (1.5 cm off the skin, hem at the hips) or loose (4.5 cm
    /// of ease around the torso, hem 10 cm lower); the pants are the same for both.
    #[arg(long, default_value = "tight")]
    pub fit: String,
}

pub fn run_synth(args: &SynthArgs) -> anyhow::Result<()> {
    use drape_trainer::dataset::synth::{generate, SynthOptions};
    let motion = MotionKind::parse(&args.motion).ok_or_else(|| {
        anyhow::anyhow!(
            "--motion '{}' is not one of walk, jog, raise-arms, turn",
            args.motion
        )
    })?;
    let garment = GarmentFit::parse(&args.fit)
        .ok_or_else(|| anyhow::anyhow!("--fit '{}' is not one of tight, loose", args.fit))?;
    let options = SynthOptions {
        width: args.size,
        height: args.size,
        frames: args.frames as usize,
        cameras: args.cameras as usize,
        motion,
        seed: args.seed,
        samples: args.samples,
        garment,
    };
    let out = drape_cli_support::output::StagedDir::new(&args.out, "--out", false)?;
    let summary = generate(out.path(), &options, &mut |stage, done, total| {
        eprint!("\r{stage:<18} {done:>5}/{total}   ");
    })
    .map_err(|e| anyhow::anyhow!(e))?;
    out.commit()?;
    eprintln!();
    println!(
        "wrote {} frames ({}x{}): neuman/ (1 moving camera), zju/ ({} static cameras), gt/ in {:.1} s to {}",
        summary.frames, args.size, args.size, summary.ring_cameras, summary.seconds, args.out.display()
    );
    Ok(())
}
