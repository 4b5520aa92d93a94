//! `[success]` in a scenario: owned here (a trial record's verdict applies
//! it), composed into `params::Scenario`.

use serde::{Deserialize, Serialize};

use crate::check::{self, ParamError};

/// How a trial is judged: `[success]` in a scenario.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SuccessParams {
    /// Largest tool-to-ball distance at t* that counts as a hit, metres.
    pub position_tolerance_m: f64,
    /// Largest |arrival - t*| that counts as timed precisely, milliseconds.
    pub timing_tolerance_ms: f64,
    /// The measured judge's belief of how long a contact's force pulse on
    /// the tool lasts (ball and disc compliance), milliseconds: a tennis ball
    /// on a rigid disc, a few.
    pub contact_pulse_ms: f64,
    /// The measured judge's belief of how late the robot's external torque
    /// estimate shows a contact's force (its filtering), FRI periods.
    pub torque_lag_periods: f64,
}

impl Default for SuccessParams {
    fn default() -> Self {
        Self {
            position_tolerance_m: 0.02,
            timing_tolerance_ms: 20.0,
            contact_pulse_ms: 4.0,
            torque_lag_periods: 1.0,
        }
    }
}

impl SuccessParams {
    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first field
    /// that is not finite or outside its range.
    pub fn validate(&self) -> Result<(), ParamError> {
        check::within(
            "success.position_tolerance_m",
            self.position_tolerance_m,
            1e-4,
            0.5,
        )?;
        check::within(
            "success.timing_tolerance_ms",
            self.timing_tolerance_ms,
            0.1,
            1000.0,
        )?;
        check::within("success.contact_pulse_ms", self.contact_pulse_ms, 0.5, 50.0)?;
        check::within(
            "success.torque_lag_periods",
            self.torque_lag_periods,
            0.0,
            10.0,
        )
    }
}
