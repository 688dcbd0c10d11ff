//! The one small trained run that tests share (`tests/fixtures/tiny-run.toml` on a
//! 32-pixel synthetic sequence): `DRAPE_TEST_RUN` names it when the test command made it
//! once; otherwise the first caller in a process trains it (seconds on lavapipe).

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use drape_engine::Context;

use crate::avatar::config::TrainConfig;
use crate::avatar::inputs::load_sequence;
use crate::avatar::run::RunInfo;
use crate::avatar::train::TrainJob;
use crate::body::procedural::{default_body, BodyOptions};
use crate::dataset::synth::{generate, SynthOptions};

/// The tiny run's configuration (the committed fixture).
pub const TINY_RUN_TOML: &str = include_str!("../../tests/fixtures/tiny-run.toml");

/// The synthetic sequence the tiny run is trained on.
pub fn tiny_synth_options() -> SynthOptions {
    SynthOptions {
        width: 32,
        height: 32,
        frames: 4,
        cameras: 2,
        ..SynthOptions::default()
    }
}

/// Trains the tiny run into `dir/run` on a sequence made in `dir/synth`.
pub fn train_tiny_run(ctx: &Context, dir: &Path) -> crate::Result<PathBuf> {
    let data = dir.join("synth");
    generate(&data, &tiny_synth_options(), &mut |_, _, _| {})?;
    let seq = load_sequence(&data, 0)?;
    let config =
        TrainConfig::quick().with_toml(TINY_RUN_TOML, Path::new("tests/fixtures/tiny-run.toml"))?;
    let run = dir.join("run");
    TrainJob::new(&seq, default_body(&BodyOptions::default()), &config, &run).train(ctx)?;
    RunInfo::new(&data, None).write(&run)?;
    Ok(run)
}

/// `run` as an avatar file at `path` with every layer's SH head bias raised by 40: its
/// colours rise far above their alpha (the test run's stay near 0.5), for the tests of
/// the premultiplied clamp the player and the C ABI promise.
pub fn write_saturated_avatar(ctx: &Context, run: &Path, path: &Path) -> crate::Result<()> {
    let mut file = crate::avatar::file::AvatarFile::from_run(ctx, run)?;
    for (name, layer) in &mut file.layers {
        let config = match name.as_str() {
            "body" => &file.layers_config.body,
            _ => &file.layers_config.cloth,
        };
        let [appearance, _, _] = crate::avatar::layer::decoder_descs(config);
        let sh = appearance
            .heads
            .iter()
            .position(|h| h.name == "sh")
            .expect("the appearance decoder has an SH head");
        let (offsets, _) = appearance.layout();
        let bias = offsets[appearance.hidden.len() + sh].1;
        for b in &mut layer.appearance[bias..bias + appearance.heads[sh].width] {
            *b += 40.0;
        }
    }
    file.write(path)
}

/// The shared tiny run: `DRAPE_TEST_RUN` if set (it must hold `model.npz`), else one
/// trained once per process under the system's temporary directory.
pub fn tiny_run(ctx: &Context) -> &'static Path {
    static RUN: OnceLock<PathBuf> = OnceLock::new();
    RUN.get_or_init(|| {
        if let Some(dir) = std::env::var_os("DRAPE_TEST_RUN").map(PathBuf::from) {
            assert!(
                dir.join("model.npz").is_file(),
                "DRAPE_TEST_RUN={} holds no model.npz",
                dir.display()
            );
            return dir;
        }
        let dir = std::env::temp_dir().join(format!("drape-tiny-run-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        train_tiny_run(ctx, &dir).unwrap_or_else(|e| panic!("training the tiny test run: {e}"))
    })
}

/// An avatar file's bytes with its `header.json` edited by `edit` and the archive
/// written again (each entry's own CRC right), for tests of what the reader refuses:
/// another format version, a checksum that does not match.
pub fn edit_avatar_header(bytes: &[u8], edit: impl FnOnce(&mut serde_json::Value)) -> Vec<u8> {
    use std::io::{Read, Write};
    let mut zip = zip::ZipArchive::new(std::io::Cursor::new(bytes)).expect("an avatar file");
    let mut out = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let options =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    let mut edit = Some(edit);
    for i in 0..zip.len() {
        let mut e = zip.by_index(i).expect("an entry");
        let mut data = Vec::new();
        e.read_to_end(&mut data).expect("an entry's bytes");
        if e.name() == crate::avatar::file::HEADER_ENTRY {
            let mut v: serde_json::Value = serde_json::from_slice(&data).expect("header.json");
            (edit.take().expect("one header"))(&mut v);
            data = serde_json::to_vec_pretty(&v).expect("header.json");
        }
        out.start_file(e.name(), options).expect("an entry");
        out.write_all(&data).expect("an entry");
    }
    out.finish().expect("the archive").into_inner()
}
