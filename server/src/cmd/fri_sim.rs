//! `isochron fri-sim`: a standalone simulated KUKA FRI controller (CONTRACT.md).
//!
//! It sends monitoring messages to `--client` every period, walks
//! MONITORING_WAIT -> MONITORING_READY -> COMMANDING_WAIT -> COMMANDING_ACTIVE
//! (asking for commanding as soon as the client's answers are good enough), and
//! closes with IDLE after `--duration-s`. It speaks the FRI version of
//! `--fri-version` (1.11, 1.14, 1.15 (default), 1.16, 2.5, 2.7: fields and, for
//! 2.7, length + CRC-32 framing); any client of that version works against it,
//! including KUKA's own SDK run without a host argument (it answers the sender).

use std::net::SocketAddr;
use std::time::Duration;

use anyhow::Context;
use clap::Args;
use rt_core::fri::FriVersion;
use rt_core::params::check;
use rt_core::sim::kuka::{FriSimParams, SimRunOptions, SimServer};

/// Arguments of `isochron fri-sim`.
#[derive(Debug, Args)]
pub struct FriSimArgs {
    /// Local address of the controller (replies come here).
    #[arg(long, default_value = "127.0.0.1:30201")]
    pub bind: SocketAddr,
    /// The FRI client (KUKA's default port is 30200).
    #[arg(long, default_value = "127.0.0.1:30200")]
    pub client: SocketAddr,
    /// Send period, whole milliseconds (1..100).
    #[arg(long, default_value_t = 5)]
    pub period_ms: u32,
    /// Close the session (send IDLE) after this many seconds.
    #[arg(long, default_value_t = 10.0)]
    pub duration_s: f64,
    /// Injected loss of monitoring messages, 0..1.
    #[arg(long, default_value_t = 0.0)]
    pub packet_loss: f64,
    /// Seed of the simulated jitter and loss.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// The FRI version to speak: 1.11, 1.14, 1.15, 1.16, 2.5 or 2.7.
    #[arg(long, default_value = "1.15")]
    pub fri_version: FriVersion,
    /// Print one JSON summary object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Runs the simulated controller for the asked duration; returns its summary.
pub fn run(args: &FriSimArgs) -> anyhow::Result<String> {
    check::within("--duration-s", args.duration_s, 0.01, 86_400.0)?;
    let params = FriSimParams {
        fri_period_ms: args.period_ms,
        packet_loss: args.packet_loss,
        seed: args.seed,
        fri_version: args.fri_version,
        ..FriSimParams::default()
    };
    params.validate().map_err(|e| {
        anyhow::anyhow!(
            e.to_string()
                .replace("fri_sim.fri_period_ms", "--period-ms")
        )
    })?;
    let duration = Duration::from_secs_f64(args.duration_s);
    // The cabinet stands in for a machine of its own: its controller thread
    // takes SCHED_FIFO when allowed, so that other load here (a lab, a board
    // simulator, a camera) does not make it grade its own slowness as the
    // client's late replies.
    rt_core::fri::priority::enable();
    let server = SimServer::spawn(
        params,
        args.bind,
        args.client,
        SimRunOptions {
            auto_command: true,
            duration: Some(duration),
            normal_priority: false,
            keep_commanding: false,
        },
    )?;
    if !args.json {
        eprintln!(
            "isochron fri-sim: FRI {} controller on {} -> client {}, {} ms period, {:.1} s",
            args.fri_version,
            server.local_addr(),
            args.client,
            args.period_ms,
            args.duration_s
        );
    }
    if !args.json {
        // Say each abort as it happens: a client that loses commanding learns
        // why from the cabinet's console, as from a real one's.
        let stats = std::sync::Arc::clone(server.stats());
        std::thread::Builder::new()
            .name("fri-sim-aborts".into())
            .spawn(move || {
                let mut seen = 0;
                loop {
                    let n = stats.aborts.load(std::sync::atomic::Ordering::Relaxed);
                    if n > seen {
                        seen = n;
                        if let Some(r) = stats.last_abort() {
                            let l = |a: &std::sync::atomic::AtomicU64| {
                                a.load(std::sync::atomic::Ordering::Relaxed)
                            };
                            eprintln!(
                                "isochron fri-sim: commanding aborted: {r} (so far: {} late \
                                 replies, {} missing, {} overruns of this controller)",
                                l(&stats.late_replies),
                                l(&stats.missing_replies),
                                l(&stats.overruns)
                            );
                        }
                    }
                    std::thread::sleep(Duration::from_millis(20));
                }
            })?;
    }
    let report = server
        .wait(duration + Duration::from_secs(5))
        .context("the simulated controller did not finish")?;
    if args.json {
        Ok(serde_json::to_string(&report)?)
    } else {
        Ok(format!(
            "messages sent {}, replies {}, late {}, missing {}\nstates reached: {}\nviolations {}{}\nround trip us: p50 {:.1}, p99 {:.1}, max {:.1}",
            report.messages_sent,
            report.replies,
            report.late_replies,
            report.missing_replies,
            report.states_reached.join(" -> "),
            report.violations,
            report
                .abort_reason
                .as_deref()
                .map(|r| format!(" (last abort: {r})"))
                .unwrap_or_default(),
            report.rtt_us.p50,
            report.rtt_us.p99,
            report.rtt_us.max,
        ))
    }
}
