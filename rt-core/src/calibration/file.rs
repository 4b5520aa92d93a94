//! The calibration file: each step's result with its residuals, date, software
//! revision and where it was measured; `serve`, `trials` and `eval` lay it over the
//! lab's beliefs (`CalibrationFile::apply`).

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::{
    CameraCalibration, CameraRobotCalibration, ContactCalibration, LedLatency, RobotLatency,
    SwingFit,
};
use crate::params::{ParamError, Scenario};

/// When, by which software and on what one step was measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StepRecord<T> {
    /// UTC date and time, RFC 3339.
    pub date: String,
    /// The software revision (`isochron --version` and the git commit).
    pub revision: String,
    /// Where it was measured: `"real lab"` or `"simulated world (scenario NAME, seed S)"`.
    pub source: String,
    /// The result with its residuals.
    pub result: T,
}

/// The pendulum step's result: the free-swing fit and the rest point.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PendulumCalibration {
    /// The free-swing fit.
    pub swing: SwingFit,
    /// The hanging ball's centre in the image, pixels (column, row).
    pub rest_px: [f64; 2],
    /// Standard deviation of the rest centre over the frames averaged, pixels.
    pub rest_std_px: [f64; 2],
    /// The swing plane's direction in the image: angle of the swing's principal axis
    /// from the image's x axis, degrees.
    pub swing_image_angle_deg: f64,
}

/// A calibration file: every step is optional (a step not yet run is absent).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CalibrationFile {
    /// `isochron calibrate camera`.
    pub camera: Option<StepRecord<CameraCalibration>>,
    /// `isochron calibrate pendulum`.
    pub pendulum: Option<StepRecord<PendulumCalibration>>,
    /// `isochron calibrate latency`.
    pub latency: Option<StepRecord<LedLatency>>,
    /// `isochron calibrate robot`.
    pub robot: Option<StepRecord<RobotLatency>>,
    /// `isochron calibrate camera-robot`.
    pub camera_robot: Option<StepRecord<CameraRobotCalibration>>,
    /// `isochron calibrate contact`.
    pub contact: Option<StepRecord<ContactCalibration>>,
}

impl CalibrationFile {
    /// Reads a calibration file; a missing file is an empty calibration.
    ///
    /// # Errors
    ///
    /// [`ParamError::Io`] when the file exists but cannot be read; [`ParamError::Parse`]
    /// when its text is not a calibration file.
    pub fn load_or_empty(path: &Path) -> Result<Self, ParamError> {
        match std::fs::read_to_string(path) {
            Ok(text) => Self::from_toml_str(&text).map_err(|e| e.in_file(path)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Self::default()),
            Err(e) => Err(ParamError::Io {
                path: path.display().to_string(),
                reason: e.to_string(),
            }),
        }
    }

    /// Reads an existing calibration file (missing: an error).
    ///
    /// # Errors
    ///
    /// [`ParamError::Io`] when the file cannot be read (also when it is missing);
    /// [`ParamError::Parse`] when its text is not a calibration file.
    pub fn from_file(path: &Path) -> Result<Self, ParamError> {
        let text = std::fs::read_to_string(path).map_err(|e| ParamError::Io {
            path: path.display().to_string(),
            reason: e.to_string(),
        })?;
        Self::from_toml_str(&text).map_err(|e| e.in_file(path))
    }

    /// Parses a calibration file's text. Unknown keys are refused.
    ///
    /// ```
    /// use rt_core::calibration::file::CalibrationFile;
    /// // An empty file: no step calibrated yet.
    /// let f = CalibrationFile::from_toml_str("").unwrap();
    /// assert!(f.pendulum.is_none() && f.latency.is_none());
    /// assert!(CalibrationFile::from_toml_str("[pendulm]\n").is_err());
    /// ```
    ///
    /// # Errors
    ///
    /// [`ParamError::Parse`] when the text is not valid TOML, has a wrong type or an
    /// unknown key.
    pub fn from_toml_str(text: &str) -> Result<Self, ParamError> {
        toml::from_str(text).map_err(|e| ParamError::parse(e.message()))
    }

    /// The file's text.
    pub fn to_toml_string(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_default()
    }

    /// Writes the file atomically (a temporary file renamed over the target).
    ///
    /// # Errors
    ///
    /// [`ParamError::Io`] when the temporary file cannot be written or renamed over `path`.
    pub fn write(&self, path: &Path) -> Result<(), ParamError> {
        let io = |e: std::io::Error| ParamError::Io {
            path: path.display().to_string(),
            reason: e.to_string(),
        };
        let tmp = path.with_extension("toml.tmp");
        std::fs::write(&tmp, self.to_toml_string()).map_err(io)?;
        std::fs::rename(&tmp, path).map_err(io)
    }

    /// The lab's beliefs with the calibrated values: the camera's intrinsics and
    /// lens (`camera.intrinsics`: the detector undistorts with them), pendulum
    /// length and damping, camera latency, the robot latency prior of the online
    /// estimator (delay plus servo lag, which is what the estimator measures),
    /// the camera's pose (`camera.pose`), the intercept point's offset
    /// (`task.intercept_offset_m`) and the measured judge's contact beliefs
    /// (`success.torque_lag_periods` and `success.contact_pulse_ms`, their
    /// sum the knock's onset offset). The result is validated; intrinsics measured
    /// at another image size than the scenario's camera are refused.
    ///
    /// # Errors
    ///
    /// [`ParamError::OutOfRange`] for `camera.intrinsics` when the camera step was
    /// measured at another image size; any [`ParamError`] of [`Scenario::validate`] on
    /// the result.
    pub fn apply(&self, scenario: &Scenario) -> Result<Scenario, ParamError> {
        let mut s = scenario.clone();
        // A simulated world stays where it is: its offsets keep being drawn
        // around the beliefs the lab had before this file.
        if let Some(w) = s.world.as_mut()
            && w.anchor.is_none()
        {
            w.anchor = Some(crate::params::world::WorldAnchor {
                pendulum_length_m: scenario.pendulum.length_m,
                pendulum_damping_per_s: scenario.pendulum.damping_per_s,
                camera_latency_ms: scenario.camera.latency_ms,
            });
        }
        if let Some(c) = &self.camera {
            let r = &c.result;
            if (r.width_px, r.height_px) != (s.camera.width_px, s.camera.height_px) {
                return Err(ParamError::OutOfRange {
                    field: "camera.intrinsics".to_owned(),
                    value: crate::check::Value::Text(format!("{}x{}", r.width_px, r.height_px)),
                    bound: crate::check::Bound::Rule(format!(
                        "the calibration file's camera step was measured at {}x{} px, the lab's camera is {}x{}: \
                         run `isochron calibrate camera` at the lab's resolution",
                        r.width_px, r.height_px, s.camera.width_px, s.camera.height_px
                    )),
                });
            }
            s.camera.intrinsics = Some(r.intrinsics);
        }
        if let Some(p) = &self.pendulum {
            s.pendulum.length_m = p.result.swing.length_m;
            s.pendulum.damping_per_s = p.result.swing.damping_per_s.max(0.0);
        }
        if let Some(l) = &self.latency {
            s.camera.latency_ms = l.result.latency_ms;
        }
        if let Some(r) = &self.robot {
            s.control.latency_prior_ms = r.result.latency_ms + r.result.servo_time_constant_ms;
        }
        if let Some(c) = &self.camera_robot {
            s.camera.pose = Some(c.result.camera_pose);
            s.task.intercept_offset_m = c.result.intercept_offset_m;
        }
        if let Some(c) = &self.contact {
            let (lag_periods, pulse_ms) = c.result.beliefs(f64::from(s.robot.fri_period_ms));
            s.success.torque_lag_periods = lag_periods;
            s.success.contact_pulse_ms = pulse_ms;
        }
        s.validate()?;
        Ok(s)
    }
}
