//! The firmware's line protocol: commands out, answers and events in.
//!
//! Pure text handling, no I/O: the driver, the fake device and the tests share it.
//! One line per message, `\n` terminated (the firmware sends `\r\n`; `\r` is ignored).

use std::fmt;

/// Longest command line the firmware accepts (without the newline).
pub const LINE_MAX: usize = 32;
/// Longest `PING` token the firmware accepts.
pub const TOKEN_MAX: usize = 16;
/// Hold limits the firmware accepts, seconds.
pub const HOLD_RANGE_S: (u16, u16) = (1, 3600);
/// Hold limit after a reset, seconds.
pub const HOLD_DEFAULT_S: u16 = 120;
/// Firmware protocol version this driver speaks.
pub const FW_VERSION: u32 = 1;

/// A command for the firmware.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum Command {
    /// `PING <token>`: answered `OK PONG <token>`; used to resynchronise.
    Ping(String),
    /// `MAGNET ON` / `MAGNET OFF`.
    Magnet(bool),
    /// `STATUS`: the device's true state.
    Status,
    /// `HOLD <s>`: the coil's maximum hold time, seconds (1..=3600).
    Hold(u16),
    /// `LED ON` / `LED OFF`: the calibration LED on D12 (in the camera's view); the
    /// pin switches before the answer is written.
    Led(bool),
    /// A raw line sent as is (diagnostics and tests, e.g. `TEST HANG`); any `OK`/`ERR` answers it.
    Raw(String),
}

impl Command {
    /// The line to send, without the newline.
    pub fn line(&self) -> String {
        match self {
            Self::Ping(t) => format!("PING {t}"),
            Self::Magnet(true) => "MAGNET ON".to_owned(),
            Self::Magnet(false) => "MAGNET OFF".to_owned(),
            Self::Status => "STATUS".to_owned(),
            Self::Hold(s) => format!("HOLD {s}"),
            Self::Led(true) => "LED ON".to_owned(),
            Self::Led(false) => "LED OFF".to_owned(),
            Self::Raw(l) => l.clone(),
        }
    }

    /// Whether `ok` is the answer this command expects.
    pub fn expects(&self, ok: &OkReply) -> bool {
        match (self, ok) {
            (Self::Ping(t), OkReply::Pong(u)) => t == u,
            (Self::Magnet(_), OkReply::Magnet(_))
            | (Self::Status, OkReply::Status(_))
            | (Self::Hold(_), OkReply::Hold { .. })
            | (Self::Led(_), OkReply::Led { .. })
            | (Self::Raw(_), _) => true,
            _ => false,
        }
    }
}

impl fmt::Display for Command {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.line())
    }
}

/// Why the board last reset, from its boot banner.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ResetCause {
    /// Power-on.
    Power,
    /// The reset pin (or the USB-serial chip's DTR pulse when the port is opened).
    External,
    /// Supply voltage dropped below the brown-out level.
    Brownout,
    /// The hardware watchdog: the main loop hung.
    Watchdog,
    /// Not known (a bootloader cleared the flags).
    Unknown,
}

impl ResetCause {
    /// Parses the firmware's word.
    pub fn parse(s: &str) -> Self {
        match s {
            "power" => Self::Power,
            "external" => Self::External,
            "brownout" => Self::Brownout,
            "watchdog" => Self::Watchdog,
            _ => Self::Unknown,
        }
    }

    /// The firmware's word.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Power => "power",
            Self::External => "external",
            Self::Brownout => "brownout",
            Self::Watchdog => "watchdog",
            Self::Unknown => "unknown",
        }
    }

    pub(crate) fn code(self) -> u32 {
        self as u32
    }

    pub(crate) fn from_code(c: u32) -> Self {
        match c {
            0 => Self::Power,
            1 => Self::External,
            2 => Self::Brownout,
            3 => Self::Watchdog,
            _ => Self::Unknown,
        }
    }
}

/// The device's state as it reported it (`OK STATUS` / `OK MAGNET`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct DeviceStatus {
    /// Whether the coil is energised.
    pub magnet_on: bool,
    /// How long the coil has been on, ms (0 when off).
    pub held_ms: u32,
    /// The coil's maximum hold time, ms.
    pub hold_max_ms: u32,
    /// Milliseconds since the board's last reset.
    pub uptime_ms: u32,
    /// Why the board last reset (only in `STATUS` answers).
    pub reset: Option<ResetCause>,
    /// Firmware version (only in `STATUS` answers).
    pub fw: Option<u32>,
}

/// A successful answer.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum OkReply {
    /// `OK PONG <token>`.
    Pong(String),
    /// `OK MAGNET ...`: the state after the switch.
    Magnet(DeviceStatus),
    /// `OK STATUS ...`.
    Status(DeviceStatus),
    /// `OK HOLD hold_max_ms=..`.
    Hold {
        /// The new hold limit, ms.
        hold_max_ms: u32,
    },
    /// `OK LED led=on|off uptime_ms=..`: the calibration LED's state after the switch.
    Led {
        /// Whether the LED is lit.
        on: bool,
        /// Milliseconds since the board's last reset.
        uptime_ms: u32,
    },
    /// Any other `OK` line (e.g. `OK HANG`), its text after `OK `.
    Other(String),
}

/// An unsolicited event from the device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum DeviceEvent {
    /// `EVT BOOT ...`: the board (re)started; the magnet is off.
    Boot {
        /// Why it reset.
        reset: ResetCause,
        /// Firmware version.
        fw: u32,
        /// Hold limit in force, ms.
        hold_max_ms: u32,
    },
    /// `EVT HOLD_LIMIT ...`: the coil protection switched the magnet off.
    HoldLimit {
        /// How long the coil had been on, ms.
        held_ms: u32,
    },
}

/// One line from the device, classified.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum Line {
    /// `OK ...`.
    Ok(OkReply),
    /// `ERR <code>`.
    Err(String),
    /// `EVT ...`.
    Event(DeviceEvent),
    /// Anything else (noise, a bootloader, a truncated line): skipped.
    Other(String),
}

fn field<'a>(words: &[&'a str], key: &str) -> Option<&'a str> {
    words
        .iter()
        .find_map(|w| w.split_once('=').and_then(|(k, v)| (k == key).then_some(v)))
}

fn num(words: &[&str], key: &str) -> Option<u32> {
    field(words, key).and_then(|v| v.parse().ok())
}

fn status(words: &[&str]) -> Option<DeviceStatus> {
    let magnet_on = match field(words, "magnet")? {
        "on" => true,
        "off" => false,
        _ => return None,
    };
    Some(DeviceStatus {
        magnet_on,
        held_ms: num(words, "held_ms")?,
        hold_max_ms: num(words, "hold_max_ms")?,
        uptime_ms: num(words, "uptime_ms")?,
        reset: field(words, "reset").map(ResetCause::parse),
        fw: num(words, "fw"),
    })
}

/// Classifies one line (without its line ending).
///
/// ```
/// use rt_core::magnet::protocol::{Line, OkReply, parse_line};
/// assert_eq!(
///     parse_line("OK PONG 42\r\n"),
///     Line::Ok(OkReply::Pong("42".to_owned()))
/// );
/// // Noise on the line is classified, never a panic.
/// assert!(matches!(parse_line("\u{0}garbage"), Line::Other(_)));
/// ```
pub fn parse_line(raw: &str) -> Line {
    let text = raw.trim_end_matches(['\r', '\n']);
    let words: Vec<&str> = text.split(' ').filter(|w| !w.is_empty()).collect();
    let other = || Line::Other(text.to_owned());
    match words.as_slice() {
        ["OK", "PONG", token] => Line::Ok(OkReply::Pong((*token).to_owned())),
        ["OK", "MAGNET", rest @ ..] => {
            status(rest).map_or_else(other, |s| Line::Ok(OkReply::Magnet(s)))
        }
        ["OK", "STATUS", rest @ ..] => {
            status(rest).map_or_else(other, |s| Line::Ok(OkReply::Status(s)))
        }
        ["OK", "HOLD", rest @ ..] => num(rest, "hold_max_ms")
            .map_or_else(other, |hold_max_ms| Line::Ok(OkReply::Hold { hold_max_ms })),
        ["OK", "LED", rest @ ..] => {
            let on = match field(rest, "led") {
                Some("on") => Some(true),
                Some("off") => Some(false),
                _ => None,
            };
            match (on, num(rest, "uptime_ms")) {
                (Some(on), Some(uptime_ms)) => Line::Ok(OkReply::Led { on, uptime_ms }),
                _ => other(),
            }
        }
        ["OK", rest @ ..] => Line::Ok(OkReply::Other(rest.join(" "))),
        ["ERR", code, ..] => Line::Err((*code).to_owned()),
        ["ERR"] => Line::Err(String::new()),
        ["EVT", "BOOT", rest @ ..] => Line::Event(DeviceEvent::Boot {
            reset: field(rest, "reset").map_or(ResetCause::Unknown, ResetCause::parse),
            fw: num(rest, "fw").unwrap_or(0),
            hold_max_ms: num(rest, "hold_max_ms").unwrap_or(0),
        }),
        ["EVT", "HOLD_LIMIT", rest @ ..] => Line::Event(DeviceEvent::HoldLimit {
            held_ms: num(rest, "held_ms").unwrap_or(0),
        }),
        _ => other(),
    }
}
