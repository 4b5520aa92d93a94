//! The simulated lab behind `isochron serve`: the closed loop of `rt_core`
//! (control step, FRI codec, simulated robot, camera model, ground-truth
//! pendulum, judging) driven in real time on a named thread
//! (`isochron-control`), one control step per FRI period, talking to the
//! server only through the bridge.
//!
//! Trials follow `rt_core::sim::VirtualLab::run_trial` (same draws, same
//! judging), paced by the wall clock so the dashboard sees them live.

use std::{
    sync::{
        Arc,
        atomic::{AtomicBool, Ordering},
    },
    thread::JoinHandle,
    time::{Duration, Instant},
};

use nalgebra::Vector3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rt_core::{
    bridge::{
        self, AbortReason as BridgeAbort, Command, ControlEnd, Event, EventRecord, FriQuality,
        FriSessionState, HorizonPoint, MagnetState, Refusal, Snapshot, TrialResult,
    },
    control::{
        AbortReason, ArmPlan, Controller, PlannedMotion, TrialRecord, TrialState, TrialTrace, judge,
    },
    ekf::Prediction,
    fri::{
        ConnectionQuality, SessionState,
        codec::{CommandEncoder, MonitoringDecoder},
    },
    params::Scenario,
    pendulum::{PendulumGeometry, PendulumModel, PendulumSim},
    sim::{
        LoopStep, TrialDraw, camera::ModelCamera, draw_trial, lab::INITIAL_JOINTS_DEG,
        robot::VirtualRobot,
    },
    trajectory::profile::ProfileKind,
};

/// Time after `Done` still recorded for the judge, seconds.
const AFTER_DONE_S: f64 = 0.3;
/// Longest a trial may take, seconds.
const TRIAL_TIMEOUT_S: f64 = 40.0;
/// Spacing of the predicted horizon points, seconds.
const HORIZON_STEP_S: f64 = 0.08;

/// The running simulated lab; dropping it stops the control thread.
#[derive(Debug)]
pub struct SimLab {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl Drop for SimLab {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl SimLab {
    /// Starts the control thread for `scenario` on the control end of a bridge.
    pub fn start(scenario: Scenario, control: ControlEnd, seed: u64) -> anyhow::Result<Self> {
        let mut rt = Runtime::new(scenario, control, seed)?;
        let stop = Arc::new(AtomicBool::new(false));
        let s = Arc::clone(&stop);
        let thread = std::thread::Builder::new()
            .name("isochron-control".into())
            .spawn(move || rt.run(&s))?;
        Ok(Self {
            stop,
            thread: Some(thread),
        })
    }
}

struct Trial {
    id: u64,
    draw: TrialDraw,
    plan: ArmPlan,
    ball: PendulumSim,
    camera: ModelCamera,
    rng: ChaCha8Rng,
    auto_release: bool,
    armed_at: Option<f64>,
    released: bool,
    done_at: Option<f64>,
    t0: f64,
}

struct Runtime {
    scenario: Scenario,
    control: ControlEnd,
    robot: VirtualRobot,
    dec: MonitoringDecoder,
    enc: CommandEncoder,
    cmd_seq: u32,
    step: LoopStep,
    period_ns: u64,
    t_ns: u64,
    seed: u64,
    trial_index: usize,
    trial: Option<Trial>,
    trace: TrialTrace,
    snap: Snapshot,
    horizon: Vec<Prediction>,
    last_state: TrialState,
    session: SessionState,
    quality: ConnectionQuality,
    prev_tool: Option<Vector3<f64>>,
    step_max_us: f64,
}

fn map_state(s: TrialState) -> bridge::TrialState {
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
        _ => BridgeAbort::Internal,
    }
}

impl Runtime {
    fn new(scenario: Scenario, control: ControlEnd, seed: u64) -> anyhow::Result<Self> {
        let period_s = f64::from(scenario.robot.fri_period_ms) * 1e-3;
        let controller = Controller::new(&scenario, period_s)?;
        let q0 = INITIAL_JOINTS_DEG.map(f64::to_radians);
        Ok(Self {
            robot: VirtualRobot::new(&scenario.robot, q0, seed),
            period_ns: u64::from(scenario.robot.fri_period_ms) * 1_000_000,
            scenario,
            control,
            dec: MonitoringDecoder::new(),
            enc: CommandEncoder::new(),
            cmd_seq: 0,
            step: LoopStep::new(controller),
            t_ns: 0,
            seed,
            trial_index: 0,
            trial: None,
            trace: TrialTrace::with_capacity(20_000),
            snap: Snapshot::default(),
            horizon: vec![Prediction::default(); bridge::HORIZON_POINTS],
            last_state: TrialState::Idle,
            session: SessionState::Idle,
            quality: ConnectionQuality::Poor,
            prev_tool: None,
            step_max_us: 0.0,
        })
    }

    fn t_s(&self) -> f64 {
        self.t_ns as f64 * 1e-9
    }

    fn run(&mut self, stop: &AtomicBool) {
        let period = Duration::from_nanos(self.period_ns);
        let mut next = Instant::now();
        let mut last = next;
        let mut period_max_us: f64 = 0.0;
        let mut period_sum_us = 0.0;
        let mut periods = 0u32;
        while !stop.load(Ordering::Acquire) {
            let now = Instant::now();
            let dt_us = (now - last).as_secs_f64() * 1e6;
            last = now;
            period_max_us = period_max_us.max(dt_us);
            period_sum_us += dt_us;
            periods += 1;
            if periods >= 200 {
                self.snap.timing.period_mean_us = period_sum_us / f64::from(periods);
                self.snap.timing.period_max_us = period_max_us;
                (period_max_us, period_sum_us, periods) = (0.0, 0.0, 0);
            }
            let started = Instant::now();
            self.cycle();
            let us = started.elapsed().as_secs_f64() * 1e6;
            self.step_max_us = self.step_max_us.max(us);
            self.snap.timing.step_us = us;
            self.snap.timing.step_max_us = self.step_max_us;
            self.control.publish(&self.snap);
            next += period;
            let now = Instant::now();
            if next > now {
                std::thread::sleep(next - now);
            } else {
                next = now;
            }
        }
    }

    /// One FRI period: commands, the simulated world, the control step, the snapshot.
    fn cycle(&mut self) {
        let t = self.t_s();
        if self.control.take_stop_request() {
            self.step.controller.abort(t, AbortReason::StopRequested);
        }
        while let Some(env) = self.control.next_command() {
            self.handle(env.id, env.command);
        }
        let t_next = (self.t_ns + self.period_ns) as f64 * 1e-9;
        if let Some(trial) = self.trial.as_mut() {
            while trial.camera.next_capture_s() <= t_next {
                let tc = trial.camera.next_capture_s();
                let _ = trial.ball.advance_to(tc.max(trial.ball.time_s()));
                trial.camera.capture(trial.ball.lateral_m(), &mut trial.rng);
            }
            let _ = trial.ball.advance_to(t_next);
            trial.camera.deliver(t_next, &mut self.step.inbox);
        }
        if let Some(m) = self.step.inbox.last() {
            self.snap.pendulum.measured = bridge::Measurement {
                valid: true,
                t_s: m.t_capture_s,
                x_m: m.lateral_m,
            };
            self.snap.counters.measurements += self.step.inbox.len() as u64;
        }
        self.tick();
        self.follow_trial();
        self.fill_snapshot();
    }

    fn tick(&mut self) {
        self.t_ns += self.period_ns;
        let now = self.t_ns;
        let Some(bytes) = self.robot.tick(now) else {
            return;
        };
        let Ok(m) = self.dec.decode(bytes) else {
            return;
        };
        self.session = m.session_state;
        self.quality = m.quality;
        let q = self
            .step
            .run(now as f64 * 1e-9, self.period_ns as f64 * 1e-9, &m);
        let seq = self.cmd_seq;
        self.cmd_seq = self.cmd_seq.wrapping_add(1);
        if let Ok(reply) = self.enc.encode(seq, m.sequence_counter, Some(&q)) {
            self.robot.on_reply(reply, now + 20_000);
        }
    }

    fn handle(&mut self, id: u64, command: Command) {
        let state = self.step.controller.state();
        let busy = !matches!(
            state,
            TrialState::Idle | TrialState::Done | TrialState::Abort(_)
        );
        let t = self.t_s();
        let (outcome, returned) = match command {
            Command::Stop => {
                self.step.controller.abort(t, AbortReason::StopRequested);
                (Ok(()), None)
            }
            Command::Arm | Command::RunTrial { .. } if busy => (Err(Refusal::Busy), None),
            Command::RunTrial { trial_id: 0 } => (Err(Refusal::Invalid), None),
            Command::Arm => (self.begin(0, false), None),
            Command::RunTrial { trial_id } => (self.begin(trial_id, true), None),
            Command::Disarm => {
                if state == TrialState::Armed || state == TrialState::Arming {
                    self.step.controller.abort(t, AbortReason::StopRequested);
                    self.trial = None;
                    let _ = self.step.controller.reset(t);
                    (Ok(()), None)
                } else {
                    (Err(Refusal::NotArmed), None)
                }
            }
            Command::Magnet { on: true } => (Ok(()), None),
            Command::Magnet { on: false } => match self.trial.as_mut() {
                Some(tr) if !tr.released && state == TrialState::Armed => {
                    let ok = tr.ball.release(t).is_ok() && self.step.controller.release(t).is_ok();
                    tr.released = ok;
                    (
                        if ok {
                            Ok(())
                        } else {
                            Err(Refusal::ChecksFailed)
                        },
                        None,
                    )
                }
                // Held while the arm is still moving home: not yet.
                Some(tr) if !tr.released => (Err(Refusal::NotArmed), None),
                // Nothing held: switching off is harmless.
                _ => (Ok(()), None),
            },
            Command::SetParams(p) if busy => (Err(Refusal::Busy), Some(p)),
            Command::SetParams(p) => {
                let period_s = f64::from(p.robot.fri_period_ms) * 1e-3;
                match Controller::new(&p, period_s) {
                    Ok(c) if p.robot.fri_period_ms == self.scenario.robot.fri_period_ms => {
                        self.step.controller = c;
                        let old = std::mem::replace(&mut self.scenario, *p);
                        (Ok(()), Some(Box::new(old)))
                    }
                    _ => (Err(Refusal::Invalid), Some(p)),
                }
            }
        };
        self.control.ack(id, outcome, returned);
    }

    /// Starts arming for a trial (`auto_release`: released after the drawn wait).
    fn begin(&mut self, id: u64, auto_release: bool) -> Result<(), Refusal> {
        let t = self.t_s();
        let _ = self.step.controller.reset(t);
        let draw = draw_trial(&self.scenario, self.seed, self.trial_index);
        self.trial_index += 1;
        let plan =
            Controller::plan(&self.scenario, draw.distance_m).map_err(|_| Refusal::Infeasible)?;
        let model =
            PendulumModel::from_params(&self.scenario.pendulum).map_err(|_| Refusal::Invalid)?;
        let geometry = PendulumGeometry::new(
            self.scenario.pendulum.length_m,
            draw.distance_m,
            self.scenario.task.intercept_height_m,
        )
        .map_err(|_| Refusal::Invalid)?;
        let ball = PendulumSim::held_at(model, geometry, draw.release_angle_deg.to_radians(), t)
            .map_err(|_| Refusal::Invalid)?;
        self.step
            .controller
            .arm(t, &plan)
            .map_err(|_| Refusal::ChecksFailed)?;
        self.trace.clear();
        self.snap.trial_id = id;
        self.trial = Some(Trial {
            id,
            draw,
            plan,
            ball,
            camera: ModelCamera::new(&self.scenario.camera, t + draw.camera_phase_s),
            rng: ChaCha8Rng::seed_from_u64(draw.seed),
            auto_release,
            armed_at: None,
            released: false,
            done_at: None,
            t0: t,
        });
        Ok(())
    }

    fn follow_trial(&mut self) {
        let t = self.t_s();
        let state = self.step.controller.state();
        if state != self.last_state {
            let trial_id = self.trial.as_ref().map_or(0, |tr| tr.id);
            self.control.emit(EventRecord {
                t_s: t,
                trial_id,
                event: Event::StateChanged {
                    from: map_state(self.last_state),
                    to: map_state(state),
                },
            });
            if let TrialState::Abort(r) = state {
                self.control.emit(EventRecord {
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
        let Some(trial) = self.trial.as_mut() else {
            return;
        };
        let q = *self.robot.joints();
        let tool = self.step.controller.tool_point(&q);
        self.trace.push(t, tool, trial.ball.ball_position_m());
        match state {
            TrialState::Armed => {
                let since = *trial.armed_at.get_or_insert(t);
                if trial.auto_release && !trial.released && t - since >= trial.draw.release_wait_s {
                    let ok =
                        trial.ball.release(t).is_ok() && self.step.controller.release(t).is_ok();
                    trial.released = ok;
                }
            }
            TrialState::Done => {
                let since = *trial.done_at.get_or_insert(t);
                if t - since >= AFTER_DONE_S {
                    self.finish();
                }
            }
            TrialState::Abort(_) => {
                self.trial = None;
                self.snap.trial_id = 0;
            }
            _ => {
                if t - trial.t0 > TRIAL_TIMEOUT_S {
                    self.step
                        .controller
                        .abort(t, AbortReason::PredictionTimeout);
                }
            }
        }
    }

    /// Judges the finished trial (as `VirtualLab::run_trial`) and reports it.
    fn finish(&mut self) {
        let Some(trial) = self.trial.take() else {
            return;
        };
        let t = self.t_s();
        let mut rec = TrialRecord {
            trial: self.trial_index,
            seed: self.seed,
            distance_m: trial.draw.distance_m,
            release_angle_deg: trial.draw.release_angle_deg,
            success: false,
            failure: None,
            final_state: "done".to_owned(),
            abort_reason: None,
            planned_movement_time_s: trial.plan.duration_s,
            judgement: None,
            prediction_crossing_time_error_ms: None,
            prediction_position_error_m: None,
            latency_estimate_ms: self.step.controller.latency().latency_s() * 1e3,
            limit_violations: self.step.controller.counters().limit_violations(),
            deadline_misses: self.step.deadline_misses,
            preempted_steps: self.step.preempted_steps,
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
        if let Some(commit) = self.step.controller.commit().copied() {
            let motion = PlannedMotion {
                start_m: self.step.controller.home_m(),
                end_m: self.step.controller.motion_target_m(),
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
        rec.decide(&self.scenario.success);
        result.success = rec.success;
        self.snap.counters.trials += 1;
        self.control.emit(EventRecord {
            t_s: t,
            trial_id: trial.id,
            event: Event::TrialFinished { result },
        });
        let _ = self.step.controller.reset(t);
        self.snap.trial_id = 0;
    }

    fn fill_snapshot(&mut self) {
        let t = self.t_s();
        let c = &self.step.controller;
        let s = &mut self.snap;
        s.t_s = t;
        s.seq += 1;
        s.trial_state = map_state(c.state());
        // Pendulum: estimate and predicted horizon.
        let l = self.scenario.pendulum.length_m;
        s.pendulum.horizon.len = 0;
        s.pendulum.crossing_t_s = f64::NAN;
        s.pendulum.crossing_sigma_s = f64::NAN;
        match c.ekf().and_then(|e| e.posterior().map(|p| (e, p))) {
            Some((ekf, (_, x, p))) => {
                s.pendulum.phi_rad = x[0];
                s.pendulum.dphi_radps = x[1];
                s.pendulum.sigma_phi_rad = p[(0, 0)].max(0.0).sqrt();
                s.pendulum.sigma_dphi_radps = p[(1, 1)].max(0.0).sqrt();
                s.pendulum.x_m = l * x[0].sin();
                s.pendulum.sigma_x_m = l * x[0].cos().abs() * s.pendulum.sigma_phi_rad;
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
            None => {
                s.pendulum.sigma_phi_rad = f64::NAN;
                s.pendulum.sigma_dphi_radps = f64::NAN;
                s.pendulum.sigma_x_m = f64::NAN;
                s.pendulum.ball_m = [f64::NAN; 3];
            }
        }
        s.pendulum.truth_ball_m = self.trial.as_ref().map_or([f64::NAN; 3], |tr| {
            let b = tr.ball.ball_position_m();
            [b.x, b.y, b.z]
        });
        // Motion: the timing system and the path.
        let ms = c.motion_sample();
        let moving = matches!(c.state(), TrialState::Intercepting);
        s.hopf.active = moving;
        s.hopf.u_init = ms.neurons.u_init;
        s.hopf.u_hopf = ms.neurons.u_hopf;
        s.hopf.u_final = ms.neurons.u_final;
        s.hopf.a = ms.a;
        s.hopf.b = ms.b;
        s.path.speed_planned_mps = ms.planned_path_speed_mps;
        let q = *self.robot.joints();
        let tool = c.tool_point(&q);
        let dt = self.period_ns as f64 * 1e-9;
        s.path.speed_executed_mps = self.prev_tool.map_or(0.0, |p| (tool - p).norm() / dt);
        self.prev_tool = Some(tool);
        let home = c.home_m();
        let target = c.motion_target_m();
        let len = (target - home).norm();
        s.path.length_m = len;
        s.path.intercept_m = [target.x, target.y, target.z];
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
                s.path.movement_time_s = self.scenario.task.movement_time_s;
                s.path.progress_planned = 0.0;
            }
        }
        s.path.progress_executed = if len > 1e-9 {
            ((tool - home).dot(&(target - home)) / (len * len)).clamp(0.0, 1.0)
        } else {
            0.0
        };
        // Arm and link.
        s.robot.q_rad = q;
        s.robot.q_cmd_rad = self.step.out.q_command_rad;
        s.robot.tool_m = [tool.x, tool.y, tool.z];
        s.robot.actuation_latency_ms = c.latency().latency_s() * 1e3;
        s.fri.session = match self.session {
            SessionState::Idle => FriSessionState::Idle,
            SessionState::MonitoringWait => FriSessionState::MonitoringWait,
            SessionState::MonitoringReady => FriSessionState::MonitoringReady,
            SessionState::CommandingWait => FriSessionState::CommandingWait,
            SessionState::CommandingActive => FriSessionState::CommandingActive,
        };
        s.fri.quality = match self.quality {
            ConnectionQuality::Poor => FriQuality::Poor,
            ConnectionQuality::Fair => FriQuality::Fair,
            ConnectionQuality::Good => FriQuality::Good,
            ConnectionQuality::Excellent => FriQuality::Excellent,
        };
        s.fri.period_ms = f64::from(self.scenario.robot.fri_period_ms);
        s.magnet = match self.trial.as_ref() {
            Some(tr) if !tr.released => MagnetState::On,
            _ => MagnetState::Off,
        };
        let k = c.counters();
        s.counters.steps = k.steps;
        s.counters.guard_interventions = k.guard_position_clamps + k.guard_step_clamps;
        s.counters.limit_violations = k.limit_violations() + self.robot.violations;
        s.timing.deadline_misses = self.step.deadline_misses;
    }
}

/// Starts the simulated lab and the server side of its bridge: what
/// `isochron serve` runs without a config. Keep the [`SimLab`] alive as long as
/// the [`crate::Lab`]; drop it after [`crate::Lab::shutdown`].
pub fn start_simulated(
    scenario: Scenario,
    records: Option<Arc<crate::Records>>,
    options: crate::LabOptions,
    seed: u64,
) -> anyhow::Result<(Arc<crate::Lab>, SimLab)> {
    let (control, end) = bridge::bridge(bridge::BridgeCapacity::default());
    let sim = SimLab::start(scenario.clone(), control, seed)?;
    let lab = crate::Lab::start(end, None, scenario, records, options)?;
    Ok((lab, sim))
}
