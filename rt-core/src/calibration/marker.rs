//! The tool's marker and the camera-robot tour, shared by the step's
//! procedures on the simulated world (`sim_extrinsics`) and on a real lab
//! (`server::calibration::run_real_camera_robot`): the marker disc (where it
//! sits on the tool, its size and colour), the tour's marker positions and
//! their joint targets, the disc's detection by colour in a frame, and the
//! camera pose's fit from the sightings. README.md ("Camera to robot").

use nalgebra::{Rotation3, SVector, Vector2, Vector3};
use opencv::{
    calib3d,
    core::{self, Mat, MatTraitConst, Point, Point2d, Point3d, Rect, Scalar, Vector},
    imgproc,
};

use super::extrinsics::{PnpFit, refine_pose};
use super::procedure::ProcedureError;
use crate::fri::Joints;
use crate::kinematics;
use crate::params::Scenario;
use crate::vision::{CameraIntrinsics, CameraPose};

/// The marker disc's centre in the flange frame, metres: on the tool's shaft,
/// 6 cm out along the flange's z axis (a constant of the tool, measured once).
pub const MARKER_OFFSET_M: [f64; 3] = [0.0, 0.0, 0.06];
/// The marker disc's radius, metres (painted on both faces, normal along the tool axis).
pub const MARKER_RADIUS_M: f64 = 0.02;
/// The marker's colour: hue (degrees), saturation, value. A green no clutter
/// object has (the renderer's clutter keeps hues 0..32 and 125..350 or is grey,
/// the ball and its decoys are 48..100).
pub const MARKER_HSV: (f64, f64, f64) = (112.0, 0.9, 0.8);
/// Hue band the detector accepts, OpenCV hue units (degrees / 2).
pub const HUE_BAND: (f64, f64) = (51.0, 61.0);
/// Joint speed of the moves, rad/s (slow: a tenth of the iiwa's slowest limit).
pub const MOVE_SPEED_RADPS: f64 = 0.17;
/// Joint margin of every target, rad (10 degrees inside the limits).
pub const TARGET_MARGIN_RAD: f64 = 0.1745;
/// After a move: wait before the frames (the servo settles), s.
pub const SETTLE_S: f64 = 0.6;
/// Frames averaged per pose.
pub const FRAMES_PER_POSE: usize = 5;
/// Frames of the hanging ball averaged for the rest pixel.
pub const REST_FRAMES: usize = 30;
/// Least poses for a pose fit.
pub const MIN_POSES: usize = 8;
/// The posture the tour's inverse kinematics starts from, degrees (the
/// cabinet's start posture: the tour is the same wherever the arm rests).
pub const TOUR_SEED_DEG: [f64; 7] = [0.0, 30.0, 0.0, -80.0, 0.0, 60.0, 0.0];

fn to_vec(q: &Joints) -> SVector<f64, 7> {
    SVector::<f64, 7>::from_column_slice(q)
}

/// The believed marker centre and the disc normal for measured joints `q`.
pub fn marker_believed(q: &Joints) -> (Vector3<f64>, Vector3<f64>) {
    let f = kinematics::flange_pose(&to_vec(q));
    let r = f.rotation.matrix();
    (
        f.translation.vector + r * Vector3::from(MARKER_OFFSET_M),
        r.column(2).into_owned(),
    )
}

/// How long the simulated tour's move between two joint targets takes (a
/// cosine profile peaking at [`MOVE_SPEED_RADPS`]), s, at least 1.
pub fn move_duration_s(a: &Joints, b: &Joints) -> f64 {
    let d = a
        .iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max);
    // Cosine profile: peak speed (pi/2) d / T.
    (std::f64::consts::FRAC_PI_2 * d / MOVE_SPEED_RADPS).max(1.0)
}

/// Marker positions of the tour (base frame, m): a grid over the pendulum's
/// region, across the image and in depth, in the order the arm visits them:
/// a serpentine (each row of the grid walked back from where the last ended),
/// so that no move crosses the whole region.
pub fn tour_points(scenario: &Scenario) -> Vec<Vector3<f64>> {
    let d = &scenario.task.distance_m;
    let h = scenario.task.intercept_height_m;
    let mut out = Vec::new();
    let mut row = 0;
    for (ix, x) in [d.lo, 0.5 * (d.lo + d.hi), d.hi].into_iter().enumerate() {
        let ys = if ix % 2 == 0 {
            [-0.30, 0.0, 0.30]
        } else {
            [0.30, 0.0, -0.30]
        };
        for y in ys {
            let dzs = if row % 2 == 0 {
                [-0.15, 0.15]
            } else {
                [0.15, -0.15]
            };
            row += 1;
            for dz in dzs {
                // Stagger the rows per depth so the image is covered evenly.
                let yy = y + 0.05 * ix as f64;
                out.push(Vector3::new(x.min(0.75), yy, h + dz + 0.03 * ix as f64));
            }
        }
    }
    out
}

/// Tilts of the tool tried, from along +x down towards -z, radians (near the
/// base a horizontal tool is out of reach: the arm comes from above, as the
/// interception's planned tilt does).
pub const TILTS_RAD: [f64; 5] = [0.0, 0.35, 0.7, 0.9, 1.05];

/// The flange orientation with the tool along +x tilted down by `tilt` (the
/// disc faces the camera behind the robot).
pub fn tool_rotation(tilt: f64) -> Rotation3<f64> {
    Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2 + tilt)
}

/// The tour's orientation at pose `i` and tilt: a little yaw and roll per pose.
pub fn tour_rotation(i: usize, tilt: f64) -> Rotation3<f64> {
    let (a, b) = [
        (0.0, 0.0),
        (0.15, 0.0),
        (-0.15, 0.1),
        (0.0, -0.15),
        (0.1, 0.15),
    ][i % 5];
    Rotation3::from_euler_angles(0.0, 0.0, a)
        * tool_rotation(tilt)
        * Rotation3::from_euler_angles(0.0, 0.0, b)
}

/// Joint targets (inside the limits by `TARGET_MARGIN_RAD`) putting the marker at
/// each point, in the points' order from `start`; unreachable points are
/// skipped. At each point the first tilt of [`TILTS_RAD`] within reach, and
/// of that pose's solutions (every arm angle and configuration) the one the
/// controller's slow move reaches soonest from the previous target
/// ([`move_to_duration_s`]): the tour's time is its moves'.
///
/// [`move_to_duration_s`]: crate::control::step::move_to_duration_s
pub fn tour_targets(points: &[Vector3<f64>], start: &Joints) -> Vec<Joints> {
    use crate::control::step::move_to_duration_s;
    use kinematics::analytic::{ArmFlags, ArmGeometry};
    const ARM_ANGLES: usize = 360;
    let mut from = kinematics::Joints::from_column_slice(start);
    let mut out = Vec::new();
    for (i, p) in points.iter().enumerate() {
        for tilt in TILTS_RAD {
            let r = tour_rotation(i, tilt);
            let flange = p - r * Vector3::from(MARKER_OFFSET_M);
            let pose = kinematics::Pose::from_parts(nalgebra::Translation3::from(flange), r);
            let Ok(geo) = ArmGeometry::new(&pose) else {
                continue;
            };
            let mut q = kinematics::Joints::zeros();
            let mut best: Option<(f64, kinematics::Joints)> = None;
            for flags in ArmFlags::ALL {
                for k in 0..ARM_ANGLES {
                    let psi = -std::f64::consts::PI
                        + std::f64::consts::TAU * (k as f64 + 0.5) / ARM_ANGLES as f64;
                    if geo
                        .solve_within(psi, flags, TARGET_MARGIN_RAD, &mut q)
                        .is_ok()
                    {
                        let t = move_to_duration_s(&from, &q);
                        if best.is_none_or(|(b, _)| t < b) {
                            best = Some((t, q));
                        }
                    }
                }
            }
            if let Some((_, q)) = best {
                from = q;
                out.push(std::array::from_fn(|j| q[j]));
                break;
            }
        }
    }
    out
}

/// Finds the marker near `guess_px` (the believed camera's prediction): the
/// pixels of its hue, their largest blob, its centroid. `None`: not seen.
///
/// # Errors
///
/// [`ProcedureError::Vision`] when OpenCV fails on the image.
pub fn find_marker(
    img: &Mat,
    guess_px: &Vector2<f64>,
    expect_r_px: f64,
) -> Result<Option<Vector2<f64>>, ProcedureError> {
    let half = (3.0 * expect_r_px + 40.0).round() as i32;
    let (cx, cy) = (guess_px.x.round() as i32, guess_px.y.round() as i32);
    let x0 = (cx - half).clamp(0, img.cols());
    let y0 = (cy - half).clamp(0, img.rows());
    let x1 = (cx + half).clamp(0, img.cols());
    let y1 = (cy + half).clamp(0, img.rows());
    if x1 - x0 < 8 || y1 - y0 < 8 {
        return Ok(None);
    }
    let roi = Mat::roi(img, Rect::new(x0, y0, x1 - x0, y1 - y0))?;
    let mut blur = Mat::default();
    imgproc::gaussian_blur_def(&roi, &mut blur, core::Size::new(3, 3), 0.0)?;
    let mut hsv = Mat::default();
    imgproc::cvt_color_def(&blur, &mut hsv, imgproc::COLOR_BGR2HSV)?;
    let mut mask = Mat::default();
    core::in_range(
        &hsv,
        &Scalar::new(HUE_BAND.0, 120.0, 60.0, 0.0),
        &Scalar::new(HUE_BAND.1, 255.0, 255.0, 0.0),
        &mut mask,
    )?;
    let mut contours = Vector::<Vector<Point>>::new();
    imgproc::find_contours_def(
        &mask,
        &mut contours,
        imgproc::RETR_EXTERNAL,
        imgproc::CHAIN_APPROX_NONE,
    )?;
    let mut best: Option<(f64, Vector2<f64>)> = None;
    for c in &contours {
        let m = imgproc::moments_def(&c)?;
        if m.m00 <= 0.0 {
            continue;
        }
        if best.is_none_or(|b| m.m00 > b.0) {
            best = Some((
                m.m00,
                Vector2::new(m.m10 / m.m00 + f64::from(x0), m.m01 / m.m00 + f64::from(y0)),
            ));
        }
    }
    let expect_area = std::f64::consts::PI * expect_r_px * expect_r_px;
    Ok(best
        .filter(|(a, _)| *a > 0.3 * expect_area && *a < 3.0 * expect_area)
        .map(|(_, c)| c))
}

/// Where the ball hangs during the step: the far end of the distances, m.
pub fn step_distance_m(s: &Scenario) -> f64 {
    s.task.distance_m.hi
}

/// `cv::solvePnP` (iterative, from the believed pose) on all sightings, then the
/// least-squares refinement (with `k1` unless the camera step gave it).
///
/// # Errors
///
/// [`ProcedureError::Vision`] when OpenCV fails; [`ProcedureError::Calibration`]
/// when the least-squares refinement refuses the sightings.
pub fn fit_pose(
    intrinsics: &CameraIntrinsics,
    points_b: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    believed: &CameraPose,
    k1_fixed: Option<f64>,
) -> Result<PnpFit, ProcedureError> {
    let obj: Vector<Point3d> = points_b
        .iter()
        .map(|p| Point3d::new(p.x, p.y, p.z))
        .collect();
    let img: Vector<Point2d> = pixels.iter().map(|p| Point2d::new(p.x, p.y)).collect();
    let k = Mat::from_slice_2d(&[
        [intrinsics.fx_px, 0.0, intrinsics.cx_px],
        [0.0, intrinsics.fy_px, intrinsics.cy_px],
        [0.0, 0.0, 1.0],
    ])?;
    let dist_v = [intrinsics.k1, intrinsics.k2, 0.0, 0.0];
    let dist = Mat::from_slice(&dist_v)?;
    let r0 = believed.base_from_camera().inverse();
    let t0 = -(r0 * believed.position());
    let rv0 = r0.scaled_axis();
    let mut rvec = Mat::from_slice(&[rv0.x, rv0.y, rv0.z])?.try_clone()?;
    let mut tvec = Mat::from_slice(&[t0.x, t0.y, t0.z])?.try_clone()?;
    let ok = calib3d::solve_pnp(
        &obj,
        &img,
        &k,
        &dist,
        &mut rvec,
        &mut tvec,
        true,
        calib3d::SOLVEPNP_ITERATIVE,
    )?;
    let get = |m: &Mat| -> Result<Vector3<f64>, ProcedureError> {
        Ok(Vector3::new(
            *m.at::<f64>(0)?,
            *m.at::<f64>(1)?,
            *m.at::<f64>(2)?,
        ))
    };
    let (r, t) = if ok {
        (Rotation3::new(get(&rvec)?), get(&tvec)?)
    } else {
        (r0, t0)
    };
    let start = (r.inverse(), -(r.inverse() * t));
    Ok(refine_pose(intrinsics, points_b, pixels, start, k1_fixed)?)
}
