//! Lens distortion (`drape_trainer::dataset::distortion`) against OpenCV
//! 4.12 (`tests/python/opencv_reference.py`, in the environment `scripts/torch-env.sh`
//! makes): projected points against `cv2.projectPoints`, the undistortion map against
//! `cv2.initUndistortRectifyMap`, undistorted images and masks against
//! `cv2.undistort`; COLMAP's distorting camera models parsed; distortion then
//! undistortion returning the image.
//!
//! Pixel convention: drape (and COLMAP) put pixel centres at +0.5, OpenCV at integers,
//! so OpenCV is given drape's K with the principal point moved by -0.5 for images; a
//! projection is the same formula in both and gets K as it is.
//!
//! Lenses: ZJU-MoCap's cameras are barrel (k1 ≈ -0.3) with tangential terms near 1e-3;
//! the cameras here span r ≈ 0.7 in normalized coordinates, as ZJU's 1024² images at
//! f ≈ 1000 do. One lens has k3 ≠ 0 and one is pincushion (k1 > 0), so that some
//! pinhole pixels see outside the distorted image.
//!
//! Without the environment these tests fail (they are not skipped): set
//! `DRAPE_TORCH_PYTHON` to a Python with opencv-python-headless, or run
//! `scripts/torch-env.sh`.
// Tolerance checks are written `!(err < tol)` so that NaN fails them (the workspace
// allows the negated comparison for this), and maxima go through `worse`, which keeps a
// NaN (`f64::max` would drop it).

use std::f64::consts::TAU;
use std::path::Path;

use drape_tests::num::uniform;
use drape_tests::reference_python::{case_dir, get, put, run};
use drape_trainer::camera::Camera;
use drape_trainer::dataset::colmap::{ColmapCamera, ColmapImage, ColmapModel};
use drape_trainer::dataset::distortion::{
    distort_mask, distort_rgb, project, Distortion, Undistorter,
};
use glam::DVec3;

const ZJU_LIKE: Distortion = Distortion {
    k1: -0.3,
    k2: 0.1,
    p1: 1e-3,
    p2: -5e-4,
    k3: 0.0,
};
const WITH_K3: Distortion = Distortion {
    k1: -0.28,
    k2: 0.14,
    p1: -7e-4,
    p2: 9e-4,
    k3: -0.05,
};
const PINCUSHION: Distortion = Distortion {
    k1: 0.15,
    k2: -0.05,
    p1: -8e-4,
    p2: 1.2e-3,
    k3: 0.03,
};
const LENSES: [(&str, Distortion); 3] = [
    ("zju_like", ZJU_LIKE),
    ("with_k3", WITH_K3),
    ("pincushion", PINCUSHION),
];

/// A small camera with unequal focal lengths and an off-centre principal point (so a
/// swapped axis shows), corners at r ≈ 0.7 like ZJU's. The pose does not matter here.
fn small_camera() -> Camera {
    Camera {
        fx: 90.0,
        fy: 86.0,
        cx: 47.3,
        cy: 41.1,
        width: 96,
        height: 80,
        rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        translation: DVec3::ZERO,
        near: Camera::NEAR,
    }
}

/// OpenCV's K for `camera`'s images: principal point moved by -0.5 (see the header).
fn opencv_k_for_images(c: &Camera) -> [[f64; 3]; 3] {
    [
        [c.fx, 0.0, c.cx - 0.5],
        [0.0, c.fy, c.cy - 0.5],
        [0.0, 0.0, 1.0],
    ]
}

/// A smooth random 8-bit image as floats u8/255: per channel a mean plus two plane
/// waves of random direction and phase, wavelengths 40 to 60 px, amplitudes 50 and 25
/// levels. Its gradient is at most about 15 levels per pixel, which bounds what
/// OpenCV's 1/32-pixel map quantization can change (see `undistorted_images_match`).
fn smooth_image(w: u32, h: u32, seed: u64) -> Vec<f32> {
    let r = uniform(3 * 2 * 3, 0.0, 1.0, seed);
    let mut out = Vec::with_capacity((w * h * 3) as usize);
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                let mut v = 100.0 + 40.0 * r[c * 6];
                for (k, amplitude) in [(0, 50.0), (1, 25.0)] {
                    let q = &r[c * 6 + 3 * k..c * 6 + 3 * k + 3];
                    let (angle, wavelength, phase) = (TAU * q[0], 40.0 + 20.0 * q[1], TAU * q[2]);
                    let along = f64::from(x) * angle.cos() + f64::from(y) * angle.sin();
                    v += amplitude * (TAU * along / wavelength + phase).sin();
                }
                out.push((v.round().clamp(0.0, 255.0) / 255.0) as f32);
            }
        }
    }
    out
}

/// A person-like mask: an ellipse and a rectangle, hard edges.
fn test_mask(w: u32, h: u32) -> Vec<bool> {
    let mut out = Vec::with_capacity((w * h) as usize);
    for y in 0..h {
        for x in 0..w {
            let (u, v) = (f64::from(x) + 0.5, f64::from(y) + 0.5);
            let ellipse = ((u - 45.0) / 28.0).powi(2) + ((v - 36.0) / 22.0).powi(2) <= 1.0;
            let rect = (10.0..31.0).contains(&u) && (50.0..73.0).contains(&v);
            out.push(ellipse || rect);
        }
    }
    out
}

/// The case directory of one lens with OpenCV's outputs for `small_camera`,
/// `smooth_image` and `test_mask`; one per calling test (`test`), since tests run in
/// parallel and a case directory is emptied when it is made.
fn opencv_image_case(test: &str, name: &str, d: Distortion) -> std::path::PathBuf {
    let cam = small_camera();
    let (w, h) = (cam.width as usize, cam.height as usize);
    let dir = case_dir("opencv-distortion", &format!("{test}_image_{name}"));
    let img = smooth_image(cam.width, cam.height, 7);
    put(
        &dir,
        "image",
        &[h, w, 3],
        &img.iter()
            .map(|&v| (f64::from(v) * 255.0).round())
            .collect::<Vec<_>>(),
    );
    put(
        &dir,
        "mask",
        &[h, w],
        &test_mask(cam.width, cam.height)
            .iter()
            .map(|&m| f64::from(u8::from(m)))
            .collect::<Vec<_>>(),
    );
    write_case(
        &dir,
        serde_json::json!({ "kind": "image", "K": opencv_k_for_images(&cam), "D": d.to_opencv() }),
    );
    run("opencv_reference.py", std::slice::from_ref(&dir));
    dir
}

/// The larger of a running maximum and a new error, NaN if either is.
fn worse(max: f64, e: f64) -> f64 {
    if e.is_nan() || e > max {
        e
    } else {
        max
    }
}

fn write_case(dir: &Path, case: serde_json::Value) {
    drape_io::write(dir.join("case.json"), case.to_string()).expect("case.json");
}

#[test]
fn projected_points_match_opencv() {
    // ZJU-like: 1024², f ≈ 1000, the principal point off centre.
    let mut cam = Camera::look_at(
        DVec3::new(0.7, -1.4, 3.3),
        DVec3::new(0.1, -0.9, -0.2),
        DVec3::NEG_Y,
        1000.0,
        1024,
        1024,
    );
    (cam.fy, cam.cx, cam.cy) = (1004.0, 511.2, 515.7);
    // Points spread over the image (normalized |x|, |y| < 0.55, r < 0.78) at depths 1.5
    // to 6, placed in camera space and taken to the world.
    let n = 400;
    let (xs, ys, zs) = (
        uniform(n, -0.55, 0.55, 11),
        uniform(n, -0.55, 0.55, 12),
        uniform(n, 1.5, 6.0, 13),
    );
    let r = cam.rotation;
    let world: Vec<[f64; 3]> = (0..n)
        .map(|i| {
            let c = [
                xs[i] * zs[i] - cam.translation[0],
                ys[i] * zs[i] - cam.translation[1],
                zs[i] - cam.translation[2],
            ];
            std::array::from_fn(|a| (0..3).map(|k| r[k][a] * c[k]).sum())
        })
        .collect();
    let mut fails = Vec::new();
    for (name, d) in [("zju_like", ZJU_LIKE), ("with_k3", WITH_K3)] {
        let dir = case_dir("opencv-distortion", &format!("project_{name}"));
        put(
            &dir,
            "points",
            &[n, 3],
            &world.iter().flatten().copied().collect::<Vec<_>>(),
        );
        let k = [
            [cam.fx, 0.0, cam.cx],
            [0.0, cam.fy, cam.cy],
            [0.0, 0.0, 1.0],
        ];
        write_case(
            &dir,
            serde_json::json!({ "kind": "project", "K": k, "D": d.to_opencv(), "R": cam.rotation, "t": cam.translation.to_array() }),
        );
        run("opencv_reference.py", std::slice::from_ref(&dir));
        let (theirs, their_inverse) = (get(&dir, "projected"), get(&dir, "undistorted"));
        let (mut worst, mut worst_inverse, mut worst_truth, mut shift) =
            (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        for (i, &p) in world.iter().enumerate() {
            let p = DVec3::from_array(p);
            let ours = project(&cam, &d, p);
            worst = worse(
                worse(worst, (ours[0] - theirs[2 * i]).abs()),
                (ours[1] - theirs[2 * i + 1]).abs(),
            );
            let pinhole = cam.project(p).expect("in front");
            shift = worse(
                shift,
                ((ours[0] - pinhole[0]).powi(2) + (ours[1] - pinhole[1]).powi(2)).sqrt(),
            );
            let inv =
                d.undistort_normalized((ours[0] - cam.cx) / cam.fx, (ours[1] - cam.cy) / cam.fy);
            worst_inverse = worse(
                worse(worst_inverse, (inv[0] - their_inverse[2 * i]).abs()),
                (inv[1] - their_inverse[2 * i + 1]).abs(),
            );
            worst_truth = worse(
                worse(worst_truth, (inv[0] - xs[i]).abs()),
                (inv[1] - ys[i]).abs(),
            );
        }
        println!("{name}: projection |ours - cv2.projectPoints| <= {worst:.2e} px (the lens moves points up to {shift:.1} px); undistort_normalized vs cv2.undistortPointsIter {worst_inverse:.2e}, vs the true x/z {worst_truth:.2e}");
        // The same f64 formula on both sides; OpenCV gets R through Rodrigues (a round
        // trip of ~1e-16 rad, ~1e-13 px at f = 1000) and orders the sums differently:
        // differences near 1e-12 px, so 1e-6 px is a wide margin that still catches
        // any wrong term (p1 = 1e-3 alone moves corners by ~0.5 px).
        if !(worst < 1e-6) {
            fails.push(format!(
                "{name}: projected points differ from cv2.projectPoints by {worst:e} px"
            ));
        }
        // The lens must matter, or the comparison proves nothing.
        if !(shift > 20.0) {
            fails.push(format!("{name}: the lens moves points by only {shift} px"));
        }
        // Both inverses converge (ours to a residual of 1e-14, OpenCV's to 200 steps or
        // 1e-15): agreement to 1e-9 normalized is 1e-6 px.
        if !(worst_inverse < 1e-9 && worst_truth < 1e-9) {
            fails.push(format!("{name}: undistort_normalized is {worst_inverse:e} from cv2.undistortPointsIter and {worst_truth:e} from the truth"));
        }
    }
    assert!(fails.is_empty(), "{}", fails.join("\n"));
}

#[test]
fn undistortion_map_and_images_match_opencv() {
    let cam = small_camera();
    let (w, h) = (cam.width as usize, cam.height as usize);
    let img = smooth_image(cam.width, cam.height, 7);
    let mut fails = Vec::new();
    for (name, d) in LENSES {
        let dir = opencv_image_case("maps", name, d);
        let u = Undistorter::new(&cam, d);
        assert_eq!((u.width(), u.height()), (cam.width, cam.height));

        // The map: both compute in f64 and store f32 (OpenCV's CV_32FC1): half an f32
        // ulp at 100 px is 4e-6 px; 1e-4 px.
        let (map_x, map_y) = (get(&dir, "map_x"), get(&dir, "map_y"));
        let mut worst_map = 0.0f64;
        for y in 0..h {
            for x in 0..w {
                let s = u.source(x as u32, y as u32);
                worst_map = worse(
                    worse(worst_map, (f64::from(s[0]) - map_x[y * w + x]).abs()),
                    (f64::from(s[1]) - map_y[y * w + x]).abs(),
                );
            }
        }

        // The image. cv2.undistort remaps with a fixed-point map (positions rounded to
        // 1/32 px, at most sqrt(2)/64 px off: with the image's gradient of at most ~15
        // levels per pixel, 0.35 of a level) and rounds to 8 bits (0.5 of a level);
        // ours samples at the exact f32 position and stays in float. So the two agree
        // to one 8-bit step, not exactly (measured 0.65). Compared where the source lies
        // at least 1 px inside the image: nearer the border both blend in the zeros of
        // BORDER_CONSTANT, a step of ~130 levels that the 1/32-px quantization turns
        // into differences of a few levels (the maximum over all pixels, printed: 2.6).
        let ours = u.rgb(&img);
        let theirs = get(&dir, "undistorted");
        let (mut worst_valid, mut worst_all, mut valid) = (0.0f64, 0.0f64, 0usize);
        let mut black = 0usize;
        for y in 0..h {
            for x in 0..w {
                let s = u.source(x as u32, y as u32);
                let inside =
                    s[0] >= 1.0 && s[1] >= 1.0 && s[0] <= w as f32 - 2.0 && s[1] <= h as f32 - 2.0;
                valid += usize::from(inside);
                black += usize::from(
                    !(s[0] > -1.0 && s[1] > -1.0 && s[0] < w as f32 && s[1] < h as f32),
                );
                for c in 0..3 {
                    let i = (y * w + x) * 3 + c;
                    let e = (f64::from(ours[i]) * 255.0 - theirs[i]).abs();
                    worst_all = worse(worst_all, e);
                    if inside {
                        worst_valid = worse(worst_valid, e);
                    }
                }
            }
        }
        println!("{name}: map |ours - cv2| <= {worst_map:.2e} px; image <= {worst_valid:.3} levels on {valid} valid pixels, <= {worst_all:.3} on all {} ({black} see nothing)", w * h);
        if !(worst_map < 1e-4) {
            fails.push(format!("{name}: the undistortion map differs from cv2.initUndistortRectifyMap by {worst_map:e} px"));
        }
        if !(worst_valid <= 1.0) {
            fails.push(format!("{name}: the undistorted image differs from cv2.undistort by {worst_valid} levels of 255"));
        }
        if valid <= w * h / 2 {
            fails.push(format!(
                "{name}: only {valid} of {} pixels are compared",
                w * h
            ));
        }
    }
    assert!(fails.is_empty(), "{}", fails.join("\n"));
}

/// Pixels of a mask with a neighbour (4-connected) of the other value.
fn boundary_pixels(mask: &[bool], w: usize, h: usize) -> usize {
    let at = |x: usize, y: usize| mask[y * w + x];
    (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .filter(|&(x, y)| {
            (x > 0 && at(x - 1, y) != at(x, y))
                || (y > 0 && at(x, y - 1) != at(x, y))
                || (x + 1 < w && at(x + 1, y) != at(x, y))
                || (y + 1 < h && at(x, y + 1) != at(x, y))
        })
        .count()
}

#[test]
fn undistorted_masks_match_opencv() {
    let cam = small_camera();
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut fails = Vec::new();
    for (name, d) in LENSES {
        let dir = opencv_image_case("masks", name, d);
        let ours = Undistorter::new(&cam, d).mask(&test_mask(cam.width, cam.height));
        // Our rule (bilinear of 0/1, then >= 0.5) on OpenCV's side: cv2.undistort of the
        // 0/255 mask, then >= 128 (255 / 2 = 127.5 rounds up to 128).
        let theirs: Vec<bool> = get(&dir, "mask_undistorted")
            .iter()
            .map(|&v| v >= 128.0)
            .collect();
        let differ = ours.iter().zip(&theirs).filter(|(a, b)| a != b).count();
        let edge = boundary_pixels(&theirs, w, h);
        let inside = theirs.iter().filter(|&&m| m).count();
        println!("{name}: {differ} of {} pixels differ from cv2 (the mask has {inside} pixels, {edge} on its edge)", w * h);
        // They can differ only where the interpolated coverage is within OpenCV's
        // position quantization (sqrt(2)/64 px, up to 0.022 of coverage at a hard edge)
        // and 8-bit rounding of one half: a few edge pixels. 2% of the edge.
        if differ * 50 > edge {
            fails.push(format!("{name}: {differ} mask pixels differ from cv2.undistort's, more than 2% of the {edge} edge pixels"));
        }
        if inside <= w * h / 5 {
            fails.push(format!(
                "{name}: the undistorted mask has only {inside} pixels"
            ));
        }
    }
    assert!(fails.is_empty(), "{}", fails.join("\n"));
}

#[test]
fn colmap_distorting_models_parse() {
    let dir = case_dir("opencv-distortion", "colmap_models");
    let cameras = "# Camera list\n\
        1 SIMPLE_RADIAL 640 480 500.5 320.25 240.75 -0.0625\n\
        2 RADIAL 640 480 510 321 239 -0.125 0.03125\n\
        3 OPENCV 800 600 700 705 401.5 299.5 -0.3 0.1 0.001 -0.0005\n\
        4 PINHOLE 800 600 700 705 401.5 299.5\n\
        5 SIMPLE_PINHOLE 800 600 700 401.5 299.5\n\
        6 FULL_OPENCV 800 600 700 705 401.5 299.5 -0.3 0.1 0.001 -0.0005 0.02 0 0 0\n\
        7 OPENCV_FISHEYE 800 600 700 705 401.5 299.5 0.1 0.01 0 0\n\
        8 FULL_OPENCV 800 600 700 705 401.5 299.5 -0.3 0.1 0.001 -0.0005 0.02 0 0.5 0\n\
        9 OPENCV 800 600 700 705 401.5 299.5 -0.3 0.1 0.001\n";
    let images: String = (1..=9)
        .map(|i| format!("{i} 1 0 0 0 0.5 -0.25 3 {i} img{i}.png\n\n"))
        .collect();
    drape_io::write(dir.join("cameras.txt"), cameras).expect("cameras.txt");
    drape_io::write(dir.join("images.txt"), images).expect("images.txt");
    drape_io::write(dir.join("points3D.txt"), "").expect("points3D.txt");
    let model = ColmapModel::read_text(&dir).expect("read the model");
    let got = |i: u32| model.images[&i].camera_and_distortion(&model.cameras[&i]);
    let none = Distortion::NONE;
    let zju = Distortion {
        k1: -0.3,
        k2: 0.1,
        p1: 0.001,
        p2: -0.0005,
        k3: 0.0,
    };
    for (i, k, d, size) in [
        (
            1,
            [500.5, 500.5, 320.25, 240.75],
            Distortion {
                k1: -0.0625,
                ..none
            },
            (640, 480),
        ),
        (
            2,
            [510.0, 510.0, 321.0, 239.0],
            Distortion {
                k1: -0.125,
                k2: 0.03125,
                ..none
            },
            (640, 480),
        ),
        (3, [700.0, 705.0, 401.5, 299.5], zju, (800, 600)),
        (4, [700.0, 705.0, 401.5, 299.5], none, (800, 600)),
        (5, [700.0, 700.0, 401.5, 299.5], none, (800, 600)),
        (
            6,
            [700.0, 705.0, 401.5, 299.5],
            Distortion { k3: 0.02, ..zju },
            (800, 600),
        ),
    ] {
        let (cam, dist) = got(i).unwrap_or_else(|e| panic!("camera {i}: {e}"));
        assert_eq!(
            [cam.fx, cam.fy, cam.cx, cam.cy],
            k,
            "camera {i} ({}) intrinsics",
            model.cameras[&i].model
        );
        assert_eq!(
            dist, d,
            "camera {i} ({}) distortion",
            model.cameras[&i].model
        );
        assert_eq!((cam.width, cam.height), size, "camera {i} size");
        assert_eq!(
            (cam.translation, cam.rotation[0]),
            (DVec3::new(0.5, -0.25, 3.0), [1.0, 0.0, 0.0]),
            "camera {i} pose"
        );
    }
    let fisheye = got(7)
        .expect_err("OPENCV_FISHEYE is not undistorted")
        .to_string();
    assert!(
        fisheye.starts_with(
            "cameras.txt: camera 7 has model OPENCV_FISHEYE, which drape does not undistort"
        ),
        "{fisheye}"
    );
    assert!(!fisheye.contains('\n'), "one line: {fisheye}");
    let rational = got(8)
        .expect_err("k5 = 0.5 is the rational model")
        .to_string();
    assert!(
        rational.contains("camera 8") && rational.contains("k5 = 0.5"),
        "{rational}"
    );
    let short = got(9).expect_err("OPENCV with 7 parameters").to_string();
    assert!(
        short.contains("camera 9 (OPENCV) has 7 PARAMS, expected 8 (fx fy cx cy k1 k2 p1 p2)"),
        "{short}"
    );

    // The writer: a fixture's camera with a lens reads back as it was written.
    let written = case_dir("opencv-distortion", "colmap_written");
    let base = small_camera();
    let mut out = ColmapModel::default();
    for (i, d) in [(1, ZJU_LIKE), (2, WITH_K3), (3, none)] {
        out.cameras
            .insert(i, ColmapCamera::from_camera_and_distortion(i, &base, &d));
        out.images
            .insert(i, ColmapImage::from_camera(i, i, format!("{i}.png"), &base));
    }
    out.write_text(&written).expect("write");
    let back = ColmapModel::read_text(&written).expect("read back");
    for (i, d, model) in [
        (1, ZJU_LIKE, "OPENCV"),
        (2, WITH_K3, "FULL_OPENCV"),
        (3, none, "PINHOLE"),
    ] {
        assert_eq!(back.cameras[&i].model, model);
        let (cam, dist) = back.images[&i]
            .camera_and_distortion(&back.cameras[&i])
            .expect("written camera");
        assert_eq!(
            (dist, [cam.fx, cam.fy, cam.cx, cam.cy]),
            (d, [base.fx, base.fy, base.cx, base.cy]),
            "camera {i}"
        );
    }
}

#[test]
fn distorting_then_undistorting_returns_the_image() {
    let cam = small_camera();
    let (w, h) = (cam.width as usize, cam.height as usize);
    let img = smooth_image(cam.width, cam.height, 9);
    let mask = test_mask(cam.width, cam.height);
    let edge = boundary_pixels(&mask, w, h);
    let mut fails = Vec::new();
    for (name, d) in LENSES {
        let u = Undistorter::new(&cam, d);
        let back = u.rgb(&distort_rgb(&cam, d, &img));
        let mask_back = u.mask(&distort_mask(&cam, d, &mask));
        // Interior: 3 px from the borders, and the source at least 2 px inside, so that
        // neither resampling reaches outside an image.
        let (mut worst, mut count) = (0.0f64, 0usize);
        for y in 3..h - 3 {
            for x in 3..w - 3 {
                let s = u.source(x as u32, y as u32);
                if !(s[0] >= 2.0 && s[1] >= 2.0 && s[0] <= w as f32 - 3.0 && s[1] <= h as f32 - 3.0)
                {
                    continue;
                }
                count += 1;
                for c in 0..3 {
                    let i = (y * w + x) * 3 + c;
                    worst = worse(worst, (f64::from(back[i]) - f64::from(img[i])).abs());
                }
            }
        }
        let differ = mask_back.iter().zip(&mask).filter(|(a, b)| a != b).count();
        println!("{name}: round trip <= {worst:.4} on {count} interior pixels; mask {differ} pixels differ ({edge} on the edge)");
        // Two bilinear resamplings of a smooth image, each off by at most 1/8 of
        // |f_xx| + |f_yy|: (75/255)(2π/40)²/8 ≈ 9e-4 on the pinhole side, up to twice
        // that on the distorted side where the barrel lens compresses the corners to
        // 0.7×, and they do not cancel (measured 3.6e-3). 0.01; a sample half a pixel
        // off would be |∇f|/2 ≈ 0.03.
        if !(worst < 0.01) {
            fails.push(format!(
                "{name}: distort_rgb then Undistorter::rgb is {worst} from the image"
            ));
        }
        if count <= w * h / 2 {
            fails.push(format!("{name}: only {count} interior pixels"));
        }
        // Each threshold can move the edge by a fraction of a pixel (measured 11 of 414
        // edge pixels): a twentieth of the edge.
        if differ * 20 > edge {
            fails.push(format!(
                "{name}: the mask's round trip changes {differ} pixels ({edge} on the edge)"
            ));
        }
    }
    assert!(fails.is_empty(), "{}", fails.join("\n"));
}
