//! The body stage's picture, `body/sheet.png`: the fitted body drawn over frames of
//! every view, to look at. One row per view, three columns (the first, middle and last
//! fitted frame, each view read at its time offset), every frame scaled to 256 px high;
//! the body's vertices as green dots and its skeleton (the 24 joints and their bones)
//! in red, projected through the view's camera and lens distortion.

use std::path::Path;

use anyhow::Context as _;
use drape_trainer::body::kinematics::{pose_body, Pose};
use drape_trainer::body::model::{SmplModel, PARENTS};
use drape_trainer::dataset::distortion;
use glam::DVec3;
use image::{ImageEncoder as _, Rgb, RgbImage};

use super::triangulate::View;

/// Each thumbnail's height in pixels.
const ROW_HEIGHT: u32 = 256;

/// A frame of the fit: the pose and translation the body is drawn at.
pub struct SheetFrame<'a> {
    pub pose: &'a Pose,
    pub translation: DVec3,
}

/// What the sheet is drawn from.
pub struct Sheet<'a> {
    /// `frames/`: view `v`'s frames are under `frames_dir/<its name>/`.
    pub frames_dir: &'a Path,
    pub views: &'a [View],
    /// Per view, its frame files in order.
    pub frame_names: &'a [Vec<String>],
    /// Per view, its time offset in frames.
    pub offsets: &'a [f64],
    pub model: &'a SmplModel,
    pub betas: &'a [f64],
    pub fitted: &'a [SheetFrame<'a>],
}

/// Draws the sheet (module header) and writes it to `path` as PNG.
pub fn write(path: &Path, sheet: &Sheet<'_>) -> anyhow::Result<()> {
    let Sheet {
        frames_dir,
        views,
        frame_names,
        offsets,
        model,
        betas,
        fitted,
    } = *sheet;
    let n = fitted.len();
    if n == 0 || views.is_empty() {
        return Ok(());
    }
    let picks = [0, n / 2, n - 1];
    let mut tiles: Vec<Vec<RgbImage>> = Vec::new();
    for (v, view) in views.iter().enumerate() {
        let mut row = Vec::new();
        for &f in &picks {
            let last = frame_names[v].len().saturating_sub(1);
            let i = ((f as f64 + offsets[v]).round().max(0.0) as usize).min(last);
            let file = frames_dir.join(&view.name).join(&frame_names[v][i]);
            let img = image::open(&file)
                .with_context(|| format!("{}", file.display()))?
                .to_rgb8();
            let s = f64::from(ROW_HEIGHT) / f64::from(img.height());
            let w = ((f64::from(img.width()) * s).round() as u32).max(1);
            let mut tile =
                image::imageops::resize(&img, w, ROW_HEIGHT, image::imageops::FilterType::Triangle);
            let posed = pose_body(model, betas, fitted[f].pose, fitted[f].translation);
            let to_px = |p: DVec3| -> Option<[f64; 2]> {
                let c = view.camera.to_camera(p);
                (c[2] > 1e-3).then(|| {
                    let q = distortion::project(&view.camera, &view.distortion, p);
                    [q[0] * s, q[1] * s]
                })
            };
            for p in posed.vertices.iter().step_by(3) {
                if let Some(q) = to_px(*p) {
                    blend(&mut tile, q, Rgb([40, 230, 60]), 0.6);
                }
            }
            for (j, &parent) in PARENTS.iter().enumerate().skip(1) {
                if let (Some(a), Some(b)) =
                    (to_px(posed.joints[j]), to_px(posed.joints[parent as usize]))
                {
                    line(&mut tile, a, b, Rgb([240, 40, 40]));
                }
            }
            row.push(tile);
        }
        tiles.push(row);
    }
    let width = tiles
        .iter()
        .map(|r| r.iter().map(RgbImage::width).sum::<u32>())
        .max()
        .unwrap_or(1);
    let mut out = RgbImage::new(width, ROW_HEIGHT * tiles.len() as u32);
    for (r, row) in tiles.iter().enumerate() {
        let mut x = 0;
        for tile in row {
            image::imageops::replace(
                &mut out,
                tile,
                i64::from(x),
                i64::from(ROW_HEIGHT) * r as i64,
            );
            x += tile.width();
        }
    }
    let mut bytes = Vec::new();
    image::codecs::png::PngEncoder::new(&mut bytes)
        .write_image(
            out.as_raw(),
            out.width(),
            out.height(),
            image::ExtendedColorType::Rgb8,
        )
        .with_context(|| format!("{}: encoding", path.display()))?;
    drape_io::write(path, bytes).with_context(|| format!("{}", path.display()))?;
    Ok(())
}

/// Mixes `colour` into the pixel at `q` (pixel centres at +0.5) by `alpha`.
fn blend(img: &mut RgbImage, q: [f64; 2], colour: Rgb<u8>, alpha: f64) {
    let (x, y) = (q[0].floor(), q[1].floor());
    if x < 0.0 || y < 0.0 || x >= f64::from(img.width()) || y >= f64::from(img.height()) {
        return;
    }
    let p = img.get_pixel_mut(x as u32, y as u32);
    for (c, k) in p.0.iter_mut().zip(colour.0) {
        *c = (f64::from(*c) * (1.0 - alpha) + f64::from(k) * alpha).round() as u8;
    }
}

/// A one-pixel line from `a` to `b`.
fn line(img: &mut RgbImage, a: [f64; 2], b: [f64; 2], colour: Rgb<u8>) {
    let steps = (b[0] - a[0])
        .abs()
        .max((b[1] - a[1]).abs())
        .ceil()
        .clamp(1.0, 4096.0) as usize;
    for k in 0..=steps {
        let t = k as f64 / steps as f64;
        blend(
            img,
            [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])],
            colour,
            1.0,
        );
    }
}
