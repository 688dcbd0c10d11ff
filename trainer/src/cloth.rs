//! XPBD cloth simulation (the stand-in for SNUG's garment network): stretch and
//! bending constraints, collision with the posed body with a margin, gravity,
//! damping, substeps, strain limiting, and attached regions that follow the body's
//! skinning. Deterministic: sequential Gauss-Seidel in a fixed order.
//!
//! Per frame the body and the attachment targets are interpolated linearly between
//! the previous and the next frame over the substeps (small-steps XPBD: the Lagrange
//! multipliers restart every substep). A substep carries the free cloth along with
//! the skinning, predicts with gravity and damping, then iterates: stretch and
//! bending, a collision pass that also records each near vertex's contact plane, and
//! the strain limit swept until no edge is more than `max_stretch + 0.02` long,
//! keeping every vertex outside its contact plane, so that a taut edge shortens by
//! sliding its cloth over the body rather than through it. Ending on the limit (not
//! on the collisions) is what bounds the strain; the planes keep the margin up to the
//! body's curvature over the millimetres a vertex slides.

use std::collections::HashMap;

use glam::DVec3;

use crate::body::kinematics::{pose_body, relative_transforms, skin, Affine, Pose};
use crate::body::model::SmplModel;
use crate::collider::{face_neighbourhoods, lerp_points, BodyCollider, COLLIDER_REACH};
use crate::garment::Garment;
use crate::motion::Motion;

/// Simulation settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClothParams {
    pub substeps: u32,
    /// Constraint sweeps per substep.
    pub iterations: u32,
    pub gravity: f64,
    /// Fraction of velocity lost per second.
    pub damping: f64,
    /// XPBD compliance of the stretch constraints (m/N).
    pub stretch_compliance: f64,
    /// XPBD compliance of the bending (cross-edge distance) constraints.
    pub bend_compliance: f64,
    /// Cloth keeps at least this far outside the body (metres).
    pub margin: f64,
    /// Edges are never longer than this factor of their rest length after a substep.
    pub max_stretch: f64,
}

impl Default for ClothParams {
    fn default() -> Self {
        Self {
            substeps: 8,
            iterations: 1,
            gravity: -9.81,
            damping: 0.5,
            stretch_compliance: 1e-8,
            bend_compliance: 1e-4,
            margin: 0.004,
            max_stretch: 1.05,
        }
    }
}

impl ClothParams {
    /// `substeps` per frame; fewer substeps get more iterations (each a collision pass
    /// and then the strain limit): about 16 per frame below 8 substeps.
    pub fn with_substeps(substeps: u32) -> Self {
        let substeps = substeps.max(1);
        Self {
            substeps,
            iterations: if substeps >= 8 { 1 } else { 16 / substeps },
            ..Self::default()
        }
    }

    /// One substep per frame (16 iterations).
    pub fn one_substep() -> Self {
        Self::with_substeps(1)
    }
}

/// How far (m) an anchored vertex may be from its anchor's neighbourhood before it is
/// re-anchored by a search of the whole body.
const ANCHOR_REACH: f64 = 0.02;

/// Vertices within this distance (m) of the body get a contact plane.
const PLANE_REACH: f64 = 0.01;

/// One XPBD step of the distance constraint `|x_a - x_b| = target` with compliance
/// `alpha` (already divided by the substep squared), moving each end by its inverse mass.
fn project_distance(
    positions: &mut [DVec3],
    [wa, wb]: [f64; 2],
    a: u32,
    b: u32,
    target: f64,
    alpha: f64,
) {
    let (ia, ib) = (a as usize, b as usize);
    if wa + wb == 0.0 {
        return;
    }
    let (pa, pb) = (positions[ia], positions[ib]);
    let l = (pa - pb).length();
    if l < 1e-12 {
        return;
    }
    let dl = -(l - target) / (wa + wb + alpha);
    let n = (pa - pb) * (1.0 / l);
    positions[ia] = pa + n * (wa * dl);
    positions[ib] = pb - n * (wb * dl);
}

/// Puts vertex `i` back `margin` outside its contact plane, if it has one.
fn keep_outside(positions: &mut [DVec3], planes: &[Option<(DVec3, DVec3)>], margin: f64, i: u32) {
    if let Some((q, n)) = planes[i as usize] {
        let p = positions[i as usize];
        let depth = margin - (p - q).dot(n);
        if depth > 0.0 {
            positions[i as usize] = p + n * depth;
        }
    }
}

/// At most this many Gauss-Seidel sweeps of the strain limit per iteration; the sweeps
/// stop sooner once no edge is longer than `max_stretch + STRAIN_TOLERANCE` times
/// its rest length.
const MAX_STRAIN_SWEEPS: usize = 300;
const STRAIN_TOLERANCE: f64 = 0.02;

/// One garment being simulated.
pub struct ClothSim {
    pub positions: Vec<DVec3>,
    velocities: Vec<DVec3>,
    inv_mass: Vec<f64>,
    stretch: Vec<(u32, u32, f64)>,
    bend: Vec<(u32, u32, f64)>,
    attached: Vec<bool>,
    params: ClothParams,
    /// Each vertex's body triangle (u32::MAX: none yet). Collisions look only around
    /// it, so cloth in a fold (crotch, armpit) is never thrown onto the far side.
    anchors: Vec<u32>,
    neighbourhoods: Option<std::sync::Arc<Vec<Vec<u32>>>>,
    /// Per vertex, the body's tangent plane (point, outward normal) found by the last
    /// collision pass when the vertex was within `PLANE_REACH` of the body: the
    /// constraint sweeps keep the vertex `margin` outside it, so that they shorten an
    /// edge by sliding over the body instead of pulling into it.
    planes: Vec<Option<(DVec3, DVec3)>>,
    /// Per vertex, where it was at its last global collision query, how far from the
    /// body it was then (a lower bound), and `body_travel` then.
    clearance: Vec<(DVec3, f64, f64)>,
    /// Sum over the substeps so far of the farthest any body vertex moved: how far
    /// any point of the body surface can have moved since a given time.
    body_travel: f64,
}

impl ClothSim {
    pub fn new(garment: &Garment, params: ClothParams) -> Self {
        let mut edges: HashMap<(u32, u32), Vec<u32>> = HashMap::new();
        for f in &garment.faces {
            for k in 0..3 {
                let (a, b, opposite) = (f[k], f[(k + 1) % 3], f[(k + 2) % 3]);
                edges
                    .entry((a.min(b), a.max(b)))
                    .or_default()
                    .push(opposite);
            }
        }
        let mut keys: Vec<&(u32, u32)> = edges.keys().collect();
        keys.sort();
        let v = &garment.vertices;
        let length = |a: u32, b: u32| (v[a as usize] - v[b as usize]).length();
        // Strain limiting sweeps the edges outward from the attached vertices (by hop
        // count), so that one Gauss-Seidel sweep carries a correction across the cloth.
        let mut hops = vec![u32::MAX; v.len()];
        let mut queue: std::collections::VecDeque<u32> = (0..v.len() as u32)
            .filter(|&i| garment.attached[i as usize])
            .collect();
        for &i in &queue {
            hops[i as usize] = 0;
        }
        let mut neighbours = vec![Vec::new(); v.len()];
        for &&(a, b) in &keys {
            neighbours[a as usize].push(b);
            neighbours[b as usize].push(a);
        }
        while let Some(i) = queue.pop_front() {
            for &n in &neighbours[i as usize] {
                if hops[n as usize] == u32::MAX {
                    hops[n as usize] = hops[i as usize] + 1;
                    queue.push_back(n);
                }
            }
        }
        let mut stretch: Vec<(u32, u32, f64)> =
            keys.iter().map(|&&(a, b)| (a, b, length(a, b))).collect();
        stretch.sort_by_key(|&(a, b, _)| (hops[a as usize].min(hops[b as usize]), a, b));
        let bend = keys
            .iter()
            .filter_map(|k| {
                let o = &edges[k];
                (o.len() == 2).then(|| (o[0], o[1], length(o[0], o[1])))
            })
            .collect();
        Self {
            positions: v.clone(),
            velocities: vec![DVec3::ZERO; v.len()],
            inv_mass: garment
                .attached
                .iter()
                .map(|&a| if a { 0.0 } else { 1.0 })
                .collect(),
            stretch,
            bend,
            attached: garment.attached.clone(),
            params,
            anchors: vec![u32::MAX; v.len()],
            neighbourhoods: None,
            planes: vec![None; v.len()],
            clearance: vec![(DVec3::ZERO, 0.0, 0.0); v.len()],
            body_travel: 0.0,
        }
    }

    fn solve_distance(&mut self, constraints_bend: bool, h: f64) {
        let (list, compliance) = if constraints_bend {
            (&self.bend, self.params.bend_compliance)
        } else {
            (&self.stretch, self.params.stretch_compliance)
        };
        let alpha = compliance / (h * h);
        for &(a, b, rest) in list {
            project_distance(
                &mut self.positions,
                [self.inv_mass[a as usize], self.inv_mass[b as usize]],
                a,
                b,
                rest,
                alpha,
            );
            keep_outside(&mut self.positions, &self.planes, self.params.margin, a);
            keep_outside(&mut self.positions, &self.planes, self.params.margin, b);
        }
    }

    /// One sweep of the strain limit: a hard (zero-compliance) distance constraint on
    /// the edges longer than `max_stretch` times their rest length, keeping vertices
    /// outside their contact planes. Returns the largest strain it met at or near the
    /// limit (at most `max_stretch` when every edge is within it).
    fn limit_strain(&mut self, moved_before: &[bool], moved: &mut [bool]) -> f64 {
        let mut worst: f64 = 0.0;
        let max = self.params.max_stretch;
        let margin = self.params.margin;
        moved.fill(false);
        for &(a, b, rest) in &self.stretch {
            let (ia, ib) = (a as usize, b as usize);
            // An edge neither of whose ends moved since the last sweep looked at it is
            // as that sweep left it: no longer than `max` times its rest length.
            if !(moved_before[ia] || moved_before[ib] || moved[ia] || moved[ib]) {
                continue;
            }
            // Most edges are well within the limit: squared lengths find them without a
            // square root. The relative margin is far above the rounding of the root, so
            // no edge at the limit is skipped, and a skipped edge (strain below `max`)
            // changes neither the projection nor the caller's `worst <= max + tolerance`.
            let l2 = (self.positions[ia] - self.positions[ib]).length_squared();
            let limit = max * rest;
            if l2 < limit * limit * (1.0 - 1e-9) {
                continue;
            }
            let l = l2.sqrt();
            worst = worst.max(l / rest);
            if l > max * rest {
                project_distance(
                    &mut self.positions,
                    [self.inv_mass[ia], self.inv_mass[ib]],
                    a,
                    b,
                    max * rest,
                    0.0,
                );
                keep_outside(&mut self.positions, &self.planes, margin, a);
                keep_outside(&mut self.positions, &self.planes, margin, b);
                moved[ia] = true;
                moved[ib] = true;
            }
        }
        worst
    }

    /// Anchors collisions to the body's triangles (see `anchors`); `neighbourhoods`
    /// from [`face_neighbourhoods`] of the body this garment collides with.
    pub fn anchor_to(&mut self, neighbourhoods: std::sync::Arc<Vec<Vec<u32>>>) {
        self.neighbourhoods = Some(neighbourhoods);
    }

    /// Pushes every free vertex `margin` outside the body at fraction `s` of the frame,
    /// whose vertices are `body_now`, and records the contact planes.
    fn collide(&mut self, body: &BodyCollider, body_now: &[DVec3], s: f64) {
        let margin = self.params.margin;
        for i in 0..self.positions.len() {
            if self.attached[i] {
                continue;
            }
            let p = self.positions[i];
            // Far from the body at the last global query, and not moved (with the body)
            // enough since to come within PLANE_REACH: nothing to do.
            let (at, clear, travel) = self.clearance[i];
            if (p - at).length() + (self.body_travel - travel) < clear - PLANE_REACH {
                self.planes[i] = None;
                // Coming back, it searches the whole body again, as it would have.
                self.anchors[i] = u32::MAX;
                continue;
            }
            self.clearance[i] = (p, 0.0, self.body_travel);
            let local = match (&self.neighbourhoods, self.anchors[i]) {
                (Some(nb), a) if a != u32::MAX => body
                    .closest_among(p, |k| body_now[k as usize], nb[a as usize].iter().copied())
                    .filter(|h| h.0.abs() < ANCHOR_REACH),
                _ => None,
            };
            self.planes[i] = None;
            let hit = local.or_else(|| {
                let global = body.query_face_at(p, s);
                // Nothing nearer than COLLIDER_REACH escapes the grid query.
                let clear = global.map_or(COLLIDER_REACH, |h| h.0.clamp(0.0, COLLIDER_REACH));
                self.clearance[i] = (p, clear, self.body_travel);
                global
            });
            if let Some((d, q, n, face)) = hit {
                self.anchors[i] = face;
                if d < margin {
                    self.positions[i] = q + n * margin;
                }
                if d < PLANE_REACH {
                    // The plane through the closest point, facing the vertex: the
                    // triangle's own normal misleads at edges and corners.
                    let out = if d < margin {
                        n
                    } else {
                        (self.positions[i] - q).normalize_or(DVec3::Z)
                    };
                    self.planes[i] = Some((q, out));
                }
            }
        }
    }

    /// Advances one frame of `dt` seconds against `collider` (the body moving over the
    /// frame); `targets(s)` gives the attached vertices' positions at fraction s of it.
    pub fn step_frame(
        &mut self,
        dt: f64,
        collider: &BodyCollider,
        targets: &dyn Fn(f64) -> Vec<DVec3>,
    ) {
        self.step_frame_carried(dt, collider, targets, &|_| None);
    }

    /// [`step_frame`](Self::step_frame), with the free vertices first carried along by
    /// the body: `carried(s)` gives every vertex's skinned rest position at fraction s
    /// (None: not carried). Each substep moves a free vertex by the change of its
    /// skinned position, and the dynamics add what differs from skinning (gravity,
    /// inertia, collisions); so a fast limb does not leave its sleeve behind, even
    /// with one substep.
    pub fn step_frame_carried(
        &mut self,
        dt: f64,
        collider: &BodyCollider,
        targets: &dyn Fn(f64) -> Vec<DVec3>,
        carried: &dyn Fn(f64) -> Option<Vec<DVec3>>,
    ) {
        let n = self.params.substeps.max(1);
        let h = dt / f64::from(n);
        let keep = (1.0 - self.params.damping * h).clamp(0.0, 1.0);
        let mut carried_before = carried(0.0);
        for s in 1..=n {
            let frac = f64::from(s) / f64::from(n);
            let goal = targets(frac);
            let carried_now = carried(frac);
            if let (Some(a), Some(b)) = (&carried_before, &carried_now) {
                for i in 0..self.positions.len() {
                    if !self.attached[i] {
                        self.positions[i] += b[i] - a[i];
                    }
                }
            }
            carried_before = carried_now;
            let previous = self.positions.clone();
            for i in 0..self.positions.len() {
                if self.attached[i] {
                    self.positions[i] = goal[i];
                    continue;
                }
                let v = &mut self.velocities[i];
                v.y += self.params.gravity * h;
                *v *= keep;
                self.positions[i] += *v * h;
            }
            let body_now = collider.vertices_at(frac);
            self.body_travel += collider.max_travel() / f64::from(n);
            self.collide(collider, &body_now, frac);
            // Each iteration ends with a collision pass and then the strain limit,
            // which keeps every vertex outside the contact plane that pass found: so
            // a substep ends with both the strain bound and (up to the body's
            // curvature over a few millimetres of sliding) the margin. With one
            // substep the iterations give collisions and limit their many rounds.
            for _ in 0..self.params.iterations.max(1) {
                self.solve_distance(false, h);
                self.solve_distance(true, h);
                self.collide(collider, &body_now, frac);
                let mut moved_before = vec![true; self.positions.len()];
                let mut moved = vec![false; self.positions.len()];
                for _ in 0..MAX_STRAIN_SWEEPS {
                    if self.limit_strain(&moved_before, &mut moved)
                        <= self.params.max_stretch + STRAIN_TOLERANCE
                    {
                        break;
                    }
                    std::mem::swap(&mut moved_before, &mut moved);
                }
            }
            for i in 0..self.positions.len() {
                self.velocities[i] = (self.positions[i] - previous[i]) * (1.0 / h);
            }
        }
    }

    /// Largest edge length over rest length, and that edge.
    pub fn max_strain_edge(&self) -> (f64, u32, u32) {
        self.stretch
            .iter()
            .map(|&(a, b, rest)| {
                (
                    (self.positions[a as usize] - self.positions[b as usize]).length() / rest,
                    a,
                    b,
                )
            })
            .fold((0.0, 0, 0), |m, e| if e.0 > m.0 { e } else { m })
    }

    /// Largest edge length over rest length.
    pub fn max_strain(&self) -> f64 {
        self.max_strain_edge().0
    }

    /// Whether vertex `i` follows the body.
    pub fn is_attached(&self, i: usize) -> bool {
        self.attached[i]
    }
}

/// Per-frame meshes of every garment, and what the simulation measured.
#[derive(Clone, Debug)]
pub struct SimulationResult {
    /// `frames[f][g]` = positions of garment g after frame f.
    pub frames: Vec<Vec<Vec<DVec3>>>,
    /// Deepest penetration into the body over all frames (metres, positive = inside).
    pub max_penetration: f64,
    /// Largest edge strain (length / rest length) over all frames.
    pub max_strain: f64,
    /// Where the largest strain was: (frame, garment, vertex a, vertex b).
    pub max_strain_at: (usize, usize, u32, u32),
    /// Where the deepest penetration was: (frame, garment, vertex).
    pub max_penetration_at: (usize, usize, usize),
    pub any_nan: bool,
}

/// Simulates `garments` on `body` through `motion`, after `pre_roll` frames that blend
/// from the first garment's build pose (the pose the clothes were made in) into the
/// motion's first frame.
pub fn simulate(
    body: &SmplModel,
    garments: &[Garment],
    motion: &Motion,
    params: ClothParams,
    pre_roll: usize,
) -> SimulationResult {
    simulate_with_progress(body, garments, motion, params, pre_roll, &mut |_, _| {})
}

/// [`simulate`], calling `progress(frame, total)` as it starts each frame (1-based;
/// settling frames included in both).
pub fn simulate_with_progress(
    body: &SmplModel,
    garments: &[Garment],
    motion: &Motion,
    params: ClothParams,
    pre_roll: usize,
    progress: &mut dyn FnMut(usize, usize),
) -> SimulationResult {
    let dt = 1.0 / motion.fps;
    let start_pose: Pose = garments.first().map_or([DVec3::ZERO; 24], |g| g.build_pose);
    let first = motion.poses.first().copied().unwrap_or(start_pose);
    // The garments are dressed where the motion starts and settle into its first pose
    // there: a body that started elsewhere would drag them across the distance.
    let origin = motion.translations.first().copied().unwrap_or(DVec3::ZERO);
    let mut schedule: Vec<(Pose, DVec3)> = (1..=pre_roll)
        .map(|k| {
            let t = k as f64 / pre_roll as f64;
            let s = t * t * (3.0 - 2.0 * t);
            (
                std::array::from_fn(|j| start_pose[j] * (1.0 - s) + first[j] * s),
                origin,
            )
        })
        .collect();
    let recorded_from = schedule.len();
    schedule.extend(
        motion
            .poses
            .iter()
            .copied()
            .zip(motion.translations.iter().copied()),
    );

    let start = pose_body(body, &[], &start_pose, origin);
    // Per garment, the skinning transforms of its build pose: a garment made in pose B
    // is skinned into pose P with A(P) · A(B)⁻¹.
    let build: Vec<[Affine; 24]> = garments
        .iter()
        .map(|g| pose_body(body, &[], &g.build_pose, DVec3::ZERO).transforms)
        .collect();
    let neighbourhoods = std::sync::Arc::new(face_neighbourhoods(body.num_vertices(), &body.faces));
    let mut sims: Vec<ClothSim> = garments
        .iter()
        .zip(&build)
        .map(|(g, b)| {
            let mut sim = ClothSim::new(g, params);
            if g.build_pose != start_pose || origin != DVec3::ZERO {
                // Skinning transforms leave the translation out; it is added after.
                sim.positions = skin(
                    &g.weights_blend6,
                    &relative_transforms(&start.transforms, b),
                    &g.vertices,
                )
                .into_iter()
                .map(|v| v + origin)
                .collect();
            }
            sim.anchor_to(neighbourhoods.clone());
            sim
        })
        .collect();
    let mut prev = start;
    let mut result = SimulationResult {
        frames: Vec::new(),
        max_penetration: f64::MIN,
        max_strain: 0.0,
        max_strain_at: (0, 0, 0, 0),
        max_penetration_at: (0, 0, 0),
        any_nan: false,
    };
    for (f, (pose, trans)) in schedule.iter().enumerate() {
        progress(f + 1, schedule.len());
        let next = pose_body(body, &[], pose, *trans);
        let prev_t = prev.transforms;
        let next_t = next.transforms;
        let collider =
            BodyCollider::moving(prev.vertices.clone(), next.vertices.clone(), &body.faces);
        let prev_trans_vec = if f == 0 { origin } else { schedule[f - 1].1 };
        // Garments do not collide with each other, so each steps on its own thread
        // (each one's result is the same as stepped alone: deterministic).
        let step_garment = |g: &Garment, sim: &mut ClothSim, b: &[Affine; 24]| {
            let (prev_t, next_t) = (
                relative_transforms(&prev_t, b),
                relative_transforms(&next_t, b),
            );
            // Attached vertices move rigidly with the garment's attachment joint.
            let mut rigid = [0.0; 24];
            rigid[g.attach_joint] = 1.0;
            let rigid = vec![rigid; g.vertices.len()];
            let a0: Vec<DVec3> = skin(&rigid, &prev_t, &g.vertices)
                .into_iter()
                .map(|v| v + prev_trans_vec)
                .collect();
            let a1: Vec<DVec3> = skin(&rigid, &next_t, &g.vertices)
                .into_iter()
                .map(|v| v + *trans)
                .collect();
            let targets = |s: f64| lerp_points(&a0, &a1, s);
            let c0: Vec<DVec3> = skin(&g.weights_blend6, &prev_t, &g.vertices)
                .into_iter()
                .map(|v| v + prev_trans_vec)
                .collect();
            let c1: Vec<DVec3> = skin(&g.weights_blend6, &next_t, &g.vertices)
                .into_iter()
                .map(|v| v + *trans)
                .collect();
            let carried = |s: f64| Some(lerp_points(&c0, &c1, s));
            sim.step_frame_carried(dt, &collider, &targets, &carried);
        };
        std::thread::scope(|scope| {
            for ((g, sim), b) in garments.iter().zip(sims.iter_mut()).zip(&build) {
                scope.spawn(move || step_garment(g, sim, b));
            }
        });
        if f >= recorded_from {
            let mut frame = Vec::with_capacity(sims.len());
            let index = f - recorded_from;
            for (gi, sim) in sims.iter().enumerate() {
                for (vi, p) in sim.positions.iter().enumerate() {
                    if !p.is_finite() {
                        result.any_nan = true;
                    }
                    if let Some((s, _, _)) = collider.query(*p) {
                        if -s > result.max_penetration {
                            result.max_penetration = -s;
                            result.max_penetration_at = (index, gi, vi);
                        }
                    }
                }
                let (strain, a, b) = sim.max_strain_edge();
                if strain > result.max_strain {
                    result.max_strain = strain;
                    result.max_strain_at = (index, gi, a, b);
                }
                frame.push(sim.positions.clone());
            }
            result.frames.push(frame);
        }
        prev = next;
    }
    result
}
