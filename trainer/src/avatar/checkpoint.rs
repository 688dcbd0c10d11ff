//! The avatar's file: one NumPy `.npz` archive (numpy reads it as it is), written whole
//! to a temporary file and renamed over the old one, so a crash mid-write leaves the
//! previous file intact. The same format is the checkpoint (`checkpoint.npz`, with the
//! optimiser's moments) and the final model (`model.npz`).
//!
//! Arrays (f32 unless noted; `L` is a layer name such as `body`):
//! - `format_version` (u32, 1 value): [`FORMAT_VERSION`];
//! - `step` (u32, 1 value): training steps taken;
//! - `L.means`, `L.quats`, `L.log_scales`: the canonical Gaussians (n×3, n×4, n×3);
//! - `L.triplane` (3×R×R×C, channels-last) and `L.triplane_box` (2×3: min, max);
//! - `L.appearance`, `L.geometry`, `L.deformation`: each decoder's flat parameters
//!   (per linear layer W out×in, then b, each from a 16-byte boundary, then any weight
//!   norms `g`; `ops::nn::MlpDesc::layout`);
//! - `L.adam.G.m`, `L.adam.G.v` (f32) and `L.adam.G.step` (u32) for each Adam group G
//!   (`position`, `triplane`, `appearance`, `geometry`, `deformation`);
//! - `L.weight_targets` (n×24: the skinning targets), `L.screen_stats` (n×3: the
//!   densification statistics since the last densification, `ops::splat::densify`) and
//!   `L.edges` (u32, E×2: the ARAP graph between the layer's Gaussians; E may be 0).
//!   A file without them loads into a model of the same Gaussian count, which keeps
//!   its own targets and graph, with zero statistics.
//! - with a scene layer: `scene.means` (n×3), `scene.log_scales` (n×3), `scene.quats`
//!   (n×4), `scene.opacity_logits` (n), `scene.sh` (n×K×3, K = (degree + 1)²), and
//!   `scene.adam.P.m`, `scene.adam.P.v`, `scene.adam.P.step` for each of them; and
//!   `scene.screen_stats` (n×3, optional as the layers' are);
//! - with pose refinement (optional: a file without it loads, with no corrections):
//!   `poses.frames` (u32, F: the training frames' numbers), `poses.delta` (f64,
//!   F×75: root rotation, 23 joints' axis-angles, translation, added to the data's),
//!   `poses.adam.m`, `poses.adam.v` (f64, F×75) and `poses.adam.step` (u32, F).
//!
//! A layer's Gaussian count n is the file's (densification changes it): loading checks
//! that every per-Gaussian array agrees with `L.means`, and every other array's
//! presence, dtype and shape against the model it is loaded into, and names the file
//! and array on a mismatch.

use std::collections::BTreeMap;
use std::path::Path;

use crate::avatar::pose_refine::PoseState;
use crate::avatar::rig::REFINED_PARAMS;
use crate::avatar::state::{
    AdamState, LayerShape, LayerState, ModelState, SceneState, ADAM_GROUPS, SCENE_PARAMS,
};
use crate::npy::{read_npz, write_npz, Array, Dtype};
use crate::TrainerError;

/// Version of the archive layout.
/// 2: decoder parameters laid out with every weight and bias on a 16-byte boundary
/// (`MlpDesc::layout`).
pub const FORMAT_VERSION: u32 = 2;

pub(crate) fn f32_array(shape: Vec<usize>, data: &[f32]) -> Array {
    Array::new(
        Dtype::F32,
        shape,
        data.iter().map(|&v| f64::from(v)).collect(),
    )
}

fn u32_array(v: u32) -> Array {
    Array::new(Dtype::U32, vec![1], vec![f64::from(v)])
}

fn edge_array(edges: &[[u32; 2]]) -> Array {
    Array::new(
        Dtype::U32,
        vec![edges.len(), 2],
        edges.iter().flatten().map(|&v| f64::from(v)).collect(),
    )
}

/// Writes `state` to `path` atomically (temporary file, then rename).
/// A layer's learned arrays (`L.means`, `L.quats`, `L.log_scales`, `L.triplane`,
/// `L.triplane_box`, the three decoders) as the checkpoint and the avatar file both
/// store them.
pub(crate) fn insert_learned_layer(a: &mut BTreeMap<String, Array>, name: &str, l: &LayerState) {
    let n = l.means.len() / 3;
    let (r, c) = (l.triplane_size.0 as usize, l.triplane_size.1 as usize);
    a.insert(format!("{name}.means"), f32_array(vec![n, 3], &l.means));
    a.insert(format!("{name}.quats"), f32_array(vec![n, 4], &l.quats));
    a.insert(
        format!("{name}.log_scales"),
        f32_array(vec![n, 3], &l.log_scales),
    );
    a.insert(
        format!("{name}.triplane"),
        f32_array(vec![3, r, r, c], &l.triplane),
    );
    a.insert(
        format!("{name}.triplane_box"),
        f32_array(vec![2, 3], &[l.triplane_box[0], l.triplane_box[1]].concat()),
    );
    for (k, p) in [
        ("appearance", &l.appearance),
        ("geometry", &l.geometry),
        ("deformation", &l.deformation),
    ] {
        a.insert(format!("{name}.{k}"), f32_array(vec![p.len()], p));
    }
}

pub fn write(path: &Path, state: &ModelState) -> crate::Result<()> {
    let mut a = BTreeMap::new();
    a.insert("format_version".to_string(), u32_array(FORMAT_VERSION));
    a.insert("step".to_string(), u32_array(state.step));
    for (name, l) in &state.layers {
        let n = l.count();
        insert_learned_layer(&mut a, name, l);
        for (g, s) in ADAM_GROUPS.iter().zip(&l.adam) {
            a.insert(
                format!("{name}.adam.{g}.m"),
                f32_array(vec![s.m.len()], &s.m),
            );
            a.insert(
                format!("{name}.adam.{g}.v"),
                f32_array(vec![s.v.len()], &s.v),
            );
            a.insert(format!("{name}.adam.{g}.step"), u32_array(s.step));
        }
        if let Some(w) = &l.weight_targets {
            a.insert(format!("{name}.weight_targets"), f32_array(vec![n, 24], w));
        }
        if let Some(st) = &l.screen_stats {
            a.insert(format!("{name}.screen_stats"), f32_array(vec![n, 3], st));
        }
        if let Some(e) = &l.edges {
            a.insert(format!("{name}.edges"), edge_array(e));
        }
    }
    if let Some(sc) = &state.scene {
        let n = sc.params[3].len();
        for ((name, p), ad) in SCENE_PARAMS.iter().zip(&sc.params).zip(&sc.adam) {
            let shape = match *name {
                "opacity_logits" => vec![n],
                "sh" => vec![n, p.len() / (3 * n.max(1)), 3],
                _ => vec![n, p.len() / n.max(1)],
            };
            a.insert(format!("scene.{name}"), f32_array(shape, p));
            a.insert(
                format!("scene.adam.{name}.m"),
                f32_array(vec![ad.m.len()], &ad.m),
            );
            a.insert(
                format!("scene.adam.{name}.v"),
                f32_array(vec![ad.v.len()], &ad.v),
            );
            a.insert(format!("scene.adam.{name}.step"), u32_array(ad.step));
        }
        if let Some(st) = &sc.screen_stats {
            a.insert("scene.screen_stats".into(), f32_array(vec![n, 3], st));
        }
    }
    if let Some(p) = &state.poses {
        let f = p.frames.len();
        let rows = |v: &[[f64; REFINED_PARAMS]]| {
            Array::new(
                Dtype::F64,
                vec![f, REFINED_PARAMS],
                v.iter().flatten().copied().collect(),
            )
        };
        a.insert(
            "poses.frames".into(),
            Array::new(
                Dtype::U32,
                vec![f],
                p.frames.iter().map(|&v| f64::from(v)).collect(),
            ),
        );
        a.insert("poses.delta".into(), rows(&p.deltas));
        a.insert("poses.adam.m".into(), rows(&p.m));
        a.insert("poses.adam.v".into(), rows(&p.v));
        a.insert(
            "poses.adam.step".into(),
            Array::new(
                Dtype::U32,
                vec![f],
                p.steps.iter().map(|&v| f64::from(v)).collect(),
            ),
        );
    }
    // Staged beside the checkpoint and moved over it once whole (and on disk): a kill
    // mid-write leaves the previous checkpoint.
    let staged = drape_io::StagedFile::new(path).map_err(|e| TrainerError::io(path, e))?;
    write_npz(staged.path(), &a)?;
    stall_if_asked(staged.path());
    staged.commit().map_err(|e| TrainerError::io(path, e))
}

/// The crash test's hook: with `DRAPE_FAILPOINT=stall-in-checkpoint-write:K`, the
/// K-th checkpoint write of the process leaves its temporary file half written, says
/// so on stderr and waits forever, so that a test can SIGKILL the process in the
/// middle of a write. Unset (always, outside that test), it does nothing.
fn stall_if_asked(tmp: &Path) {
    static WRITES: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let Ok(spec) = std::env::var("DRAPE_FAILPOINT") else {
        return;
    };
    let Some(k) = spec
        .strip_prefix("stall-in-checkpoint-write:")
        .and_then(|k| k.parse::<u32>().ok())
    else {
        return;
    };
    if WRITES.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1 != k {
        return;
    }
    if let Ok(f) = std::fs::OpenOptions::new().write(true).open(tmp) {
        let len = f.metadata().map(|m| m.len()).unwrap_or(0);
        let _ = f.set_len(len / 2);
        let _ = f.sync_all();
    }
    eprintln!("failpoint: stalled writing {}", tmp.display());
    loop {
        std::thread::sleep(std::time::Duration::from_secs(1));
    }
}

/// Reads `path`, checking it against `shapes` and, with a scene layer, the scene's SH
/// degree (the model it is loaded into).
pub fn read(
    path: &Path,
    shapes: &[LayerShape],
    scene_sh_degree: Option<u32>,
) -> crate::Result<ModelState> {
    let a = read_npz(path)?;
    let bad = |key: &str, problem: String| TrainerError::checkpoint(path, key, problem);
    let missing = |key: &str| {
        bad(
            key,
            "array is missing (a checkpoint of another model?)".into(),
        )
    };
    let get = |key: &str, dtype: Dtype, len: usize| -> crate::Result<Vec<f32>> {
        let arr = a.get(key).ok_or_else(|| missing(key))?;
        if arr.dtype != dtype {
            return Err(bad(
                key,
                format!("array has dtype {:?}, expected {dtype:?}", arr.dtype),
            ));
        }
        if arr.data.len() != len {
            return Err(bad(
                key,
                format!(
                    "array has shape {:?} ({} values), but this model needs {len}",
                    arr.shape,
                    arr.data.len()
                ),
            ));
        }
        let values: Vec<f32> = arr.data.iter().map(|&v| v as f32).collect();
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(bad(key, format!("value {i} is {} (a run that diverged, or a damaged file; an earlier checkpoint may be intact)", values[i])));
        }
        Ok(values)
    };
    let version = get("format_version", Dtype::U32, 1)?[0] as u32;
    if version != FORMAT_VERSION {
        return Err(bad(
            "format_version",
            format!("format version {version}, this drape reads version {FORMAT_VERSION}"),
        ));
    }
    let step = get("step", Dtype::U32, 1)?[0] as u32;
    let mut layers = Vec::new();
    // The Gaussian count of a per-Gaussian array of `width` floats each: the file's.
    let count_of = |key: &str, width: usize| -> crate::Result<usize> {
        let arr = a.get(key).ok_or_else(|| missing(key))?;
        if arr.data.is_empty() || arr.data.len() % width != 0 {
            return Err(bad(
                key,
                format!(
                    "array has {} values, not a positive multiple of {width}",
                    arr.data.len()
                ),
            ));
        }
        Ok(arr.data.len() / width)
    };
    let optional = |key: &str, len: usize| -> crate::Result<Option<Vec<f32>>> {
        if a.contains_key(key) {
            get(key, Dtype::F32, len).map(Some)
        } else {
            Ok(None)
        }
    };
    for s in shapes {
        let name = &s.name;
        let n = count_of(&format!("{name}.means"), 3)?;
        let (r, c) = (s.triplane_size.0 as usize, s.triplane_size.1 as usize);
        let bx = get(&format!("{name}.triplane_box"), Dtype::F32, 6)?;
        let adam_lens = [
            3 * n,
            3 * r * r * c,
            s.decoders[0],
            s.decoders[1],
            s.decoders[2],
        ];
        let mut adam = Vec::new();
        for (g, &len) in ADAM_GROUPS.iter().zip(&adam_lens) {
            adam.push(AdamState {
                m: get(&format!("{name}.adam.{g}.m"), Dtype::F32, len)?,
                v: get(&format!("{name}.adam.{g}.v"), Dtype::F32, len)?,
                step: get(&format!("{name}.adam.{g}.step"), Dtype::U32, 1)?[0] as u32,
            });
        }
        layers.push((
            name.clone(),
            LayerState {
                means: get(&format!("{name}.means"), Dtype::F32, 3 * n)?,
                quats: get(&format!("{name}.quats"), Dtype::F32, 4 * n)?,
                log_scales: get(&format!("{name}.log_scales"), Dtype::F32, 3 * n)?,
                triplane: get(&format!("{name}.triplane"), Dtype::F32, 3 * r * r * c)?,
                triplane_size: s.triplane_size,
                triplane_box: [[bx[0], bx[1], bx[2]], [bx[3], bx[4], bx[5]]],
                appearance: get(&format!("{name}.appearance"), Dtype::F32, s.decoders[0])?,
                geometry: get(&format!("{name}.geometry"), Dtype::F32, s.decoders[1])?,
                deformation: get(&format!("{name}.deformation"), Dtype::F32, s.decoders[2])?,
                adam,
                weight_targets: match optional(&format!("{name}.weight_targets"), 24 * n)? {
                    None if n != s.count => return Err(bad(&format!("{name}.weight_targets"), format!("array is missing, and layer '{name}' has {n} Gaussians (this model has {}; a checkpoint of another model?)", s.count))),
                    w => w,
                },
                screen_stats: optional(&format!("{name}.screen_stats"), 3 * n)?,
                edges: match a.get(&format!("{name}.edges")) {
                    None => None,
                    Some(arr) => {
                        let key = format!("{name}.edges");
                        if arr.dtype != Dtype::U32 || arr.data.len() % 2 != 0 {
                            return Err(bad(&key, format!("array is {:?} of shape {:?}, expected U32 of shape [E, 2]", arr.dtype, arr.shape)));
                        }
                        if let Some(&g) = arr.data.iter().find(|&&v| v as usize >= n) {
                            return Err(bad(&key, format!("array names Gaussian {g}, but the layer has {n}")));
                        }
                        Some(arr.data.chunks_exact(2).map(|e| [e[0] as u32, e[1] as u32]).collect())
                    }
                },
            },
        ));
    }
    let scene = match scene_sh_degree {
        None => {
            if a.contains_key("scene.means") {
                return Err(bad("scene.means", "the file has a scene layer, but this model has none (trained with other --layers?)".into()));
            }
            None
        }
        Some(degree) => {
            let n = count_of("scene.opacity_logits", 1)?;
            let k = drape_shared::splat::layout::sh_coeffs(degree);
            let lens = [3 * n, 3 * n, 4 * n, n, 3 * k * n];
            let mut params = Vec::new();
            let mut adam = Vec::new();
            for (name, len) in SCENE_PARAMS.iter().zip(lens) {
                params.push(get(&format!("scene.{name}"), Dtype::F32, len)?);
                adam.push(AdamState {
                    m: get(&format!("scene.adam.{name}.m"), Dtype::F32, len)?,
                    v: get(&format!("scene.adam.{name}.v"), Dtype::F32, len)?,
                    step: get(&format!("scene.adam.{name}.step"), Dtype::U32, 1)?[0] as u32,
                });
            }
            Some(SceneState {
                params,
                adam,
                screen_stats: optional("scene.screen_stats", 3 * n)?,
            })
        }
    };
    let poses = match a.get("poses.frames") {
        None => None,
        Some(frames) => {
            let frames: Vec<u32> = match frames.dtype {
                Dtype::U32 => frames.data.iter().map(|&v| v as u32).collect(),
                other => {
                    return Err(bad(
                        "poses.frames",
                        format!("array has dtype {other:?}, expected U32"),
                    ))
                }
            };
            let f = frames.len();
            let rows = |key: &str| -> crate::Result<Vec<[f64; REFINED_PARAMS]>> {
                let arr = a
                    .get(key)
                    .ok_or_else(|| bad(key, "array is missing (poses.frames is there)".into()))?;
                if arr.dtype != Dtype::F64 || arr.data.len() != f * REFINED_PARAMS {
                    return Err(bad(key, format!("array is {:?} of shape {:?}, expected F64 of shape [{f}, {REFINED_PARAMS}]", arr.dtype, arr.shape)));
                }
                if let Some(i) = arr.data.iter().position(|v| !v.is_finite()) {
                    return Err(bad(
                        key,
                        format!(
                            "value {i} is {} (a run that diverged, or a damaged file)",
                            arr.data[i]
                        ),
                    ));
                }
                Ok(arr
                    .data
                    .chunks_exact(REFINED_PARAMS)
                    .map(|c| std::array::from_fn(|k| c[k]))
                    .collect())
            };
            let steps: Vec<u32> = get("poses.adam.step", Dtype::U32, f)?
                .iter()
                .map(|&v| v as u32)
                .collect();
            Some(PoseState {
                frames,
                deltas: rows("poses.delta")?,
                m: rows("poses.adam.m")?,
                v: rows("poses.adam.v")?,
                steps,
            })
        }
    };
    for (name, l) in &layers {
        if let Some(g) = l
            .quats
            .chunks_exact(4)
            .position(|q| q.iter().all(|&c| c == 0.0))
        {
            return Err(bad(
                &format!("{name}.quats"),
                format!("Gaussian {g} has the zero quaternion (no rotation)"),
            ));
        }
        let [lo, hi] = l.triplane_box;
        if (0..3).any(|k| !(lo[k] < hi[k])) {
            return Err(bad(
                &format!("{name}.triplane_box"),
                format!("min {lo:?} is not below max {hi:?} on every axis"),
            ));
        }
    }
    if let Some(s) = &scene {
        if let Some(g) = s.params[2]
            .chunks_exact(4)
            .position(|q| q.iter().all(|&c| c == 0.0))
        {
            return Err(bad(
                "scene.quats",
                format!("Gaussian {g} has the zero quaternion (no rotation)"),
            ));
        }
    }
    Ok(ModelState {
        step,
        layers,
        scene,
        poses,
    })
}
