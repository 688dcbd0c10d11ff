//! The posed body as a collider for cloth: its triangles filed in the spatial grid
//! (`grid`) by their bounds over a frame, and queries for the closest point of the
//! body, its normal and signed distance, at any fraction of the frame the body moves
//! through linearly.

use glam::DVec3;

use crate::grid::{bounds, Grid};

/// Points moving linearly from `a` to `b`, at fraction `s`.
pub(crate) fn lerp_points(a: &[DVec3], b: &[DVec3], s: f64) -> Vec<DVec3> {
    a.iter()
        .zip(b)
        .map(|(x, y)| *x * (1.0 - s) + *y * s)
        .collect()
}

/// The posed body over one frame as a collider: its vertices at the frame's start and
/// end (queried at any fraction between), triangles in a uniform grid covering both.
pub struct BodyCollider {
    start: Vec<DVec3>,
    end: Vec<DVec3>,
    faces: Vec<[u32; 3]>,
    /// Each triangle filed by its bounds over the frame, grown by `COLLIDER_REACH`.
    grid: Grid,
    /// The farthest any vertex moves over the frame.
    travel: f64,
}

fn closest_point_on_triangle(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> DVec3 {
    // Ericson, Real-Time Collision Detection, 5.1.5.
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = 1.0 / (va + vb + vc);
    a + (ab * (vb * denom) + ac * (vc * denom))
}

/// Grid cell of the collider (metres).
const COLLIDER_CELL: f64 = 0.03;
/// Triangles are filed in every cell within this distance, so that a query of one
/// cell sees every triangle that close to the point.
pub(crate) const COLLIDER_REACH: f64 = 0.02;

impl BodyCollider {
    /// A body that does not move.
    pub fn new(vertices: Vec<DVec3>, faces: &[[u32; 3]]) -> Self {
        Self::moving(vertices.clone(), vertices, faces)
    }

    /// A body moving linearly from `start` to `end` over the frame.
    pub fn moving(start: Vec<DVec3>, end: Vec<DVec3>, faces: &[[u32; 3]]) -> Self {
        let boxes = faces.iter().map(|f| {
            bounds(
                f.map(|k| start[k as usize])
                    .into_iter()
                    .chain(f.map(|k| end[k as usize])),
            )
        });
        let grid = Grid::of_boxes(boxes, COLLIDER_CELL, COLLIDER_REACH);
        let travel = start
            .iter()
            .zip(&end)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max);
        Self {
            start,
            end,
            faces: faces.to_vec(),
            grid,
            travel,
        }
    }

    /// Signed distance to the body (negative inside) and the closest surface point and
    /// normal, exact for points within `COLLIDER_REACH` of the surface; None when
    /// nothing is that near.
    pub fn query(&self, p: DVec3) -> Option<(f64, DVec3, DVec3)> {
        self.query_at(p, 1.0)
    }

    /// [`query`](Self::query) against the body at fraction `s` of the frame.
    pub fn query_at(&self, p: DVec3, s: f64) -> Option<(f64, DVec3, DVec3)> {
        self.query_face_at(p, s).map(|(d, q, n, _)| (d, q, n))
    }

    /// The farthest any body vertex moves over the frame.
    pub fn max_travel(&self) -> f64 {
        self.travel
    }

    /// The body's vertices at fraction `s` of the frame.
    pub fn vertices_at(&self, s: f64) -> Vec<DVec3> {
        lerp_points(&self.start, &self.end, s)
    }

    /// [`query_at`](Self::query_at), also naming the closest triangle.
    pub(crate) fn query_face_at(&self, p: DVec3, s: f64) -> Option<(f64, DVec3, DVec3, u32)> {
        let vertex = |k: u32| self.start[k as usize] * (1.0 - s) + self.end[k as usize] * s;
        self.closest_among(p, vertex, self.grid.at(p).iter().copied())
    }

    /// The closest of `faces` to `p`, with the body's vertices given by `vertex`:
    /// (signed distance, point, normal, face).
    pub(crate) fn closest_among(
        &self,
        p: DVec3,
        vertex: impl Fn(u32) -> DVec3,
        faces: impl Iterator<Item = u32>,
    ) -> Option<(f64, DVec3, DVec3, u32)> {
        let mut best: Option<(f64, DVec3, [DVec3; 3], u32)> = None;
        for t in faces {
            let [a, b, c] = self.faces[t as usize].map(&vertex);
            let q = closest_point_on_triangle(p, a, b, c);
            let d2 = (p - q).length_squared();
            // Squared distances; ties go to the first triangle (a fixed order).
            if best.is_none_or(|(bd2, ..)| d2 < bd2 - 1e-24) {
                best = Some((d2, q, [a, b, c], t));
            }
        }
        best.map(|(d2, q, [a, b, c], t)| {
            let n = (b - a).cross(c - a).normalize_or(DVec3::Z);
            let d = d2.sqrt();
            (if (p - q).dot(n) < 0.0 { -d } else { d }, q, n, t)
        })
    }
}

/// For every body triangle, the triangles sharing a vertex with it (itself included):
/// the neighbourhood an anchored cloth vertex collides with.
pub fn face_neighbourhoods(num_vertices: usize, faces: &[[u32; 3]]) -> Vec<Vec<u32>> {
    let mut by_vertex = vec![Vec::new(); num_vertices];
    for (i, f) in faces.iter().enumerate() {
        for &v in f {
            by_vertex[v as usize].push(i as u32);
        }
    }
    faces
        .iter()
        .map(|f| {
            let mut n: Vec<u32> = f
                .iter()
                .flat_map(|&v| by_vertex[v as usize].iter().copied())
                .collect();
            n.sort_unstable();
            n.dedup();
            n
        })
        .collect()
}
