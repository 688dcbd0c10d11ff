//! The float type kernels are generic over: `f32` on the GPU and in CPU references,
//! `f64` in the gradient checks. Transcendentals come from `num_traits::Float` with
//! its `libm` backend, which rust-gpu lowers to GLSL.std.450 instructions, except the
//! splatting math's `exp` and `ln` in `f32` ([`exp_f32`], [`ln_f32`]): written out so
//! that GPU and host return the same bits.

pub use num_traits::Float;

/// A float the shared math runs on.
pub trait Real:
    Float
    + core::ops::AddAssign
    + core::ops::SubAssign
    + core::ops::MulAssign
    + core::ops::DivAssign
    + Default
{
    /// Converts an `f32` constant or input.
    fn of(v: f32) -> Self;
    /// Converts back (rounding for `f64`).
    fn to_f32(self) -> f32;
    /// `e^x` as the splatting math computes it: for `f32` the deterministic
    /// [`exp_f32`], so GPU and CPU take identical threshold decisions; for `f64` the
    /// library function (the gradient checks need the true derivative).
    fn exp_k(self) -> Self;
    /// `ln x` as the splatting math computes it (see [`exp_k`](Real::exp_k)).
    fn ln_k(self) -> Self;
}

impl Real for f32 {
    #[inline]
    fn of(v: f32) -> Self {
        v
    }
    #[inline]
    fn to_f32(self) -> f32 {
        self
    }
    #[inline]
    fn exp_k(self) -> Self {
        exp_f32(self)
    }
    #[inline]
    fn ln_k(self) -> Self {
        ln_f32(self)
    }
}

impl Real for f64 {
    #[inline]
    fn of(v: f32) -> Self {
        v as f64
    }
    #[inline]
    fn to_f32(self) -> f32 {
        self as f32
    }
    #[inline]
    fn exp_k(self) -> Self {
        self.exp()
    }
    #[inline]
    fn ln_k(self) -> Self {
        self.ln()
    }
}

/// `e^x` from adds, multiplies, `floor` and bit operations only, so that every IEEE
/// implementation (the GPU driver's and the host's) returns the same bits; GPU
/// drivers' own `exp` is an approximation that differs from the host's in the last
/// bits, which would flip `alpha >= alpha_min` decisions between the two. Relative
/// error below 2e-7 on [-87, 88]; 0 below, +inf above; NaN stays NaN.
///
/// ```
/// let x = 1.2345f32;
/// assert!((drape_shared::real::exp_f32(x) - x.exp()).abs() <= 2e-7 * x.exp());
/// assert_eq!(drape_shared::real::exp_f32(-200.0), 0.0);
/// ```
pub fn exp_f32(x: f32) -> f32 {
    if x.is_nan() {
        return x;
    }
    if x < -87.0 {
        return 0.0;
    }
    if x > 88.5 {
        return f32::INFINITY;
    }
    const LOG2E: f32 = core::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    let n = num_traits::Float::floor(x * LOG2E + 0.5);
    let r = (x - n * LN2_HI) - n * LN2_LO;
    // Taylor series of e^r on |r| <= 0.35 to degree 7 (error < 1e-8 relative).
    let p = 1.0
        + r * (1.0
            + r * (0.5
                + r * (1.0 / 6.0
                    + r * (1.0 / 24.0
                        + r * (1.0 / 120.0 + r * (1.0 / 720.0 + r * (1.0 / 5040.0)))))));
    // 2^n by building the exponent; n in [-126, 128) after the range checks, split in
    // two factors so that neither over- nor underflows.
    let ni = n as i32;
    let half = ni / 2;
    let a = f32::from_bits(((half + 127) as u32) << 23);
    let b = f32::from_bits(((ni - half + 127) as u32) << 23);
    p * a * b
}

/// `ln x` from adds, multiplies and bit operations only (see [`exp_f32`]). Relative
/// error below 2e-7 for normal positive `x`; `-inf` at 0, NaN below 0 or for NaN,
/// `+inf` at `+inf`; subnormals are treated as 0.
///
/// ```
/// let x = 123.456f32;
/// assert!((drape_shared::real::ln_f32(x) - x.ln()).abs() <= 2e-7 * x.ln().abs());
/// ```
pub fn ln_f32(x: f32) -> f32 {
    if !(x >= 0.0) {
        return f32::NAN;
    }
    if x == f32::INFINITY {
        return x;
    }
    let bits = x.to_bits();
    let exponent = ((bits >> 23) & 0xff) as i32;
    if exponent == 0 {
        return f32::NEG_INFINITY;
    }
    // x = m * 2^e with m in [sqrt(1/2), sqrt(2)).
    let mut e = exponent - 127;
    let mut m = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000);
    if m > core::f32::consts::SQRT_2 {
        m *= 0.5;
        e += 1;
    }
    // ln m = 2 atanh(s), s = (m - 1) / (m + 1), |s| < 0.172.
    let s = (m - 1.0) / (m + 1.0);
    let s2 = s * s;
    let series = 1.0 + s2 * (1.0 / 3.0 + s2 * (1.0 / 5.0 + s2 * (1.0 / 7.0 + s2 * (1.0 / 9.0))));
    const LN2: f32 = core::f32::consts::LN_2;
    2.0 * s * series + e as f32 * LN2
}

/// 3-vector.
pub type V3<F> = [F; 3];
/// 3x3 matrix, row-major: `m[row][col]`.
pub type M3<F> = [[F; 3]; 3];

#[inline]
pub fn zero3<F: Real>() -> V3<F> {
    [F::zero(); 3]
}

#[inline]
pub fn zero33<F: Real>() -> M3<F> {
    [[F::zero(); 3]; 3]
}

#[inline]
pub fn dot3<F: Real>(a: V3<F>, b: V3<F>) -> F {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `m * v`.
#[inline]
pub fn mat_vec<F: Real>(m: &M3<F>, v: V3<F>) -> V3<F> {
    [dot3(m[0], v), dot3(m[1], v), dot3(m[2], v)]
}

/// `m^T * v`.
#[inline]
pub fn mat_t_vec<F: Real>(m: &M3<F>, v: V3<F>) -> V3<F> {
    [
        m[0][0] * v[0] + m[1][0] * v[1] + m[2][0] * v[2],
        m[0][1] * v[0] + m[1][1] * v[1] + m[2][1] * v[2],
        m[0][2] * v[0] + m[1][2] * v[1] + m[2][2] * v[2],
    ]
}

/// `a * b`.
pub fn mat_mul<F: Real>(a: &M3<F>, b: &M3<F>) -> M3<F> {
    let mut out = zero33();
    crate::each_index!(3, i => {
        crate::each_index!(3, j => {
            out[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        });
    });
    out
}

pub fn transpose<F: Real>(a: &M3<F>) -> M3<F> {
    [
        [a[0][0], a[1][0], a[2][0]],
        [a[0][1], a[1][1], a[2][1]],
        [a[0][2], a[1][2], a[2][2]],
    ]
}

/// True when every value is finite (NaN fails it).
#[inline]
pub fn all_finite<F: Real, const N: usize>(values: &[F; N]) -> bool {
    let mut i = 0;
    while i < N {
        if !values[i].is_finite() {
            return false;
        }
        i += 1;
    }
    true
}
