//! The client side of an FRI session as a socket-free step function.
//!
//! [`FriClient::on_datagram`] takes one controller datagram and the time it was
//! received, calls the [`ControlStep`] once, and returns the reply datagram (or
//! none: in IDLE, between `receiveMultiplier` answers, or for a bad datagram).
//! [`FriClient::poll`] detects a silent controller. The real-time runtime
//! ([`super::session`]) and virtual-time drivers both use it.

use std::sync::Arc;
use std::sync::atomic::{AtomicU8, AtomicU32, AtomicU64, Ordering::Relaxed};

use serde::{Deserialize, Serialize};

use super::codec::{CodecError, CommandEncoder, Joints, Monitoring, MonitoringDecoder};
use super::framing::FrameError;
use super::guard::{CommandGuard, GuardOutcome, GuardParams};
use super::proto::{ConnectionQuality, SessionState};
use super::stats::{AtomicJoints, LatencyHistogram, LatencySummary};
use super::version::FriVersion;
use crate::check::{self, ParamError};

/// Most receive periods a command's step may cover in the guard (after lost
/// messages; the simulated controller's `missing_after_periods`).
const MAX_GUARD_PERIODS: u32 = 3;

/// Client settings, units in the names.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FriClientParams {
    /// The controller counts as silent after this many receive periods without a
    /// valid message (the safe reaction then follows at once).
    pub silence_periods: f64,
    /// A reply whose receive -> send time exceeds this fraction of the receive
    /// period is counted late.
    pub late_fraction: f64,
    /// The command guard.
    pub guard: GuardParams,
    /// Apply the guard (always `true` on a robot; `false` only to test the
    /// controller's own limit checks).
    pub guard_enabled: bool,
    /// The FRI version the controller speaks (`"1.15"` by default).
    pub version: FriVersion,
}

impl Default for FriClientParams {
    fn default() -> Self {
        Self {
            silence_periods: 2.0,
            late_fraction: 0.5,
            guard: GuardParams::default(),
            guard_enabled: true,
            version: FriVersion::default(),
        }
    }
}

impl FriClientParams {
    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first field
    /// (the guard's included) that is not finite or outside its range.
    pub fn validate(&self) -> Result<(), ParamError> {
        check::within("fri.silence_periods", self.silence_periods, 1.0, 100.0)?;
        check::within("fri.late_fraction", self.late_fraction, 0.01, 10.0)?;
        self.guard.validate()
    }
}

/// The client's view of the session: the controller's state, or no link.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LinkState {
    /// No valid controller message yet, or the controller went silent.
    Disconnected,
    /// The controller closed the session.
    Idle,
    /// MONITORING_WAIT.
    MonitoringWait,
    /// MONITORING_READY.
    MonitoringReady,
    /// COMMANDING_WAIT.
    CommandingWait,
    /// COMMANDING_ACTIVE.
    CommandingActive,
}

impl LinkState {
    fn from_session(s: SessionState) -> Self {
        match s {
            SessionState::Idle => Self::Idle,
            SessionState::MonitoringWait => Self::MonitoringWait,
            SessionState::MonitoringReady => Self::MonitoringReady,
            SessionState::CommandingWait => Self::CommandingWait,
            SessionState::CommandingActive => Self::CommandingActive,
        }
    }
    fn code(self) -> u8 {
        self as u8
    }
    fn from_code(c: u8) -> Self {
        match c {
            1 => Self::Idle,
            2 => Self::MonitoringWait,
            3 => Self::MonitoringReady,
            4 => Self::CommandingWait,
            5 => Self::CommandingActive,
            _ => Self::Disconnected,
        }
    }
}

/// Why the control must stop its motion.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum StopReason {
    /// The controller left COMMANDING_* (abort, quality drop) for this state.
    LeftCommanding(SessionState),
    /// No valid controller message for `silence_periods` receive periods.
    ControllerSilent,
    /// The controller sent IDLE: the session is closed.
    SessionClosed,
}

impl std::fmt::Display for StopReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::LeftCommanding(s) => {
                write!(f, "the FRI session left commanding for {}", s.name())
            }
            Self::ControllerSilent => f.write_str("the robot controller fell silent"),
            Self::SessionClosed => f.write_str("the robot controller closed the FRI session"),
        }
    }
}

/// What the control step sees, once per controller message.
#[derive(Debug, Clone, Copy)]
pub struct StepInput<'a> {
    /// When the message was received, ns on the driver's clock.
    pub now_ns: u64,
    /// The receive period (`sendPeriod * receiveMultiplier`), seconds.
    pub receive_period_s: f64,
    /// True when this message is answered with `command_rad` (COMMANDING_ACTIVE
    /// and a reply is due).
    pub commanding: bool,
    /// The decoded monitoring message.
    pub monitoring: &'a Monitoring,
}

/// The control step the session calls once per controller message (on the
/// session's real-time thread: no allocation, lock, log or blocking).
pub trait ControlStep {
    /// One step. `command_rad` holds the last command sent (so doing nothing
    /// holds position); in COMMANDING_ACTIVE the value left there is guarded and
    /// sent. In other states it is ignored.
    fn step(&mut self, input: &StepInput<'_>, command_rad: &mut Joints);

    /// The motion must stop (called once per event, on the same thread).
    fn stop(&mut self, reason: StopReason) {
        let _ = reason;
    }

    /// Called once after each controller datagram the client handled, when
    /// its reply (if it had one) has been sent: work that must not delay the
    /// reply (the lab's trial bookkeeping and snapshot). On the same thread,
    /// before the next datagram.
    fn after_reply(&mut self) {}

    /// No controller message came within a receive timeout (the session's
    /// thread calls it then, at least every few tens of milliseconds while
    /// there is no link; `now_ns` on the session's clock): time-driven work
    /// that must not wait for the next message (on the same thread).
    fn idle(&mut self, now_ns: u64) {
        let _ = now_ns;
    }
}

/// A control that holds the position the controller handed over.
#[derive(Debug, Clone, Copy, Default)]
pub struct HoldPosition;

impl ControlStep for HoldPosition {
    fn step(&mut self, _input: &StepInput<'_>, _command_rad: &mut Joints) {}
}

/// Counters and state of a client session, written by its thread and read by
/// anyone without locks.
#[derive(Debug, Default)]
pub struct SessionStats {
    state: AtomicU8,
    quality: AtomicU8,
    version: AtomicU8,
    receive_period_us: AtomicU32,
    /// Valid controller messages received.
    pub received: AtomicU64,
    /// Replies sent.
    pub replies: AtomicU64,
    /// Replies that carried a joint command (COMMANDING_ACTIVE).
    pub commands: AtomicU64,
    /// Datagrams refused by the decoder (garbage, truncated, wrong identifier,
    /// bad framing); none of them reaches the control step.
    pub decode_errors: AtomicU64,
    /// Of those, FRI 2.7 frames whose CRC-32 did not match.
    pub crc_errors: AtomicU64,
    /// Of those, FRI 2.7 frames whose length field did not match the datagram.
    pub frame_length_errors: AtomicU64,
    /// Datagrams from an address other than the configured controller.
    pub foreign_datagrams: AtomicU64,
    /// Replies whose receive -> send time exceeded `late_fraction` of the period.
    pub late_replies: AtomicU64,
    /// Controller messages never received (gaps in its sequence counter).
    pub missed_cycles: AtomicU64,
    /// Times the controller went silent (the safe reaction ran).
    pub silences: AtomicU64,
    /// Times the session left COMMANDING_* other than by IDLE (controller abort,
    /// quality drop).
    pub commanding_lost: AtomicU64,
    /// Times COMMANDING_ACTIVE was entered.
    pub commanding_entered: AtomicU64,
    /// IDLE messages received (session closed by the controller).
    pub closed: AtomicU64,
    /// Commands with a non-finite value (held instead).
    pub guard_non_finite: AtomicU64,
    /// Commands clamped into the position limits.
    pub guard_position: AtomicU64,
    /// Commands whose step was clamped to the velocity limit.
    pub guard_step: AtomicU64,
    /// Send errors of the socket.
    pub send_errors: AtomicU64,
    /// Time the session spent polling for expected datagrams without sleeping
    /// ([`crate::fri::priority::RtTuning::spin`]), ns.
    pub spin_ns: AtomicU64,
    /// Spins that ended without the datagram (the controller was late).
    pub spins_gave_up: AtomicU64,
    /// Receive -> reply sent, per reply.
    pub reply_latency: LatencyHistogram,
    /// Of that, the control step ([`ControlStep::step`]), wall clock, per
    /// controller message (by the runtime: the client has no clock).
    pub step_latency: LatencyHistogram,
    /// Of that, handing the reply to the kernel (`send_to`), per reply (by
    /// the runtime). On a CPU shared with a higher-priority receiver (the
    /// simulated controller) it includes the receiver's handling of it.
    pub send_latency: LatencyHistogram,
    /// |arrival interval - send period| between consecutive messages.
    pub arrival_jitter: LatencyHistogram,
    /// The controller's last `sequenceCounter`.
    pub last_controller_sequence: AtomicU32,
    /// The client's next `sequenceCounter`.
    pub next_client_sequence: AtomicU32,
    last_reply_latency_ns: AtomicU64,
    /// The last measured joint positions, rad.
    pub measured_rad: AtomicJoints,
    /// The last command sent, rad.
    pub commanded_rad: AtomicJoints,
}

/// A plain copy of [`SessionStats`] for display and JSON.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SessionStatus {
    /// The FRI version the client speaks (`"1.15"`).
    pub version: &'static str,
    /// Session state (or no link).
    pub state: LinkState,
    /// The controller's connection quality; `None` without a link.
    pub quality: Option<&'static str>,
    /// Receive period, ms (NaN before the first message).
    pub period_ms: f64,
    /// Valid controller messages received.
    pub received: u64,
    /// Replies sent.
    pub replies: u64,
    /// Replies carrying a joint command.
    pub commands: u64,
    /// Datagrams refused by the decoder.
    pub decode_errors: u64,
    /// FRI 2.7 frames refused for their CRC-32.
    pub crc_errors: u64,
    /// FRI 2.7 frames refused for their length field.
    pub frame_length_errors: u64,
    /// Late replies.
    pub late_replies: u64,
    /// Controller messages never received.
    pub missed_cycles: u64,
    /// Times the controller went silent.
    pub silences: u64,
    /// Times commanding ended other than by IDLE.
    pub commanding_lost: u64,
    /// Guard interventions: non-finite, position, step.
    pub guard_non_finite: u64,
    /// Commands clamped into the position limits.
    pub guard_position: u64,
    /// Commands clamped to the velocity limit.
    pub guard_step: u64,
    /// Receive -> reply latency of the last reply, us.
    pub reply_latency_us: f64,
    /// Receive -> reply latency percentiles, us.
    pub reply_latency: LatencySummary,
    /// Arrival jitter percentiles, us.
    pub arrival_jitter: LatencySummary,
}

impl SessionStats {
    /// The session state as the client sees it.
    pub fn state(&self) -> LinkState {
        LinkState::from_code(self.state.load(Relaxed))
    }

    /// The controller's quality, `None` without a link.
    pub fn quality(&self) -> Option<ConnectionQuality> {
        match self.state() {
            LinkState::Disconnected => None,
            _ => ConnectionQuality::try_from(i32::from(self.quality.load(Relaxed))).ok(),
        }
    }

    /// The FRI version the client speaks.
    pub fn version(&self) -> FriVersion {
        // 0: not set (the default version); else the index in `ALL` + 1.
        match usize::from(self.version.load(Relaxed)) {
            0 => FriVersion::default(),
            i => FriVersion::ALL.get(i - 1).copied().unwrap_or_default(),
        }
    }

    /// Records the receive -> reply time of one reply (by the runtime).
    pub fn record_reply_latency(&self, ns: u64, late_after_ns: u64) {
        self.reply_latency.record_ns(ns);
        self.last_reply_latency_ns.store(ns, Relaxed);
        if ns > late_after_ns {
            self.late_replies.fetch_add(1, Relaxed);
        }
    }

    /// A consistent-enough copy of every counter.
    pub fn snapshot(&self) -> SessionStatus {
        let l = |a: &AtomicU64| a.load(Relaxed);
        let p = self.receive_period_us.load(Relaxed);
        SessionStatus {
            version: self.version().name(),
            state: self.state(),
            quality: self.quality().map(ConnectionQuality::name),
            period_ms: if p == 0 { f64::NAN } else { f64::from(p) / 1e3 },
            received: l(&self.received),
            replies: l(&self.replies),
            commands: l(&self.commands),
            decode_errors: l(&self.decode_errors),
            crc_errors: l(&self.crc_errors),
            frame_length_errors: l(&self.frame_length_errors),
            late_replies: l(&self.late_replies),
            missed_cycles: l(&self.missed_cycles),
            silences: l(&self.silences),
            commanding_lost: l(&self.commanding_lost),
            guard_non_finite: l(&self.guard_non_finite),
            guard_position: l(&self.guard_position),
            guard_step: l(&self.guard_step),
            reply_latency_us: l(&self.last_reply_latency_ns) as f64 / 1e3,
            reply_latency: self.reply_latency.summary_us(),
            arrival_jitter: self.arrival_jitter.summary_us(),
        }
    }
}

/// The client's state machine (FRI.md, "Session states"), free of sockets and clocks.
#[derive(Debug)]
pub struct FriClient {
    params: FriClientParams,
    guard: CommandGuard,
    decoder: MonitoringDecoder,
    encoder: CommandEncoder,
    stats: Arc<SessionStats>,
    state: LinkState,
    sequence: u32,
    since_reply: u32,
    last_rx_ns: Option<u64>,
    last_controller_seq: Option<u32>,
    receive_period_ns: u64,
    send_period_ns: u64,
    last_command: Joints,
    have_command: bool,
    /// The controller's counter of the message the last command answered
    /// (`None` until a command in this commanding).
    last_command_ref: Option<u32>,
}

impl FriClient {
    /// A client; `params` are validated.
    ///
    /// # Errors
    ///
    /// The [`ParamError`] of [`FriClientParams::validate`] when `params` are invalid.
    pub fn new(params: FriClientParams) -> Result<Self, ParamError> {
        params.validate()?;
        let stats = SessionStats::default();
        let code = FriVersion::ALL
            .iter()
            .position(|v| *v == params.version)
            .unwrap_or(0);
        stats.version.store(code as u8 + 1, Relaxed);
        Ok(Self {
            guard: CommandGuard::new(&params.guard),
            decoder: MonitoringDecoder::with_version(params.version),
            encoder: CommandEncoder::with_version(params.version),
            params,
            stats: Arc::new(stats),
            state: LinkState::Disconnected,
            sequence: 0,
            since_reply: 0,
            last_rx_ns: None,
            last_controller_seq: None,
            receive_period_ns: 0,
            send_period_ns: 0,
            last_command: [0.0; 7],
            have_command: false,
            last_command_ref: None,
        })
    }

    /// The shared counters.
    pub fn stats(&self) -> &Arc<SessionStats> {
        &self.stats
    }

    /// The session state as the client sees it.
    pub fn state(&self) -> LinkState {
        self.state
    }

    /// Receive period, ns (0 before the first message).
    pub fn receive_period_ns(&self) -> u64 {
        self.receive_period_ns
    }

    /// The time by which the next controller message must arrive, or `None`
    /// while there is no link.
    pub fn deadline_ns(&self) -> Option<u64> {
        match (self.state, self.last_rx_ns) {
            (LinkState::Disconnected | LinkState::Idle, _) | (_, None) => None,
            (_, Some(t)) => {
                let p = self.receive_period_ns.max(1_000_000) as f64;
                Some(t + (self.params.silence_periods * p) as u64)
            }
        }
    }

    /// Late-reply threshold, ns.
    pub fn late_after_ns(&self) -> u64 {
        (self.params.late_fraction * self.receive_period_ns as f64) as u64
    }

    fn set_state(&mut self, s: LinkState) {
        self.state = s;
        self.stats.state.store(s.code(), Relaxed);
    }

    /// Checks for a silent controller at `now_ns`: past the deadline the link
    /// is declared lost, the control is told to stop, and `true` is returned.
    pub fn poll<C: ControlStep + ?Sized>(&mut self, now_ns: u64, control: &mut C) -> bool {
        match self.deadline_ns() {
            Some(d) if now_ns >= d => {
                self.stats.silences.fetch_add(1, Relaxed);
                self.set_state(LinkState::Disconnected);
                // The last command is kept: if the controller comes back still
                // commanding, the next command continues from it (the guard's
                // step limit then holds across the gap).
                self.since_reply = 0;
                control.stop(StopReason::ControllerSilent);
                true
            }
            _ => false,
        }
    }

    /// Handles one datagram received at `now_ns`; returns the reply to send.
    pub fn on_datagram<C: ControlStep + ?Sized>(
        &mut self,
        bytes: &[u8],
        now_ns: u64,
        control: &mut C,
    ) -> Option<&[u8]> {
        let m = match self.decoder.decode(bytes) {
            Ok(m) => m,
            Err(e) => {
                self.stats.decode_errors.fetch_add(1, Relaxed);
                match e {
                    CodecError::Frame(FrameError::Crc { .. }) => {
                        self.stats.crc_errors.fetch_add(1, Relaxed);
                    }
                    CodecError::Frame(FrameError::Length { .. }) => {
                        self.stats.frame_length_errors.fetch_add(1, Relaxed);
                    }
                    _ => {}
                }
                return None;
            }
        };
        self.on_monitoring(&m, now_ns, control)
    }

    fn on_monitoring<C: ControlStep + ?Sized>(
        &mut self,
        m: &Monitoring,
        now_ns: u64,
        control: &mut C,
    ) -> Option<&[u8]> {
        let st = &self.stats;
        st.received.fetch_add(1, Relaxed);
        // Cadence and loss.
        if let Some(prev) = self.last_controller_seq {
            let gap = m.sequence_counter.wrapping_sub(prev);
            if gap > 1 && gap < 1 << 20 {
                st.missed_cycles.fetch_add(u64::from(gap - 1), Relaxed);
            }
            if let Some(t) = self.last_rx_ns
                && (1..1 << 20).contains(&gap)
                && self.send_period_ns > 0
            {
                let expected = self.send_period_ns * u64::from(gap);
                st.arrival_jitter
                    .record_ns(now_ns.saturating_sub(t).abs_diff(expected));
            }
        }
        self.last_controller_seq = Some(m.sequence_counter);
        st.last_controller_sequence
            .store(m.sequence_counter, Relaxed);
        self.last_rx_ns = Some(now_ns);
        self.send_period_ns = u64::from(m.send_period_ms) * 1_000_000;
        let rp = self.send_period_ns * u64::from(m.receive_multiplier);
        if rp != self.receive_period_ns {
            self.receive_period_ns = rp;
            self.since_reply = 0;
            st.receive_period_us.store((rp / 1000) as u32, Relaxed);
        }
        st.quality.store(m.quality as u8, Relaxed);
        if let Some(q) = &m.measured_joint_position_rad {
            st.measured_rad.store(q);
        }

        let prev_state = self.state;
        let new_state = LinkState::from_session(m.session_state);
        let was_commanding = matches!(
            prev_state,
            LinkState::CommandingWait | LinkState::CommandingActive
        );
        let is_commanding = m.session_state.is_commanding();
        self.set_state(new_state);
        if was_commanding && !is_commanding {
            self.have_command = false;
            if m.session_state == SessionState::Idle {
                control.stop(StopReason::SessionClosed);
            } else {
                self.stats.commanding_lost.fetch_add(1, Relaxed);
                control.stop(StopReason::LeftCommanding(m.session_state));
            }
        }
        if m.session_state == SessionState::Idle {
            if prev_state != LinkState::Idle {
                self.stats.closed.fetch_add(1, Relaxed);
            }
            self.since_reply = 0;
            return None; // IDLE: the client sends nothing.
        }

        self.since_reply += 1;
        let reply_due = self.since_reply >= m.receive_multiplier;
        let period_s = self.receive_period_ns as f64 * 1e-9;

        // The hand-over position: what the controller's interpolator holds.
        // A non-finite one is not taken: the guard holds the previous command
        // when asked for NaN, so it must never start from one.
        let finite = |q: &Joints| q.iter().all(|v| v.is_finite());
        let handover = m
            .ipo_joint_position_rad
            .filter(finite)
            .or(m.commanded_joint_position_rad.filter(finite))
            .or(m.measured_joint_position_rad.filter(finite));
        let entering_active =
            new_state == LinkState::CommandingActive && prev_state != LinkState::CommandingActive;
        if entering_active {
            self.stats.commanding_entered.fetch_add(1, Relaxed);
        }
        if !self.have_command || new_state != LinkState::CommandingActive {
            if let Some(q) = handover {
                self.last_command = q;
                self.have_command = true;
            }
            self.last_command_ref = None;
        }

        let commanding = new_state == LinkState::CommandingActive && reply_due && self.have_command;
        let mut cmd = self.last_command;
        let input = StepInput {
            now_ns,
            receive_period_s: period_s,
            commanding,
            monitoring: m,
        };
        control.step(&input, &mut cmd);
        if !reply_due {
            return None;
        }
        self.since_reply = 0;

        let joints: Option<Joints> = match new_state {
            LinkState::CommandingActive if self.have_command => {
                if self.params.guard_enabled {
                    // The step may cover the receive periods since the
                    // message the last command answered (a lost message in
                    // between: two), as the controller's own check does, at
                    // most three.
                    let periods = self.last_command_ref.map_or(1, |last| {
                        (m.sequence_counter.wrapping_sub(last) / m.receive_multiplier.max(1))
                            .clamp(1, MAX_GUARD_PERIODS)
                    });
                    let g: GuardOutcome = self.guard.apply(
                        &mut cmd,
                        &self.last_command,
                        period_s * f64::from(periods),
                    );
                    if g.held_non_finite {
                        self.stats.guard_non_finite.fetch_add(1, Relaxed);
                    }
                    if g.clamped_position {
                        self.stats.guard_position.fetch_add(1, Relaxed);
                    }
                    if g.clamped_step {
                        self.stats.guard_step.fetch_add(1, Relaxed);
                    }
                }
                self.last_command = cmd;
                self.last_command_ref = Some(m.sequence_counter);
                self.stats.commands.fetch_add(1, Relaxed);
                Some(cmd)
            }
            // COMMANDING_WAIT: mirror the interpolator exactly.
            LinkState::CommandingWait => m.ipo_joint_position_rad,
            _ => None,
        };
        if let Some(q) = &joints {
            self.stats.commanded_rad.store(q);
        }
        let seq = self.sequence;
        if let Ok(bytes) = self
            .encoder
            .encode(seq, m.sequence_counter, joints.as_ref())
        {
            self.sequence = self.sequence.wrapping_add(1);
            self.stats
                .next_client_sequence
                .store(self.sequence, Relaxed);
            self.stats.replies.fetch_add(1, Relaxed);
            Some(bytes)
        } else {
            self.stats.send_errors.fetch_add(1, Relaxed);
            None
        }
    }
}
