//! The entry points the fuzz targets (`fuzz/`, `cargo fuzz`, nightly) and the stable
//! corpus replay test (`trainer/tests/trainer/fuzz_corpus.rs`) share: one function per
//! loader, taking arbitrary bytes and calling the loader exactly as the product does.
//! Each may return any error; none may panic, abort, overflow its stack or hang.
//!
//! Loaders that read paths get the bytes through a file of this thread's own in the
//! temporary directory (named with the extension the loader expects), so the code
//! under test is the product's, file handling included.

use std::path::{Path, PathBuf};

/// A fuzz entry point: any bytes in, no panic out.
pub type Target = fn(&[u8]);

/// The loaders, by target name (the `fuzz/fuzz_targets/<name>.rs` files and the
/// corpus folders `fuzz/corpus/<name>/`).
pub const TARGETS: [(&str, Target); 12] = [
    ("ply", ply),
    ("obj", obj),
    ("npy", npy),
    ("npz", npz),
    ("pickle", pickle),
    ("colmap", colmap),
    ("camera_json", camera_json),
    ("config_toml", config_toml),
    ("checkpoint", checkpoint),
    ("image", image),
    ("motion", motion),
    ("smpl", smpl),
];

/// A scratch file for this process and thread, with `name`'s extension.
fn scratch(name: &str) -> PathBuf {
    let thread = format!("{:?}", std::thread::current().id())
        .chars()
        .filter(char::is_ascii_digit)
        .collect::<String>();
    std::env::temp_dir()
        .join(format!("drape-fuzz-{}-{thread}", std::process::id()))
        .join(name)
}

fn with_file(name: &str, data: &[u8], f: impl FnOnce(&Path)) {
    let path = scratch(name);
    let _ = std::fs::create_dir_all(path.parent().expect("in a folder"));
    if drape_io::write(&path, data).is_ok() {
        f(&path);
    }
}

/// A 3DGS PLY (`drape render --ply`).
pub fn ply(data: &[u8]) {
    with_file("scene.ply", data, |p| {
        let _ = crate::ply::read(p);
    });
}

/// An OBJ garment (`drape simulate --garment`) on a small procedural body.
pub fn obj(data: &[u8]) {
    use std::sync::OnceLock;
    static BODY: OnceLock<crate::body::model::SmplModel> = OnceLock::new();
    let body = BODY.get_or_init(|| {
        crate::body::procedural::default_body(&crate::body::procedural::BodyOptions {
            cell: 0.05,
            ..Default::default()
        })
    });
    with_file("garment.obj", data, |p| {
        let _ = crate::garment::load_obj(p, body);
    });
}

/// A NumPy `.npy` array.
pub fn npy(data: &[u8]) {
    let _ = crate::npy::decode(data, "fuzz.npy", None);
}

/// A NumPy `.npz` archive.
pub fn npz(data: &[u8]) {
    with_file("arrays.npz", data, |p| {
        let _ = crate::npy::Npz::read(p);
    });
}

/// A pickled object array (ZJU-MoCap's `annots.npy`), through the annotations reader.
pub fn pickle(data: &[u8]) {
    let _ = crate::pickle::decode(data, "fuzz.pkl");
    with_file("annots.npy", data, |p| {
        let _ = crate::dataset::zju::ZjuAnnots::read(p.parent().expect("in a folder"));
        let _ = crate::dataset::zju::ZjuSmpl::read_file(p);
    });
}

/// COLMAP text: `cameras.txt`, `images.txt` and `points3D.txt` are the input split at
/// its first two `\0` bytes.
pub fn colmap(data: &[u8]) {
    let mut parts = data.splitn(3, |&b| b == 0);
    let files = [
        parts.next().unwrap_or(&[]),
        parts.next().unwrap_or(&[]),
        parts.next().unwrap_or(&[]),
    ];
    let dir = scratch("sparse");
    let _ = std::fs::create_dir_all(&dir);
    for (name, bytes) in ["cameras.txt", "images.txt", "points3D.txt"]
        .iter()
        .zip(files)
    {
        if drape_io::write(dir.join(name), bytes).is_err() {
            return;
        }
    }
    if let Ok(model) = crate::dataset::colmap::ColmapModel::read_text(&dir) {
        for img in model.images.values() {
            if let Some(cam) = model.cameras.get(&img.camera_id) {
                let _ = img.camera_and_distortion(cam);
            }
        }
    }
}

/// A camera file of `drape render --camera`.
pub fn camera_json(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(cam) = crate::camera_file::parse(text) {
        let _ = cam.validate();
    }
}

/// A `drape train --config` file laid over the quick preset.
pub fn config_toml(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let base = crate::avatar::config::TrainConfig::quick();
    let _ = base.with_toml(text, Path::new("fuzz.toml"));
}

/// A checkpoint or model (`model.npz`) read for a tiny body-only model and for one with a
/// scene layer.
pub fn checkpoint(data: &[u8]) {
    use crate::avatar::checkpoint::read;
    use crate::avatar::state::LayerShape;
    with_file("checkpoint.npz", data, |p| {
        // The shapes of the seeds in fuzz/corpus/checkpoint (2x2x1 triplane, 4-parameter decoders).
        let shape = LayerShape {
            name: "body".into(),
            triplane_size: (2, 1),
            decoders: [4, 4, 4],
            count: 4,
        };
        let _ = read(p, std::slice::from_ref(&shape), None);
        let _ = read(p, &[shape], Some(0));
    });
}

/// An image (PNG or JPEG, by its bytes), read as a frame and as a mask.
pub fn image(data: &[u8]) {
    let ext = if data.starts_with(&[0xFF, 0xD8]) {
        "jpg"
    } else {
        "png"
    };
    with_file(&format!("frame.{ext}"), data, |p| {
        let _ = crate::dataset::image::dimensions(p);
        let _ = crate::dataset::image::read_rgb(p);
        let _ = crate::dataset::image::read_mask(p, crate::dataset::image::MaskRule::AtLeastHalf);
    });
}

/// A motion file (`--motion x.npz`).
pub fn motion(data: &[u8]) {
    with_file("motion.npz", data, |p| {
        let _ = crate::motion::Motion::load_npz(p);
    });
}

/// NeuMan's SMPL parameters and an SMPL body model (`.npz`).
pub fn smpl(data: &[u8]) {
    with_file("smpl.npz", data, |p| {
        let _ = crate::dataset::neuman::SmplSequence::read_npz(p);
        let _ = crate::body::model::SmplModel::load_npz(p);
    });
}
