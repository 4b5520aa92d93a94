//! The control step: called once per FRI message, it folds in the newest camera
//! measurements, runs the filter, checks the interception condition, steps the
//! timed motion, maps it through inverse kinematics in the planned posture,
//! guards the command and returns it. No allocation, no lock, no log: what
//! happens is counted in [`ControlCounters`].

use nalgebra::{UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::beliefs::Beliefs;
use super::latency::LatencyEstimator;
use super::measured::ARRIVAL_SETTLE_M;
use super::rebound::PredictedRebound;
use super::state::{AbortReason, TrialMachine, TrialState};
use crate::check::{self, ParamError};
use crate::ekf::{Ekf, EkfCounters, EkfError, EkfParams, MotionRequest, PassDirection, StateVec};
use crate::kinematics::iiwa7::{
    ACCELERATION_LIMIT_RADPS2, JOINTS, POSITION_LIMIT_RAD, VELOCITY_LIMIT_RADPS,
};
use crate::kinematics::{Joints, Tool, tool_pose};
use crate::pendulum::{PendulumGeometry, PendulumModel};
use crate::timing::TimingError;
use crate::timing::{MotionPhase, MotionSample, TimedMotion, TimingParams};
use crate::trajectory::profile::ProfileKind;
use crate::trajectory::strike::{
    CONTACT_PHASES, STRIKE_RETURN_SIGN, STRIKE_TOOL_MASS_KG, StrikeError, StrikeRefusal, Stroke,
    SwingClearance, plan_strike, strike_direction,
};
use crate::trajectory::{
    Infeasibility, MotionRequest as PathRequest, PlanError, Posture, TaskMode, TrajectoryParams,
};

/// The closed loop's settings: `[control]` in a scenario.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ControlParams {
    /// Shortest duration of the joint-space move to home when arming, seconds.
    pub home_move_time_s: f64,
    /// How long the arm holds the intercept point after arriving, seconds.
    pub hold_time_s: f64,
    /// Abort when no pass has been committed to this long after release, seconds.
    pub track_timeout_s: f64,
    /// Abort when no camera measurement arrived for this long while tracking, seconds
    /// (longer than the ball spends outside the image at the ends of a long swing).
    pub camera_timeout_s: f64,
    /// Latency assumed until the online estimate is confident, milliseconds.
    pub latency_prior_ms: f64,
    /// Memory of the latency estimate, seconds of motion.
    pub latency_memory_s: f64,
    /// Joint position margin the planned motion keeps, degrees.
    pub posture_margin_deg: f64,
    /// Largest joint speed of a planned motion as a fraction of the limit.
    pub max_speed_ratio: f64,
    /// Take the shortest feasible duration when the asked one is too fast
    /// (otherwise refuse the motion).
    pub allow_shortest_feasible: bool,
    /// Margin the command guard keeps from the joint position limits, degrees.
    pub guard_margin_deg: f64,
    /// Largest commanded joint step per period as a fraction of the speed limit.
    pub guard_speed_ratio: f64,
    /// Follow the filter's refined pass time while the motion runs (trades the
    /// constancy of the movement time for arrival accuracy; off by default: the
    /// commit threshold already bounds the pass-time uncertainty).
    pub retime: bool,
    /// How arrival is judged: 0 = the end of the best-fitting ideal profile
    /// (CONTRACT.md's fitted arrival); > 0 = the tool settling within this
    /// distance of its final point (the reality lab's physical judge, 0.002).
    /// The motion is timed so that this arrival meets the ball's pass, metres.
    pub arrival_settle_m: f64,
    /// Carry the filter's estimate of the pendulum's frequency (`k = g/l`,
    /// with `ekf.estimate_frequency`) from trial to trial within a session: each
    /// trial's filter starts from what the earlier ones learned.
    pub learn_frequency: bool,
    /// Track the camera's time offset per session from the magnet releases: the
    /// filter's swing, carried back, turns at rest `delta + d` after the coil
    /// went off (`delta`: the stamps' error, `d`: the magnet's release delay);
    /// the motion starts `delta` earlier.
    pub camera_offset_from_release: bool,
    /// Track the camera's time offset per session from the contacts too: the
    /// measured judge's pass anchored on the contact (the robot's clock)
    /// against the camera's pass shows what the offset missed, whatever the
    /// magnet's release delay; each such trial pairs with its release's
    /// turning time to learn the release delay itself (its mean and spread,
    /// kept across sessions: the same magnet), which then replaces
    /// `release_delay_prior_ms` / `release_delay_std_ms` from the third one.
    pub camera_offset_from_contact: bool,
    /// Trim the motion's start per session by the robot's own lateness: each
    /// judged contact shows when the tool arrived against the camera's pass
    /// (the measured timing error less the camera clock error, both on the
    /// robot's clock: what the arm added to the plan, e.g. a servo slower
    /// than the latency estimate sees); their precision-weighted mean, shrunk
    /// towards 0 ([`ARRIVAL_TRIM_PRIOR_STD_S`], each trial
    /// [`ARRIVAL_TRIM_TRIAL_STD_S`]), starts the motion that much earlier.
    pub arrival_trim_from_contact: bool,
    /// Keep the detections of a ball the magnet still holds out of the
    /// filter: after the coil went off, a detection within
    /// [`HELD_GATE_SIGMAS`] measurement noises (and [`HELD_GATE_MIN_M`]) of
    /// where the ball hung while armed is a ball not yet let go (a release
    /// delay of tens of ms is one to three frames), and the filter starts
    /// from the first two that moved. Without it a held pair starts the
    /// swing too early and the filter may gate the real one out.
    pub skip_held_detections: bool,
    /// The magnet's release delay believed (coil off -> ball falls), mean, ms.
    pub release_delay_prior_ms: f64,
    /// Its trial-to-trial standard deviation, ms.
    pub release_delay_std_ms: f64,
    /// Prior standard deviation of the camera's time offset, ms (how much the
    /// first releases of a session may move it).
    pub camera_offset_std_ms: f64,
}

impl Default for ControlParams {
    fn default() -> Self {
        Self {
            home_move_time_s: 2.0,
            hold_time_s: 0.3,
            track_timeout_s: 12.0,
            camera_timeout_s: 2.0,
            latency_prior_ms: 0.0,
            latency_memory_s: 30.0,
            posture_margin_deg: 5.0,
            max_speed_ratio: 0.9,
            allow_shortest_feasible: true,
            guard_margin_deg: 2.0,
            guard_speed_ratio: 1.0,
            retime: false,
            arrival_settle_m: 0.0,
            learn_frequency: false,
            camera_offset_from_release: false,
            camera_offset_from_contact: false,
            arrival_trim_from_contact: false,
            skip_held_detections: false,
            release_delay_prior_ms: 0.0,
            release_delay_std_ms: 5.0,
            camera_offset_std_ms: 10.0,
        }
    }
}

impl ControlParams {
    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first field
    /// that is not finite or outside its range.
    pub fn validate(&self) -> Result<(), ParamError> {
        check::within("control.home_move_time_s", self.home_move_time_s, 0.2, 30.0)?;
        check::within("control.hold_time_s", self.hold_time_s, 0.0, 10.0)?;
        check::within("control.track_timeout_s", self.track_timeout_s, 0.5, 120.0)?;
        check::within(
            "control.camera_timeout_s",
            self.camera_timeout_s,
            0.05,
            10.0,
        )?;
        check::within(
            "control.latency_prior_ms",
            self.latency_prior_ms,
            0.0,
            500.0,
        )?;
        check::within(
            "control.latency_memory_s",
            self.latency_memory_s,
            0.5,
            3600.0,
        )?;
        check::within(
            "control.posture_margin_deg",
            self.posture_margin_deg,
            0.0,
            30.0,
        )?;
        check::within("control.max_speed_ratio", self.max_speed_ratio, 0.05, 1.0)?;
        check::within("control.guard_margin_deg", self.guard_margin_deg, 0.0, 30.0)?;
        check::within(
            "control.guard_speed_ratio",
            self.guard_speed_ratio,
            0.05,
            1.0,
        )?;
        check::within("control.arrival_settle_m", self.arrival_settle_m, 0.0, 0.05)?;
        check::within(
            "control.release_delay_prior_ms",
            self.release_delay_prior_ms,
            0.0,
            500.0,
        )?;
        check::within(
            "control.release_delay_std_ms",
            self.release_delay_std_ms,
            0.01,
            500.0,
        )?;
        check::within(
            "control.camera_offset_std_ms",
            self.camera_offset_std_ms,
            0.01,
            500.0,
        )
    }
}

/// Errors of the controller's non-real-time calls (construction, arming).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum ControlError {
    /// A parameter was refused.
    #[error(transparent)]
    Params(#[from] ParamError),
    /// The motion cannot be planned at all: an invalid request, or out of the
    /// arm's reach (with the inverse kinematics' joint, value and limit).
    #[error("{prefix}{0}", prefix = if .0.is_unreachable() { "infeasible motion: " } else { "" })]
    Plan(#[from] PlanError),
    /// The planned posture may not run as asked: the binding joint, its limit
    /// and the numbers (`trajectory::plan`'s reason).
    #[error("infeasible motion: {0}")]
    Infeasible(#[from] Infeasibility),
    /// The filter refused its set-up.
    #[error(transparent)]
    Filter(#[from] EkfError),
    /// The timed motion refused its set-up.
    #[error(transparent)]
    Motion(#[from] TimingError),
    /// A strike's stroke may not run (issue #38): out of reach, a joint's
    /// speed, acceleration or margin, or its torque, at every contact phase
    /// tried (the first phase's reason: contact at the peak speed).
    #[error("infeasible strike at {speed_mps} m/s: {why}")]
    Strike {
        /// The tool speed at contact asked, m/s.
        speed_mps: f64,
        /// Why the stroke was refused.
        why: StrikeRefusal,
    },
    /// A strike's stroke could not be built (a bad number) or checked.
    #[error(transparent)]
    StrikePlan(#[from] StrikeError),
    /// An excitation out of range (`Excitation::is_valid`).
    #[error(
        "excitation out of range: joint {} (A1-A7 are 0-6), amplitude {} rad (0 < a <= 0.05), \
         duration {} s (1-20)",
        .0.joint, .0.amplitude_rad, .0.duration_s
    )]
    Excitation(Excitation),
    /// A joint target out of range (`Controller::move_to`): the joint,
    /// 0-based, and the value asked, radians (NaN included).
    #[error(
        "joint target out of range: A{} = {} rad (finite, within the joint's limit less {} rad)",
        .0 + 1, .1, MOVE_TO_MARGIN_RAD
    )]
    Target(usize, f64),
    /// Not allowed in the current state.
    #[error("cannot {what} while {state}")]
    State {
        /// What was asked.
        what: &'static str,
        /// The current state's name.
        state: &'static str,
    },
}

impl ControlError {
    /// Whether the motion is refused as not feasible (out of reach, or too
    /// close to a limit), rather than for a bad request or state.
    pub const fn is_infeasible(&self) -> bool {
        matches!(self, Self::Infeasible(_) | Self::Strike { .. })
            || matches!(self, Self::Plan(e) if e.is_unreachable())
    }
}

/// Everything a trial's motion needs, planned before arming (not real-time:
/// [`Controller::plan`] may take tens of milliseconds).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArmPlan {
    /// Distance robot base axis -> intercept point, metres.
    pub distance_m: f64,
    /// The intercept point (the ball at rest), base frame, metres.
    pub intercept_m: Vector3<f64>,
    /// The posture of the motion (`trajectory::plan`'s choice) and the
    /// per-cycle IK in it.
    pub posture: Posture,
    /// The motion's duration (the asked one, or the shortest feasible), seconds.
    pub duration_s: f64,
    /// The motion generator's arrival as CONTRACT.md measures it (end of the
    /// best-fitting ideal profile) minus its nominal arrival, seconds; found by
    /// running the generator once at plan time, and compensated when committing.
    pub arrival_offset_s: f64,
    /// How much earlier the tool settles within [`ARRIVAL_SETTLE_M`] (the
    /// measured judge's arrival) than the arrival the motion is timed for
    /// (`control.arrival_settle_m`'s), planned, seconds: 0 when timed for
    /// that settling, about 0.14 s at 1.5 s when timed for the fitted
    /// arrival. The measured judge adds it to the settling it sees.
    pub settle_lead_s: f64,
    /// Strike mode (`task.mode = "strike"`): the stroke; `None`: stop mode.
    /// Then `duration_s` is the stroke's time from its start to the
    /// contact, `arrival_offset_s` the generator's contact offset (its
    /// progress reaches the contact point that much after `duration_s`),
    /// and `posture` is planned for the whole cycle `S -> B`.
    pub strike: Option<StrikeArm>,
}

pub use crate::trajectory::strike::STRIKE_SWING_CLEARANCE_M;

/// A strike trial's stroke as the controller runs it (issue #38,
/// `trajectory::strike`): one Hopf cycle along a straight line from `S`
/// through the intercept point `P` to the brake point `B`, contact at the
/// phase `contact_fraction` of the cycle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StrikeArm {
    /// The stroke's start `S`, where the arm waits armed, base frame, metres.
    pub start_m: Vector3<f64>,
    /// The brake point `B`, where the cycle ends at rest, metres.
    pub end_m: Vector3<f64>,
    /// The whole cycle's duration `2 pi / w`, seconds.
    pub cycle_s: f64,
    /// The contact phase as a fraction of the cycle (`phi_a / 2 pi`).
    pub contact_fraction: f64,
    /// `|P - S|`, metres.
    pub approach_m: f64,
    /// The planned tool speed at contact (`task.strike_speed_mps`), m/s.
    pub speed_mps: f64,
    /// The motion generator's path speed at its contact (the planned one
    /// as the Hopf dynamics run it, offline at the FRI period), m/s.
    pub generator_speed_mps: f64,
    /// The strike direction (unit, in the swing plane).
    pub direction: Vector3<f64>,
    /// The believed restitution of ball and tool
    /// (`pendulum.contact_restitution`): the predicted rebound's.
    pub restitution: f64,
}

/// A sighting of the ball, as the filter fuses it: its lateral position at
/// the frame's capture time (a frame where the ball was found; the camera's
/// whole per-frame result is a [`crate::vision::Measurement`]).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Sighting {
    /// Capture time, seconds (the control clock).
    pub t_capture_s: f64,
    /// Lateral (base y) position of the ball, metres.
    pub lateral_m: f64,
}

/// One FRI message's worth of input.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepInput {
    /// Time of the message, seconds (the control clock).
    pub t_s: f64,
    /// Measured joint positions, radians.
    pub q_measured_rad: [f64; JOINTS],
    /// Whether the session is in COMMANDING_ACTIVE (commands are executed).
    pub commanding: bool,
}

/// The step's output (caller-owned).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepOutput {
    /// Joint command, radians (already guarded).
    pub q_command_rad: [f64; JOINTS],
    /// The trial state after the step.
    pub state: TrialState,
}

impl Default for StepOutput {
    fn default() -> Self {
        Self {
            q_command_rad: [0.0; JOINTS],
            state: TrialState::Idle,
        }
    }
}

/// Counters the step keeps instead of logging.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
pub struct ControlCounters {
    /// Steps run.
    pub steps: u64,
    /// Camera measurements received.
    pub measurements: u64,
    /// Measurements the filter fused.
    pub fused: u64,
    /// Measurements the filter refused (bad input or gated out).
    pub rejected: u64,
    /// Predictions asked of the filter that it could not give.
    pub prediction_errors: u64,
    /// Interception checks answered from the last prediction (the filter had
    /// not changed since and its motion start lay beyond this cycle).
    pub predictions_reused: u64,
    /// Motion re-timings to a refined pass prediction.
    pub retimes: u64,
    /// Calls the timed motion refused.
    pub motion_errors: u64,
    /// Inverse-kinematics failures.
    pub ik_failures: u64,
    /// Commands the guard clamped to a position limit.
    pub guard_position_clamps: u64,
    /// Commands the guard clamped to the largest step per period.
    pub guard_step_clamps: u64,
    /// Commands that were not finite (replaced by the previous one).
    pub guard_non_finite: u64,
    /// Measured joint positions beyond a position limit.
    pub measured_limit_violations: u64,
    /// Steps without COMMANDING_ACTIVE.
    pub not_commanding: u64,
    /// Aborts.
    pub aborts: u64,
}

impl ControlCounters {
    /// Everything that counts as a limit violation in a trial's result.
    pub fn limit_violations(&self) -> u64 {
        self.guard_position_clamps
            + self.guard_step_clamps
            + self.guard_non_finite
            + self.measured_limit_violations
    }
}

/// What was decided when the interception condition was met.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Commit {
    /// When the step that committed ran, seconds.
    pub t_commit_s: f64,
    /// When the motion starts (its `t = 0`), seconds.
    pub motion_start_s: f64,
    /// The motion's planned duration at commit, seconds.
    pub duration_s: f64,
    /// Predicted pass time, seconds.
    pub predicted_pass_s: f64,
    /// Its standard deviation, seconds.
    pub predicted_pass_std_s: f64,
    /// Predicted ball centre at the pass, metres.
    pub predicted_ball_m: Vector3<f64>,
    /// The latency compensated (the robot's), seconds.
    pub latency_s: f64,
    /// The camera time offset compensated (stamps late by this), seconds.
    pub camera_offset_s: f64,
    /// The arrival trim compensated (the motion starts this much earlier),
    /// seconds.
    pub trim_s: f64,
    /// The generator's arrival offset compensated, seconds.
    pub arrival_offset_s: f64,
    /// Direction of the committed pass (sign of the lateral velocity).
    pub direction_positive: bool,
    /// A strike's predicted rebound (issue #38; `None`: a stop, or a
    /// belief it could not be made from).
    pub rebound: Option<PredictedRebound>,
}

/// The last interception prediction and the filter state it came from: while
/// the filter does not change (no measurement processed) the predicted pass,
/// and so the motion's start, stay the same, and no commit can happen before
/// that start. The crossing search then runs once per camera measurement
/// instead of once per FRI cycle.
#[derive(Debug, Clone, Copy, PartialEq)]
struct PredictionCache {
    filter: EkfCounters,
    posterior_t_s: f64,
    posterior_x: StateVec,
    duration_s: f64,
    latency_s: f64,
    start_s: f64,
}

/// What a session (a reboot of the lab) has taught so far.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SessionMemory {
    /// `k = g/l` and its variance, 1/s^2 and 1/s^4 (`learn_frequency`).
    pub k: Option<(f64, f64)>,
    /// Sum of the releases' turning lags `t_turn - t_release` this session
    /// (each the camera offset plus the release delay), seconds.
    pub lag_sum_s: f64,
    /// How many releases.
    pub offset_n: u32,
    /// Sum of the contacts' camera offsets over their variances, 1/s.
    pub contact_weighted_sum: f64,
    /// Sum of their inverse variances, 1/s^2.
    pub contact_weight: f64,
    /// How many contacts.
    pub contact_n: u32,
    /// Sum of the contacts' arrival lateness readings over their
    /// variances, 1/s (`arrival_trim_from_contact`).
    pub trim_weighted_sum: f64,
    /// Sum of their inverse variances, 1/s^2.
    pub trim_weight: f64,
    /// How many.
    pub trim_n: u32,
}

/// A detection after the release within this many measurement noises of
/// the held ball's position is a ball still held
/// (`skip_held_detections`) ...
pub const HELD_GATE_SIGMAS: f64 = 4.0;
/// ... and within at least this, metres.
pub const HELD_GATE_MIN_M: f64 = 0.002;
/// Detections of the held ball needed (while armed) before any is skipped.
pub const HELD_MIN_DETECTIONS: u32 = 3;

/// Prior standard deviation of the arrival trim, seconds.
pub const ARRIVAL_TRIM_PRIOR_STD_S: f64 = 0.010;
/// Trial-to-trial standard deviation of the robot's lateness (its jitter,
/// the servo's response to each motion) added to each reading's own,
/// seconds.
pub const ARRIVAL_TRIM_TRIAL_STD_S: f64 = 0.003;

/// What the lab's releases taught about its magnet: the release delay's
/// mean and spread (Welford), paired release by release with the camera
/// offset a contact measured. Kept across sessions (a reboot leaves the
/// magnet as it was).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct MagnetMemory {
    /// Releases measured.
    pub n: u32,
    /// Mean release delay, seconds.
    pub mean_s: f64,
    /// Sum of squared deviations, s^2.
    pub m2_s2: f64,
}

impl MagnetMemory {
    /// Releases measured before the learned delay replaces the prior.
    pub const MIN_RELEASES: u32 = 3;
    /// Smallest spread believed, seconds (the turning time's own noise).
    pub const MIN_STD_S: f64 = 0.002;

    fn add(&mut self, d_s: f64) {
        self.n += 1;
        let dev = d_s - self.mean_s;
        self.mean_s += dev / f64::from(self.n);
        self.m2_s2 += dev * (d_s - self.mean_s);
    }

    /// The learned mean and standard deviation, seconds, once there are
    /// [`Self::MIN_RELEASES`].
    pub fn learned(&self) -> Option<(f64, f64)> {
        (self.n >= Self::MIN_RELEASES).then(|| {
            let var = self.m2_s2 / f64::from(self.n - 1);
            (self.mean_s, var.sqrt().max(Self::MIN_STD_S))
        })
    }
}

/// What the sessions before this one ended with: the camera offset and the
/// arrival trim each learned from at least [`SessionPriors::MIN_CONTACTS`]
/// contacts (mean and spread, Welford). From the second such session on they
/// replace the zero-mean priors of the next session's first trials: a reboot
/// changes the latencies "slightly" (the paper), not from scratch. Kept
/// across sessions, as the magnet's memory.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SessionPriors {
    /// Sessions folded in.
    pub n: u32,
    /// Mean camera offset, seconds, and sum of squared deviations, s^2.
    pub offset_mean_s: f64,
    /// Sum of squared deviations of the offsets, s^2.
    pub offset_m2_s2: f64,
    /// Mean arrival trim, seconds.
    pub trim_mean_s: f64,
    /// Sum of squared deviations of the trims, s^2.
    pub trim_m2_s2: f64,
}

impl SessionPriors {
    /// Contacts a session needs before it is folded in.
    pub const MIN_CONTACTS: u32 = 3;
    /// Sessions needed before the priors are used.
    pub const MIN_SESSIONS: u32 = 2;
    /// Smallest spread believed, seconds.
    pub const MIN_STD_S: f64 = 0.002;

    fn add(&mut self, offset_s: f64, trim_s: f64) {
        self.n += 1;
        let n = f64::from(self.n);
        let d = offset_s - self.offset_mean_s;
        self.offset_mean_s += d / n;
        self.offset_m2_s2 += d * (offset_s - self.offset_mean_s);
        let d = trim_s - self.trim_mean_s;
        self.trim_mean_s += d / n;
        self.trim_m2_s2 += d * (trim_s - self.trim_mean_s);
    }

    /// The camera offset's prior (mean, std), seconds, once learned.
    pub fn offset(&self) -> Option<(f64, f64)> {
        (self.n >= Self::MIN_SESSIONS).then(|| {
            let sd = (self.offset_m2_s2 / f64::from(self.n - 1)).sqrt();
            (self.offset_mean_s, sd.max(Self::MIN_STD_S))
        })
    }

    /// The arrival trim's prior (mean, std), seconds, once learned.
    pub fn trim(&self) -> Option<(f64, f64)> {
        (self.n >= Self::MIN_SESSIONS).then(|| {
            let sd = (self.trim_m2_s2 / f64::from(self.n - 1)).sqrt();
            (self.trim_mean_s, sd.max(Self::MIN_STD_S))
        })
    }
}

/// What the running trial shows (folded into the session at its end).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
struct TrialLearning {
    /// Posterior time the snapshot was taken from, seconds.
    posterior_t_s: f64,
    k: Option<(f64, f64)>,
    /// `t_turn - t_release`: this release's turning lag (camera offset
    /// plus release delay), seconds.
    lag_s: Option<f64>,
    /// Whether a contact's camera offset has been taken for this trial.
    contact_taken: bool,
    /// The arrival trim this trial's motion used, seconds.
    trim_used_s: f64,
    /// Whether a contact's arrival lateness has been taken for this trial.
    arrival_taken: bool,
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct JointMove {
    q0: Joints,
    q1: Joints,
    t0: f64,
    duration_s: f64,
}

impl JointMove {
    fn at(&self, t: f64) -> Joints {
        let s = ProfileKind::MinJerk.position((t - self.t0) / self.duration_s);
        self.q0 + (self.q1 - self.q0) * s
    }

    fn done(&self, t: f64) -> bool {
        t >= self.t0 + self.duration_s
    }
}

/// A small excitation of one joint from rest: the robot calibration step's
/// motion ([`Controller::excite`]). From where the arm rests, the joint
/// moves `amplitude_rad` away and back every [`EXCITE_STEP_EVERY_S`], each
/// move a minimum-jerk transition of [`EXCITE_RAMP_S`] (at 0.05 rad: peak
/// speed 0.47 rad/s, peak acceleration 7.2 rad/s^2, within every joint's
/// limits, so that drives which saturate there still follow it), for
/// `duration_s`; then it rests where it began.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Excitation {
    /// The joint, 0-based (6 is A7, the wrist).
    pub joint: usize,
    /// The steps' height, radians, in `(0, 0.05]`.
    pub amplitude_rad: f64,
    /// How long the steps go on, seconds, in `[1, 20]`.
    pub duration_s: f64,
}

/// Seconds between an excitation's moves.
pub const EXCITE_STEP_EVERY_S: f64 = 0.4;
/// Each move's duration, seconds.
pub const EXCITE_RAMP_S: f64 = 0.2;

/// How far inside every joint's limit a [`Controller::move_to`] target must
/// stay, radians (5 degrees).
pub const MOVE_TO_MARGIN_RAD: f64 = 0.0873;
/// The share of each joint's speed and acceleration limits a
/// [`Controller::move_to`] move may use (a slow, calibration-tour move).
pub const MOVE_TO_LIMIT_SHARE: f64 = 0.2;

/// The share of each joint's speed and acceleration limits a
/// [`Controller::knock_to`] move may use (the contact step's knock: a few
/// tenths of a metre per second at the tool).
pub const KNOCK_LIMIT_SHARE: f64 = 0.5;
/// The shortest [`Controller::knock_to`] move, s.
pub const KNOCK_MIN_S: f64 = 0.3;

/// How long a [`Controller::move_to`] move from `q0` to `q1` (radians)
/// takes, s: the minimum-jerk profile's peak speed (1.875 d / T) and peak
/// acceleration (5.77 d / T^2, taken as 5.78) within [`MOVE_TO_LIMIT_SHARE`] of every
/// joint's limits, at least 1 s.
pub fn move_to_duration_s(q0: &Joints, q1: &Joints) -> f64 {
    move_duration_s(q0, q1, MOVE_TO_LIMIT_SHARE, 1.0)
}

/// How long a minimum-jerk joint move from `q0` to `q1` within `share` of
/// every joint's speed and acceleration limits takes, at least `min_s`, s.
pub fn move_duration_s(q0: &Joints, q1: &Joints, share: f64, min_s: f64) -> f64 {
    let mut dur: f64 = min_s;
    for j in 0..JOINTS {
        let d = (q1[j] - q0[j]).abs();
        dur = dur
            .max(1.875 * d / (share * VELOCITY_LIMIT_RADPS[j]))
            .max((5.78 * d / (share * ACCELERATION_LIMIT_RADPS2[j])).sqrt());
    }
    dur
}

impl Excitation {
    /// Whether the joint, amplitude and duration are in range.
    pub fn is_valid(&self) -> bool {
        self.joint < JOINTS
            && self.amplitude_rad > 0.0
            && self.amplitude_rad <= 0.05
            && (1.0..=20.0).contains(&self.duration_s)
    }

    /// The joint's offset from where it rested, `s` seconds after the start,
    /// radians: 0 before the first move and from `duration_s` on.
    pub fn offset_rad(&self, s: f64) -> f64 {
        if !(s > 0.0 && s < self.duration_s) {
            return 0.0;
        }
        // Slot k holds `amplitude_rad` away when k is odd and the move back
        // (in slot k + 1) ends within the duration; each slot begins with
        // the move from the previous slot's level to its own.
        let level = |k: f64| {
            f64::from(u8::from(
                k.rem_euclid(2.0) == 1.0
                    && (k + 1.0) * EXCITE_STEP_EVERY_S + EXCITE_RAMP_S <= self.duration_s,
            ))
        };
        let k = (s / EXCITE_STEP_EVERY_S).floor();
        let from = if k >= 1.0 { level(k - 1.0) } else { 0.0 };
        let to = level(k);
        let u = ((s - k * EXCITE_STEP_EVERY_S) / EXCITE_RAMP_S).min(1.0);
        self.amplitude_rad * (from + (to - from) * ProfileKind::MinJerk.position(u))
    }
}

/// The closed-loop controller: one per robot; trials come and go.
#[derive(Debug, Clone)]
pub struct Controller {
    params: ControlParams,
    /// `task.intercept_height_m` of the beliefs (the pendulum's geometry at arming).
    intercept_height_m: f64,
    ekf_params: EkfParams,
    model: PendulumModel,
    tool: Tool,
    machine: TrialMachine,
    ekf: Option<Ekf>,
    motion: TimedMotion,
    sample: MotionSample,
    latency: LatencyEstimator,
    plan: Option<ArmPlan>,
    /// `task.home_m`.
    task_home_m: Vector3<f64>,
    /// Where the trial's motion starts: `task_home_m`, or a strike's `S`.
    home_m: Vector3<f64>,
    jmove: Option<JointMove>,
    /// A running excitation, its start (s) and the joints it rests at.
    excite: Option<(Excitation, f64, Joints)>,
    q_meas: Joints,
    q_cmd: Joints,
    v_cmd: Joints,
    have_cmd: bool,
    have_meas: bool,
    t_last: Option<f64>,
    t_state: f64,
    t_release: f64,
    t_last_measurement: f64,
    commit: Option<Commit>,
    prediction: Option<PredictionCache>,
    counters: ControlCounters,
    abort_reason: Option<AbortReason>,
    session: SessionMemory,
    magnet: MagnetMemory,
    /// What earlier sessions ended with (kept across sessions).
    priors: SessionPriors,
    learning: TrialLearning,
    /// The held ball's detections while armed: sum of lateral positions,
    /// metres, and count (`skip_held_detections`).
    held_sum_m: f64,
    held_n: u32,
    /// Post-release detections skipped as still held, this trial.
    held_skipped: u32,
    /// Why the filter's newest plan of a motion was not confident enough to
    /// commit, this trial (`None`: no plan yet): what a trial that times out
    /// without a motion says.
    last_doubt: Option<crate::ekf::Doubt>,
}

impl Controller {
    /// A controller for the lab `beliefs` describe (`params::Scenario::beliefs`)
    /// with an FRI period of `period_s`.
    ///
    /// # Errors
    ///
    /// [`ControlError::Params`] when the beliefs or the timing parameters are invalid.
    pub fn new(beliefs: &Beliefs, period_s: f64) -> Result<Self, ControlError> {
        beliefs.validate()?;
        let params = &beliefs.control;
        let ekf = &beliefs.ekf;
        let timing = &beliefs.timing;
        let model = PendulumModel::from_params(&beliefs.pendulum)?;
        let motion = TimedMotion::new(timing.clone())?;
        let [hx, hy, hz] = beliefs.task.home_m;
        Ok(Self {
            params: params.clone(),
            intercept_height_m: beliefs.task.intercept_height_m,
            ekf_params: ekf.clone(),
            model,
            tool: Tool::along_z(beliefs.task.tool_length_m),
            machine: TrialMachine::new(),
            ekf: None,
            motion,
            sample: MotionSample::default(),
            latency: LatencyEstimator::new(
                period_s,
                params.latency_prior_ms * 1e-3,
                params.latency_memory_s,
            ),
            plan: None,
            task_home_m: Vector3::new(hx, hy, hz),
            home_m: Vector3::new(hx, hy, hz),
            jmove: None,
            excite: None,
            q_meas: Joints::zeros(),
            q_cmd: Joints::zeros(),
            v_cmd: Joints::zeros(),
            have_cmd: false,
            have_meas: false,
            t_last: None,
            t_state: 0.0,
            t_release: 0.0,
            t_last_measurement: f64::NEG_INFINITY,
            commit: None,
            prediction: None,
            last_doubt: None,
            counters: ControlCounters::default(),
            abort_reason: None,
            session: SessionMemory::default(),
            magnet: MagnetMemory::default(),
            priors: SessionPriors::default(),
            learning: TrialLearning::default(),
            held_sum_m: 0.0,
            held_n: 0,
            held_skipped: 0,
        })
    }

    /// Plans a trial's motion to the intercept point at `distance_m` (not
    /// real-time: run it off the control thread, then hand it to [`Self::arm`]).
    ///
    /// # Errors
    ///
    /// [`ControlError::Params`] for a distance outside 0.1..=1.2 m;
    /// [`ControlError::Plan`] when the posture planner refuses (e.g. out of reach);
    /// [`ControlError::Infeasible`] when the plan may not run as asked;
    /// [`ControlError::Motion`] when the timed motion refuses the path.
    pub fn plan(beliefs: &Beliefs, distance_m: f64) -> Result<ArmPlan, ControlError> {
        let params = &beliefs.control;
        let timing = &beliefs.timing;
        check::within("task.distance_m", distance_m, 0.1, 1.2)?;
        if beliefs.task.mode == TaskMode::Strike {
            return Self::plan_strike(beliefs, distance_m);
        }
        let task = &beliefs.task;
        let home = Vector3::from(task.home_m);
        // The believed rest point: `task.intercept_offset_m` (calibrated) included.
        let intercept = task.intercept_m(distance_m);
        // The posture planner of `trajectory` (the same one `isochron kin plan`
        // reports), with this section's speed ratio and position margin.
        let traj = TrajectoryParams {
            velocity_fraction: params.max_speed_ratio,
            position_margin_deg: params.posture_margin_deg,
            ..TrajectoryParams::default()
        };
        let mut req = PathRequest::interception(task, distance_m);
        let mut mp = crate::trajectory::plan(&req, &traj)?;
        if !mp.feasible && mp.shortest_feasible_s.is_finite() && params.allow_shortest_feasible {
            // Too fast: the same posture at its shortest feasible duration
            // (speeds scale with 1/T, accelerations with 1/T^2).
            req.movement_time_s = mp.shortest_feasible_s;
            mp = crate::trajectory::evaluate(&req, &traj, mp.tilt_rad, mp.arm_angle_rad)?;
        }
        // A plan that is not feasible says why (`reason` is `Some` exactly then).
        if let Some(why) = mp.reason {
            return Err(ControlError::Infeasible(why));
        }
        let posture = mp.posture();
        let duration = req.movement_time_s;
        let period_s = f64::from(beliefs.fri_period_ms) * 1e-3;
        let arrival_offset_s = generator_arrival_offset(
            timing,
            &home,
            &intercept,
            &posture,
            duration,
            period_s,
            params.arrival_settle_m,
        )?;
        let settle_lead_s = if (params.arrival_settle_m - ARRIVAL_SETTLE_M).abs() < 1e-12 {
            0.0
        } else {
            arrival_offset_s
                - generator_arrival_offset(
                    timing,
                    &home,
                    &intercept,
                    &posture,
                    duration,
                    period_s,
                    ARRIVAL_SETTLE_M,
                )?
        };
        Ok(ArmPlan {
            distance_m,
            intercept_m: intercept,
            posture,
            duration_s: duration,
            arrival_offset_s,
            settle_lead_s,
            strike: None,
        })
    }

    /// Strike mode's plan (issue #38): the stroke through the believed
    /// intercept point along `task.strike_direction_deg` (returning the ball
    /// towards [`STRIKE_RETURN_SIGN`]), meeting it at
    /// `task.strike_speed_mps` after `task.movement_time_s`, at the first
    /// contact phase of [`CONTACT_PHASES`] whose whole cycle is feasible
    /// (reach, joint speeds, accelerations and margins of the same planner
    /// as the stop mode's, joint torques by `trajectory::strike::plan_strike`).
    /// Never the shortest feasible duration: a strike's speed and timing are
    /// the task.
    fn plan_strike(beliefs: &Beliefs, distance_m: f64) -> Result<ArmPlan, ControlError> {
        let params = &beliefs.control;
        let task = &beliefs.task;
        let intercept = task.intercept_m(distance_m);
        let traj = TrajectoryParams {
            velocity_fraction: params.max_speed_ratio,
            position_margin_deg: params.posture_margin_deg,
            ..TrajectoryParams::default()
        };
        let direction = strike_direction(STRIKE_RETURN_SIGN, task.strike_direction_deg);
        let tool = Tool::along_z(task.tool_length_m);
        let mut why = None;
        for f in CONTACT_PHASES {
            let stroke = Stroke::new(
                intercept,
                direction,
                task.strike_speed_mps,
                task.movement_time_s,
                f,
                tool,
            )?;
            let sp = plan_strike(stroke, &traj, STRIKE_TOOL_MASS_KG)?;
            let Some(mp) = sp.plan.filter(|_| sp.feasible) else {
                // The first phase's reason (contact at the peak speed:
                // the shortest approach) says what binds.
                why = why.or(sp.reason);
                continue;
            };
            let s = &sp.stroke;
            // The arm waits at S from arming on: out of the swing's way
            // (the believed arc through the intercept point, in the swing
            // plane), or the ball meets the waiting tool.
            let swing = SwingClearance::new(
                beliefs.pendulum.length_m,
                beliefs.pendulum.ball_radius_m,
                task.tool_contact_radius_m,
            );
            if let Some(refusal) = swing.check(s) {
                why = why.or(Some(refusal));
                continue;
            }
            let posture = mp.posture();
            let period_s = f64::from(beliefs.fri_period_ms) * 1e-3;
            let (arrival_offset_s, generator_speed_mps) =
                generator_contact(&beliefs.timing, s, &posture, period_s)?;
            return Ok(ArmPlan {
                distance_m,
                intercept_m: intercept,
                posture,
                duration_s: s.contact_s,
                arrival_offset_s,
                settle_lead_s: 0.0,
                strike: Some(StrikeArm {
                    start_m: s.request.start_m,
                    end_m: s.request.end_m,
                    cycle_s: s.request.movement_time_s,
                    contact_fraction: s.contact_fraction,
                    approach_m: s.approach_m,
                    speed_mps: s.speed_mps,
                    generator_speed_mps,
                    direction: s.direction,
                    restitution: beliefs.pendulum.contact_restitution,
                }),
            });
        }
        Err(why.map_or(
            ControlError::State {
                what: "plan a strike (no contact phase was tried)",
                state: "planning",
            },
            |why| ControlError::Strike {
                speed_mps: task.strike_speed_mps,
                why,
            },
        ))
    }

    /// The current trial state.
    pub fn state(&self) -> TrialState {
        self.machine.state()
    }

    /// The counters.
    pub fn counters(&self) -> &ControlCounters {
        &self.counters
    }

    /// The latency estimator.
    pub fn latency(&self) -> &LatencyEstimator {
        &self.latency
    }

    /// The filter of the current trial, once armed.
    pub fn ekf(&self) -> Option<&Ekf> {
        self.ekf.as_ref()
    }

    /// The plan of the current trial, once armed.
    pub fn arm_plan(&self) -> Option<&ArmPlan> {
        self.plan.as_ref()
    }

    /// What was committed to, once the interception condition was met.
    pub fn commit(&self) -> Option<&Commit> {
        self.commit.as_ref()
    }

    /// When the committed motion arrives (its start plus its possibly
    /// re-timed arrival), seconds; `None` before a commit.
    pub fn planned_arrival_s(&self) -> Option<f64> {
        self.commit
            .as_ref()
            .map(|c| c.motion_start_s + self.motion.arrival_time_s())
    }

    /// The timed motion's latest sample.
    pub fn motion_sample(&self) -> &MotionSample {
        &self.sample
    }

    /// The last guarded joint command.
    pub fn q_command(&self) -> &Joints {
        &self.q_cmd
    }

    /// Where the trial's motion starts (tool point), metres: the task's
    /// home, or in strike mode the armed trial's stroke start `S`.
    pub fn home_m(&self) -> Vector3<f64> {
        self.home_m
    }

    /// When the committed strike's contact is planned (its start plus the
    /// contact phase of its possibly re-timed cycle), seconds; `None` before
    /// a commit or in stop mode.
    pub fn planned_contact_s(&self) -> Option<f64> {
        let s = self.plan.as_ref()?.strike?;
        self.commit
            .as_ref()
            .map(|c| c.motion_start_s + self.motion.arrival_time_s() * s.contact_fraction)
    }

    /// The end point of the running (or last) motion: its last target, metres.
    pub fn motion_target_m(&self) -> Vector3<f64> {
        self.sample.target_m
    }

    /// The reason of the last abort.
    pub fn abort_reason(&self) -> Option<AbortReason> {
        self.abort_reason
    }

    /// The pendulum's effective length `g/k` this trial's filter showed
    /// before the pass (`ekf.estimate_frequency` with `learn_frequency`), metres.
    pub fn trial_length_estimate_m(&self) -> Option<f64> {
        self.learning.k.map(|(k, _)| self.model.gravity_mps2 / k)
    }

    /// What this session has learned so far.
    pub fn session_memory(&self) -> &SessionMemory {
        &self.session
    }

    /// A new session began (the lab was rebooted: the camera's clock offset,
    /// the robot's latency and the pendulum may have changed): forgets what
    /// the earlier trials taught (`learn_frequency`, `camera_offset_from_release`).
    pub fn new_session(&mut self) {
        // What the ending session learned from its contacts becomes part of
        // the next sessions' priors.
        let m = &self.session;
        if m.contact_n >= SessionPriors::MIN_CONTACTS || m.trim_n >= SessionPriors::MIN_CONTACTS {
            let (offset, trim) = (self.camera_offset_s(), self.arrival_trim_s());
            if offset.is_finite() && trim.is_finite() {
                self.priors.add(offset, trim);
            }
        }
        self.session = SessionMemory::default();
        self.learning = TrialLearning::default();
    }

    /// What the earlier sessions ended with (the next sessions' priors).
    pub fn session_priors(&self) -> &SessionPriors {
        &self.priors
    }

    /// Detections after this trial's release skipped as a ball still held
    /// (`skip_held_detections`).
    pub fn held_skipped(&self) -> u32 {
        self.held_skipped
    }

    /// What the lab's releases taught about its magnet so far.
    pub fn magnet_memory(&self) -> &MagnetMemory {
        &self.magnet
    }

    /// The release delay believed now, its mean and standard deviation,
    /// seconds: learned from the contacts (`camera_offset_from_contact`)
    /// once there are enough, the prior until then.
    pub fn release_delay_belief_s(&self) -> (f64, f64) {
        let prior = (
            self.params.release_delay_prior_ms * 1e-3,
            self.params.release_delay_std_ms * 1e-3,
        );
        if !self.params.camera_offset_from_contact {
            return prior;
        }
        self.magnet.learned().unwrap_or(prior)
    }

    /// The camera time offset to compensate, seconds (0 when neither source
    /// is on): the precision-weighted mean of the session's releases and
    /// this trial's (each `t_turn - t_release - d` with variance `sigma_d^2`,
    /// `d` and `sigma_d` the release delay believed) and of the session's
    /// contacts (each the offset the measured judge saw, with its variance),
    /// shrunk towards 0 by the prior `sigma_delta`.
    pub fn camera_offset_s(&self) -> f64 {
        let (release, contact) = (
            self.params.camera_offset_from_release,
            self.params.camera_offset_from_contact,
        );
        if !release && !contact {
            return 0.0;
        }
        let param_sp = self.params.camera_offset_std_ms * 1e-3;
        let (m0, sp) = if contact {
            self.priors.offset().unwrap_or((0.0, param_sp))
        } else {
            (0.0, param_sp)
        };
        let (mut num, mut den) = (m0 / (sp * sp), 1.0 / (sp * sp));
        if release {
            let (mut lag_sum, mut n) = (self.session.lag_sum_s, f64::from(self.session.offset_n));
            if let Some(l) = self.learning.lag_s {
                lag_sum += l;
                n += 1.0;
            }
            let (d, sd) = self.release_delay_belief_s();
            num += (lag_sum - n * d) / (sd * sd);
            den += n / (sd * sd);
        }
        if contact {
            num += self.session.contact_weighted_sum;
            den += self.session.contact_weight;
        }
        num / den
    }

    /// A contact showed the camera's time offset of the trial that ended:
    /// `offset_s` (the offset the trial compensated plus what the measured
    /// judge saw it miss) with standard deviation `std_s`. Taken once a
    /// trial, into the session's contacts, and paired with the trial's
    /// release (its turning lag minus this offset: one release delay) into
    /// the magnet's memory. Ignored unless `camera_offset_from_contact`, or
    /// when not finite, beyond 0.2 s or `std_s` not positive. Allocation-free.
    pub fn learn_from_contact(&mut self, offset_s: f64, std_s: f64) {
        if !self.params.camera_offset_from_contact
            || self.learning.contact_taken
            || !offset_s.is_finite()
            || offset_s.abs() > 0.2
            || !std_s.is_finite()
            || std_s <= 0.0
        {
            return;
        }
        // Not sharper than a millisecond: the contact's own model error.
        let var = std_s.max(1e-3).powi(2);
        self.session.contact_weighted_sum += offset_s / var;
        self.session.contact_weight += 1.0 / var;
        self.session.contact_n += 1;
        self.learning.contact_taken = true;
        if let Some(lag) = self.learning.lag_s {
            let d = lag - offset_s;
            if (0.0..=0.5).contains(&d) {
                self.magnet.add(d);
            }
        }
    }

    /// The arrival trim, seconds (0 unless `arrival_trim_from_contact`):
    /// the session's readings of the robot's lateness, precision-weighted,
    /// shrunk towards 0.
    pub fn arrival_trim_s(&self) -> f64 {
        if !self.params.arrival_trim_from_contact {
            return 0.0;
        }
        let (m0, sd0) = self
            .priors
            .trim()
            .unwrap_or((0.0, ARRIVAL_TRIM_PRIOR_STD_S));
        let prior = 1.0 / (sd0 * sd0);
        (m0 * prior + self.session.trim_weighted_sum) / (prior + self.session.trim_weight)
    }

    /// A contact showed the trial's arrival against the camera's pass:
    /// `lateness_s` late (the measured timing error less the camera clock
    /// error) with standard deviation `std_s`. With the trim the motion
    /// used, one reading of the robot's lateness; taken once a trial.
    /// Ignored unless `arrival_trim_from_contact`, or when not finite,
    /// beyond 50 ms or `std_s` not positive. Allocation-free.
    pub fn learn_from_arrival(&mut self, lateness_s: f64, std_s: f64) {
        if !self.params.arrival_trim_from_contact
            || self.learning.arrival_taken
            || !lateness_s.is_finite()
            || lateness_s.abs() > 0.05
            || !std_s.is_finite()
            || std_s <= 0.0
        {
            return;
        }
        let reading = self.learning.trim_used_s + lateness_s;
        let var = std_s * std_s + ARRIVAL_TRIM_TRIAL_STD_S * ARRIVAL_TRIM_TRIAL_STD_S;
        self.session.trim_weighted_sum += reading / var;
        self.session.trim_weight += 1.0 / var;
        self.session.trim_n += 1;
        self.learning.arrival_taken = true;
    }

    /// Takes what the filter shows about the constants of the session (its
    /// frequency, and the release's turning time against the coil's switch).
    /// Not real-time critical but allocation-free: three predictions.
    fn learn_from_filter(&mut self) {
        if !self.params.learn_frequency
            && !self.params.camera_offset_from_release
            && !self.params.camera_offset_from_contact
        {
            return;
        }
        let Some(ekf) = self.ekf.as_ref() else {
            return;
        };
        let Some((t_post, x, p)) = ekf.posterior() else {
            return;
        };
        if t_post == self.learning.posterior_t_s {
            return;
        }
        if ekf.params().estimate_frequency {
            let (k, var) = (
                x[crate::ekf::model::K],
                p[(crate::ekf::model::K, crate::ekf::model::K)],
            );
            if k.is_finite() && k > 0.0 && var.is_finite() && var > 0.0 {
                self.learning.k = Some((k, var));
            }
        }
        if self.params.camera_offset_from_release || self.params.camera_offset_from_contact {
            // Newton on phi'(t) = 0 from the believed drop time.
            let d = self.release_delay_belief_s().0;
            let mut t = self.t_release + d;
            let mut pred = crate::ekf::Prediction::default();
            let mut found = None;
            for _ in 0..4 {
                if ekf.predict_at(t, &mut pred).is_err() {
                    break;
                }
                let s = pred.state;
                let acc =
                    -s[crate::ekf::model::K] * s[0].sin() - s[crate::ekf::model::ALPHA] * s[1];
                if !acc.is_finite() || acc.abs() < 1e-9 {
                    break;
                }
                let step = s[1] / acc;
                t -= step;
                if step.abs() < 1e-5 {
                    found = Some(t);
                    break;
                }
            }
            if let Some(t_turn) = found {
                // A turning point far from the believed drop is not this
                // release's (the next is half a period, ~1.4 s, away).
                if (t_turn - self.t_release - d).abs() < 0.2 {
                    self.learning.lag_s = Some(t_turn - self.t_release);
                }
            }
        }
        self.learning.posterior_t_s = t_post;
    }

    /// Folds the finished trial's lessons into the session's memory.
    fn end_trial_learning(&mut self) {
        if self.commit.is_some() {
            if let Some((k, var)) = self.learning.k {
                // A little forgetting: 0.02% of k per trial.
                let drift = 2e-4 * k;
                self.session.k = Some((k, var + drift * drift));
            }
            if let Some(l) = self.learning.lag_s {
                self.session.lag_sum_s += l;
                self.session.offset_n += 1;
            }
        }
        self.learning = TrialLearning::default();
    }

    /// Takes over what `old` learned in this session where the new beliefs
    /// keep what it was learned against (new parameters replacing a
    /// controller between trials: a calibration step's result, a changed
    /// movement time): the robot latency estimate when the estimator's
    /// settings are the same (a lab whose arm is already home would otherwise
    /// plan its next trial with the prior: 20 ms late through `isochron
    /// world` after the pendulum step); the pendulum's learned frequency (the
    /// same pendulum swung); the camera offsets of the releases and the
    /// contacts when `camera_latency_same` (they are offsets from that
    /// belief); the magnet's learned release delay (the same magnet). Copies
    /// fixed-size state only: no allocation on the control thread.
    pub fn carry_session(&mut self, old: &Self, camera_latency_same: bool) {
        if self.latency.same_settings(&old.latency) {
            self.latency.clone_from(&old.latency);
        }
        if camera_latency_same {
            self.session = old.session;
        } else {
            self.session.k = old.session.k;
        }
        if !self.latency.same_settings(&old.latency) {
            // The robot's lateness was read against the old latency beliefs.
            self.session.trim_weighted_sum = 0.0;
            self.session.trim_weight = 0.0;
            self.session.trim_n = 0;
        }
        // The same magnet.
        self.magnet = old.magnet;
        self.priors = old.priors;
    }

    /// The tool this controller plans with.
    pub fn tool(&self) -> &Tool {
        &self.tool
    }

    fn go(&mut self, t: f64, to: TrialState) {
        if self.machine.go(to).is_ok() {
            self.t_state = t;
        }
    }

    /// Aborts the trial (safe stop: the commanded motion decelerates to rest).
    pub fn abort(&mut self, t_s: f64, reason: AbortReason) {
        if matches!(self.machine.state(), TrialState::Aborted) {
            return;
        }
        self.machine.abort();
        self.t_state = t_s;
        self.abort_reason = Some(reason);
        self.counters.aborts += 1;
        self.jmove = None;
        self.excite = None;
    }

    /// Starts an excitation of one joint from where the arm rests (the
    /// robot calibration step; see [`Excitation`]): allowed in `Idle`
    /// (between trials) with the commands at rest, once the robot has sent
    /// a message, while no other excitation runs. The commands stay within the guard; a stop or an
    /// abort ends it where it is (the safe stop), arming waits until it is
    /// over ([`Self::exciting`]).
    ///
    /// # Errors
    ///
    /// [`ControlError::Excitation`] for a joint, amplitude or duration out of
    /// range; [`ControlError::State`] when not `Idle`, before the robot's
    /// first message, or while an excitation runs.
    pub fn excite(&mut self, t_s: f64, e: Excitation) -> Result<(), ControlError> {
        if !e.is_valid() {
            return Err(ControlError::Excitation(e));
        }
        if self.machine.state() != TrialState::Idle
            || !self.have_meas
            || self.excite.is_some()
            || self.jmove.is_some()
            || !self.at_rest()
        {
            return Err(ControlError::State {
                what: if self.excite.is_some() {
                    "excite (an excitation runs)"
                } else if !self.at_rest() || self.jmove.is_some() {
                    "excite (the arm moves)"
                } else if self.have_meas {
                    "excite"
                } else {
                    "excite before the robot's first FRI message"
                },
                state: self.machine.state().name(),
            });
        }
        let hold = if self.have_cmd {
            self.q_cmd
        } else {
            self.q_meas
        };
        self.excite = Some((e, t_s, hold));
        Ok(())
    }

    /// Starts a slow move of the arm to joint `target` (radians) from where
    /// it rests: a minimum-jerk joint move at [`MOVE_TO_LIMIT_SHARE`] of each
    /// joint's speed and acceleration limits (at least 1 s), after which the
    /// commands hold at the target (the camera-robot calibration's tour).
    /// Allowed in `Idle` with the commands at rest, once the robot has sent
    /// a message. Every target stays [`MOVE_TO_MARGIN_RAD`] inside the limits;
    /// a stop ends the move where it is. Returns the move's duration, s.
    ///
    /// # Errors
    ///
    /// [`ControlError::Target`] for a joint value that is not finite or too
    /// near its limit; [`ControlError::State`] when not `Idle`, before the
    /// robot's first message, while the arm moves or an excitation runs.
    pub fn move_to(&mut self, t_s: f64, target: &[f64; JOINTS]) -> Result<f64, ControlError> {
        self.joint_move(t_s, target, MOVE_TO_LIMIT_SHARE, 1.0)
    }

    /// A [`Self::move_to`] move at [`KNOCK_LIMIT_SHARE`] of the joints'
    /// limits (at least [`KNOCK_MIN_S`]): the contact step's knock on the
    /// hanging ball. The same rules and errors.
    ///
    /// # Errors
    ///
    /// As [`Self::move_to`].
    pub fn knock_to(&mut self, t_s: f64, target: &[f64; JOINTS]) -> Result<f64, ControlError> {
        self.joint_move(t_s, target, KNOCK_LIMIT_SHARE, KNOCK_MIN_S)
    }

    fn joint_move(
        &mut self,
        t_s: f64,
        target: &[f64; JOINTS],
        share: f64,
        min_s: f64,
    ) -> Result<f64, ControlError> {
        for (j, (&q, lim)) in target.iter().zip(POSITION_LIMIT_RAD).enumerate() {
            if !(q.is_finite() && q.abs() <= lim - MOVE_TO_MARGIN_RAD) {
                return Err(ControlError::Target(j, q));
            }
        }
        if self.machine.state() != TrialState::Idle
            || !self.have_meas
            || self.excite.is_some()
            || self.jmove.is_some()
            || !self.at_rest()
        {
            return Err(ControlError::State {
                what: if !self.have_meas {
                    "move before the robot's first FRI message"
                } else if self.excite.is_some() {
                    "move (an excitation runs)"
                } else {
                    "move (the arm moves)"
                },
                state: self.machine.state().name(),
            });
        }
        let q0 = if self.have_cmd {
            self.q_cmd
        } else {
            self.q_meas
        };
        let q1 = Joints::from_column_slice(target);
        let dur = move_duration_s(&q0, &q1, share, min_s);
        self.jmove = Some(JointMove {
            q0,
            q1,
            t0: t_s,
            duration_s: dur,
        });
        Ok(dur)
    }

    /// Whether a [`Self::move_to`] move runs.
    pub fn moving_to(&self) -> bool {
        self.machine.state() == TrialState::Idle && self.jmove.is_some()
    }

    /// Whether a calibration's motion runs: an excitation or a move to a
    /// pose (the dead-man watches it; no trial starts meanwhile).
    pub fn calibrating_motion(&self) -> bool {
        self.excite.is_some() || self.moving_to()
    }

    /// Whether an excitation runs ([`Self::excite`]).
    pub fn exciting(&self) -> bool {
        self.excite.is_some()
    }

    /// Whether the commands stand still (the last step commanded no motion).
    pub fn at_rest(&self) -> bool {
        self.v_cmd.iter().all(|v| v.abs() < 1e-9)
    }

    /// Arms a trial with a plan from [`Self::plan`]: builds the filter for
    /// the pendulum at the plan's distance and starts the move home in the
    /// motion's posture; `Armed` once there. Allowed from `Idle`.
    ///
    /// # Errors
    ///
    /// [`ControlError::State`] when not `Idle` or before the robot's first FRI
    /// message; [`ControlError::Params`] or [`ControlError::Filter`] when the plan's
    /// pendulum geometry or the filter is refused.
    pub fn arm(&mut self, t_s: f64, plan: &ArmPlan) -> Result<(), ControlError> {
        if self.machine.state() != TrialState::Idle
            || !self.have_meas
            || self.excite.is_some()
            || self.jmove.is_some()
        {
            return Err(ControlError::State {
                what: if self.have_meas {
                    "arm"
                } else {
                    "arm before the robot's first FRI message"
                },
                state: self.machine.state().name(),
            });
        }
        let mut geometry = PendulumGeometry::new(
            self.model.length_m,
            plan.distance_m,
            self.intercept_height_m,
        )?;
        // The pivot above the believed rest point (with the calibrated offset).
        geometry.pivot_m = plan.intercept_m + Vector3::new(0.0, 0.0, self.model.length_m);
        let mut ekf = Ekf::new(self.ekf_params.clone(), self.model, geometry)?;
        if self.params.learn_frequency {
            ekf.set_constant_priors(self.session.k, None)?;
        }
        let q0 = if self.have_cmd {
            self.q_cmd
        } else {
            self.q_meas
        };
        let q1 = plan.posture.q_home;
        // Duration: at least the configured one, and slow enough for half the
        // speed and acceleration limits (minimum jerk: peak speed 1.875 d/T,
        // peak acceleration 5.77 d/T^2).
        let mut dur = self.params.home_move_time_s;
        for j in 0..JOINTS {
            let d = (q1[j] - q0[j]).abs();
            dur = dur
                .max(1.875 * d / (0.5 * VELOCITY_LIMIT_RADPS[j]))
                .max((5.78 * d / (0.5 * ACCELERATION_LIMIT_RADPS2[j])).sqrt());
        }
        self.machine
            .go(TrialState::Arming)
            .map_err(|_| ControlError::State {
                what: "arm",
                state: self.machine.state().name(),
            })?;
        self.t_state = t_s;
        self.ekf = Some(ekf);
        self.held_sum_m = 0.0;
        self.held_n = 0;
        self.held_skipped = 0;
        self.plan = Some(*plan);
        self.home_m = plan.strike.map_or(self.task_home_m, |s| s.start_m);
        self.commit = None;
        self.prediction = None;
        self.abort_reason = None;
        self.jmove = Some(JointMove {
            q0,
            q1,
            t0: t_s,
            duration_s: dur,
        });
        let _ = self.motion.reset(&self.home_m);
        Ok(())
    }

    /// The magnet let go of the ball at `t_s`: `Armed -> Released`.
    ///
    /// # Errors
    ///
    /// [`ControlError::State`] when the trial is not `Armed`.
    pub fn release(&mut self, t_s: f64) -> Result<(), ControlError> {
        self.machine
            .go(TrialState::Released)
            .map_err(|_| ControlError::State {
                what: "release",
                state: self.machine.state().name(),
            })?;
        self.t_state = t_s;
        self.t_release = t_s;
        self.t_last_measurement = t_s;
        self.last_doubt = None;
        Ok(())
    }

    /// Why the newest plan of this trial's motion was not confident enough
    /// to commit (`Doubt::None`: it was; `None`: no plan since the release).
    pub fn last_doubt(&self) -> Option<crate::ekf::Doubt> {
        self.last_doubt
    }

    /// Back to `Idle` from `Done`, `Abort` or `Armed` (holding where it is).
    ///
    /// # Errors
    ///
    /// [`ControlError::State`] when the trial is not in `Done`, `Abort` or `Armed`.
    pub fn reset(&mut self, t_s: f64) -> Result<(), ControlError> {
        self.machine
            .go(TrialState::Idle)
            .map_err(|_| ControlError::State {
                what: "reset",
                state: self.machine.state().name(),
            })?;
        self.t_state = t_s;
        self.jmove = None;
        self.end_trial_learning();
        Ok(())
    }

    /// One control step (see the module documentation). `measurements` are the
    /// camera measurements that arrived since the last step.
    pub fn step<I: IntoIterator<Item = Sighting>>(
        &mut self,
        input: &StepInput,
        measurements: I,
        out: &mut StepOutput,
    ) {
        let t = input.t_s;
        let dt = match self.t_last {
            Some(tl) if t > tl => t - tl,
            _ => self.latency.period_s(),
        };
        self.t_last = Some(t);
        self.counters.steps += 1;
        self.q_meas = Joints::from(input.q_measured_rad);
        self.have_meas = true;
        let beyond = self
            .q_meas
            .iter()
            .zip(POSITION_LIMIT_RAD)
            .any(|(q, lim)| q.is_nan() || q.abs() > lim);
        if beyond {
            self.counters.measured_limit_violations += 1;
        }
        if !self.have_cmd {
            self.q_cmd = self.q_meas;
        }
        if self.have_cmd && input.commanding {
            self.latency.observe(&input.q_measured_rad);
        }
        self.fold_measurements(t, measurements);

        let state = self.machine.state();
        if !input.commanding {
            self.counters.not_commanding += 1;
            if !matches!(
                state,
                TrialState::Idle | TrialState::Armed | TrialState::Done | TrialState::Aborted
            ) {
                self.abort(t, AbortReason::FriLost);
            }
        }
        let mut target = self.q_cmd;
        match self.machine.state() {
            TrialState::Idle => {
                if let Some(m) = self.jmove {
                    // A move to a pose (`move_to`); the robot leaving
                    // COMMANDING_ACTIVE ends it where it is.
                    if !input.commanding {
                        self.jmove = None;
                    } else if m.done(t) {
                        self.jmove = None;
                        target = m.q1;
                    } else {
                        target = m.at(t);
                    }
                }
                if let Some((e, t0, hold)) = self.excite {
                    target = hold;
                    target[e.joint] += e.offset_rad(t - t0);
                    if t - t0 >= e.duration_s || !input.commanding {
                        self.excite = None;
                    }
                }
            }
            TrialState::Armed | TrialState::Done => {}
            TrialState::Arming => {
                if let Some(m) = self.jmove {
                    target = m.at(t);
                    let settled = (self.q_meas - m.q1).amax() < 0.2f64.to_radians();
                    if m.done(t) && settled {
                        self.jmove = None;
                        target = m.q1;
                        self.go(t, TrialState::Armed);
                    } else if t - m.t0 > m.duration_s + 5.0 {
                        self.abort(t, AbortReason::GuardTripped);
                    }
                }
            }
            TrialState::Released => {
                if self.ekf.as_ref().is_some_and(Ekf::is_initialised) {
                    self.go(t, TrialState::Tracking);
                }
                self.check_camera(t);
            }
            TrialState::Tracking => {
                self.check_camera(t);
                if self.machine.state() == TrialState::Tracking {
                    self.learn_from_filter();
                    self.try_commit(t, dt);
                }
            }
            TrialState::Intercepting | TrialState::Holding => {
                if let Some(q) = self.motion_command(t, dt) {
                    target = q;
                }
            }
            TrialState::Aborted => {
                // Safe stop: the commanded velocity decays at half the
                // acceleration limits until the arm rests.
                for j in 0..JOINTS {
                    let a = 0.5 * ACCELERATION_LIMIT_RADPS2[j] * dt;
                    let v = self.v_cmd[j];
                    self.v_cmd[j] = if v.abs() <= a {
                        0.0
                    } else {
                        v - a * v.signum()
                    };
                    target[j] = self.q_cmd[j] + self.v_cmd[j] * dt;
                }
            }
        }
        let q = if input.commanding {
            self.guard(&target, dt)
        } else {
            self.q_meas
        };
        if input.commanding {
            self.v_cmd = (q - self.q_cmd) / dt;
        } else {
            self.v_cmd = Joints::zeros();
        }
        self.q_cmd = q;
        self.have_cmd = true;
        if input.commanding {
            self.latency.commanded(&q.into());
        }
        out.q_command_rad = q.into();
        out.state = self.machine.state();
    }

    fn fold_measurements<I: IntoIterator<Item = Sighting>>(&mut self, t: f64, meas: I) {
        // From the release on, the filter follows the ball also after the
        // trial (done, aborted, back to idle): the ball keeps swinging, and the
        // dashboard's estimate and its band continue between trials. A new
        // filter is built when the next trial arms.
        let state = self.machine.state();
        let active = !matches!(state, TrialState::Arming | TrialState::Armed);
        let gate = (HELD_GATE_SIGMAS * self.ekf_params.measurement_noise_m).max(HELD_GATE_MIN_M);
        for m in meas {
            self.counters.measurements += 1;
            if state == TrialState::Armed && m.lateral_m.is_finite() {
                self.held_sum_m += m.lateral_m;
                self.held_n += 1;
            }
            if !active {
                continue;
            }
            if self.params.skip_held_detections
                && self.held_n >= HELD_MIN_DETECTIONS
                && m.t_capture_s >= self.t_release
                && self.ekf.as_ref().is_some_and(|e| !e.is_initialised())
                && (m.lateral_m - self.held_sum_m / f64::from(self.held_n)).abs() <= gate
            {
                // The magnet has not let go yet.
                self.held_skipped += 1;
                continue;
            }
            let Some(ekf) = self.ekf.as_mut() else {
                continue;
            };
            if m.t_capture_s < self.t_release {
                // Captured while the magnet still held the ball.
                continue;
            }
            if m.t_capture_s > t + 1e-9 {
                self.counters.rejected += 1;
                continue;
            }
            match ekf.measure(m.t_capture_s, m.lateral_m) {
                Ok(
                    crate::ekf::MeasureOutcome::Rejected { .. }
                    | crate::ekf::MeasureOutcome::TooOld,
                ) => {
                    self.counters.rejected += 1;
                }
                Ok(_) => {
                    self.counters.fused += 1;
                    self.t_last_measurement = self.t_last_measurement.max(m.t_capture_s);
                }
                Err(_) => self.counters.rejected += 1,
            }
        }
    }

    fn check_camera(&mut self, t: f64) {
        if t - self.t_last_measurement
            > self.params.camera_timeout_s + self.scenario_latency_allowance()
        {
            self.abort(t, AbortReason::CameraLost);
        } else if t - self.t_release > self.params.track_timeout_s {
            self.abort(t, AbortReason::PredictionTimeout);
        }
    }

    /// Capture-to-arrival time of measurements is not known to the controller;
    /// allow a generous fixed 0.2 s on top of the timeout.
    fn scenario_latency_allowance(&self) -> f64 {
        0.2
    }

    fn try_commit(&mut self, t: f64, dt: f64) {
        let (Some(ekf), Some(plan)) = (self.ekf.as_ref(), self.plan.as_ref()) else {
            return;
        };
        let robot_latency_s = self.latency.latency_s();
        let camera_offset_s = self.camera_offset_s();
        let trim_s = self.arrival_trim_s();
        self.learning.trim_used_s = trim_s;
        // Stamps late by the camera offset put the predicted pass as late;
        // a robot that arrives late by the trim starts as much earlier.
        let latency_s = (robot_latency_s + camera_offset_s + trim_s).max(0.0);
        let duration_s = (plan.duration_s + plan.arrival_offset_s).max(0.0);
        let filter = ekf.counters();
        let posterior = ekf.posterior();
        if let (Some(c), Some((pt, px, _))) = (self.prediction.as_ref(), posterior.as_ref()) {
            let same = c.filter == filter
                && c.posterior_t_s == *pt
                && c.posterior_x == *px
                && c.duration_s == duration_s
                && c.latency_s == latency_s;
            if same && c.start_s >= t + dt {
                self.counters.predictions_reused += 1;
                return;
            }
        }
        let req = MotionRequest {
            lateral_m: 0.0,
            duration_s,
            latency_s,
            pass_index: 0,
            // A strike meets the passes that run against its stroke.
            direction: if plan.strike.is_some() {
                if STRIKE_RETURN_SIGN < 0.0 {
                    PassDirection::TowardsPositiveY
                } else {
                    PassDirection::TowardsNegativeY
                }
            } else {
                PassDirection::Any
            },
        };
        let offset = plan.arrival_offset_s;
        let mp = match ekf.plan_motion(t, &req) {
            Ok(Some(mp)) => mp,
            Ok(None) => {
                self.prediction = None;
                return;
            }
            Err(_) => {
                self.prediction = None;
                self.counters.prediction_errors += 1;
                return;
            }
        };
        self.last_doubt = Some(mp.doubt);
        self.prediction = posterior.map(|(pt, px, _)| PredictionCache {
            filter,
            posterior_t_s: pt,
            posterior_x: px,
            duration_s,
            latency_s,
            start_s: mp.start_s,
        });
        if !mp.confident || mp.start_s >= t + dt {
            return;
        }
        // Commit: the motion's t = 0 is mp.start_s (within this cycle).
        let orientation = UnitQuaternion::from_rotation_matrix(&plan.posture.orientation);
        let target = mp.pass.ball_m;
        // A strike runs its whole cycle S -> B (through the believed
        // intercept point, where the arm was armed for it); the contact
        // comes at its phase, `duration_s` after the start.
        let begun = match plan.strike {
            Some(s) => self
                .motion
                .begin(&s.start_m, &s.end_m, &orientation, s.cycle_s),
            None => self
                .motion
                .begin(&self.home_m, &target, &orientation, plan.duration_s),
        };
        if begun.is_err() {
            self.counters.motion_errors += 1;
            self.abort(t, AbortReason::Infeasible);
            return;
        }
        self.motion.sample(&mut self.sample);
        self.commit = Some(Commit {
            t_commit_s: t,
            motion_start_s: mp.start_s,
            arrival_offset_s: offset,
            duration_s: plan.duration_s,
            predicted_pass_s: mp.pass.t_s,
            predicted_pass_std_s: mp.pass.time_std_s,
            predicted_ball_m: mp.pass.ball_m,
            latency_s: robot_latency_s,
            camera_offset_s,
            trim_s,
            direction_positive: mp.pass.lateral_velocity_mps > 0.0,
            rebound: plan
                .strike
                .and_then(|k| self.predicted_rebound(&k, mp.pass.lateral_velocity_mps)),
        });
        self.go(t, TrialState::Intercepting);
    }

    /// A strike's rebound as the controller predicts it at its commit
    /// (`control::rebound`): the stroke's planned speed along the return,
    /// the filter's predicted ball speed at the pass, the believed
    /// restitution, and the filter's frequency and damping (the beliefs'
    /// when it has none).
    fn predicted_rebound(&self, k: &StrikeArm, ball_in_mps: f64) -> Option<PredictedRebound> {
        let believed_k = self.model.gravity_mps2 / self.model.length_m.max(1e-6);
        let (kk, alpha) = self
            .ekf
            .as_ref()
            .and_then(Ekf::posterior)
            .map_or((believed_k, self.model.damping_per_s), |(_, x, _)| {
                (x[crate::ekf::model::K], x[crate::ekf::model::ALPHA])
            });
        let finite_pos = |v: f64, or: f64| if v.is_finite() && v > 0.0 { v } else { or };
        PredictedRebound::new(
            k.restitution,
            k.speed_mps * k.direction.y.hypot(k.direction.x),
            ball_in_mps,
            finite_pos(kk, believed_k),
            if alpha.is_finite() && alpha >= 0.0 {
                alpha
            } else {
                self.model.damping_per_s
            },
        )
    }

    /// Re-times the motion to the filter's latest prediction of the committed pass.
    fn refine(&mut self, t: f64) {
        let (Some(ekf), Some(c)) = (self.ekf.as_ref(), self.commit.as_ref()) else {
            return;
        };
        let dir = if c.direction_positive {
            PassDirection::TowardsPositiveY
        } else {
            PassDirection::TowardsNegativeY
        };
        let mut buf = [crate::ekf::Crossing::default(); 1];
        let from = (c.predicted_pass_s - 0.3).max(t);
        match ekf.crossings(from, 0.0, dir, &mut buf) {
            Ok(1) if (buf[0].t_s - c.predicted_pass_s).abs() < 0.2 => {
                // As at the commit: the robot's latency (its latest
                // estimate), the camera's offset and the arrival trim.
                let arrival = buf[0].t_s
                    - (self.latency.latency_s() + c.camera_offset_s + c.trim_s).max(0.0)
                    - c.motion_start_s
                    - c.arrival_offset_s;
                // A strike's contact is its cycle's phase `contact_fraction`:
                // the cycle re-timed so that its contact comes at the pass.
                let arrival = self
                    .plan
                    .and_then(|p| p.strike)
                    .map_or(arrival, |s| arrival / s.contact_fraction);
                if (arrival - self.motion.arrival_time_s()).abs() > 1e-5
                    && self.motion.retime(arrival).is_ok()
                {
                    self.counters.retimes += 1;
                }
            }
            Ok(_) => {}
            Err(_) => self.counters.prediction_errors += 1,
        }
    }

    fn motion_command(&mut self, t: f64, dt: f64) -> Option<Joints> {
        let c = self.commit?;
        let plan = self.plan?;
        if t <= c.motion_start_s {
            return Some(plan.posture.q_home);
        }
        if self.machine.state() == TrialState::Intercepting {
            // The swing until shortly before the pass (then the tool may touch
            // the ball) still teaches the session's constants.
            let before_pass = self
                .ekf
                .as_ref()
                .and_then(Ekf::posterior)
                .is_some_and(|(tp, _, _)| tp < c.predicted_pass_s - 0.2);
            if before_pass {
                self.learn_from_filter();
            }
            if self.params.retime {
                self.refine(t);
            }
        }
        let h = (t - c.motion_start_s).min(dt);
        if self.motion.step(h, None, &mut self.sample).is_err() {
            self.counters.motion_errors += 1;
        }
        let mut q = self.q_cmd;
        if plan
            .posture
            .joints_for_point(&self.sample.position_m, &self.q_cmd, &mut q)
            .is_err()
        {
            self.counters.ik_failures += 1;
            self.abort(t, AbortReason::IkFailed);
            return None;
        }
        match self.machine.state() {
            TrialState::Intercepting if self.sample.phase == MotionPhase::Arrived => {
                self.go(t, TrialState::Holding);
            }
            TrialState::Holding if t - self.t_state >= self.params.hold_time_s => {
                self.go(t, TrialState::Done);
            }
            _ => {}
        }
        Some(q)
    }

    /// The command guard: finite, inside the position limits less the margin,
    /// and no joint stepping faster than the speed limit allows.
    fn guard(&mut self, target: &Joints, dt: f64) -> Joints {
        let margin = self.params.guard_margin_deg.to_radians();
        let mut q = *target;
        if !q.iter().all(|v| v.is_finite()) {
            self.counters.guard_non_finite += 1;
            return self.q_cmd;
        }
        let mut pos_clamped = false;
        let mut step_clamped = false;
        for j in 0..JOINTS {
            let lim = POSITION_LIMIT_RAD[j] - margin;
            if q[j].abs() > lim {
                q[j] = q[j].clamp(-lim, lim);
                pos_clamped = true;
            }
            let max_step = VELOCITY_LIMIT_RADPS[j] * self.params.guard_speed_ratio * dt;
            let step = q[j] - self.q_cmd[j];
            if step.abs() > max_step {
                q[j] = self.q_cmd[j] + max_step * step.signum();
                step_clamped = true;
            }
        }
        self.counters.guard_position_clamps += u64::from(pos_clamped);
        self.counters.guard_step_clamps += u64::from(step_clamped);
        q
    }

    /// The tool point of a joint vector (forward kinematics with this tool).
    pub fn tool_point(&self, q: &[f64; JOINTS]) -> Vector3<f64> {
        tool_pose(&Joints::from(*q), &self.tool).translation.vector
    }

    /// The tool's axis (its frame's z, base frame) at a joint vector.
    pub fn tool_axis(&self, q: &[f64; JOINTS]) -> Vector3<f64> {
        tool_pose(&Joints::from(*q), &self.tool)
            .rotation
            .matrix()
            .column(2)
            .into_owned()
    }
}

/// Runs the motion generator once, offline, over a strike's whole cycle at
/// the FRI period: returns when its progress reaches the contact point
/// (the approach length) minus the stroke's contact time, seconds, and its
/// path speed there, m/s.
fn generator_contact(
    timing: &TimingParams,
    stroke: &Stroke,
    posture: &Posture,
    period_s: f64,
) -> Result<(f64, f64), ControlError> {
    let mut m = TimedMotion::new(timing.clone())?;
    let q = UnitQuaternion::from_rotation_matrix(&posture.orientation);
    let (start, end) = (stroke.request.start_m, stroke.request.end_m);
    m.begin(&start, &end, &q, stroke.request.movement_time_s)?;
    let dir = (end - start).normalize();
    let n = ((stroke.request.movement_time_s * 1.3) / period_s).ceil() as usize;
    let mut s = MotionSample::default();
    let (mut t0, mut p0, mut v0) = (0.0, 0.0, 0.0);
    for k in 1..=n {
        m.step(period_s, None, &mut s)?;
        let t1 = k as f64 * period_s;
        let p1 = (s.position_m - start).dot(&dir);
        if p1 >= stroke.approach_m {
            let f = ((stroke.approach_m - p0) / (p1 - p0).max(1e-12)).clamp(0.0, 1.0);
            let speed = v0 + f * (s.path_speed_mps - v0);
            return Ok((t0 + f * (t1 - t0) - stroke.contact_s, speed));
        }
        (t0, p0, v0) = (t1, p1, s.path_speed_mps);
    }
    // The generator never reached the contact point: time it as planned.
    Ok((0.0, stroke.speed_mps))
}

/// Runs the motion generator once, offline, over the planned motion at the FRI
/// period and fits the ideal profile to its progress (CONTRACT.md's arrival):
/// returns fitted arrival minus nominal arrival, seconds. With `settle_m > 0`
/// arrival is instead when the progress settles within `settle_m` of the end.
fn generator_arrival_offset(
    timing: &TimingParams,
    start: &Vector3<f64>,
    end: &Vector3<f64>,
    posture: &Posture,
    duration_s: f64,
    period_s: f64,
    settle_m: f64,
) -> Result<f64, ControlError> {
    let mut m = TimedMotion::new(timing.clone())?;
    let q = UnitQuaternion::from_rotation_matrix(&posture.orientation);
    m.begin(start, end, &q, duration_s)?;
    let dir = (end - start).normalize();
    let n = ((duration_s * 1.3) / period_s).ceil() as usize;
    let mut ts = Vec::with_capacity(n + 1);
    let mut ps = Vec::with_capacity(n + 1);
    ts.push(0.0);
    ps.push(0.0);
    let mut s = MotionSample::default();
    for k in 1..=n {
        m.step(period_s, None, &mut s)?;
        ts.push(k as f64 * period_s);
        ps.push((s.position_m - start).dot(&dir));
    }
    if settle_m > 0.0 {
        let d = (end - start).norm();
        if let Some(i) = ps.iter().rposition(|p| d - p > settle_m) {
            if i + 1 < ps.len() {
                let (ga, gb) = (d - ps[i], d - ps[i + 1]);
                let f = if ga > gb {
                    (ga - settle_m) / (ga - gb)
                } else {
                    1.0
                };
                return Ok(ts[i] + f.clamp(0.0, 1.0) * (ts[i + 1] - ts[i]) - duration_s);
            }
        }
        return Ok(0.0);
    }
    let (t0, dur, _) = super::judge::fit_profile(
        ProfileKind::Hopf,
        (end - start).norm(),
        &ts,
        &ps,
        0.0,
        duration_s,
    );
    Ok(t0 + dur - duration_s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn planning_finds_the_generators_arrival_and_refuses_what_cannot_be_reached() {
        let s = Beliefs::default();
        let plan = Controller::plan(&s, 0.6).unwrap();
        assert_eq!(plan.duration_s, 1.5);
        // The Hopf generator's best-fitting ideal profile ends a few ms early.
        assert!(plan.arrival_offset_s.abs() < 0.05, "{plan:?}");
        // 1.1 m is out of reach at any duration.
        // The error keeps the inverse kinematics' numbers.
        let err = Controller::plan(&s, 1.1).unwrap_err();
        assert!(err.is_infeasible(), "{err}");
        assert!(
            matches!(
                err,
                ControlError::Plan(PlanError::Unreachable {
                    ik: Some(crate::kinematics::analytic::IkError::OutOfReach { .. }),
                    ..
                })
            ),
            "{err:?}"
        );
        assert!(
            err.to_string()
                .starts_with("infeasible motion: unreachable"),
            "{err}"
        );
        // Too fast without the shortest-feasible fallback: refused, naming the joint.
        let mut fast = Beliefs::default();
        fast.task.movement_time_s = 0.8;
        fast.control.allow_shortest_feasible = false;
        let err = Controller::plan(&fast, 0.8).unwrap_err();
        assert!(err.is_infeasible(), "{err}");
        let ControlError::Infeasible(Infeasibility::TooFast {
            joint,
            duration_s,
            shortest_feasible_s,
            ..
        }) = err
        else {
            panic!("{err:?}")
        };
        assert_eq!(duration_s, 0.8);
        assert!(shortest_feasible_s > 1.3, "{shortest_feasible_s}");
        assert!(joint < JOINTS);
        let err = err.to_string();
        assert!(err.contains("shortest feasible duration"), "{err}");
        fast.control.allow_shortest_feasible = true;
        let plan = Controller::plan(&fast, 0.8).unwrap();
        assert!(plan.duration_s > 1.3, "{plan:?}");
    }

    /// Arms `c` with a perfect robot (measured = commanded) until `Armed`;
    /// returns the time and the joints.
    fn arm_perfectly_at(c: &mut Controller, plan: &ArmPlan, t0: f64) -> (f64, [f64; JOINTS]) {
        let mut q = [0.0, 0.5, 0.0, -1.4, 0.0, 1.2, 0.0];
        let mut out = StepOutput::default();
        let mut t = t0;
        let input = |t, q| StepInput {
            t_s: t,
            q_measured_rad: q,
            commanding: true,
        };
        c.step(&input(t, q), std::iter::empty(), &mut out);
        c.arm(t, plan).unwrap();
        while c.state() != TrialState::Armed && t < t0 + 20.0 {
            t += 0.005;
            c.step(&input(t, q), std::iter::empty(), &mut out);
            q = out.q_command_rad;
        }
        assert_eq!(c.state(), TrialState::Armed);
        (t, q)
    }

    /// Releases the ball (the coil goes off at the returned time; the ball
    /// falls `delay_s` later) and runs 2.4 s with frames whose stamps are
    /// `offset_s` late.
    fn release_and_track(c: &mut Controller, s: &Beliefs, delay_s: f64, offset_s: f64) {
        release_and_track_at(c, s, delay_s, offset_s, 0.0);
    }

    /// [`release_and_track`] arming at `t0`; returns the time it ended.
    fn release_and_track_at(
        c: &mut Controller,
        s: &Beliefs,
        delay_s: f64,
        offset_s: f64,
        t0: f64,
    ) -> f64 {
        release_and_track_for(c, s, delay_s, offset_s, t0, 2.4)
    }

    /// [`release_and_track_at`] for `track_s` after the release.
    fn release_and_track_for(
        c: &mut Controller,
        s: &Beliefs,
        delay_s: f64,
        offset_s: f64,
        t0: f64,
        track_s: f64,
    ) -> f64 {
        let (mut t, mut q) = arm_perfectly_at(c, &Controller::plan(s, 0.6).unwrap(), t0);
        let model = PendulumModel::from_params(&s.pendulum).unwrap();
        let geometry =
            PendulumGeometry::new(model.length_m, 0.6, s.task.intercept_height_m).unwrap();
        let mut truth =
            crate::pendulum::PendulumSim::held_at(model, geometry, 25f64.to_radians(), t).unwrap();
        let held = truth.lateral_m();
        let mut out = StepOutput::default();
        // The camera sees the ball hang on the magnet while armed.
        for i in 0..10 {
            t += 0.033;
            let input = StepInput {
                t_s: t,
                q_measured_rad: q,
                commanding: true,
            };
            let m = Sighting {
                t_capture_s: t - 0.035 + offset_s + 1e-4 * f64::from(i % 3),
                lateral_m: held,
            };
            c.step(&input, [m], &mut out);
            q = out.q_command_rad;
        }
        let t_pin = t;
        c.release(t_pin).unwrap();
        truth.release(t_pin + delay_s).unwrap();
        let mut next_frame = t_pin + 0.01;
        let mut frames: Vec<(f64, Sighting)> = Vec::new();
        while t < t_pin + track_s {
            t += 0.005;
            while next_frame <= t {
                let lateral_m = if next_frame < t_pin + delay_s {
                    held
                } else {
                    truth.advance_to(next_frame).unwrap();
                    truth.lateral_m()
                };
                frames.push((
                    next_frame + 0.035,
                    Sighting {
                        t_capture_s: next_frame + offset_s,
                        lateral_m,
                    },
                ));
                next_frame += 1.0 / 30.0;
            }
            let ready: Vec<Sighting> = frames
                .iter()
                .filter(|(avail, _)| *avail <= t)
                .map(|(_, m)| *m)
                .collect();
            frames.retain(|(avail, _)| *avail > t);
            let input = StepInput {
                t_s: t,
                q_measured_rad: q,
                commanding: true,
            };
            c.step(&input, ready, &mut out);
            q = out.q_command_rad;
        }
        t
    }

    fn strike_beliefs(speed_mps: f64) -> Beliefs {
        let mut s = Beliefs::default();
        s.task.mode = TaskMode::Strike;
        s.task.strike_speed_mps = speed_mps;
        s.task.strike_direction_deg = 20.0;
        s
    }

    /// Strike mode plans the stroke through the intercept point (the arm
    /// armed at its start `S`, the contact `movement_time_s` after the
    /// stroke's start, the generator timed for it) and refuses, before
    /// anything moves, a stroke the arm cannot run.
    #[test]
    fn a_strike_is_planned_through_the_intercept_point_or_refused_with_its_reason() {
        let s = strike_beliefs(0.5);
        let plan = Controller::plan(&s, 0.6).unwrap();
        let k = plan.strike.expect("a strike plan");
        let p = s.task.intercept_m(0.6);
        assert_eq!(plan.duration_s, s.task.movement_time_s);
        assert!((k.start_m + k.direction * k.approach_m - p).norm() < 1e-9);
        // The direction: in the swing plane, rising 20 degrees, returning
        // the ball towards -y.
        assert!(k.direction.x.abs() < 1e-12 && k.direction.y < 0.0);
        assert!((k.direction.z.asin().to_degrees() - 20.0).abs() < 1e-9);
        // The posture starts at S: the arm waits there, armed.
        let c = Controller::new(&s, 0.005).unwrap();
        let at_home = c.tool_point(&plan.posture.q_home.into());
        assert!(
            (at_home - k.start_m).norm() < 1e-6,
            "{at_home} vs {}",
            k.start_m
        );
        // The Hopf dynamics reach the contact point within a few ms of the
        // plan, at about the planned speed.
        assert!(
            plan.arrival_offset_s.abs() < 0.02,
            "{}",
            plan.arrival_offset_s
        );
        assert!(
            (k.generator_speed_mps - 0.5).abs() < 0.05,
            "{}",
            k.generator_speed_mps
        );
        // Horizontal: the arm would wait at S in the swing's way.
        let mut flat = strike_beliefs(0.5);
        flat.task.strike_direction_deg = 0.0;
        let e = Controller::plan(&flat, 0.6).unwrap_err();
        assert!(
            matches!(
                e,
                ControlError::Strike {
                    why: StrikeRefusal::InTheSwing { .. },
                    ..
                }
            ),
            "{e:?}"
        );
        // Too fast for the arm: refused as infeasible, naming why.
        let e = Controller::plan(&strike_beliefs(3.0), 0.6).unwrap_err();
        assert!(e.is_infeasible(), "{e}");
        assert!(matches!(e, ControlError::Strike { .. }), "{e:?}");
        assert!(e.to_string().contains("infeasible strike at 3 m/s"), "{e}");
    }

    /// A strike trial commits the stroke so that the contact (not the end
    /// of the cycle) comes at the predicted pass, on a pass against the
    /// stroke; the tool is at the intercept point then, moving at the
    /// strike speed along the strike direction, and every command stays
    /// inside the limits.
    #[test]
    fn a_strike_meets_the_predicted_pass_at_its_contact_with_the_planned_speed() {
        let s = strike_beliefs(0.5);
        let plan = Controller::plan(&s, 0.6).unwrap();
        let k = plan.strike.unwrap();
        let mut c = Controller::new(&s, 0.005).unwrap();
        // Tracked up to 1 s after the release: committed (the stroke's
        // start), the contact still ahead.
        let mut t = release_and_track_for(&mut c, &s, 0.0, 0.0, 0.0, 1.0);
        let commit = *c.commit().expect("committed");
        assert!(commit.direction_positive, "a pass towards +y");
        let contact = c.planned_contact_s().unwrap();
        assert!(contact > t + 0.5, "contact at {contact}, now {t}");
        let latency = commit.latency_s + commit.camera_offset_s + commit.trim_s;
        assert!(
            (contact - (commit.predicted_pass_s - latency)).abs() < 0.01,
            "contact {contact} vs pass {} less {latency}",
            commit.predicted_pass_s
        );
        // Run on (no more frames) through the contact to the end.
        let mut q: [f64; JOINTS] = (*c.q_command()).into();
        let mut out = StepOutput::default();
        let mut near: Option<(f64, Vector3<f64>, Vector3<f64>)> = None;
        let mut prev = c.tool_point(&q);
        while c.state() != TrialState::Done && t < contact + 3.0 {
            t += 0.005;
            let input = StepInput {
                t_s: t,
                q_measured_rad: q,
                commanding: true,
            };
            c.step(&input, std::iter::empty(), &mut out);
            q = out.q_command_rad;
            let at = c.tool_point(&q);
            let v = (at - prev) / 0.005;
            prev = at;
            if near.is_none_or(|(tn, _, _)| (t - contact).abs() < (tn - contact).abs()) {
                near = Some((t, at, v));
            }
        }
        assert_eq!(c.state(), TrialState::Done);
        assert_eq!(c.counters().limit_violations(), 0);
        let (_, at, v) = near.unwrap();
        let p = plan.intercept_m;
        assert!((at - p).norm() < 0.01, "{at} vs {p}");
        assert!((v.norm() - 0.5).abs() < 0.05, "{v}");
        assert!(v.normalize().dot(&k.direction) > 0.99, "{v}");
        // The cycle ended at rest at B.
        assert!((c.tool_point(&q) - k.end_m).norm() < 0.005);
    }

    /// A strike's commit carries the rebound the controller predicts from
    /// its beliefs: the stroke's speed along the return, the filter's pass
    /// speed (a 25 degree release on 1.93 m passes at most at
    /// `2 sqrt(g l) sin(12.5 deg)` = 1.88 m/s; the pass towards `+y` is the
    /// second, about 2.1 s on: `e^(-0.015 * 2.1)` less), the believed restitution
    /// (`pendulum.contact_restitution`) and frequency; a stop's carries none.
    #[test]
    fn a_strikes_commit_predicts_its_rebound_from_the_beliefs() {
        for e in [0.0, 0.5] {
            let mut s = strike_beliefs(0.5);
            s.pendulum.contact_restitution = e;
            let mut c = Controller::new(&s, 0.005).unwrap();
            release_and_track_for(&mut c, &s, 0.0, 0.0, 0.0, 1.0);
            let k = c
                .commit()
                .expect("committed")
                .rebound
                .expect("a prediction");
            let u = 0.5 * 20f64.to_radians().cos();
            assert!((k.tool_return_speed_mps - u).abs() < 1e-9, "{k:?}");
            let v_in = 1.8836 * (-0.015f64 * 2.1).exp();
            assert!((k.ball_in_speed_mps - v_in).abs() < 0.02, "{k:?}");
            assert_eq!(k.restitution, e);
            let expected = (1.0 + e) * u + e * k.ball_in_speed_mps;
            assert!((k.ball_speed_mps - expected).abs() < 1e-9, "{k:?}");
            let w = (9.81f64 / 1.93).sqrt();
            assert!((k.omega_radps - w).abs() < 0.01 * w, "{k:?}");
            // A quarter period out, v_out / w high (a little less: damping).
            assert!(k.amplitude_m < k.ball_speed_mps / k.omega_radps, "{k:?}");
            assert!(
                k.amplitude_m > 0.95 * k.ball_speed_mps / k.omega_radps,
                "{k:?}"
            );
        }
        let s = Beliefs::default();
        let mut c = Controller::new(&s, 0.005).unwrap();
        release_and_track(&mut c, &s, 0.0, 0.0);
        assert_eq!(c.commit().expect("committed").rebound, None);
    }

    /// A camera whose frames all come later than the filter may plan on
    /// (`max_measurement_age_s` below the camera's 35 ms): no commit, and the
    /// controller says why (what a trial that times out reports); a camera
    /// on time commits, and its last plan was confident.
    #[test]
    fn the_last_doubt_says_why_no_motion_was_committed() {
        let mut s = Beliefs::default();
        s.ekf.max_measurement_age_s = 0.01;
        let mut c = Controller::new(&s, 0.005).unwrap();
        assert_eq!(c.last_doubt(), None);
        release_and_track(&mut c, &s, 0.0, 0.0);
        assert!(c.commit.is_none(), "committed on stale measurements");
        assert_eq!(c.last_doubt(), Some(crate::ekf::Doubt::StaleMeasurement));
        let s = Beliefs::default();
        let mut c = Controller::new(&s, 0.005).unwrap();
        release_and_track(&mut c, &s, 0.0, 0.0);
        assert!(c.commit.is_some(), "no commit on a camera on time");
        assert_eq!(c.last_doubt(), Some(crate::ekf::Doubt::None));
    }

    #[test]
    fn contacts_read_the_camera_offset_whatever_the_release_delay_and_learn_the_magnet() {
        let mut s = Beliefs::default();
        s.control.camera_offset_from_release = true;
        s.control.camera_offset_from_contact = true;
        // Believed 15 +- 7 ms; this magnet lets go 60..90 ms after the coil.
        s.control.release_delay_prior_ms = 15.0;
        s.control.release_delay_std_ms = 7.0;
        s.control.learn_frequency = true;
        s.ekf.estimate_frequency = true;
        let delays = [0.060, 0.090, 0.075, 0.080];
        // The stamps are 8 ms late.
        let offset = 0.008;
        let mut c = Controller::new(&s, 0.005).unwrap();
        let mut t = 0.0;
        let mut first_release_only = None;
        for d in delays {
            t = release_and_track_at(&mut c, &s, d, offset, t) + 0.5;
            first_release_only.get_or_insert(c.camera_offset_s());
            // The measured judge's contact shows the offset (1 ms); a
            // second reading of the same trial is not taken, nor garbage.
            c.learn_from_contact(offset, 0.001);
            c.learn_from_contact(0.1, 0.001);
            c.learn_from_contact(f64::NAN, 0.001);
            c.abort(t, AbortReason::StopRequested);
            c.reset(t).unwrap();
            t += 0.5;
        }
        // The releases alone read delay + offset - 15 ms, shrunk by the prior: ~27 ms off.
        let first = first_release_only.unwrap();
        assert!((first - offset).abs() > 0.02, "{first}");
        assert_eq!(c.session_memory().contact_n, 4);
        let got = c.camera_offset_s();
        assert!((got - offset).abs() < 0.0015, "camera offset {got}");
        // The magnet: its mean and spread, from the releases paired with the contacts.
        let (mean, sd) = c.magnet_memory().learned().expect("4 releases");
        assert!((mean - 0.07625).abs() < 0.004, "release delay {mean}");
        assert!(sd > 0.005 && sd < 0.02, "spread {sd}");
        assert_eq!(c.release_delay_belief_s(), (mean, sd));
        // A reboot: the camera's offset is forgotten, the magnet is not;
        // the next session's first release reads the offset about right.
        c.new_session();
        assert_eq!(c.camera_offset_s(), 0.0);
        assert_eq!(c.magnet_memory().n, 4);
        release_and_track_at(&mut c, &s, 0.070, offset, t);
        let next = c.camera_offset_s();
        assert!((next - offset).abs() < 0.008, "{next}");
        // Off: contacts are ignored.
        s.control.camera_offset_from_contact = false;
        let mut off = Controller::new(&s, 0.005).unwrap();
        off.learn_from_contact(offset, 0.001);
        assert_eq!(off.session_memory().contact_n, 0);
    }

    #[test]
    fn detections_of_a_ball_still_held_are_kept_out_of_the_filter() {
        // This magnet lets go 90 ms after the coil (up to three frames of a
        // ball that has not moved); the stamps are right.
        let delay = 0.090;
        let run = |skip: bool| {
            let mut s = Beliefs::default();
            s.control.skip_held_detections = skip;
            let mut c = Controller::new(&s, 0.005).unwrap();
            release_and_track_at(&mut c, &s, delay, 0.0, 0.0);
            let t_init = c.ekf().and_then(Ekf::initialised_at_s);
            let pass = c.commit().map(|k| k.predicted_pass_s);
            (c.held_skipped(), t_init, pass, c.t_release)
        };
        let (skipped, t_init, pass, t_pin) = run(true);
        // Three held frames, and one or two that moved less than the gate.
        assert!((3..=5).contains(&skipped), "{skipped}");
        // The filter started from detections of the falling ball.
        let t_init = t_init.expect("initialised");
        assert!(t_init > t_pin + delay, "{t_init} vs {}", t_pin + delay);
        // The true first pass of the rest point.
        let s = Beliefs::default();
        let model = PendulumModel::from_params(&s.pendulum).unwrap();
        let geometry =
            PendulumGeometry::new(model.length_m, 0.6, s.task.intercept_height_m).unwrap();
        let mut truth =
            crate::pendulum::PendulumSim::held_at(model, geometry, 25f64.to_radians(), t_pin)
                .unwrap();
        truth.release(t_pin + delay).unwrap();
        // Its passes of the rest point; the predicted one is the nearest.
        let pass = pass.expect("a commit");
        let (mut t, mut y, mut passes) = (t_pin + delay, truth.lateral_m(), Vec::new());
        while t < pass + 1.0 {
            t += 1e-4;
            truth.advance_to(t).unwrap();
            if truth.lateral_m().signum() != y.signum() {
                passes.push(t);
            }
            y = truth.lateral_m();
        }
        let error = |p: f64| {
            passes
                .iter()
                .map(|t| (p - t).abs())
                .fold(f64::INFINITY, f64::min)
        };
        let err_skip = error(pass);
        assert!(err_skip < 0.004, "{err_skip}");
        // Fed to the filter, the held detections start the swing early.
        let (skipped, _, pass, _) = run(false);
        assert_eq!(skipped, 0);
        let err_fed = pass.map_or(f64::INFINITY, error);
        println!(
            "held detections: skipped, pass error {:.2} ms; fed, {:.2} ms",
            err_skip * 1e3,
            err_fed * 1e3
        );
        assert!(err_fed > 2.0 * err_skip, "fed {err_fed} skipped {err_skip}");
    }

    #[test]
    fn contacts_teach_the_robots_lateness_and_the_motion_starts_that_much_earlier() {
        let mut s = Beliefs::default();
        s.control.arrival_trim_from_contact = true;
        let mut c = Controller::new(&s, 0.005).unwrap();
        // The arm arrives 15 ms after the plan (a servo slower than its
        // latency shows); each contact reads what is left after the trim.
        let late = 0.015;
        let mut t = 0.0;
        let mut leads = Vec::new();
        for trial in 0..5 {
            let used = c.arrival_trim_s();
            t = release_and_track_at(&mut c, &s, 0.0, 0.0, t);
            let k = *c.commit().expect("a commit");
            leads.push((k.predicted_pass_s - k.motion_start_s, used));
            c.learn_from_arrival(late - used, 0.001);
            // Once a trial; garbage changes nothing.
            c.learn_from_arrival(0.04, 0.001);
            c.learn_from_arrival(f64::NAN, 0.001);
            c.learn_from_arrival(0.2, 0.001);
            c.learn_from_arrival(0.01, 0.0);
            assert_eq!(c.session_memory().trim_n, trial + 1);
            c.abort(t, AbortReason::StopRequested);
            c.reset(t).unwrap();
            t += 0.5;
        }
        // Five readings of 15 ms (each +-3.2 ms) against the prior 0 +- 10 ms.
        let trim = c.arrival_trim_s();
        assert!((trim - late).abs() < 0.0006, "trim {trim}");
        // Each motion started earlier by the trim it used.
        let (lead0, _) = leads[0];
        for &(lead, used) in &leads[1..] {
            assert!(used > 0.01, "{leads:?}");
            assert!((lead - lead0 - used).abs() < 1e-6, "{leads:?}");
        }
        // A new session starts from the prior (one session is not yet a
        // spread) ...
        c.new_session();
        assert_eq!(c.session_priors().n, 1);
        assert_eq!(c.arrival_trim_s(), 0.0);
        // ... a second one like it makes the earlier sessions' trims the
        // next session's prior.
        for _ in 0..5 {
            let used = c.arrival_trim_s();
            t = release_and_track_at(&mut c, &s, 0.0, 0.0, t);
            c.learn_from_arrival(late - used, 0.001);
            c.abort(t, AbortReason::StopRequested);
            c.reset(t).unwrap();
            t += 0.5;
        }
        c.new_session();
        let (mean, sd) = c.session_priors().trim().expect("two sessions");
        assert!((mean - late).abs() < 0.0006, "{mean}");
        assert_eq!(sd, SessionPriors::MIN_STD_S);
        assert_eq!(c.arrival_trim_s(), mean);
        // Re-timing to the filter's latest prediction keeps the trim: each
        // motion still arrives earlier by the trim it used.
        let mut r = s.clone();
        r.control.retime = true;
        let mut c = Controller::new(&r, 0.005).unwrap();
        let mut t = 0.0;
        let mut leads = Vec::new();
        for _ in 0..4 {
            let used = c.arrival_trim_s();
            t = release_and_track_at(&mut c, &r, 0.0, 0.0, t);
            let k = *c.commit().expect("a commit");
            let arrival = c.planned_arrival_s().expect("committed");
            leads.push((k.predicted_pass_s - arrival, used));
            c.learn_from_arrival(late - used, 0.001);
            c.abort(t, AbortReason::StopRequested);
            c.reset(t).unwrap();
            t += 0.5;
        }
        // (Without the trim in the re-timing, every motion is re-timed back
        // to the untrimmed arrival: the leads would all be equal.)
        let (lead0, _) = leads[0];
        for &(lead, used) in &leads[1..] {
            assert!(used > 0.01, "{leads:?}");
            assert!((lead - lead0 - used).abs() < 1e-4, "{leads:?}");
        }
        // Off, contacts teach nothing.
        s.control.arrival_trim_from_contact = false;
        let mut off = Controller::new(&s, 0.005).unwrap();
        off.learn_from_arrival(late, 0.001);
        assert_eq!(off.session_memory().trim_n, 0);
        assert_eq!(off.arrival_trim_s(), 0.0);
    }

    #[test]
    fn new_beliefs_carry_what_the_session_learned_where_its_basis_holds() {
        let mut s = Beliefs::default();
        s.control.camera_offset_from_release = true;
        s.control.release_delay_prior_ms = 15.0;
        s.control.release_delay_std_ms = 0.5;
        s.control.learn_frequency = true;
        s.ekf.estimate_frequency = true;
        let mut old = Controller::new(&s, 0.005).unwrap();
        // The robot answers 25 ms late (prior 0): a moving joint teaches it.
        let lag = 5;
        let cmd = |i: usize| {
            let mut q = [0.0; JOINTS];
            q[0] = 0.3 * (i as f64 * 0.005 * 3.0).sin();
            q
        };
        for i in 0..2000usize {
            old.latency.observe(&cmd(i.saturating_sub(lag)));
            old.latency.commanded(&cmd(i));
        }
        assert!(old.latency().report().confident);
        release_and_track(&mut old, &s, 0.020, 0.008);
        old.abort(10.0, AbortReason::StopRequested);
        old.reset(10.0).unwrap();
        assert_eq!(old.session_memory().offset_n, 1);
        let learned = old.latency().report();
        // A calibrated pendulum length: everything carries.
        let mut t = s.clone();
        t.pendulum.length_m += 0.01;
        let mut new = Controller::new(&t, 0.005).unwrap();
        assert_ne!(new.latency().report(), learned);
        new.carry_session(&old, true);
        assert_eq!(new.latency().report(), learned);
        assert_eq!(new.session_memory(), old.session_memory());
        // A new camera latency belief: the releases' offsets (from the old
        // belief) do not carry; a new robot latency prior: its estimate
        // starts again from the prior.
        let mut u = s.clone();
        u.control.latency_prior_ms = 10.0;
        let mut fresh = Controller::new(&u, 0.005).unwrap();
        let before = fresh.latency().report();
        fresh.carry_session(&old, false);
        assert_eq!(fresh.latency().report(), before);
        assert_eq!(fresh.session_memory().offset_n, 0);
        assert_eq!(fresh.session_memory().k, old.session_memory().k);
    }

    #[test]
    fn the_camera_offset_is_read_from_the_release_and_forgotten_at_a_new_session() {
        let mut s = Beliefs::default();
        s.control.camera_offset_from_release = true;
        s.control.release_delay_prior_ms = 15.0;
        // Trust the releases (a tight release delay) to read the offset itself.
        s.control.release_delay_std_ms = 0.5;
        s.control.learn_frequency = true;
        s.ekf.estimate_frequency = true;
        let mut c = Controller::new(&s, 0.005).unwrap();
        // The ball falls 20 ms after the coil (5 ms more than believed); the
        // stamps are 8 ms late: the release shows 13 ms.
        release_and_track(&mut c, &s, 0.020, 0.008);
        let got = c.camera_offset_s();
        assert!((got - 0.013).abs() < 0.002, "{got}");
        // Committed with it: the motion starts that much earlier.
        let commit = c.commit().copied().expect("committed within 2.4 s");
        assert!((commit.camera_offset_s - got).abs() < 0.002);
        // The trial's end folds it (and the frequency) into the session.
        c.abort(10.0, AbortReason::StopRequested);
        c.reset(10.0).unwrap();
        assert_eq!(c.session_memory().offset_n, 1);
        assert!(c.session_memory().k.is_some());
        assert!((c.camera_offset_s() - got).abs() < 0.002);
        c.new_session();
        assert_eq!(c.camera_offset_s(), 0.0);
        assert_eq!(c.session_memory(), &SessionMemory::default());
        // Off: nothing compensated whatever the releases show.
        s.control.camera_offset_from_release = false;
        let mut off = Controller::new(&s, 0.005).unwrap();
        release_and_track(&mut off, &s, 0.020, 0.008);
        assert_eq!(off.camera_offset_s(), 0.0);
        assert_eq!(off.commit().map(|c| c.camera_offset_s), Some(0.0));
    }

    #[test]
    fn arming_moves_home_and_a_stop_decelerates_to_rest() {
        let s = Beliefs::default();
        let mut c = Controller::new(&s, 0.005).unwrap();
        let plan = Controller::plan(&s, 0.5).unwrap();
        let mut q = [0.0, 0.5, 0.0, -1.4, 0.0, 1.2, 0.0];
        let mut out = StepOutput::default();
        let none = std::iter::empty::<Sighting>();
        c.step(
            &StepInput {
                t_s: 0.0,
                q_measured_rad: q,
                commanding: true,
            },
            none,
            &mut out,
        );
        c.arm(0.0, &plan).unwrap();
        // Refused twice.
        assert!(c.arm(0.0, &plan).is_err());
        let mut t = 0.0;
        while c.state() != TrialState::Armed && t < 20.0 {
            t += 0.005;
            c.step(
                &StepInput {
                    t_s: t,
                    q_measured_rad: q,
                    commanding: true,
                },
                std::iter::empty(),
                &mut out,
            );
            q = out.q_command_rad; // a perfect robot
        }
        assert_eq!(c.state(), TrialState::Armed);
        let home = c.tool_point(&q);
        assert!((home - Vector3::from(s.task.home_m)).norm() < 1e-6);
        assert_eq!(c.counters().limit_violations(), 0);
        // A stop from Armed: nothing moves afterwards.
        c.abort(t, AbortReason::StopRequested);
        for _ in 0..10 {
            t += 0.005;
            c.step(
                &StepInput {
                    t_s: t,
                    q_measured_rad: q,
                    commanding: true,
                },
                std::iter::empty(),
                &mut out,
            );
            assert_eq!(out.q_command_rad, q);
        }
        assert_eq!(c.state(), TrialState::Aborted);
        assert_eq!(c.abort_reason(), Some(AbortReason::StopRequested));
        // Release is refused after an abort; a reset is allowed.
        assert!(c.release(t).is_err());
        c.reset(t).unwrap();
        assert_eq!(c.state(), TrialState::Idle);
    }

    /// The camera-robot tour's move: the commands go to the target within
    /// the share of the speed and acceleration limits and hold there; a
    /// target out of the limits (or NaN) and a busy controller are refused
    /// with nothing moving; a stop ends the move; no trial arms meanwhile.
    #[test]
    fn a_move_to_a_pose_stays_slow_inside_the_limits_holds_there_and_refuses_bad_targets() {
        let s = Beliefs::default();
        let dt = 0.005;
        let mut c = Controller::new(&s, dt).unwrap();
        let q0 = [0.1, 0.5, -0.2, -1.4, 0.3, 1.2, 0.4];
        let target = [0.4, 0.7, -0.1, -1.0, 0.5, 0.9, 0.2];
        let mut out = StepOutput::default();
        let step = |c: &mut Controller, t: f64, q: [f64; JOINTS], out: &mut StepOutput| {
            c.step(
                &StepInput {
                    t_s: t,
                    q_measured_rad: q,
                    commanding: true,
                },
                std::iter::empty::<Sighting>(),
                out,
            );
        };
        assert!(
            matches!(c.move_to(0.0, &target), Err(ControlError::State { .. })),
            "before the first message"
        );
        step(&mut c, 0.0, q0, &mut out);
        let mut beyond = target;
        beyond[3] = -(POSITION_LIMIT_RAD[3] - MOVE_TO_MARGIN_RAD) - 0.01;
        let mut nan = target;
        nan[5] = f64::NAN;
        for (bad, joint) in [(beyond, 3), (nan, 5)] {
            match c.move_to(0.0, &bad) {
                Err(ControlError::Target(j, _)) => assert_eq!(j, joint),
                other => panic!("{bad:?}: {other:?}"),
            }
            assert!(!c.moving_to());
        }
        let dur = c.move_to(0.0, &target).unwrap();
        assert!(dur >= 1.0);
        assert!(c.moving_to());
        assert!(c.move_to(0.0, &target).is_err(), "one at a time");
        let e = Excitation {
            joint: 6,
            amplitude_rad: 0.05,
            duration_s: 4.0,
        };
        assert!(c.excite(0.0, e).is_err(), "no excitation while it moves");
        let plan = Controller::plan(&s, 0.5).unwrap();
        assert!(c.arm(0.0, &plan).is_err(), "no trial while it moves");
        let (mut t, mut q) = (0.0, q0);
        let mut v_prev = [0.0; JOINTS];
        while c.moving_to() {
            t += dt;
            step(&mut c, t, q, &mut out);
            let next = out.q_command_rad;
            for j in 0..JOINTS {
                let v = (next[j] - q[j]) / dt;
                assert!(
                    v.abs() <= MOVE_TO_LIMIT_SHARE * VELOCITY_LIMIT_RADPS[j] + 1e-9,
                    "A{} {v} rad/s at {t}",
                    j + 1
                );
                assert!(
                    ((v - v_prev[j]) / dt).abs()
                        <= MOVE_TO_LIMIT_SHARE * ACCELERATION_LIMIT_RADPS2[j] + 1e-6,
                    "A{} {} rad/s^2 at {t}",
                    j + 1,
                    (v - v_prev[j]) / dt
                );
                assert!(next[j].abs() < POSITION_LIMIT_RAD[j]);
                v_prev[j] = v;
            }
            q = next;
            assert!(t < dur + 1.0, "the move did not end");
        }
        assert_eq!(q, target, "at the target");
        for _ in 0..20 {
            t += dt;
            step(&mut c, t, q, &mut out);
            assert_eq!(out.q_command_rad, target, "holds there");
        }
        assert!(c.at_rest());
        // A stop during a move: it ends, and the commands come to rest.
        c.move_to(t, &q0).unwrap();
        for _ in 0..100 {
            t += dt;
            step(&mut c, t, q, &mut out);
            q = out.q_command_rad;
        }
        c.abort(t, AbortReason::StopRequested);
        assert!(!c.moving_to());
        for _ in 0..400 {
            t += dt;
            step(&mut c, t, q, &mut out);
            q = out.q_command_rad;
        }
        assert!(c.at_rest());
        assert!(
            (q[0] - q0[0]).abs() > 0.01,
            "stopped on its way, not at the end"
        );
    }

    /// The robot step's excitation: only the chosen joint moves, by at most
    /// its amplitude, within the speed and acceleration limits; the arm
    /// rests where it began at the end; bad requests and a busy controller
    /// are refused with nothing changed; a stop ends it at once.
    #[test]
    fn an_excitation_moves_one_joint_within_the_limits_and_rests_where_it_began() {
        let s = Beliefs::default();
        let dt = 0.005;
        let mut c = Controller::new(&s, dt).unwrap();
        let q0 = [0.1, 0.5, -0.2, -1.4, 0.3, 1.2, 0.4];
        let mut out = StepOutput::default();
        let step = |c: &mut Controller, t: f64, q: [f64; JOINTS], out: &mut StepOutput| {
            c.step(
                &StepInput {
                    t_s: t,
                    q_measured_rad: q,
                    commanding: true,
                },
                std::iter::empty::<Sighting>(),
                out,
            );
        };
        let e = Excitation {
            joint: 6,
            amplitude_rad: 0.05,
            duration_s: 4.0,
        };
        assert!(
            matches!(c.excite(0.0, e), Err(ControlError::State { .. })),
            "before the first message"
        );
        step(&mut c, 0.0, q0, &mut out);
        for bad in [
            Excitation { joint: 7, ..e },
            Excitation {
                amplitude_rad: 0.0,
                ..e
            },
            Excitation {
                amplitude_rad: 0.06,
                ..e
            },
            Excitation {
                amplitude_rad: f64::NAN,
                ..e
            },
            Excitation {
                duration_s: 0.5,
                ..e
            },
            Excitation {
                duration_s: f64::INFINITY,
                ..e
            },
        ] {
            assert!(
                matches!(c.excite(0.0, bad), Err(ControlError::Excitation(b)) if b.joint == bad.joint),
                "{bad:?}"
            );
            assert!(!c.exciting());
        }
        c.excite(0.0, e).unwrap();
        assert!(c.exciting());
        assert!(c.excite(0.0, e).is_err(), "one at a time");
        let plan = Controller::plan(&s, 0.5).unwrap();
        assert!(c.arm(0.0, &plan).is_err(), "no trial while it runs");
        let (mut t, mut q) = (0.0, q0);
        let (mut v_prev, mut peak, mut moves) = (0.0_f64, 0.0_f64, 0);
        let mut was_out = false;
        while c.exciting() {
            t += dt;
            step(&mut c, t, q, &mut out);
            let next = out.q_command_rad;
            for j in 0..JOINTS - 1 {
                assert_eq!(next[j], q0[j], "joint {j} moved at {t}");
            }
            let d = next[6] - q0[6];
            assert!((-1e-12..=0.05 + 1e-12).contains(&d), "A7 {d} rad at {t}");
            let v = (next[6] - q[6]) / dt;
            assert!(v.abs() <= VELOCITY_LIMIT_RADPS[6], "{v} rad/s");
            assert!(
                ((v - v_prev) / dt).abs() <= ACCELERATION_LIMIT_RADPS2[6],
                "{} rad/s^2",
                (v - v_prev) / dt
            );
            v_prev = v;
            peak = peak.max(d);
            let out_now = d > 0.04;
            moves += usize::from(out_now != was_out);
            was_out = out_now;
            q = next;
            assert!(t < 5.0, "the excitation did not end");
        }
        assert!((t - 4.0).abs() <= dt, "ended at {t}");
        assert!((peak - 0.05).abs() < 1e-9, "peak {peak}");
        // A move every 0.4 s: out in slots 1, 3, 5 and 7, back in 2, 4, 6
        // and 8 (slot 9's would not be back within the 4 s).
        assert_eq!(moves, 8);
        assert_eq!(out.q_command_rad, q0, "rests where it began");
        assert_eq!(c.state(), TrialState::Idle);
        // A stop ends a running one where it is and the arm decelerates.
        c.excite(t, e).unwrap();
        for _ in 0..100 {
            t += dt;
            step(&mut c, t, q, &mut out);
            q = out.q_command_rad;
        }
        c.abort(t, AbortReason::StopRequested);
        assert!(!c.exciting());
        assert!(c.excite(t, e).is_err(), "not while aborted");
        let before = q[6];
        for _ in 0..200 {
            t += dt;
            step(&mut c, t, q, &mut out);
            q = out.q_command_rad;
        }
        // Mid-move (0.47 rad/s) at half the acceleration limit: 0.014 rad.
        assert!(
            (q[6] - before).abs() < 0.02,
            "stopped near where it was: {} -> {}",
            before,
            q[6]
        );
        assert!(c.at_rest());
    }
}
