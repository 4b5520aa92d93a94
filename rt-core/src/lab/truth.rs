//! The world as the trial driver meets it when it judges on ground truth: a
//! [`TruthObserver`] (issue #35, "one world model"). The driver holds no
//! truth of its own and imports nothing from `sim`: a simulated lab hands it
//! an observer implemented there (`SimTruth`, `sim/truth.rs`: the ideal pendulum
//! of a truthful world, or the reality lab's true ball on the true tool with
//! its contacts and the physical judge); the real lab has none and is judged
//! by what it measures.
//!
//! The driver calls the observer on the control thread: [`TruthObserver::step`]
//! on every message once the reply is out (`ControlStep::after_reply`), the
//! rest once per trial. None of its calls may allocate, lock, log or block,
//! except [`TruthObserver::hang`] (a trial's start, on the operator's command).

use nalgebra::Vector3;

use super::trial::TrialDraw;
use crate::bridge::Refusal;
pub use crate::control::report::PhysicalJudgement;
use crate::control::{ArmPlan, Commit};
use crate::fri::codec::Joints;
use crate::params::Scenario;

/// True passes of the ball through the intercept point kept per trial.
pub const MAX_PASSES: usize = 64;

/// A trial the driver starts (what the world needs to hang its true ball).
#[derive(Debug, Clone, Copy)]
pub struct TrialStart<'a> {
    /// When the trial starts, control clock, seconds.
    pub t_s: f64,
    /// The lab's scenario (the beliefs and, for a simulated lab, `[world]`).
    pub scenario: &'a Scenario,
    /// The run's seed.
    pub seed: u64,
    /// The trial's index in the run (its draw).
    pub index: usize,
    /// What the trial drew.
    pub draw: &'a TrialDraw,
    /// The controller's plan of the trial.
    pub plan: &'a ArmPlan,
}

/// Why a trial could not be judged physically.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum PhysicalJudgeError {
    /// Fewer than 2 samples.
    #[error("the world trace has too few samples")]
    TooFewSamples,
    /// The ball never passed the intercept point.
    #[error("the true ball never passed the intercept point")]
    NoPass,
}

/// What a strike trial is judged against (defined beside the judges' figures).
pub use crate::control::report::StrikeAim;

/// The physical judge's verdict on a trial with the tool-ball distance at
/// its `t*` (the reported position error).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PhysicalVerdict {
    /// The physical judge's figures.
    pub judgement: PhysicalJudgement,
    /// The true contact disc's centre to the true ball at `t*`, metres.
    pub position_error_m: f64,
}

/// The ground truth of a simulated lab, as the trial driver follows and
/// judges it (see the module documentation). Frames and units: the robot
/// base frame of `control`, metres, seconds on the control clock.
pub trait TruthObserver: Send {
    /// A trial starts: the true ball hangs at the drawn release angle (not
    /// yet shown to the camera: [`Self::show`]). `Err`: the world cannot
    /// hang it (the trial is refused).
    ///
    /// # Errors
    ///
    /// A [`Refusal`] when the world cannot hang the ball for this trial.
    fn hang(&mut self, start: &TrialStart<'_>) -> Result<(), Refusal>;

    /// The trial is armed: from now on the camera sees the hanging ball.
    fn show(&mut self);

    /// The magnet's coil let go at `t_s` (its pin time): the ball swings
    /// from then (the world may hold it a little longer).
    fn release(&mut self, t_s: f64);

    /// The robot's true joints at this message, where the simulator tells
    /// them (`None`: the measured ones stand for them).
    fn true_joints(&self) -> Option<Joints>;

    /// Advances the truth to `t_s` (one step of `period_s` after the
    /// previous), the robot's true joints `q_true`: appends the true passes
    /// through the intercept point since the last step to `passes` (at most
    /// [`MAX_PASSES`]), fills `at_predicted` (while `None`) with the true
    /// ball centre at the committed prediction's pass time once it is past,
    /// and returns the true ball centre now (the judge's trace).
    fn step(
        &mut self,
        t_s: f64,
        q_true: &Joints,
        period_s: f64,
        commit: Option<&Commit>,
        passes: &mut Vec<(f64, Vector3<f64>)>,
        at_predicted: &mut Option<Vector3<f64>>,
    ) -> Vector3<f64>;

    /// The true ball centre now (the dashboard), `None` before a trial.
    fn ball_m(&self) -> Option<Vector3<f64>>;

    /// The true intercept point the truthful judge measures against
    /// (`None`: the plan's, a truthful world).
    fn intercept_m(&self) -> Option<Vector3<f64>>;

    /// The physical judge of the trial on the true world (`None`: a truthful
    /// world, judged by `control::judge` alone): `passes` as
    /// [`Self::step`] collected them, `committed_pass_s` the controller's
    /// predicted pass, `tolerance_ms` the timing tolerance, `strike` a
    /// strike trial's aim (`None`: stop mode).
    fn judge_physical(
        &mut self,
        passes: &[(f64, Vector3<f64>)],
        committed_pass_s: f64,
        tolerance_ms: f64,
        strike: Option<&StrikeAim>,
    ) -> Option<Result<PhysicalVerdict, PhysicalJudgeError>>;
}
