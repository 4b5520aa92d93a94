//! The control step as the FRI cycle calls it: the controller, its camera
//! inbox and the step's timing (wall clock and thread CPU time).

use crate::control::{
    Controller, Lateness, Sighting, StepClock, StepInput, StepOutput, StepRecord, StepTimings,
};
use crate::fri::codec::Monitoring;
use crate::fri::proto::SessionState;
use crate::kinematics::iiwa7::JOINTS;

/// The control step as the FRI cycle calls it: the controller, the camera
/// measurements delivered since the last message, and the cycle's timing.
///
/// Each step is timed by wall clock and by the thread's CPU time
/// ([`StepClock`]): a step whose own computation exceeded the period is a
/// deadline miss; one that only took longer by wall clock was preempted.
#[derive(Debug)]
pub struct LoopStep {
    /// The controller.
    pub controller: Controller,
    /// Camera measurements delivered since the last step.
    pub inbox: Vec<Sighting>,
    /// The last step's output.
    pub out: StepOutput,
    /// Steps whose own computation (thread CPU time) took longer than the FRI period.
    pub deadline_misses: u64,
    /// Steps longer than the FRI period by wall clock whose computation fitted
    /// in it (the thread was preempted while the step ran).
    pub preempted_steps: u64,
    /// Longest step, wall clock, nanoseconds.
    pub max_step_ns: u64,
    /// Longest step, thread CPU time, nanoseconds.
    pub max_step_cpu_ns: u64,
    /// When `Some`, every step's cost and states are recorded (benches; the
    /// buffer is preallocated and never grows).
    pub timings: Option<StepTimings>,
    /// Whether each step also reads the thread's CPU time (two system calls a
    /// step; [`StepClock::start_wall`]). The real-time lab does not: on its FRI
    /// thread the reply is the only system call of a cycle, and a step longer
    /// than the period counts as a deadline miss, preempted or not. The
    /// virtual-time lab and the benches do (they separate the two).
    pub cpu_time: bool,
}

impl LoopStep {
    /// Wraps a controller.
    pub fn new(controller: Controller) -> Self {
        Self {
            controller,
            inbox: Vec::with_capacity(64),
            out: StepOutput::default(),
            deadline_misses: 0,
            preempted_steps: 0,
            max_step_ns: 0,
            max_step_cpu_ns: 0,
            timings: None,
            cpu_time: true,
        }
    }

    /// One step for the monitoring message `m` received at `t_s`; returns the
    /// command to send.
    pub fn run(&mut self, t_s: f64, period_s: f64, m: &Monitoring) -> [f64; JOINTS] {
        let before = self.controller.state();
        let clock = if self.cpu_time {
            StepClock::start()
        } else {
            StepClock::start_wall()
        };
        let q = m
            .measured_joint_position_rad
            .unwrap_or(self.out.q_command_rad);
        let si = StepInput {
            t_s,
            q_measured_rad: q,
            commanding: m.session_state == SessionState::CommandingActive,
        };
        self.controller
            .step(&si, self.inbox.drain(..), &mut self.out);
        let cost = clock.stop();
        self.max_step_ns = self.max_step_ns.max(cost.wall_ns);
        self.max_step_cpu_ns = self.max_step_cpu_ns.max(cost.cpu_ns);
        // The period is positive and far below u64::MAX nanoseconds.
        match cost.lateness((period_s * 1e9) as u64) {
            Lateness::OnTime => {}
            Lateness::Preempted => self.preempted_steps += 1,
            Lateness::Overrun => self.deadline_misses += 1,
        }
        if let Some(t) = self.timings.as_mut() {
            t.record(StepRecord {
                cost,
                before,
                after: self.out.state,
            });
        }
        self.out.q_command_rad
    }
}
