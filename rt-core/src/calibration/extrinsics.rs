//! Camera to robot (pure part, no OpenCV): the camera's pose in the robot base
//! frame refined by least squares on marker sightings (base-frame points from the
//! robot's forward kinematics, their detected pixels), and the intercept point's
//! record. The procedure that collects the sightings is `sim_extrinsics` (on the
//! simulated world); `README.md` ("Camera to robot") gives frames and units.

use nalgebra::{Matrix3, Rotation3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::CalibrationError;
use super::lsq::levenberg_marquardt;
use crate::vision::{CameraIntrinsics, CameraPose};

/// The camera-robot step's result (the calibration file's `[camera_robot]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraRobotCalibration {
    /// The camera's pose in the robot base frame (centre in metres; yaw, pitch,
    /// roll in degrees as `vision::CameraPose`): what `apply` makes the lab believe.
    pub camera_pose: CameraPose,
    /// `base_from_camera` as rows (camera x right, y down, z along the optical axis).
    pub base_from_camera_rows: [[f64; 3]; 3],
    /// Root mean square of the marker reprojection residuals, pixels.
    pub reprojection_rms_px: f64,
    /// Marker poses used (seen in enough frames).
    pub poses: usize,
    /// Marker poses commanded.
    pub poses_commanded: usize,
    /// The radial distortion `k1` the fit used: the camera step's when the file had
    /// one, else fitted here beside the pose.
    pub k1: f64,
    /// Whether `k1` was fitted here (no camera step in the file).
    pub k1_fitted: bool,
    /// One standard deviation of the camera centre, base x y z, metres.
    pub position_std_m: [f64; 3],
    /// The marker's centre in the flange frame, metres (a constant of the tool).
    pub marker_offset_m: [f64; 3],
    /// The hanging ball's centre (the intercept point), robot base frame, metres.
    pub intercept_m: [f64; 3],
    /// `intercept_m` minus the nominal intercept point `(distance, 0,
    /// intercept_height)` at the step's distance (the far end of `task.distance_m`):
    /// `task.intercept_offset_m`.
    pub intercept_offset_m: [f64; 3],
    /// The ball's rest centre in the image, pixels.
    pub rest_px: [f64; 2],
    /// How the intercept point's depth (base x) was found: `"touch"` (the tool's
    /// disc touched the hanging ball) or `"plane"` (the believed swing plane).
    pub intercept_depth_from: String,
}

/// The camera's pose from `base_from_camera` and its centre.
pub fn camera_pose_of(base_from_camera: &Rotation3<f64>, position_m: &Vector3<f64>) -> CameraPose {
    // CameraPose: base_from_camera = Rz(yaw) Ry(pitch) Rx(roll) * nominal.
    let nominal = CameraPose {
        position_m: [0.0; 3],
        yaw_deg: 0.0,
        pitch_deg: 0.0,
        roll_deg: 0.0,
    }
    .base_from_camera();
    let m = base_from_camera * nominal.inverse();
    let (roll, pitch, yaw) = m.euler_angles();
    CameraPose {
        position_m: [position_m.x, position_m.y, position_m.z],
        yaw_deg: yaw.to_degrees(),
        pitch_deg: pitch.to_degrees(),
        roll_deg: roll.to_degrees(),
    }
}

/// The angle between two rotations, radians.
pub fn rotation_angle_rad(a: &Rotation3<f64>, b: &Rotation3<f64>) -> f64 {
    (a.inverse() * b).angle()
}

/// A fitted camera pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PnpFit {
    /// `base_from_camera`.
    pub base_from_camera: Rotation3<f64>,
    /// Camera centre, base frame, metres.
    pub position_m: Vector3<f64>,
    /// Radial distortion used or fitted.
    pub k1: f64,
    /// Reprojection RMS, pixels.
    pub rms_px: f64,
    /// One standard deviation of the centre, metres.
    pub position_std_m: Vector3<f64>,
}

/// Projects a base-frame point through a camera at `camera_from_base` (rotation
/// vector `r`, translation `t`) with `intrinsics` and radial `k1`.
fn project(
    intrinsics: &CameraIntrinsics,
    r: &Rotation3<f64>,
    t: &Vector3<f64>,
    k1: f64,
    p: &Vector3<f64>,
) -> Option<Vector2<f64>> {
    let k = CameraIntrinsics { k1, ..*intrinsics };
    k.project(&(r * p + t))
}

/// Refines the camera pose (and `k1` when `k1_fixed` is `None`) by
/// Levenberg-Marquardt on the reprojection residuals of `points_b` (base frame,
/// metres) seen at `pixels`, from `start` (`base_from_camera`, centre).
///
/// # Errors
///
/// [`CalibrationError::TooFewSamples`] with fewer than 4 points (5 when `k1` is
/// fitted) or when `pixels` and `points_b` differ in length;
/// [`CalibrationError::FitFailed`] when the fit does not converge or is not finite.
pub fn refine_pose(
    intrinsics: &CameraIntrinsics,
    points_b: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    start: (Rotation3<f64>, Vector3<f64>),
    k1_fixed: Option<f64>,
) -> Result<PnpFit, CalibrationError> {
    let n = points_b.len();
    let need = if k1_fixed.is_some() { 4 } else { 5 };
    if n < need || pixels.len() != n {
        return Err(CalibrationError::TooFewSamples {
            what: "marker poses",
            got: n.min(pixels.len()),
            need,
        });
    }
    // Parameters: a small rotation (vector) applied to the start's camera_from_base,
    // the translation, then k1.
    let r0 = start.0.inverse();
    let t0 = -(r0 * start.1);
    let unpack = |p: &[f64]| -> (Rotation3<f64>, Vector3<f64>, f64) {
        let dr = Rotation3::new(Vector3::new(p[0], p[1], p[2]));
        let k1 = k1_fixed.unwrap_or_else(|| p.get(6).copied().unwrap_or(0.0));
        (dr * r0, Vector3::new(p[3], p[4], p[5]), k1)
    };
    let mut start_p = vec![0.0, 0.0, 0.0, t0.x, t0.y, t0.z];
    let mut scale = vec![1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6];
    if k1_fixed.is_none() {
        start_p.push(0.0);
        scale.push(1e-6);
    }
    let fit = levenberg_marquardt(&start_p, &scale, 2 * n, 200, |p, out| {
        let (r, t, k1) = unpack(p);
        for (i, (pb, px)) in points_b.iter().zip(pixels).enumerate() {
            let Some(q) = project(intrinsics, &r, &t, k1, pb) else {
                return false;
            };
            out[2 * i] = q.x - px.x;
            out[2 * i + 1] = q.y - px.y;
        }
        true
    })
    .ok_or_else(|| CalibrationError::FitFailed {
        what: "camera pose",
        reason: "the marker points do not determine the pose (too few, or all in a line)"
            .to_owned(),
    })?;
    let (r, t, k1) = unpack(&fit.params);
    let base_from_camera = r.inverse();
    let position_m = -(base_from_camera * t);
    // The centre's spread: c = -R^T t, with t's spread (rotation's neglected: the
    // centre's uncertainty is dominated by depth along the optical axis).
    let cov_t = Matrix3::from_diagonal(&Vector3::new(
        fit.std[3].powi(2),
        fit.std[4].powi(2),
        fit.std[5].powi(2),
    ));
    let cov_c = base_from_camera.matrix() * cov_t * base_from_camera.matrix().transpose();
    if !(fit.rms.is_finite() && position_m.iter().all(|v| v.is_finite())) {
        return Err(CalibrationError::FitFailed {
            what: "camera pose",
            reason: "not finite".to_owned(),
        });
    }
    Ok(PnpFit {
        base_from_camera,
        position_m,
        k1,
        rms_px: fit.rms,
        position_std_m: Vector3::new(
            cov_c[(0, 0)].sqrt(),
            cov_c[(1, 1)].sqrt(),
            cov_c[(2, 2)].sqrt(),
        ),
    })
}

/// Reprojects `points_b` through a fitted pose.
pub fn reproject(
    intrinsics: &CameraIntrinsics,
    fit: &PnpFit,
    points_b: &[Vector3<f64>],
) -> Vec<[f64; 2]> {
    let r = fit.base_from_camera.inverse();
    let t = -(r * fit.position_m);
    points_b
        .iter()
        .filter_map(|p| project(intrinsics, &r, &t, fit.k1, p))
        .map(|q| [q.x, q.y])
        .collect()
}

/// The ray through pixel `(u, v)` of the fitted camera, base frame (unit).
pub fn ray_b(intrinsics: &CameraIntrinsics, fit: &PnpFit, u_px: f64, v_px: f64) -> Vector3<f64> {
    let k = CameraIntrinsics {
        k1: fit.k1,
        ..*intrinsics
    };
    (fit.base_from_camera * k.ray(u_px, v_px)).normalize()
}
