//! The virtual-time runtime: one thread, deterministic for a seed, faster than
//! real time. Every FRI message goes through the simulated controller's codec
//! and the real client ([`FriClient`]); every camera frame through the camera
//! model; the controller's step is the same one the real-time runtime runs.

use nalgebra::Vector3;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::camera::ModelCamera;
use super::camera::{BallState, SimCamera, SimCameraParams, SimVision};
use super::magnet::{Switch, VirtualMagnet};
use super::world::{
    Disc, LatencyModel, TruePendulum, World, WorldCamera, WorldJoints, WorldSample, judge_physical,
};
use crate::control::judge::{PlannedMotion, TrialTrace, judge};
use crate::control::{ControlError, Controller, Measurement, TrialRecord, TrialState};
use crate::fri::client::{FriClient, FriClientParams, LinkState};
use crate::fri::proto::SessionState;
use crate::kinematics::iiwa7::JOINTS;
use crate::lab::{FriLoopStep, LoopStep, TrialDraw, draw_trial};
use crate::params::Scenario;
use crate::params::VisionMode;
use crate::pendulum::{PendulumGeometry, PendulumModel, PendulumSim};
use crate::sim::kuka::controller::WorldRobot;
use crate::sim::kuka::{FriSimParams, SimController};
use crate::trajectory::profile::ProfileKind;
use crate::vision::{CameraIntrinsics, DetectorParams, SwingPlaneCalibration};

/// Errors setting up the lab.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum LabError {
    /// The controller refused its parameters.
    #[error(transparent)]
    Control(#[from] ControlError),
    /// The simulated robot refused its parameters or its session.
    #[error("simulated robot: {0}")]
    Robot(String),
}

/// The virtual-time lab: one simulated KUKA controller ([`SimController`]),
/// one FRI client session ([`FriClient`]) and one closed-loop controller
/// ([`FriLoopStep`]) across trials (so the latency estimate carries over, as
/// it does in the lab).
#[derive(Debug)]
pub struct VirtualLab {
    scenario: Scenario,
    robot: SimController,
    client: FriClient,
    step: FriLoopStep,
    period_ns: u64,
    t_ns: u64,
    seed: u64,
    trace: TrialTrace,
    /// The true ball's passes through the intercept point's `y` in the
    /// current trial: exact time (root of the ground-truth pendulum) and the
    /// ball centre then.
    passes: Vec<(f64, Vector3<f64>)>,
    /// The true ball centre at the committed prediction's pass time (exact:
    /// the ground-truth pendulum taken there), per predicted time seen.
    at_predicted: Vec<(f64, Vector3<f64>)>,
    vision: Option<SimVision>,
    magnet: VirtualMagnet,
    last_release: Option<Switch>,
    in_flight: std::collections::VecDeque<(f64, Measurement)>,
    /// The reality lab (`[world]`): the true world sampled once per period
    /// for the physical judge, and the session the simulated robot is in.
    world_trace: Vec<WorldSample>,
    world_session: Option<u64>,
    /// When `Some`, every byte the controller reads (FRI messages, then the
    /// measurements handed to it) is appended (tests: the controller cannot
    /// read the world).
    pub input_log: Option<Vec<u8>>,
}

/// Joint angles of the simulated robot at power-on, degrees.
pub const INITIAL_JOINTS_DEG: [f64; JOINTS] = [0.0, 30.0, 0.0, -80.0, 0.0, 60.0, 0.0];
/// Monitoring datagram sent -> command datagram back at the controller, in
/// virtual time (a loopback round trip), nanoseconds.
pub const LOOPBACK_NS: u64 = 20_000;
/// Unix time of the lab's time 0 (message timestamps; fixed for determinism), ns.
const EPOCH_UNIX_NS: u64 = 1_700_000_000_000_000_000;
/// Mixed into a trial's seed for the magnet's own random stream.
const MAGNET_STREAM: u64 = 0x6d61_676e_6574;
/// Mixed into a trial's world seed for the true camera's own random stream.
const CAMERA_STREAM: u64 = 0x6361_6d65_7261;
/// Longest wait for the session to reach COMMANDING_ACTIVE, seconds.
const COMMANDING_TIMEOUT_S: f64 = 5.0;

/// The simulated KUKA controller of `scenario`'s lab: its `[robot]` section
/// (FRI period, command-to-motion latency and jitter) over
/// [`FriSimParams`]'s defaults (5 ms servo lag), the joints at
/// [`INITIAL_JOINTS_DEG`], its random draws seeded with `seed`. The jitter is
/// capped at the latency (a command never takes effect before it arrives).
pub fn robot_params(scenario: &Scenario, seed: u64) -> FriSimParams {
    let mut p = FriSimParams::from_robot(&scenario.robot);
    p.latency_jitter_ms = p.latency_jitter_ms.min(p.latency_ms);
    p.initial_joint_position_deg = INITIAL_JOINTS_DEG;
    p.seed = seed;
    p
}
/// Longest a trial may take in virtual time, seconds.
const TRIAL_TIMEOUT_S: f64 = 40.0;
/// Time after `Done` still recorded (for the judge), seconds.
const AFTER_DONE_S: f64 = 0.3;

impl VirtualLab {
    /// A lab for `scenario`, its simulated robot seeded from `seed`
    /// ([`robot_params`]).
    pub fn new(scenario: &Scenario, seed: u64) -> Result<Self, LabError> {
        Self::with_robot(scenario, seed, robot_params(scenario, seed))
    }

    /// A lab for `scenario` whose simulated KUKA controller has `robot`
    /// (e.g. [`robot_params`] with injected faults). Brings the FRI session up
    /// to COMMANDING_ACTIVE.
    pub fn with_robot(
        scenario: &Scenario,
        seed: u64,
        robot: FriSimParams,
    ) -> Result<Self, LabError> {
        let period_ms = robot.fri_period_ms * robot.receive_multiplier;
        let period_s = f64::from(period_ms) * 1e-3;
        // The controller is built from the beliefs only: it never holds `[world]`.
        let controller = Controller::new(&scenario.beliefs(), period_s)?;
        let robot_period_ns = robot.period_ns();
        let robot =
            SimController::new(robot, EPOCH_UNIX_NS).map_err(|e| LabError::Robot(e.to_string()))?;
        let client = FriClient::new(FriClientParams::default())
            .map_err(|e| LabError::Robot(e.to_string()))?;
        // Full vision: frames rendered and run through the OpenCV detector.
        let vision = if scenario.camera.vision == VisionMode::Full {
            let cam = SimCamera::new(
                &scenario.camera,
                &SimCameraParams::default(),
                scenario.pendulum.ball_radius_m,
                seed,
            )
            .map_err(|e| LabError::Robot(format!("camera: {e}")))?;
            let rest = nalgebra::Vector3::new(
                scenario.task.distance_m.lo,
                0.0,
                scenario.task.intercept_height_m,
            );
            let cal = cam.true_calibration(&rest);
            Some(
                SimVision::new(cam, DetectorParams::default(), cal)
                    .map_err(|e| LabError::Robot(format!("vision: {e}")))?,
            )
        } else {
            None
        };
        let mut lab = Self {
            scenario: scenario.clone(),
            robot,
            client,
            step: FriLoopStep::new(controller),
            period_ns: robot_period_ns,
            t_ns: 0,
            seed,
            trace: TrialTrace::with_capacity(20_000),
            passes: Vec::with_capacity(16),
            at_predicted: Vec::with_capacity(16),
            vision,
            magnet: VirtualMagnet::new(0.0),
            last_release: None,
            in_flight: std::collections::VecDeque::with_capacity(64),
            world_trace: Vec::new(),
            world_session: None,
            input_log: None,
        };
        lab.ensure_commanding()?;
        Ok(lab)
    }

    /// Runs the session until the client is in COMMANDING_ACTIVE (asking the
    /// controller for commanding first, as the robot program does).
    fn ensure_commanding(&mut self) -> Result<(), LabError> {
        let max = (COMMANDING_TIMEOUT_S * 1e9 / self.period_ns as f64).ceil() as usize;
        for _ in 0..max {
            if self.client.state() == LinkState::CommandingActive
                && self.robot.state() == SessionState::CommandingActive
            {
                return Ok(());
            }
            if self.robot.state() != SessionState::CommandingActive {
                self.robot.request_commanding();
            }
            self.tick();
        }
        Err(LabError::Robot(format!(
            "the FRI session did not reach COMMANDING_ACTIVE within {COMMANDING_TIMEOUT_S} s \
             (controller {}, quality {})",
            self.robot.state().name(),
            self.robot.quality().name()
        )))
    }

    /// The last trial's release: decided, command written, coil switched off.
    pub fn last_release(&self) -> Option<Switch> {
        self.last_release
    }

    /// The simulated KUKA controller (for inspection).
    pub fn robot(&self) -> &SimController {
        &self.robot
    }

    /// The FRI client session (for inspection).
    pub fn client(&self) -> &FriClient {
        &self.client
    }

    /// The controller (for inspection).
    pub fn controller(&self) -> &Controller {
        self.step.controller()
    }

    /// How this lab produces camera measurements: `"full"` (rendered frames
    /// through the OpenCV detector) or `"model"` (the measurement model).
    pub fn vision_used(&self) -> &'static str {
        if self.vision.is_some() {
            "full"
        } else {
            "model"
        }
    }

    /// The loop adapter (step timing, deadline misses).
    pub fn loop_step(&mut self) -> &mut LoopStep {
        &mut self.step.step
    }

    /// The virtual time, seconds.
    pub fn t_s(&self) -> f64 {
        self.t_ns as f64 * 1e-9
    }

    /// One controller send period: the simulated controller's monitoring
    /// datagram goes to the FRI client, which runs the control step and
    /// returns the command datagram; that reaches the controller a loopback
    /// round trip later. A silent controller is noticed by the client's poll.
    fn tick(&mut self) {
        self.t_ns += self.period_ns;
        let now = self.t_ns;
        self.client.poll(now, &mut self.step);
        let Some(bytes) = self.robot.tick(now) else {
            return;
        };
        if let Some(log) = self.input_log.as_mut() {
            // What the controller reads: the FRI message and the measurements.
            log.extend_from_slice(bytes);
            for m in &self.step.step.inbox {
                log.extend_from_slice(format!("{m:?}").as_bytes());
            }
        }
        if let Some(reply) = self.client.on_datagram(bytes, now, &mut self.step) {
            self.robot.on_reply(reply, now + LOOPBACK_NS);
        }
    }

    /// Runs trial `index` of the run and judges it.
    pub fn run_trial(&mut self, index: usize) -> TrialRecord {
        let draw = draw_trial(&self.scenario, self.seed, index);
        let mut rec = TrialRecord {
            trial: index,
            seed: self.seed,
            distance_m: draw.distance_m,
            release_angle_deg: draw.release_angle_deg,
            success: false,
            failure: None,
            final_state: "idle".to_owned(),
            abort_reason: None,
            planned_movement_time_s: self.scenario.task.movement_time_s,
            judgement: None,
            physical: None,
            prediction_crossing_time_error_ms: None,
            prediction_position_error_m: None,
            latency_estimate_ms: self.step.step.controller.latency().latency_s() * 1e3,
            limit_violations: 0,
            deadline_misses: 0,
            preempted_steps: 0,
        };
        let plan = match Controller::plan(&self.scenario.beliefs(), draw.distance_m) {
            Ok(p) => p,
            Err(e) => {
                rec.failure = Some(e.to_string());
                rec.decide(&self.scenario.success);
                return rec;
            }
        };
        rec.planned_movement_time_s = plan.duration_s;
        // The reality lab: this trial's true world (None: a truthful world).
        let world = World::for_trial(&self.scenario, self.seed, index, &plan.intercept_m);
        if let Some(w) = &world {
            self.enter_session(w);
        }
        // A controller abort in an earlier trial left the session out of
        // commanding: the robot program starts the overlay again.
        if let Err(e) = self.ensure_commanding() {
            rec.failure = Some(e.to_string());
            rec.decide(&self.scenario.success);
            return rec;
        }
        self.step.clear_stop();
        let before = *self.step.step.controller.counters();
        let fri_before = self.fri_counts();
        let misses_before = self.step.step.deadline_misses;
        let preempted_before = self.step.step.preempted_steps;
        let outcome = match &world {
            Some(w) => self.simulate_world(&draw, &plan, w),
            None => self.simulate(&draw, &plan),
        };
        let c = self.step.controller().counters();
        let fri = self.fri_counts();
        rec.limit_violations = c.limit_violations() - before.limit_violations()
            + (fri.violations - fri_before.violations);
        rec.deadline_misses = self.step.step.deadline_misses - misses_before;
        rec.preempted_steps = self.step.step.preempted_steps - preempted_before;
        let state = self.step.controller().state();
        rec.final_state = state.name().to_owned();
        if let TrialState::Abort(r) = state {
            let mut why = r.name().to_owned();
            if let Some(stop) = self.step.last_stop() {
                why.push_str(&format!(": {stop}"));
            }
            if fri.aborts > fri_before.aborts
                && let Some(a) = self.robot.stats().last_abort()
            {
                why.push_str(&format!(" (the robot controller aborted commanding: {a})"));
            }
            rec.abort_reason = Some(why);
        }
        if let Err(msg) = outcome {
            rec.failure = Some(msg);
        }
        if let Some(commit) = self.step.step.controller.commit().copied() {
            rec.latency_estimate_ms = commit.latency_s * 1e3;
            let motion = PlannedMotion {
                start_m: self.step.step.controller.home_m(),
                end_m: self.step.step.controller.motion_target_m(),
                profile: ProfileKind::Hopf,
                duration_s: commit.duration_s,
                commanded_start_s: commit.motion_start_s,
            };
            let intercept = world.as_ref().map_or(plan.intercept_m, |w| w.intercept_m);
            match judge(&self.trace, &motion, &intercept) {
                Ok(j) => rec.judgement = Some(j),
                Err(e) => {
                    if rec.failure.is_none() {
                        rec.failure = Some(format!("not judged: {e}"));
                    }
                }
            }
            // The prediction at commit against the truth: its pass time
            // against the true pass t* nearest to it (a root of the true
            // pendulum), its ball centre against the true ball centre at the
            // predicted time exactly (as the filter's own tests measure it; at
            // t* itself both are the intercept point by definition).
            if let Some((tp, _)) = nearest_pass(&self.passes, commit.predicted_pass_s) {
                rec.prediction_crossing_time_error_ms = Some((commit.predicted_pass_s - tp) * 1e3);
            }
            if let Some(&(_, truth)) = self
                .at_predicted
                .iter()
                .find(|(t, _)| *t == commit.predicted_pass_s)
            {
                rec.prediction_position_error_m = Some((commit.predicted_ball_m - truth).norm());
            }
        }
        if let (Some(w), Some(commit)) = (&world, self.step.step.controller.commit().copied()) {
            self.judge_world(w, commit.predicted_pass_s, &mut rec);
        }
        let t = self.t_s();
        let _ = self.step.step.controller.reset(t);
        rec.decide(&self.scenario.success);
        rec
    }

    /// Enters the session of `world` when the simulated robot is not in it yet
    /// (a "reboot": a new latency, servos and inertias).
    fn enter_session(&mut self, world: &World) {
        if self.world_session == Some(world.session.session) {
            return;
        }
        self.world_session = Some(world.session.session);
        let Some(w) = self.scenario.world.as_ref() else {
            return;
        };
        let r = &w.robot;
        let mut joints = WorldJoints::new(
            *self.robot.joint_rad(),
            &world.session,
            self.robot.params().servo_time_constant_ms * 1e-3,
            r.torque_limit_scale,
            r.torque_trip,
            r.position_noise_rad,
            self.seed ^ world.session.session.wrapping_mul(0x9E37_79B9_7F4A_7C15),
        );
        joints.set_interpolation_s(self.period_ns as f64 * 1e-9);
        self.robot.set_world(Some(WorldRobot {
            latency: LatencyModel::from_session(&world.session, self.t_s()),
            joints,
        }));
    }

    /// The physical judge on the true world: fills `rec.physical` and puts
    /// its figures (t*, arrival, |timing error|, tool-ball distance at t*)
    /// into the reported judgement; the fitted movement time stays.
    fn judge_world(&self, world: &World, committed_pass_s: f64, rec: &mut TrialRecord) {
        let passes: Vec<f64> = self.passes.iter().map(|p| p.0).collect();
        match judge_physical(
            &self.world_trace,
            &passes,
            committed_pass_s,
            world.pendulum.ball_radius_m,
            self.scenario.success.timing_tolerance_ms,
        ) {
            Ok(p) => {
                let at = self
                    .world_trace
                    .iter()
                    .min_by(|a, b| {
                        (a.t_s - p.t_star_s)
                            .abs()
                            .total_cmp(&(b.t_s - p.t_star_s).abs())
                    })
                    .map_or(f64::NAN, |s| (s.disc.centre_m - s.ball_m).norm());
                if let Some(j) = rec.judgement.as_mut() {
                    j.t_star_s = p.t_star_s;
                    j.arrival_s = p.arrival_s;
                    j.timing_error_ms = p.timing_error_ms.abs();
                    j.position_error_m = at;
                }
                rec.physical = Some(p);
            }
            Err(e) => {
                if rec.failure.is_none() {
                    rec.failure = Some(format!("not judged: {e}"));
                }
            }
        }
    }

    /// [`simulate`](Self::simulate) in the reality lab: the true pendulum,
    /// the true camera and the true geometry of `world` (the simulated robot
    /// already carries the session's robot, [`enter_session`](Self::enter_session)).
    /// The controller sees only what it saw before: measurements and FRI
    /// messages.
    fn simulate_world(
        &mut self,
        draw: &TrialDraw,
        plan: &crate::control::ArmPlan,
        world: &World,
    ) -> Result<(), String> {
        self.trace.clear();
        self.passes.clear();
        self.at_predicted.clear();
        self.world_trace.clear();
        self.last_release = None;
        let t0 = self.t_s();
        let mut ball = TruePendulum::held_at(
            world.pendulum,
            draw.release_angle_deg.to_radians(),
            world.trial.out_of_plane_rad,
            t0,
            world.trial.seed,
        );
        // The same ball without the tool in its way: t* (when the ball would
        // pass the intercept point) and contact are judged on it; the real
        // ball stops against the tool.
        let mut ghost = ball.clone();
        let mut ghost_drop: Option<f64> = None;
        let mut rng = ChaCha8Rng::seed_from_u64(draw.seed);
        let mut cam_rng = ChaCha8Rng::seed_from_u64(world.trial.seed ^ CAMERA_STREAM);
        let cam = self.scenario.camera.clone();
        let sim_cam = SimCameraParams::default();
        let intrinsics = CameraIntrinsics::from_hfov(cam.width_px, cam.height_px, sim_cam.hfov_deg);
        let wcam = WorldCamera::from_session(
            sim_cam.pose,
            intrinsics,
            cam.height_px,
            cam.latency_ms * 1e-3,
            &world.session,
        );
        // What the lab believes: the believed camera, the believed rest point.
        let believed = SwingPlaneCalibration::from_pose(
            intrinsics,
            &sim_cam.pose,
            &plan.intercept_m,
            self.scenario.pendulum.ball_radius_m,
        );
        let period = 1.0 / cam.fps;
        let mut next_frame = t0 + draw.camera_phase_s;
        if let Some(v) = self.vision.as_mut() {
            v.set_calibration(believed);
            v.reset(draw.seed);
        }
        self.in_flight.clear();
        self.step
            .controller_mut()
            .arm(t0, plan)
            .map_err(|e| e.to_string())?;
        let mut magnet_rng = ChaCha8Rng::seed_from_u64(draw.seed ^ MAGNET_STREAM);
        self.magnet.switch(t0, true, &mut magnet_rng)?;
        let mut release: Option<(f64, f64)> = None;
        let mut drop_at: Option<f64> = None;
        let mut told = false;
        let mut armed_at: Option<f64> = None;
        let mut done_at: Option<f64> = None;
        let mut last_disc: Option<Disc> = None;
        let true_y = world.intercept_m.y;
        loop {
            let t_next = (self.t_ns + self.period_ns) as f64 * 1e-9;
            if let Some(tp) = ghost.next_crossing_s(true_y, t_next - ghost.time_s()) {
                let mut at = ghost.clone();
                at.advance_to(tp);
                self.passes.push((tp, at.ball_position_m()));
            }
            if let Some(c) = self.step.controller().commit()
                && c.predicted_pass_s >= ghost.time_s()
                && c.predicted_pass_s < t_next
                && !ghost.is_held()
            {
                let mut at = ghost.clone();
                at.advance_to(c.predicted_pass_s);
                self.at_predicted
                    .push((c.predicted_pass_s, at.ball_position_m()));
            }
            // Frames whose exposure starts before the next message.
            while next_frame <= t_next {
                let tc = next_frame;
                next_frame += period;
                advance_true_ball(&mut ball, &mut drop_at, tc);
                let timing = wcam.timing(tc, &mut cam_rng);
                let dropped = cam.drop_rate > 0.0 && cam_rng.random_bool(cam.drop_rate.min(1.0));
                let Some(sight) = wcam.sight(tc, |t| {
                    let mut b = ball.clone();
                    b.advance_to(t);
                    b.ball_position_m()
                }) else {
                    continue;
                };
                if let Some(v) = self.vision.as_mut() {
                    // The renderer draws, through the believed camera, the
                    // point the true camera sees.
                    let state = BallState {
                        centre_m: wcam.equivalent_centre_m(&sight.px, &ball.ball_position_m()),
                        velocity_mps: ball.ball_velocity_mps(),
                    };
                    match v.capture(tc, Some(&state)) {
                        Ok(Some(m)) if m.found => self.in_flight.push_back((
                            timing.t_delivered_s,
                            Measurement {
                                t_capture_s: timing.t_stamp_s,
                                lateral_m: m.lateral_m,
                            },
                        )),
                        Ok(_) => {}
                        Err(e) => return Err(format!("vision: {e}")),
                    }
                } else if !dropped && let Some(lat) = believed.lateral_m(sight.px.x, sight.px.y) {
                    let z = lat
                        + super::camera::model::MODEL_NOISE_M * super::camera::gaussian(&mut rng);
                    self.in_flight.push_back((
                        timing.t_delivered_s,
                        Measurement {
                            t_capture_s: timing.t_stamp_s,
                            lateral_m: z,
                        },
                    ));
                }
            }
            advance_true_ball(&mut ball, &mut drop_at, t_next);
            advance_true_ball(&mut ghost, &mut ghost_drop, t_next);
            // Delivered in order of delivery (jitter may reorder frames).
            self.in_flight
                .make_contiguous()
                .sort_by(|a, b| a.0.total_cmp(&b.0));
            while let Some(&(avail, m)) = self.in_flight.front() {
                if avail > t_next {
                    break;
                }
                self.step.step.inbox.push(m);
                self.in_flight.pop_front();
            }
            self.tick();
            let t = self.t_s();
            let q = *self.robot.joint_rad();
            let tool = self.step.step.controller.tool_point(&q);
            // The true tool (world kinematics); the ball stops against its disc.
            let disc = world.arm.disc(&q);
            let v_disc = last_disc.map_or(Vector3::zeros(), |d| {
                (disc.centre_m - d.centre_m) / (self.period_ns as f64 * 1e-9)
            });
            last_disc = Some(disc);
            ball.collide(&disc, &v_disc, 0.0);
            self.trace.push(t, tool, ball.ball_position_m());
            self.world_trace.push(WorldSample {
                t_s: t,
                ball_m: ghost.ball_position_m(),
                disc,
            });
            let state = self.step.step.controller.state();
            match state {
                TrialState::Armed => {
                    let since = *armed_at.get_or_insert(t);
                    if release.is_none() && t - since >= draw.release_wait_s {
                        let sw = self.magnet.switch(t, false, &mut magnet_rng)?;
                        self.last_release = Some(sw);
                        release = Some((t, sw.t_pin_s));
                        // Residual magnetism holds the ball a little longer.
                        drop_at = Some(sw.t_pin_s + world.trial.release_delay_s);
                        ghost_drop = drop_at;
                    }
                    if let Some((_, pin)) = release
                        && !told
                        && t >= pin
                    {
                        self.step
                            .controller_mut()
                            .release(pin)
                            .map_err(|e| e.to_string())?;
                        told = true;
                    }
                }
                TrialState::Done => {
                    let since = *done_at.get_or_insert(t);
                    if t - since >= AFTER_DONE_S {
                        return Ok(());
                    }
                }
                TrialState::Abort(_) => return Ok(()),
                _ => {}
            }
            if t - t0 > TRIAL_TIMEOUT_S {
                return Err(format!("timeout in state {}", state.name()));
            }
        }
    }

    /// The FRI side's limit violations (commands the client's guard had to
    /// change, commands the simulated controller refused with an abort) and the
    /// controller's commanding aborts of any kind.
    fn fri_counts(&self) -> FriCounts {
        use std::sync::atomic::Ordering::Relaxed;
        let c = self.client.stats();
        let r = self.robot.stats();
        FriCounts {
            violations: c.guard_position.load(Relaxed)
                + c.guard_step.load(Relaxed)
                + c.guard_non_finite.load(Relaxed)
                + r.violations.load(Relaxed),
            aborts: r.aborts.load(Relaxed),
        }
    }

    fn simulate(&mut self, draw: &TrialDraw, plan: &crate::control::ArmPlan) -> Result<(), String> {
        self.trace.clear();
        self.passes.clear();
        self.at_predicted.clear();
        self.last_release = None;
        let model =
            PendulumModel::from_params(&self.scenario.pendulum).map_err(|e| e.to_string())?;
        let geometry = PendulumGeometry::new(
            self.scenario.pendulum.length_m,
            draw.distance_m,
            self.scenario.task.intercept_height_m,
        )
        .map_err(|e| e.to_string())?;
        let t0 = self.t_s();
        let mut ball =
            PendulumSim::held_at(model, geometry, draw.release_angle_deg.to_radians(), t0)
                .map_err(|e| e.to_string())?;
        let mut rng = ChaCha8Rng::seed_from_u64(draw.seed);
        let mut camera = ModelCamera::new(&self.scenario.camera, t0 + draw.camera_phase_s);
        if let Some(v) = self.vision.as_mut() {
            let cal = v.camera().true_calibration(&geometry.rest_position_m());
            v.set_calibration(cal);
            v.reset(draw.seed);
        }
        self.in_flight.clear();
        self.step
            .controller_mut()
            .arm(t0, plan)
            .map_err(|e| e.to_string())?;
        // The magnet holds the ball; its commands go over the simulated serial
        // line to the firmware model (delays drawn from their own stream, so
        // the camera's draws do not depend on them).
        let mut magnet_rng = ChaCha8Rng::seed_from_u64(draw.seed ^ MAGNET_STREAM);
        self.magnet.switch(t0, true, &mut magnet_rng)?;
        // Decided to release at .0, the coil's pin switches at .1 (the ball
        // drops then); the controller is told once a step has passed it.
        let mut release: Option<(f64, f64)> = None;
        let mut drop_at: Option<f64> = None;
        let mut told = false;
        let mut armed_at: Option<f64> = None;
        let mut done_at: Option<f64> = None;
        loop {
            let t_next = (self.t_ns + self.period_ns) as f64 * 1e-9;
            // A true pass before the next message: found on a copy of the
            // pendulum, which is then taken there to read the ball centre.
            if let Some(tp) = ball.next_crossing_s(plan.intercept_m.y, t_next - ball.time_s()) {
                let mut at = ball.clone();
                at.advance_to(tp).map_err(|e| e.to_string())?;
                self.passes.push((tp, at.ball_position_m()));
            }
            // The committed prediction's pass time before the next message.
            if let Some(c) = self.step.controller().commit()
                && c.predicted_pass_s >= ball.time_s()
                && c.predicted_pass_s < t_next
                && !ball.is_held()
            {
                let mut at = ball.clone();
                at.advance_to(c.predicted_pass_s)
                    .map_err(|e| e.to_string())?;
                self.at_predicted
                    .push((c.predicted_pass_s, at.ball_position_m()));
            }
            // Camera frames captured up to the next message.
            while camera.next_capture_s() <= t_next {
                let tc = camera.next_capture_s();
                advance_ball(&mut ball, &mut drop_at, tc)?;
                if let Some(v) = self.vision.as_mut() {
                    camera.skip();
                    let state = BallState {
                        centre_m: ball.ball_position_m(),
                        velocity_mps: ball.ball_velocity_mps(),
                    };
                    match v.capture(tc, Some(&state)) {
                        Ok(Some(m)) if m.found => self.in_flight.push_back((
                            m.t_available_s,
                            Measurement {
                                t_capture_s: m.t_capture_s,
                                lateral_m: m.lateral_m,
                            },
                        )),
                        Ok(_) => {}
                        Err(e) => return Err(format!("vision: {e}")),
                    }
                } else {
                    camera.capture(ball.lateral_m(), &mut rng);
                }
            }
            advance_ball(&mut ball, &mut drop_at, t_next)?;
            camera.deliver(t_next, &mut self.step.step.inbox);
            while let Some(&(avail, m)) = self.in_flight.front() {
                if avail > t_next {
                    break;
                }
                self.step.step.inbox.push(m);
                self.in_flight.pop_front();
            }
            self.tick();
            let t = self.t_s();
            let q = *self.robot.joint_rad();
            let tool = self.step.step.controller.tool_point(&q);
            self.trace.push(t, tool, ball.ball_position_m());
            let state = self.step.step.controller.state();
            match state {
                TrialState::Armed => {
                    let since = *armed_at.get_or_insert(t);
                    if release.is_none() && t - since >= draw.release_wait_s {
                        let sw = self.magnet.switch(t, false, &mut magnet_rng)?;
                        self.last_release = Some(sw);
                        release = Some((t, sw.t_pin_s));
                        drop_at = Some(sw.t_pin_s);
                    }
                    if let Some((_, pin)) = release
                        && !told
                        && t >= pin
                    {
                        // The driver's release hook: the pin time.
                        self.step
                            .controller_mut()
                            .release(pin)
                            .map_err(|e| e.to_string())?;
                        told = true;
                    }
                }
                TrialState::Done => {
                    let since = *done_at.get_or_insert(t);
                    if t - since >= AFTER_DONE_S {
                        return Ok(());
                    }
                }
                TrialState::Abort(_) => return Ok(()),
                _ => {}
            }
            if t - t0 > TRIAL_TIMEOUT_S {
                return Err(format!("timeout in state {}", state.name()));
            }
        }
    }
}

/// Advances the true pendulum to `t_s`, dropping the ball at `drop_at` on
/// the way (the coil's pin time).
fn advance_ball(ball: &mut PendulumSim, drop_at: &mut Option<f64>, t_s: f64) -> Result<(), String> {
    if let Some(tr) = *drop_at
        && tr <= t_s
    {
        ball.release(tr.max(ball.time_s()))
            .map_err(|e| e.to_string())?;
        *drop_at = None;
    }
    ball.advance_to(t_s.max(ball.time_s()))
        .map_err(|e| e.to_string())
}

/// Advances the true pendulum to `t_s`, dropping the ball at `drop_at`.
fn advance_true_ball(ball: &mut TruePendulum, drop_at: &mut Option<f64>, t_s: f64) {
    if let Some(tr) = *drop_at
        && tr <= t_s
    {
        ball.release(tr.max(ball.time_s()));
        *drop_at = None;
    }
    ball.advance_to(t_s);
}

#[derive(Debug, Clone, Copy)]
struct FriCounts {
    violations: u64,
    aborts: u64,
}

/// The pass in `passes` nearest to `t_s`.
fn nearest_pass(passes: &[(f64, Vector3<f64>)], t_s: f64) -> Option<(f64, Vector3<f64>)> {
    passes
        .iter()
        .min_by(|a, b| (a.0 - t_s).abs().total_cmp(&(b.0 - t_s).abs()))
        .copied()
}

/// Tool point helper for tests: where the tool is for joint vector `q`.
pub fn tool_point(controller: &Controller, q: &[f64; JOINTS]) -> Vector3<f64> {
    controller.tool_point(q)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::Ordering::Relaxed;

    fn model_lab() -> Scenario {
        let mut s = Scenario::default();
        s.camera.vision = VisionMode::Model;
        s
    }

    #[test]
    fn trials_run_through_the_fri_session_and_the_simulated_controller() {
        let s = model_lab();
        let mut lab = VirtualLab::new(&s, 3).unwrap();
        assert_eq!(lab.client().state(), LinkState::CommandingActive);
        let applied_before = lab.robot().stats().commands_applied.load(Relaxed);
        let r = lab.run_trial(0);
        assert!(r.success, "{r:?}");
        let sim = lab.robot().stats().report();
        let cli = lab.client().stats().snapshot();
        // Every command the controller moved with came through the client.
        assert!(sim.commands_applied > applied_before + 300, "{sim:?}");
        assert_eq!(sim.commands_accepted, cli.commands);
        assert_eq!(sim.violations + sim.aborts, 0, "{sim:?}");
        assert_eq!(sim.client_sequence_errors, 0, "{sim:?}");
        assert_eq!(cli.late_replies + cli.missed_cycles + cli.silences, 0);
        assert_eq!(sim.quality, "EXCELLENT");
        // The latency estimate sees the robot's latency plus its servo lag.
        assert!(r.latency_estimate_ms > 8.0, "{r:?}");
    }

    #[test]
    fn the_ball_drops_when_the_magnets_pin_switches() {
        let s = model_lab();
        let mut lab = VirtualLab::new(&s, 9).unwrap();
        let mut pins = Vec::new();
        for i in 0..3 {
            let r = lab.run_trial(i);
            assert!(r.success, "{r:?}");
            let sw = lab.last_release().unwrap();
            // 11 bytes at 115200 baud after the host's wake-up delay.
            let line_s = 11.0 * 10.0 / 115_200.0;
            assert!(
                sw.latency_s() >= line_s
                    && sw.latency_s() < line_s + super::super::magnet::HOST_WRITE_DELAY_MAX_S,
                "{sw:?}"
            );
            // Until the pin time the ball hangs still; after it, it swings.
            let i_pin = lab.trace.t_s.partition_point(|&t| t < sw.t_pin_s);
            let still = lab.trace.ball_m[i_pin - 1];
            assert_eq!(lab.trace.ball_m[0], still);
            assert_ne!(lab.trace.ball_m[i_pin + 2], still);
            pins.push(sw.t_pin_s);
        }
        // The same seed, the same releases.
        let mut again = VirtualLab::new(&s, 9).unwrap();
        for (i, pin) in pins.iter().enumerate() {
            again.run_trial(i);
            assert_eq!(again.last_release().unwrap().t_pin_s, *pin);
        }
    }

    #[test]
    fn the_prediction_is_compared_with_the_truth_at_exact_times() {
        let s = model_lab();
        let mut lab = VirtualLab::new(&s, 5).unwrap();
        for i in 0..4 {
            let r = lab.run_trial(i);
            assert!(r.success, "{r:?}");
            // At the predicted time exactly, the filter's place error is its
            // pass-time error times the ball's speed (<= 3 m/s): about a millimetre (a
            // trace sample up to one period after t* would add up to
            // 1.5 m/s * 5 ms of ball travel).
            let e = r.prediction_position_error_m.unwrap();
            let dt = r.prediction_crossing_time_error_ms.unwrap();
            assert!(dt.abs() < 2.0, "trial {i}: {dt} ms");
            assert!(e < 0.003, "trial {i}: {e} m");
            assert!(
                e <= (dt.abs() * 1e-3 * 3.0).max(1e-4),
                "trial {i}: {e} m, {dt} ms"
            );
            // t* is a root of the true pendulum: the ball is then at the
            // intercept point's y.
            let (tp, p) = lab.passes[0];
            assert!(tp > 0.0 && p.y.abs() < 1e-9, "{tp} {p}");
        }
    }

    #[test]
    fn a_controller_abort_ends_the_trial_as_an_abort_and_counts_a_violation() {
        let s = model_lab();
        // A controller that trips at half the joints' speed limits: the
        // interception motion is faster than that.
        let mut robot = robot_params(&s, 1);
        robot.velocity_tolerance = 0.5;
        let mut lab = VirtualLab::with_robot(&s, 1, robot).unwrap();
        let r = lab.run_trial(0);
        assert!(!r.success);
        assert_eq!(r.final_state, "abort");
        let why = r.abort_reason.as_deref().unwrap();
        assert!(why.starts_with("fri_lost"), "{why}");
        assert!(why.contains("left commanding"), "{why}");
        assert!(why.contains("velocity limit"), "{why}");
        assert!(r.limit_violations >= 1, "{r:?}");
        assert!(r.failure.as_deref().unwrap().contains("abort"), "{r:?}");
        // The next trial brings the session back to commanding first.
        let r2 = lab.run_trial(1);
        assert_ne!(r2.final_state, "idle", "{r2:?}");
        assert!(lab.robot().stats().commanding_entered.load(Relaxed) >= 2);
    }

    #[test]
    fn the_controller_cannot_read_the_world() {
        // Two labs that differ only in `[world]` (the pendulum's true length
        // and the camera's true latency): the controller's inputs are
        // byte-identical until the first measurement, and the outcomes differ.
        let run = |world: &str| {
            let mut s =
                Scenario::from_toml_str(&format!("[camera]\nvision = \"model\"\n{world}")).unwrap();
            s.name = "x".into();
            let mut lab = VirtualLab::new(&s, 4).unwrap();
            lab.input_log = Some(Vec::new());
            let r = lab.run_trial(0);
            (lab.input_log.take().unwrap(), r)
        };
        let (a, ra) = run("[world.pendulum]\nlength_error_m = 0.0\n");
        let (b, rb) =
            run("[world.pendulum]\nlength_error_m = 0.02\n[world.camera]\nlatency_ms = 12.0\n");
        let first = |log: &[u8]| {
            let key = b"Measurement";
            log.windows(key.len()).position(|w| w == key).unwrap()
        };
        let (fa, fb) = (first(&a), first(&b));
        assert!(fa > 1000, "{fa}");
        let n = fa.min(fb);
        assert_eq!(
            a[..n],
            b[..n],
            "the inputs differ before the first measurement"
        );
        assert_ne!(a, b);
        let (pa, pb) = (ra.physical.unwrap(), rb.physical.unwrap());
        assert_ne!(pa.t_star_s, pb.t_star_s);
        assert_ne!(pa.timing_error_ms, pb.timing_error_ms);
    }

    #[test]
    fn a_bad_robot_is_refused_with_the_field() {
        let s = model_lab();
        let mut robot = robot_params(&s, 1);
        robot.latency_ms = 500.0;
        let e = VirtualLab::with_robot(&s, 1, robot).unwrap_err();
        assert!(e.to_string().contains("fri_sim.latency_ms"), "{e}");
    }
}
