//! The cloth layer's physics losses on the GPU (kernels `cloth_loss::*`): the
//! simulation term (bidirectional Chamfer through Geman–McClure) and ARAP (the
//! variance of edge lengths), each adding its gradient to the posed Gaussian centres;
//! and their CPU references from the same shared functions (`drape_shared::cloth_loss`,
//! which states the math), generic over f32/f64.
//!
//! Nearest neighbours two ways ([`NearestSearch`]): tiled brute force (exact, no build
//! step, deterministic gradient gathered per point; the faster one below about 700 ×
//! 700 points) and a uniform grid (bounds, cell keys, the stable radix sort, cell ranges, a
//! shell search with a brute-force finish for the queries it could not settle within
//! llvmpipe's loop budget; the gradient's target terms scattered in deterministic
//! fixed point): exact too, the faster one from a few thousand points per side (what
//! training's cloth losses use), and what makes 10⁶ × 10⁶ sets possible. `Auto` picks the
//! grid above [`AUTO_GRID_PAIRS`] point pairs.

use drape_shared::cloth_loss::{
    arap_edge_grad, chamfer_pair_grad, distance2, geman_mcclure, ArapParams, ChamferParams,
    GridParams, CHAMFER_CHUNK, CHAMFER_FINISH, CHAMFER_LAST, CHAMFER_MERGE, CHAMFER_OWN_TERM,
    GRID_BOUNDS_WORDS, GRID_CELL_BITS, GRID_MAX_CELLS,
};
use drape_shared::real::Real;

use crate::buffer::{Buffer, BufferDesc};
use crate::context::Context;
use crate::error::{EngineError, Result};
use crate::kernels;
use crate::mirror::{read_through, Mirror};
use crate::ops::accumulate::FixedPointScratch;
use crate::ops::radix_sort::RadixSort;
use crate::recorder::{flat_grid as grid, Recording};

/// How [`Chamfer`] finds nearest neighbours. Both are exact (ties to the lower index).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum NearestSearch {
    /// The grid when `n · m` exceeds [`AUTO_GRID_PAIRS`], else brute force.
    #[default]
    Auto,
    /// Every pair: O(n · m), best for small sets.
    BruteForce,
    /// A uniform grid: cell keys sorted by the radix sort, then the cells near each query.
    Grid,
}

/// Above this many point pairs `Auto` searches through the grid. The grid has a fixed
/// cost (fills, sort passes) that brute force does not, and brute force grows with
/// `n · m`: 2^19 is about where the two crossed on lavapipe (`engine-bench ops --only
/// chamfer --chamfer-compare N`; the figures are in docs/performance.md, "SSIM, Chamfer,
/// triplane").
pub const AUTO_GRID_PAIRS: u64 = 1 << 19;

/// The grid's scratch: bounds, (cell, point) pairs and their sort, cell ranges, and
/// the fixed-point sums of the gradient's target terms.
struct GridScratch {
    bounds: Buffer,
    keys: Buffer,
    order: Buffer,
    start: Buffer,
    end: Buffer,
    sort: RadixSort,
    target_terms: FixedPointScratch,
}

impl GridScratch {
    fn new(ctx: &Context, max_pred: u32, max_target: u32) -> Result<Self> {
        let len = max_pred.max(max_target).max(1);
        let b = |name: &str, words: u64| ctx.create_buffer(name, BufferDesc::gpu_only(4 * words));
        let cells = u64::from(GRID_MAX_CELLS);
        Ok(Self {
            bounds: b("chamfer grid bounds", u64::from(GRID_BOUNDS_WORDS))?,
            keys: b("chamfer grid keys", len.into())?,
            order: b("chamfer grid order", len.into())?,
            start: b("chamfer grid cell starts", cells)?,
            end: b("chamfer grid cell ends", cells)?,
            sort: RadixSort::new(ctx, len)?,
            target_terms: FixedPointScratch::new(ctx, "chamfer target terms", 3 * max_pred.max(1))?,
        })
    }

    /// Records the nearest of `points` (`np`) to each of `queries` (`nq`) into
    /// `index_out` and `d2_out`.
    #[allow(clippy::too_many_arguments)]
    fn record_nearest<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        queries: &'a Buffer,
        nq: u32,
        points: &'a Buffer,
        np: u32,
        index_out: &'a Buffer,
        d2_out: &'a Buffer,
    ) -> Result<()> {
        let p = GridParams {
            queries: np,
            points: np,
            _pad: [0; 2],
        };
        rec.fill(&self.bounds, 0);
        rec.fill(&self.start, 0);
        rec.fill(&self.end, 0);
        rec.dispatch(
            "chamfer.grid_bounds",
            kernels::cloth_loss::Bounds {
                points: points.read(),
                bounds: self.bounds.write(),
            },
            &p,
            grid(np),
        )?;
        rec.dispatch(
            "chamfer.grid_keys",
            kernels::cloth_loss::CellKeys {
                points: points.read(),
                bounds: self.bounds.read(),
                keys: self.keys.write(),
                values: self.order.write(),
            },
            &p,
            grid(np),
        )?;
        self.sort
            .record(rec, &self.keys, &self.order, np, GRID_CELL_BITS)?;
        rec.dispatch(
            "chamfer.grid_ranges",
            kernels::cloth_loss::CellRanges {
                keys: self.keys.read(),
                start: self.start.write(),
                end: self.end.write(),
            },
            &p,
            grid(np),
        )?;
        let q = GridParams {
            queries: nq,
            points: np,
            _pad: [0; 2],
        };
        rec.dispatch(
            "chamfer.grid_search",
            kernels::cloth_loss::NearestGrid {
                queries: queries.read(),
                points: points.read(),
                bounds: self.bounds.read(),
                start: self.start.read(),
                end: self.end.read(),
                order: self.order.read(),
                index_out: index_out.write(),
                d2_out: d2_out.write(),
            },
            &q,
            grid(nq),
        )?;
        // Queries the grid left unfinished (over the step budget) by brute force; a
        // workgroup with none returns at once.
        let chunks = np.div_ceil(CHAMFER_CHUNK);
        for (k, offset) in (0..np).step_by(CHAMFER_CHUNK as usize).enumerate() {
            let last = if k + 1 == chunks as usize {
                CHAMFER_LAST
            } else {
                0
            };
            let f = ChamferParams {
                queries: nq,
                points: np,
                offset,
                flags: CHAMFER_FINISH | last,
                ..Default::default()
            };
            rec.dispatch(
                "chamfer.grid_finish",
                kernels::cloth_loss::Nearest {
                    queries: queries.read(),
                    points: points.read(),
                    index_out: index_out.write(),
                    d2_out: d2_out.write(),
                },
                &f,
                grid(nq),
            )?;
        }
        Ok(())
    }
}

/// Scratch for Chamfer losses between up to `max_pred` predicted and `max_target`
/// target points.
pub struct Chamfer {
    max_pred: u32,
    max_target: u32,
    pred_nearest: Buffer,
    pred_d2: Buffer,
    target_nearest: Buffer,
    target_d2: Buffer,
    search: NearestSearch,
    /// Made when `search` can pick the grid for sets of the planned size.
    grid: Option<GridScratch>,
    /// (n, m, σ²) of the last recording, for reading its values back.
    last: std::cell::Cell<(u32, u32, f32)>,
    /// `pred_d2` and `target_d2` in host memory, where [`Chamfer::keep_host_mirror`]
    /// asked for them.
    d2_mirrors: Option<[Mirror; 2]>,
}

/// `½ (mean ρ(d(p, Q)) + mean ρ(d(q, P)))` and the plain Chamfer distance
/// `½ (mean d(p, Q) + mean d(q, P))` of one evaluation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChamferValue {
    /// The robust Chamfer loss.
    pub robust: f64,
    /// The plain Chamfer distance.
    pub distance: f64,
}

impl Chamfer {
    /// Scratch for up to `max_pred` predicted and `max_target` target points ([`NearestSearch::Auto`]).
    pub fn new(ctx: &Context, max_pred: u32, max_target: u32) -> Result<Self> {
        Self::with_search(ctx, max_pred, max_target, NearestSearch::Auto)
    }

    /// A plan that finds nearest neighbours as `search` says.
    pub fn with_search(
        ctx: &Context,
        max_pred: u32,
        max_target: u32,
        search: NearestSearch,
    ) -> Result<Self> {
        let b = |name: &str, n: u32| {
            ctx.create_buffer(name, BufferDesc::gpu_only(4 * u64::from(n.max(1))))
        };
        let may_grid = match search {
            NearestSearch::BruteForce => false,
            NearestSearch::Grid => true,
            NearestSearch::Auto => u64::from(max_pred) * u64::from(max_target) > AUTO_GRID_PAIRS,
        };
        Ok(Self {
            search,
            grid: if may_grid {
                Some(GridScratch::new(ctx, max_pred, max_target)?)
            } else {
                None
            },
            max_pred,
            max_target,
            pred_nearest: b("chamfer pred nearest", max_pred)?,
            pred_d2: b("chamfer pred d2", max_pred)?,
            target_nearest: b("chamfer target nearest", max_target)?,
            target_d2: b("chamfer target d2", max_target)?,
            last: std::cell::Cell::new((0, 0, 0.0)),
            d2_mirrors: None,
        })
    }

    /// Keeps a host copy of both sides' squared distances: after
    /// [`Chamfer::record_readback`] in the recording that computed them,
    /// [`Chamfer::read_value`] reads them without a submission or a wait of its own.
    pub fn keep_host_mirror(&mut self, ctx: &Context) -> Result<()> {
        self.d2_mirrors = Some([
            Mirror::new(ctx, &self.pred_d2)?,
            Mirror::new(ctx, &self.target_d2)?,
        ]);
        Ok(())
    }

    /// Records the copy of the distances just recorded into the host mirrors (nothing
    /// without them).
    pub fn record_readback<'a>(&'a self, rec: &mut Recording<'a>) {
        if let Some([p, t]) = &self.d2_mirrors {
            let (n, m, _) = self.last.get();
            p.record_copy(rec, &self.pred_d2, 4 * u64::from(n));
            t.record_copy(rec, &self.target_d2, 4 * u64::from(m));
        }
    }

    /// Records the nearest neighbours of `pred` (`n` points, xyz) in `target` (`m`)
    /// and back and, with `grad = Some((buffer, λ))`, adds `λ ∂L_sim/∂pred` to it.
    /// An empty set is an error (the distance has no value), as is one larger than
    /// this scratch was made for.
    #[allow(clippy::too_many_arguments)]
    pub fn record<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        pred: &'a Buffer,
        n: u32,
        target: &'a Buffer,
        m: u32,
        sigma: f32,
        grad: Option<(&'a Buffer, f32)>,
    ) -> Result<()> {
        if n == 0 {
            return Err(EngineError::Empty {
                what: "the predicted point set",
                why: "the Chamfer distance needs a point on each side",
            });
        }
        if m == 0 {
            return Err(EngineError::Empty {
                what: "the target point set",
                why: "the Chamfer distance needs a point on each side",
            });
        }
        if n > self.max_pred {
            return Err(EngineError::too_large(
                "predicted Chamfer points",
                n.into(),
                self.max_pred.into(),
                "the Chamfer plan",
            ));
        }
        if m > self.max_target {
            return Err(EngineError::too_large(
                "target Chamfer points",
                m.into(),
                self.max_target.into(),
                "the Chamfer plan",
            ));
        }
        let sigma2 = sigma * sigma;
        self.last.set((n, m, sigma2));
        self.d2_mirrors
            .iter()
            .flatten()
            .for_each(Mirror::mark_stale);
        let this = self;
        let use_grid = match self.search {
            NearestSearch::BruteForce => false,
            NearestSearch::Grid => true,
            NearestSearch::Auto => u64::from(n) * u64::from(m) > AUTO_GRID_PAIRS,
        };
        if let (true, Some(gs)) = (use_grid, &this.grid) {
            gs.record_nearest(rec, pred, n, target, m, &this.pred_nearest, &this.pred_d2)?;
            gs.record_nearest(
                rec,
                target,
                m,
                pred,
                n,
                &this.target_nearest,
                &this.target_d2,
            )?;
            if let Some((g, lambda)) = grad {
                let p = ChamferParams {
                    queries: m,
                    points: n,
                    sigma2,
                    scale_pred: 0.5 * lambda / n as f32,
                    scale_target: 0.5 * lambda / m as f32,
                    ..Default::default()
                };
                gs.target_terms.record_clear(rec);
                rec.dispatch(
                    "chamfer.grad_scatter",
                    kernels::cloth_loss::ChamferGradScatter {
                        pred: pred.read(),
                        target: target.read(),
                        target_nearest: this.target_nearest.read(),
                        scratch: gs.target_terms.buffer().write(),
                    },
                    &p,
                    grid(m),
                )?;
                let q = ChamferParams {
                    queries: n,
                    points: m,
                    ..p
                };
                rec.dispatch(
                    "chamfer.grad_gather",
                    kernels::cloth_loss::ChamferGradGather {
                        pred: pred.read(),
                        target: target.read(),
                        pred_nearest: this.pred_nearest.read(),
                        scratch: gs.target_terms.buffer().read(),
                        grad: g.write(),
                    },
                    &q,
                    grid(n),
                )?;
            }
            return Ok(());
        }
        // Each dispatch walks one chunk of the searched set (llvmpipe's loop cap),
        // merging with the chunks before; the chunks of one search are ordered by
        // barriers, the two directions are independent.
        for (k, offset) in (0..m).step_by(CHAMFER_CHUNK as usize).enumerate() {
            let p = ChamferParams {
                queries: n,
                points: m,
                sigma2,
                offset,
                flags: if k > 0 { CHAMFER_MERGE } else { 0 },
                ..Default::default()
            };
            rec.dispatch(
                "chamfer.nearest_pred",
                kernels::cloth_loss::Nearest {
                    queries: pred.read(),
                    points: target.read(),
                    index_out: this.pred_nearest.write(),
                    d2_out: this.pred_d2.write(),
                },
                &p,
                grid(n),
            )?;
        }
        for (k, offset) in (0..n).step_by(CHAMFER_CHUNK as usize).enumerate() {
            let p = ChamferParams {
                queries: m,
                points: n,
                sigma2,
                offset,
                flags: if k > 0 { CHAMFER_MERGE } else { 0 },
                ..Default::default()
            };
            rec.dispatch(
                "chamfer.nearest_target",
                kernels::cloth_loss::Nearest {
                    queries: target.read(),
                    points: pred.read(),
                    index_out: this.target_nearest.write(),
                    d2_out: this.target_d2.write(),
                },
                &p,
                grid(m),
            )?;
        }
        if let Some((g, lambda)) = grad {
            for (k, offset) in (0..m).step_by(CHAMFER_CHUNK as usize).enumerate() {
                let p = ChamferParams {
                    queries: n,
                    points: m,
                    sigma2,
                    scale_pred: 0.5 * lambda / n as f32,
                    scale_target: 0.5 * lambda / m as f32,
                    offset,
                    flags: if k == 0 { CHAMFER_OWN_TERM } else { 0 },
                    _pad: 0,
                };
                rec.dispatch(
                    "chamfer.grad",
                    kernels::cloth_loss::ChamferGrad {
                        pred: pred.read(),
                        target: target.read(),
                        pred_nearest: this.pred_nearest.read(),
                        target_nearest: this.target_nearest.read(),
                        grad: g.write(),
                    },
                    &p,
                    grid(n),
                )?;
            }
        }
        Ok(())
    }

    /// The values of the last recorded evaluation (the distances from the host mirrors
    /// where the recording that computed them copied them there, otherwise read back
    /// from the device).
    pub fn read_value(&mut self, ctx: &Context) -> Result<ChamferValue> {
        let (n, m, sigma2) = self.last.get();
        let (pm, tm) = match self.d2_mirrors.as_mut() {
            Some([p, t]) => (Some(p), Some(t)),
            None => (None, None),
        };
        let a = read_through::<f32>(ctx, pm, &mut self.pred_d2, n as usize)?;
        let b = read_through::<f32>(ctx, tm, &mut self.target_d2, m as usize)?;
        Ok(chamfer_value(&a, &b, f64::from(sigma2)))
    }

    /// The nearest-neighbour indices of the last evaluation: (pred → target, target → pred).
    pub fn read_nearest(&mut self, ctx: &Context) -> Result<(Vec<u32>, Vec<u32>)> {
        let (n, m, _) = self.last.get();
        Ok((
            ctx.read_buffer(&mut self.pred_nearest, n as usize)?,
            ctx.read_buffer(&mut self.target_nearest, m as usize)?,
        ))
    }
}

fn chamfer_value(pred_d2: &[f32], target_d2: &[f32], sigma2: f64) -> ChamferValue {
    let mean = |v: &[f32], f: &dyn Fn(f64) -> f64| {
        v.iter().map(|&d| f(f64::from(d))).sum::<f64>() / v.len().max(1) as f64
    };
    let rho = |d2: f64| geman_mcclure(d2, sigma2).0;
    ChamferValue {
        robust: 0.5 * (mean(pred_d2, &rho) + mean(target_d2, &rho)),
        distance: 0.5 * (mean(pred_d2, &f64::sqrt) + mean(target_d2, &f64::sqrt)),
    }
}

/// The edge graph of a point set and scratch for its ARAP term.
pub struct Arap {
    /// Points in the graph.
    pub vertices: u32,
    /// Undirected edges in the graph.
    pub edges: u32,
    edge_list: Buffer,
    offsets: Buffer,
    neighbours: Buffer,
    lengths: Buffer,
    stats: Buffer,
    /// `stats` in host memory, where [`Arap::keep_host_mirror`] asked for it.
    stats_mirror: Option<Mirror>,
}

impl Arap {
    /// Uploads the graph of `edges` (pairs of distinct vertex indices below `vertices`;
    /// checked) in both the edge-list and the per-vertex (CSR) form.
    pub fn new(ctx: &Context, vertices: u32, edges: &[[u32; 2]]) -> Result<Self> {
        for (k, e) in edges.iter().enumerate() {
            assert!(
                e[0] < vertices && e[1] < vertices && e[0] != e[1],
                "ARAP edge {k} {e:?} is not a pair of distinct vertices below {vertices}"
            );
        }
        let (offsets, neighbours) = csr(vertices as usize, edges);
        let b = |name: &str, words: usize| {
            ctx.create_buffer(name, BufferDesc::gpu_only(4 * words.max(1) as u64))
        };
        let mut edge_list = b("arap edges", 2 * edges.len())?;
        let mut off = b("arap offsets", offsets.len())?;
        let mut nb = b("arap neighbours", neighbours.len())?;
        if !edges.is_empty() {
            ctx.write_buffer(
                &mut edge_list,
                &edges.iter().flatten().copied().collect::<Vec<u32>>(),
            )?;
            ctx.write_buffer(&mut nb, &neighbours)?;
        }
        ctx.write_buffer(&mut off, &offsets)?;
        Ok(Self {
            vertices,
            edges: edges.len() as u32,
            edge_list,
            offsets: off,
            neighbours: nb,
            lengths: b("arap lengths", edges.len())?,
            stats: b("arap stats", 2)?,
            stats_mirror: None,
        })
    }

    /// Keeps a host copy of the statistics: after [`Arap::record_readback`] in the
    /// recording that computed them, [`Arap::read_stats`] reads them without a
    /// submission or a wait of its own.
    pub fn keep_host_mirror(&mut self, ctx: &Context) -> Result<()> {
        self.stats_mirror = Some(Mirror::new(ctx, &self.stats)?);
        Ok(())
    }

    /// Records the copy of the statistics just recorded into the host mirror (nothing
    /// without one).
    pub fn record_readback<'a>(&'a self, rec: &mut Recording<'a>) {
        if let Some(m) = &self.stats_mirror {
            m.record_copy(rec, &self.stats, 8);
        }
    }

    /// Records the edge-length variance of `positions` (this graph's vertices, xyz)
    /// and, with `grad = Some((buffer, λ))`, adds `λ ∂var/∂positions` to it.
    pub fn record<'a>(
        &'a self,
        rec: &mut Recording<'a>,
        positions: &'a Buffer,
        grad: Option<(&'a Buffer, f32)>,
    ) -> Result<()> {
        if let Some(m) = &self.stats_mirror {
            m.mark_stale();
        }
        let p = ArapParams {
            edges: self.edges,
            vertices: self.vertices,
            scale: grad.map_or(0.0, |g| g.1),
            _pad: 0,
        };
        rec.dispatch(
            "arap.lengths",
            kernels::cloth_loss::ArapLengths {
                positions: positions.read(),
                edges: self.edge_list.read(),
                lengths: self.lengths.write(),
            },
            &p,
            grid(self.edges),
        )?;
        rec.dispatch(
            "arap.stats",
            kernels::cloth_loss::ArapStats {
                lengths: self.lengths.read(),
                stats: self.stats.write(),
            },
            &p,
            [1, 1, 1],
        )?;
        if let Some((g, _)) = grad {
            rec.dispatch(
                "arap.grad",
                kernels::cloth_loss::ArapGrad {
                    positions: positions.read(),
                    offsets: self.offsets.read(),
                    neighbours: self.neighbours.read(),
                    stats: self.stats.read(),
                    grad: g.write(),
                },
                &p,
                grid(self.vertices),
            )?;
        }
        Ok(())
    }

    /// `[mean edge length, variance]` of the last recorded evaluation (from the host
    /// mirror where the recording that computed them copied them there).
    pub fn read_stats(&mut self, ctx: &Context) -> Result<[f32; 2]> {
        let v = read_through::<f32>(ctx, self.stats_mirror.as_mut(), &mut self.stats, 2)?;
        Ok([v[0], v[1]])
    }
}

/// The per-vertex adjacency of an edge list: `offsets` (vertices + 1) into
/// `neighbours` (each edge appears at both ends).
pub fn csr(vertices: usize, edges: &[[u32; 2]]) -> (Vec<u32>, Vec<u32>) {
    let mut degree = vec![0u32; vertices + 1];
    for e in edges {
        degree[e[0] as usize + 1] += 1;
        degree[e[1] as usize + 1] += 1;
    }
    for v in 0..vertices {
        degree[v + 1] += degree[v];
    }
    let offsets = degree.clone();
    let mut fill = degree;
    let mut neighbours = vec![0u32; 2 * edges.len()];
    for e in edges {
        for (a, b) in [(e[0], e[1]), (e[1], e[0])] {
            neighbours[fill[a as usize] as usize] = b;
            fill[a as usize] += 1;
        }
    }
    (offsets, neighbours)
}

/// CPU references of the nearest-point search, the Chamfer loss and the ARAP loss, generic over f32/f64.
pub mod reference {
    use super::*;

    /// Nearest point of `points` to each of `queries` (lower index on ties) and its
    /// squared distance: the CPU reference of `cloth_loss::nearest`.
    pub fn nearest<F: Real>(queries: &[[F; 3]], points: &[[F; 3]]) -> Vec<(usize, F)> {
        queries
            .iter()
            .map(|&q| {
                let mut best = (usize::MAX, F::infinity());
                for (j, &p) in points.iter().enumerate() {
                    let d = distance2(q, p);
                    if d < best.1 {
                        best = (j, d);
                    }
                }
                best
            })
            .collect()
    }

    /// CPU reference: (`L_sim` without λ, `∂L_sim/∂pred`) for non-empty sets.
    pub fn chamfer<F: Real>(pred: &[[F; 3]], target: &[[F; 3]], sigma: F) -> (F, Vec<[F; 3]>) {
        let sigma2 = sigma * sigma;
        let half = F::of(0.5);
        let (n, m) = (F::of(pred.len() as f32), F::of(target.len() as f32));
        let fwd = nearest(pred, target);
        let bwd = nearest(target, pred);
        let mut loss = F::zero();
        let mut grad = vec![[F::zero(); 3]; pred.len()];
        for (i, &(j, d2)) in fwd.iter().enumerate() {
            loss += half * geman_mcclure(d2, sigma2).0 / n;
            grad[i] = chamfer_pair_grad(pred[i], target[j], sigma2, half / n);
        }
        for (j, &(i, d2)) in bwd.iter().enumerate() {
            loss += half * geman_mcclure(d2, sigma2).0 / m;
            let g = chamfer_pair_grad(pred[i], target[j], sigma2, half / m);
            for c in 0..3 {
                grad[i][c] += g[c];
            }
        }
        (loss, grad)
    }

    /// CPU reference: (variance of the edge lengths, its gradient to the positions).
    pub fn arap<F: Real>(positions: &[[F; 3]], edges: &[[u32; 2]]) -> (F, Vec<[F; 3]>) {
        let mut grad = vec![[F::zero(); 3]; positions.len()];
        if edges.is_empty() {
            return (F::zero(), grad);
        }
        let e = F::of(edges.len() as f32);
        let lengths: Vec<F> = edges
            .iter()
            .map(|&[a, b]| distance2(positions[a as usize], positions[b as usize]).sqrt())
            .collect();
        let mean = lengths.iter().fold(F::zero(), |s, &l| s + l) / e;
        let var = lengths
            .iter()
            .fold(F::zero(), |s, &l| s + (l - mean) * (l - mean))
            / e;
        for &[a, b] in edges {
            let (pa, pb) = (positions[a as usize], positions[b as usize]);
            let ga = arap_edge_grad(pa, pb, mean, e, F::one());
            let gb = arap_edge_grad(pb, pa, mean, e, F::one());
            for c in 0..3 {
                grad[a as usize][c] += ga[c];
                grad[b as usize][c] += gb[c];
            }
        }
        (var, grad)
    }
}
