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

pub use calibration::{
    CalibrationReport, CameraIntrinsics, CameraPose, SwingPlaneCalibration, undistortion_error_px,
};
#[cfg(feature = "opencv")]
pub use detector::{Detection, Detector, DetectorParams};
#[cfg(feature = "opencv")]
pub use source::{
    ChannelSource, Frame, FrameSource, RawFrame, Recorder, StreamSource, VideoFileSource,
    WebcamParams, WebcamSource, is_stream_url,
};
#[cfg(feature = "opencv")]
pub use thread::{VisionPipeline, VisionStats};

use crate::check::ParamError;

/// Anything that went wrong in the vision part.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum VisionError {
    /// OpenCV reported an error (its code and message).
    #[cfg(feature = "opencv")]
    #[error("OpenCV: {}", .0.message)]
    OpenCv(#[from] opencv::Error),
    /// A camera, file or device could not be opened.
    #[error("cannot open {what}: {reason}")]
    Open {
        /// What was asked for (a path or a device).
        what: String,
        /// Why it failed.
        reason: String,
    },
    /// An image that the step cannot use.
    #[error("bad frame: {0}")]
    BadFrame(#[from] FrameProblem),
    /// A parameter was refused.
    #[error(transparent)]
    Param(#[from] ParamError),
    /// The camera looks along the swing plane (its normal is perpendicular to
    /// the camera's ray to the ball): the plane cannot be measured.
    #[error("calibration: the camera looks along the swing plane: the plane cannot be measured")]
    PlaneEdgeOn,
    /// The given camera-ball distance and the one from the ball's apparent
    /// size disagree by more than the tolerance.
    #[error(
        "calibration: the given distance {given_distance_m:.3} m and the distance from the ball's apparent size \
         {size_distance_m:.3} m differ by {:.1}% (more than {:.1}%): check the distance, the \
         focal length and the ball radius",
        100.0 * relative_disagreement,
        100.0 * tolerance
    )]
    SizeDisagrees {
        /// The distance given for the calibration, metres.
        given_distance_m: f64,
        /// The distance from the ball's apparent size, metres.
        size_distance_m: f64,
        /// `size_distance_m / given_distance_m - 1` (a fraction).
        relative_disagreement: f64,
        /// The largest disagreement allowed (a fraction).
        tolerance: f64,
    },
    /// The vision thread could not be started.
    #[error("vision thread: {0}")]
    Spawn(#[source] std::io::Error),
    /// The vision thread panicked.
    #[error("vision thread: the vision thread panicked")]
    Panicked,
}

/// What is wrong with an image (a [`VisionError::BadFrame`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum FrameProblem {
    /// An image with no pixels.
    #[error("empty image")]
    Empty,
    /// A camera delivered a frame with no pixels.
    #[error("the {camera} returned an empty image")]
    EmptyFrom {
        /// Which camera (`"webcam"`, `"camera stream"`).
        camera: &'static str,
    },
    /// Not the 8-bit 3-channel BGR image the step takes.
    #[error(
        "expected a non-empty 8-bit 3-channel BGR image, got {width_px}x{height_px} of type {cv_type}"
    )]
    NotBgr {
        /// The image's width, pixels.
        width_px: i32,
        /// The image's height, pixels.
        height_px: i32,
        /// Its OpenCV type code (`CV_8UC3` is wanted).
        cv_type: i32,
    },
    /// A frame of another size or type than the recorder's.
    #[error(
        "the recorder takes {want_width_px}x{want_height_px} BGR frames, got {width_px}x{height_px} of type {cv_type}"
    )]
    RecorderSize {
        /// The recorder's width, pixels.
        want_width_px: i32,
        /// The recorder's height, pixels.
        want_height_px: i32,
        /// The frame's width, pixels.
        width_px: i32,
        /// The frame's height, pixels.
        height_px: i32,
        /// Its OpenCV type code.
        cv_type: i32,
    },
    /// Image buffers whose lengths are not `width * height`.
    #[error("morphology of a {width_px}x{height_px} image given {src_bytes} and {dst_bytes} bytes")]
    BufferSize {
        /// The image's width, pixels.
        width_px: usize,
        /// The image's height, pixels.
        height_px: usize,
        /// The source buffer's length, bytes.
        src_bytes: usize,
        /// The destination buffer's length, bytes.
        dst_bytes: usize,
    },
    /// OpenCV's JPEG encoder refused the image.
    #[error("JPEG encoding failed")]
    JpegEncoding,
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
///
/// # Errors
///
/// [`VisionError::OpenCv`] when OpenCV refuses the setting.
#[cfg(feature = "opencv")]
pub fn limit_opencv_threads() -> Result<(), VisionError> {
    opencv::core::set_num_threads(1)?;
    Ok(())
}

#[cfg(all(test, feature = "opencv"))]
mod edge_tests;
#[cfg(all(test, feature = "opencv"))]
mod tests;
