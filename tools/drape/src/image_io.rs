//! PNG in and out for the CLI: 8-bit RGB(A) or grey, any bit depth the `png` crate
//! expands; pixels as floats in [0, 1].

use std::path::Path;

use anyhow::{bail, Context as _};
use drape_engine::ops::splat::fit::Image;

/// Reads a PNG as RGB floats (alpha dropped, grey expanded).
pub fn read_png(path: &Path) -> anyhow::Result<Image> {
    let file = std::fs::File::open(path).with_context(|| format!("{}: cannot open", path.display()))?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = decoder.read_info().with_context(|| format!("{}: not a PNG file", path.display()))?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).with_context(|| format!("{}: truncated or corrupt PNG data", path.display()))?;
    let channels = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        other => bail!("{}: colour type {other:?} is not supported", path.display()),
    };
    let (w, h) = (info.width, info.height);
    let mut rgb = Vec::with_capacity((3 * w * h) as usize);
    for px in buf[..info.buffer_size()].chunks_exact(channels) {
        let c = |i: usize| f32::from(px[i]) / 255.0;
        match channels {
            1 | 2 => rgb.extend([c(0); 3]),
            _ => rgb.extend([c(0), c(1), c(2)]),
        }
    }
    Ok(Image { width: w, height: h, rgb })
}

/// Writes RGB floats (clamped to [0, 1]) as an 8-bit RGB PNG.
pub fn write_png(path: &Path, width: u32, height: u32, rgb: &[f32]) -> anyhow::Result<()> {
    let file = std::fs::File::create(path).with_context(|| format!("{}: cannot create", path.display()))?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), width, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header().with_context(|| format!("{}: writing the header", path.display()))?;
    let bytes: Vec<u8> = rgb.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect();
    writer.write_image_data(&bytes).with_context(|| format!("{}: writing pixels", path.display()))?;
    Ok(())
}
