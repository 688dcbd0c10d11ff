//! The project's own body model, in the SMPL format: a closed, human-proportioned
//! triangle mesh in T-pose (y up, facing +z, the body's left at +x, about 1.72 m),
//! SMPL's 24 joints with their order and meaning, smooth skinning weights, a joint
//! regressor, two shape directions (height, girth) and zero pose blend shapes.
//!
//! The surface is the zero level of a smooth union of tapered capsules (one or two
//! per bone) and ellipsoids (torso, head), extracted by marching tetrahedra on a
//! regular grid: a single isosurface is closed, manifold and free of
//! self-intersections by construction.

use std::collections::HashMap;

use glam::DVec3;

use crate::body::model::{SmplModel, NUM_JOINTS, NUM_POSE_FEATURES, PARENTS};
use crate::mesh::adjacency;

/// Rest positions of SMPL's joints for the default body, in T-pose (metres).
pub const JOINTS: [DVec3; NUM_JOINTS] = [
    DVec3::new(0.0, 0.93, 0.0),      // pelvis
    DVec3::new(0.085, 0.86, 0.0),    // left hip
    DVec3::new(-0.085, 0.86, 0.0),   // right hip
    DVec3::new(0.0, 1.04, -0.01),    // spine1
    DVec3::new(0.095, 0.49, 0.01),   // left knee
    DVec3::new(-0.095, 0.49, 0.01),  // right knee
    DVec3::new(0.0, 1.16, -0.01),    // spine2
    DVec3::new(0.095, 0.08, -0.02),  // left ankle
    DVec3::new(-0.095, 0.08, -0.02), // right ankle
    DVec3::new(0.0, 1.28, 0.0),      // spine3
    DVec3::new(0.10, 0.025, 0.11),   // left foot
    DVec3::new(-0.10, 0.025, 0.11),  // right foot
    DVec3::new(0.0, 1.46, 0.0),      // neck
    DVec3::new(0.07, 1.40, 0.0),     // left collar
    DVec3::new(-0.07, 1.40, 0.0),    // right collar
    DVec3::new(0.0, 1.56, 0.02),     // head
    DVec3::new(0.18, 1.41, 0.0),     // left shoulder
    DVec3::new(-0.18, 1.41, 0.0),    // right shoulder
    DVec3::new(0.44, 1.41, 0.0),     // left elbow
    DVec3::new(-0.44, 1.41, 0.0),    // right elbow
    DVec3::new(0.68, 1.41, 0.0),     // left wrist
    DVec3::new(-0.68, 1.41, 0.0),    // right wrist
    DVec3::new(0.76, 1.41, 0.0),     // left hand
    DVec3::new(-0.76, 1.41, 0.0),    // right hand
];

/// A piece of the body: a tapered capsule from `a` to `b`, owned by joint `joint`
/// (whose rotation moves it), with space squashed along z by `z_squash`.
#[derive(Clone, Copy, Debug)]
struct Part {
    a: DVec3,
    b: DVec3,
    ra: f64,
    rb: f64,
    z_squash: f64,
    joint: usize,
}

const fn part(a: DVec3, b: DVec3, ra: f64, rb: f64, z_squash: f64, joint: usize) -> Part {
    Part {
        a,
        b,
        ra,
        rb,
        z_squash,
        joint,
    }
}

fn parts() -> Vec<Part> {
    let j = JOINTS;
    let mut p = vec![
        // Pelvis and torso, wider than deep.
        part(
            DVec3::new(0.055, 0.86, 0.0),
            DVec3::new(0.07, 1.02, 0.0),
            0.115,
            0.11,
            0.72,
            0,
        ),
        part(
            DVec3::new(-0.055, 0.86, 0.0),
            DVec3::new(-0.07, 1.02, 0.0),
            0.115,
            0.11,
            0.72,
            0,
        ),
        part(
            DVec3::new(0.065, 1.02, 0.0),
            DVec3::new(0.07, 1.14, 0.0),
            0.105,
            0.11,
            0.7,
            3,
        ),
        part(
            DVec3::new(-0.065, 1.02, 0.0),
            DVec3::new(-0.07, 1.14, 0.0),
            0.105,
            0.11,
            0.7,
            3,
        ),
        part(
            DVec3::new(0.07, 1.14, 0.0),
            DVec3::new(0.075, 1.26, 0.0),
            0.11,
            0.115,
            0.72,
            6,
        ),
        part(
            DVec3::new(-0.07, 1.14, 0.0),
            DVec3::new(-0.075, 1.26, 0.0),
            0.11,
            0.115,
            0.72,
            6,
        ),
        part(
            DVec3::new(0.075, 1.26, 0.0),
            DVec3::new(0.08, 1.36, 0.0),
            0.115,
            0.1,
            0.72,
            9,
        ),
        part(
            DVec3::new(-0.075, 1.26, 0.0),
            DVec3::new(-0.08, 1.36, 0.0),
            0.115,
            0.1,
            0.72,
            9,
        ),
        // Neck and head.
        part(
            DVec3::new(0.0, 1.38, 0.0),
            DVec3::new(0.0, 1.50, 0.01),
            0.06,
            0.055,
            1.0,
            12,
        ),
        part(
            DVec3::new(0.0, 1.55, 0.025),
            DVec3::new(0.0, 1.64, 0.02),
            0.09,
            0.085,
            0.95,
            15,
        ),
    ];
    for side in [1.0, -1.0] {
        let (l, s) = (if side > 0.0 { 0 } else { 1 }, side);
        let m = |v: DVec3| DVec3::new(v[0] * s, v[1], v[2]);
        p.extend([
            // Collar to shoulder, upper arm, forearm, hand.
            part(
                m(DVec3::new(0.06, 1.38, 0.0)),
                m(j[16 + l]),
                0.06,
                0.058,
                0.85,
                13 + l,
            ),
            part(j[16 + l], j[18 + l], 0.052, 0.042, 1.0, 16 + l),
            part(j[18 + l], j[20 + l], 0.042, 0.032, 1.0, 18 + l),
            part(j[20 + l], j[22 + l], 0.035, 0.034, 0.6, 20 + l),
            part(
                j[22 + l],
                m(DVec3::new(0.83, 1.41, 0.0)),
                0.034,
                0.03,
                0.6,
                22 + l,
            ),
            // Thigh, shin, foot, toes.
            part(j[1 + l], j[4 + l], 0.085, 0.055, 1.0, 1 + l),
            part(j[4 + l], j[7 + l], 0.053, 0.04, 1.0, 4 + l),
            part(j[7 + l], j[10 + l], 0.045, 0.038, 0.75, 7 + l),
            part(
                j[10 + l],
                m(DVec3::new(0.105, 0.025, 0.16)),
                0.035,
                0.03,
                0.75,
                10 + l,
            ),
        ]);
    }
    p
}

/// Distance from p to the segment a-b and the parameter of the closest point.
fn segment_distance(p: DVec3, a: DVec3, b: DVec3) -> (f64, f64) {
    let ab = b - a;
    let t = ((p - a).dot(ab) / ab.dot(ab).max(1e-12)).clamp(0.0, 1.0);
    ((p - (a + ab * t)).length(), t)
}

fn part_sdf(p: DVec3, q: &Part) -> f64 {
    // Squash space along z around the part's axis, then a tapered capsule (linear
    // radius along the closest point: not an exact distance, which the level set
    // does not need).
    let centre_z = 0.5 * (q.a[2] + q.b[2]);
    let ps = DVec3::new(p[0], p[1], centre_z + (p[2] - centre_z) / q.z_squash);
    let (d, t) = segment_distance(ps, q.a, q.b);
    (d - (q.ra + (q.rb - q.ra) * t)) * q.z_squash.min(1.0)
}

/// Polynomial smooth minimum (blend radius k).
fn smin(a: f64, b: f64, k: f64) -> f64 {
    let h = (0.5 + 0.5 * (b - a) / k).clamp(0.0, 1.0);
    b + (a - b) * h - k * h * (1.0 - h)
}

fn body_sdf(p: DVec3, parts: &[Part]) -> f64 {
    parts.iter().fold(f64::MAX, |acc, q| {
        let d = part_sdf(p, q);
        if acc == f64::MAX {
            d
        } else {
            smin(acc, d, 0.025)
        }
    })
}

/// Marching tetrahedra of `f` over the box [lo, hi] with cell size h: a closed mesh
/// with outward-facing triangles, vertices welded on grid edges.
fn marching_tetrahedra(
    f: &dyn Fn(DVec3) -> f64,
    lo: DVec3,
    hi: DVec3,
    h: f64,
) -> (Vec<DVec3>, Vec<[u32; 3]>) {
    let n = [0, 1, 2].map(|k| ((hi[k] - lo[k]) / h).ceil() as usize + 1);
    let idx = |x: usize, y: usize, z: usize| (x * n[1] + y) * n[2] + z;
    let pos = |x: usize, y: usize, z: usize| {
        DVec3::new(
            lo[0] + x as f64 * h,
            lo[1] + y as f64 * h,
            lo[2] + z as f64 * h,
        )
    };
    let mut values = vec![0.0; n[0] * n[1] * n[2]];
    for x in 0..n[0] {
        for y in 0..n[1] {
            for z in 0..n[2] {
                let v = f(pos(x, y, z));
                // Keep grid values away from zero: a crossing then never lies within
                // ~8% of a grid point, which would make slivers and near-duplicate
                // vertices (any nonzero values still give a closed surface).
                let eps = 0.15 * h;
                values[idx(x, y, z)] = if v.abs() < eps {
                    if v < 0.0 {
                        -eps
                    } else {
                        eps
                    }
                } else {
                    v
                };
            }
        }
    }
    // Kuhn subdivision of the cube into 6 tetrahedra along the 0-7 diagonal: shared
    // faces of neighbouring cubes are split the same way.
    const CORNERS: [[usize; 3]; 8] = [
        [0, 0, 0],
        [1, 0, 0],
        [0, 1, 0],
        [1, 1, 0],
        [0, 0, 1],
        [1, 0, 1],
        [0, 1, 1],
        [1, 1, 1],
    ];
    const TETS: [[usize; 4]; 6] = [
        [0, 1, 3, 7],
        [0, 3, 2, 7],
        [0, 2, 6, 7],
        [0, 6, 4, 7],
        [0, 4, 5, 7],
        [0, 5, 1, 7],
    ];
    let mut vertices: Vec<DVec3> = Vec::new();
    let mut on_edge: HashMap<(usize, usize), u32> = HashMap::new();
    let mut faces = Vec::new();
    let mut vertex_on = |a: usize,
                         pa: DVec3,
                         va: f64,
                         b: usize,
                         pb: DVec3,
                         vb: f64,
                         vertices: &mut Vec<DVec3>|
     -> u32 {
        let key = (a.min(b), a.max(b));
        *on_edge.entry(key).or_insert_with(|| {
            let t = va / (va - vb);
            vertices.push(pa + (pb - pa) * t);
            (vertices.len() - 1) as u32
        })
    };
    for x in 0..n[0] - 1 {
        for y in 0..n[1] - 1 {
            for z in 0..n[2] - 1 {
                let corner = |c: usize| {
                    let o = CORNERS[c];
                    let (cx, cy, cz) = (x + o[0], y + o[1], z + o[2]);
                    (idx(cx, cy, cz), pos(cx, cy, cz))
                };
                for tet in TETS {
                    let pts = tet.map(corner);
                    let vals = pts.map(|(i, _)| values[i]);
                    let inside: Vec<usize> = (0..4).filter(|&k| vals[k] < 0.0).collect();
                    let outside: Vec<usize> = (0..4).filter(|&k| vals[k] >= 0.0).collect();
                    let mut cut = |i: usize, o: usize, vertices: &mut Vec<DVec3>| {
                        vertex_on(
                            pts[i].0, pts[i].1, vals[i], pts[o].0, pts[o].1, vals[o], vertices,
                        )
                    };
                    let mut tris: Vec<[u32; 3]> = Vec::new();
                    match inside.len() {
                        1 => {
                            let i = inside[0];
                            tris.push([
                                cut(i, outside[0], &mut vertices),
                                cut(i, outside[1], &mut vertices),
                                cut(i, outside[2], &mut vertices),
                            ]);
                        }
                        3 => {
                            let o = outside[0];
                            tris.push([
                                cut(inside[0], o, &mut vertices),
                                cut(inside[1], o, &mut vertices),
                                cut(inside[2], o, &mut vertices),
                            ]);
                        }
                        2 => {
                            let (i0, i1, o0, o1) = (inside[0], inside[1], outside[0], outside[1]);
                            let a = cut(i0, o0, &mut vertices);
                            let b = cut(i0, o1, &mut vertices);
                            let c = cut(i1, o1, &mut vertices);
                            let d = cut(i1, o0, &mut vertices);
                            tris.push([a, b, c]);
                            tris.push([a, c, d]);
                        }
                        _ => {}
                    }
                    // Orient outward: the normal points from the inside corners to the outside ones.
                    let centre = |ks: &[usize]| {
                        ks.iter().fold(DVec3::ZERO, |acc, &k| {
                            acc + pts[k].1 * (1.0 / ks.len() as f64)
                        })
                    };
                    if !tris.is_empty() {
                        let out_dir = centre(&outside) - centre(&inside);
                        for t in &mut tris {
                            let [p0, p1, p2] = t.map(|v| vertices[v as usize]);
                            if (p1 - p0).cross(p2 - p0).dot(out_dir) < 0.0 {
                                t.swap(1, 2);
                            }
                        }
                        faces.extend(tris);
                    }
                }
            }
        }
    }
    // Drop triangles that collapsed to a point or a line (two cuts on one welded vertex).
    faces.retain(|f: &[u32; 3]| f[0] != f[1] && f[1] != f[2] && f[0] != f[2]);
    (vertices, faces)
}

/// Evens out the triangles: each vertex moves halfway to its neighbours' centroid,
/// then back onto the zero level along the field's gradient. Connectivity is
/// unchanged, so the mesh stays closed.
fn relax_on_surface(
    v: &mut [DVec3],
    faces: &[[u32; 3]],
    f: &dyn Fn(DVec3) -> f64,
    iterations: usize,
) {
    let adj = adjacency(v.len(), faces);
    let h = 1e-4;
    for _ in 0..iterations {
        let prev = v.to_vec();
        for (i, p) in v.iter_mut().enumerate() {
            let nb = &adj[i];
            if nb.is_empty() {
                continue;
            }
            let c = nb.iter().fold(DVec3::ZERO, |acc, &k| {
                acc + prev[k as usize] * (1.0 / nb.len() as f64)
            });
            let mut q = prev[i] * 0.5 + c * 0.5;
            for _ in 0..3 {
                let d = f(q);
                let g = DVec3::from_array([0, 1, 2].map(|k| {
                    let mut a = q;
                    let mut b = q;
                    a[k] += h;
                    b[k] -= h;
                    (f(a) - f(b)) / (2.0 * h)
                }));
                let g2 = g.dot(g).max(1e-12);
                q -= g * (d / g2);
            }
            *p = q;
        }
    }
}

/// Options of the procedural body.
#[derive(Clone, Copy, Debug)]
pub struct BodyOptions {
    /// Grid cell size of the surface extraction (metres); smaller means more vertices.
    pub cell: f64,
    /// Shape coefficients stored (SMPL files have 10 or 300); the first two are used.
    pub num_betas: usize,
}

impl Default for BodyOptions {
    fn default() -> Self {
        Self {
            cell: 0.028,
            num_betas: 10,
        }
    }
}

/// Builds the default body.
pub fn default_body(options: &BodyOptions) -> SmplModel {
    let parts = parts();
    let sdf = |p: DVec3| body_sdf(p, &parts);
    let (mut v, faces) = marching_tetrahedra(
        &sdf,
        DVec3::new(-0.95, -0.06, -0.25),
        DVec3::new(0.95, 1.80, 0.30),
        options.cell,
    );
    let nv = v.len();
    relax_on_surface(&mut v, &faces, &sdf, 6);

    // Skinning weights: Gaussian falloff from each joint's parts, smoothed over the
    // mesh, normalized to a partition of unity.
    let sigma = 0.035;
    let mut weights: Vec<[f64; NUM_JOINTS]> = v
        .iter()
        .map(|&p| {
            let mut w = [0.0; NUM_JOINTS];
            // A point before the start of a part (in its rounded cap, towards the
            // parent) belongs to the parent: penalise it, or a lowered arm would drag
            // the top of the shoulder with it.
            let dists: Vec<(usize, f64)> = parts
                .iter()
                .map(|q| {
                    let ab = q.b - q.a;
                    let t_raw = (p - q.a).dot(ab) / ab.dot(ab).max(1e-12);
                    (
                        q.joint,
                        part_sdf(p, q) + 3.0 * (-t_raw).max(0.0) * ab.length(),
                    )
                })
                .collect();
            let best = dists.iter().map(|d| d.1).fold(f64::MAX, f64::min);
            for (j, d) in dists {
                let e = (d - best) / sigma;
                w[j] += (-e * e).exp();
            }
            w
        })
        .collect();
    let adj = adjacency(nv, &faces);
    for _ in 0..4 {
        let prev = weights.clone();
        for (i, w) in weights.iter_mut().enumerate() {
            let nb = &adj[i];
            for j in 0..NUM_JOINTS {
                let mean =
                    nb.iter().map(|&k| prev[k as usize][j]).sum::<f64>() / nb.len().max(1) as f64;
                w[j] = 0.5 * prev[i][j] + 0.5 * mean;
            }
        }
    }
    for w in &mut weights {
        let s: f64 = w.iter().sum();
        for x in w.iter_mut() {
            *x /= s;
        }
    }

    // Joint regressor: for each joint, the ring of surface vertices in a thin slab
    // through the joint, perpendicular to its bone, that the joint moves (weight at
    // least 0.2, which keeps the other leg or the arms out); the ring's centroid lies
    // on the limb's axis.
    let mut j_regressor = vec![vec![0.0; nv]; NUM_JOINTS];
    for (j, row) in j_regressor.iter_mut().enumerate() {
        let c = JOINTS[j];
        // The child that continues the limb (for the pelvis and spine3, the spine, the
        // most central child).
        let child = (0..NUM_JOINTS)
            .filter(|&k| PARENTS[k] == j as i32)
            .min_by(|&a, &b| {
                (JOINTS[a][0] - c[0])
                    .abs()
                    .total_cmp(&(JOINTS[b][0] - c[0]).abs())
            });
        let axis = match child {
            Some(k) => (JOINTS[k] - c).normalize_or(DVec3::Z),
            None => (c - JOINTS[PARENTS[j] as usize]).normalize_or(DVec3::Z),
        };
        let mut slab = 0.012;
        loop {
            let candidates: Vec<(usize, f64)> = v
                .iter()
                .enumerate()
                .filter(|(i, p)| (**p - c).dot(axis).abs() < slab && weights[*i][j] >= 0.2)
                .map(|(i, p)| (i, (*p - c).length()))
                .filter(|&(_, d)| d < 0.3)
                .collect();
            let mut ring: Vec<usize> = candidates.iter().map(|c| c.0).collect();
            // A coarse surface (a large cell) may have no ring of six near the joint:
            // then its six nearest vertices, whatever their weights.
            if ring.len() < 6 && slab > 0.5 {
                let mut nearest: Vec<(usize, f64)> = v
                    .iter()
                    .enumerate()
                    .map(|(i, p)| (i, (*p - c).length()))
                    .collect();
                nearest.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
                ring = nearest.into_iter().take(6).map(|(i, _)| i).collect();
            }
            if ring.len() >= 6 || slab > 0.5 {
                for &i in &ring {
                    row[i] = 1.0 / ring.len() as f64;
                }
                break;
            }
            slab *= 1.5;
        }
    }

    // Shape directions: 0 = height (+5% per unit, from the floor), 1 = girth (+8% of
    // the distance from the nearest part's axis per unit); the rest zero.
    let b = options.num_betas.max(2);
    let shapedirs: Vec<[Vec<f64>; 3]> = v
        .iter()
        .map(|&p| {
            let mut d = [vec![0.0; b], vec![0.0; b], vec![0.0; b]];
            d[1][0] = 0.05 * p[1];
            let nearest = parts
                .iter()
                .min_by(|x, y| part_sdf(p, x).total_cmp(&part_sdf(p, y)))
                .expect("the body has parts");
            let (_, t) = segment_distance(p, nearest.a, nearest.b);
            let axis = nearest.a + (nearest.b - nearest.a) * t;
            let radial = p - axis;
            for k in 0..3 {
                d[k][1] = 0.08 * radial[k];
            }
            d
        })
        .collect();

    SmplModel {
        v_template: v,
        shapedirs,
        num_betas: b,
        posedirs: vec![
            [
                vec![0.0; NUM_POSE_FEATURES],
                vec![0.0; NUM_POSE_FEATURES],
                vec![0.0; NUM_POSE_FEATURES]
            ];
            nv
        ],
        j_regressor,
        weights,
        parents: PARENTS,
        faces,
    }
}
