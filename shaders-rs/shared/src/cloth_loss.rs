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
//! staged in workgroup memory): exact, with no build step and no tuning, and the
//! training sizes (10⁴ × 10⁴ per frame) cost less than the splatting; a uniform grid
//! would win for 10⁶-point sets. Ties go to the lower index.
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
