//! The Fréchet distance between two sets of FID features, or between the Gaussians of
//! their statistics.
//!
//! `|μ1 − μ2|² + tr(Σ1 + Σ2 − 2 (Σ1 Σ2)^½)` with unbiased covariances (as `numpy.cov`),
//! in f64. `tr (Σ1 Σ2)^½` is the sum of the square roots of the eigenvalues of the
//! symmetric positive semidefinite `Σ1^½ Σ2 Σ1^½` (same spectrum as `Σ1 Σ2`), not a
//! general matrix square root as scipy's `sqrtm`: no complex parts to drop and no `eps`
//! to add when the product is singular (which it always is with fewer images than 2048
//! features). From features with fewer images than dimensions the same spectrum comes
//! from an images × images matrix (see [`frechet_distance_of_features`]). Eigenvalues
//! that roundoff makes slightly negative (above −1e-9 of the largest) are taken as 0;
//! below that the input is not a covariance and is refused. Non-finite features and
//! statistics are refused.

use ndarray::linalg::general_mat_mul;
use ndarray::{ArrayView2, ArrayViewMut2};

use crate::metrics::fid::linalg::{from_eigen, matmul, symmetric_eigen, symmetrised};
use crate::TrainerError;

/// Eigenvalues below `-NEGATIVE_TOLERANCE * largest` mean the matrix is not PSD.
const NEGATIVE_TOLERANCE: f64 = 1e-9;

/// Mean and unbiased covariance (divided by n − 1, as `numpy.cov(rowvar=False)`) of
/// feature vectors, in f64; `cov` is dim × dim, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Statistics {
    pub dim: usize,
    pub mean: Vec<f64>,
    pub cov: Vec<f64>,
}

impl Statistics {
    /// The statistics of at least two feature vectors of one length.
    pub fn of(features: &[Vec<f32>]) -> crate::Result<Self> {
        let (dim, centred) = centred_rows(features)?;
        let n = features.len();
        let mean = mean_of(features, dim);
        // Σ = Aᵀ A with A the centred rows scaled by 1/√(n − 1).
        let a = ArrayView2::from_shape((n, dim), &centred).expect("n x dim by construction");
        let mut cov = vec![0.0f64; dim * dim];
        general_mat_mul(
            1.0,
            &a.t(),
            &a,
            0.0,
            &mut ArrayViewMut2::from_shape((dim, dim), &mut cov)
                .expect("dim x dim by construction"),
        );
        Ok(Self { dim, mean, cov })
    }
}

fn mean_of(features: &[Vec<f32>], dim: usize) -> Vec<f64> {
    let mut mean = vec![0.0f64; dim];
    for f in features {
        for (m, &v) in mean.iter_mut().zip(f) {
            *m += f64::from(v);
        }
    }
    mean.iter().map(|m| m / features.len() as f64).collect()
}

/// (dim, rows − mean scaled by 1/√(n − 1), n × dim row-major): checked features.
fn centred_rows(features: &[Vec<f32>]) -> crate::Result<(usize, Vec<f64>)> {
    let n = features.len();
    if n < 2 {
        return Err(TrainerError::invalid(
            "FID features",
            format!("a covariance needs at least 2 feature vectors, got {n}"),
        ));
    }
    let dim = features[0].len();
    if dim == 0 || features.iter().any(|f| f.len() != dim) {
        return Err(TrainerError::invalid(
            "FID features",
            format!("feature vectors of different or zero lengths (the first has {dim})"),
        ));
    }
    if features.iter().flatten().any(|v| !v.is_finite()) {
        return Err(TrainerError::numeric("FID", "a non-finite feature"));
    }
    let mean = mean_of(features, dim);
    let s = 1.0 / ((n - 1) as f64).sqrt();
    Ok((
        dim,
        features
            .iter()
            .flat_map(|f| {
                f.iter()
                    .zip(&mean)
                    .map(move |(&v, m)| (f64::from(v) - m) * s)
            })
            .collect(),
    ))
}

/// The Fréchet distance between two Gaussians given by their statistics:
/// `|μ1 − μ2|² + tr Σ1 + tr Σ2 − 2 Σᵢ √λᵢ(Σ1^½ Σ2 Σ1^½)`. Two symmetric
/// eigendecompositions of dim × dim (Jacobi, [`symmetric_eigen`]): fine at tens to
/// hundreds of dimensions; at 2048, n³ or worse, far too slow (docs/performance.md,
/// "Host-side timings"), so FID from features uses [`frechet_distance_of_features`],
/// which needs it only with 2048 images or more.
pub fn frechet_distance(a: &Statistics, b: &Statistics) -> crate::Result<f64> {
    let d = a.dim;
    if b.dim != d
        || a.mean.len() != d
        || b.mean.len() != d
        || a.cov.len() != d * d
        || b.cov.len() != d * d
    {
        return Err(TrainerError::invalid(
            "FID statistics",
            format!("statistics of different sizes ({} and {})", a.dim, b.dim),
        ));
    }
    if a.mean
        .iter()
        .chain(&a.cov)
        .chain(&b.mean)
        .chain(&b.cov)
        .any(|v| !v.is_finite())
    {
        return Err(TrainerError::numeric("FID", "non-finite statistics"));
    }
    let (values, vectors) = symmetric_eigen(symmetrised(&a.cov, d), d, true);
    let roots = clamped(&values, "the first covariance")?
        .iter()
        .map(|v| v.sqrt())
        .collect::<Vec<_>>();
    // Σ1^½ = V diag(√λ) Vᵀ.
    let root1 = from_eigen(&vectors, &roots, d);
    let product = matmul(&matmul(&root1, &b.cov, d), &root1, d);
    let (mu, _) = symmetric_eigen(symmetrised(&product, d), d, false);
    let tr_sqrt: f64 = clamped(&mu, "Σ1^½ Σ2 Σ1^½")?.iter().map(|v| v.sqrt()).sum();
    let trace = |m: &[f64]| (0..d).map(|i| m[i * d + i]).sum::<f64>();
    let mean_term: f64 = a
        .mean
        .iter()
        .zip(&b.mean)
        .map(|(x, y)| (x - y).powi(2))
        .sum();
    Ok(mean_term + trace(&a.cov) + trace(&b.cov) - 2.0 * tr_sqrt)
}

/// The Fréchet distance between the Gaussians fitted to two sets of feature vectors
/// (at least two each). With fewer images than dimensions (FID's usual case: tens of
/// held-out frames, 2048 features) `Σᵢ = Aᵢᵀ Aᵢ` with `Aᵢ` the centred rows over
/// √(nᵢ − 1), and the nonzero eigenvalues of `Σ1 Σ2 = A1ᵀ (A1 A2ᵀ A2)` are those of
/// `(A1 A2ᵀ)(A2 A1ᵀ) = M Mᵀ`, an n1 × n1 (or, as `Mᵀ M`, n2 × n2) matrix: the same
/// trace from a small eigenproblem, exact, not an approximation. Otherwise, through
/// [`Statistics`] and [`frechet_distance`].
pub fn frechet_distance_of_features(a: &[Vec<f32>], b: &[Vec<f32>]) -> crate::Result<f64> {
    let (d, a1) = centred_rows(a)?;
    let (d2, a2) = centred_rows(b)?;
    if d != d2 {
        return Err(TrainerError::invalid(
            "FID features",
            format!("feature vectors of lengths {d} and {d2}"),
        ));
    }
    let (n1, n2) = (a.len(), b.len());
    if n1.min(n2) >= d {
        return frechet_distance(&Statistics::of(a)?, &Statistics::of(b)?);
    }
    let v1 = ArrayView2::from_shape((n1, d), &a1).expect("n1 x d by construction");
    let v2 = ArrayView2::from_shape((n2, d), &a2).expect("n2 x d by construction");
    let mut m = vec![0.0f64; n1 * n2];
    general_mat_mul(
        1.0,
        &v1,
        &v2.t(),
        0.0,
        &mut ArrayViewMut2::from_shape((n1, n2), &mut m).expect("n1 x n2 by construction"),
    );
    let mv = ArrayView2::from_shape((n1, n2), &m).expect("n1 x n2 by construction");
    let k = n1.min(n2);
    let mut g = vec![0.0f64; k * k];
    let mut gv = ArrayViewMut2::from_shape((k, k), &mut g).expect("k x k by construction");
    if n1 <= n2 {
        general_mat_mul(1.0, &mv, &mv.t(), 0.0, &mut gv);
    } else {
        general_mat_mul(1.0, &mv.t(), &mv, 0.0, &mut gv);
    }
    let (mu, _) = symmetric_eigen(symmetrised(&g, k), k, false);
    let tr_sqrt: f64 = clamped(&mu, "M Mᵀ")?.iter().map(|v| v.sqrt()).sum();
    let (mean1, mean2) = (mean_of(a, d), mean_of(b, d));
    let mean_term: f64 = mean1.iter().zip(&mean2).map(|(x, y)| (x - y).powi(2)).sum();
    let tr = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>();
    Ok(mean_term + tr(&a1) + tr(&a2) - 2.0 * tr_sqrt)
}

/// Eigenvalues with roundoff negatives (above `-NEGATIVE_TOLERANCE` × the largest
/// magnitude) set to 0; an error names `what` when one is below.
fn clamped(values: &[f64], what: &str) -> crate::Result<Vec<f64>> {
    let largest = values.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if let Some(v) = values.iter().find(|&&v| v < -NEGATIVE_TOLERANCE * largest) {
        return Err(TrainerError::numeric(
            "FID",
            format!("{what} is not positive semidefinite: eigenvalue {v:e} (largest {largest:e})"),
        ));
    }
    Ok(values.iter().map(|&v| v.max(0.0)).collect())
}
