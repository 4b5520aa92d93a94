//! The real-time lab runtime: what `isochron serve` and `isochron bench`'s
//! `loop` run. Named threads and the wall clock around the same closed loop as
//! the virtual-time lab:
//!
//! - `isochron-fri` (the control thread): [`FriSession`] owns the UDP socket;
//!   each controller datagram goes through [`crate::fri::FriClient`], which
//!   calls [`LabStep`] (the closed loop's [`super::FriLoopStep`] plus the
//!   bridge, the vision ring, the magnet and the ground truth) once, and
//!   sends the guarded command back.
//! - `isochron-fri-sim`: a simulated KUKA controller over loopback UDP
//!   ([`FriLink::Simulated`]: a [`SimulatedRobot`] the caller's factory
//!   starts, `sim`'s); or a real controller at an address.
//! - `isochron-vision`: a [`crate::vision::FrameSource`] (the simulated
//!   camera rendering the ground-truth pendulum, [`CameraLink::Simulated`],
//!   `sim`'s; a webcam or a video file) ->
//!   OpenCV detector -> a bounded wait-free ring to the control thread, and
//!   downscaled JPEG frames to the bridge's frame channel.
//! - `isochron-magnet` (+ `-rx`): the magnet driver on a simulated board
//!   behind a pty ([`MagnetLink::Simulated`], `sim`'s) or a serial port; `isochron-lab-io` carries the control thread's switch
//!   requests to it (serial I/O blocks) and keeps the simulated controller
//!   commanding. The driver's event hook reports the coil's switches to the
//!   control thread through a ring: the ground-truth ball is released when the
//!   magnet reports off.
//!
//! The runtime imports nothing from `sim` (issue #35): a simulated link is a
//! factory the caller hands in (`simulated` in `sim/wall_lab.rs` builds the whole
//! simulated lab), called once the runtime knows what the link needs (the
//! lab's clock, the FRI client's address).

use std::any::Any;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serde::Serialize;

pub use super::step::LabStep;
use super::step::{
    CameraBasis, IoReply, IoRequest, LabClock, LabParts, MagnetNote, Truth, plan_or_params,
};
use super::vision::{LedFeed, StillSlot};
pub use super::vision::{VideoParams, VideoStats, VisionLoop, VisionParts};

use crate::bridge::{ControlEnd, FrameSender};
use crate::control::Controller;
use crate::fri::stats::LatencyHistogram;
use crate::fri::{FriSession, FriSessionParams, SessionState, SessionStats};
use crate::magnet::{EventKind, MagnetHandle, MagnetParams};
use crate::params::Scenario;
use crate::vision::{
    DetectorParams, FrameSource, SwingPlaneCalibration, VisionError, VisionStats, source::Clock,
};

/// Reply latency percentiles, microseconds.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct LatencyUs {
    /// Samples.
    pub count: u64,
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// 99.9th percentile.
    pub p999: f64,
    /// Largest.
    pub max: f64,
}

impl From<crate::fri::stats::LatencySummary> for LatencyUs {
    fn from(s: crate::fri::stats::LatencySummary) -> Self {
        Self {
            count: s.count,
            p50: s.p50,
            p99: s.p99,
            p999: s.p999,
            max: s.max,
        }
    }
}

/// What one real-time loop run measured (CONTRACT.md, `isochron bench`'s `loop`).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct LoopReport {
    /// FRI send period, milliseconds.
    pub period_ms: u32,
    /// Monitoring messages the controller sent in the window.
    pub cycles: u64,
    /// Replies that reached the controller after the next message was due.
    pub late_replies: u64,
    /// Cycles whose reply never reached the controller.
    pub missed_cycles: u64,
    /// Controller send -> reply received, microseconds (the window).
    pub reply_latency_us: LatencyUs,
    /// Control steps longer than the period.
    pub deadline_misses: u64,
    /// Replies the client sent later than half a period after the message.
    pub client_late_replies: u64,
    /// Controller messages the client never received.
    pub client_missed_cycles: u64,
    /// The client's own share of the round trip: datagram received -> reply
    /// sent (decode, control step, encode, send), microseconds (the window).
    /// The rest of `reply_latency_us` is the controller's send and the two
    /// hand-overs through the kernel.
    pub client_us: LatencyUs,
    /// Of `client_us`, the control step (the lab's whole step: commands,
    /// camera, trial, snapshot), microseconds (the window).
    pub client_step_us: LatencyUs,
    /// Of `client_us`, the reply's `send_to` (on the FRI CPU it includes
    /// the simulated controller taking the reply), microseconds (the window).
    pub client_send_us: LatencyUs,
    /// Fraction of the window the client spent polling for expected datagrams
    /// without sleeping ([`crate::fri::priority::RtTuning::spin`]; 0 without).
    pub spin_cpu_share: f64,
    /// Spins in the window that ended without the datagram (it came late).
    pub spins_gave_up: u64,
    /// WebSocket clients connected while measuring (set by the service).
    pub ws_clients: u64,
    /// State messages the service produced per second while measuring.
    pub ws_state_messages_per_s: f64,
    /// The real-time measures the lab took ([`crate::fri::priority::enable`]).
    pub rt: crate::fri::priority::RtStatus,
}

/// Errors of the real-time runtime.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RuntimeError {
    /// A socket or thread could not be set up.
    #[error("real-time lab: {0}")]
    Io(#[from] std::io::Error),
    /// The controller refused the scenario.
    #[error(transparent)]
    Control(#[from] crate::control::ControlError),
    /// The FRI session could not start.
    #[error(transparent)]
    Session(#[from] crate::fri::SessionError),
    /// The simulated controller could not start: its error, kept whole (the
    /// runtime does not name the simulator's types).
    #[error(transparent)]
    Sim(Box<dyn std::error::Error + Send + Sync>),
    /// The camera or the detector could not start.
    #[error(transparent)]
    Vision(#[from] VisionError),
    /// The magnet driver could not start.
    #[error(transparent)]
    Magnet(#[from] crate::magnet::MagnetError),
    /// A parameter was refused.
    #[error(transparent)]
    Param(#[from] crate::check::ParamError),
    /// A thread panicked.
    #[error("real-time lab: the {0} thread failed")]
    Thread(&'static str),
    /// The FRI session did not reach COMMANDING_ACTIVE in time.
    #[error(
        "real-time lab: the FRI session did not reach COMMANDING_ACTIVE within {timeout:?} (it is {state:?})"
    )]
    NotCommanding {
        /// How long it was given.
        timeout: Duration,
        /// The session's state then.
        state: crate::fri::LinkState,
    },
}

/// A simulated robot controller behind the FRI link (`sim`'s), as the
/// runtime supervises and measures it.
pub trait SimulatedRobot: Send + Sync {
    /// The controller's FRI session state.
    fn state(&self) -> SessionState;
    /// Asks the controller for commanding (as the robot program does).
    fn request_commanding(&self);
    /// The loop as the controller counts it.
    fn loop_counts(&self) -> RobotLoopCounts;
    /// Controller send -> reply received, as the controller measures it.
    fn rtt(&self) -> &LatencyHistogram;
    /// The simulator itself (tests inspect it).
    fn as_any(&self) -> &dyn Any;
}

/// A simulated controller's counts of the loop.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RobotLoopCounts {
    /// Monitoring messages sent.
    pub messages_sent: u64,
    /// Replies that arrived after the next message was due.
    pub late_replies: u64,
    /// Cycles whose reply never came.
    pub missing_replies: u64,
}

/// Starts a simulated controller for `scenario` and `seed` that sends to the
/// FRI client at the given address (loopback).
pub type RobotFactory = Box<
    dyn FnOnce(&Scenario, u64, SocketAddr) -> Result<Arc<dyn SimulatedRobot>, RuntimeError> + Send,
>;

/// Where the robot is.
pub enum FriLink {
    /// A simulated KUKA controller on loopback UDP (`isochron-fri-sim`),
    /// started by the factory once the client listens.
    Simulated(RobotFactory),
    /// A controller (the robot, or `isochron fri-sim`) at `controller`; the
    /// client listens on `bind`.
    Controller {
        /// Local address of the FRI client.
        bind: SocketAddr,
        /// The controller's address.
        controller: SocketAddr,
    },
}

impl std::fmt::Debug for FriLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Simulated(_) => f.write_str("Simulated"),
            Self::Controller { bind, controller } => f
                .debug_struct("Controller")
                .field("bind", bind)
                .field("controller", controller)
                .finish(),
        }
    }
}

/// Builds a frame source on the lab's clock (again after it stopped: a
/// camera unplugged and plugged in).
pub type SourceFactory = Box<dyn FnMut(Clock) -> Result<Box<dyn FrameSource>, VisionError> + Send>;

/// What a simulated camera's factory is given.
#[derive(Debug, Clone, Copy)]
pub struct CameraSetup<'a> {
    /// The lab's scenario.
    pub scenario: &'a Scenario,
    /// The run's seed.
    pub seed: u64,
    /// The pendulum's distance when it cannot move; `None`: drawn per trial.
    pub fixed_distance_m: Option<f64>,
    /// The lab's clock (the camera's stamps).
    pub clock: Clock,
    /// The controller's period, seconds.
    pub period_s: f64,
}

/// A simulated camera and the ground truth it renders: the frame source,
/// its calibration at the start, the ring of its calibrations per trial and
/// the truth the trial driver follows (`LabParts::truth`).
pub struct SimulatedCamera {
    /// The frames.
    pub source: Box<dyn FrameSource>,
    /// The swing plane as the camera sees it at the start.
    pub calibration: SwingPlaneCalibration,
    /// The camera's calibration per trial (the simulated pendulum moves).
    pub calibrations: rtrb::Consumer<SwingPlaneCalibration>,
    /// The ground truth, to the trial driver.
    pub truth: Truth,
}

/// Builds the simulated camera (and the lab's ground truth).
pub type CameraFactory =
    Box<dyn FnOnce(&CameraSetup<'_>) -> Result<SimulatedCamera, RuntimeError> + Send>;

/// Where the camera images come from.
pub enum CameraLink {
    /// The simulated camera rendering the ground-truth pendulum (`sim`'s).
    Simulated(CameraFactory),
    /// A real source (webcam, video file, network stream) and what the lab
    /// believes of it before its calibration file.
    Source {
        /// Opens the source on the lab's clock.
        open: SourceFactory,
        /// The camera and pendulum as the lab's configuration puts them: the
        /// swing plane follows the beliefs from there ([`CameraBasis::plane`]).
        basis: CameraBasis,
    },
}

impl std::fmt::Debug for CameraLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Simulated(_) => f.write_str("Simulated"),
            Self::Source { basis, .. } => f
                .debug_struct("Source")
                .field("basis", basis)
                .finish_non_exhaustive(),
        }
    }
}

/// Starts a simulated magnet board: the driver's parameters (its port) and
/// what keeps the board running (dropped with the lab).
pub type MagnetFactory =
    Box<dyn FnOnce() -> Result<(MagnetParams, Box<dyn Any + Send>), RuntimeError> + Send>;

/// Where the magnet is.
pub enum MagnetLink {
    /// A simulated board behind a pseudo-terminal (`sim`'s fake board).
    Simulated(MagnetFactory),
    /// A serial device (the Arduino, or the firmware under simavr on a pty).
    Port(MagnetParams),
}

impl std::fmt::Debug for MagnetLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Simulated(_) => f.write_str("Simulated"),
            Self::Port(p) => f.debug_tuple("Port").field(p).finish(),
        }
    }
}

/// How to build the lab.
#[derive(Debug)]
pub struct LabSetup {
    /// Task, pendulum, camera, robot, tuning.
    pub scenario: Scenario,
    /// Seed of the trial draws and the simulators.
    pub seed: u64,
    /// The robot.
    pub fri: FriLink,
    /// The camera.
    pub camera: CameraLink,
    /// The magnet.
    pub magnet: MagnetLink,
    /// The pendulum's distance when it cannot move (the real lab); `None`:
    /// drawn per trial.
    pub fixed_distance_m: Option<f64>,
    /// The dashboard's camera stream.
    pub video: VideoParams,
    /// The FRI client's settings (guard, silence, lateness).
    pub session: crate::fri::FriClientParams,
    /// The operator dead-man: while a trial runs, an operator heartbeat
    /// ([`crate::bridge::HeartbeatHandle`]) must come at least this often, or
    /// the motion stops safely (abort `operator_lost`). `None`: off.
    pub operator_timeout_s: Option<f64>,
    /// Where the magnet board's LED shows in the camera's image: centre
    /// column, centre row and radius, pixels (`None`: not read; the
    /// latency step needs it). Its readings: [`LabRuntime::led_feed`].
    pub led_roi_px: Option<[f64; 3]>,
    /// The simulated lab's stand ([`super::Stand`]): with one, each trial's
    /// distance is its own (drawn or asked, not `fixed_distance_m`) and the
    /// stand is asked to put the pendulum there and hang the ball at the
    /// trial's release angle. `None`: the pendulum stays put.
    pub stand: Option<Arc<super::Stand>>,
}

impl LabSetup {
    /// A lab for `scenario` with these links. The FRI client declares the
    /// controller silent after 50 ms (at least two periods), not after two
    /// periods: on a shared machine the controller's thread can miss its
    /// slot for tens of milliseconds, which is a late message, not a lost
    /// robot (the controller's own grading still sees every late reply).
    pub fn new(
        scenario: Scenario,
        seed: u64,
        fri: FriLink,
        camera: CameraLink,
        magnet: MagnetLink,
    ) -> Self {
        let period_ms = f64::from(scenario.robot.fri_period_ms.max(1));
        let session = crate::fri::FriClientParams {
            silence_periods: (50.0 / period_ms).clamp(2.0, 100.0),
            ..crate::fri::FriClientParams::default()
        };
        Self {
            scenario,
            seed,
            fri,
            camera,
            magnet,
            fixed_distance_m: None,
            video: VideoParams::default(),
            session,
            operator_timeout_s: None,
            led_roi_px: None,
            stand: None,
        }
    }
}

/// Counters of the `isochron-lab-io` thread.
#[derive(Debug, Default)]
pub struct IoStats {
    /// Magnet switches carried out.
    pub magnet_switches: AtomicU64,
    /// Magnet switches the device refused or did not answer.
    pub magnet_failures: AtomicU64,
    /// Times the simulated controller was asked to command again.
    pub commanding_requests: AtomicU64,
}

/// The running real-time lab; dropping it stops every thread.
pub struct LabRuntime {
    session: Option<FriSession<LabStep>>,
    session_stats: Arc<SessionStats>,
    sim: Option<Arc<dyn SimulatedRobot>>,
    vision: Option<VisionLoop>,
    magnet: MagnetHandle,
    /// What keeps a simulated magnet board running.
    fake: Option<Box<dyn Any + Send>>,
    io: Option<JoinHandle<()>>,
    io_stats: Arc<IoStats>,
    stop_io: Arc<AtomicBool>,
    epoch: Instant,
    period_ms: u32,
    rt: crate::fri::priority::RtStatus,
    led_feed: Option<Arc<LedFeed>>,
    stills: Option<Arc<StillSlot>>,
}

impl std::fmt::Debug for LabRuntime {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LabRuntime")
            .field("period_ms", &self.period_ms)
            .field("fri", &self.session_stats.state())
            .finish_non_exhaustive()
    }
}

impl LabRuntime {
    /// Starts every thread; the control thread talks to the server only
    /// through `control` (and `frames`, from the vision thread).
    ///
    /// # Errors
    ///
    /// [`RuntimeError::Param`] for an invalid scenario or video section;
    /// [`RuntimeError::Control`], [`RuntimeError::Magnet`], [`RuntimeError::Vision`] or
    /// [`RuntimeError::Session`] when the controller, magnet, vision or FRI session does
    /// not start; [`RuntimeError::Io`] when a thread cannot be spawned; the error of a
    /// simulated device's start function.
    pub fn start(
        setup: LabSetup,
        control: ControlEnd,
        frames: Option<FrameSender>,
    ) -> Result<Self, RuntimeError> {
        let LabSetup {
            scenario,
            seed,
            fri,
            camera,
            magnet,
            fixed_distance_m,
            video,
            session: client_params,
            operator_timeout_s,
            led_roi_px,
            stand,
        } = setup;
        // A stand moves the pendulum to each trial's own distance.
        let fixed_distance_m = if stand.is_some() {
            None
        } else {
            fixed_distance_m
        };
        scenario.validate()?;
        video.validate()?;
        // The FRI threads started from here on run first when the machine is busy.
        let rt = crate::fri::priority::enable();
        let epoch = Instant::now();
        control.set_epoch(epoch);
        let clock = Clock::new(epoch);
        let period_ms = scenario.robot.fri_period_ms;
        // The controller is built from the beliefs only: it never holds `[world]`.
        let controller = Controller::new(&scenario.beliefs(), f64::from(period_ms) * 1e-3)?;

        // The magnet: driver thread, its events to the control thread.
        let (mut note_tx, note_rx) = rtrb::RingBuffer::<MagnetNote>::new(64);
        let (fake, params) = match magnet {
            MagnetLink::Simulated(start) => {
                let (p, board) = start()?;
                (Some(board), p)
            }
            MagnetLink::Port(p) => (None, p),
        };
        let hook = Box::new(move |e: &crate::magnet::MagnetEvent| {
            let on = match e.kind {
                EventKind::Switched { on, .. } => on,
                EventKind::HoldLimit { .. } | EventKind::Boot { .. } => false,
                _ => return,
            };
            let t_s = e.at.saturating_duration_since(epoch).as_secs_f64();
            let _ = note_tx.push(MagnetNote { on, t_s });
        });
        let magnet = MagnetHandle::spawn_with_hook(params, hook)?;
        let (req_tx, req_rx) = rtrb::RingBuffer::<IoRequest>::new(16);
        let (reply_tx, reply_rx) = rtrb::RingBuffer::<IoReply>::new(16);

        // The camera: the simulated one renders the truth the control thread hands over.
        let (meas_tx, meas_rx) = crate::vision::measurement_ring(64);
        let mut reopen = None;
        let mut real_plane = None;
        let mut camera_lost_after_s = super::step::CAMERA_LOST_AFTER_S;
        let (source, calibration, truth, calibrations): (
            Box<dyn FrameSource>,
            SwingPlaneCalibration,
            Option<Truth>,
            _,
        ) = match camera {
            CameraLink::Simulated(start) => {
                camera_lost_after_s = super::step::SIMULATED_CAMERA_LOST_AFTER_S;
                let cam = start(&CameraSetup {
                    scenario: &scenario,
                    seed,
                    fixed_distance_m,
                    clock,
                    period_s: f64::from(period_ms) * 1e-3,
                })?;
                (
                    cam.source,
                    cam.calibration,
                    Some(cam.truth),
                    Some(cam.calibrations),
                )
            }
            CameraLink::Source { mut open, basis } => {
                // A camera that does not answer at start (unplugged, its
                // stream not up) is a lost camera, not a service that does
                // not start: tried again every REOPEN_EVERY_S, trials
                // refused until it delivers.
                let source = open(clock).unwrap_or_else(|e| {
                    eprintln!(
                        "isochron: the camera does not deliver ({e}); trying again every {} s",
                        super::vision::REOPEN_EVERY_S
                    );
                    Box::new(super::vision::NoCamera(e.to_string()))
                });
                reopen = Some(open);
                // New beliefs move the plane (`LabParts::real_plane`).
                let (planes_tx, planes_rx) = rtrb::RingBuffer::<SwingPlaneCalibration>::new(4);
                real_plane = Some(super::step::RealPlane {
                    basis,
                    planes: planes_tx,
                });
                (source, basis.plane(&scenario), None, Some(planes_rx))
            }
        };
        let (led_tap, led_feed) = match led_roi_px {
            Some(roi) => {
                let (tap, feed) = LedFeed::new(roi);
                (Some(tap), Some(Arc::new(feed)))
            }
            None => (None, None),
        };
        // Full-resolution frames on request, from a real camera (the camera step).
        let stills = reopen.is_some().then(|| Arc::new(StillSlot::default()));
        let stamp_latency = Arc::new(AtomicU64::new(f64::NAN.to_bits()));
        let vision = VisionLoop::spawn(VisionParts {
            source,
            detector: DetectorParams::default(),
            calibration,
            calibrations,
            measurements: meas_tx,
            video: frames.map(|f| (f, video)),
            clock,
            reopen,
            led: led_tap,
            stills: stills.clone(),
            stamp_latency: Some(Arc::clone(&stamp_latency)),
        })?;

        // The control thread: the FRI client session calling the lab's step.
        let session_cell = Arc::new(OnceLock::new());
        let mut step = LabStep::new(
            controller,
            LabParts {
                scenario: Box::new(scenario.clone()),
                seed,
                fixed_distance_m,
                bridge: control,
                clock: LabClock::Wall(epoch),
                measurements: meas_rx,
                magnet_notes: note_rx,
                io_requests: req_tx,
                io_replies: reply_rx,
                magnet: Some(magnet.clone()),
                session: Arc::clone(&session_cell),
                truth,
                calibration,
                operator_timeout_s,
                stamp_latency: Some(stamp_latency),
                real_plane,
                camera_lost_after_s,
                stand,
            },
        );
        // On the FRI thread the reply is the only system call of a cycle: the
        // step is timed by wall clock only (`LoopStep::cpu_time`).
        step.inner_mut().step.cpu_time = false;
        let (bind, controller_addr, start_robot) = match fri {
            FriLink::Simulated(start) => (SocketAddr::from(([127, 0, 0, 1], 0)), None, Some(start)),
            FriLink::Controller { bind, controller } => (bind, Some(controller), None),
        };
        let session = FriSession::spawn(
            FriSessionParams {
                bind,
                controller: controller_addr,
                exit_on_idle: false,
                client: client_params,
            },
            step,
        )?;
        let session_stats = Arc::clone(session.stats());
        let _ = session_cell.set(Arc::clone(&session_stats));

        // The robot: the simulated controller sends to the client's socket.
        let sim = match start_robot {
            Some(start) => Some(start(&scenario, seed, session.local_addr())?),
            None => None,
        };

        let stop_io = Arc::new(AtomicBool::new(false));
        let io_stats = Arc::new(IoStats::default());
        let io = {
            let mut io = Io {
                stats: Arc::clone(&io_stats),
                requests: req_rx,
                replies: reply_tx,
                magnet: magnet.clone(),
                sim: sim.clone(),
                scenario,
            };
            let stop = Arc::clone(&stop_io);
            std::thread::Builder::new()
                .name("isochron-lab-io".into())
                .spawn(move || io.run(&stop))?
        };
        Ok(Self {
            session: Some(session),
            session_stats,
            sim,
            vision: Some(vision),
            magnet,
            fake,
            io: Some(io),
            io_stats,
            stop_io,
            epoch,
            period_ms,
            rt,
            led_feed,
            stills,
        })
    }

    /// The FRI client session's counters (late replies, missed cycles, state).
    pub fn session_stats(&self) -> &Arc<SessionStats> {
        &self.session_stats
    }

    /// The simulated controller (simulated robot only).
    pub fn simulated_robot(&self) -> Option<&Arc<dyn SimulatedRobot>> {
        self.sim.as_ref()
    }

    /// The FRI client's local address.
    pub fn fri_local_addr(&self) -> Option<SocketAddr> {
        self.session.as_ref().map(FriSession::local_addr)
    }

    /// The vision thread's detection counters.
    pub fn vision_stats(&self) -> Option<&Arc<VisionStats>> {
        self.vision.as_ref().map(VisionLoop::stats)
    }

    /// The camera stream's counters.
    pub fn video_stats(&self) -> Option<&Arc<VideoStats>> {
        self.vision.as_ref().map(VisionLoop::video)
    }

    /// The camera's readings of the magnet board's LED (with
    /// [`LabSetup::led_roi_px`]).
    pub fn led_feed(&self) -> Option<&Arc<LedFeed>> {
        self.led_feed.as_ref()
    }

    /// Full-resolution frames on request (a real camera's).
    pub fn stills(&self) -> Option<&Arc<StillSlot>> {
        self.stills.as_ref()
    }

    /// The magnet driver.
    pub fn magnet(&self) -> &MagnetHandle {
        &self.magnet
    }

    /// The simulated magnet board (when the lab uses one; tests downcast it).
    pub fn simulated_magnet(&self) -> Option<&(dyn Any + Send)> {
        self.fake.as_deref()
    }

    /// The `isochron-lab-io` thread's counters.
    pub fn io_stats(&self) -> &Arc<IoStats> {
        &self.io_stats
    }

    /// The control clock's zero.
    pub fn epoch(&self) -> Instant {
        self.epoch
    }

    /// The FRI period, milliseconds.
    pub fn period_ms(&self) -> u32 {
        self.period_ms
    }

    /// Waits until the FRI session is COMMANDING_ACTIVE.
    ///
    /// # Errors
    ///
    /// [`RuntimeError::NotCommanding`] when the session is not COMMANDING_ACTIVE
    /// within `timeout`.
    pub fn wait_commanding(&self, timeout: Duration) -> Result<(), RuntimeError> {
        let deadline = Instant::now() + timeout;
        while self.session_stats.state() != crate::fri::LinkState::CommandingActive {
            if Instant::now() > deadline {
                return Err(RuntimeError::NotCommanding {
                    timeout,
                    state: self.session_stats.state(),
                });
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        Ok(())
    }

    /// Measures the loop for `window`: the controller's view of the replies
    /// (simulated robot) and the client's counters.
    pub fn measure(&self, window: Duration) -> LoopReport {
        let read = || {
            let st = &self.session_stats;
            let c = (
                st.late_replies.load(Ordering::Relaxed),
                st.missed_cycles.load(Ordering::Relaxed),
                st.spin_ns.load(Ordering::Relaxed),
                st.spins_gave_up.load(Ordering::Relaxed),
            );
            let s = self.sim.as_ref().map(|s| {
                let n = s.loop_counts();
                (n.messages_sent, n.late_replies, n.missing_replies)
            });
            (c, s.unwrap_or((st.received.load(Ordering::Relaxed), 0, 0)))
        };
        // The histograms of the window only: the session's start-up (first
        // touches of its memory, the clients connecting) is not the loop.
        let st = &self.session_stats;
        let rtt = || self.sim.as_ref().map_or(&st.reply_latency, |s| s.rtt());
        let starts = [
            rtt().copy(),
            st.reply_latency.copy(),
            st.step_latency.copy(),
            st.send_latency.copy(),
        ];
        let (c0, s0) = read();
        std::thread::sleep(window);
        let (c1, s1) = read();
        let us = |h: &crate::fri::stats::LatencyHistogram, start| {
            LatencyUs::from(h.since(start).summary_us())
        };
        LoopReport {
            period_ms: self.period_ms,
            cycles: s1.0 - s0.0,
            late_replies: s1.1 - s0.1,
            missed_cycles: s1.2 - s0.2,
            reply_latency_us: us(rtt(), &starts[0]),
            deadline_misses: 0,
            client_late_replies: c1.0 - c0.0,
            client_missed_cycles: c1.1 - c0.1,
            client_us: us(&st.reply_latency, &starts[1]),
            client_step_us: us(&st.step_latency, &starts[2]),
            client_send_us: us(&st.send_latency, &starts[3]),
            spin_cpu_share: (c1.2 - c0.2) as f64 / window.as_nanos().max(1) as f64,
            spins_gave_up: c1.3 - c0.3,
            ws_clients: 0,
            ws_state_messages_per_s: 0.0,
            rt: self.rt,
        }
    }

    /// Stops every thread; returns the control step (its counters).
    ///
    /// # Errors
    ///
    /// [`RuntimeError::Thread`] when the FRI session thread panicked, failed or was
    /// already stopped.
    pub fn stop(mut self) -> Result<LabStep, RuntimeError> {
        self.shutdown()
    }

    fn shutdown(&mut self) -> Result<LabStep, RuntimeError> {
        self.stop_io.store(true, Ordering::Relaxed);
        let step = match self.session.take() {
            Some(s) => s.stop().map_err(|_| RuntimeError::Thread("isochron-fri"))?,
            None => return Err(RuntimeError::Thread("isochron-fri")),
        };
        self.sim = None;
        if let Some(v) = self.vision.take() {
            let _ = v.stop();
        }
        if let Some(h) = self.io.take() {
            let _ = h.join();
        }
        Ok(step)
    }
}

impl Drop for LabRuntime {
    fn drop(&mut self) {
        if self.session.is_some() {
            let _ = self.shutdown();
        }
    }
}

/// What `isochron-lab-io` owns: planning, parameter changes and magnet
/// switches for the control thread, and the simulated controller's supervision.
struct Io {
    stats: Arc<IoStats>,
    requests: rtrb::Consumer<IoRequest>,
    replies: rtrb::Producer<IoReply>,
    magnet: MagnetHandle,
    sim: Option<Arc<dyn SimulatedRobot>>,
    scenario: Scenario,
}

impl Io {
    fn run(&mut self, stop: &AtomicBool) {
        let mut next_check = Instant::now();
        while !stop.load(Ordering::Relaxed) {
            while let Ok(req) = self.requests.pop() {
                self.serve(req);
            }
            if let Some(sim) = &self.sim
                && Instant::now() >= next_check
            {
                next_check = Instant::now() + Duration::from_millis(50);
                // The controller dropped out of commanding (e.g. a burst of late
                // replies graded the link poor): ask again, as an operator would.
                if sim.state() == SessionState::MonitoringReady {
                    sim.request_commanding();
                    self.stats
                        .commanding_requests
                        .fetch_add(1, Ordering::Relaxed);
                }
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    fn serve(&mut self, req: IoRequest) {
        let reply = match req {
            IoRequest::Magnet(on) => {
                // Blocks until the board answers (or the driver's timeout).
                let c = match self.magnet.set_magnet(on) {
                    Ok(_) => &self.stats.magnet_switches,
                    Err(_) => &self.stats.magnet_failures,
                };
                c.fetch_add(1, Ordering::Relaxed);
                return;
            }
            IoRequest::Free(c) => {
                drop(c);
                return;
            }
            req => match plan_or_params(&mut self.scenario, req).map(|(reply, _)| reply) {
                Some(reply) => reply,
                None => return,
            },
        };
        // The control thread drains replies every step; the ring holds more
        // than the requests it can have open (one).
        let _ = self.replies.push(reply);
    }
}
