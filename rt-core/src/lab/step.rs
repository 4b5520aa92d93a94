//! The lab's control step on the FRI session's thread: [`LabStep`] wraps the
//! closed loop's [`FriLoopStep`] and, around each call, polls the bridge
//! (stop, commands), folds in the camera measurements of the vision ring,
//! follows the magnet, keeps the ground truth and the judge's trace, reports
//! events and publishes the snapshot. Nothing here allocates, locks, logs or
//! blocks, except handling a command (planning a trial, new parameters),
//! which happens once per operator action.

use std::sync::{Arc, OnceLock};
use std::time::Instant;

use nalgebra::Vector3;
use rtrb::{Consumer, Producer};

use super::fri_step::FriLoopStep;
use super::trial::{TrialDraw, draw_trial};
use super::vision::TruthUpdate;
use crate::bridge::{
    self, AbortReason as BridgeAbort, Command, ControlEnd, Event, EventRecord, FriQuality,
    FriSessionState, HorizonPoint, MagnetState, Refusal, Snapshot, TrialResult,
};
use crate::control::{
    AbortReason, ArmPlan, Controller, Measurement, PlannedMotion, TrialRecord, TrialState,
    TrialTrace, judge,
};
use crate::ekf::Prediction;
use crate::fri::client::{ControlStep, SessionStats, StepInput, StopReason};
use crate::fri::codec::Joints;
use crate::fri::proto::{ConnectionQuality, SessionState};
use crate::magnet::{MagnetHandle, view};
use crate::params::Scenario;
use crate::pendulum::{PendulumGeometry, PendulumModel, PendulumSim};

use crate::trajectory::profile::ProfileKind;
use crate::vision::{CameraIntrinsics, CameraPose, SwingPlaneCalibration};

/// Time after `Done` still recorded for the judge, seconds.
const AFTER_DONE_S: f64 = 0.3;
/// Longest a trial may take, seconds.
pub(crate) const TRIAL_TIMEOUT_S: f64 = 40.0;
/// Spacing of the predicted horizon points, seconds.
const HORIZON_STEP_S: f64 = 0.08;
/// The predicted horizon is recomputed this often (the stream runs at 100 Hz).
const HORIZON_EVERY_S: f64 = 0.01;
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
        draw: TrialDraw,
    },
    /// Build a controller for new parameters (answered by [`IoReply::Params`]).
    Params { ack: u64, scenario: Box<Scenario> },
    /// Memory to free off the control thread.
    Free(Box<Controller>),
}

/// `isochron-lab-io`'s answers.
// The ring's slots are allocated once; boxing the plan would free memory on
// the control thread instead.
#[allow(clippy::large_enum_variant)]
pub(crate) enum IoReply {
    /// A trial's plan, or why there is none.
    Plan {
        ack: u64,
        trial_id: u64,
        auto_release: bool,
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
pub(crate) struct CameraModel {
    pub intrinsics: CameraIntrinsics,
    pub pose: CameraPose,
    pub ball_radius_m: f64,
}

/// The ground truth of the simulated lab, shared with the simulated camera.
pub(crate) struct Truth {
    pub to_camera: Producer<TruthUpdate>,
    pub calibrations: Producer<SwingPlaneCalibration>,
    pub camera: CameraModel,
}

struct Trial {
    id: u64,
    draw: TrialDraw,
    plan: ArmPlan,
    /// The true pendulum (simulated lab only).
    ball: Option<PendulumSim>,
    auto_release: bool,
    armed_at: Option<f64>,
    release_requested: bool,
    magnet_was_on: bool,
    released: bool,
    done_at: Option<f64>,
    t0: f64,
}

/// Everything the control thread owns besides the closed loop.
pub(crate) struct LabParts {
    pub scenario: Box<Scenario>,
    pub seed: u64,
    /// The pendulum's distance when it cannot move (the real lab); `None`:
    /// drawn per trial (the simulated lab).
    pub fixed_distance_m: Option<f64>,
    pub bridge: ControlEnd,
    pub epoch: Instant,
    pub measurements: Consumer<crate::vision::Measurement>,
    pub magnet_notes: Consumer<MagnetNote>,
    pub io_requests: Producer<IoRequest>,
    pub io_replies: Consumer<IoReply>,
    pub magnet: MagnetHandle,
    pub session: Arc<OnceLock<Arc<SessionStats>>>,
    pub truth: Option<Truth>,
    /// The camera's calibration at the start (the dashboard's overlays).
    pub calibration: SwingPlaneCalibration,
    /// The operator dead-man time, seconds (`None`: off).
    pub operator_timeout_s: Option<f64>,
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
    snap: Snapshot,
    horizon: Vec<Prediction>,
    next_horizon_s: f64,
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
    magnet_failures: u64,
    /// A command waiting for `isochron-lab-io` (its ack id; true: cancelled by a stop).
    pending: Option<(u64, bool)>,
    /// When the operator last commanded a trial (counts as a heartbeat), control clock, s.
    operator_since_s: f64,
}

impl std::fmt::Debug for LabStep {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LabStep")
            .field("t_s", &self.t_s)
            .field("trial_index", &self.trial_index)
            .finish_non_exhaustive()
    }
}

pub(crate) fn map_state(s: TrialState) -> bridge::TrialState {
    match s {
        TrialState::Idle => bridge::TrialState::Idle,
        TrialState::Arming => bridge::TrialState::Arming,
        TrialState::Armed => bridge::TrialState::Armed,
        TrialState::Released => bridge::TrialState::Released,
        TrialState::Tracking => bridge::TrialState::Tracking,
        TrialState::Intercepting => bridge::TrialState::Intercepting,
        TrialState::Holding => bridge::TrialState::Holding,
        TrialState::Done => bridge::TrialState::Done,
        TrialState::Abort(_) => bridge::TrialState::Aborted,
    }
}

fn map_abort(r: AbortReason) -> BridgeAbort {
    match r {
        AbortReason::StopRequested => BridgeAbort::Stop,
        AbortReason::Infeasible => BridgeAbort::Infeasible,
        AbortReason::IkFailed | AbortReason::GuardTripped => BridgeAbort::LimitViolation,
        AbortReason::CameraLost => BridgeAbort::CameraLost,
        AbortReason::FriLost => BridgeAbort::FriLost,
        AbortReason::PredictionTimeout | AbortReason::MissedWindow => BridgeAbort::Timeout,
        AbortReason::MagnetFault => BridgeAbort::MagnetFault,
        AbortReason::OperatorLost => BridgeAbort::OperatorLost,
        _ => BridgeAbort::Internal,
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
            snap,
            horizon: vec![Prediction::default(); bridge::HORIZON_POINTS],
            next_horizon_s: 0.0,
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
            magnet_failures: 0,
            pending: None,
            operator_since_s: f64::NEG_INFINITY,
        }
    }

    /// Steps whose computation took longer than the FRI period.
    pub fn deadline_misses(&self) -> u64 {
        self.inner.step.deadline_misses
    }

    /// The closed loop.
    pub fn inner(&self) -> &FriLoopStep {
        &self.inner
    }

    /// The latest snapshot.
    pub fn snapshot(&self) -> &Snapshot {
        &self.snap
    }

    fn controller(&mut self) -> &mut Controller {
        self.inner.controller_mut()
    }

    /// Before the closed loop's step: commands, magnet, measurements.
    fn before(&mut self, t: f64) {
        if self.p.bridge.take_stop_request() {
            self.controller().abort(t, AbortReason::StopRequested);
            if let Some(p) = self.pending.as_mut() {
                p.1 = true;
            }
        }
        while let Ok(reply) = self.p.io_replies.pop() {
            self.io_reply(t, reply);
        }
        while let Some(env) = self.p.bridge.next_command() {
            self.handle(t, env.id, env.command);
        }
        self.dead_man(t);
        self.follow_magnet();
        let mut n = 0u64;
        while let Ok(m) = self.p.measurements.pop() {
            self.snap.camera.set_frame(&m);
            if !m.found {
                continue;
            }
            let inbox = &mut self.inner.step.inbox;
            if inbox.len() < inbox.capacity() {
                inbox.push(Measurement {
                    t_capture_s: m.t_capture_s,
                    lateral_m: m.lateral_m,
                });
                n += 1;
            } else {
                self.snap.counters.measurement_overflows += 1;
            }
            self.snap.pendulum.measured = bridge::Measurement {
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
            TrialState::Idle | TrialState::Done | TrialState::Abort(_)
        ) {
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
        if let Some(v) = self.p.magnet.try_view() {
            self.snap.magnet = match (v.link, v.magnet) {
                (view::LinkState::Lost, _) => MagnetState::Fault,
                (_, view::MagnetState::On) => MagnetState::On,
                (_, view::MagnetState::Off) => MagnetState::Off,
                (_, view::MagnetState::Unknown) => MagnetState::Unknown,
            };
            if let Some(tr) = self.trial.as_mut()
                && v.magnet == view::MagnetState::On
            {
                tr.magnet_was_on = true;
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
            if let Some(ball) = tr.ball.as_mut() {
                let at = t.max(ball.time_s());
                if ball.release(at).is_ok()
                    && let Some(truth) = self.p.truth.as_mut()
                {
                    let _ = truth.to_camera.push(TruthUpdate::Ball(ball.clone()));
                }
            }
            let c = self.inner.controller_mut();
            if c.state() == TrialState::Armed {
                let _ = c.release(t);
            } else if !matches!(c.state(), TrialState::Abort(_) | TrialState::Done) {
                // Dropped before the arm was ready (e.g. the coil's hold limit).
                c.abort(t, AbortReason::MagnetFault);
            }
        }
    }

    fn request_magnet(&mut self, on: bool) -> bool {
        let ok = self.p.io_requests.push(IoRequest::Magnet(on)).is_ok();
        if !ok {
            self.magnet_failures += 1;
        }
        ok
    }

    fn handle(&mut self, t: f64, id: u64, command: Command) {
        let state = self.inner.controller().state();
        let busy = self.pending.is_some()
            || !matches!(
                state,
                TrialState::Idle | TrialState::Done | TrialState::Abort(_)
            );
        let (outcome, returned) = match command {
            Command::Stop => {
                self.controller().abort(t, AbortReason::StopRequested);
                if let Some(p) = self.pending.as_mut() {
                    p.1 = true;
                }
                (Ok(()), None)
            }
            Command::Arm | Command::RunTrial { .. } if busy => (Err(Refusal::Busy), None),
            Command::RunTrial { trial_id: 0 } => (Err(Refusal::Invalid), None),
            Command::Arm => {
                self.operator_since_s = t;
                return self.plan(id, 0, false);
            }
            Command::RunTrial { trial_id } => {
                self.operator_since_s = t;
                return self.plan(id, trial_id, true);
            }
            Command::Disarm => {
                if state == TrialState::Armed || state == TrialState::Arming {
                    self.controller().abort(t, AbortReason::StopRequested);
                    self.trial = None;
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
    fn plan(&mut self, ack: u64, trial_id: u64, auto_release: bool) {
        let mut draw = draw_trial(&self.p.scenario, self.p.seed, self.trial_index);
        if let Some(d) = self.p.fixed_distance_m {
            draw.distance_m = d;
        }
        let req = IoRequest::Plan {
            ack,
            trial_id,
            auto_release,
            draw,
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
                draw,
                plan,
            } => {
                let outcome = match plan {
                    _ if cancelled => Err(Refusal::ChecksFailed),
                    Ok(plan) => self.begin(t, trial_id, auto_release, draw, plan),
                    Err(r) => Err(r),
                };
                self.p.bridge.ack(ack, outcome, None);
            }
            IoReply::Params { ack, result } => match result {
                Ok((mut controller, mut scenario)) if !cancelled => {
                    std::mem::swap(self.controller(), &mut *controller);
                    std::mem::swap(&mut self.p.scenario, &mut scenario);
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
        id: u64,
        auto_release: bool,
        draw: TrialDraw,
        plan: ArmPlan,
    ) -> Result<(), Refusal> {
        let _ = self.controller().reset(t);
        // The trial starts now on the operator's command: the dead-man counts from here.
        self.operator_since_s = t;
        let ball = match &self.p.truth {
            Some(_) => {
                let s = &self.p.scenario;
                let model =
                    PendulumModel::from_params(&s.pendulum).map_err(|_| Refusal::Invalid)?;
                let geometry = PendulumGeometry::new(
                    s.pendulum.length_m,
                    draw.distance_m,
                    s.task.intercept_height_m,
                )
                .map_err(|_| Refusal::Invalid)?;
                Some(
                    PendulumSim::held_at(model, geometry, draw.release_angle_deg.to_radians(), t)
                        .map_err(|_| Refusal::Invalid)?,
                )
            }
            None => None,
        };
        if !self.request_magnet(true) {
            return Err(Refusal::DeviceUnavailable);
        }
        self.controller()
            .arm(t, &plan)
            .map_err(|_| Refusal::ChecksFailed)?;
        if let (Some(truth), Some(ball)) = (self.p.truth.as_mut(), ball.as_ref()) {
            let cam = truth.camera;
            let rest = Vector3::new(
                draw.distance_m,
                0.0,
                self.p.scenario.task.intercept_height_m,
            );
            let cal = SwingPlaneCalibration::from_pose(
                cam.intrinsics,
                &cam.pose,
                &rest,
                cam.ball_radius_m,
            );
            let size = &self.p.scenario.camera;
            self.snap
                .camera
                .set_calibration(&cal, size.width_px, size.height_px);
            let _ = truth.calibrations.push(cal);
            let _ = truth.to_camera.push(TruthUpdate::Ball(ball.clone()));
        }
        self.inner.clear_stop();
        self.trace.clear();
        self.snap.trial_id = id;
        self.trial = Some(Trial {
            id,
            draw,
            plan,
            ball,
            auto_release,
            armed_at: None,
            release_requested: false,
            magnet_was_on: false,
            released: false,
            done_at: None,
            t0: t,
        });
        Ok(())
    }

    /// After the closed loop's step: truth, trace, trial progress, events.
    fn follow_trial(&mut self, t: f64) {
        let state = self.inner.controller().state();
        if state != self.last_state {
            let trial_id = self.trial.as_ref().map_or(0, |tr| tr.id);
            self.p.bridge.emit(EventRecord {
                t_s: t,
                trial_id,
                event: Event::StateChanged {
                    from: map_state(self.last_state),
                    to: map_state(state),
                },
            });
            if let TrialState::Abort(r) = state {
                self.p.bridge.emit(EventRecord {
                    t_s: t,
                    trial_id,
                    event: Event::Aborted {
                        reason: map_abort(r),
                    },
                });
                self.snap.counters.trials += 1;
            }
            self.last_state = state;
        }
        let tool = self.inner.controller().tool_point(&self.q);
        let Some(trial) = self.trial.as_mut() else {
            return;
        };
        if let Some(ball) = trial.ball.as_mut() {
            if trial.released && t > ball.time_s() {
                let _ = ball.advance_to(t);
            }
            self.trace.push(t, tool, ball.ball_position_m());
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
                    self.finish(t);
                    return;
                }
            }
            TrialState::Abort(_) => {
                self.trial = None;
                self.snap.trial_id = 0;
                return;
            }
            _ => {
                if t - trial.t0 > TRIAL_TIMEOUT_S {
                    self.controller().abort(t, AbortReason::PredictionTimeout);
                }
            }
        }
        if want_release && self.request_magnet(false) {
            if let Some(tr) = self.trial.as_mut() {
                tr.release_requested = true;
            }
        }
    }

    /// Judges the finished trial on ground truth (simulated lab) and reports it.
    fn finish(&mut self, t: f64) {
        let Some(trial) = self.trial.take() else {
            return;
        };
        let c = self.inner.controller();
        let mut rec = TrialRecord {
            trial: self.trial_index,
            seed: self.p.seed,
            distance_m: trial.draw.distance_m,
            release_angle_deg: trial.draw.release_angle_deg,
            success: false,
            failure: None,
            final_state: "done".to_owned(),
            abort_reason: None,
            planned_movement_time_s: trial.plan.duration_s,
            judgement: None,
            physical: None,
            prediction_crossing_time_error_ms: None,
            prediction_position_error_m: None,
            latency_estimate_ms: c.latency().latency_s() * 1e3,
            limit_violations: c.counters().limit_violations(),
            deadline_misses: self.inner.step.deadline_misses,
            preempted_steps: self.inner.step.preempted_steps,
        };
        let mut result = TrialResult {
            success: false,
            timing_error_ms: f64::NAN,
            position_error_m: f64::NAN,
            movement_time_s: f64::NAN,
            distance_m: trial.draw.distance_m,
            t_star_s: f64::NAN,
            arrival_t_s: f64::NAN,
            prediction_time_error_ms: f64::NAN,
            limit_violations: rec.limit_violations,
        };
        if let (Some(commit), true) = (c.commit().copied(), trial.ball.is_some()) {
            let motion = PlannedMotion {
                start_m: c.home_m(),
                end_m: c.motion_target_m(),
                profile: ProfileKind::Hopf,
                duration_s: commit.duration_s,
                commanded_start_s: commit.motion_start_s,
            };
            if let Ok(j) = judge(&self.trace, &motion, &trial.plan.intercept_m) {
                result.timing_error_ms = j.timing_error_ms;
                result.position_error_m = j.position_error_m;
                result.movement_time_s = j.movement_time_s;
                result.t_star_s = j.t_star_s;
                result.arrival_t_s = j.arrival_s;
                result.prediction_time_error_ms = (commit.predicted_pass_s - j.t_star_s) * 1e3;
                rec.judgement = Some(j);
            }
        }
        rec.decide(&self.p.scenario.success);
        result.success = rec.success;
        self.snap.counters.trials += 1;
        self.p.bridge.emit(EventRecord {
            t_s: t,
            trial_id: trial.id,
            event: Event::TrialFinished { result },
        });
        let _ = self.controller().reset(t);
        self.snap.trial_id = 0;
    }

    fn fill_snapshot(&mut self, t: f64) {
        let c = self.inner.controller();
        let s = &mut self.snap;
        s.t_s = t;
        s.seq += 1;
        s.trial_state = map_state(c.state());
        // Pendulum: estimate and predicted horizon.
        let l = self.p.scenario.pendulum.length_m;
        match c.ekf().and_then(|e| e.posterior().map(|p| (e, p))) {
            Some((ekf, (_, x, p))) => {
                s.pendulum.phi_rad = x[0];
                s.pendulum.dphi_radps = x[1];
                s.pendulum.sigma_phi_rad = p[(0, 0)].max(0.0).sqrt();
                s.pendulum.sigma_dphi_radps = p[(1, 1)].max(0.0).sqrt();
                s.pendulum.x_m = l * x[0].sin();
                s.pendulum.sigma_x_m = l * x[0].cos().abs() * s.pendulum.sigma_phi_rad;
                if t >= self.next_horizon_s {
                    self.next_horizon_s = t + HORIZON_EVERY_S;
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
            }
            None => {
                s.pendulum.horizon.len = 0;
                s.pendulum.sigma_phi_rad = f64::NAN;
                s.pendulum.sigma_dphi_radps = f64::NAN;
                s.pendulum.sigma_x_m = f64::NAN;
                s.pendulum.ball_m = [f64::NAN; 3];
            }
        }
        s.pendulum.truth_ball_m =
            self.trial
                .as_ref()
                .and_then(|tr| tr.ball.as_ref())
                .map_or([f64::NAN; 3], |b| {
                    let b = b.ball_position_m();
                    [b.x, b.y, b.z]
                });
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
        match c.commit() {
            Some(cm) => {
                s.path.start_t_s = cm.motion_start_s;
                s.path.arrival_t_s = cm.motion_start_s + cm.duration_s;
                s.path.movement_time_s = cm.duration_s;
                s.path.progress_planned = ((t - cm.motion_start_s) / cm.duration_s).clamp(0.0, 1.0);
                s.pendulum.crossing_t_s = cm.predicted_pass_s;
                s.pendulum.crossing_sigma_s = cm.predicted_pass_std_s;
            }
            None => {
                s.path.start_t_s = f64::NAN;
                s.path.arrival_t_s = f64::NAN;
                s.path.movement_time_s = self.p.scenario.task.movement_time_s;
                s.path.progress_planned = 0.0;
            }
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
        // The control clock is the lab's (shared with the camera): the
        // session's receive time moved by the offset between the two clocks,
        // taken at the first message (error: the receive -> step delay, us).
        let lab_ns = started.saturating_duration_since(self.p.epoch).as_nanos() as i64;
        let off = *self
            .offset_ns
            .get_or_insert(lab_ns - input.now_ns.min(i64::MAX as u64) as i64);
        let now_ns = (input.now_ns as i64).saturating_add(off).max(0) as u64;
        let t = now_ns as f64 * 1e-9;
        self.t_s = t;
        let m = input.monitoring;
        self.session = m.session_state;
        self.quality = m.quality;
        if let Some(q) = m.measured_joint_position_rad {
            self.q = q;
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
        self.follow_trial(t);
        self.fill_snapshot(t);
        let us = started.elapsed().as_secs_f64() * 1e6;
        self.step_max_us = self.step_max_us.max(us);
        self.snap.timing.step_us = us;
        self.snap.timing.step_max_us = self.step_max_us;
        self.p.bridge.publish(&self.snap);
    }

    fn stop(&mut self, reason: StopReason) {
        self.inner.stop(reason);
        if !matches!(reason, StopReason::LeftCommanding(_)) {
            self.session = SessionState::Idle;
            self.snap.fri.session = FriSessionState::Disconnected;
            self.snap.fri.quality = FriQuality::Unknown;
            // Publish the lost link (this runs on the control thread too).
            self.p.bridge.publish_latest(&self.snap);
        }
    }
}
