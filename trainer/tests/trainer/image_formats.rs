//! The dataset image reader against files other tools write (Pillow, OpenCV): 16-bit,
//! RGBA, grey + alpha and CMYK images load with the right values, a 16-bit mask reads
//! by each rule, and a truncated JPEG fails in one line naming the file.

use drape_tests::reference_python::{case_dir, get, run};
use drape_trainer::dataset::image::{read_mask, read_rgb, MaskRule};

fn max_diff(a: &[f32], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (f64::from(*x) - y).abs())
        .fold(0.0, f64::max)
}

#[test]
fn images_written_by_other_tools_load_with_their_values() {
    let dir = case_dir("image_formats", "fixtures");
    run("image_fixtures.py", std::slice::from_ref(&dir));
    for (file, expected, tol, why) in [
        // f32 holds v/65535 to ~3e-8: a 16-bit image truncated to 8 bits would be off by up to 1/255.
        ("rgb16.png", "rgb16_expected", 1e-6, "16 bits kept"),
        ("rgba.png", "rgba_expected", 1e-6, "exact 8-bit values"),
        (
            "grey_alpha.png",
            "grey_alpha_expected",
            1e-6,
            "exact 8-bit values",
        ),
        // Two JPEG decoders (libjpeg's and zune-jpeg) may round the IDCT and the colour
        // conversion differently: two 8-bit steps.
        (
            "rgb.jpg",
            "rgb_jpg_expected",
            2.0 / 255.0 + 1e-6,
            "IDCT rounding",
        ),
        (
            "cmyk.jpg",
            "cmyk_expected",
            2.0 / 255.0 + 1e-6,
            "IDCT rounding",
        ),
    ] {
        let img = read_rgb(&dir.join(file)).unwrap_or_else(|e| panic!("{file}: {e}"));
        assert_eq!((img.width, img.height), (16, 12), "{file}");
        let d = max_diff(&img.rgb, &get(&dir, expected));
        eprintln!("{file}: max difference {d:.2e} ({why})");
        assert!(d <= tol, "{file}: max difference {d} > {tol} ({why})");
    }
    for (rule, expected) in [
        (MaskRule::NonZero, "mask16_nonzero"),
        (MaskRule::AtLeastHalf, "mask16_half"),
    ] {
        let (w, h, m) = read_mask(&dir.join("mask16.png"), rule).unwrap();
        assert_eq!((w, h), (16, 12));
        let want: Vec<bool> = get(&dir, expected).iter().map(|&v| v > 0.5).collect();
        assert_eq!(m, want, "{rule:?}");
    }
    let err = read_rgb(&dir.join("truncated.jpg"))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("truncated.jpg") && err.lines().count() == 1,
        "{err}"
    );
}
