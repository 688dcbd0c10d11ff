//! Gaussians initialized from a skinned mesh, as HUGS does for the body and Cloth-HUGS
//! for the garments: the mesh subdivided (midpoint, twice in the paper preset) with
//! skinning weights and shape blend shapes averaged onto the new vertices; one Gaussian
//! per vertex, rotated so its third axis is the surface normal, flat along the normal
//! and as wide as half the mean incident edge in the tangent plane; opacity 0.1, SH DC
//! 0.5.

use std::collections::HashMap;

use crate::avatar::groups::Layer;
use drape_engine::ops::splat::scene::GaussianCloud;
use drape_shared::splat::layout::MAX_SH_COEFFS;
use drape_shared::splat::project::Gaussian;
use glam::DVec3;

use crate::body::model::NUM_JOINTS;
use crate::mesh::{rotation_to_quaternion, vertex_normals};

/// A triangle mesh with per-vertex skinning weights and shape blend shapes.
#[derive(Clone, Debug, PartialEq)]
pub struct SkinnedMesh {
    pub vertices: Vec<DVec3>,
    pub faces: Vec<[u32; 3]>,
    pub weights: Vec<[f64; NUM_JOINTS]>,
    /// `shapedirs[v][axis][b]` (may have zero betas).
    pub shapedirs: Vec<[Vec<f64>; 3]>,
}

impl SkinnedMesh {
    /// One level of midpoint subdivision: every triangle into four, new vertices on
    /// edge midpoints with averaged weights and blend shapes.
    pub fn subdivide(&self) -> Self {
        let mut out = self.clone();
        let mut midpoint: HashMap<(u32, u32), u32> = HashMap::new();
        let mut faces = Vec::with_capacity(self.faces.len() * 4);
        let mut mid = |a: u32, b: u32, out: &mut SkinnedMesh| -> u32 {
            *midpoint.entry((a.min(b), a.max(b))).or_insert_with(|| {
                let (ia, ib) = (a as usize, b as usize);
                out.vertices
                    .push((self.vertices[ia] + self.vertices[ib]) * 0.5);
                let mut w = [0.0; NUM_JOINTS];
                for j in 0..NUM_JOINTS {
                    w[j] = 0.5 * (self.weights[ia][j] + self.weights[ib][j]);
                }
                out.weights.push(w);
                let d = [0, 1, 2].map(|k| {
                    self.shapedirs[ia][k]
                        .iter()
                        .zip(&self.shapedirs[ib][k])
                        .map(|(x, y)| 0.5 * (x + y))
                        .collect()
                });
                out.shapedirs.push(d);
                (out.vertices.len() - 1) as u32
            })
        };
        for f in &self.faces {
            let [a, b, c] = *f;
            let ab = mid(a, b, &mut out);
            let bc = mid(b, c, &mut out);
            let ca = mid(c, a, &mut out);
            faces.extend([[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]);
        }
        out.faces = faces;
        out
    }
}

/// Gaussians at the vertices of `mesh` after `levels` subdivisions, with their
/// skinning weights (the subdivided mesh is returned too).
pub fn gaussians_from_mesh(
    mesh: &SkinnedMesh,
    levels: u32,
    sh_degree: u32,
    layer: Layer,
) -> (GaussianCloud, SkinnedMesh) {
    let mut m = mesh.clone();
    for _ in 0..levels {
        m = m.subdivide();
    }
    let normals = vertex_normals(&m.vertices, &m.faces);
    let mut edge_sum = vec![0.0; m.vertices.len()];
    let mut edge_count = vec![0u32; m.vertices.len()];
    for f in &m.faces {
        for k in 0..3 {
            let (a, b) = (f[k] as usize, f[(k + 1) % 3] as usize);
            let l = (m.vertices[a] - m.vertices[b]).length();
            // Each interior edge is seen from two faces, so both ends count it twice.
            edge_sum[a] += l;
            edge_sum[b] += l;
            edge_count[a] += 1;
            edge_count[b] += 1;
        }
    }
    let mut cloud = GaussianCloud::new(sh_degree);
    let opacity_logit = (0.1f64 / 0.9).ln() as f32;
    for (i, v) in m.vertices.iter().enumerate() {
        let n = normals[i];
        let helper = if n[0].abs() < 0.9 { DVec3::X } else { DVec3::Y };
        let t1 = helper.cross(n).normalize_or(DVec3::Z);
        let t2 = n.cross(t1);
        // The rotation whose columns are the tangents and the normal.
        let q = rotation_to_quaternion(&[
            [t1[0], t2[0], n[0]],
            [t1[1], t2[1], n[1]],
            [t1[2], t2[2], n[2]],
        ]);
        let mean_edge = edge_sum[i] / f64::from(edge_count[i].max(1));
        let tangent = (0.5 * mean_edge).max(1e-5);
        let mut sh = [[0.0f32; 3]; MAX_SH_COEFFS];
        sh[0] = [0.5; 3];
        cloud.push(
            &Gaussian {
                mean: v.as_vec3().to_array(),
                log_scale: [
                    tangent.ln() as f32,
                    tangent.ln() as f32,
                    (0.1 * tangent).ln() as f32,
                ],
                quat: q.map(|x| x as f32),
                opacity_logit,
                sh,
            },
            layer,
        );
    }
    (cloud, m)
}
