#![doc = include_str!("README.md")]

pub mod client;
pub mod codec;
pub mod doctor;
pub mod framing;
pub mod guard;
pub mod net;
pub mod priority;
pub mod proto;
pub mod session;
pub mod stats;
pub mod version;

#[cfg(test)]
mod golden_tests;
#[cfg(test)]
mod tests;

pub use client::{
    ControlStep, FriClient, FriClientParams, HoldPosition, LinkState, SessionStats, SessionStatus,
    StepInput, StopReason,
};
pub use codec::{
    COMMAND_MESSAGE_ID, CodecError, Command, CommandDecoder, CommandEncoder, Joints,
    MAX_DATAGRAM_BYTES, MONITORING_MESSAGE_ID, Monitoring, MonitoringDecoder, MonitoringEncoder,
    UnixTime, Wrench,
};
pub use framing::FrameError;
pub use guard::{CommandGuard, GuardOutcome, GuardParams};
pub use proto::{ConnectionQuality, SessionState};
pub use session::{FriSession, FriSessionParams, SessionError};
pub use version::FriVersion;
