//! The cloth layer's physics losses (`drape_shared::cloth_loss` states the math):
//! nearest neighbours and the Chamfer + Geman–McClure gradient by tiled brute force,
//! and the edge-length-variance ARAP term with its gradient.
//!
//! Every kernel here runs 256 invocations per workgroup and indexes
//! `(workgroup_id.y * num_workgroups.x + workgroup_id.x) * 256 + lid` (the engine's
//! `flat_grid`). The tiled kernels never return early: every invocation reaches every
//! barrier, and the ones past the end only help stage tiles.

use drape_shared::cloth_loss::{arap_edge_grad, chamfer_pair_grad, distance2, ArapParams, ChamferParams, CHAMFER_CHUNK, CHAMFER_MERGE, CHAMFER_OWN_TERM, CLOTH_LOSS_GROUP};
use spirv_std::arch::workgroup_memory_barrier_with_group_sync as barrier;
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
/// (the host refuses empty sets before it gets here).
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
) {
    let q = index(group, groups, lid);
    let active = q < p.queries;
    let me = if active { point(queries, q) } else { [0.0; 3] };
    let mut best = f32::INFINITY;
    let mut best_i = u32::MAX;
    if active && p.flags & CHAMFER_MERGE != 0 {
        best = d2_out[q as usize];
        best_i = index_out[q as usize];
    }
    let end = if p.points - p.offset < CHAMFER_CHUNK { p.points } else { p.offset + CHAMFER_CHUNK };
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
        let count = if end - t0 < CLOTH_LOSS_GROUP { end - t0 } else { CLOTH_LOSS_GROUP };
        let mut k = 0u32;
        while k < count {
            let l = 3 * k as usize;
            let d = distance2(me, [tile[l], tile[l + 1], tile[l + 2]]);
            if d < best {
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
        index_out[q as usize] = best_i;
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
    let end = if p.points - p.offset < CHAMFER_CHUNK { p.points } else { p.offset + CHAMFER_CHUNK };
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
        let count = if end - t0 < CLOTH_LOSS_GROUP { end - t0 } else { CLOTH_LOSS_GROUP };
        let mut k = 0u32;
        while k < count {
            if tile_nearest[k as usize] == i {
                let l = 3 * k as usize;
                let d = chamfer_pair_grad(me, [tile[l], tile[l + 1], tile[l + 2]], p.sigma2, p.scale_target);
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
    lengths[e as usize] = drape_shared::real::Float::sqrt(distance2(point(positions, a), point(positions, b)));
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
    let inv = if p.edges > 0 { 1.0 / p.edges as f32 } else { 0.0 };
    let mean = tree_sum(sums, lid, p.edges, lengths, 0.0, false) * inv;
    let var = tree_sum(sums, lid, p.edges, lengths, mean, true) * inv;
    if lid == 0 {
        stats[0] = mean;
        stats[1] = var;
    }
}

/// Σ v (or Σ (v - mean)² with `squared`) over `values[..len]`, by all 256
/// invocations; every invocation gets the total.
fn tree_sum(sums: &mut [f32; GROUP], lid: u32, len: u32, values: &[f32], mean: f32, squared: bool) -> f32 {
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
        let d = arap_edge_grad(me, point(positions, neighbours[k as usize]), mean, edges, p.scale);
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
