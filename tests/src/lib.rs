//! Helpers every GPU test binary shares (the engine's, `tests/tests/engine`, and the
//! trainer's): a validated GPU context that fails the test that caused any validation
//! message, device features a test may skip on, input patterns, the splatter's
//! comparison helpers, and the runner of the independent Python references.
// `deny`, not `forbid`: the `host` module is a host application's Vulkan code and
// allows it for itself; every other module stays free of unsafe.
#![deny(unsafe_code)]

use std::ops::Deref;
use std::sync::Arc;

use drape_engine::validation::ValidationSink;
use drape_engine::{Context, ContextDesc};
use rand::{Rng, SeedableRng};

/// A context with validation on and poisoned buffers. When it is dropped (after every
/// buffer made from it, if declared first), it fails the test on any validation
/// message, including those of device and instance destruction.
pub struct TestGpu {
    ctx: Option<Context>,
    sink: Arc<ValidationSink>,
}

/// Opens the test device (lavapipe in CI; `DRAPE_DEVICE` overrides).
pub fn gpu() -> TestGpu {
    gpu_with(&ContextDesc::for_tests())
}

/// [`gpu`] opened with `desc` (which must keep validation on), e.g. with
/// `force_staging` to count host waits as a discrete GPU would have them.
pub fn gpu_with(desc: &ContextDesc) -> TestGpu {
    let ctx = Context::new(desc).unwrap_or_else(|e| panic!("opening the test device: {e}"));
    let sink = ctx
        .validation_sink()
        .expect("tests always run with validation");
    TestGpu {
        ctx: Some(ctx),
        sink,
    }
}

impl Deref for TestGpu {
    type Target = Context;
    fn deref(&self) -> &Context {
        self.ctx.as_ref().expect("context present until drop")
    }
}

impl Drop for TestGpu {
    fn drop(&mut self) {
        drop(self.ctx.take());
        let messages = self.sink.drain();
        if !messages.is_empty() && !std::thread::panicking() {
            panic!(
                "{} validation message(s):\n{}",
                messages.len(),
                messages.join("\n")
            );
        }
    }
}

/// Device features a test may need. A test that cannot run without one calls
/// [`has_feature`] and reports itself skipped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Feature {
    /// `shaderBufferFloat32AtomicAdd`.
    FloatAtomics,
    /// Compute-queue timestamps.
    Timestamps,
    /// The subgroup rasterizers: a CPU device with subgroups of 8 lanes and ballot.
    SubgroupRaster,
    /// The subgroup and texel GEMMs (`nn_lavapipe`): subgroups of 8 lanes with ballot.
    SubgroupGemm,
}

impl Feature {
    pub fn name(self) -> &'static str {
        match self {
            Feature::FloatAtomics => "float-atomics",
            Feature::Timestamps => "timestamps",
            Feature::SubgroupRaster => "subgroup-raster",
            Feature::SubgroupGemm => "subgroup-gemm",
        }
    }

    fn present(self, ctx: &Context) -> bool {
        match self {
            Feature::FloatAtomics => ctx.info().float_atomic_add,
            Feature::Timestamps => ctx.info().timestamp_valid_bits > 0,
            Feature::SubgroupRaster => {
                drape_engine::ops::splat::render::subgroup_raster_supported(ctx.info())
            }
            Feature::SubgroupGemm => drape_engine::ops::nn::subgroup_gemm_supported(ctx.info()),
        }
    }
}

/// Whether the device has `feature`. Without it, prints `SKIPPED: <test>: ...` on
/// stderr (visible in the test output, so a skip is not mistaken for a pass), and
/// panics instead when `DRAPE_EXPECT_FEATURES` (comma-separated names; the test
/// command sets what lavapipe has) lists it: CI fails if its device lost a feature.
pub fn has_feature(ctx: &Context, feature: Feature, test: &str) -> bool {
    if feature.present(ctx) {
        return true;
    }
    let expected = std::env::var("DRAPE_EXPECT_FEATURES").unwrap_or_default();
    if expected.split(',').any(|f| f.trim() == feature.name()) {
        panic!(
            "{test}: the device '{}' lacks {}, which DRAPE_EXPECT_FEATURES says it has",
            ctx.info().name,
            feature.name()
        );
    }
    eprintln!(
        "SKIPPED: {test}: the device '{}' lacks {}",
        ctx.info().name,
        feature.name()
    );
    false
}

/// Input orders every GPU op is tested on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pattern {
    Random,
    AllEqual,
    Sorted,
    ReverseSorted,
}

impl Pattern {
    pub const ALL: [Pattern; 4] = [
        Pattern::Random,
        Pattern::AllEqual,
        Pattern::Sorted,
        Pattern::ReverseSorted,
    ];

    /// `len` values below 2^bits (all 32 bits for 32) in this pattern, reproducible
    /// from `seed`.
    pub fn generate(self, len: usize, bits: u32, seed: u64) -> Vec<u32> {
        let mask = if bits >= 32 {
            u32::MAX
        } else {
            (1u32 << bits) - 1
        };
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let mut v: Vec<u32> = match self {
            Pattern::AllEqual => vec![0x5A5A_5A5A & mask; len],
            _ => (0..len).map(|_| rng.random::<u32>() & mask).collect(),
        };
        match self {
            Pattern::Sorted => v.sort_unstable(),
            Pattern::ReverseSorted => v.sort_unstable_by(|a, b| b.cmp(a)),
            Pattern::Random | Pattern::AllEqual => {}
        }
        v
    }
}

/// Checks that `rgba` (4 floats a pixel) is premultiplied, as the player and the C ABI
/// promise: alpha within [0, 1] and each colour value within [0, alpha]; and that it
/// shows something (alpha above 1/2 somewhere). Returns how many of those covered pixels
/// have a colour value at its alpha (the clamp's bound). `what` names the image.
pub fn premultiplied_at_alpha(rgba: &[f32], what: &str) -> usize {
    for (i, p) in rgba.chunks(4).enumerate() {
        assert!(
            (0.0..=1.0).contains(&p[3]) && p[..3].iter().all(|&c| (0.0..=p[3]).contains(&c)),
            "{what}: pixel {i} is {p:?}"
        );
    }
    assert!(
        rgba.chunks(4).any(|p| p[3] > 0.5),
        "{what}: the avatar covers some pixels"
    );
    rgba.chunks(4)
        .filter(|p| p[3] > 0.5 && p[..3].contains(&p[3]))
        .count()
}

pub mod host;
pub mod module_graph;

pub mod num {
    //! Numbers for the op tests: random inputs, conversions, and the one error measure
    //! every GPU-vs-reference assertion uses.
    use rand::{Rng, SeedableRng};

    /// `len` values uniform in `[lo, hi)`, reproducible from `seed`.
    pub fn uniform(len: usize, lo: f64, hi: f64, seed: u64) -> Vec<f64> {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        (0..len).map(|_| rng.random_range(lo..hi)).collect()
    }

    pub fn to_f32(v: &[f64]) -> Vec<f32> {
        v.iter().map(|&x| x as f32).collect()
    }

    pub fn to_f64(v: &[f32]) -> Vec<f64> {
        v.iter().map(|&x| f64::from(x)).collect()
    }

    /// Largest |a - b| divided by the largest |b| (at least `floor`): a relative error
    /// of the whole array, so entries near zero are not judged on their own.
    pub fn rel_err(a: &[f64], b: &[f64], floor: f64) -> f64 {
        assert_eq!(a.len(), b.len(), "lengths differ");
        let scale = b.iter().fold(floor, |m, v| m.max(v.abs()));
        a.iter()
            .zip(b)
            .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
            / scale
    }
}

pub mod splat {
    //! Scenes and helpers for the splatting tests.
    use drape_engine::context::DeviceKind;
    use drape_engine::ops::splat::reference::{self, ReferenceRender};
    use drape_engine::ops::splat::render::{
        ForwardStats, GaussianBuffers, RasterVariant, RenderedImage, SplatRenderer,
    };
    use drape_engine::ops::splat::scene::{GaussianCloud, PinholeCamera, RenderSettings};
    use drape_engine::Context;
    use drape_shared::splat::layout::FrameParams;
    use drape_shared::splat::project::Gaussian;

    /// A camera 5 units from the origin looking at it, with a coloured background.
    pub fn camera(width: u32, height: u32) -> PinholeCamera {
        let mut cam = PinholeCamera::look_at(
            [0.3, -0.4, -5.0],
            [0.0, 0.0, 0.0],
            [0.0, -1.0, 0.0],
            45.0,
            width,
            height,
        )
        .expect("valid camera");
        cam.background = [0.1, 0.2, 0.3];
        cam
    }

    /// `n` random Gaussians around the origin, sized so that a few hundred cover the view.
    pub fn scene(n: usize, sh_degree: u32, seed: u64) -> GaussianCloud {
        let scale = if n > 1000 { 0.04 } else { 0.12 };
        GaussianCloud::random(n, sh_degree, 1.6, (-1.0, 1.0), scale, seed)
    }

    /// Renders on the GPU and reads the image back.
    pub fn gpu_render(
        ctx: &Context,
        cloud: &GaussianCloud,
        cam: &PinholeCamera,
        settings: &RenderSettings,
    ) -> (RenderedImage, ForwardStats) {
        gpu_render_with(ctx, cloud, cam, settings, RasterVariant::Auto)
    }

    /// [`gpu_render`] through the given rasterizer kernels.
    pub fn gpu_render_with(
        ctx: &Context,
        cloud: &GaussianCloud,
        cam: &PinholeCamera,
        settings: &RenderSettings,
        variant: RasterVariant,
    ) -> (RenderedImage, ForwardStats) {
        let gaussians = GaussianBuffers::upload(ctx, "test gaussians", cloud).expect("upload");
        let mut renderer =
            SplatRenderer::new(ctx, cam.width, cam.height, cloud.len()).expect("renderer");
        renderer
            .set_raster_variant(variant)
            .expect("raster variant");
        let stats = renderer
            .forward(&gaussians, cam, settings)
            .expect("forward");
        (renderer.read_image().expect("read"), stats)
    }

    /// The rasterizer variants this device runs: the workgroup kernels always, the
    /// subgroup ones where the device has them (else `test` prints that it skipped them,
    /// or fails where `DRAPE_EXPECT_FEATURES` names `subgroup-raster`).
    pub fn raster_variants(ctx: &Context, test: &str) -> Vec<RasterVariant> {
        let mut v = vec![RasterVariant::Workgroup];
        if crate::has_feature(
            ctx,
            crate::Feature::SubgroupRaster,
            &format!("{test} (subgroup rasterizer)"),
        ) {
            v.push(RasterVariant::Subgroup);
        }
        v
    }

    /// Largest absolute difference.
    pub fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    }

    /// Forward tolerance on a CPU device (lavapipe): RGB and alpha absolute, depth
    /// relative to itself. Both sides run the same f32 code and llvmpipe computes exp
    /// and ln as the host does; only their last bits may differ.
    pub const CPU_DEVICE_FORWARD_TOLERANCE: f32 = 1e-5;
    /// The same on a GPU. Vulkan allows exp a few ULP (3 + 2|x|; an H100 is within
    /// about 6e-7 relative for a splat above `alpha_min`, where |x| ≤ 5.5) and may fuse
    /// a·b + c. A pixel's colour is Σ cᵢ αᵢ Tᵢ, and an error δ in one α moves every later
    /// term by at most Tᵢ αᵢ δ / (1 - αᵢ) ≤ δ in all: n splats give at most n δ, 6e-5 for
    /// the ~100 splats of the densest pixels here (an H100: at most 8.0e-5, at 128x128
    /// with 10,000 Gaussians).
    pub const GPU_FORWARD_TOLERANCE: f32 = 1e-4;
    /// How far the CPU reference's thresholds (`alpha_min`, `transmittance_min`) are
    /// moved, relatively, to find pixels where a decision is near its threshold.
    pub const THRESHOLD_NUDGE: f32 = 1e-3;

    /// What [`assert_forward_close`] saw.
    #[derive(Debug)]
    pub struct ForwardComparison {
        /// Largest difference (RGB and alpha absolute, depth relative) at pixels with
        /// no decision near its threshold.
        pub max_error: f32,
        /// Pixels compared, and of those the ones with a decision near its threshold
        /// (always 0 on a CPU device, which gets no such allowance).
        pub pixels: usize,
        pub near_threshold: usize,
    }

    /// Checks a GPU forward `image` against the CPU reference `cpu` (of `gaussians` at
    /// `frame`) at every `step`-th pixel, panicking with `what` and the pixel.
    ///
    /// On a CPU device every pixel is within [`CPU_DEVICE_FORWARD_TOLERANCE`]. On a GPU
    /// the transcendental functions and fused multiply-adds differ in their last bits,
    /// which can flip a decision that lies within rounding of its threshold (`α ≥
    /// alpha_min`, `T > transmittance_min`) and so add or drop a whole splat at that
    /// pixel. The reference is rendered twice more with both thresholds moved by
    /// [`THRESHOLD_NUDGE`] down and up; where that changes a pixel, the pixel may differ
    /// by those two changes added (what flipping its near decisions either way can
    /// do) on top of [`GPU_FORWARD_TOLERANCE`]; every other pixel is within
    /// [`GPU_FORWARD_TOLERANCE`]. At most 5% of the pixels may be near a threshold, so
    /// the allowance cannot swallow the comparison (an H100: 0.25-0.36% at 64x64 to 128x128,
    /// 2.6% in the 1080p scene of 6,500 large splats, whose `alpha_min` rims cover many
    /// pixels).
    pub fn assert_forward_close(
        ctx: &Context,
        image: &RenderedImage,
        gaussians: &[Gaussian<f32>],
        frame: &FrameParams,
        cpu: &ReferenceRender<f32>,
        step: usize,
        what: &str,
    ) -> ForwardComparison {
        assert_forward_close_to(
            ctx,
            image,
            gaussians,
            frame,
            cpu,
            reference::render,
            GPU_FORWARD_TOLERANCE,
            step,
            what,
        )
    }

    /// [`assert_forward_close`] for a reference that `render_reference` makes (the CPU
    /// reference of a precision knob, say), holding a GPU to `gpu_tolerance` instead of
    /// [`GPU_FORWARD_TOLERANCE`]: the nudged renders that find the pixels near a
    /// threshold must come from the same function as `cpu`, or the knob's own rounding
    /// reads as nearness (seen on an H200 with half-precision splats against the f32
    /// reference: half the pixels "near").
    #[allow(clippy::too_many_arguments)]
    pub fn assert_forward_close_to(
        ctx: &Context,
        image: &RenderedImage,
        gaussians: &[Gaussian<f32>],
        frame: &FrameParams,
        cpu: &ReferenceRender<f32>,
        render_reference: fn(&[Gaussian<f32>], &FrameParams) -> ReferenceRender<f32>,
        gpu_tolerance: f32,
        step: usize,
        what: &str,
    ) -> ForwardComparison {
        let pixels = (image.width * image.height) as usize;
        assert_eq!(
            (cpu.width, cpu.height),
            (image.width, image.height),
            "{what}: image sizes"
        );
        let on_cpu = ctx.info().kind == DeviceKind::Cpu;
        let nudged = |factor: f32| {
            let mut f = *frame;
            f.alpha_min *= factor;
            f.transmittance_min *= factor;
            render_reference(gaussians, &f)
        };
        let (lo, hi) = if on_cpu {
            (None, None)
        } else {
            (
                Some(nudged(1.0 - THRESHOLD_NUDGE)),
                Some(nudged(1.0 + THRESHOLD_NUDGE)),
            )
        };
        let tolerance = if on_cpu {
            CPU_DEVICE_FORWARD_TOLERANCE
        } else {
            gpu_tolerance
        };
        let mut seen = ForwardComparison {
            max_error: 0.0,
            pixels: 0,
            near_threshold: 0,
        };
        for p in (0..pixels).step_by(step.max(1)) {
            // (value, GPU, CPU, lower, upper, scale): colour and alpha absolute, depth
            // relative to the depth (Σ w z with z near 5).
            let get = |r: &Option<ReferenceRender<f32>>,
                       v: fn(&ReferenceRender<f32>, usize) -> f32| {
                r.as_ref().map(|r| v(r, p))
            };
            type Channel = fn(&ReferenceRender<f32>, usize) -> f32;
            let values: [(&str, f32, Channel, f32); 5] = [
                ("red", image.rgb[3 * p], |r, p| r.rgb[3 * p], 1.0),
                ("green", image.rgb[3 * p + 1], |r, p| r.rgb[3 * p + 1], 1.0),
                ("blue", image.rgb[3 * p + 2], |r, p| r.rgb[3 * p + 2], 1.0),
                ("alpha", image.alpha[p], |r, p| r.alpha[p], 1.0),
                (
                    "depth",
                    image.depth[p],
                    |r, p| r.depth[p],
                    cpu.depth[p].abs().max(1.0),
                ),
            ];
            let mut near = false;
            let mut checks = Vec::with_capacity(5);
            for (name, g, v, scale) in values {
                let c = v(cpu, p);
                let slack = [get(&lo, v), get(&hi, v)]
                    .into_iter()
                    .flatten()
                    .map(|x| (x - c).abs() / scale)
                    .sum::<f32>();
                near |= slack > tolerance;
                checks.push((name, g, c, scale, slack));
            }
            for (name, g, c, scale, slack) in checks {
                let e = (g - c).abs() / scale;
                let allowed = tolerance + if near { slack } else { 0.0 };
                assert!(e <= allowed, "{what}: pixel {p} ({}, {}) {name}: GPU {g} vs CPU {c}, error {e:e} over {allowed:e} (near a threshold: {near}, nudged thresholds move it {slack:e})", p % image.width as usize, p / image.width as usize);
                if !near {
                    seen.max_error = seen.max_error.max(e);
                }
            }
            seen.pixels += 1;
            seen.near_threshold += usize::from(near);
        }
        assert!(
            seen.near_threshold * 20 <= seen.pixels,
            "{what}: {} of {} pixels near a threshold: the comparison would be too loose",
            seen.near_threshold,
            seen.pixels
        );
        seen
    }
}

/// An RGB picture, 3 floats per pixel in [0, 1], row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Picture {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// The pixels, row-major from the top row.
    pub rgb: Vec<f32>,
}

/// A procedural 64x64-style test picture: a smooth two-colour gradient, three soft
/// disks of different colours and sizes, and a ring; values in [0, 1].
pub fn test_picture(width: u32, height: u32) -> Picture {
    let mut rgb = Vec::with_capacity((3 * width * height) as usize);
    for y in 0..height {
        for x in 0..width {
            let (u, v) = (
                (x as f32 + 0.5) / width as f32,
                (y as f32 + 0.5) / height as f32,
            );
            let mut c = [0.15 + 0.6 * u, 0.2 + 0.5 * v, 0.55 - 0.3 * u * v];
            let disks = [
                ([0.3, 0.35], 0.18, [0.95, 0.3, 0.2]),
                ([0.7, 0.6], 0.22, [0.2, 0.8, 0.35]),
                ([0.45, 0.8], 0.1, [0.95, 0.9, 0.2]),
            ];
            for (centre, radius, colour) in disks {
                let d = ((u - centre[0]).powi(2) + (v - centre[1]).powi(2)).sqrt();
                let w = (1.0 - ((d - radius) / 0.02).clamp(-1.0, 1.0)) * 0.5;
                for k in 0..3 {
                    c[k] = c[k] * (1.0 - w) + colour[k] * w;
                }
            }
            let d = ((u - 0.72).powi(2) + (v - 0.25).powi(2)).sqrt();
            let ring = (-((d - 0.12) / 0.025).powi(2)).exp();
            for k in 0..3 {
                c[k] = c[k] * (1.0 - ring) + 0.05 * ring;
            }
            rgb.extend(c);
        }
    }
    Picture { width, height, rgb }
}

pub mod reference_python {
    //! Running the independent Python references (`tests/python/*.py`) in the virtual
    //! environment `scripts/torch-env.sh` makes: NumPy files in, NumPy files out, one
    //! directory per case. Without the environment the calling test fails, it is not
    //! skipped.
    use std::path::{Path, PathBuf};
    use std::process::Command;

    /// `DRAPE_TORCH_PYTHON`, else the project's `target/torch-venv`.
    pub fn python() -> PathBuf {
        if let Ok(p) = std::env::var("DRAPE_TORCH_PYTHON") {
            return p.into();
        }
        let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/torch-venv/bin/python");
        assert!(venv.exists(), "no reference environment (PyTorch, gsplat, scikit-image): run scripts/torch-env.sh (the test command does) or set DRAPE_TORCH_PYTHON");
        venv
    }

    /// `DRAPE_CLIENTS_PYTHON`, else the project's `target/clients-venv` (numpy 1.x and
    /// kubernetes-validate, from `scripts/clients-env.sh`, which the test command runs).
    pub fn clients_python() -> PathBuf {
        if let Ok(p) = std::env::var("DRAPE_CLIENTS_PYTHON") {
            return p.into();
        }
        let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/clients-venv/bin/python");
        assert!(venv.exists(), "no numpy 1.x environment: run scripts/clients-env.sh (the test command does) or set DRAPE_CLIENTS_PYTHON");
        venv
    }

    /// A fresh, empty directory for one case: `<target>/tmp/<group>/<name>`, beside the
    /// test binary (`<target>/<profile>/deps/`), where cargo's `CARGO_TARGET_TMPDIR` is
    /// (that variable exists only when integration tests themselves compile).
    pub fn case_dir(group: &str, name: &str) -> PathBuf {
        let exe = std::env::current_exe().expect("test executable");
        let target = exe
            .ancestors()
            .nth(3)
            .expect("<target>/<profile>/deps/<test>");
        let d = target.join("tmp").join(group).join(name);
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).expect("case directory");
        d
    }

    /// Writes `dir/name.npy`: little-endian float64, C order, format 1.0. The exchange
    /// with Python needs only this one dtype; the trainer's `npy` module (the product's
    /// reader, tested against numpy itself) is not linked here so that the engine's
    /// tests do not link the trainer.
    pub fn put(dir: &Path, name: &str, shape: &[usize], data: &[f64]) {
        assert_eq!(
            shape.iter().product::<usize>(),
            data.len(),
            "{name}: shape {shape:?} does not hold {} values",
            data.len()
        );
        let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
        let shape = if dims.len() == 1 {
            format!("({},)", dims[0])
        } else {
            format!("({})", dims.join(", "))
        };
        let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}");
        // Data starts at a multiple of 64 bytes; the header ends in '\n'.
        header.push_str(&" ".repeat((64 - (10 + header.len() + 1) % 64) % 64));
        header.push('\n');
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        bytes.extend((header.len() as u16).to_le_bytes());
        bytes.extend(header.as_bytes());
        bytes.extend(data.iter().flat_map(|v| v.to_le_bytes()));
        drape_io::write(dir.join(format!("{name}.npy")), bytes).expect("write npy");
    }

    /// Reads `dir/name.npy` as numpy writes it from the reference scripts: float64,
    /// little-endian, C order (format 1.x, 2.x or 3.x header).
    pub fn get(dir: &Path, name: &str) -> Vec<f64> {
        let path = dir.join(format!("{name}.npy"));
        let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert!(
            bytes.len() >= 10 && bytes.starts_with(b"\x93NUMPY"),
            "{}: not a .npy file",
            path.display()
        );
        let (header_len, start) = match bytes[6] {
            1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
            _ => (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            ),
        };
        let header = String::from_utf8_lossy(&bytes[start..start + header_len]);
        assert!(
            header.contains("'descr': '<f8'") && header.contains("'fortran_order': False"),
            "{}: expected C-order float64, header {header}",
            path.display()
        );
        bytes[start + header_len..]
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
            .collect()
    }

    /// Runs `tests/python/<script>` on `dirs` and fails the test, with its stderr, if
    /// the script fails.
    pub fn run(script: &str, dirs: &[PathBuf]) {
        run_with(&python(), script, dirs)
    }

    /// [`run`] with another interpreter (e.g. [`clients_python`]).
    pub fn run_with(python: &Path, script: &str, dirs: &[PathBuf]) {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("python")
            .join(script);
        let out = Command::new(python)
            .arg(&path)
            .args(dirs)
            .output()
            .unwrap_or_else(|e| panic!("running {script}: {e}"));
        assert!(
            out.status.success(),
            "{script} failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
}
