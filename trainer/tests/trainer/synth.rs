//! The synthetic generator and the NeuMan / ZJU-MoCap loaders on its output and on its
//! rewrites into each published layout variant (with lens distortion, JPEG frames,
//! missing and inverted masks), and `drape inspect`'s findings on them.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use drape_trainer::body::kinematics::pose_body;
use drape_trainer::body::procedural::{default_body, BodyOptions};
use drape_trainer::body::SmplModel;
use drape_trainer::dataset::error::DatasetError;
use drape_trainer::dataset::inspect::inspect;
use drape_trainer::dataset::layout::{detect, Variant};
use drape_trainer::dataset::loader::{
    load_neuman, load_zju, BodyParams, DatasetFrame, NeumanSplit,
};
use drape_trainer::dataset::raster::{render, Drawable};
use drape_trainer::dataset::split::Split;
use drape_trainer::dataset::synth::{
    generate, handheld_camera, posed_from_zju, ring_camera, SynthOptions,
};
use drape_trainer::dataset::variants::{write_neuman_variant, write_zju_variant};
use drape_trainer::garment::load_obj;
use drape_trainer::motion::{procedural, MotionKind};
use glam::DVec3;

const OPTIONS: SynthOptions = SynthOptions {
    width: 64,
    height: 64,
    frames: 6,
    cameras: 2,
    motion: MotionKind::Walk,
    seed: 3,
    samples: 1,
    garment: drape_trainer::garment::GarmentFit::Tight,
};

fn base() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = std::env::temp_dir()
            .join(format!("drape-synth-tests-{}", std::process::id()))
            .join("base");
        generate(&dir, &OPTIONS, &mut |_, _, _| {}).expect("synth");
        dir
    })
}

fn model() -> &'static SmplModel {
    static M: OnceLock<SmplModel> = OnceLock::new();
    M.get_or_init(|| default_body(&BodyOptions::default()))
}

/// A private copy of the generated data to damage.
fn copy(name: &str) -> PathBuf {
    fn rec(from: &Path, to: &Path) {
        std::fs::create_dir_all(to).unwrap();
        for e in std::fs::read_dir(from).unwrap() {
            let e = e.unwrap();
            let (src, dst) = (e.path(), to.join(e.file_name()));
            if src.is_dir() {
                rec(&src, &dst)
            } else {
                std::fs::copy(&src, &dst).unwrap();
            }
        }
    }
    let dst = base().parent().unwrap().join(name);
    let _ = std::fs::remove_dir_all(&dst);
    rec(base(), &dst);
    dst
}

#[test]
fn loaders_read_every_frame_and_split() {
    let n = load_neuman(&base().join("neuman"), NeumanSplit::EveryFifth).expect("neuman");
    assert_eq!(n.len(), OPTIONS.frames);
    assert_eq!(
        n.iter().filter(|f| f.split == Split::Test).count(),
        1,
        "frame 2 of 6"
    );
    assert!(n
        .iter()
        .all(|f| f.garment_masks.is_some() && f.rgb.len() == 64 * 64 * 3));
    let z = load_zju(&base().join("zju"), 0).expect("zju");
    assert_eq!(z.len(), OPTIONS.frames * OPTIONS.cameras);
    assert_eq!(
        z.iter().filter(|f| f.split == Split::Train).count(),
        OPTIONS.frames
    );
}

#[test]
fn loaded_cameras_project_like_the_generator() {
    let motion = procedural(OPTIONS.motion, OPTIONS.frames, 30.0, 1.0);
    let points: Vec<DVec3> = model()
        .v_template
        .iter()
        .step_by(500)
        .map(|v| DVec3::new(v[0], v[1], v[2] + 0.3))
        .collect();
    let close = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).abs().max((a[1] - b[1]).abs());
    for f in load_neuman(&base().join("neuman"), NeumanSplit::EveryFifth).unwrap() {
        let t = motion.translations[f.frame];
        let truth = handheld_camera(
            f.frame,
            OPTIONS.frames,
            DVec3::new(t[0], t[1] + 1.0, t[2]),
            OPTIONS.seed,
            64,
            64,
        );
        for p in &points {
            let (a, b) = (f.camera.project(*p).unwrap(), truth.project(*p).unwrap());
            // 1e-3 px: the COLMAP text keeps every digit of the quaternion and translation.
            assert!(
                close(a, b) < 1e-3,
                "NeuMan frame {}: {a:?} vs {b:?}",
                f.frame
            );
        }
    }
    let mean = motion
        .translations
        .iter()
        .fold([0.0; 3], |a, t| [a[0] + t[0], a[1] + t[1], a[2] + t[2]])
        .map(|v| v / OPTIONS.frames as f64);
    for f in load_zju(&base().join("zju"), 0).unwrap() {
        let truth = ring_camera(
            f.view,
            OPTIONS.cameras,
            DVec3::new(mean[0], mean[1] + 1.0, mean[2]),
            64,
            64,
        );
        for p in &points {
            let (a, b) = (f.camera.project(*p).unwrap(), truth.project(*p).unwrap());
            // 1e-3 px: T goes through millimetres and back.
            assert!(close(a, b) < 1e-3, "ZJU view {}: {a:?} vs {b:?}", f.view);
        }
    }
}

fn posed(frame: &DatasetFrame) -> Vec<DVec3> {
    match &frame.body {
        BodyParams::Smpl {
            pose,
            betas,
            translation,
            ..
        } => pose_body(model(), betas, pose, *translation).vertices,
        BodyParams::Zju(p) => posed_from_zju(model(), p),
    }
}

/// IoU of the frame's person mask with the body posed from the loaded parameters, seen
/// through the loaded camera, dressed in the generator's garment meshes of that frame
/// (`gt/garments/`): what is checked is the camera and the body parameters.
fn iou_with_reprojected_person(frame: &DatasetFrame) -> f64 {
    let v = posed(frame);
    let garments: Vec<_> = ["tshirt", "pants"]
        .iter()
        .map(|name| {
            load_obj(
                &base()
                    .join("gt/garments")
                    .join(format!("{name}_{:04}.obj", frame.frame)),
                model(),
            )
            .expect("ground-truth garment")
        })
        .collect();
    let white = |_uv: [f64; 2]| [1.0, 1.0, 1.0];
    let uvs = vec![[0.0; 2]; v.len()];
    let mut items = vec![Drawable {
        vertices: &v,
        faces: &model().faces,
        uvs: &uvs,
        object: 1,
        texture: &white,
        two_sided: true,
    }];
    items.extend(garments.iter().map(|g| Drawable {
        vertices: &g.vertices,
        faces: &g.faces,
        uvs: &g.uvs,
        object: 1,
        texture: &white,
        two_sided: true,
    }));
    let r = render(
        &frame.camera,
        &items,
        OPTIONS.samples,
        [0.0; 3],
        DVec3::Y,
        1.0,
    );
    let person: Vec<bool> = r.coverage[1].iter().map(|&c| c >= 0.5).collect();
    let inter = person
        .iter()
        .zip(&frame.mask)
        .filter(|(a, b)| **a && **b)
        .count();
    let union = person
        .iter()
        .zip(&frame.mask)
        .filter(|(a, b)| **a || **b)
        .count();
    inter as f64 / union.max(1) as f64
}

#[test]
fn masks_align_with_the_reprojected_person() {
    let frames = load_neuman(&base().join("neuman"), NeumanSplit::EveryFifth)
        .unwrap()
        .into_iter()
        .chain(load_zju(&base().join("zju"), 0).unwrap());
    let mut worst = 1.0f64;
    for f in frames {
        let iou = iou_with_reprojected_person(&f);
        worst = worst.min(iou);
        // 0.98: the generator's geometry, rasterizer and sampling; only the camera and
        // the body parameters went through the files (0.997 was the worst seen).
        assert!(iou >= 0.98, "{}: IoU {iou:.3}", f.image_path.display());
    }
    eprintln!("worst IoU {worst:.3}");
}

#[test]
fn numpy_reads_annots_and_every_npz() {
    let dir = base();
    let script = format!(
        r#"
import glob, numpy as np
a = np.load({annots:?}, allow_pickle=True).item()
assert set(a) == {{'cams', 'ims'}} and len(a['cams']['K']) == {cams} and len(a['ims']) == {frames}
assert a['cams']['R'][0].shape == (3, 3) and a['cams']['T'][0].shape == (3, 1) and a['cams']['D'][0].shape == (5, 1)
for p in sorted(glob.glob({params:?})):
    d = np.load(p, allow_pickle=True).item()
    assert d['poses'].shape == (1, 72) and d['Rh'].shape == (1, 3) and d['Th'].shape == (1, 3) and d['shapes'].shape == (1, 10), p
for p in glob.glob({npz:?}, recursive=True):
    z = np.load(p)
    assert z['global_orient'].shape == ({frames}, 3) and z['body_pose'].shape == ({frames}, 69), p
    assert z['betas'].shape == ({frames}, 10) and z['transl'].shape == ({frames}, 3) and z['scale'].shape == ({frames},), p
v = np.load({verts:?})
assert v.ndim == 2 and v.shape[1] == 3
d = np.load({depth:?})
assert d.shape == (64, 64) and d.dtype == np.float32 and d.max() > 0
"#,
        annots = dir.join("zju/annots.npy").display().to_string(),
        params = dir.join("zju/smpl_params/*.npy").display().to_string(),
        npz = dir.join("**/*.npz").display().to_string(),
        verts = dir.join("zju/vertices/0.npy").display().to_string(),
        depth = dir.join("neuman/depths/00000.npy").display().to_string(),
        cams = OPTIONS.cameras,
        frames = OPTIONS.frames,
    );
    let out = std::process::Command::new("python3")
        .arg("-c")
        .arg(script)
        .output()
        .expect("python3 runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn expect_err(result: Result<Vec<DatasetFrame>, DatasetError>, needles: &[&str]) {
    let err = result.expect_err("bad data must not load").to_string();
    assert_eq!(err.lines().count(), 1, "one line: {err}");
    for n in needles {
        assert!(err.contains(n), "'{n}' not in: {err}");
    }
}

#[test]
fn bad_input_is_named() {
    // A missing image.
    let d = copy("missing");
    std::fs::remove_file(d.join("neuman/images/00003.png")).unwrap();
    expect_err(
        load_neuman(&d.join("neuman"), NeumanSplit::EveryFifth),
        &["images/00003.png"],
    );
    // A truncated JPEG.
    let d = copy("truncated");
    let p = d.join("zju/images/Camera_B2/000001.jpg");
    let bytes = std::fs::read(&p).unwrap();
    drape_io::write(&p, &bytes[..bytes.len() / 2]).unwrap();
    expect_err(load_zju(&d.join("zju"), 0), &["Camera_B2/000001.jpg"]);
    // A wrong array shape.
    let d = copy("shape");
    let mut arrays =
        drape_trainer::npy::read_npz(&d.join("neuman/4d_humans/smpl_optimized_aligned_scale.npz"))
            .unwrap();
    arrays.insert(
        "body_pose".into(),
        drape_trainer::npy::Array::f64(vec![OPTIONS.frames, 66], vec![0.0; OPTIONS.frames * 66]),
    );
    drape_trainer::npy::write_npz(
        &d.join("neuman/4d_humans/smpl_optimized_aligned_scale.npz"),
        &arrays,
    )
    .unwrap();
    expect_err(
        load_neuman(&d.join("neuman"), NeumanSplit::EveryFifth),
        &["smpl_optimized_aligned_scale.npz", "body_pose", "shape"],
    );
    // A NaN pose.
    let d = copy("nan");
    let mut p = drape_trainer::dataset::zju::ZjuSmpl::read(&d.join("zju"), 4).unwrap();
    p.poses[10] = f64::NAN;
    p.write(&d.join("zju"), 4).unwrap();
    expect_err(
        load_zju(&d.join("zju"), 0),
        &["smpl_params/4.npy", "'poses'", "not finite"],
    );
    // A camera with a singular rotation.
    let d = copy("singular");
    let images = d.join("neuman/sparse/images.txt");
    let text = std::fs::read_to_string(&images).unwrap();
    let broken: Vec<String> = text
        .lines()
        .map(|l| {
            if l.starts_with("2 ") {
                let w: Vec<&str> = l.split(' ').collect();
                format!("2 0 0 0 0 {}", w[5..].join(" "))
            } else {
                l.to_string()
            }
        })
        .collect();
    drape_io::write(&images, broken.join("\n") + "\n").unwrap();
    expect_err(
        load_neuman(&d.join("neuman"), NeumanSplit::EveryFifth),
        &["images.txt", "is zero, no rotation"],
    );
}

/// Every published variant, written from the generated sequence (files copied byte
/// for byte, renamed and moved), loads to exactly the frames the original loads to.
#[test]
fn every_published_variant_loads_like_the_generated_layout() {
    let root = base().parent().unwrap().join("variants");
    let zju = load_zju(&base().join("zju"), 0).unwrap();
    for v in [
        Variant::ZjuRefined,
        Variant::ZjuNeuralBody,
        Variant::ZjuCoreView313,
    ] {
        let dir = root.join(v.name());
        let _ = std::fs::remove_dir_all(&dir);
        write_zju_variant(&base().join("zju"), &dir, v).unwrap();
        assert_eq!(detect(&dir).unwrap(), v);
        let got = load_zju(&dir, 0).unwrap_or_else(|e| panic!("{}: {e}", v.name()));
        assert_eq!(got.len(), zju.len(), "{}", v.name());
        for (a, b) in got.iter().zip(&zju) {
            assert_eq!(
                (a.frame, a.view, a.split),
                (b.frame, b.view, b.split),
                "{}",
                v.name()
            );
            // Exact: the same bytes decoded by the same decoder; the same parameter file.
            assert_eq!(
                a.rgb,
                b.rgb,
                "{} frame {} view {}",
                v.name(),
                a.frame,
                a.view
            );
            assert_eq!(
                a.mask,
                b.mask,
                "{} frame {} view {}",
                v.name(),
                a.frame,
                a.view
            );
            assert_eq!(a.body, b.body, "{} frame {}", v.name(), a.frame);
            assert_eq!(a.camera, b.camera, "{}", v.name());
        }
    }
    let neuman = load_neuman(&base().join("neuman"), NeumanSplit::EveryFifth).unwrap();
    for v in [Variant::Neuman, Variant::NeumanHugs] {
        let dir = root.join(v.name());
        let _ = std::fs::remove_dir_all(&dir);
        write_neuman_variant(&base().join("neuman"), &dir, v).unwrap();
        assert_eq!(detect(&dir).unwrap(), v);
        let got = load_neuman(&dir, NeumanSplit::EveryFifth).unwrap();
        assert_eq!(got.len(), neuman.len());
        for (a, b) in got.iter().zip(&neuman) {
            // Detectron2's inverted masks and HUGS's SAM masks say the same thing.
            assert_eq!(a.mask, b.mask, "{} frame {}", v.name(), a.frame);
            assert_eq!(a.rgb, b.rgb);
            assert!(
                a.mask.iter().any(|&m| m) && a.mask.iter().any(|&m| !m),
                "a person and a background"
            );
        }
    }
}

/// The ZJU-MoCap frames are JPEG: the loss against the lossless render is bounded.
#[test]
fn jpeg_frames_lose_little() {
    // The NeuMan frames are lossless PNG renders of the same scene; write one as the ZJU
    // frames are written and read it back.
    let png = base().join("neuman/images/00001.png");
    let img = drape_trainer::dataset::image::read_rgb(&png).unwrap();
    let jpg = base().parent().unwrap().join("loss.jpg");
    drape_trainer::dataset::image::write_rgb(&jpg, img.width, img.height, &img.rgb).unwrap();
    let back = drape_trainer::dataset::image::read_rgb(&jpg).unwrap();
    let mse = img
        .rgb
        .iter()
        .zip(&back.rgb)
        .map(|(a, b)| f64::from(a - b).powi(2))
        .sum::<f64>()
        / img.rgb.len() as f64;
    let psnr = -10.0 * mse.log10();
    let max = img
        .rgb
        .iter()
        .zip(&back.rgb)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    eprintln!(
        "JPEG q{}: PSNR {psnr:.2} dB, max error {:.1} steps",
        drape_trainer::dataset::image::ZJU_JPEG_QUALITY,
        max * 255.0
    );
    // 35 dB: quality 95 on 64 px renders with hard edges (room, garments) measured
    // 36.6 dB (max 19 steps, on edges); a lower quality or a decoder in the wrong colour
    // space falls far below.
    assert!(psnr > 35.0, "PSNR {psnr:.2} dB");
}

#[test]
fn inspect_names_the_variant_and_the_first_missing_file() {
    let root = base().parent().unwrap().join("inspect");
    for v in Variant::ALL {
        let dir = root.join(v.name());
        let _ = std::fs::remove_dir_all(&dir);
        if v.is_zju() {
            write_zju_variant(&base().join("zju"), &dir, v).unwrap();
        } else {
            write_neuman_variant(&base().join("neuman"), &dir, v).unwrap();
        }
        let found = inspect(&dir);
        assert_eq!(found.variant, Some(v.name()));
        assert_eq!(found.problem, None, "{}", v.name());
        assert_eq!(found.image_size, Some((64, 64)));
        assert_eq!(found.frames, OPTIONS.frames);
        assert_eq!(found.cameras, if v.is_zju() { OPTIONS.cameras } else { 1 });
    }
    // One mask missing: named, with the variant that was assumed.
    let dir = root.join(Variant::ZjuCoreView313.name());
    let gone =
        dir.join("mask_cihp/Camera (2)/CoreView_313_Camera_(2)_0004_2019-08-23_16-08-50.592.png");
    std::fs::remove_file(&gone).unwrap();
    let problem = inspect(&dir).problem.expect("a missing mask is a problem");
    assert!(
        problem.contains(&gone.display().to_string()) && problem.contains("zju-coreview313"),
        "{problem}"
    );
    let dir = root.join(Variant::Neuman.name());
    std::fs::remove_file(dir.join("segmentations/00002.png")).unwrap();
    let problem = inspect(&dir).problem.expect("a missing mask is a problem");
    assert!(
        problem.contains("segmentations/00002.png") && problem.contains("neuman"),
        "{problem}"
    );
    // Parameters only NeuMan's own pickle has: the file drape needs is named.
    let dir = root.join(Variant::NeumanHugs.name());
    std::fs::remove_file(dir.join("4d_humans/smpl_optimized_aligned_scale.npz")).unwrap();
    let problem = inspect(&dir).problem.expect("no SMPL file is a problem");
    assert!(
        problem.contains("smpl_optimized_aligned_scale.npz") && problem.contains("neuman+hugs"),
        "{problem}"
    );
}

/// A ZJU-MoCap sequence seen through the release's kind of lens (non-zero D) loads back
/// to the pinhole frames: the loader undistorts images and masks as `cv2.undistort`
/// does (the map itself is checked against OpenCV in `distortion.rs`).
#[test]
fn distorted_zju_frames_are_undistorted_at_load() {
    let dir = base().parent().unwrap().join("distorted");
    let _ = std::fs::remove_dir_all(&dir);
    // ZJU-like barrel distortion with tangential terms, strong at 64 px.
    let d = [-0.3, 0.1, 1e-3, -5e-4, 0.0];
    drape_trainer::dataset::variants::write_zju_distorted(&base().join("zju"), &dir, &d).unwrap();
    let pinhole = load_zju(&base().join("zju"), 0).unwrap();
    let got = load_zju(&dir, 0).unwrap();
    let raw =
        drape_trainer::dataset::image::read_rgb(&dir.join("images/Camera_B1/000000.jpg")).unwrap();
    let und = drape_trainer::dataset::distortion::Undistorter::new(
        &got[0].camera,
        drape_trainer::dataset::distortion::Distortion::from_opencv(&d),
    );
    let lens = drape_trainer::dataset::distortion::Distortion::from_opencv(&d);
    let mean_abs = |x: &[f32], y: &[f32], inside: &[usize]| {
        inside
            .iter()
            .flat_map(|&i| (0..3).map(move |k| 3 * i + k))
            .map(|j| f64::from((x[j] - y[j]).abs()))
            .sum::<f64>()
            / (3 * inside.len()) as f64
    };
    let (mut worst_jpeg, mut worst_err, mut worst_iou, mut worst_raw) =
        (0.0f64, 0.0f64, 1.0f64, f64::INFINITY);
    for (a, b) in got.iter().zip(&pinhole) {
        assert_eq!(a.camera, b.camera, "the pinhole camera is unchanged");
        // Interior: pixels whose source lies at least 2 px inside the image (outside it
        // the distorted image holds no data).
        let inside: Vec<usize> = (0..a.mask.len())
            .filter(|&i| {
                let s = und.source((i % 64) as u32, (i / 64) as u32);
                s[0] >= 2.0 && s[1] >= 2.0 && s[0] <= 61.0 && s[1] <= 61.0
            })
            .collect();
        // What the loader must return, computed in memory: the pinhole frame distorted
        // and undistorted; the file in between adds only a JPEG encoding.
        let expected = und.rgb(&drape_trainer::dataset::distortion::distort_rgb(
            &b.camera, lens, &b.rgb,
        ));
        worst_jpeg = worst_jpeg.max(mean_abs(&a.rgb, &expected, &inside));
        worst_err = worst_err.max(mean_abs(&a.rgb, &b.rgb, &inside));
        let inter = inside.iter().filter(|&&i| a.mask[i] && b.mask[i]).count();
        let union = inside.iter().filter(|&&i| a.mask[i] || b.mask[i]).count();
        worst_iou = worst_iou.min(inter as f64 / union.max(1) as f64);
        if a.frame == 0 && a.view == 0 {
            worst_raw = mean_abs(&raw.rgb, &b.rgb, &inside);
        }
    }
    eprintln!("loaded vs undistort(distort(pinhole)): {worst_jpeg:.4}; vs pinhole {worst_err:.4} (the raw distorted frame {worst_raw:.4}); mask IoU {worst_iou:.3}");
    // One JPEG encoding at quality 95 of a 64 px render: under 2 8-bit steps on average.
    assert!(worst_jpeg < 2.0 / 255.0, "loaded vs expected: {worst_jpeg}");
    // The two bilinear resamplings blur the 64 px textures (0.03 here); the raw
    // distorted frame is far further off, so the loader did undo the lens.
    assert!(
        worst_raw > 2.0 * worst_err,
        "vs pinhole {worst_err}, raw {worst_raw}"
    );
    assert!(worst_iou > 0.9, "mask IoU {worst_iou}");
}

/// NeuMan masks written the other way round (the person white in `segmentations/`) are
/// refused, not inverted silently.
#[test]
fn inverted_neuman_masks_are_refused() {
    let dir = base().parent().unwrap().join("inverted");
    let _ = std::fs::remove_dir_all(&dir);
    write_neuman_variant(&base().join("neuman"), &dir, Variant::Neuman).unwrap();
    for entry in std::fs::read_dir(dir.join("segmentations")).unwrap() {
        let path = entry.unwrap().path();
        let (w, h, mask) = drape_trainer::dataset::image::read_mask(
            &path,
            drape_trainer::dataset::image::MaskRule::BelowHalf,
        )
        .unwrap();
        drape_trainer::dataset::image::write_mask(&path, w, h, &mask).unwrap();
    }
    expect_err(
        load_neuman(&dir, NeumanSplit::EveryFifth),
        &["segmentations/00000.png", "sam_segmentations"],
    );
    let problem = inspect(&dir).problem.expect("inverted masks are a problem");
    assert!(problem.contains("segmentations/00000.png"), "{problem}");
}
