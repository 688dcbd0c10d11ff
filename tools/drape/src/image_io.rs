//! Images in and out for the CLI, through the `image` crate: targets read as RGB floats
//! in [0, 1], and `drape render`'s outputs (PNG, NumPy `.npy`, OpenEXR). Every error is
//! one line that names the file.

use std::path::{Path, PathBuf};

use anyhow::anyhow;
use drape_engine::ops::splat::render::RenderedImage;
use drape_trainer::npy;
use image::ImageFormat;

/// An RGB image, 3 floats per pixel in [0, 1], row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<f32>,
}

/// Reads a PNG (8 or 16 bit; grey, grey + alpha, RGB or RGBA) or a JPEG (grey, RGB or
/// CMYK) as RGB floats in [0, 1], through the datasets' reader (`drape_trainer::dataset::
/// image`, which says how alpha, grey, 16 bits, EXIF orientation and truncated JPEGs
/// are handled), so that a target and a training frame are read alike.
pub fn read_rgb(path: &Path) -> anyhow::Result<Image> {
    let img = drape_trainer::dataset::image::read_rgb(path).map_err(|e| anyhow!("{e}"))?;
    Ok(Image {
        width: img.width,
        height: img.height,
        rgb: img.rgb,
    })
}

/// Writes RGB floats (clamped to [0, 1]) as an 8-bit RGB PNG.
pub fn write_png(path: &Path, width: u32, height: u32, rgb: &[f32]) -> anyhow::Result<()> {
    let bytes: Vec<u8> = rgb
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let image = image::RgbImage::from_raw(width, height, bytes).ok_or_else(|| {
        anyhow!(
            "{}: {width}x{height} does not match {} samples",
            path.display(),
            rgb.len()
        )
    })?;
    image
        .save_with_format(path, ImageFormat::Png)
        .map_err(|e| anyhow!("{}: cannot write: {e}", path.display()))
}

/// The files `drape render --out` writes, chosen by the extension.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RenderFormat {
    /// 8-bit RGB over the background.
    Png,
    /// float32 H x W x 5: premultiplied R, G, B, alpha, depth.
    Npy,
    /// float32 premultiplied RGBA, plus depth in `<stem>.depth.exr`.
    Exr,
}

impl RenderFormat {
    pub const ACCEPTED: &'static str = ".png, .npy, .exr";

    /// The format `path`'s extension names (in any case), or an error listing those
    /// accepted.
    pub fn from_path(path: &Path) -> anyhow::Result<Self> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match ext.as_deref() {
            Some("png") => Ok(Self::Png),
            Some("npy") => Ok(Self::Npy),
            Some("exr") => Ok(Self::Exr),
            Some(other) => Err(anyhow!(
                "{}: unknown output format '.{other}'; accepted: {}",
                path.display(),
                Self::ACCEPTED
            )),
            None => Err(anyhow!(
                "{}: no extension to choose the output format by; accepted: {}",
                path.display(),
                Self::ACCEPTED
            )),
        }
    }
}

/// `<stem>.depth.exr` beside an EXR output: the `image` crate writes only RGB and RGBA
/// EXR, so depth cannot be a fifth channel of the colour file.
pub fn depth_exr_path(path: &Path) -> PathBuf {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!("{stem}.depth.exr"))
}

/// Colour premultiplied by alpha: the renderer's colour is `Σ wᵢ cᵢ + (1 - alpha)·background`,
/// so the background is taken back out (exact for the default black one; within float
/// rounding otherwise), making the float files independent of `background`.
fn premultiplied(image: &RenderedImage, background: [f32; 3]) -> Vec<f32> {
    let mut rgb = image.rgb.clone();
    if background != [0.0; 3] {
        for (px, &a) in rgb.chunks_exact_mut(3).zip(&image.alpha) {
            for (c, b) in px.iter_mut().zip(background) {
                *c -= (1.0 - a) * b;
            }
        }
    }
    rgb
}

/// Expected camera-space z of what each pixel hits (`Σ wᵢ zᵢ / alpha`), 0 where alpha
/// is 0 (nothing hit), as in `drape synth`'s depth maps.
fn expected_depth(image: &RenderedImage) -> Vec<f32> {
    image
        .depth
        .iter()
        .zip(&image.alpha)
        .map(|(&d, &a)| if a > 0.0 { d / a } else { 0.0 })
        .collect()
}

fn sizes_differ(path: &Path, image: &RenderedImage) -> anyhow::Error {
    anyhow!(
        "{}: the render's {}x{} image holds {} colour, {} alpha and {} depth values",
        path.display(),
        image.width,
        image.height,
        image.rgb.len(),
        image.alpha.len(),
        image.depth.len()
    )
}

/// Writes a render in `format`; `background` is the colour the renderer composited
/// over. Returns the files written.
pub fn write_render(
    path: &Path,
    format: RenderFormat,
    image: &RenderedImage,
    background: [f32; 3],
) -> anyhow::Result<Vec<PathBuf>> {
    let (w, h) = (image.width, image.height);
    let pixels = w as usize * h as usize;
    if image.rgb.len() != 3 * pixels || image.alpha.len() != pixels || image.depth.len() != pixels {
        return Err(sizes_differ(path, image));
    }
    match format {
        RenderFormat::Png => {
            write_png(path, w, h, &image.rgb)?;
            Ok(vec![path.to_path_buf()])
        }
        RenderFormat::Npy => {
            let rgb = premultiplied(image, background);
            let depth = expected_depth(image);
            let mut data = Vec::with_capacity(5 * depth.len());
            for (i, px) in rgb.chunks_exact(3).enumerate() {
                data.extend([px[0], px[1], px[2], image.alpha[i], depth[i]].map(f64::from));
            }
            let array = npy::Array::new(npy::Dtype::F32, vec![h as usize, w as usize, 5], data);
            drape_io::write(path, npy::encode(&array))
                .map_err(|e| anyhow!("{}: cannot write: {e}", path.display()))?;
            Ok(vec![path.to_path_buf()])
        }
        RenderFormat::Exr => {
            let rgb = premultiplied(image, background);
            let rgba: Vec<f32> = rgb
                .chunks_exact(3)
                .zip(&image.alpha)
                .flat_map(|(px, &a)| [px[0], px[1], px[2], a])
                .collect();
            let colour = image::Rgba32FImage::from_raw(w, h, rgba)
                .ok_or_else(|| sizes_differ(path, image))?;
            colour
                .save_with_format(path, ImageFormat::OpenExr)
                .map_err(|e| anyhow!("{}: cannot write: {e}", path.display()))?;
            // Grey as R = G = B: the only one-value layout the encoder has.
            let depth_path = depth_exr_path(path);
            let depth: Vec<f32> = expected_depth(image)
                .into_iter()
                .flat_map(|d| [d; 3])
                .collect();
            let depth_image = image::Rgb32FImage::from_raw(w, h, depth)
                .ok_or_else(|| sizes_differ(&depth_path, image))?;
            depth_image
                .save_with_format(&depth_path, ImageFormat::OpenExr)
                .map_err(|e| anyhow!("{}: cannot write: {e}", depth_path.display()))?;
            Ok(vec![path.to_path_buf(), depth_path])
        }
    }
}
