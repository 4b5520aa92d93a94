#![doc = include_str!("README.md")]

mod model;
#[cfg(test)]
mod tests;

use std::sync::{
    Arc, OnceLock,
    atomic::{AtomicU64, Ordering},
};
use std::time::Instant;

pub use model::*;

/// Ring sizes of a [`bridge`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BridgeCapacity {
    /// Snapshots buffered for the recorder (at 1 kHz, 2048 is 2 s).
    pub telemetry: usize,
    /// Events buffered.
    pub events: usize,
    /// Commands waiting for the control thread.
    pub commands: usize,
    /// Acknowledgements waiting for the server.
    pub acks: usize,
}

impl Default for BridgeCapacity {
    fn default() -> Self {
        Self {
            telemetry: 2048,
            events: 256,
            commands: 32,
            acks: 32,
        }
    }
}

/// Counters shared by both ends; every hand-off that could not be made is counted
/// here, never waited on.
#[derive(Debug, Default)]
pub struct BridgeStats {
    /// Snapshots published by the control thread.
    pub published: AtomicU64,
    /// Snapshots the recorder lost because the telemetry ring was full.
    pub telemetry_overflows: AtomicU64,
    /// Events lost because the event ring was full.
    pub event_overflows: AtomicU64,
    /// Commands refused by the server end because the command ring was full.
    pub command_overflows: AtomicU64,
    /// Acknowledgements lost because the ack ring was full.
    pub ack_overflows: AtomicU64,
    /// Camera frames dropped because the frame ring was full.
    pub frame_overflows: AtomicU64,
    /// Emergency stops requested (see [`StopHandle`]).
    pub stop_requests: AtomicU64,
    /// Operator heartbeats received (see [`HeartbeatHandle`]).
    pub heartbeats: AtomicU64,
    /// The latest operator heartbeat, control clock, microseconds (`fetch_max`:
    /// any operator's heartbeat keeps the motion alive).
    pub heartbeat_us: AtomicU64,
    /// The control clock's epoch, set once by the control side when it starts.
    pub epoch: OnceLock<Instant>,
}

impl BridgeStats {
    /// A plain copy of the counters.
    pub fn read(&self) -> BridgeCounters {
        BridgeCounters {
            published: self.published.load(Ordering::Relaxed),
            telemetry_overflows: self.telemetry_overflows.load(Ordering::Relaxed),
            event_overflows: self.event_overflows.load(Ordering::Relaxed),
            command_overflows: self.command_overflows.load(Ordering::Relaxed),
            ack_overflows: self.ack_overflows.load(Ordering::Relaxed),
            frame_overflows: self.frame_overflows.load(Ordering::Relaxed),
            stop_requests: self.stop_requests.load(Ordering::Relaxed),
            heartbeats: self.heartbeats.load(Ordering::Relaxed),
        }
    }
}

/// A copy of [`BridgeStats`].
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, ts_rs::TS, utoipa::ToSchema,
)]
pub struct BridgeCounters {
    /// Snapshots published by the control thread.
    #[ts(type = "number")]
    pub published: u64,
    /// Snapshots the recorder lost (telemetry ring full).
    #[ts(type = "number")]
    pub telemetry_overflows: u64,
    /// Events lost (event ring full).
    #[ts(type = "number")]
    pub event_overflows: u64,
    /// Commands refused because the command ring was full.
    #[ts(type = "number")]
    pub command_overflows: u64,
    /// Acknowledgements lost (ack ring full).
    #[ts(type = "number")]
    pub ack_overflows: u64,
    /// Camera frames dropped (frame ring full).
    #[ts(type = "number")]
    pub frame_overflows: u64,
    /// Emergency stops requested.
    #[ts(type = "number")]
    pub stop_requests: u64,
    /// Operator heartbeats received.
    #[ts(type = "number")]
    pub heartbeats: u64,
}

fn bump(c: &AtomicU64) {
    c.fetch_add(1, Ordering::Relaxed);
}

/// Builds the two ends of a bridge. Allocates everything now; nothing on the
/// control side allocates afterwards.
pub fn bridge(capacity: BridgeCapacity) -> (ControlEnd, ServerEnd) {
    let stats = Arc::new(BridgeStats::default());
    let (latest_in, latest_out) = triple_buffer::TripleBuffer::new(&Snapshot::default()).split();
    let (telemetry_tx, telemetry_rx) = rtrb::RingBuffer::new(capacity.telemetry.max(1));
    let (event_tx, event_rx) = rtrb::RingBuffer::new(capacity.events.max(1));
    let (command_tx, command_rx) = rtrb::RingBuffer::new(capacity.commands.max(1));
    let (ack_tx, ack_rx) = rtrb::RingBuffer::new(capacity.acks.max(1));
    let control = ControlEnd {
        latest: latest_in,
        telemetry: telemetry_tx,
        events: event_tx,
        commands: command_rx,
        acks: ack_tx,
        stats: Arc::clone(&stats),
        stops_seen: 0,
    };
    let server = ServerEnd {
        latest: LatestReader { out: latest_out },
        telemetry: TelemetryReader { rx: telemetry_rx },
        events: EventReader { rx: event_rx },
        commands: CommandSender {
            tx: command_tx,
            next_id: 1,
            stats: Arc::clone(&stats),
        },
        acks: AckReader { rx: ack_rx },
        stop: StopHandle {
            stats: Arc::clone(&stats),
        },
        heartbeat: HeartbeatHandle {
            stats: Arc::clone(&stats),
        },
        stats,
    };
    (control, server)
}

/// The control thread's end. Every method is wait-free and allocation-free.
#[derive(Debug)]
pub struct ControlEnd {
    latest: triple_buffer::Input<Snapshot>,
    telemetry: rtrb::Producer<Snapshot>,
    events: rtrb::Producer<EventRecord>,
    commands: rtrb::Consumer<CommandEnvelope>,
    acks: rtrb::Producer<Ack>,
    stats: Arc<BridgeStats>,
    stops_seen: u64,
}

impl ControlEnd {
    /// True once for every emergency stop requested through a [`StopHandle`]
    /// since the last call (check it every step, before the command ring: a
    /// stop must not depend on a free slot in a ring).
    pub fn take_stop_request(&mut self) -> bool {
        let n = self.stats.stop_requests.load(Ordering::Acquire);
        let new = n != self.stops_seen;
        self.stops_seen = n;
        new
    }

    /// Publishes a snapshot: it becomes the latest value, and is queued for the
    /// recorder (counted as a telemetry overflow when the ring is full).
    pub fn publish(&mut self, snapshot: &Snapshot) {
        self.latest.write(*snapshot);
        bump(&self.stats.published);
        if self.telemetry.push(*snapshot).is_err() {
            bump(&self.stats.telemetry_overflows);
        }
    }

    /// Publishes a snapshot as the latest value only (not recorded).
    pub fn publish_latest(&mut self, snapshot: &Snapshot) {
        self.latest.write(*snapshot);
        bump(&self.stats.published);
    }

    /// Reports an event; returns false (and counts it) when the ring is full.
    pub fn emit(&mut self, event: EventRecord) -> bool {
        let ok = self.events.push(event).is_ok();
        if !ok {
            bump(&self.stats.event_overflows);
        }
        ok
    }

    /// The next command, if any (poll once per step).
    pub fn next_command(&mut self) -> Option<CommandEnvelope> {
        self.commands.pop().ok()
    }

    /// Answers a command. `returned` carries memory to be freed off this thread
    /// (the old parameters after [`Command::SetParams`], or the refused new ones).
    /// Returns false (and counts it) when the ack ring is full; the ack, and the
    /// memory it carries, is then dropped here, so size the ring above the
    /// command ring (the default does).
    pub fn ack(
        &mut self,
        id: u64,
        outcome: Result<(), Refusal>,
        returned: Option<Box<crate::params::Scenario>>,
    ) -> bool {
        let ok = self
            .acks
            .push(Ack {
                id,
                outcome,
                returned,
            })
            .is_ok();
        if !ok {
            bump(&self.stats.ack_overflows);
        }
        ok
    }

    /// The shared counters.
    pub fn stats(&self) -> &Arc<BridgeStats> {
        &self.stats
    }

    /// Sets the control clock's epoch (once, before the first step), so that
    /// operator heartbeats are stamped on the control clock.
    pub fn set_epoch(&self, epoch: Instant) {
        let _ = self.stats.epoch.set(epoch);
    }

    /// The latest operator heartbeat on the control clock, seconds (none yet: `None`).
    pub fn last_heartbeat_s(&self) -> Option<f64> {
        if self.stats.heartbeats.load(Ordering::Acquire) == 0 {
            return None;
        }
        Some(self.stats.heartbeat_us.load(Ordering::Acquire) as f64 * 1e-6)
    }
}

/// The server's end, in parts that can live in different places.
#[derive(Debug)]
pub struct ServerEnd {
    /// The latest snapshot.
    pub latest: LatestReader,
    /// Every published snapshot, for the recorder.
    pub telemetry: TelemetryReader,
    /// Events.
    pub events: EventReader,
    /// Commands to the control thread.
    pub commands: CommandSender,
    /// Answers to the commands.
    pub acks: AckReader,
    /// Emergency stop, independent of the command ring.
    pub stop: StopHandle,
    /// Operator heartbeats (the dead-man), independent of the command ring.
    pub heartbeat: HeartbeatHandle,
    /// The shared counters.
    pub stats: Arc<BridgeStats>,
}

/// Requests an emergency stop without going through the command ring (so a full
/// ring cannot delay it). Cloneable; any thread.
#[derive(Debug, Clone)]
pub struct StopHandle {
    stats: Arc<BridgeStats>,
}

impl StopHandle {
    /// Requests a stop; the control thread sees it at its next step.
    pub fn request_stop(&self) {
        self.stats.stop_requests.fetch_add(1, Ordering::Release);
    }
}

/// Records an operator heartbeat for the control thread's dead-man without
/// going through the command ring: two atomics. Cloneable; any thread.
#[derive(Debug, Clone)]
pub struct HeartbeatHandle {
    stats: Arc<BridgeStats>,
}

impl HeartbeatHandle {
    /// Records a heartbeat now; returns its time on the control clock, seconds
    /// (`None` while the control side has not started its clock).
    pub fn beat(&self) -> Option<f64> {
        let epoch = self.stats.epoch.get()?;
        let us = u64::try_from(epoch.elapsed().as_micros()).unwrap_or(u64::MAX);
        self.stats.heartbeat_us.fetch_max(us, Ordering::AcqRel);
        self.stats.heartbeats.fetch_add(1, Ordering::Release);
        Some(us as f64 * 1e-6)
    }
}

/// Reads the latest snapshot (one reader).
#[derive(Debug)]
pub struct LatestReader {
    out: triple_buffer::Output<Snapshot>,
}

impl LatestReader {
    /// The latest snapshot (the default one until the first publish).
    pub fn read(&mut self) -> &Snapshot {
        self.out.read()
    }

    /// True when a snapshot was published since the last [`read`](Self::read).
    pub fn updated(&self) -> bool {
        self.out.updated()
    }
}

/// Drains the telemetry ring.
#[derive(Debug)]
pub struct TelemetryReader {
    rx: rtrb::Consumer<Snapshot>,
}

impl TelemetryReader {
    /// The oldest queued snapshot.
    pub fn pop(&mut self) -> Option<Snapshot> {
        self.rx.pop().ok()
    }

    /// Snapshots waiting.
    pub fn len(&self) -> usize {
        self.rx.slots()
    }

    /// True when nothing waits.
    pub fn is_empty(&self) -> bool {
        self.rx.is_empty()
    }
}

/// Drains the event ring.
#[derive(Debug)]
pub struct EventReader {
    rx: rtrb::Consumer<EventRecord>,
}

impl EventReader {
    /// The oldest queued event.
    pub fn pop(&mut self) -> Option<EventRecord> {
        self.rx.pop().ok()
    }
}

/// Sends commands (one sender; wrap it in a lock to share it).
#[derive(Debug)]
pub struct CommandSender {
    tx: rtrb::Producer<CommandEnvelope>,
    next_id: u64,
    stats: Arc<BridgeStats>,
}

impl CommandSender {
    /// Queues a command and returns the id its [`Ack`] will carry; when the ring
    /// is full the command comes back (counted as a command overflow).
    ///
    /// # Errors
    ///
    /// Gives the command back as the `Err` value when the command ring is full
    /// (counted in the stats' command overflows).
    pub fn send(&mut self, command: Command) -> Result<u64, Command> {
        let id = self.next_id;
        match self.tx.push(CommandEnvelope { id, command }) {
            Ok(()) => {
                self.next_id += 1;
                Ok(id)
            }
            Err(rtrb::PushError::Full(env)) => {
                bump(&self.stats.command_overflows);
                Err(env.command)
            }
        }
    }

    /// True when the control end was dropped (nobody will answer).
    pub fn is_abandoned(&self) -> bool {
        self.tx.is_abandoned()
    }
}

/// Drains the acknowledgements.
#[derive(Debug)]
pub struct AckReader {
    rx: rtrb::Consumer<Ack>,
}

impl AckReader {
    /// The oldest queued acknowledgement.
    pub fn pop(&mut self) -> Option<Ack> {
        self.rx.pop().ok()
    }
}

/// A camera frame for the dashboard (from the vision thread, not the control thread).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    /// Its number: the `frame` of the vision measurement made from it (and of the
    /// state's camera detection), so the dashboard draws the overlay of this frame.
    pub frame: u64,
    /// Capture time, control clock, microseconds.
    pub t_us: u64,
    /// JPEG bytes.
    pub jpeg: Vec<u8>,
}

/// Builds a bounded frame channel; a full ring drops the new frame (counted in `stats`).
pub fn frame_channel(capacity: usize, stats: Arc<BridgeStats>) -> (FrameSender, FrameReceiver) {
    let (tx, rx) = rtrb::RingBuffer::new(capacity.max(1));
    (FrameSender { tx, stats }, FrameReceiver { rx })
}

/// The vision side of the frame channel.
#[derive(Debug)]
pub struct FrameSender {
    tx: rtrb::Producer<Frame>,
    stats: Arc<BridgeStats>,
}

impl FrameSender {
    /// Offers a frame; returns false (and counts it) when the ring is full.
    pub fn send(&mut self, frame: Frame) -> bool {
        let ok = self.tx.push(frame).is_ok();
        if !ok {
            bump(&self.stats.frame_overflows);
        }
        ok
    }
}

/// The server side of the frame channel.
#[derive(Debug)]
pub struct FrameReceiver {
    rx: rtrb::Consumer<Frame>,
}

impl FrameReceiver {
    /// The oldest queued frame.
    pub fn pop(&mut self) -> Option<Frame> {
        self.rx.pop().ok()
    }
}
