//! The straight-line motion of the tool point with a held orientation.

use nalgebra::{Rotation3, Translation3, Vector3};

use super::profile::ProfileKind;
use super::task::TaskParams;
use crate::kinematics::{Pose, Tool};

/// The tool orientation "pointing down, tilted by `tilt_rad` about the base y axis":
/// `Ry(pi + tilt)`. The tool's z axis is `(-sin tilt, 0, -cos tilt)`, so a positive
/// tilt leans the tool tip back towards the base (the flange moves outwards).
pub fn tool_rotation(tilt_rad: f64) -> Rotation3<f64> {
    Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI + tilt_rad)
}

/// A timed straight-line motion of the tool point (the request a plan answers).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionRequest {
    /// Tool point at the start (home), base frame, metres.
    pub start_m: Vector3<f64>,
    /// Tool point at the end (the intercept point), base frame, metres.
    pub end_m: Vector3<f64>,
    /// Duration, seconds.
    pub movement_time_s: f64,
    /// Velocity profile along the line.
    pub profile: ProfileKind,
    /// The tool on the flange.
    pub tool: Tool,
}

impl MotionRequest {
    /// The paper's interception motion: from `task.home_m` to the intercept point
    /// `(distance_m, 0, task.intercept_height_m) + task.intercept_offset_m` in `task.movement_time_s`, Hopf
    /// (sinusoidal) profile, tool `task.tool_length_m` along the flange's z axis.
    pub fn interception(task: &TaskParams, distance_m: f64) -> Self {
        Self {
            start_m: Vector3::from(task.home_m),
            end_m: task.intercept_m(distance_m),
            movement_time_s: task.movement_time_s,
            profile: ProfileKind::Hopf,
            tool: Tool::along_z(task.tool_length_m),
        }
    }

    /// Path length, metres.
    pub fn length_m(&self) -> f64 {
        (self.end_m - self.start_m).norm()
    }

    /// The tool point at path fraction `s` in `[0, 1]` (clamped).
    #[inline]
    pub fn point_at(&self, s: f64) -> Vector3<f64> {
        self.start_m + (self.end_m - self.start_m) * s.clamp(0.0, 1.0)
    }

    /// `base_from_flange` that puts the tool point at `p_m` with orientation `r`.
    #[inline]
    pub fn flange_pose_for(&self, p_m: &Vector3<f64>, r: &Rotation3<f64>) -> Pose {
        let tool = Pose::from_parts(Translation3::from(*p_m), *r);
        self.tool.flange_for(&tool)
    }
}
