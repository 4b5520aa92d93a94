//! The timed straight-line Cartesian motion with online re-planning.

use std::f64::consts::{PI, TAU};

use nalgebra::{UnitQuaternion, Vector3};
use serde::Serialize;

use super::dynamics::{HopfDrive, SpeedDynamics, SpeedState};
use super::neurons::{Neurons, Regime};
use super::{TimingError, TimingParams};
use crate::check::ParamError;
use crate::trajectory::profile::ProfileKind;

/// Shortest motion accepted by [`TimedMotion::begin`], metres.
pub const MIN_DISTANCE_M: f64 = 1e-3;
/// Shortest duration accepted, seconds.
pub const MIN_DURATION_S: f64 = 0.05;
/// Longest duration accepted, seconds.
pub const MAX_DURATION_S: f64 = 60.0;
/// Longest step accepted by [`TimedMotion::step`], seconds.
pub const MAX_STEP_S: f64 = 0.1;
/// Largest path speed at which a new motion may begin from `Arrived`, m/s.
pub const REST_SPEED_MPS: f64 = 1e-3;

/// Where a motion is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MotionPhase {
    /// No motion yet: at rest, `u_init` selected.
    Idle,
    /// Between the interception condition and the end of the cycle.
    Moving,
    /// The cycle is done: holding the target, `u_final` selected.
    Arrived,
}

/// One sample of the motion, written by [`TimedMotion::step`] into
/// caller-owned memory (everything a plot or the control step needs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionSample {
    /// Where the motion is.
    pub phase: MotionPhase,
    /// Time since [`TimedMotion::begin`], seconds.
    pub t_s: f64,
    /// Planned arrival time since `begin`, seconds (fixed unless re-timed).
    pub arrival_time_s: f64,
    /// Commanded tool point, robot base frame, metres.
    pub position_m: Vector3<f64>,
    /// Commanded tool velocity, base frame, m/s (`path_speed_mps` along the path).
    pub velocity_mps: Vector3<f64>,
    /// Tool orientation, held for the whole motion (base from tool).
    pub orientation: UnitQuaternion<f64>,
    /// The target as last given (before smoothing), metres.
    pub target_m: Vector3<f64>,
    /// Path speed the dynamics produce (the executed command), m/s.
    pub path_speed_mps: f64,
    /// Path speed of the ideal profile for the current target, m/s.
    pub planned_path_speed_mps: f64,
    /// Path speed of the measured positions, when they are given, m/s.
    pub measured_path_speed_mps: Option<f64>,
    /// Path length covered, metres.
    pub progress_m: f64,
    /// Distance from the commanded tool point to the target, metres.
    pub remaining_m: f64,
    /// The oscillator's `a` (= path speed), m/s.
    pub a: f64,
    /// The oscillator's `b`, m/s.
    pub b: f64,
    /// Current limit-cycle radius `R_h`, m/s.
    pub radius_mps: f64,
    /// Current angular frequency `omega`, rad/s.
    pub omega_rad_per_s: f64,
    /// Oscillator phase, 0 at the start and `2 pi` at the end of the cycle, rad.
    pub phase_rad: f64,
    /// The three neuron activations.
    pub neurons: Neurons,
    /// The winning neuron's regime.
    pub regime: Regime,
    /// Integration substeps the last step used.
    pub substeps: u32,
    /// Re-plans of amplitude and frequency since `begin`.
    pub replans: u64,
}

impl Default for MotionSample {
    fn default() -> Self {
        Self {
            phase: MotionPhase::Idle,
            t_s: 0.0,
            arrival_time_s: 0.0,
            position_m: Vector3::zeros(),
            velocity_mps: Vector3::zeros(),
            orientation: UnitQuaternion::identity(),
            target_m: Vector3::zeros(),
            path_speed_mps: 0.0,
            planned_path_speed_mps: 0.0,
            measured_path_speed_mps: None,
            progress_m: 0.0,
            remaining_m: 0.0,
            a: 0.0,
            b: 0.0,
            radius_mps: 0.0,
            omega_rad_per_s: 0.0,
            phase_rad: 0.0,
            neurons: Neurons::resting(0.0),
            regime: Regime::Init,
            substeps: 0,
            replans: 0,
        }
    }
}

/// A timed straight-line Cartesian motion: from a start point to a target in a
/// fixed time, the tool orientation held, the path speed integrated from the
/// Hopf dynamics (or the minimum-jerk baseline), re-planned online so that the
/// arrival time stays fixed when the target moves or the robot lags.
///
/// Build once with [`TimedMotion::new`]; [`begin`](Self::begin) when the
/// interception condition is met; call [`step`](Self::step) once per FRI period.
/// `step` does not allocate, lock or log.
#[derive(Debug, Clone, PartialEq)]
pub struct TimedMotion {
    params: TimingParams,
    dynamics: SpeedDynamics,
    profile: ProfileKind,
    phase: MotionPhase,
    t_s: f64,
    arrival_s: f64,
    start_m: Vector3<f64>,
    target_m: Vector3<f64>,
    goal_m: Vector3<f64>,
    goal_vel_mps: Vector3<f64>,
    position_m: Vector3<f64>,
    direction: Vector3<f64>,
    orientation: UnitQuaternion<f64>,
    state: SpeedState,
    accel_mps2: f64,
    radius_mps: f64,
    nominal_radius_mps: f64,
    omega_rad_per_s: f64,
    phase_rad: f64,
    frozen: bool,
    fed_back: bool,
    schedule_tau: f64,
    lag_offset_s: f64,
    centred: bool,
    end_advance_s: f64,
    last_measured_m: Option<Vector3<f64>>,
    measured_speed_mps: Option<f64>,
    substeps: u32,
    replans: u64,
}

impl TimedMotion {
    /// An idle motion at the origin; the parameters are validated first.
    ///
    /// # Errors
    ///
    /// The error of [`TimingParams::validate`] naming the first bad field.
    pub fn new(params: TimingParams) -> Result<Self, ParamError> {
        params.validate()?;
        let dynamics = SpeedDynamics::new(&params);
        let floor = params.neuron_floor;
        Ok(Self {
            profile: params.profile,
            params,
            dynamics,
            phase: MotionPhase::Idle,
            t_s: 0.0,
            arrival_s: 0.0,
            start_m: Vector3::zeros(),
            target_m: Vector3::zeros(),
            goal_m: Vector3::zeros(),
            goal_vel_mps: Vector3::zeros(),
            position_m: Vector3::zeros(),
            direction: Vector3::x(),
            orientation: UnitQuaternion::identity(),
            state: SpeedState::resting(floor),
            accel_mps2: 0.0,
            radius_mps: 1.0,
            nominal_radius_mps: 1.0,
            omega_rad_per_s: 0.0,
            phase_rad: 0.0,
            frozen: false,
            fed_back: false,
            schedule_tau: 0.0,
            lag_offset_s: 0.0,
            centred: false,
            end_advance_s: 0.0,
            last_measured_m: None,
            measured_speed_mps: None,
            substeps: 0,
            replans: 0,
        })
    }

    /// The parameters in use.
    pub fn params(&self) -> &TimingParams {
        &self.params
    }

    /// Where the motion is.
    pub fn phase(&self) -> MotionPhase {
        self.phase
    }

    /// The commanded tool point, metres.
    pub fn position_m(&self) -> Vector3<f64> {
        self.position_m
    }

    /// Time since `begin`, seconds.
    pub fn t_s(&self) -> f64 {
        self.t_s
    }

    /// Planned arrival time since `begin`, seconds.
    pub fn arrival_time_s(&self) -> f64 {
        self.arrival_s
    }

    /// Starts a motion (the interception condition is met): from `start_m` to
    /// `target_m` in `duration_s` seconds, holding `orientation`.
    ///
    /// Refused, changing nothing, while a motion runs ([`TimingError::Busy`]),
    /// while the previous one has not come to rest, for non-finite input, a path
    /// shorter than [`MIN_DISTANCE_M`] or a duration outside
    /// [`MIN_DURATION_S`]..=[`MAX_DURATION_S`].
    ///
    /// ```
    /// use nalgebra::{UnitQuaternion, Vector3};
    /// use rt_core::timing::{MotionPhase, MotionSample, TimedMotion, TimingParams};
    /// use rt_core::trajectory::profile::ProfileKind;
    /// let mut m = TimedMotion::new(TimingParams::default()).unwrap();
    /// let (a, b) = (Vector3::new(0.4, 0.0, 0.5), Vector3::new(0.7, 0.0, 0.3));
    /// let held = UnitQuaternion::identity();
    /// // A duration outside [0.05, 60] s is refused.
    /// assert!(m.begin(&a, &b, &held, 0.0).is_err());
    /// m.begin(&a, &b, &held, 1.5).unwrap();
    /// let (mut s, mut times, mut progress) = (MotionSample::default(), vec![], vec![]);
    /// while s.phase != MotionPhase::Arrived {
    ///     m.step(0.001, None, &mut s).unwrap();
    ///     times.push(s.t_s);
    ///     progress.push((s.position_m - a).norm());
    /// }
    /// assert!((s.position_m - b).norm() < 1e-4);
    /// // The arrival (CONTRACT.md: the least-squares fit of the ideal profile).
    /// let d = (b - a).norm();
    /// let fit = rt_core::timing::fit_arrival(ProfileKind::Hopf, d, 1.5, &times, &progress).unwrap();
    /// assert!((fit.arrival_s - 1.5).abs() < 0.001);
    /// ```
    ///
    /// # Errors
    ///
    /// [`TimingError::Busy`] while a motion runs; [`TimingError::NotFinite`] for
    /// non-finite input; [`TimingError::OutOfRange`] while the previous motion has not
    /// come to rest, or for a too-short path or a duration out of range.
    pub fn begin(
        &mut self,
        start_m: &Vector3<f64>,
        target_m: &Vector3<f64>,
        orientation: &UnitQuaternion<f64>,
        duration_s: f64,
    ) -> Result<(), TimingError> {
        if self.phase == MotionPhase::Moving {
            return Err(TimingError::Busy);
        }
        if self.phase == MotionPhase::Arrived && self.state.a.abs() > REST_SPEED_MPS {
            return Err(TimingError::OutOfRange {
                what: "path speed at begin (m/s)",
                value: self.state.a,
                bound: "the previous motion must have come to rest",
            });
        }
        finite_vec("start_m", start_m)?;
        finite_vec("target_m", target_m)?;
        if !orientation.coords.iter().all(|v| v.is_finite()) {
            return Err(TimingError::NotFinite {
                what: "orientation",
            });
        }
        if !duration_s.is_finite() {
            return Err(TimingError::NotFinite { what: "duration_s" });
        }
        if !(MIN_DURATION_S..=MAX_DURATION_S).contains(&duration_s) {
            return Err(TimingError::OutOfRange {
                what: "duration_s",
                value: duration_s,
                bound: "must be in [0.05, 60] s",
            });
        }
        let delta = target_m - start_m;
        let distance = delta.norm();
        if !distance.is_finite() || distance < MIN_DISTANCE_M {
            return Err(TimingError::OutOfRange {
                what: "distance start_m -> target_m (m)",
                value: distance,
                bound: "must be finite and >= 0.001 m",
            });
        }
        self.profile = self.params.profile;
        self.phase = MotionPhase::Moving;
        self.t_s = 0.0;
        self.arrival_s = duration_s;
        self.start_m = *start_m;
        self.target_m = *target_m;
        self.goal_m = *target_m;
        self.goal_vel_mps = Vector3::zeros();
        self.position_m = *start_m;
        self.direction = delta / distance;
        self.orientation = *orientation;
        self.state.a = 0.0;
        self.state.b = 0.0;
        self.state.s = 0.0;
        self.accel_mps2 = 0.0;
        self.nominal_radius_mps = distance / duration_s;
        self.radius_mps = self.nominal_radius_mps;
        self.omega_rad_per_s = TAU / duration_s;
        self.phase_rad = 0.0;
        self.frozen = false;
        self.fed_back = false;
        self.schedule_tau = 0.0;
        self.lag_offset_s = 0.0;
        self.centred = false;
        self.end_advance_s = 0.0;
        self.last_measured_m = None;
        self.measured_speed_mps = None;
        self.replans = 0;
        Ok(())
    }

    /// Moves the target (the filter refined its prediction). The remaining path
    /// and the oscillator's amplitude are re-planned so the arrival time stays
    /// fixed; the new target is approached through a critically damped filter,
    /// so the commanded velocity stays continuous. Refused before any `begin`.
    ///
    /// # Errors
    ///
    /// [`TimingError::NotStarted`] before any `begin`; [`TimingError::NotFinite`] for a
    /// non-finite target.
    pub fn retarget(&mut self, target_m: &Vector3<f64>) -> Result<(), TimingError> {
        if self.phase == MotionPhase::Idle {
            return Err(TimingError::NotStarted);
        }
        finite_vec("target_m", target_m)?;
        if self.phase == MotionPhase::Moving {
            // A moved target rescales the path; it is not a delay: keep the
            // schedule lag continuous across the change.
            let (before, _) = self.schedule_lag(&self.target_m, self.schedule_tau);
            let (after, _) = self.schedule_lag(target_m, self.schedule_tau);
            self.lag_offset_s += before - after;
        }
        self.target_m = *target_m;
        let d = (target_m - self.start_m).norm().max(MIN_DISTANCE_M);
        self.nominal_radius_mps = d / self.arrival_s;
        Ok(())
    }

    /// Moves the planned arrival time (seconds since `begin`) while moving; it
    /// must leave at least [`MIN_DURATION_S`] from now.
    ///
    /// # Errors
    ///
    /// [`TimingError::NotStarted`] when not moving; [`TimingError::NotFinite`] for a
    /// non-finite time; [`TimingError::OutOfRange`] for a time out of range or once the
    /// motion is in its last (frozen) phase.
    pub fn retime(&mut self, arrival_time_s: f64) -> Result<(), TimingError> {
        if self.phase != MotionPhase::Moving {
            return Err(TimingError::NotStarted);
        }
        if !arrival_time_s.is_finite() {
            return Err(TimingError::NotFinite {
                what: "arrival_time_s",
            });
        }
        if arrival_time_s < self.t_s + MIN_DURATION_S || arrival_time_s > MAX_DURATION_S {
            return Err(TimingError::OutOfRange {
                what: "arrival_time_s",
                value: arrival_time_s,
                bound: "must be at least 0.05 s from now and at most 60 s",
            });
        }
        if self.frozen {
            return Err(TimingError::OutOfRange {
                what: "arrival_time_s",
                value: arrival_time_s,
                bound: "the motion is in its last phase and can no longer be re-timed",
            });
        }
        self.arrival_s = arrival_time_s;
        let d = (self.target_m - self.start_m).norm().max(MIN_DISTANCE_M);
        self.nominal_radius_mps = d / arrival_time_s;
        Ok(())
    }

    /// Back to idle at `position_m` (an abort or a new session); refused for
    /// non-finite input.
    ///
    /// # Errors
    ///
    /// [`TimingError::NotFinite`] when `position_m` has a NaN or infinite coordinate.
    pub fn reset(&mut self, position_m: &Vector3<f64>) -> Result<(), TimingError> {
        finite_vec("position_m", position_m)?;
        let floor = self.dynamics.neuron_floor();
        self.phase = MotionPhase::Idle;
        self.t_s = 0.0;
        self.arrival_s = 0.0;
        self.position_m = *position_m;
        self.start_m = *position_m;
        self.target_m = *position_m;
        self.goal_m = *position_m;
        self.goal_vel_mps = Vector3::zeros();
        self.state = SpeedState::resting(floor);
        self.accel_mps2 = 0.0;
        self.phase_rad = 0.0;
        self.omega_rad_per_s = 0.0;
        self.last_measured_m = None;
        self.measured_speed_mps = None;
        Ok(())
    }

    /// Advances by `dt_s` seconds (one FRI period, 1..10 ms typically) and
    /// writes the new sample into `out`.
    ///
    /// `measured_m`, when given, is where the robot's tool point actually is,
    /// already compensated for the command-to-motion latency (comparable with
    /// the command). While moving, the command is pulled towards it at
    /// `progress_feedback_per_s`, and the remaining path is re-planned from
    /// there so that the arrival time stays fixed (temporal stabilisation).
    ///
    /// A `dt_s` that is not finite, not positive or above [`MAX_STEP_S`], or a
    /// non-finite measurement, is refused and changes nothing.
    ///
    /// # Errors
    ///
    /// [`TimingError::NotFinite`] for a non-finite `dt_s` or measurement;
    /// [`TimingError::OutOfRange`] for a `dt_s` that is not positive or above [`MAX_STEP_S`].
    pub fn step(
        &mut self,
        dt_s: f64,
        measured_m: Option<&Vector3<f64>>,
        out: &mut MotionSample,
    ) -> Result<(), TimingError> {
        if !dt_s.is_finite() {
            return Err(TimingError::NotFinite { what: "dt_s" });
        }
        if !(dt_s > 0.0 && dt_s <= MAX_STEP_S) {
            return Err(TimingError::OutOfRange {
                what: "dt_s",
                value: dt_s,
                bound: "must be in (0, 0.1] s",
            });
        }
        if let Some(m) = measured_m {
            finite_vec("measured_m", m)?;
        }
        if let Some(m) = measured_m {
            self.measured_speed_mps = self
                .last_measured_m
                .map(|last| (m - last).dot(&self.direction) / dt_s);
            self.last_measured_m = Some(*m);
            if self.phase == MotionPhase::Moving && self.params.progress_feedback_per_s > 0.0 {
                self.fed_back = true;
                let k = 1.0 - (-self.params.progress_feedback_per_s * dt_s).exp();
                let d = (m - self.position_m) * k;
                self.state.s += d.dot(&self.direction);
                self.position_m += d;
            }
        } else {
            self.measured_speed_mps = None;
        }
        let n = (dt_s / self.params.max_substep_s)
            .ceil()
            .clamp(1.0, 10_000.0);
        let h = dt_s / n;
        // n is a small whole number (at most 10_000), so the cast is exact.
        let n = n as u32;
        for _ in 0..n {
            self.substep(h);
        }
        self.substeps = n;
        self.sample(out);
        Ok(())
    }

    /// Writes the current sample into `out` without advancing.
    pub fn sample(&self, out: &mut MotionSample) {
        let remaining = (self.target_m - self.position_m).norm();
        let planned = if self.phase == MotionPhase::Idle || self.arrival_s <= 0.0 {
            0.0
        } else {
            let d = (self.target_m - self.start_m).norm();
            self.profile.velocity(self.t_s / self.arrival_s) * d / self.arrival_s
        };
        *out = MotionSample {
            phase: self.phase,
            t_s: self.t_s,
            arrival_time_s: self.arrival_s,
            position_m: self.position_m,
            velocity_mps: self.direction * self.state.a,
            orientation: self.orientation,
            target_m: self.target_m,
            path_speed_mps: self.state.a,
            planned_path_speed_mps: planned,
            measured_path_speed_mps: self.measured_speed_mps,
            progress_m: self.state.s,
            remaining_m: remaining,
            a: self.state.a,
            b: self.state.b,
            radius_mps: self.radius_mps,
            omega_rad_per_s: self.omega_rad_per_s,
            phase_rad: self.phase_rad,
            neurons: self.state.neurons,
            regime: self.state.neurons.winner(),
            substeps: self.substeps,
            replans: self.replans,
        };
    }

    /// The oscillator phase from the state, unwrapped against the last one.
    ///
    /// On the cycle `a = R_h (1 - cos phi)` and `b = -R_h sin phi`, so
    /// `phi = 2 atan2(a, -b)` whatever `R_h`: re-planning `R_h` does not move
    /// the phase it is computed from (with the centre-relative angle
    /// `atan2(-b, R_h - a)` the re-plan feeds back on itself and diverges late
    /// in the cycle).
    fn oscillator_phase(&self) -> f64 {
        let raw = 2.0 * self.state.a.atan2(-self.state.b);
        let d = raw - self.phase_rad;
        self.phase_rad + (d - TAU * (d / TAU).round())
    }

    /// One integration substep of `h` seconds.
    fn substep(&mut self, h: f64) {
        // The target passes through a critically damped second-order filter.
        if self.params.target_smoothing_s > 0.0 {
            let wn = 1.0 / self.params.target_smoothing_s;
            let acc = wn * wn * (self.target_m - self.goal_m) - 2.0 * wn * self.goal_vel_mps;
            self.goal_vel_mps += acc * h;
            self.goal_m += self.goal_vel_mps * h;
        } else {
            self.goal_m = self.target_m;
        }
        let to_goal = self.goal_m - self.position_m;
        let remaining = to_goal.norm();
        if remaining > 1e-12 {
            self.direction = to_goal / remaining;
        }
        let s_old = self.state.s;
        match self.phase {
            MotionPhase::Idle => {
                let drive = HopfDrive {
                    radius_mps: 1.0,
                    omega_rad_per_s: 0.0,
                    remaining_m: 0.0,
                    regime: Regime::Init,
                };
                self.dynamics.step(&mut self.state, h, &drive);
                self.state.a = 0.0;
                self.state.b = 0.0;
                self.state.s = s_old;
                return;
            }
            MotionPhase::Moving => match self.profile {
                ProfileKind::Hopf => self.hopf_substep(h, remaining),
                ProfileKind::MinJerk => self.min_jerk_substep(h, remaining),
            },
            MotionPhase::Arrived => {
                let drive = HopfDrive {
                    radius_mps: self.radius_mps,
                    omega_rad_per_s: self.omega_rad_per_s,
                    remaining_m: remaining,
                    regime: Regime::Final,
                };
                self.dynamics.step(&mut self.state, h, &drive);
                self.t_s += h;
            }
        }
        let mut ds = self.state.s - s_old;
        if ds > remaining {
            ds = remaining;
            self.state.s = s_old + ds;
        }
        self.position_m += self.direction * ds;
    }

    /// Back on schedule soon, not only at the end: while the motion lags its
    /// ideal schedule (the profile's closed form, centred after the neurons'
    /// hand-over) by `lag`, its end is planned `schedule_gain * lag` earlier,
    /// faded out over the second half of the motion so that it still ends at
    /// `t_end`. Returns the end time to plan for.
    fn schedule_end(&mut self, t_end: f64) -> f64 {
        let gain = self.params.schedule_gain;
        let ready = self.centred || self.profile == ProfileKind::MinJerk;
        // Only measurements reveal lost progress; without them the plan is
        // only rescaled.
        if gain <= 0.0 || !ready || self.frozen || !self.fed_back {
            return t_end;
        }
        let (lag, tau) = self.schedule_lag(&self.target_m, self.schedule_tau);
        self.schedule_tau = tau;
        let lag = (lag + self.lag_offset_s).clamp(-0.1, 0.1);
        let fade = ((TAU - self.params.replan_freeze_rad - self.phase_rad) / PI).clamp(0.0, 1.0);
        // Never squeeze or stretch what is left by more than a quarter.
        let left = t_end - self.t_s;
        (t_end - gain * fade * lag).clamp(t_end - 0.25 * left, t_end + 0.25 * left)
    }

    /// How far the motion lags its schedule towards `target`, seconds, with
    /// the schedule position `tau` found from `guess`: the fraction done
    /// `s / (s + |target - p|)` is where the centred ideal profile was at
    /// `t - lag`.
    fn schedule_lag(&self, target: &Vector3<f64>, guess: f64) -> (f64, f64) {
        let done = self.state.s.max(0.0);
        let total = done + (target - self.position_m).norm();
        if total <= 0.0 {
            return (0.0, guess);
        }
        let tau = inverse_position(self.profile, done / total, guess);
        let d0 = self.end_advance_s;
        let on_schedule = d0 + (self.arrival_s - 2.0 * d0) * tau;
        (self.t_s - on_schedule, tau)
    }

    fn hopf_substep(&mut self, h: f64, remaining: f64) {
        // The neurons hand over in a few tau_u, during which the cycle barely
        // runs: once u_hopf has taken over, the cycle is `delay` behind the
        // ideal one, and the rest is planned to end `delay` early so that the
        // profile stays centred on the ideal (CONTRACT's arrival is a
        // least-squares fit over the whole motion).
        if !self.centred && self.dynamics.weight(self.state.neurons.u_hopf) > 0.999 {
            let (t, phi) = (self.t_s, self.phase_rad);
            let delay = (TAU * t - phi * self.arrival_s) / (TAU - 2.0 * phi);
            self.end_advance_s = if delay.is_finite() {
                delay.clamp(0.0, 0.1 * self.arrival_s)
            } else {
                0.0
            };
            self.centred = true;
        }
        let t_end = self.arrival_s - self.end_advance_s;
        let t_plan = self.schedule_end(t_end);
        let t_rem = t_plan - self.t_s;
        if !self.frozen && t_rem > h {
            match replan(self.state.a, remaining, t_rem, self.phase_rad) {
                Some(phi) if TAU - phi > self.params.replan_freeze_rad => {
                    let w_nom = TAU / self.arrival_s;
                    self.omega_rad_per_s = ((TAU - phi) / t_rem).clamp(0.5 * w_nom, 2.0 * w_nom);
                    let one_minus_cos = 2.0 * (0.5 * phi).sin().powi(2);
                    let r = if self.state.a > 0.0 && one_minus_cos > 0.0 {
                        self.state.a / one_minus_cos
                    } else {
                        remaining / t_rem
                    };
                    self.radius_mps =
                        r.clamp(0.1 * self.nominal_radius_mps, 4.0 * self.nominal_radius_mps);
                    // Put the auxiliary variable on the re-planned cycle at the
                    // phase the path speed `a` has on it; `a` is not touched.
                    self.state.b = -self.radius_mps * phi.sin();
                    self.phase_rad = phi;
                    self.replans += 1;
                }
                Some(_) => self.frozen = true,
                // No cosine from this speed fits the distance left (the target
                // came closer): keep the cycle and try again next substep.
                None => {}
            }
        } else {
            self.frozen = true;
        }
        let phi = self.phase_rad;
        let drive = HopfDrive {
            radius_mps: self.radius_mps,
            omega_rad_per_s: self.omega_rad_per_s,
            remaining_m: remaining,
            regime: Regime::Hopf,
        };
        self.dynamics.step(&mut self.state, h, &drive);
        self.t_s += h;
        self.phase_rad = self.oscillator_phase().max(phi);
        if self.phase_rad >= TAU || self.t_s >= t_end - 1e-9 {
            self.phase = MotionPhase::Arrived;
        }
    }

    fn min_jerk_substep(&mut self, h: f64, remaining: f64) {
        let t_end = self.arrival_s;
        let t_rem = self.schedule_end(t_end) - self.t_s;
        let s_old = self.state.s;
        let (ds, v, acc, last) = if t_end - self.t_s <= h * (1.0 + 1e-9) {
            (remaining, 0.0, 0.0, true)
        } else {
            let (ds, v, acc) = quintic_step(remaining, self.state.a, self.accel_mps2, t_rem, h);
            (ds, v, acc, false)
        };
        // The neurons still mark the regime; the path speed is the quintic's.
        let drive = HopfDrive {
            radius_mps: self.radius_mps,
            omega_rad_per_s: self.omega_rad_per_s,
            remaining_m: remaining,
            regime: Regime::Hopf,
        };
        self.dynamics.step(&mut self.state, h, &drive);
        self.state.a = v;
        self.state.b = 0.0;
        self.state.s = s_old + ds;
        self.accel_mps2 = acc;
        self.t_s += h;
        self.phase_rad = TAU * (self.t_s / self.arrival_s).min(1.0);
        self.replans += 1;
        if last {
            self.phase = MotionPhase::Arrived;
        }
    }
}

/// The phase `phi` in `(0, 2 pi)` of the cycle that, from the path speed `a`
/// now, covers `remaining` metres in exactly `t_rem` seconds and ends at rest:
/// `a = R_h (1 - cos phi)`, `remaining = (R_h / omega) ((2 pi - phi) + sin phi)`,
/// `omega = (2 pi - phi) / t_rem`. Eliminating `R_h` and `omega` leaves
/// `g(phi) = remaining / (a t_rem) = q` with `g` falling from infinity
/// (phi -> 0) to 1/3 (phi -> 2 pi). Solved as the rising root of
/// `q (1 - cos phi)(2 pi - phi) - (2 pi - phi + sin phi)` by Newton from
/// `guess` (the last phase), with bisection as the safeguard. `None` when no
/// such cycle exists (the path speed is already too high for the distance left).
fn replan(a: f64, remaining: f64, t_rem: f64, guess: f64) -> Option<f64> {
    if a <= 0.0 {
        return Some(0.0);
    }
    let q = remaining / (a * t_rem);
    if !q.is_finite() || q <= 1.0 / 3.0 {
        return None;
    }
    let k = |phi: f64| {
        let (sin, cos) = phi.sin_cos();
        let m = 1.0 - cos;
        let p = TAU - phi;
        let y = q * m * p - (p + sin);
        let dy = q * (sin * p - m) + m;
        (y, dy)
    };
    Some(rising_root(0.0, TAU * (1.0 - 1e-9), guess, k))
}

/// `tau` in `[0, 1]` with `kind.position(tau) = f` (both shapes rise
/// monotonically), by Newton from `guess` with bisection as the safeguard.
fn inverse_position(kind: ProfileKind, f: f64, guess: f64) -> f64 {
    let f = f.clamp(0.0, 1.0);
    rising_root(0.0, 1.0, guess, |tau| {
        (kind.position(tau) - f, kind.velocity(tau))
    })
}

/// The root of `f` (returning value and derivative) on `[lo, hi]`, where `f`
/// is negative below the root and positive above it: Newton steps from `x0`,
/// bisection whenever a step leaves the bracket; at most 60 iterations.
fn rising_root(mut lo: f64, mut hi: f64, x0: f64, f: impl Fn(f64) -> (f64, f64)) -> f64 {
    let mut x = if x0.is_finite() {
        x0.clamp(lo, hi)
    } else {
        0.5 * (lo + hi)
    };
    for _ in 0..60 {
        let (y, dy) = f(x);
        if y == 0.0 {
            return x;
        }
        if y < 0.0 {
            lo = x;
        } else {
            hi = x;
        }
        let newton = x - y / dy;
        let next = if dy > 0.0 && newton > lo && newton < hi {
            newton
        } else {
            0.5 * (lo + hi)
        };
        if (next - x).abs() <= 1e-14 * (1.0 + x.abs()) || hi - lo <= 1e-14 {
            return next;
        }
        x = next;
    }
    x
}

/// The minimum-jerk quintic from `(0, v0, a0)` to `(l, 0, 0)` in `t` seconds
/// (Flash and Hogan; re-planned each step as in Hoff and Arbib), evaluated at
/// `h`: `(distance, speed, acceleration)`.
fn quintic_step(l: f64, v0: f64, a0: f64, t: f64, h: f64) -> (f64, f64, f64) {
    let c1 = v0;
    let c2 = 0.5 * a0;
    let c3 = (20.0 * l - 12.0 * v0 * t - 3.0 * a0 * t * t) / (2.0 * t.powi(3));
    let c4 = (-30.0 * l + 16.0 * v0 * t + 3.0 * a0 * t * t) / (2.0 * t.powi(4));
    let c5 = (12.0 * l - 6.0 * v0 * t - a0 * t * t) / (2.0 * t.powi(5));
    let x = h * (c1 + h * (c2 + h * (c3 + h * (c4 + h * c5))));
    let v = c1 + h * (2.0 * c2 + h * (3.0 * c3 + h * (4.0 * c4 + h * 5.0 * c5)));
    let a = 2.0 * c2 + h * (6.0 * c3 + h * (12.0 * c4 + h * 20.0 * c5));
    (x, v, a)
}

fn finite_vec(what: &'static str, v: &Vector3<f64>) -> Result<(), TimingError> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(TimingError::NotFinite { what })
    }
}

#[cfg(test)]
mod quintic_tests {
    use super::quintic_step;

    #[test]
    fn quintic_lands_on_the_target_at_rest() {
        let (x, v, a) = quintic_step(0.7, 0.3, -0.2, 0.8, 0.8);
        assert!((x - 0.7).abs() < 1e-12 && v.abs() < 1e-12 && a.abs() < 1e-12);
        let (x, v, a) = quintic_step(0.7, 0.3, -0.2, 0.8, 0.0);
        assert!(x.abs() < 1e-15 && (v - 0.3).abs() < 1e-15 && (a + 0.2).abs() < 1e-15);
    }
}

#[cfg(test)]
mod root_tests {
    use super::*;

    #[test]
    fn replan_recovers_the_phase_of_an_ideal_cycle() {
        // On the ideal cycle (R = 0.5, T = 1.5): a, L and t_rem at phase phi.
        let (r, t) = (0.5, 1.5);
        let w = TAU / t;
        for i in 1..60 {
            let phi = TAU * f64::from(i) / 61.0;
            let a = r * (1.0 - phi.cos());
            let left = r / w * ((TAU - phi) + phi.sin());
            let t_rem = (TAU - phi) / w;
            for guess in [0.0, phi, TAU] {
                let got = replan(a, left, t_rem, guess).unwrap();
                assert!((got - phi).abs() < 1e-9, "{phi} from {guess}: {got}");
            }
        }
        assert_eq!(replan(0.3, 0.01, 1.0, 1.0), None);
    }

    #[test]
    fn inverse_position_inverts_both_shapes() {
        for kind in [ProfileKind::Hopf, ProfileKind::MinJerk] {
            for i in 0..=100 {
                let tau = f64::from(i) / 100.0;
                let f = kind.position(tau);
                for guess in [0.0, 0.5, 1.0] {
                    let got = inverse_position(kind, f, guess);
                    assert!((kind.position(got) - f).abs() < 1e-12, "{kind:?} {tau}");
                }
            }
        }
    }
}
