//! `isochron fri doctor`: what is wrong with the FRI connection, in plain words
//! (`rt_core::fri::doctor`). Reads the lab config's `[fri]` section (address,
//! controller, period, version), listens where the client would, answers as the
//! client would, and prints its findings; exit status 0 only when a session
//! could be established. The last report is also written to
//! `<data_dir>/fri-doctor.json`, where the dashboard's FRI panel shows it.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::{Args, Subcommand};
use rt_core::fri::FriVersion;
use rt_core::fri::doctor::{self, DoctorParams, DoctorReport};
use rt_core::params::check;

use server::config::ServeConfig;

use server::FRI_DOCTOR_REPORT_FILE as REPORT_FILE;

/// `isochron fri ...`.
#[derive(Debug, Subcommand)]
pub enum FriCommand {
    /// Diagnose the FRI connection: listens where the client would and says what it sees.
    Doctor(DoctorArgs),
}

/// Arguments of `isochron fri doctor`.
#[derive(Debug, Args)]
pub struct DoctorArgs {
    /// The lab config (TOML) whose [fri] section is checked (default: its defaults).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Listen here instead of fri.local_bind.
    #[arg(long)]
    pub listen: Option<SocketAddr>,
    /// How long to listen, seconds.
    #[arg(long, default_value_t = 3.0)]
    pub seconds: f64,
    /// The controller's address instead of fri.controller ("any": answer any sender).
    #[arg(long)]
    pub controller: Option<String>,
    /// The expected send period instead of fri.period_ms.
    #[arg(long)]
    pub period_ms: Option<u32>,
    /// The expected FRI version instead of fri.version.
    #[arg(long)]
    pub fri_version: Option<FriVersion>,
    /// Other ports to watch for the controller's datagrams (default: KUKA's range 30200-30209).
    #[arg(long, default_value = "30200-30209")]
    pub scan_ports: String,
    /// Only listen; do not answer the controller.
    #[arg(long)]
    pub no_answer: bool,
    /// Where the last report is written (default: the config's server.data_dir).
    #[arg(long)]
    pub data_dir: Option<PathBuf>,
    /// Print the report as JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

fn parse_ports(s: &str) -> anyhow::Result<Vec<u16>> {
    let s = s.trim();
    if s.is_empty() || s == "none" {
        return Ok(Vec::new());
    }
    let (a, b) = s.split_once('-').unwrap_or((s, s));
    let lo: u16 = a
        .trim()
        .parse()
        .context("--scan-ports: expected PORT or LO-HI")?;
    let hi: u16 = b
        .trim()
        .parse()
        .context("--scan-ports: expected PORT or LO-HI")?;
    anyhow::ensure!(
        lo >= 1 && lo <= hi && hi - lo < 64,
        "--scan-ports: expected LO-HI with 1 <= LO <= HI and at most 64 ports, got {s}"
    );
    Ok((lo..=hi).collect())
}

/// Runs the doctor; returns its report (text or JSON) and whether a session
/// could be established.
pub fn run(args: DoctorArgs) -> anyhow::Result<(String, bool)> {
    check::within("--seconds", args.seconds, 0.1, 600.0)?;
    let cfg = match &args.config {
        Some(path) => ServeConfig::from_file(path)?,
        None => ServeConfig::default(),
    };
    let controller = match args.controller.as_deref() {
        None => Some(cfg.fri.controller),
        Some("any") => None,
        Some(a) => Some(
            a.parse::<SocketAddr>()
                .with_context(|| format!("--controller: not an address: {a}"))?,
        ),
    };
    let period_ms = args.period_ms.unwrap_or(cfg.fri.period_ms);
    check::within_u32("--period-ms", period_ms, 1, 100)?;
    let params = DoctorParams {
        listen: args.listen.unwrap_or(cfg.fri.local_bind),
        controller,
        period_ms,
        version: args.fri_version.unwrap_or(cfg.fri.version),
        duration: Duration::from_secs_f64(args.seconds),
        scan_ports: parse_ports(&args.scan_ports)?,
        answer: !args.no_answer,
    };
    if !args.json {
        eprintln!(
            "isochron fri doctor: listening on {} for {:.1} s ...",
            params.listen, args.seconds
        );
    }
    let report = doctor::run(&params).context("fri doctor")?;
    let data_dir = args.data_dir.unwrap_or(cfg.server.data_dir);
    save(&report, &data_dir);
    let ok = report.ok();
    let out = if args.json {
        serde_json::to_string(&report)?
    } else {
        report.to_text()
    };
    Ok((out, ok))
}

/// Writes the report for the dashboard; a folder that cannot be written is
/// reported on stderr, not an error of the diagnosis.
fn save(report: &DoctorReport, dir: &std::path::Path) {
    let write = || -> std::io::Result<()> {
        std::fs::create_dir_all(dir)?;
        let json = serde_json::to_vec_pretty(report).map_err(std::io::Error::other)?;
        let tmp = dir.join(format!("{REPORT_FILE}.tmp"));
        std::fs::write(&tmp, json)?;
        std::fs::rename(&tmp, dir.join(REPORT_FILE))
    };
    if let Err(e) = write() {
        eprintln!(
            "isochron fri doctor: cannot write {}: {e}",
            dir.join(REPORT_FILE).display()
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn port_ranges_parse_and_bad_ones_are_refused() {
        assert_eq!(parse_ports("30200-30202").unwrap(), [30200, 30201, 30202]);
        assert_eq!(parse_ports("30205").unwrap(), [30205]);
        assert!(parse_ports("none").unwrap().is_empty());
        for bad in ["x", "30210-30200", "0-3", "1000-2000"] {
            assert!(parse_ports(bad).is_err(), "{bad}");
        }
    }
}
