//! Triangle-mesh utilities in f64: edges and their face counts (watertightness),
//! vertex normals, adjacency, and a triangle-triangle intersection test for checking
//! that a mesh does not cross itself (its candidates from the spatial grid in `grid`).

use std::collections::HashMap;

use glam::DVec3;

use crate::grid::{bounds, Grid};

/// Unit quaternion (w, x, y, z) of a rotation matrix (rows).
///
/// Not glam's `DQuat::from_mat3`: that one picks its branch differently and rounds
/// differently, and the quaternions in the COLMAP files `drape synth` writes come from
/// this formula.
pub fn rotation_to_quaternion(m: &[[f64; 3]; 3]) -> [f64; 4] {
    let trace = m[0][0] + m[1][1] + m[2][2];
    let q = if trace > 0.0 {
        let s = (trace + 1.0).sqrt() * 2.0;
        [
            0.25 * s,
            (m[2][1] - m[1][2]) / s,
            (m[0][2] - m[2][0]) / s,
            (m[1][0] - m[0][1]) / s,
        ]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
        [
            (m[2][1] - m[1][2]) / s,
            0.25 * s,
            (m[0][1] + m[1][0]) / s,
            (m[0][2] + m[2][0]) / s,
        ]
    } else if m[1][1] > m[2][2] {
        let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
        [
            (m[0][2] - m[2][0]) / s,
            (m[0][1] + m[1][0]) / s,
            0.25 * s,
            (m[1][2] + m[2][1]) / s,
        ]
    } else {
        let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
        [
            (m[1][0] - m[0][1]) / s,
            (m[0][2] + m[2][0]) / s,
            (m[1][2] + m[2][1]) / s,
            0.25 * s,
        ]
    };
    // w >= 0, as COLMAP writes them (q and -q are the same rotation).
    let sign = if q[0] < 0.0 { -1.0 } else { 1.0 };
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    q.map(|v| sign * v / n)
}

/// Undirected edges with the number of faces using each.
pub fn edge_face_counts(faces: &[[u32; 3]]) -> HashMap<(u32, u32), u32> {
    let mut counts = HashMap::new();
    for f in faces {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            *counts.entry((a.min(b), a.max(b))).or_insert(0) += 1;
        }
    }
    counts
}

/// Every edge shared by exactly two faces.
pub fn is_watertight(faces: &[[u32; 3]]) -> bool {
    edge_face_counts(faces).values().all(|&c| c == 2)
}

/// Area-weighted vertex normals.
pub fn vertex_normals(vertices: &[DVec3], faces: &[[u32; 3]]) -> Vec<DVec3> {
    let mut n = vec![DVec3::ZERO; vertices.len()];
    for f in faces {
        let [a, b, c] = f.map(|i| vertices[i as usize]);
        let fn_ = (b - a).cross(c - a);
        for &i in f {
            n[i as usize] += fn_;
        }
    }
    n.into_iter().map(|v| v.normalize_or(DVec3::Z)).collect()
}

/// Neighbours of every vertex.
pub fn adjacency(num_vertices: usize, faces: &[[u32; 3]]) -> Vec<Vec<u32>> {
    let mut adj = vec![Vec::new(); num_vertices];
    for f in faces {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            if !adj[a as usize].contains(&b) {
                adj[a as usize].push(b);
            }
            if !adj[b as usize].contains(&a) {
                adj[b as usize].push(a);
            }
        }
    }
    adj
}

/// Signed volume (positive for outward-facing triangles of a closed mesh).
pub fn signed_volume(vertices: &[DVec3], faces: &[[u32; 3]]) -> f64 {
    faces
        .iter()
        .map(|f| {
            vertices[f[0] as usize].dot(vertices[f[1] as usize].cross(vertices[f[2] as usize]))
                / 6.0
        })
        .sum()
}

fn segment_hits_triangle(p: DVec3, q: DVec3, t: [DVec3; 3]) -> bool {
    // Möller-Trumbore on the segment p->q, strict inside tests.
    let (e1, e2, d) = (t[1] - t[0], t[2] - t[0], q - p);
    let h = d.cross(e2);
    let a = e1.dot(h);
    if a.abs() < 1e-14 {
        return false;
    }
    let f = 1.0 / a;
    let s = p - t[0];
    let u = f * s.dot(h);
    if !(u > 1e-9 && u < 1.0 - 1e-9) {
        return false;
    }
    let qv = s.cross(e1);
    let v = f * d.dot(qv);
    if !(v > 1e-9 && u + v < 1.0 - 1e-9) {
        return false;
    }
    let t_hit = f * e2.dot(qv);
    t_hit > 1e-9 && t_hit < 1.0 - 1e-9
}

/// Whether two triangles that share no vertex intersect (an edge of one crosses the
/// interior of the other).
pub fn triangles_intersect(a: [DVec3; 3], b: [DVec3; 3]) -> bool {
    (0..3).any(|k| segment_hits_triangle(a[k], a[(k + 1) % 3], b))
        || (0..3).any(|k| segment_hits_triangle(b[k], b[(k + 1) % 3], a))
}

/// Pairs of faces, sharing no vertex, that intersect, at most `limit` of them (the
/// same ones every run). Candidates are the pairs filed in a common cell of a grid of
/// the faces' bounds: two triangles that meet have overlapping bounds, hence a cell in
/// common.
pub fn self_intersections(
    vertices: &[DVec3],
    faces: &[[u32; 3]],
    limit: usize,
) -> Vec<(usize, usize)> {
    // Cells about two edges long: a face spans few cells and a cell holds few faces.
    let cell = faces
        .iter()
        .map(|f| (vertices[f[0] as usize] - vertices[f[1] as usize]).length())
        .sum::<f64>()
        / faces.len().max(1) as f64
        * 2.0;
    let cell = cell.max(1e-6);
    let grid = Grid::of_boxes(
        faces
            .iter()
            .map(|f| bounds(f.map(|v| vertices[v as usize]))),
        cell,
        0.0,
    );
    let mut found = std::collections::BTreeSet::new();
    for list in grid.cells() {
        for (ii, &i) in list.iter().enumerate() {
            for &j in &list[ii + 1..] {
                let (fi, fj) = (faces[i as usize], faces[j as usize]);
                if fi.iter().any(|v| fj.contains(v)) {
                    continue;
                }
                if triangles_intersect(
                    fi.map(|v| vertices[v as usize]),
                    fj.map(|v| vertices[v as usize]),
                ) {
                    found.insert((i.min(j) as usize, i.max(j) as usize));
                    if found.len() >= limit {
                        return found.into_iter().collect();
                    }
                }
            }
        }
    }
    found.into_iter().collect()
}
