#![doc = include_str!("README.md")]

#[cfg(feature = "serial")]
pub mod driver;
#[cfg_attr(
    not(feature = "serial"),
    allow(
        dead_code,
        reason = "without `serial` nothing speaks to the board: the codec's encoders are unused"
    )
)]
pub mod protocol;
#[cfg_attr(
    not(feature = "serial"),
    allow(
        dead_code,
        reason = "without `serial` the shared view's encoders are unused (its types stay public)"
    )
)]
pub mod view;

#[cfg(all(test, feature = "serial"))]
mod tests;

use serde::{Deserialize, Serialize};

use crate::check::{self, ParamError};

#[cfg(feature = "serial")]
pub use driver::{Answer, EventHook, MagnetEvent, MagnetHandle, Pending};
pub use protocol::{Command, DeviceEvent, DeviceStatus, OkReply, ResetCause};
pub use view::{EventKind, LinkState, MagnetState, MagnetView, SwitchCause};

/// The magnet driver's parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MagnetParams {
    /// Serial port path (`/dev/ttyACM0` for an Uno; a pty path in tests).
    pub port: String,
    /// Baud rate (the firmware runs at 115200; ignored on a pty).
    pub baud: u32,
    /// How long one command may wait for its answer, ms.
    pub command_timeout_ms: f64,
    /// How long to resynchronise after opening the port (an Uno resets for 1..2 s
    /// when the port opens) or after a timeout, ms.
    pub boot_timeout_ms: f64,
    /// Pause between attempts to reopen a missing device, ms.
    pub reconnect_interval_ms: f64,
    /// How often the driver asks `STATUS` when idle, ms.
    pub status_poll_ms: f64,
    /// The coil's maximum hold time, set on the device at every connection, s.
    pub hold_limit_s: u16,
}

impl Default for MagnetParams {
    fn default() -> Self {
        Self {
            port: "/dev/ttyACM0".to_owned(),
            baud: 115_200,
            command_timeout_ms: 300.0,
            boot_timeout_ms: 3000.0,
            reconnect_interval_ms: 250.0,
            status_poll_ms: 1000.0,
            hold_limit_s: protocol::HOLD_DEFAULT_S,
        }
    }
}

impl MagnetParams {
    /// Default parameters for the device at `port`.
    pub fn for_port(port: impl Into<String>) -> Self {
        Self {
            port: port.into(),
            ..Self::default()
        }
    }

    /// Checks every field, naming the first bad one (`magnet.command_timeout_ms`).
    ///
    /// # Errors
    ///
    /// [`ParamError::OutOfRange`] for an empty port, and [`ParamError::NotFinite`] or
    /// [`ParamError::OutOfRange`] naming the first other field outside its range.
    pub fn validate(&self) -> Result<(), ParamError> {
        if self.port.trim().is_empty() {
            return Err(ParamError::OutOfRange {
                field: "magnet.port".to_owned(),
                value: check::Value::Text(self.port.clone()),
                bound: check::Bound::rule("must name a serial port"),
            });
        }
        check::within_u32("magnet.baud", self.baud, 300, 2_000_000)?;
        check::within(
            "magnet.command_timeout_ms",
            self.command_timeout_ms,
            5.0,
            10_000.0,
        )?;
        check::within(
            "magnet.boot_timeout_ms",
            self.boot_timeout_ms,
            10.0,
            60_000.0,
        )?;
        check::within(
            "magnet.reconnect_interval_ms",
            self.reconnect_interval_ms,
            1.0,
            60_000.0,
        )?;
        check::within(
            "magnet.status_poll_ms",
            self.status_poll_ms,
            10.0,
            600_000.0,
        )?;
        check::within_u32(
            "magnet.hold_limit_s",
            u32::from(self.hold_limit_s),
            u32::from(protocol::HOLD_RANGE_S.0),
            u32::from(protocol::HOLD_RANGE_S.1),
        )
    }
}

/// What can go wrong talking to the magnet.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum MagnetError {
    /// Bad parameters; nothing was started.
    #[error(transparent)]
    Params(#[from] ParamError),
    /// The device is not (yet) connected.
    #[error("magnet device {port} is not connected: {reason}")]
    NotConnected {
        /// The port path.
        port: String,
        /// Why (the last connection attempt's error).
        reason: String,
    },
    /// The device went away during the command (unplugged, simulator killed).
    #[error("magnet device {port} lost: {reason}")]
    DeviceLost {
        /// The port path.
        port: String,
        /// What the operating system said.
        reason: String,
    },
    /// No answer within the command timeout.
    #[error("magnet device {port} did not answer `{command}` within {timeout_ms} ms")]
    Timeout {
        /// The port path.
        port: String,
        /// The command line.
        command: String,
        /// The timeout that passed, ms.
        timeout_ms: f64,
    },
    /// The device refused the command (`ERR <code>`).
    #[error("magnet device refused `{command}`: ERR {code}")]
    Device {
        /// The command line.
        command: String,
        /// The firmware's error code.
        code: String,
    },
    /// An answer of another kind than the command asked for (the answer as parsed).
    #[error("unexpected answer from the magnet device: {0:?}")]
    Protocol(OkReply),
    /// Too many requests queued.
    #[error("the magnet driver's queue is full; try again")]
    Busy,
    /// The driver thread has stopped.
    #[error("the magnet driver has stopped")]
    Stopped,
    /// The driver thread could not start (the operating system's reason).
    #[error("cannot start the magnet driver: {kind}")]
    Spawn {
        /// What kind of failure the operating system reported.
        kind: std::io::ErrorKind,
    },
}
