//! Camera sources behind one trait, and the MJPG recorder.
//!
//! Every source timestamps its frames at capture on a [`Clock`] (seconds since
//! the clock's epoch), so the filter can compensate the delay.

use std::{
    path::{Path, PathBuf},
    time::{Duration, Instant},
};

use opencv::{
    core::{Mat, MatTraitConst, MatTraitManual, Size},
    prelude::{VideoCaptureTrait, VideoCaptureTraitConst, VideoWriterTrait, VideoWriterTraitConst},
    videoio::{self, VideoCapture, VideoWriter},
};

use super::{FrameProblem, VisionError};
use crate::check;
use crate::params::CameraParams;

/// A monotonic clock: seconds since an epoch shared by the threads that compare times.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Clock {
    epoch: Instant,
}

impl Clock {
    /// A clock whose zero is `epoch`.
    pub const fn new(epoch: Instant) -> Self {
        Self { epoch }
    }

    /// A clock whose zero is now.
    pub fn start() -> Self {
        Self::new(Instant::now())
    }

    /// Seconds since the epoch.
    pub fn now_s(&self) -> f64 {
        self.epoch.elapsed().as_secs_f64()
    }

    /// Sleeps until the clock reads `t_s` (returns at once if it has passed).
    pub fn sleep_until(&self, t_s: f64) {
        let dt = t_s - self.now_s();
        if dt > 0.0 && dt.is_finite() {
            std::thread::sleep(Duration::from_secs_f64(dt.min(3600.0)));
        }
    }
}

/// One captured image.
#[derive(Debug)]
pub struct Frame<'a> {
    /// Frame number from the source, from 0 (lost frames leave gaps).
    pub index: u64,
    /// When the image was taken (middle of the exposure), seconds on the source's clock.
    pub t_capture_s: f64,
    /// The 8-bit BGR image; valid until the next call to the source.
    pub image: &'a Mat,
}

/// Anything that delivers timestamped frames.
pub trait FrameSource: Send {
    /// Waits for the next frame; `Ok(None)` at the end of the stream.
    ///
    /// # Errors
    ///
    /// A [`VisionError`] when the source cannot deliver a frame (e.g.
    /// [`VisionError::Open`] for a lost device, [`VisionError::BadFrame`] for an empty one).
    fn next_frame(&mut self) -> Result<Option<Frame<'_>>, VisionError>;

    /// The nominal frame rate, frames per second.
    fn fps(&self) -> f64;

    /// The exposure -> delivery latency the source subtracts from a frame's
    /// delivery time to stamp it, seconds (0: stamped otherwise, e.g. a
    /// video file's own times).
    fn stamp_latency_s(&self) -> f64 {
        0.0
    }

    /// Stamps the next frames with this latency (the lab's belief changed:
    /// the latency step's result). Sources that stamp otherwise ignore it.
    fn set_stamp_latency_s(&mut self, _latency_s: f64) {}
}

/// A V4L2 webcam: `[camera]` gives resolution and frame rate.
#[derive(Debug, Clone, PartialEq)]
pub struct WebcamParams {
    /// Device path, e.g. `/dev/video0`.
    pub device: PathBuf,
    /// Resolution, frame rate and the exposure -> delivery latency (`latency_ms`).
    pub camera: CameraParams,
}

/// A V4L2 webcam through OpenCV: one-frame buffer, frames stamped at capture.
pub struct WebcamSource {
    cap: VideoCapture,
    image: Mat,
    clock: Clock,
    latency_s: f64,
    fps: f64,
    index: u64,
}

impl std::fmt::Debug for WebcamSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WebcamSource")
            .field("fps", &self.fps)
            .field("index", &self.index)
            .finish_non_exhaustive()
    }
}

impl WebcamSource {
    /// Opens the device and asks for the resolution, frame rate and a buffer of 1.
    ///
    /// # Errors
    ///
    /// [`VisionError::Param`] for invalid camera parameters; [`VisionError::Open`] when
    /// the device is missing or cannot be opened as a V4L2 camera;
    /// [`VisionError::OpenCv`] when a capture property cannot be set or read.
    pub fn open(params: &WebcamParams, clock: Clock) -> Result<Self, VisionError> {
        params.camera.validate()?;
        let what = params.device.display().to_string();
        let open_err = |reason: String| VisionError::Open {
            what: what.clone(),
            reason,
        };
        if !params.device.exists() {
            return Err(open_err("no such device".into()));
        }
        let mut cap = VideoCapture::from_file(&params.device, videoio::CAP_V4L2)
            .map_err(|e| open_err(e.message))?;
        if !cap.is_opened()? {
            return Err(open_err("OpenCV could not open it as a V4L2 camera".into()));
        }
        let c = &params.camera;
        let mjpg = VideoWriter::fourcc('M', 'J', 'P', 'G')?;
        cap.set(videoio::CAP_PROP_FOURCC, f64::from(mjpg))?;
        cap.set(videoio::CAP_PROP_FRAME_WIDTH, f64::from(c.width_px))?;
        cap.set(videoio::CAP_PROP_FRAME_HEIGHT, f64::from(c.height_px))?;
        cap.set(videoio::CAP_PROP_FPS, c.fps)?;
        // V4L2 keeps 4 frames by default: old frames would add latency.
        cap.set(videoio::CAP_PROP_BUFFERSIZE, 1.0)?;
        let fps = cap.get(videoio::CAP_PROP_FPS)?;
        Ok(Self {
            cap,
            image: Mat::default(),
            clock,
            latency_s: c.latency_ms * 1e-3,
            fps: if fps.is_finite() && fps > 0.0 {
                fps
            } else {
                c.fps
            },
            index: 0,
        })
    }
}

impl FrameSource for WebcamSource {
    fn next_frame(&mut self) -> Result<Option<Frame<'_>>, VisionError> {
        if !self.cap.grab()? {
            return Err(VisionError::Open {
                what: "webcam".into(),
                reason: "the camera stopped delivering frames".into(),
            });
        }
        // Stamp at delivery, minus the camera's exposure -> delivery latency.
        let t_capture_s = self.clock.now_s() - self.latency_s;
        if !self.cap.retrieve(&mut self.image, 0)? || self.image.empty() {
            return Err(FrameProblem::EmptyFrom { camera: "webcam" }.into());
        }
        let index = self.index;
        self.index += 1;
        Ok(Some(Frame {
            index,
            t_capture_s,
            image: &self.image,
        }))
    }

    fn fps(&self) -> f64 {
        self.fps
    }

    fn stamp_latency_s(&self) -> f64 {
        self.latency_s
    }

    fn set_stamp_latency_s(&mut self, latency_s: f64) {
        if latency_s.is_finite() && latency_s >= 0.0 {
            self.latency_s = latency_s;
        }
    }
}

/// Whether a `[camera] device` names a network camera stream (`http://`,
/// `https://`, `rtsp://`) rather than a device or a file.
pub fn is_stream_url(device: &str) -> bool {
    ["http://", "https://", "rtsp://"].iter().any(|scheme| {
        device.len() > scheme.len() && device[..scheme.len()].eq_ignore_ascii_case(scheme)
    })
}

/// The `host:port` a stream URL connects to (`http` 80, `https` 443, `rtsp`
/// 554 when the URL names none); `None` when the URL names no host.
pub fn stream_authority(url: &str) -> Option<(String, u16)> {
    let (scheme, rest) = url.split_once("://")?;
    let default = match scheme.to_ascii_lowercase().as_str() {
        "http" => 80,
        "https" => 443,
        "rtsp" => 554,
        _ => return None,
    };
    let authority = rest.split(['/', '?', '#']).next()?;
    let host_port = authority.rsplit_once('@').map_or(authority, |(_, h)| h);
    let (host, port) = if let Some(v6) = host_port.strip_prefix('[') {
        let (host, after) = v6.split_once(']')?;
        (host, after.strip_prefix(':'))
    } else {
        match host_port.rsplit_once(':') {
            Some((h, p)) => (h, Some(p)),
            None => (host_port, None),
        }
    };
    if host.is_empty() {
        return None;
    }
    let port = match port {
        Some(p) => p.parse().ok()?,
        None => default,
    };
    Some((host.to_owned(), port))
}

/// Whether something accepts a TCP connection at the stream URL's host and
/// port within `timeout`: the clear reason when not (FFmpeg would only log
/// its own lines, once per attempt, on the service's standard error).
fn probe_stream(url: &str, timeout: std::time::Duration) -> Result<(), String> {
    use std::net::{TcpStream, ToSocketAddrs};
    let Some((host, port)) = stream_authority(url) else {
        return Err("the URL names no host".into());
    };
    let addrs: Vec<_> = (host.as_str(), port)
        .to_socket_addrs()
        .map_err(|e| format!("cannot resolve {host}: {e}"))?
        .collect();
    let mut last = format!("{host} resolves to no address");
    for a in addrs {
        match TcpStream::connect_timeout(&a, timeout) {
            Ok(_) => return Ok(()),
            Err(e) => last = format!("nothing answers at {a}: {e}"),
        }
    }
    Err(last)
}

/// How long opening a network camera stream may take, and reading one frame
/// from it, before it counts as not answering, ms.
pub const STREAM_TIMEOUT_MS: i32 = 3000;

/// A network camera's stream (an IP camera's MJPEG over HTTP, or RTSP)
/// through OpenCV's FFmpeg backend: frames stamped as a webcam's, at
/// delivery minus the camera's exposure -> delivery latency.
pub struct StreamSource {
    cap: VideoCapture,
    image: Mat,
    url: String,
    clock: Clock,
    latency_s: f64,
    fps: f64,
    index: u64,
}

impl std::fmt::Debug for StreamSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StreamSource")
            .field("url", &self.url)
            .field("index", &self.index)
            .finish_non_exhaustive()
    }
}

impl StreamSource {
    /// Opens the stream at `url` (at most [`STREAM_TIMEOUT_MS`]); `camera`
    /// gives the believed frame rate and latency.
    ///
    /// # Errors
    ///
    /// [`VisionError::Param`] for invalid camera parameters; [`VisionError::Open`] for
    /// a URL that is not a stream URL, a host that does not answer, or a stream that
    /// cannot be opened in time; [`VisionError::OpenCv`] when OpenCV fails.
    pub fn open(url: &str, camera: &CameraParams, clock: Clock) -> Result<Self, VisionError> {
        camera.validate()?;
        let open_err = |reason: String| VisionError::Open {
            what: url.to_owned(),
            reason,
        };
        if !is_stream_url(url) {
            return Err(open_err(
                "not a stream URL (http://, https:// or rtsp://)".into(),
            ));
        }
        probe_stream(
            url,
            std::time::Duration::from_millis(STREAM_TIMEOUT_MS as u64),
        )
        .map_err(open_err)?;
        let params = opencv::core::Vector::<i32>::from_slice(&[
            videoio::CAP_PROP_OPEN_TIMEOUT_MSEC,
            STREAM_TIMEOUT_MS,
            videoio::CAP_PROP_READ_TIMEOUT_MSEC,
            STREAM_TIMEOUT_MS,
        ]);
        let cap = VideoCapture::from_file_with_params(url, videoio::CAP_FFMPEG, &params)
            .map_err(|e| open_err(e.message))?;
        if !cap.is_opened()? {
            return Err(open_err(format!(
                "no camera stream answered within {} s",
                STREAM_TIMEOUT_MS / 1000
            )));
        }
        Ok(Self {
            cap,
            image: Mat::default(),
            url: url.to_owned(),
            clock,
            latency_s: camera.latency_ms * 1e-3,
            fps: camera.fps,
            index: 0,
        })
    }
}

impl FrameSource for StreamSource {
    fn next_frame(&mut self) -> Result<Option<Frame<'_>>, VisionError> {
        if !self.cap.grab()? {
            return Err(VisionError::Open {
                what: self.url.clone(),
                reason: "the camera stream stopped delivering frames".into(),
            });
        }
        let t_capture_s = self.clock.now_s() - self.latency_s;
        if !self.cap.retrieve(&mut self.image, 0)? || self.image.empty() {
            return Err(FrameProblem::EmptyFrom {
                camera: "camera stream",
            }
            .into());
        }
        let index = self.index;
        self.index += 1;
        Ok(Some(Frame {
            index,
            t_capture_s,
            image: &self.image,
        }))
    }

    fn fps(&self) -> f64 {
        self.fps
    }

    fn stamp_latency_s(&self) -> f64 {
        self.latency_s
    }

    fn set_stamp_latency_s(&mut self, latency_s: f64) {
        if latency_s.is_finite() && latency_s >= 0.0 {
            self.latency_s = latency_s;
        }
    }
}

/// One frame handed over in the service's own process: 8-bit BGR rows, as
/// the camera rendered them (a simulated world's webcam run beside the lab:
/// no network, no JPEG round trip).
#[derive(Debug, Clone)]
pub struct RawFrame {
    /// Image width, pixels.
    pub width: i32,
    /// Image height, pixels.
    pub height: i32,
    /// `width * height * 3` bytes, row by row.
    pub bgr: std::sync::Arc<Vec<u8>>,
}

/// Frames handed over in-process ([`RawFrame`], through a bounded channel
/// whose sender never waits): stamped at their arrival minus the believed
/// latency, as a stream's frames are; what it skips is only the transport
/// (the HTTP stream, FFmpeg's demuxing, the JPEG decoding).
pub struct ChannelSource {
    rx: std::sync::mpsc::Receiver<RawFrame>,
    image: Mat,
    clock: Clock,
    latency_s: f64,
    fps: f64,
    index: u64,
}

impl std::fmt::Debug for ChannelSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ChannelSource")
            .field("index", &self.index)
            .finish_non_exhaustive()
    }
}

impl ChannelSource {
    /// Frames from `rx`; `camera` gives the believed frame rate and latency.
    ///
    /// # Errors
    ///
    /// [`VisionError::Param`] for invalid camera parameters.
    pub fn new(
        rx: std::sync::mpsc::Receiver<RawFrame>,
        camera: &CameraParams,
        clock: Clock,
    ) -> Result<Self, VisionError> {
        camera.validate()?;
        Ok(Self {
            rx,
            image: Mat::default(),
            clock,
            latency_s: camera.latency_ms * 1e-3,
            fps: camera.fps,
            index: 0,
        })
    }
}

impl FrameSource for ChannelSource {
    fn next_frame(&mut self) -> Result<Option<Frame<'_>>, VisionError> {
        let stopped = |reason: &str| VisionError::Open {
            what: "the in-process camera".into(),
            reason: reason.into(),
        };
        let frame = match self.rx.recv_timeout(Duration::from_millis(
            STREAM_TIMEOUT_MS.unsigned_abs().into(),
        )) {
            Ok(f) => f,
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
                return Err(stopped("no frame within the stream timeout"));
            }
            Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
                return Err(stopped("the camera stopped delivering frames"));
            }
        };
        let t_capture_s = self.clock.now_s() - self.latency_s;
        let (w, h) = (frame.width, frame.height);
        let bytes = usize::try_from(w).unwrap_or(0) * usize::try_from(h).unwrap_or(0) * 3;
        if w <= 0 || h <= 0 || frame.bgr.len() != bytes {
            return Err(FrameProblem::EmptyFrom {
                camera: "in-process camera",
            }
            .into());
        }
        if self.image.rows() != h
            || self.image.cols() != w
            || self.image.typ() != opencv::core::CV_8UC3
        {
            self.image = Mat::new_rows_cols_with_default(
                h,
                w,
                opencv::core::CV_8UC3,
                opencv::core::Scalar::all(0.0),
            )?;
        }
        self.image.data_bytes_mut()?.copy_from_slice(&frame.bgr);
        let index = self.index;
        self.index += 1;
        Ok(Some(Frame {
            index,
            t_capture_s,
            image: &self.image,
        }))
    }

    fn fps(&self) -> f64 {
        self.fps
    }

    fn stamp_latency_s(&self) -> f64 {
        self.latency_s
    }

    fn set_stamp_latency_s(&mut self, latency_s: f64) {
        if latency_s.is_finite() && latency_s >= 0.0 {
            self.latency_s = latency_s;
        }
    }
}

/// A recorded video, optionally paced at its frame rate and looped.
pub struct VideoFileSource {
    cap: VideoCapture,
    image: Mat,
    path: PathBuf,
    clock: Option<Clock>,
    start_s: f64,
    looping: bool,
    fps: f64,
    index: u64,
    file_index: u64,
}

impl std::fmt::Debug for VideoFileSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VideoFileSource")
            .field("path", &self.path)
            .field("fps", &self.fps)
            .field("index", &self.index)
            .finish_non_exhaustive()
    }
}

impl VideoFileSource {
    /// Opens a video file. With a clock, frames are delivered at the file's frame
    /// rate and stamped on the clock; without, as fast as they decode, stamped
    /// `index / fps` (the file's own time).
    ///
    /// # Errors
    ///
    /// [`VisionError::Open`] when `path` is not a file or not a video OpenCV can
    /// decode; [`VisionError::OpenCv`] when OpenCV fails.
    pub fn open(path: &Path, pace: Option<Clock>, looping: bool) -> Result<Self, VisionError> {
        let what = path.display().to_string();
        if !path.is_file() {
            return Err(VisionError::Open {
                what,
                reason: "no such file".into(),
            });
        }
        let cap =
            VideoCapture::from_file(path, videoio::CAP_FFMPEG).map_err(|e| VisionError::Open {
                what: what.clone(),
                reason: e.message,
            })?;
        if !cap.is_opened()? {
            return Err(VisionError::Open {
                what,
                reason: "not a video OpenCV can decode".into(),
            });
        }
        let fps = cap.get(videoio::CAP_PROP_FPS)?;
        let fps = if fps.is_finite() && (0.1..=1000.0).contains(&fps) {
            fps
        } else {
            30.0
        };
        Ok(Self {
            cap,
            image: Mat::default(),
            path: path.to_owned(),
            start_s: pace.map_or(0.0, |c| c.now_s()),
            clock: pace,
            looping,
            fps,
            index: 0,
            file_index: 0,
        })
    }

    /// Number of frames the container declares (may be approximate or 0).
    pub fn frame_count(&self) -> u64 {
        self.cap
            .get(videoio::CAP_PROP_FRAME_COUNT)
            .ok()
            .filter(|n| n.is_finite() && *n > 0.0)
            .map_or(0, |n| n as u64)
    }
}

impl FrameSource for VideoFileSource {
    fn next_frame(&mut self) -> Result<Option<Frame<'_>>, VisionError> {
        let mut ok = self.cap.read(&mut self.image)? && !self.image.empty();
        if !ok && self.looping && self.file_index > 0 {
            self.cap.set(videoio::CAP_PROP_POS_FRAMES, 0.0)?;
            self.file_index = 0;
            ok = self.cap.read(&mut self.image)? && !self.image.empty();
        }
        if !ok {
            return Ok(None);
        }
        let index = self.index;
        self.index += 1;
        self.file_index += 1;
        let t_file = index as f64 / self.fps;
        let t_capture_s = match self.clock {
            Some(clock) => {
                let t = self.start_s + t_file;
                clock.sleep_until(t);
                t
            }
            None => t_file,
        };
        Ok(Some(Frame {
            index,
            t_capture_s,
            image: &self.image,
        }))
    }

    fn fps(&self) -> f64 {
        self.fps
    }
}

/// Writes frames to an MJPG `.avi` file.
pub struct Recorder {
    writer: VideoWriter,
    size: Size,
    frames: u64,
}

impl std::fmt::Debug for Recorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recorder")
            .field("size", &self.size)
            .field("frames", &self.frames)
            .finish_non_exhaustive()
    }
}

impl Recorder {
    /// Creates (or replaces) `path` for `width_px` x `height_px` BGR frames at `fps`.
    ///
    /// # Errors
    ///
    /// [`VisionError::Param`] for a frame rate or size out of range;
    /// [`VisionError::Open`] when the MJPG file cannot be written at `path`;
    /// [`VisionError::OpenCv`] when OpenCV fails.
    pub fn create(
        path: &Path,
        width_px: u32,
        height_px: u32,
        fps: f64,
    ) -> Result<Self, VisionError> {
        check::within("recorder.fps", fps, 0.1, 1000.0)?;
        check::within_u32("recorder.width_px", width_px, 16, 7680)?;
        check::within_u32("recorder.height_px", height_px, 16, 4320)?;
        let size = Size::new(width_px as i32, height_px as i32);
        let fourcc = VideoWriter::fourcc('M', 'J', 'P', 'G')?;
        let what = path.display().to_string();
        let writer =
            VideoWriter::new_with_backend(path, videoio::CAP_FFMPEG, fourcc, fps, size, true)
                .map_err(|e| VisionError::Open {
                    what: what.clone(),
                    reason: e.message,
                })?;
        // VideoWriter reports failure only through is_opened().
        if !writer.is_opened()? {
            return Err(VisionError::Open {
                what,
                reason: "cannot write an MJPG .avi there".into(),
            });
        }
        Ok(Self {
            writer,
            size,
            frames: 0,
        })
    }

    /// Appends one frame of the recorder's size.
    ///
    /// # Errors
    ///
    /// [`VisionError::BadFrame`] when `image` is not of the recorder's size and type;
    /// [`VisionError::OpenCv`] when writing fails.
    pub fn write(&mut self, image: &Mat) -> Result<(), VisionError> {
        if image.size()? != self.size || image.typ() != opencv::core::CV_8UC3 {
            return Err(FrameProblem::RecorderSize {
                want_width_px: self.size.width,
                want_height_px: self.size.height,
                width_px: image.cols(),
                height_px: image.rows(),
                cv_type: image.typ(),
            }
            .into());
        }
        self.writer.write(image)?;
        self.frames += 1;
        Ok(())
    }

    /// Frames written so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Finishes the file.
    ///
    /// # Errors
    ///
    /// [`VisionError::OpenCv`] when the writer cannot be released.
    pub fn finish(mut self) -> Result<u64, VisionError> {
        self.writer.release()?;
        Ok(self.frames)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stream_urls_host_and_port_are_read_with_the_schemes_defaults() {
        let a = |u: &str| stream_authority(u);
        assert_eq!(a("http://cam.lab/stream"), Some(("cam.lab".into(), 80)));
        assert_eq!(
            a("HTTPS://cam.lab:8443/x?y"),
            Some(("cam.lab".into(), 8443))
        );
        assert_eq!(
            a("rtsp://user:pw@10.0.0.7/live"),
            Some(("10.0.0.7".into(), 554))
        );
        assert_eq!(a("http://[::1]:8081/mjpg"), Some(("::1".into(), 8081)));
        assert_eq!(a("http://127.0.0.1:9"), Some(("127.0.0.1".into(), 9)));
        assert_eq!(a("http:///stream"), None);
        assert_eq!(a("http://cam:port/"), None);
        assert_eq!(a("/dev/video0"), None);
    }

    #[test]
    fn a_stream_url_where_nothing_listens_is_refused_naming_the_address() {
        // A port nobody listens on: bound, then let go.
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let url = format!("http://127.0.0.1:{port}/stream.mjpg");
        let clock = Clock::new(std::time::Instant::now());
        let e = StreamSource::open(&url, &CameraParams::default(), clock).unwrap_err();
        let msg = e.to_string();
        assert!(
            msg.contains(&url) && msg.contains(&format!("nothing answers at 127.0.0.1:{port}")),
            "{msg}"
        );
        // A listener that answers passes the probe (OpenCV then finds no stream).
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}/x", l.local_addr().unwrap());
        assert!(probe_stream(&url, std::time::Duration::from_secs(3)).is_ok());
    }
}
