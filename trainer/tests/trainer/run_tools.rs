//! A finished run opened again: `drape eval`'s evaluation reproduces the training's
//! held-out metrics; `drape edit`'s recolour, swap and removal change the renders only
//! where the garments are; `drape animate` poses the avatar in a new motion and writes
//! the frames and a GIF; bad runs and motions are refused with one clear message.
//! Two tiny runs (body + cloth, 64 × 64, a few steps) are trained once for the binary.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use drape_engine::ops::splat::scene::RenderSettings;
use drape_engine::Context;
use drape_tests::gpu;
use drape_trainer::avatar::animate::{animate, place_pose, AnimateOptions};
use drape_trainer::avatar::edit::{edit, Edit};
use drape_trainer::avatar::eval::{evaluate, EvalInputs};
use drape_trainer::avatar::model::LayerChoice;
use drape_trainer::avatar::run::{OpenRun, RunInfo};
use drape_trainer::avatar::train::{load_sequence, TrainConfig, TrainJob};
use drape_trainer::body::procedural::{default_body, BodyOptions};
use drape_trainer::dataset::loader::BodyParams;

use drape_trainer::motion::{procedural, MotionKind};
use drape_trainer::TrainerError;
use glam::DVec3;

fn tmp(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name);
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn data() -> &'static Path {
    crate::fixtures::small_sequence()
}

/// Two runs (seeds 1 and 2) of body + cloth, trained 30 steps: enough for the garments
/// to take colour and differ between the runs, small enough for seconds on lavapipe.
fn runs() -> &'static [PathBuf; 2] {
    static R: OnceLock<[PathBuf; 2]> = OnceLock::new();
    R.get_or_init(|| {
        let ctx = gpu();
        let seq = load_sequence(data(), 0).expect("sequence");
        [1u64, 2].map(|seed| {
            let mut c = TrainConfig::quick();
            c.layers.decimate = 6;
            c.layers.body.triplane_resolution = 16;
            c.layers.body.triplane_channels = 8;
            c.layers.cloth.triplane_resolution = 16;
            c.layers.cloth.triplane_channels = 8;
            c.layers.body.decoder_width = 32;
            c.layers.cloth.decoder_width = 32;
            c.schedule.fit_steps = 20;
            c.schedule.steps = 30;
            c.schedule.log_every = 10;
            c.seed = seed;
            c.layers.choice = LayerChoice::parse("body+cloth").unwrap();
            // Densified twice and with pose-dependent offsets, so that opening a run
            // (eval, animate, edit) meets layers of counts other than their initial
            // ones and the pose-blend head.
            c.densify = drape_trainer::avatar::densify::DensifyConfig {
                every: 10,
                from: 10,
                until: 20,
                grad_threshold: 2e-5,
                ..c.densify.clone()
            };
            c.layers.body.pose_offsets = true;
            c.layers.cloth.pose_offsets = true;
            let out = tmp(&format!("run-tools-run{seed}"));
            TrainJob::new(&seq, default_body(&BodyOptions::default()), &c, &out)
                .train(&ctx)
                .expect("training");
            RunInfo::new(data(), None).write(&out).expect("run.json");
            out
        })
    })
}

/// The run's avatar rendered on the first held-out frame: (image, matte = the cloth's
/// alpha here, where nothing hides the cloth), or the single image without a cloth layer.
fn render_first(ctx: &Context, run: &mut OpenRun) -> (Vec<f32>, Option<Vec<f32>>) {
    let f = run.test_frames()[0].clone();
    let ft = run.rig.frame(&f.body);
    run.avatar.set_frame(ctx, &ft).expect("transforms");
    let mut rec = ctx.record("test forward").expect("record");
    run.avatar
        .record_forward(&mut rec, ft.log_scale)
        .expect("forward");
    rec.submit_and_wait().expect("submit");
    let cam = f.camera.to_pinhole([0.0; 3]);
    run.renderer
        .forward(ctx, &run.avatar, &cam, &RenderSettings::default())
        .expect("render");
    let rgb = run.renderer.read_rgb(ctx).expect("read");
    let matte = run
        .renderer
        .read_passes()
        .expect("passes")
        .map(|[_, _, m]| m);
    (rgb, matte)
}

/// Largest per-value difference outside the garments (any matte above
/// [`GARMENT_ALPHA`]) and the mean difference where the first matte is above one half
/// (the garment's body, not its soft edge).
fn split_difference(a: &[f32], b: &[f32], mattes: &[&[f32]]) -> (f32, f32) {
    let (mut outside, mut inside, mut n) = (0.0f32, 0.0f32, 0usize);
    for i in 0..a.len() / 3 {
        let d = (0..3)
            .map(|c| (a[3 * i + c] - b[3 * i + c]).abs())
            .fold(0.0, f32::max);
        if mattes[0][3 * i] > 0.5 {
            inside += d;
            n += 1;
        }
        if mattes.iter().all(|m| m[3 * i] <= GARMENT_ALPHA) {
            outside = outside.max(d);
        }
    }
    assert!(n > 20, "only {n} pixels of garment in view");
    (outside, inside / n as f32)
}

/// A pixel is garment where a matte (cloth alpha) exceeds this: outside it the cloth
/// contributes at most this much to the composite (`(C/A)·V` with `C/A` in [0, 1]).
const GARMENT_ALPHA: f32 = 1e-3;

#[test]
fn eval_reproduces_the_training_metrics_and_writes_its_tables() {
    let ctx = gpu();
    let run_dir = &runs()[0];
    let mut run = OpenRun::open(&ctx, run_dir, None, None).expect("open");
    assert_eq!(run.step, 30);
    // The run was densified: its layers hold other counts than they started with.
    let log = std::fs::read_to_string(run_dir.join("log.jsonl")).expect("log");
    let grown = log
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).expect("json"))
        .filter(|l| l.get("densify").is_some())
        .any(|l| l["densify"]["body"]["after"] != l["densify"]["body"]["before"]);
    assert!(grown, "no densification changed the body's count");
    // The pose-blend head (the deformation decoder's last: its bias is the last 621
    // values) started at zero and was trained.
    let model = drape_trainer::npy::read_npz(&run_dir.join("model.npz")).expect("model");
    let deformation = &model["body.deformation"].data;
    assert!(
        deformation[deformation.len() - 621..]
            .iter()
            .any(|&v| v != 0.0),
        "the pose-blend head did not move"
    );
    let frames: Vec<_> = run.test_frames().into_iter().cloned().collect();
    let refs: Vec<_> = frames.iter().collect();
    let gt = drape_trainer::avatar::cloth_target::ground_truth_dir(&run.seq.dir);
    let out = tmp("run-tools-eval");
    std::fs::create_dir_all(&out).expect("out");
    let inputs = EvalInputs {
        rig: &run.rig,
        frames: &refs,
        ground_truth: gt.as_deref(),
        lpips: None,
        sheets: Some(&out),
    };
    let (mean, per_frame) = evaluate(
        &ctx,
        &mut run.avatar,
        &mut run.renderer,
        &inputs,
        &mut |_| {},
    )
    .expect("evaluate");
    let metrics: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(run_dir.join("metrics.json")).expect("metrics.json"),
    )
    .expect("json");
    let fin = &metrics["fin"];
    // The same model rendered from the same cameras: the forward pass has no atomics,
    // so only the model file's f32 round trip could move it (it does not: exact f32).
    for (key, value) in [
        ("psnr_full", mean.psnr_full),
        ("psnr_crop", mean.psnr_crop),
        ("ssim_full", mean.ssim_full),
        ("ssim_crop", mean.ssim_crop),
    ] {
        let want = fin[key].as_f64().expect(key);
        assert!(
            (value - want).abs() < 1e-6,
            "{key}: eval {value}, training's {want}"
        );
    }
    let (c, want) = (
        mean.cloth_chamfer
            .expect("synthetic data has ground-truth garments"),
        fin["cloth_chamfer"].as_f64().expect("chamfer"),
    );
    assert!(
        (c - want).abs() < 1e-7,
        "cloth Chamfer: eval {c}, training's {want}"
    );
    assert_eq!(per_frame.len(), frames.len());
    // The mean is the mean of the rows (f64 sums of a few values).
    let psnr_rows = per_frame.iter().map(|f| f.psnr_full).sum::<f64>() / per_frame.len() as f64;
    assert!((psnr_rows - mean.psnr_full).abs() < 1e-12);
    // A sheet per frame, six panels wide (truth, render, error, three passes).
    let f = &frames[0];
    let sheet = out.join(format!("frame{:04}_view{}.png", f.frame, f.view));
    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(&sheet).expect("sheet written"),
    ));
    let info = decoder.read_info().expect("png").info().clone();
    assert_eq!((info.width, info.height), (6 * f.width, f.height));
}

#[test]
fn recolour_and_swap_change_only_the_garments_and_removal_uncovers_the_body() {
    let ctx = gpu();
    let [a, b] = runs();
    let mut original = OpenRun::open(&ctx, a, None, None).expect("open a");
    let (before, matte_a) = render_first(&ctx, &mut original);
    let matte_a = matte_a.expect("three passes: the cloth has a matte");

    // Recolour: a 120° hue rotation.
    let out = tmp("run-tools-recolour");
    edit(
        &ctx,
        &mut original,
        &Edit::Recolour { hue_degrees: 120.0 },
        None,
        &out,
    )
    .expect("recolour");
    let mut recoloured = OpenRun::open(&ctx, &out, None, None).expect("open recoloured");
    let (after, _) = render_first(&ctx, &mut recoloured);
    let (outside, inside) = split_difference(&before, &after, &[&matte_a]);
    eprintln!("recolour: max change outside the garments {outside:.2e}, mean inside {inside:.3}");
    assert!(
        outside <= GARMENT_ALPHA,
        "the recolour changed pixels outside the garments by {outside}"
    );
    // After 30 steps the garments are still near their initial grey (a rotation about
    // the grey axis moves a colour by √3 times its distance from grey): measured 0.019;
    // a recolour that changed nothing gives exactly 0.
    assert!(
        inside > 0.005,
        "the recolour hardly changed the garments: {inside}"
    );

    // Swap: run b's cloth on run a's body.
    let mut other = OpenRun::open(&ctx, b, None, None).expect("open b");
    let (_, matte_b) = render_first(&ctx, &mut other);
    let out = tmp("run-tools-swap");
    edit(
        &ctx,
        &mut original,
        &Edit::SwapCloth,
        Some(&mut other),
        &out,
    )
    .expect("swap");
    let mut swapped = OpenRun::open(&ctx, &out, None, None).expect("open swapped");
    let (after, matte_s) = render_first(&ctx, &mut swapped);
    let (matte_b, matte_s) = (matte_b.expect("b's matte"), matte_s.expect("swapped matte"));
    // The swapped run's matte is b's: the cloth is b's, posed by the same frame.
    assert!(
        matte_s
            .iter()
            .zip(&matte_b)
            .all(|(x, y)| (x - y).abs() < 1e-6),
        "the swapped cloth is not b's"
    );
    let (outside, inside) = split_difference(&before, &after, &[&matte_a, &matte_b]);
    eprintln!("swap: max change outside either garment {outside:.2e}, mean inside {inside:.3}");
    assert!(
        outside <= GARMENT_ALPHA,
        "the swap changed pixels outside the garments by {outside}"
    );
    assert!(
        inside > 1e-3,
        "the swapped garments render as the original: {inside}"
    );

    // Removal: what remains is the base pass (body) of the original.
    let out = tmp("run-tools-remove");
    edit(&ctx, &mut original, &Edit::RemoveCloth, None, &out).expect("remove");
    let mut bare = OpenRun::open(&ctx, &out, None, None).expect("open bare");
    assert!(
        !bare.layers.cloth && bare.avatar.cloth().is_none(),
        "the cloth layer is gone"
    );
    let (after, none) = render_first(&ctx, &mut bare);
    assert!(none.is_none(), "no passes without a cloth layer");
    let (outside, inside) = split_difference(&before, &after, &[&matte_a]);
    eprintln!("remove: max change outside the garments {outside:.2e}, mean inside {inside:.3}");
    assert!(
        outside <= GARMENT_ALPHA,
        "removing the cloth changed pixels outside it by {outside}"
    );
    // The body's colours under the garments are learned apart from the cloth's.
    assert!(
        inside > 0.005,
        "removing the cloth changed nothing under it: {inside}"
    );

    // An edit into a non-empty directory is refused and writes nothing.
    let err = edit(&ctx, &mut original, &Edit::RemoveCloth, None, a).expect_err("refused");
    assert!(matches!(err, TrainerError::Run { .. }), "{err:?}");
    let err = err.to_string();
    assert!(err.contains("not empty"), "{err}");
    // Nothing to edit without a cloth layer.
    let err = edit(
        &ctx,
        &mut bare,
        &Edit::Recolour { hue_degrees: 10.0 },
        None,
        &tmp("run-tools-never"),
    )
    .expect_err("refused")
    .to_string();
    assert!(err.contains("no cloth layer"), "{err}");
    assert!(!tmp("run-tools-never").exists());
}

#[test]
fn animate_poses_the_avatar_in_a_new_motion_from_an_orbiting_camera() {
    let ctx = gpu();
    let mut run = OpenRun::open(&ctx, &runs()[0], None, None).expect("open");
    let out = tmp("run-tools-animate");
    std::fs::create_dir_all(&out).expect("out");
    let motion = procedural(MotionKind::Walk, 4, 30.0, 1.0);
    let background = [1.0, 0.0, 1.0];
    let report = animate(
        &ctx,
        &mut run,
        &motion,
        &AnimateOptions {
            frames: 4,
            orbit_degrees: 90.0,
            background,
            gif: true,
        },
        &out,
        &mut |_, _| {},
    )
    .expect("animate");
    assert_eq!(report.frames, 4);
    assert_eq!(report.frame_ms.len(), 4);
    let mut images = Vec::new();
    for k in 0..4 {
        let path = out.join(format!("frame{k:04}.png"));
        let mut dec = png::Decoder::new(std::io::BufReader::new(
            std::fs::File::open(&path).expect("frame written"),
        ))
        .read_info()
        .expect("png");
        let mut buf = vec![0; dec.output_buffer_size()];
        dec.next_frame(&mut buf).expect("decode");
        images.push(buf);
    }
    let (w, h) = (report.width as usize, report.height as usize);
    for (k, img) in images.iter().enumerate() {
        // The camera looks at the pelvis: the person covers the image centre.
        let c = 3 * ((h / 2) * w + w / 2);
        assert_ne!(
            &img[c..c + 3],
            &[255, 0, 255],
            "frame {k}: the image centre shows the background"
        );
        // And most of the frame is background (a person, not a smear over everything).
        let bg = img.chunks_exact(3).filter(|p| p == &[255, 0, 255]).count();
        assert!(
            bg > w * h / 2,
            "frame {k}: only {bg} of {} pixels are background",
            w * h
        );
    }
    // The pose and the camera move: consecutive frames differ.
    for k in 1..4 {
        let changed = images[k]
            .iter()
            .zip(&images[k - 1])
            .filter(|(x, y)| x != y)
            .count();
        assert!(
            changed > 50,
            "frames {} and {k} differ in {changed} values",
            k - 1
        );
    }
    // The GIF holds the four frames.
    let mut options = gif::DecodeOptions::new();
    options.set_color_output(gif::ColorOutput::RGBA);
    let mut dec = options
        .read_info(std::fs::File::open(out.join("animation.gif")).expect("gif written"))
        .expect("gif");
    let mut n = 0;
    while dec.read_next_frame().expect("gif frame").is_some() {
        n += 1;
    }
    assert_eq!(n, 4, "GIF frames");
}

/// An AMASS file as numpy writes it (SMPL-H poses, a string gender, 120 fps) drives
/// `animate` through the same loader `drape animate --motion FILE.npz` uses.
#[test]
fn animate_takes_an_amass_file_numpy_wrote() {
    let dir = drape_tests::reference_python::case_dir("run_tools", "amass");
    drape_tests::reference_python::run("write_motions.py", std::slice::from_ref(&dir));
    let motion =
        drape_trainer::motion::Motion::load_npz(&dir.join("amass.npz")).expect("AMASS loads");
    assert_eq!(motion.fps, 120.0);
    let ctx = gpu();
    let mut run = OpenRun::open(&ctx, &runs()[0], None, None).expect("open");
    let out = tmp("run-tools-animate-amass");
    std::fs::create_dir_all(&out).expect("out");
    let background = [1.0, 0.0, 1.0];
    let report = animate(
        &ctx,
        &mut run,
        &motion,
        &AnimateOptions {
            frames: 3,
            orbit_degrees: 0.0,
            background,
            gif: false,
        },
        &out,
        &mut |_, _| {},
    )
    .expect("animate");
    assert_eq!(report.frames, 3);
    for k in 0..3 {
        let img = drape_trainer::dataset::image::read_rgb(&out.join(format!("frame{k:04}.png")))
            .expect("frame written");
        let (w, h) = (img.width as usize, img.height as usize);
        // The camera looks at the pelvis: the person covers the image centre (magenta is
        // the background), whatever the AMASS root orientation did to the body.
        let c = 3 * ((h / 2) * w + w / 2);
        let centre = [img.rgb[c], img.rgb[c + 1], img.rgb[c + 2]];
        assert!(
            centre != [1.0, 0.0, 1.0],
            "frame {k}: the image centre shows the background"
        );
    }
}

#[test]
fn placing_the_anchor_pose_reproduces_the_anchor() {
    let ctx = gpu();
    let run = OpenRun::open(&ctx, &runs()[0], None, None).expect("open");
    let anchor = run.test_frames()[0].body.clone();
    let BodyParams::Smpl { pose, .. } = &anchor else {
        panic!("NeuMan layout: SMPL parameters")
    };
    // The anchor's own joints with a zero root and no translation: the anchor itself.
    let mut own = *pose;
    own[0] = DVec3::ZERO;
    let placed = place_pose(&anchor, &own, DVec3::ZERO);
    let (x, y) = (
        run.rig.frame(&anchor).transforms,
        run.rig.frame(&placed).transforms,
    );
    // f32 transforms; the root goes through matrix → axis-angle → matrix in f64.
    assert!(
        x.iter().zip(&y).all(|(p, q)| (p - q).abs() < 1e-5),
        "placed transforms differ"
    );
}

#[test]
fn bad_runs_and_motions_are_refused_with_the_file_named() {
    let ctx = gpu();
    let src = &runs()[0];
    // A run without run.json needs --data.
    let copy = tmp("run-tools-old-run");
    std::fs::create_dir_all(&copy).expect("copy");
    for f in ["config.json", "model.npz"] {
        std::fs::copy(src.join(f), copy.join(f)).expect("copy file");
    }
    let err = OpenRun::open(&ctx, &copy, None, None)
        .err()
        .expect("no run.json")
        .to_string();
    assert!(err.contains("run.json") && err.contains("--data"), "{err}");
    assert!(
        OpenRun::open(&ctx, &copy, Some(data()), None).is_ok(),
        "with --data it opens"
    );
    // A model file of another format version.
    let mut arrays = drape_trainer::npy::read_npz(&copy.join("model.npz")).expect("read");
    arrays.insert(
        "format_version".into(),
        drape_trainer::npy::Array::new(drape_trainer::npy::Dtype::U32, vec![1], vec![99.0]),
    );
    drape_trainer::npy::write_npz(&copy.join("model.npz"), &arrays).expect("write");
    let err = OpenRun::open(&ctx, &copy, Some(data()), None)
        .err()
        .expect("old format");
    assert!(
        matches!(&err, TrainerError::Checkpoint { key, .. } if key == "format_version"),
        "{err:?}"
    );
    let err = err.to_string();
    assert!(
        err.contains("model.npz") && err.contains("format version 99"),
        "{err}"
    );
    // Not a run at all.
    let err = OpenRun::open(&ctx, Path::new("/nonexistent/run"), None, None)
        .err()
        .expect("missing")
        .to_string();
    assert!(err.contains("no such run directory"), "{err}");
    // A motion with 23 joints (69 pose values).
    let path = tmp("run-tools-bad-motion.npz");
    let mut a = std::collections::BTreeMap::new();
    a.insert(
        "poses".to_string(),
        drape_trainer::npy::Array::f64(vec![2, 69], vec![0.0; 138]),
    );
    a.insert(
        "trans".to_string(),
        drape_trainer::npy::Array::f64(vec![2, 3], vec![0.0; 6]),
    );
    a.insert(
        "fps".to_string(),
        drape_trainer::npy::Array::f64(vec![1], vec![30.0]),
    );
    drape_trainer::npy::write_npz(&path, &a).expect("write motion");
    let err = drape_trainer::motion::Motion::load_npz(&path)
        .expect_err("wrong joints")
        .to_string();
    assert!(
        err.contains("run-tools-bad-motion.npz") && err.contains("poses"),
        "{err}"
    );
}
