//! The true robot: command-to-motion latency per session with a slow drift,
//! per-joint second-order position servos (following error grows with speed
//! and acceleration), noisy measured positions, joint torques from the rigid-body
//! dynamics checked against the torque limits (the over-current trip).
//!
//! Servo of each joint towards its (delayed) setpoint `s`:
//!
//! ```text
//! q'' = w^2 (s - q) - 2 zeta w q'
//! ```
//!
//! integrated exactly enough with sub-steps of at most 0.25 ms (semi-implicit
//! Euler). Following a ramp of speed `v` it lags by `2 zeta v / w`.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::dynamics::{ArmDynamics, TorqueTrip, check_torques};
use super::params::SessionDraw;
use crate::kinematics::iiwa7::JOINTS;
use crate::sim::camera::gaussian;

/// Largest servo sub-step, seconds.
pub const SERVO_STEP_S: f64 = 2.5e-4;

/// The command-to-motion latency of one session: its value at the session's
/// start plus a slow sine drift.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LatencyModel {
    /// Latency at the session's start (drift phase aside), s.
    pub base_s: f64,
    /// Drift amplitude, s.
    pub drift_s: f64,
    /// Drift period, s.
    pub period_s: f64,
    /// Drift phase, rad.
    pub phase_rad: f64,
    /// Session start time, s.
    pub t0_s: f64,
}

impl LatencyModel {
    /// The session's latency model starting at `t0_s`.
    pub fn from_session(d: &SessionDraw, t0_s: f64) -> Self {
        Self {
            base_s: d.robot_latency_s,
            drift_s: d.robot_drift_s,
            period_s: d.robot_drift_period_s,
            phase_rad: d.robot_drift_phase_rad,
            t0_s,
        }
    }

    /// Latency at time `t_s`, s (never negative).
    pub fn latency_s(&self, t_s: f64) -> f64 {
        let w = std::f64::consts::TAU / self.period_s.max(1e-3);
        let drift = self.drift_s * ((t_s - self.t0_s) * w + self.phase_rad).sin();
        (self.base_s + drift).max(0.0)
    }
}

/// The joints of the true robot: servo state, dynamics, noise, trip.
#[derive(Debug, Clone)]
pub struct WorldJoints {
    q: [f64; JOINTS],
    qd: [f64; JOINTS],
    qdd: [f64; JOINTS],
    omega_radps: f64,
    zeta: f64,
    /// First-order lag used when `omega_radps == 0`, s.
    tau_s: f64,
    dynamics: ArmDynamics,
    torque_scale: f64,
    trip_enabled: bool,
    noise_rad: f64,
    rng: ChaCha8Rng,
    peak_torque_ratio: [f64; JOINTS],
    trip: Option<TorqueTrip>,
    /// A new setpoint is approached linearly over this time (the drive's
    /// interpolator), s; 0: a step.
    interp_s: f64,
    ramp_from: [f64; JOINTS],
    ramp_to: [f64; JOINTS],
    ramp_t_s: f64,
}

impl WorldJoints {
    /// Joints at rest at `q0`, with the session's servo and inertia draws.
    pub fn new(
        q0: [f64; JOINTS],
        session: &SessionDraw,
        first_order_tau_s: f64,
        torque_scale: f64,
        trip_enabled: bool,
        noise_rad: f64,
        seed: u64,
    ) -> Self {
        Self {
            q: q0,
            qd: [0.0; JOINTS],
            qdd: [0.0; JOINTS],
            omega_radps: session.servo_omega_radps,
            zeta: session.servo_damping_ratio,
            tau_s: first_order_tau_s,
            dynamics: ArmDynamics::scaled(&session.inertia_factor),
            torque_scale,
            trip_enabled,
            noise_rad,
            rng: ChaCha8Rng::seed_from_u64(seed),
            peak_torque_ratio: [0.0; JOINTS],
            trip: None,
            interp_s: 0.0,
            ramp_from: q0,
            ramp_to: q0,
            ramp_t_s: 0.0,
        }
    }

    /// Approach each new setpoint linearly over `interp_s` (the drive's
    /// interpolator; the FRI period), instead of as a step.
    pub fn set_interpolation_s(&mut self, interp_s: f64) {
        self.interp_s = interp_s.max(0.0);
    }

    fn ramp_value(&self, i: usize) -> f64 {
        if self.interp_s <= 0.0 || self.ramp_t_s >= self.interp_s {
            return self.ramp_to[i];
        }
        let f = self.ramp_t_s / self.interp_s;
        self.ramp_from[i] + (self.ramp_to[i] - self.ramp_from[i]) * f
    }

    /// True joint positions, rad.
    pub fn q(&self) -> &[f64; JOINTS] {
        &self.q
    }

    /// True joint velocities, rad/s.
    pub fn qd(&self) -> &[f64; JOINTS] {
        &self.qd
    }

    /// The torque trip, once one happened (the drives then hold still).
    pub fn trip(&self) -> Option<TorqueTrip> {
        self.trip
    }

    /// Clears a trip (a new commanding phase).
    pub fn clear_trip(&mut self) {
        self.trip = None;
    }

    /// Largest |torque| / limit seen per joint.
    pub fn peak_torque_ratio(&self) -> &[f64; JOINTS] {
        &self.peak_torque_ratio
    }

    /// Stops the joints where they are (after a trip or an abort).
    pub fn halt(&mut self) {
        self.qd = [0.0; JOINTS];
        self.qdd = [0.0; JOINTS];
    }

    /// Servos towards `setpoint` for `dt_s`; computes the torques on the way
    /// and trips when one exceeds its limit. Returns the trip, if any.
    pub fn integrate(&mut self, setpoint: &[f64; JOINTS], dt_s: f64) -> Option<TorqueTrip> {
        if dt_s.is_nan() || dt_s <= 0.0 {
            return self.trip;
        }
        if self.trip.is_some() {
            self.halt();
            return self.trip;
        }
        if self.omega_radps <= 0.0 {
            let a = if self.tau_s <= 0.0 {
                1.0
            } else {
                1.0 - (-dt_s / self.tau_s).exp()
            };
            for ((q, qd), s) in self.q.iter_mut().zip(self.qd.iter_mut()).zip(setpoint) {
                let dq = (s - *q) * a;
                *qd = dq / dt_s;
                *q += dq;
            }
            return None;
        }
        if *setpoint != self.ramp_to {
            let mut from = [0.0; JOINTS];
            for (i, f) in from.iter_mut().enumerate() {
                *f = self.ramp_value(i);
            }
            self.ramp_from = from;
            self.ramp_to = *setpoint;
            self.ramp_t_s = 0.0;
        }
        let n = (dt_s / SERVO_STEP_S).ceil().max(1.0);
        let h = dt_s / n;
        let w2 = self.omega_radps * self.omega_radps;
        let c = 2.0 * self.zeta * self.omega_radps;
        for _ in 0..n as usize {
            self.ramp_t_s += h;
            for i in 0..JOINTS {
                let a = w2 * (self.ramp_value(i) - self.q[i]) - c * self.qd[i];
                self.qdd[i] = a;
                self.qd[i] += a * h;
                self.q[i] += self.qd[i] * h;
            }
            let tau = self.dynamics.torques(&self.q, &self.qd, &self.qdd);
            for (i, t) in tau.iter().enumerate() {
                let r =
                    t.abs() / (crate::kinematics::iiwa7::TORQUE_LIMIT_NM[i] * self.torque_scale);
                self.peak_torque_ratio[i] = self.peak_torque_ratio[i].max(r);
            }
            if self.trip_enabled
                && let Err(trip) = check_torques(&tau, self.torque_scale)
            {
                self.trip = Some(trip);
                self.halt();
                return self.trip;
            }
        }
        None
    }

    /// The measured joint positions: the true ones plus Gaussian noise.
    pub fn measured(&mut self) -> [f64; JOINTS] {
        let mut m = self.q;
        if self.noise_rad > 0.0 {
            for v in &mut m {
                *v += self.noise_rad * gaussian(&mut self.rng);
            }
        }
        m
    }
}
