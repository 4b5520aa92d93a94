//! The driver's state as other threads see it: a copyable [`MagnetView`] published
//! through a sequence lock built from atomics only (one writer: the magnet thread;
//! any number of readers, which never block the writer and never allocate).

use std::sync::atomic::{AtomicU64, Ordering, fence};

use super::protocol::ResetCause;

/// Whether the driver is talking to the device.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LinkState {
    /// Opening the port / resynchronising (also before the first attempt).
    Connecting,
    /// The device answers.
    Connected,
    /// The device is missing, unplugged or silent; the driver keeps retrying.
    Lost,
}

/// The magnet's state as last reported by the device.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MagnetState {
    /// Not known: never connected, or the link was lost.
    Unknown,
    /// Off: the ball is not held.
    Off,
    /// On: the coil holds the ball.
    On,
}

/// Why the magnet's known state changed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SwitchCause {
    /// A `MAGNET ON|OFF` command.
    Command,
    /// The firmware's hold limit.
    HoldLimit,
    /// The board reset (every reset leaves the coil off).
    Reset,
    /// A `STATUS` answer disagreed with what the driver knew.
    Status,
}

/// Something that happened to the magnet or its link.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum EventKind {
    /// The device answers (after opening the port or reconnecting).
    Connected,
    /// The device went missing, was unplugged or fell silent.
    Lost,
    /// The magnet's known state changed.
    Switched {
        /// The new state: `true` on.
        on: bool,
        /// Why.
        cause: SwitchCause,
    },
    /// The board (re)started (its boot banner).
    Boot {
        /// Why it reset.
        reset: ResetCause,
    },
    /// The firmware's coil protection switched the magnet off.
    HoldLimit {
        /// How long the coil had been on, ms.
        held_ms: u32,
    },
}

impl EventKind {
    fn encode(self) -> u64 {
        let (tag, payload): (u64, u32) = match self {
            Self::Connected => (1, 0),
            Self::Lost => (2, 0),
            Self::Switched { on, cause } => (3, u32::from(on) | ((cause as u32) << 1)),
            Self::Boot { reset } => (4, reset.code()),
            Self::HoldLimit { held_ms } => (5, held_ms),
        };
        tag | (u64::from(payload) << 32)
    }

    fn decode(w: u64) -> Option<Self> {
        let payload = (w >> 32) as u32;
        Some(match w & 0xff {
            1 => Self::Connected,
            2 => Self::Lost,
            3 => Self::Switched {
                on: payload & 1 == 1,
                cause: match payload >> 1 {
                    0 => SwitchCause::Command,
                    1 => SwitchCause::HoldLimit,
                    2 => SwitchCause::Reset,
                    _ => SwitchCause::Status,
                },
            },
            4 => Self::Boot {
                reset: ResetCause::from_code(payload),
            },
            5 => Self::HoldLimit { held_ms: payload },
            _ => return None,
        })
    }
}

/// A consistent snapshot of the driver's state. Times are nanoseconds since the
/// handle's [`epoch`](super::MagnetHandle::epoch).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct MagnetView {
    /// The link to the device.
    pub link: LinkState,
    /// The magnet's state as the device last reported it.
    pub magnet: MagnetState,
    /// When the known magnet state last changed (0: never).
    pub changed_at_ns: u64,
    /// The latest event.
    pub last_event: Option<EventKind>,
    /// When the latest event happened (0: none yet).
    pub last_event_at_ns: u64,
    /// Events so far (a change of this counter means a new event).
    pub events: u64,
    /// Why the board last reset, from its latest boot banner or status.
    pub last_reset: Option<ResetCause>,
    /// The device's hold limit, ms (0: not known yet).
    pub hold_max_ms: u32,
    /// Round-trip time of the latest answered command, microseconds.
    pub last_rtt_us: u32,
    /// Commands answered (`OK` or `ERR`).
    pub commands: u64,
    /// Commands that timed out.
    pub timeouts: u64,
    /// Successful connections (1 after the first, +1 per reconnection).
    pub connects: u64,
    /// Lines from the device that were neither an answer nor an event (skipped).
    pub stray_lines: u64,
}

impl Default for MagnetView {
    fn default() -> Self {
        Self {
            link: LinkState::Connecting,
            magnet: MagnetState::Unknown,
            changed_at_ns: 0,
            last_event: None,
            last_event_at_ns: 0,
            events: 0,
            last_reset: None,
            hold_max_ms: 0,
            last_rtt_us: 0,
            commands: 0,
            timeouts: 0,
            connects: 0,
            stray_lines: 0,
        }
    }
}

const WORDS: usize = 10;

impl MagnetView {
    fn encode(&self) -> [u64; WORDS] {
        let link = self.link as u64;
        let magnet = self.magnet as u64;
        let reset = self.last_reset.map_or(0, |r| u64::from(r.code()) + 1);
        [
            link | (magnet << 8) | (reset << 16),
            self.changed_at_ns,
            self.last_event.map_or(0, EventKind::encode),
            self.last_event_at_ns,
            self.events,
            u64::from(self.hold_max_ms) | (u64::from(self.last_rtt_us) << 32),
            self.commands,
            self.timeouts,
            self.connects,
            self.stray_lines,
        ]
    }

    fn decode(w: &[u64; WORDS]) -> Self {
        let link = match w[0] & 0xff {
            1 => LinkState::Connected,
            2 => LinkState::Lost,
            _ => LinkState::Connecting,
        };
        let magnet = match (w[0] >> 8) & 0xff {
            1 => MagnetState::Off,
            2 => MagnetState::On,
            _ => MagnetState::Unknown,
        };
        let reset = (w[0] >> 16) & 0xff;
        Self {
            link,
            magnet,
            changed_at_ns: w[1],
            last_event: EventKind::decode(w[2]),
            last_event_at_ns: w[3],
            events: w[4],
            last_reset: (reset != 0).then(|| ResetCause::from_code((reset - 1) as u32)),
            hold_max_ms: w[5] as u32,
            last_rtt_us: (w[5] >> 32) as u32,
            commands: w[6],
            timeouts: w[7],
            connects: w[8],
            stray_lines: w[9],
        }
    }
}

/// The sequence lock: even sequence = stable, odd = being written.
#[derive(Debug)]
pub(crate) struct ViewCell {
    seq: AtomicU64,
    words: [AtomicU64; WORDS],
}

impl ViewCell {
    pub(crate) fn new(view: &MagnetView) -> Self {
        let cell = Self {
            seq: AtomicU64::new(0),
            words: Default::default(),
        };
        cell.publish(view);
        cell
    }

    /// Only the magnet thread calls this (single writer).
    pub(crate) fn publish(&self, view: &MagnetView) {
        let s = self.seq.load(Ordering::Relaxed);
        self.seq.store(s.wrapping_add(1), Ordering::Relaxed);
        fence(Ordering::Release);
        for (slot, w) in self.words.iter().zip(view.encode()) {
            slot.store(w, Ordering::Relaxed);
        }
        self.seq.store(s.wrapping_add(2), Ordering::Release);
    }

    /// One attempt; `None` when a write was in progress.
    pub(crate) fn try_read(&self) -> Option<MagnetView> {
        let s1 = self.seq.load(Ordering::Acquire);
        if s1 & 1 == 1 {
            return None;
        }
        let mut w = [0u64; WORDS];
        for (v, slot) in w.iter_mut().zip(&self.words) {
            *v = slot.load(Ordering::Relaxed);
        }
        fence(Ordering::Acquire);
        let s2 = self.seq.load(Ordering::Relaxed);
        (s1 == s2).then(|| MagnetView::decode(&w))
    }
}
