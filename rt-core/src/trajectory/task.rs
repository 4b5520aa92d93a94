//! `[task]` in a scenario: owned here (the interception motion is planned
//! from it), composed into `params::Scenario`.

use serde::{Deserialize, Serialize};

use crate::check::{self, ParamError, RangeParam};

/// The interception task: `[task]` in a scenario.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TaskParams {
    /// Horizontal distance robot base axis -> intercept point, drawn per trial, metres.
    pub distance_m: RangeParam,
    /// Height of the intercept point (the ball at rest) above the robot base, metres.
    pub intercept_height_m: f64,
    /// The intercept point's offset from `(distance, 0, intercept_height_m)`,
    /// base frame, metres (`isochron calibrate camera-robot` measures it; the
    /// ball's rest point is `(distance, 0, intercept_height_m) + offset`).
    pub intercept_offset_m: [f64; 3],
    /// Tool point at the start of every motion, robot base frame, metres.
    pub home_m: [f64; 3],
    /// Tool point along the flange's z axis, metres.
    pub tool_length_m: f64,
    /// Radius of the tool's contact disc (centred on the tool point, normal
    /// along the tool axis), metres: where the ball first touches the tool,
    /// for the measured judge.
    pub tool_contact_radius_m: f64,
    /// Duration of the interception motion, seconds.
    pub movement_time_s: f64,
}

impl Default for TaskParams {
    fn default() -> Self {
        Self {
            distance_m: RangeParam::new(0.35, 0.80),
            intercept_height_m: 0.30,
            intercept_offset_m: [0.0; 3],
            home_m: [0.30, 0.0, 0.50],
            tool_length_m: 0.10,
            tool_contact_radius_m: 0.03,
            movement_time_s: 1.5,
        }
    }
}

impl TaskParams {
    /// The believed intercept point (the ball at rest) for a trial at `distance_m`,
    /// base frame, metres.
    pub fn intercept_m(&self, distance_m: f64) -> nalgebra::Vector3<f64> {
        nalgebra::Vector3::new(
            distance_m + self.intercept_offset_m[0],
            self.intercept_offset_m[1],
            self.intercept_height_m + self.intercept_offset_m[2],
        )
    }

    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`], [`ParamError::OutOfRange`] or [`ParamError::Reversed`]
    /// naming the first field that is not finite, outside its range or a reversed range.
    pub fn validate(&self) -> Result<(), ParamError> {
        self.distance_m
            .validate_with("task.distance_m", |f, v| check::within(f, v, 0.1, 1.2))?;
        check::within(
            "task.intercept_height_m",
            self.intercept_height_m,
            -0.5,
            1.5,
        )?;
        for (i, v) in self.intercept_offset_m.iter().enumerate() {
            check::within(&format!("task.intercept_offset_m[{i}]"), *v, -0.1, 0.1)?;
        }
        for (i, v) in self.home_m.iter().enumerate() {
            check::within(&format!("task.home_m[{i}]"), *v, -1.2, 1.5)?;
        }
        check::within("task.tool_length_m", self.tool_length_m, 0.0, 0.5)?;
        check::within(
            "task.tool_contact_radius_m",
            self.tool_contact_radius_m,
            0.0,
            0.2,
        )?;
        check::within("task.movement_time_s", self.movement_time_s, 0.3, 10.0)
    }
}
