//! Pinhole camera model and the pixel -> swing-plane conversion.
//!
//! Frames: the robot base frame `b` (x forward towards the pendulum, z up, y to the
//! left) and the camera frame `c` (OpenCV convention: x right in the image, y down,
//! z along the optical axis). Pixel coordinates have pixel centres at integers.

use nalgebra::{Matrix3, Rotation3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::VisionError;
use crate::check::{self, ParamError};

/// Pinhole intrinsics with OpenCV's Brown-Conrady distortion: two radial terms
/// (`k1, k2`; `k3` is taken as zero) and two tangential ones (`p1, p2`) on
/// normalised coordinates, as `cv::calibrateCamera` gives them
/// (`isochron calibrate camera`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraIntrinsics {
    /// Focal length along image columns, pixels.
    pub fx_px: f64,
    /// Focal length along image rows, pixels.
    pub fy_px: f64,
    /// Principal point, column, pixels.
    pub cx_px: f64,
    /// Principal point, row, pixels.
    pub cy_px: f64,
    /// Radial distortion, r^2 term.
    pub k1: f64,
    /// Radial distortion, r^4 term.
    pub k2: f64,
    /// Tangential distortion `p1` (absent in older files: 0).
    pub p1: f64,
    /// Tangential distortion `p2` (absent in older files: 0).
    pub p2: f64,
}

impl Default for CameraIntrinsics {
    /// A Logitech C920 at 1280x720: 70 degrees horizontal field of view, no distortion.
    fn default() -> Self {
        Self::from_hfov(1280, 720, 70.0)
    }
}

impl CameraIntrinsics {
    /// Square pixels, principal point at the image centre, given horizontal field of view.
    pub fn from_hfov(width_px: u32, height_px: u32, hfov_deg: f64) -> Self {
        let f = 0.5 * f64::from(width_px) / (0.5 * hfov_deg.to_radians()).tan();
        Self {
            fx_px: f,
            fy_px: f,
            cx_px: 0.5 * f64::from(width_px) - 0.5,
            cy_px: 0.5 * f64::from(height_px) - 0.5,
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
        }
    }

    /// Checks every field; `prefix` is the dotted path of this struct.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first field
    /// that is not finite or outside its range.
    pub fn validate(&self, prefix: &str) -> Result<(), ParamError> {
        check::within(&format!("{prefix}.fx_px"), self.fx_px, 10.0, 1e5)?;
        check::within(&format!("{prefix}.fy_px"), self.fy_px, 10.0, 1e5)?;
        check::within(&format!("{prefix}.cx_px"), self.cx_px, -1e4, 1e4)?;
        check::within(&format!("{prefix}.cy_px"), self.cy_px, -1e4, 1e4)?;
        check::within(&format!("{prefix}.k1"), self.k1, -1.0, 1.0)?;
        check::within(&format!("{prefix}.k2"), self.k2, -1.0, 1.0)?;
        check::within(&format!("{prefix}.p1"), self.p1, -0.1, 0.1)?;
        check::within(&format!("{prefix}.p2"), self.p2, -0.1, 0.1)
    }

    /// Whether the lens has any distortion term.
    pub fn has_distortion(&self) -> bool {
        self.k1 != 0.0 || self.k2 != 0.0 || self.p1 != 0.0 || self.p2 != 0.0
    }

    /// Distorts normalised coordinates `(x, y)` (Brown-Conrady, OpenCV's model
    /// with `k3 = 0`).
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2;
        (
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// Projects a point in the camera frame (metres) to pixels; `None` behind the camera.
    pub fn project(&self, p_c: &Vector3<f64>) -> Option<Vector2<f64>> {
        if p_c.z <= 1e-6 {
            return None;
        }
        let (x, y) = self.distort(p_c.x / p_c.z, p_c.y / p_c.z);
        Some(Vector2::new(
            self.fx_px * x + self.cx_px,
            self.fy_px * y + self.cy_px,
        ))
    }

    /// The ray through a pixel, in the camera frame, scaled to z = 1 (distortion removed).
    ///
    /// Allocation-free; the detector calls it per frame.
    pub fn ray(&self, u_px: f64, v_px: f64) -> Vector3<f64> {
        let xd = (u_px - self.cx_px) / self.fx_px;
        let yd = (v_px - self.cy_px) / self.fy_px;
        let (mut x, mut y) = (xd, yd);
        if self.has_distortion() {
            // Fixed-point undistortion (OpenCV's undistortPoints does the same):
            // x = (xd - tangential(x, y)) / radial(x, y). It contracts by about
            // 2 |k1| r^2 per step: 20 steps reach 1e-8 px even in a 70 degree
            // lens's corners with k1 = -0.3.
            for _ in 0..20 {
                let r2 = x * x + y * y;
                let radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2;
                if radial.abs() < 1e-6 {
                    break;
                }
                let dx = 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
                let dy = self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
                x = (xd - dx) / radial;
                y = (yd - dy) / radial;
            }
        }
        Vector3::new(x, y, 1.0)
    }
}

/// Where the camera stands and where it looks, in the robot base frame.
///
/// With all angles zero the camera looks along the base's +x with the image's
/// right along base -y and the image's down along base -z. Then, applied in the
/// base frame: roll about the optical axis, pitch (positive looks down), yaw
/// (positive looks left, towards +y).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraPose {
    /// Camera centre in the robot base frame, metres.
    pub position_m: [f64; 3],
    /// Rotation about base z, degrees (positive: looks towards +y).
    pub yaw_deg: f64,
    /// Rotation about base y, degrees (positive: looks down).
    pub pitch_deg: f64,
    /// Rotation about the optical axis, degrees.
    pub roll_deg: f64,
}

impl Default for CameraPose {
    /// Beside and behind the robot, 0.25 m to its left, at 0.45 m, looking along +x.
    fn default() -> Self {
        Self {
            position_m: [-1.0, 0.25, 0.45],
            yaw_deg: 0.0,
            pitch_deg: 0.0,
            roll_deg: 0.0,
        }
    }
}

impl CameraPose {
    /// Checks every field; `prefix` is the dotted path of this struct.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first field
    /// that is not finite or outside its range.
    pub fn validate(&self, prefix: &str) -> Result<(), ParamError> {
        for (i, v) in self.position_m.iter().enumerate() {
            check::within(&format!("{prefix}.position_m[{i}]"), *v, -10.0, 10.0)?;
        }
        check::within(&format!("{prefix}.yaw_deg"), self.yaw_deg, -60.0, 60.0)?;
        check::within(&format!("{prefix}.pitch_deg"), self.pitch_deg, -60.0, 60.0)?;
        check::within(&format!("{prefix}.roll_deg"), self.roll_deg, -30.0, 30.0)
    }

    /// The rotation taking camera-frame vectors to base-frame vectors.
    pub fn base_from_camera(&self) -> Rotation3<f64> {
        // Columns: the camera's x, y, z axes written in the base frame.
        let nominal = Rotation3::from_matrix_unchecked(Matrix3::new(
            0.0, 0.0, 1.0, //
            -1.0, 0.0, 0.0, //
            0.0, -1.0, 0.0,
        ));
        let yaw = Rotation3::from_axis_angle(&Vector3::z_axis(), self.yaw_deg.to_radians());
        let pitch = Rotation3::from_axis_angle(&Vector3::y_axis(), self.pitch_deg.to_radians());
        let roll = Rotation3::from_axis_angle(&Vector3::x_axis(), self.roll_deg.to_radians());
        yaw * pitch * roll * nominal
    }

    /// The camera centre as a vector.
    pub fn position(&self) -> Vector3<f64> {
        Vector3::from(self.position_m)
    }

    /// A base-frame point expressed in the camera frame.
    pub fn to_camera(&self, p_b: &Vector3<f64>) -> Vector3<f64> {
        self.base_from_camera().inverse() * (p_b - self.position())
    }
}

/// Pixel -> lateral position on the pendulum's swing plane.
///
/// The swing plane is vertical, perpendicular to the base's x axis, and contains
/// the ball's rest position. The lateral coordinate is measured along the base's
/// +y from the rest position: the paper's x = l sin(phi). Everything is stored in
/// the camera frame, so the conversion needs no camera position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SwingPlaneCalibration {
    /// The camera's intrinsics.
    pub intrinsics: CameraIntrinsics,
    /// Rest position of the ball centre, camera frame, metres.
    pub rest_c: Vector3<f64>,
    /// Plane normal (base +x), camera frame.
    pub normal_c: Vector3<f64>,
    /// Lateral axis (base +y), camera frame.
    pub lateral_c: Vector3<f64>,
    /// Ball radius, metres (for the size cross-check).
    pub ball_radius_m: f64,
}

/// What a calibration from the ball at rest found.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CalibrationReport {
    /// The distance the user gave: camera centre -> ball centre, metres.
    pub given_distance_m: f64,
    /// The distance implied by the ball's apparent size, metres.
    pub size_distance_m: f64,
    /// `size_distance_m / given_distance_m - 1`.
    pub relative_disagreement: f64,
    /// Camera centre in the base frame implied by the rest position, metres.
    pub camera_position_m: [f64; 3],
    /// Horizontal distance camera -> swing plane along base x, metres.
    pub plane_distance_m: f64,
}

impl SwingPlaneCalibration {
    /// The calibration when the camera's pose and the rest position are known exactly
    /// (the simulated lab, or a surveyed setup).
    pub fn from_pose(
        intrinsics: CameraIntrinsics,
        pose: &CameraPose,
        rest_b: &Vector3<f64>,
        ball_radius_m: f64,
    ) -> Self {
        let r_cb = pose.base_from_camera().inverse();
        Self {
            intrinsics,
            rest_c: pose.to_camera(rest_b),
            normal_c: r_cb * Vector3::x(),
            lateral_c: r_cb * Vector3::y(),
            ball_radius_m,
        }
    }

    /// Calibrates the plane from the hanging ball at rest.
    ///
    /// `(u_px, v_px, r_px)` is the detected ball (average several frames), and
    /// `distance_m` the measured camera centre -> ball centre distance. The camera's
    /// orientation comes from `pose` (its position is ignored and reported back,
    /// computed from `rest_b`, the rest position in the base frame). The apparent
    /// size gives a second distance; if the two differ by more than
    /// `size_tolerance` (relative) the calibration is refused.
    ///
    /// # Errors
    ///
    /// [`VisionError::Param`] for bad intrinsics, pose, distance, radius, tolerance or
    /// detection; [`VisionError::PlaneEdgeOn`] when the camera looks along the swing
    /// plane; [`VisionError::SizeDisagrees`] when the two distances differ too much.
    pub fn from_rest_observation(
        intrinsics: CameraIntrinsics,
        pose: &CameraPose,
        rest_b: &Vector3<f64>,
        (u_px, v_px, r_px): (f64, f64, f64),
        distance_m: f64,
        ball_radius_m: f64,
        size_tolerance: f64,
    ) -> Result<(Self, CalibrationReport), VisionError> {
        intrinsics.validate("calibration.intrinsics")?;
        pose.validate("calibration.pose")?;
        check::within("calibration.distance_m", distance_m, 0.1, 20.0)?;
        check::within("calibration.ball_radius_m", ball_radius_m, 0.005, 0.2)?;
        check::within("calibration.size_tolerance", size_tolerance, 0.0, 1.0)?;
        check::finite("calibration.u_px", u_px)?;
        check::finite("calibration.v_px", v_px)?;
        check::within("calibration.r_px", r_px, 1.0, 1e4)?;
        let ray = intrinsics.ray(u_px, v_px);
        let rest_c = ray.normalize() * distance_m;
        let r_bc = pose.base_from_camera();
        let r_cb = r_bc.inverse();
        let cal = Self {
            intrinsics,
            rest_c,
            normal_c: r_cb * Vector3::x(),
            lateral_c: r_cb * Vector3::y(),
            ball_radius_m,
        };
        let size_distance_m = cal.distance_from_size_m(u_px, v_px, r_px);
        let relative_disagreement = size_distance_m / distance_m - 1.0;
        let camera = rest_b - r_bc * rest_c;
        let report = CalibrationReport {
            given_distance_m: distance_m,
            size_distance_m,
            relative_disagreement,
            camera_position_m: [camera.x, camera.y, camera.z],
            plane_distance_m: rest_c.dot(&cal.normal_c),
        };
        if cal.normal_c.dot(&ray).abs() < 1e-3 {
            return Err(VisionError::PlaneEdgeOn);
        }
        if relative_disagreement.abs() > size_tolerance {
            return Err(VisionError::SizeDisagrees {
                given_distance_m: distance_m,
                size_distance_m,
                relative_disagreement,
                tolerance: size_tolerance,
            });
        }
        Ok((cal, report))
    }

    /// Lateral position (metres, along base +y, zero at rest) of the ball whose
    /// centre is seen at pixel `(u_px, v_px)`; `None` when the ray misses the plane.
    ///
    /// Allocation-free; the control step may call it.
    pub fn lateral_m(&self, u_px: f64, v_px: f64) -> Option<f64> {
        let ray = self.intrinsics.ray(u_px, v_px);
        let den = self.normal_c.dot(&ray);
        if den.abs() < 1e-9 {
            return None;
        }
        let s = self.normal_c.dot(&self.rest_c) / den;
        if s <= 0.0 {
            return None;
        }
        Some(self.lateral_c.dot(&(ray * s - self.rest_c)))
    }

    /// The ball centre in the camera frame for a pixel, on the swing plane.
    pub fn point_on_plane_c(&self, u_px: f64, v_px: f64) -> Option<Vector3<f64>> {
        let ray = self.intrinsics.ray(u_px, v_px);
        let den = self.normal_c.dot(&ray);
        if den.abs() < 1e-9 {
            return None;
        }
        let s = self.normal_c.dot(&self.rest_c) / den;
        (s > 0.0).then(|| ray * s)
    }

    /// Camera -> ball distance implied by an apparent radius `r_px` at `(u_px, v_px)`.
    ///
    /// Uses the angle the radius subtends across the radial direction (where a
    /// sphere's silhouette is not stretched): distance = R / sin(alpha).
    pub fn distance_from_size_m(&self, u_px: f64, v_px: f64, r_px: f64) -> f64 {
        let k = &self.intrinsics;
        let a = k.ray(u_px, v_px);
        let (du, dv) = ((u_px - k.cx_px) / k.fx_px, (v_px - k.cy_px) / k.fy_px);
        let n = du.hypot(dv);
        // Unit tangential direction in pixels (any direction at the image centre).
        let (tu, tv) = if n > 1e-9 {
            (-dv / n, du / n)
        } else {
            (1.0, 0.0)
        };
        let b = k.ray(u_px + r_px * tu, v_px + r_px * tv);
        let cos = a.dot(&b) / (a.norm() * b.norm());
        let sin = (1.0 - cos * cos).max(0.0).sqrt();
        if sin <= 1e-12 {
            return f64::INFINITY;
        }
        self.ball_radius_m / sin
    }
}

/// How far `believed`'s undistortion puts the point the true camera shows at
/// pixel `(u, v)` from its true pinhole projection, pixels: each camera maps its
/// own undistorted ray back through its own pinhole (`K (x, y, 1)`), so a
/// focal length traded against `k1` by the fit does not count, only what is
/// left of the lens.
pub fn undistortion_error_px(
    truth: &CameraIntrinsics,
    believed: &CameraIntrinsics,
    u: f64,
    v: f64,
) -> f64 {
    let pinhole = |k: &CameraIntrinsics| {
        let r = k.ray(u, v);
        nalgebra::Vector2::new(k.fx_px * r.x + k.cx_px, k.fy_px * r.y + k.cy_px)
    };
    (pinhole(believed) - pinhole(truth)).norm()
}
