//! `[task]` in a scenario: owned here (the interception motion is planned
//! from it), composed into `params::Scenario`.

use serde::{Deserialize, Serialize};

use crate::check::{self, ParamError, RangeParam};

/// What a trial's motion does to the ball: `task.mode`.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, utoipa::ToSchema, ts_rs::TS,
)]
#[serde(rename_all = "snake_case")]
pub enum TaskMode {
    /// The paper's task: the tool arrives at the intercept point at the
    /// ball's pass and stops there, at rest (the ball is stopped).
    #[default]
    Stop,
    /// Issue #38: the tool meets the ball at the intercept point at the
    /// ball's pass with `task.strike_speed_mps` along
    /// `task.strike_direction_deg`, then brakes to rest
    /// (`trajectory::strike`).
    Strike,
}

impl TaskMode {
    /// The mode's name as the scenario writes it.
    pub const fn as_str(self) -> &'static str {
        match self {
            Self::Stop => "stop",
            Self::Strike => "strike",
        }
    }
}

/// The largest `task.strike_speed_mps` a scenario may ask for, m/s (the
/// planner refuses most strokes far below it: `isochron kin strike-map`).
pub const STRIKE_SPEED_MAX_MPS: f64 = 5.0;

/// The steepest `task.strike_direction_deg` a scenario may ask for, degrees
/// either side of the horizontal.
pub const STRIKE_DIRECTION_MAX_DEG: f64 = 60.0;

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
    /// Duration of the interception motion, seconds (in strike mode: from
    /// the stroke's start to the contact).
    pub movement_time_s: f64,
    /// `"stop"` (default: the tool arrives at rest and stops the ball) or
    /// `"strike"` (the tool meets the ball with `strike_speed_mps`, then
    /// brakes to rest; issue #38).
    pub mode: TaskMode,
    /// Strike mode: the tool's speed at contact along the strike direction,
    /// m/s (> 0). With restitution 0 the ball leaves with the tool's speed
    /// along the contact normal: `strike_speed_mps * cos(strike_direction_deg)`.
    pub strike_speed_mps: f64,
    /// Strike mode: the strike direction's elevation above the horizontal in
    /// the swing plane, degrees (-60..60); the direction's horizontal part
    /// is the ball's return (against its pass).
    pub strike_direction_deg: f64,
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
            mode: TaskMode::Stop,
            strike_speed_mps: 0.5,
            strike_direction_deg: 20.0,
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
        check::within("task.movement_time_s", self.movement_time_s, 0.3, 10.0)?;
        // Checked in stop mode too: a scenario switched to strike later
        // (`PUT /api/params`) must be valid already.
        check::positive("task.strike_speed_mps", self.strike_speed_mps)?;
        check::within(
            "task.strike_speed_mps",
            self.strike_speed_mps,
            0.0,
            STRIKE_SPEED_MAX_MPS,
        )?;
        check::within(
            "task.strike_direction_deg",
            self.strike_direction_deg,
            -STRIKE_DIRECTION_MAX_DEG,
            STRIKE_DIRECTION_MAX_DEG,
        )
    }
}
