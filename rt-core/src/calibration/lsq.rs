//! A small Levenberg-Marquardt least-squares solver with a numeric (central
//! difference) Jacobian, for the calibration fits (a handful of parameters,
//! hundreds of residuals; not on any real-time path).

use nalgebra::{DMatrix, DVector};

/// The result of [`levenberg_marquardt`].
#[derive(Debug, Clone)]
pub struct LsqResult {
    /// The parameters at the minimum.
    pub params: Vec<f64>,
    /// Root mean square of the residuals there.
    pub rms: f64,
    /// One standard deviation of each parameter, from `(J^T J)^-1 s^2` with
    /// `s^2 = sum r^2 / (n - p)` (Gauss-Newton covariance at the minimum).
    pub std: Vec<f64>,
    /// Iterations taken.
    pub iterations: usize,
}

/// Minimises `sum r_i(p)^2`. `residuals(p, r)` fills `r` (length `n`) and returns
/// false when `p` is not admissible (the step is then refused). `scale` gives the
/// finite-difference step of each parameter. Returns `None` when the start is not
/// admissible or the normal equations are singular at the end.
///
/// ```
/// use rt_core::calibration::lsq::levenberg_marquardt;
/// // A line y = 2x + 1 through five exact points.
/// let xs = [0.0, 1.0, 2.0, 3.0, 4.0];
/// let fit = levenberg_marquardt(&[0.0, 0.0], &[1e-6, 1e-6], xs.len(), 50, |p, r| {
///     for (ri, x) in r.iter_mut().zip(xs) {
///         *ri = p[0] * x + p[1] - (2.0 * x + 1.0);
///     }
///     true
/// })
/// .unwrap();
/// assert!((fit.params[0] - 2.0).abs() < 1e-6 && (fit.params[1] - 1.0).abs() < 1e-6);
/// ```
pub fn levenberg_marquardt(
    start: &[f64],
    scale: &[f64],
    n: usize,
    max_iterations: usize,
    mut residuals: impl FnMut(&[f64], &mut [f64]) -> bool,
) -> Option<LsqResult> {
    let np = start.len();
    if n <= np || scale.len() != np {
        return None;
    }
    let mut p = start.to_vec();
    let mut r = vec![0.0; n];
    if !residuals(&p, &mut r) {
        return None;
    }
    let mut cost: f64 = r.iter().map(|x| x * x).sum();
    let mut lambda = 1e-3;
    let mut jac = DMatrix::<f64>::zeros(n, np);
    let mut rp = vec![0.0; n];
    let mut rm = vec![0.0; n];
    let mut iterations = 0;
    let mut trial = vec![0.0; np];
    let mut rt = vec![0.0; n];
    let jacobian = |p: &[f64],
                    jac: &mut DMatrix<f64>,
                    rp: &mut [f64],
                    rm: &mut [f64],
                    residuals: &mut dyn FnMut(&[f64], &mut [f64]) -> bool|
     -> bool {
        let mut q = p.to_vec();
        for j in 0..np {
            let h = scale[j];
            q[j] = p[j] + h;
            let okp = residuals(&q, rp);
            q[j] = p[j] - h;
            let okm = residuals(&q, rm);
            q[j] = p[j];
            if !(okp && okm) {
                return false;
            }
            for i in 0..n {
                jac[(i, j)] = (rp[i] - rm[i]) / (2.0 * h);
            }
        }
        true
    };
    for _ in 0..max_iterations {
        iterations += 1;
        if !jacobian(&p, &mut jac, &mut rp, &mut rm, &mut residuals) {
            return None;
        }
        let jt = jac.transpose();
        let jtj = &jt * &jac;
        let g = &jt * DVector::from_column_slice(&r);
        let mut improved = false;
        for _ in 0..20 {
            let mut a = jtj.clone();
            for k in 0..np {
                a[(k, k)] += lambda * jtj[(k, k)].max(1e-12);
            }
            let Some(step) = a.lu().solve(&(-&g)) else {
                lambda *= 10.0;
                continue;
            };
            for k in 0..np {
                trial[k] = p[k] + step[k];
            }
            if residuals(&trial, &mut rt) {
                let c: f64 = rt.iter().map(|x| x * x).sum();
                if c.is_finite() && c < cost {
                    let rel = (cost - c) / cost.max(1e-300);
                    p.copy_from_slice(&trial);
                    r.copy_from_slice(&rt);
                    cost = c;
                    lambda = (lambda * 0.3).max(1e-12);
                    improved = true;
                    if rel < 1e-12 {
                        return finish(p, &r, &jac, n, np, iterations);
                    }
                    break;
                }
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    // Covariance at the final point.
    if !jacobian(&p, &mut jac, &mut rp, &mut rm, &mut residuals) {
        return None;
    }
    finish(p, &r, &jac, n, np, iterations)
}

fn finish(
    p: Vec<f64>,
    r: &[f64],
    jac: &DMatrix<f64>,
    n: usize,
    np: usize,
    iterations: usize,
) -> Option<LsqResult> {
    let cost: f64 = r.iter().map(|x| x * x).sum();
    let s2 = cost / (n - np) as f64;
    let jtj = jac.transpose() * jac;
    let cov = jtj.try_inverse()?;
    let std = (0..np)
        .map(|k| (cov[(k, k)].max(0.0) * s2).sqrt())
        .collect();
    Some(LsqResult {
        params: p,
        rms: (cost / n as f64).sqrt(),
        std,
        iterations,
    })
}
