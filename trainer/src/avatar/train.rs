//! Training the avatar: load a sequence, build the layers the data requires, fit the
//! skinning weights, then step (sample a training frame → deform → render → L1 →
//! backward → Adam) and evaluate on the held-out frames.
//!
//! What is built so far (the rest of the issue is not): the body layer (the thin,
//! whole path: triplane + decoders + learned skinning + splatting + 0.8 L1 + 0.2
//! (1 - SSIM) + Adam), trained
//! against the person masked onto a random background colour each step (HUGS), which
//! folds the cloth into the body as HUGS does (the single-layer baseline). The cloth
//! and scene layers, compositing, LPIPS and the cloth losses, pose refinement and
//! densification come next.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use drape_engine::ops::splat::ply;
use drape_engine::ops::ssim::Ssim;
use drape_engine::ops::splat::render::{Accumulation, SplatRenderer};
use drape_engine::ops::splat::scene::{Layer, PinholeCamera, RenderSettings};
use drape_engine::{BufferDesc, Context, Kernel};
use drape_shared::adam::LossParams;
use rand::{Rng, SeedableRng};

use crate::avatar::checkpoint::{self, ModelState};
use crate::avatar::layer::{HumanLayer, LayerConfig};
use crate::avatar::rig::Rig;
use crate::body::gaussians::{gaussians_from_mesh, SkinnedMesh};
use crate::body::procedural::{default_body, BodyOptions};
use crate::body::SmplModel;
use crate::dataset::loader::{load_neuman, load_zju, BodyParams, DatasetFrame, NeumanSplit};
use crate::dataset::raster::RasterCamera;
use crate::dataset::split::Split;

/// Everything a run is configured by (written to the run directory as `config.json`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    pub preset: String,
    /// Optimisation steps after the skinning-weight fit.
    pub steps: u32,
    pub seed: u64,
    /// Midpoint subdivisions of the body mesh for the body layer's Gaussians (0-2).
    pub subdivision: u32,
    /// Keep every n-th of the body's Gaussians (1: all), each widened by √n in the
    /// surface plane so the body stays covered: for tests and quick looks.
    pub decimate: u32,
    pub body: LayerConfig,
    /// Adam steps fitting the deformation decoder to the body's skinning weights.
    pub fit_steps: u32,
    pub fit_lr: f32,
    /// Steps between log lines (loss and training PSNR).
    pub log_every: u32,
    /// Steps between checkpoints (`checkpoint.npz`, replaced atomically); one is also
    /// written at the end.
    pub checkpoint_every: u32,
    /// A step with any non-finite gradient is skipped (counted and logged); this many
    /// in a row stop the run.
    pub max_skipped_steps: u32,
    /// Image loss `λ_l1 L1 + λ_ssim (1 - SSIM)` (paper: 0.8, 0.2).
    pub lambda_l1: f32,
    pub lambda_ssim: f32,
    /// ZJU-MoCap: the training camera's index.
    pub zju_train_camera: usize,
}

impl TrainConfig {
    /// What finishes in about ten minutes on lavapipe on a 2-core machine at the
    /// synthetic data's 128 × 128: every second vertex of the body mesh without
    /// subdivision (4,700 Gaussians), 64 × 64 × 16 triplanes, the full HUGS decoders,
    /// 150 fitting and 600 training steps. The decoders dominate a step there (the
    /// GEMM runs at ~7 GFLOP/s on lavapipe), so the Gaussian count sets the pace.
    pub fn quick() -> Self {
        Self {
            preset: "quick".into(),
            steps: 600,
            seed: 1,
            subdivision: 0,
            decimate: 2,
            body: LayerConfig { triplane_resolution: 64, triplane_channels: 16, ..LayerConfig::default() },
            fit_steps: 150,
            fit_lr: 3e-3,
            log_every: 25,
            checkpoint_every: 200,
            max_skipped_steps: 10,
            lambda_l1: 0.8,
            lambda_ssim: 0.2,
            zju_train_camera: 0,
        }
    }

    /// The paper's setting (for a GPU): two subdivisions, 256 × 256 × 32 triplanes,
    /// 20k steps.
    pub fn paper() -> Self {
        Self { preset: "paper".into(), steps: 20_000, subdivision: 2, decimate: 1, body: LayerConfig::default(), fit_steps: 3000, fit_lr: 1e-3, log_every: 100, checkpoint_every: 1000, ..Self::quick() }
    }

    pub fn preset(name: &str) -> Result<Self, String> {
        match name {
            "quick" => Ok(Self::quick()),
            "paper" => Ok(Self::paper()),
            other => Err(format!("unknown preset '{other}' (quick, paper)")),
        }
    }

    /// Checks values a config file could get wrong, naming the field.
    pub fn validate(&self) -> Result<(), String> {
        let rates = [
            ("body.lr_position", self.body.lr_position),
            ("body.lr_triplane", self.body.lr_triplane),
            ("body.lr_decoders", self.body.lr_decoders),
            ("body.lr_deformation", self.body.lr_deformation),
            ("fit_lr", self.fit_lr),
            ("lambda_l1", self.lambda_l1),
            ("lambda_ssim", self.lambda_ssim),
        ];
        for (name, v) in rates {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{name} must be a finite rate >= 0, got {v}"));
            }
        }
        if self.decimate == 0 {
            return Err("decimate must be >= 1".into());
        }
        if self.subdivision > 2 {
            return Err(format!("subdivision must be 0, 1 or 2, got {}", self.subdivision));
        }
        if self.body.sh_degree > 3 {
            return Err(format!("body.sh_degree must be 0-3, got {}", self.body.sh_degree));
        }
        if self.body.triplane_resolution < 2 || self.body.triplane_channels == 0 {
            return Err("body.triplane_resolution must be >= 2 and body.triplane_channels >= 1".into());
        }
        Ok(())
    }
}

/// The on-disk layout a sequence came in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum Layout {
    NeuMan,
    ZjuMocap,
}

/// A loaded sequence.
pub struct Sequence {
    pub dir: PathBuf,
    pub layout: Layout,
    pub frames: Vec<DatasetFrame>,
}

/// Loads `dir` in whichever layout it is: NeuMan (`sparse/`), ZJU-MoCap
/// (`annots.npy`), or the root `drape synth` writes (its `neuman/`).
pub fn load_sequence(dir: &Path, zju_train_camera: usize) -> Result<Sequence, String> {
    if dir.join("sparse").is_dir() {
        return Ok(Sequence { dir: dir.into(), layout: Layout::NeuMan, frames: load_neuman(dir, NeumanSplit::EveryFifth)? });
    }
    if dir.join("annots.npy").is_file() {
        return Ok(Sequence { dir: dir.into(), layout: Layout::ZjuMocap, frames: load_zju(dir, zju_train_camera)? });
    }
    if dir.join("neuman").join("sparse").is_dir() {
        return load_sequence(&dir.join("neuman"), zju_train_camera);
    }
    if !dir.exists() {
        return Err(format!("{}: no such directory", dir.display()));
    }
    Err(format!("{}: neither a NeuMan sequence (sparse/) nor a ZJU-MoCap one (annots.npy), nor a `drape synth` output (neuman/)", dir.display()))
}

fn camera(c: &RasterCamera, background: [f32; 3]) -> PinholeCamera {
    PinholeCamera {
        fx: c.fx as f32,
        fy: c.fy as f32,
        cx: c.cx as f32,
        cy: c.cy as f32,
        width: c.width,
        height: c.height,
        rotation: c.rotation.map(|r| r.map(|v| v as f32)),
        translation: c.translation.map(|v| v as f32),
        near: c.near as f32,
        far: 1e4,
        background,
    }
}

/// The frame's person on a constant background.
fn masked_target(f: &DatasetFrame, background: [f32; 3]) -> Vec<f32> {
    f.mask.iter().enumerate().flat_map(|(i, &m)| if m { [f.rgb[3 * i], f.rgb[3 * i + 1], f.rgb[3 * i + 2]] } else { background }).collect()
}

/// Peak signal-to-noise ratio (dB) of images in [0, 1].
pub fn psnr(a: &[f32], b: &[f32]) -> f64 {
    let mse = a.iter().zip(b).map(|(x, y)| f64::from(x - y).powi(2)).sum::<f64>() / a.len().max(1) as f64;
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

fn crop(rgb: &[f32], width: u32, (x0, y0, x1, y1): (u32, u32, u32, u32)) -> Vec<f32> {
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
    /// Whole image, the person on black (the body layer alone is evaluated).
    pub psnr_full: f64,
    /// The person mask's bounding box (HUGS's human crop).
    pub psnr_crop: f64,
}

impl TrainConfig {
    /// Reads a run's `config.json` (for `--resume`), naming the file on any problem.
    pub fn read_run(dir: &Path) -> Result<Self, String> {
        let path = dir.join("config.json");
        let text = std::fs::read_to_string(&path).map_err(|e| format!("{}: {e}", path.display()))?;
        let c: Self = serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
        c.validate().map_err(|e| format!("{}: {e}", path.display()))?;
        Ok(c)
    }
}

/// What a run did.
#[derive(Clone, Debug, serde::Serialize)]
pub struct TrainReport {
    pub layout: Layout,
    pub gaussians: Vec<(String, u32)>,
    pub fit_steps: u32,
    pub fit_mse: f64,
    pub fit_seconds: f64,
    /// The step training started from (0, or the checkpoint's when resumed).
    pub start_step: u32,
    pub steps: u32,
    pub train_seconds: f64,
    pub iterations_per_second: f64,
    pub skipped_steps: u32,
    pub initial: EvalMetrics,
    pub fin: EvalMetrics,
}

/// Progress of a run, for a progress line.
#[derive(Clone, Debug)]
pub enum Progress {
    Fit { step: u32, total: u32, mse: f64 },
    Step { step: u32, total: u32, l1: f64, psnr: f64, it_per_s: f64 },
    Eval { done: usize, total: usize },
}

/// The default body (the project's procedural one) or an SMPL file.
pub fn body_model(path: Option<&Path>) -> Result<SmplModel, String> {
    match path {
        Some(p) => SmplModel::load_npz(p).map_err(|e| e.to_string()),
        None => Ok(default_body(&BodyOptions::default())),
    }
}

fn betas_of(f: &DatasetFrame) -> Vec<f64> {
    match &f.body {
        BodyParams::Smpl { betas, .. } => betas.clone(),
        BodyParams::Zju(p) => p.shapes.to_vec(),
    }
}

fn gpu<T>(r: drape_engine::Result<T>) -> Result<T, String> {
    r.map_err(|e| e.to_string())
}

/// The body layer's canonical Gaussians and their skinning targets.
fn body_layer(ctx: &Context, rig: &Rig, config: &TrainConfig) -> Result<HumanLayer, String> {
    let mesh = SkinnedMesh {
        vertices: rig.canonical_vertices(),
        faces: rig.model.faces.clone(),
        weights: rig.model.weights.clone(),
        shapedirs: vec![[Vec::new(), Vec::new(), Vec::new()]; rig.model.num_vertices()],
    };
    let (full, sub) = gaussians_from_mesh(&mesh, config.subdivision, config.body.sh_degree, Layer::Body);
    let keep = config.decimate.max(1) as usize;
    let widen = 0.5 * (keep as f32).ln();
    let mut cloud = drape_engine::ops::splat::scene::GaussianCloud::new(full.sh_degree);
    let mut weights = Vec::new();
    for i in (0..full.len()).step_by(keep) {
        let mut g = full.gaussian::<f32>(i);
        // The two tangent axes (the third is the normal).
        g.log_scale[0] += widen;
        g.log_scale[1] += widen;
        cloud.push(&g, Layer::Body);
        weights.extend(sub.weights[i].iter().map(|&w| w as f32));
    }
    gpu(HumanLayer::new(ctx, "body", &cloud, &weights, &config.body, config.steps, config.seed))
}

/// Renders every held-out frame on black and compares with the masked ground truth.
fn evaluate(ctx: &Context, layer: &mut HumanLayer, rig: &Rig, frames: &[&DatasetFrame], renderer: &mut SplatRenderer, out_dir: Option<&Path>, progress: &mut dyn FnMut(Progress)) -> Result<EvalMetrics, String> {
    let settings = RenderSettings::default();
    let mut m = EvalMetrics::default();
    for (k, f) in frames.iter().enumerate() {
        progress(Progress::Eval { done: k, total: frames.len() });
        let ft = rig.frame(&f.body);
        gpu(ctx.write_buffer(&mut layer.transforms, &ft.transforms))?;
        {
            let mut rec = gpu(ctx.record("eval forward"))?;
            gpu(layer.record_forward(&mut rec, ft.log_scale))?;
            gpu(rec.submit_and_wait())?;
        }
        let cam = camera(&f.camera, [0.0; 3]);
        gpu(renderer.forward(&layer.posed, &cam, &settings))?;
        let image = gpu(renderer.read_image())?;
        let target = masked_target(f, [0.0; 3]);
        m.psnr_full += psnr(&image.rgb, &target);
        if let Some(b) = mask_bbox(&f.mask, f.width) {
            m.psnr_crop += psnr(&crop(&image.rgb, f.width, b), &crop(&target, f.width, b));
        }
        if let Some(dir) = out_dir {
            // Ground truth | render, side by side.
            let w = f.width as usize;
            let mut sheet = Vec::with_capacity(2 * target.len());
            for y in 0..f.height as usize {
                sheet.extend_from_slice(&target[3 * y * w..3 * (y + 1) * w]);
                sheet.extend_from_slice(&image.rgb[3 * y * w..3 * (y + 1) * w]);
            }
            crate::dataset::image::write_rgb(&dir.join(format!("frame{:04}_view{}.png", f.frame, f.view)), 2 * f.width, f.height, &sheet)?;
        }
    }
    m.frames = frames.len();
    let n = frames.len().max(1) as f64;
    m.psnr_full /= n;
    m.psnr_crop /= n;
    Ok(m)
}

fn write_json(path: &Path, value: &impl serde::Serialize) -> Result<(), String> {
    let text = serde_json::to_string_pretty(value).map_err(|e| e.to_string())?;
    // Written whole to a temporary file, then renamed: never half a file.
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, text + "\n").map_err(|e| format!("{}: {e}", tmp.display()))?;
    std::fs::rename(&tmp, path).map_err(|e| format!("{}: {e}", path.display()))
}

/// Trains on `seq` into the run directory `out`: a new one (it must not exist, or be
/// empty), or with `resume` the run's last checkpoint (`out/checkpoint.npz`), continued
/// to `config.steps`. The step's frame and background come from `(seed, step)`, so a
/// resumed run samples what the uninterrupted one would have.
pub fn train(ctx: &Context, seq: &Sequence, model: SmplModel, config: &TrainConfig, out: &Path, resume: bool, progress: &mut dyn FnMut(Progress)) -> Result<TrainReport, String> {
    config.validate()?;
    let train_frames: Vec<&DatasetFrame> = seq.frames.iter().filter(|f| f.split == Split::Train).collect();
    let test_frames: Vec<&DatasetFrame> = seq.frames.iter().filter(|f| f.split == Split::Test).collect();
    if train_frames.is_empty() {
        return Err(format!("{}: no training frames", seq.dir.display()));
    }
    let (width, height) = (train_frames[0].width, train_frames[0].height);
    if let Some(f) = seq.frames.iter().find(|f| (f.width, f.height) != (width, height)) {
        return Err(format!("{}: {}x{}, but the sequence's first training image is {width}x{height}", f.image_path.display(), f.width, f.height));
    }
    let checkpoint_path = out.join("checkpoint.npz");
    if resume {
        if !checkpoint_path.is_file() {
            return Err(format!("{}: no checkpoint to resume from", checkpoint_path.display()));
        }
    } else {
        if out.exists() && std::fs::read_dir(out).map_err(|e| format!("{}: {e}", out.display()))?.next().is_some() {
            return Err(format!("{}: the run directory exists and is not empty (use --resume to continue it)", out.display()));
        }
        std::fs::create_dir_all(out.join("eval")).map_err(|e| format!("{}: {e}", out.display()))?;
        write_json(&out.join("config.json"), config)?;
    }
    let log_path = out.join("log.jsonl");
    let mut log = std::fs::OpenOptions::new().create(true).append(true).open(&log_path).map_err(|e| format!("{}: {e}", log_path.display()))?;

    let rig = Rig::new(model, &betas_of(train_frames[0]));
    let mut layer = body_layer(ctx, &rig, config)?;
    let n = layer.count;
    let mut renderer = gpu(SplatRenderer::new(ctx, width, height, n as usize))?;

    // 1. The deformation decoder learns the body's skinning weights (or the run's
    //    checkpoint is loaded: its decoders have been fitted already).
    let t0 = Instant::now();
    let total_fit = config.fit_steps;
    let (start_step, fit_mse) = if resume {
        let state = checkpoint::read(&checkpoint_path, &[layer.shape()])?;
        gpu(layer.restore(ctx, &state.layers[0].1))?;
        (state.step, f64::NAN)
    } else {
        (0, gpu(layer.fit_skinning_weights(ctx, total_fit, config.fit_lr, 25, |step, mse| progress(Progress::Fit { step, total: total_fit, mse })))?)
    };
    let fit_seconds = t0.elapsed().as_secs_f64();
    let initial = evaluate(ctx, &mut layer, &rig, &test_frames, &mut renderer, None, progress)?;

    // 2. The main loop.
    let pixels = (width * height) as usize;
    let mut target = gpu(ctx.create_buffer("train target", BufferDesc::gpu_only(12 * pixels as u64)))?;
    let grad_rgb = gpu(ctx.create_buffer("train grad rgb", BufferDesc::gpu_only(12 * pixels as u64)))?;
    let mut abs_error = gpu(ctx.create_buffer("train abs error", BufferDesc::gpu_only(12 * pixels as u64)))?;
    let zeros = gpu(ctx.create_buffer("train zero grads", BufferDesc::gpu_only(4 * pixels as u64)))?;
    {
        let mut rec = gpu(ctx.record("train zero"))?;
        rec.fill(&zeros, 0);
        gpu(rec.submit_and_wait())?;
    }
    let loss = LossParams { len: 3 * pixels as u32, scale: config.lambda_l1 / (3 * pixels) as f32, _pad: [0; 2] };
    let mut ssim = gpu(Ssim::new(ctx, width, height))?;
    let settings = RenderSettings::default();
    let use_atomics = ctx.info().float_atomic_add;
    let t_train = Instant::now();
    let mut skipped = 0u32;
    let mut skipped_in_a_row = 0u32;
    let mut nonfinite = gpu(ctx.create_buffer("train non-finite count", BufferDesc::gpu_only(4)))?;
    let save = |layer: &mut HumanLayer, step: u32, path: &Path| -> Result<(), String> {
        let state = ModelState { step, layers: vec![("body".into(), gpu(layer.state(ctx))?)] };
        checkpoint::write(path, &state)
    };
    for step in start_step..config.steps {
        let mut rng = rand::rngs::StdRng::seed_from_u64(config.seed ^ u64::from(step).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let f = train_frames[rng.random_range(0..train_frames.len())];
        let background: [f32; 3] = [rng.random(), rng.random(), rng.random()];
        let ft = rig.frame(&f.body);
        gpu(ctx.write_buffer(&mut layer.transforms, &ft.transforms))?;
        gpu(ctx.write_buffer(&mut target, &masked_target(f, background)))?;
        {
            let mut rec = gpu(ctx.record("train forward"))?;
            gpu(layer.record_forward(&mut rec, ft.log_scale))?;
            gpu(rec.submit_and_wait())?;
        }
        let cam = camera(&f.camera, background);
        gpu(renderer.forward(&layer.posed, &cam, &settings))?;
        {
            let (rgb, _, _) = renderer.outputs();
            let mut rec = gpu(ctx.record("train loss"))?;
            gpu(rec.pass("loss.l1_grad", Kernel::TrainL1Grad).read(rgb).read(&target).write(&grad_rgb).write(&abs_error).push(&loss).dispatch([loss.len.div_ceil(256), 1, 1]))?;
            rec.barrier();
            // λ (1 - SSIM): adds -λ ∂SSIM/∂rgb to the L1 gradient.
            gpu(ssim.record(&mut rec, rgb, &target, Some((&grad_rgb, -config.lambda_ssim))))?;
            gpu(rec.submit_and_wait())?;
        }
        gpu(renderer.backward(&layer.posed, &grad_rgb, &zeros, &zeros, &layer.posed_grads, Accumulation::Auto))?;
        {
            let mut rec = gpu(ctx.record("train backward"))?;
            rec.fill(&nonfinite, 0);
            gpu(layer.record_backward(&mut rec, use_atomics))?;
            gpu(layer.record_count_nonfinite(&mut rec, &nonfinite))?;
            gpu(rec.submit_and_wait())?;
        }
        // The guard: a step with a non-finite gradient is never applied.
        let bad = gpu(ctx.read_buffer::<u32>(&mut nonfinite, 1))?[0];
        if bad > 0 {
            skipped += 1;
            skipped_in_a_row += 1;
            let line = serde_json::json!({ "step": step, "frame": f.frame, "skipped": true, "nonfinite_gradients": bad });
            writeln!(log, "{line}").map_err(|e| format!("{}: {e}", log_path.display()))?;
            if skipped_in_a_row >= config.max_skipped_steps.max(1) {
                return Err(format!(
                    "stopped at step {step}: {skipped_in_a_row} steps in a row had non-finite gradients ({bad} values in the last, frame {} of {}); the last checkpoint is {}",
                    f.frame,
                    seq.dir.display(),
                    checkpoint_path.display()
                ));
            }
            continue;
        }
        skipped_in_a_row = 0;
        {
            let mut rec = gpu(ctx.record("train adam"))?;
            gpu(layer.record_adam(&mut rec, true))?;
            gpu(rec.submit_and_wait())?;
        }
        if step % config.log_every.max(1) == 0 || step + 1 == config.steps {
            let e = gpu(ctx.read_buffer::<f32>(&mut abs_error, 3 * pixels))?;
            let l1 = e.iter().map(|&v| f64::from(v)).sum::<f64>() / e.len() as f64;
            let mse = e.iter().map(|&v| f64::from(v) * f64::from(v)).sum::<f64>() / e.len() as f64;
            let p = -10.0 * mse.max(1e-20).log10();
            let ssim_value = gpu(ssim.read_mean(ctx))?;
            let secs = t_train.elapsed().as_secs_f64();
            let it_per_s = f64::from(step + 1 - start_step) / secs.max(1e-9);
            let line = serde_json::json!({ "step": step, "frame": f.frame, "l1": l1, "ssim": ssim_value, "loss": f64::from(config.lambda_l1) * l1 + f64::from(config.lambda_ssim) * (1.0 - ssim_value), "psnr_train": p, "lr_position": layer.groups.position.lr(), "seconds": secs });
            writeln!(log, "{line}").map_err(|e| format!("{}: {e}", log_path.display()))?;
            progress(Progress::Step { step: step + 1, total: config.steps, l1, psnr: p, it_per_s });
        }
        if config.checkpoint_every > 0 && (step + 1) % config.checkpoint_every == 0 && step + 1 < config.steps {
            save(&mut layer, step + 1, &checkpoint_path)?;
        }
    }
    save(&mut layer, config.steps.max(start_step), &checkpoint_path)?;
    save(&mut layer, config.steps.max(start_step), &out.join("model.npz"))?;
    let train_seconds = t_train.elapsed().as_secs_f64();
    let fin = evaluate(ctx, &mut layer, &rig, &test_frames, &mut renderer, Some(&out.join("eval")), progress)?;
    // The posed body of the first held-out frame as a standard 3DGS PLY.
    if let Some(f) = test_frames.first() {
        let ft = rig.frame(&f.body);
        gpu(ctx.write_buffer(&mut layer.transforms, &ft.transforms))?;
        {
            let mut rec = gpu(ctx.record("export forward"))?;
            gpu(layer.record_forward(&mut rec, ft.log_scale))?;
            gpu(rec.submit_and_wait())?;
        }
        let cloud = gpu(layer.read_posed(ctx))?;
        let path = out.join(format!("body_frame{:04}.ply", f.frame));
        ply::write(&path, &cloud).map_err(|e| e.to_string())?;
    }
    // A novel pose (the procedural raise-arms motion, halfway) on the first held-out
    // frame's root, translation and camera.
    if let Some(f) = test_frames.first() {
        let motion = crate::motion::procedural(crate::motion::MotionKind::RaiseArms, 30, 30.0, 1.0);
        let novel = &motion.poses[15];
        let body = match &f.body {
            BodyParams::Smpl { pose, betas, translation, scale } => {
                let mut p = *pose;
                p[1..].copy_from_slice(&novel[1..]);
                BodyParams::Smpl { pose: p, betas: betas.clone(), translation: *translation, scale: *scale }
            }
            BodyParams::Zju(z) => {
                let mut z = z.clone();
                for j in 1..24 {
                    z.poses[3 * j..3 * j + 3].copy_from_slice(&novel[j]);
                }
                BodyParams::Zju(z)
            }
        };
        let ft = rig.frame(&body);
        gpu(ctx.write_buffer(&mut layer.transforms, &ft.transforms))?;
        {
            let mut rec = gpu(ctx.record("novel pose forward"))?;
            gpu(layer.record_forward(&mut rec, ft.log_scale))?;
            gpu(rec.submit_and_wait())?;
        }
        gpu(renderer.forward(&layer.posed, &camera(&f.camera, [0.0; 3]), &settings))?;
        let image = gpu(renderer.read_image())?;
        crate::dataset::image::write_rgb(&out.join("novel_pose.png"), width, height, &image.rgb)?;
    }
    let report = TrainReport {
        layout: seq.layout,
        gaussians: vec![("body".into(), n)],
        fit_steps: total_fit,
        fit_mse,
        fit_seconds,
        start_step,
        steps: config.steps,
        train_seconds,
        iterations_per_second: f64::from(config.steps.saturating_sub(start_step)) / train_seconds.max(1e-9),
        skipped_steps: skipped,
        initial,
        fin,
    };
    write_json(&out.join("metrics.json"), &report)?;
    Ok(report)
}
