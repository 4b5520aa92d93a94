//! `isochron calibrate (camera|latency|pendulum|camera-robot|robot)
//! [--scenario FILE] [--seed S] [--release-deg D] [--out FILE] [--json]
//! [--accuracy N]`: one calibration step on a scenario's world; its result,
//! residuals, date and revision go into the calibration file (CONTRACT.md).
//!
//! The step runs as it runs on a real lab, and nowhere else: this process
//! starts the scenario's world (`crate::world`: its cabinet over FRI UDP,
//! its webcam's MJPEG stream, the magnet firmware in simavr on a
//! pseudo-terminal, its operator's hands) and serves a real lab on it as
//! `isochron serve --config` in a child process, which knows nothing of the
//! world; the step is posted to that service (`POST /api/calibration/{step}`)
//! and its job followed to its end. The world's truth (what it drew) is
//! reported beside the estimate; nothing of it goes into the file.

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::{Arc, mpsc};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use rt_core::{
    calibration::{CalibrationFile, StepRecord, extrinsics::rotation_angle_rad},
    params::Scenario,
    vision::{CameraIntrinsics, undistortion_error_px},
};
use serde_json::{Value, json};
use server::calibration::{
    Step, TARGET_CAMERA_LATENCY_MS, TARGET_CAMERA_POSITION_MM, TARGET_CAMERA_ROTATION_DEG,
    TARGET_INTERCEPT_MM, TARGET_K1, TARGET_LENGTH_M, TARGET_ROBOT_LATENCY_MS,
};
use server::world::{LabWorld, WorldReady, WorldSpec, default_firmware_dir, http_json};

/// Arguments of `isochron calibrate`.
#[derive(Debug, clap::Args)]
pub struct CalibrateArgs {
    /// The step to run.
    #[arg(value_enum)]
    pub step: Step,
    /// The real lab's configuration (lab.mode = "real"): its steps run in the
    /// service (`isochron serve --config`), not here.
    #[arg(long, conflicts_with = "scenario")]
    pub config: Option<PathBuf>,
    /// A scenario: run the step on its world (its `[world]`, else a truthful
    /// world of its beliefs; default: the paper's lab).
    #[arg(long)]
    pub scenario: Option<PathBuf>,
    /// The world's draws (the same session `trials --seed S` meets first).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Pendulum step: the angle the ball is hung at before the release, degrees.
    #[arg(long)]
    pub release_deg: Option<f64>,
    /// The calibration file to update (other steps' results in it are kept).
    #[arg(long, default_value = "calibration.toml")]
    pub out: PathBuf,
    /// Print one JSON object instead of a summary.
    #[arg(long)]
    pub json: bool,
    /// Accuracy check instead of a calibration: run the step (after the steps
    /// it needs) on N worlds (seeds seed..seed+N), report each error against
    /// the world's truth and the worst against the target; writes nothing.
    #[arg(long, value_name = "N")]
    pub accuracy: Option<u64>,
    /// The magnet firmware's build (default: this tree's `firmware/magnet/build`).
    #[arg(long, hide = true)]
    pub firmware_dir: Option<PathBuf>,
}

/// How long one step may run, s (the camera step's 16 held poses and the
/// camera-robot step's tour take a minute or two; a starved machine longer).
const STEP_TIMEOUT_S: u64 = 600;
/// How long the lab may take to come up (the robot commanding, the board
/// answering, the camera delivering), s.
const READY_TIMEOUT_S: u64 = 120;
/// How often a step refused for a passing reason is posted again.
const ATTEMPTS: usize = 3;

/// What one step gave on a world.
struct WorldStep {
    /// The job's result (as the service wrote it into the file).
    result: Value,
    /// The step's record from the service's calibration file.
    file: CalibrationFile,
    /// What the world drew.
    ready: WorldReady,
    /// The webcam's own truth (`GET /truth`) after the step: what it delivered.
    camera: Value,
}

/// Runs one step; returns the text for stdout. Nothing is written unless the step
/// gave a result.
///
/// # Errors
///
/// For bad arguments, a calibration file that does not parse, a step whose
/// prerequisites are not in the file, a world or service that does not start,
/// and a step that fails (its job's reason).
pub fn run(args: &CalibrateArgs) -> anyhow::Result<String> {
    if let Some(config) = &args.config {
        bail!(
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
    if let Some(d) = args.release_deg {
        if args.step != Step::Pendulum {
            bail!("--release-deg is the pendulum step's (the angle the ball is hung at)");
        }
        if !(d.is_finite() && (0.0..=60.0).contains(&d)) {
            bail!("--release-deg = {d} is out of range: must be 0..=60");
        }
    }
    if let Some(n) = args.accuracy {
        return accuracy(args, &scenario, n);
    }
    // Read the file first: a broken calibration file is an error before anything runs.
    let mut file = CalibrationFile::load_or_empty(&args.out)?;
    let missing = args.step.missing_in(&file);
    if !missing.is_empty() {
        bail!(
            "calibrate {}: needs the {} step{} first (run `isochron calibrate {} --out {}`); nothing written",
            args.step.name(),
            missing.join(" and "),
            if missing.len() > 1 { "s" } else { "" },
            missing[0],
            args.out.display()
        );
    }
    let source = world_source(&scenario, args.seed);
    let done = on_world(args, &scenario, args.seed, &file, &[args.step])?;
    take_step(args.step, &done.file, &mut file, &source)?;
    // The beliefs with the new file must still be a valid lab.
    file.apply(&scenario)
        .with_context(|| format!("calibrate {}: the result", args.step.name()))?;
    file.write(&args.out)?;
    let (truth, error) = against_truth(args.step, &done, &scenario);
    let summary = json!({
        "step": args.step.name(),
        "source": source,
        "file": args.out.display().to_string(),
        "result": done.result,
        "truth": truth,
        "error": error,
    });
    if args.json {
        return Ok(summary.to_string());
    }
    Ok(format!(
        "calibrate {} on the {source}: written to {}\nresult: {}\nerror against the world's truth: {}",
        args.step.name(),
        args.out.display(),
        serde_json::to_string_pretty(&summary["result"])?,
        summary["error"]
    ))
}

/// Where the records say a step was measured.
fn world_source(scenario: &Scenario, seed: u64) -> String {
    format!(
        "simulated world (scenario {}, seed {seed}) behind a real lab's interfaces",
        scenario.name
    )
}

/// `--accuracy N`: the step on N worlds, after the steps it needs on each.
fn accuracy(args: &CalibrateArgs, scenario: &Scenario, n: u64) -> anyhow::Result<String> {
    if n == 0 || n > 100 {
        bail!("--accuracy = {n} is out of range: must be 1..=100");
    }
    let mut steps: Vec<Step> = args.step.prerequisites().to_vec();
    steps.push(args.step);
    let mut rows = Vec::new();
    let (mut worst, mut name, mut target) = (0.0_f64, "", 0.0);
    for seed in args.seed..args.seed + n {
        let t0 = Instant::now();
        let done = on_world(args, scenario, seed, &CalibrationFile::default(), &steps)
            .with_context(|| format!("calibrate {} (seed {seed})", args.step.name()))?;
        let (truth, error) = against_truth(args.step, &done, scenario);
        let (figure, value, t) = headline(args.step, &error);
        (name, target) = (figure, t);
        worst = worst.max(value.abs());
        rows.push(
            json!({"seed": seed, "result": done.result, "truth": truth, "error": error,
                         "figure": value, "run_s": t0.elapsed().as_secs_f64()}),
        );
    }
    let source = format!(
        "simulated world (scenario {}, seeds {}..={}) behind a real lab's interfaces",
        scenario.name,
        args.seed,
        args.seed + n - 1
    );
    let within = worst <= target;
    let summary = json!({
        "step": args.step.name(),
        "source": source,
        "steps_run": steps.iter().map(|s| s.name()).collect::<Vec<_>>(),
        "figure": name,
        "draws": rows,
        "max_abs_error": worst,
        "target": target,
        "within_target": within,
    });
    if args.json {
        return Ok(summary.to_string());
    }
    let mut out = format!(
        "calibrate {} accuracy on the {source}:\n| seed | {name} error | errors | run s |\n|---|---|---|---|\n",
        args.step.name()
    );
    for r in &rows {
        out.push_str(&format!(
            "| {} | {:+.4} | {} | {:.1} |\n",
            r["seed"],
            r["figure"].as_f64().unwrap_or(f64::NAN),
            r["error"],
            r["run_s"].as_f64().unwrap_or(f64::NAN)
        ));
    }
    out.push_str(&format!(
        "max |{name} error| {worst:.4} (target {target}): {}",
        if within { "within" } else { "OUTSIDE" }
    ));
    Ok(out)
}

/// The step's headline error (its name, the value, the target).
fn headline(step: Step, error: &Value) -> (&'static str, f64, f64) {
    let f = |k: &str| error[k].as_f64().unwrap_or(f64::NAN);
    match step {
        Step::Camera => ("k1", f("k1"), TARGET_K1),
        Step::Latency => (
            "camera_latency_ms",
            f("camera_latency_ms"),
            TARGET_CAMERA_LATENCY_MS,
        ),
        Step::Pendulum => ("length_m", f("length_m"), TARGET_LENGTH_M),
        Step::CameraRobot => (
            "camera_rotation_deg",
            f("camera_rotation_deg"),
            TARGET_CAMERA_ROTATION_DEG,
        ),
        Step::Robot => (
            "robot_delay_ms",
            f("robot_delay_ms"),
            TARGET_ROBOT_LATENCY_MS,
        ),
        Step::Contact => (
            "onset_offset_ms",
            f("onset_offset_ms"),
            server::calibration::TARGET_CONTACT_OFFSET_MS,
        ),
    }
}

/// The step's result against what the world drew: `(truth, error)`.
fn against_truth(step: Step, done: &WorldStep, scenario: &Scenario) -> (Value, Value) {
    let r = &done.result;
    let w = &done.ready;
    let f = |v: &Value| v.as_f64().unwrap_or(f64::NAN);
    match step {
        Step::Camera => {
            let t = w.camera_intrinsics;
            let Ok(k) = serde_json::from_value::<CameraIntrinsics>(r["intrinsics"].clone()) else {
                return (json!(t), Value::Null);
            };
            let corners = |inset: f64| corner_error_px(scenario, &t, &k, inset);
            (
                json!(t),
                json!({"fx_px": k.fx_px - t.fx_px, "fy_px": k.fy_px - t.fy_px,
                       "cx_px": k.cx_px - t.cx_px, "cy_px": k.cy_px - t.cy_px,
                       "k1": k.k1 - t.k1, "k2": k.k2 - t.k2, "p1": k.p1 - t.p1, "p2": k.p2 - t.p2,
                       "corner_px": corners(40.0), "corner_inner_px": corners(100.0)}),
            )
        }
        Step::Latency => {
            // The webcam delivers each frame at its drawn latency, later on a
            // loaded machine; the lab's stream transport and decoding come on
            // top, and they are in what the lab must believe (capture to
            // measurement), not in the world's truth: the error is against
            // what the webcam delivered.
            let delivered = f(&done.camera["led_delivered_latency_ms"]);
            let est = f(&r["latency_ms"]);
            (
                json!({"camera_latency_ms": w.led_latency_ms,
                       "delivered_latency_ms": delivered,
                       "frames": done.camera["frames"], "late_frames": done.camera["late_frames"]}),
                json!({"camera_latency_ms": est - delivered,
                       "against_drawn_ms": est - w.led_latency_ms}),
            )
        }
        Step::Pendulum => (
            json!({"length_m": w.pendulum_length_m, "damping_per_s": w.pendulum_damping_per_s,
                   "drag_per_m": w.pendulum_drag_per_m}),
            json!({"length_m": f(&r["swing"]["length_m"]) - w.pendulum_length_m,
                   "damping_per_s": f(&r["swing"]["damping_per_s"]) - w.pendulum_damping_per_s}),
        ),
        Step::Robot => {
            // What the lab's timing takes (`control.latency_prior_ms`): the
            // latency plus the servo lag, against the world's delay.
            let est = f(&r["latency_ms"]) + f(&r["servo_time_constant_ms"]);
            (
                json!({"robot_delay_ms": w.robot_delay_ms, "robot_latency_ms": w.robot_latency_ms,
                       "servo_lag_ms": w.robot_servo_lag_ms}),
                json!({"robot_delay_ms": est - w.robot_delay_ms}),
            )
        }
        Step::Contact => {
            // The measured judge subtracts the lag and half the pulse from
            // the pulse's centre: their sum is what the knock learns (both
            // streams are the robot's messages: their transit cancels).
            let truth = w.torque_lag_ms + 0.5 * w.contact_pulse_ms;
            (
                json!({"onset_offset_ms": truth, "torque_lag_ms": w.torque_lag_ms,
                       "contact_pulse_ms": w.contact_pulse_ms}),
                json!({"onset_offset_ms": f(&r["onset_offset_ms"]) - truth,
                       "pulse_ms": f(&r["pulse_ms"]) - w.contact_pulse_ms}),
            )
        }
        Step::CameraRobot => {
            let Ok(pose) =
                serde_json::from_value::<rt_core::vision::CameraPose>(r["camera_pose"].clone())
            else {
                return (json!({"camera_pose": w.camera_pose}), Value::Null);
            };
            let t = &w.camera_pose;
            let rot =
                rotation_angle_rad(&pose.base_from_camera(), &t.base_from_camera()).to_degrees();
            let pos = (pose.position() - t.position()).norm() * 1e3;
            let icp: Vec<f64> = (0..3)
                .map(|i| (f(&r["intercept_m"][i]) - w.ball_rest_m[i]) * 1e3)
                .collect();
            // The intercept point's depth is the believed swing plane's (no
            // touch on a real lab): its side and height are the step's.
            let icp_mm = icp[1].hypot(icp[2]);
            (
                json!({"camera_pose": t, "intercept_m": w.ball_rest_m}),
                json!({"camera_rotation_deg": rot, "camera_position_mm": pos,
                       "intercept_mm": icp_mm, "intercept_xyz_mm": icp,
                       "intercept_target_mm": TARGET_INTERCEPT_MM,
                       "camera_position_target_mm": TARGET_CAMERA_POSITION_MM}),
            )
        }
    }
}

/// The calibrated lens's undistortion error near the image's corners (`inset`
/// px in from both edges; the worst of the four), pixels.
fn corner_error_px(
    scenario: &Scenario,
    truth: &CameraIntrinsics,
    believed: &CameraIntrinsics,
    inset: f64,
) -> f64 {
    let (w, h) = (
        f64::from(scenario.camera.width_px) - 1.0 - inset,
        f64::from(scenario.camera.height_px) - 1.0 - inset,
    );
    [(inset, inset), (w, inset), (inset, h), (w, h)]
        .iter()
        .map(|&(u, v)| undistortion_error_px(truth, believed, u, v))
        .fold(0.0, f64::max)
}

/// Puts `step`'s record from `from` into `into`, saying it was measured on `source`.
fn take_step(
    step: Step,
    from: &CalibrationFile,
    into: &mut CalibrationFile,
    source: &str,
) -> anyhow::Result<()> {
    fn named<T: Clone>(r: Option<&StepRecord<T>>, source: &str) -> Option<StepRecord<T>> {
        r.map(|r| StepRecord {
            source: source.to_owned(),
            ..r.clone()
        })
    }
    let taken = match step {
        Step::Camera => {
            into.camera = named(from.camera.as_ref(), source);
            into.camera.is_some()
        }
        Step::Latency => {
            into.latency = named(from.latency.as_ref(), source);
            into.latency.is_some()
        }
        Step::Pendulum => {
            into.pendulum = named(from.pendulum.as_ref(), source);
            into.pendulum.is_some()
        }
        Step::CameraRobot => {
            into.camera_robot = named(from.camera_robot.as_ref(), source);
            into.camera_robot.is_some()
        }
        Step::Robot => {
            into.robot = named(from.robot.as_ref(), source);
            into.robot.is_some()
        }
        Step::Contact => {
            into.contact = named(from.contact.as_ref(), source);
            into.contact.is_some()
        }
    };
    if !taken {
        bail!(
            "calibrate {}: the service said done but wrote no result",
            step.name()
        );
    }
    Ok(())
}

/// The service in a child process, killed (SIGTERM, then SIGKILL) when dropped.
struct Service {
    child: Child,
    addr: SocketAddr,
    /// Its standard error's latest lines (for a failure's report).
    stderr: Arc<std::sync::Mutex<std::collections::VecDeque<String>>>,
}

impl Service {
    /// `isochron serve --config CONFIG` on a free loopback port, once it listens.
    fn start(config: &Path, data: &Path) -> anyhow::Result<Self> {
        let exe = std::env::current_exe().context("this program's path")?;
        let mut child = Command::new(exe)
            .args(["serve", "--bind", "127.0.0.1:0", "--config"])
            .arg(config)
            .arg("--data-dir")
            .arg(data)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .context("cannot start the lab's service (isochron serve)")?;
        let stderr = Arc::new(std::sync::Mutex::new(std::collections::VecDeque::new()));
        if let Some(err) = child.stderr.take() {
            let lines = Arc::clone(&stderr);
            std::thread::Builder::new()
                .name("isochron-calibrate-log".into())
                .spawn(move || {
                    for line in BufReader::new(err).lines().map_while(Result::ok) {
                        let mut l = lines
                            .lock()
                            .unwrap_or_else(std::sync::PoisonError::into_inner);
                        if l.len() == 20 {
                            l.pop_front();
                        }
                        l.push_back(line);
                    }
                })?;
        }
        let (tx, rx) = mpsc::sync_channel(4);
        if let Some(out) = child.stdout.take() {
            std::thread::Builder::new()
                .name("isochron-calibrate-out".into())
                .spawn(move || {
                    for line in BufReader::new(out).lines().map_while(Result::ok) {
                        if let Some(addr) = line
                            .split("http://")
                            .nth(1)
                            .and_then(|s| s.split(['/', ' ']).next())
                            .and_then(|s| s.parse::<SocketAddr>().ok())
                        {
                            let _ = tx.try_send(addr);
                        }
                    }
                })?;
        }
        let mut service = Self {
            child,
            addr: SocketAddr::from(([127, 0, 0, 1], 0)),
            stderr,
        };
        let deadline = Instant::now() + Duration::from_secs(READY_TIMEOUT_S);
        loop {
            match rx.recv_timeout(Duration::from_millis(200)) {
                Ok(addr) => {
                    service.addr = addr;
                    return Ok(service);
                }
                Err(_) if Instant::now() > deadline => {
                    bail!(
                        "the lab's service did not listen within {READY_TIMEOUT_S} s{}",
                        service.said()
                    );
                }
                Err(_) => {
                    if let Ok(Some(status)) = service.child.try_wait() {
                        bail!("the lab's service ended ({status}){}", service.said());
                    }
                }
            }
        }
    }

    /// Its latest standard error, for a report.
    fn said(&self) -> String {
        let l = self
            .stderr
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if l.is_empty() {
            String::new()
        } else {
            format!(": {}", l.iter().cloned().collect::<Vec<_>>().join(" | "))
        }
    }
}

impl Drop for Service {
    fn drop(&mut self) {
        if let Some(pid) =
            rustix::process::Pid::from_raw(i32::try_from(self.child.id()).unwrap_or(0))
        {
            let _ = rustix::process::kill_process(pid, rustix::process::Signal::TERM);
        }
        let deadline = Instant::now() + Duration::from_secs(10);
        while Instant::now() < deadline {
            if matches!(self.child.try_wait(), Ok(Some(_))) {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The world's thread, stopped and joined when dropped.
struct Running {
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Drop for Running {
    fn drop(&mut self) {
        self.stop.store(true, Relaxed);
        if let Some(h) = self.thread.take() {
            let _ = h.join();
        }
    }
}

/// Starts `scenario`'s world (session `seed`), a real lab's service on it
/// with `file` as its calibration file, runs `steps` in order through the
/// service, and returns the last step's result with the file the service
/// wrote and the world's truth.
fn on_world(
    args: &CalibrateArgs,
    scenario: &Scenario,
    seed: u64,
    file: &CalibrationFile,
    steps: &[Step],
) -> anyhow::Result<WorldStep> {
    let dir = tempfile::tempdir().context("a temporary folder")?;
    let calibration = dir.path().join("calibration.toml");
    if *file != CalibrationFile::default() {
        file.write(&calibration)?;
    }
    // The cabinet's controller thread takes SCHED_FIFO when allowed.
    rt_core::fri::priority::enable();
    let world = LabWorld::start(&WorldSpec {
        scenario: scenario.clone(),
        seed,
        fri_version: rt_core::fri::FriVersion::default(),
        distance_m: None,
        firmware_dir: args
            .firmware_dir
            .clone()
            .unwrap_or_else(default_firmware_dir),
        serial_port: dir.path().join("magnet.tty"),
        stand: None,
    })?;
    let beliefs = dir.path().join("lab.scenario.toml");
    std::fs::write(&beliefs, world.beliefs().to_toml_string())
        .with_context(|| format!("cannot write {}", beliefs.display()))?;
    let mut cfg = world.lab_config(&beliefs);
    // A world's arm harms no one: no operator holds a dead-man here.
    cfg.lab.dead_man = Some(false);
    cfg.lab.calibration_file = Some(calibration.clone());
    let config = dir.path().join("lab.toml");
    std::fs::write(&config, toml::to_string_pretty(&cfg)?)
        .with_context(|| format!("cannot write {}", config.display()))?;
    let ready = world.ready.clone();
    let camera_host = ready
        .camera_url
        .trim_start_matches("http://")
        .split('/')
        .next()
        .and_then(|h| h.parse::<SocketAddr>().ok());
    let mut service = Service::start(&config, &dir.path().join("data"))?;
    world.start_operator(&format!("http://{}", service.addr))?;
    let stop = Arc::new(AtomicBool::new(false));
    let stopped = Arc::clone(&stop);
    let mut world = world;
    let running = Running {
        stop,
        thread: Some(
            std::thread::Builder::new()
                .name("isochron-world".into())
                .spawn(move || {
                    let mut sink = std::io::sink();
                    while !stopped.load(Relaxed) {
                        if world.poll(&mut sink, Duration::from_millis(200)).is_err() {
                            return;
                        }
                    }
                })?,
        ),
    };
    let mut result = Value::Null;
    for &step in steps {
        result = run_step(
            &service,
            step,
            args.release_deg.filter(|_| step == Step::Pendulum),
        )
        .map_err(|e| anyhow::anyhow!("{e:#}{}", service.said_if_gone()))?;
    }
    let camera = camera_host
        .and_then(|h| http_json(h, "GET", "/truth", "").ok())
        .map_or(Value::Null, |(_, v)| v);
    // The world first: a cabinet whose lab went away would say it left
    // commanding.
    drop(running);
    drop(service);
    let file = CalibrationFile::from_file(&calibration)
        .context("the service's calibration file after the step")?;
    Ok(WorldStep {
        result,
        file,
        ready,
        camera,
    })
}

impl Service {
    /// What it said last, when it has ended (empty while it runs).
    fn said_if_gone(&mut self) -> String {
        match self.child.try_wait() {
            Ok(Some(status)) => format!(" (the lab's service ended: {status}){}", self.said()),
            _ => String::new(),
        }
    }
}

/// Whether the lab's state says it can run a step: the robot commanding,
/// the board answering, the camera delivering.
fn lab_ready(state: &Value) -> Option<u64> {
    (state["fri"]["session"] == "commanding_active"
        && (state["magnet"] == "on" || state["magnet"] == "off")
        && state["camera"]["lost"] == false
        && state["camera"]["frame"].as_u64().is_some_and(|f| f > 0))
    .then(|| state["fri"]["commanding_lost"].as_u64())
    .flatten()
}

/// Posts `step` to the service once its lab is steadily ready, follows the
/// job to its end, and returns its result; a step refused for a passing
/// reason (the board answered late, the robot left commanding for a
/// moment) is posted again, at most [`ATTEMPTS`] times in all.
fn run_step(service: &Service, step: Step, release_deg: Option<f64>) -> anyhow::Result<Value> {
    let addr = service.addr;
    let body = release_deg.map_or_else(String::new, |d| json!({"release_deg": d}).to_string());
    let mut attempt = 0;
    loop {
        attempt += 1;
        // Ready, and the robot commanding steadily for 2 s.
        let deadline = Instant::now() + Duration::from_secs(READY_TIMEOUT_S);
        let mut steady: Option<(Instant, u64)> = None;
        loop {
            let now = http_json(addr, "GET", "/api/state", "")
                .ok()
                .and_then(|(_, s)| lab_ready(&s));
            steady = match (steady, now) {
                (Some((since, lost)), Some(n)) if n == lost => Some((since, lost)),
                (_, Some(n)) => Some((Instant::now(), n)),
                (_, None) => None,
            };
            if steady.is_some_and(|(since, _)| since.elapsed() >= Duration::from_secs(2)) {
                break;
            }
            if Instant::now() > deadline {
                bail!(
                    "calibrate {}: the lab was not ready within {READY_TIMEOUT_S} s (the robot \
                     commanding, the magnet board answering, the camera delivering)",
                    step.name()
                );
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let (status, started) = http_json(
            addr,
            "POST",
            &format!("/api/calibration/{}", step.name()),
            &body,
        )?;
        if status != 202 {
            let why = started["error"]
                .as_str()
                .map_or_else(|| started.to_string(), str::to_owned);
            bail!("calibrate {}: {why}", step.name());
        }
        let id = started["id"].as_u64();
        let deadline = Instant::now() + Duration::from_secs(STEP_TIMEOUT_S);
        let job = loop {
            std::thread::sleep(Duration::from_millis(250));
            if let Ok((200, c)) = http_json(addr, "GET", "/api/calibration", "") {
                let job = &c["job"];
                if job["id"].as_u64() == id && job["state"] != "running" {
                    break job.clone();
                }
            }
            if Instant::now() > deadline {
                bail!(
                    "calibrate {}: the step did not end within {STEP_TIMEOUT_S} s",
                    step.name()
                );
            }
        };
        if job["state"] == "done" {
            return Ok(job["result"].clone());
        }
        let message = job["message"].as_str().unwrap_or("failed").to_owned();
        let passing = [
            "magnet device",
            "left commanding",
            "moving the arm home was stopped",
            // A busy host's frames (the procedure says to calibrate when quieter).
            "arrive too irregularly",
        ];
        if attempt < ATTEMPTS && passing.iter().any(|p| message.contains(p)) {
            eprintln!(
                "calibrate {}: refused for a passing reason, posted again: {message}",
                step.name()
            );
            continue;
        }
        // The job's message names the step already ("calibrate pendulum: ...").
        if message.starts_with("calibrate ") {
            bail!("{message}");
        }
        bail!("calibrate {}: {message}", step.name());
    }
}
