//! The tool's marker disc in the world's frames: its rim projected through
//! the true camera (its pose and lens) from the true arm's flange pose
//! (`TrueArm::flange`: the session's joint offsets and geometry errors),
//! filled in the marker's colour with sensor noise over it. The disc is
//! where the lab believes it on the tool (`calibration::marker`'s offset and
//! radius: a constant of the tool); what differs from the lab's belief is the
//! arm carrying it and the camera seeing it.

use nalgebra::{Matrix3, Vector2, Vector3};
use opencv::{
    core::{Mat, MatTraitConst, MatTraitManual, Point, Rect, Scalar, Vector},
    imgproc,
};
use rand_chacha::ChaCha8Rng;

use super::camera::WorldCamera;
use crate::calibration::marker::{MARKER_HSV, MARKER_OFFSET_M, MARKER_RADIUS_M};

/// The marker's centre and the disc's normal (the tool axis), base frame,
/// for the true flange `(position, rotation)`.
pub fn marker_pose(flange: &(Vector3<f64>, Matrix3<f64>)) -> (Vector3<f64>, Vector3<f64>) {
    let (p, r) = flange;
    (
        p + r * Vector3::from(MARKER_OFFSET_M),
        r.column(2).into_owned(),
    )
}

/// The disc's rim through `camera` (48 points), `None` when any point is
/// behind it.
pub fn marker_rim(
    camera: &WorldCamera,
    centre: &Vector3<f64>,
    normal: &Vector3<f64>,
) -> Option<Vec<Vector2<f64>>> {
    let u = normal
        .cross(&Vector3::z())
        .try_normalize(1e-9)
        .unwrap_or(Vector3::y());
    let v = normal.cross(&u);
    (0..48)
        .map(|k| {
            let a = std::f64::consts::TAU * f64::from(k) / 48.0;
            camera.project(&(centre + MARKER_RADIUS_M * (a.cos() * u + a.sin() * v)))
        })
        .collect()
}

/// Fills the marker disc (its projected rim, `marker_rim`) into the BGR
/// `img`, with pixel noise `noise` (grey levels, 1 sigma) over its region.
///
/// # Errors
///
/// OpenCV's, when filling or copying fails.
pub fn draw_marker(
    img: &mut Mat,
    rim: &[Vector2<f64>],
    noise: f64,
    rng: &mut ChaCha8Rng,
) -> opencv::Result<()> {
    const SHIFT: i32 = 4;
    let scale = f64::from(1 << SHIFT);
    let pts: Vector<Point> = rim
        .iter()
        .map(|p| Point::new((p.x * scale).round() as i32, (p.y * scale).round() as i32))
        .collect();
    let mut polys = Vector::<Vector<Point>>::new();
    polys.push(pts);
    let (h, s, v) = MARKER_HSV;
    let c = v * s;
    let hp = h / 60.0;
    let x = c * (1.0 - (hp % 2.0 - 1.0).abs());
    let m = v - c;
    // Hue 112: between green and cyan (r = 0 side).
    let (r, g, b) = (x + m, c + m, m);
    let colour = Scalar::new(b * 255.0, g * 255.0, r * 255.0, 0.0);
    imgproc::fill_poly(
        img,
        &polys,
        colour,
        imgproc::LINE_AA,
        SHIFT,
        Point::default(),
    )?;
    // Sensor noise on the disc's box (the background has its own).
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for p in rim {
        x0 = x0.min(p.x);
        y0 = y0.min(p.y);
        x1 = x1.max(p.x);
        y1 = y1.max(p.y);
    }
    let rect = Rect::new(
        (x0.floor() as i32 - 2).max(0),
        (y0.floor() as i32 - 2).max(0),
        0,
        0,
    );
    let rect = Rect::new(
        rect.x,
        rect.y,
        ((x1.ceil() as i32 + 2).min(img.cols()) - rect.x).max(0),
        ((y1.ceil() as i32 + 2).min(img.rows()) - rect.y).max(0),
    );
    if noise > 0.0 && rect.width > 0 && rect.height > 0 {
        let mut patch = Mat::roi(img, rect)?.try_clone()?;
        for v in patch.data_bytes_mut()? {
            *v = (f64::from(*v) + noise * crate::sim::camera::gaussian(rng))
                .round()
                .clamp(0.0, 255.0) as u8;
        }
        let mut roi = Mat::roi_mut(img, rect)?;
        patch.copy_to(&mut roi)?;
    }
    Ok(())
}
