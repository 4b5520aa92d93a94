//! `[pendulum]` in a scenario: owned here, composed into `params::Scenario`.

use serde::{Deserialize, Serialize};

use crate::check::{self, ParamError, RangeParam};

/// The pendulum: `[pendulum]` in a scenario.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PendulumParams {
    /// Pivot to ball centre, metres (paper: 1.93 m).
    pub length_m: f64,
    /// Viscous damping alpha in phi'' = -(g/l) sin(phi) - alpha phi', 1/s.
    pub damping_per_s: f64,
    /// Gravity, m/s^2.
    pub gravity_mps2: f64,
    /// Ball radius, metres (tennis ball: 0.0335 m).
    pub ball_radius_m: f64,
    /// Release angle drawn uniformly per trial, degrees from the vertical.
    pub release_angle_deg: RangeParam,
    /// The believed coefficient of restitution of ball and tool (0..1): a
    /// strike's predicted rebound leaves the tool with `(1 + e)` times the
    /// tool's speed along the return plus `e` times the ball's incoming
    /// speed (0, the default: the ball leaves with the tool's speed, as the
    /// strike's target assumes). The world's is `world.pendulum.contact_restitution`.
    pub contact_restitution: f64,
}

impl Default for PendulumParams {
    fn default() -> Self {
        Self {
            length_m: 1.93,
            damping_per_s: 0.03,
            gravity_mps2: 9.81,
            ball_radius_m: 0.0335,
            release_angle_deg: RangeParam::new(15.0, 35.0),
            contact_restitution: 0.0,
        }
    }
}

impl PendulumParams {
    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`], [`ParamError::OutOfRange`] or [`ParamError::Reversed`]
    /// naming the first field that is not finite, outside its range or a reversed range.
    pub fn validate(&self) -> Result<(), ParamError> {
        check::within("pendulum.length_m", self.length_m, 0.1, 10.0)?;
        check::within("pendulum.damping_per_s", self.damping_per_s, 0.0, 5.0)?;
        check::within("pendulum.gravity_mps2", self.gravity_mps2, 0.1, 100.0)?;
        check::within("pendulum.ball_radius_m", self.ball_radius_m, 0.005, 0.2)?;
        check::probability("pendulum.contact_restitution", self.contact_restitution)?;
        self.release_angle_deg
            .validate_with("pendulum.release_angle_deg", |f, v| {
                check::within(f, v, 1.0, 60.0)
            })
    }
}
