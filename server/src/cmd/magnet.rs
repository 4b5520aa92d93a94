//! `isochron magnet --port PATH (on|off|status)`: talks to the magnet firmware
//! over serial and prints the device's state as JSON.

use rt_core::magnet::{MagnetError, MagnetHandle, MagnetParams, MagnetView};

/// What to do with the magnet.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum MagnetAction {
    /// Switch the magnet on (hold the ball).
    On,
    /// Switch the magnet off (drop the ball).
    Off,
    /// Ask the device's state.
    Status,
}

/// Arguments of `isochron magnet`.
#[derive(Debug, clap::Args)]
pub struct MagnetArgs {
    /// Serial port of the Arduino (e.g. /dev/ttyACM0; ptys are not listed by the OS, give the path).
    #[arg(long)]
    pub port: String,
    /// What to do.
    #[arg(value_enum)]
    pub action: MagnetAction,
    /// How long to wait for the board to answer after opening the port (an Uno resets for 1..2 s), ms.
    #[arg(long, default_value_t = 3000.0)]
    pub boot_timeout_ms: f64,
    /// How long one command may wait for its answer, ms.
    #[arg(long, default_value_t = 300.0)]
    pub command_timeout_ms: f64,
    /// The coil's maximum hold time set on the device, s (1..3600).
    #[arg(long, default_value_t = 120)]
    pub hold_s: u16,
}

/// The JSON this command prints.
#[derive(Debug, serde::Serialize)]
pub struct MagnetReport {
    /// `"on"` or `"off"`: the device's own report.
    pub magnet: &'static str,
    /// The port talked to.
    pub port: String,
    /// How long the coil has been on, ms.
    pub held_ms: u32,
    /// The coil's maximum hold time, ms.
    pub hold_max_ms: u32,
    /// Milliseconds since the board's last reset.
    pub uptime_ms: u32,
    /// Why the board last reset.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reset: Option<rt_core::magnet::ResetCause>,
    /// Firmware protocol version (in `status` answers).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fw: Option<u32>,
    /// Round trip of the command, ms.
    pub rtt_ms: f64,
}

/// Runs `isochron magnet`; returns the JSON line to print.
pub fn run(args: MagnetArgs) -> anyhow::Result<String> {
    let params = MagnetParams {
        port: args.port.clone(),
        boot_timeout_ms: args.boot_timeout_ms,
        command_timeout_ms: args.command_timeout_ms,
        hold_limit_s: args.hold_s,
        // One attempt: a missing device is reported, not waited for.
        reconnect_interval_ms: 60_000.0,
        status_poll_ms: 600_000.0,
        ..MagnetParams::default()
    };
    let handle = MagnetHandle::spawn(params)?;
    let cmd = match args.action {
        MagnetAction::On => rt_core::magnet::Command::Magnet(true),
        MagnetAction::Off => rt_core::magnet::Command::Magnet(false),
        MagnetAction::Status => rt_core::magnet::Command::Status,
    };
    let answer = handle.submit(cmd)?.wait().map_err(clarify)?;
    let status = answer
        .status()
        .ok_or_else(|| MagnetError::Protocol(answer.reply.clone()))?;
    let view: MagnetView = handle.view();
    let report = MagnetReport {
        magnet: if status.magnet_on { "on" } else { "off" },
        port: args.port,
        held_ms: status.held_ms,
        hold_max_ms: status.hold_max_ms,
        uptime_ms: status.uptime_ms,
        reset: status.reset.or(view.last_reset),
        fw: status.fw,
        rtt_ms: (answer.rtt.as_secs_f64() * 1e6).round() / 1000.0,
    };
    drop(handle);
    Ok(serde_json::to_string(&report)?)
}

fn clarify(e: MagnetError) -> anyhow::Error {
    match e {
        MagnetError::NotConnected { port, reason } => anyhow::anyhow!(
            "no magnet device at {port}: {reason} (is the Arduino plugged in and flashed? see firmware/magnet/README.md)"
        ),
        other => other.into(),
    }
}
