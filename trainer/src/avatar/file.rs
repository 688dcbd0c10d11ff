//! The trained avatar as one file an app ships (`NAME.avatar`; the format is
//! `docs/avatar-format.md`): what rendering needs and nothing it does not, so that a
//! player loads it without the run directory or the capture it was trained on.
//!
//! The file is a ZIP archive of stored (uncompressed) entries, which `numpy.load` opens
//! as it opens an `.npz`: `header.json` first (the format, its version, the checksum,
//! the layers' sizes and the default camera's size), then one `.npy` per array, in name
//! order. The checksum is CRC-32 (zlib's) over the bytes of every `.npy` entry (header
//! and data) in name order, as `crc32:` and eight lower-case hex digits; the header is
//! not part of it.
//!
//! Arrays (f32 unless noted; `L` a human layer's name, `body` or `cloth`):
//! - `L.means`, `L.quats`, `L.log_scales`: the canonical Gaussians (n×3, n×4, n×3);
//! - `L.triplane` (3×R×R×C, channels last), `L.triplane_box` (2×3: min, max);
//! - `L.appearance`, `L.geometry`, `L.deformation`: the decoders' flat parameters
//!   (`ops::nn::MlpDesc::layout`); the deformation decoder's first head is the skinning
//!   weights, so the file holds no per-Gaussian weights of its own;
//! - a scene layer: `scene.means`, `scene.log_scales`, `scene.quats`,
//!   `scene.opacity_logits`, `scene.sh` (as `model.npz`);
//! - the rig: `rig.parents` (i32, 24), `rig.rest_joints` (f64, 24×3: the shaped
//!   body's joints at rest), `rig.betas` (f64: the shape they came from, for the record);
//! - the default view: `default.camera` (f64: fx, fy, cx, cy, near),
//!   `default.camera_rotation` (f64, 3×3, world to camera, rows),
//!   `default.camera_translation` (f64, 3), `default.pose` (f64, 24×3 axis-angles;
//!   ZJU-MoCap: joint 0 unused), and for an SMPL body `default.translation` (f64, 3) and
//!   `default.scale` (f64, 1), for a ZJU-MoCap body `default.rh`, `default.th` (f64, 3)
//!   and `default.shapes` (f64, 10).

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::path::Path;

use drape_engine::Context;
use glam::DVec3;

use crate::avatar::assemble::Layers;
use crate::avatar::checkpoint::{f32_array, insert_learned_layer};
use crate::avatar::config::{LayersConfig, TrainConfig};
use crate::avatar::model::Avatar;
use crate::avatar::rig::Rig;
use crate::avatar::run::OpenRun;
use crate::avatar::scene::{cloud_of, SceneLayer};
use crate::avatar::state::{LayerState, ModelState, SceneState, SCENE_PARAMS};
use crate::body::model::NUM_JOINTS;
use crate::camera::Camera;
use crate::dataset::loader::BodyParams;
use crate::dataset::zju::ZjuSmpl;
use crate::npy::{decode, encode, Array, Dtype};
use crate::TrainerError;

/// `header.json`'s `format`.
pub const AVATAR_FORMAT: &str = "drape-avatar";
/// The version of the layout this module reads and writes.
pub const AVATAR_FORMAT_VERSION: u32 = 1;
/// The archive's first entry.
pub const HEADER_ENTRY: &str = "header.json";

/// `header.json`.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AvatarHeader {
    /// [`AVATAR_FORMAT`].
    pub format: String,
    /// [`AVATAR_FORMAT_VERSION`].
    pub format_version: u32,
    /// `crc32:` and 8 hex digits (see the module's header).
    pub checksum: String,
    /// Training steps the model had taken.
    pub step: u32,
    /// The human layers, in render order (`body`, then `cloth` if present).
    pub layers: Vec<String>,
    /// Whether the file has a scene layer.
    pub scene: bool,
    /// The 3DGS scene extent (the scene layer's; none without one).
    pub scene_extent: Option<f32>,
    /// The layers' sizes: triplane, decoders, SH degree, pose offsets, compositing (the
    /// run's `config.json` `layers` group; its rates are training's, kept as they were).
    pub layers_config: LayersConfig,
    /// The run accumulated deterministically (the player does too).
    pub deterministic: bool,
    /// The default camera's image size.
    pub width: u32,
    pub height: u32,
    /// `smpl` (NeuMan/HUGS convention) or `zju` (ZJU-MoCap).
    pub body: String,
    /// How the avatar's colour is encoded, in words.
    pub colour: String,
}

/// A trained avatar on the host, as the file holds it.
#[derive(Clone, Debug, PartialEq)]
pub struct AvatarFile {
    pub step: u32,
    pub layers_config: LayersConfig,
    pub deterministic: bool,
    /// The layers' parameters (no optimiser state, no skinning targets).
    pub layers: Vec<(String, LayerState)>,
    pub scene: Option<(SceneState, f32)>,
    pub parents: [i32; NUM_JOINTS],
    pub rest_joints: [DVec3; NUM_JOINTS],
    pub betas: Vec<f64>,
    pub default_camera: Camera,
    pub default_body: BodyParams,
}

const COLOUR: &str = "each layer's appearance decoder gives opacity and SH coefficients of its layers_config sh_degree; colour = SH + 0.5, clamped at 0, in the training images' values; frames are premultiplied RGBA";

fn f64_array(shape: Vec<usize>, data: &[f64]) -> Array {
    Array::new(Dtype::F64, shape, data.to_vec())
}

/// The checksum of the array entries' bytes, in name order.
fn checksum<'a>(entries: impl Iterator<Item = &'a [u8]>) -> String {
    let mut h = crc32fast::Hasher::new();
    for e in entries {
        h.update(e);
    }
    format!("crc32:{:08x}", h.finalize())
}

impl AvatarFile {
    /// The avatar of the run at `dir` (its dataset read once, for the default view and
    /// the body's shape): what `drape export` writes.
    pub fn from_run(ctx: &Context, dir: &Path) -> crate::Result<Self> {
        let mut run = OpenRun::open(ctx, dir, None, None)?;
        let anchor = run
            .test_frames()
            .first()
            .copied()
            .or_else(|| run.seq.frames.first())
            .ok_or_else(|| TrainerError::run(&run.dir, "the run's sequence has no frames"))?
            .clone();
        let state = run.avatar.state(ctx, run.step)?;
        let extent = run.avatar.scene.as_ref().map(|s| s.extent);
        let layers = state
            .layers
            .into_iter()
            .map(|(name, mut l)| {
                l.adam.clear();
                l.weight_targets = None;
                l.screen_stats = None;
                l.edges = None;
                (name, l)
            })
            .collect();
        let scene = state.scene.map(|mut s| {
            s.adam.clear();
            s.screen_stats = None;
            (s, extent.unwrap_or(0.0))
        });
        Ok(Self {
            step: run.step,
            layers_config: run.config.layers.clone(),
            deterministic: run.config.deterministic,
            layers,
            scene,
            parents: run.rig.model.parents,
            rest_joints: run.rig.rest_joints(),
            betas: run.rig.betas.clone(),
            default_camera: anchor.camera,
            default_body: anchor.body,
        })
    }

    /// The arrays of the file, by entry name (without `.npy`).
    fn arrays(&self) -> BTreeMap<String, Array> {
        let mut a = BTreeMap::new();
        for (name, l) in &self.layers {
            insert_learned_layer(&mut a, name, l);
        }
        if let Some((s, _)) = &self.scene {
            let n = s.params[3].len();
            for (name, p) in SCENE_PARAMS.iter().zip(&s.params) {
                let shape = match *name {
                    "opacity_logits" => vec![n],
                    "sh" => vec![n, p.len() / (3 * n.max(1)), 3],
                    _ => vec![n, p.len() / n.max(1)],
                };
                a.insert(format!("scene.{name}"), f32_array(shape, p));
            }
        }
        a.insert(
            "rig.parents".into(),
            Array::new(
                Dtype::I32,
                vec![NUM_JOINTS],
                self.parents.iter().map(|&p| f64::from(p)).collect(),
            ),
        );
        a.insert(
            "rig.rest_joints".into(),
            f64_array(
                vec![NUM_JOINTS, 3],
                &self
                    .rest_joints
                    .iter()
                    .flat_map(|j| j.to_array())
                    .collect::<Vec<_>>(),
            ),
        );
        a.insert(
            "rig.betas".into(),
            f64_array(vec![self.betas.len()], &self.betas),
        );
        let c = &self.default_camera;
        a.insert(
            "default.camera".into(),
            f64_array(vec![5], &[c.fx, c.fy, c.cx, c.cy, c.near]),
        );
        a.insert(
            "default.camera_rotation".into(),
            f64_array(vec![3, 3], &c.rotation.concat()),
        );
        a.insert(
            "default.camera_translation".into(),
            f64_array(vec![3], &c.translation.to_array()),
        );
        match &self.default_body {
            BodyParams::Smpl {
                pose,
                translation,
                scale,
                ..
            } => {
                let p: Vec<f64> = pose.iter().flat_map(|j| j.to_array()).collect();
                a.insert("default.pose".into(), f64_array(vec![NUM_JOINTS, 3], &p));
                a.insert(
                    "default.translation".into(),
                    f64_array(vec![3], &translation.to_array()),
                );
                a.insert("default.scale".into(), f64_array(vec![1], &[*scale]));
            }
            BodyParams::Zju(z) => {
                a.insert(
                    "default.pose".into(),
                    f64_array(vec![NUM_JOINTS, 3], &z.poses),
                );
                a.insert("default.rh".into(), f64_array(vec![3], &z.rh));
                a.insert("default.th".into(), f64_array(vec![3], &z.th));
                a.insert("default.shapes".into(), f64_array(vec![10], &z.shapes));
            }
        }
        a
    }

    /// The file's bytes.
    pub fn to_bytes(&self) -> crate::Result<Vec<u8>> {
        let encoded: BTreeMap<String, Vec<u8>> = self
            .arrays()
            .iter()
            .map(|(k, v)| (format!("{k}.npy"), encode(v)))
            .collect();
        let header = AvatarHeader {
            format: AVATAR_FORMAT.into(),
            format_version: AVATAR_FORMAT_VERSION,
            checksum: checksum(encoded.values().map(Vec::as_slice)),
            step: self.step,
            layers: self.layers.iter().map(|(n, _)| n.clone()).collect(),
            scene: self.scene.is_some(),
            scene_extent: self.scene.as_ref().map(|s| s.1),
            layers_config: self.layers_config.clone(),
            deterministic: self.deterministic,
            width: self.default_camera.width,
            height: self.default_camera.height,
            body: match self.default_body {
                BodyParams::Smpl { .. } => "smpl".into(),
                BodyParams::Zju(_) => "zju".into(),
            },
            colour: COLOUR.into(),
        };
        let json = serde_json::to_vec_pretty(&header).expect("the header serialises");
        let zip_err = |e: zip::result::ZipError| {
            TrainerError::avatar_file(Path::new("(memory)"), e.to_string())
        };
        let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
        let options = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored);
        zip.start_file(HEADER_ENTRY, options).map_err(zip_err)?;
        zip.write_all(&json)
            .map_err(|e| TrainerError::io(Path::new("(memory)"), e))?;
        for (name, bytes) in &encoded {
            zip.start_file(name.as_str(), options).map_err(zip_err)?;
            zip.write_all(bytes)
                .map_err(|e| TrainerError::io(Path::new("(memory)"), e))?;
        }
        Ok(zip.finish().map_err(zip_err)?.into_inner())
    }

    /// Writes the file whole or not at all.
    pub fn write(&self, path: &Path) -> crate::Result<()> {
        let bytes = self.to_bytes()?;
        drape_io::write(path, bytes).map_err(|e| TrainerError::io(path, e))
    }

    /// Reads `path`.
    pub fn read(path: &Path) -> crate::Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| TrainerError::io(path, e))?;
        Self::from_bytes(&bytes, path)
    }

    /// Reads a file's bytes; `path` names it in errors.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> crate::Result<Self> {
        let bad = |problem: String| TrainerError::avatar_file(path, problem);
        let mut zip = zip::ZipArchive::new(std::io::Cursor::new(bytes)).map_err(|e| {
            bad(format!(
                "not a readable avatar file (truncated, or not a .avatar archive): {e}"
            ))
        })?;
        // Entries pointing at shared bytes could otherwise make a small file read as many
        // times its size: their stored sizes together must fit in the file, once each.
        const MAX_ENTRIES: usize = 256;
        if zip.len() > MAX_ENTRIES {
            return Err(bad(format!(
                "{} entries (an avatar file has at most {MAX_ENTRIES})",
                zip.len()
            )));
        }
        let mut entries = BTreeMap::new();
        let mut stored: u64 = 0;
        for i in 0..zip.len() {
            let mut e = zip
                .by_index(i)
                .map_err(|e| bad(format!("entry {i}: {e} (a damaged file?)")))?;
            if e.compression() != zip::CompressionMethod::Stored {
                return Err(bad(format!(
                    "entry {} is compressed; avatar files store their entries",
                    e.name()
                )));
            }
            let name = e.name().to_string();
            if name != HEADER_ENTRY && !name.ends_with(".npy") {
                return Err(bad(format!(
                    "entry {name}: not {HEADER_ENTRY} or an .npy array"
                )));
            }
            if entries.contains_key(&name) {
                return Err(bad(format!("entry {name} appears twice")));
            }
            stored = stored.saturating_add(e.size());
            if stored > bytes.len() as u64 {
                return Err(bad(format!(
                    "entries' sizes add up to more than the file's {} bytes (a damaged file?)",
                    bytes.len()
                )));
            }
            // A stored entry holds what it occupies: its size is bounded by the file's.
            let mut data = Vec::with_capacity((e.size() as usize).min(bytes.len()));
            e.read_to_end(&mut data)
                .map_err(|err| bad(format!("entry {name}: {err} (a damaged file?)")))?;
            entries.insert(name, data);
        }
        let header = entries
            .remove(HEADER_ENTRY)
            .ok_or_else(|| bad(format!("no {HEADER_ENTRY} (not an avatar file?)")))?;
        let value: serde_json::Value =
            serde_json::from_slice(&header).map_err(|e| bad(format!("{HEADER_ENTRY}: {e}")))?;
        if value.get("format").and_then(|v| v.as_str()) != Some(AVATAR_FORMAT) {
            return Err(bad(format!(
                "{HEADER_ENTRY}: format is not \"{AVATAR_FORMAT}\" (not an avatar file?)"
            )));
        }
        match value.get("format_version").and_then(|v| v.as_u64()) {
            Some(v) if v == u64::from(AVATAR_FORMAT_VERSION) => {}
            v => {
                return Err(bad(format!(
                "format version {}, this drape reads version {AVATAR_FORMAT_VERSION} (export it again with this drape, or use a newer one)",
                v.map_or("missing".to_string(), |v| v.to_string())
            )))
            }
        }
        let header: AvatarHeader =
            serde_json::from_value(value).map_err(|e| bad(format!("{HEADER_ENTRY}: {e}")))?;
        let sum = checksum(entries.values().map(Vec::as_slice));
        if sum != header.checksum {
            return Err(bad(format!(
                "checksum mismatch: the header says {}, the arrays give {sum} (a damaged or edited file)",
                header.checksum
            )));
        }
        let mut arrays = BTreeMap::new();
        for (name, data) in &entries {
            let key = name.strip_suffix(".npy").ok_or_else(|| {
                bad(format!(
                    "entry {name} is neither {HEADER_ENTRY} nor an .npy"
                ))
            })?;
            let file = path.display().to_string();
            arrays.insert(key.to_string(), decode(data, &file, Some(key))?);
        }
        Self::from_arrays(&header, &arrays, path)
    }

    fn from_arrays(
        header: &AvatarHeader,
        a: &BTreeMap<String, Array>,
        path: &Path,
    ) -> crate::Result<Self> {
        let bad = |key: &str, problem: String| TrainerError::checkpoint(path, key, problem);
        let get = |key: &str, dtype: Dtype, shape: &[usize]| -> crate::Result<&[f64]> {
            let arr = a
                .get(key)
                .ok_or_else(|| bad(key, "array is missing".into()))?;
            if arr.dtype != dtype || arr.shape != shape {
                return Err(bad(
                    key,
                    format!(
                        "array is {:?} of shape {:?}, expected {dtype:?} of shape {shape:?}",
                        arr.dtype, arr.shape
                    ),
                ));
            }
            if let Some(i) = arr.data.iter().position(|v| !v.is_finite()) {
                return Err(bad(key, format!("value {i} is {}", arr.data[i])));
            }
            Ok(&arr.data)
        };
        let f32s = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        let len_of = |key: &str| a.get(key).map_or(0, |arr| arr.data.len());
        // The header is outside the checksum: its sizes are checked as a config's are
        // (bounded triplanes, decoders and SH degrees), so an edited header is an error,
        // not a huge allocation or a panic.
        let header_error =
            |problem: String| TrainerError::avatar_file(path, format!("{HEADER_ENTRY}: {problem}"));
        let config = TrainConfig {
            layers: header.layers_config.clone(),
            ..TrainConfig::quick()
        };
        config
            .validate()
            .map_err(|e| header_error(format!("layers_config: {e}")))?;
        if !matches!(
            header.layers.iter().map(String::as_str).collect::<Vec<_>>()[..],
            ["body"] | ["body", "cloth"]
        ) {
            return Err(header_error(format!(
                "layers {:?}: expected [\"body\"] or [\"body\", \"cloth\"]",
                header.layers
            )));
        }
        let mut layers = Vec::new();
        for name in &header.layers {
            let config = match name.as_str() {
                "body" => &header.layers_config.body,
                "cloth" => &header.layers_config.cloth,
                other => {
                    return Err(TrainerError::avatar_file(
                        path,
                        format!("{HEADER_ENTRY}: unknown layer '{other}' (body or cloth)"),
                    ))
                }
            };
            let n = len_of(&format!("{name}.means")) / 3;
            if n == 0 {
                return Err(bad(
                    &format!("{name}.means"),
                    "array is missing or empty".into(),
                ));
            }
            let (r, c) = (
                config.triplane_resolution as usize,
                config.triplane_channels as usize,
            );
            let bx = get(&format!("{name}.triplane_box"), Dtype::F32, &[2, 3])?;
            let descs = crate::avatar::layer::decoder_descs(config);
            let decoder = |k: &str, desc: &drape_engine::ops::nn::MlpDesc| {
                let key = format!("{name}.{k}");
                let expected = desc.layout().1;
                if len_of(&key) != expected {
                    return Err(bad(
                        &key,
                        format!(
                            "{} parameters, but the header's layer sizes make {expected}",
                            len_of(&key)
                        ),
                    ));
                }
                Ok(f32s(get(&key, Dtype::F32, &[expected])?))
            };
            layers.push((
                name.clone(),
                LayerState {
                    means: f32s(get(&format!("{name}.means"), Dtype::F32, &[n, 3])?),
                    quats: f32s(get(&format!("{name}.quats"), Dtype::F32, &[n, 4])?),
                    log_scales: f32s(get(&format!("{name}.log_scales"), Dtype::F32, &[n, 3])?),
                    triplane: f32s(get(&format!("{name}.triplane"), Dtype::F32, &[3, r, r, c])?),
                    triplane_size: (config.triplane_resolution, config.triplane_channels),
                    triplane_box: [
                        [bx[0] as f32, bx[1] as f32, bx[2] as f32],
                        [bx[3] as f32, bx[4] as f32, bx[5] as f32],
                    ],
                    appearance: decoder("appearance", &descs[0])?,
                    geometry: decoder("geometry", &descs[1])?,
                    deformation: decoder("deformation", &descs[2])?,
                    adam: Vec::new(),
                    weight_targets: None,
                    screen_stats: None,
                    edges: None,
                },
            ));
        }
        let scene = if header.scene {
            let n = len_of("scene.opacity_logits");
            let k = drape_shared::splat::layout::sh_coeffs(header.layers_config.scene.sh_degree);
            let shapes = [vec![n, 3], vec![n, 3], vec![n, 4], vec![n], vec![n, k, 3]];
            let mut params = Vec::new();
            for (p, shape) in SCENE_PARAMS.iter().zip(shapes) {
                params.push(f32s(get(&format!("scene.{p}"), Dtype::F32, &shape)?));
            }
            Some((
                SceneState {
                    params,
                    adam: Vec::new(),
                    screen_stats: None,
                },
                header.scene_extent.unwrap_or(0.0),
            ))
        } else {
            None
        };
        let parents_raw = get("rig.parents", Dtype::I32, &[NUM_JOINTS])?;
        let parents: [i32; NUM_JOINTS] = std::array::from_fn(|j| parents_raw[j] as i32);
        if let Some(j) = (1..NUM_JOINTS).find(|&j| !(0..j as i32).contains(&parents[j])) {
            return Err(bad(
                "rig.parents",
                format!(
                    "joint {j}'s parent is {} (an earlier joint expected)",
                    parents[j]
                ),
            ));
        }
        let joints = get("rig.rest_joints", Dtype::F64, &[NUM_JOINTS, 3])?;
        let rest_joints = std::array::from_fn(|j| DVec3::from_slice(&joints[3 * j..3 * j + 3]));
        let betas = get("rig.betas", Dtype::F64, &[len_of("rig.betas")])?.to_vec();
        let cam = get("default.camera", Dtype::F64, &[5])?;
        // A default view an app can render: a bounded image and a camera that projects.
        const MAX_SIDE: u32 = 16_384;
        if !(1..=MAX_SIDE).contains(&header.width) || !(1..=MAX_SIDE).contains(&header.height) {
            return Err(header_error(format!(
                "default image {}x{}: each side 1 to {MAX_SIDE}",
                header.width, header.height
            )));
        }
        if !(cam[0] > 0.0 && cam[1] > 0.0 && cam[4] > 0.0) {
            return Err(bad(
                "default.camera",
                format!(
                    "fx {}, fy {}, near {}: each must be positive",
                    cam[0], cam[1], cam[4]
                ),
            ));
        }
        let rot = get("default.camera_rotation", Dtype::F64, &[3, 3])?;
        let default_camera = Camera {
            fx: cam[0],
            fy: cam[1],
            cx: cam[2],
            cy: cam[3],
            width: header.width,
            height: header.height,
            rotation: std::array::from_fn(|r| std::array::from_fn(|c| rot[3 * r + c])),
            translation: DVec3::from_slice(get("default.camera_translation", Dtype::F64, &[3])?),
            near: cam[4],
        };
        let pose = get("default.pose", Dtype::F64, &[NUM_JOINTS, 3])?;
        let default_body = match header.body.as_str() {
            "smpl" => BodyParams::Smpl {
                pose: std::array::from_fn(|j| DVec3::from_slice(&pose[3 * j..3 * j + 3])),
                betas: betas.clone(),
                translation: DVec3::from_slice(get("default.translation", Dtype::F64, &[3])?),
                scale: get("default.scale", Dtype::F64, &[1])?[0],
            },
            "zju" => BodyParams::Zju(ZjuSmpl {
                poses: std::array::from_fn(|k| pose[k]),
                rh: std::array::from_fn(|k| {
                    get("default.rh", Dtype::F64, &[3]).map_or(0.0, |v| v[k])
                }),
                th: std::array::from_fn(|k| {
                    get("default.th", Dtype::F64, &[3]).map_or(0.0, |v| v[k])
                }),
                shapes: std::array::from_fn(|k| {
                    get("default.shapes", Dtype::F64, &[10]).map_or(0.0, |v| v[k])
                }),
            }),
            other => {
                return Err(TrainerError::avatar_file(
                    path,
                    format!("{HEADER_ENTRY}: body '{other}' (smpl or zju)"),
                ))
            }
        };
        Ok(Self {
            step: header.step,
            layers_config: header.layers_config.clone(),
            deterministic: header.deterministic,
            layers,
            scene,
            parents,
            rest_joints,
            betas,
            default_camera,
            default_body,
        })
    }

    /// The body rig (posing only: the file has no mesh).
    pub fn rig(&self) -> Rig {
        Rig::from_joints(self.parents, self.rest_joints, &self.betas)
    }

    /// The layers as `assemble::build_avatar` chooses them.
    pub fn layer_set(&self) -> Layers {
        Layers {
            cloth: self.layers.iter().any(|(n, _)| n == "cloth"),
            scene: self.scene.is_some(),
        }
    }

    /// The avatar on the GPU, ready to pose and render (no optimiser state).
    pub fn build(&self, ctx: &Context) -> crate::Result<Avatar> {
        let config = TrainConfig {
            layers: self.layers_config.clone(),
            deterministic: self.deterministic,
            ..TrainConfig::quick()
        };
        let mut inits = Vec::new();
        let mut configs = Vec::new();
        for (name, l) in &self.layers {
            let lc = if name == "cloth" {
                &config.layers.cloth
            } else {
                &config.layers.body
            };
            inits.push(crate::avatar::model::LayerInit {
                name: name.clone(),
                cloud: crate::avatar::layer::canonical_cloud(l, lc.sh_degree),
                // Training's skinning targets: rendering does not read them.
                weights: vec![0.0; NUM_JOINTS * l.count()],
                edges: Vec::new(),
            });
            configs.push(lc.clone());
        }
        let scene = match &self.scene {
            Some((s, extent)) => Some(SceneLayer::new(
                ctx,
                &cloud_of(s, config.layers.scene.sh_degree),
                *extent,
                &config.layers.scene,
                config.schedule.steps,
            )?),
            None => None,
        };
        let lbs = vec![0.0; inits.len()];
        let mut avatar = Avatar::new(
            ctx,
            &inits,
            &configs,
            &lbs,
            scene,
            config.schedule.steps,
            config.seed,
        )?;
        if config.deterministic {
            avatar.set_accumulation(
                ctx,
                drape_engine::ops::accumulate::Accumulation::Deterministic,
            )?;
        }
        let state = ModelState {
            step: self.step,
            layers: self.layers.clone(),
            scene: self.scene.as_ref().map(|s| s.0.clone()),
            poses: None,
        };
        avatar.restore(ctx, &state)?;
        Ok(avatar)
    }
}
