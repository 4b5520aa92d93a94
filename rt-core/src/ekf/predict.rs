//! The predictor: future states, crossing times and motion start times, computed
//! from the current posterior without disturbing the filter.

use nalgebra::Vector3;

use super::model::{self, StateCov, StateVec};
use super::{Ekf, EkfError, Phase, finite};

/// Most passes [`Ekf::plan_motion`] looks through (`pass_index < MAX_PLAN_PASSES`).
pub const MAX_PLAN_PASSES: usize = 8;

/// The predicted pendulum at one time.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Prediction {
    /// Time of the prediction, seconds.
    pub t_s: f64,
    /// `[phi_rad, phi_dot_radps, alpha_per_s, k_per_s2, b_m]`.
    pub state: StateVec,
    /// Covariance of `state`.
    pub cov: StateCov,
    /// Lateral position `l sin(phi)` (base-frame y), metres.
    pub lateral_m: f64,
    /// Standard deviation of `lateral_m`, metres.
    pub lateral_std_m: f64,
    /// Ball centre, robot base frame, metres.
    pub ball_m: Vector3<f64>,
    /// Standard deviation of each coordinate of `ball_m` (first order), metres.
    pub ball_std_m: Vector3<f64>,
    /// Ball centre velocity, robot base frame, m/s.
    pub ball_velocity_mps: Vector3<f64>,
}

/// Which passes through a lateral position count.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PassDirection {
    /// Both directions.
    #[default]
    Any,
    /// Only passes moving towards +y.
    TowardsPositiveY,
    /// Only passes moving towards -y.
    TowardsNegativeY,
}

/// A predicted pass of the ball centre through a lateral position.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Crossing {
    /// Predicted time of the pass, seconds.
    pub t_s: f64,
    /// Standard deviation of `t_s` (first order: lateral std / lateral speed), seconds.
    pub time_std_s: f64,
    /// Lateral (y) velocity at the pass, m/s (its sign is the direction).
    pub lateral_velocity_mps: f64,
    /// Ball centre at the pass, robot base frame, metres.
    pub ball_m: Vector3<f64>,
    /// Ball centre velocity at the pass, robot base frame, m/s.
    pub ball_velocity_mps: Vector3<f64>,
    /// Predicted `[phi, phi', alpha, k, b]` at the pass.
    pub state: StateVec,
}

/// A motion that must meet the ball at a pass.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionRequest {
    /// Lateral position of the meeting point (0: the bottom, the default intercept), metres.
    pub lateral_m: f64,
    /// Duration of the motion, seconds.
    pub duration_s: f64,
    /// Expected delay from command to motion, seconds.
    pub latency_s: f64,
    /// Which reachable pass: 0 = the first one the motion can still meet.
    pub pass_index: usize,
    /// Which passes count.
    pub direction: PassDirection,
}

/// Why a plan is not confident enough to commit to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Doubt {
    /// Confident.
    None,
    /// The filter has not observed the ball for `min_observation_s` yet.
    ShortObservation,
    /// No measurement fused within `max_measurement_age_s`.
    StaleMeasurement,
    /// The newest measurement was rejected as an outlier.
    Rejecting,
    /// The pass time's standard deviation exceeds `commit_max_time_std_ms`.
    Uncertain,
}

/// When to start a motion to meet a pass.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionPlan {
    /// The pass to meet.
    pub pass: Crossing,
    /// When the motion command must start: `pass.t_s - duration_s - latency_s`.
    pub start_s: f64,
    /// `start_s - now`: time left before the command must start (>= 0).
    pub slack_s: f64,
    /// Whether the prediction is good enough to commit to.
    pub confident: bool,
    /// Why not, when not.
    pub doubt: Doubt,
}

impl Ekf {
    fn posterior_or_err(&self) -> Result<(f64, StateVec, StateCov), EkfError> {
        if self.phase != Phase::Running {
            return Err(EkfError::NotInitialised);
        }
        self.posterior().ok_or(EkfError::NotInitialised)
    }

    fn check_span(&self, what: &'static str, dt: f64) -> Result<(), EkfError> {
        if dt.abs() > 2.0 * self.params.horizon_s {
            return Err(EkfError::OutOfRange {
                what,
                value: dt,
                bound: "must be within twice the horizon of the last measurement",
            });
        }
        Ok(())
    }

    fn fill_prediction(&self, t_s: f64, x: &StateVec, p: &StateCov, out: &mut Prediction) {
        let g = &self.geometry;
        let jac = g.position_jacobian(x[0]);
        let var_phi = p[(0, 0)].max(0.0);
        out.t_s = t_s;
        out.state = *x;
        out.cov = *p;
        // What the camera would measure: the model's lateral plus the estimated
        // rest offset `b` (0 unless `estimate_offset`).
        let (z, c) = model::measure(g.length_m, x);
        out.lateral_m = z;
        out.lateral_std_m = (c * p * c.transpose())[0].max(0.0).sqrt();
        out.ball_m = g.ball_position_m(x[0]);
        out.ball_std_m = jac.abs() * var_phi.sqrt();
        out.ball_velocity_mps = g.ball_velocity_mps(x[0], x[1]);
    }

    /// The predicted state, ball position and their uncertainty at `t_s` (within twice
    /// `horizon_s` of the last measurement), written into `out`.
    ///
    /// # Errors
    ///
    /// [`EkfError::NotFinite`] for a non-finite `t_s`; [`EkfError::NotInitialised`]
    /// before the filter runs; [`EkfError::OutOfRange`] when `t_s` is more than twice
    /// `horizon_s` from the last measurement.
    pub fn predict_at(&self, t_s: f64, out: &mut Prediction) -> Result<(), EkfError> {
        finite("t_s", t_s)?;
        let (t0, x0, p0) = self.posterior_or_err()?;
        self.check_span("t_s", t_s - t0)?;
        let (x, p) = self.propagate(&x0, &p0, t_s - t0);
        self.fill_prediction(t_s, &x, &p, out);
        Ok(())
    }

    /// Predictions at `t_start_s + i step_s` for each slot of `out` (the dashboard's
    /// horizon; the paper shows 300 steps); returns how many were filled (fewer when
    /// the span passes twice the horizon).
    ///
    /// # Errors
    ///
    /// [`EkfError::NotFinite`] for non-finite input; [`EkfError::OutOfRange`] for a
    /// `step_s` that is not `> 0` or a start more than twice `horizon_s` from the last
    /// measurement; [`EkfError::NotInitialised`] before the filter runs.
    pub fn predict_horizon(
        &self,
        t_start_s: f64,
        step_s: f64,
        out: &mut [Prediction],
    ) -> Result<usize, EkfError> {
        finite("t_start_s", t_start_s)?;
        finite("step_s", step_s)?;
        if step_s.is_nan() || step_s <= 0.0 {
            return Err(EkfError::OutOfRange {
                what: "step_s",
                value: step_s,
                bound: "must be > 0",
            });
        }
        let (t0, x0, p0) = self.posterior_or_err()?;
        self.check_span("t_start_s", t_start_s - t0)?;
        let (mut x, mut p) = self.propagate(&x0, &p0, t_start_s - t0);
        let limit = t0 + 2.0 * self.params.horizon_s;
        let mut n = 0;
        for (i, slot) in out.iter_mut().enumerate() {
            let t = t_start_s + i as f64 * step_s;
            if t > limit {
                break;
            }
            if i > 0 {
                (x, p) = self.propagate(&x, &p, step_s);
            }
            self.fill_prediction(t, &x, &p, slot);
            n += 1;
        }
        Ok(n)
    }

    /// The next passes of the ball centre through lateral position `lateral_m`
    /// (`|lateral_m| < l`; relative to the estimated rest point, i.e. `l sin(phi)`
    /// without the offset `b`: 0 is the bottom) at or after `t_from_s`, up to `horizon_s` after it, written
    /// into `out` in time order; returns how many were found (at most `out.len()`).
    ///
    /// # Errors
    ///
    /// [`EkfError::NotFinite`] for non-finite input; [`EkfError::OutOfRange`] when
    /// `|lateral_m|` reaches the length or `t_from_s` is more than twice `horizon_s`
    /// from the last measurement; [`EkfError::NotInitialised`] before the filter runs.
    pub fn crossings(
        &self,
        t_from_s: f64,
        lateral_m: f64,
        direction: PassDirection,
        out: &mut [Crossing],
    ) -> Result<usize, EkfError> {
        finite("t_from_s", t_from_s)?;
        finite("lateral_m", lateral_m)?;
        if lateral_m.abs() >= self.model.length_m {
            return Err(EkfError::OutOfRange {
                what: "lateral_m",
                value: lateral_m,
                bound: "must be inside the pendulum's length",
            });
        }
        let (t0, x0, p0) = self.posterior_or_err()?;
        self.check_span("t_from_s", t_from_s - t0)?;
        if out.is_empty() {
            return Ok(0);
        }
        let l = self.model.length_m;
        let pm = self.params.process_model;
        let gfun = |x: &StateVec| l * x[0].sin() - lateral_m;
        let h = self.params.max_step_s;
        let q = self.q(h);
        let t_end = t_from_s.max(t0) + self.params.horizon_s;
        let (mut x, mut p, mut t) = (x0, p0, t0);
        let mut g0 = gfun(&x);
        let mut n = 0;
        while t < t_end && n < out.len() {
            let (x1, f) = model::step(pm, &x, h);
            let g1 = gfun(&x1);
            if (g0 < 0.0) != (g1 < 0.0) {
                // Newton on the sub-step length, from a linear guess.
                let mut tau = if g0 == g1 {
                    0.5 * h
                } else {
                    h * g0 / (g0 - g1)
                };
                for _ in 0..4 {
                    let (xt, _) = model::step(pm, &x, tau);
                    let dg = l * xt[0].cos() * xt[1];
                    if dg == 0.0 || !dg.is_finite() {
                        break;
                    }
                    tau = (tau - gfun(&xt) / dg).clamp(0.0, h);
                }
                let tc = t + tau;
                let (xc, fc) = model::step(pm, &x, tau);
                let vy = l * xc[0].cos() * xc[1];
                let wanted = match direction {
                    PassDirection::Any => true,
                    PassDirection::TowardsPositiveY => vy > 0.0,
                    PassDirection::TowardsNegativeY => vy < 0.0,
                };
                if tc >= t_from_s && wanted {
                    let pc = model::carry_cov(&fc, &p) + self.q(tau);
                    let cy = l * xc[0].cos();
                    let var_y = cy * cy * pc[(0, 0)].max(0.0);
                    let time_std_s = if vy == 0.0 {
                        f64::INFINITY
                    } else {
                        var_y.sqrt() / vy.abs()
                    };
                    out[n] = Crossing {
                        t_s: tc,
                        time_std_s,
                        lateral_velocity_mps: vy,
                        ball_m: self.geometry.ball_position_m(xc[0]),
                        ball_velocity_mps: self.geometry.ball_velocity_mps(xc[0], xc[1]),
                        state: xc,
                    };
                    n += 1;
                }
            }
            p = model::carry_cov(&f, &p) + q;
            x = x1;
            t += h;
            g0 = g1;
        }
        Ok(n)
    }

    /// When a motion of `req.duration_s` (plus `req.latency_s`) must start, at time
    /// `now_s`, to meet pass `req.pass_index` among those it can still reach, and
    /// whether the prediction is confident enough to commit. `Ok(None)` when no such
    /// pass lies within the horizon.
    ///
    /// # Errors
    ///
    /// [`EkfError::NotFinite`] for non-finite input; [`EkfError::OutOfRange`] for a
    /// negative duration or latency, a `pass_index` of 8 or more, or as
    /// [`Self::crossings`]; [`EkfError::NotInitialised`] before the filter runs.
    pub fn plan_motion(
        &self,
        now_s: f64,
        req: &MotionRequest,
    ) -> Result<Option<MotionPlan>, EkfError> {
        finite("now_s", now_s)?;
        finite("duration_s", req.duration_s)?;
        finite("latency_s", req.latency_s)?;
        if req.duration_s < 0.0 || req.latency_s < 0.0 {
            return Err(EkfError::OutOfRange {
                what: if req.duration_s < 0.0 {
                    "duration_s"
                } else {
                    "latency_s"
                },
                value: req.duration_s.min(req.latency_s),
                bound: "must be >= 0",
            });
        }
        if req.pass_index >= MAX_PLAN_PASSES {
            return Err(EkfError::OutOfRange {
                what: "pass_index",
                value: req.pass_index as f64,
                bound: "must be < 8",
            });
        }
        let lead = req.duration_s + req.latency_s;
        let mut buf = [Crossing::default(); MAX_PLAN_PASSES];
        let n = self.crossings(
            now_s + lead,
            req.lateral_m,
            req.direction,
            &mut buf[..=req.pass_index],
        )?;
        if n <= req.pass_index {
            return Ok(None);
        }
        let pass = buf[req.pass_index];
        let start_s = pass.t_s - lead;
        let doubt = if now_s - self.t_init < self.params.min_observation_s {
            Doubt::ShortObservation
        } else if now_s - self.t_last_fused > self.params.max_measurement_age_s {
            Doubt::StaleMeasurement
        } else if self.consecutive_rejections > 0 {
            Doubt::Rejecting
        } else if pass.time_std_s.is_nan()
            || pass.time_std_s * 1e3 > self.params.commit_max_time_std_ms
        {
            Doubt::Uncertain
        } else {
            Doubt::None
        };
        Ok(Some(MotionPlan {
            pass,
            start_s,
            slack_s: start_s - now_s,
            confident: doubt == Doubt::None,
            doubt,
        }))
    }
}
