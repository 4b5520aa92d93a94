//! The server side of the bridge: a named thread (`isochron-bridge`) drains the
//! control thread's hand-offs at the stream rate, serialises each state message
//! once and fans it out to every WebSocket client through bounded broadcast
//! channels; HTTP handlers send commands and wait for their acknowledgement.

use std::{
    collections::HashMap,
    sync::{
        Arc, Mutex,
        atomic::{AtomicBool, AtomicU64, Ordering},
    },
    thread::JoinHandle,
    time::{Duration, Instant},
};

use axum::{body::Bytes, extract::ws::Utf8Bytes};
use rt_core::{
    bridge::{
        BridgeCounters, BridgeStats, Command, Event, EventRecord, FrameReceiver, HeartbeatHandle,
        Refusal, ServerEnd, Snapshot, StopHandle,
    },
    params::Scenario,
};
use serde::Serialize;
use tokio::sync::{broadcast, oneshot};

use crate::records::{Recorder, Records, TrialEnd};
use crate::viz::Foxglove;

/// How the bridge thread and the stream behave.
#[derive(Debug, Clone)]
pub struct LabOptions {
    /// State messages per second on `/ws`.
    pub state_hz: f64,
    /// How long a command waits for the control thread's answer.
    pub ack_timeout: Duration,
    /// A WebSocket client that cannot take a message within this time is dropped.
    pub ws_send_timeout: Duration,
    /// Messages buffered per WebSocket client before it skips (state) ones.
    pub ws_buffer: usize,
    /// `simulated` or `real` (written into the recordings' metadata).
    pub lab_mode: &'static str,
    /// Where the pendulum hangs when the lab cannot move it (a real lab:
    /// its configuration's `calibration.pivot_m`), m from the robot's base
    /// axis: every trial is planned there, and one asking for another
    /// distance is refused. `None`: each trial's own (the simulated lab's
    /// stand moves the pendulum).
    pub fixed_distance_m: Option<f64>,
}

impl Default for LabOptions {
    fn default() -> Self {
        Self {
            state_hz: 100.0,
            ack_timeout: Duration::from_secs(3),
            ws_send_timeout: Duration::from_secs(2),
            ws_buffer: 32,
            lab_mode: "simulated",
            fixed_distance_m: None,
        }
    }
}

/// Counters of the WebSocket stream (shown in every state message).
#[derive(Debug, Default)]
pub struct StreamStats {
    /// Clients connected now (state stream and camera).
    pub clients: AtomicU64,
    /// State messages produced by the bridge thread.
    pub state_messages: AtomicU64,
    /// Messages a slow client skipped (it got the newer ones instead).
    pub skipped: AtomicU64,
    /// Clients dropped because they stalled.
    pub dropped_clients: AtomicU64,
    /// Camera frames forwarded.
    pub frames: AtomicU64,
}

/// A copy of [`StreamStats`].
#[derive(Debug, Clone, Copy, Serialize, utoipa::ToSchema, ts_rs::TS)]
pub struct StreamCounters {
    /// Clients connected now.
    #[ts(type = "number")]
    pub clients: u64,
    /// State messages produced.
    #[ts(type = "number")]
    pub state_messages: u64,
    /// Messages slow clients skipped.
    #[ts(type = "number")]
    pub skipped: u64,
    /// Clients dropped because they stalled.
    #[ts(type = "number")]
    pub dropped_clients: u64,
    /// Camera frames forwarded.
    #[ts(type = "number")]
    pub frames: u64,
}

impl StreamStats {
    /// A plain copy.
    pub fn read(&self) -> StreamCounters {
        StreamCounters {
            clients: self.clients.load(Ordering::Relaxed),
            state_messages: self.state_messages.load(Ordering::Relaxed),
            skipped: self.skipped.load(Ordering::Relaxed),
            dropped_clients: self.dropped_clients.load(Ordering::Relaxed),
            frames: self.frames.load(Ordering::Relaxed),
        }
    }
}

/// Why a command did not go through.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum CommandError {
    /// The control thread refused it.
    #[error("{}", .0.message())]
    Refused(Refusal),
    /// The command ring is full (the control thread is behind).
    #[error("the control loop is busy; try again")]
    Full,
    /// No control thread runs.
    #[error("the lab is not running")]
    NotRunning,
    /// No answer within the timeout.
    #[error("the control loop did not answer in time")]
    NoAnswer,
}

/// A state message of `/ws` and `GET /api/state`: the snapshot's fields, with
/// the hand-off counters.
#[derive(Serialize, ts_rs::TS, utoipa::ToSchema)]
pub struct StateMessage<'a> {
    /// Always `state`.
    #[serde(rename = "type")]
    #[ts(type = "\"state\"")]
    #[schema(value_type = String, pattern = "^state$")]
    pub kind: &'static str,
    /// The control thread's snapshot.
    #[serde(flatten)]
    #[ts(flatten)]
    pub snapshot: &'a Snapshot,
    /// Bridge hand-off counters.
    pub bridge: BridgeCounters,
    /// WebSocket stream counters.
    pub stream: StreamCounters,
}

/// An event message of `/ws`.
#[derive(Serialize, ts_rs::TS, utoipa::ToSchema)]
pub struct EventMessage<'a> {
    /// Always `event`.
    #[serde(rename = "type")]
    #[ts(type = "\"event\"")]
    #[schema(value_type = String, pattern = "^event$")]
    pub kind: &'static str,
    /// The event, its time and trial.
    #[serde(flatten)]
    #[ts(flatten)]
    pub record: &'a EventRecord,
    /// A sentence for people, for aborts.
    #[serde(skip_serializing_if = "Option::is_none")]
    #[ts(optional)]
    pub message: Option<&'static str>,
}

/// Who waits for a command's answer: the request (gone once it timed out)
/// and, for a trial, its record's id (a late answer still settles the record).
#[derive(Debug)]
struct Waiter {
    tx: oneshot::Sender<Result<(), Refusal>>,
    trial: Option<u64>,
}

type Pending = HashMap<u64, Waiter>;

/// The lab as the server sees it.
#[derive(Debug)]
pub struct Lab {
    commands: Mutex<rt_core::bridge::CommandSender>,
    pending: Mutex<Pending>,
    stop: StopHandle,
    heartbeat: HeartbeatHandle,
    state_tx: broadcast::Sender<Utf8Bytes>,
    event_tx: broadcast::Sender<Utf8Bytes>,
    frame_tx: broadcast::Sender<Bytes>,
    latest: Mutex<Option<(Snapshot, Utf8Bytes)>>,
    params: Mutex<Scenario>,
    /// Serialises parameter changes (read-merge-validate-send-store).
    pub params_update: tokio::sync::Mutex<()>,
    /// Serialises starting a trial and starting a calibration step: each
    /// checks that the other is not running, then starts, under it.
    /// Without it both passed their checks at once (a demo trial and a
    /// calibration step ran side by side).
    pub start_gate: tokio::sync::Mutex<()>,
    /// The newest trial the control loop accepted, and the newest trial a
    /// published state has shown: a trial accepted but not shown yet still
    /// runs ([`Lab::trial_unshown`]).
    trial_accepted: AtomicU64,
    trial_shown: AtomicU64,
    bridge_stats: Arc<BridgeStats>,
    stream: StreamStats,
    options: LabOptions,
    shutdown: Arc<AtomicBool>,
    thread: Mutex<Option<JoinHandle<()>>>,
    foxglove: Arc<foxglove::Context>,
    devices: std::sync::OnceLock<Devices>,
    /// One joint's commanded and measured positions from every published
    /// state, while the robot calibration step records them ([`Lab::tap_joint`]).
    joint_tap: Mutex<Option<JointTap>>,
}

/// One joint's commanded and measured positions (and the measured tool
/// point and external torques), in the control clock, from
/// every state the control loop published (the telemetry ring: the states
/// it lost when full are missing here too: `telemetry_overflows`).
#[derive(Debug, Clone, Default)]
pub struct JointTap {
    /// The joint, 0-based.
    pub joint: usize,
    /// What the control loop commanded at each step.
    pub commands: Vec<rt_core::calibration::robot::JointSample>,
    /// What the robot measured, received at each step.
    pub measured: Vec<rt_core::calibration::robot::JointSample>,
    /// The measured tool point (base frame, m) at each step, as `measured`.
    pub tool_m: Vec<[f64; 3]>,
    /// FRI's external joint torques (N m) at each step, as `measured`.
    pub tau_ext_nm: Vec<[f64; rt_core::kinematics::iiwa7::JOINTS]>,
    /// The steps' trial states were all `idle` (no trial ran meanwhile).
    pub idle: bool,
    /// The control clock's time of the first state after the robot left
    /// commanding (`fri.commanding_lost` grew): the tap keeps nothing from
    /// then on (the drives stopped where they were; the commands did not).
    pub cut_s: Option<f64>,
    /// `fri.commanding_lost` at the tap's first state.
    lost_before: Option<u64>,
    /// The control step count of the latest sample (states published
    /// between the robot's messages repeat the last step: left out).
    last_step: u64,
}

/// At most this many samples a tap keeps (60 s at 1 kHz).
const JOINT_TAP_MAX: usize = 60_000;

/// The lab's devices as the service reads them for people (off the real-time
/// path): why a camera or a magnet board does not deliver.
#[derive(Debug)]
pub struct Devices {
    /// The vision thread's counters (its camera's problem).
    pub vision: Option<Arc<rt_core::vision::VisionStats>>,
    /// The magnet driver.
    pub magnet: Option<rt_core::magnet::MagnetHandle>,
    /// The camera's readings of the magnet board's LED (`calibration.led_px`).
    pub led: Option<Arc<rt_core::lab::LedFeed>>,
    /// Full-resolution frames on request (a real camera's: the camera step).
    pub stills: Option<Arc<rt_core::lab::StillSlot>>,
    /// The control clock's zero.
    pub epoch: Option<std::time::Instant>,
}

/// One device that keeps the lab from running trials, and why.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, utoipa::ToSchema)]
pub struct DeviceProblem {
    /// `robot`, `camera` or `magnet`.
    pub device: &'static str,
    /// What is wrong, naming the device (its address, stream or port).
    pub message: String,
}

/// What the bridge thread owns.
struct Pump {
    lab: Arc<Lab>,
    end_latest: rt_core::bridge::LatestReader,
    end_telemetry: rt_core::bridge::TelemetryReader,
    end_events: rt_core::bridge::EventReader,
    end_acks: rt_core::bridge::AckReader,
    frames: Option<FrameReceiver>,
    records: Option<Arc<Records>>,
    recorder: Recorder,
    /// Trials whose end was recorded: their later snapshots are not recorded.
    ended: Option<u64>,
    /// `fri.commanding_lost` as the log last said it.
    commanding_lost: u64,
    /// The Foxglove channels (live server and MCAP recordings).
    fox: Foxglove,
}

impl Lab {
    /// Starts the bridge thread over the server end of a bridge.
    ///
    /// # Errors
    ///
    /// When the bridge thread cannot be spawned.
    pub fn start(
        end: ServerEnd,
        frames: Option<FrameReceiver>,
        params: Scenario,
        records: Option<Arc<Records>>,
        options: LabOptions,
    ) -> anyhow::Result<Arc<Self>> {
        let ServerEnd {
            latest,
            telemetry,
            events,
            commands,
            acks,
            stop,
            heartbeat,
            stats,
        } = end;
        let (state_tx, _) = broadcast::channel(options.ws_buffer.max(1));
        let (event_tx, _) = broadcast::channel(256);
        let (frame_tx, _) = broadcast::channel(4);
        let fox = Foxglove::new(&params);
        let lab = Arc::new(Self {
            commands: Mutex::new(commands),
            pending: Mutex::new(HashMap::new()),
            stop,
            heartbeat,
            state_tx,
            event_tx,
            frame_tx,
            latest: Mutex::new(None),
            params: Mutex::new(params),
            params_update: tokio::sync::Mutex::new(()),
            start_gate: tokio::sync::Mutex::new(()),
            trial_accepted: AtomicU64::new(0),
            trial_shown: AtomicU64::new(0),
            bridge_stats: stats,
            stream: StreamStats::default(),
            options,
            shutdown: Arc::new(AtomicBool::new(false)),
            thread: Mutex::new(None),
            foxglove: Arc::clone(fox.context()),
            devices: std::sync::OnceLock::new(),
            joint_tap: Mutex::new(None),
        });
        let pump = Pump {
            lab: Arc::clone(&lab),
            end_latest: latest,
            end_telemetry: telemetry,
            end_events: events,
            end_acks: acks,
            frames,
            records,
            recorder: Recorder::default(),
            ended: None,
            commanding_lost: 0,
            fox,
        };
        let handle = std::thread::Builder::new()
            .name("isochron-bridge".into())
            .spawn(move || pump.run())?;
        if let Ok(mut t) = lab.thread.lock() {
            *t = Some(handle);
        }
        Ok(lab)
    }

    /// Tells the lab where to read its devices' problems (once; later calls
    /// change nothing).
    pub fn set_devices(&self, devices: Devices) {
        let _ = self.devices.set(devices);
    }

    /// The lab's devices (once the runtime has started).
    pub fn devices(&self) -> Option<&Devices> {
        self.devices.get()
    }

    /// The devices that keep the lab from running trials now, each with why
    /// (empty when every device delivers): the robot when its FRI session
    /// is not commanding, the camera when it delivers no frames, the magnet
    /// when its board does not answer.
    pub fn device_problems(&self) -> Vec<DeviceProblem> {
        use rt_core::bridge::FriSessionState as S;
        let mut out = Vec::new();
        if let Some((s, _)) = self.latest() {
            let why = match s.fri.session {
                S::CommandingActive => None,
                S::Disconnected => Some("no message from the robot's controller (FRI)"),
                S::Idle => Some("the robot's FRI session ended (IDLE)"),
                S::MonitoringWait => {
                    Some("the robot's FRI session is MONITORING_WAIT (connection quality too low)")
                }
                S::MonitoringReady => Some(
                    "the robot's FRI session is MONITORING_READY: its application has not \
                     started commanding",
                ),
                S::CommandingWait => Some("the robot's FRI session is COMMANDING_WAIT"),
            };
            if let Some(why) = why {
                out.push(DeviceProblem {
                    device: "robot",
                    message: why.to_owned(),
                });
            }
        }
        if let Some(d) = self.devices.get() {
            if let Some(p) = d.vision.as_ref().and_then(|v| v.problem()) {
                out.push(DeviceProblem {
                    device: "camera",
                    message: format!("the camera delivers no frames: {p}"),
                });
            }
            if let Some(p) = d
                .magnet
                .as_ref()
                .and_then(rt_core::magnet::MagnetHandle::problem)
            {
                out.push(DeviceProblem {
                    device: "magnet",
                    message: p,
                });
            }
        }
        out
    }

    /// Stops the bridge thread (it finishes any open recording) and waits for it.
    pub fn shutdown(&self) {
        self.shutdown.store(true, Ordering::Release);
        let handle = self.thread.lock().ok().and_then(|mut t| t.take());
        if let Some(h) = handle {
            let _ = h.join();
        }
    }

    /// The Foxglove context: a live server (`viz::start_server`) or an MCAP
    /// writer added to it receives every channel the bridge thread logs.
    pub fn foxglove_context(&self) -> &Arc<foxglove::Context> {
        &self.foxglove
    }

    /// The stream options.
    pub fn options(&self) -> &LabOptions {
        &self.options
    }

    /// The stream counters.
    pub fn stream(&self) -> &StreamStats {
        &self.stream
    }

    /// The bridge counters.
    pub fn bridge_counters(&self) -> BridgeCounters {
        self.bridge_stats.read()
    }

    /// Starts recording `joint`'s commanded and measured positions from
    /// every state published from now on (a tap already running starts over).
    pub fn tap_joint(&self, joint: usize) {
        if let Ok(mut t) = self.joint_tap.lock() {
            *t = Some(JointTap {
                joint,
                commands: Vec::with_capacity(16_384),
                measured: Vec::with_capacity(16_384),
                tool_m: Vec::with_capacity(16_384),
                tau_ext_nm: Vec::with_capacity(16_384),
                idle: true,
                cut_s: None,
                lost_before: None,
                last_step: 0,
            });
        }
    }

    /// Ends the recording [`Self::tap_joint`] began and takes what it holds.
    pub fn take_tap(&self) -> Option<JointTap> {
        self.joint_tap.lock().ok().and_then(|mut t| t.take())
    }

    /// Where the running tap stopped because the robot left commanding
    /// ([`JointTap::cut_s`]; `None` while it records, or none runs).
    pub fn tap_cut(&self) -> Option<f64> {
        self.joint_tap
            .lock()
            .ok()
            .and_then(|t| t.as_ref().and_then(|t| t.cut_s))
    }

    /// How many states the running tap holds (0: none runs).
    pub fn tap_len(&self) -> usize {
        self.joint_tap
            .lock()
            .ok()
            .and_then(|t| t.as_ref().map(|t| t.measured.len()))
            .unwrap_or(0)
    }

    /// The latest snapshot and its JSON state message, once the lab published one.
    pub fn latest(&self) -> Option<(Snapshot, Utf8Bytes)> {
        self.latest.lock().ok().and_then(|l| l.clone())
    }

    /// The current parameters.
    pub fn params(&self) -> Scenario {
        self.params
            .lock()
            .map_or_else(|p| p.into_inner().clone(), |p| p.clone())
    }

    /// Stores parameters the control thread accepted.
    pub fn store_params(&self, p: Scenario) {
        match self.params.lock() {
            Ok(mut g) => *g = p,
            Err(poisoned) => *poisoned.into_inner() = p,
        }
    }

    /// Subscribes to state messages.
    pub fn subscribe_state(&self) -> broadcast::Receiver<Utf8Bytes> {
        self.state_tx.subscribe()
    }

    /// Subscribes to event messages.
    pub fn subscribe_events(&self) -> broadcast::Receiver<Utf8Bytes> {
        self.event_tx.subscribe()
    }

    /// Subscribes to camera frames (JPEG).
    pub fn subscribe_frames(&self) -> broadcast::Receiver<Bytes> {
        self.frame_tx.subscribe()
    }

    /// Records an operator heartbeat (the dead-man); its time on the control
    /// clock, seconds (`None` before the control thread started its clock).
    pub fn heartbeat(&self) -> Option<f64> {
        self.heartbeat.beat()
    }

    /// Emergency stop: the stop flag (independent of the ring) and the command.
    /// Returns true when the control thread acknowledged it in time.
    pub async fn stop(&self) -> bool {
        self.stop.request_stop();
        self.command(Command::Stop).await.is_ok()
    }

    /// Sends a message to the WebSocket's event stream (e.g. a run's progress).
    pub fn publish_event_text(&self, text: String) {
        let _ = self.event_tx.send(text.into());
    }

    /// Sends a command and waits for its acknowledgement.
    ///
    /// # Errors
    ///
    /// [`CommandError::NotRunning`] when no control thread runs;
    /// [`CommandError::Full`] when the command ring is full; [`CommandError::Refused`]
    /// when the control thread refuses; [`CommandError::NoAnswer`] after the timeout.
    pub async fn command(&self, command: Command) -> Result<(), CommandError> {
        self.send(command, None).await
    }

    /// Starts the trial whose record is `trial_id`. When the control loop
    /// answers only after the timeout, the answer still settles the record
    /// (the bridge thread deletes it when the trial was refused; an accepted
    /// trial finishes as any other), so a trial the lab ran is never lost.
    ///
    /// # Errors
    ///
    /// As [`Self::command`].
    pub async fn run_trial(
        &self,
        trial_id: u64,
        setup: rt_core::bridge::TrialSetup,
    ) -> Result<(), CommandError> {
        self.send(Command::RunTrial { trial_id, setup }, Some(trial_id))
            .await?;
        self.trial_accepted.fetch_max(trial_id, Ordering::Relaxed);
        Ok(())
    }

    /// Whether the control loop accepted a trial that no published state has
    /// shown yet (the acknowledgement comes before the next state): it runs,
    /// though [`Lab::latest`] does not say so yet.
    pub fn trial_unshown(&self) -> bool {
        self.trial_accepted.load(Ordering::Relaxed) > self.trial_shown.load(Ordering::Relaxed)
    }

    async fn send(&self, command: Command, trial: Option<u64>) -> Result<(), CommandError> {
        let rx = {
            let mut pending = self.pending.lock().map_err(|_| CommandError::NotRunning)?;
            let mut tx = self.commands.lock().map_err(|_| CommandError::NotRunning)?;
            if tx.is_abandoned() {
                return Err(CommandError::NotRunning);
            }
            let id = tx.send(command).map_err(|_| CommandError::Full)?;
            let (ack_tx, ack_rx) = oneshot::channel();
            pending.insert(id, Waiter { tx: ack_tx, trial });
            (id, ack_rx)
        };
        let (id, rx) = rx;
        match tokio::time::timeout(self.options.ack_timeout, rx).await {
            Ok(Ok(outcome)) => outcome.map_err(CommandError::Refused),
            Ok(Err(_)) => Err(CommandError::NotRunning),
            Err(_) => {
                // A trial's waiter stays: its late answer settles the record.
                if trial.is_none()
                    && let Ok(mut p) = self.pending.lock()
                {
                    p.remove(&id);
                }
                Err(CommandError::NoAnswer)
            }
        }
    }
}

impl Pump {
    fn run(mut self) {
        let period = Duration::from_secs_f64(1.0 / self.lab.options.state_hz.clamp(1.0, 1000.0));
        let mut next = Instant::now();
        let mut events = Vec::with_capacity(64);
        // Runs until shut down, or until nobody but this thread holds the lab.
        while !self.lab.shutdown.load(Ordering::Acquire) && Arc::strong_count(&self.lab) > 1 {
            self.tick(&mut events);
            next += period;
            let now = Instant::now();
            if next > now {
                std::thread::sleep(next - now);
            } else {
                // Behind (e.g. the machine was busy): do not try to catch up in a burst.
                next = now;
            }
        }
        self.tick(&mut events);
        if let Some((id, n)) = self.recorder.finish() {
            tracing::info!(trial = id, samples = n, "recording closed at shutdown");
        }
        if let Some((id, path, _)) = self.fox.finish_recording(None) {
            tracing::info!(trial = id, path = %path.display(), "MCAP recording closed at shutdown");
        }
    }

    fn tick(&mut self, events: &mut Vec<EventRecord>) {
        self.dispatch_acks();
        // Events first, then all telemetry: every snapshot published before an
        // event was emitted is then in the ring, so a trial's recording is whole
        // before its end is processed.
        events.clear();
        while let Some(e) = self.end_events.pop() {
            events.push(e);
        }
        self.record_telemetry();
        for e in events.iter() {
            self.handle_event(e);
        }
        self.recorder.flush();
        self.forward_frames();
        self.publish_state();
    }

    fn dispatch_acks(&mut self) {
        while let Some(ack) = self.end_acks.pop() {
            // `ack.returned` (old parameters) is freed here, off the control thread.
            let waiter = self
                .lab
                .pending
                .lock()
                .ok()
                .and_then(|mut p| p.remove(&ack.id));
            let Some(Waiter { tx, trial }) = waiter else {
                continue;
            };
            if tx.send(ack.outcome).is_ok() {
                continue;
            }
            // Nobody waits any more (the request timed out): a trial the
            // control loop refused late never ran, so its record goes, as it
            // does for a refusal in time; an accepted one finishes by its events.
            if let (Some(id), Err(refusal), Some(records)) = (trial, ack.outcome, &self.records) {
                match records.delete_trial(id) {
                    Ok(()) => tracing::warn!(
                        trial = id,
                        reason = refusal.as_str(),
                        "a trial refused after its request timed out: record removed"
                    ),
                    Err(e) => {
                        tracing::error!(trial = id, error = ?e, "cannot remove a refused trial");
                    }
                }
            }
        }
    }

    fn record_telemetry(&mut self) {
        let mut tap = self.lab.joint_tap.lock().ok();
        while let Some(s) = self.end_telemetry.pop() {
            if s.fri.commanding_lost > self.commanding_lost {
                self.commanding_lost = s.fri.commanding_lost;
                tracing::warn!(
                    times = s.fri.commanding_lost,
                    session = ?s.fri.session,
                    quality = ?s.fri.quality,
                    late_replies = s.fri.late_replies,
                    silences = s.fri.silences,
                    "the robot's FRI session left commanding"
                );
            }
            if let Some(t) = tap.as_mut().and_then(|t| t.as_mut())
                && t.cut_s.is_none()
                && s.fri.commanding_lost > *t.lost_before.get_or_insert(s.fri.commanding_lost)
            {
                t.cut_s = Some(s.t_s);
            }
            if let Some(t) = tap.as_mut().and_then(|t| t.as_mut())
                && t.cut_s.is_none()
                && t.measured.len() < JOINT_TAP_MAX
                && s.counters.steps > t.last_step
                && let (Some(&c), Some(&m)) =
                    (s.robot.q_cmd_rad.get(t.joint), s.robot.q_rad.get(t.joint))
            {
                use rt_core::calibration::robot::JointSample;
                t.last_step = s.counters.steps;
                t.idle &= s.trial_state == rt_core::bridge::TrialState::Idle;
                t.commands.push(JointSample {
                    t_s: s.t_s,
                    q_rad: c,
                });
                t.measured.push(JointSample {
                    t_s: s.t_s,
                    q_rad: m,
                });
                t.tool_m.push(s.robot.tool_m);
                t.tau_ext_nm.push(s.robot.tau_ext_nm);
            }
            let Some(records) = &self.records else {
                continue;
            };
            if s.trial_id == 0 || self.ended == Some(s.trial_id) {
                continue;
            }
            let path = records.recording_path(s.trial_id);
            if let Err(e) = self.recorder.append(&path, s.trial_id, &s) {
                tracing::error!(trial = s.trial_id, error = %e, "cannot record");
            }
        }
    }

    fn handle_event(&mut self, e: &EventRecord) {
        let message = match e.event {
            Event::Aborted { reason, .. } => Some(reason.message()),
            _ => None,
        };
        let msg = EventMessage {
            kind: "event",
            record: e,
            message,
        };
        match serde_json::to_string(&msg) {
            Ok(text) => {
                let _ = self.lab.event_tx.send(text.into());
            }
            Err(err) => tracing::error!(error = %err, "cannot serialise an event"),
        }
        let end = match e.event {
            Event::TrialFinished { result } => TrialEnd::Done(result),
            Event::Aborted { reason, detail } => TrialEnd::Aborted(reason, detail),
            Event::StateChanged { .. } => return,
        };
        if e.trial_id == 0 {
            return;
        }
        let samples = match self.recorder.current() {
            Some(id) if id == e.trial_id => self.recorder.finish().map_or(0, |(_, n)| n),
            _ => 0,
        };
        self.ended = Some(e.trial_id);
        if self.fox.recording() == Some(e.trial_id) {
            self.fox.finish_recording(Some(&end));
        }
        // An abort is said in the service's log with its reason.
        let aborted = match end {
            TrialEnd::Aborted(kind, detail) => Some((kind.as_str(), detail)),
            TrialEnd::Done(_) => None,
        };
        if let Some(records) = &self.records {
            match records.finish_trial(e.trial_id, end, samples) {
                Ok(true) => {
                    if let Some((reason, detail)) = aborted {
                        tracing::warn!(
                            trial = e.trial_id,
                            samples,
                            reason,
                            detail,
                            "trial recorded: aborted"
                        );
                    } else {
                        tracing::info!(trial = e.trial_id, samples, "trial recorded");
                    }
                }
                Ok(false) => tracing::debug!(trial = e.trial_id, "trial end for no running trial"),
                Err(err) => {
                    tracing::error!(trial = e.trial_id, error = ?err, "cannot record the trial");
                }
            }
        }
    }

    fn forward_frames(&mut self) {
        let Some(frames) = self.frames.as_mut() else {
            return;
        };
        let mut newest = None;
        while let Some(f) = frames.pop() {
            newest = Some(f);
        }
        if let Some(f) = newest {
            self.lab.stream.frames.fetch_add(1, Ordering::Relaxed);
            self.fox.publish_frame(
                f.t_us as f64 * 1e-6,
                &f.jpeg,
                crate::viz::jpeg_width(&f.jpeg),
            );
            let tagged = crate::viz::jpeg_tagged(&f.jpeg, f.frame, f.t_us);
            let _ = self.lab.frame_tx.send(Bytes::from(tagged));
        }
    }

    /// Opens the MCAP recording of a trial at its first state tick.
    fn record_mcap(&mut self, s: &Snapshot) {
        let Some(records) = &self.records else {
            return;
        };
        let id = s.trial_id;
        if id == 0 || self.ended == Some(id) || self.fox.recording() == Some(id) {
            return;
        }
        let params = self.lab.params();
        self.fox.set_scenario(&params);
        let meta = crate::viz::RecordingContext {
            scenario: params.name.clone(),
            parameters_toml: toml::to_string(&params).unwrap_or_default(),
            revision: crate::VERSION.to_owned(),
            lab_mode: self.lab.options.lab_mode,
        };
        let path = records.mcap_path(id);
        if let Err(e) = self.fox.start_recording(id, &path, &meta) {
            tracing::error!(trial = id, error = %e, "cannot start the MCAP recording");
        }
    }

    fn publish_state(&mut self) {
        if !self.end_latest.updated() {
            return;
        }
        let snapshot = *self.end_latest.read();
        self.record_mcap(&snapshot);
        self.fox.publish_state(&snapshot);
        let msg = StateMessage {
            kind: "state",
            snapshot: &snapshot,
            bridge: self.lab.bridge_stats.read(),
            stream: self.lab.stream.read(),
        };
        let text: Utf8Bytes = match serde_json::to_string(&msg) {
            Ok(t) => t.into(),
            Err(err) => {
                tracing::error!(error = %err, "cannot serialise the state");
                return;
            }
        };
        self.lab
            .stream
            .state_messages
            .fetch_add(1, Ordering::Relaxed);
        self.lab
            .trial_shown
            .fetch_max(snapshot.trial_id, Ordering::Relaxed);
        if let Ok(mut l) = self.lab.latest.lock() {
            *l = Some((snapshot, text.clone()));
        }
        let _ = self.lab.state_tx.send(text);
    }
}

impl Drop for Lab {
    fn drop(&mut self) {
        self.shutdown.store(true, Ordering::Release);
    }
}
