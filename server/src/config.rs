//! `isochron serve --config FILE`: the service and the lab's hardware (TOML).
//!
//! Every key is optional; with no file the service runs the simulated lab on
//! loopback. Unknown keys are refused, like scenario files.

use std::{net::SocketAddr, path::PathBuf};

use rt_core::params::{ParamError, check};
use serde::{Deserialize, Serialize};

/// The whole configuration file.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServeConfig {
    /// The HTTP service.
    pub server: ServerSection,
    /// Which lab runs.
    pub lab: LabSection,
    /// The webcam (real lab).
    pub camera: CameraHardware,
    /// The robot's FRI link (real lab).
    pub fri: FriHardware,
    /// The magnet's Arduino (real lab).
    pub magnet: MagnetHardware,
    /// Camera-to-pendulum calibration (real lab).
    pub calibration: Calibration,
}

/// `[server]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServerSection {
    /// Listen address; anything but loopback needs a token.
    pub bind: SocketAddr,
    /// Bearer token for every command endpoint (or `ISOCHRON_TOKEN` / `--token`).
    pub token: Option<String>,
    /// Where trial records (SQLite) and recordings go.
    pub data_dir: PathBuf,
    /// Folder of the built dashboard (default: web/dist of the source tree).
    pub web_dir: Option<PathBuf>,
    /// State messages per second on `/ws`.
    pub state_hz: f64,
    /// Largest request body, bytes.
    pub body_limit_bytes: usize,
    /// Web origins (`https://host:port`) allowed to call the API from a browser
    /// page served elsewhere. Empty (the default): same origin only.
    pub cors_origins: Vec<String>,
    /// A WebSocket client that cannot take a message within this time is dropped, ms.
    pub ws_send_timeout_ms: u64,
}

impl Default for ServerSection {
    fn default() -> Self {
        Self {
            bind: SocketAddr::from(([127, 0, 0, 1], 8080)),
            token: None,
            data_dir: PathBuf::from("data"),
            web_dir: None,
            state_hz: 100.0,
            body_limit_bytes: 64 * 1024,
            cors_origins: Vec::new(),
            ws_send_timeout_ms: 2000,
        }
    }
}

/// Which lab the service drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LabMode {
    /// The simulated lab: simulated pendulum, camera, robot over loopback UDP FRI, magnet.
    #[default]
    Simulated,
    /// The real lab: webcam, KUKA controller over FRI, Arduino magnet.
    Real,
}

/// `[lab]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LabSection {
    /// `simulated` (default) or `real`.
    pub mode: LabMode,
    /// Scenario file with the task and tuning (default: the paper's lab).
    pub scenario: Option<PathBuf>,
    /// The calibration file `isochron calibrate` writes (laid over the scenario's
    /// beliefs); `serve --calibration` overrides it.
    pub calibration_file: Option<PathBuf>,
    /// A real lab refuses trials until the pendulum and camera latency are
    /// calibrated, unless this is true (an explicit override).
    pub allow_uncalibrated: bool,
    /// The operator dead-man: while a trial runs, an operator must send a
    /// heartbeat (`POST /api/heartbeat`; the dashboard does it) at least every
    /// `operator_timeout_s`, or the motion stops safely (abort `operator_lost`).
    /// Default: on in the real lab, off in the simulated one.
    pub dead_man: Option<bool>,
    /// The dead-man time, seconds.
    pub operator_timeout_s: f64,
}

impl Default for LabSection {
    fn default() -> Self {
        Self {
            mode: LabMode::default(),
            scenario: None,
            calibration_file: None,
            allow_uncalibrated: false,
            dead_man: None,
            operator_timeout_s: 1.0,
        }
    }
}

impl LabSection {
    /// The dead-man time in force (`None`: off).
    pub fn operator_timeout(&self) -> Option<f64> {
        self.dead_man
            .unwrap_or(self.mode == LabMode::Real)
            .then_some(self.operator_timeout_s)
    }
}

/// `[camera]`: the webcam.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraHardware {
    /// V4L2 device, a video file (looped at its frame rate), or a network
    /// camera's stream URL (`http://`, `https://`, `rtsp://`: MJPEG or RTSP).
    pub device: PathBuf,
    /// Requested width, pixels.
    pub width_px: u32,
    /// Requested height, pixels.
    pub height_px: u32,
    /// Requested frame rate.
    pub fps: f64,
}

impl Default for CameraHardware {
    fn default() -> Self {
        Self {
            device: PathBuf::from("/dev/video0"),
            width_px: 1280,
            height_px: 720,
            fps: 30.0,
        }
    }
}

/// `[fri]`: the robot controller.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FriHardware {
    /// Local UDP address the FRI client listens on (KUKA's default port is 30200).
    pub local_bind: SocketAddr,
    /// The controller's address (KONI interface).
    pub controller: SocketAddr,
    /// Send period configured in the robot application, ms.
    pub period_ms: u32,
    /// The FRI version of the controller's Sunrise release (`"1.15"` default;
    /// `"1.11"`, `"1.14"`, `"1.15"`, `"1.16"`, `"2.5"`, `"2.7"`).
    pub version: rt_core::fri::FriVersion,
}

impl Default for FriHardware {
    fn default() -> Self {
        Self {
            local_bind: SocketAddr::from(([192, 170, 10, 1], 30200)),
            controller: SocketAddr::from(([192, 170, 10, 2], 30200)),
            period_ms: 5,
            version: rt_core::fri::FriVersion::default(),
        }
    }
}

/// `[magnet]`: the Arduino.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MagnetHardware {
    /// Serial device.
    pub port: PathBuf,
    /// Baud rate.
    pub baud: u32,
    /// How long one command may wait for the board's answer before the
    /// driver resynchronises (and, silent for its boot time too, declares
    /// the link lost), ms. An Uno answers within a few ms; a board that
    /// shares a busy machine (a simulator) needs more.
    pub command_timeout_ms: f64,
}

impl Default for MagnetHardware {
    fn default() -> Self {
        Self {
            port: PathBuf::from("/dev/ttyACM0"),
            baud: 115_200,
            command_timeout_ms: rt_core::magnet::MagnetParams::default().command_timeout_ms,
        }
    }
}

/// `[calibration]`: where the camera sees the swing plane.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Calibration {
    /// Camera focal length, pixels.
    pub focal_length_px: f64,
    /// Principal point (cx, cy), pixels.
    pub principal_point_px: [f64; 2],
    /// Camera centre to the swing plane along the optical axis, metres.
    pub plane_distance_m: f64,
    /// Pendulum pivot in the robot base frame, metres.
    pub pivot_m: [f64; 3],
    /// Where the camera is and where it looks, in the robot base frame. Without
    /// it the camera is taken to sit on the pivot's line along -x at the height
    /// of the ball at rest, `plane_distance_m` before the swing plane, looking
    /// along +x.
    pub camera_pose: Option<rt_core::vision::CameraPose>,
    /// Where the magnet board's LED shows in the camera's image: centre
    /// column, centre row and radius, pixels (read off the camera panel).
    /// The latency step needs it; without it that step is refused.
    pub led_px: Option<[f64; 3]>,
}

impl Default for Calibration {
    fn default() -> Self {
        Self {
            focal_length_px: 900.0,
            principal_point_px: [640.0, 360.0],
            plane_distance_m: 1.5,
            pivot_m: [0.6, 0.0, 2.23],
            camera_pose: None,
            led_px: None,
        }
    }
}

impl ServeConfig {
    /// Parses and validates a configuration (unknown keys are refused).
    ///
    /// # Errors
    ///
    /// [`ParamError::Parse`] for bad TOML, a wrong type or an unknown key; the error of
    /// [`Self::validate`] naming the first bad field.
    pub fn from_toml_str(text: &str) -> Result<Self, ParamError> {
        let cfg: Self = toml::from_str(text).map_err(|e| rt_core::params::toml_error(text, &e))?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Reads, parses and validates a configuration file.
    ///
    /// # Errors
    ///
    /// [`ParamError::Io`] when the file cannot be read; otherwise as
    /// [`Self::from_toml_str`], with the file named.
    pub fn from_file(path: &std::path::Path) -> Result<Self, ParamError> {
        let text = std::fs::read_to_string(path).map_err(|e| ParamError::Io {
            path: path.display().to_string(),
            reason: e.to_string(),
        })?;
        Self::from_toml_str(&text).map_err(|e| e.in_file(path))
    }

    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first bad
    /// field (a CORS origin with a path included), or the error of the camera pose's check.
    pub fn validate(&self) -> Result<(), ParamError> {
        let s = &self.server;
        check::within("server.state_hz", s.state_hz, 1.0, 1000.0)?;
        check::within(
            "server.body_limit_bytes",
            s.body_limit_bytes as f64,
            1024.0,
            16.0 * 1024.0 * 1024.0,
        )?;
        check::within(
            "server.ws_send_timeout_ms",
            s.ws_send_timeout_ms as f64,
            10.0,
            60_000.0,
        )?;
        for (i, o) in s.cors_origins.iter().enumerate() {
            if !(o.starts_with("http://") || o.starts_with("https://")) || o.ends_with('/') {
                return Err(ParamError::OutOfRange {
                    field: format!("server.cors_origins[{i}]"),
                    value: check::Value::Text(o.clone()),
                    bound: check::Bound::rule("must be an origin like https://host:port (no path)"),
                });
            }
        }
        check::within(
            "lab.operator_timeout_s",
            self.lab.operator_timeout_s,
            0.05,
            60.0,
        )?;
        let c = &self.camera;
        check::within_u32("camera.width_px", c.width_px, 64, 7680)?;
        check::within_u32("camera.height_px", c.height_px, 48, 4320)?;
        check::within("camera.fps", c.fps, 1.0, 500.0)?;
        check::within_u32("fri.period_ms", self.fri.period_ms, 1, 100)?;
        check::within(
            "magnet.command_timeout_ms",
            self.magnet.command_timeout_ms,
            5.0,
            10_000.0,
        )?;
        check::within_u32("magnet.baud", self.magnet.baud, 300, 2_000_000)?;
        let k = &self.calibration;
        check::within("calibration.focal_length_px", k.focal_length_px, 1.0, 1e5)?;
        for (i, v) in k.principal_point_px.iter().enumerate() {
            check::within(
                &format!("calibration.principal_point_px[{i}]"),
                *v,
                0.0,
                1e4,
            )?;
        }
        check::within(
            "calibration.plane_distance_m",
            k.plane_distance_m,
            0.1,
            20.0,
        )?;
        for (i, v) in k.pivot_m.iter().enumerate() {
            check::within(&format!("calibration.pivot_m[{i}]"), *v, -10.0, 10.0)?;
        }
        if let Some(pose) = &k.camera_pose {
            pose.validate("calibration.camera_pose")?;
        }
        if let Some([x, y, r]) = k.led_px {
            check::within("calibration.led_px[0]", x, 0.0, f64::from(c.width_px - 1))?;
            check::within("calibration.led_px[1]", y, 0.0, f64::from(c.height_px - 1))?;
            check::within("calibration.led_px[2]", r, 1.0, 200.0)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_example_lab_config_parses() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../config/lab.toml");
        let cfg = ServeConfig::from_file(std::path::Path::new(path)).unwrap();
        assert_eq!(cfg.lab.mode, LabMode::Real);
        assert_eq!(cfg.fri.controller.port(), 30200);
        let pose = cfg.calibration.camera_pose.unwrap();
        assert_eq!(pose.position_m, [-0.9, 0.0, 0.30]);
    }

    #[test]
    fn unknown_keys_and_bad_values_are_refused() {
        let e = ServeConfig::from_toml_str("[server]\nstate_hz = 0.0\n").unwrap_err();
        assert_eq!(e.field(), Some("server.state_hz"));
        let e = ServeConfig::from_toml_str(
            "[calibration.camera_pose]\nposition_m = [0.0, 0.0, 12.0]\n",
        )
        .unwrap_err();
        assert_eq!(e.field(), Some("calibration.camera_pose.position_m[2]"));
        let e = ServeConfig::from_toml_str("[calibration.camera_pose]\nyaw = 3.0\n").unwrap_err();
        assert!(e.to_string().contains("yaw"), "{e}");
        let e = ServeConfig::from_toml_str("[fri]\nperiod = 5\n").unwrap_err();
        assert!(e.to_string().contains("period"), "{e}");
        let e = ServeConfig::from_toml_str("[fri]\nversion = \"2.6\"\n").unwrap_err();
        assert!(e.to_string().contains("unknown FRI version \"2.6\""), "{e}");
        let e = ServeConfig::from_toml_str("[calibration]\nled_px = [40.0, 9000.0, 10.0]\n")
            .unwrap_err();
        assert_eq!(e.field(), Some("calibration.led_px[1]"));
        let e = ServeConfig::from_toml_str("[calibration]\nled_px = [40.0, 40.0]\n").unwrap_err();
        assert!(e.to_string().contains("led_px"), "{e}");
        let cfg = ServeConfig::from_toml_str("[fri]\nversion = \"2.7\"\n").unwrap();
        assert_eq!(cfg.fri.version, rt_core::fri::FriVersion::V2_7);
        assert_eq!(
            ServeConfig::from_toml_str("").unwrap(),
            ServeConfig::default()
        );
    }
}
