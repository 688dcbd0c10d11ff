//! NeuMan's SMPL file as HUGS reads it, `4d_humans/smpl_optimized_aligned_scale.npz`:
//! per frame `global_orient` (F×3), `body_pose` (F×69), `betas` (F×10), `transl` (F×3),
//! and `scale` (F, or one value). Errors name the file and the key.

use std::collections::BTreeMap;
use std::path::Path;

use glam::DVec3;

use crate::body::kinematics::Pose;
use crate::body::NUM_JOINTS;
use crate::npy::{self, Array, NpyError};

/// Per-frame SMPL parameters of one sequence.
#[derive(Clone, Debug, PartialEq)]
pub struct SmplSequence {
    pub poses: Vec<Pose>,
    pub betas: Vec<Vec<f64>>,
    pub translations: Vec<DVec3>,
    pub scales: Vec<f64>,
}

impl SmplSequence {
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    pub fn write_npz(&self, path: &Path) -> Result<(), NpyError> {
        let f = self.len();
        let nb = self.betas.first().map_or(10, Vec::len);
        let mut a = BTreeMap::new();
        a.insert(
            "global_orient".into(),
            Array::f64(
                vec![f, 3],
                self.poses.iter().flat_map(|p| p[0].to_array()).collect(),
            ),
        );
        a.insert(
            "body_pose".into(),
            Array::f64(
                vec![f, 69],
                self.poses
                    .iter()
                    .flat_map(|p| p[1..].iter().flat_map(|r| r.to_array()).collect::<Vec<_>>())
                    .collect(),
            ),
        );
        a.insert(
            "betas".into(),
            Array::f64(vec![f, nb], self.betas.iter().flatten().copied().collect()),
        );
        a.insert(
            "transl".into(),
            Array::f64(
                vec![f, 3],
                self.translations
                    .iter()
                    .flat_map(|t| t.to_array())
                    .collect(),
            ),
        );
        a.insert("scale".into(), Array::f64(vec![f], self.scales.clone()));
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(|error| NpyError::Io {
                file: parent.display().to_string(),
                error,
            })?;
        }
        npy::write_npz(path, &a)
    }

    pub fn read_npz(path: &Path) -> Result<Self, NpyError> {
        let file = path.display().to_string();
        let a = npy::read_npz(path)?;
        let go = npy::require(&a, &file, "global_orient", &[None, Some(3)])?;
        let f = go.shape[0];
        let bp = npy::require(
            &a,
            &file,
            "body_pose",
            &[Some(f), Some(3 * (NUM_JOINTS - 1))],
        )?;
        let betas = npy::require(&a, &file, "betas", &[Some(f), None])
            .or_else(|_| npy::require(&a, &file, "betas", &[None]))?;
        let tr = npy::require(&a, &file, "transl", &[Some(f), Some(3)])?;
        let scale = npy::require(&a, &file, "scale", &[None])?;
        if scale.data.len() != f && scale.data.len() != 1 {
            return Err(NpyError::Format {
                file,
                key: Some("scale".into()),
                problem: format!("{} values for {f} frames (need {f} or 1)", scale.data.len()),
            });
        }
        let poses = (0..f)
            .map(|i| {
                let mut p: Pose = [DVec3::ZERO; NUM_JOINTS];
                p[0] = DVec3::from_slice(&go.data[3 * i..3 * i + 3]);
                for j in 1..NUM_JOINTS {
                    let b = i * 69 + 3 * (j - 1);
                    p[j] = DVec3::from_slice(&bp.data[b..b + 3]);
                }
                p
            })
            .collect();
        let nb = *betas.shape.last().expect("betas has a shape");
        if nb == 0 {
            return Err(NpyError::Format {
                file,
                key: Some("betas".into()),
                problem: format!(
                    "shape {:?}: no shape coefficients (SMPL has 10)",
                    betas.shape
                ),
            });
        }
        for (key, a) in [
            ("global_orient", go),
            ("body_pose", bp),
            ("betas", betas),
            ("transl", tr),
            ("scale", scale),
        ] {
            if let Some(i) = a.data.iter().position(|v| !v.is_finite()) {
                return Err(NpyError::Format {
                    file,
                    key: Some(key.into()),
                    problem: format!("value {i} is {} (not finite)", a.data[i]),
                });
            }
        }
        if let Some(i) = tr
            .data
            .iter()
            .position(|v| v.abs() > crate::motion::MAX_TRANSLATION)
        {
            return Err(NpyError::Format {
                file,
                key: Some("transl".into()),
                problem: format!(
                    "value {i} is {}; drape takes translations within {} of the origin",
                    tr.data[i],
                    crate::motion::MAX_TRANSLATION
                ),
            });
        }
        if let Some(i) = scale.data.iter().position(|&s| !(s > 0.0 && s < 1e6)) {
            return Err(NpyError::Format {
                file,
                key: Some("scale".into()),
                problem: format!(
                    "value {i} is {}; the scale of a body must be positive",
                    scale.data[i]
                ),
            });
        }
        let betas = if betas.shape.len() == 2 {
            betas.data.chunks_exact(nb).map(<[f64]>::to_vec).collect()
        } else {
            vec![betas.data.clone(); f]
        };
        Ok(Self {
            poses,
            betas,
            translations: tr.data.chunks_exact(3).map(DVec3::from_slice).collect(),
            scales: if scale.data.len() == 1 {
                vec![scale.data[0]; f]
            } else {
                scale.data.clone()
            },
        })
    }
}
