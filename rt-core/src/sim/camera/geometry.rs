//! The simulated camera's settings and the true ball it films (no OpenCV:
//! the measurement-model lab and the camera's geometry need only these).

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::check::{self, ParamError};
use crate::vision::CameraPose;

/// The ball's true state in the robot base frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BallState {
    /// Ball centre, metres.
    pub centre_m: Vector3<f64>,
    /// Ball velocity, m/s (the ball moves linearly over the short exposure).
    pub velocity_mps: Vector3<f64>,
}

impl BallState {
    /// A ball at `centre_m` moving with `velocity_mps` (base frame).
    pub fn from_arrays(centre_m: [f64; 3], velocity_mps: [f64; 3]) -> Self {
        Self {
            centre_m: Vector3::from(centre_m),
            velocity_mps: Vector3::from(velocity_mps),
        }
    }
}

/// The simulated camera's own settings (the `[camera]` section of the scenario
/// gives frame rate, size, noise, drops, latency and the vision mode).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimCameraParams {
    /// Horizontal field of view, degrees (Logitech C920: about 70).
    pub hfov_deg: f64,
    /// Where the camera stands, robot base frame.
    pub pose: CameraPose,
    /// Exposure time, milliseconds (the ball is smeared over it).
    pub exposure_ms: f64,
    /// Standard deviation of the capture -> available latency around `camera.latency_ms`, ms.
    pub latency_jitter_ms: f64,
    /// Ball colour under full light, RGB 0..255 (optic yellow).
    pub ball_rgb: [f64; 3],
    /// Number of clutter objects drawn on the background.
    pub clutter_count: u32,
    /// Relative lighting change between frames and across the image, 0..0.5.
    pub lighting_variation: f64,
    /// Number of pre-rendered lighting variants (each a full frame of static noise).
    pub lighting_variants: u32,
    /// In `model` mode: standard deviation of the measured centre, pixels.
    pub model_noise_px: f64,
    /// Seed of the background (texture and clutter).
    pub scene_seed: u64,
}

impl Default for SimCameraParams {
    fn default() -> Self {
        Self {
            hfov_deg: 70.0,
            pose: CameraPose::default(),
            exposure_ms: 6.0,
            latency_jitter_ms: 1.0,
            ball_rgb: [205.0, 235.0, 60.0],
            clutter_count: 40,
            lighting_variation: 0.1,
            lighting_variants: 4,
            model_noise_px: 0.3,
            scene_seed: 7,
        }
    }
}

impl SimCameraParams {
    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first field
    /// (the pose's included) that is not finite or outside its range.
    pub fn validate(&self) -> Result<(), ParamError> {
        check::within("sim_camera.hfov_deg", self.hfov_deg, 10.0, 150.0)?;
        self.pose.validate("sim_camera.pose")?;
        check::within("sim_camera.exposure_ms", self.exposure_ms, 0.0, 100.0)?;
        check::within(
            "sim_camera.latency_jitter_ms",
            self.latency_jitter_ms,
            0.0,
            100.0,
        )?;
        for (i, v) in self.ball_rgb.iter().enumerate() {
            check::within(&format!("sim_camera.ball_rgb[{i}]"), *v, 0.0, 255.0)?;
        }
        check::within_u32("sim_camera.clutter_count", self.clutter_count, 0, 1000)?;
        check::within(
            "sim_camera.lighting_variation",
            self.lighting_variation,
            0.0,
            0.5,
        )?;
        check::within_u32(
            "sim_camera.lighting_variants",
            self.lighting_variants,
            1,
            16,
        )?;
        check::within("sim_camera.model_noise_px", self.model_noise_px, 0.0, 50.0)
    }
}
