//! The world's webcam: frames of the true ball as the true camera takes
//! them (its stamps and delivery latency, rolling shutter, exposure, lens
//! and pose: [`WorldCamera`]), rendered (`sim::camera::SimCamera`, through
//! the believed camera at the point the true camera sees, as the virtual
//! lab's rendered frames) and encoded as JPEG for a network camera stream
//! (`isochron world`). The magnet board's calibration LED (D12), when lit,
//! shows as a small bright spot in the image's top-left corner ([`LED_PX`]),
//! as bright as the share of its row's exposure it was lit
//! ([`WorldWebcam::led_lit_share`]).
//!
//! The true ball reaches the webcam as samples of the world's steps
//! ([`BallSample`], one per controller cycle); the ball between two samples
//! is their cubic Hermite interpolation (position and velocity at both
//! ends: under 0.1 mm at 5 ms steps of a 2 m pendulum).

use std::collections::VecDeque;

use nalgebra::Vector3;
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, Point, Scalar, Vector};
use opencv::imgcodecs;
use opencv::imgproc;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::board::BoardOperator;
use super::camera::{FrameTiming, WorldCamera};
use super::marker::{draw_marker, marker_rim};
use super::params::SessionDraw;
use crate::calibration::Chessboard;
use crate::params::Scenario;
use crate::sim::camera::{BallState, SimCamera, SimCameraParams};
use crate::vision::VisionError;

/// The true ball at one world step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BallSample {
    /// World clock, s.
    pub t_s: f64,
    /// Ball centre, base frame, m.
    pub centre_m: Vector3<f64>,
    /// Ball velocity, m/s.
    pub velocity_mps: Vector3<f64>,
    /// The true arm's points (`TrueArm::points`), when it may hide the ball
    /// (`world.camera.arm_occludes`).
    pub arm_m: Option<[Vector3<f64>; crate::kinematics::iiwa7::JOINTS + 2]>,
    /// The tool's marker disc, when it is on the tool: its centre and
    /// normal, base frame (`marker::marker_pose` of the true flange).
    pub marker_m: Option<(Vector3<f64>, Vector3<f64>)>,
}

/// Samples kept (2 s at 1 ms steps).
const HISTORY: usize = 2048;
/// JPEG quality of the stream.
pub const JPEG_QUALITY: i32 = 90;
/// Where the LED shows, pixels, and its radius.
pub const LED_PX: (i32, i32, i32) = (40, 40, 10);

/// The world's webcam (module docs).
pub struct WorldWebcam {
    render: SimCamera,
    camera: WorldCamera,
    history: VecDeque<BallSample>,
    rng: ChaCha8Rng,
    with_led: Mat,
    jpeg: Vector<u8>,
    period_s: f64,
    /// The operator's board and the hold shown (0-based), when one is held.
    board: Option<(BoardOperator, usize)>,
    with_board: Mat,
    with_marker: Mat,
    /// The latest frame ([`Self::frame`]).
    out: Mat,
    noise: f64,
    size: (f64, f64),
    seed: u64,
}

impl std::fmt::Debug for WorldWebcam {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WorldWebcam")
            .field("samples", &self.history.len())
            .finish_non_exhaustive()
    }
}

impl WorldWebcam {
    /// The session's true camera for `scenario`'s believed one (the
    /// simulated lab's pose, `SimCameraParams::default()`).
    ///
    /// # Errors
    ///
    /// The error of [`SimCamera::new`] (invalid camera parameters, OpenCV).
    pub fn new(scenario: &Scenario, session: &SessionDraw, seed: u64) -> Result<Self, VisionError> {
        let params = SimCameraParams::default();
        let render = SimCamera::new(
            &scenario.camera,
            &params,
            scenario.pendulum.ball_radius_m,
            seed,
        )?;
        let camera = WorldCamera::from_session(
            params.pose,
            scenario.camera.believed_intrinsics(params.hfov_deg),
            scenario.camera.height_px,
            scenario.camera.latency_ms * 1e-3,
            session,
        );
        Ok(Self {
            render,
            camera,
            history: VecDeque::with_capacity(HISTORY),
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0x7765_6263_616d),
            with_led: Mat::default(),
            jpeg: Vector::new(),
            period_s: camera.frame_period_s(1.0 / scenario.camera.fps),
            board: None,
            with_board: Mat::default(),
            with_marker: Mat::default(),
            out: Mat::default(),
            noise: scenario.camera.image_noise,
            size: (
                f64::from(scenario.camera.width_px),
                f64::from(scenario.camera.height_px),
            ),
            seed,
        })
    }

    /// Time between frames (the true camera's clock), s.
    pub fn period_s(&self) -> f64 {
        self.period_s
    }

    /// How long after a frame's exposure starts the truth it shows is all
    /// known (exposure and readout), s.
    pub fn truth_after_s(&self) -> f64 {
        self.camera.exposure_s + self.camera.rolling_shutter_s + self.camera.frame_jitter_s
    }

    /// The true camera.
    pub fn camera(&self) -> &WorldCamera {
        &self.camera
    }

    /// The operator holds the default chessboard (9 x 6 inner corners, 30 mm
    /// squares) at hold `pose` of `views` (0-based; planned over the true
    /// camera's image as a person watching the live view places it), or
    /// lowers it (`None`). The holds stay planned while `views` does not change.
    pub fn hold_board(&mut self, held: Option<(usize, usize)>) {
        let Some((pose, views)) = held else {
            self.board = None;
            return;
        };
        match self.board.as_mut() {
            Some((op, shown)) if op.views() == views => *shown = pose,
            _ => {
                let op = BoardOperator::new(
                    &self.camera,
                    Chessboard::default(),
                    views,
                    self.size,
                    self.seed,
                );
                self.board = Some((op, pose));
            }
        }
    }

    /// One world step's true ball.
    pub fn push(&mut self, s: BallSample) {
        if self.history.back().is_some_and(|b| s.t_s <= b.t_s) {
            return;
        }
        if self.history.len() == HISTORY {
            self.history.pop_front();
        }
        self.history.push_back(s);
    }

    /// The latest sample's time, s.
    pub fn latest_s(&self) -> Option<f64> {
        self.history.back().map(|s| s.t_s)
    }

    /// The true ball at `t_s` (interpolated; the nearest end outside the samples).
    pub fn ball_at(&self, t_s: f64) -> Option<(Vector3<f64>, Vector3<f64>)> {
        let h = &self.history;
        let (first, last) = (h.front()?, h.back()?);
        if t_s <= first.t_s {
            return Some((first.centre_m, first.velocity_mps));
        }
        if t_s >= last.t_s {
            return Some((last.centre_m, last.velocity_mps));
        }
        let i = h.partition_point(|s| s.t_s <= t_s);
        let (a, b) = (&h[i - 1], &h[i]);
        let dt = b.t_s - a.t_s;
        let u = (t_s - a.t_s) / dt;
        let (u2, u3) = (u * u, u * u * u);
        let h00 = 2.0 * u3 - 3.0 * u2 + 1.0;
        let h10 = u3 - 2.0 * u2 + u;
        let h01 = -2.0 * u3 + 3.0 * u2;
        let h11 = u3 - u2;
        let p = a.centre_m * h00
            + a.velocity_mps * (h10 * dt)
            + b.centre_m * h01
            + b.velocity_mps * (h11 * dt);
        let v = a.velocity_mps * (1.0 - u) + b.velocity_mps * u;
        Some((p, v))
    }

    /// When the frame of slot `t_slot_s` starts its exposure, is delivered, and its stamp.
    pub fn timing(&mut self, t_slot_s: f64) -> FrameTiming {
        self.camera.timing(t_slot_s, &mut self.rng)
    }

    /// The true arm's points nearest `t_s` (`None`: no arm that hides the ball).
    fn arm_at(&self, t_s: f64) -> Option<[Vector3<f64>; crate::kinematics::iiwa7::JOINTS + 2]> {
        let h = &self.history;
        let i = h
            .partition_point(|s| s.t_s <= t_s)
            .min(h.len().checked_sub(1)?);
        h[i].arm_m
    }

    /// The marker disc nearest `t_s` (`None`: not on the tool).
    fn marker_at(&self, t_s: f64) -> Option<(Vector3<f64>, Vector3<f64>)> {
        let h = &self.history;
        let i = h
            .partition_point(|s| s.t_s <= t_s)
            .min(h.len().checked_sub(1)?);
        h[i].marker_m
    }

    /// When the LED's row of the frame whose exposure starts at
    /// `t_start_s` is exposed: from, to (the rolling shutter reads it
    /// `LED_PX.1 / height` of the readout after the top row), s.
    pub fn led_exposure_s(&self, t_start_s: f64) -> (f64, f64) {
        let c = &self.camera;
        let row = f64::from(LED_PX.1) / c.height_px.max(1.0);
        let from = t_start_s + c.rolling_shutter_s * row;
        (from, from + c.exposure_s)
    }

    /// The true latency of the LED's row: from the middle of its exposure
    /// to the frame's delivery, on average over the delivery and frame-time
    /// jitter, s (what the latency step measures). A frame is delivered
    /// `max(L + j, F + e)` after its slot (`WorldCamera::timing`: latency `L`,
    /// jitter `j` in `[0, J]`, exposure start `e` in `[-f, f]`, readout end
    /// and transfer `F`) and its LED row is exposed around `e`; the mean of
    /// `max(L + j - e, F)` is taken by the midpoint rule.
    pub fn led_latency_s(&self) -> f64 {
        const N: u32 = 256;
        let c = &self.camera;
        let (from, to) = self.led_exposure_s(0.0);
        let latency = (c.believed_latency_s + c.latency_offset_s).max(0.0);
        let floor = c.earliest_delivery_s(0.0);
        let mut sum = 0.0;
        for a in 0..N {
            let j = c.jitter_s * (f64::from(a) + 0.5) / f64::from(N);
            for b in 0..N {
                let e = c.frame_jitter_s * (2.0 * (f64::from(b) + 0.5) / f64::from(N) - 1.0);
                sum += (latency + j - e).max(floor);
            }
        }
        sum / f64::from(N * N) - 0.5 * (from + to)
    }

    /// The share of the LED row's exposure (`led_exposure_s`) during which
    /// the LED was lit, given its switches `(time, on)` in time order (lit
    /// before the first when `lit_before`).
    pub fn led_lit_share(
        &self,
        t_start_s: f64,
        lit_before: bool,
        switches: impl IntoIterator<Item = (f64, bool)>,
    ) -> f64 {
        let (a, b) = self.led_exposure_s(t_start_s);
        let mut state = lit_before;
        let mut last = a;
        let mut lit = 0.0;
        for (t, on) in switches {
            if t <= a {
                state = on;
                continue;
            }
            if t >= b {
                break;
            }
            if state {
                lit += t - last;
            }
            last = t;
            state = on;
        }
        if b <= a {
            // No exposure time (an ideal camera): the state at its instant.
            return if state { 1.0 } else { 0.0 };
        }
        if state {
            lit += b - last;
        }
        (lit / (b - a)).clamp(0.0, 1.0)
    }

    /// The JPEG of the frame whose exposure starts at `t_start_s`
    /// ([`Self::frame`]).
    ///
    /// # Errors
    ///
    /// [`VisionError::OpenCv`] when rendering, drawing the LED or encoding fails;
    /// [`VisionError::BadFrame`] when the JPEG encoder refuses the image.
    pub fn frame_jpeg(&mut self, t_start_s: f64, led: f64) -> Result<&[u8], VisionError> {
        self.frame(t_start_s, led)?;
        let params = Vector::<i32>::from_slice(&[imgcodecs::IMWRITE_JPEG_QUALITY, JPEG_QUALITY]);
        self.jpeg.clear();
        if !imgcodecs::imencode(".jpg", &self.out, &mut self.jpeg, &params)? {
            return Err(crate::vision::FrameProblem::JpegEncoding.into());
        }
        Ok(self.jpeg.as_slice())
    }

    /// The latest frame [`Self::frame`] (or [`Self::frame_jpeg`]) rendered,
    /// as a raw frame to hand over in-process.
    ///
    /// # Errors
    ///
    /// [`VisionError::OpenCv`] when the image's bytes cannot be read.
    pub fn latest_raw(&self) -> Result<crate::vision::RawFrame, VisionError> {
        Ok(crate::vision::RawFrame {
            width: self.out.cols(),
            height: self.out.rows(),
            bgr: std::sync::Arc::new(self.out.data_bytes()?.to_vec()),
        })
    }

    /// The frame whose exposure starts at `t_start_s` (the ball where the
    /// true camera sees it; out of view: no ball), with the LED lit for the
    /// share `led` (0..1) of its row's exposure: 8-bit BGR, valid until the
    /// next frame.
    ///
    /// # Errors
    ///
    /// [`VisionError::OpenCv`] when rendering or drawing fails.
    pub fn frame(&mut self, t_start_s: f64, led: f64) -> Result<&Mat, VisionError> {
        // The tool's marker disc (on while the operator has fitted it),
        // where the true camera sees the true arm's tool.
        let rim = self
            .marker_at(t_start_s)
            .and_then(|(c, n)| marker_rim(&self.camera, &c, &n));
        let sight = self.camera.sight(t_start_s, |t| {
            self.ball_at(t).map_or(Vector3::zeros(), |b| b.0)
        });
        let state = match (sight, self.ball_at(t_start_s)) {
            (Some(s), Some((p, v))) => {
                // A ball the true arm hides is not drawn.
                let hidden = self
                    .arm_at(t_start_s)
                    .is_some_and(|arm| self.camera.occluded(&arm, &p));
                (!hidden).then(|| BallState {
                    centre_m: self.camera.equivalent_centre_m(&s.px, &p),
                    velocity_mps: v,
                })
            }
            _ => None,
        };
        self.render.set_ball_gain(self.camera.light_gain(t_start_s));
        let image = self.render.render(state.as_ref())?;
        let image = if led > 0.0 {
            image.copy_to(&mut self.with_led)?;
            let (x, y, r) = LED_PX;
            imgproc::circle(
                &mut self.with_led,
                Point::new(x, y),
                r,
                Scalar::new(255.0, 255.0, 255.0, 0.0),
                -1,
                imgproc::LINE_8,
                0,
            )?;
            if led < 1.0 {
                // Lit for part of the exposure: that share of the light.
                let mut mixed = Mat::default();
                opencv::core::add_weighted(
                    image,
                    1.0 - led,
                    &self.with_led,
                    led,
                    0.0,
                    &mut mixed,
                    -1,
                )?;
                self.with_led = mixed;
            }
            &self.with_led
        } else {
            image
        };
        let image = match self.board.as_mut() {
            Some((op, pose)) => {
                image.copy_to(&mut self.with_board)?;
                op.draw(&self.camera, *pose, &mut self.with_board, self.noise)?;
                &self.with_board
            }
            None => image,
        };
        let image = match rim {
            Some(rim) => {
                image.copy_to(&mut self.with_marker)?;
                draw_marker(&mut self.with_marker, &rim, self.noise, &mut self.rng)?;
                &self.with_marker
            }
            None => image,
        };
        image.copy_to(&mut self.out)?;
        Ok(&self.out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::{Detector, DetectorParams, SwingPlaneCalibration};

    /// The default scenario's truthful world's webcam (seed 1).
    fn webcam() -> (Scenario, WorldWebcam) {
        let s = Scenario::default();
        let session = s
            .world
            .clone()
            .unwrap_or_default()
            .draw_session(1, 0, s.robot.latency_ms);
        let cam = WorldWebcam::new(&s, &session, 1).unwrap();
        (s, cam)
    }

    #[test]
    fn the_stream_shows_the_true_ball_where_the_detector_finds_it() {
        let (s, mut cam) = webcam();
        // A ball swinging along y through the believed rest point.
        let rest = Vector3::new(s.task.distance_m.lerp(0.5), 0.0, s.task.intercept_height_m);
        for k in 0..200 {
            let t = f64::from(k) * 0.005;
            let y = 0.3 * (3.0 * t).sin();
            cam.push(BallSample {
                t_s: t,
                centre_m: rest + Vector3::new(0.0, y, 0.0),
                velocity_mps: Vector3::new(0.0, 0.9 * (3.0 * t).cos(), 0.0),
                arm_m: None,
                marker_m: None,
            });
        }
        // Interpolation between samples is exact to well under a mm here.
        let (p, _) = cam.ball_at(0.5025).unwrap();
        assert!((p.y - 0.3 * (3.0f64 * 0.5025).sin()).abs() < 1e-4, "{p}");
        let pose = SimCameraParams::default().pose;
        let intrinsics = s
            .camera
            .believed_intrinsics(SimCameraParams::default().hfov_deg);
        let cal =
            SwingPlaneCalibration::from_pose(intrinsics, &pose, &rest, s.pendulum.ball_radius_m);
        let mut det = Detector::new(DetectorParams::default()).unwrap();
        for &t in &[0.2, 0.5, 0.8] {
            let jpeg = cam
                .frame_jpeg(t, if t > 0.6 { 1.0 } else { 0.0 })
                .unwrap()
                .to_vec();
            let img =
                imgcodecs::imdecode(&Vector::<u8>::from_slice(&jpeg), imgcodecs::IMREAD_COLOR)
                    .unwrap();
            assert_eq!(img.cols() as u32, s.camera.width_px);
            let d = det
                .detect(&img, t)
                .unwrap()
                .expect("the ball is found in the stream's frame");
            let lateral = cal.lateral_m(d.x_px, d.y_px).unwrap();
            let truth = 0.3 * (3.0 * t).sin();
            assert!(
                (lateral - truth).abs() < 0.005,
                "t {t}: {lateral} vs {truth}"
            );
        }
    }

    #[test]
    fn the_operators_board_shows_where_the_lab_finds_its_corners_and_goes_when_lowered() {
        let (_, mut cam) = webcam();
        let board = Chessboard::default();
        let corners = |cam: &mut WorldWebcam| {
            let jpeg = cam.frame_jpeg(0.2, 0.0).unwrap().to_vec();
            let img = imgcodecs::imdecode(
                &Vector::<u8>::from_slice(&jpeg),
                imgcodecs::IMREAD_GRAYSCALE,
            )
            .unwrap();
            crate::calibration::intrinsics::detect_corners(&img, &board).unwrap()
        };
        assert_eq!(corners(&mut cam), None, "a board before one is held");
        let mut seen = Vec::new();
        for pose in 0..4 {
            cam.hold_board(Some((pose, 12)));
            let c = corners(&mut cam).unwrap_or_else(|| panic!("hold {pose}: no corners"));
            assert_eq!(c.len(), board.corners());
            seen.push(c[0]);
        }
        // Each hold is somewhere else in the image.
        for (i, a) in seen.iter().enumerate() {
            for b in &seen[i + 1..] {
                assert!((a[0] - b[0]).hypot(a[1] - b[1]) > 20.0, "{seen:?}");
            }
        }
        cam.hold_board(None);
        assert_eq!(corners(&mut cam), None, "the board lowered");
    }

    #[test]
    fn the_led_rows_true_latency_is_the_mean_of_its_frames_even_where_the_readout_floors_them() {
        let (_, mut cam) = webcam();
        // Reality seed 1's webcam: 29.7 ms drawn, 4 ms of jitter, 8 ms of
        // exposure, 25 ms of readout, 1 ms of frame-time jitter, 2 ms of
        // transfer: every frame waits for its readout (34..36 ms after its
        // slot, where 29.7..33.7 ms were drawn).
        cam.camera.latency_offset_s = 0.0297 - cam.camera.believed_latency_s;
        cam.camera.jitter_s = 0.004;
        cam.camera.exposure_s = 0.008;
        cam.camera.rolling_shutter_s = 0.025;
        cam.camera.frame_jitter_s = 0.001;
        cam.camera.transfer_s = 0.002;
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let n = 40_000;
        let mut sum = 0.0;
        for k in 0..n {
            let slot = f64::from(k) / 30.0;
            let f = cam.camera.timing(slot, &mut rng);
            let (a, b) = cam.led_exposure_s(f.t_start_s);
            sum += f.t_delivered_s - 0.5 * (a + b);
        }
        let mean = sum / f64::from(n);
        let truth = cam.led_latency_s();
        assert!(
            (mean - truth).abs() < 1e-4,
            "frames {:.3} ms, truth {:.3} ms",
            mean * 1e3,
            truth * 1e3
        );
        // Without the floor the truth would be 29.7 + 2 ms less the LED
        // row's middle: the floor moves it later.
        let (a, b) = cam.led_exposure_s(0.0);
        assert!(truth > 0.0317 - 0.5 * (a + b) + 1e-3, "{}", truth * 1e3);
    }

    #[test]
    fn the_led_shows_the_share_of_its_rows_exposure_it_was_lit() {
        let (_, mut cam) = webcam();
        cam.camera.exposure_s = 0.010;
        cam.camera.rolling_shutter_s = 0.018;
        let (a, b) = cam.led_exposure_s(1.0);
        let row = f64::from(LED_PX.1) / cam.camera.height_px;
        assert!((a - (1.0 + 0.018 * row)).abs() < 1e-12 && (b - a - 0.010).abs() < 1e-12);
        // Off before, on 30% into the exposure, off again after it.
        let share = cam.led_lit_share(1.0, false, [(a + 0.003, true), (b + 0.5, false)]);
        assert!((share - 0.7).abs() < 1e-9, "{share}");
        assert_eq!(cam.led_lit_share(1.0, true, []), 1.0);
        assert_eq!(
            cam.led_lit_share(1.0, false, [(a - 0.1, true), (a - 0.05, false)]),
            0.0
        );
        // The latency the step measures: to the middle of the LED row's exposure.
        let c = cam.camera;
        let want = (c.believed_latency_s + c.latency_offset_s).max(0.0) + 0.5 * c.jitter_s
            - 0.018 * row
            - 0.005;
        assert!((cam.led_latency_s() - want).abs() < 1e-12);
        // The region reads brighter with the share lit, about linearly.
        let roi = [f64::from(LED_PX.0), f64::from(LED_PX.1), 4.0];
        let level = |cam: &mut WorldWebcam, share: f64| {
            let jpeg = cam.frame_jpeg(0.2, share).unwrap().to_vec();
            let img =
                imgcodecs::imdecode(&Vector::<u8>::from_slice(&jpeg), imgcodecs::IMREAD_COLOR)
                    .unwrap();
            crate::lab::vision::led_level(&img, roi).unwrap().unwrap()
        };
        let (off, half, on) = (
            level(&mut cam, 0.0),
            level(&mut cam, 0.5),
            level(&mut cam, 1.0),
        );
        assert!(on - off > 100.0, "off {off}, on {on}");
        assert!(
            (half - 0.5 * (off + on)).abs() < 10.0,
            "off {off}, half {half}, on {on}"
        );
    }
}
