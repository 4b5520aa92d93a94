//! `isochron calibrate (camera|latency|pendulum|camera-robot|robot) [--config FILE]
//! [--scenario FILE] [--seed S] [--out FILE] [--json]`: one calibration step; its
//! result, residuals, date and revision go into the calibration file (CONTRACT.md).
//!
//! On a scenario's simulated world the truth is hidden in the simulators
//! (`rt_core::calibration::simworld`) and reported beside the estimate; nothing of
//! it goes into the file.

use std::path::PathBuf;

use anyhow::Context;
use rt_core::{
    calibration::{
        CalibrationFile, StepRecord,
        simworld::{self, HiddenWorld},
    },
    params::Scenario,
};
use serde_json::json;

/// The steps, in the order a lab runs them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Step {
    /// Camera intrinsics and distortion from a chessboard.
    Camera,
    /// Camera latency by the magnet board's LED.
    Latency,
    /// Pendulum: rest point, free-swing fit (length, damping).
    Pendulum,
    /// The camera's pose in the robot base frame and the intercept point.
    CameraRobot,
    /// Robot command-to-motion latency and servo lag (a small excitation through FRI).
    Robot,
}

impl Step {
    fn name(self) -> &'static str {
        match self {
            Self::Camera => "camera",
            Self::Latency => "latency",
            Self::Pendulum => "pendulum",
            Self::CameraRobot => "camera-robot",
            Self::Robot => "robot",
        }
    }
}

/// Arguments of `isochron calibrate`.
#[derive(Debug, clap::Args)]
pub struct CalibrateArgs {
    /// The step to run.
    #[arg(value_enum)]
    pub step: Step,
    /// The real lab's configuration (lab.mode = "real"): run the step on the hardware.
    #[arg(long, conflicts_with = "scenario")]
    pub config: Option<PathBuf>,
    /// A scenario: run the step on its simulated world (default: the paper's lab).
    #[arg(long)]
    pub scenario: Option<PathBuf>,
    /// The simulated world's session (its hidden draw).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Pendulum step: the angle the magnet holds the ball at before the release, degrees.
    #[arg(long, default_value_t = 25.0)]
    pub release_deg: f64,
    /// The calibration file to update (other steps' results in it are kept).
    #[arg(long, default_value = "calibration.toml")]
    pub out: PathBuf,
    /// Print one JSON object instead of a summary.
    #[arg(long)]
    pub json: bool,
    /// Accuracy check instead of a calibration: run the step on N hidden draws
    /// (seeds seed..seed+N) of the simulated world, report each error against the
    /// truth and the worst against the target; writes nothing.
    #[arg(long, value_name = "N")]
    pub accuracy: Option<u64>,
}

/// The acceptance targets (absolute error).
const TARGET_LENGTH_M: f64 = 0.003;
const TARGET_CAMERA_LATENCY_MS: f64 = 2.0;
const TARGET_ROBOT_LATENCY_MS: f64 = 1.0;

/// One draw of a step: (the figure, its estimate, its truth).
fn one_draw(
    step: Step,
    scenario: &Scenario,
    seed: u64,
) -> anyhow::Result<(&'static str, f64, f64, f64)> {
    let world = HiddenWorld::draw(scenario, seed);
    Ok(match step {
        Step::Pendulum => {
            let r = simworld::run_pendulum(scenario, &world, seed, 25.0, 20.0)?;
            (
                "length_m",
                r.calibration.swing.length_m,
                r.true_length_m,
                TARGET_LENGTH_M,
            )
        }
        Step::Latency => {
            let r = simworld::run_led_latency(scenario, &world, seed, 40, true)?;
            (
                "camera_latency_ms",
                r.result.latency_ms,
                r.true_latency_ms,
                TARGET_CAMERA_LATENCY_MS,
            )
        }
        Step::Robot => {
            let r = simworld::run_robot(scenario, &world, seed, 0.02, 4.0)?;
            (
                "robot_latency_ms",
                r.result.latency_ms,
                r.true_latency_ms,
                TARGET_ROBOT_LATENCY_MS,
            )
        }
        Step::Camera | Step::CameraRobot => anyhow::bail!(
            "calibrate {}: this step is not implemented yet (pendulum, latency and robot are)",
            step.name()
        ),
    })
}

fn accuracy(args: &CalibrateArgs, scenario: &Scenario, n: u64) -> anyhow::Result<String> {
    if n == 0 || n > 1000 {
        anyhow::bail!("--accuracy = {n} is out of range: must be 1..=1000");
    }
    let mut rows = Vec::new();
    let mut worst: f64 = 0.0;
    let mut name = "";
    let mut target = 0.0;
    for seed in args.seed..args.seed + n {
        let (figure, estimate, truth, t) = one_draw(args.step, scenario, seed)
            .with_context(|| format!("calibrate {} (seed {seed})", args.step.name()))?;
        name = figure;
        target = t;
        worst = worst.max((estimate - truth).abs());
        rows.push(
            json!({"seed": seed, "estimate": estimate, "truth": truth, "error": estimate - truth}),
        );
    }
    let summary = json!({
        "step": args.step.name(),
        "source": format!("simulated world (scenario {}), hidden draws", scenario.name),
        "figure": name,
        "draws": rows,
        "max_abs_error": worst,
        "target": target,
        "within_target": worst <= target,
    });
    if args.json {
        return Ok(summary.to_string());
    }
    let mut out = format!(
        "calibrate {} accuracy over {n} hidden draws of the simulated world (scenario {}):\n| seed | {name} estimate | truth | error |\n|---|---|---|---|\n",
        args.step.name(),
        scenario.name
    );
    for r in &rows {
        out.push_str(&format!(
            "| {} | {:.4} | {:.4} | {:+.4} |\n",
            r["seed"],
            r["estimate"].as_f64().unwrap_or(f64::NAN),
            r["truth"].as_f64().unwrap_or(f64::NAN),
            r["error"].as_f64().unwrap_or(f64::NAN)
        ));
    }
    out.push_str(&format!(
        "max |error| {worst:.4} (target {target}): {}",
        if worst <= target { "within" } else { "OUTSIDE" }
    ));
    Ok(out)
}

/// `date` as RFC 3339 UTC, from the system clock.
fn utc_now() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let days = i64::try_from(secs / 86_400).unwrap_or(0);
    let rem = secs % 86_400;
    // Civil date from days since 1970-01-01 (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}Z",
        rem / 3600,
        (rem / 60) % 60,
        rem % 60
    )
}

fn step_record<T>((date, revision, source): (String, String, String), result: T) -> StepRecord<T> {
    StepRecord {
        date,
        revision,
        source,
        result,
    }
}

/// Runs one step; returns the text for stdout. Nothing is written unless the step
/// gave a result.
pub fn run(args: &CalibrateArgs) -> anyhow::Result<String> {
    if let Some(config) = &args.config {
        anyhow::bail!(
            "calibrate {} --config {}: the real-lab procedure of this step is not implemented yet \
             (run it on a scenario's simulated world with --scenario)",
            args.step.name(),
            config.display()
        );
    }
    let scenario = match &args.scenario {
        Some(p) => Scenario::from_file(p)?,
        None => Scenario::default(),
    };
    if let Some(n) = args.accuracy {
        return accuracy(args, &scenario, n);
    }
    // Read the file first: a broken calibration file is an error before anything runs.
    let mut file = CalibrationFile::load_or_empty(&args.out)?;
    let world = HiddenWorld::draw(&scenario, args.seed);
    let source = format!(
        "simulated world (scenario {}, seed {})",
        scenario.name, args.seed
    );
    let record = |step_source: &str| {
        (
            utc_now(),
            server::VERSION.to_owned(),
            step_source.to_owned(),
        )
    };
    let (result, truth, error) = match args.step {
        Step::Pendulum => {
            if !(args.release_deg.is_finite() && (0.0..=60.0).contains(&args.release_deg)) {
                anyhow::bail!(
                    "--release-deg = {} is out of range: must be 0..=60",
                    args.release_deg
                );
            }
            let run = simworld::run_pendulum(&scenario, &world, args.seed, args.release_deg, 20.0)
                .context("calibrate pendulum")?;
            let c = &run.calibration;
            let out = (
                serde_json::to_value(c)?,
                json!({"length_m": run.true_length_m, "damping_per_s": run.true_damping_per_s,
                       "rest_m": run.true_rest_m}),
                json!({"length_m": c.swing.length_m - run.true_length_m,
                       "damping_per_s": c.swing.damping_per_s - run.true_damping_per_s,
                       "rest_height_m": run.rest_m[2] - run.true_rest_m[2]}),
            );
            file.pendulum = Some(step_record(record(&source), run.calibration));
            out
        }
        Step::Latency => {
            let run = simworld::run_led_latency(&scenario, &world, args.seed, 40, true)
                .context("calibrate latency")?;
            let out = (
                serde_json::to_value(&run.result)?,
                json!({"camera_latency_ms": run.true_latency_ms}),
                json!({"camera_latency_ms": run.result.latency_ms - run.true_latency_ms}),
            );
            file.latency = Some(step_record(record(&source), run.result));
            out
        }
        Step::Robot => {
            let run = simworld::run_robot(&scenario, &world, args.seed, 0.02, 4.0)
                .context("calibrate robot")?;
            let out = (
                serde_json::to_value(&run.result)?,
                json!({"robot_latency_ms": run.true_latency_ms,
                       "servo_time_constant_ms": run.true_servo_time_constant_ms}),
                json!({"robot_latency_ms": run.result.latency_ms - run.true_latency_ms,
                       "servo_time_constant_ms": run.result.servo_time_constant_ms
                           - run.true_servo_time_constant_ms}),
            );
            file.robot = Some(step_record(record(&source), run.result));
            out
        }
        Step::Camera | Step::CameraRobot => anyhow::bail!(
            "calibrate {}: this step is not implemented yet (pendulum, latency and robot are)",
            args.step.name()
        ),
    };
    // The beliefs with the new file must still be a valid lab.
    file.apply(&scenario)
        .with_context(|| format!("calibrate {}: the result", args.step.name()))?;
    file.write(&args.out)?;
    let summary = json!({
        "step": args.step.name(),
        "source": source,
        "file": args.out.display().to_string(),
        "result": result,
        "truth": truth,
        "error": error,
    });
    if args.json {
        return Ok(summary.to_string());
    }
    Ok(format!(
        "calibrate {} on the {source}: written to {}\nresult: {}\nerror against the hidden truth: {}",
        args.step.name(),
        args.out.display(),
        serde_json::to_string_pretty(&summary["result"])?,
        summary["error"]
    ))
}
