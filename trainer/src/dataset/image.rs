//! PNG files of the datasets: RGB images and single-channel masks, read back with
//! errors that name the file.

use std::path::Path;

/// Writes RGB floats in [0, 1] as an 8-bit PNG.
pub fn write_rgb(path: &Path, width: u32, height: u32, rgb: &[f32]) -> Result<(), String> {
    let bytes: Vec<u8> = rgb.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect();
    write(path, width, height, png::ColorType::Rgb, &bytes)
}

/// Writes a mask (0 or 255) as an 8-bit grey PNG.
pub fn write_mask(path: &Path, width: u32, height: u32, mask: &[bool]) -> Result<(), String> {
    let bytes: Vec<u8> = mask.iter().map(|&m| if m { 255 } else { 0 }).collect();
    write(path, width, height, png::ColorType::Grayscale, &bytes)
}

fn write(path: &Path, width: u32, height: u32, color: png::ColorType, bytes: &[u8]) -> Result<(), String> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    }
    let file = std::fs::File::create(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), width, height);
    enc.set_color(color);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header().map_err(|e| format!("{}: {e}", path.display()))?;
    w.write_image_data(bytes).map_err(|e| format!("{}: {e}", path.display()))
}

/// An 8-bit image: (width, height, channels, bytes).
pub fn read(path: &Path) -> Result<(u32, u32, usize, Vec<u8>), String> {
    let file = std::fs::File::open(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut dec = png::Decoder::new(std::io::BufReader::new(file));
    dec.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = dec.read_info().map_err(|e| format!("{}: not a PNG file ({e})", path.display()))?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| format!("{}: truncated or corrupt PNG ({e})", path.display()))?;
    let channels = info.color_type.samples();
    buf.truncate(info.buffer_size());
    Ok((info.width, info.height, channels, buf))
}

/// A mask: pixels whose first channel is at least 128.
pub fn read_mask(path: &Path) -> Result<(u32, u32, Vec<bool>), String> {
    let (w, h, c, bytes) = read(path)?;
    Ok((w, h, bytes.chunks_exact(c).map(|p| p[0] >= 128).collect()))
}
