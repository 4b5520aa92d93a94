//! Camera intrinsics and distortion from views of a chessboard: OpenCV's
//! `calibrateCameraExtended` on the detected inner corners of each view (the
//! board's corners on its own plane, `z = 0`, metres). The model is OpenCV's
//! pinhole with Brown-Conrady distortion `k1, k2, p1, p2` (`k3` fixed to 0: a
//! webcam's 70 degree lens needs no sixth-order term and a free `k3` trades
//! against `k1`).
//!
//! The types are plain data (the calibration file holds them in every build);
//! the fit needs the `opencv` feature.

use serde::{Deserialize, Serialize};

use super::CalibrationError;
use crate::vision::CameraIntrinsics;
#[cfg(feature = "opencv")]
use crate::vision::VisionError;

/// Views with the board found that the fit needs at least.
pub const MIN_VIEWS: usize = 8;
/// A fit whose RMS reprojection error is larger than this is refused, pixels
/// (a sharp board gives ~0.1-0.3 px; more means wrong corners or a moving board).
pub const MAX_RMS_PX: f64 = 2.0;

/// A printed chessboard: its inner corners (where four squares meet) and the
/// size of its squares.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Chessboard {
    /// Inner corners along a row (OpenCV's `patternSize.width`).
    pub inner_cols: u32,
    /// Inner corners along a column (`patternSize.height`).
    pub inner_rows: u32,
    /// Side of a square, metres (measure the print: printers scale).
    pub square_m: f64,
}

impl Default for Chessboard {
    /// 9 x 6 inner corners (10 x 7 squares), 30 mm squares: OpenCV's sample
    /// board printed on A3.
    fn default() -> Self {
        Self {
            inner_cols: 9,
            inner_rows: 6,
            square_m: 0.03,
        }
    }
}

impl Chessboard {
    /// Checks the board; the error names the bad value.
    ///
    /// # Errors
    ///
    /// [`CalibrationError::FitFailed`] when a side has outside 3..=40 inner corners, the
    /// board is square, or the square size is outside 0.002..=0.5 m (or not finite).
    pub fn validate(&self) -> Result<(), CalibrationError> {
        let ok = (3..=40).contains(&self.inner_cols)
            && (3..=40).contains(&self.inner_rows)
            && self.inner_cols != self.inner_rows
            && self.square_m.is_finite()
            && (0.002..=0.5).contains(&self.square_m);
        if ok {
            Ok(())
        } else {
            Err(CalibrationError::FitFailed {
                what: "camera intrinsics",
                reason: format!(
                    "chessboard {}x{} inner corners, {} m squares: need 3..=40 corners each way \
                     (not square: its orientation must be unambiguous) and squares 0.002..=0.5 m",
                    self.inner_cols, self.inner_rows, self.square_m
                ),
            })
        }
    }

    /// Number of inner corners.
    pub fn corners(&self) -> usize {
        self.inner_cols as usize * self.inner_rows as usize
    }

    /// The inner corners on the board's plane, metres, in OpenCV's order (row
    /// by row, `inner_cols` per row): `(col * square, row * square, 0)`.
    pub fn object_points(&self) -> Vec<[f64; 3]> {
        let s = self.square_m;
        (0..self.inner_rows)
            .flat_map(|r| {
                (0..self.inner_cols).map(move |c| [f64::from(c) * s, f64::from(r) * s, 0.0])
            })
            .collect()
    }
}

/// One view of the board: its detected inner corners, pixels, in the order of
/// [`Chessboard::object_points`] (`None`: the board was not found in that frame).
#[derive(Debug, Clone, PartialEq)]
pub struct BoardView {
    /// Detected corners, pixels (x right, y down, pixel centres at integers).
    pub corners_px: Option<Vec<[f64; 2]>>,
}

/// The camera step's result (the calibration file's `[camera.result]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraCalibration {
    /// Image width the intrinsics are for, pixels.
    pub width_px: u32,
    /// Image height, pixels.
    pub height_px: u32,
    /// The fitted focal lengths, principal point and distortion (what the lab
    /// believes after this step).
    pub intrinsics: CameraIntrinsics,
    /// Standard deviations of `fx, fy, cx, cy` (pixels) and `k1, k2, p1, p2`,
    /// in that order (OpenCV's, from the fit's Jacobian and residuals).
    pub std_dev: [f64; 8],
    /// RMS reprojection error over all corners of all views, pixels.
    pub rms_px: f64,
    /// RMS reprojection error of each view used, pixels.
    pub per_view_rms_px: Vec<f64>,
    /// Views with the board found (the fit's views).
    pub views_used: usize,
    /// Frames the board was looked for in.
    pub views_shown: usize,
    /// The board.
    pub board: Chessboard,
}

/// The fit and, per view used, the corners the fitted camera puts where the
/// board was (for the live view), pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct IntrinsicsFit {
    /// The result.
    pub calibration: CameraCalibration,
    /// Per view used: (index into the views given, reprojected corners).
    pub reprojected: Vec<(usize, Vec<[f64; 2]>)>,
}

impl IntrinsicsFit {
    /// The fit as the step's live view shows it: per view used (of the
    /// `seen` views given to the fit, `views` asked for), its detected and
    /// reprojected corners and its RMS.
    pub fn views(&self, seen: &[BoardView], views: usize) -> Vec<super::StepView> {
        self.reprojected
            .iter()
            .enumerate()
            .map(|(k, (index, reprojected))| super::StepView {
                progress: 1.0,
                message: format!(
                    "fit: view {} of {views}: RMS {:.3} px (all views {:.3} px)",
                    index + 1,
                    self.calibration
                        .per_view_rms_px
                        .get(k)
                        .copied()
                        .unwrap_or(f64::NAN),
                    self.calibration.rms_px
                ),
                kind: super::ViewKind::Image,
                points: seen
                    .get(*index)
                    .and_then(|v| v.corners_px.clone())
                    .unwrap_or_default(),
                fit: reprojected.clone(),
            })
            .collect()
    }
}

/// Calibrates the camera from `views` of `board` in `width_px x height_px`
/// frames (OpenCV's `calibrateCameraExtended`, `k3` fixed). Refused: the board
/// found in no view ("no board visible"), fewer than [`MIN_VIEWS`] views with
/// it, a view with the wrong number of corners or a non-finite one, a fit that
/// is not finite or whose RMS is above [`MAX_RMS_PX`].
///
/// # Errors
///
/// [`CalibrationError::BoardNotSeen`] when no view has the board;
/// [`CalibrationError::TooFewSamples`] with fewer than [`MIN_VIEWS`] views;
/// [`CalibrationError::NotFinite`] for a non-finite corner; otherwise
/// [`CalibrationError::FitFailed`] (a bad board, a view's corner count, an OpenCV
/// error, a non-camera fit, an RMS above [`MAX_RMS_PX`]).
#[cfg(feature = "opencv")]
pub fn fit_intrinsics(
    board: &Chessboard,
    views: &[BoardView],
    width_px: u32,
    height_px: u32,
) -> Result<IntrinsicsFit, CalibrationError> {
    use opencv::{
        calib3d,
        core::{self, Mat, MatTraitConst, Point2f, Point3f, Vector},
    };
    board.validate()?;
    let cv = |e: opencv::Error| CalibrationError::FitFailed {
        what: "camera intrinsics",
        reason: format!("OpenCV: {e}"),
    };
    let used: Vec<(usize, &Vec<[f64; 2]>)> = views
        .iter()
        .enumerate()
        .filter_map(|(i, v)| v.corners_px.as_ref().map(|c| (i, c)))
        .collect();
    if used.is_empty() {
        return Err(CalibrationError::BoardNotSeen {
            shown: views.len(),
            inner_cols: board.inner_cols,
            inner_rows: board.inner_rows,
        });
    }
    if used.len() < MIN_VIEWS {
        return Err(CalibrationError::TooFewSamples {
            what: "chessboard views (hold the board at more poses)",
            got: used.len(),
            need: MIN_VIEWS,
        });
    }
    let n = board.corners();
    let object: Vector<Point3f> = board
        .object_points()
        .iter()
        .map(|p| Point3f::new(p[0] as f32, p[1] as f32, p[2] as f32))
        .collect();
    let mut object_points = Vector::<Vector<Point3f>>::new();
    let mut image_points = Vector::<Vector<Point2f>>::new();
    for (index, (_, corners)) in used.iter().enumerate() {
        if corners.len() != n {
            return Err(CalibrationError::FitFailed {
                what: "camera intrinsics",
                reason: format!(
                    "view {index}: {} corners, the {}x{} board has {n}",
                    corners.len(),
                    board.inner_cols,
                    board.inner_rows
                ),
            });
        }
        if let Some(bad) = corners
            .iter()
            .position(|c| !(c[0].is_finite() && c[1].is_finite()))
        {
            return Err(CalibrationError::NotFinite {
                what: "chessboard corner",
                index: index * n + bad,
            });
        }
        object_points.push(object.clone());
        image_points.push(
            corners
                .iter()
                .map(|c| Point2f::new(c[0] as f32, c[1] as f32))
                .collect(),
        );
    }
    let size = core::Size::new(
        i32::try_from(width_px).unwrap_or(i32::MAX),
        i32::try_from(height_px).unwrap_or(i32::MAX),
    );
    let mut camera = Mat::default();
    let mut dist = Mat::default();
    let mut rvecs = Vector::<Mat>::new();
    let mut tvecs = Vector::<Mat>::new();
    let mut std_in = Mat::default();
    let mut std_ex = Mat::default();
    let mut per_view = Mat::default();
    let criteria = core::TermCriteria::new(
        core::TermCriteria_COUNT + core::TermCriteria_EPS,
        100,
        f64::EPSILON,
    )
    .map_err(cv)?;
    let rms = calib3d::calibrate_camera_extended(
        &object_points,
        &image_points,
        size,
        &mut camera,
        &mut dist,
        &mut rvecs,
        &mut tvecs,
        &mut std_in,
        &mut std_ex,
        &mut per_view,
        calib3d::CALIB_FIX_K3,
        criteria,
    )
    .map_err(cv)?;
    let at = |m: &Mat, r: i32, c: i32| -> Result<f64, CalibrationError> {
        m.at_2d::<f64>(r, c).copied().map_err(cv)
    };
    let flat = |m: &Mat, i: i32| -> Result<f64, CalibrationError> {
        if m.rows() == 1 {
            at(m, 0, i)
        } else {
            at(m, i, 0)
        }
    };
    let intrinsics = CameraIntrinsics {
        fx_px: at(&camera, 0, 0)?,
        fy_px: at(&camera, 1, 1)?,
        cx_px: at(&camera, 0, 2)?,
        cy_px: at(&camera, 1, 2)?,
        k1: flat(&dist, 0)?,
        k2: flat(&dist, 1)?,
        p1: flat(&dist, 2)?,
        p2: flat(&dist, 3)?,
    };
    let mut std_dev = [f64::NAN; 8];
    if std_in.total() >= 8 {
        for (i, s) in std_dev.iter_mut().enumerate() {
            *s = flat(&std_in, i as i32)?;
        }
    }
    let per_view_rms_px = (0..per_view.total() as i32)
        .map(|i| flat(&per_view, i))
        .collect::<Result<Vec<_>, _>>()?;
    let finite = [
        intrinsics.fx_px,
        intrinsics.fy_px,
        intrinsics.cx_px,
        intrinsics.cy_px,
        intrinsics.k1,
        intrinsics.k2,
        intrinsics.p1,
        intrinsics.p2,
        rms,
    ]
    .iter()
    .all(|v| v.is_finite());
    if !finite || intrinsics.fx_px <= 0.0 || intrinsics.fy_px <= 0.0 {
        return Err(CalibrationError::FitFailed {
            what: "camera intrinsics",
            reason: format!("the fit is not a camera: {intrinsics:?}, RMS {rms} px"),
        });
    }
    if rms > MAX_RMS_PX {
        return Err(CalibrationError::FitFailed {
            what: "camera intrinsics",
            reason: format!(
                "RMS reprojection error {rms:.2} px, at most {MAX_RMS_PX} px accepted \
                 (is the board flat, still and the square size right?)"
            ),
        });
    }
    // The corners where the fitted camera puts the board of each view.
    let mut reprojected = Vec::with_capacity(used.len());
    for (k, (index, _)) in used.iter().enumerate() {
        let mut pts = Vector::<Point2f>::new();
        calib3d::project_points_def(
            &object,
            &rvecs.get(k).map_err(cv)?,
            &tvecs.get(k).map_err(cv)?,
            &camera,
            &dist,
            &mut pts,
        )
        .map_err(cv)?;
        reprojected.push((
            *index,
            pts.iter()
                .map(|p| [f64::from(p.x), f64::from(p.y)])
                .collect(),
        ));
    }
    Ok(IntrinsicsFit {
        calibration: CameraCalibration {
            width_px,
            height_px,
            intrinsics,
            std_dev,
            rms_px: rms,
            per_view_rms_px,
            views_used: used.len(),
            views_shown: views.len(),
            board: *board,
        },
        reprojected,
    })
}

/// Finds the board's inner corners as a lab does: `findChessboardCorners`
/// (adaptive threshold, normalised image, the fast check) on the frame halved
/// (on a cluttered 1280 x 720 scene without a board the full-size adaptive
/// search takes ~10 s a frame, the halved one ~20 ms), else on the full frame
/// with one threshold; then `cornerSubPix` on the full frame with a window
/// smaller than half the smallest square seen.
///
/// # Errors
///
/// [`VisionError::OpenCv`] when an OpenCV call fails (a board not found is
/// `Ok(None)`).
#[cfg(feature = "opencv")]
pub fn detect_corners(
    gray: &opencv::core::Mat,
    board: &Chessboard,
) -> Result<Option<Vec<[f64; 2]>>, VisionError> {
    use opencv::{
        calib3d,
        core::{self, Mat, MatTraitConst, Point2f, Size, Vector},
        imgproc,
    };
    let pattern = Size::new(board.inner_cols as i32, board.inner_rows as i32);
    let mut half = Mat::default();
    imgproc::resize(
        gray,
        &mut half,
        Size::new(gray.cols() / 2, gray.rows() / 2),
        0.0,
        0.0,
        imgproc::INTER_AREA,
    )?;
    let mut coarse = Vector::<Point2f>::new();
    let found = calib3d::find_chessboard_corners(
        &half,
        pattern,
        &mut coarse,
        calib3d::CALIB_CB_ADAPTIVE_THRESH
            | calib3d::CALIB_CB_NORMALIZE_IMAGE
            | calib3d::CALIB_CB_FAST_CHECK,
    )?;
    let mut corners = Vector::<Point2f>::new();
    if found && coarse.len() == board.corners() {
        // Half-frame pixel centres to full-frame ones: u = 2 u' + 1/2.
        corners = coarse
            .iter()
            .map(|p| Point2f::new(2.0 * p.x + 0.5, 2.0 * p.y + 0.5))
            .collect();
    } else {
        // A small or steep board: the full frame, one global threshold
        // (normalised image) and the fast check (~0.15 s without a board).
        let found = calib3d::find_chessboard_corners(
            gray,
            pattern,
            &mut corners,
            calib3d::CALIB_CB_NORMALIZE_IMAGE | calib3d::CALIB_CB_FAST_CHECK,
        )?;
        if !found || corners.len() != board.corners() {
            return Ok(None);
        }
    }
    // The smallest spacing of neighbouring corners along the rows.
    let cols = board.inner_cols as usize;
    let mut spacing = f64::MAX;
    for (k, p) in corners.iter().enumerate() {
        if (k + 1) % cols != 0
            && let Ok(q) = corners.get(k + 1)
        {
            spacing = spacing.min(f64::from(p.x - q.x).hypot(f64::from(p.y - q.y)));
        }
        if let Ok(q) = corners.get(k + cols) {
            spacing = spacing.min(f64::from(p.x - q.x).hypot(f64::from(p.y - q.y)));
        }
    }
    let win = ((0.4 * spacing).floor() as i32).clamp(2, 11);
    imgproc::corner_sub_pix(
        gray,
        &mut corners,
        Size::new(win, win),
        Size::new(-1, -1),
        core::TermCriteria::new(core::TermCriteria_COUNT + core::TermCriteria_EPS, 50, 1e-3)?,
    )?;
    Ok(Some(
        corners
            .iter()
            .map(|p| [f64::from(p.x), f64::from(p.y)])
            .collect(),
    ))
}
