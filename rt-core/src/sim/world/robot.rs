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
//! integrated exactly enough with sub-steps of at most 0.25 ms, and at most
//! `0.1 / w` and `0.25 / (2 zeta w)` (semi-implicit Euler: stable and within
//! a few per cent of the exact ramp lag up to `MAX_SERVO_NATURAL_HZ` and a
//! damping ratio of 3). Following a ramp of speed `v` it lags by `2 zeta v / w`.
//!
//! The drives saturate (`[world.robot]`): the servo's acceleration at
//! `acceleration_limit_scale` times the model's limit, its speed at `velocity_limit_scale` times
//! KUKA's limit. A contact's impulse `J` at point `p` pushes the joints by
//! `dq' = (M(q) + A)^-1 J_p^T J`, `A` the drives' reflected rotor
//! inertias (`contact_push`). The torque trip checks the
//! rigid-body torques with either servo (the first-order lag's acceleration
//! is its velocity's change per step).

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
    /// Speed saturation per joint, rad/s (infinite: none).
    max_speed_radps: [f64; JOINTS],
    /// Acceleration saturation per joint, rad/s^2 (infinite: none).
    max_accel_radps2: [f64; JOINTS],
    /// A contact pushes the joints.
    contact_push: bool,
    /// Joint speeds clipped by the saturation (sub-steps x joints).
    saturated: u64,
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
            max_speed_radps: [f64::INFINITY; JOINTS],
            max_accel_radps2: [f64::INFINITY; JOINTS],
            contact_push: false,
            saturated: 0,
        }
    }

    /// Saturates each joint's speed at `velocity_scale` times KUKA's limit
    /// and its acceleration at `accel_scale` times the model's
    /// (`ACCELERATION_LIMIT_RADPS2`); 0: no saturation.
    pub fn set_saturation(&mut self, velocity_scale: f64, accel_scale: f64) {
        use crate::kinematics::iiwa7::{ACCELERATION_LIMIT_RADPS2, VELOCITY_LIMIT_RADPS};
        let cap = |scale: f64, limit: f64| {
            if scale > 0.0 {
                limit * scale
            } else {
                f64::INFINITY
            }
        };
        for i in 0..JOINTS {
            self.max_speed_radps[i] = cap(velocity_scale, VELOCITY_LIMIT_RADPS[i]);
            self.max_accel_radps2[i] = cap(accel_scale, ACCELERATION_LIMIT_RADPS2[i]);
        }
    }

    /// Let contacts push the joints ([`Self::push`]).
    pub fn set_contact_push(&mut self, on: bool) {
        self.contact_push = on;
    }

    /// Sub-steps x joints whose speed or acceleration the drives clipped.
    pub fn saturated(&self) -> u64 {
        self.saturated
    }

    /// A contact's impulse `impulse_ns` at `point_m` (base frame) pushes the
    /// true joints: `dq' = (M(q) + A)^-1 J_p^T impulse`, `A` the drives'
    /// reflected rotor inertias (`dynamics::ARMATURE_KGM2`) (with the first-order lag,
    /// which has no velocity state, the displacement it would relax from,
    /// `dq' tau`). Nothing when contact push is off or after a trip.
    pub fn push(&mut self, point_m: &nalgebra::Vector3<f64>, impulse_ns: &nalgebra::Vector3<f64>) {
        if !self.contact_push || self.trip.is_some() {
            return;
        }
        let tau = super::contact::joint_torques(&self.q, point_m, impulse_ns);
        let m = self.dynamics.push_matrix(&self.q);
        let Some(chol) = m.cholesky() else {
            return;
        };
        let dqd = chol.solve(&nalgebra::SVector::<f64, JOINTS>::from(tau));
        for i in 0..JOINTS {
            if !dqd[i].is_finite() {
                return;
            }
        }
        if self.omega_radps <= 0.0 {
            for i in 0..JOINTS {
                self.q[i] += dqd[i] * self.tau_s;
            }
        } else {
            for i in 0..JOINTS {
                self.qd[i] += dqd[i];
            }
        }
    }

    /// Checks the torques of `q, qd, qdd` against the limits (peaks kept);
    /// trips and halts when one exceeds its limit.
    fn check(&mut self) -> Option<TorqueTrip> {
        let tau = self.dynamics.torques(&self.q, &self.qd, &self.qdd);
        for (i, t) in tau.iter().enumerate() {
            let r = t.abs() / (crate::kinematics::iiwa7::TORQUE_LIMIT_NM[i] * self.torque_scale);
            self.peak_torque_ratio[i] = self.peak_torque_ratio[i].max(r);
        }
        if self.trip_enabled
            && let Err(trip) = check_torques(&tau, self.torque_scale)
        {
            self.trip = Some(trip);
            self.halt();
            return self.trip;
        }
        None
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
            for (i, s) in setpoint.iter().enumerate() {
                let mut v = (s - self.q[i]) * a / dt_s;
                if v.abs() > self.max_speed_radps[i] {
                    v = v.clamp(-self.max_speed_radps[i], self.max_speed_radps[i]);
                    self.saturated += 1;
                }
                let dv = v - self.qd[i];
                if dv.abs() > self.max_accel_radps2[i] * dt_s {
                    v = self.qd[i] + dv.signum() * self.max_accel_radps2[i] * dt_s;
                    self.saturated += 1;
                }
                // The mean acceleration over at least an interpolation
                // period: a setpoint's step is a jump of the lag's speed,
                // spread by the drive's interpolator, not an infinite torque.
                self.qdd[i] = (v - self.qd[i]) / dt_s.max(self.interp_s).max(SERVO_STEP_S);
                self.qd[i] = v;
                self.q[i] += v * dt_s;
            }
            return self.check();
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
        let w2 = self.omega_radps * self.omega_radps;
        let c = 2.0 * self.zeta * self.omega_radps;
        // Small enough for the stiffest, most damped servo a world may draw.
        let h_max = SERVO_STEP_S.min(0.1 / self.omega_radps).min(0.25 / c);
        let n = (dt_s / h_max).ceil().max(1.0);
        let h = dt_s / n;
        for _ in 0..n as usize {
            for i in 0..JOINTS {
                // The state at the sub-step's start (its reference too): the
                // ramp's steady lag is then exactly `2 zeta v / w`.
                let mut a = w2 * (self.ramp_value(i) - self.q[i]) - c * self.qd[i];
                if a.abs() > self.max_accel_radps2[i] {
                    a = a.clamp(-self.max_accel_radps2[i], self.max_accel_radps2[i]);
                    self.saturated += 1;
                }
                let mut v = self.qd[i] + a * h;
                if v.abs() > self.max_speed_radps[i] {
                    v = v.clamp(-self.max_speed_radps[i], self.max_speed_radps[i]);
                    a = (v - self.qd[i]) / h;
                    self.saturated += 1;
                }
                self.qdd[i] = a;
                self.qd[i] = v;
                self.q[i] += v * h;
            }
            self.ramp_t_s += h;
            if let Some(trip) = self.check() {
                return Some(trip);
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
