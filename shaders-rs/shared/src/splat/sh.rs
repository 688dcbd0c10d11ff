//! Real spherical harmonics up to degree 3 (the 3DGS basis and sign convention) and
//! their gradients with respect to the (unit) direction.

use crate::real::{Real, V3};
use crate::splat::layout::MAX_SH_COEFFS;

/// The degree-0 SH basis constant, 1 / (2 √π).
pub const C0: f32 = 0.282_094_8;
const C1: f32 = 0.488_602_5;
const C2: [f32; 5] = [
    1.092_548_4,
    -1.092_548_4,
    0.315_391_57,
    -1.092_548_4,
    0.546_274_2,
];
const C3: [f32; 7] = [
    -0.590_043_6,
    2.890_611_4,
    -0.457_045_8,
    0.373_176_34,
    -0.457_045_8,
    1.445_305_7,
    -0.590_043_6,
];

/// The basis functions at unit direction `d`; entries past the degree are 0.
pub fn basis<F: Real>(degree: u32, d: V3<F>) -> [F; MAX_SH_COEFFS] {
    let c = F::of;
    let (x, y, z) = (d[0], d[1], d[2]);
    let mut b = [F::zero(); MAX_SH_COEFFS];
    b[0] = c(C0);
    if degree >= 1 {
        b[1] = -c(C1) * y;
        b[2] = c(C1) * z;
        b[3] = -c(C1) * x;
    }
    if degree >= 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        b[4] = c(C2[0]) * x * y;
        b[5] = c(C2[1]) * y * z;
        b[6] = c(C2[2]) * (c(2.0) * zz - xx - yy);
        b[7] = c(C2[3]) * x * z;
        b[8] = c(C2[4]) * (xx - yy);
        if degree >= 3 {
            b[9] = c(C3[0]) * y * (c(3.0) * xx - yy);
            b[10] = c(C3[1]) * x * y * z;
            b[11] = c(C3[2]) * y * (c(4.0) * zz - xx - yy);
            b[12] = c(C3[3]) * z * (c(2.0) * zz - c(3.0) * xx - c(3.0) * yy);
            b[13] = c(C3[4]) * x * (c(4.0) * zz - xx - yy);
            b[14] = c(C3[5]) * z * (xx - yy);
            b[15] = c(C3[6]) * x * (xx - c(3.0) * yy);
        }
    }
    b
}

/// `sum_k w[k] * grad(basis_k)(d)`: the gradient, with respect to the direction, of a
/// weighted sum of basis functions.
pub fn basis_weighted_grad<F: Real>(degree: u32, d: V3<F>, w: &[F; MAX_SH_COEFFS]) -> V3<F> {
    let c = F::of;
    let (x, y, z) = (d[0], d[1], d[2]);
    let mut g = [F::zero(); 3];
    if degree >= 1 {
        g[1] -= c(C1) * w[1];
        g[2] += c(C1) * w[2];
        g[0] -= c(C1) * w[3];
    }
    if degree >= 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        let t = c(C2[0]) * w[4];
        g[0] += t * y;
        g[1] += t * x;
        let t = c(C2[1]) * w[5];
        g[1] += t * z;
        g[2] += t * y;
        let t = c(C2[2]) * w[6];
        g[0] -= c(2.0) * t * x;
        g[1] -= c(2.0) * t * y;
        g[2] += c(4.0) * t * z;
        let t = c(C2[3]) * w[7];
        g[0] += t * z;
        g[2] += t * x;
        let t = c(C2[4]) * w[8];
        g[0] += c(2.0) * t * x;
        g[1] -= c(2.0) * t * y;
        if degree >= 3 {
            let t = c(C3[0]) * w[9];
            g[0] += t * c(6.0) * x * y;
            g[1] += t * (c(3.0) * xx - c(3.0) * yy);
            let t = c(C3[1]) * w[10];
            g[0] += t * y * z;
            g[1] += t * x * z;
            g[2] += t * x * y;
            let t = c(C3[2]) * w[11];
            g[0] -= t * c(2.0) * x * y;
            g[1] += t * (c(4.0) * zz - xx - c(3.0) * yy);
            g[2] += t * c(8.0) * y * z;
            let t = c(C3[3]) * w[12];
            g[0] -= t * c(6.0) * x * z;
            g[1] -= t * c(6.0) * y * z;
            g[2] += t * (c(6.0) * zz - c(3.0) * xx - c(3.0) * yy);
            let t = c(C3[4]) * w[13];
            g[0] += t * (c(4.0) * zz - c(3.0) * xx - yy);
            g[1] -= t * c(2.0) * x * y;
            g[2] += t * c(8.0) * x * z;
            let t = c(C3[5]) * w[14];
            g[0] += t * c(2.0) * x * z;
            g[1] -= t * c(2.0) * y * z;
            g[2] += t * (xx - yy);
            let t = c(C3[6]) * w[15];
            g[0] += t * (c(3.0) * xx - c(3.0) * yy);
            g[1] -= t * c(6.0) * x * y;
        }
    }
    g
}
