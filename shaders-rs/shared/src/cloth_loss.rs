//! The paper's physics losses on the cloth layer's posed Gaussian centres, and their
//! gradients to those centres.
//!
//! **Simulation (Chamfer + Geman–McClure).** With `P` the predicted points (`n`), `Q`
//! the simulated garment vertices of the frame (`m`), `d(p, Q)` the distance to the
//! nearest point of the other set and `ρ(d) = d² / (d² + σ²)`:
//! `L_sim = ½ (1/n Σ_p ρ(d(p, Q)) + 1/m Σ_q ρ(d(q, P)))`. ρ saturates at 1 for
//! `d ≫ σ`, so a far outlier (a sleeve the simulation put elsewhere) pulls with a
//! bounded force; `σ` is in scene units (metres), default [`GM_SIGMA_DEFAULT`].
//! Nearest neighbours by tiled brute force (every pair, a tile of the other set
//! staged in workgroup memory): exact, with no build step and no tuning, the faster
//! way for small sets; from about 700 × 700 points on (training's cloth losses
//! included) through a uniform grid (below), exact as well. Ties go to the lower index.
//!
//! **ARAP (the paper's form).** The variance of the edge lengths `ℓ_e = |v_a - v_b|`
//! over the garment edges between cloth Gaussians: `L = 1/E Σ (ℓ_e - ℓ̄)²`;
//! `∂L/∂ℓ_e = 2/E (ℓ_e - ℓ̄)` (the mean's own derivative sums to zero), and
//! `∂ℓ_e/∂v_a = (v_a - v_b) / ℓ_e` (0 for a zero-length edge, where it is undefined).

use crate::real::Real;

/// Default Geman–McClure σ (metres): about a garment's thickness plus the
/// simulation's error, so points within a centimetre or two pull nearly
/// quadratically and farther ones saturate.
pub const GM_SIGMA_DEFAULT: f32 = 0.02;

/// Workgroup size of the cloth-loss kernels, and the tile of the other point set
/// staged in workgroup memory.
pub const CLOTH_LOSS_GROUP: u32 = 256;

/// Push constants of `cloth_loss::nearest` and `cloth_loss::chamfer_grad`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct ChamferParams {
    /// Points searched from (`nearest`), or predicted points (`chamfer_grad`).
    pub queries: u32,
    /// Points searched in (`nearest`), or target points (`chamfer_grad`).
    pub points: u32,
    /// `σ²` of Geman–McClure.
    pub sigma2: f32,
    /// Multiplies the predicted-to-target term's gradient (`λ · ½ / n`).
    pub scale_pred: f32,
    /// Multiplies the target-to-predicted term's gradient (`λ · ½ / m`).
    pub scale_target: f32,
    /// This dispatch covers `points[offset .. offset + CHAMFER_CHUNK]` (see
    /// [`CHAMFER_CHUNK`]).
    pub offset: u32,
    /// [`CHAMFER_MERGE`], [`CHAMFER_OWN_TERM`].
    pub flags: u32,
    pub _pad: u32,
}

/// Points of the searched set one dispatch walks: llvmpipe abandons an invocation
/// after 65,535 loop iterations, so larger sets are searched in chunks, each
/// dispatch merging with the best found so far.
pub const CHAMFER_CHUNK: u32 = 32_768;
/// `nearest`: start from the best of the earlier chunks (in the output buffers).
pub const CHAMFER_MERGE: u32 = 1;
/// `chamfer_grad`: add the point's own term (once, in the first chunk).
pub const CHAMFER_OWN_TERM: u32 = 2;

/// Push constants of the `cloth_loss::arap_*` kernels.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct ArapParams {
    pub edges: u32,
    pub vertices: u32,
    /// Multiplies the gradient (the loss weight λ).
    pub scale: f32,
    pub _pad: u32,
}

/// `(ρ(d²), dρ/d(d²))` of Geman–McClure, `ρ = d² / (d² + σ²)`.
#[inline]
pub fn geman_mcclure<F: Real>(d2: F, sigma2: F) -> (F, F) {
    let denom = d2 + sigma2;
    (d2 / denom, sigma2 / (denom * denom))
}

/// Squared distance of two points.
#[inline]
pub fn distance2<F: Real>(a: [F; 3], b: [F; 3]) -> F {
    let (x, y, z) = (a[0] - b[0], a[1] - b[1], a[2] - b[2]);
    x * x + y * y + z * z
}

/// The gradient of `scale · ρ(|p - q|²)` with respect to `p`.
#[inline]
pub fn chamfer_pair_grad<F: Real>(p: [F; 3], q: [F; 3], sigma2: F, scale: F) -> [F; 3] {
    let (_, d) = geman_mcclure(distance2(p, q), sigma2);
    let k = F::of(2.0) * scale * d;
    [k * (p[0] - q[0]), k * (p[1] - q[1]), k * (p[2] - q[2])]
}

/// The gradient of the edge-length variance through one edge `a → b` to `a`:
/// `scale · 2/E (ℓ - ℓ̄) (a - b) / ℓ`.
#[inline]
pub fn arap_edge_grad<F: Real>(a: [F; 3], b: [F; 3], mean: F, edges: F, scale: F) -> [F; 3] {
    let len = distance2(a, b).sqrt();
    if len <= F::zero() {
        return [F::zero(); 3];
    }
    let k = scale * F::of(2.0) * (len - mean) / (edges * len);
    [k * (a[0] - b[0]), k * (a[1] - b[1]), k * (a[2] - b[2])]
}

// ---------------------------------------------------------------------------------
// Nearest neighbours through a uniform grid, for sets too large for brute force.
//
// The searched set's bounding box (found on the GPU by atomic maxima of
// order-preserving integer keys, [`ordered_key`]) is cut into about
// [`GRID_CELLS_PER_POINT`] cells per point (at most [`GRID_MAX_CELLS`]); the points are
// sorted by cell (the engine's stable radix sort) and each cell's range found. A query
// visits the cells in shells of growing Chebyshev radius `r` around its own cell (its
// position clamped into the box) and stops once its best distance is below `r·h`
// (minus [`GridSpec::slack`]): every point outside the shells searched is farther than
// that, also for a query outside the box (its projection onto the box is nearer to every
// point in it). So the search is exact, ties go to the lower index as in brute force,
// and a query costs the points of the few cells around it: for 10⁶ × 10⁶ points that is
// hundreds of distances per query instead of 10⁶. A query that would need more than
// [`GRID_STEP_BUDGET`] loop steps (llvmpipe abandons an invocation after 65,535; far
// outliers, or a set piled into a few cells) is marked [`NEAREST_UNFINISHED`] and
// finished by the brute-force kernel, which starts from the best the grid found.
// ---------------------------------------------------------------------------------

/// Cells per searched point: four keeps the cells of a surface sampled by the points
/// (a garment, where most of the box is empty) at a few points each.
pub const GRID_CELLS_PER_POINT: u32 = 4;
/// At most this many cells (their start and end words: 32 MiB).
pub const GRID_MAX_CELLS: u32 = 1 << 22;
/// Bits of a cell index: the radix sort's key width.
pub const GRID_CELL_BITS: u32 = 22;
/// Loop steps (cells and points visited) a grid query may take before it hands over
/// to brute force: below llvmpipe's 65,535 with room for the shell loops' own steps.
pub const GRID_STEP_BUDGET: u32 = 48_000;
/// Set in a query's nearest index while its search is unfinished (the brute-force
/// finish clears it). Indices are below 2^31 (point sets below 2^24).
pub const NEAREST_UNFINISHED: u32 = 1 << 31;
/// `nearest` (brute force) finishes only the queries marked unfinished, starting from
/// their best so far; the other queries' workgroups return at once.
pub const CHAMFER_FINISH: u32 = 4;
/// `nearest`: this is the last chunk; clear [`NEAREST_UNFINISHED`] as it writes.
pub const CHAMFER_LAST: u32 = 8;
/// Words of the bounds buffer: the ordered keys of max x, y, z and of max -x, -y, -z.
pub const GRID_BOUNDS_WORDS: u32 = 6;

/// Push constants of the grid kernels (`cloth_loss::bounds`, `cell_keys`,
/// `cell_ranges`, `nearest_grid`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct GridParams {
    /// Points searched from (`nearest_grid`); keys sorted (`cell_ranges`).
    pub queries: u32,
    /// Points of the gridded set.
    pub points: u32,
    pub _pad: [u32; 2],
}

/// An f32 as a u32 whose unsigned order is the floats' order (negative floats
/// have all bits flipped, positive ones the sign bit set), so that integer atomic
/// maxima find float maxima. 0 is below every key.
#[inline]
pub fn ordered_key(x: f32) -> u32 {
    let b = x.to_bits();
    if b & 0x8000_0000 != 0 {
        !b
    } else {
        b | 0x8000_0000
    }
}

/// The inverse of [`ordered_key`].
#[inline]
pub fn from_ordered_key(k: u32) -> f32 {
    if k & 0x8000_0000 != 0 {
        f32::from_bits(k & 0x7fff_ffff)
    } else {
        f32::from_bits(!k)
    }
}

/// A uniform grid over a box: cell `(x, y, z)` covers `origin + [x, x + 1)·h` etc.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridSpec {
    pub origin: [f32; 3],
    /// Cell edge.
    pub h: f32,
    pub dims: [u32; 3],
    /// What f32 rounding may move a point across a cell face by: the stopping bound
    /// is `r·h - slack`.
    pub slack: f32,
}

impl GridSpec {
    /// The grid for points within `[lo, hi]` (componentwise; from the bounds buffer),
    /// `points` of them.
    pub fn new(lo: [f32; 3], hi: [f32; 3], points: u32) -> Self {
        let mut extent = [0.0f32; 3];
        let mut widest = 0.0f32;
        let mut magnitude = 0.0f32;
        for a in 0..3 {
            extent[a] = if hi[a] > lo[a] { hi[a] - lo[a] } else { 0.0 };
            widest = if extent[a] > widest {
                extent[a]
            } else {
                widest
            };
            let m = if lo[a] < 0.0 { -lo[a] } else { lo[a] };
            magnitude = if m > magnitude { m } else { magnitude };
        }
        // Non-finite bounds (the kernels skip non-finite points, so only an empty or
        // all-non-finite set gets here) and coincident points: one cell.
        if !(widest > 0.0) || !(widest < f32::MAX) || !(magnitude < f32::MAX) {
            let o = if magnitude < f32::MAX { lo } else { [0.0; 3] };
            return Self {
                origin: o,
                h: 1.0,
                dims: [1, 1, 1],
                slack: 0.0,
            };
        }
        // A flat or thin set still gets cells across its thin axes: each extent is
        // at least a thousandth of the widest.
        let floor = widest * 1e-3;
        let mut volume = 1.0f32;
        // Indexed, not `iter_mut`: rust-gpu cannot turn an array into a slice.
        for a in 0..3 {
            extent[a] = if extent[a] > floor { extent[a] } else { floor };
            volume *= extent[a];
        }
        // No u64 here: the shaders are built without the Int64 capability.
        let wanted = if points > GRID_MAX_CELLS / GRID_CELLS_PER_POINT {
            GRID_MAX_CELLS
        } else if points == 0 {
            1
        } else {
            points * GRID_CELLS_PER_POINT
        };
        // h = cbrt(volume / wanted), then grown until the rounded-up dims fit.
        let mut h = crate::real::exp_f32(crate::real::ln_f32(volume / wanted as f32) * (1.0 / 3.0));
        if !(h > 0.0) {
            // The volume underflowed (a box of 1e-13 m): cells of the widest extent's size.
            h = widest / 64.0;
        }
        let mut dims = [1u32; 3];
        let mut tries = 0;
        while tries < 16 {
            // Counted in f32 (exact below 2^24, and only compared with 2^22 above).
            let mut cells = 1.0f32;
            for a in 0..3 {
                let d = num_traits::Float::ceil(extent[a] / h);
                dims[a] = if d < 1.0 {
                    1
                } else if d > 65_536.0 {
                    65_536
                } else {
                    d as u32
                };
                cells *= dims[a] as f32;
            }
            if cells <= GRID_MAX_CELLS as f32 {
                break;
            }
            h *= 1.26;
            tries += 1;
        }
        // Rounding of (p - origin) / h is relative to the coordinates' size.
        let slack = (magnitude + widest) * 4e-6;
        Self {
            origin: lo,
            h,
            dims,
            slack,
        }
    }

    /// The box from the bounds buffer's ordered keys (see [`GRID_BOUNDS_WORDS`]).
    pub fn from_bounds(bounds: [u32; 6], points: u32) -> Self {
        let hi = [
            from_ordered_key(bounds[0]),
            from_ordered_key(bounds[1]),
            from_ordered_key(bounds[2]),
        ];
        let lo = [
            -from_ordered_key(bounds[3]),
            -from_ordered_key(bounds[4]),
            -from_ordered_key(bounds[5]),
        ];
        Self::new(lo, hi, points)
    }

    /// The cell holding `p` (clamped into the grid; NaN goes to 0).
    #[inline]
    pub fn cell_of(&self, p: [f32; 3]) -> [u32; 3] {
        let mut c = [0u32; 3];
        for a in 0..3 {
            let t = (p[a] - self.origin[a]) / self.h;
            let last = (self.dims[a] - 1) as f32;
            c[a] = if t >= last {
                self.dims[a] - 1
            } else if t > 0.0 {
                t as u32
            } else {
                0
            };
        }
        c
    }

    /// Linear index of cell `c`.
    #[inline]
    pub fn linear(&self, c: [u32; 3]) -> u32 {
        (c[2] * self.dims[1] + c[1]) * self.dims[0] + c[0]
    }

    pub fn cells(&self) -> u32 {
        self.dims[0] * self.dims[1] * self.dims[2]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ordered_keys_sort_like_the_floats() {
        let v = [
            f32::NEG_INFINITY,
            -1e30,
            -2.5,
            -1e-30,
            -0.0,
            0.0,
            1e-30,
            3.0,
            1e30,
            f32::INFINITY,
        ];
        for w in v.windows(2) {
            assert!(
                ordered_key(w[0]) <= ordered_key(w[1]),
                "{} vs {}",
                w[0],
                w[1]
            );
            assert!(ordered_key(w[0]) > 0, "0 must stay below every key");
        }
        for x in v {
            assert_eq!(from_ordered_key(ordered_key(x)).to_bits(), x.to_bits());
        }
    }

    #[test]
    fn grids_fit_their_cap_and_cover_their_box() {
        let cases = [
            ([0.0f32; 3], [1.0f32; 3], 1_000_000u32),
            ([-0.3, 0.0, -0.3], [0.3, 0.6, 0.3], 20_000),
            ([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], 5_000),
            ([5.0, 5.0, 5.0], [5.0, 5.0, 5.0], 700),
            ([1e3, 1e3, 1e3], [1e3 + 1e-9, 1e3, 1e3], 10),
            ([0.0; 3], [1.0; 3], 0),
        ];
        for (lo, hi, n) in cases {
            let g = GridSpec::new(lo, hi, n);
            assert!(g.h > 0.0 && g.h.is_finite(), "{lo:?}..{hi:?}: h {}", g.h);
            assert!(
                g.cells() <= GRID_MAX_CELLS && g.cells() >= 1,
                "{lo:?}..{hi:?}: {} cells",
                g.cells()
            );
            for a in 0..3 {
                // The box's far corner lands in the last cell, not past it.
                assert!(
                    g.origin[a] + g.dims[a] as f32 * g.h >= hi[a] - g.slack,
                    "{lo:?}..{hi:?}: axis {a} not covered"
                );
            }
            let c = g.cell_of(hi);
            assert!(
                (0..3).all(|a| c[a] < g.dims[a]),
                "{lo:?}..{hi:?}: the far corner's cell {c:?} is outside {:?}",
                g.dims
            );
            assert_eq!(g.cell_of(lo), [0; 3]);
            assert_eq!(
                g.cell_of([1e30; 3]),
                [g.dims[0] - 1, g.dims[1] - 1, g.dims[2] - 1],
                "far points clamp to the last cell"
            );
            assert_eq!(g.cell_of([f32::NAN; 3]), [0; 3]);
        }
    }
}
