//! Per-Gaussian deformation of a triplane-driven layer: the decoders' outputs applied
//! to the canonical Gaussian, then linear blend skinning with the predicted weights
//! (HUGS's rule), forward and backward, generic over f32/f64.
//!
//! Canonical Gaussian: mean μ, unit quaternion q₀, log-scales s₀. Decoded: offset Δμ,
//! 6D rotation r (Zhou et al. 2019), log-scale delta Δs, skinning weights w (softmax
//! output, summing to 1). Joint transforms A_j = [R_j | t_j] (3x4, the frame's pose,
//! translation and scale folded in).
//!
//! - posed mean: `x + Σ_j w_j (A_j x̂ - x)` with `x = μ + Δμ` (= `Σ_j w_j A_j x̂`
//!   when the weights sum to 1; the same form as `skinning`).
//! - posed rotation: `M = (Σ_j w_j R_j) · R(q₀) · R6(r)`. A blend of rotations is not
//!   a rotation: `Σ w_j R_j` shrinks (and can shear) where joints disagree. We do not
//!   re-orthogonalise: `M` is turned into a quaternion by the branch of Shepperd's
//!   method for its largest diagonal term, written without the square root (each
//!   branch is linear in `M`, exactly proportional to the quaternion when `M` is a
//!   rotation), and the splatter normalises it. The shrink is thus dropped rather than
//!   applied to the scales, as HUGS does by converting the blended matrix.
//! - log-scales: `s₀ + Δs`.
//!
//! The gradient on the 24 transforms (for pose and translation refinement) is a sum
//! over the Gaussians: `∂L/∂A_j = Σ_i w_ij [g_i x̂_iᵀ + (G_B,i | 0)]`, with `g` the
//! posed mean's gradient, `x̂ = (μ + Δμ, 1)` and `G_B` the blended rotation's. The
//! backward writes each Gaussian's `TRANSFORM_TERMS` (g, x, G_B) and
//! [`transform_grad_add`] sums them per joint, in fixed chunks (no atomics).
//!
//! Optional pose-dependent offsets ([`pose_blend_offset`], HUGS's per-Gaussian
//! `posedirs`) are added to Δμ before the deformation, from the frame's
//! [`POSE_FEATURES`] pose features.

use crate::real::{mat_mul, transpose, Real, M3, V3};
/// Gaussians one invocation of the transforms' gradient sums (one chunk), as the
/// body skinning's: the partial sums are `ceil(n / CHUNK) × 24 × 12` floats.
pub use crate::skinning::TRANSFORM_GRAD_CHUNK;
use crate::skinning::{
    dot3, rotation_minus_identity_t, transform_delta, SKIN_JOINTS, TRANSFORM_FLOATS,
};
use crate::splat::project::quat_to_mat;

/// Below this norm a 6D column is divided by it instead (PyTorch's `F.normalize` eps).
pub const NORMALIZE_EPS: f32 = 1e-12;

/// Floats per Gaussian of the terms the transforms' gradient is summed from: the
/// posed mean's gradient (3), `x = μ + Δμ` (3) and the blended rotation's gradient
/// (9, row-major).
pub const TRANSFORM_TERMS: usize = 15;

/// Push constants of the `deform::*` kernels.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct DeformParams {
    pub count: u32,
    /// Added to every posed log-scale: `ln` of the frame's global body scale.
    pub log_scale_offset: f32,
    pub _pad: [u32; 2],
}

/// `a × b`.
#[inline]
pub fn cross<F: Real>(a: V3<F>, b: V3<F>) -> V3<F> {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline]
fn scale3<F: Real>(a: V3<F>, s: F) -> V3<F> {
    [a[0] * s, a[1] * s, a[2] * s]
}

#[inline]
fn sub3<F: Real>(a: V3<F>, b: V3<F>) -> V3<F> {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
fn add3<F: Real>(a: V3<F>, b: V3<F>) -> V3<F> {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// `v / max(|v|, eps)` and the divisor.
#[inline]
fn normalize<F: Real>(v: V3<F>) -> (V3<F>, F) {
    let n = dot3(v, v).sqrt().max(F::of(NORMALIZE_EPS));
    (scale3(v, F::one() / n), n)
}

/// Backward of [`normalize`]: gradient on `v` from the gradient `g` on `b = v / n`.
#[inline]
fn normalize_bwd<F: Real>(b: V3<F>, n: F, g: V3<F>) -> V3<F> {
    if n > F::of(NORMALIZE_EPS) {
        scale3(sub3(g, scale3(b, dot3(b, g))), F::one() / n)
    } else {
        scale3(g, F::one() / n)
    }
}

/// The 6D rotation representation to a matrix by Gram–Schmidt, rows `b1, b2, b3`
/// (PyTorch3D's `rotation_6d_to_matrix`): `b1 = a1/|a1|`, `b2` the normalised part of
/// `a2` orthogonal to `b1`, `b3 = b1 × b2`.
#[inline]
pub fn rot6d_to_matrix<F: Real>(r: [F; 6]) -> M3<F> {
    let (b1, _) = normalize([r[0], r[1], r[2]]);
    let a2 = [r[3], r[4], r[5]];
    let (b2, _) = normalize(sub3(a2, scale3(b1, dot3(b1, a2))));
    [b1, b2, cross(b1, b2)]
}

/// Gradient on the 6D vector from the gradient `g` on the matrix.
#[inline]
pub fn rot6d_to_matrix_bwd<F: Real>(r: [F; 6], g: &M3<F>) -> [F; 6] {
    let a1 = [r[0], r[1], r[2]];
    let a2 = [r[3], r[4], r[5]];
    let (b1, n1) = normalize(a1);
    let d = dot3(b1, a2);
    let u = sub3(a2, scale3(b1, d));
    let (b2, n2) = normalize(u);
    // b3 = b1 × b2.
    let gb1 = add3(g[0], cross(b2, g[2]));
    let gb2 = add3(g[1], cross(g[2], b1));
    let gu = normalize_bwd(b2, n2, gb2);
    // u = a2 - (b1·a2) b1.
    let b1_gu = dot3(b1, gu);
    let ga2 = sub3(gu, scale3(b1, b1_gu));
    let gb1 = sub3(gb1, add3(scale3(gu, d), scale3(a2, b1_gu)));
    let ga1 = normalize_bwd(b1, n1, gb1);
    [ga1[0], ga1[1], ga1[2], ga2[0], ga2[1], ga2[2]]
}

/// Which Shepperd branch [`matrix_to_quat`] takes: 0 trace, 1-3 the diagonal term.
#[inline]
fn quat_branch<F: Real>(m: &M3<F>) -> u32 {
    let tr = m[0][0] + m[1][1] + m[2][2];
    let mut best = tr;
    let mut branch = 0;
    let mut i = 0;
    while i < 3 {
        if m[i][i] > best {
            best = m[i][i];
            branch = i as u32 + 1;
        }
        i += 1;
    }
    branch
}

/// A quaternion (w, x, y, z), not normalised, proportional to the rotation `m` when
/// `m` is one (see the module header for other matrices).
#[inline]
pub fn matrix_to_quat<F: Real>(m: &M3<F>) -> [F; 4] {
    let one = F::one();
    match quat_branch(m) {
        0 => [
            one + m[0][0] + m[1][1] + m[2][2],
            m[2][1] - m[1][2],
            m[0][2] - m[2][0],
            m[1][0] - m[0][1],
        ],
        1 => [
            m[2][1] - m[1][2],
            one + m[0][0] - m[1][1] - m[2][2],
            m[0][1] + m[1][0],
            m[0][2] + m[2][0],
        ],
        2 => [
            m[0][2] - m[2][0],
            m[0][1] + m[1][0],
            one - m[0][0] + m[1][1] - m[2][2],
            m[1][2] + m[2][1],
        ],
        _ => [
            m[1][0] - m[0][1],
            m[0][2] + m[2][0],
            m[1][2] + m[2][1],
            one - m[0][0] - m[1][1] + m[2][2],
        ],
    }
}

/// Gradient on `m` from the gradient `g` on [`matrix_to_quat`]'s output (the branch is
/// held fixed: the map is piecewise linear).
#[inline]
pub fn matrix_to_quat_bwd<F: Real>(m: &M3<F>, g: [F; 4]) -> M3<F> {
    let z = F::zero();
    let mut o = [[z; 3]; 3];
    match quat_branch(m) {
        0 => {
            o[0][0] = g[0];
            o[1][1] = g[0];
            o[2][2] = g[0];
            o[2][1] = g[1];
            o[1][2] = -g[1];
            o[0][2] = g[2];
            o[2][0] = -g[2];
            o[1][0] = g[3];
            o[0][1] = -g[3];
        }
        1 => {
            o[2][1] = g[0];
            o[1][2] = -g[0];
            o[0][0] = g[1];
            o[1][1] = -g[1];
            o[2][2] = -g[1];
            o[0][1] = g[2];
            o[1][0] = g[2];
            o[0][2] = g[3];
            o[2][0] = g[3];
        }
        2 => {
            o[0][2] = g[0];
            o[2][0] = -g[0];
            o[0][1] = g[1];
            o[1][0] = g[1];
            o[0][0] = -g[2];
            o[1][1] = g[2];
            o[2][2] = -g[2];
            o[1][2] = g[3];
            o[2][1] = g[3];
        }
        _ => {
            o[1][0] = g[0];
            o[0][1] = -g[0];
            o[0][2] = g[1];
            o[2][0] = g[1];
            o[1][2] = g[2];
            o[2][1] = g[2];
            o[0][0] = -g[3];
            o[1][1] = -g[3];
            o[2][2] = g[3];
        }
    }
    o
}

/// One Gaussian's inputs.
#[derive(Clone, Copy, Debug)]
pub struct DeformInput<F> {
    pub mean: V3<F>,
    /// Canonical rotation, unit quaternion (w, x, y, z).
    pub quat: [F; 4],
    pub log_scale: V3<F>,
    pub offset: V3<F>,
    pub rot6d: [F; 6],
    pub log_scale_delta: V3<F>,
    pub weights: [F; SKIN_JOINTS],
}

/// One Gaussian's posed outputs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DeformOutput<F> {
    pub mean: V3<F>,
    /// Not normalised (the splatter normalises).
    pub quat: [F; 4],
    pub log_scale: V3<F>,
}

/// Gradients on the inputs that are learned or decoded (the canonical rotation and
/// the transforms are not differentiated here).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DeformGrad<F> {
    pub mean: V3<F>,
    pub offset: V3<F>,
    pub rot6d: [F; 6],
    pub log_scale_delta: V3<F>,
    pub weights: [F; SKIN_JOINTS],
    /// The terms the transforms' gradient is summed from ([`TRANSFORM_TERMS`]).
    pub transform_terms: [F; TRANSFORM_TERMS],
}

/// Adds one Gaussian's share of `∂L/∂A_j` (3x4 row-major) for its weight `w` on
/// joint `j`, from its [`TRANSFORM_TERMS`] (the posed mean is `x + Σ w_j (A_j x̂ - x)`
/// and the blended rotation `Σ w_j R_j`).
#[inline]
pub fn transform_grad_add<F: Real>(
    terms: &[F; TRANSFORM_TERMS],
    w: F,
    out: &mut [F; TRANSFORM_FLOATS],
) {
    crate::each_index!(3, r => {
        let g = terms[r];
        crate::each_index!(3, c => {
            out[4 * r + c] += w * (g * terms[3 + c] + terms[6 + 3 * r + c]);
        });
        out[4 * r + 3] += w * g;
    });
}

/// Transform `j` of 24 packed 3x4 transforms.
#[inline]
pub fn transform<F: Real>(transforms: &[F], j: usize) -> [F; TRANSFORM_FLOATS] {
    let b = j * TRANSFORM_FLOATS;
    let mut a = [F::zero(); TRANSFORM_FLOATS];
    let mut k = 0;
    while k < TRANSFORM_FLOATS {
        a[k] = transforms[b + k];
        k += 1;
    }
    a
}

#[inline]
fn rotation_of<F: Real>(a: &[F; TRANSFORM_FLOATS]) -> M3<F> {
    [[a[0], a[1], a[2]], [a[4], a[5], a[6]], [a[8], a[9], a[10]]]
}

/// `Σ_j w_j R_j`.
#[inline]
fn blended_rotation<F: Real>(transforms: &[F], w: &[F; SKIN_JOINTS]) -> M3<F> {
    let z = F::zero();
    let mut b = [[z; 3]; 3];
    let mut j = 0;
    while j < SKIN_JOINTS {
        if w[j] != z {
            let r = rotation_of(&transform(transforms, j));
            let mut i = 0;
            while i < 9 {
                b[i / 3][i % 3] += w[j] * r[i / 3][i % 3];
                i += 1;
            }
        }
        j += 1;
    }
    b
}

/// Forward: the posed Gaussian.
#[inline]
pub fn deform_fwd<F: Real>(g: &DeformInput<F>, transforms: &[F]) -> DeformOutput<F> {
    let x = add3(g.mean, g.offset);
    let mut mean = x;
    let mut j = 0;
    while j < SKIN_JOINTS {
        if g.weights[j] != F::zero() {
            let d = transform_delta(&transform(transforms, j), x);
            mean = add3(mean, scale3(d, g.weights[j]));
        }
        j += 1;
    }
    let canonical = mat_mul(&quat_to_mat(g.quat), &rot6d_to_matrix(g.rot6d));
    let m = mat_mul(&blended_rotation(transforms, &g.weights), &canonical);
    DeformOutput {
        mean,
        quat: matrix_to_quat(&m),
        log_scale: add3(g.log_scale, g.log_scale_delta),
    }
}

/// Backward: gradients from those on the posed mean, quaternion and log-scales.
#[inline]
pub fn deform_bwd<F: Real>(
    g: &DeformInput<F>,
    transforms: &[F],
    up: &DeformOutput<F>,
) -> DeformGrad<F> {
    let z = F::zero();
    let x = add3(g.mean, g.offset);
    let rq = quat_to_mat(g.quat);
    let r6 = rot6d_to_matrix(g.rot6d);
    let canonical = mat_mul(&rq, &r6);
    let b = blended_rotation(transforms, &g.weights);
    let m = mat_mul(&b, &canonical);
    let gm = matrix_to_quat_bwd(&m, up.quat);
    // M = B C: dB = dM Cᵀ, dC = Bᵀ dM; C = Rq R6: dR6 = Rqᵀ dC.
    let gb = mat_mul(&gm, &transpose(&canonical));
    let gc = mat_mul(&transpose(&b), &gm);
    let g6 = mat_mul(&transpose(&rq), &gc);
    let mut weights = [z; SKIN_JOINTS];
    let mut gx = up.mean;
    let mut j = 0;
    while j < SKIN_JOINTS {
        let a = transform(transforms, j);
        let r = rotation_of(&a);
        let mut gw = dot3(up.mean, transform_delta(&a, x));
        let mut i = 0;
        while i < 9 {
            gw += gb[i / 3][i % 3] * r[i / 3][i % 3];
            i += 1;
        }
        weights[j] = gw;
        gx = add3(
            gx,
            scale3(rotation_minus_identity_t(&a, up.mean), g.weights[j]),
        );
        j += 1;
    }
    let transform_terms = [
        up.mean[0], up.mean[1], up.mean[2], x[0], x[1], x[2], gb[0][0], gb[0][1], gb[0][2],
        gb[1][0], gb[1][1], gb[1][2], gb[2][0], gb[2][1], gb[2][2],
    ];
    DeformGrad {
        mean: gx,
        offset: gx,
        rot6d: rot6d_to_matrix_bwd(g.rot6d, &g6),
        log_scale_delta: up.log_scale,
        weights,
        transform_terms,
    }
}

/// Pose features of the pose-dependent offsets: `R_j − I` of joints 1-23, each 3x3
/// row-major (SMPL's `pose_feature`, 23 × 9).
pub const POSE_FEATURES: usize = 207;
/// Floats of one Gaussian's pose-blend basis: 207 × 3, feature-major (`B[3k + a]`).
pub const POSE_BLEND_FLOATS: usize = 3 * POSE_FEATURES;

/// Push constants of `deform::pose_blend_fwd` (`count` Gaussians) and
/// `deform::pose_blend_bwd` (`count` Gaussians, one invocation per basis float).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(not(target_arch = "spirv"), derive(bytemuck::Pod, bytemuck::Zeroable))]
pub struct PoseBlendParams {
    pub count: u32,
    pub _pad: [u32; 3],
}

/// The pose-dependent offset of Gaussian `i` (HUGS's per-Gaussian `posedirs`, as
/// SMPL's pose blend shapes): `Σ_k B_i[k] p_k`, a 3-vector per pose feature `p_k`.
pub fn pose_blend_offset<F: Real>(basis: &[F], i: usize, features: &[F]) -> [F; 3] {
    let mut out = [F::zero(); 3];
    let base = i * POSE_BLEND_FLOATS;
    let mut k = 0;
    while k < POSE_FEATURES {
        let p = features[k];
        out[0] += basis[base + 3 * k] * p;
        out[1] += basis[base + 3 * k + 1] * p;
        out[2] += basis[base + 3 * k + 2] * p;
        k += 1;
    }
    out
}

/// The gradient on basis float `j` of all Gaussians' (`j = i · 621 + 3k + a`) from the
/// offsets' gradient: `∂L/∂B_i[k][a] = p_k · ∂L/∂o_i[a]` (the offset is linear in it).
pub fn pose_blend_basis_grad<F: Real>(j: usize, features: &[F], grad_offsets: &[F]) -> F {
    let i = j / POSE_BLEND_FLOATS;
    let r = j % POSE_BLEND_FLOATS;
    features[r / 3] * grad_offsets[3 * i + r % 3]
}
