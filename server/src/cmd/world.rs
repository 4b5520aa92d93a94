//! `isochron world`: the lab's hardware as a process of its own, the world
//! of a scenario (its `[world]`, or a truthful one) on the wall clock behind
//! the interfaces a real lab has, and nothing else:
//!
//! - **the KUKA cabinet** over FRI UDP: the simulated controller
//!   (`sim::kuka`) with the world's robot (latency and drift, servo, joint
//!   noise, torque trip) and the external torques of the ball's contacts;
//! - **the webcam**: frames of the world's true ball as its true camera takes
//!   them (`sim::world::webcam`), served as MJPEG over HTTP
//!   (`http://127.0.0.1:PORT/video.mjpg`, what an IP camera serves and
//!   OpenCV's `VideoCapture` opens), each delivered at its true latency;
//! - **the Arduino**: the magnet firmware in simavr behind a pseudo-terminal
//!   (`firmware/magnet`, `make firmware`); its coil pin lets the world's ball
//!   go after the world's release delay, and switching it on hangs the ball
//!   on the magnet (the operator's hands); its LED pin lights a spot in the
//!   frames.
//!
//! It writes `--lab-config` (the real-lab configuration for this hardware,
//! read by `isochron serve --config`, with the lab's beliefs beside it as
//! `<name>.scenario.toml`) once everything answers, and one JSON line per
//! release to `--truth` (`sim::world::live::ReleaseTruth`, times as Unix
//! seconds). Nothing in `isochron serve --config` knows it talks to a world.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::Args;
use rt_core::fri::FriVersion;
use rt_core::params::{Scenario, check};
use server::world::{LabWorld, WorldSpec, default_firmware_dir};

/// Arguments of `isochron world`.
#[derive(Debug, Args)]
pub struct WorldArgs {
    /// The world: a scenario file (its `[world]`; without one, a truthful world).
    #[arg(long)]
    pub scenario: PathBuf,
    /// Seed of the world's draws.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Where to write the lab's configuration for `isochron serve --config`
    /// (the lab's beliefs go beside it, `<name>.scenario.toml`; the magnet's
    /// serial port is `<name>.tty`).
    #[arg(long)]
    pub lab_config: PathBuf,
    /// Where to write one JSON line per release the world saw.
    #[arg(long)]
    pub truth: PathBuf,
    /// The FRI version the cabinet speaks: 1.11, 1.14, 1.15, 1.16, 2.5 or 2.7.
    #[arg(long, default_value = "1.15")]
    pub fri_version: FriVersion,
    /// Where the pendulum hangs: the distance from the robot's base to the
    /// ball at rest, m (default: the middle of the scenario's `task.distance_m`).
    #[arg(long)]
    pub distance_m: Option<f64>,
    /// The folder of the magnet firmware and its simavr host (default: this
    /// source tree's `firmware/magnet/build`, `make firmware`).
    #[arg(long)]
    pub firmware_dir: Option<PathBuf>,
    /// Write `lab.allow_uncalibrated = true` into the lab configuration (for a
    /// truthful world, whose beliefs are its truth).
    #[arg(long)]
    pub allow_uncalibrated: bool,
    /// The service the operator watches (`http://HOST:PORT`): while its
    /// camera step asks for the chessboard at a pose, the operator holds it
    /// there in front of the webcam.
    #[arg(long)]
    pub operator: Option<String>,
    /// Stop after this many seconds (default: run until killed).
    #[arg(long)]
    pub duration_s: Option<f64>,
}

/// Runs the world until killed (or `--duration-s`); returns a summary.
pub fn run(args: &WorldArgs) -> anyhow::Result<String> {
    let scenario = Scenario::from_file(&args.scenario)?;
    if let Some(d) = args.duration_s {
        check::within("--duration-s", d, 0.1, 30.0 * 86_400.0)?;
    }
    let config_dir = args
        .lab_config
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    if !config_dir.is_dir() {
        bail!(
            "--lab-config: the folder {} does not exist",
            config_dir.display()
        );
    }
    let beliefs_path = args.lab_config.with_extension("scenario.toml");
    let mut truth_file = std::fs::File::create(&args.truth)
        .with_context(|| format!("--truth: cannot write {}", args.truth.display()))?;
    // The cabinet's controller thread takes SCHED_FIFO when allowed (see
    // `fri-sim`): a real cabinet is a machine of its own.
    rt_core::fri::priority::enable();
    let mut world = LabWorld::start(&WorldSpec {
        scenario,
        seed: args.seed,
        fri_version: args.fri_version,
        distance_m: args.distance_m,
        firmware_dir: args
            .firmware_dir
            .clone()
            .unwrap_or_else(default_firmware_dir),
        serial_port: args.lab_config.with_extension("tty"),
        stand: None,
    })?;
    if let Some(service) = &args.operator {
        world.start_operator(service)?;
    }
    // The lab's configuration for this hardware: written last, once all answers.
    std::fs::write(&beliefs_path, world.beliefs().to_toml_string())
        .with_context(|| format!("cannot write {}", beliefs_path.display()))?;
    let mut cfg = world.lab_config(&beliefs_path);
    cfg.lab.allow_uncalibrated = args.allow_uncalibrated;
    let text = toml::to_string_pretty(&cfg).context("the lab configuration")?;
    let tmp = args.lab_config.with_extension("toml.part");
    std::fs::write(&tmp, text).with_context(|| format!("cannot write {}", tmp.display()))?;
    std::fs::rename(&tmp, &args.lab_config)
        .with_context(|| format!("cannot write {}", args.lab_config.display()))?;
    let mut ready = serde_json::to_value(&world.ready)?;
    ready["lab_config"] = serde_json::to_value(&args.lab_config)?;
    println!("{ready}");
    std::io::stdout().flush()?;
    let r = &world.ready;
    eprintln!(
        "isochron world: a {} world (seed {}): FRI {} cabinet on {} -> {}, webcam {}, Arduino on {}; lab configuration {}",
        r.world,
        args.seed,
        args.fri_version,
        r.fri_controller,
        r.fri_client,
        r.camera_url,
        r.serial_port.display(),
        args.lab_config.display()
    );
    let started = Instant::now();
    while args
        .duration_s
        .is_none_or(|d| started.elapsed().as_secs_f64() < d)
    {
        world.poll(&mut truth_file, Duration::from_millis(100))?;
    }
    let (releases, frames) = world.counts();
    Ok(format!(
        "isochron world: {releases} releases, {frames} frames served"
    ))
}
