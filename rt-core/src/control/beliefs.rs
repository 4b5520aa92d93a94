//! What the controller is told about its lab: exactly the sections of a
//! scenario it reads, each owned by its part. `params::Scenario::beliefs`
//! builds one; `control` never imports `params` (issue #19).

use super::step::ControlParams;
use crate::check::{self, ParamError};
use crate::ekf::EkfParams;
use crate::pendulum::PendulumParams;
use crate::timing::TimingParams;
use crate::trajectory::TaskParams;

/// The bounds of `robot.fri_period_ms`, whole milliseconds (`[robot]` is
/// validated with the same ones).
pub const FRI_PERIOD_MS_BOUNDS: (u32, u32) = (1, 100);

/// The default FRI send period, milliseconds (`[robot]`'s default).
pub const FRI_PERIOD_MS_DEFAULT: u32 = 5;

/// The controller's view of the lab: never `[world]` (the lab as it really
/// is), `[camera]`, `[success]` or the robot's true latency.
#[derive(Debug, Clone, PartialEq)]
pub struct Beliefs {
    /// The pendulum (`[pendulum]`).
    pub pendulum: PendulumParams,
    /// The interception task (`[task]`).
    pub task: TaskParams,
    /// The FRI send period, whole milliseconds (`robot.fri_period_ms`).
    pub fri_period_ms: u32,
    /// The extended Kalman filter and predictor (`[ekf]`).
    pub ekf: EkfParams,
    /// The Hopf timing dynamics and the timed motion (`[timing]`).
    pub timing: TimingParams,
    /// The closed loop (`[control]`).
    pub control: ControlParams,
}

impl Default for Beliefs {
    fn default() -> Self {
        Self {
            pendulum: PendulumParams::default(),
            task: TaskParams::default(),
            fri_period_ms: FRI_PERIOD_MS_DEFAULT,
            ekf: EkfParams::default(),
            timing: TimingParams::default(),
            control: ControlParams::default(),
        }
    }
}

impl Beliefs {
    /// Checks every section in the order `Scenario::validate` does; the error
    /// names the first bad field (`control.hold_time_s`, `robot.fri_period_ms`).
    ///
    /// # Errors
    ///
    /// The first [`ParamError`] of a section's check (pendulum, task, FRI period, EKF,
    /// timing, control).
    pub fn validate(&self) -> Result<(), ParamError> {
        self.pendulum.validate()?;
        self.task.validate()?;
        validate_fri_period_ms("robot.fri_period_ms", self.fri_period_ms)?;
        self.ekf.validate()?;
        self.timing.validate()?;
        self.control.validate()
    }
}

/// Checks an FRI send period against [`FRI_PERIOD_MS_BOUNDS`].
///
/// # Errors
///
/// [`ParamError::OutOfRange`] when `ms` is outside [`FRI_PERIOD_MS_BOUNDS`].
pub fn validate_fri_period_ms(field: &str, ms: u32) -> Result<(), ParamError> {
    let (lo, hi) = FRI_PERIOD_MS_BOUNDS;
    check::within_u32(field, ms, lo, hi)
}
