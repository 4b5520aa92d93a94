//! `TimingParams`: the tunable constants of the speed dynamics, the neurons and
//! the online re-planning.

use serde::{Deserialize, Serialize};

use crate::check::{self, ParamError};
use crate::trajectory::profile::ProfileKind;

/// Parameters of the timed motion (`[timing]` once the closed loop wires it in).
///
/// The paper states the structure of its dynamics but no numbers; the defaults
/// are ours, chosen so that one 1.5 s motion is timed to well under a
/// millisecond at every FRI period from 1 to 10 ms (see the module README).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TimingParams {
    /// Velocity profile: `"hopf"` (the paper's, integrated from the dynamics) or
    /// `"min_jerk"` (the Flash and Hogan baseline, re-planned online).
    pub profile: ProfileKind,
    /// Hopf parameter lambda: the limit cycle attracts at rate `2 lambda`, 1/s.
    pub hopf_lambda_per_s: f64,
    /// c1: rate of the initial fixed point (rest before the motion), 1/s.
    pub init_gain_per_s: f64,
    /// c2: rate of the final fixed point (rest at the target), 1/s.
    pub final_gain_per_s: f64,
    /// k_f: path speed per metre of remaining distance in the final regime, 1/s
    /// (holds the tool on the target; 0 disables).
    pub final_position_gain_per_s: f64,
    /// tau_u: time constant of the competitive neural dynamics, seconds.
    pub neuron_time_constant_s: f64,
    /// mu of the selected neuron (> 0).
    pub neuron_advantage: f64,
    /// -mu of the neurons not selected (>= 0; their mu is minus this).
    pub neuron_disadvantage: f64,
    /// nu: mutual inhibition between neurons; must exceed `neuron_advantage`.
    pub neuron_competition: f64,
    /// Lowest activation of a suppressed neuron (the deterministic stand-in for
    /// the noise of the cited work, so a neuron can rise when selected).
    pub neuron_floor: f64,
    /// Largest internal integration step, seconds; a step of `dt` is split into
    /// `ceil(dt / max_substep_s)` equal substeps.
    pub max_substep_s: f64,
    /// Rate at which the command's position is pulled to a measured position, 1/s
    /// (0 ignores measurements).
    pub progress_feedback_per_s: f64,
    /// Time constant of the critically damped filter a new target passes
    /// through (keeps the velocity direction continuous), seconds (0: none).
    pub target_smoothing_s: f64,
    /// How hard a lagging motion hurries back onto its schedule: the cycle's
    /// end is planned `schedule_gain * lag` earlier while it lags (0: the lost
    /// progress is only made up by the planned end).
    pub schedule_gain: f64,
    /// Remaining oscillator phase below which amplitude and frequency are no
    /// longer re-planned (the re-plan is ill-conditioned at the very end), rad.
    pub replan_freeze_rad: f64,
}

impl Default for TimingParams {
    fn default() -> Self {
        Self {
            profile: ProfileKind::Hopf,
            hopf_lambda_per_s: 20.0,
            init_gain_per_s: 40.0,
            final_gain_per_s: 40.0,
            final_position_gain_per_s: 10.0,
            neuron_time_constant_s: 0.005,
            neuron_advantage: 4.0,
            neuron_disadvantage: 2.0,
            neuron_competition: 6.0,
            neuron_floor: 0.01,
            max_substep_s: 0.001,
            progress_feedback_per_s: 100.0,
            target_smoothing_s: 0.03,
            schedule_gain: 10.0,
            replan_freeze_rad: 0.6,
        }
    }
}

impl TimingParams {
    /// Checks every field; the error names the first bad one (`timing.<field>`).
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first field
    /// that is not finite, outside its range or inconsistent with another.
    pub fn validate(&self) -> Result<(), ParamError> {
        check::within(
            "timing.hopf_lambda_per_s",
            self.hopf_lambda_per_s,
            0.5,
            200.0,
        )?;
        check::within("timing.init_gain_per_s", self.init_gain_per_s, 0.5, 500.0)?;
        check::within("timing.final_gain_per_s", self.final_gain_per_s, 0.5, 500.0)?;
        check::within(
            "timing.final_position_gain_per_s",
            self.final_position_gain_per_s,
            0.0,
            100.0,
        )?;
        check::within(
            "timing.neuron_time_constant_s",
            self.neuron_time_constant_s,
            1e-4,
            1.0,
        )?;
        check::within("timing.neuron_advantage", self.neuron_advantage, 0.1, 100.0)?;
        check::within(
            "timing.neuron_disadvantage",
            self.neuron_disadvantage,
            0.0,
            100.0,
        )?;
        check::within(
            "timing.neuron_competition",
            self.neuron_competition,
            0.1,
            1000.0,
        )?;
        if self.neuron_competition <= self.neuron_advantage {
            return Err(check::out_of_range(
                "timing.neuron_competition",
                self.neuron_competition,
                check::Bound::rule("must exceed timing.neuron_advantage (winner takes all)"),
            ));
        }
        check::within("timing.neuron_floor", self.neuron_floor, 1e-6, 0.1)?;
        check::within("timing.max_substep_s", self.max_substep_s, 1e-5, 0.01)?;
        // RK4 is stable for rate * h up to about 2.78; keep a margin.
        let fastest = (self.neuron_advantage.max(self.neuron_disadvantage)
            + self.neuron_competition)
            / self.neuron_time_constant_s;
        let fastest = fastest
            .max(2.0 * self.hopf_lambda_per_s)
            .max(self.init_gain_per_s)
            .max(self.final_gain_per_s);
        if fastest * self.max_substep_s > 2.5 {
            return Err(check::out_of_range(
                "timing.max_substep_s",
                self.max_substep_s,
                check::Bound::rule(
                    "too large for the fastest rate of the dynamics (rate * step must be <= 2.5)",
                ),
            ));
        }
        check::within(
            "timing.progress_feedback_per_s",
            self.progress_feedback_per_s,
            0.0,
            10_000.0,
        )?;
        check::within(
            "timing.target_smoothing_s",
            self.target_smoothing_s,
            0.0,
            1.0,
        )?;
        check::within(
            "timing.replan_freeze_rad",
            self.replan_freeze_rad,
            0.05,
            3.0,
        )
    }
}
