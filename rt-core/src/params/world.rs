//! `[world]`: what the simulated lab *is* (CONTRACT.md, "`[world]`"), and the
//! per-session / per-trial draws of its values. A scenario section like the
//! others, parsed here; read only by the simulators (`sim::world`, which
//! re-exports it): the controller is built from [`super::Scenario::beliefs`],
//! which has none.
//!
//! Every key is optional; the default of every key is the truthful value (the
//! world equals the beliefs), so `[world]` with no keys is a truthful world.
//! A value is a number or `[lo, hi]`, drawn uniformly per session or per trial
//! as its documentation says (`scenarios/README.md` lists them all).

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::{ParamError, RangeParam, check};

/// `[world.sessions]`: how trials are grouped into sessions ("reboots").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SessionParams {
    /// Trials per session; trial `i` is in session `i / trials_per_session`.
    pub trials_per_session: u32,
}

impl Default for SessionParams {
    fn default() -> Self {
        Self {
            trials_per_session: 20,
        }
    }
}

/// `[world.pendulum]`: the true pendulum.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WorldPendulumParams {
    /// True effective length minus the believed `pendulum.length_m`, m (per session).
    pub length_error_m: RangeParam,
    /// True linear damping as a multiple of the believed `pendulum.damping_per_s`
    /// (0: no linear damping, drag only), per session.
    pub damping_scale: RangeParam,
    /// Drag coefficient of the ball (quadratic air drag; 0: none), per session.
    pub drag_coefficient: RangeParam,
    /// Ball mass, kg (tennis ball: 0.057), used by the drag.
    pub ball_mass_kg: f64,
    /// Air density, kg/m^3.
    pub air_density_kgpm3: f64,
    /// Pivot (Coulomb) friction as a tangential deceleration of the ball, m/s^2, per session.
    pub pivot_friction_mps2: RangeParam,
    /// Out-of-plane angle of the string at release, degrees (sign drawn too), per trial.
    pub out_of_plane_deg: RangeParam,
    /// Delay between the coil's pin switching off and the ball dropping
    /// (residual magnetism), ms, per trial (default: the believed
    /// `control.release_delay_prior_ms`, the magnet the controller was built for).
    pub release_delay_ms: Option<RangeParam>,
    /// Standard deviation of a random horizontal acceleration (air), held for
    /// 50 ms at a time, m/s^2, per trial.
    pub disturbance_mps2: RangeParam,
    /// How long a contact's force pulse on the tool lasts (ball and disc
    /// compliance), ms, per session. The measured judge's belief of it is
    /// `success.contact_pulse_ms`.
    pub contact_pulse_ms: RangeParam,
    /// Coefficient of restitution of ball and tool (0..1): the share of
    /// their approach speed along the contact normal that they separate
    /// with (0, the default: the ball stops against the tool, the stop
    /// mode's catch; a tennis ball on a rigid plate: about 0.75).
    pub contact_restitution: f64,
}

impl Default for WorldPendulumParams {
    fn default() -> Self {
        Self {
            length_error_m: RangeParam::fixed(0.0),
            damping_scale: RangeParam::fixed(1.0),
            drag_coefficient: RangeParam::fixed(0.0),
            ball_mass_kg: 0.057,
            air_density_kgpm3: 1.2,
            pivot_friction_mps2: RangeParam::fixed(0.0),
            out_of_plane_deg: RangeParam::fixed(0.0),
            release_delay_ms: None,
            disturbance_mps2: RangeParam::fixed(0.0),
            contact_pulse_ms: RangeParam::fixed(4.0),
            contact_restitution: 0.0,
        }
    }
}

/// `[world.camera]`: the true camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WorldCameraParams {
    /// True capture -> delivery latency minus the believed `camera.latency_ms`, ms, per session.
    pub latency_ms: RangeParam,
    /// Per-frame latency jitter, uniform in `[0, value]`, ms (the value per session).
    pub latency_jitter_ms: RangeParam,
    /// Rolling shutter: time from reading the first row to the last, ms, per session.
    pub rolling_shutter_ms: RangeParam,
    /// Exposure time (the ball is smeared over it), ms, per session.
    pub exposure_ms: RangeParam,
    /// The least time from the end of a frame's readout (its last row's
    /// exposure) to its delivery: the last USB packets and the driver, ms,
    /// per session. A latency drawn shorter than exposure + readout + this
    /// is not physical: such a frame is delivered at that floor.
    pub transfer_ms: RangeParam,
    /// Radial distortion k1 (normalised image coordinates), per session.
    pub distortion_k1: RangeParam,
    /// Radial distortion k2, per session.
    pub distortion_k2: RangeParam,
    /// Tangential distortion p1, per session.
    pub distortion_p1: RangeParam,
    /// Tangential distortion p2, per session.
    pub distortion_p2: RangeParam,
    /// True camera rotation off the believed one, about each axis, degrees, per session.
    pub pose_error_deg: RangeParam,
    /// True camera position off the believed one, along each axis, m, per session.
    pub pose_error_m: RangeParam,
    /// The camera's frame clock runs fast (+) or slow (-) against the PC's by
    /// this much, parts per million, per session: frames come that much more
    /// often, and the stamps (the camera's clock mapped to the PC's at the
    /// session's start) drift by it.
    pub clock_drift_ppm: RangeParam,
    /// Each frame's exposure starts up to this far either side of its slot on
    /// the frame clock while its delivery keeps the slot, ms (bound per
    /// session, the value per frame): stamp errors of both signs.
    pub frame_jitter_ms: RangeParam,
    /// Auto-exposure: the frame's brightness gain wanders by up to this
    /// fraction either way (a sine of period 4..20 s), per session.
    pub exposure_gain_variation: RangeParam,
    /// Mains flicker (100 Hz): relative brightness modulation of the light,
    /// averaged over each frame's exposure, per session.
    pub flicker: RangeParam,
    /// A person walking past: in half of the 10 s windows of the lab's clock
    /// the light on the ball falls by this fraction for 0.5..1.5 s, per
    /// session (0: none).
    pub shadow_depth: RangeParam,
    /// The true arm and tool hide the ball where they stand between it and
    /// the camera.
    pub arm_occludes: bool,
}

impl Default for WorldCameraParams {
    fn default() -> Self {
        Self {
            latency_ms: RangeParam::fixed(0.0),
            latency_jitter_ms: RangeParam::fixed(0.0),
            rolling_shutter_ms: RangeParam::fixed(0.0),
            exposure_ms: RangeParam::fixed(0.0),
            transfer_ms: RangeParam::fixed(0.0),
            distortion_k1: RangeParam::fixed(0.0),
            distortion_k2: RangeParam::fixed(0.0),
            distortion_p1: RangeParam::fixed(0.0),
            distortion_p2: RangeParam::fixed(0.0),
            pose_error_deg: RangeParam::fixed(0.0),
            pose_error_m: RangeParam::fixed(0.0),
            clock_drift_ppm: RangeParam::fixed(0.0),
            frame_jitter_ms: RangeParam::fixed(0.0),
            exposure_gain_variation: RangeParam::fixed(0.0),
            flicker: RangeParam::fixed(0.0),
            shadow_depth: RangeParam::fixed(0.0),
            arm_occludes: false,
        }
    }
}

/// `[world.robot]`: the true robot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WorldRobotParams {
    /// Command-to-motion latency, ms, per session (default: `robot.latency_ms`).
    pub latency_ms: Option<RangeParam>,
    /// Amplitude of the latency's slow drift within a session, ms (a sine of
    /// period 60..300 s and random phase), per session.
    pub latency_drift_ms: RangeParam,
    /// Natural frequency of each joint's second-order position servo, Hz
    /// (0: the first-order 5 ms lag of the truthful robot), per session.
    pub servo_natural_hz: RangeParam,
    /// Damping ratio of the servo, per session.
    pub servo_damping_ratio: RangeParam,
    /// Standard deviation of the measured joint positions' noise, rad.
    pub position_noise_rad: f64,
    /// Relative error of every link's mass and inertia against the CAD values,
    /// drawn per link and session (e.g. 0.05: within +-5%).
    pub inertia_error: f64,
    /// The joint torque limits as a fraction of KUKA's specification.
    pub torque_limit_scale: f64,
    /// Check torques from the rigid-body dynamics against the limits (trip).
    pub torque_trip: bool,
    /// The control step's own CPU time delays its reply in virtual time
    /// (not bit-for-bit deterministic then).
    pub step_time_delays_reply: bool,
    /// Fraction of the monitoring datagrams lost on the way to the PC, per session.
    pub packet_loss: RangeParam,
    /// Fraction of the command datagrams lost on the way to the robot, per session.
    pub reply_loss: RangeParam,
    /// Per-command jitter of the command-to-motion latency, uniform in
    /// `[-value, +value]` ms (bound per session): moves a command to the
    /// nearest controller cycle.
    pub command_jitter_ms: RangeParam,
    /// One-way latency of a datagram between the robot controller and the PC
    /// (each way), ms, per session.
    pub message_latency_ms: RangeParam,
    /// Extra one-way delay of each datagram, uniform in `[0, value]` ms
    /// (bound per session).
    pub message_jitter_ms: RangeParam,
    /// The drives saturate each joint's speed at this fraction of KUKA's
    /// velocity limit (0: no saturation).
    pub velocity_limit_scale: f64,
    /// The drives saturate each joint's acceleration at this fraction of the
    /// model's limits (`kinematics::iiwa7::ACCELERATION_LIMIT_RADPS2`; 0: none).
    pub acceleration_limit_scale: f64,
    /// A contact's impulse pushes the true arm (through its mass matrix);
    /// the servos pull it back.
    pub contact_push: bool,
    /// How late the robot's external torque estimate shows a contact's
    /// force (its filtering), FRI periods, per session. The measured judge's
    /// belief of it is `success.torque_lag_periods`.
    pub torque_lag_periods: RangeParam,
}

impl Default for WorldRobotParams {
    fn default() -> Self {
        Self {
            latency_ms: None,
            latency_drift_ms: RangeParam::fixed(0.0),
            servo_natural_hz: RangeParam::fixed(0.0),
            servo_damping_ratio: RangeParam::fixed(0.7),
            position_noise_rad: 0.0,
            inertia_error: 0.0,
            torque_limit_scale: 1.0,
            torque_trip: false,
            step_time_delays_reply: false,
            packet_loss: RangeParam::fixed(0.0),
            reply_loss: RangeParam::fixed(0.0),
            command_jitter_ms: RangeParam::fixed(0.0),
            message_latency_ms: RangeParam::fixed(0.0),
            message_jitter_ms: RangeParam::fixed(0.0),
            velocity_limit_scale: 0.0,
            acceleration_limit_scale: 0.0,
            contact_push: false,
            torque_lag_periods: RangeParam::fixed(1.0),
        }
    }
}

/// `[world.geometry]`: the true lab geometry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WorldGeometryParams {
    /// True intercept point (ball at rest) off the believed one, along each axis, m, per session.
    pub intercept_error_m: RangeParam,
    /// True tool length minus `task.tool_length_m`, m, per session.
    pub tool_length_error_m: RangeParam,
    /// Error of each DH link length `d_i`, m, per session.
    pub dh_length_error_m: RangeParam,
    /// Error of each joint's zero offset, degrees, per session.
    pub joint_offset_error_deg: RangeParam,
    /// Radius of the tool's contact disc (at the tool point, normal along the
    /// tool axis) the judge uses, m.
    pub contact_disc_radius_m: f64,
}

impl Default for WorldGeometryParams {
    fn default() -> Self {
        Self {
            intercept_error_m: RangeParam::fixed(0.0),
            tool_length_error_m: RangeParam::fixed(0.0),
            dh_length_error_m: RangeParam::fixed(0.0),
            joint_offset_error_deg: RangeParam::fixed(0.0),
            contact_disc_radius_m: 0.03,
        }
    }
}

/// `[world]`: the whole simulated world.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WorldParams {
    /// Sessions.
    pub sessions: SessionParams,
    /// The true pendulum.
    pub pendulum: WorldPendulumParams,
    /// The true camera.
    pub camera: WorldCameraParams,
    /// The true robot.
    pub robot: WorldRobotParams,
    /// The true geometry.
    pub geometry: WorldGeometryParams,
    /// The beliefs the world's draws are relative to: the lab's nominal values
    /// before a calibration file changed them (`CalibrationFile::apply` sets
    /// it), so that the truth stays where it is when the lab learns it. None:
    /// the scenario's own beliefs. Never read from or written to a file.
    #[serde(skip)]
    pub anchor: Option<WorldAnchor>,
}

/// The nominal beliefs a world's offsets are drawn around (see
/// [`WorldParams::anchor`]).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct WorldAnchor {
    /// Nominal pendulum length, m (true = this + the session's length error).
    pub pendulum_length_m: f64,
    /// Nominal damping, 1/s (true = this x the session's damping scale).
    pub pendulum_damping_per_s: f64,
    /// Nominal camera latency, ms (true = this + the session's offset).
    pub camera_latency_ms: f64,
}

/// Highest servo natural frequency a world may draw, Hz: the servo's sub-steps
/// shrink with it (`sim::world::robot`), and the ramp-lag law `2 zeta v / w`
/// is tested at this end (`sim::world::tests`).
pub const MAX_SERVO_NATURAL_HZ: f64 = 200.0;

/// A limit whose 0 means "none": 0, or within `[lo, hi]`.
fn off_or_within(field: &str, v: f64, lo: f64, hi: f64) -> Result<(), ParamError> {
    check::within(field, v, 0.0, hi)?;
    if v > 0.0 && v < lo {
        return Err(check::out_of_range(
            field,
            v,
            check::Bound::ZeroOrAtLeast(lo),
        ));
    }
    Ok(())
}

fn range(field: &str, r: &RangeParam, lo: f64, hi: f64) -> Result<(), ParamError> {
    r.validate_with(field, |f, v| check::within(f, v, lo, hi))
}

impl WorldParams {
    /// Checks every field; the error names the first bad one (`world.camera.latency_ms`).
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`], [`ParamError::OutOfRange`] or [`ParamError::Reversed`]
    /// naming the first field that is not finite, outside its range or a reversed range.
    pub fn validate(&self) -> Result<(), ParamError> {
        check::within_u32(
            "world.sessions.trials_per_session",
            self.sessions.trials_per_session,
            1,
            1_000_000,
        )?;
        let p = &self.pendulum;
        range(
            "world.pendulum.length_error_m",
            &p.length_error_m,
            -0.5,
            0.5,
        )?;
        range("world.pendulum.damping_scale", &p.damping_scale, 0.0, 20.0)?;
        range(
            "world.pendulum.drag_coefficient",
            &p.drag_coefficient,
            0.0,
            2.0,
        )?;
        check::within("world.pendulum.ball_mass_kg", p.ball_mass_kg, 0.001, 10.0)?;
        check::within(
            "world.pendulum.air_density_kgpm3",
            p.air_density_kgpm3,
            0.0,
            5.0,
        )?;
        range(
            "world.pendulum.pivot_friction_mps2",
            &p.pivot_friction_mps2,
            0.0,
            1.0,
        )?;
        range(
            "world.pendulum.out_of_plane_deg",
            &p.out_of_plane_deg,
            0.0,
            10.0,
        )?;
        if let Some(d) = &p.release_delay_ms {
            range("world.pendulum.release_delay_ms", d, 0.0, 500.0)?;
        }
        range(
            "world.pendulum.disturbance_mps2",
            &p.disturbance_mps2,
            0.0,
            1.0,
        )?;
        range(
            "world.pendulum.contact_pulse_ms",
            &p.contact_pulse_ms,
            0.5,
            50.0,
        )?;
        check::probability("world.pendulum.contact_restitution", p.contact_restitution)?;
        let c = &self.camera;
        range("world.camera.latency_ms", &c.latency_ms, -500.0, 500.0)?;
        range(
            "world.camera.latency_jitter_ms",
            &c.latency_jitter_ms,
            0.0,
            100.0,
        )?;
        range(
            "world.camera.rolling_shutter_ms",
            &c.rolling_shutter_ms,
            0.0,
            100.0,
        )?;
        range("world.camera.exposure_ms", &c.exposure_ms, 0.0, 100.0)?;
        range("world.camera.transfer_ms", &c.transfer_ms, 0.0, 100.0)?;
        range("world.camera.distortion_k1", &c.distortion_k1, -1.0, 1.0)?;
        range("world.camera.distortion_k2", &c.distortion_k2, -1.0, 1.0)?;
        range("world.camera.distortion_p1", &c.distortion_p1, -0.1, 0.1)?;
        range("world.camera.distortion_p2", &c.distortion_p2, -0.1, 0.1)?;
        range(
            "world.camera.pose_error_deg",
            &c.pose_error_deg,
            -10.0,
            10.0,
        )?;
        range("world.camera.pose_error_m", &c.pose_error_m, -0.5, 0.5)?;
        range(
            "world.camera.clock_drift_ppm",
            &c.clock_drift_ppm,
            -1000.0,
            1000.0,
        )?;
        range(
            "world.camera.frame_jitter_ms",
            &c.frame_jitter_ms,
            0.0,
            20.0,
        )?;
        range(
            "world.camera.exposure_gain_variation",
            &c.exposure_gain_variation,
            0.0,
            0.9,
        )?;
        range("world.camera.flicker", &c.flicker, 0.0, 0.9)?;
        range("world.camera.shadow_depth", &c.shadow_depth, 0.0, 0.95)?;
        let r = &self.robot;
        if let Some(l) = &r.latency_ms {
            range("world.robot.latency_ms", l, 0.0, 200.0)?;
        }
        range(
            "world.robot.latency_drift_ms",
            &r.latency_drift_ms,
            0.0,
            50.0,
        )?;
        range(
            "world.robot.servo_natural_hz",
            &r.servo_natural_hz,
            0.0,
            MAX_SERVO_NATURAL_HZ,
        )?;
        if r.servo_natural_hz.lo > 0.0 && r.servo_natural_hz.lo < 2.0 {
            return Err(check::out_of_range(
                "world.robot.servo_natural_hz",
                r.servo_natural_hz.lo,
                check::Bound::ZeroOrAtLeast(2.0),
            ));
        }
        range(
            "world.robot.servo_damping_ratio",
            &r.servo_damping_ratio,
            0.2,
            3.0,
        )?;
        check::within(
            "world.robot.position_noise_rad",
            r.position_noise_rad,
            0.0,
            0.01,
        )?;
        check::within("world.robot.inertia_error", r.inertia_error, 0.0, 0.5)?;
        range("world.robot.packet_loss", &r.packet_loss, 0.0, 0.5)?;
        range("world.robot.reply_loss", &r.reply_loss, 0.0, 0.5)?;
        range(
            "world.robot.command_jitter_ms",
            &r.command_jitter_ms,
            0.0,
            50.0,
        )?;
        range(
            "world.robot.message_latency_ms",
            &r.message_latency_ms,
            0.0,
            20.0,
        )?;
        range(
            "world.robot.message_jitter_ms",
            &r.message_jitter_ms,
            0.0,
            20.0,
        )?;
        range(
            "world.robot.torque_lag_periods",
            &r.torque_lag_periods,
            0.0,
            10.0,
        )?;
        off_or_within(
            "world.robot.velocity_limit_scale",
            r.velocity_limit_scale,
            0.05,
            2.0,
        )?;
        off_or_within(
            "world.robot.acceleration_limit_scale",
            r.acceleration_limit_scale,
            0.05,
            10.0,
        )?;
        check::within(
            "world.robot.torque_limit_scale",
            r.torque_limit_scale,
            0.05,
            2.0,
        )?;
        let g = &self.geometry;
        range(
            "world.geometry.intercept_error_m",
            &g.intercept_error_m,
            -0.1,
            0.1,
        )?;
        range(
            "world.geometry.tool_length_error_m",
            &g.tool_length_error_m,
            -0.05,
            0.05,
        )?;
        range(
            "world.geometry.dh_length_error_m",
            &g.dh_length_error_m,
            -0.01,
            0.01,
        )?;
        range(
            "world.geometry.joint_offset_error_deg",
            &g.joint_offset_error_deg,
            -2.0,
            2.0,
        )?;
        check::within(
            "world.geometry.contact_disc_radius_m",
            g.contact_disc_radius_m,
            0.001,
            0.3,
        )
    }

    /// Session of trial `index`.
    pub fn session_of(&self, index: usize) -> u64 {
        (index as u64) / u64::from(self.sessions.trials_per_session.max(1))
    }
}

/// Values drawn once per session (one "reboot" of the lab).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SessionDraw {
    /// Session number.
    pub session: u64,
    /// True length minus believed, m.
    pub length_error_m: f64,
    /// Linear damping multiple.
    pub damping_scale: f64,
    /// Drag coefficient.
    pub drag_coefficient: f64,
    /// Pivot friction, m/s^2.
    pub pivot_friction_mps2: f64,
    /// Camera latency minus believed, s.
    pub camera_latency_offset_s: f64,
    /// Per-frame jitter bound, s.
    pub camera_jitter_s: f64,
    /// Rolling shutter readout, s.
    pub rolling_shutter_s: f64,
    /// Exposure, s.
    pub exposure_s: f64,
    /// Readout end -> delivery at the least, s.
    pub transfer_s: f64,
    /// Distortion `[k1, k2, p1, p2]`.
    pub distortion: [f64; 4],
    /// Camera rotation error about base x, y, z, rad.
    pub camera_rotation_error_rad: [f64; 3],
    /// Camera position error, m.
    pub camera_position_error_m: [f64; 3],
    /// Robot latency at the session's start, s.
    pub robot_latency_s: f64,
    /// Drift amplitude, s.
    pub robot_drift_s: f64,
    /// Drift period, s.
    pub robot_drift_period_s: f64,
    /// Drift phase, rad.
    pub robot_drift_phase_rad: f64,
    /// Servo natural frequency, rad/s (0: first-order lag).
    pub servo_omega_radps: f64,
    /// Servo damping ratio.
    pub servo_damping_ratio: f64,
    /// Per-link mass/inertia factor (1 = CAD).
    pub inertia_factor: [f64; 8],
    /// Intercept point error, m.
    pub intercept_error_m: [f64; 3],
    /// Tool length error, m.
    pub tool_length_error_m: f64,
    /// DH `d_i` errors, m.
    pub dh_length_error_m: [f64; 7],
    /// Joint zero-offset errors, rad.
    pub joint_offset_error_rad: [f64; 7],
    /// Camera clock rate error, fraction (ppm x 1e-6).
    pub camera_clock_drift: f64,
    /// Exposure-start jitter bound, s.
    pub frame_jitter_s: f64,
    /// Auto-exposure gain amplitude, fraction.
    pub exposure_gain_variation: f64,
    /// Auto-exposure period, s.
    pub exposure_gain_period_s: f64,
    /// Auto-exposure phase, rad.
    pub exposure_gain_phase_rad: f64,
    /// Mains flicker amplitude, fraction.
    pub flicker: f64,
    /// Depth of a passing shadow, fraction of the light (0: none).
    pub shadow_depth: f64,
    /// Seed of the shadows' schedule.
    pub shadow_seed: u64,
    /// Monitoring datagram loss, fraction.
    pub packet_loss: f64,
    /// Command datagram loss, fraction.
    pub reply_loss: f64,
    /// Per-command latency jitter bound, s.
    pub command_jitter_s: f64,
    /// One-way datagram latency, s.
    pub message_latency_s: f64,
    /// One-way datagram jitter bound, s.
    pub message_jitter_s: f64,
    /// The external torque estimate's lag behind a contact's force, FRI periods.
    pub torque_lag_periods: f64,
    /// A contact's force pulse, s.
    pub contact_pulse_s: f64,
}

/// Values drawn per trial.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrialWorldDraw {
    /// Out-of-plane angle at release (signed), rad.
    pub out_of_plane_rad: f64,
    /// Delay pin -> drop, s.
    pub release_delay_s: f64,
    /// Disturbance standard deviation, m/s^2.
    pub disturbance_mps2: f64,
    /// Seed of the trial's own world noise (jitter, disturbances, joint noise).
    pub seed: u64,
}

const SESSION_STREAM: u64 = 0x7365_7373_696f_6e00;
const TRIAL_STREAM: u64 = 0x776f_726c_6474_7269;

fn mix(seed: u64, index: u64, stream: u64) -> u64 {
    seed.wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(index.wrapping_mul(0xD1B5_4A32_D192_ED03))
        ^ stream
}

fn pick(r: &RangeParam, rng: &mut ChaCha8Rng) -> f64 {
    // Always one draw per key, so adding a range elsewhere does not shift the others.
    let u: f64 = rng.random_range(0.0..=1.0);
    r.lerp(u)
}

impl WorldParams {
    /// The draws of session `session` of a run with `seed`, for a lab whose
    /// believed robot latency is `believed_robot_latency_ms`.
    pub fn draw_session(
        &self,
        seed: u64,
        session: u64,
        believed_robot_latency_ms: f64,
    ) -> SessionDraw {
        let mut rng = ChaCha8Rng::seed_from_u64(mix(seed, session, SESSION_STREAM));
        let p = &self.pendulum;
        let c = &self.camera;
        let r = &self.robot;
        let g = &self.geometry;
        let length_error_m = pick(&p.length_error_m, &mut rng);
        let damping_scale = pick(&p.damping_scale, &mut rng);
        let drag_coefficient = pick(&p.drag_coefficient, &mut rng);
        let pivot_friction_mps2 = pick(&p.pivot_friction_mps2, &mut rng);
        let camera_latency_offset_s = pick(&c.latency_ms, &mut rng) * 1e-3;
        let camera_jitter_s = pick(&c.latency_jitter_ms, &mut rng) * 1e-3;
        let rolling_shutter_s = pick(&c.rolling_shutter_ms, &mut rng) * 1e-3;
        let exposure_s = pick(&c.exposure_ms, &mut rng) * 1e-3;
        let distortion = [
            pick(&c.distortion_k1, &mut rng),
            pick(&c.distortion_k2, &mut rng),
            pick(&c.distortion_p1, &mut rng),
            pick(&c.distortion_p2, &mut rng),
        ];
        let mut camera_rotation_error_rad = [0.0; 3];
        for v in &mut camera_rotation_error_rad {
            *v = pick(&c.pose_error_deg, &mut rng).to_radians();
        }
        let mut camera_position_error_m = [0.0; 3];
        for v in &mut camera_position_error_m {
            *v = pick(&c.pose_error_m, &mut rng);
        }
        let lat = r
            .latency_ms
            .unwrap_or(RangeParam::fixed(believed_robot_latency_ms));
        let robot_latency_s = pick(&lat, &mut rng) * 1e-3;
        let robot_drift_s = pick(&r.latency_drift_ms, &mut rng) * 1e-3;
        let robot_drift_period_s = rng.random_range(60.0..=300.0);
        let robot_drift_phase_rad = rng.random_range(0.0..std::f64::consts::TAU);
        let servo_omega_radps = pick(&r.servo_natural_hz, &mut rng) * std::f64::consts::TAU;
        let servo_damping_ratio = pick(&r.servo_damping_ratio, &mut rng);
        let mut inertia_factor = [1.0; 8];
        for v in &mut inertia_factor {
            *v = 1.0 + r.inertia_error * rng.random_range(-1.0..=1.0);
        }
        let mut intercept_error_m = [0.0; 3];
        for v in &mut intercept_error_m {
            *v = pick(&g.intercept_error_m, &mut rng);
        }
        let tool_length_error_m = pick(&g.tool_length_error_m, &mut rng);
        let mut dh_length_error_m = [0.0; 7];
        for v in &mut dh_length_error_m {
            *v = pick(&g.dh_length_error_m, &mut rng);
        }
        let mut joint_offset_error_rad = [0.0; 7];
        for v in &mut joint_offset_error_rad {
            *v = pick(&g.joint_offset_error_deg, &mut rng).to_radians();
        }
        // Keys added later draw after the earlier ones: their draws stay.
        let camera_clock_drift = pick(&c.clock_drift_ppm, &mut rng) * 1e-6;
        let frame_jitter_s = pick(&c.frame_jitter_ms, &mut rng) * 1e-3;
        let exposure_gain_variation = pick(&c.exposure_gain_variation, &mut rng);
        let exposure_gain_period_s = rng.random_range(4.0..=20.0);
        let exposure_gain_phase_rad = rng.random_range(0.0..std::f64::consts::TAU);
        let flicker = pick(&c.flicker, &mut rng);
        let shadow_depth = pick(&c.shadow_depth, &mut rng);
        let shadow_seed = rng.random();
        let packet_loss = pick(&r.packet_loss, &mut rng);
        let reply_loss = pick(&r.reply_loss, &mut rng);
        let command_jitter_s = pick(&r.command_jitter_ms, &mut rng) * 1e-3;
        let message_latency_s = pick(&r.message_latency_ms, &mut rng) * 1e-3;
        let message_jitter_s = pick(&r.message_jitter_ms, &mut rng) * 1e-3;
        let torque_lag_periods = pick(&r.torque_lag_periods, &mut rng);
        let contact_pulse_s = pick(&p.contact_pulse_ms, &mut rng) * 1e-3;
        let transfer_s = pick(&c.transfer_ms, &mut rng) * 1e-3;
        SessionDraw {
            session,
            length_error_m,
            damping_scale,
            drag_coefficient,
            pivot_friction_mps2,
            camera_latency_offset_s,
            camera_jitter_s,
            rolling_shutter_s,
            exposure_s,
            transfer_s,
            distortion,
            camera_rotation_error_rad,
            camera_position_error_m,
            robot_latency_s,
            robot_drift_s,
            robot_drift_period_s,
            robot_drift_phase_rad,
            servo_omega_radps,
            servo_damping_ratio,
            inertia_factor,
            intercept_error_m,
            tool_length_error_m,
            dh_length_error_m,
            joint_offset_error_rad,
            camera_clock_drift,
            frame_jitter_s,
            exposure_gain_variation,
            exposure_gain_period_s,
            exposure_gain_phase_rad,
            flicker,
            shadow_depth,
            shadow_seed,
            packet_loss,
            reply_loss,
            command_jitter_s,
            message_latency_s,
            message_jitter_s,
            torque_lag_periods,
            contact_pulse_s,
        }
    }

    /// The draws of trial `index` of a run with `seed`, for a lab whose
    /// believed release delay is `believed_release_delay_ms`.
    pub fn draw_trial(
        &self,
        seed: u64,
        index: usize,
        believed_release_delay_ms: f64,
    ) -> TrialWorldDraw {
        let mut rng = ChaCha8Rng::seed_from_u64(mix(seed, index as u64, TRIAL_STREAM));
        let p = &self.pendulum;
        let oop = pick(&p.out_of_plane_deg, &mut rng).to_radians();
        let sign = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
        let release_delay_s = pick(
            &p.release_delay_ms
                .unwrap_or(RangeParam::fixed(believed_release_delay_ms)),
            &mut rng,
        ) * 1e-3;
        let disturbance_mps2 = pick(&p.disturbance_mps2, &mut rng);
        TrialWorldDraw {
            out_of_plane_rad: sign * oop,
            release_delay_s,
            disturbance_mps2,
            seed: rng.random(),
        }
    }
}
