//! The filter's process and measurement models and their exact Jacobians.
//!
//! State `x = [phi_rad, phi_dot_radps, alpha_per_s, k_per_s2, b_m]`: `alpha` (the
//! damping), `k = g/l` (the squared small-angle frequency) and `b` (the lateral
//! offset of the measured rest point) are constants of the motion, each estimated
//! only when its switch is on (`estimate_damping`, `estimate_frequency`,
//! `estimate_offset`); otherwise its variance stays zero and it keeps the
//! model's value (`alpha` = the damping, `k = g/l`, `b = 0`).

use nalgebra::{SMatrix, SVector};
use serde::{Deserialize, Serialize};

/// Number of filter states.
pub const N: usize = 5;
/// Filter state `[phi_rad, phi_dot_radps, alpha_per_s, k_per_s2, b_m]`.
pub type StateVec = SVector<f64, N>;
/// Filter state covariance (rad, rad/s, 1/s, 1/s^2, m).
pub type StateCov = SMatrix<f64, N, N>;
/// A state Jacobian.
pub type StateJac = SMatrix<f64, N, N>;
/// The measurement row `C`.
pub type MeasRow = SMatrix<f64, 1, N>;

/// Index of `alpha` in the state.
pub const ALPHA: usize = 2;
/// Index of `k = g/l` in the state.
pub const K: usize = 3;
/// Index of the lateral offset `b` in the state.
pub const B: usize = 4;

/// A state from its parts.
#[inline]
pub fn state(phi: f64, rate: f64, alpha: f64, k: f64, b: f64) -> StateVec {
    SVector::from([phi, rate, alpha, k, b])
}

/// How the state is carried over a time step.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProcessModel {
    /// Classical Runge-Kutta over eq. 8 with its exact Jacobian (default).
    Rk4,
    /// The paper's eq. 9: the second-order Taylor step and its Jacobian `A`.
    PaperTaylor2,
}

/// How process noise enters over a step of length `T`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProcessNoiseModel {
    /// Continuous white angular acceleration of spectral density `q`:
    /// `Q = q [[T^3/3, T^2/2], [T^2/2, T]]` (default; independent of how time is split).
    Continuous,
    /// The paper's eqs. 16-19: `Q = G_d G_d^T sigma`, `G_d = [T^2/2, T]^T`
    /// (piecewise-constant acceleration of variance `sigma` over each step).
    Paper,
}

/// `f(x)` of eq. 8 augmented with constant `alpha`, `k` and `b`; `k = g/l` is
/// the state's own.
#[inline]
fn deriv(x: &StateVec) -> StateVec {
    let mut d = StateVec::zeros();
    d[0] = x[1];
    d[1] = -x[K] * x[0].sin() - x[ALPHA] * x[1];
    d
}

/// The rows of `df/dx` at `x` that are not zero: those of `phi` and
/// `phi_dot` (the constants' rows are zero).
#[inline]
fn deriv_jacobian_rows(x: &StateVec) -> JacRows {
    let mut j = JacRows::zeros();
    j[(0, 1)] = 1.0;
    j[(1, 0)] = -x[K] * x[0].cos();
    j[(1, 1)] = -x[ALPHA];
    j[(1, ALPHA)] = -x[1];
    j[(1, K)] = -x[0].sin();
    j
}

/// Rows 0 and 1 of a matrix whose other rows are zero (`df/dx` and its
/// products in the RK4 chain), or of a step Jacobian minus the identity.
pub type JacRows = SMatrix<f64, 2, N>;

/// `J (I + D s)` for `J`, `D` zero outside rows 0 and 1: `J + J[:, 0..2] D s`.
#[inline]
fn chain(j: &JacRows, d: &JacRows, s: f64) -> JacRows {
    j + j.fixed_columns::<2>(0) * d * s
}

/// One RK4 step of length `h` (may be negative) and the exact Jacobian of that
/// map. Every `df/dx` in the chain is zero outside rows 0 and 1, so the chain
/// is carried in those two rows (2x5 instead of 5x5 products) and the step's
/// Jacobian is the identity outside them.
#[inline]
pub fn rk4_step(x: &StateVec, h: f64) -> (StateVec, StateJac) {
    let k1 = deriv(x);
    let d1 = deriv_jacobian_rows(x);
    let x2 = x + k1 * (0.5 * h);
    let k2 = deriv(&x2);
    let d2 = chain(&deriv_jacobian_rows(&x2), &d1, 0.5 * h);
    let x3 = x + k2 * (0.5 * h);
    let k3 = deriv(&x3);
    let d3 = chain(&deriv_jacobian_rows(&x3), &d2, 0.5 * h);
    let x4 = x + k3 * h;
    let k4 = deriv(&x4);
    let d4 = chain(&deriv_jacobian_rows(&x4), &d3, h);
    let xn = x + (k1 + (k2 + k3) * 2.0 + k4) * (h / 6.0);
    let mut f = StateJac::identity();
    let mut top = f.fixed_rows_mut::<2>(0);
    top += (d1 + (d2 + d3) * 2.0 + d4) * (h / 6.0);
    (xn, f)
}

/// `F P F^T` for a step Jacobian `F` that is the identity outside rows 0 and 1
/// (both process models: the constants carry over unchanged): 100
/// multiply-adds instead of 250.
#[inline]
pub fn carry_cov(f: &StateJac, p: &StateCov) -> StateCov {
    debug_assert!(
        (2..N).all(|i| (0..N).all(|j| f[(i, j)] == if i == j { 1.0 } else { 0.0 })),
        "a step Jacobian must be the identity outside rows 0 and 1"
    );
    let rows = f.fixed_rows::<2>(0);
    // F P: rows 0 and 1 are F's rows times P; the others are P's.
    let mut fp = *p;
    let top = rows * p;
    fp.fixed_rows_mut::<2>(0).copy_from(&top);
    // (F P) F^T: columns 0 and 1 are (F P) times F's rows; the others (F P)'s.
    let left = fp * rows.transpose();
    fp.fixed_columns_mut::<2>(0).copy_from(&left);
    fp
}

/// RK4 step without the Jacobian (mean only).
#[inline]
pub fn rk4_mean(x: &StateVec, h: f64) -> StateVec {
    let k1 = deriv(x);
    let k2 = deriv(&(x + k1 * (0.5 * h)));
    let k3 = deriv(&(x + k2 * (0.5 * h)));
    let k4 = deriv(&(x + k3 * h));
    x + (k1 + (k2 + k3) * 2.0 + k4) * (h / 6.0)
}

/// The paper's eq. 9 (second-order Taylor step) and its Jacobian `A` (with the
/// derivatives with respect to `alpha` and `k` as further columns).
#[inline]
pub fn paper_step(x: &StateVec, t: f64) -> (StateVec, StateJac) {
    let (s, c) = x[0].sin_cos();
    let (alpha, k) = (x[ALPHA], x[K]);
    let a = -alpha * x[1] - k * s;
    let mut xn = *x;
    xn[0] = x[0] + t * x[1] + 0.5 * t * t * a;
    xn[1] = x[1] + t * a;
    let mut jac = StateJac::identity();
    jac[(0, 0)] = 1.0 - 0.5 * t * t * k * c;
    jac[(0, 1)] = t - 0.5 * t * t * alpha;
    jac[(0, ALPHA)] = -0.5 * t * t * x[1];
    jac[(0, K)] = -0.5 * t * t * s;
    jac[(1, 0)] = -t * k * c;
    jac[(1, 1)] = 1.0 - alpha * t;
    jac[(1, ALPHA)] = -t * x[1];
    jac[(1, K)] = -t * s;
    (xn, jac)
}

/// One model step of length `h` with its Jacobian.
#[inline]
pub fn step(model: ProcessModel, x: &StateVec, h: f64) -> (StateVec, StateJac) {
    match model {
        ProcessModel::Rk4 => rk4_step(x, h),
        ProcessModel::PaperTaylor2 => paper_step(x, h),
    }
}

/// Process noise covariance over a step of length `|h|`.
///
/// `accel` is the spectral density `q` (rad^2/s^3) for [`ProcessNoiseModel::Continuous`]
/// or the variance `sigma` (rad^2/s^4) for [`ProcessNoiseModel::Paper`]; `damping_psd`
/// (1/s^3) drives a random walk of `alpha`.
#[inline]
pub fn process_noise(model: ProcessNoiseModel, accel: f64, damping_psd: f64, h: f64) -> StateCov {
    let t = h.abs();
    let (q11, q12, q22) = match model {
        ProcessNoiseModel::Continuous => (accel * t * t * t / 3.0, accel * t * t / 2.0, accel * t),
        ProcessNoiseModel::Paper => {
            // G_d G_d^T sigma with G_d = [T^2/2, T]^T.
            let g0 = 0.5 * t * t;
            (accel * g0 * g0, accel * g0 * t, accel * t * t)
        }
    };
    let mut q = StateCov::zeros();
    q[(0, 0)] = q11;
    q[(0, 1)] = q12;
    q[(1, 0)] = q12;
    q[(1, 1)] = q22;
    q[(ALPHA, ALPHA)] = damping_psd * t;
    q
}

/// Measurement `z = l sin(phi) + b` (eq. 10 plus the rest offset) and its
/// Jacobian `C = [l cos(phi), 0, 0, 0, 1]` (the paper's `C = [cos(phi), 0]`
/// omits the factor `l`). `l` is the believed length: with `k` estimated, a
/// wrong length scales the angle by the length's error (a 1% error moves the
/// large-angle period by ~0.05% at 25 deg), while `k` carries the frequency.
#[inline]
pub fn measure(l: f64, x: &StateVec) -> (f64, MeasRow) {
    let (s, c) = x[0].sin_cos();
    let mut row = MeasRow::zeros();
    row[0] = l * c;
    row[B] = 1.0;
    (l * s + x[B], row)
}
