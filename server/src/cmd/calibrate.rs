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
    calibration::{CalibrationFile, Unwatched, simworld::HiddenWorld},
    params::Scenario,
};
use serde_json::json;
use server::calibration::{
    Step, StepOptions, TARGET_CAMERA_POSITION_MM, TARGET_CAMERA_ROTATION_DEG, TARGET_INTERCEPT_MM,
    run_step, stamp,
};

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
    /// Camera-robot step: leave out the touch of the hanging ball (the intercept
    /// point's depth is then the believed swing plane).
    #[arg(long)]
    pub no_touch: bool,
    /// Camera-robot step: cover the marker (a check that the step refuses).
    #[arg(long, hide = true)]
    pub hide_marker: bool,
    /// Camera step: board views the virtual operator holds up.
    #[arg(long, default_value_t = StepOptions::default().views)]
    pub views: usize,
    /// Camera step: the operator holds the board outside the camera's view (a
    /// check that the step refuses, "no board visible", and writes nothing).
    #[arg(long, hide = true)]
    pub board_out_of_view: bool,
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

fn accuracy(
    args: &CalibrateArgs,
    scenario: &Scenario,
    n: u64,
    opts: StepOptions,
) -> anyhow::Result<String> {
    if n == 0 || n > 1000 {
        anyhow::bail!("--accuracy = {n} is out of range: must be 1..=1000");
    }
    if args.step == Step::CameraRobot {
        return accuracy_camera_robot(args, scenario, n, opts);
    }
    let mut rows = Vec::new();
    let mut worst: f64 = 0.0;
    let mut name = "";
    let mut target = 0.0;
    for seed in args.seed..args.seed + n {
        let world = HiddenWorld::draw(scenario, seed);
        let t0 = std::time::Instant::now();
        let out = run_step(args.step, scenario, &world, seed, opts, &mut Unwatched)
            .with_context(|| format!("calibrate {} (seed {seed})", args.step.name()))?;
        let (figure, estimate, truth, t) = out.figure;
        name = figure;
        target = t;
        worst = worst.max((estimate - truth).abs());
        rows.push(json!({"seed": seed, "estimate": estimate, "truth": truth,
                         "error": estimate - truth, "errors": out.error,
                         "rms_px": out.result["rms_px"], "views_used": out.result["views_used"],
                         "run_s": t0.elapsed().as_secs_f64()}));
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
            "| {} | {:.4} | {:.4} | {:+.4} |",
            r["seed"],
            r["estimate"].as_f64().unwrap_or(f64::NAN),
            r["truth"].as_f64().unwrap_or(f64::NAN),
            r["error"].as_f64().unwrap_or(f64::NAN)
        ));
        if args.step == Step::Camera {
            let e = &r["errors"];
            let f = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
            out.push_str(&format!(
                " fx {:+.2} px, cx {:+.2} px, cy {:+.2} px, corners {:.2} px (100 px in: {:.2}), \
                 RMS {:.3} px, {} views, {:.1} s",
                f(&e["fx_px"]),
                f(&e["cx_px"]),
                f(&e["cy_px"]),
                f(&e["corner_px"]),
                f(&e["corner_inner_px"]),
                f(&r["rms_px"]),
                r["views_used"],
                f(&r["run_s"])
            ));
        }
        out.push('\n');
    }
    out.push_str(&format!(
        "max |error| {worst:.4} (target {target}): {}",
        if worst <= target { "within" } else { "OUTSIDE" }
    ));
    Ok(out)
}

/// `--accuracy N` of the camera-robot step: its three figures per draw (the
/// camera's rotation and position, the intercept point), with the beliefs'
/// errors before the step and the run time.
fn accuracy_camera_robot(
    args: &CalibrateArgs,
    scenario: &Scenario,
    n: u64,
    opts: StepOptions,
) -> anyhow::Result<String> {
    let mut rows = Vec::new();
    let (mut rot, mut pos, mut icp): (f64, f64, f64) = (0.0, 0.0, 0.0);
    for seed in args.seed..args.seed + n {
        let world = HiddenWorld::draw(scenario, seed);
        let t0 = std::time::Instant::now();
        let out = run_step(args.step, scenario, &world, seed, opts, &mut Unwatched)
            .with_context(|| format!("calibrate camera-robot (seed {seed})"))?;
        let secs = t0.elapsed().as_secs_f64();
        let e = out.error.clone();
        let f = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
        rot = rot.max(f(&e["camera_rotation_deg"]));
        pos = pos.max(f(&e["camera_position_mm"]));
        icp = icp.max(f(&e["intercept_mm"]));
        rows.push(json!({"seed": seed, "error": e,
                         "reprojection_rms_px": out.result["reprojection_rms_px"],
                         "poses": out.result["poses"], "k1": out.result["k1"],
                         "run_s": secs}));
    }
    let within = rot <= TARGET_CAMERA_ROTATION_DEG
        && pos <= TARGET_CAMERA_POSITION_MM
        && icp <= TARGET_INTERCEPT_MM;
    let summary = json!({
        "step": args.step.name(),
        "source": format!("simulated world (scenario {}), hidden draws", scenario.name),
        "draws": rows,
        "max_error": {"camera_rotation_deg": rot, "camera_position_mm": pos, "intercept_mm": icp},
        "target": {"camera_rotation_deg": TARGET_CAMERA_ROTATION_DEG,
                   "camera_position_mm": TARGET_CAMERA_POSITION_MM,
                   "intercept_mm": TARGET_INTERCEPT_MM},
        "within_target": within,
    });
    if args.json {
        return Ok(summary.to_string());
    }
    let mut out = format!(
        "calibrate camera-robot accuracy over {n} hidden draws of the simulated world (scenario {}):\n\
         | seed | rotation err deg (before) | position err mm (before) | intercept err mm (before) | rms px | poses | run s |\n\
         |---|---|---|---|---|---|---|\n",
        scenario.name
    );
    for r in &rows {
        let e = &r["error"];
        let f = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
        out.push_str(&format!(
            "| {} | {:.3} ({:.3}) | {:.2} ({:.2}) | {:.2} ({:.2}) | {:.2} | {} | {:.1} |\n",
            r["seed"],
            f(&e["camera_rotation_deg"]),
            f(&e["before"]["camera_rotation_deg"]),
            f(&e["camera_position_mm"]),
            f(&e["before"]["camera_position_mm"]),
            f(&e["intercept_mm"]),
            f(&e["before"]["intercept_mm"]),
            f(&r["reprojection_rms_px"]),
            r["poses"],
            f(&r["run_s"]),
        ));
    }
    out.push_str(&format!(
        "max error: rotation {rot:.3} deg (target {TARGET_CAMERA_ROTATION_DEG}), position {pos:.2} mm \
         (target {TARGET_CAMERA_POSITION_MM}), intercept {icp:.2} mm (target {TARGET_INTERCEPT_MM}): {}",
        if within { "within" } else { "OUTSIDE" }
    ));
    Ok(out)
}

/// Runs one step; returns the text for stdout. Nothing is written unless the step
/// gave a result.
pub fn run(args: &CalibrateArgs) -> anyhow::Result<String> {
    if let Some(config) = &args.config {
        anyhow::bail!(
            "calibrate {step} --config {cfg}: on a real lab the steps run in the service, through \
             the lab's own robot, camera and magnet: `isochron serve --config {cfg}`, then `POST \
             /api/calibration/{step}` (or the dashboard's Calibration panel)",
            step = args.step.name(),
            cfg = config.display()
        );
    }
    let scenario = match &args.scenario {
        Some(p) => Scenario::from_file(p)?,
        None => Scenario::default(),
    };
    if !(args.release_deg.is_finite() && (0.0..=60.0).contains(&args.release_deg)) {
        anyhow::bail!(
            "--release-deg = {} is out of range: must be 0..=60",
            args.release_deg
        );
    }
    let opts = StepOptions {
        release_deg: args.release_deg,
        touch: !args.no_touch,
        marker_visible: !args.hide_marker,
        views: args.views,
        board_visible: !args.board_out_of_view,
    };
    if let Some(n) = args.accuracy {
        return accuracy(args, &scenario, n, opts);
    }
    // Read the file first: a broken calibration file is an error before anything runs.
    let mut file = CalibrationFile::load_or_empty(&args.out)?;
    // The camera step's lens is a belief the later steps use (camera-robot's PnP).
    let mut scenario = scenario;
    if let Some(c) = &file.camera {
        scenario.camera.intrinsics = Some(c.result.intrinsics);
    }
    let world = HiddenWorld::draw(&scenario, args.seed);
    let source = format!(
        "simulated world (scenario {}, seed {})",
        scenario.name, args.seed
    );
    let outcome = run_step(
        args.step,
        &scenario,
        &world,
        args.seed,
        opts,
        &mut Unwatched,
    )?;
    let (result, truth, error) = (
        outcome.result.clone(),
        outcome.truth.clone(),
        outcome.error.clone(),
    );
    outcome.record_into(&mut file, stamp(&source));
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

#[cfg(test)]
mod tests {
    use super::*;

    fn args(step: Step, out: PathBuf) -> CalibrateArgs {
        CalibrateArgs {
            step,
            config: None,
            scenario: Some(PathBuf::from(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/../scenarios/reality.toml"
            ))),
            seed: 1,
            release_deg: 25.0,
            no_touch: false,
            hide_marker: false,
            views: StepOptions::default().views,
            board_out_of_view: false,
            out,
            json: true,
            accuracy: None,
        }
    }

    /// The board never in view: a clear message, and the calibration file is
    /// neither created nor changed.
    #[test]
    fn camera_step_without_a_board_writes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("calibration.toml");
        let mut a = args(Step::Camera, out.clone());
        a.board_out_of_view = true;
        let e = format!("{:#}", run(&a).unwrap_err());
        assert!(e.contains("calibrate camera: no board visible"), "{e}");
        assert!(!out.exists(), "nothing written");
        let before = "[latency]\ndate = \"d\"\nrevision = \"r\"\nsource = \"s\"\n\
                      [latency.result]\nlatency_ms = 40.0\nbound_ms = 0.5\nspread_ms = 1.0\n\
                      serial_one_way_ms = 1.0\nframe_period_ms = 33.3\nedges = 40\nedges_seen = 40\n\
                      edges_consistent = 40\nframes = 300\n";
        assert!(CalibrationFile::from_toml_str(before).is_ok());
        std::fs::write(&out, before).unwrap();
        let e = format!("{:#}", run(&a).unwrap_err());
        assert!(e.contains("no board visible"), "{e}");
        assert_eq!(std::fs::read_to_string(&out).unwrap(), before, "unchanged");
    }
}
