//! The camera step on the simulated world: a virtual operator holds a printed
//! chessboard in front of the true camera at varied poses; each frame is
//! rendered through the true camera (its lens bends the board's lines) over
//! the lab's rendered scene, and the board's corners are found as a real lab
//! finds them (`cv::findChessboardCorners` + `cv::cornerSubPix`). The procedure
//! never reads a true corner pixel: it hands the detections to
//! [`fit_intrinsics`](super::fit_intrinsics).

use nalgebra::{Rotation3, Unit, Vector2, Vector3};
use opencv::{
    calib3d,
    core::{
        self, Mat, MatTraitConst, MatTraitConstManual, MatTraitManual, Point, Point2f, Rect,
        Scalar, Size, Vector,
    },
    imgproc,
};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::intrinsics::{BoardView, CameraCalibration, Chessboard, fit_intrinsics};
use super::simworld::{HiddenWorld, ProcedureError};
use super::view::{StepView, ViewKind, Watch};
use crate::params::Scenario;
use crate::sim::camera::{SimCamera, SimCameraParams};
use crate::sim::world::camera::WorldCamera;
use crate::vision::CameraIntrinsics;

/// Supersampling of the board's rendering (per axis): the coverage of each
/// pixel by the board's squares is the mean over `SS x SS` sub-pixels.
const SS: i32 = 4;
/// Fixed-point bits of the polygon vertices handed to `fillPoly`.
const SHIFT: i32 = 6;
/// Segments each square's side is cut into before projecting (the lens bends it).
const SIDE_SEGMENTS: usize = 6;
/// Grey levels of the print: paper and ink (before the scene's lighting).
const PAPER: f64 = 215.0;
const INK: f64 = 28.0;
/// White margin around the squares, in squares.
const MARGIN_SQUARES: f64 = 1.0;
/// Pixels the board (with its margin) keeps from the image's edges.
const EDGE_PX: f64 = 8.0;

/// The camera step on the simulated world, with the truth beside the result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraRun {
    /// What the step measured.
    pub result: CameraCalibration,
    /// The true camera's intrinsics and lens.
    pub truth: CameraIntrinsics,
}

/// Where the operator holds the board: its centre at `depth_m` along the ray
/// through `aim` (normalised image coordinates, the undistorted pinhole's),
/// facing the camera, then tilted and turned in its plane.
#[derive(Debug, Clone, Copy)]
struct Hold {
    aim: Vector2<f64>,
    depth_m: f64,
    tilt_rad: f64,
    tilt_dir_rad: f64,
    roll_rad: f64,
}

/// The board's geometry in the camera frame for one hold: `point(x, y)` of the
/// board's plane (metres, the object points' frame) in the camera frame.
struct Placed {
    rot: Rotation3<f64>,
    centre_c: Vector3<f64>,
    centre_obj: Vector2<f64>,
}

impl Placed {
    fn new(board: &Chessboard, hold: &Hold) -> Self {
        let ray = Vector3::new(hold.aim.x, hold.aim.y, 1.0);
        let face =
            Rotation3::rotation_between(&Vector3::z(), &ray).unwrap_or_else(Rotation3::identity);
        let axis = Unit::new_normalize(Vector3::new(
            hold.tilt_dir_rad.cos(),
            hold.tilt_dir_rad.sin(),
            0.0,
        ));
        let tilt = Rotation3::from_axis_angle(&axis, hold.tilt_rad);
        let roll = Rotation3::from_axis_angle(&Vector3::z_axis(), hold.roll_rad);
        let s = board.square_m;
        Self {
            rot: face * tilt * roll,
            centre_c: ray * hold.depth_m,
            centre_obj: Vector2::new(
                0.5 * f64::from(board.inner_cols - 1) * s,
                0.5 * f64::from(board.inner_rows - 1) * s,
            ),
        }
    }

    fn point_c(&self, x: f64, y: f64) -> Vector3<f64> {
        self.centre_c + self.rot * Vector3::new(x - self.centre_obj.x, y - self.centre_obj.y, 0.0)
    }
}

/// A quadrilateral of the board's plane (corners in order), its sides cut into
/// segments, projected through the true camera; `None` if a point is behind it.
fn project_outline(
    cam: &WorldCamera,
    base_from_c: &dyn Fn(Vector3<f64>) -> Vector3<f64>,
    placed: &Placed,
    quad: [[f64; 2]; 4],
) -> Option<Vec<Vector2<f64>>> {
    let mut out = Vec::with_capacity(4 * SIDE_SEGMENTS);
    for i in 0..4 {
        let (a, b) = (quad[i], quad[(i + 1) % 4]);
        for k in 0..SIDE_SEGMENTS {
            let t = k as f64 / SIDE_SEGMENTS as f64;
            let (x, y) = (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]));
            out.push(cam.project(&base_from_c(placed.point_c(x, y)))?);
        }
    }
    Some(out)
}

/// The board's outline (margin included) and its dark squares, in pixels, or
/// `None` when any of it is behind the camera or outside the image.
struct Drawn {
    outline: Vec<Vector2<f64>>,
    squares: Vec<Vec<Vector2<f64>>>,
}

fn draw_board(
    cam: &WorldCamera,
    board: &Chessboard,
    hold: &Hold,
    (w, h): (f64, f64),
) -> Option<Drawn> {
    let placed = Placed::new(board, hold);
    let base_from_c = |p: Vector3<f64>| cam.base_from_camera * p + cam.position_m;
    let s = board.square_m;
    let (cols, rows) = (f64::from(board.inner_cols), f64::from(board.inner_rows));
    // Squares span -1..=cols (x) and -1..=rows (y) in squares; the margin beyond.
    let m = MARGIN_SQUARES + 1.0;
    let (x0, x1, y0, y1) = (-m * s, (cols + m - 1.0) * s, -m * s, (rows + m - 1.0) * s);
    let outline = project_outline(
        cam,
        &base_from_c,
        &placed,
        [[x0, y0], [x1, y0], [x1, y1], [x0, y1]],
    )?;
    let inside = outline.iter().all(|p| {
        p.x >= EDGE_PX && p.y >= EDGE_PX && p.x <= w - 1.0 - EDGE_PX && p.y <= h - 1.0 - EDGE_PX
    });
    if !inside {
        return None;
    }
    let mut squares = Vec::new();
    for j in 0..=board.inner_rows {
        for i in 0..=board.inner_cols {
            if (i + j) % 2 == 1 {
                continue;
            }
            let (a, b) = ((f64::from(i) - 1.0) * s, (f64::from(j) - 1.0) * s);
            squares.push(project_outline(
                cam,
                &base_from_c,
                &placed,
                [[a, b], [a + s, b], [a + s, b + s], [a, b + s]],
            )?);
        }
    }
    Some(Drawn { outline, squares })
}

/// The operator's `n` holds: aims spread over the image (its corners, where the
/// lens shows most, first), depths 0.5..1.5 m, tilts 15..40 degrees in turning
/// directions, a little roll; each moved toward the image centre and back
/// until the whole board is in view (as the operator does, watching the live view).
fn plan_holds(
    cam: &WorldCamera,
    board: &Chessboard,
    n: usize,
    size: (f64, f64),
    rng: &mut ChaCha8Rng,
) -> Vec<Hold> {
    let k = &cam.intrinsics;
    // Normalised half extents of the image.
    let (ax, ay) = (0.5 * size.0 / k.fx_px, 0.5 * size.1 / k.fy_px);
    let spots = [
        (-1.0, -1.0),
        (1.0, 1.0),
        (1.0, -1.0),
        (-1.0, 1.0),
        (0.0, 0.0),
        (0.0, -1.0),
        (0.0, 1.0),
        (-1.0, 0.0),
        (1.0, 0.0),
    ];
    let mut holds = Vec::with_capacity(n);
    for i in 0..n {
        let (sx, sy) = if i < spots.len() {
            spots[i]
        } else {
            (rng.random_range(-1.0..=1.0), rng.random_range(-1.0..=1.0))
        };
        let mut hold = Hold {
            aim: Vector2::new(sx * ax, sy * ay),
            depth_m: rng.random_range(0.5..=1.5),
            tilt_rad: rng.random_range(15.0f64..=40.0).to_radians(),
            tilt_dir_rad: i as f64 * 2.399 + rng.random_range(-0.3..=0.3),
            roll_rad: rng.random_range(-20.0f64..=20.0).to_radians(),
        };
        for _ in 0..60 {
            if draw_board(cam, board, &hold, size).is_some() {
                break;
            }
            // Toward the centre a little, back a little.
            hold.aim *= 0.95;
            hold.depth_m = (hold.depth_m + 0.03).min(1.5);
        }
        holds.push(hold);
    }
    holds
}

/// Fills `poly` (pixels) into the supersampled canvas whose origin is pixel
/// `origin` of the frame.
fn fill(
    canvas: &mut Mat,
    poly: &[Vector2<f64>],
    origin: (i32, i32),
    value: f64,
) -> Result<(), ProcedureError> {
    let scale = f64::from(SS) * f64::from(1 << SHIFT);
    let pts: Vector<Point> = poly
        .iter()
        .map(|p| {
            // Sub-pixel (i, j) of the canvas covers frame pixels
            // [x0 + i/SS - 1/2, ..+1/SS): its centre is at x0 + (i + 1/2)/SS - 1/2.
            let u = (p.x - f64::from(origin.0) + 0.5) * f64::from(SS) - 0.5;
            let v = (p.y - f64::from(origin.1) + 0.5) * f64::from(SS) - 0.5;
            Point::new(
                (u * scale / f64::from(SS)).round() as i32,
                (v * scale / f64::from(SS)).round() as i32,
            )
        })
        .collect();
    let mut polys = Vector::<Vector<Point>>::new();
    polys.push(pts);
    imgproc::fill_poly(
        canvas,
        &polys,
        Scalar::all(value),
        imgproc::LINE_8,
        SHIFT,
        Point::default(),
    )?;
    Ok(())
}

/// Box-Muller normal sample.
fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.random_range(f64::EPSILON..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// One grey frame: the lab's scene with the board drawn over it (coverage
/// from the supersampled squares, the scene's lighting gradient across the
/// print, a slight defocus, fresh pixel noise).
fn render_view(
    scene: &Mat,
    drawn: Option<&Drawn>,
    noise: f64,
    rng: &mut ChaCha8Rng,
) -> Result<Mat, ProcedureError> {
    let mut gray = Mat::default();
    imgproc::cvt_color_def(scene, &mut gray, imgproc::COLOR_BGR2GRAY)?;
    let Some(d) = drawn else {
        return Ok(gray);
    };
    let (w, h) = (gray.cols(), gray.rows());
    let (mut lo, mut hi) = (
        Vector2::new(f64::MAX, f64::MAX),
        Vector2::new(f64::MIN, f64::MIN),
    );
    for p in &d.outline {
        lo = lo.inf(p);
        hi = hi.sup(p);
    }
    let x0 = (lo.x.floor() as i32 - 2).clamp(0, w - 1);
    let y0 = (lo.y.floor() as i32 - 2).clamp(0, h - 1);
    let x1 = (hi.x.ceil() as i32 + 3).clamp(x0 + 1, w);
    let y1 = (hi.y.ceil() as i32 + 3).clamp(y0 + 1, h);
    let (bw, bh) = (x1 - x0, y1 - y0);
    // Coverage of the print (alpha) and its ink-weighted value, supersampled.
    let mut alpha =
        Mat::new_rows_cols_with_default(bh * SS, bw * SS, core::CV_8UC1, Scalar::all(0.0))?;
    let mut value =
        Mat::new_rows_cols_with_default(bh * SS, bw * SS, core::CV_8UC1, Scalar::all(0.0))?;
    fill(&mut alpha, &d.outline, (x0, y0), 255.0)?;
    fill(&mut value, &d.outline, (x0, y0), PAPER)?;
    for sq in &d.squares {
        fill(&mut value, sq, (x0, y0), INK)?;
    }
    let mut a_small = Mat::default();
    let mut v_small = Mat::default();
    let size = Size::new(bw, bh);
    imgproc::resize(&alpha, &mut a_small, size, 0.0, 0.0, imgproc::INTER_AREA)?;
    imgproc::resize(&value, &mut v_small, size, 0.0, 0.0, imgproc::INTER_AREA)?;
    // The scene's light falls on the print too: a gentle gradient and a random gain.
    let gain = rng.random_range(0.75..=1.05);
    let (gx, gy) = (rng.random_range(-0.25..=0.25), rng.random_range(-0.2..=0.2));
    let mut region = Mat::roi(&gray, Rect::new(x0, y0, bw, bh))?.try_clone()?;
    {
        let a = a_small.data_bytes()?.to_vec();
        let v = v_small.data_bytes()?.to_vec();
        let out = region.data_bytes_mut()?;
        for j in 0..bh as usize {
            for i in 0..bw as usize {
                let k = j * bw as usize + i;
                let cover = f64::from(a[k]) / 255.0;
                if cover <= 0.0 {
                    continue;
                }
                let u = (f64::from(x0) + i as f64) / f64::from(w) - 0.5;
                let t = (f64::from(y0) + j as f64) / f64::from(h) - 0.5;
                let light = gain * (1.0 + gx * u + gy * t);
                // `value` is premultiplied by the coverage (zero outside the print).
                let print = f64::from(v[k]) * light + cover * noise * gauss(rng);
                let bg = f64::from(out[k]);
                out[k] = (bg * (1.0 - cover) + print).round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    // A slight defocus over the print's region.
    let mut soft = Mat::default();
    imgproc::gaussian_blur_def(&region, &mut soft, Size::new(5, 5), 0.7)?;
    let mut dst = Mat::roi_mut(&mut gray, Rect::new(x0, y0, bw, bh))?;
    soft.copy_to(&mut dst)?;
    Ok(gray)
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
/// [`ProcedureError::Vision`] when an OpenCV call fails (a board not found is
/// `Ok(None)`).
pub fn detect_corners(
    gray: &Mat,
    board: &Chessboard,
) -> Result<Option<Vec<[f64; 2]>>, ProcedureError> {
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

/// The true camera's intrinsics and lens (the simulators' side).
pub fn true_intrinsics(cam: &WorldCamera) -> CameraIntrinsics {
    let [k1, k2, p1, p2] = cam.distortion;
    CameraIntrinsics {
        k1,
        k2,
        p1,
        p2,
        ..cam.intrinsics
    }
}

/// The camera step: `views` holds of `board` in front of the true camera of
/// `world`, one frame each, corners detected and fitted. `board_in_view =
/// false`: the operator holds it outside the camera's view (the step must then
/// refuse, "no board visible"). Reports each view to `watch`.
///
/// # Errors
///
/// [`ProcedureError::Params`] for an invalid scenario; [`ProcedureError::Views`]
/// for `views` outside 1..=200; [`ProcedureError::Calibration`] for a bad board or
/// when [`fit_intrinsics`] refuses the views (e.g. no board visible);
/// [`ProcedureError::Vision`] when rendering or corner detection fails.
pub fn run_camera(
    scenario: &Scenario,
    world: &HiddenWorld,
    seed: u64,
    board: &Chessboard,
    views: usize,
    board_in_view: bool,
    watch: &mut dyn Watch,
) -> Result<CameraRun, ProcedureError> {
    scenario.validate()?;
    board.validate()?;
    if !(1..=200).contains(&views) {
        return Err(ProcedureError::Views { views });
    }
    let cam = world.world_camera(scenario);
    let (w, h) = (scenario.camera.width_px, scenario.camera.height_px);
    let size = (f64::from(w), f64::from(h));
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xc4e5_5b0a);
    let holds = plan_holds(&cam, board, views, size, &mut rng);
    // The lab's scene (background, clutter, lighting, noise) from the renderer.
    let mut scene_cam = SimCamera::new(
        &scenario.camera,
        &SimCameraParams::default(),
        scenario.pendulum.ball_radius_m,
        seed,
    )?;
    let mut seen = Vec::with_capacity(views);
    for (i, hold) in holds.iter().enumerate() {
        let drawn = if board_in_view {
            draw_board(&cam, board, hold, size)
        } else {
            None
        };
        let scene = scene_cam.render(None)?.try_clone()?;
        let gray = render_view(
            &scene,
            drawn.as_ref(),
            scenario.camera.image_noise,
            &mut rng,
        )?;
        let corners = detect_corners(&gray, board)?;
        watch.seen(StepView {
            progress: (i + 1) as f64 / (views + 1) as f64,
            message: match &corners {
                Some(c) => format!("board view {} of {views}: {} corners", i + 1, c.len()),
                None => format!("board view {} of {views}: no board found", i + 1),
            },
            kind: ViewKind::Image,
            points: corners.clone().unwrap_or_default(),
            fit: Vec::new(),
        });
        seen.push(BoardView {
            corners_px: corners,
        });
    }
    let fit = fit_intrinsics(board, &seen, w, h)?;
    for (k, (index, reprojected)) in fit.reprojected.iter().enumerate() {
        watch.seen(StepView {
            progress: 1.0,
            message: format!(
                "fit: view {} of {views}: RMS {:.3} px (all views {:.3} px)",
                index + 1,
                fit.calibration
                    .per_view_rms_px
                    .get(k)
                    .copied()
                    .unwrap_or(f64::NAN),
                fit.calibration.rms_px
            ),
            kind: ViewKind::Image,
            points: seen[*index].corners_px.clone().unwrap_or_default(),
            fit: reprojected.clone(),
        });
    }
    Ok(CameraRun {
        result: fit.calibration,
        truth: true_intrinsics(&cam),
    })
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
        Vector2::new(k.fx_px * r.x + k.cx_px, k.fy_px * r.y + k.cy_px)
    };
    (pinhole(believed) - pinhole(truth)).norm()
}
