//! Garments: the T-shirt and pants the project makes around the default body (regions
//! of its surface, posed in the A-pose the motions start from, lifted along the
//! normals; open at neck, sleeves, waist and legs; cylindrical UVs), OBJ garments a
//! user supplies (read with `tobj`), skinning weights from the body (nearest vertex,
//! and HUGS' 6-nearest blend with weights `exp(-d²)`, d in metres), and the attachment
//! regions that follow skinning in the simulator.
//!
//! A garment's rest shape is the shape it has on the body in its `build_pose`; its
//! edge lengths there are the lengths the simulator keeps. Making the clothes in the
//! A-pose rather than the T-pose matters: linear blend skinning stretches the skin on
//! top of the shoulder by tens of percent when the arms come down, and a shirt made in
//! the T-pose would have to stretch with it.

use std::path::Path;

use glam::DVec3;

use crate::body::kinematics::{a_pose, pose_body, t_pose, Pose};
use crate::body::model::{SmplModel, NUM_JOINTS};
use crate::grid::Grid;
use crate::mesh::vertex_normals;

/// A garment mesh bound to a body.
#[derive(Clone, Debug, PartialEq)]
pub struct Garment {
    pub name: String,
    /// Rest positions, on the body posed in `build_pose`.
    pub vertices: Vec<DVec3>,
    pub faces: Vec<[u32; 3]>,
    pub uvs: Vec<[f64; 2]>,
    /// Weights of the nearest body vertex.
    pub weights: Vec<[f64; NUM_JOINTS]>,
    /// HUGS' target: the 6 nearest body vertices blended with `exp(-d²)`.
    pub weights_blend6: Vec<[f64; NUM_JOINTS]>,
    /// Vertices that follow the body (waistband, shoulders): rigidly with
    /// `attach_joint`, so that the attached band itself never stretches.
    pub attached: Vec<bool>,
    pub attach_joint: usize,
    /// The body pose the rest positions are in (zero translation, zero shape).
    pub build_pose: Pose,
}

/// Why a garment file could not be used; names the file.
#[derive(Debug, thiserror::Error)]
pub enum GarmentError {
    /// The OBJ reader failed: the file is missing or unreadable, or is not OBJ text.
    // `error`, not `source`: the message carries it; a `source` would make anyhow
    // print it twice.
    #[error("{path}: {error}")]
    Read {
        path: String,
        error: tobj::LoadError,
    },
    /// The OBJ reads but is no garment: what is wrong with it.
    #[error("{path}: {problem}")]
    Invalid { path: String, problem: String },
}

/// Indices of the k nearest body vertices (brute force over a coarse grid).
struct NearestBody<'a> {
    vertices: &'a [DVec3],
    grid: Grid,
}

impl<'a> NearestBody<'a> {
    fn new(vertices: &'a [DVec3]) -> Self {
        Self {
            vertices,
            grid: Grid::of_points(vertices, 0.05),
        }
    }

    fn k_nearest(&self, p: DVec3, k: usize) -> Vec<(u32, f64)> {
        let mut ring = 1;
        loop {
            let mut found: Vec<(u32, f64)> = self
                .grid
                .around(p, ring)
                .map(|i| (i, (self.vertices[i as usize] - p).length()))
                .collect();
            // Everything within `ring` cells is exact; beyond needs a larger ring.
            found.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
            if found.len() >= k && found[k - 1].1 <= ring as f64 * self.grid.cell_size() {
                found.truncate(k);
                return found;
            }
            if ring > 40 {
                // Farther than 2 m: every vertex, by brute force (bounded by the body's size).
                let mut all: Vec<(u32, f64)> = self
                    .vertices
                    .iter()
                    .enumerate()
                    .map(|(i, v)| (i as u32, (*v - p).length()))
                    .collect();
                all.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
                all.truncate(k);
                return all;
            }
            ring += 1;
        }
    }
}

/// Binds garment vertices to a body whose vertices are at `body_vertices` (the body
/// posed as the garment is): nearest-vertex weights and the 6-nearest blend.
pub fn bind_weights(
    body: &SmplModel,
    body_vertices: &[DVec3],
    vertices: &[DVec3],
) -> (Vec<[f64; NUM_JOINTS]>, Vec<[f64; NUM_JOINTS]>) {
    let near = NearestBody::new(body_vertices);
    let mut nearest = Vec::with_capacity(vertices.len());
    let mut blend = Vec::with_capacity(vertices.len());
    for &v in vertices {
        let k = near.k_nearest(v, 6);
        nearest.push(body.weights[k[0].0 as usize]);
        let mut w = [0.0; NUM_JOINTS];
        let mut total = 0.0;
        for &(i, d) in &k {
            let e = (-d * d).exp();
            total += e;
            for j in 0..NUM_JOINTS {
                w[j] += e * body.weights[i as usize][j];
            }
        }
        for x in w.iter_mut() {
            *x /= total;
        }
        blend.push(w);
    }
    (nearest, blend)
}

/// A garment from the body faces whose vertices all satisfy `region`, made on the body
/// posed in `build_pose` and lifted by `offset` along its vertex normals; `attach`
/// marks the attached vertices. `region`, `attach` and the UVs see the T-pose
/// position of the body vertex a garment vertex comes from.
fn from_region(
    body: &SmplModel,
    build_pose: Pose,
    name: &str,
    region: impl Fn(DVec3) -> bool,
    offset: impl Fn(DVec3) -> f64,
    attach: impl Fn(DVec3) -> bool,
    attach_joint: usize,
) -> Garment {
    let posed = pose_body(body, &[], &build_pose, DVec3::ZERO).vertices;
    let normals = vertex_normals(&posed, &body.faces);
    let mut map = vec![u32::MAX; body.num_vertices()];
    let mut source = Vec::new();
    let mut faces = Vec::new();
    for f in &body.faces {
        if f.iter().all(|&i| region(body.v_template[i as usize])) {
            let mut g = [0u32; 3];
            for (k, &i) in f.iter().enumerate() {
                if map[i as usize] == u32::MAX {
                    map[i as usize] = source.len() as u32;
                    source.push(i as usize);
                }
                g[k] = map[i as usize];
            }
            faces.push(g);
        }
    }
    let clearance: Vec<f64> = source.iter().map(|&i| offset(body.v_template[i])).collect();
    let mut vertices: Vec<DVec3> = source
        .iter()
        .zip(&clearance)
        .map(|(&i, &c)| posed[i] + normals[i] * c)
        .collect();
    relax_off_body(&mut vertices, &faces, &posed, &body.faces, &clearance, 30);
    let uvs = source
        .iter()
        .map(|&i| {
            let v = body.v_template[i];
            [(v[0].atan2(v[2]) / std::f64::consts::TAU + 0.5), v[1] / 1.8]
        })
        .collect();
    let (weights, weights_blend6) = bind_weights(body, &posed, &vertices);
    let attached = source.iter().map(|&i| attach(body.v_template[i])).collect();
    Garment {
        name: name.to_string(),
        vertices,
        faces,
        uvs,
        weights,
        weights_blend6,
        attached,
        attach_joint,
        build_pose,
    }
}

/// Smooths a garment's rest shape the way cloth hangs: Laplacian steps that bridge
/// concave places (the crotch, the armpits) instead of following the skin into them,
/// each followed by pushing every vertex back to at least `clearance` off the body.
/// Offsetting along normals alone folds the surface where facing normals converge.
fn relax_off_body(
    vertices: &mut [DVec3],
    faces: &[[u32; 3]],
    body_vertices: &[DVec3],
    body_faces: &[[u32; 3]],
    clearance: &[f64],
    iterations: usize,
) {
    let collider = crate::collider::BodyCollider::new(body_vertices.to_vec(), body_faces);
    let adj = crate::mesh::adjacency(vertices.len(), faces);
    let boundary: Vec<bool> = {
        let counts = crate::mesh::edge_face_counts(faces);
        let mut b = vec![false; vertices.len()];
        for (&(x, y), &c) in &counts {
            if c == 1 {
                b[x as usize] = true;
                b[y as usize] = true;
            }
        }
        b
    };
    for _ in 0..iterations {
        let prev = vertices.to_vec();
        for (i, v) in vertices.iter_mut().enumerate() {
            // Openings keep their shape (the smoothing would shrink them).
            if boundary[i] || adj[i].is_empty() {
                continue;
            }
            let c = adj[i].iter().fold(DVec3::ZERO, |acc, &k| {
                acc + prev[k as usize] * (1.0 / adj[i].len() as f64)
            });
            *v = prev[i] * 0.5 + c * 0.5;
            if let Some((d, q, n)) = collider.query(*v) {
                if d < clearance[i] {
                    // Away from the closest point rather than along its triangle's
                    // normal: in a crease (an armpit) many vertices share one closest
                    // point, and the normal would put them all in one place.
                    let out = if d > 1e-6 {
                        (*v - q).normalize_or(DVec3::Z)
                    } else {
                        n
                    };
                    *v = q + out * clearance[i];
                }
            }
        }
    }
}

/// Lift of the T-shirt off the skin (metres).
pub const TSHIRT_OFFSET: f64 = 0.015;
/// Lift of the pants off the skin.
pub const PANTS_OFFSET: f64 = 0.012;

/// A short-sleeved T-shirt around the default body: torso from the hips to below the
/// neck, sleeves to mid upper arm; attached on top of the shoulders, inside the
/// shoulder joint (so that raising or lowering the arms does not stretch it).
pub fn tshirt(body: &SmplModel) -> Garment {
    from_region(
        body,
        a_pose(),
        "tshirt",
        |v| {
            let torso = v[1] > 0.96 && v[1] < 1.43 && v[0].abs() < 0.22;
            let sleeve = v[1] > 1.30 && v[1] < 1.50 && v[0].abs() < 0.36;
            let neck = v[1] > 1.40 && v[0].abs() < 0.075;
            (torso || sleeve) && !neck
        },
        |_| TSHIRT_OFFSET,
        |v| v[1] > 1.40 && v[0].abs() > 0.08 && v[0].abs() < 0.14,
        9, // spine3: the collars are its children and the shoulders beyond them
    )
}

/// How the T-shirt sits on the body: the benchmark (`drape bench-cloth`) wants a garment
/// that moves away from the skin, where cloth and body disagree most.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum GarmentFit {
    /// `tshirt`: 1.5 cm off the skin, hem at the hips (the default).
    #[default]
    Tight,
    /// `loose_tshirt`: 4.5 cm of ease around the torso and a hem 10 cm lower.
    Loose,
}

impl GarmentFit {
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "tight" => Some(Self::Tight),
            "loose" => Some(Self::Loose),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Tight => "tight",
            Self::Loose => "loose",
        }
    }

    /// The upper garment of this fit; the pants are the same for both.
    pub fn upper(self, body: &SmplModel) -> Garment {
        match self {
            Self::Tight => tshirt(body),
            Self::Loose => loose_tshirt(body),
        }
    }
}

/// The loose T-shirt's lift off the skin below the chest (metres).
pub const LOOSE_TSHIRT_OFFSET: f64 = 0.045;

/// The loose T-shirt's lift at a T-pose body point: tight (`TSHIRT_OFFSET`) on top of
/// the shoulders, where it is attached and hangs from, growing smoothly to
/// `LOOSE_TSHIRT_OFFSET` from the chest down; the sleeves get half the extra ease (a
/// sleeve as wide as the torso's ease would swallow the upper arm).
fn loose_tshirt_offset(v: DVec3) -> f64 {
    let smooth = |t: f64| {
        let t = t.clamp(0.0, 1.0);
        t * t * (3.0 - 2.0 * t)
    };
    let down = smooth((1.40 - v[1]) / (1.40 - 1.25));
    let sleeve = 1.0 - 0.5 * smooth((v[0].abs() - 0.18) / 0.08);
    TSHIRT_OFFSET + (LOOSE_TSHIRT_OFFSET - TSHIRT_OFFSET) * down * sleeve
}

/// A loose T-shirt: the tight one's sleeves, neck and attachment, with more ease around
/// the torso and the hem 10 cm lower (over the pants' waistband, to the upper hip).
/// Named `tshirt` like the tight one, since it plays the same part: the ground-truth
/// files and the loaders look for the upper garment by that name.
pub fn loose_tshirt(body: &SmplModel) -> Garment {
    from_region(
        body,
        a_pose(),
        "tshirt",
        |v| {
            let torso = v[1] > 0.86 && v[1] < 1.43 && v[0].abs() < 0.22;
            let sleeve = v[1] > 1.30 && v[1] < 1.50 && v[0].abs() < 0.36;
            let neck = v[1] > 1.40 && v[0].abs() < 0.075;
            (torso || sleeve) && !neck
        },
        loose_tshirt_offset,
        |v| v[1] > 1.40 && v[0].abs() > 0.08 && v[0].abs() < 0.14,
        9,
    )
}

/// Extra lift of the trouser legs from the knees down (metres).
pub const PANTS_LEG_EASE: f64 = 0.01;

/// The pants' lift off the skin at a T-pose body point: `PANTS_OFFSET` from the waist
/// to the upper thigh, growing smoothly to `PANTS_LEG_EASE` more from above the knee
/// down: trouser legs are looser than the seat, and a knee bends inside them.
fn pants_offset(v: DVec3) -> f64 {
    let (top, bottom) = (0.75, 0.55);
    let t = ((top - v[1]) / (top - bottom)).clamp(0.0, 1.0);
    PANTS_OFFSET + PANTS_LEG_EASE * t * t * (3.0 - 2.0 * t)
}

/// Long pants around the default body: from the waist to above the ankles; attached
/// at the waistband.
pub fn pants(body: &SmplModel) -> Garment {
    from_region(
        body,
        a_pose(),
        "pants",
        |v| v[1] > 0.14 && v[1] < 1.0 && v[0].abs() < 0.25,
        pants_offset,
        |v| v[1] > 0.95,
        0,
    )
}

/// Reads an OBJ garment (triangulated; UVs kept when present) made on `body` in its
/// rest pose (the T-pose) and binds it to the body; attached vertices are those
/// within 1 cm of the body.
pub fn load_obj(path: &Path, body: &SmplModel) -> Result<Garment, GarmentError> {
    let err = |problem: String| GarmentError::Invalid {
        path: path.display().to_string(),
        problem,
    };
    let (models, _) = tobj::load_obj(
        path,
        &tobj::LoadOptions {
            triangulate: true,
            single_index: true,
            ..Default::default()
        },
    )
    .map_err(|error| GarmentError::Read {
        path: path.display().to_string(),
        error,
    })?;
    let mut vertices = Vec::new();
    let mut faces = Vec::new();
    let mut uvs = Vec::new();
    for m in &models {
        let base = vertices.len() as u32;
        let mesh = &m.mesh;
        if mesh.positions.iter().any(|v| !v.is_finite()) {
            return Err(err(format!(
                "object '{}' has a non-finite vertex coordinate",
                m.name
            )));
        }
        vertices.extend(
            mesh.positions
                .chunks_exact(3)
                .map(|c| DVec3::new(f64::from(c[0]), f64::from(c[1]), f64::from(c[2]))),
        );
        if mesh.texcoords.len() / 2 == mesh.positions.len() / 3 {
            uvs.extend(
                mesh.texcoords
                    .chunks_exact(2)
                    .map(|c| [f64::from(c[0]), f64::from(c[1])]),
            );
        } else {
            uvs.extend(std::iter::repeat_n([0.0, 0.0], mesh.positions.len() / 3));
        }
        for f in mesh.indices.chunks_exact(3) {
            faces.push([base + f[0], base + f[1], base + f[2]]);
        }
    }
    if faces.is_empty() {
        return Err(err("no triangles".into()));
    }
    check_garment(&vertices, &faces, body).map_err(err)?;
    let (weights, weights_blend6) = bind_weights(body, &body.v_template, &vertices);
    let near = NearestBody::new(&body.v_template);
    let attached: Vec<bool> = vertices
        .iter()
        .map(|&v| near.k_nearest(v, 1)[0].1 < 0.01)
        .collect();
    // The joint that moves the attached vertices most, on average.
    let mut total = [0.0; NUM_JOINTS];
    for (w, _) in weights.iter().zip(&attached).filter(|(_, a)| **a) {
        for j in 0..NUM_JOINTS {
            total[j] += w[j];
        }
    }
    let attach_joint = (0..NUM_JOINTS)
        .max_by(|&a, &b| total[a].total_cmp(&total[b]))
        .unwrap_or(0);
    let name = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "garment".into());
    Ok(Garment {
        name,
        vertices,
        faces,
        uvs,
        weights,
        weights_blend6,
        attached,
        attach_joint,
        build_pose: t_pose(),
    })
}

/// The farthest a garment vertex may be from the body it is made on (metres): a loose
/// skirt's hem is a few tens of centimetres from the legs.
pub const MAX_GARMENT_DISTANCE: f64 = 0.5;

/// A garment drape can simulate on `body` (rest-pose vertices): faces that index its
/// vertices and have an area, and every vertex within [`MAX_GARMENT_DISTANCE`] of the
/// body, with a guess at the unit when it is not.
fn check_garment(vertices: &[DVec3], faces: &[[u32; 3]], model: &SmplModel) -> Result<(), String> {
    let body = &model.v_template;
    for (i, f) in faces.iter().enumerate() {
        if let Some(&k) = f.iter().find(|&&k| k as usize >= vertices.len()) {
            return Err(format!(
                "face {} refers to vertex {} of {}",
                i + 1,
                k + 1,
                vertices.len()
            ));
        }
        let [a, b, c] = f.map(|k| vertices[k as usize]);
        let n = (b - a).cross(c - a);
        let area = 0.5 * n.length();
        if !(area > 1e-12) {
            return Err(format!("face {} (vertices {} {} {}) is degenerate (area {area:.1e} m²): its corners are on one line", i + 1, f[0] + 1, f[1] + 1, f[2] + 1));
        }
    }
    let (lo, hi) = crate::grid::bounds(vertices.iter().copied());
    let (blo, bhi) = crate::grid::bounds(body.iter().copied());
    let size = (hi - lo).length();
    let body_size = (bhi - blo).length();
    let near = NearestBody::new(body);
    // Beyond the body's box by more than the limit, a vertex is too far without a
    // search (a far point would walk many empty rings of the grid).
    let to_box = |v: DVec3| {
        (0..3)
            .map(|k| (blo[k] - v[k]).max(v[k] - bhi[k]).max(0.0).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    // Each vertex's nearest body vertex (None beyond the box) and its distance.
    let nearest: Vec<(Option<u32>, f64)> = vertices
        .iter()
        .map(|&v| {
            let b = to_box(v);
            if b > MAX_GARMENT_DISTANCE {
                return (None, b);
            }
            near.k_nearest(v, 1)
                .first()
                .map_or((None, f64::INFINITY), |&(i, d)| (Some(i), d))
        })
        .collect();
    let (worst, at) = nearest
        .iter()
        .enumerate()
        .map(|(i, &(_, d))| (d, i))
        .fold((0.0f64, 0), |a, b| if b.0 > a.0 { b } else { a });
    if worst > MAX_GARMENT_DISTANCE {
        let unit = match size / body_size {
            r if r > 300.0 => " (it is about 1000 times the body's size: millimetres?)",
            r if r > 30.0 => " (it is about 100 times the body's size: centimetres?)",
            _ => " (is it made on the body in its rest pose, the T-pose, in metres?)",
        };
        return Err(format!(
            "vertex {} is {worst:.2} m from the body (at most {MAX_GARMENT_DISTANCE} m): the garment spans {size:.2} units, the body {body_size:.2} m{unit}",
            at + 1
        ));
    }
    // Around the body, not in it: a vertex more than 1 cm under the surface (behind
    // its nearest body vertex, along that vertex's normal) is inside.
    let normals = vertex_normals(body, &model.faces);
    let inside = vertices
        .iter()
        .zip(&nearest)
        .filter(|(v, (i, _))| {
            i.is_some_and(|i| {
                let (b, n) = (body[i as usize], normals[i as usize]);
                (0..3).map(|k| (v[k] - b[k]) * n[k]).sum::<f64>() < -0.01
            })
        })
        .count();
    if 2 * inside > vertices.len() {
        return Err(format!("{inside} of its {} vertices are inside the body (over 1 cm under its surface): a garment is made around the body, in its rest pose", vertices.len()));
    }
    Ok(())
}

/// Writes a mesh as OBJ (positions, optional UVs, triangles).
pub fn write_obj(
    path: &Path,
    vertices: &[DVec3],
    faces: &[[u32; 3]],
    uvs: Option<&[[f64; 2]]>,
) -> std::io::Result<()> {
    drape_io::write_with(path, |out| write_obj_to(out, vertices, faces, uvs))
}

fn write_obj_to(
    out: &mut impl std::io::Write,
    vertices: &[DVec3],
    faces: &[[u32; 3]],
    uvs: Option<&[[f64; 2]]>,
) -> std::io::Result<()> {
    for v in vertices {
        writeln!(out, "v {:.6} {:.6} {:.6}", v[0], v[1], v[2])?;
    }
    if let Some(uvs) = uvs {
        for t in uvs {
            writeln!(out, "vt {:.6} {:.6}", t[0], t[1])?;
        }
    }
    for f in faces {
        let [a, b, c] = f.map(|i| i + 1);
        if uvs.is_some() {
            writeln!(out, "f {a}/{a} {b}/{b} {c}/{c}")?;
        } else {
            writeln!(out, "f {a} {b} {c}")?;
        }
    }
    out.flush()
}
