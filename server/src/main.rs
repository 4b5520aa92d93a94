//! `isochron`: the lab service and its command-line tools (CONTRACT.md, "Commands").

// Outside tests the service returns errors and never panics on them: no
// `unwrap()`/`expect()` (tests may: clippy.toml's allow-*-in-tests).
#![cfg_attr(not(test), warn(clippy::unwrap_used, clippy::expect_used))]

use std::{net::SocketAddr, path::PathBuf, process::ExitCode};

use clap::{Parser, Subcommand};
use rt_core::params::Scenario;
use tracing_subscriber::EnvFilter;

mod cmd;
mod plot;

#[derive(Debug, Parser)]
#[command(name = "isochron", version = server::VERSION, about = "Timed interception of a swinging ball by a KUKA LBR iiwa 7")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the lab service (the simulated lab unless a config says otherwise: a
    /// truthful world in this process behind a real lab's interfaces, its stand
    /// following each trial's distance; `make firmware` builds its magnet board).
    Serve {
        /// Service and hardware configuration (TOML, e.g. config/lab.toml).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Address to listen on (default 127.0.0.1:8080); anything but loopback needs --token.
        #[arg(long)]
        bind: Option<SocketAddr>,
        /// Bearer token required for every command endpoint.
        #[arg(long, env = "ISOCHRON_TOKEN")]
        token: Option<String>,
        /// Folder of the built dashboard (default: web/dist of this source tree).
        #[arg(long)]
        web_dir: Option<PathBuf>,
        /// Where trial records and recordings go (default: ./data).
        #[arg(long)]
        data_dir: Option<PathBuf>,
        /// A parameter file laid over the lab's scenario (a partial scenario, e.g. the
        /// [ekf] file `isochron tune` writes); repeat to lay several in order.
        #[arg(long)]
        params: Vec<PathBuf>,
        /// The calibration file `isochron calibrate` writes (default: the config's
        /// lab.calibration_file); a real lab refuses trials without one.
        #[arg(long)]
        calibration: Option<PathBuf>,
        /// Also run a Foxglove WebSocket server on this address (loopback only, e.g.
        /// 127.0.0.1:8765): the arm, pendulum, camera and plots live in Foxglove.
        #[arg(long)]
        foxglove: Option<SocketAddr>,
        /// The real-time measures of the lab's FRI threads: `auto` (all of them
        /// with two or more CPUs, `fifo,mlock` on one), `all`, `none`, or a
        /// comma-separated list of `fifo`, `pin`, `isolate`, `mlock`, `spin`.
        #[arg(long, default_value = "auto")]
        rt_tuning: String,
        /// Serve a real lab on this scenario's simulated world, run in this process
        /// (its [world], or a truthful one; as `isochron world` runs it: FRI cabinet,
        /// webcam stream, magnet firmware in simavr). Not with --config.
        #[arg(long)]
        scenario: Option<PathBuf>,
        /// Seed of the served world's draws (--scenario's, or the simulated lab's).
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Let a real lab (or a --scenario world with [world]) run trials before it is calibrated.
        #[arg(long)]
        allow_uncalibrated: bool,
        /// Demo mode: run trials unattended with varied distances and movement
        /// times (the kiosk page /demo; GET /api/demo). A real lab runs them only
        /// while an operator's heartbeat holds the demo enabled.
        #[arg(long)]
        demo: bool,
        /// Seconds from one demo trial's start to the next (default 10; with --demo).
        #[arg(long)]
        demo_interval_s: Option<f64>,
    },
    /// One calibration step (camera, latency, pendulum, camera-robot, robot, contact); writes the calibration file.
    Calibrate(cmd::calibrate::CalibrateArgs),
    /// Estimate the EKF's noise parameters from a recorded trial (writes an [ekf] file and Fig. 4).
    Tune(cmd::tune::TuneArgs),
    /// Run N closed-loop trials of a scenario in virtual time and judge them on ground truth.
    Trials(cmd::trials::TrialsArgs),
    /// Combine the --json outputs of `trials --shard I/N` into the unsharded run's summary.
    Merge(cmd::merge::MergeArgs),
    /// Measure the hot paths and the real-time loop (1 ms FRI over loopback UDP).
    Bench(cmd::bench::BenchArgs),
    /// iiwa 7 kinematics: forward (fk), inverse (ik) and motion planning (plan).
    Kin(cmd::kin::KinArgs),
    /// Switch the pendulum's magnet or ask its state (the Arduino firmware over serial); prints JSON.
    Magnet(cmd::magnet::MagnetArgs),
    /// Run trials across distances and movement times and write a report beside the paper's results;
    /// `--envelope`: the reality lab's robustness envelope per world factor.
    Eval(cmd::eval::EvalArgs),
    /// A standalone simulated KUKA FRI controller (FRI 1.11 to 2.7, --fri-version).
    FriSim(cmd::fri_sim::FriSimArgs),
    /// The lab's hardware as a process: a scenario's world behind a KUKA cabinet (FRI),
    /// a webcam stream (MJPEG over HTTP) and the magnet firmware on a pty; writes the
    /// lab configuration for `serve --config` and one truth line per release.
    World(cmd::world::WorldArgs),
    /// The FRI link: `fri doctor` diagnoses the connection to the robot controller.
    Fri {
        #[command(subcommand)]
        command: cmd::fri_doctor::FriCommand,
    },
    /// Run the ball detector over a recorded video.
    Detect(cmd::detect::DetectArgs),
    /// Scenario files.
    Scenario {
        #[command(subcommand)]
        command: ScenarioCommand,
    },
}

#[derive(Debug, Subcommand)]
enum ScenarioCommand {
    /// Validate a scenario file and print it fully resolved (defaults filled in) as JSON.
    Check {
        /// The scenario file (TOML).
        file: PathBuf,
    },
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        // Colours on a terminal only: a log redirected to a file or read by
        // journald stays plain text.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // One line naming what was wrong (CONTRACT.md).
            let chain: Vec<String> = e.chain().map(ToString::to_string).collect();
            eprintln!("isochron: {}", chain.join(": "));
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Serve {
            config,
            bind,
            token,
            web_dir,
            data_dir,
            params,
            calibration,
            foxglove,
            rt_tuning,
            scenario,
            seed,
            allow_uncalibrated,
            demo,
            demo_interval_s,
        } => server::serve::run(server::serve::ServeArgs {
            config,
            bind,
            token,
            web_dir,
            data_dir,
            params,
            calibration,
            foxglove,
            rt_tuning: Some(
                rt_core::fri::priority::RtTuning::parse(&rt_tuning)
                    .map_err(|e| anyhow::anyhow!("--rt-tuning: {e}"))?,
            ),
            world: scenario,
            world_seed: seed,
            allow_uncalibrated,
            demo,
            demo_interval_s,
        }),
        Command::Tune(args) => print_out(&cmd::tune::run(args)?),
        Command::Calibrate(args) => print_out(&cmd::calibrate::run(&args)?),
        Command::Trials(args) => print_out(&cmd::trials::run(&args)?),
        Command::Merge(args) => print_out(&cmd::merge::run(&args)?),
        Command::Bench(args) => print_out(&cmd::bench::run(&args)?),
        Command::Kin(args) => cmd::kin::run(args),
        Command::Magnet(args) => print_out(&cmd::magnet::run(args)?),
        Command::Eval(args) => print_out(&cmd::eval::run(&args)?),
        Command::FriSim(args) => print_out(&cmd::fri_sim::run(&args)?),
        Command::World(args) => print_out(&cmd::world::run(&args)?),
        Command::Fri {
            command: cmd::fri_doctor::FriCommand::Doctor(args),
        } => {
            let (report, ok) = cmd::fri_doctor::run(args)?;
            print_out(&report)?;
            if ok {
                Ok(())
            } else {
                // The report says why; the status says that.
                std::process::exit(2)
            }
        }
        Command::Detect(args) => cmd::detect::run(&args),
        Command::Scenario {
            command: ScenarioCommand::Check { file },
        } => {
            let scenario = Scenario::from_file(&file)?;
            print_out(&serde_json::to_string_pretty(&scenario)?)
        }
    }
}

/// Writes a line to stdout; a closed pipe (`| head`) is not an error.
fn print_out(text: &str) -> anyhow::Result<()> {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    match writeln!(out, "{text}").and_then(|()| out.flush()) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e.into()),
        _ => Ok(()),
    }
}
