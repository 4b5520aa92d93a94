//! The filter's process and measurement models and their exact Jacobians.
//!
//! State `x = [phi_rad, phi_dot_radps, alpha_per_s]`; `alpha` (the damping) is a
//! constant of the motion (`alpha' = 0`), estimated when `estimate_damping` is on.

use nalgebra::{Matrix3, RowVector3, Vector3};
use serde::{Deserialize, Serialize};

/// Filter state `[phi_rad, phi_dot_radps, alpha_per_s]`.
pub type StateVec = Vector3<f64>;
/// Filter state covariance (rad, rad/s, 1/s).
pub type StateCov = Matrix3<f64>;

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

/// `f(x)` of eq. 8 augmented with `alpha' = 0`; `k = g/l`.
#[inline]
fn deriv(k: f64, x: &StateVec) -> StateVec {
    Vector3::new(x[1], -k * x[0].sin() - x[2] * x[1], 0.0)
}

/// `df/dx` at `x`.
#[inline]
fn deriv_jacobian(k: f64, x: &StateVec) -> Matrix3<f64> {
    Matrix3::new(0.0, 1.0, 0.0, -k * x[0].cos(), -x[2], -x[1], 0.0, 0.0, 0.0)
}

/// One RK4 step of length `h` (may be negative) and the exact Jacobian of that map.
#[inline]
pub fn rk4_step(k: f64, x: &StateVec, h: f64) -> (StateVec, Matrix3<f64>) {
    let i = Matrix3::identity();
    let k1 = deriv(k, x);
    let d1 = deriv_jacobian(k, x);
    let x2 = x + k1 * (0.5 * h);
    let k2 = deriv(k, &x2);
    let d2 = deriv_jacobian(k, &x2) * (i + d1 * (0.5 * h));
    let x3 = x + k2 * (0.5 * h);
    let k3 = deriv(k, &x3);
    let d3 = deriv_jacobian(k, &x3) * (i + d2 * (0.5 * h));
    let x4 = x + k3 * h;
    let k4 = deriv(k, &x4);
    let d4 = deriv_jacobian(k, &x4) * (i + d3 * h);
    let xn = x + (k1 + (k2 + k3) * 2.0 + k4) * (h / 6.0);
    let f = i + (d1 + (d2 + d3) * 2.0 + d4) * (h / 6.0);
    (xn, f)
}

/// RK4 step without the Jacobian (mean only).
#[inline]
pub fn rk4_mean(k: f64, x: &StateVec, h: f64) -> StateVec {
    let k1 = deriv(k, x);
    let k2 = deriv(k, &(x + k1 * (0.5 * h)));
    let k3 = deriv(k, &(x + k2 * (0.5 * h)));
    let k4 = deriv(k, &(x + k3 * h));
    x + (k1 + (k2 + k3) * 2.0 + k4) * (h / 6.0)
}

/// The paper's eq. 9 (second-order Taylor step) and its Jacobian `A` (with the
/// derivative with respect to `alpha` as the third column).
#[inline]
pub fn paper_step(k: f64, x: &StateVec, t: f64) -> (StateVec, Matrix3<f64>) {
    let (s, c) = x[0].sin_cos();
    let a = -x[2] * x[1] - k * s;
    let xn = Vector3::new(x[0] + t * x[1] + 0.5 * t * t * a, x[1] + t * a, x[2]);
    let jac = Matrix3::new(
        1.0 - 0.5 * t * t * k * c,
        t - 0.5 * t * t * x[2],
        -0.5 * t * t * x[1],
        -t * k * c,
        1.0 - x[2] * t,
        -t * x[1],
        0.0,
        0.0,
        1.0,
    );
    (xn, jac)
}

/// One model step of length `h` with its Jacobian.
#[inline]
pub fn step(model: ProcessModel, k: f64, x: &StateVec, h: f64) -> (StateVec, Matrix3<f64>) {
    match model {
        ProcessModel::Rk4 => rk4_step(k, x, h),
        ProcessModel::PaperTaylor2 => paper_step(k, x, h),
    }
}

/// Process noise covariance over a step of length `|h|`.
///
/// `accel` is the spectral density `q` (rad^2/s^3) for [`ProcessNoiseModel::Continuous`]
/// or the variance `sigma` (rad^2/s^4) for [`ProcessNoiseModel::Paper`]; `damping_psd`
/// (1/s^3) drives a random walk of `alpha`.
#[inline]
pub fn process_noise(
    model: ProcessNoiseModel,
    accel: f64,
    damping_psd: f64,
    h: f64,
) -> Matrix3<f64> {
    let t = h.abs();
    let (q11, q12, q22) = match model {
        ProcessNoiseModel::Continuous => (accel * t * t * t / 3.0, accel * t * t / 2.0, accel * t),
        ProcessNoiseModel::Paper => {
            // G_d G_d^T sigma with G_d = [T^2/2, T]^T.
            let g0 = 0.5 * t * t;
            (accel * g0 * g0, accel * g0 * t, accel * t * t)
        }
    };
    Matrix3::new(q11, q12, 0.0, q12, q22, 0.0, 0.0, 0.0, damping_psd * t)
}

/// Measurement `z = l sin(phi)` (eq. 10) and its Jacobian `C = [l cos(phi), 0, 0]`
/// (the paper's `C = [cos(phi), 0]` omits the factor `l`).
#[inline]
pub fn measure(l: f64, x: &StateVec) -> (f64, RowVector3<f64>) {
    let (s, c) = x[0].sin_cos();
    (l * s, RowVector3::new(l * c, 0.0, 0.0))
}
