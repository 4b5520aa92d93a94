//! A printed chessboard in the world, held by an operator in front of the
//! true camera (the camera step's board): its holds, its drawing through the
//! true camera (the lens bends its lines) and its rendering over a frame
//! (supersampled coverage, the scene's light, noise, a slight defocus). The
//! simulated camera step (`calibration::sim_intrinsics`) and the world's
//! webcam (`isochron world --operator`) both draw it here.

use nalgebra::{Rotation3, Unit, Vector2, Vector3};
use opencv::{
    core::{
        self, Mat, MatTraitConst, MatTraitConstManual, MatTraitManual, Point, Rect, Scalar, Size,
        Vector,
    },
    imgproc,
};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::camera::WorldCamera;
use crate::calibration::Chessboard;
use crate::vision::VisionError;

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

/// Where the operator holds the board: its centre at `depth_m` along the ray
/// through `aim` (normalised image coordinates, the undistorted pinhole's),
/// facing the camera, then tilted and turned in its plane.
#[derive(Debug, Clone, Copy)]
pub struct Hold {
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
#[derive(Debug, Clone)]
pub struct Drawn {
    outline: Vec<Vector2<f64>>,
    squares: Vec<Vec<Vector2<f64>>>,
}

/// The board held at `hold` as the true camera `cam` sees it in an image of
/// `(w, h)` pixels; `None` when any of it is behind the camera or outside
/// the image (less [`EDGE_PX`]).
pub fn draw_board(
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
pub fn plan_holds(
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
) -> Result<(), VisionError> {
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

/// One grey frame: the lab's scene with the board drawn over it
/// ([`overlay`]).
///
/// # Errors
///
/// [`VisionError::OpenCv`] when an OpenCV call fails.
pub fn render_view(
    scene: &Mat,
    drawn: Option<&Drawn>,
    noise: f64,
    rng: &mut ChaCha8Rng,
) -> Result<Mat, VisionError> {
    let mut gray = Mat::default();
    imgproc::cvt_color_def(scene, &mut gray, imgproc::COLOR_BGR2GRAY)?;
    if let Some(d) = drawn {
        overlay(&mut gray, d, noise, rng)?;
    }
    Ok(gray)
}

/// Draws the held board over `image` (grey or BGR, 8 bits): coverage from
/// the supersampled squares, the scene's lighting gradient across the print
/// (a gentle gradient and a random gain), fresh pixel noise (one draw per
/// pixel, the same in every channel: the print is grey), a slight defocus.
///
/// # Errors
///
/// [`VisionError::OpenCv`] when an OpenCV call fails.
pub fn overlay(
    image: &mut Mat,
    d: &Drawn,
    noise: f64,
    rng: &mut ChaCha8Rng,
) -> Result<(), VisionError> {
    let (w, h) = (image.cols(), image.rows());
    let ch = image.channels().max(1) as usize;
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
    let mut region = Mat::roi(image, Rect::new(x0, y0, bw, bh))?.try_clone()?;
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
                for c in 0..ch {
                    let bg = f64::from(out[k * ch + c]);
                    out[k * ch + c] = (bg * (1.0 - cover) + print).round().clamp(0.0, 255.0) as u8;
                }
            }
        }
    }
    // A slight defocus over the print's region.
    let mut soft = Mat::default();
    imgproc::gaussian_blur_def(&region, &mut soft, Size::new(5, 5), 0.7)?;
    let mut dst = Mat::roi_mut(image, Rect::new(x0, y0, bw, bh))?;
    soft.copy_to(&mut dst)?;
    Ok(())
}

/// An operator's printed board for the camera step: `views` holds planned
/// (from the operator's seed) over the true camera's image, the board drawn
/// over a frame at the one asked for.
pub struct BoardOperator {
    board: Chessboard,
    holds: Vec<Hold>,
    size: (f64, f64),
    rng: ChaCha8Rng,
}

impl std::fmt::Debug for BoardOperator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BoardOperator")
            .field("board", &self.board)
            .field("holds", &self.holds.len())
            .finish_non_exhaustive()
    }
}

impl BoardOperator {
    /// `views` holds of `board` in front of `cam` (an image of `size`
    /// pixels: width, height).
    pub fn new(
        cam: &WorldCamera,
        board: Chessboard,
        views: usize,
        size: (f64, f64),
        seed: u64,
    ) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x6f70_6572_6174_6f72);
        let holds = plan_holds(cam, &board, views, size, &mut rng);
        Self {
            board,
            holds,
            size,
            rng,
        }
    }

    /// Holds planned.
    pub fn views(&self) -> usize {
        self.holds.len()
    }

    /// Draws the board held at hold `pose` (0-based) over `image` as `cam`
    /// sees it; false (nothing drawn) when `pose` is past the plan or the
    /// board would leave the image.
    ///
    /// # Errors
    ///
    /// [`VisionError::OpenCv`] when an OpenCV call fails.
    pub fn draw(
        &mut self,
        cam: &WorldCamera,
        pose: usize,
        image: &mut Mat,
        noise: f64,
    ) -> Result<bool, VisionError> {
        let Some(hold) = self.holds.get(pose) else {
            return Ok(false);
        };
        let Some(d) = draw_board(cam, &self.board, hold, self.size) else {
            return Ok(false);
        };
        overlay(image, &d, noise, &mut self.rng)?;
        Ok(true)
    }
}
