//! The command guard: every joint command passes it before it is sent.
//!
//! In order: a command with any non-finite value is replaced by the previous one
//! (hold); each joint is clamped into its position limits less a margin; each
//! joint's step from the previous command is clamped to
//! `velocity_fraction * v_max * period`. The previous command is within the
//! limits, so clamping the step keeps the result within them (the set is convex).

use serde::{Deserialize, Serialize};

use super::codec::Joints;
use crate::check::{self, ParamError};
use crate::kinematics::iiwa7::{JOINTS, POSITION_LIMIT_RAD, VELOCITY_LIMIT_RADPS};

/// Guard settings: `[fri.guard]`-style, units in the names.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GuardParams {
    /// Clamp commands this far inside the joint position limits, degrees.
    pub position_margin_deg: f64,
    /// Largest step per receive period as a fraction of `v_max * period` (0..1].
    pub velocity_fraction: f64,
}

impl Default for GuardParams {
    fn default() -> Self {
        Self {
            position_margin_deg: 0.5,
            velocity_fraction: 0.95,
        }
    }
}

impl GuardParams {
    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first field
    /// that is not finite or outside its range.
    pub fn validate(&self) -> Result<(), ParamError> {
        check::within(
            "fri.guard.position_margin_deg",
            self.position_margin_deg,
            0.0,
            10.0,
        )?;
        check::within(
            "fri.guard.velocity_fraction",
            self.velocity_fraction,
            0.01,
            1.0,
        )
    }
}

/// What the guard changed in one command (all `false`: sent as asked).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct GuardOutcome {
    /// A value was NaN or infinite: the previous command was held.
    pub held_non_finite: bool,
    /// At least one joint was clamped into its position limits.
    pub clamped_position: bool,
    /// At least one joint's step was clamped to the velocity limit.
    pub clamped_step: bool,
}

impl GuardOutcome {
    /// True when the command was changed.
    pub const fn changed(&self) -> bool {
        self.held_non_finite || self.clamped_position || self.clamped_step
    }
}

/// The guard, built once from [`GuardParams`] and the iiwa 7's limits.
#[derive(Debug, Clone, PartialEq)]
pub struct CommandGuard {
    lo_rad: Joints,
    hi_rad: Joints,
    max_speed_radps: Joints,
}

impl Default for CommandGuard {
    fn default() -> Self {
        Self::new(&GuardParams::default())
    }
}

impl CommandGuard {
    /// A guard for the iiwa 7 (params must be valid; see [`GuardParams::validate`]).
    pub fn new(p: &GuardParams) -> Self {
        let margin = p.position_margin_deg.to_radians().max(0.0);
        let frac = p.velocity_fraction.clamp(0.0, 1.0);
        Self {
            lo_rad: std::array::from_fn(|i| -POSITION_LIMIT_RAD[i] + margin),
            hi_rad: std::array::from_fn(|i| POSITION_LIMIT_RAD[i] - margin),
            max_speed_radps: std::array::from_fn(|i| VELOCITY_LIMIT_RADPS[i] * frac),
        }
    }

    /// Largest step per `period_s` for each joint, rad.
    pub fn max_step_rad(&self, period_s: f64) -> Joints {
        std::array::from_fn(|i| self.max_speed_radps[i] * period_s)
    }

    /// Makes `cmd` safe to send after `prev` (the last command sent), `period_s`
    /// apart. No allocation; never panics.
    pub fn apply(&self, cmd: &mut Joints, prev: &Joints, period_s: f64) -> GuardOutcome {
        let mut out = GuardOutcome::default();
        if cmd.iter().any(|v| !v.is_finite()) {
            *cmd = *prev;
            out.held_non_finite = true;
        }
        let period_s = if period_s.is_finite() && period_s > 0.0 {
            period_s
        } else {
            0.0
        };
        for i in 0..JOINTS {
            let clamped = cmd[i].clamp(self.lo_rad[i], self.hi_rad[i]);
            if clamped != cmd[i] {
                out.clamped_position = true;
                cmd[i] = clamped;
            }
            let max = self.max_speed_radps[i] * period_s;
            if prev[i].is_finite() {
                let step = cmd[i] - prev[i];
                if step.abs() > max {
                    out.clamped_step = true;
                    cmd[i] = prev[i] + max.copysign(step);
                }
            }
        }
        out
    }
}
