//! What the measured judge needs of a trial (`control::measured`), recorded
//! by the trial driver in buffers allocated once: the camera's detections,
//! the measured tool point (measured joint positions through the
//! controller's kinematics and believed tool) and FRI's external joint
//! torques. A full buffer stops taking samples (a trial is at most
//! `TRIAL_TIMEOUT_S` long; the buffers hold that much).

use crate::control::measured::{MeasuredInputs, MeasuredJudgement, Sighting, judge_measured};
use crate::control::report::StrikeAim;

/// The measured judge's recording of one trial.
#[derive(Debug)]
pub(crate) struct MeasuredTrace {
    sightings: Vec<Sighting>,
    tool_t_s: Vec<f64>,
    tool_m: Vec<[f64; 3]>,
    torque_t_s: Vec<f64>,
    torques_nm: Vec<[f64; 7]>,
    /// The filter's rest offset shortly before the pass, m.
    pub rest_lateral_m: f64,
    /// The filter's pendulum frequency shortly before the pass, rad/s.
    pub omega_radps: Option<f64>,
}

/// What the judge takes besides the recording.
#[derive(Debug, Clone, Copy)]
pub(crate) struct MeasuredBeliefs {
    /// The committed pass, camera-stamp time, s.
    pub predicted_pass_s: f64,
    /// The camera offset the controller compensated (stamps late by it), s.
    pub camera_offset_s: f64,
    /// One detection's noise, m.
    pub sigma_x_m: f64,
    /// The believed pendulum frequency, rad/s (when the filter learned none).
    pub omega_radps: f64,
    /// Settling radius of the arrival, m.
    pub settle_m: f64,
    /// The plan's lead of that settling over the arrival the motion was
    /// timed for (`ArmPlan::settle_lead_s`), s.
    pub settle_lead_s: f64,
    /// Timing tolerance, ms.
    pub tolerance_ms: f64,
    /// The FRI period, s.
    pub period_s: f64,
    /// The believed intercept point's lateral (base `y`), m.
    pub intercept_y_m: f64,
    /// Ball centre to tool point along the swing at the first touch, m.
    pub contact_reach_m: f64,
    /// How late the external torques show a contact's force, s
    /// (`success.torque_lag_periods` FRI periods: a belief).
    pub contact_delay_s: f64,
    /// How long a contact's force pulse lasts, s (`success.contact_pulse_ms`: a belief).
    pub contact_pulse_s: f64,
    /// Strike mode's aim (the controller's plan; `None`: a stop).
    pub strike: Option<StrikeAim>,
}

impl MeasuredTrace {
    /// Room for `sightings` detections and `samples` control steps.
    pub fn with_capacity(sightings: usize, samples: usize) -> Self {
        Self {
            sightings: Vec::with_capacity(sightings),
            tool_t_s: Vec::with_capacity(samples),
            tool_m: Vec::with_capacity(samples),
            torque_t_s: Vec::with_capacity(samples),
            torques_nm: Vec::with_capacity(samples),
            rest_lateral_m: 0.0,
            omega_radps: None,
        }
    }

    /// Forgets the previous trial.
    pub fn clear(&mut self) {
        self.sightings.clear();
        self.tool_t_s.clear();
        self.tool_m.clear();
        self.torque_t_s.clear();
        self.torques_nm.clear();
        self.rest_lateral_m = 0.0;
        self.omega_radps = None;
    }

    /// A camera detection (capture time, lateral position).
    pub fn sighting(&mut self, t_s: f64, x_m: f64) {
        if self.sightings.len() < self.sightings.capacity() {
            self.sightings.push(Sighting { t_s, x_m });
        }
    }

    /// The movement the measured tool point made along `motion`'s path:
    /// `(start, duration)` of the ideal profile that best fits it
    /// ([`crate::control::judge::fit_movement`]); `None` when it cannot be
    /// fitted (too few samples, no motion).
    pub fn movement(
        &self,
        motion: &crate::control::judge::PlannedMotion,
        scratch: &mut crate::control::judge::JudgeScratch,
    ) -> Option<(f64, f64)> {
        let samples = self
            .tool_t_s
            .iter()
            .zip(&self.tool_m)
            .map(|(&t, p)| (t, nalgebra::Vector3::from(*p)));
        crate::control::judge::fit_movement(samples, motion, scratch)
            .ok()
            .map(|(start_s, dur_s, _)| (start_s, dur_s))
    }

    /// The measured tool point at `t_s`.
    pub fn tool(&mut self, t_s: f64, p: [f64; 3]) {
        if self.tool_t_s.len() < self.tool_t_s.capacity() {
            self.tool_t_s.push(t_s);
            self.tool_m.push(p);
        }
    }

    /// The external joint torques at `t_s`.
    pub fn torques(&mut self, t_s: f64, tau: [f64; 7]) {
        if self.torque_t_s.len() < self.torque_t_s.capacity() {
            self.torque_t_s.push(t_s);
            self.torques_nm.push(tau);
        }
    }

    /// Judges the recording (moves the detections onto the control clock
    /// first; nothing allocates). `None` without tool samples.
    pub fn judge(&mut self, b: &MeasuredBeliefs) -> Option<MeasuredJudgement> {
        if self.tool_t_s.is_empty() {
            return None;
        }
        for s in &mut self.sightings {
            s.t_s -= b.camera_offset_s;
        }
        let j = judge_measured(&MeasuredInputs {
            sightings: &self.sightings,
            rest_lateral_m: self.rest_lateral_m,
            sigma_x_m: b.sigma_x_m,
            omega_radps: self.omega_radps.unwrap_or(b.omega_radps),
            predicted_pass_s: b.predicted_pass_s - b.camera_offset_s,
            tool_t_s: &self.tool_t_s,
            tool_m: &self.tool_m,
            torque_t_s: &self.torque_t_s,
            torques_nm: &self.torques_nm,
            settle_m: b.settle_m,
            arrival_lead_s: b.settle_lead_s,
            tolerance_ms: b.tolerance_ms,
            contact_delay_s: b.contact_delay_s,
            contact_pulse_s: b.contact_pulse_s,
            contact_period_s: b.period_s,
            intercept_y_m: b.intercept_y_m,
            contact_reach_m: b.contact_reach_m,
            strike: b.strike,
        });
        for s in &mut self.sightings {
            s.t_s += b.camera_offset_s;
        }
        Some(j)
    }
}
