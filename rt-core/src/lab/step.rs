//! The trial driver: the one code path that owns a trial's lifecycle, in
//! both clocks. [`LabStep`] wraps the closed loop's [`FriLoopStep`] and,
//! around each call, polls the bridge (stop, commands), folds in the camera
//! measurements of the vision ring, follows the magnet, keeps the ground
//! truth and the judge's trace, runs the trial (plan, arm, wait for release,
//! commit, move, judge, time out, return home), reports events and publishes
//! the snapshot. Nothing here allocates, locks, logs or blocks, except
//! handling a command (planning a trial, new parameters), which happens once
//! per operator action.

use std::sync::{Arc, OnceLock};
use std::time::Instant;

use nalgebra::Vector3;
use rtrb::{Consumer, Producer};

use super::fri_step::FriLoopStep;
use super::measured::{MeasuredBeliefs, MeasuredTrace};
use super::trial::{TrialDraw, draw_trial};
use super::truth::{
    MAX_PASSES, PhysicalJudgeError, PhysicalJudgement, StrikeAim, TrialStart, TruthObserver,
};
use crate::bridge::{
    self, AbortKind as BridgeAbort, AbortView, Command, ControlEnd, Event, EventRecord, FriQuality,
    FriSessionState, HorizonPoint, JudgedBy, Refusal, Snapshot, TrialResult, TrialSetup,
};
use crate::control::measured::{ARRIVAL_SETTLE_M, MeasuredJudgement};
use crate::control::{
    AbortReason, ArmPlan, ControlError, Controller, JudgeScratch, Judgement, PlannedMotion,
    Sighting, TrialState, TrialTrace, judge_into, judge_strike_crossing,
};
use crate::ekf::Prediction;
use crate::fri::client::{ControlStep, SessionStats, StepInput, StopReason};
use crate::fri::codec::Joints;
use crate::fri::proto::{ConnectionQuality, SessionState};
#[cfg(feature = "serial")]
use crate::magnet::{MagnetHandle, view};
use crate::params::Scenario;
use crate::trajectory::profile::ProfileKind;
use crate::vision::{CameraIntrinsics, CameraPose, SwingPlaneCalibration};

/// Time after `Done` still recorded for the judge, seconds.
pub const AFTER_DONE_S: f64 = 0.3;
/// Longest a trial may take from arming, seconds.
pub const TRIAL_TIMEOUT_S: f64 = 40.0;
/// How long the robot controller may fall silent before a running trial
/// counts the FRI link as lost, seconds. The FRI client calls a silence after
/// a few periods (`fri::FriClientParams::silence_periods`), which a busy
/// machine's scheduler can cause on its own; a controller that keeps
/// commanding through the gap continues the trial (a controller that dropped
/// out says so when it comes back: `StopReason::LeftCommanding`).
pub const FRI_LOST_AFTER_S: f64 = 0.3;
/// What a real lab's trial record says until it has a measured judge.
pub const NOT_JUDGED_REAL: &str =
    "not judged: this lab has no ground truth and no measured judge (the real lab)";
/// A real camera that delivers no frame for this long is lost (unplugged,
/// its stream broken): a running trial aborts as `camera_lost`, new ones
/// are refused until frames come again, seconds.
pub const CAMERA_LOST_AFTER_S: f64 = 1.0;
/// The simulated lab's camera is a thread of this process rendering frames:
/// on a loaded machine it renders late, which is not a lost camera (as the
/// simulated magnet board's answers get 2 s). Seconds without a frame.
pub const SIMULATED_CAMERA_LOST_AFTER_S: f64 = 5.0;
/// An abort's detail when the camera stopped delivering frames mid-trial.
pub const CAMERA_LOST: &str =
    "the camera stopped delivering frames (unplugged or its stream broke)";
/// An abort's detail when the magnet board stopped answering mid-trial.
pub const MAGNET_LOST: &str =
    "the magnet board stopped answering (serial link lost) while it held the ball";
/// A real lab's trial whose measurements could not decide it.
pub const NOT_JUDGED_MEASURED: &str =
    "not judged: the measured judge saw a contact but no pass of the ball to time it";
/// A real lab's trial whose robot reported no external joint torques (all
/// samples equal, or none: `isochron fri-sim`, a controller that does not
/// estimate them): the measured judge cannot see a contact, so neither a hit
/// nor a miss (the record still carries the measured timing).
pub const NOT_JUDGED_NO_TORQUE: &str = "not judged (measured): the robot reported no external \
     joint torques, so contact cannot be seen";
/// The robot's messages paused around the pass or the arrival.
pub const NOT_JUDGED_ROBOT_GAP: &str = "not judged (measured): the robot's messages paused around \
     the pass or the arrival (a busy machine's FRI silence), so contact and arrival cannot be seen";
/// A finished motion the judge could not fit.
pub const NOT_JUDGED_TRACE: &str = "not judged: the recorded motion could not be judged";
/// A trial that ended without a committed motion.
pub const NOT_JUDGED_NO_MOTION: &str = "not judged: there was no motion to judge";

/// The control clock of a lab.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LabClock {
    /// The wall clock from `epoch` (shared with the camera): the session's
    /// receive times are shifted onto it at the first message.
    Wall(Instant),
    /// Virtual time: the FRI client's `now_ns` is the control clock.
    Virtual,
}

/// How a trial ended, as the control thread saw it (plain data: no
/// allocation at the end of a trial; the virtual lab turns it into a
/// [`crate::control::TrialRecord`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrialOutcome {
    /// The trial's id (the operator's `trial_id`, 0 for a bare arm).
    pub id: u64,
    /// Index of the trial in the run (its draw).
    pub index: usize,
    /// What the trial drew from the seed.
    pub draw: TrialDraw,
    /// The motion's planned duration, seconds.
    pub planned_movement_time_s: f64,
    /// The state the trial ended in (`Done` or `Aborted`).
    pub final_state: TrialState,
    /// Why the trial was aborted (the controller's reason), when it was.
    pub abort_reason: Option<AbortReason>,
    /// The ground-truth verdict (when the lab knows the truth and there was a motion).
    pub judgement: Option<Judgement>,
    /// Why the motion could not be judged, when it could not.
    pub judge_error: Option<crate::control::judge::JudgeError>,
    /// The physical judge's verdict on the true world (the reality lab,
    /// `[world]`, in virtual time); then it decides success.
    pub physical: Option<PhysicalJudgement>,
    /// Why the physical judge could not judge the trial, when it could not.
    pub physical_error: Option<PhysicalJudgeError>,
    /// The measured judge's verdict (every lab; the real lab's judgement),
    /// when there was a committed motion.
    pub measured: Option<MeasuredJudgement>,
    /// At commit: predicted pass time minus the nearest true pass, milliseconds.
    pub prediction_crossing_time_error_ms: Option<f64>,
    /// At commit: predicted ball centre to the true one at the predicted time, metres.
    pub prediction_position_error_m: Option<f64>,
    /// The latency the interception compensated (at commit), milliseconds.
    pub latency_estimate_ms: f64,
    /// The camera time offset compensated (at commit), milliseconds.
    pub camera_offset_estimate_ms: Option<f64>,
    /// The pendulum length the filter had learned before the pass, metres.
    pub length_estimate_m: Option<f64>,
    /// The controller's limit violations during the trial.
    pub limit_violations: u64,
    /// Control steps over the period (own computation) during the trial.
    pub deadline_misses: u64,
    /// Control steps over the period by wall clock only during the trial.
    pub preempted_steps: u64,
    /// When the trial ended, control clock, seconds.
    pub t_end_s: f64,
}
/// Spacing of the predicted horizon points, seconds.
const HORIZON_STEP_S: f64 = 0.08;
/// The predicted horizon is recomputed when the filter fused a new measurement
/// (at the camera's rate) and at least this often otherwise, so that its start
/// follows the clock. (Every 10 ms, as before, put a horizon propagation of
/// about 10 us on every tenth FRI cycle, though the horizon only changes when
/// the posterior does.)
const HORIZON_EVERY_S: f64 = 0.05;
/// Steps per window of the period statistics.
const PERIOD_WINDOW: u32 = 200;

/// A magnet switch as the driver saw it, on the control clock.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct MagnetNote {
    /// The coil's new state.
    pub on: bool,
    /// When it switched, control clock, seconds.
    pub t_s: f64,
}

/// Work the control thread hands to `isochron-lab-io` (planning allocates and
/// takes far longer than an FRI period; serial I/O blocks).
pub(crate) enum IoRequest {
    /// Switch the magnet.
    Magnet(bool),
    /// Plan the motion of a trial (answered by [`IoReply::Plan`]).
    Plan {
        ack: u64,
        trial_id: u64,
        auto_release: bool,
        index: usize,
        draw: TrialDraw,
        /// The trial's own movement time and task (else the scenario's).
        setup: TrialSetup,
    },
    /// Build a controller for new parameters (answered by [`IoReply::Params`]).
    Params { ack: u64, scenario: Box<Scenario> },
    /// Memory to free off the control thread.
    Free(Box<Controller>),
}

/// `isochron-lab-io`'s answers.
#[expect(
    clippy::large_enum_variant,
    reason = "the ring's slots are allocated once; boxing the plan would free memory on the control thread"
)]
pub(crate) enum IoReply {
    /// A trial's plan, or why there is none.
    Plan {
        ack: u64,
        trial_id: u64,
        auto_release: bool,
        index: usize,
        draw: TrialDraw,
        plan: Result<ArmPlan, Refusal>,
    },
    /// A controller for the new parameters, or the refused parameters.
    Params {
        ack: u64,
        result: Result<(Box<Controller>, Box<Scenario>), Box<Scenario>>,
    },
}

/// The simulated camera's geometry, to recompute its calibration when the
/// simulated pendulum moves (per trial).
#[derive(Debug, Clone, Copy)]
pub struct CameraModel {
    /// The believed intrinsics (the detector's calibration undistorts with them).
    pub intrinsics: CameraIntrinsics,
    /// The camera's pose.
    pub pose: CameraPose,
    /// The ball's radius, m.
    pub ball_radius_m: f64,
}

/// The ground truth of a simulated lab: the world's observer (implemented
/// in `sim`) and the simulated camera's calibration, moved with the truth
/// per trial.
pub struct Truth {
    /// The world as the driver follows and judges it.
    pub observer: Box<dyn TruthObserver>,
    /// The simulated camera's calibrations, one per trial.
    pub calibrations: Producer<SwingPlaneCalibration>,
    /// The simulated camera's geometry.
    pub camera: CameraModel,
}

struct Trial {
    id: u64,
    draw: TrialDraw,
    plan: ArmPlan,
    /// The lab follows the trial's ground truth (`LabParts::truth`: the
    /// simulated lab only).
    truth: bool,
    auto_release: bool,
    armed_at: Option<f64>,
    release_requested: bool,
    magnet_was_on: bool,
    released: bool,
    done_at: Option<f64>,
    t0: f64,
    index: usize,
    /// Controller limit violations, deadline misses, preempted steps at the start.
    counters_at_start: (u64, u64, u64),
    /// The true ball centre at the committed prediction's pass time (exact).
    at_predicted: Option<Vector3<f64>>,
}

/// Everything the control thread owns besides the closed loop.
pub(crate) struct LabParts {
    pub scenario: Box<Scenario>,
    pub seed: u64,
    /// The pendulum's distance when it cannot move (the real lab); `None`:
    /// drawn per trial (the simulated lab).
    pub fixed_distance_m: Option<f64>,
    pub bridge: ControlEnd,
    pub clock: LabClock,
    pub measurements: Consumer<crate::vision::Measurement>,
    pub magnet_notes: Consumer<MagnetNote>,
    pub io_requests: Producer<IoRequest>,
    pub io_replies: Consumer<IoReply>,
    /// The magnet driver's view (`None`: the virtual-time magnet, known
    /// only through its notes).
    #[cfg(feature = "serial")]
    pub magnet: Option<MagnetHandle>,
    pub session: Arc<OnceLock<Arc<SessionStats>>>,
    pub truth: Option<Truth>,
    /// The camera's calibration at the start (the dashboard's overlays).
    pub calibration: SwingPlaneCalibration,
    /// The operator dead-man time, seconds (`None`: off).
    pub operator_timeout_s: Option<f64>,
    /// The latency the camera's stamps take, seconds as `f64` bits (the
    /// vision thread reads it): set when new beliefs change the camera's
    /// latency. `None`: stamps not the lab's (the virtual lab).
    pub stamp_latency: Option<Arc<std::sync::atomic::AtomicU64>>,
    /// A real camera's swing plane, derived from its basis and the beliefs
    /// in force, handed to the vision thread when new beliefs are taken
    /// (`None`: the simulated labs, whose plane moves with each trial's truth).
    pub real_plane: Option<RealPlane>,
    /// Seconds without a frame after which the camera is lost (wall clock):
    /// [`CAMERA_LOST_AFTER_S`], or [`SIMULATED_CAMERA_LOST_AFTER_S`] for the
    /// simulated lab's rendering thread.
    pub camera_lost_after_s: f64,
    /// The simulated lab's stand (`None`: a pendulum that stays put): each
    /// trial's distance and release angle are asked of it before the
    /// magnet switches on, and a real camera's plane moves with it.
    pub stand: Option<std::sync::Arc<super::Stand>>,
}

/// What a real lab believes of its camera and pendulum without the
/// calibration file's camera and camera-robot steps (its configuration's
/// `[calibration]`): the swing plane the detector measures on is derived
/// from it and the beliefs in force, at the start and whenever new beliefs
/// are taken (a calibration step's result), so that the detector sees the
/// camera the controller believes in.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraBasis {
    /// The intrinsics without the camera step (no lens).
    pub intrinsics: crate::vision::CameraIntrinsics,
    /// The camera's pose without the camera-robot step, base frame.
    pub pose: crate::vision::CameraPose,
    /// The pendulum's pivot, base frame, m.
    pub pivot_m: [f64; 3],
}

impl CameraBasis {
    /// The basis with the pendulum moved to `distance_m` from the robot's
    /// base along the same bearing (the simulated lab's stand,
    /// [`super::Stand`]); the camera stays where it is.
    pub fn at_distance(&self, distance_m: f64) -> Self {
        let [px, py, pz] = self.pivot_m;
        let r = px.hypot(py);
        let (ux, uy) = if r > 1e-9 {
            (px / r, py / r)
        } else {
            (1.0, 0.0)
        };
        Self {
            pivot_m: [ux * distance_m, uy * distance_m, pz],
            ..*self
        }
    }

    /// The camera and the ball's rest centre as `scenario`'s beliefs have
    /// them: the camera step's intrinsics and lens, else the basis's; the
    /// camera-robot step's pose, else the basis's; the rest centre the
    /// believed length below the pivot, moved by the believed intercept
    /// offset (`task.intercept_offset_m`, the camera-robot step's).
    pub fn believed(
        &self,
        scenario: &Scenario,
    ) -> (
        crate::vision::CameraIntrinsics,
        crate::vision::CameraPose,
        nalgebra::Vector3<f64>,
    ) {
        let [px, py, pz] = self.pivot_m;
        let rest = nalgebra::Vector3::new(px, py, pz - scenario.pendulum.length_m)
            + nalgebra::Vector3::from(scenario.task.intercept_offset_m);
        (
            scenario.camera.intrinsics.unwrap_or(self.intrinsics),
            scenario.camera.pose.unwrap_or(self.pose),
            rest,
        )
    }

    /// The swing plane the detector measures on under `scenario`'s beliefs.
    pub fn plane(&self, scenario: &Scenario) -> SwingPlaneCalibration {
        let (k, pose, rest) = self.believed(scenario);
        SwingPlaneCalibration::from_pose(k, &pose, &rest, scenario.pendulum.ball_radius_m)
    }
}

/// A real camera's basis and the ring its new swing planes go out on.
pub struct RealPlane {
    /// What the lab's configuration believes of the camera and pendulum.
    pub basis: CameraBasis,
    /// To the vision thread (a fresh detector on each).
    pub planes: Producer<SwingPlaneCalibration>,
}

/// The lab's control step (see the module documentation).
pub struct LabStep {
    inner: FriLoopStep,
    p: LabParts,
    offset_ns: Option<i64>,
    t_s: f64,
    period_s: f64,
    trial_index: usize,
    trial: Option<Trial>,
    trace: TrialTrace,
    judge_scratch: JudgeScratch,
    /// The true ball's passes through the intercept point's `y` in the
    /// current trial: exact time (a root of the true pendulum) and centre.
    passes: Vec<(f64, Vector3<f64>)>,
    /// What the measured judge needs (detections, measured tool, external torques).
    measured: MeasuredTrace,
    /// The simulated robot's true joints at this message (virtual lab).
    q_true: Option<Joints>,
    /// FRI's external joint torques of the latest message (NaN: none sent).
    tau_ext: Joints,
    outcome: Option<TrialOutcome>,
    snap: Snapshot,
    horizon: Vec<Prediction>,
    next_horizon_s: f64,
    /// The posterior time the horizon was last computed from.
    horizon_posterior_s: f64,
    last_state: TrialState,
    /// The previous measured tool point and the robot's sample time of it
    /// (sequence counter x send period), seconds.
    prev_tool: Option<(f64, Vector3<f64>)>,
    /// The robot's sample time of the latest measurement, seconds.
    robot_t_s: f64,
    q: Joints,
    session: SessionState,
    quality: ConnectionQuality,
    last_step_at: Option<Instant>,
    period_sum_us: f64,
    period_max_us: f64,
    periods: u32,
    step_max_us: f64,
    /// A step whose trial bookkeeping and snapshot wait for its reply to be
    /// sent (`ControlStep::after_reply`): its control time, s.
    after_pending: Option<f64>,
    magnet_failures: u64,
    /// A command waiting for `isochron-lab-io` (its ack id; true: cancelled by a stop).
    pending: Option<(u64, bool)>,
    /// When the operator last commanded a trial (counts as a heartbeat), control clock, s.
    operator_since_s: f64,
    /// When the latest camera frame's measurement arrived, control clock, s.
    last_frame_s: Option<f64>,
    /// The robot controller fell silent at this time (the last message),
    /// control clock, s; cleared by its next message.
    silent_since: Option<f64>,
    /// How the FRI link was last lost (for the abort's detail).
    abort_detail: &'static str,
}

impl std::fmt::Debug for LabStep {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LabStep")
            .field("t_s", &self.t_s)
            .field("trial_index", &self.trial_index)
            .finish_non_exhaustive()
    }
}

fn map_session(s: SessionState) -> FriSessionState {
    match s {
        SessionState::Idle => FriSessionState::Idle,
        SessionState::MonitoringWait => FriSessionState::MonitoringWait,
        SessionState::MonitoringReady => FriSessionState::MonitoringReady,
        SessionState::CommandingWait => FriSessionState::CommandingWait,
        SessionState::CommandingActive => FriSessionState::CommandingActive,
    }
}

fn map_quality(q: ConnectionQuality) -> FriQuality {
    match q {
        ConnectionQuality::Poor => FriQuality::Poor,
        ConnectionQuality::Fair => FriQuality::Fair,
        ConnectionQuality::Good => FriQuality::Good,
        ConnectionQuality::Excellent => FriQuality::Excellent,
    }
}

impl LabStep {
    pub(crate) fn new(controller: Controller, p: LabParts) -> Self {
        let period_s = f64::from(p.scenario.robot.fri_period_ms) * 1e-3;
        let trace_len = (TRIAL_TIMEOUT_S / period_s) as usize + 1000;
        let sightings_len =
            (TRIAL_TIMEOUT_S * p.scenario.camera.fps.clamp(1.0, 500.0)) as usize + 64;
        let mut snap = Snapshot::default();
        let cam = &p.scenario.camera;
        snap.camera
            .set_calibration(&p.calibration, cam.width_px, cam.height_px);
        Self {
            inner: FriLoopStep::new(controller),
            p,
            offset_ns: None,
            t_s: 0.0,
            period_s,
            trial_index: 0,
            trial: None,
            trace: TrialTrace::with_capacity(trace_len),
            judge_scratch: JudgeScratch::with_capacity(trace_len),
            passes: Vec::with_capacity(MAX_PASSES),
            measured: MeasuredTrace::with_capacity(sightings_len, trace_len),
            q_true: None,
            tau_ext: [f64::NAN; crate::kinematics::iiwa7::JOINTS],
            outcome: None,
            snap,
            horizon: vec![Prediction::default(); bridge::HORIZON_POINTS],
            next_horizon_s: 0.0,
            horizon_posterior_s: f64::NAN,
            last_state: TrialState::Idle,
            prev_tool: None,
            robot_t_s: 0.0,
            q: [0.0; 7],
            session: SessionState::Idle,
            quality: ConnectionQuality::Poor,
            last_step_at: None,
            period_sum_us: 0.0,
            period_max_us: 0.0,
            periods: 0,
            step_max_us: 0.0,
            after_pending: None,
            magnet_failures: 0,
            pending: None,
            operator_since_s: f64::NEG_INFINITY,
            last_frame_s: None,
            silent_since: None,
            abort_detail: "",
        }
    }

    /// The FRI session commands now (COMMANDING_ACTIVE, not silent): a trial
    /// may start.
    fn commanding(&self) -> bool {
        self.session == SessionState::CommandingActive && self.silent_since.is_none()
    }

    /// The camera stopped delivering frames: none for over
    /// `LabParts::camera_lost_after_s` ([`CAMERA_LOST_AFTER_S`] for a real
    /// camera) on the wall clock, where a real camera can be unplugged,
    /// counted from the lab's start when none ever came (a camera that does
    /// not answer).
    fn camera_lost(&self, t: f64) -> bool {
        matches!(self.p.clock, LabClock::Wall(_))
            && t - self.last_frame_s.unwrap_or(0.0) > self.p.camera_lost_after_s
    }

    fn magnet_lost(&self) -> bool {
        #[cfg(feature = "serial")]
        if let Some(v) = self.p.magnet.as_ref().and_then(MagnetHandle::try_view) {
            // Lost, or never connected (a port where no board answers): a
            // trial would arm a magnet nobody hears.
            return v.link != view::LinkState::Connected;
        }
        false
    }

    /// The FRI link is lost for the trial: the closed loop stops (aborting
    /// a running trial as `fri_lost`) and the trial's end is reported now,
    /// whether or not the controller's messages come back.
    fn lose_link(&mut self, reason: StopReason) {
        self.abort_detail = stop_detail(reason);
        self.inner.stop(reason);
        let t = self.t_s;
        self.settle(t, true);
    }

    /// Reports a state change and ends a trial that is over: an aborted one
    /// at once; a done one after `AFTER_DONE_S` of trace, or now when `now`
    /// (no more messages will come to record it).
    fn settle(&mut self, t: f64, now: bool) {
        self.emit_state(t);
        let Some(trial) = self.trial.as_mut() else {
            return;
        };
        match self.inner.controller().state() {
            TrialState::Aborted => self.conclude(t),
            TrialState::Done => {
                let since = *trial.done_at.get_or_insert(t);
                if now || t - since >= AFTER_DONE_S {
                    self.conclude(t);
                }
            }
            _ => {}
        }
    }

    /// Between controller messages, when none came for a while (the session
    /// thread calls it on its receive timeouts): declares the link lost after
    /// `FRI_LOST_AFTER_S` of silence, answers the operator's commands (a
    /// trial is refused while the robot does not command), ends the trial
    /// that is over and publishes the snapshot. Nothing allocates.
    fn between_messages(&mut self, t: f64) {
        if let Some(since) = self.silent_since
            && t - since > FRI_LOST_AFTER_S
        {
            self.silent_since = None;
            self.lose_link(StopReason::ControllerSilent);
            self.session = SessionState::Idle;
        }
        if self.p.bridge.take_stop_request() {
            let at = self.t_s;
            self.stop_now(at);
        }
        while let Ok(reply) = self.p.io_replies.pop() {
            self.io_reply(t, reply);
        }
        self.take_commands(t);
        self.follow_magnet();
        // The trial's time-out runs without messages too (as in `follow_trial`).
        let state = self.inner.controller().state();
        let timed_out = !matches!(
            state,
            TrialState::Idle | TrialState::Done | TrialState::Aborted
        ) && self.trial.as_ref().is_some_and(|tr| {
            (tr.auto_release || state != TrialState::Armed) && t - tr.t0 > TRIAL_TIMEOUT_S
        });
        if timed_out {
            self.controller().abort(t, AbortReason::PredictionTimeout);
        }
        self.settle(t, false);
        self.snap.t_s = self.snap.t_s.max(t);
        self.snap.seq += 1;
        self.snap.trial_state = self.inner.controller().state();
        self.snap.ready = bridge::Readiness::from_refusal(self.trial_refusal(t));
        self.p.bridge.publish(&self.snap);
    }

    /// Reports the controller's state change (and an abort's reason).
    fn emit_state(&mut self, t: f64) {
        let state = self.inner.controller().state();
        if state == self.last_state {
            return;
        }
        let trial_id = self.trial.as_ref().map_or(0, |tr| tr.id);
        self.p.bridge.emit(EventRecord {
            t_s: t,
            trial_id,
            event: Event::StateChanged {
                from: self.last_state,
                to: state,
            },
        });
        if state == TrialState::Aborted
            && let Some(r) = self.inner.controller().abort_reason()
        {
            let reason = BridgeAbort::from(r);
            let detail = match reason {
                _ if !self.abort_detail.is_empty() => self.abort_detail,
                BridgeAbort::FriLost => session_detail(self.session),
                BridgeAbort::Timeout => doubt_detail(self.inner.controller().last_doubt()),
                _ => "",
            };
            self.p.bridge.emit(EventRecord {
                t_s: t,
                trial_id,
                event: Event::Aborted { reason, detail },
            });
            self.snap.abort = AbortView {
                trial_id,
                reason: Some(reason),
                message: reason.message(),
                detail,
            };
            self.snap.counters.trials += 1;
        }
        self.last_state = state;
    }

    /// Steps whose computation took longer than the FRI period.
    pub fn deadline_misses(&self) -> u64 {
        self.inner.step.deadline_misses
    }

    /// The closed loop.
    pub fn inner(&self) -> &FriLoopStep {
        &self.inner
    }

    /// The closed loop (its step timing; the controller between steps).
    pub fn inner_mut(&mut self) -> &mut FriLoopStep {
        &mut self.inner
    }

    /// The latest snapshot.
    pub fn snapshot(&self) -> &Snapshot {
        &self.snap
    }

    /// No trial is held (running, armed or finishing its record) and none is
    /// being planned: every trial the lab took has been concluded.
    pub fn is_idle(&self) -> bool {
        self.trial.is_none() && self.pending.is_none()
    }

    /// The last finished trial's outcome, once (taken).
    pub fn take_outcome(&mut self) -> Option<TrialOutcome> {
        self.outcome.take()
    }

    /// Index (draw) of the next trial planned.
    pub fn set_next_trial(&mut self, index: usize) {
        self.trial_index = index;
    }

    /// The current trial's judge trace (tool point and true ball centre).
    pub fn trace(&self) -> &TrialTrace {
        &self.trace
    }

    /// The current trial's true passes through the intercept point's `y`.
    pub fn passes(&self) -> &[(f64, Vector3<f64>)] {
        &self.passes
    }

    fn controller(&mut self) -> &mut Controller {
        self.inner.controller_mut()
    }

    /// Before the closed loop's step: commands, magnet, measurements.
    fn before(&mut self, t: f64) {
        if self.p.bridge.take_stop_request() {
            self.stop_now(t);
        }
        while let Ok(reply) = self.p.io_replies.pop() {
            self.io_reply(t, reply);
        }
        self.take_commands(t);
        self.dead_man(t);
        self.follow_magnet();
        if self.trial.is_some() && self.camera_lost(t) {
            let state = self.inner.controller().state();
            if !matches!(
                state,
                TrialState::Idle | TrialState::Done | TrialState::Aborted
            ) {
                self.abort_detail = CAMERA_LOST;
                self.inner
                    .controller_mut()
                    .abort(t, AbortReason::CameraLost);
            }
        }
        let mut n = 0u64;
        while let Ok(m) = self.p.measurements.pop() {
            self.snap.camera.set_frame(&m);
            self.last_frame_s = Some(t);
            if !m.found {
                continue;
            }
            if self.trial.is_some() {
                self.measured.sighting(m.t_capture_s, m.lateral_m);
            }
            let inbox = &mut self.inner.step.inbox;
            if inbox.len() < inbox.capacity() {
                inbox.push(Sighting {
                    t_capture_s: m.t_capture_s,
                    lateral_m: m.lateral_m,
                });
                n += 1;
            } else {
                self.snap.counters.measurement_overflows += 1;
            }
            self.snap.pendulum.measured = bridge::MeasurementView {
                valid: true,
                t_s: m.t_capture_s,
                x_m: m.lateral_m,
            };
        }
        self.snap.counters.measurements += n;
    }

    /// The operator dead-man: while a trial runs (from arming until it is
    /// done or aborted), the latest operator heartbeat (or the command that
    /// started the trial) must be younger than the dead-man time; otherwise
    /// the motion stops safely (abort `operator_lost`, counted). Two atomic
    /// loads; nothing allocates.
    fn dead_man(&mut self, t: f64) {
        let Some(timeout_s) = self.p.operator_timeout_s else {
            return;
        };
        let state = self.inner.controller().state();
        if matches!(
            state,
            TrialState::Idle | TrialState::Done | TrialState::Aborted
        ) && !self.inner.controller().calibrating_motion()
        {
            return;
        }
        let last = self
            .p
            .bridge
            .last_heartbeat_s()
            .unwrap_or(f64::NEG_INFINITY)
            .max(self.operator_since_s);
        if t - last > timeout_s {
            self.controller().abort(t, AbortReason::OperatorLost);
            self.snap.counters.operator_timeouts += 1;
        }
    }

    fn follow_magnet(&mut self) {
        #[cfg(feature = "serial")]
        if let Some(v) = self.p.magnet.as_ref().and_then(MagnetHandle::try_view) {
            self.snap.magnet = match (v.link, v.magnet) {
                (view::LinkState::Lost, _) => bridge::MagnetState::Fault,
                (_, view::MagnetState::On) => bridge::MagnetState::On,
                (_, view::MagnetState::Off) => bridge::MagnetState::Off,
                (_, view::MagnetState::Unknown) => bridge::MagnetState::Unknown,
            };
            if let Some(tr) = self.trial.as_mut()
                && v.magnet == view::MagnetState::On
            {
                tr.magnet_was_on = true;
            }
            // The board holding the ball stopped answering: the trial cannot
            // release it as planned (after the release it no longer matters).
            let state = self.inner.controller().state();
            if v.link == view::LinkState::Lost
                && self.trial.as_ref().is_some_and(|tr| !tr.released)
                && matches!(state, TrialState::Arming | TrialState::Armed)
            {
                self.abort_detail = MAGNET_LOST;
                let t = self.t_s;
                self.inner
                    .controller_mut()
                    .abort(t, AbortReason::MagnetFault);
            }
        }
        while let Ok(note) = self.p.magnet_notes.pop() {
            let Some(tr) = self.trial.as_mut() else {
                continue;
            };
            if note.on {
                tr.magnet_was_on = true;
                continue;
            }
            if tr.released || !tr.magnet_was_on || note.t_s < tr.t0 {
                continue;
            }
            // The coil let go: the ball swings from this moment.
            let t = note.t_s;
            tr.released = true;
            if tr.truth
                && let Some(truth) = self.p.truth.as_mut()
            {
                truth.observer.release(t);
            }
            let c = self.inner.controller_mut();
            if c.state() == TrialState::Armed {
                let _ = c.release(t);
            } else if !matches!(c.state(), TrialState::Aborted | TrialState::Done) {
                // Dropped before the arm was ready (e.g. the coil's hold limit).
                c.abort(t, AbortReason::MagnetFault);
            }
        }
    }

    /// Asks the simulated lab's stand for the pendulum at `distance_m` and
    /// the ball hung at `release_deg`, and moves a real camera's swing plane
    /// with the pivot (nothing without a stand).
    fn place_stand(&mut self, distance_m: f64, release_deg: f64) {
        let Some(stand) = self.p.stand.as_ref() else {
            return;
        };
        stand.place(distance_m, release_deg);
        if let Some(rp) = self.p.real_plane.as_mut() {
            let moved = rp.basis.at_distance(distance_m);
            if moved != rp.basis {
                rp.basis = moved;
                self.push_real_plane();
            }
        }
    }

    /// Hands the vision thread (a fresh detector) and the dashboard's
    /// overlays the swing plane a real camera's basis and the beliefs in
    /// force put the ball in (nothing for the simulated labs).
    fn push_real_plane(&mut self) {
        if let Some(rp) = self.p.real_plane.as_mut() {
            let cal = rp.basis.plane(&self.p.scenario);
            let cam = &self.p.scenario.camera;
            self.snap
                .camera
                .set_calibration(&cal, cam.width_px, cam.height_px);
            let _ = rp.planes.push(cal);
        }
    }

    fn request_magnet(&mut self, on: bool) -> bool {
        let ok = self.p.io_requests.push(IoRequest::Magnet(on)).is_ok();
        if !ok {
            self.magnet_failures += 1;
        }
        ok
    }

    /// A done trial whose after-done trace is still being recorded
    /// (`AFTER_DONE_S`): it has not been concluded (judged and reported) yet.
    fn finishing(&self) -> bool {
        self.trial.is_some() && self.inner.controller().state() == TrialState::Done
    }

    /// The operator's commands, in order. While a done trial still records its
    /// after-done trace they wait in their ring (at most `AFTER_DONE_S`): a
    /// trial started then would take the place of the one not yet concluded,
    /// and new parameters would replace the controller that judges it. A stop
    /// never waits (the bridge's stop flag, `stop_now`).
    fn take_commands(&mut self, t: f64) {
        while !self.finishing()
            && let Some(env) = self.p.bridge.next_command()
        {
            self.handle(t, env.id, env.command);
        }
    }

    /// Stops the motion now. A done trial still recording its after-done
    /// trace is concluded first (as done: the stop does not undo a trial that
    /// finished); a trial being planned is cancelled.
    fn stop_now(&mut self, t: f64) {
        if self.finishing() {
            self.conclude(t);
        }
        self.controller().abort(t, AbortReason::StopRequested);
        if let Some(p) = self.pending.as_mut() {
            p.1 = true;
        }
    }

    /// Why a trial posted now would be refused (`None`: it would start), as
    /// [`Self::handle`] decides it; published in the snapshot (`ready`).
    fn trial_refusal(&self, t: f64) -> Option<Refusal> {
        let state = self.inner.controller().state();
        if self.pending.is_some()
            || self.finishing()
            || self.inner.controller().calibrating_motion()
            || !matches!(
                state,
                TrialState::Idle | TrialState::Done | TrialState::Aborted
            )
        {
            Some(Refusal::Busy)
        } else if !self.commanding() {
            Some(Refusal::RobotNotCommanding)
        } else if self.magnet_lost() || self.camera_lost(t) {
            Some(Refusal::DeviceUnavailable)
        } else {
            None
        }
    }

    fn handle(&mut self, t: f64, id: u64, command: Command) {
        let state = self.inner.controller().state();
        let busy = self.pending.is_some()
            || self.inner.controller().calibrating_motion()
            || !matches!(
                state,
                TrialState::Idle | TrialState::Done | TrialState::Aborted
            );
        let (outcome, returned) = match command {
            Command::Stop => {
                self.stop_now(t);
                (Ok(()), None)
            }
            Command::Arm | Command::RunTrial { .. } if busy => (Err(Refusal::Busy), None),
            Command::Arm | Command::RunTrial { .. } if !self.commanding() => {
                (Err(Refusal::RobotNotCommanding), None)
            }
            Command::Arm | Command::RunTrial { .. }
                if self.magnet_lost() || self.camera_lost(t) =>
            {
                (Err(Refusal::DeviceUnavailable), None)
            }
            Command::RunTrial { trial_id: 0, .. } => (Err(Refusal::Invalid), None),
            Command::Arm => {
                self.operator_since_s = t;
                return self.plan(id, 0, false, TrialSetup::default());
            }
            Command::RunTrial { trial_id, setup } => {
                self.operator_since_s = t;
                return self.plan(id, trial_id, true, setup);
            }
            Command::Disarm => {
                if state == TrialState::Armed || state == TrialState::Arming {
                    // The trial ends here: reported (and recorded) as disarmed.
                    self.controller().abort(t, AbortReason::Disarmed);
                    self.conclude(t);
                    let _ = self.controller().reset(t);
                    (Ok(()), None)
                } else {
                    (Err(Refusal::NotArmed), None)
                }
            }
            Command::Magnet { on: true } => {
                if self.request_magnet(true) {
                    (Ok(()), None)
                } else {
                    (Err(Refusal::DeviceUnavailable), None)
                }
            }
            Command::Magnet { on: false } => match self.trial.as_ref() {
                Some(tr) if !tr.released && state != TrialState::Armed => {
                    // Held while the arm is still moving home: not yet.
                    (Err(Refusal::NotArmed), None)
                }
                Some(_) | None => {
                    let ok = self.request_magnet(false);
                    if let Some(tr) = self.trial.as_mut() {
                        tr.release_requested |= ok;
                    }
                    if ok {
                        (Ok(()), None)
                    } else {
                        (Err(Refusal::DeviceUnavailable), None)
                    }
                }
            },
            Command::Excite(_) if busy || !self.inner.controller().at_rest() => {
                (Err(Refusal::Busy), None)
            }
            Command::Excite(_) if !self.commanding() => (Err(Refusal::RobotNotCommanding), None),
            Command::Excite(e) => {
                // Between trials: a finished trial is concluded (it was,
                // unless it still records its after-done trace, when commands
                // wait) and the controller rests in `Idle`.
                self.conclude(t);
                if state != TrialState::Idle {
                    let _ = self.controller().reset(t);
                }
                match self.controller().excite(t, e) {
                    Ok(()) => {
                        // A motion: the dead-man counts from here.
                        self.operator_since_s = t;
                        (Ok(()), None)
                    }
                    Err(_) => (Err(Refusal::Invalid), None),
                }
            }
            Command::MoveTo(_) | Command::Knock(_)
                if busy || !self.inner.controller().at_rest() =>
            {
                (Err(Refusal::Busy), None)
            }
            Command::MoveTo(_) | Command::Knock(_) if !self.commanding() => {
                (Err(Refusal::RobotNotCommanding), None)
            }
            Command::MoveTo(q) => (self.joint_move(t, state, &q, false), None),
            Command::Knock(q) => (self.joint_move(t, state, &q, true), None),
            Command::SetParams(p) if busy => (Err(Refusal::Busy), Some(p)),
            Command::SetParams(p) => {
                match self.p.io_requests.push(IoRequest::Params {
                    ack: id,
                    scenario: p,
                }) {
                    Ok(()) => {
                        self.pending = Some((id, false));
                        return;
                    }
                    Err(rtrb::PushError::Full(IoRequest::Params { scenario, .. })) => {
                        (Err(Refusal::Busy), Some(scenario))
                    }
                    Err(_) => (Err(Refusal::Busy), None),
                }
            }
        };
        self.p.bridge.ack(id, outcome, returned);
    }

    /// Asks `isochron-lab-io` for the plan of the next trial; the command is
    /// answered when the plan is back.
    fn plan(&mut self, ack: u64, trial_id: u64, auto_release: bool, setup: TrialSetup) {
        let mut draw = draw_trial(&self.p.scenario, self.p.seed, self.trial_index);
        if let Some(d) = setup.distance_m.or(self.p.fixed_distance_m) {
            draw.distance_m = d;
        }
        if let Some(r) = setup.release_deg {
            draw.release_angle_deg = r.abs().copysign(draw.release_angle_deg);
        }
        let req = IoRequest::Plan {
            ack,
            trial_id,
            auto_release,
            index: self.trial_index,
            draw,
            setup,
        };
        if self.p.io_requests.push(req).is_ok() {
            self.trial_index += 1;
            self.pending = Some((ack, false));
        } else {
            self.p.bridge.ack(ack, Err(Refusal::Busy), None);
        }
    }

    fn io_reply(&mut self, t: f64, reply: IoReply) {
        let cancelled = self.pending.is_some_and(|p| p.1);
        self.pending = None;
        match reply {
            IoReply::Plan {
                ack,
                trial_id,
                auto_release,
                index,
                draw,
                plan,
            } => {
                let outcome = match plan {
                    _ if cancelled => Err(Refusal::ChecksFailed),
                    Ok(plan) => self.begin(t, (trial_id, index), auto_release, draw, plan),
                    Err(r) => Err(r),
                };
                self.p.bridge.ack(ack, outcome, None);
            }
            IoReply::Params { ack, result } => match result {
                Ok((mut controller, mut scenario)) if !cancelled => {
                    // What this session taught the old controller carries
                    // over where the new beliefs keep its basis.
                    let same_camera =
                        scenario.camera.latency_ms == self.p.scenario.camera.latency_ms;
                    controller.carry_session(self.controller(), same_camera);
                    std::mem::swap(self.controller(), &mut *controller);
                    std::mem::swap(&mut self.p.scenario, &mut scenario);
                    if !same_camera && let Some(l) = self.p.stamp_latency.as_ref() {
                        // The frames from now on are stamped with the new
                        // belief (the latency step's result).
                        l.store(
                            (self.p.scenario.camera.latency_ms * 1e-3).to_bits(),
                            std::sync::atomic::Ordering::Relaxed,
                        );
                    }
                    // The detector measures on the plane the new beliefs
                    // put the camera and the ball at (a calibration step's
                    // lens, pose, length, offset).
                    self.push_real_plane();
                    // The old controller is freed off this thread.
                    let _ = self.p.io_requests.push(IoRequest::Free(controller));
                    let _ = self.p.bridge.ack(ack, Ok(()), Some(scenario));
                }
                Ok((controller, scenario)) => {
                    let _ = self.p.io_requests.push(IoRequest::Free(controller));
                    let _ = self.p.bridge.ack(ack, Err(Refusal::Busy), Some(scenario));
                }
                Err(scenario) => {
                    let _ = self
                        .p
                        .bridge
                        .ack(ack, Err(Refusal::Invalid), Some(scenario));
                }
            },
        }
    }

    /// Starts arming a planned trial (`auto_release`: released after the drawn wait).
    fn begin(
        &mut self,
        t: f64,
        (id, index): (u64, usize),
        auto_release: bool,
        draw: TrialDraw,
        plan: ArmPlan,
    ) -> Result<(), Refusal> {
        if !self.commanding() {
            // The session dropped out while the trial was planned.
            return Err(Refusal::RobotNotCommanding);
        }
        // A trial still held is concluded before the next takes its place
        // (commands wait while one finishes, so this is only a safety net:
        // no trial ends without its outcome and report).
        self.conclude(t);
        let _ = self.controller().reset(t);
        // The trial starts now on the operator's command: the dead-man counts from here.
        self.operator_since_s = t;
        // The world hangs the trial's true ball (the simulated lab).
        let truth = match self.p.truth.as_mut() {
            Some(truth) => {
                truth.observer.hang(&TrialStart {
                    t_s: t,
                    scenario: &self.p.scenario,
                    seed: self.p.seed,
                    index,
                    draw: &draw,
                    plan: &plan,
                })?;
                true
            }
            None => false,
        };
        self.place_stand(draw.distance_m, draw.release_angle_deg);
        if !self.request_magnet(true) {
            return Err(Refusal::DeviceUnavailable);
        }
        self.controller()
            .arm(t, &plan)
            .map_err(|_| Refusal::ChecksFailed)?;
        if let Some(truth) = self.p.truth.as_mut() {
            let cam = truth.camera;
            // What the lab believes: the camera's pose and the rest point (both
            // as calibrated, when they are).
            let rest = plan.intercept_m;
            let pose = self.p.scenario.camera.pose.unwrap_or(cam.pose);
            let cal =
                SwingPlaneCalibration::from_pose(cam.intrinsics, &pose, &rest, cam.ball_radius_m);
            let size = &self.p.scenario.camera;
            self.snap
                .camera
                .set_calibration(&cal, size.width_px, size.height_px);
            let _ = truth.calibrations.push(cal);
            truth.observer.show();
        }
        self.inner.clear_stop();
        self.abort_detail = "";
        self.snap.abort = AbortView::default();
        self.trace.clear();
        self.passes.clear();
        self.measured.clear();
        self.outcome = None;
        self.snap.trial_id = id;
        let counters_at_start = (
            self.inner.controller().counters().limit_violations(),
            self.inner.step.deadline_misses,
            self.inner.step.preempted_steps,
        );
        self.trial = Some(Trial {
            id,
            draw,
            plan,
            truth,
            auto_release,
            armed_at: None,
            release_requested: false,
            magnet_was_on: false,
            released: false,
            done_at: None,
            t0: t,
            index,
            counters_at_start,
            at_predicted: None,
        });
        Ok(())
    }

    /// After the closed loop's step: truth, trace, trial progress, events.
    fn follow_trial(&mut self, t: f64) {
        self.emit_state(t);
        let state = self.inner.controller().state();
        // The robot's true joints where the simulator tells them (the judge's
        // tool point), else the measured ones.
        let commit = self.inner.controller().commit().copied();
        if self.trial.is_some() {
            self.record_measured(t, commit.as_ref());
        }
        let Some(trial) = self.trial.as_mut() else {
            return;
        };
        let q_true = self.q_true.unwrap_or(self.q);
        let tool = self.inner.controller().tool_point(&q_true);
        if trial.truth
            && let Some(truth) = self.p.truth.as_mut()
        {
            let ball = truth.observer.step(
                t,
                &q_true,
                self.period_s,
                commit.as_ref(),
                &mut self.passes,
                &mut trial.at_predicted,
            );
            self.trace.push(t, tool, ball);
        }
        let mut want_release = false;
        match state {
            TrialState::Armed => {
                let since = *trial.armed_at.get_or_insert(t);
                want_release = trial.auto_release
                    && !trial.release_requested
                    && t - since >= trial.draw.release_wait_s;
            }
            TrialState::Done => {
                let since = *trial.done_at.get_or_insert(t);
                if t - since >= AFTER_DONE_S {
                    self.conclude(t);
                }
                return;
            }
            TrialState::Aborted => {
                self.conclude(t);
                return;
            }
            _ => {}
        }
        // An operator's trial waits in Armed for the release as long as it
        // takes; any other trial ends by this time.
        let timed_out =
            (trial.auto_release || state != TrialState::Armed) && t - trial.t0 > TRIAL_TIMEOUT_S;
        if timed_out {
            self.controller().abort(t, AbortReason::PredictionTimeout);
            return;
        }
        if want_release && self.request_magnet(false) {
            if let Some(tr) = self.trial.as_mut() {
                tr.release_requested = true;
            }
        }
    }

    /// The measured judge's samples of this step: the measured tool point
    /// (the controller's kinematics and believed tool) and, until shortly
    /// before the committed pass, the filter's rest offset and frequency.
    fn record_measured(&mut self, t: f64, commit: Option<&crate::control::Commit>) {
        let c = self.inner.controller();
        let p = c.tool_point(&self.q);
        self.measured.tool(t, [p.x, p.y, p.z]);
        if let Some((tp, x, _)) = c.ekf().and_then(crate::ekf::Ekf::posterior)
            && commit.is_none_or(|cm| tp < cm.predicted_pass_s - 0.2)
        {
            if self.p.scenario.ekf.estimate_offset {
                self.measured.rest_lateral_m = x[crate::ekf::model::B];
            }
            if let Some(l) = c.trial_length_estimate_m().filter(|l| *l > 0.0) {
                self.measured.omega_radps =
                    Some((self.p.scenario.pendulum.gravity_mps2 / l).sqrt());
            }
        }
    }

    /// Ends the trial: judges it on ground truth (when the lab knows the
    /// truth), keeps its [`TrialOutcome`] and, when it finished, reports it.
    /// A move to joints `q` between trials ([`Command::MoveTo`], or
    /// [`Command::Knock`] when `knock`), as an excitation.
    fn joint_move(
        &mut self,
        t: f64,
        state: TrialState,
        q: &[f64; crate::kinematics::iiwa7::JOINTS],
        knock: bool,
    ) -> Result<(), Refusal> {
        self.conclude(t);
        if state != TrialState::Idle {
            let _ = self.controller().reset(t);
        }
        let moved = if knock {
            self.controller().knock_to(t, q)
        } else {
            self.controller().move_to(t, q)
        };
        match moved {
            Ok(_) => {
                self.operator_since_s = t;
                Ok(())
            }
            Err(crate::control::ControlError::Target(..)) => Err(Refusal::Infeasible),
            Err(_) => Err(Refusal::Busy),
        }
    }

    fn conclude(&mut self, t: f64) {
        if self.trial.is_none() {
            return;
        }
        // The state change (an abort's reason) is reported with this trial's
        // id before the trial is let go.
        self.emit_state(t);
        let Some(trial) = self.trial.take() else {
            return;
        };
        let mut measured_movement = None;
        let c = self.inner.controller();
        let state = c.state();
        let (v0, m0, p0) = trial.counters_at_start;
        let mut o = TrialOutcome {
            id: trial.id,
            index: trial.index,
            draw: trial.draw,
            planned_movement_time_s: trial.plan.duration_s,
            final_state: state,
            abort_reason: if state == TrialState::Aborted {
                c.abort_reason()
            } else {
                None
            },
            judgement: None,
            judge_error: None,
            physical: None,
            physical_error: None,
            measured: None,
            prediction_crossing_time_error_ms: None,
            prediction_position_error_m: None,
            latency_estimate_ms: c.latency().latency_s() * 1e3,
            camera_offset_estimate_ms: None,
            length_estimate_m: c.trial_length_estimate_m(),
            limit_violations: c.counters().limit_violations().saturating_sub(v0),
            deadline_misses: self.inner.step.deadline_misses.saturating_sub(m0),
            preempted_steps: self.inner.step.preempted_steps.saturating_sub(p0),
            t_end_s: t,
        };
        if let Some(commit) = c.commit().copied() {
            let pendulum = &self.p.scenario.pendulum;
            // A strike's aim, for both judges.
            let aim = trial.plan.strike.map(|k| StrikeAim {
                planned_tool_speed_mps: k.speed_mps,
                // Restitution 0 (the controller's belief): the ball
                // leaves with the tool's speed along the contact
                // normal, the swing's horizontal at the pass.
                target_ball_speed_mps: k.speed_mps * k.direction.y.hypot(k.direction.x),
                return_sign: k.direction.y.signum(),
                // What the controller predicted at its commit (its beliefs).
                predicted: commit.rebound,
            });
            o.measured = self.measured.judge(&MeasuredBeliefs {
                predicted_pass_s: commit.predicted_pass_s,
                camera_offset_s: commit.camera_offset_s,
                sigma_x_m: self.p.scenario.ekf.measurement_noise_m,
                omega_radps: (pendulum.gravity_mps2 / pendulum.length_m.max(1e-3)).sqrt(),
                settle_m: ARRIVAL_SETTLE_M,
                settle_lead_s: trial.plan.settle_lead_s,
                tolerance_ms: self.p.scenario.success.timing_tolerance_ms,
                period_s: self.period_s,
                contact_delay_s: self.p.scenario.success.torque_lag_periods * self.period_s,
                contact_pulse_s: self.p.scenario.success.contact_pulse_ms * 1e-3,
                strike: aim,
                intercept_y_m: trial.plan.intercept_m.y,
                // The ball first touches the disc's rim (the ball's radius
                // and the disc's extent along the swing at the measured
                // tool axis).
                contact_reach_m: {
                    let n = self.inner.controller().tool_axis(&self.q);
                    pendulum.ball_radius_m
                        + self.p.scenario.task.tool_contact_radius_m
                            * (1.0 - n.y * n.y).max(0.0).sqrt()
                },
            });
            o.latency_estimate_ms = commit.latency_s * 1e3;
            o.camera_offset_estimate_ms = Some(commit.camera_offset_s * 1e3);
            let motion = PlannedMotion {
                start_m: c.home_m(),
                end_m: c.motion_target_m(),
                profile: ProfileKind::Hopf,
                duration_s: commit.duration_s,
                commanded_start_s: commit.motion_start_s,
            };
            if !trial.truth {
                // The movement as the measured joints show it (the real lab's
                // movement time: fitted as the truth's judge fits the true tool).
                measured_movement = self.measured.movement(&motion, &mut self.judge_scratch);
            }
            if trial.truth {
                let intercept = self
                    .p
                    .truth
                    .as_ref()
                    .and_then(|truth| truth.observer.intercept_m())
                    .unwrap_or(trial.plan.intercept_m);
                match judge_into(&self.trace, &motion, &intercept, &mut self.judge_scratch) {
                    // A strike meets the ball on its way (issue #38): its
                    // arrival is the tool's crossing of the intercept point.
                    Ok(j) => {
                        o.judgement = Some(trial.plan.strike.map_or(j, |k| {
                            judge_strike_crossing(
                                &j,
                                &self.trace,
                                &intercept,
                                k.direction.y.signum(),
                                commit.predicted_pass_s,
                                &mut self.judge_scratch,
                            )
                            .unwrap_or(j)
                        }));
                    }
                    Err(e) => o.judge_error = Some(e),
                }
                if let Some((tp, _)) = nearest_pass(&self.passes, commit.predicted_pass_s) {
                    o.prediction_crossing_time_error_ms =
                        Some((commit.predicted_pass_s - tp) * 1e3);
                }
                if let Some(truth) = trial.at_predicted {
                    o.prediction_position_error_m = Some((commit.predicted_ball_m - truth).norm());
                }
            }
            if trial.truth {
                self.judge_world(commit.predicted_pass_s, aim.as_ref(), &mut o);
            }
        }
        // A contact shows what the camera offset missed (whatever the
        // magnet's release delay): the controller learns from it. Not from
        // a strike yet: the measured judge times one (its own pass and
        // arrival), but learning from its contacts was neither built nor
        // tested for strokes.
        let measured = o.measured.filter(|_| trial.plan.strike.is_none());
        if let (Some(m), Some(used_ms)) = (measured, o.camera_offset_estimate_ms)
            && let (Some(e_ms), Some(sd_ms)) =
                (m.camera_clock_error_ms, m.camera_clock_error_std_ms)
        {
            self.controller()
                .learn_from_contact((used_ms + e_ms) * 1e-3, sd_ms * 1e-3);
        }
        // The arrival against the camera's pass: what the robot added to
        // the plan (the measured timing error less the camera's clock error).
        if let Some(m) = measured
            && let (Some(t_ms), Some(e_ms), Some(sd_ms)) = (
                m.timing_error_ms,
                m.camera_clock_error_ms,
                m.camera_clock_error_std_ms,
            )
        {
            self.controller()
                .learn_from_arrival((t_ms - e_ms) * 1e-3, sd_ms * 1e-3);
        }
        self.outcome = Some(o);
        self.snap.trial_id = 0;
        if state != TrialState::Done {
            // Aborted: reported by the state change (`Aborted`).
            return;
        }
        let mj = o
            .measured
            .filter(super::super::control::measured::MeasuredJudgement::judged);
        let j = o.judgement.or_else(|| {
            // The real lab: the measured judge's figures, and the movement
            // fitted on the measured tool point.
            let m = mj.filter(|_| !trial.truth)?;
            let (start_s, movement_time_s) = measured_movement.unwrap_or((f64::NAN, f64::NAN));
            Some(Judgement {
                t_star_s: m.pass_t_s.unwrap_or(f64::NAN),
                start_s,
                arrival_s: m.arrival_t_s.unwrap_or(f64::NAN),
                timing_error_ms: m.timing_error_ms.map_or(f64::NAN, f64::abs),
                position_error_m: f64::NAN,
                movement_time_s,
                fit_rms_m: f64::NAN,
            })
        });
        let not_judged = if o.physical.is_some() || (o.physical_error.is_none() && j.is_some()) {
            None
        } else if !trial.truth && o.measured.is_some_and(|m| !m.torque_signal) {
            Some(NOT_JUDGED_NO_TORQUE)
        } else if !trial.truth && o.measured.is_some_and(|m| m.robot_gap_ms.is_some()) {
            Some(NOT_JUDGED_ROBOT_GAP)
        } else if !trial.truth && o.measured.is_some() {
            Some(NOT_JUDGED_MEASURED)
        } else if !trial.truth && no_motion(&o) {
            Some(NOT_JUDGED_NO_MOTION)
        } else if !trial.truth {
            Some(NOT_JUDGED_REAL)
        } else if no_motion(&o) {
            Some(NOT_JUDGED_NO_MOTION)
        } else {
            Some(NOT_JUDGED_TRACE)
        };
        let result = TrialResult {
            success: o.succeeded(&self.p.scenario.success),
            timing_error_ms: j.map_or(f64::NAN, |j| j.timing_error_ms),
            position_error_m: j.map_or(f64::NAN, |j| j.position_error_m),
            // A real lab's trial not judged still says how long its motion
            // took, as its measured joints show it.
            movement_time_s: j.map_or_else(
                || measured_movement.map_or(f64::NAN, |(_, mt)| mt),
                |j| j.movement_time_s,
            ),
            distance_m: trial.draw.distance_m,
            t_star_s: j.map_or(f64::NAN, |j| j.t_star_s),
            arrival_t_s: j.map_or(f64::NAN, |j| j.arrival_s),
            prediction_time_error_ms: o.prediction_crossing_time_error_ms.unwrap_or(f64::NAN),
            limit_violations: o.limit_violations,
            not_judged,
            measured: o.measured,
            judged_by: match not_judged {
                Some(_) => None,
                None if o.physical.is_some() => Some(JudgedBy::Physical),
                None if o.judgement.is_some() => Some(JudgedBy::Truth),
                None => Some(JudgedBy::Measured),
            },
        };
        self.snap.counters.trials += 1;
        self.p.bridge.emit(EventRecord {
            t_s: t,
            trial_id: trial.id,
            event: Event::TrialFinished { result },
        });
        let _ = self.controller().reset(t);
    }

    /// The physical judge on the true world: fills `o.physical` and puts its
    /// figures (t*, arrival, |timing error|, tool-ball distance at t*) into
    /// the reported judgement; the fitted movement time stays.
    fn judge_world(
        &mut self,
        committed_pass_s: f64,
        strike: Option<&StrikeAim>,
        o: &mut TrialOutcome,
    ) {
        let tolerance_ms = self.p.scenario.success.timing_tolerance_ms;
        let Some(verdict) = self.p.truth.as_mut().and_then(|truth| {
            truth
                .observer
                .judge_physical(&self.passes, committed_pass_s, tolerance_ms, strike)
        }) else {
            return;
        };
        match verdict {
            Ok(v) => {
                let p = v.judgement;
                if let Some(j) = o.judgement.as_mut() {
                    j.t_star_s = p.t_star_s;
                    j.arrival_s = p.arrival_s;
                    j.timing_error_ms = p.timing_error_ms.abs();
                    j.position_error_m = v.position_error_m;
                }
                o.physical = Some(p);
            }
            Err(e) => o.physical_error = Some(e),
        }
    }

    fn fill_snapshot(&mut self, t: f64) {
        self.snap.camera.lost = self.camera_lost(t);
        self.snap.ready = bridge::Readiness::from_refusal(self.trial_refusal(t));
        let c = self.inner.controller();
        let s = &mut self.snap;
        s.t_s = t;
        s.seq += 1;
        s.trial_state = c.state();
        // Pendulum: where it hangs, its estimate and predicted horizon.
        s.pendulum.rest_distance_m = self
            .p
            .stand
            .as_ref()
            .map(|st| st.asked().0)
            .or(self.p.fixed_distance_m)
            .unwrap_or(f64::NAN);
        let l = self.p.scenario.pendulum.length_m;
        if let Some((ekf, (t_post, x, p))) = c.ekf().and_then(|e| e.posterior().map(|p| (e, p))) {
            s.pendulum.phi_rad = x[0];
            s.pendulum.dphi_radps = x[1];
            s.pendulum.sigma_phi_rad = p[(0, 0)].max(0.0).sqrt();
            s.pendulum.sigma_dphi_radps = p[(1, 1)].max(0.0).sqrt();
            s.pendulum.x_m = l * x[0].sin();
            s.pendulum.sigma_x_m = l * x[0].cos().abs() * s.pendulum.sigma_phi_rad;
            if t >= self.next_horizon_s || t_post != self.horizon_posterior_s {
                self.next_horizon_s = t + HORIZON_EVERY_S;
                self.horizon_posterior_s = t_post;
                s.pendulum.horizon.len = 0;
                if let Ok(n) = ekf.predict_horizon(t, HORIZON_STEP_S, &mut self.horizon) {
                    if let Some(first) = self.horizon.first().filter(|_| n > 0) {
                        s.pendulum.ball_m = [first.ball_m.x, first.ball_m.y, first.ball_m.z];
                    }
                    for pr in &self.horizon[..n] {
                        s.pendulum.horizon.push(HorizonPoint {
                            t_s: pr.t_s,
                            x_m: pr.lateral_m,
                            sigma_m: pr.lateral_std_m,
                        });
                    }
                }
            }
        } else {
            s.pendulum.horizon.len = 0;
            s.pendulum.sigma_phi_rad = f64::NAN;
            s.pendulum.sigma_dphi_radps = f64::NAN;
            s.pendulum.sigma_x_m = f64::NAN;
            s.pendulum.ball_m = [f64::NAN; 3];
        }
        s.pendulum.truth_ball_m = self
            .trial
            .as_ref()
            .filter(|tr| tr.truth)
            .and(self.p.truth.as_ref())
            .and_then(|truth| truth.observer.ball_m())
            .map_or([f64::NAN; 3], |b| [b.x, b.y, b.z]);
        // Motion: the timing system (Hopf oscillator and neurons) and the path.
        let ms = c.motion_sample();
        s.hopf.active = matches!(c.state(), TrialState::Intercepting);
        s.hopf.a = ms.a;
        s.hopf.b = ms.b;
        s.hopf.u_init = ms.neurons.u_init;
        s.hopf.u_hopf = ms.neurons.u_hopf;
        s.hopf.u_final = ms.neurons.u_final;
        s.path.speed_planned_mps = ms.planned_path_speed_mps;
        let tool = c.tool_point(&self.q);
        // Differentiated on the robot's clock (its sequence counter at its send
        // period), not on the receive times: a late message followed by a
        // prompt one is 2 periods of motion over microseconds of receive time,
        // which read as spikes of tens of m/s while the arm moved home.
        let tr = self.robot_t_s;
        match self.prev_tool {
            Some((tp, p)) if tr > tp => {
                s.path.speed_executed_mps = (tool - p).norm() / (tr - tp);
                self.prev_tool = Some((tr, tool));
            }
            Some(_) => {}
            None => {
                s.path.speed_executed_mps = 0.0;
                self.prev_tool = Some((tr, tool));
            }
        }
        let home = c.home_m();
        let target = c.motion_target_m();
        let len = (target - home).norm();
        s.path.length_m = len;
        s.path.intercept_m = [target.x, target.y, target.z];
        s.pendulum.crossing_t_s = f64::NAN;
        s.pendulum.crossing_sigma_s = f64::NAN;
        if let Some(cm) = c.commit() {
            s.path.start_t_s = cm.motion_start_s;
            s.path.arrival_t_s = cm.motion_start_s + cm.duration_s;
            s.path.movement_time_s = cm.duration_s;
            s.path.progress_planned = ((t - cm.motion_start_s) / cm.duration_s).clamp(0.0, 1.0);
            s.pendulum.crossing_t_s = cm.predicted_pass_s;
            s.pendulum.crossing_sigma_s = cm.predicted_pass_std_s;
        } else {
            s.path.start_t_s = f64::NAN;
            s.path.arrival_t_s = f64::NAN;
            s.path.movement_time_s = self.p.scenario.task.movement_time_s;
            s.path.progress_planned = 0.0;
        }
        s.path.progress_executed = if len > 1e-9 {
            ((tool - home).dot(&(target - home)) / (len * len)).clamp(0.0, 1.0)
        } else {
            0.0
        };
        // Arm and link.
        s.robot.q_rad = self.q;
        s.robot.q_cmd_rad = self.inner.step.out.q_command_rad;
        s.robot.tool_m = [tool.x, tool.y, tool.z];
        s.robot.actuation_latency_ms = c.latency().latency_s() * 1e3;
        s.robot.tau_ext_nm = self.tau_ext;
        s.fri.session = map_session(self.session);
        s.fri.quality = map_quality(self.quality);
        s.fri.period_ms = self.period_s * 1e3;
        if let Some(st) = self.p.session.get() {
            use std::sync::atomic::Ordering::Relaxed;
            s.fri.late_replies = st.late_replies.load(Relaxed);
            s.fri.missed_cycles = st.missed_cycles.load(Relaxed);
            s.fri.silences = st.silences.load(Relaxed);
            s.fri.commanding_lost = st.commanding_lost.load(Relaxed);
            if s.seq % 10 == 0 {
                // The session measures receive -> send after this step returns:
                // its median so far (a scan of a fixed histogram, every 10 steps).
                s.fri.reply_latency_us = st.reply_latency.quantile_ns(0.5) as f64 * 1e-3;
            }
        }
        let k = c.counters();
        s.counters.steps = k.steps;
        s.counters.guard_interventions = k.guard_position_clamps + k.guard_step_clamps;
        s.counters.limit_violations = k.limit_violations();
        s.timing.deadline_misses = self.inner.step.deadline_misses;
    }

    fn period_stats(&mut self, now: Instant) {
        if let Some(last) = self.last_step_at {
            let dt_us = (now - last).as_secs_f64() * 1e6;
            self.period_max_us = self.period_max_us.max(dt_us);
            self.period_sum_us += dt_us;
            self.periods += 1;
            if self.periods >= PERIOD_WINDOW {
                self.snap.timing.period_mean_us = self.period_sum_us / f64::from(self.periods);
                self.snap.timing.period_max_us = self.period_max_us;
                (self.period_max_us, self.period_sum_us, self.periods) = (0.0, 0.0, 0);
            }
        }
        self.last_step_at = Some(now);
    }
}

impl ControlStep for LabStep {
    fn step(&mut self, input: &StepInput<'_>, command_rad: &mut Joints) {
        let started = Instant::now();
        self.period_stats(started);
        let now_ns = match self.p.clock {
            // The control clock is the lab's (shared with the camera): the
            // session's receive time moved by the offset between the two
            // clocks, taken at the first message (error: the receive -> step
            // delay, us).
            LabClock::Wall(epoch) => {
                let lab_ns = started.saturating_duration_since(epoch).as_nanos() as i64;
                let off = *self
                    .offset_ns
                    .get_or_insert(lab_ns - input.now_ns.min(i64::MAX as u64) as i64);
                (input.now_ns as i64).saturating_add(off).max(0) as u64
            }
            LabClock::Virtual => input.now_ns,
        };
        let t = now_ns as f64 * 1e-9;
        if let Some(since) = self.silent_since.take()
            && t - since > FRI_LOST_AFTER_S
        {
            // The controller came back after the link counted as lost.
            self.lose_link(StopReason::ControllerSilent);
        }
        self.t_s = t;
        let m = input.monitoring;
        self.session = m.session_state;
        self.quality = m.quality;
        if let Some(q) = m.measured_joint_position_rad {
            self.q = q;
        }
        if let Some(tau) = m.external_torque_nm {
            self.tau_ext = tau;
            if self.trial.is_some() {
                self.measured.torques(t, tau);
            }
        }
        if let Some(q) = self.p.truth.as_ref().and_then(|t| t.observer.true_joints()) {
            self.q_true = q.iter().all(|v| v.is_finite()).then_some(q);
        }
        let send_period_s = if m.send_period_ms > 0 {
            f64::from(m.send_period_ms) * 1e-3
        } else {
            self.period_s
        };
        let robot_t_s = f64::from(m.sequence_counter) * send_period_s;
        if robot_t_s < self.robot_t_s {
            // The counter wrapped or a new session began: start over.
            self.prev_tool = None;
        }
        self.robot_t_s = robot_t_s;
        self.before(t);
        let lab_input = StepInput { now_ns, ..*input };
        self.inner.step(&lab_input, command_rad);
        // The rest waits until the reply is out (`after_reply`).
        let us = started.elapsed().as_secs_f64() * 1e6;
        self.step_max_us = self.step_max_us.max(us);
        self.snap.timing.step_us = us;
        self.snap.timing.step_max_us = self.step_max_us;
        self.after_pending = Some(t);
    }

    fn after_reply(&mut self) {
        // The trial follows the step it saw (the judge's trace, the passes,
        // the result), then the snapshot: none of it changes the command
        // just sent, and all of it happens before the next message.
        let Some(t) = self.after_pending.take() else {
            return;
        };
        self.follow_trial(t);
        self.fill_snapshot(t);
        self.p.bridge.publish(&self.snap);
    }

    fn idle(&mut self, now_ns: u64) {
        let t = match self.p.clock {
            LabClock::Wall(epoch) => epoch.elapsed().as_secs_f64(),
            LabClock::Virtual => now_ns as f64 * 1e-9,
        };
        self.between_messages(t);
    }

    fn stop(&mut self, reason: StopReason) {
        if reason == StopReason::ControllerSilent {
            // A gap, not yet a lost link (`FRI_LOST_AFTER_S`).
            self.silent_since.get_or_insert(self.t_s);
        } else {
            self.lose_link(reason);
        }
        if !matches!(reason, StopReason::LeftCommanding(_)) {
            self.session = SessionState::Idle;
            self.snap.fri.session = FriSessionState::Disconnected;
            self.snap.fri.quality = FriQuality::Unknown;
            self.snap.ready = bridge::Readiness::from_refusal(self.trial_refusal(self.t_s));
            // Publish the lost link (this runs on the control thread too).
            self.p.bridge.publish_latest(&self.snap);
        }
    }
}

impl TrialOutcome {
    /// The success rule of [`crate::control::TrialRecord::decide`] on what
    /// the control thread knows (no abort, no limit violation, both errors
    /// within tolerance), without building the record.
    pub fn succeeded(&self, tol: &crate::control::SuccessParams) -> bool {
        if self.physical.is_none()
            && self.judgement.is_none()
            && let Some(m) = self.measured.filter(MeasuredJudgement::judged)
        {
            // The real lab: the measured judge decides.
            return self.final_state == TrialState::Done && self.limit_violations == 0 && m.success;
        }
        if let Some(p) = &self.physical {
            // The reality lab: the physical judge decides (as
            // `TrialRecord::decide`).
            return self.final_state == TrialState::Done
                && self.limit_violations == 0
                && p.contact_s.is_some()
                && p.timing_error_ms.abs() <= tol.timing_tolerance_ms
                && p.strike.is_none_or(|s| s.speed_ok);
        }
        self.final_state == TrialState::Done
            && self.limit_violations == 0
            && self.judgement.is_some_and(|j| {
                j.timing_error_ms <= tol.timing_tolerance_ms
                    && j.position_error_m <= tol.position_tolerance_m
            })
    }
}

/// No committed motion in the trial (nothing for the judge).
fn no_motion(o: &TrialOutcome) -> bool {
    o.judgement.is_none() && o.judge_error.is_none() && o.physical_error.is_none()
}

/// How the FRI link was lost, for an abort's detail.
const fn stop_detail(reason: StopReason) -> &'static str {
    match reason {
        StopReason::ControllerSilent => "the robot controller fell silent (no FRI message)",
        StopReason::SessionClosed => "the robot controller closed the FRI session (IDLE)",
        StopReason::LeftCommanding(s) => match s {
            SessionState::MonitoringWait => "the FRI session left commanding for MONITORING_WAIT",
            SessionState::MonitoringReady => "the FRI session left commanding for MONITORING_READY",
            _ => "the FRI session left commanding",
        },
    }
}

/// Why a trial that timed out had not committed to a motion: the filter's
/// doubt about its newest plan (empty without a plan, or when it was
/// confident: its start then came and went).
const fn doubt_detail(doubt: Option<crate::ekf::Doubt>) -> &'static str {
    use crate::ekf::Doubt;
    match doubt {
        None | Some(Doubt::None) => "",
        Some(Doubt::ShortObservation) => {
            "the filter had not followed the ball long enough to commit"
        }
        Some(Doubt::StaleMeasurement) => {
            "the camera's newest measurement was too old to commit on (frames late or missing)"
        }
        Some(Doubt::Rejecting) => "the camera's newest measurements were rejected as outliers",
        Some(Doubt::Uncertain) => {
            "the predicted pass time stayed too uncertain to commit (ekf.commit_max_time_std_ms)"
        }
    }
}

/// The session state a trial saw when it lost commanding without a stop event.
const fn session_detail(s: SessionState) -> &'static str {
    match s {
        SessionState::CommandingActive => "",
        SessionState::CommandingWait => "the FRI session was COMMANDING_WAIT, not commanding",
        SessionState::MonitoringReady => "the FRI session was MONITORING_READY, not commanding",
        SessionState::MonitoringWait => "the FRI session was MONITORING_WAIT, not commanding",
        SessionState::Idle => "the FRI session was closed (IDLE)",
    }
}

/// The pass in `passes` nearest to `t_s`.
fn nearest_pass(passes: &[(f64, Vector3<f64>)], t_s: f64) -> Option<(f64, Vector3<f64>)> {
    passes
        .iter()
        .min_by(|a, b| (a.0 - t_s).abs().total_cmp(&(b.0 - t_s).abs()))
        .copied()
}

/// Answers a planning or parameter request of the control thread (on
/// `isochron-lab-io` in real time, in line in virtual time); `None` for the
/// other requests.
/// The beliefs a trial plans on: the scenario's, with the trial's own
/// movement time and task (stop or strike, a strike's speed and direction)
/// where `setup` has them.
pub fn trial_beliefs(scenario: &Scenario, setup: &TrialSetup) -> crate::control::Beliefs {
    let mut b = scenario.beliefs();
    if let Some(mt) = setup.movement_time_s {
        b.task.movement_time_s = mt;
    }
    if let Some(m) = setup.mode {
        b.task.mode = m;
    }
    if let Some(v) = setup.strike_speed_mps {
        b.task.strike_speed_mps = v;
    }
    if let Some(d) = setup.strike_direction_deg {
        b.task.strike_direction_deg = d;
    }
    b
}

/// With the reply, the controller's error when the plan is refused (the reply
/// carries only the [`Refusal`]; the virtual lab records the error).
pub(crate) fn plan_or_params(
    scenario: &mut Scenario,
    req: IoRequest,
) -> Option<(IoReply, Option<ControlError>)> {
    let mut why = None;
    let reply = match req {
        IoRequest::Plan {
            ack,
            trial_id,
            auto_release,
            index,
            draw,
            setup,
        } => IoReply::Plan {
            ack,
            trial_id,
            auto_release,
            index,
            draw,
            // The controller plans on the beliefs only (never `[world]`),
            // with the trial's own movement time and task when it has them.
            plan: Controller::plan(&trial_beliefs(scenario, &setup), draw.distance_m).map_err(
                |e| {
                    why = Some(e);
                    crate::bridge::Refusal::Infeasible
                },
            ),
        },
        IoRequest::Params { ack, scenario: new } => {
            let period = f64::from(new.robot.fri_period_ms) * 1e-3;
            let same_period = new.robot.fri_period_ms == scenario.robot.fri_period_ms;
            let controller = new
                .validate_but_world()
                .map_err(ControlError::from)
                .and_then(|()| Controller::new(&new.beliefs(), period));
            match controller {
                Ok(c) if same_period => {
                    *scenario = (*new).clone();
                    IoReply::Params {
                        ack,
                        result: Ok((Box::new(c), new)),
                    }
                }
                _ => IoReply::Params {
                    ack,
                    result: Err(new),
                },
            }
        }
        IoRequest::Magnet(_) | IoRequest::Free(_) => return None,
    };
    Some((reply, why))
}

#[cfg(test)]
mod camera_basis_tests {
    use super::*;
    use nalgebra::Vector3;

    /// A real camera's swing plane follows the beliefs taken: before any
    /// step, the basis's camera and the rest the believed length below the
    /// pivot; after the camera-robot step (its pose and intercept offset),
    /// the pendulum step (its length) and the camera step (its lens), the
    /// plane reads a ball 10 cm out from the new rest as 10 cm, where the
    /// basis's plane is millimetres off.
    #[test]
    fn a_real_cameras_plane_follows_the_beliefs_taken() {
        let mut s = Scenario::default();
        let basis = CameraBasis {
            intrinsics: CameraIntrinsics::from_hfov(1280, 720, 70.0),
            pose: CameraPose {
                position_m: [-0.9, 0.0, 0.6],
                ..CameraPose::default()
            },
            pivot_m: [0.6, 0.0, 0.6 + s.pendulum.length_m],
        };
        let (k, pose, rest) = basis.believed(&s);
        assert_eq!((k, pose), (basis.intrinsics, basis.pose));
        assert!((rest - Vector3::new(0.6, 0.0, 0.6)).norm() < 1e-12);
        let before = basis.plane(&s);
        s.camera.pose = Some(CameraPose {
            position_m: [-0.91, 0.012, 0.615],
            yaw_deg: 0.4,
            pitch_deg: -0.3,
            roll_deg: 0.2,
        });
        s.camera.intrinsics = Some(CameraIntrinsics {
            k1: 0.01,
            ..CameraIntrinsics::from_hfov(1280, 720, 69.0)
        });
        s.task.intercept_offset_m = [0.0, 0.004, -0.003];
        s.pendulum.length_m += 0.02;
        let (k, pose, rest) = basis.believed(&s);
        assert_eq!(Some(k), s.camera.intrinsics);
        assert_eq!(Some(pose), s.camera.pose);
        assert!((rest - Vector3::new(0.6, 0.004, 0.6 - 0.02 - 0.003)).norm() < 1e-12);
        let after = basis.plane(&s);
        let ball = rest + Vector3::new(0.0, 0.1, 0.0);
        let px = k.project(&pose.to_camera(&ball)).unwrap();
        let lateral = after.lateral_m(px.x, px.y).unwrap();
        assert!((lateral - 0.1).abs() < 1e-5, "{lateral}");
        let stale = before.lateral_m(px.x, px.y).unwrap();
        assert!((stale - 0.1).abs() > 0.002, "{stale}");
    }
}
