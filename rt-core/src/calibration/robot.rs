//! Robot latency and servo: one joint's commanded and measured positions under a
//! small excitation -> command-to-motion delay and first-order servo lag.
//!
//! Model: the command sent at `t_k` becomes the setpoint at `t_k + L` (held until
//! the next); the joint follows the setpoint with a first-order lag `tau`:
//! `q' = (setpoint - q) / tau`. `L` and `tau` are found by a grid search and
//! refined by least squares on the measured positions.

use serde::{Deserialize, Serialize};

use super::{CalibrationError, lsq};

/// One sample of the excited joint.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointSample {
    /// Time, seconds (one clock for commands and measurements).
    pub t_s: f64,
    /// Position, radians.
    pub q_rad: f64,
}

/// The fitted robot response.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobotLatency {
    /// Command sent -> setpoint applied, milliseconds (mean over the excitation).
    pub latency_ms: f64,
    /// One standard deviation of `latency_ms` (from the fit).
    pub latency_std_ms: f64,
    /// First-order servo time constant, milliseconds.
    pub servo_time_constant_ms: f64,
    /// -3 dB bandwidth of the servo lag, `1 / (2 pi tau)`, Hz.
    pub bandwidth_hz: f64,
    /// Root mean square of the position residuals, radians.
    pub residual_rms_rad: f64,
    /// Commands used.
    pub commands: usize,
    /// Measurements used.
    pub measurements: usize,
}

/// Smallest peak-to-peak measured motion the fit accepts, radians.
pub const MIN_MOTION_RAD: f64 = 1e-3;

/// Fits the delay and the servo lag. Commands and measurements are each in time order.
///
/// # Errors
///
/// [`CalibrationError::NotFinite`] for a non-finite sample;
/// [`CalibrationError::TooFewSamples`] with fewer than 20 commands or measurements;
/// [`CalibrationError::NoResponse`] when the joint moved too little;
/// [`CalibrationError::FitFailed`] when the fit does not converge.
pub fn fit_robot_latency(
    commands: &[JointSample],
    measured: &[JointSample],
) -> Result<RobotLatency, CalibrationError> {
    const WHAT: &str = "robot latency";
    for (index, s) in commands.iter().chain(measured).enumerate() {
        if !s.t_s.is_finite() || !s.q_rad.is_finite() {
            return Err(CalibrationError::NotFinite { what: WHAT, index });
        }
    }
    if commands.len() < 20 || measured.len() < 20 {
        return Err(CalibrationError::TooFewSamples {
            what: WHAT,
            got: commands.len().min(measured.len()),
            need: 20,
        });
    }
    let (lo, hi) = measured
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), s| {
            (l.min(s.q_rad), h.max(s.q_rad))
        });
    if hi - lo < MIN_MOTION_RAD {
        return Err(CalibrationError::NoResponse {
            moved_rad: hi - lo,
            min_rad: MIN_MOTION_RAD,
        });
    }
    let q0 = measured[0].q_rad;
    let mut r = vec![0.0; measured.len()];
    let mut best = (f64::INFINITY, 0.0, 0.0);
    // Grid: 0..100 ms in 0.5 ms, tau 0..50 ms in 1 ms.
    for li in 0..=200 {
        let l = f64::from(li) * 0.5e-3;
        for ti in 0..=50 {
            let tau = f64::from(ti) * 1e-3;
            simulate(commands, measured, l, tau, q0, &mut r);
            let c: f64 = r.iter().map(|x| x * x).sum();
            if c < best.0 {
                best = (c, l, tau);
            }
        }
    }
    let fit = lsq::levenberg_marquardt(
        &[best.1, best.2.max(1e-4)],
        &[2e-5, 2e-5],
        measured.len(),
        50,
        |p, r| {
            if !(p[0] >= 0.0 && p[0] < 0.5 && p[1] >= 0.0 && p[1] < 0.5) {
                return false;
            }
            simulate(commands, measured, p[0], p[1], q0, r);
            true
        },
    )
    .ok_or_else(|| CalibrationError::FitFailed {
        what: WHAT,
        reason: "the least-squares fit did not converge".into(),
    })?;
    let (l, tau) = (fit.params[0], fit.params[1]);
    Ok(RobotLatency {
        latency_ms: l * 1e3,
        latency_std_ms: fit.std[0] * 1e3,
        servo_time_constant_ms: tau * 1e3,
        bandwidth_hz: if tau > 0.0 {
            1.0 / (std::f64::consts::TAU * tau)
        } else {
            f64::INFINITY
        },
        residual_rms_rad: fit.rms,
        commands: commands.len(),
        measurements: measured.len(),
    })
}

/// The model's joint position at each measurement time, minus the measurement, into `r`.
fn simulate(
    commands: &[JointSample],
    measured: &[JointSample],
    latency_s: f64,
    tau_s: f64,
    q0: f64,
    r: &mut [f64],
) {
    let mut q = q0;
    let mut sp = q0;
    let mut t = measured[0].t_s;
    let mut k = commands.partition_point(|c| c.t_s + latency_s <= t);
    if k > 0 {
        sp = commands[k - 1].q_rad;
    }
    let step = |q: &mut f64, sp: f64, dt: f64| {
        if dt <= 0.0 {
            return;
        }
        if tau_s <= 0.0 {
            *q = sp;
        } else {
            *q += (sp - *q) * (1.0 - (-dt / tau_s).exp());
        }
    };
    for (ri, m) in r.iter_mut().zip(measured) {
        while k < commands.len() && commands[k].t_s + latency_s <= m.t_s {
            let due = commands[k].t_s + latency_s;
            step(&mut q, sp, due - t);
            t = due.max(t);
            sp = commands[k].q_rad;
            k += 1;
        }
        step(&mut q, sp, m.t_s - t);
        t = m.t_s;
        *ri = q - m.q_rad;
    }
}
