#![doc = include_str!("README.md")]

pub mod client;
pub mod codec;
pub mod guard;
pub mod net;
pub mod proto;
pub mod session;
pub mod stats;

#[cfg(test)]
mod tests;

pub use client::{
    ControlStep, FriClient, FriClientParams, HoldPosition, LinkState, SessionStats, SessionStatus,
    StepInput, StopReason,
};
pub use codec::{
    COMMAND_MESSAGE_ID, CodecError, Command, CommandDecoder, CommandEncoder, Joints,
    MAX_DATAGRAM_BYTES, MONITORING_MESSAGE_ID, Monitoring, MonitoringDecoder, MonitoringEncoder,
    UnixTime,
};
pub use guard::{CommandGuard, GuardOutcome, GuardParams};
pub use proto::{ConnectionQuality, SessionState};
pub use session::{FriSession, FriSessionParams, SessionError};
