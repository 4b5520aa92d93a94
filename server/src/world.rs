//! The lab's hardware as a world (`isochron world`, and `isochron serve
//! --scenario` in-process): the world
//! of a scenario (its `[world]`, or a truthful one) on the wall clock behind
//! the interfaces a real lab has, and nothing else:
//!
//! - **the KUKA cabinet** over FRI UDP: the simulated controller
//!   (`sim::kuka`) with the world's robot (latency and drift, servo, joint
//!   noise, torque trip) and the external torques of the ball's contacts;
//! - **the webcam**: frames of the world's true ball as its true camera takes
//!   them (`sim::world::webcam`), served as MJPEG over HTTP
//!   (`http://127.0.0.1:PORT/video.mjpg`, what an IP camera serves and
//!   OpenCV's `VideoCapture` opens), each delivered at its true latency;
//! - **the Arduino**: the magnet firmware in simavr behind a pseudo-terminal
//!   (`firmware/magnet`, `make firmware`); its coil pin lets the world's ball
//!   go after the world's release delay, and switching it on hangs the ball
//!   on the magnet (the operator's hands); its LED pin lights a spot in the
//!   frames (`webcam::LED_PX`, as bright as the share of its row's exposure
//!   it was lit: the latency step's light; the lab configuration says where
//!   it shows, `calibration.led_px`).
//!
//! It writes `--lab-config` (the real-lab configuration for this hardware,
//! read by `isochron serve --config`, with the lab's beliefs beside it as
//! `<name>.scenario.toml`) once everything answers, and one JSON line per
//! release to `--truth` (`sim::world::live::ReleaseTruth`, times as Unix
//! seconds). Nothing in `isochron serve --config` knows it talks to a world.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use nalgebra::Vector3;
use rt_core::fri::FriVersion;
use rt_core::params::{Scenario, check};
use rt_core::sim::kuka::controller::WorldRobot;
use rt_core::sim::kuka::{SimRunOptions, SimServer};
use rt_core::sim::world::live::{LiveWorld, ReleaseTruth};
use rt_core::sim::world::marker::marker_pose;
use rt_core::sim::world::webcam::{BallSample, WorldWebcam};
use serde::Serialize;

use crate::config::{LabMode, ServeConfig};

/// What the world is and where its hardware answers.
#[derive(Debug, Clone, Serialize)]
pub struct WorldReady {
    /// `truthful` or `reality` (the scenario has `[world]`).
    pub world: &'static str,
    /// The cabinet's FRI address (`fri.controller`).
    pub fri_controller: SocketAddr,
    /// Where the cabinet sends (`fri.local_bind` of the service).
    pub fri_client: SocketAddr,
    /// The webcam's stream.
    pub camera_url: String,
    /// The Arduino's serial port.
    pub serial_port: PathBuf,
    /// The world's truth of what the latency step measures: from the middle
    /// of the LED row's exposure to the frame's delivery, on average, ms.
    pub led_latency_ms: f64,
    /// The world's truth of what the pendulum step measures: the string's
    /// length (pivot to the ball's centre), m.
    pub pendulum_length_m: f64,
    /// The world's linear damping of the swing, 1/s (its quadratic air drag
    /// beside it: `pendulum_drag_per_m`).
    pub pendulum_damping_per_s: f64,
    /// The world's quadratic air drag, 1/m (0 in a truthful world).
    pub pendulum_drag_per_m: f64,
    /// The world's contact force pulse, ms (the measured judge believes
    /// `success.contact_pulse_ms`).
    pub contact_pulse_ms: f64,
    /// How late the world's robot shows a contact in its external torques,
    /// ms (the measured judge believes `success.torque_lag_periods` FRI periods).
    pub torque_lag_ms: f64,
    /// The world's command-to-motion latency at the session's start, ms
    /// (from the controller cycle whose message a command answers to the
    /// setpoint's taking effect; it drifts by `[world.robot] latency_drift_ms`).
    pub robot_latency_ms: f64,
    /// The world's servo lag behind a ramp, ms: `2 zeta / omega` of its
    /// second-order servo, or the first-order lag's time constant.
    pub robot_servo_lag_ms: f64,
    /// The world's truth of what the robot step measures (its latency plus
    /// its servo lag): from a command's computation to the measured joints
    /// that show it, on average, ms: the latency, the servo lag, half an
    /// FRI period with the second-order servo (the drive's interpolation)
    /// and the monitoring message's age (latency plus half its jitter).
    pub robot_delay_ms: f64,
    /// The world's true camera: its focal lengths, principal point and lens
    /// (what the camera step measures).
    pub camera_intrinsics: rt_core::vision::CameraIntrinsics,
    /// The world's true camera pose in the robot base frame (what the
    /// camera-robot step measures).
    pub camera_pose: rt_core::vision::CameraPose,
    /// The hanging ball's true centre at rest, robot base frame, m (the
    /// camera-robot step's intercept point).
    pub ball_rest_m: [f64; 3],
}

/// The board the operator holds for the camera step: `(pose, views)`, 0-based.
type HeldBoard = Arc<Mutex<Option<(usize, usize)>>>;
/// Whether the operator has fitted the marker disc to the tool (the
/// camera-robot step).
type MarkerOn = Arc<AtomicBool>;
/// How often the operator reads the service's calibration job, ms.
const OPERATOR_POLL_MS: u64 = 100;

/// The LED's switches the board made, `(world time, on)` in order (the
/// latest [`LED_SWITCHES`]).
type LedSwitches = Arc<Mutex<std::collections::VecDeque<(f64, bool)>>>;
/// The magnet command timeout the lab configuration gives the simulated
/// board, ms (a real Uno's default is 300).
pub const SIMULATED_BOARD_TIMEOUT_MS: f64 = 2000.0;
/// LED switches kept for the frames still to render.
const LED_SWITCHES: usize = 64;

/// One line of the truth file: a release as the world saw it, Unix seconds.
#[derive(Debug, Serialize)]
struct TruthLine<'a> {
    world: &'static str,
    index: usize,
    coil_off_unix_s: f64,
    drop_unix_s: f64,
    release_angle_deg: f64,
    t_star_unix_s: Option<f64>,
    arrival_unix_s: Option<f64>,
    timing_error_ms: Option<f64>,
    contact: bool,
    contact_unix_s: Option<f64>,
    success: bool,
    not_judged: Option<&'a str>,
    /// A strike's figures (strike mode, issue #38).
    #[serde(skip_serializing_if = "Option::is_none")]
    strike: Option<rt_core::control::report::StrikeJudgement>,
}

/// How late the webcam delivered its frames: its drawn latency is what the
/// world means, but a frame is rendered and encoded only after its exposure
/// (and the truth it needs) is over, so on a slow or busy machine it leaves
/// later than drawn. Served as the world's truth at `GET /truth`.
#[derive(Debug, Default)]
struct Lateness {
    frames: u64,
    /// Frames delivered more than [`LATE_S`] after their drawn time.
    late: u64,
    sum_s: f64,
    /// The latest frames' lateness, s (at most [`RECENT_FRAMES`]).
    recent: std::collections::VecDeque<f64>,
}

/// A frame counts as late past this, s.
const LATE_S: f64 = 0.001;
/// Frames the recent lateness is the mean of (8.5 s at 30 fps).
const RECENT_FRAMES: usize = 256;

impl Lateness {
    fn add(&mut self, late_s: f64) {
        let late_s = late_s.max(0.0);
        self.frames += 1;
        self.late += u64::from(late_s > LATE_S);
        self.sum_s += late_s;
        if self.recent.len() == RECENT_FRAMES {
            self.recent.pop_front();
        }
        self.recent.push_back(late_s);
    }

    /// The world's camera truth as JSON: the drawn LED latency, and what it
    /// delivered (drawn + the recent frames' mean lateness).
    fn json(&self, led_latency_ms: f64) -> serde_json::Value {
        let mean = |sum: f64, n: usize| if n == 0 { 0.0 } else { sum / n as f64 };
        let recent_ms = mean(self.recent.iter().sum(), self.recent.len()) * 1e3;
        serde_json::json!({
            "led_latency_ms": led_latency_ms,
            "frames": self.frames,
            "late_frames": self.late,
            "mean_lateness_ms": mean(self.sum_s, usize::try_from(self.frames).unwrap_or(usize::MAX)) * 1e3,
            "recent_frames": self.recent.len(),
            "recent_lateness_ms": recent_ms,
            "led_delivered_latency_ms": led_latency_ms + recent_ms,
        })
    }
}

/// The webcam's in-process receivers (the lab of the service this world runs
/// in): each one's queue of raw frames. What they skip is only transport:
/// the HTTP stream, the JPEG round trip and FFmpeg's demuxing; the frames
/// are the same renders, delivered at the same moments.
#[derive(Debug, Clone, Default)]
pub struct FrameTaps {
    senders: Arc<Mutex<Vec<SyncSender<rt_core::vision::RawFrame>>>>,
    /// Frames a full queue did not take (a receiver that fell behind).
    dropped: Arc<AtomicU64>,
}

impl FrameTaps {
    /// A new receiver of the frames from the next one on (a bounded queue
    /// of [`CLIENT_QUEUE`]; the webcam never waits for it).
    pub fn subscribe(&self) -> Receiver<rt_core::vision::RawFrame> {
        let (tx, rx) = std::sync::mpsc::sync_channel(CLIENT_QUEUE);
        self.senders
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .push(tx);
        rx
    }

    /// Frames a receiver's full queue did not take, so far.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Relaxed)
    }

    fn active(&self) -> bool {
        !self
            .senders
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .is_empty()
    }

    fn publish(&self, frame: &rt_core::vision::RawFrame) {
        let mut list = self
            .senders
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        list.retain(|tx| match tx.try_send(frame.clone()) {
            Ok(()) => true,
            Err(TrySendError::Full(_)) => {
                self.dropped.fetch_add(1, Relaxed);
                true
            }
            Err(TrySendError::Disconnected(_)) => false,
        });
    }
}

/// The webcam stream's clients: each one's queue of JPEG frames.
type Clients = Arc<Mutex<Vec<SyncSender<Arc<Vec<u8>>>>>>;

/// Frames a slow stream client may have queued before it misses some.
const CLIENT_QUEUE: usize = 2;
/// How long a frame's truth is waited for past its exposure (two FRI
/// periods of world steps and a scheduler's hiccup), s.
const TRUTH_MARGIN_S: f64 = 0.012;

/// The world to run.
#[derive(Debug, Clone)]
pub struct WorldSpec {
    /// The scenario (its `[world]`; without one, a truthful world).
    pub scenario: Scenario,
    /// Seed of the world's draws.
    pub seed: u64,
    /// The FRI version the cabinet speaks.
    pub fri_version: FriVersion,
    /// The distance from the robot's base to the ball at rest, m (default:
    /// the middle of the scenario's `task.distance_m`).
    pub distance_m: Option<f64>,
    /// The folder of the magnet firmware and its simavr host.
    pub firmware_dir: PathBuf,
    /// Where the Arduino's serial port appears (a symlink to its pty).
    pub serial_port: PathBuf,
    /// The simulated lab's stand (`isochron serve`'s in-process world):
    /// where the lab asks the pendulum to stand and the ball to hang; read
    /// every controller cycle (`None`: the pendulum stays at `distance_m`).
    pub stand: Option<Arc<rt_core::lab::Stand>>,
}

/// This source tree's magnet firmware build (`make firmware`).
pub fn default_firmware_dir() -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../firmware/magnet/build"
    ))
}

/// A running world: its cabinet, board, webcam and the truth of its releases.
pub struct LabWorld {
    /// Where its hardware answers.
    pub ready: WorldReady,
    scenario: Scenario,
    intercept_m: Vector3<f64>,
    fri_version: FriVersion,
    cabinet: SimServer,
    board: Board,
    board_gone: Arc<AtomicBool>,
    truth_rx: Receiver<ReleaseTruth>,
    epoch_unix_s: f64,
    frames: Arc<AtomicU64>,
    releases: usize,
    /// The cabinet's commanding aborts said so far ([`Self::poll`]).
    aborts_said: u64,
    held_board: HeldBoard,
    marker_on: MarkerOn,
    /// The stand and the hands that hang the ball (the operator asks angles of it).
    hands: Arc<rt_core::lab::Stand>,
    /// The webcam's rendering thread and its stop (ended and joined when
    /// the world is dropped: it renders with OpenCV, which must not run
    /// while the process exits).
    camera: Option<std::thread::JoinHandle<()>>,
    camera_stop: Arc<AtomicBool>,
    taps: FrameTaps,
}

impl Drop for LabWorld {
    fn drop(&mut self) {
        // The webcam first (it reads what the cabinet steps); the cabinet
        // and the board stop as their own fields drop.
        self.camera_stop.store(true, Relaxed);
        if let Some(h) = self.camera.take() {
            let _ = h.join();
        }
    }
}

impl std::fmt::Debug for LabWorld {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LabWorld")
            .field("ready", &self.ready)
            .finish_non_exhaustive()
    }
}

impl LabWorld {
    /// Starts the world's board, cabinet and webcam.
    ///
    /// # Errors
    ///
    /// When the distance is outside 0.2..=1.2 m, the firmware or its host is missing,
    /// or the board, cabinet or webcam (sockets, threads, renderer) cannot start.
    pub fn start(spec: &WorldSpec) -> anyhow::Result<Self> {
        let scenario = &spec.scenario;
        let kind = if scenario.world.is_some() {
            "reality"
        } else {
            "truthful"
        };
        let distance_m = spec
            .distance_m
            .unwrap_or_else(|| scenario.task.distance_m.lerp(0.5));
        check::within("--distance-m", distance_m, 0.2, 1.2)?;
        let intercept = Vector3::new(distance_m, 0.0, scenario.task.intercept_height_m);
        let dir = &spec.firmware_dir;
        let (elf, host) = (dir.join("magnet.elf"), dir.join("magnet-sim"));
        if !elf.is_file() || !host.is_file() {
            bail!(
                "the magnet firmware or its simavr host is missing in {} (run `make firmware`)",
                dir.display()
            );
        }
        let tty = spec.serial_port.clone();
        // The Arduino.
        let mut board = Board::spawn(&host, &elf, &tty)?;
        // The world and the cabinet, which steps it every controller cycle.
        let mut world = LiveWorld::new(scenario, spec.seed, intercept, 0.0);
        let session = world.world().session;
        let true_pendulum = world.world().pendulum;
        let wp = scenario.world.clone().unwrap_or_default();
        let mut params = rt_core::sim::robot_params(scenario, spec.seed);
        params.fri_version = spec.fri_version;
        let period_s = f64::from(params.fri_period_ms) * 1e-3;
        let robot_latency_ms = session.robot_latency_s * 1e3;
        // The second-order servo follows the drive's interpolation of each
        // setpoint over one FRI period (half a period late on average); the
        // first-order lag takes each setpoint as it comes.
        let (robot_servo_lag_ms, robot_interpolation_ms) = if session.servo_omega_radps > 0.0 {
            (
                2.0 * session.servo_damping_ratio / session.servo_omega_radps * 1e3,
                0.5 * period_s * 1e3,
            )
        } else {
            (params.servo_time_constant_ms, 0.0)
        };
        let robot = WorldRobot::for_session(
            &wp,
            &session,
            std::array::from_fn(|i| params.initial_joint_position_deg[i].to_radians()),
            params.servo_time_constant_ms * 1e-3,
            period_s,
            0.0,
            [
                spec.seed ^ 0x9E37_79B9_7F4A_7C15,
                spec.seed ^ 0xD1B5_4A32_D192_ED03,
            ],
        );
        let (mut coil_tx, mut coil_rx) = rtrb::RingBuffer::<(bool, f64)>::new(64);
        let (mut ball_tx, mut ball_rx) = rtrb::RingBuffer::<BallSample>::new(8192);
        // A release every few seconds, drained every 100 ms: never full.
        let (truth_tx, truth_rx) = std::sync::mpsc::sync_channel::<ReleaseTruth>(256);
        let client = free_udp_port()?;
        let occludes = wp.camera.arm_occludes;
        let marker_on: MarkerOn = Arc::default();
        let marker_seen = Arc::clone(&marker_on);
        // Where the pendulum stands and the next hang's angle: the simulated
        // lab's stand, or the operator's hands alone (a pendulum that stays).
        let stand = spec
            .stand
            .clone()
            .unwrap_or_else(|| Arc::new(rt_core::lab::Stand::at(distance_m)));
        let hands = Arc::clone(&stand);
        let mut stand_seen = (distance_m, None);
        let mut steadied_seen = 0;
        let hook: rt_core::sim::kuka::server::TickHook = Box::new(move |sim, t_ns| {
            let t = t_ns as f64 * 1e-9;
            // The stand first: a hang asked for comes after it.
            let asked = stand.asked();
            if asked != stand_seen {
                stand_seen = asked;
                world.place_stand(t, asked.0, asked.1);
            }
            let steadied = stand.steadied();
            if steadied != steadied_seen {
                steadied_seen = steadied;
                world.steady(t);
            }
            while let Ok((on, at)) = coil_rx.pop() {
                world.coil(on, at);
            }
            if let Some(c) = world.step(t, sim.joint_rad()) {
                sim.contact(c);
            }
            let arm_m = occludes.then(|| world.world().arm.points(sim.joint_rad()));
            let marker_m = marker_seen
                .load(Relaxed)
                .then(|| marker_pose(&world.world().arm.flange(sim.joint_rad())));
            let b = world.ball();
            let _ = ball_tx.push(BallSample {
                t_s: t,
                centre_m: b.ball_position_m(),
                velocity_mps: b.ball_velocity_mps(),
                arm_m,
                marker_m,
            });
            for r in world.take_truth() {
                let _ = truth_tx.try_send(r);
            }
        });
        let cabinet = SimServer::spawn_with(
            params,
            "127.0.0.1:0".parse()?,
            client,
            SimRunOptions {
                auto_command: true,
                duration: None,
                normal_priority: false,
                keep_commanding: true,
            },
            Some(robot),
            Some(hook),
        )?;
        let epoch = cabinet.epoch();
        let epoch_unix_s = cabinet.epoch_unix_ns() as f64 * 1e-9;

        // The board's pins reach the world.
        let led: LedSwitches = Arc::default();
        let board_gone = Arc::new(AtomicBool::new(false));
        {
            let (led, gone) = (Arc::clone(&led), Arc::clone(&board_gone));
            let stdout = board.stdout.take().context("the board's output")?;
            std::thread::Builder::new()
                .name("isochron-world-board".into())
                .spawn(move || {
                    for line in stdout.lines() {
                        let Ok(line) = line else { break };
                        let t = epoch.elapsed().as_secs_f64();
                        let mut words = line.split_whitespace();
                        if words.next() != Some("PIN") {
                            continue;
                        }
                        let (pin, level) = (words.next(), words.next());
                        match (pin, level) {
                            (Some("D8"), Some(v)) => {
                                let _ = coil_tx.push((v == "1", t));
                            }
                            (Some("D12"), Some(v)) => {
                                let mut l = led
                                    .lock()
                                    .unwrap_or_else(std::sync::PoisonError::into_inner);
                                if l.len() == LED_SWITCHES {
                                    l.pop_front();
                                }
                                l.push_back((t, v == "1"));
                            }
                            _ => {}
                        }
                    }
                    gone.store(true, Relaxed);
                })?;
        }

        // The webcam.
        let camera_stop = Arc::new(AtomicBool::new(false));
        let camera;
        let listener = TcpListener::bind("127.0.0.1:0").context("the webcam's stream socket")?;
        let camera_url = format!("http://{}/video.mjpg", listener.local_addr()?);
        let clients: Clients = Arc::default();
        let taps = FrameTaps::default();
        let frames = Arc::new(AtomicU64::new(0));
        let mut webcam = WorldWebcam::new(scenario, &session, spec.seed)?;
        let led_latency_ms = webcam.led_latency_s() * 1e3;
        let webcam_camera = *webcam.camera();
        let camera_intrinsics = webcam.camera().true_intrinsics();
        let held_board: HeldBoard = Arc::default();
        let lateness = Arc::new(Mutex::new(Lateness::default()));
        {
            let (clients, lateness, taps) =
                (Arc::clone(&clients), Arc::clone(&lateness), taps.clone());
            std::thread::Builder::new()
                .name("isochron-world-http".into())
                .spawn(move || {
                    serve_stream(&listener, &clients, &lateness, &taps, led_latency_ms);
                })?;
        }
        {
            let taps = taps.clone();
            let (clients, frames, led, lateness, held_board) = (
                Arc::clone(&clients),
                Arc::clone(&frames),
                Arc::clone(&led),
                Arc::clone(&lateness),
                Arc::clone(&held_board),
            );
            let stop = Arc::clone(&camera_stop);
            camera = Some(
                std::thread::Builder::new()
                    .name("isochron-world-camera".into())
                    .spawn(move || {
                        let now = || epoch.elapsed().as_secs_f64();
                        let period = webcam.period_s();
                        let mut k: u64 = 0;
                        while !stop.load(Relaxed) {
                            let t_start = k as f64 * period;
                            sleep_until(epoch, t_start + webcam.truth_after_s() + TRUTH_MARGIN_S);
                            while let Ok(s) = ball_rx.pop() {
                                webcam.push(s);
                            }
                            let timing = webcam.timing(t_start);
                            let share = {
                                // Off at the board's start; the switches kept
                                // reach back seconds before any frame rendered.
                                let l = led
                                    .lock()
                                    .unwrap_or_else(std::sync::PoisonError::into_inner);
                                webcam.led_lit_share(timing.t_start_s, false, l.iter().copied())
                            };
                            webcam.hold_board(
                                *held_board
                                    .lock()
                                    .unwrap_or_else(std::sync::PoisonError::into_inner),
                            );
                            // The JPEG only for the stream's clients, the
                            // raw frame only for the in-process ones.
                            let streamed = clients.lock().is_ok_and(|c| !c.is_empty());
                            let frame = match rendered(
                                &mut webcam,
                                timing.t_start_s,
                                share,
                                streamed,
                                taps.active(),
                            ) {
                                Ok(f) => f,
                                Err(e) => {
                                    eprintln!("isochron world: the webcam failed: {e}");
                                    return;
                                }
                            };
                            sleep_until(epoch, timing.t_delivered_s);
                            if let Some(jpeg) = &frame.0 {
                                publish(&clients, jpeg);
                            }
                            if let Some(raw) = &frame.1 {
                                taps.publish(raw);
                            }
                            frames.fetch_add(1, Relaxed);
                            if let Ok(mut l) = lateness.lock() {
                                l.add(now() - timing.t_delivered_s);
                            }
                            k += 1;
                            // Fallen behind by more than a few frames (a stalled
                            // machine): the camera goes on from now, as a webcam
                            // that dropped frames.
                            let behind = now() - (k as f64 * period);
                            if behind > 4.0 * period {
                                k += (behind / period) as u64;
                            }
                        }
                    })?,
            );
        }

        let ready = WorldReady {
            world: kind,
            fri_controller: cabinet.local_addr(),
            fri_client: client,
            camera_url,
            serial_port: tty,
            led_latency_ms,
            pendulum_length_m: true_pendulum.length_m,
            pendulum_damping_per_s: true_pendulum.damping_per_s,
            pendulum_drag_per_m: true_pendulum.drag_per_m,
            contact_pulse_ms: session.contact_pulse_s * 1e3,
            torque_lag_ms: session.torque_lag_periods * period_s * 1e3,
            robot_latency_ms,
            robot_servo_lag_ms,
            robot_delay_ms: robot_latency_ms
                + robot_servo_lag_ms
                + robot_interpolation_ms
                + (session.message_latency_s + 0.5 * session.message_jitter_s) * 1e3,
            camera_intrinsics,
            camera_pose: rt_core::calibration::extrinsics::camera_pose_of(
                &webcam_camera.base_from_camera,
                &webcam_camera.position_m,
            ),
            ball_rest_m: (true_pendulum.pivot_m - Vector3::new(0.0, 0.0, true_pendulum.length_m))
                .into(),
        };
        Ok(Self {
            ready,
            scenario: scenario.clone(),
            intercept_m: intercept,
            fri_version: spec.fri_version,
            cabinet,
            board,
            board_gone,
            truth_rx,
            epoch_unix_s,
            frames,
            releases: 0,
            aborts_said: 0,
            held_board,
            marker_on,
            hands,
            camera,
            camera_stop,
            taps,
        })
    }

    /// The webcam's in-process receivers: a lab served in this process
    /// takes its frames here rather than through the stream.
    pub fn frame_taps(&self) -> FrameTaps {
        self.taps.clone()
    }

    /// Starts the operator: the hands the calibration steps need. It reads
    /// the service's calibration job (`GET {service}/api/calibration`, as a
    /// person reads the dashboard) every [`OPERATOR_POLL_MS`] and, while the
    /// camera step asks for the chessboard at pose K of N, holds it there in
    /// front of the webcam (its own plan of N holds over the true camera's
    /// image), otherwise the board is lowered; fits the marker disc for the
    /// camera-robot step; hangs the ball at the angle the pendulum step
    /// asks ([`asked_hang_deg`]); and stops the ball by hand when the
    /// contact step asks it to hang still ([`asked_steady`]).
    ///
    /// # Errors
    ///
    /// When `service` is not `http://HOST:PORT` or its thread cannot start.
    pub fn start_operator(&self, service: &str) -> anyhow::Result<()> {
        use std::net::ToSocketAddrs;
        let hostport = service
            .strip_prefix("http://")
            .with_context(|| format!("--operator {service}: give the service as http://HOST:PORT"))?
            .trim_end_matches('/');
        let addr = hostport
            .to_socket_addrs()
            .with_context(|| format!("--operator {service}: not an address"))?
            .next()
            .with_context(|| format!("--operator {service}: no address"))?;
        self.start_operator_with(move || Some(addr))
    }

    /// [`Self::start_operator`] for a service whose address `service` gives
    /// once it is known (`isochron serve --scenario`: after it binds).
    ///
    /// # Errors
    ///
    /// When its thread cannot start.
    pub fn start_operator_with(
        &self,
        service: impl Fn() -> Option<SocketAddr> + Send + 'static,
    ) -> anyhow::Result<()> {
        let held = Arc::clone(&self.held_board);
        let marker = Arc::clone(&self.marker_on);
        let hands = Arc::clone(&self.hands);
        std::thread::Builder::new()
            .name("isochron-world-operator".into())
            .spawn(move || {
                loop {
                    std::thread::sleep(Duration::from_millis(OPERATOR_POLL_MS));
                    let job =
                        service().and_then(|addr| http_get_json(addr, "/api/calibration").ok());
                    let asked = job.as_ref().and_then(asked_pose);
                    *held
                        .lock()
                        .unwrap_or_else(std::sync::PoisonError::into_inner) = asked;
                    marker.store(job.as_ref().is_some_and(asked_marker), Relaxed);
                    if let Some(d) = job.as_ref().and_then(asked_hang_deg) {
                        hands.place(f64::NAN, d);
                    }
                    if job.as_ref().is_some_and(asked_steady) {
                        hands.steady();
                    }
                }
            })?;
        Ok(())
    }

    /// The lab's configuration for this hardware (`isochron serve --config`):
    /// a real lab's, its beliefs the scenario's (at `beliefs_path`, without
    /// `[world]`), uncalibrated as a lab that has not yet calibrated.
    pub fn lab_config(&self, beliefs_path: &Path) -> ServeConfig {
        let beliefs = self.beliefs();
        let mut cfg = ServeConfig::default();
        cfg.lab.mode = LabMode::Real;
        cfg.lab.scenario = Some(absolute(beliefs_path));
        cfg.camera.device = PathBuf::from(&self.ready.camera_url);
        cfg.camera.width_px = beliefs.camera.width_px;
        cfg.camera.height_px = beliefs.camera.height_px;
        cfg.camera.fps = beliefs.camera.fps;
        cfg.fri.local_bind = self.ready.fri_client;
        cfg.fri.controller = self.ready.fri_controller;
        cfg.fri.period_ms = beliefs.robot.fri_period_ms;
        cfg.fri.version = self.fri_version;
        cfg.magnet.port = absolute(&self.ready.serial_port);
        // The board is a simulator sharing the machine: on a loaded one it
        // answers late, which is not a lost board.
        cfg.magnet.command_timeout_ms = SIMULATED_BOARD_TIMEOUT_MS;
        // What the lab believes of its camera and pendulum before calibrating:
        // the camera's nominal lens and where it was put (the simulated lab's).
        let cam = rt_core::sim::camera::SimCameraParams::default();
        let k = beliefs.camera.believed_intrinsics(cam.hfov_deg);
        let i = self.intercept_m;
        cfg.calibration.focal_length_px = k.fx_px;
        cfg.calibration.principal_point_px = [k.cx_px, k.cy_px];
        cfg.calibration.pivot_m = [i.x, i.y, i.z + beliefs.pendulum.length_m];
        cfg.calibration.plane_distance_m = (i.x - cam.pose.position_m[0]).max(0.1);
        cfg.calibration.camera_pose = Some(cam.pose);
        // Where the board's LED shows in the frames (a lab reads it off its
        // camera's image).
        let (x, y, r) = rt_core::sim::world::webcam::LED_PX;
        cfg.calibration.led_px = Some([f64::from(x), f64::from(y), f64::from(r)]);
        cfg
    }

    /// The lab's beliefs: the scenario without `[world]`.
    pub fn beliefs(&self) -> Scenario {
        let mut b = self.scenario.clone();
        b.world = None;
        b
    }

    /// Writes the releases concluded since the last call to `out`, one JSON
    /// line each (waits up to `wait` for the first); fails when the board or
    /// the cabinet has stopped.
    ///
    /// # Errors
    ///
    /// When writing to `out` fails, or the magnet board's simulator or the cabinet has
    /// stopped.
    pub fn poll(&mut self, out: &mut dyn Write, wait: Duration) -> anyhow::Result<usize> {
        let mut n = 0;
        let mut wait = wait;
        loop {
            match self.truth_rx.recv_timeout(wait) {
                Ok(r) => {
                    write_truth(out, self.ready.world, &r, self.epoch_unix_s)?;
                    n += 1;
                    wait = Duration::ZERO;
                }
                Err(RecvTimeoutError::Timeout) => break,
                Err(RecvTimeoutError::Disconnected) => bail!("the cabinet stopped"),
            }
        }
        self.releases += n;
        // As a real cabinet's pendant shows it: why it left commanding, and
        // whose lateness it counted (the lab's replies, or its own cycles).
        let stats = self.cabinet.stats();
        let aborts = stats.aborts.load(Relaxed);
        if aborts > self.aborts_said {
            self.aborts_said = aborts;
            eprintln!(
                "isochron world: the cabinet left commanding ({}); so far {} late and {} missing \
                 of {} replies, {} cycles the cabinet itself was not scheduled for",
                stats
                    .last_abort()
                    .map_or_else(|| "no reason kept".to_string(), |r| r.to_string()),
                stats.late_replies.load(Relaxed),
                stats.missing_replies.load(Relaxed),
                stats.replies.load(Relaxed),
                stats.overruns.load(Relaxed),
            );
        }
        if self.board_gone.load(Relaxed) || self.board.exited() {
            bail!("the magnet board's simulator ended");
        }
        if self.cabinet.is_finished() {
            bail!("the cabinet stopped");
        }
        Ok(n)
    }

    /// Releases written so far and frames served.
    pub fn counts(&self) -> (usize, u64) {
        (self.releases, self.frames.load(Relaxed))
    }
}

/// The pose the service's camera step asks the operator for, `(pose,
/// views)` 0-based, read from its running job's message ("... at pose K of
/// N ..."); `None` when no camera step runs.
pub fn asked_pose(calibration: &serde_json::Value) -> Option<(usize, usize)> {
    let job = &calibration["job"];
    if job["state"] != "running" || job["step"] != "camera" {
        return None;
    }
    let m = job["message"].as_str()?;
    let rest = &m[m.find("at pose ")? + "at pose ".len()..];
    let mut numbers = rest
        .split(|c: char| !c.is_ascii_digit())
        .filter(|w| !w.is_empty());
    let k: usize = numbers.next()?.parse().ok()?;
    let n: usize = numbers.next()?.parse().ok()?;
    (1..=n).contains(&k).then(|| (k - 1, n))
}

/// The release angle the service's running pendulum step asks the ball
/// hung at, degrees (its message says
/// [`crate::calibration::hang_prompt`]); `None` when it asks none.
pub fn asked_hang_deg(calibration: &serde_json::Value) -> Option<f64> {
    let job = &calibration["job"];
    if job["state"] != "running" || job["step"] != "pendulum" {
        return None;
    }
    let m = job["message"].as_str()?;
    let head = crate::calibration::hang_prompt(0.0);
    let head = head.split("0.0").next()?;
    let rest = &m[m.find(head)? + head.len()..];
    let d: f64 = rest.split_whitespace().next()?.parse().ok()?;
    (d.is_finite() && d > 0.0 && d <= 60.0).then_some(d)
}

/// Whether the service's running contact step asks for the ball to be
/// stopped by hand (its message says [`crate::calibration::STEADY_PROMPT`]).
pub fn asked_steady(calibration: &serde_json::Value) -> bool {
    let job = &calibration["job"];
    job["state"] == "running"
        && job["step"] == "contact"
        && job["message"]
            .as_str()
            .is_some_and(|m| m.contains(crate::calibration::STEADY_PROMPT))
}

/// Whether the service's running job is the camera-robot step, which asks
/// for the marker disc on the tool (the operator fits it for the step and
/// takes it off after).
pub fn asked_marker(calibration: &serde_json::Value) -> bool {
    let job = &calibration["job"];
    job["state"] == "running" && job["step"] == "camera-robot"
}

/// `GET path` of the service at `addr`, its JSON body (HTTP/1.1, the
/// connection closed after it).
fn http_get_json(addr: SocketAddr, path: &str) -> anyhow::Result<serde_json::Value> {
    let (status, body) = http_json(addr, "GET", path, "")?;
    if status != 200 {
        bail!("GET {path}: {status} {body}");
    }
    Ok(body)
}

/// `method path` with the JSON `body` (empty: none) to the service at
/// `addr`: the status and the JSON answer (`null` when it is not JSON).
/// HTTP/1.1, the connection closed after it; an answer waited for at most
/// 10 s (a starved machine's service answers late, not never).
///
/// # Errors
///
/// When the service cannot be reached, does not answer in time, or answers
/// something other than an HTTP/1.x response with a length.
pub fn http_json(
    addr: SocketAddr,
    method: &str,
    path: &str,
    body: &str,
) -> anyhow::Result<(u16, serde_json::Value)> {
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(2))?;
    s.set_read_timeout(Some(Duration::from_secs(10)))?;
    s.set_write_timeout(Some(Duration::from_secs(5)))?;
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\
         content-type: application/json\r\ncontent-length: {}\r\n\r\n{body}",
        body.len()
    )?;
    let mut buf = Vec::new();
    s.take(1 << 22).read_to_end(&mut buf)?;
    let text = String::from_utf8_lossy(&buf);
    let (head, answer) = text
        .split_once("\r\n\r\n")
        .context("no end of the HTTP header")?;
    let status: u16 = head
        .strip_prefix("HTTP/1.1 ")
        .or_else(|| head.strip_prefix("HTTP/1.0 "))
        .and_then(|r| r.get(..3))
        .and_then(|c| c.parse().ok())
        .with_context(|| {
            format!(
                "{method} {path}: not an HTTP answer: {}",
                head.lines().next().unwrap_or_default()
            )
        })?;
    if head
        .to_ascii_lowercase()
        .contains("transfer-encoding: chunked")
    {
        bail!("{method} {path}: a chunked answer");
    }
    Ok((
        status,
        serde_json::from_str(answer).unwrap_or(serde_json::Value::Null),
    ))
}

fn absolute(p: &Path) -> PathBuf {
    std::path::absolute(p).unwrap_or_else(|_| p.to_owned())
}

fn write_truth(
    out: &mut dyn Write,
    world: &'static str,
    r: &ReleaseTruth,
    epoch_unix_s: f64,
) -> anyhow::Result<()> {
    let unix = |t: f64| epoch_unix_s + t;
    let line = TruthLine {
        world,
        index: r.index,
        coil_off_unix_s: unix(r.coil_off_s),
        drop_unix_s: unix(r.drop_s),
        release_angle_deg: r.release_angle_deg,
        t_star_unix_s: r.t_star_s.map(unix),
        arrival_unix_s: r.arrival_s.map(unix),
        timing_error_ms: r.timing_error_ms,
        contact: r.contact,
        contact_unix_s: r.contact_s.map(unix),
        success: r.success,
        not_judged: r.not_judged.as_deref(),
        strike: r.strike,
    };
    writeln!(out, "{}", serde_json::to_string(&line)?)?;
    out.flush()?;
    Ok(())
}

fn sleep_until(epoch: Instant, t_s: f64) {
    let dt = t_s - epoch.elapsed().as_secs_f64();
    if dt > 0.0 {
        std::thread::sleep(Duration::from_secs_f64(dt.min(1.0)));
    }
}

/// A free loopback UDP port for the service's FRI client.
fn free_udp_port() -> anyhow::Result<SocketAddr> {
    let s = UdpSocket::bind("127.0.0.1:0").context("a UDP port for the FRI client")?;
    Ok(s.local_addr()?)
}

/// Hands a frame to every stream client (a client whose queue is full
/// misses it; a gone one is dropped).
/// One frame as the stream's JPEG and as the in-process receivers' raw frame.
type Rendered = (Option<Arc<Vec<u8>>>, Option<rt_core::vision::RawFrame>);

/// The webcam's frame at `t_start_s` as the stream's JPEG (`jpeg`) and as
/// the in-process receivers' raw frame (`raw`), each only when asked for
/// (neither: not rendered, as no one looks).
fn rendered(
    webcam: &mut WorldWebcam,
    t_start_s: f64,
    led: f64,
    jpeg: bool,
    raw: bool,
) -> Result<Rendered, rt_core::vision::VisionError> {
    let jpeg = if jpeg {
        Some(Arc::new(webcam.frame_jpeg(t_start_s, led)?.to_vec()))
    } else {
        None
    };
    if !raw {
        return Ok((jpeg, None));
    }
    if jpeg.is_none() {
        webcam.frame(t_start_s, led)?;
    }
    Ok((jpeg, Some(webcam.latest_raw()?)))
}

fn publish(clients: &Mutex<Vec<SyncSender<Arc<Vec<u8>>>>>, jpeg: &Arc<Vec<u8>>) {
    let Ok(mut list) = clients.lock() else {
        return;
    };
    list.retain(|tx| {
        !matches!(
            tx.try_send(Arc::clone(jpeg)),
            Err(TrySendError::Disconnected(_))
        )
    });
}

/// Accepts stream clients: `GET /video.mjpg` gets the MJPEG stream
/// (`multipart/x-mixed-replace`), `GET /truth` the camera's truth (JSON:
/// [`Lateness::json`], with `in_process_dropped_frames`: the frames a full
/// in-process queue did not take, [`FrameTaps::dropped`]), anything else 404.
fn serve_stream(
    listener: &TcpListener,
    clients: &Clients,
    lateness: &Arc<Mutex<Lateness>>,
    taps: &FrameTaps,
    led_latency_ms: f64,
) {
    for stream in listener.incoming() {
        let Ok(stream) = stream else { continue };
        let (tx, rx) = std::sync::mpsc::sync_channel(CLIENT_QUEUE);
        let (clients, lateness, taps) = (Arc::clone(clients), Arc::clone(lateness), taps.clone());
        let _ = std::thread::Builder::new()
            .name("isochron-world-client".into())
            .spawn(move || {
                let truth = || {
                    let mut t = lateness
                        .lock()
                        .unwrap_or_else(std::sync::PoisonError::into_inner)
                        .json(led_latency_ms);
                    t["in_process_dropped_frames"] = taps.dropped().into();
                    t
                };
                let _ = stream_client(stream, &clients, tx, &rx, truth);
            });
    }
}

fn stream_client(
    mut stream: TcpStream,
    clients: &Mutex<Vec<SyncSender<Arc<Vec<u8>>>>>,
    tx: SyncSender<Arc<Vec<u8>>>,
    rx: &Receiver<Arc<Vec<u8>>>,
    truth: impl FnOnce() -> serde_json::Value,
) -> std::io::Result<()> {
    stream.set_read_timeout(Some(Duration::from_secs(2)))?;
    stream.set_write_timeout(Some(Duration::from_secs(2)))?;
    stream.set_nodelay(true)?;
    let mut head = Vec::new();
    let mut buf = [0u8; 512];
    while !head.windows(4).any(|w| w == b"\r\n\r\n") {
        let n = stream.read(&mut buf)?;
        if n == 0 || head.len() > 8192 {
            return Ok(());
        }
        head.extend_from_slice(&buf[..n]);
    }
    let line = String::from_utf8_lossy(&head);
    let mut words = line.split_whitespace();
    let request = (words.next(), words.next());
    if request == (Some("GET"), Some("/truth")) {
        let body = truth().to_string();
        return stream.write_all(
            format!(
                "HTTP/1.0 200 OK\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
                body.len()
            )
            .as_bytes(),
        );
    }
    if request != (Some("GET"), Some("/video.mjpg")) {
        return stream.write_all(
            b"HTTP/1.0 404 Not Found\r\nContent-Type: text/plain\r\n\r\nthe stream is /video.mjpg\n",
        );
    }
    stream.write_all(
        b"HTTP/1.0 200 OK\r\nCache-Control: no-cache\r\nContent-Type: multipart/x-mixed-replace; boundary=frame\r\n\r\n",
    )?;
    if let Ok(mut list) = clients.lock() {
        list.push(tx);
    }
    while let Ok(jpeg) = rx.recv() {
        let part = format!(
            "--frame\r\nContent-Type: image/jpeg\r\nContent-Length: {}\r\n\r\n",
            jpeg.len()
        );
        stream.write_all(part.as_bytes())?;
        stream.write_all(&jpeg)?;
        stream.write_all(b"\r\n")?;
    }
    Ok(())
}

/// The magnet board: the firmware in its simavr host behind a pty.
struct Board {
    child: Child,
    stdout: Option<BufReader<std::process::ChildStdout>>,
}

impl Board {
    fn spawn(host: &Path, elf: &Path, tty: &Path) -> anyhow::Result<Self> {
        let mut child = Command::new(host)
            .arg(elf)
            .arg(tty)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .with_context(|| format!("cannot start {}", host.display()))?;
        let stdout = child.stdout.take().context("the board's output")?;
        let mut reader = BufReader::new(stdout);
        // simavr says what it loaded, the host its pins' first levels, then READY.
        let mut line = String::new();
        for _ in 0..32 {
            line.clear();
            if reader.read_line(&mut line)? == 0 || line.starts_with("READY") {
                break;
            }
        }
        if !line.starts_with("READY") {
            let _ = child.kill();
            bail!("the magnet board's simulator did not start: {line:?}");
        }
        Ok(Self {
            child,
            stdout: Some(reader),
        })
    }

    fn exited(&mut self) -> bool {
        !matches!(self.child.try_wait(), Ok(None))
    }
}

impl Drop for Board {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[cfg(test)]
mod tests {
    use super::asked_pose;
    use serde_json::json;

    #[test]
    fn the_operator_stops_the_ball_only_when_a_running_contact_step_asks() {
        use super::asked_steady;
        let job = |step: &str, state: &str, message: &str| json!({"job": {"step": step, "state": state, "message": message}});
        let asking = format!(
            "waiting for the ball to hang still: it swings by 3.2 mm ({})",
            crate::calibration::STEADY_PROMPT
        );
        assert!(asked_steady(&job("contact", "running", &asking)));
        assert!(!asked_steady(&job("contact", "failed", &asking)));
        assert!(!asked_steady(&job("pendulum", "running", &asking)));
        assert!(!asked_steady(&job(
            "contact",
            "running",
            "knocking the ball"
        )));
        assert!(!asked_steady(&json!({})));
    }

    #[test]
    fn the_operator_hangs_the_ball_where_a_running_pendulum_step_asks() {
        use super::asked_hang_deg;
        let job = |step: &str, state: &str, message: &str| json!({"job": {"step": step, "state": state, "message": message}});
        let asking = format!(
            "magnet on: {}; the swing is recorded when it lets go",
            crate::calibration::hang_prompt(12.5)
        );
        assert_eq!(
            asked_hang_deg(&job("pendulum", "running", &asking)),
            Some(12.5)
        );
        assert_eq!(asked_hang_deg(&job("pendulum", "done", &asking)), None);
        assert_eq!(asked_hang_deg(&job("camera", "running", &asking)), None);
        let plain =
            "magnet on: hang the ball on the magnet (at least 5 cm from where it hangs at rest)";
        assert_eq!(asked_hang_deg(&job("pendulum", "running", plain)), None);
        for bad in ["NaN", "-3", "0", "61", "x"] {
            let m = format!("hang the ball on the magnet {bad} deg out");
            assert_eq!(
                asked_hang_deg(&job("pendulum", "running", &m)),
                None,
                "{bad}"
            );
        }
    }

    #[test]
    fn the_operator_holds_the_board_only_where_a_running_camera_step_asks() {
        let job = |step: &str, state: &str, message: &str| json!({"job": {"step": step, "state": state, "message": message}});
        let asking = "hold the chessboard (9 x 6 inner corners, 30 mm squares) still at pose 3 of 12: all of it in view";
        assert_eq!(asked_pose(&job("camera", "running", asking)), Some((2, 12)));
        assert_eq!(asked_pose(&job("camera", "done", asking)), None);
        assert_eq!(asked_pose(&job("pendulum", "running", asking)), None);
        assert_eq!(
            asked_pose(&job("camera", "running", "fit: view 3 of 12")),
            None
        );
        for bad in [
            "at pose 0 of 12",
            "at pose 13 of 12",
            "at pose x of 12",
            "at pose 3",
        ] {
            assert_eq!(asked_pose(&job("camera", "running", bad)), None, "{bad}");
        }
        assert_eq!(asked_pose(&json!({"job": null})), None);
    }
}
