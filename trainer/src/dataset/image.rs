//! Image files of the datasets, through the `image` crate: RGB images in PNG (8- or
//! 16-bit; grey, grey + alpha, RGB, RGBA) or JPEG (grey, RGB, CMYK), and masks, read
//! back with errors that name the file. Writing: PNG, or JPEG at a stated quality
//! (ZJU-MoCap ships JPEG frames).
//!
//! Orientation: a JPEG's EXIF orientation is applied (the picture a viewer shows).
//! A JPEG that ends before its end-of-image marker is refused (see `jpeg_complete`).
//!
//! Colour: an image with alpha is read as its colour channels (alpha dropped: the
//! datasets' images are opaque photographs; a mask says where the person is). 16-bit
//! PNGs keep their precision: values are divided by 65535, not truncated to 8 bits.
//!
//! Masks: a pixel's value is the largest of its colour channels, in [0, 1]. Which values
//! are the person is the layout's rule ([`MaskRule`]), because the published datasets
//! disagree: ZJU-MoCap's loaders take any non-zero pixel, NeuMan's Detectron2 masks mark
//! the person black on white, HUGS's SAM masks mark it white on black.

use std::io::Cursor;
use std::path::Path;

use image::metadata::Orientation;
use image::ImageEncoder as _;
use image::{
    DynamicImage, ExtendedColorType, ImageDecoder as _, ImageError, ImageFormat, ImageReader,
};

use crate::dataset::error::DatasetError;

/// JPEG quality of the ZJU-MoCap frames `drape synth` writes (the release's frames are
/// JPEG too): 36.6 dB PSNR against the lossless render on a 64 px frame, the error
/// concentrated on hard edges (see the synth test `jpeg_frames_lose_little`).
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

fn reader(path: &Path, bytes: &[u8]) -> Result<ImageReader<Cursor<Vec<u8>>>, DatasetError> {
    // By content, not by name: a PNG called `x.jpg` is still a PNG.
    let reader = ImageReader::new(Cursor::new(bytes.to_vec()))
        .with_guessed_format()
        .map_err(|e| DatasetError::io(path, e))?;
    match reader.format() {
        None => {
            return Err(DatasetError::image(
                path,
                "not a PNG or JPEG this program reads (unrecognised contents)",
            ))
        }
        Some(ImageFormat::Jpeg) => jpeg_complete(path, bytes)?,
        Some(_) => {}
    }
    Ok(reader)
}

/// Decodes a file with its EXIF orientation applied (the picture a viewer shows, as
/// OpenCV's `imread` returns it).
fn decode(path: &Path) -> Result<DynamicImage, DatasetError> {
    let bytes = std::fs::read(path).map_err(|e| DatasetError::io(path, e))?;
    let named = |e: ImageError| DatasetError::image(path, describe(&e));
    let mut decoder = reader(path, &bytes)?.into_decoder().map_err(named)?;
    check_size(path, decoder.dimensions(), decoder.total_bytes())?;
    let orientation = decoder.orientation().map_err(named)?;
    let mut image = DynamicImage::from_decoder(decoder).map_err(named)?;
    image.apply_orientation(orientation);
    Ok(image)
}

/// The largest image drape decodes: 16384 on a side and 1 GiB decoded (a 16-bit RGBA
/// 8192 x 8192). The header's claim is checked before the decoder allocates for it.
pub const MAX_IMAGE_SIDE: u32 = 16384;
pub const MAX_IMAGE_BYTES: u64 = 1 << 30;

fn check_size(path: &Path, (w, h): (u32, u32), bytes: u64) -> Result<(), DatasetError> {
    if w == 0 || h == 0 || w > MAX_IMAGE_SIDE || h > MAX_IMAGE_SIDE || bytes > MAX_IMAGE_BYTES {
        return Err(DatasetError::image(path, format!("too large or empty: {w}x{h} ({bytes} bytes decoded); drape reads images of 1 to {MAX_IMAGE_SIDE} pixels a side and at most {MAX_IMAGE_BYTES} bytes")));
    }
    Ok(())
}

/// One line for an `ImageError`, saying which kind of trouble it is.
fn describe(e: &ImageError) -> String {
    let detail = e.to_string();
    let detail = detail.lines().next().unwrap_or("").trim();
    match e {
        ImageError::Unsupported(_) => format!("not a PNG or JPEG this program reads: {detail}"),
        // The bytes are in memory, so the decoder's only I/O error is running out of them.
        ImageError::Decoding(_) | ImageError::IoError(_) => {
            format!("truncated or corrupt image: {detail}")
        }
        ImageError::Limits(_) => format!("too large: {detail}"),
        _ => detail.to_string(),
    }
}

/// Whether a JPEG's markers run through to its end-of-image marker. The `image` crate's
/// JPEG decoder is lenient: a file cut short decodes without error, the missing part
/// grey, which would silently become a wrong training target. Walking the markers finds
/// the cut without decoding: outside the entropy-coded data every segment states its
/// length, and inside it a 0xFF byte is always followed by a stuffed 0x00, a restart
/// marker or the next marker. Bytes after the end marker (camera trailers) are allowed.
/// A cut or corrupt file is [`DatasetError::Image`] for `path`.
fn jpeg_complete(path: &Path, b: &[u8]) -> Result<(), DatasetError> {
    let truncated = || {
        DatasetError::image(
            path,
            "truncated JPEG (the data ends before its end-of-image marker)",
        )
    };
    let mut i = 2; // past SOI, which guessing the format checked
    loop {
        // Garbage between segments is skipped, as libjpeg does (with a warning).
        while i < b.len() && b[i] != 0xFF {
            i += 1;
        }
        // Any number of 0xFF fill bytes may precede a marker.
        while i < b.len() && b[i] == 0xFF {
            i += 1;
        }
        let Some(&marker) = b.get(i) else {
            return Err(truncated());
        };
        i += 1;
        match marker {
            0xD9 => return Ok(()),
            // Standalone markers (TEM, RSTn) carry no length.
            0x01 | 0xD0..=0xD7 => continue,
            _ => {}
        }
        let Some(len) = b
            .get(i..i + 2)
            .map(|l| usize::from(u16::from_be_bytes([l[0], l[1]])))
        else {
            return Err(truncated());
        };
        if len < 2 {
            return Err(DatasetError::image(
                path,
                format!(
                    "corrupt JPEG (segment 0xFF{marker:02X} at byte {} has length {len})",
                    i - 2
                ),
            ));
        }
        i += len;
        if i > b.len() {
            return Err(truncated());
        }
        if marker == 0xDA {
            // Start of scan: entropy-coded data up to the next marker.
            loop {
                match (b.get(i), b.get(i + 1)) {
                    (Some(0xFF), Some(0x00 | 0xD0..=0xD7)) => i += 2,
                    (Some(0xFF), Some(_)) => break,
                    (Some(_), _) => i += 1,
                    (None, _) => return Err(truncated()),
                }
            }
        }
    }
}

/// The size of an image as decoded (EXIF orientation applied), from its header alone.
pub fn dimensions(path: &Path) -> Result<(u32, u32), DatasetError> {
    let bytes = std::fs::read(path).map_err(|e| DatasetError::io(path, e))?;
    let named = |e: ImageError| DatasetError::image(path, describe(&e));
    let mut decoder = reader(path, &bytes)?.into_decoder().map_err(named)?;
    let (w, h) = decoder.dimensions();
    check_size(path, (w, h), decoder.total_bytes())?;
    let turned = matches!(
        decoder.orientation().map_err(named)?,
        Orientation::Rotate90
            | Orientation::Rotate270
            | Orientation::Rotate90FlipH
            | Orientation::Rotate270FlipH
    );
    Ok(if turned { (h, w) } else { (w, h) })
}

/// Reads an RGB image (see the module header for the formats).
pub fn read_rgb(path: &Path) -> Result<RgbImage, DatasetError> {
    let img = decode(path)?;
    let (width, height) = (img.width(), img.height());
    // `to_rgb32f` divides 8-bit values by 255 and 16-bit ones by 65535, and repeats grey.
    Ok(RgbImage {
        width,
        height,
        rgb: img.to_rgb32f().into_raw(),
    })
}

/// Reads a mask with the layout's rule.
pub fn read_mask(path: &Path, rule: MaskRule) -> Result<(u32, u32, Vec<bool>), DatasetError> {
    let img = decode(path)?;
    let (w, h) = (img.width(), img.height());
    let mask = img
        .to_rgba16()
        .pixels()
        .map(|p| rule.is_person(p.0[0].max(p.0[1]).max(p.0[2])))
        .collect();
    Ok((w, h, mask))
}

fn to_bytes(rgb: &[f32]) -> Vec<u8> {
    rgb.iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect()
}

fn create_parent(path: &Path) -> Result<(), DatasetError> {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => {
            std::fs::create_dir_all(dir).map_err(|e| DatasetError::io(dir, e))
        }
        _ => Ok(()),
    }
}

fn save(
    path: &Path,
    width: u32,
    height: u32,
    bytes: &[u8],
    color: ExtendedColorType,
) -> Result<(), DatasetError> {
    create_parent(path)?;
    let format = image::ImageFormat::from_path(path)
        .map_err(|_| DatasetError::image(path, "unknown image extension (use .png or .jpg)"))?;
    // Encoding errors travel out of the writer as I/O errors' payloads.
    let encoded = |r: image::ImageResult<()>| r.map_err(std::io::Error::other);
    let written = match format {
        image::ImageFormat::Png => drape_io::write_with(path, |w| {
            encoded(image::codecs::png::PngEncoder::new(w).write_image(bytes, width, height, color))
        }),
        image::ImageFormat::Jpeg => drape_io::write_with(path, |w| {
            encoded(
                image::codecs::jpeg::JpegEncoder::new_with_quality(w, ZJU_JPEG_QUALITY)
                    .encode(bytes, width, height, color),
            )
        }),
        _ => {
            return Err(DatasetError::image(
                path,
                "unsupported image extension (use .png or .jpg)",
            ))
        }
    };
    written.map_err(|e| match e.downcast::<image::ImageError>() {
        Ok(e) => DatasetError::image(path, e.to_string()),
        Err(e) => DatasetError::io(path, e),
    })
}

/// Writes RGB floats in [0, 1] as 8-bit PNG or JPEG ([`ZJU_JPEG_QUALITY`]), by extension.
pub fn write_rgb(path: &Path, width: u32, height: u32, rgb: &[f32]) -> Result<(), DatasetError> {
    save(path, width, height, &to_bytes(rgb), ExtendedColorType::Rgb8)
}

/// Writes a mask as an 8-bit grey PNG: `person` where the mask is set, `other` elsewhere
/// (255 / 0 for ZJU-MoCap and HUGS, 0 / 255 for NeuMan's Detectron2 masks).
pub fn write_mask_values(
    path: &Path,
    width: u32,
    height: u32,
    mask: &[bool],
    person: u8,
    other: u8,
) -> Result<(), DatasetError> {
    let bytes: Vec<u8> = mask
        .iter()
        .map(|&m| if m { person } else { other })
        .collect();
    save(path, width, height, &bytes, ExtendedColorType::L8)
}

/// Writes a mask (person 255, elsewhere 0) as an 8-bit grey PNG.
pub fn write_mask(path: &Path, width: u32, height: u32, mask: &[bool]) -> Result<(), DatasetError> {
    write_mask_values(path, width, height, mask, 255, 0)
}
