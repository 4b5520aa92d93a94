//! The true camera: where it really stands, its lens, its shutter and its
//! clock, against what the lab believes (`[camera]`, the believed pose and
//! intrinsics the vision pipeline calibrates with).
//!
//! - **Timing.** Exposure of a frame starts at `t0` (the frame clock). It is
//!   delivered at `t0 + L_true + j`, `L_true = camera.latency_ms +
//!   world.camera.latency_ms`, `j` uniform in `[0, jitter]` per frame. The
//!   source stamps it as the real webcam source does: delivery time minus the
//!   *believed* latency, so a wrong belief or jitter shows up as a stamp error.
//!   No frame is delivered before its last row is read and sent: the
//!   delivery is at least `t_start + exposure + readout + transfer` (a latency
//!   drawn shorter than that, as `[world.camera] latency_ms` may, takes the
//!   floor).
//! - **Rolling shutter.** Row `v` is read `v / H * readout` after `t0`; the
//!   ball is seen where it was when its own row was exposed.
//! - **Exposure.** The ball is smeared over the exposure; the detected centre
//!   is the smear's centroid (the mean of the projections over the exposure).
//! - **Lens.** Brown-Conrady distortion `k1, k2, p1, p2` on normalised coordinates.
//! - **Pose.** The true camera is rotated (base x, y, z, radians) and shifted
//!   off the believed pose.
//! - **Clock.** The frame clock runs `1 + drift` times the PC's rate (frames
//!   come that much more often; the source stamps on the PC's clock, so the
//!   drift moves the frames against the swing, not the stamps). Each frame's
//!   exposure starts `U(-f, f)` off its slot while its delivery keeps the
//!   slot: stamp errors of both signs.
//! - **Light.** The ball's brightness is scaled by
//!   `g(t) = (1 + A sin(2 pi t/P + phi)) (1 + F m(t)) (1 - s(t))`: auto-exposure (`A`, period `P` 4..20 s),
//!   100 Hz mains flicker averaged over the exposure (`m(t)`, the mean of
//!   `sin(2 pi 100 t)` over it) and a passing shadow (`s(t)`: depth `S` for
//!   0.5..1.5 s in half of the lab clock's 10 s windows, drawn from the
//!   session's seed per window).
//! - **Occlusion.** `occluded` tells whether the true arm (capsules along its
//!   links and tool) stands in the line of sight to the ball's centre.
//!
//! `equivalent_centre_m` turns the true ball into the point the *believed*
//! camera would see at the same pixel and depth: handing that to a renderer
//! built on the believed camera makes rendered frames carry every effect.

use nalgebra::{Rotation3, Vector2, Vector3};
use rand::RngExt;

use super::params::SessionDraw;
use crate::vision::{CameraIntrinsics, CameraPose};

/// Samples across the exposure for the smear's centroid.
const EXPOSURE_SAMPLES: usize = 7;

/// A frame as the true camera makes it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameTiming {
    /// Start of the exposure (frame clock), s.
    pub t_start_s: f64,
    /// When the frame reaches the host, s.
    pub t_delivered_s: f64,
    /// The stamp the source gives it: delivery minus the believed latency, s.
    pub t_stamp_s: f64,
}

/// Where the true camera sees the ball in one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sighting {
    /// Detected centre (smear centroid), pixels.
    pub px: Vector2<f64>,
    /// Time the ball's row was read (start of its exposure), s.
    pub t_row_s: f64,
}

/// The true camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WorldCamera {
    /// What the lab believes (pose).
    pub believed_pose: CameraPose,
    /// The believed intrinsics (no distortion).
    pub intrinsics: CameraIntrinsics,
    /// Image height, pixels.
    pub height_px: f64,
    /// True camera centre, base frame, m.
    pub position_m: Vector3<f64>,
    /// True `base_from_camera`.
    pub base_from_camera: Rotation3<f64>,
    /// `[k1, k2, p1, p2]`.
    pub distortion: [f64; 4],
    /// Readout top row -> bottom row, s.
    pub rolling_shutter_s: f64,
    /// Exposure, s.
    pub exposure_s: f64,
    /// Readout end -> delivery at the least (the last packets), s.
    pub transfer_s: f64,
    /// The believed latency, s.
    pub believed_latency_s: f64,
    /// True latency minus the believed one, s.
    pub latency_offset_s: f64,
    /// Per-frame jitter bound, s.
    pub jitter_s: f64,
    /// Frame clock rate error (fraction; + fast).
    pub clock_drift: f64,
    /// Exposure-start jitter bound (either sign), s.
    pub frame_jitter_s: f64,
    /// Auto-exposure gain amplitude, its period (s) and phase (rad).
    pub exposure_gain: (f64, f64, f64),
    /// Mains flicker amplitude.
    pub flicker: f64,
    /// Depth of a passing shadow (0: none) and the seed of their schedule.
    pub shadow: (f64, u64),
}

/// Mains flicker frequency of the light (50 Hz mains), Hz.
pub const FLICKER_HZ: f64 = 100.0;
/// The shadows' schedule: one window of the lab clock, s.
pub const SHADOW_WINDOW_S: f64 = 10.0;
/// The arm's links as capsules of this radius, m (the iiwa's links are
/// 0.12-0.14 m across).
pub const LINK_RADIUS_M: f64 = 0.065;
/// The tool's shaft as a capsule of this radius, m.
pub const TOOL_RADIUS_M: f64 = 0.02;

impl WorldCamera {
    /// The true camera's intrinsics and lens (what the camera step measures).
    pub fn true_intrinsics(&self) -> crate::vision::CameraIntrinsics {
        let [k1, k2, p1, p2] = self.distortion;
        crate::vision::CameraIntrinsics {
            k1,
            k2,
            p1,
            p2,
            ..self.intrinsics
        }
    }

    /// A camera that is what the lab believes (no effect).
    pub fn truthful(
        believed_pose: CameraPose,
        intrinsics: CameraIntrinsics,
        height_px: u32,
        believed_latency_s: f64,
    ) -> Self {
        Self {
            believed_pose,
            intrinsics,
            height_px: f64::from(height_px),
            position_m: believed_pose.position(),
            base_from_camera: believed_pose.base_from_camera(),
            distortion: [0.0; 4],
            rolling_shutter_s: 0.0,
            exposure_s: 0.0,
            transfer_s: 0.0,
            believed_latency_s,
            latency_offset_s: 0.0,
            jitter_s: 0.0,
            clock_drift: 0.0,
            frame_jitter_s: 0.0,
            exposure_gain: (0.0, 1.0, 0.0),
            flicker: 0.0,
            shadow: (0.0, 0),
        }
    }

    /// The session's true camera around the believed one.
    pub fn from_session(
        believed_pose: CameraPose,
        intrinsics: CameraIntrinsics,
        height_px: u32,
        believed_latency_s: f64,
        s: &SessionDraw,
    ) -> Self {
        let mut c = Self::truthful(believed_pose, intrinsics, height_px, believed_latency_s);
        let [rx, ry, rz] = s.camera_rotation_error_rad;
        let err = Rotation3::from_euler_angles(rx, ry, rz);
        c.base_from_camera = err * c.base_from_camera;
        c.position_m += Vector3::from(s.camera_position_error_m);
        c.distortion = s.distortion;
        c.rolling_shutter_s = s.rolling_shutter_s;
        c.exposure_s = s.exposure_s;
        c.transfer_s = s.transfer_s;
        c.latency_offset_s = s.camera_latency_offset_s;
        c.jitter_s = s.camera_jitter_s;
        c.clock_drift = s.camera_clock_drift;
        c.frame_jitter_s = s.frame_jitter_s;
        c.exposure_gain = (
            s.exposure_gain_variation,
            s.exposure_gain_period_s,
            s.exposure_gain_phase_rad,
        );
        c.flicker = s.flicker;
        c.shadow = (s.shadow_depth, s.shadow_seed);
        c
    }

    /// The true time between frames for a nominal `period_s` (the camera's
    /// clock drift), s.
    pub fn frame_period_s(&self, period_s: f64) -> f64 {
        period_s / (1.0 + self.clock_drift)
    }

    /// The earliest a frame whose exposure starts at `t_start_s` can reach
    /// the host: its last row exposed and read, and sent, s.
    pub fn earliest_delivery_s(&self, t_start_s: f64) -> f64 {
        t_start_s + self.exposure_s + self.rolling_shutter_s + self.transfer_s
    }

    /// Delivery and stamp of the frame of slot `t_slot_s` on the frame clock
    /// (its exposure starts there, give or take the frame-time jitter): the
    /// true latency after the slot, or [`Self::earliest_delivery_s`] when that
    /// is later.
    pub fn timing(&self, t_slot_s: f64, rng: &mut impl rand::Rng) -> FrameTiming {
        let j = if self.jitter_s > 0.0 {
            rng.random_range(0.0..=self.jitter_s)
        } else {
            0.0
        };
        let e = if self.frame_jitter_s > 0.0 {
            rng.random_range(-self.frame_jitter_s..=self.frame_jitter_s)
        } else {
            0.0
        };
        let t_start_s = t_slot_s + e;
        let delivered = (t_slot_s + (self.believed_latency_s + self.latency_offset_s).max(0.0) + j)
            .max(self.earliest_delivery_s(t_start_s));
        FrameTiming {
            t_start_s,
            t_delivered_s: delivered,
            t_stamp_s: delivered - self.believed_latency_s,
        }
    }

    /// The light on the ball in the frame whose exposure starts at
    /// `t_start_s`, as a gain (1: as believed).
    pub fn light_gain(&self, t_start_s: f64) -> f64 {
        let (a, period, phase) = self.exposure_gain;
        let mut g = 1.0;
        if a > 0.0 {
            g *= 1.0 + a * (std::f64::consts::TAU * t_start_s / period.max(1e-3) + phase).sin();
        }
        if self.flicker > 0.0 {
            let w = std::f64::consts::TAU * FLICKER_HZ;
            let m = if self.exposure_s > 0.0 {
                ((w * t_start_s).cos() - (w * (t_start_s + self.exposure_s)).cos())
                    / (w * self.exposure_s)
            } else {
                (w * t_start_s).sin()
            };
            g *= 1.0 + self.flicker * m;
        }
        g * (1.0 - self.shadow_at(t_start_s))
    }

    /// The passing shadow's depth at `t_s` (0: none).
    pub fn shadow_at(&self, t_s: f64) -> f64 {
        let (depth, seed) = self.shadow;
        if depth <= 0.0 || !t_s.is_finite() {
            return 0.0;
        }
        let k = (t_s / SHADOW_WINDOW_S).floor();
        let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(
            seed ^ (k as i64 as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15),
        );
        if !rng.random_bool(0.5) {
            return 0.0;
        }
        let start = k * SHADOW_WINDOW_S + rng.random_range(0.0..=SHADOW_WINDOW_S - 1.5);
        let duration = rng.random_range(0.5..=1.5);
        if (start..start + duration).contains(&t_s) {
            depth
        } else {
            0.0
        }
    }

    /// Whether the arm whose link points (base, joints, flange, tool point
    /// in order) are `points` hides the ball centred at `ball_m` from the
    /// true camera: the line of sight passes within a link's (or the
    /// tool's, last segment) capsule before it reaches the ball.
    pub fn occluded(&self, points: &[Vector3<f64>], ball_m: &Vector3<f64>) -> bool {
        let n = points.len();
        points.windows(2).enumerate().any(|(i, seg)| {
            let r = if i + 2 == n {
                TOOL_RADIUS_M
            } else {
                LINK_RADIUS_M
            };
            segment_distance(&self.position_m, ball_m, &seg[0], &seg[1]) < r
        })
    }

    /// Projects a base-frame point through the true camera (with distortion);
    /// `None` behind it.
    pub fn project(&self, p_b: &Vector3<f64>) -> Option<Vector2<f64>> {
        let pc = self.base_from_camera.inverse() * (p_b - self.position_m);
        if pc.z <= 1e-6 {
            return None;
        }
        let (x, y) = (pc.x / pc.z, pc.y / pc.z);
        let [k1, k2, p1, p2] = self.distortion;
        let r2 = x * x + y * y;
        let radial = 1.0 + k1 * r2 + k2 * r2 * r2;
        let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        let k = &self.intrinsics;
        Some(Vector2::new(k.fx_px * xd + k.cx_px, k.fy_px * yd + k.cy_px))
    }

    /// Where the ball (centre at `ball(t)`) is seen in the frame whose exposure
    /// starts at `t_start_s`: its row's read time (rolling shutter, found by
    /// fixed-point iteration) and the centroid of its smear over the exposure.
    pub fn sight(
        &self,
        t_start_s: f64,
        mut ball: impl FnMut(f64) -> Vector3<f64>,
    ) -> Option<Sighting> {
        let mut t_row = t_start_s;
        let mut px = self.smear(t_row, &mut ball)?;
        if self.rolling_shutter_s > 0.0 {
            for _ in 0..4 {
                let row = px.y.clamp(0.0, self.height_px);
                t_row = t_start_s + row / self.height_px * self.rolling_shutter_s;
                px = self.smear(t_row, &mut ball)?;
            }
        }
        Some(Sighting { px, t_row_s: t_row })
    }

    fn smear(&self, t_s: f64, ball: &mut impl FnMut(f64) -> Vector3<f64>) -> Option<Vector2<f64>> {
        if self.exposure_s <= 0.0 {
            return self.project(&ball(t_s));
        }
        let mut sum = Vector2::zeros();
        for k in 0..EXPOSURE_SAMPLES {
            let t = t_s + self.exposure_s * (k as f64) / ((EXPOSURE_SAMPLES - 1) as f64);
            sum += self.project(&ball(t))?;
        }
        Some(sum / EXPOSURE_SAMPLES as f64)
    }

    /// The point the believed camera sees at pixel `px` at the depth of
    /// `depth_from_b` (believed camera frame): what a renderer built on the
    /// believed camera must draw so that it appears at `px`.
    pub fn equivalent_centre_m(
        &self,
        px: &Vector2<f64>,
        depth_from_b: &Vector3<f64>,
    ) -> Vector3<f64> {
        let pc = self.believed_pose.to_camera(depth_from_b);
        let ray = self.intrinsics.ray(px.x, px.y);
        let p_c = ray * pc.z.max(1e-3);
        self.believed_pose.base_from_camera() * p_c + self.believed_pose.position()
    }
}

/// Shortest distance between segments `p0 p1` and `q0 q1` (parameters clamped).
fn segment_distance(
    p0: &Vector3<f64>,
    p1: &Vector3<f64>,
    q0: &Vector3<f64>,
    q1: &Vector3<f64>,
) -> f64 {
    let d1 = p1 - p0;
    let d2 = q1 - q0;
    let r = p0 - q0;
    let a = d1.dot(&d1);
    let e = d2.dot(&d2);
    let f = d2.dot(&r);
    let (s, t) = if a <= 1e-12 && e <= 1e-12 {
        (0.0, 0.0)
    } else if a <= 1e-12 {
        (0.0, (f / e).clamp(0.0, 1.0))
    } else {
        let c = d1.dot(&r);
        if e <= 1e-12 {
            ((-c / a).clamp(0.0, 1.0), 0.0)
        } else {
            let b = d1.dot(&d2);
            let denom = a * e - b * b;
            let mut s = if denom > 1e-12 {
                ((b * f - c * e) / denom).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let mut t = (b * s + f) / e;
            if t < 0.0 {
                t = 0.0;
                s = (-c / a).clamp(0.0, 1.0);
            } else if t > 1.0 {
                t = 1.0;
                s = ((b - c) / a).clamp(0.0, 1.0);
            }
            (s, t)
        }
    };
    ((p0 + d1 * s) - (q0 + d2 * t)).norm()
}
