//! The vision thread: capture -> detect -> convert -> bounded ring to the control step.

use std::{
    sync::{
        Arc,
        atomic::{AtomicBool, AtomicU64, Ordering},
    },
    thread::JoinHandle,
};

use rtrb::{Consumer, Producer, RingBuffer};

use super::{
    Detector, DetectorParams, Frame, FrameSource, Measurement, SwingPlaneCalibration, VisionError,
    source::Clock,
};

/// The bounded single-producer single-consumer ring of measurements.
///
/// The vision thread pushes; the control step pops with `Consumer::pop`, which
/// neither allocates nor blocks.
pub fn measurement_ring(capacity: usize) -> (Producer<Measurement>, Consumer<Measurement>) {
    RingBuffer::new(capacity.max(1))
}

/// Detector + calibration: one image in, one measurement out.
#[derive(Debug)]
pub struct VisionPipeline {
    detector: Detector,
    calibration: SwingPlaneCalibration,
}

impl VisionPipeline {
    /// A pipeline with validated detector parameters.
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
    pub fn process(
        &mut self,
        frame: &Frame<'_>,
        t_available_s: f64,
    ) -> Result<Measurement, VisionError> {
        Ok(
            match self.detector.detect(frame.image, frame.t_capture_s)? {
                Some(det) => Measurement::from_detection(
                    frame.index,
                    frame.t_capture_s,
                    t_available_s,
                    &det,
                    &self.calibration,
                ),
                None => Measurement::missing(frame.index, frame.t_capture_s, t_available_s),
            },
        )
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
}

/// A running vision thread (`isochron-vision`).
#[derive(Debug)]
pub struct VisionThread {
    stop: Arc<AtomicBool>,
    stats: Arc<VisionStats>,
    handle: Option<JoinHandle<Result<(), VisionError>>>,
}

impl VisionThread {
    /// Starts the thread: it takes frames from `source` until it ends, an error
    /// occurs or [`VisionThread::stop`] is called, and pushes every processed
    /// frame's measurement (found or not) into `ring`, stamped available on
    /// `clock` when it is pushed. A full ring drops the measurement and counts it.
    pub fn spawn(
        mut source: Box<dyn FrameSource>,
        mut pipeline: VisionPipeline,
        mut ring: Producer<Measurement>,
        clock: Clock,
    ) -> Result<Self, VisionError> {
        let stop = Arc::new(AtomicBool::new(false));
        let stats = Arc::new(VisionStats::default());
        let (stop_t, stats_t) = (Arc::clone(&stop), Arc::clone(&stats));
        let handle = std::thread::Builder::new()
            .name("isochron-vision".into())
            .spawn(move || -> Result<(), VisionError> {
                // OpenCV's pool would compete with the control thread for the cores.
                super::limit_opencv_threads()?;
                while !stop_t.load(Ordering::Relaxed) {
                    let Some(frame) = source.next_frame()? else {
                        break;
                    };
                    let t0 = clock.now_s();
                    let m = pipeline.process(&frame, t0)?;
                    let t1 = clock.now_s();
                    let m = Measurement {
                        t_available_s: t1,
                        ..m
                    };
                    let us = ((t1 - t0) * 1e6).max(0.0) as u64;
                    stats_t.last_frame_us.store(us, Ordering::Relaxed);
                    stats_t.max_frame_us.fetch_max(us, Ordering::Relaxed);
                    stats_t.frames.fetch_add(1, Ordering::Relaxed);
                    if m.found {
                        stats_t.found.fetch_add(1, Ordering::Relaxed);
                    }
                    if ring.push(m).is_err() {
                        stats_t.overflows.fetch_add(1, Ordering::Relaxed);
                    }
                }
                Ok(())
            })
            .map_err(|e| VisionError::Thread(e.to_string()))?;
        Ok(Self {
            stop,
            stats,
            handle: Some(handle),
        })
    }

    /// The thread's counters.
    pub fn stats(&self) -> Arc<VisionStats> {
        Arc::clone(&self.stats)
    }

    /// Whether the thread has ended (end of stream or error).
    pub fn is_finished(&self) -> bool {
        self.handle.as_ref().is_none_or(JoinHandle::is_finished)
    }

    /// Asks the thread to stop after the current frame and waits for it; returns
    /// the error it ended with, if any.
    pub fn stop(mut self) -> Result<(), VisionError> {
        self.stop.store(true, Ordering::Relaxed);
        self.join()
    }

    fn join(&mut self) -> Result<(), VisionError> {
        match self.handle.take() {
            Some(h) => h
                .join()
                .map_err(|_| VisionError::Thread("the vision thread panicked".into()))?,
            None => Ok(()),
        }
    }
}

impl Drop for VisionThread {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        let _ = self.join();
    }
}
