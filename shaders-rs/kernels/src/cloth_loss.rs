//! The cloth layer's physics losses (`drape_shared::cloth_loss` states the math):
//! nearest neighbours and the Chamfer + Geman–McClure gradient by tiled brute force
//! or through a uniform grid (`bounds`, `cell_keys`, the engine's radix sort,
//! `cell_ranges`, `nearest_grid`, and the gradient as a deterministic fixed-point
//! scatter, `chamfer_grad_scatter` + `chamfer_grad_gather`), and the
//! edge-length-variance ARAP term with its gradient.
//!
//! Every kernel here runs 256 invocations per workgroup and indexes
//! `(workgroup_id.y * num_workgroups.x + workgroup_id.x) * 256 + lid` (the engine's
//! `flat_grid`). The tiled kernels never return early: every invocation reaches every
//! barrier, and the ones past the end only help stage tiles.

use drape_shared::cloth_loss::{
    arap_edge_grad, chamfer_pair_grad, distance2, ordered_key, ArapParams, ChamferParams,
    GridParams, GridSpec, CHAMFER_CHUNK, CHAMFER_FINISH, CHAMFER_LAST, CHAMFER_MERGE,
    CHAMFER_OWN_TERM, CLOTH_LOSS_GROUP, GRID_STEP_BUDGET, NEAREST_UNFINISHED,
};
use spirv_std::arch::workgroup_memory_barrier_with_group_sync as barrier;

use crate::atomics;
use spirv_std::glam::UVec3;
use spirv_std::spirv;

const GROUP: usize = CLOTH_LOSS_GROUP as usize;
const TILE3: usize = 3 * GROUP;

fn index(group: UVec3, groups: UVec3, lid: u32) -> u32 {
    (group.y * groups.x + group.x) * CLOTH_LOSS_GROUP + lid
}

fn point(v: &[f32], i: u32) -> [f32; 3] {
    let b = 3 * i as usize;
    [v[b], v[b + 1], v[b + 2]]
}

/// For each of `queries` points, the nearest of `points[offset..offset + CHAMFER_CHUNK]`
/// (`index`, lower index on ties) and the squared distance (`d2`), merged with the
/// earlier chunks' best under `CHAMFER_MERGE`. With no points: `u32::MAX` and +inf
/// (the host refuses empty sets before it gets here). Under `CHAMFER_FINISH` only the
/// queries `nearest_grid` left marked `NEAREST_UNFINISHED` are searched, from the best
/// the grid found, and `CHAMFER_LAST` clears the mark.
#[spirv(compute(threads(256)))]
pub fn nearest(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &ChamferParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] queries: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] points: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] index_out: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] d2_out: &mut [f32],
    #[spirv(workgroup)] tile: &mut [f32; TILE3],
    #[spirv(workgroup)] unfinished: &mut [u32; 1],
) {
    let q = index(group, groups, lid);
    let finish = p.flags & CHAMFER_FINISH != 0;
    let mut active = q < p.queries;
    let mut best = f32::INFINITY;
    let mut best_i = u32::MAX;
    if finish {
        let stored = if active { index_out[q as usize] } else { 0 };
        active = active && stored & NEAREST_UNFINISHED != 0;
        if active {
            best = d2_out[q as usize];
            best_i = stored & !NEAREST_UNFINISHED;
        }
        // A workgroup with nothing to finish leaves at once (the usual case), all of
        // its invocations together, so every barrier below is still reached by all.
        if lid == 0 {
            unfinished[0] = 0;
        }
        barrier();
        if active {
            atomics::add_u32_workgroup(&mut unfinished[0], 1);
        }
        barrier();
        if unfinished[0] == 0 {
            return;
        }
    } else if active && p.flags & CHAMFER_MERGE != 0 {
        best = d2_out[q as usize];
        best_i = index_out[q as usize];
    }
    let me = if active { point(queries, q) } else { [0.0; 3] };
    let end = if p.points - p.offset < CHAMFER_CHUNK {
        p.points
    } else {
        p.offset + CHAMFER_CHUNK
    };
    let mut t0 = p.offset;
    while t0 < end {
        let j = t0 + lid;
        if j < end {
            let s = point(points, j);
            let l = 3 * lid as usize;
            tile[l] = s[0];
            tile[l + 1] = s[1];
            tile[l + 2] = s[2];
        }
        barrier();
        let count = if end - t0 < CLOTH_LOSS_GROUP {
            end - t0
        } else {
            CLOTH_LOSS_GROUP
        };
        let mut k = 0u32;
        while k < count {
            let l = 3 * k as usize;
            let d = distance2(me, [tile[l], tile[l + 1], tile[l + 2]]);
            // The index test only matters when finishing from a grid's best, which
            // may hold a higher index at the same distance.
            if d < best || (d == best && t0 + k < best_i) {
                best = d;
                best_i = t0 + k;
            }
            k += 1;
        }
        // Everyone is done with the tile before it is overwritten.
        barrier();
        t0 += CLOTH_LOSS_GROUP;
    }
    if active {
        index_out[q as usize] = if finish && p.flags & CHAMFER_LAST == 0 {
            best_i | NEAREST_UNFINISHED
        } else {
            best_i
        };
        d2_out[q as usize] = best;
    }
}

/// `grad[p] += ∂ L_sim / ∂ p` for each of `queries` predicted points: its own term
/// (to its nearest target, under `CHAMFER_OWN_TERM`) plus the terms of every target
/// of this chunk whose nearest prediction it is (a gather over the targets, tiled:
/// deterministic, no atomics).
#[spirv(compute(threads(256)))]
pub fn chamfer_grad(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &ChamferParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pred: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] target: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] pred_nearest: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] target_nearest: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] grad: &mut [f32],
    #[spirv(workgroup)] tile: &mut [f32; TILE3],
    #[spirv(workgroup)] tile_nearest: &mut [u32; GROUP],
) {
    let i = index(group, groups, lid);
    let active = i < p.queries;
    let me = if active { point(pred, i) } else { [0.0; 3] };
    let mut g = [0.0f32; 3];
    if active && p.points > 0 && p.flags & CHAMFER_OWN_TERM != 0 {
        let n = pred_nearest[i as usize];
        let n = if n < p.points { n } else { 0 };
        g = chamfer_pair_grad(me, point(target, n), p.sigma2, p.scale_pred);
    }
    let end = if p.points - p.offset < CHAMFER_CHUNK {
        p.points
    } else {
        p.offset + CHAMFER_CHUNK
    };
    let mut t0 = p.offset;
    while t0 < end {
        let j = t0 + lid;
        if j < end {
            let s = point(target, j);
            let l = 3 * lid as usize;
            tile[l] = s[0];
            tile[l + 1] = s[1];
            tile[l + 2] = s[2];
            tile_nearest[lid as usize] = target_nearest[j as usize];
        }
        barrier();
        let count = if end - t0 < CLOTH_LOSS_GROUP {
            end - t0
        } else {
            CLOTH_LOSS_GROUP
        };
        let mut k = 0u32;
        while k < count {
            if tile_nearest[k as usize] == i {
                let l = 3 * k as usize;
                let d = chamfer_pair_grad(
                    me,
                    [tile[l], tile[l + 1], tile[l + 2]],
                    p.sigma2,
                    p.scale_target,
                );
                g[0] += d[0];
                g[1] += d[1];
                g[2] += d[2];
            }
            k += 1;
        }
        barrier();
        t0 += CLOTH_LOSS_GROUP;
    }
    if active {
        let b = 3 * i as usize;
        grad[b] += g[0];
        grad[b + 1] += g[1];
        grad[b + 2] += g[2];
    }
}

/// `lengths[e] = |v_a - v_b|` for each edge `(a, b)` of `edges` (u32 pairs).
#[spirv(compute(threads(256)))]
pub fn arap_lengths(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &ArapParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] positions: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] edges: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] lengths: &mut [f32],
) {
    let e = index(group, groups, lid);
    if e >= p.edges {
        return;
    }
    let (a, b) = (edges[2 * e as usize], edges[2 * e as usize + 1]);
    lengths[e as usize] =
        drape_shared::real::Float::sqrt(distance2(point(positions, a), point(positions, b)));
}

/// One workgroup: `stats = [mean, variance]` of `lengths[..edges]` (a fixed
/// summation order: strided partial sums, then a tree).
#[spirv(compute(threads(256)))]
pub fn arap_stats(
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &ArapParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] lengths: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] stats: &mut [f32],
    #[spirv(workgroup)] sums: &mut [f32; GROUP],
) {
    let inv = if p.edges > 0 {
        1.0 / p.edges as f32
    } else {
        0.0
    };
    let mean = tree_sum(sums, lid, p.edges, lengths, 0.0, false) * inv;
    let var = tree_sum(sums, lid, p.edges, lengths, mean, true) * inv;
    if lid == 0 {
        stats[0] = mean;
        stats[1] = var;
    }
}

/// Σ v (or Σ (v - mean)² with `squared`) over `values[..len]`, by all 256
/// invocations; every invocation gets the total.
fn tree_sum(
    sums: &mut [f32; GROUP],
    lid: u32,
    len: u32,
    values: &[f32],
    mean: f32,
    squared: bool,
) -> f32 {
    let mut s = 0.0f32;
    let mut k = lid;
    while k < len {
        let v = values[k as usize] - mean;
        s += if squared { v * v } else { v };
        k += CLOTH_LOSS_GROUP;
    }
    sums[lid as usize] = s;
    barrier();
    let mut half = CLOTH_LOSS_GROUP / 2;
    while half > 0 {
        if lid < half {
            sums[lid as usize] += sums[(lid + half) as usize];
        }
        barrier();
        half /= 2;
    }
    let total = sums[0];
    barrier();
    total
}

/// `grad[v] += scale · ∂ var(ℓ) / ∂ v` for each vertex, over its edges in CSR form:
/// `offsets[v]..offsets[v + 1]` index `neighbours` (the other end of each edge).
#[spirv(compute(threads(256)))]
pub fn arap_grad(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &ArapParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] positions: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] offsets: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] neighbours: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] stats: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] grad: &mut [f32],
) {
    let v = index(group, groups, lid);
    if v >= p.vertices {
        return;
    }
    let me = point(positions, v);
    let mean = stats[0];
    let edges = p.edges as f32;
    let mut g = [0.0f32; 3];
    let mut k = offsets[v as usize];
    let end = offsets[v as usize + 1];
    while k < end {
        let d = arap_edge_grad(
            me,
            point(positions, neighbours[k as usize]),
            mean,
            edges,
            p.scale,
        );
        g[0] += d[0];
        g[1] += d[1];
        g[2] += d[2];
        k += 1;
    }
    let b = 3 * v as usize;
    grad[b] += g[0];
    grad[b + 1] += g[1];
    grad[b + 2] += g[2];
}

/// The gridded set's bounds: atomic maxima of the ordered keys of `x, y, z` and of
/// `-x, -y, -z` (a workgroup's maxima first, then one device atomic per word) into
/// `bounds` (6 words, zeroed by the host). Non-finite points are left out.
#[spirv(compute(threads(256)))]
pub fn bounds(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &GridParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] points: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] bounds: &mut [u32],
    #[spirv(workgroup)] local: &mut [u32; 6],
) {
    let j = index(group, groups, lid);
    if lid < 6 {
        local[lid as usize] = 0;
    }
    barrier();
    if j < p.points {
        let v = point(points, j);
        if v[0].is_finite() && v[1].is_finite() && v[2].is_finite() {
            atomics::max_u32_workgroup(&mut local[0], ordered_key(v[0]));
            atomics::max_u32_workgroup(&mut local[1], ordered_key(v[1]));
            atomics::max_u32_workgroup(&mut local[2], ordered_key(v[2]));
            atomics::max_u32_workgroup(&mut local[3], ordered_key(-v[0]));
            atomics::max_u32_workgroup(&mut local[4], ordered_key(-v[1]));
            atomics::max_u32_workgroup(&mut local[5], ordered_key(-v[2]));
        }
    }
    barrier();
    if lid < 6 && local[lid as usize] != 0 {
        atomics::max_u32(&mut bounds[lid as usize], local[lid as usize]);
    }
}

fn grid_of(bounds: &[u32], points: u32) -> GridSpec {
    GridSpec::from_bounds(
        [
            bounds[0], bounds[1], bounds[2], bounds[3], bounds[4], bounds[5],
        ],
        points,
    )
}

/// `keys[j]` = the grid cell of point `j`, `values[j] = j`: the pairs the radix sort
/// orders by cell (stably, so each cell lists its points by index).
#[spirv(compute(threads(256)))]
pub fn cell_keys(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &GridParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] points: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] bounds: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] keys: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] values: &mut [u32],
) {
    let j = index(group, groups, lid);
    if j >= p.points {
        return;
    }
    let g = grid_of(bounds, p.points);
    keys[j as usize] = g.linear(g.cell_of(point(points, j)));
    values[j as usize] = j;
}

/// Each cell's range `start[c]..end[c]` in the sorted keys (`p.queries` of them; both
/// arrays zeroed by the host, so empty cells read as empty).
#[spirv(compute(threads(256)))]
pub fn cell_ranges(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &GridParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] keys: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] start: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] end: &mut [u32],
) {
    let s = index(group, groups, lid);
    if s >= p.queries {
        return;
    }
    let k = keys[s as usize];
    if s == 0 || keys[s as usize - 1] != k {
        start[k as usize] = s;
    }
    if s + 1 == p.queries || keys[s as usize + 1] != k {
        end[k as usize] = s + 1;
    }
}

/// One query's search state.
struct Search {
    me: [f32; 3],
    best: f32,
    best_i: u32,
    steps: u32,
}

/// Visits the points of cell `cell` (their indices are `order[start[cell]..end[cell]]`).
fn visit_cell(
    s: &mut Search,
    cell: u32,
    points: &[f32],
    start: &[u32],
    end: &[u32],
    order: &[u32],
) {
    let mut k = start[cell as usize];
    let stop = end[cell as usize];
    while k < stop && s.steps < GRID_STEP_BUDGET {
        let j = order[k as usize];
        let d = distance2(s.me, point(points, j));
        if d < s.best || (d == s.best && j < s.best_i) {
            s.best = d;
            s.best_i = j;
        }
        s.steps += 1;
        k += 1;
    }
}

/// For each of `queries` points, the nearest of the gridded `points` (see
/// `drape_shared::cloth_loss`, "Nearest neighbours through a uniform grid"): shells of
/// cells of growing radius until the best distance is below the radius, or the
/// budget is spent (the index is then marked `NEAREST_UNFINISHED` for brute force).
#[spirv(compute(threads(256)))]
pub fn nearest_grid(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &GridParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] queries: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] points: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] bounds: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] start: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] end: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 5)] order: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 6)] index_out: &mut [u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 7)] d2_out: &mut [f32],
) {
    let q = index(group, groups, lid);
    if q >= p.queries {
        return;
    }
    let g = grid_of(bounds, p.points);
    let me = point(queries, q);
    let c = g.cell_of(me);
    let last = [g.dims[0] - 1, g.dims[1] - 1, g.dims[2] - 1];
    let mut s = Search {
        me,
        best: f32::INFINITY,
        best_i: u32::MAX,
        steps: 0,
    };
    let mut r = 0u32;
    let mut done = false;
    let mut finished = false;
    while !done {
        // The shell of Chebyshev radius r: every cell with max |offset| == r, clipped
        // to the grid.
        let zl = if c[2] >= r { c[2] - r } else { 0 };
        let zh = if c[2] + r < last[2] {
            c[2] + r
        } else {
            last[2]
        };
        let yl = if c[1] >= r { c[1] - r } else { 0 };
        let yh = if c[1] + r < last[1] {
            c[1] + r
        } else {
            last[1]
        };
        let xl = if c[0] >= r { c[0] - r } else { 0 };
        let xh = if c[0] + r < last[0] {
            c[0] + r
        } else {
            last[0]
        };
        let mut z = zl;
        while z <= zh && s.steps < GRID_STEP_BUDGET {
            let z_face = z + r == c[2] || z == c[2] + r;
            let mut y = yl;
            while y <= yh && s.steps < GRID_STEP_BUDGET {
                let row = (z * g.dims[1] + y) * g.dims[0];
                if z_face || y + r == c[1] || y == c[1] + r {
                    let mut x = xl;
                    while x <= xh && s.steps < GRID_STEP_BUDGET {
                        visit_cell(&mut s, row + x, points, start, end, order);
                        s.steps += 1;
                        x += 1;
                    }
                } else {
                    // Inside the shell's z and y faces only the two x faces belong to it.
                    if c[0] >= r {
                        visit_cell(&mut s, row + c[0] - r, points, start, end, order);
                    }
                    if c[0] + r <= last[0] {
                        visit_cell(&mut s, row + c[0] + r, points, start, end, order);
                    }
                }
                s.steps += 1;
                y += 1;
            }
            s.steps += 1;
            z += 1;
        }
        s.steps += 1;
        if s.steps >= GRID_STEP_BUDGET {
            done = true;
        } else {
            let covered =
                xl == 0 && yl == 0 && zl == 0 && xh == last[0] && yh == last[1] && zh == last[2];
            let bound = r as f32 * g.h - g.slack;
            if covered || (bound > 0.0 && s.best < bound * bound) {
                done = true;
                finished = true;
            }
            r += 1;
        }
    }
    index_out[q as usize] = if finished {
        s.best_i
    } else {
        s.best_i | NEAREST_UNFINISHED
    };
    d2_out[q as usize] = s.best;
}

/// The target-to-predicted term of the gradient as a scatter: each of `queries`
/// targets adds its pair gradient (`scale_target`) to its nearest prediction in
/// 64-bit fixed point (`scratch`: 3 values per prediction and the flag word), so the
/// sum does not depend on the order the targets run in.
#[spirv(compute(threads(256)))]
pub fn chamfer_grad_scatter(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &ChamferParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pred: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] target: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] target_nearest: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] scratch: &mut [u32],
) {
    let j = index(group, groups, lid);
    if j >= p.queries {
        return;
    }
    let i = target_nearest[j as usize];
    if i >= p.points {
        return;
    }
    let g = chamfer_pair_grad(point(pred, i), point(target, j), p.sigma2, p.scale_target);
    let b = 3 * i as usize;
    atomics::add_fixed(scratch, b, g[0]);
    atomics::add_fixed(scratch, b + 1, g[1]);
    atomics::add_fixed(scratch, b + 2, g[2]);
}

/// `grad[p] +=` each of `queries` predictions' own term (to its nearest of `points`
/// targets, `scale_pred`) and the target terms `chamfer_grad_scatter` summed for it
/// (NaN everywhere if a non-finite value was scattered).
#[spirv(compute(threads(256)))]
pub fn chamfer_grad_gather(
    #[spirv(workgroup_id)] group: UVec3,
    #[spirv(num_workgroups)] groups: UVec3,
    #[spirv(local_invocation_index)] lid: u32,
    #[spirv(push_constant)] p: &ChamferParams,
    #[spirv(storage_buffer, descriptor_set = 0, binding = 0)] pred: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 1)] target: &[f32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 2)] pred_nearest: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 3)] scratch: &[u32],
    #[spirv(storage_buffer, descriptor_set = 0, binding = 4)] grad: &mut [f32],
) {
    let i = index(group, groups, lid);
    if i >= p.queries {
        return;
    }
    let me = point(pred, i);
    let n = pred_nearest[i as usize];
    let n = if n < p.points { n } else { 0 };
    let own = chamfer_pair_grad(me, point(target, n), p.sigma2, p.scale_pred);
    let poisoned = scratch[scratch.len() - 1] != 0;
    let b = 3 * i as usize;
    grad[b] += own[0] + fixed_sum(scratch, b, poisoned);
    grad[b + 1] += own[1] + fixed_sum(scratch, b + 1, poisoned);
    grad[b + 2] += own[2] + fixed_sum(scratch, b + 2, poisoned);
}

/// Value `i` of a fixed-point scratch (NaN when the scratch is poisoned). A function,
/// not a closure: rust-gpu cannot load a captured bool through its pointer.
fn fixed_sum(scratch: &[u32], i: usize, poisoned: bool) -> f32 {
    if poisoned {
        f32::NAN
    } else {
        drape_shared::fixed_point::decode([scratch[2 * i], scratch[2 * i + 1]])
    }
}
