//! A trained avatar as one file: the committed fixture (`tests/fixtures/avatar/`: a
//! tiny run's `config.json` and `model.npz`, and `renders.npy`, what the player rendered
//! from them before the avatar file existed, through `OpenRun` and the run's dataset)
//! is what the player renders now, from the run directory and from its exported file
//! with the dataset and the run deleted.
//!
//! `DRAPE_BLESS_AVATAR=1` trains a new tiny run and writes the fixture again (only when
//! the model or the renders are meant to change).

use std::path::{Path, PathBuf};

use drape_engine::Context;
use drape_trainer::avatar::file::AvatarFile;
use drape_trainer::avatar::player::{AvatarPlayer, ViewCamera};
use drape_trainer::avatar::run::RunInfo;
use drape_trainer::camera::Camera;
use drape_trainer::dataset::synth::generate;
use drape_trainer::npy::{decode, encode, Array, Dtype};
use drape_trainer::testing::{edit_avatar_header, tiny_synth_options, train_tiny_run};

/// The fixture's renders: 3 images of 64 x 64 premultiplied RGBA.
const SIZE: u32 = 64;
const IMAGES: usize = 3;

fn fixture_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/avatar")
}

/// A fresh, empty directory for one test.
fn scratch(name: &str) -> PathBuf {
    drape_tests::reference_python::case_dir("avatar-file", name)
}

/// `camera` for a square image `side` pixels wide (the intrinsics scale with the image).
fn camera_at(camera: &Camera, side: u32) -> ViewCamera {
    let k = side as f32 / camera.width as f32;
    let mut cam = ViewCamera::from_camera(camera);
    cam.fx *= k;
    cam.fy *= k;
    cam.cx *= k;
    cam.cy *= k;
    cam
}

/// The run's default camera at 64 x 64 (the run's images are 32 x 32).
fn camera_64(player: &AvatarPlayer) -> ViewCamera {
    camera_at(player.default_camera(), SIZE)
}

/// Poses `player` as its default body with the arms and a knee bent.
fn bend(player: &mut AvatarPlayer) {
    let (mut pose, translation) =
        drape_trainer::avatar::player::smpl_pose_of(player.default_body()).expect("an SMPL body");
    pose[3 * 16 + 2] -= 0.8; // left shoulder
    pose[3 * 17 + 2] += 0.8; // right shoulder
    pose[3 * 4] += 0.6; // left knee
    player.set_pose(&pose, &translation).expect("pose");
}

/// The fixture's images, in order: the default (held-out) camera and pose; a camera
/// moved 0.3 m to the side; the default camera with the arms and a knee bent.
fn renders(player: &mut AvatarPlayer) -> Vec<f32> {
    let cam = camera_64(player);
    let mut out = player.render(&cam, SIZE, SIZE).expect("default view");
    let mut side = cam;
    side.world_to_camera[3] += 0.3;
    out.extend(player.render(&side, SIZE, SIZE).expect("side view"));
    bend(player);
    out.extend(player.render(&cam, SIZE, SIZE).expect("posed"));
    out
}

/// The fixture's run copied into `dir/run`, with the tiny sequence made again in
/// `dir/synth` (the synthetic data are deterministic) and named by its `run.json`.
fn fixture_run(dir: &Path) -> PathBuf {
    let data = dir.join("synth");
    generate(&data, &tiny_synth_options(), &mut |_, _, _| {}).expect("synth");
    let run = dir.join("run");
    std::fs::create_dir_all(&run).unwrap();
    for f in ["config.json", "model.npz"] {
        std::fs::copy(fixture_dir().join("run").join(f), run.join(f)).unwrap();
    }
    RunInfo::new(&data, None).write(&run).unwrap();
    run
}

fn fixture_renders() -> Vec<f32> {
    let path = fixture_dir().join("renders.npy");
    let bytes = std::fs::read(&path).expect("tests/fixtures/avatar/renders.npy");
    let a = decode(&bytes, "renders.npy", None).expect("renders.npy");
    assert_eq!(a.shape, [IMAGES, SIZE as usize, SIZE as usize, 4]);
    a.data.iter().map(|&v| v as f32).collect()
}

/// Bit for bit, naming the first differing value.
fn assert_identical(what: &str, got: &[f32], expected: &[f32]) {
    assert_eq!(got.len(), expected.len(), "{what}: value count");
    if let Some(i) = (0..got.len()).find(|&i| got[i].to_bits() != expected[i].to_bits()) {
        let px = i / 4;
        let per = (SIZE * SIZE) as usize;
        panic!(
            "{what}: image {} pixel ({}, {}) channel {} is {}, the fixture has {}",
            px / per,
            px % per % SIZE as usize,
            px % per / SIZE as usize,
            i % 4,
            got[i],
            expected[i]
        );
    }
}

fn bless(ctx: &Context) {
    let dir = scratch("bless");
    let trained = train_tiny_run(ctx, &dir).expect("tiny run");
    let out = fixture_dir().join("run");
    std::fs::create_dir_all(&out).unwrap();
    for f in ["config.json", "model.npz"] {
        std::fs::copy(trained.join(f), out.join(f)).unwrap();
    }
    let run = fixture_run(&scratch("bless-render"));
    let mut player = AvatarPlayer::load(ctx, &run, 1).expect("player");
    let pixels = renders(&mut player);
    let a = Array::new(
        Dtype::F32,
        vec![IMAGES, SIZE as usize, SIZE as usize, 4],
        pixels.iter().map(|&v| f64::from(v)).collect(),
    );
    drape_io::write(fixture_dir().join("renders.npy"), encode(&a)).unwrap();
}

#[test]
fn the_run_directory_renders_the_fixture() {
    let ctx = drape_tests::gpu();
    if std::env::var_os("DRAPE_BLESS_AVATAR").is_some() {
        bless(&ctx);
    }
    let expected = fixture_renders();
    assert!(
        expected.chunks(4).filter(|p| p[3] > 0.5).count() > 100,
        "the fixture's avatar covers some pixels"
    );
    let run = fixture_run(&scratch("run-directory"));
    let mut player = AvatarPlayer::load(&ctx, &run, 1).expect("player");
    assert_identical("the run directory", &renders(&mut player), &expected);
}

/// Premultiplied means each colour value within [0, alpha] and alpha within [0, 1]: the
/// player's renders of the small test run (the one the test command trains) through
/// every held-out image's camera and body, and through its default camera, that camera
/// moved 0.3 m to either side and 0.5 m closer, at 32 x 32 and 96 x 96, at rest and
/// posed (arms and a knee bent). The spherical-harmonic colours are not clamped on the
/// GPU; this run's colours stay near 0.5, so the same avatar with its SH biases raised
/// renders colours far above their alpha, which the player's clamp must bound.
#[test]
fn every_colour_value_the_player_returns_is_within_zero_and_its_alpha() {
    let ctx = drape_tests::gpu();
    let run = drape_trainer::testing::tiny_run(&ctx);
    let info = RunInfo::read(run)
        .expect("run.json")
        .expect("the test run records its data");
    let seq = drape_trainer::avatar::inputs::load_sequence(&info.data, 0)
        .expect("the test run's sequence");
    let hot_path = scratch("premultiplied").join("hot.avatar");
    drape_trainer::testing::write_saturated_avatar(&ctx, run, &hot_path)
        .expect("the saturated avatar");
    check_premultiplied(&ctx, run, &seq, false);
    check_premultiplied(&ctx, &hot_path, &seq, true);
}

/// Renders `path` through the views above and checks each value's range, and that each
/// render shows the person (alpha above 1/2 somewhere); `saturated`: and that some
/// pixel's colour is at its alpha (the clamp's bound: the raised biases worked).
fn check_premultiplied(
    ctx: &Context,
    path: &Path,
    seq: &drape_trainer::avatar::inputs::Sequence,
    saturated: bool,
) {
    let mut player = AvatarPlayer::load(ctx, path, 1).expect("player");
    let mut images: Vec<(String, Vec<f32>)> = Vec::new();
    let held_out = seq
        .frames
        .iter()
        .filter(|f| f.split == drape_trainer::dataset::split::Split::Test);
    for f in held_out {
        player.set_body(f.body.clone());
        let cam = ViewCamera::from_camera(&f.camera);
        let rgba = player
            .render(&cam, f.width, f.height)
            .expect("held-out view");
        images.push((format!("held-out frame {} view {}", f.frame, f.view), rgba));
    }
    assert!(!images.is_empty(), "the small run holds images out");
    player.set_body(player.default_body().clone());
    let camera = *player.default_camera();
    let mut views = vec![camera];
    for (axis, shift) in [(0, 0.3), (0, -0.3), (2, -0.5)] {
        let mut c = camera;
        c.translation[axis] += shift;
        views.push(c);
    }
    for posed in [false, true] {
        if posed {
            bend(&mut player);
        }
        for (v, view) in views.iter().enumerate() {
            for side in [32u32, 96] {
                let rgba = player
                    .render(&camera_at(view, side), side, side)
                    .expect("render");
                images.push((format!("posed {posed}, view {v}, {side}x{side}"), rgba));
            }
        }
    }
    let mut at_alpha = 0;
    for (what, rgba) in &images {
        at_alpha +=
            drape_tests::premultiplied_at_alpha(rgba, &format!("{}: {what}", path.display()));
    }
    assert!(
        !saturated || at_alpha > 0,
        "{}: no colour reaches its alpha",
        path.display()
    );
}

/// `drape export` in the library: the fixture's run as a file, then the run and its
/// dataset deleted; the file alone renders the fixture bit for bit.
#[test]
fn the_exported_file_renders_the_fixture_without_its_run_or_dataset() {
    let ctx = drape_tests::gpu();
    let expected = fixture_renders();
    let dir = scratch("exported");
    let run = fixture_run(&dir);
    let path = dir.join("tiny.avatar");
    AvatarFile::from_run(&ctx, &run)
        .expect("export")
        .write(&path)
        .expect("write");
    std::fs::remove_dir_all(&run).unwrap();
    std::fs::remove_dir_all(dir.join("synth")).unwrap();
    let mut player = AvatarPlayer::load(&ctx, &path, 1).expect("the avatar file");
    assert_identical("the avatar file", &renders(&mut player), &expected);
    // Two frames in flight: each slot built from the file renders the same.
    let mut player = AvatarPlayer::load(&ctx, &path, 2).expect("the avatar file");
    let first = renders(&mut player);
    assert_identical("two frames in flight", &first, &expected);
}

/// Another format version, a truncated file and a checksum that does not match the
/// arrays: each refused with one line naming the file and the reason.
#[test]
fn damaged_avatar_files_are_refused_naming_the_file() {
    let ctx = drape_tests::gpu();
    let dir = scratch("damaged");
    let run = fixture_run(&dir);
    let good = AvatarFile::from_run(&ctx, &run)
        .expect("export")
        .to_bytes()
        .unwrap();
    let path = dir.join("damaged.avatar");
    // The header is outside the checksum: an edited one is refused by its own checks.
    let cases: [(&str, Vec<u8>, &str); 6] = [
        (
            "version 2",
            edit_avatar_header(&good, |h| h["format_version"] = 2.into()),
            "format version 2, this drape reads version 1",
        ),
        (
            "truncated",
            good[..good.len() * 2 / 3].to_vec(),
            "not a readable avatar file",
        ),
        (
            "checksum flipped",
            edit_avatar_header(&good, |h| {
                let s = h["checksum"].as_str().unwrap().to_string();
                let last = if s.ends_with('0') { "1" } else { "0" };
                h["checksum"] = format!("{}{last}", &s[..s.len() - 1]).into();
            }),
            "checksum mismatch",
        ),
        (
            "a triplane of terabytes",
            edit_avatar_header(&good, |h| {
                h["layers_config"]["body"]["triplane_resolution"] = 1_000_000.into()
            }),
            "layers_config",
        ),
        (
            "wider decoders than the arrays",
            edit_avatar_header(&good, |h| {
                let w = h["layers_config"]["body"]["decoder_width"]
                    .as_u64()
                    .unwrap();
                h["layers_config"]["body"]["decoder_width"] = (2 * w).into();
            }),
            "body.appearance",
        ),
        (
            "a cloth layer alone",
            edit_avatar_header(&good, |h| h["layers"] = serde_json::json!(["cloth"])),
            "expected [\"body\"] or [\"body\", \"cloth\"]",
        ),
    ];
    for (what, bytes, needle) in cases {
        drape_io::write(&path, &bytes).unwrap();
        let err = match AvatarFile::read(&path) {
            Ok(_) => panic!("{what}: read"),
            Err(e) => e.to_string(),
        };
        assert!(
            err.contains("damaged.avatar") && err.contains(needle) && !err.contains('\n'),
            "{what}: {err}"
        );
        let err = match AvatarPlayer::load(&ctx, &path, 1) {
            Ok(_) => panic!("{what}: loaded"),
            Err(e) => e.to_string(),
        };
        assert!(err.contains(needle), "{what}: the player says {err}");
    }
    AvatarFile::from_bytes(&good, &path).expect("the undamaged bytes read");
}

/// `scripts/avatar-reader.py` (numpy and the standard library, no drape code) reads the
/// exported file, verifies its checksum and gives back the canonical Gaussians bit for
/// bit as the trained model holds them (`model.npz`); it refuses a flipped checksum.
#[test]
fn the_python_reader_reproduces_the_canonical_gaussians() {
    let ctx = drape_tests::gpu();
    let dir = scratch("python-reader");
    let run = fixture_run(&dir);
    let path = dir.join("tiny.avatar");
    let file = AvatarFile::from_run(&ctx, &run).expect("export");
    file.write(&path).expect("write");
    let python = drape_tests::reference_python::clients_python();
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../scripts/avatar-reader.py");
    let out = dir.join("gaussians.npz");
    let o = std::process::Command::new(&python)
        .arg(&script)
        .arg(&path)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap_or_else(|e| {
            panic!(
                "running {} with {}: {e}",
                script.display(),
                python.display()
            )
        });
    assert!(
        o.status.success(),
        "avatar-reader.py: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let got = drape_trainer::npy::read_npz(&out).expect("the reader's arrays");
    let model = drape_trainer::npy::read_npz(&run.join("model.npz")).expect("model.npz");
    let mut compared = 0;
    for layer in ["body", "cloth"] {
        for k in ["means", "quats", "log_scales"] {
            let key = format!("{layer}.{k}");
            let (g, m) = (&got[&key], &model[&key]);
            assert_eq!(g.dtype, Dtype::F32, "{key}");
            assert_eq!(g.shape, m.shape, "{key}");
            let bits = |a: &Array| {
                a.data
                    .iter()
                    .map(|&v| (v as f32).to_bits())
                    .collect::<Vec<_>>()
            };
            assert!(
                bits(g) == bits(m),
                "{key}: the reader's values differ from model.npz's"
            );
            compared += g.data.len();
        }
    }
    assert!(compared > 1000, "{compared} values compared");
    let flipped = edit_avatar_header(&std::fs::read(&path).unwrap(), |h| {
        h["checksum"] = "crc32:00000000".into()
    });
    drape_io::write(&path, flipped).unwrap();
    let o = std::process::Command::new(&python)
        .arg(&script)
        .arg(&path)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("checksum mismatch") && err.contains("tiny.avatar"),
        "the reader took a flipped checksum: {err}"
    );
}
