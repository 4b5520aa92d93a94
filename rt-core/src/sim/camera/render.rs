//! The simulated camera: the true ball rendered through a pinhole camera onto a
//! textured, cluttered lab background, with lighting variation, motion blur over
//! the exposure, pixel noise, dropped frames and latency.
//!
//! Speed: the background (texture and clutter) is rendered once, and a few
//! full-frame lighting variants with static pixel noise are prepared from it. Each
//! frame picks a variant and redraws only the ball's region (ball, blur, shading,
//! fresh noise) in place; the region is restored before the next frame.

use nalgebra::{Rotation3, Vector3};
use opencv::{
    core::{
        self, Mat, MatTraitConst, MatTraitConstManual, MatTraitManual, Point, Rect, Scalar, Vector,
    },
    imgproc,
};
use rand::{Rng, RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::geometry::{BallState, SimCameraParams};
use crate::check;
use crate::params::{CameraParams, VisionMode};
use crate::vision::source::{Clock, Frame};
use crate::vision::{
    CameraIntrinsics, Detector, DetectorParams, FrameSource, Measurement, SwingPlaneCalibration,
    VisionError,
};

/// Lighting of one variant: gain * (1 + gx (x/W - 1/2) + gy (y/H - 1/2)).
#[derive(Debug, Clone, Copy)]
struct Light {
    gain: f64,
    gx: f64,
    gy: f64,
}

/// A ball counts as visible when this many pixels of background surround it
/// inside the frame (a ball touching the frame's edge may be cut off, and is not
/// reported).
pub const VISIBLE_MARGIN_PX: f64 = 2.0;

const NOISE_TABLE: usize = 1 << 16;

/// The simulated camera (see the module docs).
pub struct SimCamera {
    camera: CameraParams,
    params: SimCameraParams,
    intrinsics: CameraIntrinsics,
    camera_from_base: Rotation3<f64>,
    position: Vector3<f64>,
    ball_radius_m: f64,
    width: i32,
    height: i32,
    background: Vec<u8>,
    variants: Vec<Mat>,
    lights: Vec<Light>,
    noise: Vec<f32>,
    rng: ChaCha8Rng,
    dirty: Option<(usize, Rect)>,
    backup: Vec<u8>,
    /// The light on the ball against the background's (the reality lab's
    /// auto-exposure, flicker, shadows: `sim::world::camera`), 1: as rendered.
    ball_gain: f64,
    current: usize,
}

impl std::fmt::Debug for SimCamera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimCamera")
            .field("camera", &self.camera)
            .field("params", &self.params)
            .finish_non_exhaustive()
    }
}

/// The ball as the camera sees it: centre and radius in pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BallImage {
    /// Centre column, pixels.
    pub x_px: f64,
    /// Centre row, pixels.
    pub y_px: f64,
    /// Radius, pixels.
    pub r_px: f64,
}

impl SimCamera {
    /// Builds the camera and renders its background. `seed` drives the per-frame
    /// randomness (noise, lighting, drops); the background comes from
    /// `params.scene_seed`.
    ///
    /// # Errors
    ///
    /// [`VisionError::Param`] for invalid camera or simulator parameters or a ball
    /// radius outside 0.005..=0.2 m; [`VisionError::OpenCv`] when painting the
    /// background fails.
    pub fn new(
        camera: &CameraParams,
        params: &SimCameraParams,
        ball_radius_m: f64,
        seed: u64,
    ) -> Result<Self, VisionError> {
        camera.validate()?;
        params.validate()?;
        check::within("pendulum.ball_radius_m", ball_radius_m, 0.005, 0.2)?;
        crate::vision::limit_opencv_threads()?;
        let (w, h) = (camera.width_px as i32, camera.height_px as i32);
        let intrinsics =
            CameraIntrinsics::from_hfov(camera.width_px, camera.height_px, params.hfov_deg);
        let mut scene = ChaCha8Rng::seed_from_u64(params.scene_seed);
        let noise = noise_table(&mut scene);
        let mut bg = Mat::new_rows_cols_with_default(h, w, core::CV_8UC3, Scalar::all(0.0))?;
        paint_texture(bg.data_bytes_mut()?, w as usize, h as usize, &mut scene);
        draw_clutter(&mut bg, params, &mut scene)?;
        let background = bg.data_bytes()?.to_vec();
        let mut lights = Vec::new();
        let mut variants = Vec::new();
        let lv = params.lighting_variation;
        for k in 0..params.lighting_variants {
            let light = if k == 0 {
                Light {
                    gain: 1.0,
                    gx: 0.0,
                    gy: 0.0,
                }
            } else {
                Light {
                    gain: 1.0 + lv * scene.random_range(-1.0..=1.0),
                    gx: lv * scene.random_range(-1.0..=1.0),
                    gy: lv * scene.random_range(-1.0..=1.0),
                }
            };
            let mut m = bg.try_clone()?;
            light_and_noise(
                m.data_bytes_mut()?,
                &background,
                w as usize,
                h as usize,
                light,
                camera.image_noise,
                &noise,
                &mut scene,
            );
            lights.push(light);
            variants.push(m);
        }
        Ok(Self {
            camera: camera.clone(),
            params: params.clone(),
            intrinsics,
            camera_from_base: params.pose.base_from_camera().inverse(),
            position: params.pose.position(),
            ball_radius_m,
            width: w,
            height: h,
            background,
            variants,
            lights,
            noise,
            rng: ChaCha8Rng::seed_from_u64(seed),
            dirty: None,
            backup: Vec::new(),
            ball_gain: 1.0,
            current: 0,
        })
    }

    /// The light on the ball in the next frames, as a gain on its rendered
    /// brightness (1: as rendered; clamped to 0..4). The background keeps its
    /// light: its clutter has none of the ball's hue, so its brightness does
    /// not change what the detector finds there.
    pub fn set_ball_gain(&mut self, gain: f64) {
        self.ball_gain = if gain.is_finite() {
            gain.clamp(0.0, 4.0)
        } else {
            1.0
        };
    }

    /// Restarts the per-frame randomness (the background is kept).
    pub fn reseed(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
    }

    /// The intrinsics the camera renders with.
    pub fn intrinsics(&self) -> &CameraIntrinsics {
        &self.intrinsics
    }

    /// The camera's settings.
    pub fn params(&self) -> &SimCameraParams {
        &self.params
    }

    /// The scenario's camera section.
    pub fn camera_params(&self) -> &CameraParams {
        &self.camera
    }

    /// The exact calibration of this camera for a ball resting at `rest_b`.
    pub fn true_calibration(&self, rest_b: &Vector3<f64>) -> SwingPlaneCalibration {
        SwingPlaneCalibration::from_pose(
            self.intrinsics,
            &self.params.pose,
            rest_b,
            self.ball_radius_m,
        )
    }

    /// Where the ball centre at `centre_b` (base frame) appears; `None` behind the camera.
    pub fn project(&self, centre_b: &Vector3<f64>) -> Option<BallImage> {
        let p_c = self.camera_from_base * (centre_b - self.position);
        let uv = self.intrinsics.project(&p_c)?;
        Some(BallImage {
            x_px: uv.x,
            y_px: uv.y,
            r_px: 0.5 * (self.intrinsics.fx_px + self.intrinsics.fy_px) * self.ball_radius_m
                / p_c.z,
        })
    }

    /// Whether the whole ball is inside the image, with a ring of at least
    /// [`VISIBLE_MARGIN_PX`] pixels of background around it.
    pub fn fully_visible(&self, centre_b: &Vector3<f64>) -> bool {
        let m = VISIBLE_MARGIN_PX;
        self.project(centre_b).is_some_and(|b| {
            b.x_px - b.r_px >= m
                && b.y_px - b.r_px >= m
                && b.x_px + b.r_px <= f64::from(self.width) - 1.0 - m
                && b.y_px + b.r_px <= f64::from(self.height) - 1.0 - m
        })
    }

    /// Draws whether the next frame is lost (`camera.drop_rate`).
    pub fn next_dropped(&mut self) -> bool {
        self.rng.random::<f64>() < self.camera.drop_rate
    }

    /// Capture -> available delay of the next frame, seconds.
    pub fn next_latency_s(&mut self) -> f64 {
        let j = self.params.latency_jitter_ms * gauss(&mut self.rng);
        (self.camera.latency_ms + j).max(0.0) * 1e-3
    }

    /// A noisy projection of the ball, without an image (`vision = "model"`);
    /// `None` when the ball is not fully visible.
    pub fn model_observation(&mut self, ball: &BallState) -> Option<BallImage> {
        if !self.fully_visible(&ball.centre_m) {
            return None;
        }
        let b = self.project(&ball.centre_m)?;
        let s = self.params.model_noise_px;
        Some(BallImage {
            x_px: b.x_px + s * gauss(&mut self.rng),
            y_px: b.y_px + s * gauss(&mut self.rng),
            r_px: b.r_px + 0.5 * s * gauss(&mut self.rng),
        })
    }

    /// Renders the frame taken with the ball in `ball` at the middle of the
    /// exposure (`None`: no ball in view). The returned image stays valid until
    /// the next call.
    ///
    /// # Errors
    ///
    /// [`VisionError::OpenCv`] when the image data cannot be accessed or the ball
    /// cannot be drawn.
    pub fn render(&mut self, ball: Option<&BallState>) -> Result<&Mat, VisionError> {
        // Undo the previous frame's ball.
        if let Some((k, rect)) = self.dirty.take() {
            let w = self.width as usize;
            let data = self.variants[k].data_bytes_mut()?;
            let rw = rect.width as usize * 3;
            for (i, row) in (rect.y..rect.y + rect.height).enumerate() {
                let start = (row as usize * w + rect.x as usize) * 3;
                data[start..start + rw].copy_from_slice(&self.backup[i * rw..(i + 1) * rw]);
            }
        }
        let k = self.rng.random_range(0..self.variants.len());
        self.current = k;
        if let Some(ball) = ball {
            self.draw_ball(k, ball)?;
        }
        Ok(&self.variants[k])
    }

    /// The last rendered image.
    pub fn image(&self) -> &Mat {
        &self.variants[self.current]
    }

    fn draw_ball(&mut self, k: usize, ball: &BallState) -> Result<(), VisionError> {
        // Sub-samples along the exposure, each projected with perspective.
        let t_exp = self.params.exposure_ms * 1e-3;
        let start = ball.centre_m - ball.velocity_mps * (0.5 * t_exp);
        let end = ball.centre_m + ball.velocity_mps * (0.5 * t_exp);
        let (Some(b0), Some(b1)) = (self.project(&start), self.project(&end)) else {
            return Ok(());
        };
        let blur_px = (b1.x_px - b0.x_px).hypot(b1.y_px - b0.y_px);
        let n = ((blur_px / 0.75).ceil() as usize + 1).clamp(1, 32);
        let mut subs = [(0.0f64, 0.0f64, 0.0f64); 32];
        let mut x_lo = f64::INFINITY;
        let mut x_hi = f64::NEG_INFINITY;
        let mut y_lo = f64::INFINITY;
        let mut y_hi = f64::NEG_INFINITY;
        for (i, s) in subs.iter_mut().take(n).enumerate() {
            let f = if n == 1 {
                0.5
            } else {
                i as f64 / (n - 1) as f64
            };
            let Some(b) = self.project(&(start + (end - start) * f)) else {
                return Ok(());
            };
            *s = (b.x_px, b.y_px, b.r_px);
            x_lo = x_lo.min(b.x_px - b.r_px);
            x_hi = x_hi.max(b.x_px + b.r_px);
            y_lo = y_lo.min(b.y_px - b.r_px);
            y_hi = y_hi.max(b.y_px + b.r_px);
        }
        let x0 = ((x_lo - 2.0).floor() as i32).clamp(0, self.width);
        let x1 = ((x_hi + 2.0).ceil() as i32 + 1).clamp(0, self.width);
        let y0 = ((y_lo - 2.0).floor() as i32).clamp(0, self.height);
        let y1 = ((y_hi + 2.0).ceil() as i32 + 1).clamp(0, self.height);
        if x1 <= x0 || y1 <= y0 {
            return Ok(());
        }
        let rect = Rect::new(x0, y0, x1 - x0, y1 - y0);
        let w = self.width as usize;
        let (wf, hf) = (f64::from(self.width), f64::from(self.height));
        let light = self.lights[k];
        let sigma = self.camera.image_noise as f32;
        let colour = [
            self.params.ball_rgb[2],
            self.params.ball_rgb[1],
            self.params.ball_rgb[0],
        ];
        let inv_n = 1.0 / n as f64;
        let rw = rect.width as usize * 3;
        self.backup.clear();
        let data = self.variants[k].data_bytes_mut()?;
        for y in y0..y1 {
            let row_start = (y as usize * w + x0 as usize) * 3;
            self.backup
                .extend_from_slice(&data[row_start..row_start + rw]);
            let mut off = self.rng.random_range(0..NOISE_TABLE - rw);
            for x in x0..x1 {
                let (px, py) = (f64::from(x), f64::from(y));
                let mut cover = 0.0;
                let mut shade = 0.0;
                for &(u, v, r) in &subs[..n] {
                    let (dx, dy) = (px - u, py - v);
                    let d = dx.hypot(dy);
                    let c = (r - d + 0.5).clamp(0.0, 1.0);
                    if c > 0.0 {
                        // Lambertian sphere lit from above and in front.
                        let q = ((dx * dx + dy * dy) / (r * r)).min(1.0);
                        let nz = (1.0 - q).sqrt();
                        let lambert = (-0.4 * dy / r + 0.9165 * nz).max(0.0);
                        cover += c;
                        shade += c * (0.55 + 0.45 * lambert);
                    }
                }
                cover *= inv_n;
                shade *= inv_n;
                let g =
                    light.gain * (1.0 + light.gx * (px / wf - 0.5) + light.gy * (py / hf - 0.5));
                let i = (y as usize * w + x as usize) * 3;
                for ch in 0..3 {
                    let bgv = f64::from(self.background[i + ch]);
                    let val = g * (bgv * (1.0 - cover) + colour[ch] * shade * self.ball_gain)
                        + f64::from(sigma * self.noise[off]);
                    off += 1;
                    data[i + ch] = val.round().clamp(0.0, 255.0) as u8;
                }
            }
        }
        self.dirty = Some((k, rect));
        Ok(())
    }
}

/// Approximately standard normal: the sum of 12 uniforms minus 6 (Irwin-Hall).
fn gauss(rng: &mut impl Rng) -> f64 {
    let mut s = 0.0;
    for _ in 0..12 {
        s += rng.random::<f64>();
    }
    s - 6.0
}

fn noise_table(rng: &mut impl Rng) -> Vec<f32> {
    (0..NOISE_TABLE).map(|_| gauss(rng) as f32).collect()
}

/// A smooth colour field (bilinear over a coarse random grid) with fine texture
/// and wall-panel stripes, in muted colours.
fn paint_texture(data: &mut [u8], w: usize, h: usize, rng: &mut impl Rng) {
    const GX: usize = 17;
    const GY: usize = 10;
    let mut grid = [[0.0f64; 3]; GX * GY];
    for c in &mut grid {
        let base = rng.random_range(60.0..190.0);
        for ch in c.iter_mut() {
            *ch = base + rng.random_range(-25.0..25.0);
        }
    }
    let stripe_period = rng.random_range(40.0..120.0);
    let mut hash: u32 = rng.random();
    for y in 0..h {
        let gy = y as f64 / h as f64 * (GY - 1) as f64;
        let (iy, fy) = ((gy as usize).min(GY - 2), gy.fract());
        for x in 0..w {
            let gx = x as f64 / w as f64 * (GX - 1) as f64;
            let (ix, fx) = ((gx as usize).min(GX - 2), gx.fract());
            let stripe = 8.0 * (x as f64 * std::f64::consts::TAU / stripe_period).sin();
            hash ^= hash << 13;
            hash ^= hash >> 17;
            hash ^= hash << 5;
            let grain = f64::from(hash & 31) - 15.5;
            let i = (y * w + x) * 3;
            for ch in 0..3 {
                let a = grid[iy * GX + ix][ch] * (1.0 - fx) + grid[iy * GX + ix + 1][ch] * fx;
                let b = grid[(iy + 1) * GX + ix][ch] * (1.0 - fx)
                    + grid[(iy + 1) * GX + ix + 1][ch] * fx;
                let v = a * (1.0 - fy) + b * fy + stripe + grain;
                data[i + ch] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
    }
}

/// BGR of a hue (degrees), saturation and value (0..1).
fn hsv_bgr(h_deg: f64, s: f64, v: f64) -> Scalar {
    let c = v * s;
    let hp = (h_deg.rem_euclid(360.0)) / 60.0;
    let x = c * (1.0 - (hp % 2.0 - 1.0).abs());
    let (r, g, b) = match hp as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    Scalar::new((b + m) * 255.0, (g + m) * 255.0, (r + m) * 255.0, 0.0)
}

/// A colour that is not the ball's: another hue, or washed out.
fn other_colour(rng: &mut impl Rng) -> Scalar {
    if rng.random_bool(0.3) {
        let v = rng.random_range(0.1..1.0);
        return hsv_bgr(rng.random_range(0.0..360.0), rng.random_range(0.0..0.2), v);
    }
    // Hues well away from the ball's 48..100 degrees.
    let h = if rng.random_bool(0.35) {
        rng.random_range(0.0..32.0)
    } else {
        rng.random_range(125.0..350.0)
    };
    hsv_bgr(h, rng.random_range(0.4..1.0), rng.random_range(0.3..1.0))
}

/// Clutter: boxes, cables and round things in other colours anywhere, and
/// ball-coloured things that are not balls (bars, a square, a ring, a cable) in
/// the top and bottom bands of the image, away from where the ball swings.
fn draw_clutter(bg: &mut Mat, p: &SimCameraParams, rng: &mut impl Rng) -> Result<(), VisionError> {
    let (w, h) = (bg.cols(), bg.rows());
    let aa = imgproc::LINE_AA;
    for _ in 0..p.clutter_count {
        let c = other_colour(rng);
        let (x, y) = (rng.random_range(0..w), rng.random_range(0..h));
        match rng.random_range(0..4) {
            0 => {
                let rect = Rect::new(x, y, rng.random_range(15..200), rng.random_range(15..160));
                imgproc::rectangle(bg, rect, c, imgproc::FILLED, aa, 0)?;
            }
            1 => {
                let p2 = Point::new(
                    x + rng.random_range(-300..300),
                    y + rng.random_range(-200..200),
                );
                imgproc::line(bg, Point::new(x, y), p2, c, rng.random_range(2..7), aa, 0)?;
            }
            _ => {
                // Ball-sized round things in other colours.
                imgproc::circle(
                    bg,
                    Point::new(x, y),
                    rng.random_range(8..45),
                    c,
                    imgproc::FILLED,
                    aa,
                    0,
                )?;
            }
        }
    }
    // Ball-coloured decoys, in the top 20% and the bottom 12% of the image.
    let ball = hsv_bgr(72.0, 0.75, 0.9);
    if p.clutter_count > 0 {
        let x = rng.random_range(0..(w - 200).max(1));
        imgproc::rectangle(
            bg,
            Rect::new(x, band(rng, h), 160, 14),
            ball,
            imgproc::FILLED,
            aa,
            0,
        )?;
        let x = rng.random_range(0..(w - 60).max(1));
        imgproc::rectangle(
            bg,
            Rect::new(x, band(rng, h), 36, 36),
            ball,
            imgproc::FILLED,
            aa,
            0,
        )?;
        let x = rng.random_range(40..(w - 40).max(41));
        imgproc::circle(bg, Point::new(x, band(rng, h) + 20), 20, ball, 4, aa, 0)?;
        let x = rng.random_range(0..(w - 300).max(1));
        let y = band(rng, h);
        imgproc::line(
            bg,
            Point::new(x, y),
            Point::new(x + 250, y + 8),
            ball,
            5,
            aa,
            0,
        )?;
    }
    Ok(())
}

/// A row in the top 20% or the bottom 12% of an image of height `h`.
fn band(rng: &mut impl Rng, h: i32) -> i32 {
    if rng.random_bool(0.5) {
        rng.random_range(5..(h / 5 - 50).max(6))
    } else {
        rng.random_range((h * 88 / 100)..(h - 20).max(h * 88 / 100 + 1))
    }
}

/// `out = background * light + sigma * noise`, rows drawn from the noise table at
/// random offsets.
#[expect(
    clippy::too_many_arguments,
    reason = "the inner loop of the renderer: its buffers and constants, no struct in between"
)]
fn light_and_noise(
    out: &mut [u8],
    bg: &[u8],
    w: usize,
    h: usize,
    light: Light,
    sigma: f64,
    noise: &[f32],
    rng: &mut impl Rng,
) {
    let row = w * 3;
    for y in 0..h {
        let mut off = rng.random_range(0..noise.len() - row);
        let gy = light.gy * (y as f64 / h as f64 - 0.5);
        for x in 0..w {
            let g = light.gain * (1.0 + light.gx * (x as f64 / w as f64 - 0.5) + gy);
            let i = y * row + x * 3;
            for ch in 0..3 {
                let v = f64::from(bg[i + ch]) * g + sigma * f64::from(noise[off]);
                off += 1;
                out[i + ch] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
    }
}

/// The simulated lab's camera and vision in virtual time: capture, drop, render,
/// detect and convert, or the fast noisy projection in `model` mode.
#[derive(Debug)]
pub struct SimVision {
    camera: SimCamera,
    detector: Detector,
    calibration: SwingPlaneCalibration,
    mode: VisionMode,
    frame: u64,
}

impl SimVision {
    /// The camera of `camera` + `sim`, the detector, and the calibration the
    /// system believes in (from [`SwingPlaneCalibration::from_rest_observation`] or
    /// [`SimCamera::true_calibration`]).
    ///
    /// # Errors
    ///
    /// The error of [`Detector::new`] when it refuses `detector`.
    pub fn new(
        camera: SimCamera,
        detector: DetectorParams,
        calibration: SwingPlaneCalibration,
    ) -> Result<Self, VisionError> {
        let mode = camera.camera.vision;
        Ok(Self {
            camera,
            detector: Detector::new(detector)?,
            calibration,
            mode,
            frame: 0,
        })
    }

    /// Seconds between frames.
    pub fn frame_period_s(&self) -> f64 {
        1.0 / self.camera.camera.fps
    }

    /// The camera.
    pub fn camera(&self) -> &SimCamera {
        &self.camera
    }

    /// The light on the ball in the next frames ([`SimCamera::set_ball_gain`]).
    pub fn set_ball_gain(&mut self, gain: f64) {
        self.camera.set_ball_gain(gain);
    }

    /// Replaces the calibration (e.g. for a new rest position) and forgets the track.
    pub fn set_calibration(&mut self, calibration: SwingPlaneCalibration) {
        self.calibration = calibration;
        self.detector.reset();
    }

    /// Restarts the per-frame randomness and the frame count; forgets the track.
    pub fn reset(&mut self, seed: u64) {
        self.camera.reseed(seed);
        self.detector.reset();
        self.frame = 0;
    }

    /// One frame taken at `t_capture_s` (middle of the exposure) of the ball in
    /// `ball` (`None`: not in view). `Ok(None)` when the frame is lost; otherwise
    /// the measurement (found or not) with its availability time.
    ///
    /// # Errors
    ///
    /// [`VisionError::OpenCv`] or [`VisionError::BadFrame`] when rendering or
    /// detection fails (a lost frame is `Ok(None)`).
    pub fn capture(
        &mut self,
        t_capture_s: f64,
        ball: Option<&BallState>,
    ) -> Result<Option<Measurement>, VisionError> {
        let frame = self.frame;
        self.frame += 1;
        if self.camera.next_dropped() {
            return Ok(None);
        }
        let t_available_s = t_capture_s + self.camera.next_latency_s();
        let m = match self.mode {
            VisionMode::Full => {
                let image = self.camera.render(ball)?;
                let m = match self.detector.detect(image, t_capture_s)? {
                    Some(det) => Measurement::from_detection(
                        frame,
                        t_capture_s,
                        t_available_s,
                        &det,
                        &self.calibration,
                    ),
                    None => Measurement::missing(frame, t_capture_s, t_available_s),
                };
                Measurement {
                    rejected: self.detector.rejected(),
                    ..m
                }
            }
            VisionMode::Model => match ball.and_then(|b| self.camera.model_observation(b)) {
                Some(b) => Measurement::from_detection(
                    frame,
                    t_capture_s,
                    t_available_s,
                    &crate::vision::Detection {
                        x_px: b.x_px,
                        y_px: b.y_px,
                        r_px: b.r_px,
                        confidence: 1.0,
                        elongation: 1.0,
                        tracked: false,
                    },
                    &self.calibration,
                ),
                None => Measurement::missing(frame, t_capture_s, t_available_s),
            },
        };
        Ok(Some(m))
    }
}

/// The simulated camera in real time: frames at the scenario's rate, each
/// delivered after its latency, showing the ball that `truth` reports for the
/// capture time (`None`: no ball in view). Lost frames are skipped.
pub struct SimCameraSource<F> {
    camera: SimCamera,
    truth: F,
    clock: Clock,
    start_s: f64,
    index: u64,
}

impl<F> std::fmt::Debug for SimCameraSource<F> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimCameraSource")
            .field("camera", &self.camera)
            .field("index", &self.index)
            .finish_non_exhaustive()
    }
}

impl<F: FnMut(f64) -> Option<BallState> + Send> SimCameraSource<F> {
    /// Starts the frame clock now.
    pub fn new(camera: SimCamera, truth: F, clock: Clock) -> Self {
        Self {
            camera,
            truth,
            start_s: clock.now_s(),
            clock,
            index: 0,
        }
    }
}

impl<F: FnMut(f64) -> Option<BallState> + Send> FrameSource for SimCameraSource<F> {
    fn next_frame(&mut self) -> Result<Option<Frame<'_>>, VisionError> {
        let period = 1.0 / self.camera.camera_params().fps;
        loop {
            let index = self.index;
            self.index += 1;
            let t_capture_s = self.start_s + index as f64 * period;
            if self.camera.next_dropped() {
                continue;
            }
            let latency = self.camera.next_latency_s();
            let ball = (self.truth)(t_capture_s);
            self.clock.sleep_until(t_capture_s + latency);
            let image = self.camera.render(ball.as_ref())?;
            return Ok(Some(Frame {
                index,
                t_capture_s,
                image,
            }));
        }
    }

    fn fps(&self) -> f64 {
        self.camera.camera_params().fps
    }
}

/// A same-coloured thing in the scene that is not a ball (the detector's
/// look-alikes), in image pixels.
#[derive(Debug, Clone, PartialEq)]
pub enum Lookalike {
    /// A filled polygon (bars, L-shapes, triangles, a hand-drawn blob).
    Polygon(Vec<[i32; 2]>),
    /// A thick line (a cable, a strap).
    Line {
        /// One end.
        a: [i32; 2],
        /// The other end.
        b: [i32; 2],
        /// Thickness, pixels.
        thickness: i32,
    },
}

/// A ball in image space for [`EdgeScene::render`]: centre at mid-exposure,
/// radius, and the centre's travel over the exposure (the motion blur), pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageBall {
    /// Centre column at mid-exposure, pixels.
    pub x_px: f64,
    /// Centre row at mid-exposure, pixels.
    pub y_px: f64,
    /// Radius, pixels.
    pub r_px: f64,
    /// Travel of the centre over the exposure, columns.
    pub blur_dx_px: f64,
    /// Travel of the centre over the exposure, rows.
    pub blur_dy_px: f64,
}

/// Scenes for the detector's hard cases, drawn directly in image pixels: a
/// textured background with ball-coloured look-alikes (non-round, drawn once),
/// the shaded ball with its motion blur, and an occluder (the arm's tool: a
/// grey polygon drawn over the ball), with fresh pixel noise every frame.
pub struct EdgeScene {
    background: Mat,
    frame: Mat,
    ball_bgr: [f64; 3],
    noise_sigma: f64,
    noise: Vec<f32>,
    rng: ChaCha8Rng,
}

impl std::fmt::Debug for EdgeScene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EdgeScene")
            .field("ball_bgr", &self.ball_bgr)
            .finish_non_exhaustive()
    }
}

impl EdgeScene {
    /// A `width` x `height` scene: texture from `seed`, the look-alikes in the
    /// ball's colour `ball_rgb` (0..255), pixel noise `noise_sigma` (grey levels).
    ///
    /// # Errors
    ///
    /// [`VisionError::OpenCv`] when an OpenCV call fails while painting the scene.
    pub fn new(
        width: i32,
        height: i32,
        ball_rgb: [f64; 3],
        lookalikes: &[Lookalike],
        noise_sigma: f64,
        seed: u64,
    ) -> Result<Self, VisionError> {
        crate::vision::limit_opencv_threads()?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut bg =
            Mat::new_rows_cols_with_default(height, width, core::CV_8UC3, Scalar::all(0.0))?;
        paint_texture(
            bg.data_bytes_mut()?,
            width as usize,
            height as usize,
            &mut rng,
        );
        // The look-alikes are lit like the ball's brightest side.
        let colour = Scalar::new(ball_rgb[2], ball_rgb[1], ball_rgb[0], 0.0);
        for l in lookalikes {
            match l {
                Lookalike::Polygon(pts) => {
                    let poly: Vector<Point> = pts.iter().map(|p| Point::new(p[0], p[1])).collect();
                    imgproc::fill_poly_def(
                        &mut bg,
                        &Vector::<Vector<Point>>::from(vec![poly]),
                        colour,
                    )?;
                }
                Lookalike::Line { a, b, thickness } => {
                    imgproc::line(
                        &mut bg,
                        Point::new(a[0], a[1]),
                        Point::new(b[0], b[1]),
                        colour,
                        *thickness,
                        imgproc::LINE_AA,
                        0,
                    )?;
                }
            }
        }
        let frame = bg.try_clone()?;
        let noise = noise_table(&mut rng);
        Ok(Self {
            background: bg,
            frame,
            ball_bgr: [ball_rgb[2], ball_rgb[1], ball_rgb[0]],
            noise_sigma,
            noise,
            rng,
        })
    }

    /// Draws one frame: the ball (if any, shaded, blurred over its travel),
    /// then the occluder polygon (if any) in `occluder_rgb`, then noise.
    ///
    /// # Errors
    ///
    /// [`VisionError::OpenCv`] when an OpenCV call fails while drawing the frame.
    pub fn render(
        &mut self,
        ball: Option<&ImageBall>,
        occluder: Option<(&[[f64; 2]], [f64; 3])>,
    ) -> Result<&Mat, VisionError> {
        self.background.copy_to(&mut self.frame)?;
        let (w, h) = (self.frame.cols(), self.frame.rows());
        if let Some(b) = ball {
            let travel = b.blur_dx_px.hypot(b.blur_dy_px);
            let n = ((travel / 0.75).ceil() as usize + 1).clamp(1, 96);
            let x0 =
                ((b.x_px - 0.5 * b.blur_dx_px.abs() - b.r_px - 2.0).floor() as i32).clamp(0, w);
            let x1 =
                ((b.x_px + 0.5 * b.blur_dx_px.abs() + b.r_px + 2.0).ceil() as i32 + 1).clamp(0, w);
            let y0 =
                ((b.y_px - 0.5 * b.blur_dy_px.abs() - b.r_px - 2.0).floor() as i32).clamp(0, h);
            let y1 =
                ((b.y_px + 0.5 * b.blur_dy_px.abs() + b.r_px + 2.0).ceil() as i32 + 1).clamp(0, h);
            let wu = w as usize;
            let data = self.frame.data_bytes_mut()?;
            let r = b.r_px;
            for y in y0..y1 {
                for x in x0..x1 {
                    let (px, py) = (f64::from(x), f64::from(y));
                    let (mut cover, mut shade) = (0.0, 0.0);
                    for i in 0..n {
                        let f = if n == 1 {
                            0.0
                        } else {
                            i as f64 / (n - 1) as f64 - 0.5
                        };
                        let (u, v) = (b.x_px + f * b.blur_dx_px, b.y_px + f * b.blur_dy_px);
                        let (dx, dy) = (px - u, py - v);
                        let c = (r - dx.hypot(dy) + 0.5).clamp(0.0, 1.0);
                        if c > 0.0 {
                            let q = ((dx * dx + dy * dy) / (r * r)).min(1.0);
                            let lambert = (-0.4 * dy / r + 0.9165 * (1.0 - q).sqrt()).max(0.0);
                            cover += c;
                            shade += c * (0.55 + 0.45 * lambert);
                        }
                    }
                    cover /= n as f64;
                    shade /= n as f64;
                    let i = (y as usize * wu + x as usize) * 3;
                    for ch in 0..3 {
                        let v = f64::from(data[i + ch]) * (1.0 - cover) + self.ball_bgr[ch] * shade;
                        data[i + ch] = v.round().clamp(0.0, 255.0) as u8;
                    }
                }
            }
        }
        if let Some((pts, rgb)) = occluder {
            let poly: Vector<Point> = pts
                .iter()
                .map(|p| Point::new(p[0].round() as i32, p[1].round() as i32))
                .collect();
            imgproc::fill_poly(
                &mut self.frame,
                &Vector::<Vector<Point>>::from(vec![poly]),
                Scalar::new(rgb[2], rgb[1], rgb[0], 0.0),
                imgproc::LINE_AA,
                0,
                Point::new(0, 0),
            )?;
        }
        if self.noise_sigma > 0.0 {
            let s = self.noise_sigma as f32;
            let row = w as usize * 3;
            let data = self.frame.data_bytes_mut()?;
            for line in data.chunks_mut(row) {
                let off = self.rng.random_range(0..NOISE_TABLE - row);
                for (v, n) in line.iter_mut().zip(&self.noise[off..off + row]) {
                    *v = (f32::from(*v) + s * n).round().clamp(0.0, 255.0) as u8;
                }
            }
        }
        Ok(&self.frame)
    }
}

/// The tool as an occluder: a long bar of width `width_px` at angle `angle_rad`
/// whose edge passes at signed distance `d_px` from `(x, y)` (the covered side
/// is the far side of the edge: `d_px = 0` covers half a ball centred there,
/// `d_px = r` none of it).
pub fn tool_occluder(x: f64, y: f64, d_px: f64, angle_rad: f64, width_px: f64) -> [[f64; 2]; 4] {
    let (s, c) = angle_rad.sin_cos();
    // Normal (c, s) points into the bar; the edge line is at distance d_px.
    let (ex, ey) = (x + c * d_px, y + s * d_px);
    let (tx, ty) = (-s * 400.0, c * 400.0);
    let (fx, fy) = (c * width_px, s * width_px);
    [
        [ex - tx, ey - ty],
        [ex + tx, ey + ty],
        [ex + tx + fx, ey + ty + fy],
        [ex - tx + fx, ey - ty + fy],
    ]
}
