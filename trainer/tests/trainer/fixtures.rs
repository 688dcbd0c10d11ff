//! What several of this binary's test modules share, made once per process.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use drape_trainer::dataset::synth::{generate, SynthOptions};

/// A small synthetic sequence (64 × 64 px, 10 frames, 2 cameras, in the NeuMan layout
/// at its root and the ZJU-MoCap one under `zju/`), generated once per test binary.
/// Tests read it and write nothing into it.
pub fn small_sequence() -> &'static Path {
    static D: OnceLock<PathBuf> = OnceLock::new();
    D.get_or_init(|| {
        let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("small-sequence");
        let _ = std::fs::remove_dir_all(&dir);
        let o = SynthOptions {
            width: 64,
            height: 64,
            frames: 10,
            cameras: 2,
            ..SynthOptions::default()
        };
        generate(&dir, &o, &mut |_, _, _| {}).expect("synthetic data");
        dir
    })
}
