//! The dense f64 linear algebra the Fréchet distance needs, on n × n row-major
//! matrices: a symmetric eigen-solver (cyclic Jacobi), and the products, transposes and
//! symmetrisation around it, with a matrix rebuilt from its eigendecomposition (a
//! positive semidefinite matrix's square root from its eigenvalues' roots).

use ndarray::linalg::general_mat_mul;
use ndarray::{ArrayView2, ArrayViewMut2};

/// `m` with each off-diagonal pair replaced by its mean: exactly symmetric, as the
/// Jacobi rotations assume, where roundoff left a product slightly asymmetric.
pub(super) fn symmetrised(m: &[f64], n: usize) -> Vec<f64> {
    let mut s = m.to_vec();
    for i in 0..n {
        for j in 0..i {
            let v = 0.5 * (m[i * n + j] + m[j * n + i]);
            s[i * n + j] = v;
            s[j * n + i] = v;
        }
    }
    s
}

/// The transpose of an n × n matrix.
fn transposed(m: &[f64], n: usize) -> Vec<f64> {
    (0..n * n).map(|k| m[(k % n) * n + k / n]).collect()
}

/// The product of two n × n matrices.
pub(super) fn matmul(a: &[f64], b: &[f64], n: usize) -> Vec<f64> {
    let mut c = vec![0.0f64; n * n];
    let av = ArrayView2::from_shape((n, n), a).expect("n x n by construction");
    let bv = ArrayView2::from_shape((n, n), b).expect("n x n by construction");
    general_mat_mul(
        1.0,
        &av,
        &bv,
        0.0,
        &mut ArrayViewMut2::from_shape((n, n), &mut c).expect("n x n by construction"),
    );
    c
}

/// `V diag(d) Vᵀ` for the eigenvectors `V` (columns of an n × n row-major matrix, as
/// [`symmetric_eigen`] returns them): with `d` the square roots of a positive
/// semidefinite matrix's eigenvalues, its square root.
pub(super) fn from_eigen(vectors: &[f64], d: &[f64], n: usize) -> Vec<f64> {
    let mut scaled = vectors.to_vec();
    for row in scaled.chunks_exact_mut(n) {
        for (v, r) in row.iter_mut().zip(d) {
            *v *= r;
        }
    }
    matmul(&scaled, &transposed(vectors, n), n)
}

/// Eigenvalues (and, with `vectors`, eigenvectors as the columns of an n × n row-major
/// matrix; otherwise an empty Vec) of a symmetric n × n row-major matrix, by cyclic
/// Jacobi rotations (Golub & Van Loan, Algorithm 8.5.3) until the off-diagonal norm is
/// below machine epsilon times the whole norm. Accurate to roundoff relative to the
/// largest eigenvalue; each sweep costs about 4 n³ flops (6 n³ with vectors, and 6-10
/// sweeps), and the rotations walk columns with no blocking, so 2048 costs at least 64
/// times 512 (docs/performance.md, "Host-side timings", has the times). Fine for the
/// tests and for FID's images × images problem; a blocked
/// tridiagonal solver (LAPACK's dsyevd, nalgebra) is the way to 2048 × 2048.
pub fn symmetric_eigen(mut a: Vec<f64>, n: usize, vectors: bool) -> (Vec<f64>, Vec<f64>) {
    assert_eq!(a.len(), n * n, "symmetric_eigen: not an n x n matrix");
    let mut v = Vec::new();
    if vectors {
        v = vec![0.0f64; n * n];
        for i in 0..n {
            v[i * n + i] = 1.0;
        }
    }
    for _sweep in 0..100 {
        let total: f64 = a.iter().map(|x| x * x).sum();
        let off: f64 = (0..n)
            .flat_map(|p| (p + 1..n).map(move |q| (p, q)))
            .map(|(p, q)| 2.0 * a[p * n + q].powi(2))
            .sum();
        // Anything but "greater" stops, so a NaN stops rather than loops.
        let threshold = (f64::EPSILON * f64::EPSILON) * total;
        if off.partial_cmp(&threshold) != Some(std::cmp::Ordering::Greater) {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = a[p * n + q];
                if apq == 0.0 {
                    continue;
                }
                let tau = (a[q * n + q] - a[p * n + p]) / (2.0 * apq);
                let t = if tau >= 0.0 {
                    1.0 / (tau + (1.0 + tau * tau).sqrt())
                } else {
                    -1.0 / (-tau + (1.0 + tau * tau).sqrt())
                };
                let c = 1.0 / (1.0 + t * t).sqrt();
                let s = t * c;
                // A ← Jᵀ A J: columns p, q, then rows p, q.
                for k in 0..n {
                    let (akp, akq) = (a[k * n + p], a[k * n + q]);
                    a[k * n + p] = c * akp - s * akq;
                    a[k * n + q] = s * akp + c * akq;
                }
                for k in 0..n {
                    let (apk, aqk) = (a[p * n + k], a[q * n + k]);
                    a[p * n + k] = c * apk - s * aqk;
                    a[q * n + k] = s * apk + c * aqk;
                }
                a[p * n + q] = 0.0;
                a[q * n + p] = 0.0;
                if vectors {
                    for k in 0..n {
                        let (vkp, vkq) = (v[k * n + p], v[k * n + q]);
                        v[k * n + p] = c * vkp - s * vkq;
                        v[k * n + q] = s * vkp + c * vkq;
                    }
                }
            }
        }
    }
    ((0..n).map(|i| a[i * n + i]).collect(), v)
}
