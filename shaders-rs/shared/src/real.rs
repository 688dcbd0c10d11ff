//! The float type kernels are generic over: `f32` on the GPU and in CPU references,
//! `f64` in the gradient checks. Transcendentals come from `num_traits::Float` with
//! its `libm` backend, which rust-gpu lowers to GLSL.std.450 instructions.

pub use num_traits::Float;

/// A float the shared math runs on.
pub trait Real:
    Float + core::ops::AddAssign + core::ops::SubAssign + core::ops::MulAssign + core::ops::DivAssign + Default
{
    /// Converts an `f32` constant or input.
    fn of(v: f32) -> Self;
    /// Converts back (rounding for `f64`).
    fn to_f32(self) -> f32;
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
    let mut i = 0;
    while i < 3 {
        let mut j = 0;
        while j < 3 {
            out[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
            j += 1;
        }
        i += 1;
    }
    out
}

pub fn transpose<F: Real>(a: &M3<F>) -> M3<F> {
    [[a[0][0], a[1][0], a[2][0]], [a[0][1], a[1][1], a[2][1]], [a[0][2], a[1][2], a[2][2]]]
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
