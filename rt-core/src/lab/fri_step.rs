//! The closed loop's control step behind the FRI client session.
//!
//! [`FriLoopStep`] implements [`fri::client::ControlStep`](crate::fri::client::ControlStep):
//! once per controller message the FRI client ([`crate::fri::FriClient`]) calls
//! [`step`](crate::fri::client::ControlStep::step), which folds in the camera
//! measurements waiting in [`LoopStep::inbox`], runs [`Controller::step`] on the
//! measured joint positions of the message and leaves the controller's joint
//! command for the client to guard and send. When the session stops commanding
//! (the controller aborted or left COMMANDING_*, fell silent, or closed the
//! session), [`stop`](crate::fri::client::ControlStep::stop) aborts the running
//! trial ([`AbortReason::FriLost`]) and keeps the FRI reason
//! ([`FriLoopStep::last_stop`]).
//!
//! The same value runs in virtual time (the virtual lab, `sim/virtual_lab.rs`, one thread) and
//! in real time (on the session's thread, [`crate::fri::FriSession`]); the
//! step neither allocates, locks, logs nor blocks once the inbox has its
//! capacity. The control clock is the session's: `t_s = now_ns * 1e-9`, so
//! camera measurements must carry capture times on the same clock.

use super::loop_step::LoopStep;
use crate::control::{AbortReason, Controller, TrialState};
use crate::fri::client::{ControlStep, StepInput, StopReason};
use crate::fri::codec::Joints;
use crate::fri::proto::SessionState;

/// The closed loop's control step as the FRI session calls it (see the module
/// documentation).
#[derive(Debug)]
pub struct FriLoopStep {
    /// The control step: the controller, its camera inbox and its step timing.
    pub step: LoopStep,
    last_t_s: f64,
    last_stop: Option<StopReason>,
    stops: u64,
    trial_aborts: u64,
}

impl FriLoopStep {
    /// Wraps a controller.
    pub fn new(controller: Controller) -> Self {
        Self::from_step(LoopStep::new(controller))
    }

    /// Wraps an existing loop step.
    pub fn from_step(step: LoopStep) -> Self {
        Self {
            step,
            last_t_s: 0.0,
            last_stop: None,
            stops: 0,
            trial_aborts: 0,
        }
    }

    /// The controller.
    pub fn controller(&self) -> &Controller {
        &self.step.controller
    }

    /// The controller, to arm, release or reset trials between steps.
    pub fn controller_mut(&mut self) -> &mut Controller {
        &mut self.step.controller
    }

    /// The session time of the last step, seconds (`now_ns * 1e-9`).
    pub fn last_t_s(&self) -> f64 {
        self.last_t_s
    }

    /// Why the session last told the control to stop, if it did since
    /// [`clear_stop`](Self::clear_stop).
    pub fn last_stop(&self) -> Option<StopReason> {
        self.last_stop
    }

    /// Forgets the last stop reason (at the start of a trial).
    pub fn clear_stop(&mut self) {
        self.last_stop = None;
    }

    /// Stop events received from the session.
    pub fn stops(&self) -> u64 {
        self.stops
    }

    /// Stop events that aborted a running trial.
    pub fn trial_aborts(&self) -> u64 {
        self.trial_aborts
    }

    /// The wrapped loop step.
    pub fn into_inner(self) -> LoopStep {
        self.step
    }
}

impl ControlStep for FriLoopStep {
    fn step(&mut self, input: &StepInput<'_>, command_rad: &mut Joints) {
        let m = input.monitoring;
        if m.session_state == SessionState::CommandingActive && !input.commanding {
            // Between `receiveMultiplier` answers (or before the hand-over):
            // nothing is sent, so the controller waits for the answered
            // message (its step spans the whole receive period). The inbox
            // keeps the measurements until then.
            return;
        }
        let t_s = input.now_ns as f64 * 1e-9;
        self.last_t_s = t_s;
        let q = self.step.run(t_s, input.receive_period_s, m);
        if input.commanding {
            *command_rad = q;
        }
    }

    fn stop(&mut self, reason: StopReason) {
        self.stops += 1;
        self.last_stop = Some(reason);
        let running = !matches!(
            self.step.controller.state(),
            TrialState::Idle | TrialState::Done | TrialState::Aborted
        );
        if running {
            self.trial_aborts += 1;
            self.step
                .controller
                .abort(self.last_t_s, AbortReason::FriLost);
        }
    }
}

#[cfg(test)]
mod tests;
