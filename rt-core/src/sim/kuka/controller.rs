//! The simulated KUKA controller (the stand-in for the Sunrise cabinet) as a
//! socket-free step function with explicit timestamps.
//!
//! [`SimController::tick`] produces the monitoring datagram due at a time;
//! [`SimController::on_reply`] takes a client datagram and its arrival time.
//! Both go through the real codec. [`super::simserver`] runs it over loopback
//! UDP on its own thread; a virtual-time driver calls the two from one thread.

use std::collections::VecDeque;
use std::fmt;
use std::sync::Arc;
use std::sync::atomic::{AtomicU8, AtomicU16, AtomicU64, Ordering::Relaxed};

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::check::{self, ParamError};
use crate::fri::codec::{CommandDecoder, Joints, Monitoring, MonitoringEncoder, UnixTime};
use crate::fri::proto::{
    ClientCommandMode, ConnectionQuality, ControlMode, DriveState, OperationMode, OverlayType,
    SafetyState, SessionState,
};
use crate::fri::stats::{AtomicF64, AtomicJoints, LatencyHistogram, LatencySummary};
use crate::kinematics::iiwa7::{JOINTS, POSITION_LIMIT_RAD, TORQUE_LIMIT_NM, VELOCITY_LIMIT_RADPS};
use crate::params::RobotParams;

/// Largest quality window, replies.
pub const MAX_QUALITY_WINDOW: usize = 1000;
/// Outstanding reply slots tracked (messages awaiting an answer).
const SLOTS: usize = 256;
/// Commands in flight between arrival and motion.
const PENDING_CAPACITY: usize = 1024;
/// Mixed into the world robot's seed for its network's random stream.
const NET_STREAM: u64 = 0x6e65_7477_6f72_6b00;
/// Servo stiffness of the torque model, N m / rad.
const SERVO_STIFFNESS_NM_PER_RAD: f64 = 2000.0;

/// The simulated robot and controller, units in the names.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FriSimParams {
    /// Controller send period, whole ms (1..100).
    pub fri_period_ms: u32,
    /// The client answers every n-th message (1..100).
    pub receive_multiplier: u32,
    /// Command-to-motion delay, ms: a command in time for its cycle reaches
    /// the servo this long after the cycle that sent the message it answers.
    pub latency_ms: f64,
    /// Uniform jitter of that delay, +/- ms: it decides only which controller
    /// cycle a command lands in (the nearest whole number of periods from its
    /// own; commands are never reordered), never the time within a cycle.
    pub latency_jitter_ms: f64,
    /// First-order servo lag of each joint towards its setpoint, ms (0: none).
    pub servo_time_constant_ms: f64,
    /// Joint positions at start, degrees.
    pub initial_joint_position_deg: [f64; JOINTS],
    /// Replies graded for the connection quality (sliding window, 10..1000).
    pub quality_window: u32,
    /// On-time replies needed before the quality can rise above FAIR.
    pub ready_after_replies: u32,
    /// A reply is late after this many send periods.
    pub late_after_periods: f64,
    /// A reply is missing after this many receive periods.
    pub missing_after_periods: f64,
    /// EXCELLENT up to this fraction of late or missing replies in the window.
    pub excellent_max_bad_fraction: f64,
    /// GOOD up to this fraction (commanding needs GOOD).
    pub good_max_bad_fraction: f64,
    /// FAIR up to this fraction; POOR above.
    pub fair_max_bad_fraction: f64,
    /// Time in COMMANDING_WAIT before COMMANDING_ACTIVE, ms.
    pub commanding_wait_ms: f64,
    /// A commanded step may be this multiple of `v_max * receive period`
    /// before commanding is aborted (the over-current trip).
    pub velocity_tolerance: f64,
    /// Injected: fraction of monitoring messages lost on the way out.
    pub packet_loss: f64,
    /// Injected: fraction of replies lost on the way in.
    pub reply_loss: f64,
    /// Injected: extra delay of every reply, ms.
    pub reply_delay_ms: f64,
    /// Injected: uniform jitter of that delay, 0..ms.
    pub reply_delay_jitter_ms: f64,
    /// Standard deviation-like uniform noise on measured positions, rad.
    pub measurement_noise_rad: f64,
    /// Seed of the random draws (jitter, loss, noise).
    pub seed: u64,
    /// The FRI version the controller speaks (`"1.15"` by default).
    pub fri_version: crate::fri::FriVersion,
}

impl Default for FriSimParams {
    fn default() -> Self {
        let r = RobotParams::default();
        Self {
            fri_period_ms: r.fri_period_ms,
            receive_multiplier: 1,
            latency_ms: r.latency_ms,
            latency_jitter_ms: r.latency_jitter_ms,
            servo_time_constant_ms: 5.0,
            initial_joint_position_deg: [0.0, 30.0, 0.0, -80.0, 0.0, 60.0, 0.0],
            quality_window: 100,
            ready_after_replies: 20,
            late_after_periods: 1.0,
            missing_after_periods: 3.0,
            excellent_max_bad_fraction: 0.02,
            good_max_bad_fraction: 0.15,
            fair_max_bad_fraction: 0.40,
            commanding_wait_ms: 20.0,
            velocity_tolerance: 1.0,
            packet_loss: 0.0,
            reply_loss: 0.0,
            reply_delay_ms: 0.0,
            reply_delay_jitter_ms: 0.0,
            measurement_noise_rad: 0.0,
            seed: 1,
            fri_version: crate::fri::FriVersion::default(),
        }
    }
}

impl FriSimParams {
    /// Defaults with the scenario's `[robot]` section.
    pub fn from_robot(r: &RobotParams) -> Self {
        Self {
            fri_period_ms: r.fri_period_ms,
            latency_ms: r.latency_ms,
            latency_jitter_ms: r.latency_jitter_ms,
            ..Self::default()
        }
    }

    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first field
    /// that is not finite, outside its range or inconsistent with another.
    pub fn validate(&self) -> Result<(), ParamError> {
        check::within_u32("fri_sim.fri_period_ms", self.fri_period_ms, 1, 100)?;
        check::within_u32(
            "fri_sim.receive_multiplier",
            self.receive_multiplier,
            1,
            100,
        )?;
        check::within_u32(
            "fri_sim.receive_multiplier",
            self.receive_multiplier * self.fri_period_ms,
            1,
            100,
        )
        .map_err(|_| {
            check::out_of_range(
                "fri_sim.receive_multiplier",
                f64::from(self.receive_multiplier),
                check::Bound::rule("receive_multiplier * fri_period_ms must be <= 100 ms"),
            )
        })?;
        check::within("fri_sim.latency_ms", self.latency_ms, 0.0, 200.0)?;
        check::within(
            "fri_sim.latency_jitter_ms",
            self.latency_jitter_ms,
            0.0,
            50.0,
        )?;
        if self.latency_jitter_ms > self.latency_ms {
            return Err(check::out_of_range(
                "fri_sim.latency_jitter_ms",
                self.latency_jitter_ms,
                check::Bound::rule("must not exceed fri_sim.latency_ms"),
            ));
        }
        check::within(
            "fri_sim.servo_time_constant_ms",
            self.servo_time_constant_ms,
            0.0,
            500.0,
        )?;
        for (i, d) in self.initial_joint_position_deg.iter().enumerate() {
            let lim = POSITION_LIMIT_RAD[i].to_degrees();
            check::within(
                &format!("fri_sim.initial_joint_position_deg[{i}]"),
                *d,
                -lim,
                lim,
            )?;
        }
        check::within_u32(
            "fri_sim.quality_window",
            self.quality_window,
            10,
            MAX_QUALITY_WINDOW as u32,
        )?;
        check::within_u32(
            "fri_sim.ready_after_replies",
            self.ready_after_replies,
            1,
            10_000,
        )?;
        check::within(
            "fri_sim.late_after_periods",
            self.late_after_periods,
            0.1,
            10.0,
        )?;
        check::within(
            "fri_sim.missing_after_periods",
            self.missing_after_periods,
            1.0,
            20.0,
        )?;
        check::within(
            "fri_sim.excellent_max_bad_fraction",
            self.excellent_max_bad_fraction,
            0.0,
            1.0,
        )?;
        check::within(
            "fri_sim.good_max_bad_fraction",
            self.good_max_bad_fraction,
            self.excellent_max_bad_fraction,
            1.0,
        )?;
        check::within(
            "fri_sim.fair_max_bad_fraction",
            self.fair_max_bad_fraction,
            self.good_max_bad_fraction,
            1.0,
        )?;
        check::within(
            "fri_sim.commanding_wait_ms",
            self.commanding_wait_ms,
            0.0,
            10_000.0,
        )?;
        check::within(
            "fri_sim.velocity_tolerance",
            self.velocity_tolerance,
            0.5,
            10.0,
        )?;
        check::probability("fri_sim.packet_loss", self.packet_loss)?;
        check::probability("fri_sim.reply_loss", self.reply_loss)?;
        check::within("fri_sim.reply_delay_ms", self.reply_delay_ms, 0.0, 1000.0)?;
        check::within(
            "fri_sim.reply_delay_jitter_ms",
            self.reply_delay_jitter_ms,
            0.0,
            1000.0,
        )?;
        check::within(
            "fri_sim.measurement_noise_rad",
            self.measurement_noise_rad,
            0.0,
            0.1,
        )
    }

    /// Send period, ns.
    pub fn period_ns(&self) -> u64 {
        u64::from(self.fri_period_ms) * 1_000_000
    }
}

/// Why the simulated controller ended commanding (its own safety stop, not a
/// trial's [`crate::control::AbortReason`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
#[non_exhaustive]
pub enum CommandingAbort {
    /// A commanded step beyond the joint's velocity limit (the over-current trip).
    VelocityLimit {
        /// Joint index 0..6 (A1..A7).
        joint: usize,
        /// The commanded step, rad.
        step_rad: f64,
        /// The largest allowed step, rad.
        max_step_rad: f64,
    },
    /// A commanded position beyond the joint's limit.
    PositionLimit {
        /// Joint index.
        joint: usize,
        /// The commanded position, rad.
        position_rad: f64,
        /// The limit, rad (symmetric).
        limit_rad: f64,
    },
    /// A NaN or infinite commanded value.
    NotFinite {
        /// Joint index.
        joint: usize,
    },
    /// The connection quality fell below GOOD while commanding.
    QualityDropped {
        /// The quality it fell to.
        quality: ConnectionQuality,
    },
    /// A joint needed more torque than its limit (the reality lab's rigid-body
    /// dynamics, `sim::world`): the over-current trip.
    TorqueLimit(crate::sim::world::TorqueTrip),
    /// The robot application ended commanding (its FRI motion ended, or an
    /// operator stopped it): not the client's doing.
    Application,
}

impl CommandingAbort {
    /// True for a joint limit violation (not a quality drop or the
    /// application's own end).
    pub const fn is_violation(&self) -> bool {
        !matches!(self, Self::QualityDropped { .. } | Self::Application)
    }
}

impl fmt::Display for CommandingAbort {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::VelocityLimit {
                joint,
                step_rad,
                max_step_rad,
            } => write!(
                f,
                "A{} commanded step {step_rad:.5} rad exceeds the velocity limit ({max_step_rad:.5} rad per period)",
                joint + 1
            ),
            Self::PositionLimit {
                joint,
                position_rad,
                limit_rad,
            } => write!(
                f,
                "A{} commanded to {position_rad:.4} rad, beyond its limit of +/-{limit_rad:.4} rad",
                joint + 1
            ),
            Self::NotFinite { joint } => write!(f, "A{} commanded a non-finite value", joint + 1),
            Self::QualityDropped { quality } => {
                write!(f, "connection quality fell to {}", quality.name())
            }
            Self::TorqueLimit(trip) => write!(f, "{trip}"),
            Self::Application => write!(f, "the robot application ended commanding"),
        }
    }
}

/// Counters and state of the simulated controller, read without locks.
#[derive(Debug, Default)]
pub struct SimStats {
    state: AtomicU8,
    quality: AtomicU8,
    states_reached: AtomicU8,
    /// The states in the order first reached, 3 bits each (state + 1).
    states_order: AtomicU16,
    /// Monitoring messages produced (including injected losses and IDLE).
    pub messages_sent: AtomicU64,
    /// Monitoring messages dropped by injection.
    pub messages_dropped: AtomicU64,
    /// Valid replies received (after injected reply loss).
    pub replies: AtomicU64,
    /// Replies dropped by injection.
    pub replies_dropped: AtomicU64,
    /// Replies later than `late_after_periods`.
    pub late_replies: AtomicU64,
    /// Expected replies that never came within `missing_after_periods`.
    pub missing_replies: AtomicU64,
    /// Replies to messages already graded missing, or to unknown counters.
    pub stale_replies: AtomicU64,
    /// Datagrams refused by the decoder.
    pub decode_errors: AtomicU64,
    /// Client sequence counters that did not rise by exactly 1.
    pub client_sequence_errors: AtomicU64,
    /// Commanding aborts for a joint limit violation.
    pub violations: AtomicU64,
    /// Commanding aborts of any kind.
    pub aborts: AtomicU64,
    /// Times COMMANDING_ACTIVE was entered.
    pub commanding_entered: AtomicU64,
    /// Commands accepted in COMMANDING_ACTIVE.
    pub commands_accepted: AtomicU64,
    /// Commands that reached the joints (after the latency).
    pub commands_applied: AtomicU64,
    /// Commands that landed one or more cycles after their own (a reply
    /// after its cycle's deadline, or the latency's jitter).
    pub late_commands: AtomicU64,
    /// Commands replaced by a newer one in the same cycle before they reached
    /// the joints.
    pub superseded_commands: AtomicU64,
    /// Receive periods in COMMANDING_ACTIVE in which no new command reached
    /// the servo (a late or missing one): the previous setpoint was held.
    pub held_cycles: AtomicU64,
    /// COMMANDING_WAIT replies that did not mirror the ipo position exactly.
    pub mirror_mismatches: AtomicU64,
    /// COMMANDING_ACTIVE replies without joint positions.
    pub empty_commands: AtomicU64,
    /// Commands dropped because too many were in flight.
    pub pending_overflow: AtomicU64,
    /// Send slots the real-time runner was late for by more than a period.
    pub overruns: AtomicU64,
    /// Datagrams from an address other than the client's.
    pub foreign_datagrams: AtomicU64,
    /// Send -> reply arrival.
    pub rtt: LatencyHistogram,
    /// True joint positions, rad.
    pub joint_rad: AtomicJoints,
    /// The setpoint the joints follow, rad.
    pub setpoint_rad: AtomicJoints,
    abort_code: AtomicU8,
    abort_joint: AtomicU8,
    abort_a: AtomicF64,
    abort_b: AtomicF64,
}

const ALL_STATES: [SessionState; 5] = [
    SessionState::Idle,
    SessionState::MonitoringWait,
    SessionState::MonitoringReady,
    SessionState::CommandingWait,
    SessionState::CommandingActive,
];

impl SimStats {
    /// The controller's session state.
    pub fn state(&self) -> SessionState {
        SessionState::try_from(i32::from(self.state.load(Relaxed))).unwrap_or(SessionState::Idle)
    }

    /// The controller's current grade of the connection.
    pub fn quality(&self) -> ConnectionQuality {
        ConnectionQuality::try_from(i32::from(self.quality.load(Relaxed)))
            .unwrap_or(ConnectionQuality::Poor)
    }

    /// True once the session has been in `s`.
    pub fn reached(&self, s: SessionState) -> bool {
        self.states_reached.load(Relaxed) & (1 << s as u8) != 0
    }

    /// The states reached, in the order first reached (e.g. MONITORING_WAIT,
    /// ..., COMMANDING_ACTIVE, IDLE).
    pub fn states_reached(&self) -> Vec<&'static str> {
        let order = self.states_order.load(Relaxed);
        (0..ALL_STATES.len())
            .map(|k| usize::from((order >> (3 * k)) & 7))
            .take_while(|code| *code != 0)
            .filter_map(|code| ALL_STATES.get(code - 1).map(|s| s.name()))
            .collect()
    }

    /// Marks `s` reached (by the controller's thread, the only writer).
    fn mark_reached(&self, s: SessionState) {
        let bit = 1u8 << s as u8;
        let before = self.states_reached.fetch_or(bit, Relaxed);
        if before & bit == 0 {
            let k = before.count_ones();
            let order = self.states_order.load(Relaxed) | ((s as u16 + 1) << (3 * k));
            self.states_order.store(order, Relaxed);
        }
    }

    /// The last abort, if any.
    pub fn last_abort(&self) -> Option<CommandingAbort> {
        let joint = usize::from(self.abort_joint.load(Relaxed));
        let (a, b) = (self.abort_a.load(), self.abort_b.load());
        match self.abort_code.load(Relaxed) {
            1 => Some(CommandingAbort::VelocityLimit {
                joint,
                step_rad: a,
                max_step_rad: b,
            }),
            2 => Some(CommandingAbort::PositionLimit {
                joint,
                position_rad: a,
                limit_rad: b,
            }),
            3 => Some(CommandingAbort::NotFinite { joint }),
            4 => Some(CommandingAbort::QualityDropped {
                quality: ConnectionQuality::try_from(a as i32).unwrap_or(ConnectionQuality::Poor),
            }),
            5 => Some(CommandingAbort::TorqueLimit(
                crate::sim::world::TorqueTrip {
                    joint,
                    name: crate::kinematics::iiwa7::JOINT_NAMES
                        .get(joint)
                        .copied()
                        .unwrap_or("A?"),
                    torque_nm: a,
                    limit_nm: b,
                },
            )),
            6 => Some(CommandingAbort::Application),
            _ => None,
        }
    }

    fn set_abort(&self, r: &CommandingAbort) {
        let (code, joint, a, b) = match *r {
            CommandingAbort::VelocityLimit {
                joint,
                step_rad,
                max_step_rad,
            } => (1, joint, step_rad, max_step_rad),
            CommandingAbort::PositionLimit {
                joint,
                position_rad,
                limit_rad,
            } => (2, joint, position_rad, limit_rad),
            CommandingAbort::NotFinite { joint } => (3, joint, f64::NAN, f64::NAN),
            CommandingAbort::QualityDropped { quality } => (4, 0, f64::from(quality as i32), 0.0),
            CommandingAbort::TorqueLimit(t) => (5, t.joint, t.torque_nm, t.limit_nm),
            CommandingAbort::Application => (6, 0, 0.0, 0.0),
        };
        self.abort_joint.store(joint as u8, Relaxed);
        self.abort_a.store(a);
        self.abort_b.store(b);
        self.abort_code.store(code, Relaxed);
    }

    /// A plain summary (the `isochron fri-sim --json` object).
    pub fn report(&self) -> SimReport {
        let l = |a: &AtomicU64| a.load(Relaxed);
        let rtt = self.rtt.summary_us();
        SimReport {
            messages_sent: l(&self.messages_sent),
            replies: l(&self.replies),
            late_replies: l(&self.late_replies),
            missing_replies: l(&self.missing_replies),
            states_reached: self.states_reached(),
            violations: l(&self.violations),
            rtt_us: rtt,
            messages_dropped: l(&self.messages_dropped),
            replies_dropped: l(&self.replies_dropped),
            stale_replies: l(&self.stale_replies),
            decode_errors: l(&self.decode_errors),
            client_sequence_errors: l(&self.client_sequence_errors),
            aborts: l(&self.aborts),
            abort_reason: self.last_abort().map(|r| r.to_string()),
            commands_accepted: l(&self.commands_accepted),
            commands_applied: l(&self.commands_applied),
            late_commands: l(&self.late_commands),
            held_cycles: l(&self.held_cycles),
            mirror_mismatches: l(&self.mirror_mismatches),
            overruns: l(&self.overruns),
            final_state: self.state().name(),
            quality: self.quality().name(),
            joint_rad: self.joint_rad.load(),
        }
    }
}

/// The simulated controller's summary.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SimReport {
    /// Monitoring messages produced.
    pub messages_sent: u64,
    /// Valid replies received.
    pub replies: u64,
    /// Late replies.
    pub late_replies: u64,
    /// Missing replies.
    pub missing_replies: u64,
    /// States reached, FRI names.
    pub states_reached: Vec<&'static str>,
    /// Commanding aborts for a limit violation.
    pub violations: u64,
    /// Send -> reply round trip, us.
    pub rtt_us: LatencySummary,
    /// Monitoring messages dropped by injection.
    pub messages_dropped: u64,
    /// Replies dropped by injection.
    pub replies_dropped: u64,
    /// Replies to already-missing or unknown messages.
    pub stale_replies: u64,
    /// Datagrams refused by the decoder.
    pub decode_errors: u64,
    /// Client counters that did not rise by 1.
    pub client_sequence_errors: u64,
    /// Commanding aborts of any kind.
    pub aborts: u64,
    /// Why commanding was last aborted.
    pub abort_reason: Option<String>,
    /// Commands accepted.
    pub commands_accepted: u64,
    /// Commands that reached the joints.
    pub commands_applied: u64,
    /// Commands that landed one or more cycles after their own.
    pub late_commands: u64,
    /// Receive periods in COMMANDING_ACTIVE with no new command (held).
    pub held_cycles: u64,
    /// COMMANDING_WAIT replies that did not mirror the ipo position.
    pub mirror_mismatches: u64,
    /// Late send slots of the real-time runner.
    pub overruns: u64,
    /// Session state at the end.
    pub final_state: &'static str,
    /// Connection quality at the end.
    pub quality: &'static str,
    /// Joint positions at the end, rad.
    pub joint_rad: Joints,
}

#[derive(Debug, Clone, Copy, Default)]
struct Slot {
    seq: u32,
    sent_ns: u64,
    open: bool,
}

/// The simulated controller.
#[derive(Debug)]
pub struct SimController {
    p: FriSimParams,
    stats: Arc<SimStats>,
    rng: ChaCha8Rng,
    enc: MonitoringEncoder,
    dec: CommandDecoder,
    epoch_unix_ns: u64,
    state: SessionState,
    quality: ConnectionQuality,
    seq: u32,
    produced: u64,
    reflected: u32,
    last_client_seq: Option<u32>,
    slots: [Slot; SLOTS],
    /// Send time and controller cycle time of every message, by
    /// `seq % SLOTS` (the round trip of an answer, the cycle its command
    /// belongs to).
    sent: [(u32, u64, u64); SLOTS],
    /// The controller's own cycle time of the last message (its clock: one
    /// period per tick, re-synchronised when a tick is off by a period).
    cycle_ns: Option<u64>,
    window: [bool; MAX_QUALITY_WINDOW],
    window_len: usize,
    window_at: usize,
    window_bad: usize,
    on_time: u64,
    q: Joints,
    setpoint: Joints,
    ipo: Joints,
    last_cmd: Joints,
    /// The message the last accepted command answered (its reflected
    /// counter; `None` at a commanding's start).
    last_cmd_ref: Option<u32>,
    pending: VecDeque<(u64, Joints)>,
    last_apply_ns: u64,
    /// When the last command reached the servo in this commanding (held
    /// cycles are the gaps).
    last_applied_due_ns: Option<u64>,
    t_ns: Option<u64>,
    wait_since_ns: u64,
    commanding_requested: bool,
    close_requested: bool,
    closed: bool,
    world: Option<WorldRobot>,
}

/// The reality lab's robot plugged into the simulated controller
/// (`sim::world`): the session's latency model replaces `latency_ms` and its
/// jitter, the world's joints (second-order servos, dynamics and torque trip,
/// measurement noise) replace the first-order lag.
#[derive(Debug, Clone)]
pub struct WorldRobot {
    /// Command-to-motion latency over time.
    pub latency: crate::sim::world::LatencyModel,
    /// The true joints.
    pub joints: crate::sim::world::WorldJoints,
    /// The latest contacts of ball and tool (their force pulses).
    contacts: [Option<crate::sim::world::Contact>; 4],
    /// How late the external torque estimate shows a contact's force, s.
    torque_lag_s: f64,
    /// When the previous monitoring message left, ns (the period the
    /// external torques average over).
    last_tick_ns: Option<u64>,
    /// The external torques' sensing noise.
    torque_rng: ChaCha8Rng,
    /// The network between the cabinet and the PC, and the command jitter.
    net: NetworkModel,
    /// Its own random stream (losses, delays, jitter).
    net_rng: ChaCha8Rng,
    /// The measured joints of the last messages (`t_ns`, joints), for a
    /// message that reaches the PC late: it carries what was measured then.
    history: [(u64, Joints); HISTORY],
    history_at: usize,
    /// Robot time of the last message's contents (kept rising).
    last_message_ns: Option<u64>,
}

/// Messages of joint history kept for the message latency (at 1 ms, 32 ms).
const HISTORY: usize = 32;

/// The reality lab's network between the cabinet and the PC (`[world.robot]`):
/// datagram losses each way, the one-way latency and its jitter, and the
/// per-command jitter of the command-to-motion latency. Zero: the truthful
/// loopback.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct NetworkModel {
    /// Fraction of monitoring datagrams lost.
    pub packet_loss: f64,
    /// Fraction of command datagrams lost.
    pub reply_loss: f64,
    /// Per-command latency jitter bound (either sign), s.
    pub command_jitter_s: f64,
    /// One-way datagram latency, s.
    pub latency_s: f64,
    /// One-way extra delay bound (uniform from 0), s.
    pub jitter_s: f64,
}

impl NetworkModel {
    /// The session's network.
    pub fn from_session(d: &crate::sim::world::SessionDraw) -> Self {
        Self {
            packet_loss: d.packet_loss,
            reply_loss: d.reply_loss,
            command_jitter_s: d.command_jitter_s,
            latency_s: d.message_latency_s,
            jitter_s: d.message_jitter_s,
        }
    }

    /// One datagram's one-way delay, ns.
    fn delay_ns(&self, rng: &mut ChaCha8Rng) -> u64 {
        let j = if self.jitter_s > 0.0 {
            rng.random_range(0.0..=self.jitter_s)
        } else {
            0.0
        };
        ((self.latency_s + j).max(0.0) * 1e9) as u64
    }
}

impl WorldRobot {
    /// The reality lab's robot: `latency`, `joints`, the external torques'
    /// noise drawn from `seed`, and their lag behind a contact's force
    /// (`torque_lag_s`: the session's `world.robot.torque_lag_periods` FRI periods).
    pub fn new(
        latency: crate::sim::world::LatencyModel,
        joints: crate::sim::world::WorldJoints,
        seed: u64,
        torque_lag_s: f64,
    ) -> Self {
        let q0 = *joints.q();
        Self {
            latency,
            joints,
            contacts: [None; 4],
            torque_lag_s,
            last_tick_ns: None,
            torque_rng: ChaCha8Rng::seed_from_u64(seed),
            net: NetworkModel::default(),
            net_rng: ChaCha8Rng::seed_from_u64(seed ^ NET_STREAM),
            history: [(0, q0); HISTORY],
            history_at: 0,
            last_message_ns: None,
        }
    }

    /// The session's robot of a reality lab: its latency model from `t0_s`,
    /// its joints from `q0` (`first_order_tau_s`: the truthful lag when the
    /// world draws no servo; interpolation over `period_s`), its network,
    /// saturation, contact push and torque trip as `[world.robot]` says;
    /// `seeds`: the joints' noise and the sensing's (external torques, network).
    pub fn for_session(
        world: &crate::sim::world::WorldParams,
        session: &crate::sim::world::SessionDraw,
        q0: Joints,
        first_order_tau_s: f64,
        period_s: f64,
        t0_s: f64,
        seeds: [u64; 2],
    ) -> Self {
        let r = &world.robot;
        let mut joints = crate::sim::world::WorldJoints::new(
            q0,
            session,
            first_order_tau_s,
            r.torque_limit_scale,
            r.torque_trip,
            r.position_noise_rad,
            seeds[0],
        );
        joints.set_interpolation_s(period_s);
        joints.set_saturation(r.velocity_limit_scale, r.acceleration_limit_scale);
        joints.set_contact_push(r.contact_push);
        let mut w = Self::new(
            crate::sim::world::LatencyModel::from_session(session, t0_s),
            joints,
            seeds[1],
            session.torque_lag_periods * period_s,
        );
        w.net = NetworkModel::from_session(session);
        w
    }

    /// The network model.
    pub fn network(&self) -> &NetworkModel {
        &self.net
    }

    /// Replaces the network model.
    pub fn set_network(&mut self, net: NetworkModel) {
        self.net = net;
    }

    /// The robot time whose measurement a message leaving at `now_ns`
    /// carries when it reaches the PC one latency later (kept rising), and
    /// those joints, interpolated in the history (`measured` is now's).
    fn delayed(&mut self, now_ns: u64, measured: Joints) -> (u64, Joints) {
        self.history_at = (self.history_at + 1) % HISTORY;
        self.history[self.history_at] = (now_ns, measured);
        let d = self.net.delay_ns(&mut self.net_rng);
        if d == 0 {
            self.last_message_ns = Some(now_ns);
            return (now_ns, measured);
        }
        let t = now_ns
            .saturating_sub(d)
            .max(self.last_message_ns.map_or(0, |p| p + 1))
            .min(now_ns);
        self.last_message_ns = Some(t);
        // Newest first: the two samples around `t`.
        let mut newer = self.history[self.history_at];
        for k in 1..HISTORY {
            let older = self.history[(self.history_at + HISTORY - k) % HISTORY];
            if older.0 >= newer.0 {
                // Past the oldest sample kept.
                break;
            }
            if older.0 <= t {
                let f = (t - older.0) as f64 / (newer.0 - older.0) as f64;
                let q = std::array::from_fn(|i| older.1[i] + (newer.1[i] - older.1[i]) * f);
                return (t, q);
            }
            newer = older;
        }
        (t, newer.1)
    }

    /// The external joint torques of the message leaving at `now_ns` for
    /// joint angles `q` (`sim::world::contact`).
    fn external_torques(&mut self, q: &Joints, now_ns: u64) -> Joints {
        let b = now_ns as f64 * 1e-9;
        let a = self.last_tick_ns.map_or(b, |t| t as f64 * 1e-9);
        self.last_tick_ns = Some(now_ns);
        let lag = self.torque_lag_s;
        let tau = crate::sim::world::contact::external_torques(
            q,
            &self.contacts,
            a - lag,
            b - lag,
            &mut self.torque_rng,
        );
        for c in &mut self.contacts {
            if c.is_some_and(|c| c.over_by(b - lag)) {
                *c = None;
            }
        }
        tau
    }
}

impl SimController {
    /// A controller in MONITORING_WAIT (quality FAIR) with the joints at rest;
    /// `epoch_unix_ns` is the Unix time of time 0 (for the message timestamps).
    ///
    /// # Errors
    ///
    /// The error of [`FriSimParams::validate`] when `params` are invalid.
    pub fn new(params: FriSimParams, epoch_unix_ns: u64) -> Result<Self, ParamError> {
        params.validate()?;
        let q: Joints = std::array::from_fn(|i| params.initial_joint_position_deg[i].to_radians());
        let stats = Arc::new(SimStats::default());
        stats.joint_rad.store(&q);
        stats.setpoint_rad.store(&q);
        let mut s = Self {
            rng: ChaCha8Rng::seed_from_u64(params.seed),
            stats,
            enc: MonitoringEncoder::with_version(params.fri_version),
            dec: CommandDecoder::with_version(params.fri_version),
            epoch_unix_ns,
            state: SessionState::MonitoringWait,
            quality: ConnectionQuality::Fair,
            seq: 0,
            produced: 0,
            reflected: 0,
            last_client_seq: None,
            slots: [Slot::default(); SLOTS],
            sent: [(0, 0, 0); SLOTS],
            cycle_ns: None,
            window: [false; MAX_QUALITY_WINDOW],
            window_len: 0,
            window_at: 0,
            window_bad: 0,
            on_time: 0,
            q,
            setpoint: q,
            ipo: q,
            last_cmd: q,
            last_cmd_ref: None,
            pending: VecDeque::with_capacity(PENDING_CAPACITY),
            last_apply_ns: 0,
            last_applied_due_ns: None,
            t_ns: None,
            wait_since_ns: 0,
            commanding_requested: false,
            close_requested: false,
            closed: false,
            world: None,
            p: params,
        };
        s.set_state(SessionState::MonitoringWait);
        s.set_quality(ConnectionQuality::Fair);
        Ok(s)
    }

    /// The shared counters.
    pub fn stats(&self) -> &Arc<SimStats> {
        &self.stats
    }

    /// The parameters.
    pub fn params(&self) -> &FriSimParams {
        &self.p
    }

    /// Session state.
    pub fn state(&self) -> SessionState {
        self.state
    }

    /// Connection quality.
    pub fn quality(&self) -> ConnectionQuality {
        self.quality
    }

    /// True joint positions, rad.
    pub fn joint_rad(&self) -> &Joints {
        &self.q
    }

    /// True once IDLE has been produced.
    pub fn is_closed(&self) -> bool {
        self.closed
    }

    /// Asks for commanding (the robot program starts its FRI overlay motion):
    /// taken up once the session is MONITORING_READY.
    pub fn request_commanding(&mut self) {
        self.commanding_requested = true;
        if let Some(w) = self.world.as_mut() {
            w.joints.clear_trip();
        }
    }

    /// Ends commanding as the robot application does
    /// ([`CommandingAbort::Application`]); nothing while not commanding.
    pub fn leave_commanding(&mut self) {
        if matches!(
            self.state,
            SessionState::CommandingWait | SessionState::CommandingActive
        ) {
            self.abort(CommandingAbort::Application);
        }
    }

    /// Closes the session: the next [`tick`](Self::tick) sends IDLE, then nothing.
    pub fn request_close(&mut self) {
        self.close_requested = true;
    }

    fn set_state(&mut self, s: SessionState) {
        if s == SessionState::CommandingActive && self.state != s {
            self.stats.commanding_entered.fetch_add(1, Relaxed);
        }
        self.state = s;
        self.stats.state.store(s as u8, Relaxed);
        self.stats.mark_reached(s);
    }

    fn set_quality(&mut self, q: ConnectionQuality) {
        self.quality = q;
        self.stats.quality.store(q as u8, Relaxed);
    }

    fn grade(&mut self, bad: bool) {
        let cap = self.p.quality_window as usize;
        if self.window_len == cap {
            if self.window[self.window_at] {
                self.window_bad -= 1;
            }
        } else {
            self.window_len += 1;
        }
        self.window[self.window_at] = bad;
        if bad {
            self.window_bad += 1;
        } else {
            self.on_time += 1;
        }
        self.window_at = (self.window_at + 1) % cap;
    }

    fn current_quality(&self) -> ConnectionQuality {
        let f = if self.window_len == 0 {
            0.0
        } else {
            self.window_bad as f64 / self.window_len as f64
        };
        let q = if f <= self.p.excellent_max_bad_fraction {
            ConnectionQuality::Excellent
        } else if f <= self.p.good_max_bad_fraction {
            ConnectionQuality::Good
        } else if f <= self.p.fair_max_bad_fraction {
            ConnectionQuality::Fair
        } else {
            ConnectionQuality::Poor
        };
        if self.on_time < u64::from(self.p.ready_after_replies) {
            q.min(ConnectionQuality::Fair)
        } else {
            q
        }
    }

    fn receive_period_ns(&self) -> u64 {
        self.p.period_ns() * u64::from(self.p.receive_multiplier)
    }

    fn finalize_missing(&mut self, now_ns: u64) {
        let after = (self.p.missing_after_periods * self.receive_period_ns() as f64) as u64;
        for i in 0..SLOTS {
            let s = self.slots[i];
            if s.open && s.sent_ns + after <= now_ns {
                self.slots[i].open = false;
                self.stats.missing_replies.fetch_add(1, Relaxed);
                self.grade(true);
            }
        }
    }

    /// Plugs the reality lab's robot in (`None`: the truthful robot of
    /// `FriSimParams`). The world's joints take over from the current ones.
    pub fn set_world(&mut self, world: Option<WorldRobot>) {
        self.world = world;
    }

    /// The reality lab's robot, when plugged in.
    pub fn world(&self) -> Option<&WorldRobot> {
        self.world.as_ref()
    }

    /// The ball met the tool (the reality lab): the contact's force pulse
    /// shows in the external torques of the next messages. Ignored without
    /// the reality lab's robot.
    pub fn contact(&mut self, contact: crate::sim::world::Contact) {
        if let Some(w) = self.world.as_mut() {
            w.joints.push(&contact.point_m, &contact.impulse_ns);
            // A free slot, else the oldest contact's.
            if let Some(slot) = w.contacts.iter_mut().min_by(|a, b| match (a, b) {
                (None, _) => std::cmp::Ordering::Less,
                (_, None) => std::cmp::Ordering::Greater,
                (Some(a), Some(b)) => a.t_s.total_cmp(&b.t_s),
            }) {
                *slot = Some(contact);
            }
        }
    }

    fn integrate(&mut self, dt_ns: u64) {
        if let Some(w) = self.world.as_mut() {
            let trip = w.joints.integrate(&self.setpoint, dt_ns as f64 * 1e-9);
            self.q = *w.joints.q();
            if let Some(trip) = trip
                && self.state.is_commanding()
            {
                self.abort(CommandingAbort::TorqueLimit(trip));
            }
            return;
        }
        let tau = self.p.servo_time_constant_ms * 1e-3;
        let a = if tau <= 0.0 {
            1.0
        } else {
            1.0 - (-(dt_ns as f64 * 1e-9) / tau).exp()
        };
        for i in 0..JOINTS {
            self.q[i] += (self.setpoint[i] - self.q[i]) * a;
        }
    }

    /// Moves the joints to `now_ns`: setpoints take effect at their due times.
    fn advance(&mut self, now_ns: u64) {
        let mut t = self.t_ns.unwrap_or(now_ns).min(now_ns);
        while let Some(&(due, q)) = self.pending.front() {
            if due > now_ns {
                break;
            }
            self.pending.pop_front();
            if self.pending.front().is_some_and(|&(next, _)| next <= due) {
                // A newer command landed in the same cycle: it wins.
                self.stats.superseded_commands.fetch_add(1, Relaxed);
                continue;
            }
            let due = due.max(t);
            self.integrate(due - t);
            t = due;
            self.setpoint = q;
            self.stats.commands_applied.fetch_add(1, Relaxed);
            self.count_held(due);
        }
        self.integrate(now_ns - t);
        self.t_ns = Some(now_ns);
        self.stats.joint_rad.store(&self.q);
        self.stats.setpoint_rad.store(&self.setpoint);
    }

    /// Counts the receive periods before `due` in which no command reached
    /// the servo (the setpoint was held).
    fn count_held(&mut self, due: u64) {
        if let Some(prev) = self.last_applied_due_ns.replace(due) {
            let gap = due.saturating_sub(prev) as f64 / self.receive_period_ns() as f64;
            let held = (gap.round() as u64).saturating_sub(1);
            if held > 0 {
                self.stats.held_cycles.fetch_add(held, Relaxed);
            }
        }
    }

    fn abort(&mut self, reason: CommandingAbort) {
        self.stats.set_abort(&reason);
        self.stats.aborts.fetch_add(1, Relaxed);
        if reason.is_violation() {
            self.stats.violations.fetch_add(1, Relaxed);
        }
        self.commanding_requested = false;
        // The drives stop where they are.
        self.pending.clear();
        self.last_applied_due_ns = None;
        self.setpoint = self.q;
        self.last_cmd = self.q;
        self.last_cmd_ref = None;
        self.ipo = self.q;
        let next = if self.quality >= ConnectionQuality::Good {
            SessionState::MonitoringReady
        } else {
            SessionState::MonitoringWait
        };
        self.set_state(next);
    }

    fn transition(&mut self, now_ns: u64) {
        let good = self.quality >= ConnectionQuality::Good;
        match self.state {
            SessionState::MonitoringWait if good => self.set_state(SessionState::MonitoringReady),
            SessionState::MonitoringReady if !good => self.set_state(SessionState::MonitoringWait),
            SessionState::MonitoringReady if self.commanding_requested => {
                self.ipo = self.setpoint;
                self.last_cmd = self.setpoint;
                self.last_cmd_ref = None;
                self.last_applied_due_ns = None;
                self.wait_since_ns = now_ns;
                self.set_state(SessionState::CommandingWait);
            }
            SessionState::CommandingWait | SessionState::CommandingActive if !good => {
                self.abort(CommandingAbort::QualityDropped {
                    quality: self.quality,
                });
            }
            SessionState::CommandingWait
                if now_ns.saturating_sub(self.wait_since_ns) as f64
                    >= self.p.commanding_wait_ms * 1e6 =>
            {
                self.set_state(SessionState::CommandingActive);
            }
            _ => {}
        }
    }

    /// The controller's cycle time of the tick at `now_ns`: one period after
    /// the previous one, or `now_ns` when the tick is off that by half a
    /// period early or a whole period late (the first tick, an overrun).
    fn next_cycle(&mut self, now_ns: u64) -> u64 {
        let p = self.p.period_ns();
        let cycle = match self.cycle_ns {
            Some(c) if now_ns + p / 2 >= c + p && now_ns < c + 2 * p => c + p,
            _ => now_ns,
        };
        self.cycle_ns = Some(cycle);
        cycle
    }

    /// The monitoring datagram due at `now_ns` (call once per send period), or
    /// `None` when it is lost by injection or the session is closed.
    pub fn tick(&mut self, now_ns: u64) -> Option<&[u8]> {
        if self.closed {
            return None;
        }
        self.finalize_missing(now_ns);
        let q = self.current_quality();
        self.set_quality(q);
        self.advance(now_ns);
        if self.close_requested {
            self.set_state(SessionState::Idle);
            self.closed = true;
        } else {
            self.transition(now_ns);
        }
        let seq = self.seq;
        self.seq = self.seq.wrapping_add(1);
        self.produced += 1;
        let r = u64::from(self.p.receive_multiplier);
        let cycle_ns = self.next_cycle(now_ns);
        self.sent[seq as usize % SLOTS] = (seq, now_ns, cycle_ns);
        if self.state != SessionState::Idle && self.produced % r == 0 {
            self.slots[seq as usize % SLOTS] = Slot {
                seq,
                sent_ns: now_ns,
                open: true,
            };
        }
        self.stats.messages_sent.fetch_add(1, Relaxed);
        let mut lost = self.state != SessionState::Idle
            && self.p.packet_loss > 0.0
            && self.rng.random_bool(self.p.packet_loss);
        let noise = self.p.measurement_noise_rad;
        let mut measured = match self.world.as_mut() {
            Some(w) => w.joints.measured(),
            None => self.q,
        };
        if noise > 0.0 {
            for v in &mut measured {
                *v += self.rng.random_range(-noise..=noise);
            }
        }
        let q_true = self.q;
        // The reality lab's network: the message reaches the PC one latency
        // later, carrying what was measured when it left; it may be lost.
        let mut stamp_ns = now_ns;
        let external: Joints = match self.world.as_mut() {
            Some(w) => {
                (stamp_ns, measured) = w.delayed(now_ns, measured);
                if self.state != SessionState::Idle
                    && w.net.packet_loss > 0.0
                    && w.net_rng.random_bool(w.net.packet_loss.min(1.0))
                {
                    lost = true;
                }
                w.external_torques(&q_true, stamp_ns)
            }
            None => [0.0; JOINTS],
        };
        if stamp_ns != now_ns {
            // The reply's round trip starts when the contents were measured.
            self.sent[seq as usize % SLOTS].1 = stamp_ns;
            let slot = &mut self.slots[seq as usize % SLOTS];
            if slot.seq == seq {
                slot.sent_ns = stamp_ns;
            }
        }
        let torque: Joints = std::array::from_fn(|i| {
            (SERVO_STIFFNESS_NM_PER_RAD * (self.setpoint[i] - self.q[i]))
                .clamp(-TORQUE_LIMIT_NM[i], TORQUE_LIMIT_NM[i])
        });
        if lost {
            self.stats.messages_dropped.fetch_add(1, Relaxed);
            return None;
        }
        let commanding = self.state.is_commanding();
        let m = Monitoring {
            sequence_counter: seq,
            reflected_sequence_counter: self.reflected,
            session_state: self.state,
            quality: self.quality,
            send_period_ms: self.p.fri_period_ms,
            receive_multiplier: self.p.receive_multiplier,
            safety_state: Some(SafetyState::NormalOperation),
            operation_mode: Some(OperationMode::AutomaticMode),
            control_mode: Some(ControlMode::PositionControlmode),
            drive_state: Some([DriveState::Active; JOINTS]),
            measured_joint_position_rad: Some(measured),
            measured_torque_nm: Some(torque),
            commanded_joint_position_rad: Some(self.setpoint),
            commanded_torque_nm: Some(torque),
            // The reality lab's contact and sensing noise; zero otherwise.
            external_torque_nm: Some(external),
            // FRI 2.7's estimated external force (Cartesian): not simulated
            // (the encoder writes it for 2.7 only).
            external_force: Some([0.0; 6]),
            timestamp: Some(UnixTime::from_ns(self.epoch_unix_ns + stamp_ns)),
            ipo_joint_position_rad: commanding.then_some(self.ipo),
            client_command_mode: commanding.then_some(ClientCommandMode::Position),
            overlay_type: commanding.then_some(OverlayType::Joint),
            tracking_performance: commanding.then_some(1.0),
        };
        self.enc.encode(&m).ok()
    }

    /// Takes a client datagram that arrived at `now_ns` (before injected delay).
    ///
    /// After the session closed, answers to its messages are still counted and
    /// graded (they were sent while it ran), but a command in them is ignored.
    pub fn on_reply(&mut self, bytes: &[u8], now_ns: u64) {
        if self.p.reply_loss > 0.0 && self.rng.random_bool(self.p.reply_loss) {
            self.stats.replies_dropped.fetch_add(1, Relaxed);
            return;
        }
        let mut delay_ms = self.p.reply_delay_ms;
        if self.p.reply_delay_jitter_ms > 0.0 {
            delay_ms += self.rng.random_range(0.0..=self.p.reply_delay_jitter_ms);
        }
        let mut arrival = now_ns + (delay_ms * 1e6) as u64;
        if let Some(w) = self.world.as_mut() {
            // The reality lab's network, the way back.
            if w.net.reply_loss > 0.0 && w.net_rng.random_bool(w.net.reply_loss.min(1.0)) {
                self.stats.replies_dropped.fetch_add(1, Relaxed);
                return;
            }
            arrival += w.net.delay_ns(&mut w.net_rng);
        }
        let Ok(c) = self.dec.decode(bytes) else {
            self.stats.decode_errors.fetch_add(1, Relaxed);
            return;
        };
        self.stats.replies.fetch_add(1, Relaxed);
        if let Some(prev) = self.last_client_seq
            && c.sequence_counter != prev.wrapping_add(1)
        {
            self.stats.client_sequence_errors.fetch_add(1, Relaxed);
        }
        self.last_client_seq = Some(c.sequence_counter);
        self.reflected = c.sequence_counter;

        // Grade the answer. A client counts its receiveMultiplier from the first
        // message it got and skips lost ones, so its answers need not fall on the
        // messages expected here: an answer to `r` covers the expected (open)
        // ones among the `receiveMultiplier` messages up to `r`.
        let r = c.reflected_sequence_counter;
        let covered = self.p.receive_multiplier;
        let mut first_sent_ns = None;
        let mut cycle_ns = None;
        for s in &mut self.slots {
            if s.open && r.wrapping_sub(s.seq) < covered {
                s.open = false;
                first_sent_ns = Some(first_sent_ns.map_or(s.sent_ns, |t: u64| t.min(s.sent_ns)));
            }
        }
        match first_sent_ns {
            Some(slot_sent_ns) => {
                let (seq, sent_ns, cycle) = self.sent[r as usize % SLOTS];
                let sent_ns = if seq == r { sent_ns } else { slot_sent_ns };
                cycle_ns = (seq == r).then_some(cycle);
                let rtt = arrival.saturating_sub(sent_ns);
                self.stats.rtt.record_ns(rtt);
                let late = rtt as f64 > self.p.late_after_periods * self.p.period_ns() as f64;
                if late {
                    self.stats.late_replies.fetch_add(1, Relaxed);
                }
                self.grade(late);
            }
            None => {
                self.stats.stale_replies.fetch_add(1, Relaxed);
            }
        }

        if self.closed {
            return;
        }
        match self.state {
            SessionState::CommandingWait => {
                if let Some(q) = c.joint_position_rad {
                    if q != self.ipo {
                        self.stats.mirror_mismatches.fetch_add(1, Relaxed);
                    }
                    if let Some(reason) = self.check_command(&q, r) {
                        self.abort(reason);
                    }
                }
            }
            SessionState::CommandingActive => match c.joint_position_rad {
                None => {
                    self.stats.empty_commands.fetch_add(1, Relaxed);
                }
                Some(q) => {
                    if let Some(reason) = self.check_command(&q, r) {
                        self.abort(reason);
                    } else {
                        self.last_cmd_ref = Some(r);
                        self.accept(q, arrival, cycle_ns);
                    }
                }
            },
            _ => {}
        }
    }

    /// The controller's checks on one commanded position (the drives' trip),
    /// answering message `reflected`. The speed is the step from the last
    /// accepted command over the receive periods between the messages the
    /// two answer (a lost message or reply in between: two periods, at most
    /// `missing_after_periods`).
    fn check_command(&self, q: &Joints, reflected: u32) -> Option<CommandingAbort> {
        let periods = self.last_cmd_ref.map_or(1.0, |last| {
            let n = reflected.wrapping_sub(last) / self.p.receive_multiplier.max(1);
            f64::from(n).clamp(1.0, self.p.missing_after_periods.max(1.0).floor())
        });
        let period_s = periods * self.receive_period_ns() as f64 * 1e-9;
        for i in 0..JOINTS {
            if !q[i].is_finite() {
                return Some(CommandingAbort::NotFinite { joint: i });
            }
            if q[i].abs() > POSITION_LIMIT_RAD[i] {
                return Some(CommandingAbort::PositionLimit {
                    joint: i,
                    position_rad: q[i],
                    limit_rad: POSITION_LIMIT_RAD[i],
                });
            }
            let max = VELOCITY_LIMIT_RADPS[i] * period_s * self.p.velocity_tolerance;
            let step = q[i] - self.last_cmd[i];
            if step.abs() > max {
                return Some(CommandingAbort::VelocityLimit {
                    joint: i,
                    step_rad: step,
                    max_step_rad: max,
                });
            }
        }
        None
    }

    /// Queues an accepted command for the cycle it lands in. Its own cycle:
    /// the latency after the controller cycle that sent the message it
    /// answers (`cycle_ns`; its arrival for an answer to a message no longer
    /// known). A reply after that message's deadline (`late_after_periods`)
    /// misses the cycles up to its arrival, the latency's jitter moves it by
    /// the nearest whole number of periods; the servo keeps the previous
    /// setpoint meanwhile (held, not extrapolated).
    fn accept(&mut self, q: Joints, arrival_ns: u64, cycle_ns: Option<u64>) {
        self.last_cmd = q;
        self.stats.commands_accepted.fetch_add(1, Relaxed);
        let mut latency_ms = self.p.latency_ms;
        let mut jitter_ms = 0.0;
        if let Some(w) = self.world.as_mut() {
            latency_ms = w.latency.latency_s(arrival_ns as f64 * 1e-9) * 1e3;
            let j = w.net.command_jitter_s;
            if j > 0.0 {
                jitter_ms = w.net_rng.random_range(-j..=j) * 1e3;
            }
        } else if self.p.latency_jitter_ms > 0.0 {
            jitter_ms = self
                .rng
                .random_range(-self.p.latency_jitter_ms..=self.p.latency_jitter_ms);
        }
        let period = self.p.period_ns();
        let base = cycle_ns.unwrap_or(arrival_ns);
        let own = base + (latency_ms.max(0.0) * 1e6) as u64;
        let deadline = base + (self.p.late_after_periods * period as f64) as u64;
        let missed = arrival_ns.saturating_sub(deadline).div_ceil(period);
        let shift = missed as i64 + (jitter_ms * 1e6 / period as f64).round() as i64;
        let due = own
            .saturating_add_signed(shift * period as i64)
            // Never before it arrived, never before the previous command
            // (in the same cycle, it replaces that one).
            .max(arrival_ns)
            .max(self.last_apply_ns);
        if due >= own + period / 2 {
            self.stats.late_commands.fetch_add(1, Relaxed);
        }
        self.last_apply_ns = due;
        if self.pending.len() >= PENDING_CAPACITY {
            self.stats.pending_overflow.fetch_add(1, Relaxed);
            self.pending.pop_front();
        }
        self.pending.push_back((due, q));
    }
}
