//! The vision pipeline (detect -> convert) and its counters; the thread that
//! runs it is the lab's `isochron-vision` (`crate::lab::VisionLoop`).

use std::sync::atomic::AtomicU64;

use super::{Detector, DetectorParams, Frame, Measurement, SwingPlaneCalibration, VisionError};

/// Detector + calibration: one image in, one measurement out.
#[derive(Debug)]
pub struct VisionPipeline {
    detector: Detector,
    calibration: SwingPlaneCalibration,
}

impl VisionPipeline {
    /// A pipeline with validated detector parameters.
    ///
    /// # Errors
    ///
    /// As [`Detector::new`].
    pub fn new(
        detector: DetectorParams,
        calibration: SwingPlaneCalibration,
    ) -> Result<Self, VisionError> {
        Ok(Self {
            detector: Detector::new(detector)?,
            calibration,
        })
    }

    /// Detects the ball in `frame` and converts it to the swing plane.
    ///
    /// # Errors
    ///
    /// As [`Detector::detect`]: [`VisionError::BadFrame`] for an image that is not
    /// 8-bit BGR, [`VisionError::OpenCv`] when OpenCV fails.
    pub fn process(
        &mut self,
        frame: &Frame<'_>,
        t_available_s: f64,
    ) -> Result<Measurement, VisionError> {
        let m = match self.detector.detect(frame.image, frame.t_capture_s)? {
            Some(det) => Measurement::from_detection(
                frame.index,
                frame.t_capture_s,
                t_available_s,
                &det,
                &self.calibration,
            ),
            None => Measurement::missing(frame.index, frame.t_capture_s, t_available_s),
        };
        Ok(Measurement {
            rejected: self.detector.rejected(),
            ..m
        })
    }

    /// The calibration in use.
    pub fn calibration(&self) -> &SwingPlaneCalibration {
        &self.calibration
    }
}

/// Counters of the vision thread (read from any thread).
#[derive(Debug, Default)]
pub struct VisionStats {
    /// Frames processed.
    pub frames: AtomicU64,
    /// Frames in which the ball was found.
    pub found: AtomicU64,
    /// Measurements dropped because the ring was full.
    pub overflows: AtomicU64,
    /// Processing time of the last frame (detect + convert), microseconds.
    pub last_frame_us: AtomicU64,
    /// Highest processing time of a frame, microseconds.
    pub max_frame_us: AtomicU64,
    /// The camera stopped and is not open again yet.
    pub lost: std::sync::atomic::AtomicBool,
    /// Times the camera was opened again after it stopped.
    pub reopened: AtomicU64,
    /// Why the camera delivers nothing (its latest failure to open or read,
    /// naming the device), `None` while it delivers: for people, read off
    /// the real-time path.
    pub problem: std::sync::Mutex<Option<String>>,
}

impl VisionStats {
    /// Why the camera delivers nothing (`None` while it delivers).
    pub fn problem(&self) -> Option<String> {
        self.problem.lock().ok().and_then(|p| p.clone())
    }

    /// Sets (or with `None` clears) why the camera delivers nothing.
    pub fn set_problem(&self, problem: Option<String>) {
        if let Ok(mut p) = self.problem.lock() {
            *p = problem;
        }
    }
}
