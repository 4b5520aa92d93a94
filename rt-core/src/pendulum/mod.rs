#![doc = include_str!("README.md")]

use nalgebra::{Vector2, Vector3};

use crate::check::{self, ParamError};

mod params;
pub use params::PendulumParams;

/// Pendulum state `[phi_rad, phi_dot_radps]`: angle from the vertical and its rate.
pub type PendulumState = Vector2<f64>;

/// Largest RK4 sub-step of the ground-truth simulator, seconds.
pub const SIM_MAX_STEP_S: f64 = 1e-3;

/// Longest interval the simulator advances or searches in one call, seconds.
pub const SIM_MAX_SPAN_S: f64 = 3600.0;

/// Most sub-steps [`PendulumModel::integrate`] takes in one call (longer intervals get
/// longer sub-steps).
pub const MAX_SUBSTEPS: f64 = 1e7;

/// The damped pendulum of the paper's eq. 8: `phi'' = -(g/l) sin(phi) - alpha phi'`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PendulumModel {
    /// Pivot to ball centre, metres.
    pub length_m: f64,
    /// Gravity, m/s^2.
    pub gravity_mps2: f64,
    /// Viscous damping alpha, 1/s.
    pub damping_per_s: f64,
}

impl PendulumModel {
    /// The model of a validated `[pendulum]` section.
    ///
    /// # Errors
    ///
    /// The error of [`PendulumParams::validate`] naming the first bad field.
    pub fn from_params(p: &PendulumParams) -> Result<Self, ParamError> {
        p.validate()?;
        Ok(Self {
            length_m: p.length_m,
            gravity_mps2: p.gravity_mps2,
            damping_per_s: p.damping_per_s,
        })
    }

    /// The model with a different damping (e.g. a mis-modelled truth), checked.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] when `damping_per_s` is
    /// not finite or outside -5..=5 per second.
    pub fn with_damping(self, damping_per_s: f64) -> Result<Self, ParamError> {
        check::within("pendulum.damping_per_s", damping_per_s, -5.0, 5.0)?;
        Ok(Self {
            damping_per_s,
            ..self
        })
    }

    /// `g / l`, 1/s^2 (the small-angle angular frequency squared).
    pub fn omega0_sq(&self) -> f64 {
        self.gravity_mps2 / self.length_m
    }

    /// Small-angle period `2 pi sqrt(l/g)`, seconds.
    ///
    /// ```
    /// use rt_core::pendulum::PendulumModel;
    /// // The paper's 1.93 m string swings with a period of about 2.79 s.
    /// let m = PendulumModel { length_m: 1.93, gravity_mps2: 9.81, damping_per_s: 0.0 };
    /// assert!((m.small_angle_period_s() - 2.787).abs() < 1e-3);
    /// ```
    pub fn small_angle_period_s(&self) -> f64 {
        std::f64::consts::TAU / self.omega0_sq().sqrt()
    }

    /// Angular acceleration of eq. 8 plus an external angular acceleration `accel_radps2`.
    #[inline]
    pub fn accel(&self, phi_rad: f64, rate_radps: f64, accel_radps2: f64) -> f64 {
        -self.omega0_sq() * phi_rad.sin() - self.damping_per_s * rate_radps + accel_radps2
    }

    /// One classical Runge-Kutta (RK4) step of length `h_s` with a constant external
    /// angular acceleration `accel_radps2` over the step.
    #[inline]
    pub fn rk4_step(&self, s: PendulumState, h_s: f64, accel_radps2: f64) -> PendulumState {
        let f = |x: PendulumState| Vector2::new(x[1], self.accel(x[0], x[1], accel_radps2));
        let k1 = f(s);
        let k2 = f(s + k1 * (0.5 * h_s));
        let k3 = f(s + k2 * (0.5 * h_s));
        let k4 = f(s + k3 * h_s);
        s + (k1 + (k2 + k3) * 2.0 + k4) * (h_s / 6.0)
    }

    /// Integrates `dt_s >= 0` with RK4 sub-steps no longer than `max_step_s` (and at
    /// most [`MAX_SUBSTEPS`] of them); a non-positive or NaN `dt_s` returns `s`.
    pub fn integrate(
        &self,
        mut s: PendulumState,
        dt_s: f64,
        max_step_s: f64,
        accel_radps2: f64,
    ) -> PendulumState {
        if dt_s.is_nan() || dt_s <= 0.0 || max_step_s.is_nan() || max_step_s <= 0.0 {
            return s;
        }
        let n = (dt_s / max_step_s).ceil().clamp(1.0, MAX_SUBSTEPS);
        let h = dt_s / n;
        // `n` is a small positive whole number here.
        for _ in 0..(n as u64) {
            s = self.rk4_step(s, h, accel_radps2);
        }
        s
    }

    /// Mechanical energy per unit mass and unit length squared, `phi'^2/2 + (g/l)(1 - cos phi)`,
    /// 1/s^2; constant when `damping_per_s == 0`.
    pub fn energy(&self, s: PendulumState) -> f64 {
        0.5 * s[1] * s[1] + self.omega0_sq() * (1.0 - s[0].cos())
    }
}

/// Where the pendulum hangs in the robot base frame (DESIGN.md, "Geometry of the paper's lab").
///
/// The pivot is at `(distance_m, 0, intercept_height_m + length_m)`; the ball swings in
/// the vertical plane `x = distance_m`; at rest it is at the intercept point
/// `(distance_m, 0, intercept_height_m)`. Positive `phi` moves the ball towards `+y`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PendulumGeometry {
    /// Pivot position, robot base frame, metres.
    pub pivot_m: Vector3<f64>,
    /// Pivot to ball centre, metres.
    pub length_m: f64,
}

impl PendulumGeometry {
    /// The geometry of a pendulum of length `length_m` whose ball rests at the intercept
    /// point `distance_m` in front of the robot's base axis (along +x) and
    /// `intercept_height_m` above the base.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] when the length, distance
    /// or intercept height is not finite or outside its range.
    pub fn new(
        length_m: f64,
        distance_m: f64,
        intercept_height_m: f64,
    ) -> Result<Self, ParamError> {
        check::within("pendulum.length_m", length_m, 0.1, 10.0)?;
        check::within("task.distance_m", distance_m, 0.1, 1.2)?;
        check::within("task.intercept_height_m", intercept_height_m, -0.5, 1.5)?;
        Ok(Self {
            pivot_m: Vector3::new(distance_m, 0.0, intercept_height_m + length_m),
            length_m,
        })
    }

    /// The ball's rest position (the default intercept point), base frame, metres.
    pub fn rest_position_m(&self) -> Vector3<f64> {
        self.pivot_m - Vector3::new(0.0, 0.0, self.length_m)
    }

    /// Ball centre at angle `phi_rad`, base frame, metres:
    /// `pivot + l (0, sin phi, -cos phi)`.
    #[inline]
    pub fn ball_position_m(&self, phi_rad: f64) -> Vector3<f64> {
        let (s, c) = phi_rad.sin_cos();
        self.pivot_m + Vector3::new(0.0, self.length_m * s, -self.length_m * c)
    }

    /// Ball centre velocity, base frame, m/s.
    #[inline]
    pub fn ball_velocity_mps(&self, phi_rad: f64, rate_radps: f64) -> Vector3<f64> {
        let (s, c) = phi_rad.sin_cos();
        Vector3::new(0.0, self.length_m * c, self.length_m * s) * rate_radps
    }

    /// `d(ball position)/d(phi)`, metres per radian.
    #[inline]
    pub fn position_jacobian(&self, phi_rad: f64) -> Vector3<f64> {
        let (s, c) = phi_rad.sin_cos();
        Vector3::new(0.0, self.length_m * c, self.length_m * s)
    }

    /// The lateral (base-frame y) coordinate the camera measures: `l sin(phi)`, metres.
    #[inline]
    pub fn lateral_m(&self, phi_rad: f64) -> f64 {
        self.length_m * phi_rad.sin()
    }
}

/// Errors of the ground-truth simulator.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum SimError {
    /// Time must not run backwards.
    #[error("time {asked_s} s is before the simulator's time {now_s} s")]
    TimeBackwards {
        /// The time asked for.
        asked_s: f64,
        /// The simulator's current time.
        now_s: f64,
    },
    /// One call may advance at most [`SIM_MAX_SPAN_S`].
    #[error("cannot advance {span_s} s in one call (at most 3600 s)")]
    TooFar {
        /// The span asked for.
        span_s: f64,
    },
    /// A non-finite time, angle or acceleration.
    #[error("{what} is not a finite number")]
    NotFinite {
        /// What was not finite.
        what: &'static str,
    },
}

/// Ground-truth pendulum: held by the magnet at an angle, then released from rest and
/// integrated with RK4 sub-steps of at most [`SIM_MAX_STEP_S`].
#[derive(Debug, Clone, PartialEq)]
pub struct PendulumSim {
    model: PendulumModel,
    geometry: PendulumGeometry,
    state: PendulumState,
    t_s: f64,
    held: bool,
}

impl PendulumSim {
    /// A pendulum held at rest at `angle_rad` at time `t_s` (the magnet is on).
    ///
    /// # Errors
    ///
    /// [`SimError::NotFinite`] when `angle_rad` or `t_s` is NaN or infinite.
    pub fn held_at(
        model: PendulumModel,
        geometry: PendulumGeometry,
        angle_rad: f64,
        t_s: f64,
    ) -> Result<Self, SimError> {
        if !angle_rad.is_finite() {
            return Err(SimError::NotFinite { what: "angle_rad" });
        }
        if !t_s.is_finite() {
            return Err(SimError::NotFinite { what: "t_s" });
        }
        Ok(Self {
            model,
            geometry,
            state: Vector2::new(angle_rad, 0.0),
            t_s,
            held: true,
        })
    }

    /// A free pendulum in state `state` at time `t_s`.
    ///
    /// # Errors
    ///
    /// [`SimError::NotFinite`] when `state` or `t_s` is NaN or infinite.
    pub fn free(
        model: PendulumModel,
        geometry: PendulumGeometry,
        state: PendulumState,
        t_s: f64,
    ) -> Result<Self, SimError> {
        if !state.iter().all(|v| v.is_finite()) {
            return Err(SimError::NotFinite { what: "state" });
        }
        if !t_s.is_finite() {
            return Err(SimError::NotFinite { what: "t_s" });
        }
        Ok(Self {
            model,
            geometry,
            state,
            t_s,
            held: false,
        })
    }

    /// The magnet lets go at `t_s` (>= the current time): the ball swings from rest.
    ///
    /// # Errors
    ///
    /// As [`Self::advance_to`].
    pub fn release(&mut self, t_s: f64) -> Result<(), SimError> {
        self.advance_to(t_s)?;
        self.held = false;
        Ok(())
    }

    /// Advances to `t_s` (>= the current time) with no disturbance.
    ///
    /// # Errors
    ///
    /// As [`Self::advance_to_with_accel`].
    pub fn advance_to(&mut self, t_s: f64) -> Result<(), SimError> {
        self.advance_to_with_accel(t_s, 0.0)
    }

    /// Advances to `t_s` with a constant external angular acceleration `accel_radps2`
    /// (the process noise a test wants the truth to carry).
    ///
    /// # Errors
    ///
    /// [`SimError::NotFinite`] for a non-finite `t_s` or `accel_radps2`;
    /// [`SimError::TimeBackwards`] when `t_s` is before the current time;
    /// [`SimError::TooFar`] when the step is longer than [`SIM_MAX_SPAN_S`].
    pub fn advance_to_with_accel(&mut self, t_s: f64, accel_radps2: f64) -> Result<(), SimError> {
        if !t_s.is_finite() {
            return Err(SimError::NotFinite { what: "t_s" });
        }
        if !accel_radps2.is_finite() {
            return Err(SimError::NotFinite {
                what: "accel_radps2",
            });
        }
        if t_s < self.t_s {
            return Err(SimError::TimeBackwards {
                asked_s: t_s,
                now_s: self.t_s,
            });
        }
        if t_s - self.t_s > SIM_MAX_SPAN_S {
            return Err(SimError::TooFar {
                span_s: t_s - self.t_s,
            });
        }
        if !self.held {
            self.state =
                self.model
                    .integrate(self.state, t_s - self.t_s, SIM_MAX_STEP_S, accel_radps2);
        }
        self.t_s = t_s;
        Ok(())
    }

    /// Current time, seconds.
    pub fn time_s(&self) -> f64 {
        self.t_s
    }

    /// Whether the magnet still holds the ball.
    pub fn is_held(&self) -> bool {
        self.held
    }

    /// Current `[phi_rad, phi_dot_radps]`.
    pub fn state(&self) -> PendulumState {
        self.state
    }

    /// The model being integrated.
    pub fn model(&self) -> &PendulumModel {
        &self.model
    }

    /// The geometry in the robot base frame.
    pub fn geometry(&self) -> &PendulumGeometry {
        &self.geometry
    }

    /// Ball centre now, base frame, metres.
    pub fn ball_position_m(&self) -> Vector3<f64> {
        self.geometry.ball_position_m(self.state[0])
    }

    /// Ball centre velocity now, base frame, m/s.
    pub fn ball_velocity_mps(&self) -> Vector3<f64> {
        self.geometry
            .ball_velocity_mps(self.state[0], self.state[1])
    }

    /// The lateral position `l sin(phi)` now (the camera's measurement without noise), metres.
    pub fn lateral_m(&self) -> f64 {
        self.geometry.lateral_m(self.state[0])
    }

    /// The first time after now (within `max_s` seconds) at which the ball centre passes
    /// lateral position `lateral_m` (either direction), found on a copy of the state
    /// without disturbing the simulator; accurate to well below a microsecond.
    /// `None` when the ball is held or does not get there in time.
    ///
    /// ```
    /// use rt_core::pendulum::{PendulumGeometry, PendulumModel, PendulumSim};
    /// let model = PendulumModel { length_m: 1.93, gravity_mps2: 9.81, damping_per_s: 0.0 };
    /// let geometry = PendulumGeometry::new(1.93, 0.6, 0.3).unwrap();
    /// let mut sim = PendulumSim::held_at(model, geometry, 0.2, 0.0).unwrap();
    /// // Held: it never passes.
    /// assert_eq!(sim.next_crossing_s(0.0, 10.0), None);
    /// sim.release(0.0).unwrap();
    /// // Released at 0.2 rad, it reaches the bottom a little after a quarter period.
    /// let t = sim.next_crossing_s(0.0, 10.0).unwrap();
    /// let quarter = model.small_angle_period_s() / 4.0;
    /// assert!(t > quarter && t < quarter * 1.01);
    /// ```
    pub fn next_crossing_s(&self, lateral_m: f64, max_s: f64) -> Option<f64> {
        if self.held || !lateral_m.is_finite() || max_s.is_nan() || max_s <= 0.0 {
            return None;
        }
        let g = |s: PendulumState| self.geometry.lateral_m(s[0]) - lateral_m;
        let mut s = self.state;
        let mut t = 0.0;
        let h = SIM_MAX_STEP_S;
        let mut g0 = g(s);
        let max_s = max_s.min(SIM_MAX_SPAN_S);
        while t < max_s {
            let s1 = self.model.rk4_step(s, h, 0.0);
            let g1 = g(s1);
            if g0 != 0.0 && g0.signum() != g1.signum() {
                // Bisection on the sub-step (RK4 from the left end is accurate there).
                let (mut lo, mut hi) = (0.0, h);
                for _ in 0..50 {
                    let mid = 0.5 * (lo + hi);
                    if g(self.model.rk4_step(s, mid, 0.0)).signum() == g0.signum() {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                return Some(self.t_s + t + 0.5 * (lo + hi));
            }
            s = s1;
            g0 = g1;
            t += h;
        }
        None
    }
}

#[cfg(test)]
mod tests;
