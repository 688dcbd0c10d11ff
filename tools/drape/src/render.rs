//! `drape render`: one image of a 3DGS PLY file, as PNG, NumPy or OpenEXR.

use std::path::PathBuf;

use anyhow::{bail, Context as _};
use drape_cli_support::DeviceArgs;
use drape_engine::ops::splat::render::render_image;
use drape_engine::ops::splat::scene::{PinholeCamera, RenderSettings};
use drape_trainer::{camera_file, ply};

use crate::image_io::{write_render, RenderFormat};

/// Options of `drape render`.
#[derive(Clone, Debug, clap::Args)]
pub struct RenderArgs {
    /// 3D Gaussian Splatting PLY file (binary little-endian, SH degree 0-3).
    #[arg(long)]
    pub ply: PathBuf,
    /// Camera as JSON: {"fx","fy","cx","cy","width","height","rotation" (3 rows,
    /// world-to-camera, x right, y down, z forward),"translation", optional "near",
    /// "far", "background"}. Overrides the look-at options.
    #[arg(long)]
    pub camera: Option<PathBuf>,
    /// Camera position for the look-at camera.
    #[arg(long, value_parser = parse_vec3, default_value = "0,0,-3")]
    pub eye: [f32; 3],
    /// Point the look-at camera aims at.
    #[arg(long = "look-at", value_parser = parse_vec3, default_value = "0,0,0")]
    pub look_at: [f32; 3],
    /// World up direction of the look-at camera.
    #[arg(long, value_parser = parse_vec3, default_value = "0,-1,0")]
    pub up: [f32; 3],
    /// Vertical field of view in degrees.
    #[arg(long, allow_negative_numbers = true, default_value_t = 50.0, value_parser = drape_cli_support::number_in::<f32>(0.01, 179.99))]
    pub fov: f32,
    /// Image width in pixels (at least 1).
    #[arg(long, allow_negative_numbers = true, default_value_t = 512, value_parser = clap::value_parser!(u32).range(1..=16384))]
    pub width: u32,
    /// Image height in pixels (at least 1).
    #[arg(long, allow_negative_numbers = true, default_value_t = 512, value_parser = clap::value_parser!(u32).range(1..=16384))]
    pub height: u32,
    /// Background colour r,g,b in [0, 1].
    #[arg(long, value_parser = parse_colour, default_value = "0,0,0")]
    pub background: [f32; 3],
    /// Antialiased mode (opacity compensated for the low-pass dilation).
    #[arg(long)]
    pub antialiased: bool,
    /// Output file; its extension chooses the format. `.png`: 8-bit RGB over the
    /// background (no alpha channel). `.npy`: float32 height x width x 5 (R, G, B,
    /// alpha, depth). `.exr`: float32 RGBA, with depth in `<stem>.depth.exr` (R = G = B
    /// = depth; the EXR writer has no fifth channel). In .npy and .exr, colour is
    /// premultiplied by alpha (the image over black, whatever the background), and
    /// depth is the expected camera-space z (along the view axis, scene units) of what
    /// the pixel hits, sum(w_i z_i) / alpha, and 0 where alpha is 0.
    #[arg(long)]
    pub out: PathBuf,
}

/// Parses "x,y,z".
pub fn parse_vec3(s: &str) -> Result<[f32; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let values: Result<Vec<f32>, _> = parts.iter().map(|p| p.parse::<f32>()).collect();
    match values {
        Ok(v) if v.len() == 3 && v.iter().all(|x| x.is_finite()) => Ok([v[0], v[1], v[2]]),
        _ => Err(format!(
            "'{s}' is not three finite numbers separated by commas"
        )),
    }
}

/// Parses "r,g,b" with each channel in [0, 1].
fn parse_colour(s: &str) -> Result<[f32; 3], String> {
    let c = parse_vec3(s)?;
    if c.iter().any(|v| !(0.0..=1.0).contains(v)) {
        return Err(format!("'{s}': each channel must be in [0, 1]"));
    }
    Ok(c)
}

fn camera(args: &RenderArgs) -> anyhow::Result<PinholeCamera> {
    let mut cam = match &args.camera {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("{}: cannot read", path.display()))?;
            let cam = camera_file::parse(&text)
                .with_context(|| format!("{}: not a camera file", path.display()))?;
            cam.validate()
                .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
            return Ok(cam);
        }
        None => PinholeCamera::look_at(
            args.eye,
            args.look_at,
            args.up,
            args.fov,
            args.width,
            args.height,
        ),
    };
    match cam.as_mut() {
        Some(c) => c.background = args.background,
        None => bail!("the look-at camera is degenerate: eye equals --look-at, --up is parallel to the view, or --fov is outside (0, 180)"),
    }
    Ok(cam.expect("checked"))
}

pub fn run(device: &DeviceArgs, args: &RenderArgs) -> anyhow::Result<()> {
    // Before any work, so that a typo in the name costs nothing.
    let format = RenderFormat::from_path(&args.out)?;
    let cam = camera(args)?;
    let cloud = ply::read(&args.ply)?;
    let mut out = drape_cli_support::output::StagedFile::new(&args.out, "--out")?;
    let depth = crate::image_io::depth_exr_path(&args.out);
    anyhow::ensure!(
        format != RenderFormat::Exr || !depth.is_dir(),
        "--out {}: its depth file {} is a directory",
        args.out.display(),
        depth.display()
    );
    let ctx = device.open()?;
    // The colour buffer (12 bytes a pixel) is one storage buffer: named by the option.
    let colour_bytes = 12 * u64::from(cam.width) * u64::from(cam.height);
    let limit = ctx.info().max_storage_buffer_range;
    if colour_bytes > limit {
        let option = args
            .camera
            .as_ref()
            .map_or("--width/--height".to_string(), |p| {
                format!("--camera {}", p.display())
            });
        anyhow::bail!("{option}: a {}x{} image needs {colour_bytes} bytes in one storage buffer; this device's maxStorageBufferRange is {limit}", cam.width, cam.height);
    }
    let settings = RenderSettings {
        antialiased: args.antialiased,
        ..RenderSettings::default()
    };
    let t0 = std::time::Instant::now();
    let (image, stats) = render_image(&ctx, &cloud, &cam, &settings)?;
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    device.check_validation(&ctx)?;
    let mut written = vec![args.out.clone()];
    if format == RenderFormat::Exr {
        // The depth file write_render puts beside the staged colour file is committed
        // with it.
        out.companion(".depth")?;
        written.push(depth);
    }
    write_render(out.path(), format, &image, cam.background)?;
    out.commit()?;
    eprintln!(
        "rendered {} Gaussians (SH degree {}) at {}x{} in {ms:.1} ms: {} tile intersections, {} blend steps, {} dropped; wrote {}",
        cloud.len(),
        cloud.sh_degree,
        image.width,
        image.height,
        stats.intersections,
        image.blend_steps,
        stats.dropped,
        written.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(" and ")
    );
    Ok(())
}
