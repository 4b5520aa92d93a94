#![doc = include_str!("README.md")]

#[cfg(feature = "opencv")]
pub mod board;
pub mod camera;
pub mod contact;
pub mod dynamics;
pub mod geometry;
pub mod judge;
pub mod live;
#[cfg(feature = "opencv")]
pub mod marker;
/// `[world]`, parsed with the rest of the scenario (`params::world`).
pub use crate::params::world as params;
pub mod pendulum;
pub mod robot;
#[cfg(feature = "opencv")]
pub mod webcam;

pub use camera::{FrameTiming, Sighting, WorldCamera};
pub use contact::Contact;
pub use dynamics::{ArmDynamics, TorqueTrip, check_torques};
pub use geometry::{TrueArm, true_intercept_m};
pub use judge::{PhysicalJudgement, StrikeAim, WorldSample, judge_physical, judge_strike};
pub use params::{SessionDraw, TrialWorldDraw, WorldParams};
pub use pendulum::{Disc, TruePendulum, TruePendulumParams};
pub use robot::{LatencyModel, WorldJoints};

use nalgebra::Vector3;

use crate::params::Scenario;

/// The world of one trial: the scenario's beliefs turned into the true lab by
/// the session's and the trial's draws. Only the simulators build and read it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct World {
    /// The session's draws.
    pub session: SessionDraw,
    /// The trial's draws.
    pub trial: TrialWorldDraw,
    /// The true pendulum's constants (pivot placed for the believed intercept point).
    pub pendulum: TruePendulumParams,
    /// The true arm and tool.
    pub arm: TrueArm,
    /// The true intercept point (ball at rest), m.
    pub intercept_m: Vector3<f64>,
}

impl World {
    /// The world of trial `index` of a run with `seed`, for `scenario` and a
    /// believed intercept point `believed_intercept_m`; `None` for a
    /// truthful scenario (no `[world]`).
    pub fn for_trial(
        scenario: &Scenario,
        seed: u64,
        index: usize,
        believed_intercept_m: &Vector3<f64>,
    ) -> Option<Self> {
        let w = scenario.world.as_ref()?;
        Self::in_session(
            scenario,
            seed,
            w.session_of(index),
            index,
            believed_intercept_m,
        )
    }

    /// The world of trial `index` in session `session` (a trial run's
    /// sessions follow the trial index; the world process keeps one session
    /// for its life: `live::LiveWorld`); `None` for a truthful scenario.
    pub fn in_session(
        scenario: &Scenario,
        seed: u64,
        session: u64,
        index: usize,
        believed_intercept_m: &Vector3<f64>,
    ) -> Option<Self> {
        let w = scenario.world.as_ref()?;
        let session = w.draw_session(seed, session, scenario.robot.latency_ms);
        let trial = w.draw_trial(seed, index, scenario.control.release_delay_prior_ms);
        let intercept_m = true_intercept_m(believed_intercept_m, &session);
        // Offsets are drawn around the nominal beliefs (before any calibration).
        let (nominal_length_m, nominal_damping_per_s) = w.anchor.map_or(
            (scenario.pendulum.length_m, scenario.pendulum.damping_per_s),
            |a| (a.pendulum_length_m, a.pendulum_damping_per_s),
        );
        let length_m = nominal_length_m + session.length_error_m;
        let pw = &w.pendulum;
        let pendulum = TruePendulumParams {
            pivot_m: intercept_m + Vector3::new(0.0, 0.0, length_m),
            length_m,
            gravity_mps2: scenario.pendulum.gravity_mps2,
            damping_per_s: nominal_damping_per_s * session.damping_scale,
            drag_per_m: TruePendulumParams::drag_factor(
                pw.air_density_kgpm3,
                session.drag_coefficient,
                scenario.pendulum.ball_radius_m,
                pw.ball_mass_kg,
            ),
            friction_mps2: session.pivot_friction_mps2,
            disturbance_mps2: trial.disturbance_mps2,
            ball_radius_m: scenario.pendulum.ball_radius_m,
            restitution: pw.contact_restitution,
        };
        let arm = TrueArm::from_session(
            scenario.task.tool_length_m,
            w.geometry.contact_disc_radius_m,
            &session,
        );
        Some(Self {
            session,
            trial,
            pendulum,
            arm,
            intercept_m,
        })
    }
}

#[cfg(test)]
mod tests;
