#![doc = include_str!("README.md")]

pub mod calibration;
#[cfg(feature = "opencv")]
pub mod colour;
#[cfg(feature = "opencv")]
pub mod detector;
pub mod morphology;
#[cfg(feature = "opencv")]
pub mod source;
#[cfg(feature = "opencv")]
pub mod thread;

pub use calibration::{CalibrationReport, CameraIntrinsics, CameraPose, SwingPlaneCalibration};
#[cfg(feature = "opencv")]
pub use detector::{Detection, Detector, DetectorParams};
#[cfg(feature = "opencv")]
pub use source::{
    Frame, FrameSource, Recorder, StreamSource, VideoFileSource, WebcamParams, WebcamSource,
    is_stream_url,
};
#[cfg(feature = "opencv")]
pub use thread::{VisionPipeline, VisionStats};

use crate::check::ParamError;

/// Anything that went wrong in the vision part.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum VisionError {
    /// OpenCV reported an error.
    #[error("OpenCV: {0}")]
    OpenCv(String),
    /// A camera, file or device could not be opened.
    #[error("cannot open {what}: {reason}")]
    Open {
        /// What was asked for (a path or a device).
        what: String,
        /// Why it failed.
        reason: String,
    },
    /// An image that the detector cannot use.
    #[error("bad frame: {0}")]
    BadFrame(String),
    /// A parameter was refused.
    #[error(transparent)]
    Param(#[from] ParamError),
    /// The calibration could not be computed or is inconsistent.
    #[error("calibration: {0}")]
    Calibration(String),
    /// The vision thread could not be started or ended with an error.
    #[error("vision thread: {0}")]
    Thread(String),
}

#[cfg(feature = "opencv")]
impl From<opencv::Error> for VisionError {
    fn from(e: opencv::Error) -> Self {
        Self::OpenCv(e.message)
    }
}

/// One camera frame turned into a measurement for the filter.
///
/// Times are seconds on the clock of whoever drives the vision (the wall clock's
/// monotonic epoch in real time, the simulation's clock in virtual time). The
/// measurement may be used from `t_available_s` on, and describes the ball at
/// `t_capture_s` (the middle of the exposure).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct Measurement {
    /// Frame number from the source (dropped frames leave gaps).
    pub frame: u64,
    /// When the image was taken (middle of the exposure), seconds.
    pub t_capture_s: f64,
    /// When the measurement became available to the control step, seconds.
    pub t_available_s: f64,
    /// Whether the ball was found; when false the other fields are zero.
    pub found: bool,
    /// Lateral position of the ball centre on the swing plane, metres, positive
    /// along the robot base's +y, zero at the calibrated rest position: the paper's
    /// measurement x = l sin(phi).
    pub lateral_m: f64,
    /// Ball centre, image column, pixels (pixel centres at integers).
    pub x_px: f64,
    /// Ball centre, image row, pixels.
    pub y_px: f64,
    /// Apparent ball radius, pixels.
    pub r_px: f64,
    /// Detector confidence, 0..1.
    pub confidence: f64,
    /// Camera -> ball distance implied by the apparent size, metres (a cross-check).
    pub size_distance_m: f64,
    /// Detections the detector dropped so far as inconsistent with the track
    /// (a ball-like blob where the tracked ball cannot be).
    pub rejected: u64,
}

impl Measurement {
    /// A frame that was processed but showed no ball.
    pub const fn missing(frame: u64, t_capture_s: f64, t_available_s: f64) -> Self {
        Self {
            frame,
            t_capture_s,
            t_available_s,
            found: false,
            lateral_m: 0.0,
            x_px: 0.0,
            y_px: 0.0,
            r_px: 0.0,
            confidence: 0.0,
            size_distance_m: 0.0,
            rejected: 0,
        }
    }

    /// A measurement from a detection converted through a calibration.
    ///
    /// Returns a missing measurement when the pixel's ray does not meet the plane.
    #[cfg(feature = "opencv")]
    pub fn from_detection(
        frame: u64,
        t_capture_s: f64,
        t_available_s: f64,
        det: &Detection,
        cal: &SwingPlaneCalibration,
    ) -> Self {
        match cal.lateral_m(det.x_px, det.y_px) {
            Some(lateral_m) => Self {
                frame,
                t_capture_s,
                t_available_s,
                found: true,
                lateral_m,
                x_px: det.x_px,
                y_px: det.y_px,
                r_px: det.r_px,
                confidence: det.confidence,
                size_distance_m: cal.distance_from_size_m(det.x_px, det.y_px, det.r_px),
                rejected: 0,
            },
            None => Self::missing(frame, t_capture_s, t_available_s),
        }
    }
}

/// The bounded single-producer single-consumer ring of measurements.
///
/// The vision thread pushes; the control step pops with `Consumer::pop`, which
/// neither allocates nor blocks.
pub fn measurement_ring(
    capacity: usize,
) -> (rtrb::Producer<Measurement>, rtrb::Consumer<Measurement>) {
    rtrb::RingBuffer::new(capacity.max(1))
}

/// Limits OpenCV to one worker thread, so the control thread keeps a core.
///
/// OpenCV's setting is process-wide; calling it again is harmless.
#[cfg(feature = "opencv")]
pub fn limit_opencv_threads() -> Result<(), VisionError> {
    opencv::core::set_num_threads(1)?;
    Ok(())
}

#[cfg(all(test, feature = "opencv"))]
mod edge_tests;
#[cfg(all(test, feature = "opencv"))]
mod tests;
