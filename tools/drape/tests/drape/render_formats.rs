//! `drape render --out` as PNG, `.npy` and OpenEXR (the same render in each, read back
//! by numpy and by the `image` crate), and the images `drape fit` reads: PNG at 8 and
//! 16 bits in every colour type, JPEG (RGB, grey, CMYK, rotated by EXIF), and broken
//! files failing in one line that names them.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use drape_engine::ops::splat::scene::GaussianCloud;
use drape_trainer::avatar::groups::Layer;
use drape_trainer::ply;

// The CLI's own reader, compiled into this test, so that pixel values are checked on the
// very code `drape fit` runs (a binary crate has no library to import it from).
#[allow(dead_code)]
#[path = "../../src/image_io.rs"]
mod image_io;

fn drape(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_drape"))
        .args(args)
        .output()
        .expect("drape runs")
}

/// A fresh directory for one test.
fn case_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir()
        .join(format!("drape-render-formats-{}", std::process::id()))
        .join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `DRAPE_TORCH_PYTHON`, else the project's `target/torch-venv` (numpy 2.1.3, Pillow).
/// Missing is a failure, not a skip: these checks are the point of the test.
fn python() -> PathBuf {
    if let Ok(p) = std::env::var("DRAPE_TORCH_PYTHON") {
        return p.into();
    }
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/torch-venv/bin/python");
    assert!(
        venv.exists(),
        "no reference environment at {}: run scripts/torch-env.sh (or set DRAPE_TORCH_PYTHON)",
        venv.display()
    );
    venv
}

fn run_python(script: &str, args: &[&str]) -> String {
    let out = Command::new(python())
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .expect("python runs");
    assert!(
        out.status.success(),
        "python failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn read_f32s(path: &Path) -> Vec<f32> {
    std::fs::read(path)
        .unwrap()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

fn assert_one_line_error(out: &Output, needle: &str) {
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "succeeded; stderr: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(stderr.trim_end().lines().count(), 1, "{stderr}");
    assert!(stderr.contains(needle), "'{needle}' not in {stderr}");
}

const W: usize = 48;
const H: usize = 40;

/// Two opaque-ish Gaussians in front of the default look-at camera (eye 0,0,-3 looking
/// at the origin), apart so they do not overlap: a red one at camera depth 3 on the
/// left and a green one at depth 4 on the right; the corners stay empty.
fn write_scene(path: &Path) {
    let mut cloud = GaussianCloud::new(0);
    // SH degree 0: colour = 0.5 + C0·sh, C0 = 0.28209479.
    // Red is about 13 px left of centre with a 9 px reach, green 11 px right with 7 px.
    for (mean, sh) in [
        ([-0.9f32, 0.0, 0.0], [1.7f32, -1.7, -1.7]),
        ([1.0, 0.0, 1.0], [-1.7, 1.7, -1.7]),
    ] {
        cloud.means.extend(mean);
        cloud.log_scales.extend([0.2f32.ln(); 3]);
        cloud.quats.extend([1.0, 0.0, 0.0, 0.0]);
        cloud.opacity_logits.push(2.0);
        cloud.sh.extend(sh);
        cloud.groups.push(Layer::Scene.group());
    }
    ply::write(path, &cloud).unwrap();
}

fn render(ply: &Path, out: &Path, extra: &[&str]) {
    let mut args = vec![
        "--validation",
        "render",
        "--ply",
        s(ply),
        "--width",
        "48",
        "--height",
        "40",
        "--out",
        s(out),
    ];
    args.extend(extra);
    let o = drape(&args);
    assert!(
        o.status.success(),
        "render to {} failed: {}",
        out.display(),
        String::from_utf8_lossy(&o.stderr)
    );
}

/// The .npy through numpy: its shape and dtype as numpy prints them, and its values.
fn numpy_load(npy: &Path) -> (String, Vec<f32>) {
    let raw = npy.with_extension("raw");
    let printed = run_python(
        "import sys, numpy as np\n\
         a = np.load(sys.argv[1])\n\
         print(a.shape, a.dtype.str)\n\
         np.ascontiguousarray(a, dtype='<f4').tofile(sys.argv[2])",
        &[s(npy), s(&raw)],
    );
    (printed.trim().to_string(), read_f32s(&raw))
}

#[test]
fn render_writes_the_same_image_as_png_npy_and_exr() {
    let dir = case_dir("formats");
    let ply = dir.join("scene.ply");
    write_scene(&ply);
    let (png, npy, exr) = (dir.join("r.png"), dir.join("r.npy"), dir.join("r.exr"));
    for out in [&png, &npy, &exr] {
        render(&ply, out, &[]);
    }

    let (printed, a) = numpy_load(&npy);
    assert_eq!(printed, "(40, 48, 5) <f4");
    let px = |x: usize, y: usize| &a[5 * (y * W + x)..5 * (y * W + x) + 5];

    // The PNG is round(255 v) of the same colour (black background, so the over-black
    // colour of the .npy is the PNG's): at most half an 8-bit step apart, tighter than
    // the one step a truncating writer would need; 1e-3 step for float rounding.
    let png_image = image::open(&png).unwrap();
    assert_eq!(
        png_image.color(),
        image::ColorType::Rgb8,
        "the PNG is 8-bit RGB, no alpha"
    );
    let png_rgb = png_image.into_rgb8();
    assert_eq!(png_rgb.dimensions(), (W as u32, H as u32));
    let mut worst = 0.0f32;
    for (i, p) in png_rgb.pixels().enumerate() {
        for c in 0..3 {
            worst = worst.max((a[5 * i + c].clamp(0.0, 1.0) * 255.0 - f32::from(p[c])).abs());
        }
    }
    assert!(
        worst <= 0.501,
        "the .npy colour is {worst} 8-bit steps from the PNG"
    );

    // The scene is what was asked for: empty corners (alpha 0, depth 0, black), and
    // each Gaussian's own depth where it covers the pixel (one splat per pixel, so
    // sum(w z) / alpha is its z up to float rounding).
    assert_eq!(px(0, 0), &[0.0; 5]);
    assert_eq!(px(W - 1, H - 1), &[0.0; 5]);
    let (mut at3, mut at4) = (0, 0);
    for i in 0..W * H {
        let (alpha, depth) = (a[5 * i + 3], a[5 * i + 4]);
        assert!((0.0..=1.0).contains(&alpha), "alpha {alpha}");
        if alpha == 0.0 {
            assert_eq!(depth, 0.0, "no hit, depth 0");
        } else if (depth - 3.0).abs() < 1e-4 {
            at3 += 1;
        } else if (depth - 4.0).abs() < 1e-4 {
            at4 += 1;
        } else {
            panic!("pixel {i}: depth {depth} is neither Gaussian's (alpha {alpha})");
        }
        // Premultiplied: no channel above alpha (SH colours here are within [0, 1]).
        for c in 0..3 {
            assert!(
                a[5 * i + c] <= alpha + 1e-6,
                "pixel {i}: colour {} above alpha {alpha}",
                a[5 * i + c]
            );
        }
    }
    assert!(
        at3 > 20 && at4 > 20,
        "pixels hit at depth 3: {at3}, at 4: {at4}"
    );
    // Red Gaussian left of centre, green right (x is not mirrored or transposed).
    let left = px(11, H / 2);
    let right = px(35, H / 2);
    assert!(
        left[0] > 0.5 && left[1] < 0.2 && (left[4] - 3.0).abs() < 1e-4,
        "left {left:?}"
    );
    assert!(
        right[1] > 0.3 && right[0] < 0.2 && (right[4] - 4.0).abs() < 1e-4,
        "right {right:?}"
    );

    // The EXR holds the very floats of the .npy: RGBA here, depth in <stem>.depth.exr.
    let rgba = image::open(&exr).unwrap().into_rgba32f();
    assert_eq!(rgba.dimensions(), (W as u32, H as u32));
    let depth = image::open(dir.join("r.depth.exr")).unwrap().into_rgb32f();
    for (i, (p, d)) in rgba.pixels().zip(depth.pixels()).enumerate() {
        assert_eq!(
            p.0,
            [a[5 * i], a[5 * i + 1], a[5 * i + 2], a[5 * i + 3]],
            "pixel {i}"
        );
        assert_eq!(d.0, [a[5 * i + 4]; 3], "pixel {i}");
    }
}

/// The float files hold premultiplied colour whatever `--background` is; the PNG is
/// composited over it.
#[test]
fn float_outputs_do_not_depend_on_the_background() {
    let dir = case_dir("background");
    let ply = dir.join("scene.ply");
    write_scene(&ply);
    render(&ply, &dir.join("black.npy"), &[]);
    render(
        &ply,
        &dir.join("blue.npy"),
        &["--background", "0.2,0.4,0.8"],
    );
    render(
        &ply,
        &dir.join("blue.png"),
        &["--background", "0.2,0.4,0.8"],
    );
    let (_, black) = numpy_load(&dir.join("black.npy"));
    let (_, blue) = numpy_load(&dir.join("blue.npy"));
    // Taking the background back out costs float rounding of values <= 1: 1e-6.
    for (i, (x, y)) in black.iter().zip(&blue).enumerate() {
        assert!(
            (x - y).abs() <= 1e-6,
            "value {i}: {x} over black, {y} over blue-grey"
        );
    }
    let png = image::open(dir.join("blue.png")).unwrap().into_rgb8();
    assert_eq!(
        png.get_pixel(0, 0).0,
        [51, 102, 204],
        "an empty pixel shows the background"
    );
}

#[test]
fn render_rejects_an_unknown_extension_before_rendering() {
    // The PLY does not exist: the extension is checked first, so that is not the error.
    let out = drape(&[
        "render",
        "--ply",
        "/nonexistent/scene.ply",
        "--out",
        "/tmp/frame.tiff",
    ]);
    assert_one_line_error(
        &out,
        "/tmp/frame.tiff: unknown output format '.tiff'; accepted: .png, .npy, .exr",
    );
    let out = drape(&[
        "render",
        "--ply",
        "/nonexistent/scene.ply",
        "--out",
        "/tmp/frame",
    ]);
    assert_one_line_error(&out, "accepted: .png, .npy, .exr");
}

/// The pixel at (x, y) of the test pattern: every sample distinct, and at 16 bits not
/// a multiple of 257, so a reader that drops to 8 bits is caught.
fn sample16(x: u32, y: u32, c: u32) -> u16 {
    ((x * 4099 + y * 1031 + c * 20011 + 13) % 65536) as u16
}

/// 8- and 16-bit PNG in each colour type read as RGB: alpha dropped, grey repeated,
/// 16-bit precision kept.
#[test]
fn png_inputs_load_with_their_pixels() {
    use image::{ImageBuffer, Luma, LumaA, Rgb, Rgba};
    let dir = case_dir("png");
    let (w, h) = (7u32, 5u32);
    let s16 = sample16;
    let s8 = |x, y, c| (s16(x, y, c) >> 8) as u8;
    let p = |n: &str| dir.join(format!("{n}.png"));
    ImageBuffer::from_fn(w, h, |x, y| Luma([s8(x, y, 0)]))
        .save(p("l8"))
        .unwrap();
    ImageBuffer::from_fn(w, h, |x, y| LumaA([s8(x, y, 0), s8(x, y, 3)]))
        .save(p("la8"))
        .unwrap();
    ImageBuffer::from_fn(w, h, |x, y| Rgb([s8(x, y, 0), s8(x, y, 1), s8(x, y, 2)]))
        .save(p("rgb8"))
        .unwrap();
    ImageBuffer::from_fn(w, h, |x, y| {
        Rgba([s8(x, y, 0), s8(x, y, 1), s8(x, y, 2), s8(x, y, 3)])
    })
    .save(p("rgba8"))
    .unwrap();
    ImageBuffer::from_fn(w, h, |x, y| Luma([s16(x, y, 0)]))
        .save(p("l16"))
        .unwrap();
    ImageBuffer::from_fn(w, h, |x, y| LumaA([s16(x, y, 0), s16(x, y, 3)]))
        .save(p("la16"))
        .unwrap();
    ImageBuffer::from_fn(w, h, |x, y| Rgb([s16(x, y, 0), s16(x, y, 1), s16(x, y, 2)]))
        .save(p("rgb16"))
        .unwrap();
    ImageBuffer::from_fn(w, h, |x, y| {
        Rgba([s16(x, y, 0), s16(x, y, 1), s16(x, y, 2), s16(x, y, 3)])
    })
    .save(p("rgba16"))
    .unwrap();
    // (name, 16-bit, grey): channel 3 of the pattern is the alpha, never read back.
    let cases = [
        ("l8", false, true),
        ("la8", false, true),
        ("rgb8", false, false),
        ("rgba8", false, false),
        ("l16", true, true),
        ("la16", true, true),
        ("rgb16", true, false),
        ("rgba16", true, false),
    ];
    for (name, wide, grey) in cases {
        let image = image_io::read_rgb(&p(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!((image.width, image.height), (w, h), "{name}");
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    let source = if grey { 0 } else { c };
                    let expected = if wide {
                        f32::from(s16(x, y, source)) / 65535.0
                    } else {
                        f32::from(s8(x, y, source)) / 255.0
                    };
                    let got = image.rgb[(3 * (y * w + x) + c) as usize];
                    // f32 rounding of v / 65535 is 6e-8; an 8-bit detour would be 2e-3 off.
                    assert!(
                        (got - expected).abs() <= 1e-6,
                        "{name} ({x}, {y}) channel {c}: {got}, expected {expected}"
                    );
                }
            }
        }
    }
    // And the binary takes them (the 16-bit and the two with alpha are the new ones).
    for name in ["rgb16", "la8", "rgba8"] {
        let target = dir.join(format!("{name}.png"));
        let out = drape(&[
            "fit",
            "--target",
            s(&target),
            "--n",
            "10",
            "--iters",
            "1",
            "--out",
            s(&dir.join(format!("{name}.ply"))),
        ]);
        assert!(
            out.status.success(),
            "fit on {name}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(
            String::from_utf8_lossy(&out.stdout).contains("(7x5)"),
            "{}",
            String::from_utf8_lossy(&out.stdout)
        );
    }
}

/// JPEGs made and decoded by Pillow (libjpeg): RGB (4:4:4), grey, CMYK (Adobe, inverted
/// as Pillow writes it), RGB with EXIF orientation 6, progressive RGB, and RGB noise;
/// `<name>.rgb` holds Pillow's RGB decode, after `exif_transpose`.
const MAKE_JPEGS: &str = r#"
import sys
import numpy as np
from PIL import Image, ImageOps
d = sys.argv[1]
w, h = 32, 24
palette = [(230, 30, 20), (20, 200, 40), (30, 40, 220), (250, 250, 250), (0, 0, 0), (128, 128, 128), (240, 220, 10), (10, 220, 230)]
rgb = np.zeros((h, w, 3), np.uint8)
for by in range(h // 8):
    for bx in range(w // 8):
        rgb[by*8:by*8+8, bx*8:bx*8+8] = palette[(by * 4 + bx) % len(palette)]
im = Image.fromarray(rgb)
im.save(f"{d}/rgb.jpg", quality=95, subsampling=0)
im.convert("L").save(f"{d}/grey.jpg", quality=95)
cmyk_palette = [(255, 0, 0, 0), (0, 255, 0, 0), (0, 0, 255, 0), (0, 0, 0, 0), (0, 0, 0, 255), (0, 0, 0, 128), (60, 200, 0, 30), (0, 120, 240, 60)]
cmyk = Image.new("CMYK", (w, h))
for by in range(h // 8):
    for bx in range(w // 8):
        cmyk.paste(cmyk_palette[(by * 4 + bx) % len(cmyk_palette)], (bx*8, by*8, bx*8+8, by*8+8))
cmyk.save(f"{d}/cmyk.jpg", quality=95)
exif = Image.Exif()
exif[0x0112] = 6
im.save(f"{d}/rotated.jpg", quality=95, subsampling=0, exif=exif)
im.save(f"{d}/progressive.jpg", quality=95, subsampling=0, progressive=True)
# Noise, so that the entropy-coded data is most of the file (for the truncation tests).
noise = np.random.default_rng(0).integers(0, 256, (96, 128, 3), dtype=np.uint8)
Image.fromarray(noise).save(f"{d}/noise.jpg", quality=90)
for name in ["rgb", "grey", "cmyk", "rotated", "progressive", "noise"]:
    ref = ImageOps.exif_transpose(Image.open(f"{d}/{name}.jpg")).convert("RGB")
    print(name, Image.open(f"{d}/{name}.jpg").mode, ref.size[0], ref.size[1])
    np.asarray(ref).tofile(f"{d}/{name}.rgb")
"#;

#[test]
fn jpeg_inputs_load_like_libjpeg_decodes_them() {
    let dir = case_dir("jpeg");
    let printed = run_python(MAKE_JPEGS, &[s(&dir)]);
    for line in printed.lines() {
        let f: Vec<&str> = line.split_whitespace().collect();
        let (name, mode, w, h) = (
            f[0],
            f[1],
            f[2].parse::<u32>().unwrap(),
            f[3].parse::<u32>().unwrap(),
        );
        let path = dir.join(format!("{name}.jpg"));
        let reference = std::fs::read(dir.join(format!("{name}.rgb"))).unwrap();
        let image = image_io::read_rgb(&path).unwrap_or_else(|e| panic!("{name} ({mode}): {e}"));
        assert_eq!(
            (image.width, image.height),
            (w, h),
            "{name}: rotated by its EXIF orientation"
        );
        // Two decoders of one file may differ in IDCT rounding and chroma upsampling
        // (noise is 4:2:0). Measured against Pillow 13: 0 steps of 255 on the flat 8x8
        // blocks (CMYK included), 4 on noise; allowed 1 and 6. A wrong channel order,
        // CMYK inversion or orientation is off by 100+.
        let worst = image
            .rgb
            .iter()
            .zip(&reference)
            .map(|(&v, &r)| (v * 255.0 - f32::from(r)).abs())
            .fold(0.0, f32::max);
        let tolerance = if name == "noise" { 6.0 } else { 1.0 };
        assert!(
            worst <= tolerance,
            "{name} ({mode}): {worst} 8-bit steps from Pillow's decode"
        );
    }
    // Bytes after the end-of-image marker (camera trailers) are not truncation.
    let mut trailer = std::fs::read(dir.join("rgb.jpg")).unwrap();
    trailer.extend(b"\xFF\xD8 trailing bytes");
    drape_io::write(dir.join("trailer.jpg"), &trailer).unwrap();
    image_io::read_rgb(&dir.join("trailer.jpg")).unwrap();
    // The binary takes a JPEG.
    let out = drape(&[
        "fit",
        "--target",
        s(&dir.join("rgb.jpg")),
        "--n",
        "10",
        "--iters",
        "1",
        "--out",
        s(&dir.join("rgb.ply")),
    ]);
    assert!(
        out.status.success(),
        "fit on a JPEG: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("(32x24)"),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
}

#[test]
fn truncated_or_foreign_files_fail_in_one_line_naming_them() {
    let dir = case_dir("truncated-jpeg");
    run_python(MAKE_JPEGS, &[s(&dir)]);
    // The decoder itself reports a file cut inside its headers, but fills one cut in
    // the entropy-coded data with grey: in half, and short of only its last 2 bytes
    // (the end-of-image marker), and a progressive one (several scans) in half.
    for (name, source, keep) in [
        ("half", "noise.jpg", 0.5),
        ("no-eoi", "noise.jpg", 1.0),
        ("progressive-half", "progressive.jpg", 0.5),
        ("headers", "rgb.jpg", 0.05),
    ] {
        let bytes = std::fs::read(dir.join(source)).unwrap();
        let cut = if keep == 1.0 {
            bytes.len() - 2
        } else {
            (bytes.len() as f64 * keep) as usize
        };
        let target = dir.join(format!("{name}.jpg"));
        drape_io::write(&target, &bytes[..cut]).unwrap();
        let out = drape(&[
            "fit",
            "--target",
            s(&target),
            "--n",
            "10",
            "--iters",
            "1",
            "--out",
            s(&dir.join("x.ply")),
        ]);
        assert_one_line_error(&out, &format!("{}: truncated", target.display()));
    }
    let target = dir.join("corrupt.png");
    drape_io::write(&target, b"\x89PNG\r\n\x1a\nhello").unwrap();
    let out = drape(&[
        "fit",
        "--target",
        s(&target),
        "--out",
        s(&dir.join("x.ply")),
    ]);
    assert_one_line_error(
        &out,
        &format!("{}: truncated or corrupt image", target.display()),
    );
    // Told apart by content, not by the name.
    let target = dir.join("text.png");
    drape_io::write(&target, b"hello").unwrap();
    let out = drape(&[
        "fit",
        "--target",
        s(&target),
        "--out",
        s(&dir.join("x.ply")),
    ]);
    assert_one_line_error(&out, &format!("{}: not a PNG or JPEG", target.display()));
}
