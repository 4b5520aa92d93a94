//! The calibration procedures run on a simulated world: the hidden truth
//! ([`HiddenWorld`]) goes to the simulators only (the pendulum, the rendered
//! camera, the simulated KUKA controller); the procedures see what a real lab's
//! would see (frames, detections, FRI messages, the firmware's answers) and hand it
//! to the pure fits. Each run returns the truth beside the estimate so the caller
//! can report the error.
//!
//! Until the scenario's `[world]` (CONTRACT.md) is available, the truth is drawn
//! here from a seed, around the scenario's beliefs (`HiddenWorld::draw`).

use nalgebra::{Rotation3, Vector3};
use opencv::{
    core::{self, Mat, MatTraitConst, Point, Rect, Scalar},
    imgproc,
};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::file::PendulumCalibration;
use super::latency::{LedEdge, LedFrame};
use super::robot::JointSample;
use super::swing::{mean_std, principal_angle_deg};
use super::view::{StepView, ViewKind, Watch, thin};
use super::{
    CalibrationError, LedLatency, RobotLatency, SwingSample, estimate_led_latency,
    fit_robot_latency, fit_swing,
};
use crate::fri::{
    ControlStep, FriClient, FriClientParams, Joints, LinkState, SessionState, StepInput,
};
use crate::params::Scenario;
use crate::pendulum::{PendulumGeometry, PendulumModel, PendulumSim};
use crate::sim::camera::{BallState, SimCamera, SimCameraParams, SimVision};
use crate::sim::kuka::{FriSimParams, SimController};
use crate::sim::world::camera::WorldCamera;
use crate::vision::{CameraIntrinsics, DetectorParams, SwingPlaneCalibration};

pub use super::procedure::ProcedureError;

/// The simulated lab as it is (the simulators' side only).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HiddenWorld {
    /// True pendulum length minus the believed one, metres (the pivot is where the
    /// lab believes; a longer string hangs the ball lower).
    pub length_error_m: f64,
    /// True viscous damping, 1/s.
    pub damping_per_s: f64,
    /// True mean capture -> delivery latency of the camera, ms.
    pub camera_latency_ms: f64,
    /// True command -> setpoint delay of the robot, ms.
    pub robot_latency_ms: f64,
    /// Uniform jitter of that delay, +- ms.
    pub robot_latency_jitter_ms: f64,
    /// True first-order servo lag of the joints, ms.
    pub servo_time_constant_ms: f64,
    /// The true camera's lens: Brown-Conrady `[k1, k2, p1, p2]` (the lab believes
    /// none until the camera step).
    #[serde(default)]
    pub distortion: [f64; 4],
    /// The true camera's rotation off the believed pose, about base x, y, z, rad.
    #[serde(default)]
    pub camera_rotation_error_rad: [f64; 3],
    /// The true camera's position off the believed pose, base frame, m.
    #[serde(default)]
    pub camera_position_error_m: [f64; 3],
    /// Rolling shutter readout, top row to bottom row, ms.
    #[serde(default)]
    pub rolling_shutter_ms: f64,
    /// Exposure, ms.
    #[serde(default)]
    pub exposure_ms: f64,
    /// Per-frame delivery jitter bound (uniform, added to the latency), ms.
    #[serde(default)]
    pub camera_jitter_ms: f64,
    /// The true intercept point (the hanging ball's rest point) minus the believed
    /// one, base frame, m.
    #[serde(default)]
    pub intercept_error_m: [f64; 3],
}

impl HiddenWorld {
    /// A session's truth. With the scenario's `[world]`: its session 0 of run
    /// `seed` (`WorldParams::draw_session`) gives the length error, the damping
    /// (believed times `damping_scale`), the camera latency (believed + offset +
    /// half the uniform jitter bound: the mean) and the robot latency at the
    /// session's start; the effects these simulators do not model yet (drag, pivot
    /// friction, out-of-plane release, rolling shutter, distortion, camera pose
    /// error, latency drift, the second-order servo) are left out, and the servo
    /// lag is drawn here. Without `[world]`: drawn from `seed` around the beliefs:
    /// length +-6 cm, damping 0.01..0.06 /s, camera latency belief -10..+30 ms (at
    /// least 5 ms), robot latency 3..30 ms with the scenario's jitter, servo lag
    /// 3..12 ms.
    pub fn draw(scenario: &Scenario, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5ca1_1b0a);
        if let Some(world) = &scenario.world {
            let d = world.draw_session(seed, 0, scenario.robot.latency_ms);
            return Self {
                length_error_m: d.length_error_m,
                damping_per_s: scenario.pendulum.damping_per_s * d.damping_scale,
                camera_latency_ms: (scenario.camera.latency_ms
                    + (d.camera_latency_offset_s + 0.5 * d.camera_jitter_s) * 1e3)
                    .max(1.0),
                robot_latency_ms: (d.robot_latency_s * 1e3).clamp(0.0, 200.0),
                robot_latency_jitter_ms: 0.0,
                servo_time_constant_ms: rng.random_range(3.0..=12.0),
                distortion: d.distortion,
                camera_rotation_error_rad: d.camera_rotation_error_rad,
                camera_position_error_m: d.camera_position_error_m,
                rolling_shutter_ms: d.rolling_shutter_s * 1e3,
                exposure_ms: d.exposure_s * 1e3,
                camera_jitter_ms: d.camera_jitter_s * 1e3,
                intercept_error_m: d.intercept_error_m,
            };
        }
        Self {
            length_error_m: rng.random_range(-0.06..=0.06),
            damping_per_s: rng.random_range(0.01..=0.06),
            camera_latency_ms: (scenario.camera.latency_ms + rng.random_range(-10.0..=30.0))
                .max(5.0),
            robot_latency_ms: rng.random_range(3.0..=30.0),
            robot_latency_jitter_ms: scenario
                .robot
                .latency_jitter_ms
                .min(rng.random_range(3.0..=30.0)),
            servo_time_constant_ms: rng.random_range(3.0..=12.0),
            ..Self::truthful(scenario)
        }
    }

    /// The truthful world: everything as the scenario believes.
    pub fn truthful(scenario: &Scenario) -> Self {
        Self {
            length_error_m: 0.0,
            damping_per_s: scenario.pendulum.damping_per_s,
            camera_latency_ms: scenario.camera.latency_ms,
            robot_latency_ms: scenario.robot.latency_ms,
            robot_latency_jitter_ms: scenario.robot.latency_jitter_ms,
            servo_time_constant_ms: 5.0,
            distortion: [0.0; 4],
            camera_rotation_error_rad: [0.0; 3],
            camera_position_error_m: [0.0; 3],
            rolling_shutter_ms: 0.0,
            exposure_ms: 0.0,
            camera_jitter_ms: 0.0,
            intercept_error_m: [0.0; 3],
        }
    }

    /// The true camera of this world around the lab's believed one (pose and
    /// intrinsics as the lab believes them, no distortion): its lens, pose error,
    /// rolling shutter, exposure and latency (`sim::world::camera`). A procedure
    /// projects through it what a real camera would show; the true latency is
    /// `camera_latency_ms`, whose mean includes half the jitter bound.
    pub fn world_camera(&self, scenario: &Scenario) -> WorldCamera {
        let cam = SimCameraParams::default();
        let intrinsics = CameraIntrinsics::from_hfov(
            scenario.camera.width_px,
            scenario.camera.height_px,
            cam.hfov_deg,
        );
        let believed_latency_s = scenario.camera.latency_ms * 1e-3;
        let mut c = WorldCamera::truthful(
            cam.pose,
            intrinsics,
            scenario.camera.height_px,
            believed_latency_s,
        );
        let [rx, ry, rz] = self.camera_rotation_error_rad;
        c.base_from_camera = Rotation3::from_euler_angles(rx, ry, rz) * c.base_from_camera;
        c.position_m += Vector3::from(self.camera_position_error_m);
        c.distortion = self.distortion;
        c.rolling_shutter_s = self.rolling_shutter_ms * 1e-3;
        c.exposure_s = self.exposure_ms * 1e-3;
        c.jitter_s = self.camera_jitter_ms * 1e-3;
        c.latency_offset_s =
            (self.camera_latency_ms - 0.5 * self.camera_jitter_ms) * 1e-3 - believed_latency_s;
        c
    }
}

/// The believed rest point (the intercept point at the near end of the distances).
fn believed_rest(s: &Scenario) -> Vector3<f64> {
    Vector3::new(s.task.distance_m.lo, 0.0, s.task.intercept_height_m)
}

/// The camera as it really is (the truth's latency), with the lab's pose.
fn true_camera(s: &Scenario, w: &HiddenWorld, seed: u64) -> Result<SimCamera, ProcedureError> {
    let mut camera = s.camera.clone();
    camera.latency_ms = w.camera_latency_ms;
    Ok(SimCamera::new(
        &camera,
        &SimCameraParams::default(),
        s.pendulum.ball_radius_m,
        seed,
    )?)
}

/// The pendulum step on the simulated world, with the truth beside the result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PendulumRun {
    /// What the step measured.
    pub calibration: PendulumCalibration,
    /// The true length, metres.
    pub true_length_m: f64,
    /// The true damping, 1/s.
    pub true_damping_per_s: f64,
    /// The true rest point (intercept point), base frame, metres.
    pub true_rest_m: [f64; 3],
    /// Where the procedure puts the rest point in the base frame: the rest
    /// detection's ray met with the swing plane (`x` = the believed distance), metres.
    pub rest_m: [f64; 3],
}

/// Frames averaged for the rest point.
const REST_FRAMES: usize = 30;

/// The pendulum step: the hanging ball's rest point (30 frames), then a free swing
/// released from `release_deg` recorded for `duration_s` and fitted.
///
/// # Errors
///
/// [`ProcedureError::Params`] for an invalid scenario;
/// [`ProcedureError::BallNotFound`] when the hanging ball is found in too few
/// frames; [`ProcedureError::RayMissesSwingPlane`]; [`ProcedureError::Pendulum`]
/// when the simulated pendulum refuses; [`ProcedureError::Calibration`] when the
/// swing fit refuses; [`ProcedureError::Vision`] from the camera.
pub fn run_pendulum(
    scenario: &Scenario,
    world: &HiddenWorld,
    seed: u64,
    release_deg: f64,
    duration_s: f64,
    watch: &mut dyn Watch,
) -> Result<PendulumRun, ProcedureError> {
    scenario.validate()?;
    let p = &scenario.pendulum;
    let rest_b = believed_rest(scenario);
    let true_length = p.length_m + world.length_error_m;
    let model = PendulumModel {
        length_m: true_length,
        gravity_mps2: p.gravity_mps2,
        damping_per_s: world.damping_per_s,
    };
    // The pivot stays where the lab believes it; the ball hangs at the true length.
    let geometry =
        PendulumGeometry::new(true_length, rest_b.x, rest_b.z + p.length_m - true_length)?;
    let cam = true_camera(scenario, world, seed)?;
    // What the lab believes: the camera's mounting and the believed rest point.
    let calibration = SwingPlaneCalibration::from_pose(
        *cam.intrinsics(),
        &SimCameraParams::default().pose,
        &rest_b,
        p.ball_radius_m,
    );
    let mut vision = SimVision::new(cam, DetectorParams::default(), calibration)?;
    let period = vision.frame_period_s();

    // 1. The hanging ball.
    let rest_true = geometry.rest_position_m();
    let at_rest = BallState {
        centre_m: rest_true,
        velocity_mps: Vector3::zeros(),
    };
    let mut rest = Vec::with_capacity(REST_FRAMES);
    for k in 0..REST_FRAMES * 2 {
        if rest.len() >= REST_FRAMES {
            break;
        }
        if let Some(m) = vision.capture(period * k as f64, Some(&at_rest))?
            && m.found
        {
            rest.push((m.x_px, m.y_px));
        }
    }
    if rest.len() < REST_FRAMES / 2 {
        return Err(ProcedureError::BallNotFound {
            found: rest.len(),
            frames: REST_FRAMES * 2,
        });
    }
    let (mu, mv, su, sv) = mean_std(&rest);
    watch.seen(StepView {
        progress: 0.05,
        message: format!(
            "hanging ball found in {} frames at ({mu:.1}, {mv:.1}) px",
            rest.len()
        ),
        kind: ViewKind::Image,
        points: rest.iter().map(|&(u, v)| [u, v]).collect(),
        fit: vec![[mu, mv]],
    });
    let rest_c = calibration
        .point_on_plane_c(mu, mv)
        .ok_or(ProcedureError::RayMissesSwingPlane)?;
    let pose = SimCameraParams::default().pose;
    let rest_m_b = pose.base_from_camera() * rest_c + pose.position();

    // 2. The free swing.
    let t_release = 2.0 * REST_FRAMES as f64 * period + 0.5;
    let mut sim = PendulumSim::held_at(model, geometry, release_deg.to_radians(), t_release)?;
    sim.release(t_release)?;
    vision.set_calibration(calibration);
    let mut samples = Vec::new();
    let mut track = Vec::new();
    let start = t_release + 0.2;
    let frames = (duration_s / period).floor() as usize;
    for k in 0..frames {
        let t = start + period * k as f64;
        sim.advance_to(t)?;
        let ball = BallState {
            centre_m: sim.ball_position_m(),
            velocity_mps: sim.ball_velocity_mps(),
        };
        if let Some(m) = vision.capture(t, Some(&ball))?
            && m.found
        {
            samples.push(SwingSample {
                t_s: m.t_capture_s,
                lateral_m: m.lateral_m,
            });
            track.push((m.x_px, m.y_px));
        }
        if (k + 1) % 60 == 0 {
            watch.seen(swing_view(
                0.05 + 0.85 * (k + 1) as f64 / frames.max(1) as f64,
                format!(
                    "free swing: {:.1} of {duration_s:.0} s recorded",
                    (k + 1) as f64 * period
                ),
                &samples,
                Vec::new(),
            ));
        }
    }
    let swing = fit_swing(&samples, p.gravity_mps2, p.length_m)?;
    let fitted = swing_curve(&swing, &samples, p.gravity_mps2);
    watch.seen(swing_view(
        1.0,
        format!(
            "fitted: length {:.4} m, damping {:.4} /s, residual {:.2} mm",
            swing.length_m,
            swing.damping_per_s,
            swing.residual_rms_m * 1e3
        ),
        &samples,
        fitted,
    ));
    Ok(PendulumRun {
        calibration: PendulumCalibration {
            swing,
            rest_px: [mu, mv],
            rest_std_px: [su, sv],
            swing_image_angle_deg: principal_angle_deg(&track),
        },
        true_length_m: true_length,
        true_damping_per_s: world.damping_per_s,
        true_rest_m: rest_true.into(),
        rest_m: rest_m_b.into(),
    })
}

/// Samples as `[t, lateral m]` for the live view (at most 400).
fn swing_view(
    progress: f64,
    message: String,
    samples: &[SwingSample],
    fit: Vec<[f64; 2]>,
) -> StepView {
    let points: Vec<[f64; 2]> = samples.iter().map(|s| [s.t_s, s.lateral_m]).collect();
    StepView {
        progress,
        message,
        kind: ViewKind::Series,
        points: thin(&points, 400),
        fit,
    }
}

/// The fitted swing at 400 times over the samples (the model `fit_swing` fits:
/// the damped nonlinear pendulum from its fitted start state).
fn swing_curve(fit: &super::SwingFit, samples: &[SwingSample], g: f64) -> Vec<[f64; 2]> {
    let (Some(first), Some(last)) = (samples.first(), samples.last()) else {
        return Vec::new();
    };
    let model = PendulumModel {
        length_m: fit.length_m,
        gravity_mps2: g,
        damping_per_s: fit.damping_per_s,
    };
    let mut state = crate::pendulum::PendulumState::new(fit.start_angle_rad, fit.start_rate_radps);
    let dt = ((last.t_s - first.t_s) / 400.0).max(1e-3);
    (0..=400)
        .map(|i| {
            if i > 0 {
                state = model.integrate(state, dt, 2e-3, 0.0);
            }
            [
                first.t_s + dt * f64::from(i),
                fit.length_m * state[0].sin() + fit.rest_offset_m,
            ]
        })
        .collect()
}

/// The camera latency step on the simulated world.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LatencyRun {
    /// What the step measured.
    pub result: LedLatency,
    /// The true mean latency, ms: in a world with the true camera's timing, from
    /// the middle of the hanging ball's exposure (its row down the rolling
    /// shutter) to the frame's delivery (what the stamps need); otherwise from
    /// the middle of the exposure.
    pub true_latency_ms: f64,
    /// Where the LED was found in the image, pixels.
    pub led_px: [f64; 2],
}

/// The LED's radius in the image, pixels, and its housing's half size.
const LED_RADIUS_PX: i32 = 4;
const LED_HOUSING_PX: i32 = 9;
/// The serial link: 115200 baud, 10 bits a byte.
const SERIAL_BYTE_S: f64 = 10.0 / 115_200.0;

/// The camera latency step: the LED (beside the pendulum, in view) switched
/// `switches` times at random phases; each frame rendered with the LED lit for the
/// part of its exposure it was on; the LED found by an on/off difference image; the
/// brightness of its region read from every frame. `led_in_view = false` covers
/// the LED (the step must then refuse).
///
/// # Errors
///
/// [`ProcedureError::Params`] for an invalid scenario;
/// [`ProcedureError::Calibration`] with [`CalibrationError::LedNotSeen`] when the
/// LED is not found (e.g. `led_in_view = false`) or when [`estimate_led_latency`]
/// refuses; [`ProcedureError::Vision`] when rendering or an OpenCV call fails.
pub fn run_led_latency(
    scenario: &Scenario,
    world: &HiddenWorld,
    seed: u64,
    switches: usize,
    led_in_view: bool,
    watch: &mut dyn Watch,
) -> Result<LatencyRun, ProcedureError> {
    scenario.validate()?;
    let mut cam = true_camera(scenario, world, seed)?;
    let period = 1.0 / scenario.camera.fps;
    // The LED sits on the magnet's stand beside the swing, 0.35 m to the robot's
    // right, at the hanging ball's height (a rolling shutter reads each row at
    // its own time: the LED's row is the ball's).
    let led_b = believed_rest(scenario) + Vector3::new(0.0, -0.35, 0.0);
    // A world with the true camera's timing (`[world]`): frames start on the
    // frame clock, rows are read down the readout, the exposure is the world's,
    // delivery is the frame start plus the true latency and its jitter; the LED
    // is where the true camera (pose, lens) sees it.
    let true_cam = world.world_camera(scenario);
    let world_timing =
        world.rolling_shutter_ms > 0.0 || world.exposure_ms > 0.0 || world.camera_jitter_ms > 0.0;
    let exposure_s = if world_timing {
        world.exposure_ms.max(0.1) * 1e-3
    } else {
        SimCameraParams::default().exposure_ms * 1e-3
    };
    let led_true_px = if world_timing {
        true_cam.project(&led_b).map(|p| (p.x, p.y))
    } else {
        cam.project(&led_b).map(|b| (b.x_px, b.y_px))
    };
    let height = f64::from(scenario.camera.height_px);
    let row_s = |v: f64| v.clamp(0.0, height) / height * world.rolling_shutter_ms * 1e-3;
    let led_at = match (led_in_view, led_true_px) {
        (true, Some((x, y))) => Some(Point::new(x.round() as i32, y.round() as i32)),
        _ => None,
    };
    let draw = |img: &Mat, lit: f64, at: Option<Point>| -> Result<Mat, ProcedureError> {
        let mut m = img.try_clone()?;
        if let Some(c) = at {
            let h = LED_HOUSING_PX;
            imgproc::rectangle(
                &mut m,
                Rect::new(c.x - h, c.y - h, 2 * h + 1, 2 * h + 1),
                Scalar::all(25.0),
                -1,
                imgproc::LINE_8,
                0,
            )?;
            let v = 25.0 + 225.0 * lit.clamp(0.0, 1.0);
            imgproc::circle(
                &mut m,
                c,
                LED_RADIUS_PX,
                Scalar::new(v * 0.9, v * 0.9, v, 0.0),
                -1,
                imgproc::LINE_AA,
                0,
            )?;
        }
        Ok(m)
    };
    // 1. Find the LED: three frames with it on and three with it off (the host
    //    waits half a second after each switch), the difference of their means,
    //    high-passed (lighting changes between frames are smooth, the LED is a
    //    spot), its brightest point.
    let mut sum_on = Mat::default();
    let mut sum_off = Mat::default();
    for (lit, sum) in [(1.0, &mut sum_on), (0.0, &mut sum_off)] {
        for _ in 0..3 {
            let img = draw(cam.render(None)?, lit, led_at)?;
            let mut gray = Mat::default();
            imgproc::cvt_color_def(&img, &mut gray, imgproc::COLOR_BGR2GRAY)?;
            let mut f = Mat::default();
            gray.convert_to_def(&mut f, core::CV_32F)?;
            if sum.empty() {
                *sum = f;
            } else {
                let mut acc = Mat::default();
                core::add_def(&*sum, &f, &mut acc)?;
                *sum = acc;
            }
        }
    }
    let mut diff = Mat::default();
    core::subtract_def(&sum_on, &sum_off, &mut diff)?;
    let mut smooth = Mat::default();
    imgproc::blur_def(&diff, &mut smooth, core::Size::new(41, 41))?;
    let mut spot = Mat::default();
    core::subtract_def(&diff, &smooth, &mut spot)?;
    let mut blurred = Mat::default();
    imgproc::gaussian_blur_def(&spot, &mut blurred, core::Size::new(5, 5), 0.0)?;
    let (mut max_v, mut max_at) = (0.0, Point::default());
    core::min_max_loc(
        &blurred,
        None,
        Some(&mut max_v),
        None,
        Some(&mut max_at),
        &core::no_array(),
    )?;
    // Sums of three frames: a spot at least MIN_CONTRAST grey levels brighter.
    if max_v < 3.0 * super::latency::MIN_CONTRAST {
        return Err(CalibrationError::LedNotSeen { edges: 2, seen: 0 }.into());
    }
    let roi = Rect::new((max_at.x - 2).max(0), (max_at.y - 2).max(0), 5, 5);
    watch.seen(StepView {
        progress: 0.1,
        message: format!("LED found at ({}, {}) px", max_at.x, max_at.y),
        kind: ViewKind::Image,
        points: vec![[f64::from(max_at.x), f64::from(max_at.y)]],
        fit: Vec::new(),
    });

    // 2. The frame grid: capture times and delivery (true latency) drawn up front;
    //    the host sees the first second of deliveries before it plans the switches.
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x1ed);
    let phase = rng.random_range(0.0..period);
    let span_s = 1.0 + (switches as f64 + 2.0) * 8.0 * period + 1.0;
    let mut grid = Vec::new();
    let mut k = 0u64;
    loop {
        let t_c = phase + period * k as f64;
        k += 1;
        if t_c > span_s {
            break;
        }
        if cam.next_dropped() {
            continue;
        }
        if world_timing {
            // t_c is the frame's start; the LED's row is exposed from
            // t_c + row time, for the exposure; the grid holds its middle.
            let led_mid = t_c + led_true_px.map_or(0.0, |p| row_s(p.1)) + 0.5 * exposure_s;
            let jitter = world.camera_jitter_ms * 1e-3;
            let delivered = t_c
                + (world.camera_latency_ms * 1e-3 - 0.5 * jitter).max(0.0)
                + rng.random_range(0.0..=jitter);
            grid.push((led_mid, delivered));
        } else {
            grid.push((t_c, t_c + cam.next_latency_s()));
        }
    }
    let early: Vec<f64> = grid.iter().map(|g| g.1).take_while(|&t| t < 1.0).collect();
    // 3. The switches at stratified random phases; the serial command's delay in
    //    and the answer's delay out (bytes at 115200 baud plus the firmware's reaction).
    let sends =
        super::latency::plan_switches(&early, period, switches, || rng.random_range(0.0..1.0));
    let mut edges = Vec::with_capacity(switches);
    let mut switch_at = Vec::with_capacity(switches);
    for (i, &t) in sends.iter().enumerate() {
        // "LED ON\n" in, "OK LED led=on uptime_ms=123456\r\n" out; the USB and
        // firmware latency each way.
        let (wire_in, wire_out) = (7.0 * SERIAL_BYTE_S, 30.0 * SERIAL_BYTE_S);
        let d_in = wire_in + rng.random_range(0.0002..0.0015);
        let d_out = wire_out + rng.random_range(0.0002..0.0015);
        edges.push(LedEdge {
            t_sent_s: t,
            round_trip_s: d_in + d_out,
            command_wire_s: wire_in,
            answer_wire_s: wire_out,
            on: i % 2 == 0,
        });
        switch_at.push((t + d_in, i % 2 == 0));
    }
    let lit_fraction = |t_mid: f64| -> f64 {
        let (a, b) = (t_mid - 0.5 * exposure_s, t_mid + 0.5 * exposure_s);
        let mut state = false;
        let mut last = a;
        let mut lit = 0.0;
        for &(ts, on) in &switch_at {
            if ts <= a {
                state = on;
                continue;
            }
            if ts >= b {
                break;
            }
            if state {
                lit += ts - last;
            }
            last = ts;
            state = on;
        }
        if state {
            lit += b - last;
        }
        lit / exposure_s
    };

    // 4. The frames, each rendered with the LED as lit over its exposure.
    let mut frames = Vec::with_capacity(grid.len());
    let brightness_view = |frames: &[LedFrame], progress: f64, message: String| StepView {
        progress,
        message,
        kind: ViewKind::Series,
        points: thin(
            &frames
                .iter()
                .map(|f| [f.t_delivered_s, f.brightness])
                .collect::<Vec<_>>(),
            600,
        ),
        fit: Vec::new(),
    };
    for (i, &(t_c, t_d)) in grid.iter().enumerate() {
        if i % 60 == 59 {
            watch.seen(brightness_view(
                &frames,
                0.1 + 0.85 * i as f64 / grid.len().max(1) as f64,
                format!("LED brightness in {} of {} frames", i, grid.len()),
            ));
        }
        let img = draw(cam.render(None)?, lit_fraction(t_c), led_at)?;
        let mut sub = Mat::default();
        imgproc::cvt_color_def(&Mat::roi(&img, roi)?, &mut sub, imgproc::COLOR_BGR2GRAY)?;
        let brightness = core::mean(&sub, &core::no_array())?[0];
        frames.push(LedFrame {
            t_delivered_s: t_d,
            brightness,
        });
    }
    frames.sort_by(|a, b| a.t_delivered_s.total_cmp(&b.t_delivered_s));
    let result = estimate_led_latency(&frames, &edges, period)?;
    let mut done = brightness_view(
        &frames,
        1.0,
        format!(
            "latency {:.2} ms (+-{:.2} ms), {} of {} switches seen",
            result.latency_ms, result.bound_ms, result.edges_seen, result.edges
        ),
    );
    // The switches as the camera should see them: each edge's switch time plus
    // the estimated latency, drawn as a step between the off and on levels.
    let (lo, hi) = frames.iter().fold((f64::MAX, f64::MIN), |(lo, hi), f| {
        (lo.min(f.brightness), hi.max(f.brightness))
    });
    for e in &edges {
        let t = e.t_sent_s + super::latency::switch_delay_s(e) + result.latency_ms * 1e-3;
        let (from, to) = if e.on { (lo, hi) } else { (hi, lo) };
        done.fit.push([t, from]);
        done.fit.push([t, to]);
    }
    watch.seen(done);
    // The truth the lab needs: from the middle of the hanging ball's exposure
    // (its row read down the rolling shutter) to the frame's delivery, mean.
    let true_latency_ms = if world_timing {
        let rest = believed_rest(scenario) + Vector3::from(world.intercept_error_m);
        let v = true_cam.project(&rest).map_or(0.5 * height, |p| p.y);
        world.camera_latency_ms - row_s(v) * 1e3 - 0.5 * exposure_s * 1e3
    } else {
        world.camera_latency_ms
    };
    Ok(LatencyRun {
        result,
        true_latency_ms,
        led_px: [f64::from(max_at.x), f64::from(max_at.y)],
    })
}

/// The robot step on the simulated world.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobotRun {
    /// What the step measured.
    pub result: RobotLatency,
    /// The true mean delay, ms.
    pub true_latency_ms: f64,
    /// The true servo lag, ms.
    pub true_servo_time_constant_ms: f64,
    /// The joint excited (0-based: 6 is A7).
    pub joint: usize,
    /// Peak excitation, radians.
    pub amplitude_rad: f64,
}

/// Seconds between the excitation's steps.
const STEP_EVERY_S: f64 = 0.3;

/// Small steps on one joint from the held position, and a record of the commands
/// and measurements.
struct Excite {
    joint: usize,
    amplitude_rad: f64,
    duration_s: f64,
    start: Option<(u64, Joints)>,
    commands: Vec<JointSample>,
    measured: Vec<JointSample>,
}

impl ControlStep for Excite {
    fn step(&mut self, input: &StepInput<'_>, command_rad: &mut Joints) {
        let t = input.now_ns as f64 * 1e-9;
        if let Some(q) = input.monitoring.measured_joint_position_rad
            && self.start.is_some()
        {
            self.measured.push(JointSample {
                t_s: t,
                q_rad: q[self.joint],
            });
        }
        if !input.commanding {
            return;
        }
        let (t0_ns, hold) = *self.start.get_or_insert((input.now_ns, *command_rad));
        let s = (input.now_ns - t0_ns) as f64 * 1e-9;
        // Small steps every 0.3 s between the held position and `amplitude_rad` away,
        // each a ramp over two periods (the command never jumps by more than half
        // the amplitude); a step's sharp corners show the dead time, its settling
        // the servo lag (a slow chirp cannot tell the two apart).
        let up = (s / STEP_EVERY_S) as u64 % 2 == 1 && s < self.duration_s - STEP_EVERY_S;
        let target = hold[self.joint] + if up { self.amplitude_rad } else { 0.0 };
        let mut q = *command_rad;
        let max_step = 0.5 * self.amplitude_rad;
        q[self.joint] += (target - q[self.joint]).clamp(-max_step, max_step);
        for (i, v) in q.iter_mut().enumerate() {
            if i != self.joint {
                *v = hold[i];
            }
        }
        *command_rad = q;
        self.commands.push(JointSample {
            t_s: t,
            q_rad: q[self.joint],
        });
    }
}

/// The robot step: the FRI session to COMMANDING_ACTIVE against the simulated KUKA
/// controller (the truth's delay, jitter and servo lag), then `duration_s` of
/// small steps of `amplitude_rad` on A7 (the wrist: the smallest moving mass, far from its
/// limits at the home pose), commands and measured positions fitted.
///
/// # Errors
///
/// [`ProcedureError::Params`] for an invalid scenario; [`ProcedureError::Amplitude`]
/// for an amplitude outside `(0, 0.05]` rad; [`ProcedureError::RobotParams`],
/// [`ProcedureError::LeftCommanding`] or [`ProcedureError::ControllerAborted`] from
/// the FRI session; [`ProcedureError::Calibration`] when [`fit_robot_latency`] refuses.
pub fn run_robot(
    scenario: &Scenario,
    world: &HiddenWorld,
    seed: u64,
    amplitude_rad: f64,
    duration_s: f64,
    watch: &mut dyn Watch,
) -> Result<RobotRun, ProcedureError> {
    scenario.validate()?;
    if !(amplitude_rad.is_finite() && amplitude_rad > 0.0 && amplitude_rad <= 0.05) {
        return Err(ProcedureError::Amplitude { amplitude_rad });
    }
    let params = FriSimParams {
        latency_ms: world.robot_latency_ms,
        latency_jitter_ms: world.robot_latency_jitter_ms.min(world.robot_latency_ms),
        servo_time_constant_ms: world.servo_time_constant_ms,
        seed,
        ..FriSimParams::from_robot(&scenario.robot)
    };
    let period_ns = params.period_ns();
    let mut robot = SimController::new(params, 1_700_000_000_000_000_000)
        .map_err(ProcedureError::RobotParams)?;
    let mut client =
        FriClient::new(FriClientParams::default()).map_err(ProcedureError::RobotParams)?;
    let joint = 6;
    let mut step = Excite {
        joint,
        amplitude_rad,
        duration_s,
        start: None,
        commands: Vec::with_capacity(4096),
        measured: Vec::with_capacity(4096),
    };
    let mut t_ns = 0u64;
    let total_ns = ((duration_s + 5.0) * 1e9) as u64;
    while t_ns < total_ns {
        t_ns += period_ns;
        if robot.state() != SessionState::CommandingActive && step.start.is_none() {
            robot.request_commanding();
        }
        client.poll(t_ns, &mut step);
        if let Some(bytes) = robot.tick(t_ns)
            && let Some(reply) = client.on_datagram(bytes, t_ns, &mut step)
        {
            robot.on_reply(reply, t_ns + 20_000);
        }
        if let Some((t0, _)) = step.start
            && (t_ns - t0) as f64 * 1e-9 > duration_s + 0.2
        {
            break;
        }
    }
    if step.start.is_none() || client.state() != LinkState::CommandingActive {
        return Err(ProcedureError::LeftCommanding {
            client: client.state(),
            controller: robot.state(),
        });
    }
    if let Some(a) = robot.stats().last_abort() {
        return Err(ProcedureError::ControllerAborted(a));
    }
    let result = fit_robot_latency(&step.commands, &step.measured)?;
    let series = |s: &[JointSample]| -> Vec<[f64; 2]> {
        let t0 = step.commands.first().map_or(0.0, |c| c.t_s);
        thin(
            &s.iter().map(|j| [j.t_s - t0, j.q_rad]).collect::<Vec<_>>(),
            800,
        )
    };
    watch.seen(StepView {
        progress: 1.0,
        message: format!(
            "A{} excited: latency {:.2} ms, servo lag {:.2} ms ({:.1} Hz)",
            joint + 1,
            result.latency_ms,
            result.servo_time_constant_ms,
            result.bandwidth_hz
        ),
        kind: ViewKind::Series,
        points: series(&step.measured),
        fit: series(&step.commands),
    });
    Ok(RobotRun {
        result,
        true_latency_ms: world.robot_latency_ms,
        true_servo_time_constant_ms: world.servo_time_constant_ms,
        joint,
        amplitude_rad,
    })
}
