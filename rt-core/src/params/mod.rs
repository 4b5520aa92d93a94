#![doc = include_str!("README.md")]

// `ParamError` and the `check` helpers live in the leaf module `crate::check`
// (every part may use it; it imports nothing of the crate).
pub use crate::check;
pub use crate::check::{ParamError, RangeParam};
// The sections owned by their parts (no back-imports into `params`).
pub use crate::control::SuccessParams;
pub use crate::pendulum::PendulumParams;
pub use crate::trajectory::{TaskMode, TaskParams};

pub mod world;

use std::path::Path;

use serde::{Deserialize, Serialize};

/// How the simulated camera produces measurements.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VisionMode {
    /// Render frames and run the OpenCV detector on them.
    Full,
    /// A noisy projection of the true ball: no images (fast).
    Model,
}

/// The camera: `[camera]` in a scenario.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraParams {
    /// Frames per second.
    pub fps: f64,
    /// Image width, pixels.
    pub width_px: u32,
    /// Image height, pixels.
    pub height_px: u32,
    /// Capture -> measurement available, milliseconds.
    pub latency_ms: f64,
    /// Standard deviation of pixel intensity noise, 0..255.
    pub image_noise: f64,
    /// Fraction of frames lost, 0..1.
    pub drop_rate: f64,
    /// `full` (render + OpenCV) or `model` (noisy projection).
    pub vision: VisionMode,
    /// Where the lab believes the camera stands (base frame): written by
    /// `isochron calibrate camera-robot` through the calibration file; `None`:
    /// the simulated lab's mounting (`SimCameraParams::pose`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pose: Option<crate::vision::CameraPose>,
    /// The believed intrinsics and lens (`[camera.intrinsics]`: `fx_px, fy_px,
    /// cx_px, cy_px, k1, k2, p1, p2`), as `isochron calibrate camera` measured
    /// them (the calibration file sets it). Absent: the simulated camera's
    /// nominal pinhole (square pixels, centred principal point, 70 degrees
    /// horizontal field of view, no distortion); the real lab's
    /// `[calibration]` focal length and principal point, no distortion.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub intrinsics: Option<crate::vision::CameraIntrinsics>,
}

impl Default for CameraParams {
    fn default() -> Self {
        Self {
            fps: 30.0,
            width_px: 1280,
            height_px: 720,
            latency_ms: 35.0,
            image_noise: 6.0,
            drop_rate: 0.02,
            vision: VisionMode::Full,
            pose: None,
            intrinsics: None,
        }
    }
}

impl CameraParams {
    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first bad
    /// field (a drop rate above 0.9 included), or the error of the pose's or
    /// intrinsics' check.
    pub fn validate(&self) -> Result<(), ParamError> {
        check::within("camera.fps", self.fps, 1.0, 500.0)?;
        check::within_u32("camera.width_px", self.width_px, 64, 7680)?;
        check::within_u32("camera.height_px", self.height_px, 48, 4320)?;
        check::within("camera.latency_ms", self.latency_ms, 0.0, 1000.0)?;
        check::within("camera.image_noise", self.image_noise, 0.0, 255.0)?;
        check::probability("camera.drop_rate", self.drop_rate)?;
        if let Some(p) = &self.pose {
            p.validate("camera.pose")?;
        }
        if self.drop_rate > 0.9 {
            return Err(check::out_of_range(
                "camera.drop_rate",
                self.drop_rate,
                check::Bound::rule("must be <= 0.9 (the ball must be seen)"),
            ));
        }
        if let Some(k) = &self.intrinsics {
            k.validate("camera.intrinsics")?;
        }
        Ok(())
    }

    /// The intrinsics the lab believes for the simulated camera: the calibrated
    /// ones (`intrinsics`) or the nominal pinhole of a `hfov_deg` lens.
    pub fn believed_intrinsics(&self, hfov_deg: f64) -> crate::vision::CameraIntrinsics {
        self.intrinsics.unwrap_or_else(|| {
            crate::vision::CameraIntrinsics::from_hfov(self.width_px, self.height_px, hfov_deg)
        })
    }
}

/// The robot and its FRI link: `[robot]` in a scenario.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RobotParams {
    /// FRI send period of the controller, whole milliseconds (1..100).
    pub fri_period_ms: u32,
    /// True command-to-motion delay of the simulated robot, ms (unknown to the controller).
    pub latency_ms: f64,
    /// Jitter of that delay, ms (unknown to the controller).
    pub latency_jitter_ms: f64,
}

impl Default for RobotParams {
    fn default() -> Self {
        Self {
            fri_period_ms: crate::control::beliefs::FRI_PERIOD_MS_DEFAULT,
            latency_ms: 8.0,
            latency_jitter_ms: 2.0,
        }
    }
}

impl RobotParams {
    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first field
    /// that is not finite or outside its range.
    pub fn validate(&self) -> Result<(), ParamError> {
        crate::control::beliefs::validate_fri_period_ms("robot.fri_period_ms", self.fri_period_ms)?;
        check::within("robot.latency_ms", self.latency_ms, 0.0, 200.0)?;
        check::within("robot.latency_jitter_ms", self.latency_jitter_ms, 0.0, 50.0)
    }
}

/// A whole scenario: the lab the system runs in (CONTRACT.md, "Scenario file").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Scenario {
    /// Short name, shown in summaries.
    pub name: String,
    /// The pendulum.
    pub pendulum: PendulumParams,
    /// The interception task.
    pub task: TaskParams,
    /// The camera.
    pub camera: CameraParams,
    /// The robot and its FRI link.
    pub robot: RobotParams,
    /// How trials are judged.
    pub success: SuccessParams,
    /// The extended Kalman filter and predictor.
    pub ekf: crate::ekf::EkfParams,
    /// The Hopf timing dynamics and the timed motion.
    pub timing: crate::timing::TimingParams,
    /// The closed loop (trial states, latency estimate, guard).
    pub control: crate::control::ControlParams,
    /// The simulated lab as it really is (`[world]`; read only by the
    /// simulators, never by the controller). `None`: a truthful world.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub world: Option<world::WorldParams>,
}

impl Default for Scenario {
    fn default() -> Self {
        Self {
            name: "paper".to_owned(),
            pendulum: PendulumParams::default(),
            task: TaskParams::default(),
            camera: CameraParams::default(),
            robot: RobotParams::default(),
            success: SuccessParams::default(),
            ekf: crate::ekf::EkfParams::default(),
            timing: crate::timing::TimingParams::default(),
            control: crate::control::ControlParams::default(),
            world: None,
        }
    }
}

impl Scenario {
    /// Checks every section; the error names the first bad field.
    ///
    /// # Errors
    ///
    /// As [`Self::validate_but_world`], then the first error of the `[world]` section's check.
    pub fn validate(&self) -> Result<(), ParamError> {
        self.validate_but_world()?;
        if let Some(w) = &self.world {
            w.validate()?;
        }
        Ok(())
    }

    /// Checks every section but `[world]` (what the lab believes; the
    /// controller checks its own part again, `control::Beliefs::validate`).
    ///
    /// # Errors
    ///
    /// [`ParamError::OutOfRange`] for a name that is empty or longer than 64
    /// characters; otherwise the first error of a section's check.
    pub fn validate_but_world(&self) -> Result<(), ParamError> {
        if self.name.is_empty() || self.name.len() > 64 {
            return Err(ParamError::OutOfRange {
                field: "name".to_owned(),
                value: check::Value::Text(self.name.clone()),
                bound: check::Bound::rule("must be 1..=64 characters"),
            });
        }
        self.pendulum.validate()?;
        self.task.validate()?;
        self.camera.validate()?;
        self.robot.validate()?;
        self.success.validate()?;
        self.ekf.validate()?;
        self.timing.validate()?;
        self.control.validate()
    }

    /// What the controller is given (its only view of the lab): the sections
    /// it reads, never `[world]`, `[camera]`, `[success]` or the robot's true
    /// latency. `control` owns the type; `params` builds it (never the reverse).
    pub fn beliefs(&self) -> crate::control::Beliefs {
        crate::control::Beliefs {
            pendulum: self.pendulum.clone(),
            task: self.task.clone(),
            fri_period_ms: self.robot.fri_period_ms,
            ekf: self.ekf.clone(),
            timing: self.timing.clone(),
            control: self.control.clone(),
        }
    }

    /// Parses and validates a scenario from TOML text. Unknown keys are refused.
    ///
    /// ```
    /// use rt_core::params::Scenario;
    /// let s = Scenario::from_toml_str("[pendulum]\nlength_m = 2.0\n").unwrap();
    /// assert_eq!(s.pendulum.length_m, 2.0);
    /// // Out of range: refused, naming the field.
    /// let e = Scenario::from_toml_str("[pendulum]\nlength_m = 50.0\n").unwrap_err();
    /// assert_eq!(e.field(), Some("pendulum.length_m"));
    /// // An unknown key is refused too.
    /// assert!(Scenario::from_toml_str("[pendulum]\nlenght_m = 2.0\n").is_err());
    /// ```
    ///
    /// # Errors
    ///
    /// [`ParamError::Parse`] for bad TOML, a wrong type or an unknown key; a
    /// validation error of [`Self::validate`] naming the first bad field.
    pub fn from_toml_str(text: &str) -> Result<Self, ParamError> {
        let scenario: Self = toml::from_str(text).map_err(|e| toml_error(text, &e))?;
        scenario.validate()?;
        Ok(scenario)
    }

    /// Reads, parses and validates a scenario file.
    ///
    /// # Errors
    ///
    /// [`ParamError::Io`] when the file cannot be read; otherwise as
    /// [`Self::from_toml_str`], with the file named.
    pub fn from_file(path: &Path) -> Result<Self, ParamError> {
        let text = std::fs::read_to_string(path).map_err(|e| ParamError::Io {
            path: path.display().to_string(),
            reason: e.to_string(),
        })?;
        Self::from_toml_str(&text).map_err(|e| e.in_file(path))
    }

    /// The scenario as TOML text (every key written out).
    pub fn to_toml_string(&self) -> String {
        // Serialising plain structs of numbers and strings cannot fail.
        toml::to_string_pretty(self).unwrap_or_default()
    }
}

/// Turns a TOML error into one line: `line N: section.key: <message>` (any
/// TOML file of the lab: scenarios, `isochron serve --config`).
pub fn toml_error(text: &str, e: &toml::de::Error) -> ParamError {
    let Some(span) = e.span() else {
        return ParamError::parse(e.message());
    };
    let start = span.start.min(text.len());
    let before = &text[..start];
    let line_no = before.matches('\n').count() + 1;
    let section = before
        .lines()
        .rev()
        .map(str::trim)
        .find(|l| l.starts_with('[') && l.ends_with(']'))
        .map(|l| l.trim_matches(|c| c == '[' || c == ']').trim());
    let line = text[before.rfind('\n').map_or(0, |i| i + 1)..]
        .lines()
        .next()
        .unwrap_or("");
    let key = line
        .split_once('=')
        .map(|(k, _)| k.trim())
        .filter(|k| !k.is_empty() && !k.starts_with('['));
    let key = match (section, key) {
        (Some(s), Some(k)) => Some(format!("{s}.{k}")),
        (None, Some(k)) => Some(k.to_owned()),
        (Some(s), None) => Some(s.to_owned()),
        (None, None) => None,
    };
    ParamError::Parse {
        path: None,
        line: Some(line_no),
        key,
        message: e.message().replace('\n', " "),
    }
}

#[cfg(test)]
mod tests;
