//! Demo mode (`isochron serve --demo`, #37) over real sockets, the service as
//! its own process:
//!
//! - the simulated lab (a truthful world behind a real lab's interfaces)
//!   runs trials unattended, each with the distance and
//!   movement time the demo gives it; it pauses saying why while the lab
//!   cannot take a trial (a calibration step runs) and resumes by itself; a
//!   restarted service's demo goes on, its counts kept;
//! - a real lab (`lab.mode = "real"`, stand-ins for the cabinet, the camera and
//!   the magnet board) pauses with the lab's reason (not calibrated, robot
//!   not commanding), runs only while an operator's heartbeat holds it, and
//!   stops the arm when the heartbeats lapse.

use std::ffi::OsStr;
use std::net::{SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use isochron_tests::isochron_bin;
use isochron_tests::service::{Service, api, not_judged_starved, starved};
use serde_json::Value;

const TOKEN: &str = "demo-token";

fn bin() -> Option<PathBuf> {
    isochron_bin(&[(&["serve", "--help"], "--demo-interval-s")])
}

/// `isochron serve --demo` on a free loopback port with a token, its log
/// beside the data directory.
fn serve(bin: &Path, data: &Path, extra: &[&str]) -> Service {
    let mut args: Vec<&OsStr> = vec![OsStr::new("--demo")];
    args.extend(extra.iter().map(OsStr::new));
    args.extend([OsStr::new("--data-dir"), data.as_os_str()]);
    let log = data.with_file_name("serve.log");
    Service::start(bin, TOKEN, &log, &args)
}

/// One request; the test fails when the service does not answer.
async fn request(addr: SocketAddr, method: &str, path: &str, body: &str) -> (u16, Value) {
    api(addr, TOKEN, method, path, body)
        .await
        .unwrap_or_else(|e| panic!("{method} {path}: the service does not answer: {e:#}"))
}

/// Polls `GET path` until `pred` holds (every 10 ms, at most `timeout`).
async fn wait_for(
    addr: SocketAddr,
    path: &str,
    timeout: Duration,
    what: &str,
    pred: impl Fn(&Value) -> bool,
) -> Value {
    isochron_tests::service::wait_for(addr, TOKEN, path, timeout, what, pred).await
}

/// The demo's trials' distances and movement times, in turn (server/src/demo.rs).
fn planned(k: usize) -> (f64, f64) {
    let d = server::demo::DISTANCES_M;
    let t = server::demo::MOVEMENT_TIMES_S;
    (d[k % d.len()], t[k % t.len()])
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_demo_runs_trials_unattended_pauses_saying_why_and_goes_on_after_a_restart() {
    let Some(bin) = bin() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let mut svc = serve(&bin, &data, &["--demo-interval-s", "1"]);
    let addr = svc.addr;

    // Unattended: nobody posts a trial, two finish.
    let d = wait_for(
        addr,
        "/api/demo",
        Duration::from_secs(180),
        "two demo trials",
        |v| v["trials"].as_u64() >= Some(2),
    )
    .await;
    println!("demo after two trials: {d}");
    assert_eq!(d["enabled"], true, "{d}");
    assert_eq!(d["operator_required"], false, "{d}");
    assert_eq!(d["interval_s"], 1.0, "{d}");
    let ci = d["success_ci95"].as_array().unwrap();
    assert!(ci[0].as_f64() <= ci[1].as_f64(), "{d}");
    // Each with the distance and movement time the demo gave it (the k-th
    // trial the k-th plan): two done, and any aborted among them ended by
    // a starved machine (the simulated lab's camera and magnet board are
    // threads of the service; beside `stress-ng` a board once stayed
    // silent past its timeouts while it held the ball).
    let list = wait_for(
        addr,
        "/api/trials?limit=100",
        Duration::from_secs(180),
        "two demo trials done",
        |l| {
            l.as_array()
                .is_some_and(|a| a.iter().filter(|t| t["status"] == "done").count() >= 2)
        },
    )
    .await;
    let mut finished: Vec<&Value> = list
        .as_array()
        .unwrap()
        .iter()
        .filter(|t| t["status"] != "running")
        .collect();
    finished.sort_by_key(|t| t["id"].as_u64());
    for (k, t) in finished.iter().enumerate() {
        println!("trial {k}: {t}");
        if t["status"] == "aborted" {
            assert!(starved(t), "trial {k}: {t}");
            continue;
        }
        let (dist, mt) = planned(k);
        assert_eq!(t["status"], "done", "{t}");
        // Judged, or not judged because the machine starved the lab, saying so.
        assert!(t["success"].is_boolean() || not_judged_starved(t), "{t}");
        let got_d = t["distance_m"].as_f64().unwrap();
        assert!(
            (got_d - dist).abs() < 0.005,
            "trial {k}: {got_d} m, planned {dist}"
        );
        // As the measured joints show it (absent only when a starved
        // machine's FRI paused through the motion's fit).
        let got_t = t["movement_time_s"].as_f64();
        assert!(
            got_t.is_some_and(|got| (got - mt).abs() < 0.05) || not_judged_starved(t),
            "trial {k}: {got_t:?} s, planned {mt}"
        );
    }

    // A calibration step makes the lab refuse trials: the demo pauses and says
    // why (the step is refused while a trial runs: posted between two).
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let (code, r) = request(addr, "POST", "/api/calibration/robot", "").await;
        if code == 202 {
            break;
        }
        assert_eq!(code, 409, "{r}");
        assert!(Instant::now() < deadline, "no gap between demo trials: {r}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let p = wait_for(
        addr,
        "/api/demo",
        Duration::from_secs(30),
        "paused while calibrating",
        |v| v["state"] == "paused",
    )
    .await;
    println!("demo paused: {p}");
    assert_eq!(p["reason"], "calibrating", "{p}");
    let msg = p["message"].as_str().unwrap();
    assert!(
        msg.starts_with("paused: ") && msg.contains("calibrat"),
        "{msg}"
    );
    // Resumes by itself when the step has finished.
    let before = p["trials"].as_u64().unwrap();
    wait_for(
        addr,
        "/api/calibration",
        Duration::from_secs(240),
        "the robot step finishes",
        |v| v["job"]["state"] != "running",
    )
    .await;
    wait_for(
        addr,
        "/api/demo",
        Duration::from_secs(120),
        "a demo trial after the calibration",
        |v| v["trials"].as_u64() > Some(before),
    )
    .await;

    // A restart: the demo goes on by itself, its counts kept.
    let (_, d) = request(addr, "GET", "/api/demo", "").await;
    let counted = d["trials"].as_u64().unwrap();
    svc.kill();
    let svc = serve(&bin, &data, &["--demo-interval-s", "1"]);
    let (code, d) = request(svc.addr, "GET", "/api/demo", "").await;
    assert_eq!(code, 200, "{d}");
    assert!(d["trials"].as_u64() >= Some(counted), "{d}, had {counted}");
    wait_for(
        svc.addr,
        "/api/demo",
        Duration::from_secs(120),
        "a demo trial after the restart",
        |v| v["trials"].as_u64() > Some(counted),
    )
    .await;

    // Without --demo: the status says it is off; a bad interval is refused.
    let (code, _) = request(svc.addr, "GET", "/api/health", "").await;
    assert_eq!(code, 200);
    let out = Command::new(&bin)
        .args([
            "serve",
            "--bind",
            "127.0.0.1:0",
            "--demo",
            "--demo-interval-s",
            "0",
        ])
        .arg("--data-dir")
        .arg(tmp.path().join("other"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("--demo-interval-s"),
        "{err}"
    );
}

// ---- A real lab ------------------------------------------------------------

/// A real lab's config with stand-ins: the camera a rendered video, the
/// magnet the fake board, the controller at `controller`.
struct RealLab {
    config: PathBuf,
    _board: rt_core::sim::magnet::FakeDevice,
}

fn free_udp_port() -> SocketAddr {
    UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
}

fn real_lab(
    dir: &Path,
    client: SocketAddr,
    controller: SocketAddr,
    allow_uncalibrated: bool,
) -> RealLab {
    use rt_core::sim::camera::{BallState, SimCamera, SimCameraParams};
    let scenario = rt_core::params::Scenario::default();
    let video = dir.join("pendulum.avi");
    let filmed = SimCameraParams::default();
    let pose = filmed.pose;
    let mut cam = SimCamera::new(
        &scenario.camera,
        &filmed,
        scenario.pendulum.ball_radius_m,
        1,
    )
    .unwrap();
    let mut rec = rt_core::vision::Recorder::create(&video, 1280, 720, 30.0).unwrap();
    for i in 0..60 {
        let y = 0.25 * (f64::from(i) * 0.15).sin();
        let ball = BallState::from_arrays([0.6, y, 0.30], [0.0, 0.0, 0.0]);
        rec.write(cam.render(Some(&ball)).unwrap()).unwrap();
    }
    rec.finish().unwrap();
    let board = rt_core::sim::magnet::FakeDevice::start(dir.join("ttyMAGNET")).unwrap();
    let toml = format!(
        "[lab]\nmode = \"real\"\nallow_uncalibrated = {allow_uncalibrated}\n\
         [fri]\nlocal_bind = \"{client}\"\ncontroller = \"{controller}\"\nperiod_ms = 5\n\
         [camera]\ndevice = \"{}\"\n\
         [magnet]\nport = \"{}\"\ncommand_timeout_ms = 2000.0\n\
         [calibration]\nfocal_length_px = 914.0\nprincipal_point_px = [640.0, 360.0]\n\
         plane_distance_m = 1.6\npivot_m = [0.6, 0.0, 2.23]\n\
         [calibration.camera_pose]\nposition_m = [{}, {}, {}]\n\
         yaw_deg = {}\npitch_deg = {}\nroll_deg = {}\n",
        video.display(),
        board.path().display(),
        pose.position_m[0],
        pose.position_m[1],
        pose.position_m[2],
        pose.yaw_deg,
        pose.pitch_deg,
        pose.roll_deg,
    );
    let config = dir.join("real.toml");
    std::fs::write(&config, toml).unwrap();
    RealLab {
        config,
        _board: board,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_real_lab_demo_pauses_for_the_lab_and_runs_only_while_an_operator_holds_it() {
    use rt_core::sim::kuka::{FriSimParams, SimRunOptions, SimServer};
    let Some(bin) = bin() else { return };
    let tmp = tempfile::tempdir().unwrap();

    // Not calibrated: paused, saying so (an operator's heartbeat changes nothing).
    let dir = tmp.path().join("uncal");
    std::fs::create_dir_all(&dir).unwrap();
    let lab = real_lab(&dir, free_udp_port(), free_udp_port(), false);
    let cfg = lab.config.to_str().unwrap().to_owned();
    let svc = serve(&bin, &dir.join("data"), &["--config", &cfg]);
    request(svc.addr, "POST", "/api/heartbeat", "").await;
    let p = wait_for(
        svc.addr,
        "/api/demo",
        Duration::from_secs(30),
        "paused: not calibrated",
        |v| v["state"] == "paused",
    )
    .await;
    println!("real lab, not calibrated: {p}");
    assert_eq!(p["reason"], "uncalibrated", "{p}");
    assert_eq!(p["operator_required"], true, "{p}");
    assert!(
        p["message"].as_str().unwrap().contains("calibration"),
        "{p}"
    );
    assert!(
        p["detail"].as_str().unwrap().contains("not calibrated"),
        "{p}"
    );
    drop(svc);
    drop(lab);

    // Calibration waived, but no cabinet answers: paused, the robot not commanding.
    let dir = tmp.path().join("silent");
    std::fs::create_dir_all(&dir).unwrap();
    let lab = real_lab(&dir, free_udp_port(), free_udp_port(), true);
    let cfg = lab.config.to_str().unwrap().to_owned();
    let svc = serve(&bin, &dir.join("data"), &["--config", &cfg]);
    let p = wait_for(
        svc.addr,
        "/api/demo",
        Duration::from_secs(30),
        "paused: robot not commanding",
        |v| v["reason"] == "robot_not_commanding",
    )
    .await;
    println!("real lab, no cabinet: {p}");
    assert_eq!(p["state"], "paused", "{p}");
    drop(svc);
    drop(lab);

    // A commanding cabinet: the demo waits for an operator; with heartbeats a
    // trial starts; when they stop, the arm is stopped and the trial ends.
    let dir = tmp.path().join("held");
    std::fs::create_dir_all(&dir).unwrap();
    let client = free_udp_port();
    let robot = SimServer::spawn(
        FriSimParams::default(),
        SocketAddr::from(([127, 0, 0, 1], 0)),
        client,
        SimRunOptions {
            auto_command: true,
            duration: None,
            normal_priority: false,
            keep_commanding: false,
        },
    )
    .unwrap();
    let lab = real_lab(&dir, client, robot.local_addr(), true);
    let cfg = lab.config.to_str().unwrap().to_owned();
    let svc = serve(
        &bin,
        &dir.join("data"),
        &["--config", &cfg, "--demo-interval-s", "1"],
    );
    let w = wait_for(
        svc.addr,
        "/api/demo",
        Duration::from_secs(60),
        "waiting for an operator",
        |v| v["state"] == "operator_needed",
    )
    .await;
    println!("real lab, no operator: {w}");
    assert_eq!(w["reason"], "operator", "{w}");
    // Its pendulum hangs where the configuration's pivot puts it (0.6 m): the
    // demo's trials go there, and a trial asking elsewhere is refused.
    assert_eq!(w["next_distance_m"], 0.6, "{w}");
    let (code, r) = request(svc.addr, "POST", "/api/trials", r#"{"distance_m": 0.4}"#).await;
    assert_eq!(
        (code, r["field"].as_str()),
        (400, Some("distance_m")),
        "{r}"
    );
    assert!(
        r["error"].as_str().unwrap().contains("hangs 0.600 m"),
        "{r}"
    );
    let (_, trials) = request(svc.addr, "GET", "/api/trials", "").await;
    assert_eq!(trials.as_array().map(Vec::len), Some(0), "{trials}");
    // The operator holds it: heartbeats every 200 ms until a demo trial runs.
    let deadline = Instant::now() + Duration::from_secs(60);
    let trial = loop {
        request(svc.addr, "POST", "/api/heartbeat", "").await;
        let (_, d) = request(svc.addr, "GET", "/api/demo", "").await;
        if d["state"] == "running" {
            break d["trial_id"].as_u64().unwrap();
        }
        assert!(
            Instant::now() < deadline,
            "no demo trial with an operator: {d}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    // The operator lets go: the trial ends (stopped), and nothing new starts.
    let rec = wait_for(
        svc.addr,
        &format!("/api/trials/{trial}"),
        Duration::from_secs(15),
        "the held trial ends once the heartbeats stop",
        |v| v["status"] != "running",
    )
    .await;
    println!("real lab, the operator let go: trial {rec}");
    assert_eq!(rec["status"], "aborted", "{rec}");
    let d = wait_for(
        svc.addr,
        "/api/demo",
        Duration::from_secs(10),
        "waiting for an operator again",
        |v| v["state"] == "operator_needed",
    )
    .await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    let (_, d2) = request(svc.addr, "GET", "/api/demo", "").await;
    assert_eq!(d2["state"], "operator_needed", "{d2}");
    assert_eq!(
        d2["trial_id"], d["trial_id"],
        "a trial started without an operator: {d2}"
    );
    drop(svc);
    drop(robot);
}

/// Strike mode in the demo (issue #38): the simulated lab switched to strike
/// over `PUT /api/params` runs its demo trials as strikes with the parameters
/// in force; the running message names the stroke's speed, and a finished
/// strike's record carries what the visitors' page lists: the tool's speed at
/// contact planned and measured, the ball's outgoing speed predicted (the
/// controller's rebound, restitution 0: the tool's speed along the return)
/// and seen (or, on a starved machine, a trial not judged that says so).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_demo_in_strike_mode_strikes_and_its_records_carry_the_predicted_and_seen_rebound() {
    let Some(bin) = bin() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let svc = serve(&bin, &data, &["--demo-interval-s", "1"]);
    let addr = svc.addr;
    // Refused while a demo trial moves the arm: posted again until taken.
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let (code, r) = request(
            addr,
            "PUT",
            "/api/params",
            r#"{"task": {"mode": "strike"}}"#,
        )
        .await;
        if code == 200 {
            break;
        }
        assert!(
            code == 409 && Instant::now() < deadline,
            "PUT /api/params: {code} {r}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let since = request(addr, "GET", "/api/trials?limit=1", "")
        .await
        .1
        .as_array()
        .and_then(|a| a.first().and_then(|t| t["id"].as_u64()))
        .unwrap_or(0);
    let running = wait_for(
        addr,
        "/api/demo",
        Duration::from_secs(180),
        "a demo strike running",
        |d| {
            d["state"] == "running"
                && d["message"]
                    .as_str()
                    .is_some_and(|m| m.contains("striking at 0.50 m/s"))
        },
    )
    .await;
    println!("demo running a strike: {running}");
    // A trial started after the switch that ended: a strike, or one a
    // starved machine ended (any other end fails below).
    let ended = move |t: &Value| t["id"].as_u64() > Some(since) && t["status"] != "running";
    let list = wait_for(
        addr,
        "/api/trials?limit=100",
        Duration::from_secs(240),
        "a demo strike finished",
        |l| l.as_array().is_some_and(|a| a.iter().any(ended)),
    )
    .await;
    let t = list
        .as_array()
        .unwrap()
        .iter()
        .rev()
        .find(|t| ended(t))
        .unwrap();
    println!("demo strike: {t}");
    if starved(t) || not_judged_starved(t) {
        eprintln!("demo strike: a starved machine's trial: {}", t["reason"]);
        return;
    }
    let k = &t["measured"]["strike"];
    assert!(k.is_object(), "the demo trial did not strike: {t}");
    assert_eq!(k["planned_tool_speed_mps"], 0.5, "{t}");
    let predicted = k["predicted"]["ball_speed_mps"]
        .as_f64()
        .unwrap_or(f64::NAN);
    assert!(
        (predicted - 0.5 * 20f64.to_radians().cos()).abs() < 1e-9,
        "{t}"
    );
    if t["measured"]["contact"] == true && t["judged_by"] == "measured" {
        assert!(
            k["tool_speed_mps"]
                .as_f64()
                .is_some_and(|v| (v - 0.5).abs() < 0.15),
            "{t}"
        );
        assert!(k["ball_speed_mps"].as_f64().is_some_and(|v| v > 0.2), "{t}");
    }
}
