//! A minimal closed loop around the [`Controller`] for benches and the
//! allocation test: the true pendulum ([`PendulumSim`]), the measurement-model
//! camera ([`ModelCamera`]: lateral position with noise, the scenario's rate,
//! drops and latency) and a robot that executes each command after the
//! scenario's latency in whole FRI periods. The control step is called on its
//! own ([`Rig::step_controller`]) between [`Rig::prepare`] and [`Rig::finish`],
//! so a caller can measure exactly the step (its time or its allocations) and
//! clone the rig in any phase of a trial.
//!
//! Not the simulated lab (`sim::VirtualLab` adds the FRI codec and session,
//! full vision, the servo model and judging); not real-time code itself.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::control::{
    ArmPlan, ControlError, Controller, Measurement, StepInput, StepOutput, TrialState,
};
use crate::kinematics::iiwa7::JOINTS;
use crate::params::Scenario;
use crate::pendulum::{PendulumGeometry, PendulumModel, PendulumSim};
use crate::sim::camera::ModelCamera;

/// Longest robot delay the rig models, FRI periods.
const MAX_DELAY: usize = 256;
/// Joint angles of the rig's robot at power-on, degrees (as the simulated lab's).
const INITIAL_JOINTS_DEG: [f64; JOINTS] = [0.0, 30.0, 0.0, -80.0, 0.0, 60.0, 0.0];
/// Wait between `Armed` and the release, seconds.
const RELEASE_WAIT_S: f64 = 0.3;

/// The minimal closed loop (see the module documentation).
#[derive(Debug, Clone)]
pub struct Rig {
    controller: Controller,
    scenario: Scenario,
    plan: ArmPlan,
    ball: PendulumSim,
    camera: ModelCamera,
    rng: ChaCha8Rng,
    inbox: Vec<Measurement>,
    input: StepInput,
    out: StepOutput,
    sent: [[f64; JOINTS]; MAX_DELAY],
    head: usize,
    delay: usize,
    period_s: f64,
    cycle: u64,
    armed_at: Option<f64>,
    release_angle_rad: f64,
    trials: u64,
}

fn setup(e: impl std::fmt::Display) -> ControlError {
    ControlError::Setup(e.to_string())
}

impl Rig {
    /// A rig for `scenario` whose first trial meets the ball at `distance_m`,
    /// released from `release_angle_deg`; random draws from `seed`. The
    /// controller has seen the robot and is arming.
    pub fn new(
        scenario: &Scenario,
        distance_m: f64,
        release_angle_deg: f64,
        seed: u64,
    ) -> Result<Self, ControlError> {
        let period_s = f64::from(scenario.robot.fri_period_ms) * 1e-3;
        let controller = Controller::new(scenario, period_s)?;
        let plan = Controller::plan(scenario, distance_m)?;
        let model = PendulumModel::from_params(&scenario.pendulum)?;
        let geometry = PendulumGeometry::new(
            scenario.pendulum.length_m,
            distance_m,
            scenario.task.intercept_height_m,
        )?;
        let angle = release_angle_deg.to_radians();
        let ball = PendulumSim::held_at(model, geometry, angle, 0.0).map_err(setup)?;
        // Whole periods of the robot's latency (at least one: the command of
        // this cycle is executed in a later one).
        let delay = ((scenario.robot.latency_ms * 1e-3 / period_s).round() as usize)
            .clamp(1, MAX_DELAY - 1);
        let q0 = INITIAL_JOINTS_DEG.map(f64::to_radians);
        let mut rig = Self {
            controller,
            scenario: scenario.clone(),
            plan,
            ball,
            camera: ModelCamera::new(&scenario.camera, 0.0),
            rng: ChaCha8Rng::seed_from_u64(seed),
            inbox: Vec::with_capacity(64),
            input: StepInput {
                t_s: 0.0,
                q_measured_rad: q0,
                commanding: true,
            },
            out: StepOutput::default(),
            sent: [q0; MAX_DELAY],
            head: 0,
            delay,
            period_s,
            cycle: 0,
            armed_at: None,
            release_angle_rad: angle,
            trials: 0,
        };
        rig.cycle();
        rig.controller.arm(rig.t_s(), &rig.plan)?;
        Ok(rig)
    }

    /// The controller.
    pub fn controller(&self) -> &Controller {
        &self.controller
    }

    /// The trial state.
    pub fn state(&self) -> TrialState {
        self.controller.state()
    }

    /// Time of the last prepared cycle, seconds.
    pub fn t_s(&self) -> f64 {
        self.input.t_s
    }

    /// Trials finished (done or aborted; each is followed by the next one).
    pub fn trials(&self) -> u64 {
        self.trials
    }

    /// Camera measurements waiting for the next step.
    pub fn pending_measurements(&self) -> usize {
        self.inbox.len()
    }

    /// Prepares the next cycle: advances the ball and the camera to its time,
    /// delivers the measurements that arrived, and reads the robot's joints.
    pub fn prepare(&mut self) {
        self.cycle += 1;
        let t = self.cycle as f64 * self.period_s;
        while self.camera.next_capture_s() <= t {
            let tc = self.camera.next_capture_s();
            let _ = self.ball.advance_to(tc.max(self.ball.time_s()));
            self.camera.capture(self.ball.lateral_m(), &mut self.rng);
        }
        let _ = self.ball.advance_to(t);
        self.camera.deliver(t, &mut self.inbox);
        let k = (self.head + MAX_DELAY - self.delay) % MAX_DELAY;
        self.input = StepInput {
            t_s: t,
            q_measured_rad: self.sent[k],
            commanding: true,
        };
    }

    /// The control step of the prepared cycle (exactly [`Controller::step`]).
    pub fn step_controller(&mut self) {
        self.controller
            .step(&self.input, self.inbox.drain(..), &mut self.out);
    }

    /// Finishes the cycle: the robot takes the command; after a short wait
    /// when armed the ball is released; a finished or aborted trial is reset
    /// and the next one armed at the same distance.
    pub fn finish(&mut self) {
        self.head = (self.head + 1) % MAX_DELAY;
        self.sent[self.head] = self.out.q_command_rad;
        let t = self.t_s();
        match self.controller.state() {
            TrialState::Armed => {
                let since = *self.armed_at.get_or_insert(t);
                if t - since >= RELEASE_WAIT_S {
                    let _ = self.ball.release(t);
                    let _ = self.controller.release(t);
                }
            }
            TrialState::Done | TrialState::Abort(_) => {
                self.trials += 1;
                self.armed_at = None;
                if let Ok(ball) = PendulumSim::held_at(
                    *self.ball.model(),
                    *self.ball.geometry(),
                    self.release_angle_rad,
                    t,
                ) {
                    self.ball = ball;
                }
                let _ = self.controller.reset(t);
                let _ = self.controller.arm(t, &self.plan);
            }
            _ => {}
        }
    }

    /// One whole cycle: [`Self::prepare`], [`Self::step_controller`], [`Self::finish`].
    pub fn cycle(&mut self) {
        self.prepare();
        self.step_controller();
        self.finish();
    }

    /// Runs cycles until `until` holds after one (true) or `max_s` of rig time
    /// passed (false).
    pub fn run_until(&mut self, max_s: f64, until: impl Fn(&Self) -> bool) -> bool {
        let end = self.t_s() + max_s;
        while self.t_s() < end {
            self.cycle();
            if until(self) {
                return true;
            }
        }
        false
    }

    /// Runs until the cycle whose step will commit to the interception (the
    /// next [`Self::step_controller`] does), leaving it prepared; false when
    /// none came within `max_s`.
    pub fn prepare_commit(&mut self, max_s: f64) -> bool {
        let end = self.t_s() + max_s;
        while self.t_s() < end {
            self.prepare();
            let mut probe = self.controller.clone();
            let mut out = self.out;
            probe.step(&self.input, self.inbox.iter().copied(), &mut out);
            if self.controller.state() == TrialState::Tracking
                && probe.state() == TrialState::Intercepting
            {
                return true;
            }
            self.step_controller();
            self.finish();
        }
        false
    }

    /// The scenario the rig runs.
    pub fn scenario(&self) -> &Scenario {
        &self.scenario
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_rig_runs_a_trial_to_the_end() {
        let mut s = Scenario::default();
        s.robot.fri_period_ms = 1;
        let mut rig = Rig::new(&s, 0.6, 20.0, 1).unwrap();
        assert!(rig.run_until(30.0, |r| r.state() == TrialState::Tracking));
        let mut commit = rig.clone();
        assert!(commit.prepare_commit(10.0));
        commit.step_controller();
        assert_eq!(commit.state(), TrialState::Intercepting);
        assert!(rig.run_until(10.0, |r| r.trials() == 1));
        let c = rig.controller().counters();
        assert_eq!(c.aborts, 0, "{c:?}");
        assert_eq!(c.limit_violations(), 0, "{c:?}");
        assert!(c.fused > 30, "{c:?}");
        // Between camera frames (30 fps, 1 ms cycles) the prediction is
        // reused: tracking took about 0.5 s here.
        assert!(c.predictions_reused > 300, "{c:?}");
    }
}
