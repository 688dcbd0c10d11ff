//! Dense Levenberg-Marquardt in f64 with forward-difference Jacobians, for the small
//! problems of the body fit (`crate::body::fit`: tens of parameters, hundreds of
//! residuals): the normal equations solved by Cholesky, the damping scaled by the
//! diagonal of JᵀJ (Marquardt's), raised tenfold on a rejected step and lowered on an
//! accepted one.

/// Solves `(JᵀJ + damping) dx = -Jᵀr` by Cholesky; None if not positive definite.
fn solve_normal(jtj: &[f64], jtr: &[f64], n: usize) -> Option<Vec<f64>> {
    let mut l = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..=i {
            let mut s = jtj[i * n + j];
            for k in 0..j {
                s -= l[i * n + k] * l[j * n + k];
            }
            if i == j {
                if !(s > 0.0) {
                    return None;
                }
                l[i * n + i] = s.sqrt();
            } else {
                l[i * n + j] = s / l[j * n + j];
            }
        }
    }
    let mut y = vec![0.0; n];
    for i in 0..n {
        let s: f64 = (0..i).map(|k| l[i * n + k] * y[k]).sum();
        y[i] = (-jtr[i] - s) / l[i * n + i];
    }
    let mut x = vec![0.0; n];
    for i in (0..n).rev() {
        let s: f64 = (i + 1..n).map(|k| l[k * n + i] * x[k]).sum();
        x[i] = (y[i] - s) / l[i * n + i];
    }
    Some(x)
}

/// Levenberg-Marquardt on `n` parameters: `residuals(state, dx)` at the step `dx`
/// from `state`, `step(state, dx)` the state moved by it. Returns the final cost.
pub(crate) fn levenberg_marquardt<S>(
    state: &mut S,
    n: usize,
    iterations: usize,
    residuals: impl Fn(&S, &[f64]) -> Vec<f64>,
    step: impl Fn(&S, &[f64]) -> S,
) -> f64 {
    let h = 1e-6;
    let mut lambda = 1e-3;
    let mut r0 = residuals(state, &vec![0.0; n]);
    let mut cost: f64 = r0.iter().map(|r| r * r).sum();
    for _ in 0..iterations {
        let m = r0.len();
        let mut jac = vec![0.0; m * n];
        let mut dx = vec![0.0; n];
        for k in 0..n {
            dx[k] = h;
            let r = residuals(state, &dx);
            dx[k] = 0.0;
            for i in 0..m {
                jac[i * n + k] = (r[i] - r0[i]) / h;
            }
        }
        let mut jtj = vec![0.0; n * n];
        let mut jtr = vec![0.0; n];
        for i in 0..m {
            let row = &jac[i * n..(i + 1) * n];
            for a in 0..n {
                if row[a] == 0.0 {
                    continue;
                }
                jtr[a] += row[a] * r0[i];
                for b in 0..=a {
                    jtj[a * n + b] += row[a] * row[b];
                }
            }
        }
        for a in 0..n {
            for b in 0..a {
                jtj[b * n + a] = jtj[a * n + b];
            }
        }
        let mut improved = false;
        for _ in 0..8 {
            let mut damped = jtj.clone();
            for a in 0..n {
                damped[a * n + a] += lambda * (jtj[a * n + a] + 1e-6);
            }
            if let Some(dx) = solve_normal(&damped, &jtr, n) {
                let r = residuals(state, &dx);
                let c: f64 = r.iter().map(|x| x * x).sum();
                if c < cost {
                    *state = step(state, &dx);
                    r0 = residuals(state, &vec![0.0; n]);
                    let converged = cost - c < 1e-9 * cost.max(1e-12);
                    cost = c;
                    lambda = (lambda * 0.3).max(1e-9);
                    improved = !converged;
                    break;
                }
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    cost
}
