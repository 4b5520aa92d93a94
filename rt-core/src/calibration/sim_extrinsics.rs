//! Camera to robot on the simulated world (`isochron calibrate camera-robot`):
//! the robot carries a coloured disc on its flange through ~18 poses in the
//! camera's view (slow joint-space moves through FRI against the simulated KUKA
//! controller); at each, frames of the disc through the *true* camera are
//! rendered and the disc is found by colour threshold, contour and centroid; the
//! disc's base-frame centre is the forward kinematics of the *measured* joints
//! plus its known offset. `cv::solvePnP` on all poses with the lab's
//! intrinsics, refined by least squares (with `k1` when the file has no camera
//! step) -> the camera's pose in the base frame. Then the intercept point: the
//! hanging ball's rest pixel, its ray through the calibrated camera met with the
//! plane of the ball's depth, that depth from the tool touching the ball
//! (hand-guided: the robot's measured pose at the touch) or, without the touch,
//! the believed swing plane. README.md ("Camera to robot").
//!
//! What the procedure sees: rendered frames, its own detections, FRI
//! monitoring. The truth (camera pose error, lens, the arm's true geometry, the
//! true rest point, the operator's touch) lives only in the simulators and is
//! returned beside the estimate.

use nalgebra::{Rotation3, SVector, Vector2, Vector3};
use opencv::core::MatTraitConst;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::extrinsics::{
    CameraRobotCalibration, camera_pose_of, ray_b, reproject, rotation_angle_rad,
};
use super::marker::{
    FRAMES_PER_POSE, MARKER_OFFSET_M, MARKER_RADIUS_M, MIN_POSES, REST_FRAMES, SETTLE_S,
    TARGET_MARGIN_RAD, TILTS_RAD, find_marker, fit_pose, marker_believed, move_duration_s,
    step_distance_m, tool_rotation, tour_points, tour_targets,
};
use super::simworld::{HiddenWorld, ProcedureError};
use super::view::{StepView, ViewKind, Watch};
use crate::fri::{
    ControlStep, FriClient, FriClientParams, Joints, LinkState, SessionState, StepInput,
};
use crate::kinematics::{self, iiwa7::POSITION_LIMIT_RAD};
use crate::params::{Scenario, VisionMode};
use crate::sim::camera::{BallState, SimCamera, SimCameraParams, SimVision};
use crate::sim::kuka::{FriSimParams, SimController};
use crate::sim::world::TrueArm;
use crate::sim::world::marker::{draw_marker, marker_rim};
use crate::vision::{CameraIntrinsics, CameraPose, DetectorParams, SwingPlaneCalibration};

/// Options of the procedure.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraRobotOptions {
    /// The marker is on the tool and in view (`false` covers it: the step must refuse).
    pub marker_visible: bool,
    /// Touch the hanging ball with the tool (hand-guided) for the intercept
    /// point's depth; `false`: the believed swing plane.
    pub touch: bool,
    /// The camera step's intrinsics and distortion when the calibration file has
    /// them (`k1` is then not fitted); `None`: the believed intrinsics, `k1` fitted.
    pub intrinsics: Option<CameraIntrinsics>,
}

impl Default for CameraRobotOptions {
    fn default() -> Self {
        Self {
            marker_visible: true,
            touch: true,
            intrinsics: None,
        }
    }
}

/// The camera-robot step on the simulated world, with the truth beside it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraRobotRun {
    /// What the step measured.
    pub calibration: CameraRobotCalibration,
    /// The true camera pose.
    pub true_camera_pose: CameraPose,
    /// The true intercept point (the hanging ball's centre), base frame, m.
    pub true_intercept_m: [f64; 3],
    /// Angle between the estimated and the true camera rotation, degrees.
    pub camera_rotation_error_deg: f64,
    /// Distance between the estimated and the true camera centre, mm.
    pub camera_position_error_mm: f64,
    /// Distance between the estimated and the true intercept point, mm.
    pub intercept_error_mm: f64,
    /// The same before the step (the believed pose and intercept point against the truth).
    pub believed_rotation_error_deg: f64,
    /// See `believed_rotation_error_deg`, mm.
    pub believed_position_error_mm: f64,
    /// See `believed_rotation_error_deg`, mm.
    pub believed_intercept_error_mm: f64,
    /// At the touch: the believed tool point (forward kinematics of the measured
    /// joints) minus the true one, base frame, m (the arm's and tool's true
    /// geometry against the model; zero without the touch).
    pub touch_kinematic_error_m: [f64; 3],
    /// Commands sent to the robot.
    pub commands_sent: usize,
    /// The smallest distance of any command to its joint limit, rad.
    pub min_command_margin_rad: f64,
}

fn to_vec(q: &Joints) -> SVector<f64, 7> {
    SVector::<f64, 7>::from_column_slice(q)
}

/// The true marker centre and normal for the robot's true joints.
fn marker_true(arm: &TrueArm, q: &Joints) -> (Vector3<f64>, Vector3<f64>) {
    let (p, r) = arm.flange(q);
    (
        p + r * Vector3::from(MARKER_OFFSET_M),
        r.column(2).into_owned(),
    )
}

/// A slow tour through joint targets: cosine-profile joint moves, a hold at each
/// for the frames; the measured joints averaged over the hold's capture window.
/// A command outside the joint limits is never sent (the tour stops instead).
struct Tour {
    targets: Vec<Joints>,
    /// Per target: (sum of measured joints, count) over its capture window.
    measured: Vec<(Joints, usize)>,
    /// Target `i` holds and frames are taken now.
    capturing: Option<usize>,
    at: usize,
    from: Option<Joints>,
    t_move_ns: u64,
    move_s: f64,
    holding_since_ns: Option<u64>,
    capture_s: f64,
    /// The latest measured joints.
    last_measured: Joints,
    done: bool,
    refused: bool,
    commands: usize,
    min_margin_rad: f64,
}

impl Tour {
    fn new(targets: Vec<Joints>, capture_s: f64) -> Self {
        let n = targets.len();
        Self {
            targets,
            measured: vec![([0.0; 7], 0); n],
            capturing: None,
            at: 0,
            from: None,
            t_move_ns: 0,
            move_s: 0.0,
            holding_since_ns: None,
            capture_s,
            last_measured: [0.0; 7],
            done: n == 0,
            refused: false,
            commands: 0,
            min_margin_rad: f64::INFINITY,
        }
    }
}

impl ControlStep for Tour {
    fn step(&mut self, input: &StepInput<'_>, command_rad: &mut Joints) {
        if let Some(q) = input.monitoring.measured_joint_position_rad {
            self.last_measured = q;
        }
        if let (Some(i), Some(q)) = (self.capturing, input.monitoring.measured_joint_position_rad) {
            let m = &mut self.measured[i];
            for (s, v) in m.0.iter_mut().zip(q.iter()) {
                *s += v;
            }
            m.1 += 1;
        }
        if !input.commanding || self.done || self.refused {
            return;
        }
        let now = input.now_ns;
        let from = *self.from.get_or_insert_with(|| {
            self.t_move_ns = now;
            self.move_s = move_duration_s(command_rad, &self.targets[0]);
            *command_rad
        });
        let target = self.targets[self.at];
        let mut q = target;
        if let Some(t0) = self.holding_since_ns {
            let held = (now - t0) as f64 * 1e-9;
            self.capturing = (held >= SETTLE_S).then_some(self.at);
            if held >= SETTLE_S + self.capture_s {
                self.capturing = None;
                self.holding_since_ns = None;
                self.at += 1;
                if self.at >= self.targets.len() {
                    self.done = true;
                } else {
                    self.from = Some(target);
                    self.t_move_ns = now;
                    self.move_s = move_duration_s(&target, &self.targets[self.at]);
                }
            }
        } else {
            let s = ((now - self.t_move_ns) as f64 * 1e-9 / self.move_s).min(1.0);
            let w = 0.5 - 0.5 * (std::f64::consts::PI * s).cos();
            for ((v, a), b) in q.iter_mut().zip(from.iter()).zip(target.iter()) {
                *v = a + (b - a) * w;
            }
            if s >= 1.0 {
                self.holding_since_ns = Some(now);
            }
        }
        // Every command inside the limits, or none at all.
        let margin = q
            .iter()
            .zip(POSITION_LIMIT_RAD)
            .map(|(v, l)| l - v.abs())
            .fold(f64::INFINITY, f64::min);
        if margin.is_nan() || margin <= 0.0 {
            self.refused = true;
            return;
        }
        self.min_margin_rad = self.min_margin_rad.min(margin);
        self.commands += 1;
        *command_rad = q;
    }
}

/// Joints that put the *true* tool point at `target` with the tool along `r`:
/// the believed IK corrected on the true arm (a few fixed-point steps); what a
/// hand guiding the tool to a place does.
fn true_ik(
    arm: &TrueArm,
    r: &Rotation3<f64>,
    target: &Vector3<f64>,
    seed: &Joints,
) -> Option<Joints> {
    let tool = Vector3::new(0.0, 0.0, arm.tool_length_m);
    let mut aim = *target;
    let mut q = to_vec(seed);
    for _ in 0..6 {
        let flange = aim - r * tool;
        let pose = kinematics::Pose::from_parts(nalgebra::Translation3::from(flange), *r);
        q = kinematics::analytic::solve(&pose, Some(&q), TARGET_MARGIN_RAD)
            .ok()?
            .q;
        let qa: Joints = std::array::from_fn(|j| q[j]);
        aim += target - arm.tool_point(&qa);
    }
    Some(std::array::from_fn(|j| q[j]))
}

/// The camera-robot step on the simulated world (module docs). `watch` gets a
/// view per marker pose (the detected pixels and, at the end, their reprojection).
///
/// # Errors
///
/// [`ProcedureError::Params`] or [`ProcedureError::RobotParams`] for an invalid
/// scenario or refused simulator parameters; the step's own variants when a part
/// fails (e.g. [`ProcedureError::TooFewPoses`], [`ProcedureError::MarkerNotSeen`],
/// [`ProcedureError::LeftCommanding`], [`ProcedureError::BallNotFound`]);
/// [`ProcedureError::Vision`] or [`ProcedureError::Calibration`] from rendering,
/// detection or the pose fit.
pub fn run_camera_robot(
    scenario: &Scenario,
    world: &HiddenWorld,
    seed: u64,
    options: &CameraRobotOptions,
    watch: &mut dyn Watch,
) -> Result<CameraRobotRun, ProcedureError> {
    scenario.validate()?;
    // The truth (simulators only): the camera, the arm, the rest point.
    let true_cam = world.world_camera(scenario);
    let arm = match &scenario.world {
        Some(w) => {
            let s = w.draw_session(seed, 0, scenario.robot.latency_ms);
            TrueArm::from_session(
                scenario.task.tool_length_m,
                w.geometry.contact_disc_radius_m,
                &s,
            )
        }
        None => TrueArm::nominal(scenario.task.tool_length_m, 0.03),
    };
    // The ball hangs at the far end of the distances for the step: there the arm
    // reaches it with the tool level (the touch then measures depth alone).
    let nominal_rest = Vector3::new(
        step_distance_m(scenario),
        0.0,
        scenario.task.intercept_height_m,
    );
    let true_rest = nominal_rest + Vector3::from(world.intercept_error_m);

    // What the lab believes.
    let sim_cam = SimCameraParams::default();
    let believed_pose = scenario.camera.pose.unwrap_or(sim_cam.pose);
    let intrinsics = options.intrinsics.unwrap_or_else(|| {
        CameraIntrinsics::from_hfov(
            scenario.camera.width_px,
            scenario.camera.height_px,
            sim_cam.hfov_deg,
        )
    });
    let mut cam_params = scenario.camera.clone();
    cam_params.vision = VisionMode::Full;
    cam_params.latency_ms = world.camera_latency_ms;
    let mut camera = SimCamera::new(&cam_params, &sim_cam, scenario.pendulum.ball_radius_m, seed)?;
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x00ca_3e7a);

    // 1. The robot: the FRI session against the simulated controller.
    let params = FriSimParams {
        latency_ms: world.robot_latency_ms,
        latency_jitter_ms: world.robot_latency_jitter_ms.min(world.robot_latency_ms),
        servo_time_constant_ms: world.servo_time_constant_ms,
        seed,
        ..FriSimParams::from_robot(&scenario.robot)
    };
    let start: Joints = std::array::from_fn(|i| params.initial_joint_position_deg[i].to_radians());
    let period_ns = params.period_ns();
    let mut robot = SimController::new(params, 1_700_000_000_000_000_000)
        .map_err(ProcedureError::RobotParams)?;
    let mut client =
        FriClient::new(FriClientParams::default()).map_err(ProcedureError::RobotParams)?;
    let mut targets = tour_targets(&tour_points(scenario), &start);
    let poses_commanded = targets.len();
    if poses_commanded < MIN_POSES {
        return Err(ProcedureError::TooFewPoses {
            reachable: poses_commanded,
            needed: MIN_POSES,
        });
    }
    // The touch (a hand guiding the tool, simulated): the true tool point just
    // before the ball, the disc's face touching it (within the operator's 0.3 mm).
    let touch_target = if options.touch {
        let gap = rng.random_range(0.0..0.0003);
        let seed_q = targets.last().copied().unwrap_or(start);
        let mut found = None;
        for tilt in TILTS_RAD {
            let r = tool_rotation(tilt);
            let n = r * Vector3::z();
            let at = true_rest - n * (scenario.pendulum.ball_radius_m + gap);
            // Approach from 5 cm along the tool's axis, then forward to the touch.
            if let Some(q) = true_ik(&arm, &r, &at, &seed_q)
                && let Some(before) = true_ik(&arm, &r, &(at - 0.05 * n), &q)
            {
                found = Some((before, q));
                break;
            }
        }
        let (before, q) = found.ok_or(ProcedureError::BallOutOfReach)?;
        targets.push(before);
        targets.push(q);
        Some(targets.len() - 1)
    } else {
        None
    };
    let capture_s = FRAMES_PER_POSE as f64 / scenario.camera.fps + 0.05;
    let mut tour = Tour::new(targets, capture_s);
    let frame_period = 1.0 / scenario.camera.fps;
    let mut detections: Vec<Vec<Vector2<f64>>> = vec![Vec::new(); poses_commanded];
    let mut next_frame_s = 0.0;
    let mut t_ns = 0u64;
    let mut started = false;
    let limit_ns = 3_600 * 1_000_000_000u64;
    while !tour.done && !tour.refused && t_ns < limit_ns {
        t_ns += period_ns;
        if robot.state() != SessionState::CommandingActive && !started {
            robot.request_commanding();
        }
        client.poll(t_ns, &mut tour);
        if let Some(bytes) = robot.tick(t_ns)
            && let Some(reply) = client.on_datagram(bytes, t_ns, &mut tour)
        {
            robot.on_reply(reply, t_ns + 20_000);
        }
        started |= tour.from.is_some();
        if started && client.state() != LinkState::CommandingActive {
            break;
        }
        let t = t_ns as f64 * 1e-9;
        let Some(i) = tour.capturing.filter(|&i| i < poses_commanded) else {
            next_frame_s = t;
            continue;
        };
        if t < next_frame_s || detections[i].len() >= FRAMES_PER_POSE {
            continue;
        }
        next_frame_s = t + frame_period;
        // A frame: the background, the disc where the true camera sees it.
        let (c, n) = marker_true(&arm, robot.joint_rad());
        let img = camera.render(None)?;
        let mut img = img.try_clone()?;
        if options.marker_visible {
            let rim = marker_rim(&true_cam, &c, &n);
            if let Some(rim) = rim {
                draw_marker(&mut img, &rim, scenario.camera.image_noise, &mut rng)?;
            }
        }
        // The procedure's side: where the believed camera expects the disc.
        let (c_b, _) = marker_believed(&tour.last_measured);
        let pc = believed_pose.to_camera(&c_b);
        let Some(guess) = intrinsics.project(&pc) else {
            continue;
        };
        let r_px = intrinsics.fx_px * MARKER_RADIUS_M / pc.z.max(0.1);
        if let Some(px) = find_marker(&img, &guess, r_px)? {
            detections[i].push(px);
        }
        if detections[i].len() == FRAMES_PER_POSE {
            let seen: Vec<[f64; 2]> = detections
                .iter()
                .filter(|d| !d.is_empty())
                .map(|d| {
                    let m = d.iter().fold(Vector2::zeros(), |a, p| a + p) / d.len() as f64;
                    [m.x, m.y]
                })
                .collect();
            watch.seen(StepView {
                progress: 0.8 * (i + 1) as f64 / poses_commanded as f64,
                message: format!("marker pose {} of {poses_commanded}: seen", i + 1),
                kind: ViewKind::Image,
                points: seen,
                fit: Vec::new(),
            });
        }
    }
    if tour.refused {
        return Err(ProcedureError::TourLeftLimits);
    }
    if !tour.done {
        return Err(ProcedureError::LeftCommanding {
            client: client.state(),
            controller: robot.state(),
        });
    }
    if let Some(a) = robot.stats().last_abort() {
        return Err(ProcedureError::ControllerAborted(a));
    }

    // 2. The sightings: mean pixel per pose, the marker's believed centre from the
    //    mean measured joints.
    let mut points_b = Vec::new();
    let mut pixels = Vec::new();
    for (i, det) in detections.iter().enumerate() {
        let (sum, k) = tour.measured[i];
        if det.len() < FRAMES_PER_POSE / 2 + 1 || k == 0 {
            continue;
        }
        let q: Joints = std::array::from_fn(|j| sum[j] / k as f64);
        let px = det.iter().fold(Vector2::zeros(), |a, p| a + p) / det.len() as f64;
        points_b.push(marker_believed(&q).0);
        pixels.push(px);
    }
    if points_b.len() < MIN_POSES {
        return Err(ProcedureError::MarkerNotSeen {
            seen: points_b.len(),
            commanded: poses_commanded,
            needed: MIN_POSES,
        });
    }

    // 3. The pose: solvePnP (iterative, from the believed pose), then least squares.
    let fit = fit_pose(
        &intrinsics,
        &points_b,
        &pixels,
        &believed_pose,
        options.intrinsics.map(|k| k.k1),
    )?;
    let fitted = reproject(&intrinsics, &fit, &points_b);
    watch.seen(StepView {
        progress: 0.85,
        message: format!(
            "camera pose from {} marker poses: reprojection rms {:.2} px",
            points_b.len(),
            fit.rms_px
        ),
        kind: ViewKind::Image,
        points: pixels.iter().map(|p| [p.x, p.y]).collect(),
        fit: fitted,
    });

    // 4. The hanging ball's rest pixel (the robot away from it: the touch comes last).
    let ball_px = true_cam
        .project(&true_rest)
        .ok_or(ProcedureError::BallOutOfView)?;
    let ball = BallState {
        centre_m: true_cam.equivalent_centre_m(&ball_px, &true_rest),
        velocity_mps: Vector3::zeros(),
    };
    let cal = SwingPlaneCalibration::from_pose(
        intrinsics,
        &believed_pose,
        &nominal_rest,
        scenario.pendulum.ball_radius_m,
    );
    let mut vision = SimVision::new(camera, DetectorParams::default(), cal)?;
    let mut rest = Vec::new();
    for k in 0..REST_FRAMES * 2 {
        if rest.len() >= REST_FRAMES {
            break;
        }
        if let Some(m) = vision.capture(frame_period * k as f64, Some(&ball))?
            && m.found
        {
            rest.push(Vector2::new(m.x_px, m.y_px));
        }
    }
    if rest.len() < REST_FRAMES / 2 {
        return Err(ProcedureError::BallNotFound {
            found: rest.len(),
            frames: REST_FRAMES * 2,
        });
    }
    let rest_px = rest.iter().fold(Vector2::zeros(), |a, p| a + p) / rest.len() as f64;
    watch.seen(StepView {
        progress: 0.95,
        message: format!("hanging ball at ({:.1}, {:.1}) px", rest_px.x, rest_px.y),
        kind: ViewKind::Image,
        points: rest.iter().map(|p| [p.x, p.y]).collect(),
        fit: vec![[rest_px.x, rest_px.y]],
    });

    // 5. The intercept point: the ray through the rest pixel met with the plane of
    //    the ball's centre, x = the touch's tool point + ball radius (or believed).
    //    The ball's centre lies on the plane `n . p = d`: with the touch, the disc's
    //    plane (normal n, the tool axis, at the measured tool point) moved out by
    //    the ball's radius; without, the believed swing plane `x = distance`.
    let mut touch_kinematic_error_m = [0.0; 3];
    let (n, d, depth_from) = match touch_target {
        Some(i) => {
            let (sum, k) = tour.measured[i];
            if k == 0 {
                return Err(ProcedureError::NoTouchMeasurement);
            }
            let q: Joints = std::array::from_fn(|j| sum[j] / k as f64);
            let tool = kinematics::tool_pose(
                &to_vec(&q),
                &kinematics::Tool::along_z(scenario.task.tool_length_m),
            );
            let n = tool.rotation.matrix().column(2).into_owned();
            // (The truth, for the report only.)
            touch_kinematic_error_m =
                (tool.translation.vector - arm.tool_point(robot.joint_rad())).into();
            let d = n.dot(&tool.translation.vector) + scenario.pendulum.ball_radius_m;
            (n, d, "touch")
        }
        None => (Vector3::x(), nominal_rest.x, "plane"),
    };
    let ray = ray_b(&intrinsics, &fit, rest_px.x, rest_px.y);
    let along = n.dot(&ray);
    if along <= 0.05 {
        return Err(ProcedureError::RayMissesBallPlane);
    }
    let s = (d - n.dot(&fit.position_m)) / along;
    let intercept = fit.position_m + ray * s;

    let pose = camera_pose_of(&fit.base_from_camera, &fit.position_m);
    let calibration = CameraRobotCalibration {
        camera_pose: pose,
        base_from_camera_rows: std::array::from_fn(|r| {
            std::array::from_fn(|c| fit.base_from_camera[(r, c)])
        }),
        reprojection_rms_px: fit.rms_px,
        poses: points_b.len(),
        poses_commanded,
        k1: fit.k1,
        k1_fitted: options.intrinsics.is_none(),
        position_std_m: fit.position_std_m.into(),
        marker_offset_m: MARKER_OFFSET_M,
        intercept_m: intercept.into(),
        intercept_offset_m: (intercept - nominal_rest).into(),
        rest_px: [rest_px.x, rest_px.y],
        intercept_depth_from: depth_from.to_owned(),
    };
    watch.seen(StepView {
        progress: 1.0,
        message: format!(
            "camera at ({:.4}, {:.4}, {:.4}) m, intercept point ({:.4}, {:.4}, {:.4}) m",
            pose.position_m[0],
            pose.position_m[1],
            pose.position_m[2],
            intercept.x,
            intercept.y,
            intercept.z
        ),
        kind: ViewKind::Image,
        points: pixels.iter().map(|p| [p.x, p.y]).collect(),
        fit: reproject(&intrinsics, &fit, &points_b),
    });
    let believed_r = believed_pose.base_from_camera();
    Ok(CameraRobotRun {
        calibration,
        true_camera_pose: camera_pose_of(&true_cam.base_from_camera, &true_cam.position_m),
        true_intercept_m: true_rest.into(),
        camera_rotation_error_deg: rotation_angle_rad(
            &fit.base_from_camera,
            &true_cam.base_from_camera,
        )
        .to_degrees(),
        camera_position_error_mm: (fit.position_m - true_cam.position_m).norm() * 1e3,
        intercept_error_mm: (intercept - true_rest).norm() * 1e3,
        believed_rotation_error_deg: rotation_angle_rad(&believed_r, &true_cam.base_from_camera)
            .to_degrees(),
        believed_position_error_mm: (believed_pose.position() - true_cam.position_m).norm() * 1e3,
        believed_intercept_error_mm: (scenario_intercept(scenario) - true_rest).norm() * 1e3,
        touch_kinematic_error_m,
        commands_sent: tour.commands,
        min_command_margin_rad: tour.min_margin_rad,
    })
}

/// The intercept point the scenario believes (nominal plus its offset).
fn scenario_intercept(s: &Scenario) -> Vector3<f64> {
    s.task.intercept_m(step_distance_m(s))
}
