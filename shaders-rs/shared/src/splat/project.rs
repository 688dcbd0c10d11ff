//! Projection of one Gaussian (EWA splatting), forward and backward.
//!
//! Forward: camera-space mean `t = R mean + T`; world covariance `Σ = M Mᵀ`,
//! `M = R(q) diag(exp(log_scale))`; camera covariance `V = W Σ Wᵀ`; screen covariance
//! `cov = J V Jᵀ + dilation·I` with the perspective Jacobian `J` evaluated at the view
//! point clamped to `fov_clamp` half-fields of view; `conic = cov⁻¹`; opacity
//! `sigmoid(logit)` (times `sqrt(det(cov - dilation·I) / det(cov))` in antialiased
//! mode); colour from spherical harmonics of the view direction, `+ 0.5`, clamped at 0.
//! Culled (not visible): non-finite parameters (also flagged dropped), depth outside
//! `[near, far]`, a degenerate covariance, opacity below `alpha_min`, or an extent
//! entirely outside the image.
//!
//! Backward: the chain above in reverse, for a gradient on (x, y, conic, opacity,
//! colour, depth); the extent and the culling tests are not differentiated.

use crate::real::{all_finite, dot3, mat_mul, mat_t_vec, mat_vec, transpose, zero33, Real, M3, V3};
use crate::splat::layout::{FrameParams, MAX_SH_COEFFS};
use crate::splat::sh;

/// The camera and render settings in the float type of the computation.
#[derive(Clone, Copy, Debug)]
pub struct Camera<F> {
    pub rot: M3<F>,
    pub trans: V3<F>,
    pub fx: F,
    pub fy: F,
    pub cx: F,
    pub cy: F,
    pub near: F,
    pub far: F,
    pub width: u32,
    pub height: u32,
    pub tiles_x: u32,
    pub tiles_y: u32,
    pub tile_size: u32,
    pub sh_degree: u32,
    pub antialiased: bool,
    pub dilation: F,
    pub alpha_min: F,
    pub max_sigmas: F,
    pub fov_clamp: F,
}

impl<F: Real> Camera<F> {
    pub fn from_frame(p: &FrameParams) -> Self {
        let r = p.rot;
        let c = F::of;
        Self {
            rot: [
                [c(r[0]), c(r[1]), c(r[2])],
                [c(r[3]), c(r[4]), c(r[5])],
                [c(r[6]), c(r[7]), c(r[8])],
            ],
            trans: [c(p.trans[0]), c(p.trans[1]), c(p.trans[2])],
            fx: c(p.fx),
            fy: c(p.fy),
            cx: c(p.cx),
            cy: c(p.cy),
            near: c(p.near),
            far: c(p.far),
            width: p.width,
            height: p.height,
            tiles_x: p.tiles_x,
            tiles_y: p.tiles_y,
            tile_size: p.tile_size,
            sh_degree: p.sh_degree,
            antialiased: p.antialiased != 0,
            dilation: c(p.dilation),
            alpha_min: c(p.alpha_min),
            max_sigmas: c(p.max_sigmas),
            fov_clamp: c(p.fov_clamp),
        }
    }

    /// Camera centre in world space, `-Rᵀ T`.
    pub fn position(&self) -> V3<F> {
        let p = mat_t_vec(&self.rot, self.trans);
        [-p[0], -p[1], -p[2]]
    }
}

/// One Gaussian's parameters (SH coefficients `sh[k][channel]`, zero past the degree).
#[derive(Clone, Copy, Debug)]
pub struct Gaussian<F> {
    pub mean: V3<F>,
    pub log_scale: V3<F>,
    /// (w, x, y, z), not necessarily normalized.
    pub quat: [F; 4],
    pub opacity_logit: F,
    pub sh: [[F; 3]; MAX_SH_COEFFS],
}

impl<F: Real> Gaussian<F> {
    /// Every parameter finite (NaN fails).
    pub fn is_finite(&self, degree: u32) -> bool {
        let mut ok =
            all_finite(&self.mean) && all_finite(&self.log_scale) && all_finite(&self.quat);
        ok = ok && self.opacity_logit.is_finite();
        let n = crate::splat::layout::sh_coeffs(degree);
        let mut k = 0;
        while k < n {
            ok = ok && all_finite(&self.sh[k]);
            k += 1;
        }
        ok
    }
}

/// Result of projecting one Gaussian.
#[derive(Clone, Copy, Debug)]
pub struct Projection<F> {
    pub visible: bool,
    /// A parameter was not finite.
    pub dropped: bool,
    pub x: F,
    pub y: F,
    pub depth: F,
    pub conic: [F; 3],
    pub opacity: F,
    pub color: V3<F>,
    /// Extent in pixels along x and y.
    pub radius: [F; 2],
}

impl<F: Real> Projection<F> {
    fn culled(dropped: bool) -> Self {
        let z = F::zero();
        Self {
            visible: false,
            dropped,
            x: z,
            y: z,
            depth: z,
            conic: [z; 3],
            opacity: z,
            color: [z; 3],
            radius: [z; 2],
        }
    }
}

/// Gradient of a loss with respect to one projected splat.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SplatGrad<F> {
    pub x: F,
    pub y: F,
    pub conic: [F; 3],
    pub opacity: F,
    pub color: V3<F>,
    pub depth: F,
}

impl<F: Real> SplatGrad<F> {
    pub fn zero() -> Self {
        let z = F::zero();
        Self {
            x: z,
            y: z,
            conic: [z; 3],
            opacity: z,
            color: [z; 3],
            depth: z,
        }
    }

    /// The flat layout of the gradient buffers (see `SPLAT_GRAD_FLOATS`).
    pub fn to_array(&self) -> [F; 10] {
        [
            self.x,
            self.y,
            self.conic[0],
            self.conic[1],
            self.conic[2],
            self.opacity,
            self.color[0],
            self.color[1],
            self.color[2],
            self.depth,
        ]
    }

    pub fn from_array(a: &[F; 10]) -> Self {
        Self {
            x: a[0],
            y: a[1],
            conic: [a[2], a[3], a[4]],
            opacity: a[5],
            color: [a[6], a[7], a[8]],
            depth: a[9],
        }
    }

    /// The sum of two gradients (written out: no loop for llvmpipe's loop budget).
    #[inline]
    pub fn add(&self, o: &Self) -> Self {
        Self {
            x: self.x + o.x,
            y: self.y + o.y,
            conic: [
                self.conic[0] + o.conic[0],
                self.conic[1] + o.conic[1],
                self.conic[2] + o.conic[2],
            ],
            opacity: self.opacity + o.opacity,
            color: [
                self.color[0] + o.color[0],
                self.color[1] + o.color[1],
                self.color[2] + o.color[2],
            ],
            depth: self.depth + o.depth,
        }
    }
}

/// Gradient of a loss with respect to one Gaussian's parameters.
#[derive(Clone, Copy, Debug)]
pub struct GaussianGrad<F> {
    pub mean: V3<F>,
    pub log_scale: V3<F>,
    pub quat: [F; 4],
    pub opacity_logit: F,
    pub sh: [[F; 3]; MAX_SH_COEFFS],
}

impl<F: Real> GaussianGrad<F> {
    pub fn zero() -> Self {
        let z = F::zero();
        Self {
            mean: [z; 3],
            log_scale: [z; 3],
            quat: [z; 4],
            opacity_logit: z,
            sh: [[z; 3]; MAX_SH_COEFFS],
        }
    }
}

/// Rotation matrix of a unit quaternion (w, x, y, z).
pub fn quat_to_mat<F: Real>(q: [F; 4]) -> M3<F> {
    let (w, x, y, z) = (q[0], q[1], q[2], q[3]);
    let one = F::one();
    let two = F::of(2.0);
    [
        [
            one - two * (y * y + z * z),
            two * (x * y - w * z),
            two * (x * z + w * y),
        ],
        [
            two * (x * y + w * z),
            one - two * (x * x + z * z),
            two * (y * z - w * x),
        ],
        [
            two * (x * z - w * y),
            two * (y * z + w * x),
            one - two * (x * x + y * y),
        ],
    ]
}

/// Normalized quaternion and its norm; a zero (or subnormal) quaternion is treated as
/// the identity rotation, with norm 0 to mark that it carries no gradient.
pub fn normalize_quat<F: Real>(q: [F; 4]) -> ([F; 4], F) {
    let n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    if n2 > F::of(1e-24) {
        let n = n2.sqrt();
        ([q[0] / n, q[1] / n, q[2] / n, q[3] / n], n)
    } else {
        let z = F::zero();
        ([F::one(), z, z, z], z)
    }
}

#[inline]
pub fn sigmoid<F: Real>(x: F) -> F {
    F::one() / (F::one() + (-x).exp_k())
}

/// Everything the forward pass computes that the backward pass needs again.
struct Chain<F> {
    t: V3<F>,
    qn: [F; 4],
    qnorm: F,
    rq: M3<F>,
    scale: V3<F>,
    m: M3<F>,
    vc: M3<F>,
    /// Jacobian rows (2 x 3).
    j: [V3<F>; 2],
    /// View point clamped (u = tx/tz, v = ty/tz), and whether each was clamped.
    u: F,
    v: F,
    u_clamped: bool,
    v_clamped: bool,
    /// Screen covariance before dilation (a, b, c).
    cov: [F; 3],
}

/// Sum over k of the outer product terms of `a (3x3) * diag * ...`: `J V Jᵀ` for a 2x3 `J`.
fn jvjt<F: Real>(j: &[V3<F>; 2], v: &M3<F>) -> [F; 3] {
    let j0v = mat_t_vec(v, j[0]); // (Vᵀ j0) = V j0 for symmetric V
    let j1v = mat_t_vec(v, j[1]);
    [dot3(j0v, j[0]), dot3(j0v, j[1]), dot3(j1v, j[1])]
}

fn chain<F: Real>(g: &Gaussian<F>, cam: &Camera<F>) -> Chain<F> {
    let t0 = mat_vec(&cam.rot, g.mean);
    let t = [
        t0[0] + cam.trans[0],
        t0[1] + cam.trans[1],
        t0[2] + cam.trans[2],
    ];
    let (qn, qnorm) = normalize_quat(g.quat);
    let rq = quat_to_mat(qn);
    let scale = [
        g.log_scale[0].exp_k(),
        g.log_scale[1].exp_k(),
        g.log_scale[2].exp_k(),
    ];
    let mut m = zero33();
    crate::each_index!(3, i => {
        crate::each_index!(3, k => {
            m[i][k] = rq[i][k] * scale[k];
        });
    });
    let sigma = mat_mul(&m, &transpose(&m));
    let vc = mat_mul(&mat_mul(&cam.rot, &sigma), &transpose(&cam.rot));

    // The Jacobian at the view point clamped to the field of view (gsplat's limits).
    let half = F::of(0.5);
    let tan_x = half * F::of(cam.width as f32) / cam.fx;
    let tan_y = half * F::of(cam.height as f32) / cam.fy;
    let slack = cam.fov_clamp - F::one();
    let lim_x_pos = (F::of(cam.width as f32) - cam.cx) / cam.fx + slack * tan_x;
    let lim_x_neg = cam.cx / cam.fx + slack * tan_x;
    let lim_y_pos = (F::of(cam.height as f32) - cam.cy) / cam.fy + slack * tan_y;
    let lim_y_neg = cam.cy / cam.fy + slack * tan_y;
    let u_raw = t[0] / t[2];
    let v_raw = t[1] / t[2];
    let u_clamped = !(u_raw <= lim_x_pos && u_raw >= -lim_x_neg);
    let v_clamped = !(v_raw <= lim_y_pos && v_raw >= -lim_y_neg);
    let u = if u_clamped {
        if u_raw > F::zero() {
            lim_x_pos
        } else {
            -lim_x_neg
        }
    } else {
        u_raw
    };
    let v = if v_clamped {
        if v_raw > F::zero() {
            lim_y_pos
        } else {
            -lim_y_neg
        }
    } else {
        v_raw
    };
    let z = F::zero();
    let j = [
        [cam.fx / t[2], z, -cam.fx * u / t[2]],
        [z, cam.fy / t[2], -cam.fy * v / t[2]],
    ];
    let cov = jvjt(&j, &vc);
    Chain {
        t,
        qn,
        qnorm,
        rq,
        scale,
        m,
        vc,
        j,
        u,
        v,
        u_clamped,
        v_clamped,
        cov,
    }
}

/// Antialiasing compensation `sqrt(det(cov) / det(cov + dilation I))` (0 if degenerate).
fn compensation<F: Real>(cov: [F; 3], dilation: F) -> F {
    let det0 = cov[0] * cov[2] - cov[1] * cov[1];
    let det1 = (cov[0] + dilation) * (cov[2] + dilation) - cov[1] * cov[1];
    let r = det0 / det1;
    if r > F::zero() {
        r.sqrt()
    } else {
        F::zero()
    }
}

/// Colour from SH at the view direction of `mean`, `+0.5`, before clamping.
fn sh_color<F: Real>(g: &Gaussian<F>, cam: &Camera<F>) -> (V3<F>, V3<F>, F) {
    let p = cam.position();
    let d = [g.mean[0] - p[0], g.mean[1] - p[1], g.mean[2] - p[2]];
    let len = dot3(d, d).sqrt();
    let dir = if len > F::zero() {
        [d[0] / len, d[1] / len, d[2] / len]
    } else {
        [F::zero(), F::zero(), F::one()]
    };
    let b = sh::basis(cam.sh_degree, dir);
    let mut color = [F::of(0.5); 3];
    crate::each_index!(16, k => {
        color[0] += b[k] * g.sh[k][0];
        color[1] += b[k] * g.sh[k][1];
        color[2] += b[k] * g.sh[k][2];
    });
    (color, dir, len)
}

/// Projects one Gaussian.
pub fn project_fwd<F: Real>(g: &Gaussian<F>, cam: &Camera<F>) -> Projection<F> {
    if !g.is_finite(cam.sh_degree) {
        return Projection::culled(true);
    }
    let c = chain(g, cam);
    if !(c.t[2] >= cam.near && c.t[2] <= cam.far) {
        return Projection::culled(false);
    }
    let a = c.cov[0] + cam.dilation;
    let b = c.cov[1];
    let cc = c.cov[2] + cam.dilation;
    let det = a * cc - b * b;
    if !(det > F::zero()) {
        return Projection::culled(false);
    }
    let mut opacity = sigmoid(g.opacity_logit);
    if cam.antialiased {
        opacity *= compensation(c.cov, cam.dilation);
    }
    if !(opacity >= cam.alpha_min) {
        return Projection::culled(false);
    }
    let extent = F::of(2.0) * (opacity / cam.alpha_min).ln_k();
    let extent = extent.sqrt().min(cam.max_sigmas);
    let radius = [(extent * a.sqrt()).ceil(), (extent * cc.sqrt()).ceil()];
    let x = cam.fx * c.t[0] / c.t[2] + cam.cx;
    let y = cam.fy * c.t[1] / c.t[2] + cam.cy;
    let w = F::of(cam.width as f32);
    let h = F::of(cam.height as f32);
    let inside = radius[0] > F::zero()
        && radius[1] > F::zero()
        && x + radius[0] > F::zero()
        && x - radius[0] < w
        && y + radius[1] > F::zero()
        && y - radius[1] < h;
    if !inside {
        return Projection::culled(false);
    }
    let (mut color, _, _) = sh_color(g, cam);
    crate::each_index!(3, ch => {
        color[ch] = color[ch].max(F::zero());
    });
    Projection {
        visible: true,
        dropped: false,
        x,
        y,
        depth: c.t[2],
        conic: [cc / det, -b / det, a / det],
        opacity,
        color,
        radius,
    }
}

/// Tile rectangle `[x0, x1) x [y0, y1)` covered by a splat at (x, y) with the given
/// radii, clamped to the image's tiles of side `tile_size`. Clamping happens in
/// floating point before the conversion, so huge or infinite extents are safe.
pub fn tile_rect<F: Real>(
    x: F,
    y: F,
    radius: [F; 2],
    tile_size: u32,
    tiles_x: u32,
    tiles_y: u32,
) -> [u32; 4] {
    let ts = F::of(tile_size as f32);
    let tx = F::of(tiles_x as f32);
    let ty = F::of(tiles_y as f32);
    let clamp = |v: F, hi: F| -> u32 { v.max(F::zero()).min(hi).to_f32() as u32 };
    [
        clamp(((x - radius[0]) / ts).floor(), tx),
        clamp(((y - radius[1]) / ts).floor(), ty),
        clamp(((x + radius[0]) / ts).ceil(), tx),
        clamp(((y + radius[1]) / ts).ceil(), ty),
    ]
}

/// Backward of [`project_fwd`] for a visible Gaussian.
pub fn project_bwd<F: Real>(
    g: &Gaussian<F>,
    cam: &Camera<F>,
    up: &SplatGrad<F>,
) -> GaussianGrad<F> {
    let mut out = GaussianGrad::zero();
    let c = chain(g, cam);
    let two = F::of(2.0);
    let half = F::of(0.5);
    let a = c.cov[0] + cam.dilation;
    let b = c.cov[1];
    let cc = c.cov[2] + cam.dilation;
    let det = a * cc - b * b;
    let conic = [cc / det, -b / det, a / det];

    // Opacity: o = sigmoid(l) * comp.
    let sig = sigmoid(g.opacity_logit);
    let comp = if cam.antialiased {
        compensation(c.cov, cam.dilation)
    } else {
        F::one()
    };
    out.opacity_logit = up.opacity * comp * sig * (F::one() - sig);
    let g_comp = up.opacity * sig;

    // Conic = inverse of the dilated covariance: dL/dCov = -C G C (symmetric matrices,
    // the off-diagonal scalar gradient split over both entries).
    let (ca, cb, ccc) = (conic[0], conic[1], conic[2]);
    let (ga, gb, gc) = (up.conic[0], up.conic[1] * half, up.conic[2]);
    // G C
    let gc00 = ga * ca + gb * cb;
    let gc01 = ga * cb + gb * ccc;
    let gc10 = gb * ca + gc * cb;
    let gc11 = gb * cb + gc * ccc;
    // C (G C)
    let d00 = -(ca * gc00 + cb * gc10);
    let d01 = -(ca * gc01 + cb * gc11);
    let d11 = -(cb * gc01 + ccc * gc11);
    let mut g_cov = [d00, two * d01, d11];
    if cam.antialiased && comp > F::zero() {
        let (a0, b0, c0) = (c.cov[0], c.cov[1], c.cov[2]);
        let det0 = a0 * c0 - b0 * b0;
        let k = half * comp * g_comp;
        g_cov[0] += k * (c0 / det0 - cc / det);
        g_cov[2] += k * (a0 / det0 - a / det);
        g_cov[1] += k * (-two * b0 / det0 + two * b / det);
    }

    // cov = J V Jᵀ.
    let g2 = [[g_cov[0], g_cov[1] * half], [g_cov[1] * half, g_cov[2]]];
    // dL/dV = Jᵀ G2 J
    let mut g_vc = zero33();
    crate::each_index!(3, i => {
        crate::each_index!(3, k => {
            let mut s = F::zero();
            crate::each_index!(2, r => {
                crate::each_index!(2, q => {
                    s += c.j[r][i] * g2[r][q] * c.j[q][k];
                });
            });
            g_vc[i][k] = s;
        });
    });
    // dL/dJ = 2 G2 J V
    let jv = [mat_t_vec(&c.vc, c.j[0]), mat_t_vec(&c.vc, c.j[1])];
    let mut g_j = [[F::zero(); 3]; 2];
    crate::each_index!(2, r => {
        crate::each_index!(3, k => {
            g_j[r][k] = two * (g2[r][0] * jv[0][k] + g2[r][1] * jv[1][k]);
        });
    });

    // V = W Σ Wᵀ -> dL/dΣ = Wᵀ dL/dV W; Σ = M Mᵀ -> dL/dM = 2 dL/dΣ M.
    let g_sigma = mat_mul(&mat_mul(&transpose(&cam.rot), &g_vc), &cam.rot);
    let g_m = mat_mul(&g_sigma, &c.m);
    let mut g_rq = zero33();
    crate::each_index!(3, i => {
        crate::each_index!(3, k => {
            let gm = two * g_m[i][k];
            g_rq[i][k] = gm * c.scale[k];
            out.log_scale[k] += gm * c.rq[i][k] * c.scale[k];
        });
    });

    // R(q̂) -> q̂ -> q.
    if c.qnorm > F::zero() {
        let (w, x, y, z) = (c.qn[0], c.qn[1], c.qn[2], c.qn[3]);
        let gr = &g_rq;
        let gw = two
            * (-z * gr[0][1] + y * gr[0][2] + z * gr[1][0] - x * gr[1][2] - y * gr[2][0]
                + x * gr[2][1]);
        let gx = two
            * (y * gr[0][1] + z * gr[0][2] + y * gr[1][0] - two * x * gr[1][1] - w * gr[1][2]
                + z * gr[2][0]
                + w * gr[2][1]
                - two * x * gr[2][2]);
        let gy = two
            * (-two * y * gr[0][0] + x * gr[0][1] + w * gr[0][2] + x * gr[1][0] + z * gr[1][2]
                - w * gr[2][0]
                + z * gr[2][1]
                - two * y * gr[2][2]);
        let gz = two
            * (-two * z * gr[0][0] - w * gr[0][1] + x * gr[0][2] + w * gr[1][0]
                - two * z * gr[1][1]
                + y * gr[1][2]
                + x * gr[2][0]
                + y * gr[2][1]);
        let gq = [gw, gx, gy, gz];
        let proj = gq[0] * c.qn[0] + gq[1] * c.qn[1] + gq[2] * c.qn[2] + gq[3] * c.qn[3];
        crate::each_index!(4, k => {
            out.quat[k] = (gq[k] - c.qn[k] * proj) / c.qnorm;
        });
    }

    // Camera-space mean: through J, the 2D mean and the depth.
    let t = c.t;
    let tz = t[2];
    let tz2 = tz * tz;
    let mut g_t = [F::zero(); 3];
    g_t[2] += g_j[0][0] * (-cam.fx / tz2) + g_j[1][1] * (-cam.fy / tz2);
    // J02 = -fx u / tz with u = tx/tz unless clamped.
    g_t[2] += g_j[0][2] * (cam.fx * c.u / tz2);
    g_t[2] += g_j[1][2] * (cam.fy * c.v / tz2);
    if !c.u_clamped {
        g_t[0] += g_j[0][2] * (-cam.fx / tz2);
        g_t[2] += g_j[0][2] * (cam.fx * t[0] / (tz2 * tz));
    }
    if !c.v_clamped {
        g_t[1] += g_j[1][2] * (-cam.fy / tz2);
        g_t[2] += g_j[1][2] * (cam.fy * t[1] / (tz2 * tz));
    }
    g_t[0] += up.x * cam.fx / tz;
    g_t[1] += up.y * cam.fy / tz;
    g_t[2] -= (up.x * cam.fx * t[0] + up.y * cam.fy * t[1]) / tz2;
    g_t[2] += up.depth;
    out.mean = mat_t_vec(&cam.rot, g_t);

    // Colour: clamp, SH coefficients, and the view direction's path to the mean.
    let (raw, dir, len) = sh_color(g, cam);
    let mut g_col = up.color;
    crate::each_index!(3, ch => {
        if !(raw[ch] > F::zero()) {
            g_col[ch] = F::zero();
        }
    });
    let basis = sh::basis(cam.sh_degree, dir);
    let mut weights = [F::zero(); MAX_SH_COEFFS];
    crate::each_index!(16, k => {
        out.sh[k] = [basis[k] * g_col[0], basis[k] * g_col[1], basis[k] * g_col[2]];
        weights[k] = g.sh[k][0] * g_col[0] + g.sh[k][1] * g_col[1] + g.sh[k][2] * g_col[2];
    });
    if len > F::zero() {
        let g_dir = sh::basis_weighted_grad(cam.sh_degree, dir, &weights);
        let along = dot3(g_dir, dir);
        crate::each_index!(3, k => {
            out.mean[k] += (g_dir[k] - dir[k] * along) / len;
        });
    }
    out
}
