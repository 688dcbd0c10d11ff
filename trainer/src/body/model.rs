//! The SMPL body model format and its `.npz` layout (as the `smplx` package reads it):
//! `v_template` V×3, `shapedirs` V×3×B, `posedirs` V×3×207, `J_regressor` 24×V,
//! `weights` V×24, `kintree_table` 2×24 (row 0: parents, the root's any value),
//! `f` F×3. Every array is validated on load; errors name the file and the key.

use std::collections::BTreeMap;
use std::path::Path;

use glam::DVec3;

use crate::npy::{self, Array, Dtype, NpyError};

/// Joints of the SMPL skeleton.
pub const NUM_JOINTS: usize = 24;
/// Pose-blend-shape features: 9 per non-root joint.
pub const NUM_POSE_FEATURES: usize = 9 * (NUM_JOINTS - 1);

/// SMPL's joint names, in its order.
pub const JOINT_NAMES: [&str; NUM_JOINTS] = [
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
];

/// SMPL's kinematic tree: parent of each joint (-1 for the root).
pub const PARENTS: [i32; NUM_JOINTS] = [
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
];

/// A body model in the SMPL format, in f64.
#[derive(Clone, Debug, PartialEq)]
pub struct SmplModel {
    /// V×3.
    pub v_template: Vec<DVec3>,
    /// `shapedirs[v][axis][b]`.
    pub shapedirs: Vec<[Vec<f64>; 3]>,
    /// Shape coefficients B.
    pub num_betas: usize,
    /// `posedirs[v][axis][k]`, k < 207 (all zero is allowed).
    pub posedirs: Vec<[Vec<f64>; 3]>,
    /// 24 rows of V weights.
    pub j_regressor: Vec<Vec<f64>>,
    /// `weights[v][j]`, each row summing to 1.
    pub weights: Vec<[f64; NUM_JOINTS]>,
    pub parents: [i32; NUM_JOINTS],
    pub faces: Vec<[u32; 3]>,
}

impl SmplModel {
    pub fn num_vertices(&self) -> usize {
        self.v_template.len()
    }

    /// Loads a model from an `.npz` in the smplx layout.
    pub fn load_npz(path: &Path) -> Result<Self, NpyError> {
        let arrays = npy::read_npz(path)?;
        Self::from_arrays(&arrays, &path.display().to_string())
    }

    /// Builds a model from arrays, validating every shape and value.
    pub fn from_arrays(arrays: &BTreeMap<String, Array>, file: &str) -> Result<Self, NpyError> {
        let bad = |key: &str, problem: String| NpyError::Format {
            file: file.to_string(),
            key: Some(key.to_string()),
            problem,
        };
        let vt = npy::require(arrays, file, "v_template", &[None, Some(3)])?;
        let v = vt.shape[0];
        if v == 0 {
            return Err(bad("v_template", "no vertices".into()));
        }
        let sd = npy::require(arrays, file, "shapedirs", &[Some(v), Some(3), None])?;
        let b = sd.shape[2];
        let pd = npy::require(
            arrays,
            file,
            "posedirs",
            &[Some(v), Some(3), Some(NUM_POSE_FEATURES)],
        )?;
        let jr = npy::require(arrays, file, "J_regressor", &[Some(NUM_JOINTS), Some(v)])?;
        let w = npy::require(arrays, file, "weights", &[Some(v), Some(NUM_JOINTS)])?;
        let kt = npy::require(arrays, file, "kintree_table", &[Some(2), Some(NUM_JOINTS)])?;
        let f = npy::require(arrays, file, "f", &[None, Some(3)])?;
        if !matches!(f.dtype, Dtype::U32 | Dtype::I32 | Dtype::I64 | Dtype::U8) {
            return Err(bad(
                "f",
                format!("dtype {:?}: face indices must be integers", f.dtype),
            ));
        }
        let mut parents = [-1i32; NUM_JOINTS];
        for (j, p) in parents.iter_mut().enumerate().skip(1) {
            let value = kt.data[j];
            if !(value >= 0.0 && value < j as f64) || value.fract() != 0.0 {
                return Err(bad(
                    "kintree_table",
                    format!("parent of joint {j} is {value}; parents must precede their children"),
                ));
            }
            *p = value as i32;
        }
        let faces: Vec<[u32; 3]> = f
            .data
            .chunks_exact(3)
            .map(|c| [c[0] as u32, c[1] as u32, c[2] as u32])
            .collect();
        if let Some(i) = f
            .data
            .iter()
            .position(|&x| x < 0.0 || x >= v as f64 || x.fract() != 0.0)
        {
            return Err(bad(
                "f",
                format!(
                    "index {} at position {i} is not a vertex (V = {v})",
                    f.data[i]
                ),
            ));
        }
        let weights: Vec<[f64; NUM_JOINTS]> = w
            .data
            .chunks_exact(NUM_JOINTS)
            .map(|c| c.try_into().expect("24"))
            .collect();
        for (i, row) in weights.iter().enumerate() {
            let s: f64 = row.iter().sum();
            if (s - 1.0).abs() > 1e-3 || row.iter().any(|&x| x < -1e-6) {
                return Err(bad("weights", format!("row {i} sums to {s} (or has a negative weight); skinning weights must be a partition of unity")));
            }
        }
        let per_vertex = |a: &Array, k: usize| -> Vec<[Vec<f64>; 3]> {
            (0..v)
                .map(|i| {
                    let base = i * 3 * k;
                    [
                        a.data[base..base + k].to_vec(),
                        a.data[base + k..base + 2 * k].to_vec(),
                        a.data[base + 2 * k..base + 3 * k].to_vec(),
                    ]
                })
                .collect()
        };
        Ok(Self {
            v_template: vt.data.chunks_exact(3).map(DVec3::from_slice).collect(),
            shapedirs: per_vertex(sd, b),
            num_betas: b,
            posedirs: per_vertex(pd, NUM_POSE_FEATURES),
            j_regressor: jr.data.chunks_exact(v).map(|r| r.to_vec()).collect(),
            weights,
            parents,
            faces,
        })
    }

    /// The arrays of the smplx layout (what `write_npz` saves).
    pub fn to_arrays(&self) -> BTreeMap<String, Array> {
        let v = self.num_vertices();
        let flat3 = |rows: &[[Vec<f64>; 3]]| {
            rows.iter()
                .flat_map(|r| r.iter().flat_map(|c| c.iter().copied()).collect::<Vec<_>>())
                .collect::<Vec<_>>()
        };
        let mut kintree = vec![0.0; 2 * NUM_JOINTS];
        for j in 0..NUM_JOINTS {
            // SMPL files store the root's parent as uint32 -1.
            kintree[j] = if self.parents[j] < 0 {
                4_294_967_295.0
            } else {
                f64::from(self.parents[j])
            };
            kintree[NUM_JOINTS + j] = j as f64;
        }
        let mut out = BTreeMap::new();
        out.insert(
            "v_template".into(),
            Array::f64(
                vec![v, 3],
                self.v_template.iter().flat_map(|v| v.to_array()).collect(),
            ),
        );
        out.insert(
            "shapedirs".into(),
            Array::f64(vec![v, 3, self.num_betas], flat3(&self.shapedirs)),
        );
        out.insert(
            "posedirs".into(),
            Array::f64(vec![v, 3, NUM_POSE_FEATURES], flat3(&self.posedirs)),
        );
        out.insert(
            "J_regressor".into(),
            Array::f64(
                vec![NUM_JOINTS, v],
                self.j_regressor.iter().flatten().copied().collect(),
            ),
        );
        out.insert(
            "weights".into(),
            Array::f64(
                vec![v, NUM_JOINTS],
                self.weights.iter().flatten().copied().collect(),
            ),
        );
        out.insert(
            "kintree_table".into(),
            Array::new(Dtype::I64, vec![2, NUM_JOINTS], kintree),
        );
        out.insert(
            "f".into(),
            Array::new(
                Dtype::U32,
                vec![self.faces.len(), 3],
                self.faces.iter().flatten().map(|&i| f64::from(i)).collect(),
            ),
        );
        out
    }

    pub fn write_npz(&self, path: &Path) -> Result<(), NpyError> {
        npy::write_npz(path, &self.to_arrays())
    }
}
