#![doc = include_str!("README.md")]

pub mod codec;
pub mod proto;

#[cfg(test)]
mod tests;

pub use codec::{
    COMMAND_MESSAGE_ID, CodecError, Command, CommandDecoder, CommandEncoder, Joints,
    MAX_DATAGRAM_BYTES, MONITORING_MESSAGE_ID, Monitoring, MonitoringDecoder, MonitoringEncoder,
    UnixTime,
};
pub use proto::{ConnectionQuality, SessionState};
