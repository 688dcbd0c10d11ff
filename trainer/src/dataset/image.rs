//! Image files of the datasets, through the `image` crate: RGB images in PNG (8- or
//! 16-bit; grey, grey + alpha, RGB, RGBA) or JPEG (grey, RGB, CMYK), and masks, read
//! back with errors that name the file. Writing: PNG, or JPEG at a stated quality
//! (ZJU-MoCap ships JPEG frames).
//!
//! Colour: an image with alpha is read as its colour channels (alpha dropped: the
//! datasets' images are opaque photographs; a mask says where the person is). 16-bit
//! PNGs keep their precision: values are divided by 65535, not truncated to 8 bits.
//!
//! Masks: a pixel's value is the largest of its colour channels, in [0, 1]. Which values
//! are the person is the layout's rule ([`MaskRule`]), because the published datasets
//! disagree: ZJU-MoCap's loaders take any non-zero pixel, NeuMan's Detectron2 masks mark
//! the person black on white, HUGS's SAM masks mark it white on black.

use std::path::Path;

use image::{DynamicImage, ExtendedColorType, ImageReader};

use crate::dataset::error::DatasetError;

/// JPEG quality of the ZJU-MoCap frames `drape synth` writes (the release's frames are
/// JPEG too; 95 keeps the loss under about two 8-bit steps on the smooth synthetic
/// textures, see the synth test).
pub const ZJU_JPEG_QUALITY: u8 = 95;

/// Which mask values are the person.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MaskRule {
    /// Any non-zero pixel (ZJU-MoCap's `mask/` and `mask_cihp/`, as Neural Body,
    /// GauHuman and GART read them).
    NonZero,
    /// At least half intensity (HUGS's `4d_humans/sam_segmentations/`, 0 or 255; half
    /// rather than non-zero so that a resampled edge does not grow the person).
    AtLeastHalf,
    /// Below half intensity: NeuMan's `segmentations/` from Detectron2 are black where
    /// the person is and white elsewhere (NeuMan's reader computes `1 - mask/255`).
    BelowHalf,
}

impl MaskRule {
    pub fn name(self) -> &'static str {
        match self {
            MaskRule::NonZero => "any non-zero pixel is the person",
            MaskRule::AtLeastHalf => "pixels at least half white are the person",
            MaskRule::BelowHalf => "black pixels (below half) are the person",
        }
    }

    fn is_person(self, value: u16) -> bool {
        match self {
            MaskRule::NonZero => value > 0,
            MaskRule::AtLeastHalf => value >= 32768,
            MaskRule::BelowHalf => value < 32768,
        }
    }
}

/// An RGB image in [0, 1], row-major, interleaved.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbImage {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<f32>,
}

fn decode(path: &Path) -> Result<DynamicImage, DatasetError> {
    let reader = ImageReader::open(path).map_err(|e| DatasetError::io(path, e))?;
    let reader = reader.with_guessed_format().map_err(|e| DatasetError::io(path, e))?;
    match reader.format() {
        None => return Err(DatasetError::image(path, "not a PNG or JPEG file (unrecognised contents)")),
        Some(image::ImageFormat::Jpeg) => check_jpeg_end(path)?,
        Some(_) => {}
    }
    // `image`'s messages can run over several lines; keep the first.
    reader.decode().map_err(|e| DatasetError::image(path, format!("cannot decode ({})", e.to_string().lines().next().unwrap_or("corrupt"))))
}

/// The JPEG decoder fills a truncated file's missing blocks with grey instead of
/// failing, so a frame cut short by a broken download would train as data: require the
/// end-of-image marker (FF D9) near the end (some writers pad a few bytes after it).
fn check_jpeg_end(path: &Path) -> Result<(), DatasetError> {
    use std::io::{Read, Seek, SeekFrom};
    let mut file = std::fs::File::open(path).map_err(|e| DatasetError::io(path, e))?;
    let len = file.metadata().map_err(|e| DatasetError::io(path, e))?.len();
    let tail_len = len.min(64);
    file.seek(SeekFrom::Start(len - tail_len)).map_err(|e| DatasetError::io(path, e))?;
    let mut tail = vec![0u8; tail_len as usize];
    file.read_exact(&mut tail).map_err(|e| DatasetError::io(path, e))?;
    if tail.windows(2).any(|w| w == [0xFF, 0xD9]) {
        Ok(())
    } else {
        Err(DatasetError::image(path, "truncated JPEG (no end-of-image marker)"))
    }
}

/// The size of an image, from its header alone.
pub fn dimensions(path: &Path) -> Result<(u32, u32), DatasetError> {
    let reader = ImageReader::open(path).map_err(|e| DatasetError::io(path, e))?.with_guessed_format().map_err(|e| DatasetError::io(path, e))?;
    reader.into_dimensions().map_err(|e| DatasetError::image(path, format!("cannot read the header ({})", e.to_string().lines().next().unwrap_or("corrupt"))))
}

/// Reads an RGB image (see the module header for the formats).
pub fn read_rgb(path: &Path) -> Result<RgbImage, DatasetError> {
    let img = decode(path)?;
    let (width, height) = (img.width(), img.height());
    // `to_rgb32f` divides 8-bit values by 255 and 16-bit ones by 65535, and repeats grey.
    Ok(RgbImage { width, height, rgb: img.to_rgb32f().into_raw() })
}

/// Reads a mask with the layout's rule.
pub fn read_mask(path: &Path, rule: MaskRule) -> Result<(u32, u32, Vec<bool>), DatasetError> {
    let img = decode(path)?;
    let (w, h) = (img.width(), img.height());
    let mask = img.to_rgba16().pixels().map(|p| rule.is_person(p.0[0].max(p.0[1]).max(p.0[2]))).collect();
    Ok((w, h, mask))
}

fn to_bytes(rgb: &[f32]) -> Vec<u8> {
    rgb.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect()
}

fn create_parent(path: &Path) -> Result<(), DatasetError> {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => std::fs::create_dir_all(dir).map_err(|e| DatasetError::io(dir, e)),
        _ => Ok(()),
    }
}

fn save(path: &Path, width: u32, height: u32, bytes: &[u8], color: ExtendedColorType) -> Result<(), DatasetError> {
    create_parent(path)?;
    let format = image::ImageFormat::from_path(path).map_err(|_| DatasetError::image(path, "unknown image extension (use .png or .jpg)"))?;
    match format {
        image::ImageFormat::Png => image::save_buffer_with_format(path, bytes, width, height, color, format).map_err(|e| DatasetError::image(path, e.to_string())),
        image::ImageFormat::Jpeg => {
            let file = std::fs::File::create(path).map_err(|e| DatasetError::io(path, e))?;
            let mut w = std::io::BufWriter::new(file);
            image::codecs::jpeg::JpegEncoder::new_with_quality(&mut w, ZJU_JPEG_QUALITY).encode(bytes, width, height, color).map_err(|e| DatasetError::image(path, e.to_string()))?;
            std::io::Write::flush(&mut w).map_err(|e| DatasetError::io(path, e))
        }
        _ => Err(DatasetError::image(path, "unsupported image extension (use .png or .jpg)")),
    }
}

/// Writes RGB floats in [0, 1] as 8-bit PNG or JPEG ([`ZJU_JPEG_QUALITY`]), by extension.
pub fn write_rgb(path: &Path, width: u32, height: u32, rgb: &[f32]) -> Result<(), DatasetError> {
    save(path, width, height, &to_bytes(rgb), ExtendedColorType::Rgb8)
}

/// Writes a mask as an 8-bit grey PNG: `person` where the mask is set, `other` elsewhere
/// (255 / 0 for ZJU-MoCap and HUGS, 0 / 255 for NeuMan's Detectron2 masks).
pub fn write_mask_values(path: &Path, width: u32, height: u32, mask: &[bool], person: u8, other: u8) -> Result<(), DatasetError> {
    let bytes: Vec<u8> = mask.iter().map(|&m| if m { person } else { other }).collect();
    save(path, width, height, &bytes, ExtendedColorType::L8)
}

/// Writes a mask (person 255, elsewhere 0) as an 8-bit grey PNG.
pub fn write_mask(path: &Path, width: u32, height: u32, mask: &[bool]) -> Result<(), DatasetError> {
    write_mask_values(path, width, height, mask, 255, 0)
}
