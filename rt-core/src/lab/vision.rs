//! The vision thread of the real-time lab (`isochron-vision`): frames from a
//! [`FrameSource`] -> the OpenCV detector and the swing-plane conversion
//! ([`VisionPipeline`]) -> measurements into a bounded wait-free ring for the
//! control thread; every few frames a downscaled JPEG into the bridge's frame
//! channel for `/ws/camera` (a full channel drops the frame, counted; video
//! never waits and never touches the measurement path).
//!
//! With an LED region ([`LedTap`]) each frame's mean brightness there goes,
//! with the frame's delivery time, into a bounded ring the service reads
//! ([`LedFeed`]: the latency step). The stamps' latency follows the lab's
//! belief when it changes (`stamp_latency`, set by the control thread).
//!
//! On request ([`StillSlot`]) the next full-resolution frame goes, in grey
//! or in colour,
//! into a one-frame slot the service takes it from (the camera step's board
//! views): the vision thread never waits for it (a slot the service holds
//! at that moment: the next frame).
//!
//! The simulated camera (`SimCameraSource`, `sim/camera/`) renders the
//! ground-truth pendulum that the control thread's truth hands over
//! (`sim/truth.rs`).

use std::sync::{
    Arc, Mutex,
    atomic::{AtomicBool, AtomicU64, Ordering},
};
use std::thread::JoinHandle;

use opencv::{
    core::{Mat, MatTraitConst, MatTraitConstManual, Rect, Size, Vector},
    imgcodecs, imgproc,
};
use rtrb::{Consumer, Producer};

use super::SourceFactory;
use crate::bridge::{Frame as VideoFrame, FrameSender};
use crate::check;
use crate::vision::{
    DetectorParams, FrameProblem, FrameSource, Measurement, SwingPlaneCalibration, VisionError,
    VisionPipeline, VisionStats, source::Clock,
};

/// The camera stream to the dashboard: downscaled JPEG frames.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VideoParams {
    /// Width of the streamed frames, pixels (height keeps the aspect ratio).
    pub width_px: u32,
    /// Frames per second streamed (at most the camera's rate).
    pub fps: f64,
    /// JPEG quality, 1..100.
    pub quality: u8,
}

impl Default for VideoParams {
    fn default() -> Self {
        Self {
            width_px: 640,
            fps: 12.0,
            quality: 70,
        }
    }
}

impl VideoParams {
    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`](crate::check::ParamError::NotFinite) or
    /// [`ParamError::OutOfRange`](crate::check::ParamError::OutOfRange) naming the first
    /// field that is not finite or outside its range.
    pub fn validate(&self) -> Result<(), crate::check::ParamError> {
        check::within_u32("video.width_px", self.width_px, 64, 3840)?;
        check::within("video.fps", self.fps, 0.5, 60.0)?;
        check::within_u32("video.quality", u32::from(self.quality), 1, 100)
    }
}

/// Counters of the camera stream (the measurement side is in [`VisionStats`]).
#[derive(Debug, Default)]
pub struct VideoStats {
    /// JPEG frames handed to the frame channel.
    pub frames: AtomicU64,
    /// Frames the channel refused (full: the server is behind).
    pub dropped: AtomicU64,
    /// Size of the last JPEG, bytes.
    pub last_bytes: AtomicU64,
    /// Encoding time of the last JPEG (resize + encode), microseconds.
    pub last_encode_us: AtomicU64,
    /// Frames the detector failed on (skipped; the thread goes on).
    pub detector_errors: AtomicU64,
}

/// One frame's reading of the magnet board's LED (the latency step).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LedReading {
    /// The source's frame number.
    pub frame: u64,
    /// When the frame reached the host: its stamp plus the latency it was
    /// stamped with, control clock, seconds.
    pub t_delivered_s: f64,
    /// Mean brightness of the LED's region over the three channels, 0..255.
    pub level: f64,
}

/// Readings kept for the service: about 8 s of a 30 fps camera.
pub const LED_READINGS: usize = 256;

/// The vision thread's side of the LED readings.
#[derive(Debug)]
pub struct LedTap {
    /// The LED's region: centre column, centre row and radius, pixels.
    pub roi_px: [f64; 3],
    /// Where the readings go (full: the newest is dropped).
    pub readings: Producer<LedReading>,
}

/// The service's side of the LED readings (what the vision thread measured
/// in the LED's region of each frame since the last [`Self::drain`]).
#[derive(Debug)]
pub struct LedFeed {
    roi_px: [f64; 3],
    readings: Mutex<Consumer<LedReading>>,
}

impl LedFeed {
    /// A feed over the LED region `roi_px` (column, row, radius in pixels):
    /// the tap goes to the vision thread ([`VisionParts::led`]).
    pub fn new(roi_px: [f64; 3]) -> (LedTap, Self) {
        let (tx, rx) = rtrb::RingBuffer::new(LED_READINGS);
        (
            LedTap {
                roi_px,
                readings: tx,
            },
            Self {
                roi_px,
                readings: Mutex::new(rx),
            },
        )
    }

    /// The LED's region: centre column, centre row and radius, pixels.
    pub fn roi_px(&self) -> [f64; 3] {
        self.roi_px
    }

    /// Moves every reading not yet taken into `out`, oldest first.
    pub fn drain(&self, out: &mut Vec<LedReading>) {
        let mut rx = self
            .readings
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        while let Ok(r) = rx.pop() {
            out.push(r);
        }
    }
}

/// One full-resolution grey frame taken for a calibration step.
#[derive(Debug, Clone, PartialEq)]
pub struct Still {
    /// The frame's number.
    pub frame: u64,
    /// Its capture time, control clock, seconds.
    pub t_capture_s: f64,
    /// Width, pixels.
    pub width_px: u32,
    /// Height, pixels.
    pub height_px: u32,
    /// Channels of `pixels`: 1 (grey) or 3 (BGR, when asked for colour and
    /// the camera delivers it).
    pub channels: u32,
    /// Row-major 8-bit pixels, `width_px * height_px * channels` of them.
    pub pixels: Vec<u8>,
}

impl Still {
    /// The frame as an OpenCV image as it was kept (a copy).
    ///
    /// # Errors
    ///
    /// [`VisionError::OpenCv`] when OpenCV refuses the buffer;
    /// [`VisionError::BadFrame`] when its size does not match.
    pub fn to_mat(&self) -> Result<Mat, VisionError> {
        let (w, h, c) = (
            self.width_px as usize,
            self.height_px as usize,
            self.channels as usize,
        );
        if w == 0 || h == 0 || !matches!(c, 1 | 3) || self.pixels.len() != w * h * c {
            return Err(FrameProblem::Empty.into());
        }
        let flat = Mat::from_slice(&self.pixels)?;
        Ok(flat
            .reshape(self.channels as i32, self.height_px as i32)?
            .try_clone()?)
    }

    /// The frame in grey (a copy; converted when kept in colour).
    ///
    /// # Errors
    ///
    /// As [`Self::to_mat`], and [`VisionError::OpenCv`] when the conversion fails.
    pub fn to_gray_mat(&self) -> Result<Mat, VisionError> {
        let m = self.to_mat()?;
        if self.channels == 1 {
            return Ok(m);
        }
        let mut gray = Mat::default();
        imgproc::cvt_color_def(&m, &mut gray, imgproc::COLOR_BGR2GRAY)?;
        Ok(gray)
    }
}

/// The service's request for one full-resolution frame, and the slot the
/// vision thread puts it in (module docs).
#[derive(Debug, Default)]
pub struct StillSlot {
    wanted: AtomicBool,
    colour: AtomicBool,
    slot: Mutex<Option<Still>>,
}

impl StillSlot {
    /// Asks for the next frame in grey (an earlier one not yet taken is dropped).
    pub fn request(&self) {
        self.ask(false);
    }

    /// Asks for the next frame in colour (BGR; grey when the camera gives grey).
    pub fn request_colour(&self) {
        self.ask(true);
    }

    fn ask(&self, colour: bool) {
        self.lock().take();
        self.colour.store(colour, Ordering::Release);
        self.wanted.store(true, Ordering::Release);
    }

    /// The frame taken since the last request, if it came.
    pub fn take(&self) -> Option<Still> {
        self.lock().take()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Option<Still>> {
        self.slot
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The vision thread's side: copies `image` (grey or BGR) when a frame
    /// is wanted and the slot is free; otherwise nothing.
    ///
    /// # Errors
    ///
    /// [`VisionError::OpenCv`] when the conversion to grey fails.
    pub fn offer(&self, frame: u64, t_capture_s: f64, image: &Mat) -> Result<(), VisionError> {
        if !self.wanted.load(Ordering::Acquire) {
            return Ok(());
        }
        let mut slot = match self.slot.try_lock() {
            Ok(g) => g,
            Err(std::sync::TryLockError::Poisoned(p)) => p.into_inner(),
            Err(std::sync::TryLockError::WouldBlock) => return Ok(()),
        };
        let colour = self.colour.load(Ordering::Acquire);
        let mut kept = Mat::default();
        match (image.channels(), colour) {
            (1, _) => image.copy_to(&mut kept)?,
            (4, true) => imgproc::cvt_color_def(image, &mut kept, imgproc::COLOR_BGRA2BGR)?,
            (4, false) => imgproc::cvt_color_def(image, &mut kept, imgproc::COLOR_BGRA2GRAY)?,
            (_, true) => image.copy_to(&mut kept)?,
            (_, false) => imgproc::cvt_color_def(image, &mut kept, imgproc::COLOR_BGR2GRAY)?,
        }
        let (w, h) = (kept.cols().max(0) as u32, kept.rows().max(0) as u32);
        *slot = Some(Still {
            frame,
            t_capture_s,
            width_px: w,
            height_px: h,
            channels: kept.channels().max(0) as u32,
            pixels: kept.data_bytes()?.to_vec(),
        });
        self.wanted.store(false, Ordering::Release);
        Ok(())
    }
}

/// Mean brightness (over the three channels, 0..255) of the square of
/// half-side `roi_px[2]` around (`roi_px[0]`, `roi_px[1]`), clipped to the
/// image; `None` when nothing of it is in the image.
///
/// # Errors
///
/// [`VisionError::OpenCv`] when taking the region or its mean fails.
pub fn led_level(image: &Mat, roi_px: [f64; 3]) -> Result<Option<f64>, VisionError> {
    let (w, h) = (image.cols(), image.rows());
    let r = roi_px[2].max(0.0).round() as i32;
    let (cx, cy) = (roi_px[0].round() as i32, roi_px[1].round() as i32);
    let (x0, y0) = ((cx - r).max(0), (cy - r).max(0));
    let (x1, y1) = ((cx + r + 1).min(w), (cy + r + 1).min(h));
    if x1 <= x0 || y1 <= y0 {
        return Ok(None);
    }
    let roi = Mat::roi(image, Rect::new(x0, y0, x1 - x0, y1 - y0))?;
    let m = opencv::core::mean(&roi, &opencv::core::no_array())?;
    let channels = image.channels().clamp(1, 3);
    Ok(Some(
        (0..channels as usize).map(|c| m[c]).sum::<f64>() / f64::from(channels),
    ))
}

/// The running vision thread.
#[derive(Debug)]
pub struct VisionLoop {
    stop: Arc<AtomicBool>,
    stats: Arc<VisionStats>,
    video: Arc<VideoStats>,
    handle: Option<JoinHandle<Result<(), VisionError>>>,
}

/// Everything the vision thread owns.
pub struct VisionParts {
    /// Where frames come from.
    pub source: Box<dyn FrameSource>,
    /// Detector settings.
    pub detector: DetectorParams,
    /// The calibration to start with.
    pub calibration: SwingPlaneCalibration,
    /// New calibrations (the simulated lab moves its pendulum per trial).
    pub calibrations: Option<Consumer<SwingPlaneCalibration>>,
    /// Measurements to the control thread.
    pub measurements: Producer<Measurement>,
    /// JPEG frames to the server, and how.
    pub video: Option<(FrameSender, VideoParams)>,
    /// The control clock.
    pub clock: Clock,
    /// Opens the source again when it stops (a real camera); `None`: the
    /// end of the source ends the thread.
    pub reopen: Option<SourceFactory>,
    /// The LED's region and where its readings go (`None`: not read).
    pub led: Option<LedTap>,
    /// Full-resolution frames on request (`None`: never asked for).
    pub stills: Option<Arc<StillSlot>>,
    /// The exposure -> delivery latency the stamps take, seconds as `f64`
    /// bits (NaN: the source's own); the control thread sets it when the
    /// lab's belief changes.
    pub stamp_latency: Option<Arc<AtomicU64>>,
}

/// A camera that could not be opened (why): it delivers nothing, so the
/// vision thread takes it as stopped and opens it again every
/// [`REOPEN_EVERY_S`].
#[derive(Debug)]
pub struct NoCamera(pub String);

impl FrameSource for NoCamera {
    fn next_frame(&mut self) -> Result<Option<crate::vision::Frame<'_>>, VisionError> {
        Err(VisionError::Open {
            what: "camera".into(),
            reason: self.0.clone(),
        })
    }

    fn fps(&self) -> f64 {
        0.0
    }
}

/// A stopped camera is tried again this often, seconds.
pub const REOPEN_EVERY_S: f64 = 0.5;

impl std::fmt::Debug for VisionParts {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VisionParts")
            .field("fps", &self.source.fps())
            .finish_non_exhaustive()
    }
}

impl VisionLoop {
    /// Starts `isochron-vision`.
    ///
    /// # Errors
    ///
    /// [`VisionError::Param`] for invalid video parameters; the error of
    /// [`VisionPipeline::new`]; [`VisionError::Spawn`] when the thread cannot start.
    pub fn spawn(parts: VisionParts) -> Result<Self, VisionError> {
        if let Some((_, v)) = &parts.video {
            v.validate()?;
        }
        let pipeline = VisionPipeline::new(parts.detector.clone(), parts.calibration)?;
        let stop = Arc::new(AtomicBool::new(false));
        let stats = Arc::new(VisionStats::default());
        let video = Arc::new(VideoStats::default());
        let (s, st, vs) = (Arc::clone(&stop), Arc::clone(&stats), Arc::clone(&video));
        let handle = std::thread::Builder::new()
            .name("isochron-vision".into())
            .spawn(move || run(parts, pipeline, &s, &st, &vs))
            .map_err(VisionError::Spawn)?;
        Ok(Self {
            stop,
            stats,
            video,
            handle: Some(handle),
        })
    }

    /// Detection counters.
    pub fn stats(&self) -> &Arc<VisionStats> {
        &self.stats
    }

    /// Camera stream counters.
    pub fn video(&self) -> &Arc<VideoStats> {
        &self.video
    }

    /// True once the thread ended (end of stream or an error).
    pub fn is_finished(&self) -> bool {
        self.handle.as_ref().is_none_or(JoinHandle::is_finished)
    }

    /// Stops the thread and returns how it ended.
    ///
    /// # Errors
    ///
    /// The error the vision thread ended with; [`VisionError::Panicked`] when it panicked.
    pub fn stop(mut self) -> Result<(), VisionError> {
        self.stop.store(true, Ordering::Relaxed);
        match self.handle.take() {
            Some(h) => h.join().map_err(|_| VisionError::Panicked)?,
            None => Ok(()),
        }
    }
}

impl Drop for VisionLoop {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

fn run(
    mut parts: VisionParts,
    mut pipeline: VisionPipeline,
    stop: &AtomicBool,
    stats: &VisionStats,
    video: &VideoStats,
) -> Result<(), VisionError> {
    crate::vision::limit_opencv_threads()?;
    let clock = parts.clock;
    let mut next_video_s = 0.0;
    let mut small = Mat::default();
    let mut jpeg = Vector::<u8>::new();
    // The stamp latency last given to the source (NaN: none yet).
    let mut applied = f64::NAN;
    while !stop.load(Ordering::Relaxed) {
        if let Some(l) = parts.stamp_latency.as_ref() {
            let want = f64::from_bits(l.load(Ordering::Relaxed));
            if want.is_finite() && want.to_bits() != applied.to_bits() {
                parts.source.set_stamp_latency_s(want);
                applied = want;
            }
        }
        let stamp_latency_s = parts.source.stamp_latency_s();
        if let Some(rx) = parts.calibrations.as_mut() {
            let mut newest = None;
            while let Ok(c) = rx.pop() {
                newest = Some(c);
            }
            if let Some(c) = newest {
                // A new pendulum position: a fresh detector (no stale track).
                pipeline = VisionPipeline::new(parts.detector.clone(), c)?;
            }
        }
        let frame = match parts.source.next_frame() {
            Ok(Some(frame)) => frame,
            ended => {
                let Some(open) = parts.reopen.as_mut() else {
                    // A source that cannot be reopened ends the thread.
                    ended?;
                    break;
                };
                // A camera that stopped (unplugged, its stream ended or
                // broken): lost until it opens again, tried every
                // REOPEN_EVERY_S; the control thread sees no frames (a
                // running trial aborts as camera_lost, new ones are refused).
                stats.lost.store(true, Ordering::Relaxed);
                stats.set_problem(Some(match ended {
                    Err(e) => e.to_string(),
                    Ok(_) => "the camera's stream ended".to_owned(),
                }));
                loop {
                    if stop.load(Ordering::Relaxed) {
                        return Ok(());
                    }
                    std::thread::sleep(std::time::Duration::from_secs_f64(REOPEN_EVERY_S));
                    match open(clock) {
                        Ok(source) => {
                            parts.source = source;
                            break;
                        }
                        Err(e) => stats.set_problem(Some(e.to_string())),
                    }
                }
                // The new source stamps with its own latency until told.
                applied = f64::NAN;
                stats.reopened.fetch_add(1, Ordering::Relaxed);
                stats.lost.store(false, Ordering::Relaxed);
                stats.set_problem(None);
                // A fresh detector: the old track is stale.
                pipeline = VisionPipeline::new(parts.detector.clone(), *pipeline.calibration())?;
                continue;
            }
        };
        let t0 = clock.now_s();
        if let Some(tap) = parts.led.as_mut()
            && let Ok(Some(level)) = led_level(frame.image, tap.roi_px)
        {
            // A full ring (nobody reading) drops the newest.
            let _ = tap.readings.push(LedReading {
                frame: frame.index,
                t_delivered_s: frame.t_capture_s + stamp_latency_s,
                level,
            });
        }
        if let Some(stills) = parts.stills.as_ref() {
            // A frame that cannot be copied stays wanted: the next one.
            let _ = stills.offer(frame.index, frame.t_capture_s, frame.image);
        }
        let Ok(m) = pipeline.process(&frame, t0) else {
            video.detector_errors.fetch_add(1, Ordering::Relaxed);
            continue;
        };
        let t1 = clock.now_s();
        let m = Measurement {
            t_available_s: t1,
            ..m
        };
        let us = ((t1 - t0) * 1e6).max(0.0) as u64;
        stats.last_frame_us.store(us, Ordering::Relaxed);
        stats.max_frame_us.fetch_max(us, Ordering::Relaxed);
        stats.frames.fetch_add(1, Ordering::Relaxed);
        if m.found {
            stats.found.fetch_add(1, Ordering::Relaxed);
        }
        if parts.measurements.push(m).is_err() {
            stats.overflows.fetch_add(1, Ordering::Relaxed);
        }
        // The dashboard's video, after the measurement is on its way.
        if let Some((tx, vp)) = parts.video.as_mut()
            && t1 >= next_video_s
        {
            next_video_s = t1.max(next_video_s) + 1.0 / vp.fps;
            let e0 = clock.now_s();
            if encode_jpeg(frame.image, vp, &mut small, &mut jpeg).is_ok() {
                video
                    .last_encode_us
                    .store(((clock.now_s() - e0) * 1e6) as u64, Ordering::Relaxed);
                video.last_bytes.store(jpeg.len() as u64, Ordering::Relaxed);
                let f = VideoFrame {
                    frame: m.frame,
                    t_us: (frame.t_capture_s.max(0.0) * 1e6) as u64,
                    jpeg: jpeg.as_slice().to_vec(),
                };
                if tx.send(f) {
                    video.frames.fetch_add(1, Ordering::Relaxed);
                } else {
                    video.dropped.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
    }
    Ok(())
}

/// Downscales `image` to `p.width_px` wide and encodes it as JPEG into `out`.
///
/// # Errors
///
/// [`VisionError::BadFrame`] for an empty image or when JPEG encoding is refused;
/// [`VisionError::OpenCv`] when resizing or encoding fails.
pub fn encode_jpeg(
    image: &Mat,
    p: &VideoParams,
    small: &mut Mat,
    out: &mut Vector<u8>,
) -> Result<(), VisionError> {
    let (w, h) = (image.cols(), image.rows());
    if w <= 0 || h <= 0 {
        return Err(FrameProblem::Empty.into());
    }
    let tw = (p.width_px as i32).min(w);
    let th = ((f64::from(h) * f64::from(tw) / f64::from(w)).round() as i32).max(1);
    let src: &Mat = if tw == w {
        image
    } else {
        imgproc::resize(
            image,
            small,
            Size::new(tw, th),
            0.0,
            0.0,
            imgproc::INTER_AREA,
        )?;
        small
    };
    let params =
        Vector::<i32>::from_slice(&[imgcodecs::IMWRITE_JPEG_QUALITY, i32::from(p.quality)]);
    out.clear();
    if !imgcodecs::imencode(".jpg", src, out, &params)? {
        return Err(FrameProblem::JpegEncoding.into());
    }
    Ok(())
}
