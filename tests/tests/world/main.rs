//! The real lab end to end against a world that reacts: `isochron world`
//! is the lab's hardware (the KUKA cabinet over FRI with the world's robot
//! and the ball's contact torques, a webcam stream of the world's ball, the
//! magnet firmware in simavr whose coil drops that ball), and `isochron
//! serve --config` the lab configuration it wrote, in real mode, knowing
//! nothing of the world. Trials run over REST with an operator's heartbeat
//! (the real lab's dead-man), are judged by the measured judge only, and
//! are paired with the world's truth file by the coil's release time.
//!
//! Properties: every trial's record finishes; each judged trial has its
//! release in the world's truth (the coil switched off while it ran); the
//! measured judge agrees with the world's physical judge on contact and on
//! success, and its timing error is within 15 ms of the true one (the p95 of
//! the difference, 3 ms in the issue's acceptance, is a figure of many
//! trials: reported here, measured by `make eval-world`). The trials
//! test's world is truthful (`scenarios/paper.toml`: its beliefs are its
//! truth, so the lab runs uncalibrated, `--allow-uncalibrated`, and `make
//! test` runs no step before its trials); the accuracy test brings a reality
//! world's lab up from nothing (all five steps over REST, then trials on
//! what they measured, without `allow_uncalibrated`). `WORLD_LAB_TRIALS` sets
//! the trials test's number of trials (default 3), `WORLD_LAB_SCENARIO`
//! another world (e.g. `scenarios/reality.toml`: the reality lab,
//! uncalibrated), `WORLD_LAB_STEPS=lab` the pendulum, latency and robot steps
//! before its trials and `WORLD_LAB_STEPS=all` the camera and camera-robot
//! steps too (`make eval-world`: 100 trials on each world, the service's and
//! the world's CPU per second reported).
//!
//! A test binary of its own (issue #34): a world and its lab load both cores,
//! and beside the other end-to-end tests (tests/tests/e2e) and `stress-ng`
//! the pendulum step measured a 1.98 m string as 1.917 m and boards starved.
//! Cargo runs test binaries one after another, so these run alone. Their
//! labs take `serve`'s default real-time measures (`auto`: the FRI threads
//! pinned to the last CPU, spinning there); with `--rt-tuning fifo,mlock`
//! the pendulum step measured the 1.98 m string as 1.956 m on a quiet
//! machine, and the served reality world's first trial disagreed with its
//! truth line on contact.

use std::{
    net::SocketAddr,
    path::Path,
    process::Command as Process,
    sync::{
        Arc,
        atomic::{AtomicBool, Ordering::Relaxed},
    },
    time::{Duration, Instant},
};

use isochron_tests::http;

/// One world and its lab at a time: a world renders its camera, runs the
/// cabinet and a simavr board, and two worlds with their labs side by side
/// on a 2-core machine starve each other's camera.
static ONE_LAB: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// How many trials the accuracy test's first draw runs once its lab is
/// calibrated.
const WORLD_CALIB_TRIALS: usize = 2;

/// How far the robot step's delay (latency plus servo lag) may be from the
/// world's, ms.
const ROBOT_DELAY_TOLERANCE_MS: f64 = 3.0;
use isochron_tests::procs::{Proc, firmware, start};
use serde_json::Value;

async fn get(addr: SocketAddr, path: &str) -> Value {
    let r = http(addr, "GET", path, &[], b"").await.unwrap();
    assert_eq!(
        r.status,
        200,
        "GET {path}: {}",
        String::from_utf8_lossy(&r.body)
    );
    r.json().unwrap()
}

/// Waits (up to `timeout`) until the calibration job is no longer running;
/// returns `GET /api/calibration`.
async fn job_end(addr: SocketAddr, timeout: Duration) -> Value {
    let deadline = Instant::now() + timeout;
    loop {
        let c = get(addr, "/api/calibration").await;
        if c["job"]["state"] != "running" {
            return c;
        }
        assert!(Instant::now() < deadline, "the step did not end: {c}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Waits (up to `timeout`) until `GET /api/health` says a trial would start.
async fn wait_ready(addr: SocketAddr, timeout: Duration) {
    let deadline = Instant::now() + timeout;
    loop {
        let h = get(addr, "/api/health").await;
        if h["ready"] == true {
            return;
        }
        assert!(Instant::now() < deadline, "the lab is not ready: {h}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Starts a trial (202, its id), as a lab's script does: a device that
/// falls silent for a moment on a loaded machine (the controller:
/// `robot_not_commanding`; the webcam's stream over a second without a
/// frame, beside `stress-ng`: `device_unavailable`) refuses with 409 and
/// says so in `GET /api/health`; the script retries for up to 30 s, and on
/// giving up says what health showed.
async fn post_trial(addr: SocketAddr) -> u64 {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let r = http(
            addr,
            "POST",
            "/api/trials",
            &[("Content-Type", "application/json")],
            b"{}",
        )
        .await
        .unwrap();
        if r.status == 202 {
            return r.json().unwrap()["id"].as_u64().unwrap();
        }
        let body = r.json().unwrap_or(Value::Null);
        let transient = r.status == 409
            && (body["reason"] == "robot_not_commanding" || body["reason"] == "device_unavailable");
        if !transient || Instant::now() > deadline {
            let health = get(addr, "/api/health").await;
            panic!("POST /api/trials: {} {body}; health {health}", r.status);
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Waits until trial `id`'s record has finished; returns it.
async fn wait_record(addr: SocketAddr, id: u64, timeout: Duration) -> Value {
    let deadline = Instant::now() + timeout;
    loop {
        let r = get(addr, &format!("/api/trials/{id}")).await;
        if r["status"] != "running" {
            return r;
        }
        assert!(Instant::now() < deadline, "trial {id} still running: {r}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

fn truth_lines(path: &Path) -> Vec<Value> {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .map(|l| serde_json::from_str(l).expect("a truth line is JSON"))
        .collect()
}

/// Runs `step` on the served real lab (an operator's heartbeat must run:
/// the pendulum step moves the arm home) and returns its result, once the
/// robot commands; the job must end `done` within 3 minutes. A step refused
/// because the magnet board did not answer (simavr starved beside `stress-ng
/// --cpu 2`: the step then says so and writes nothing, as it must) is run
/// again once the board answers, at most three times in all.
/// The operator's page: a heartbeat every 200 ms (the real lab's dead-man).
struct Heartbeat {
    beating: Arc<AtomicBool>,
    task: tokio::task::JoinHandle<()>,
}

impl Heartbeat {
    fn start(addr: SocketAddr) -> Self {
        let beating = Arc::new(AtomicBool::new(true));
        let task = {
            let beating = Arc::clone(&beating);
            tokio::spawn(async move {
                while beating.load(Relaxed) {
                    let _ = http(addr, "POST", "/api/heartbeat", &[], b"").await;
                    tokio::time::sleep(Duration::from_millis(200)).await;
                }
            })
        };
        Self { beating, task }
    }

    async fn stop(self) {
        self.beating.store(false, Relaxed);
        let _ = self.task.await;
    }
}

/// `isochron world --scenario SCENARIO` (with `world_args`) writing its lab
/// configuration and truth into `dir`, its operator watching the service, and
/// `isochron serve --config` on that configuration: the two processes, the
/// service's address and the world's ready line.
fn world_and_lab(
    bin: &Path,
    scenario: &Path,
    dir: &Path,
    world_args: &[&str],
) -> (Proc, Proc, SocketAddr, Value) {
    let (lab, truth) = (dir.join("lab.toml"), dir.join("truth.jsonl"));
    // The service's port, chosen before the world starts (its operator
    // watches the service; the service reads the world's configuration).
    let service: SocketAddr = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .unwrap();
    let (world, line) = start(
        "isochron world",
        Process::new(bin)
            .arg("world")
            .arg("--scenario")
            .arg(scenario)
            .args(world_args)
            .arg("--operator")
            .arg(format!("http://{service}"))
            .arg("--lab-config")
            .arg(&lab)
            .arg("--truth")
            .arg(&truth),
        "\"lab_config\"",
        Duration::from_secs(30),
    );
    let ready: Value = serde_json::from_str(&line).unwrap();
    let (serve, addr) = serve_lab_at(bin, &lab, &dir.join("data"), "isochron serve", service);
    (world, serve, addr, ready)
}

/// The address in `serve`'s "listening on http://ADDR/" line.
fn listening_addr(line: &str) -> SocketAddr {
    line.split("http://")
        .nth(1)
        .and_then(|s| s.split(['/', ' ']).next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no address in {line:?}"))
}

/// `isochron serve --config LAB --data-dir DATA` on a free port: the
/// process and its address.
fn serve_lab(bin: &Path, lab: &Path, data: &Path, name: &'static str) -> (Proc, SocketAddr) {
    serve_lab_at(bin, lab, data, name, SocketAddr::from(([127, 0, 0, 1], 0)))
}

/// `isochron serve --config LAB --data-dir DATA --bind BIND`.
fn serve_lab_at(
    bin: &Path,
    lab: &Path,
    data: &Path,
    name: &'static str,
    bind: SocketAddr,
) -> (Proc, SocketAddr) {
    let (serve, line) = start(
        name,
        Process::new(bin)
            .arg("serve")
            .arg("--bind")
            .arg(bind.to_string())
            .arg("--config")
            .arg(lab)
            .arg("--data-dir")
            .arg(data),
        "listening on http://",
        Duration::from_secs(60),
    );
    let addr = listening_addr(&line);
    (serve, addr)
}

/// The world webcam's truth (`GET /truth` beside its stream): the drawn LED
/// latency and what it delivered, the frames' lateness added.
async fn camera_truth(ready: &Value) -> Value {
    let url = ready["camera_url"].as_str().unwrap();
    let host: SocketAddr = url
        .trim_start_matches("http://")
        .split('/')
        .next()
        .and_then(|h| h.parse().ok())
        .unwrap_or_else(|| panic!("no address in {url}"));
    let r = http(host, "GET", "/truth", &[], b"").await.unwrap();
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    r.json().unwrap()
}

async fn calibrate(addr: SocketAddr, step: &str) -> Value {
    for attempt in 1..=3 {
        // Ready, and the robot commanding steadily for 2 s (a starved
        // machine's FRI leaves commanding now and then; a step started right
        // after it came back is likely cut again).
        let deadline = Instant::now() + Duration::from_secs(60);
        let mut steady: Option<(Instant, u64)> = None;
        loop {
            let ready = http(addr, "GET", "/api/state", &[], b"")
                .await
                .ok()
                .and_then(|r| r.json().ok())
                .filter(|s| {
                    s["fri"]["session"] == "commanding_active"
                        && (s["magnet"] == "on" || s["magnet"] == "off")
                        && s["camera"]["lost"] == false
                        && s["camera"]["frame"].as_u64().is_some_and(|f| f > 0)
                })
                .and_then(|s| s["fri"]["commanding_lost"].as_u64());
            steady = match (steady, ready) {
                (Some((since, lost)), Some(now)) if now == lost => Some((since, lost)),
                (_, Some(now)) => Some((Instant::now(), now)),
                (_, None) => None,
            };
            if steady.is_some_and(|(since, _)| since.elapsed() >= Duration::from_secs(2)) {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "the robot does not command steadily, the board does not answer, or the camera does not deliver"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let r = http(addr, "POST", &format!("/api/calibration/{step}"), &[], b"")
            .await
            .unwrap();
        assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
        let deadline = Instant::now() + Duration::from_secs(180);
        let status = loop {
            let c = get(addr, "/api/calibration").await;
            if c["job"]["state"] != "running" {
                break c;
            }
            assert!(Instant::now() < deadline, "the step did not end: {c}");
            tokio::time::sleep(Duration::from_millis(500)).await;
        };
        assert_eq!(status["source"], "the real lab", "{status}");
        let message = status["job"]["message"].as_str().unwrap_or_default();
        // What a lab's script runs again: a board that answered late, or a
        // robot that left commanding for a moment (a starved machine's FRI).
        let again = [
            "magnet device",
            "left commanding",
            "moving the arm home was stopped",
        ];
        if status["job"]["state"] == "failed"
            && again.iter().any(|a| message.contains(a))
            && attempt < 3
        {
            println!("world lab: {step} step refused (attempt {attempt}): {message}");
            continue;
        }
        if status["job"]["state"] != "done" {
            let state = get(addr, "/api/state").await;
            let health = get(addr, "/api/health").await;
            panic!(
                "the {step} step did not succeed: {status}\n camera: {}\n fri: {}\n devices: {}",
                state["camera"], state["fri"], health["devices"]
            );
        }
        let fri = get(addr, "/api/state").await["fri"].clone();
        println!(
            "world lab: {step} step done: {message} (FRI: commanding lost {} times so far)",
            fri["commanding_lost"]
        );
        return status["job"]["result"].clone();
    }
    unreachable!("the third attempt returns or fails above")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn trials_on_the_world_are_judged_by_the_measured_judge_as_the_world_judges_them() {
    let _one = ONE_LAB.lock().await;
    let Some(_) = firmware() else {
        return;
    };
    let Some(bin) = isochron_tests::isochron_bin(&[
        (&["world", "--help"], "--lab-config"),
        (&["serve", "--help"], "--config"),
    ]) else {
        return;
    };
    let n: usize = std::env::var("WORLD_LAB_TRIALS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    let dir = tempfile::tempdir().unwrap();
    let (lab, truth) = (dir.path().join("lab.toml"), dir.path().join("truth.jsonl"));
    let scenario = std::env::var_os("WORLD_LAB_SCENARIO").map_or_else(
        || Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml"),
        std::path::PathBuf::from,
    );
    let (world, mut serve, addr, ready) =
        world_and_lab(&bin, &scenario, dir.path(), &["--allow-uncalibrated"]);
    if std::env::var_os("WORLD_LAB_SCENARIO").is_none() {
        assert_eq!(ready["world"], "truthful", "{ready}");
    }
    // The configuration is a real lab's: nothing in it names a world.
    let text = std::fs::read_to_string(&lab).unwrap();
    assert!(
        text.contains("mode = \"real\"") && !text.contains("[world"),
        "{text}"
    );

    // The operator's page: a heartbeat every 200 ms (the real lab's dead-man).
    let heart = Heartbeat::start(addr);

    // `WORLD_LAB_STEPS=lab` or `all` (`make eval-world`): the calibration
    // steps before the trials, as a lab brought up from nothing runs them.
    // `make test` runs none here (the world is truthful: the lab's beliefs
    // are its truth); the accuracy test runs all five on the reality world,
    // then trials on what they measured.
    let steps = std::env::var("WORLD_LAB_STEPS").unwrap_or_default();
    if steps == "lab" || steps == "all" {
        // The pendulum step through the lab's own robot, camera and magnet (a
        // real-lab procedure built so far): the lab's beliefs take the swing the
        // world has before the trials.
        let pendulum = calibrate(addr, "pendulum").await;
        println!(
            "world lab: pendulum step: length {} m (the world's {}), damping {} /s, residual {} m",
            pendulum["swing"]["length_m"],
            ready["pendulum_length_m"],
            pendulum["swing"]["damping_per_s"],
            pendulum["swing"]["residual_rms_m"]
        );
        let (length, true_length) = (
            pendulum["swing"]["length_m"].as_f64().unwrap(),
            ready["pendulum_length_m"].as_f64().unwrap(),
        );
        assert!(
            (length - true_length).abs() < 0.01,
            "length {length} m vs the world's {true_length} m"
        );

        // The latency step through the camera and the board's LED: the world's
        // latency of the LED's row, plus what the stream adds on the way (the
        // world's encoding when it runs late, the transport, the lab's decoding:
        // a real camera's latency includes them; 15 ms beside `stress-ng --cpu
        // 2`), never less; consistent switches pin it within a few ms. A sign
        // or clock error is far outside.
        let latency = calibrate(addr, "latency").await;
        let camera = camera_truth(&ready).await;
        let (est, truth_ms) = (
            latency["latency_ms"].as_f64().unwrap(),
            ready["led_latency_ms"].as_f64().unwrap(),
        );
        println!(
            "world lab: latency step: {est:.2} ms (+- {} ms, {} of {} switches seen); the world's {truth_ms:.2} ms \
             drawn, {} ms delivered ({} of {} frames late)",
            latency["bound_ms"],
            latency["edges_seen"],
            latency["edges"],
            camera["led_delivered_latency_ms"],
            camera["late_frames"],
            camera["frames"]
        );
        assert!(
            est >= truth_ms - 2.0 && est <= truth_ms + 50.0,
            "latency {est} ms vs the world's {truth_ms} ms: {latency}"
        );
        assert!(
            latency["bound_ms"].as_f64().unwrap() <= 5.0
                && latency["edges_consistent"].as_u64().unwrap() >= 10,
            "{latency}"
        );

        // The robot step through FRI: A7 in small steps, the measured joint
        // fitted to the commands; their delay (latency plus servo lag) is the
        // world's within a few ms, and becomes what the lab's online latency
        // estimate starts from.
        let robot = calibrate(addr, "robot").await;
        let (delay, true_delay) = (
            robot["latency_ms"].as_f64().unwrap()
                + robot["servo_time_constant_ms"].as_f64().unwrap(),
            ready["robot_delay_ms"].as_f64().unwrap(),
        );
        println!(
            "world lab: robot step: latency {} ms + servo lag {} ms = {delay:.2} ms; the world's {true_delay:.2} ms \
             (latency {} + servo {})",
            robot["latency_ms"],
            robot["servo_time_constant_ms"],
            ready["robot_latency_ms"],
            ready["robot_servo_lag_ms"]
        );
        assert!(
            (delay - true_delay).abs() <= ROBOT_DELAY_TOLERANCE_MS,
            "robot delay {delay} ms vs the world's {true_delay} ms: {robot}"
        );
    }

    // `WORLD_LAB_STEPS=all`: the camera and camera-robot steps too, so the
    // trials run on the lens, camera pose and intercept point the lab
    // measured (the accuracy test checks those steps against the truth;
    // here their effect on the trials is what counts).
    if steps == "all" {
        let lens = calibrate(addr, "camera").await;
        let cr = calibrate(addr, "camera-robot").await;
        println!(
            "world lab: camera step: k1 {} (the world's {}), RMS {} px; camera-robot step: {} of {} \
             marker poses, RMS {} px, intercept {} (the world's ball at rest {})",
            lens["intrinsics"]["k1"],
            ready["camera_intrinsics"]["k1"],
            lens["rms_px"],
            cr["poses"],
            cr["poses_commanded"],
            cr["reprojection_rms_px"],
            cr["intercept_m"],
            ready["ball_rest_m"]
        );
    }

    heart.stop().await;
    trials_paired(addr, &truth, &serve, &world, n, &ready).await;

    // The same lab with a camera URL that does not answer: the service
    // starts and answers, shows the camera lost, refuses trials (409
    // `device_unavailable`) and writes no record.
    serve.kill();
    let camera = ready["camera_url"].as_str().unwrap();
    let nocam = dir.path().join("nocam.toml");
    // ... and no LED region: the latency step is refused.
    let mut table: toml::Table = toml::from_str(&text).unwrap();
    let led = table
        .get_mut("calibration")
        .and_then(toml::Value::as_table_mut)
        .and_then(|c| c.remove("led_px"));
    assert!(led.is_some(), "the world wrote calibration.led_px: {text}");
    let no_led = toml::to_string(&table).unwrap();
    std::fs::write(
        &nocam,
        no_led.replace(camera, "http://127.0.0.1:9/video.mjpg"),
    )
    .unwrap();
    let (_serve, addr) = serve_lab(
        &bin,
        &nocam,
        &dir.path().join("data-nocam"),
        "isochron serve (no camera)",
    );
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        // 503 until the lab publishes its first state.
        let r = http(addr, "GET", "/api/state", &[], b"").await.unwrap();
        let s = if r.status == 200 {
            r.json().unwrap()
        } else {
            Value::Null
        };
        if s["camera"]["lost"] == true && s["fri"]["session"] == "commanding_active" {
            assert_eq!(s["ready"]["reason"], "device_unavailable", "{}", s["ready"]);
            break;
        }
        assert!(
            Instant::now() < deadline,
            "camera {} fri {}",
            s["camera"],
            s["fri"]
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // Refused. A post the service does not answer within the client's 10 s
    // (a streak beside `stress-ng` saw one; not measured why: the likeliest,
    // the record's two synchronous commits waiting on the disk behind the
    // other tests' writes) is posted again, twice at most.
    let mut tries = 0;
    let r = loop {
        match http(addr, "POST", "/api/trials", &[], b"").await {
            Ok(r) => break r,
            Err(e) if isochron_tests::service::timed_out(&e) && tries < 2 => {
                eprintln!("the refused trial's post: no answer ({e:#}); again");
                tries += 1;
            }
            Err(e) => panic!("POST /api/trials: the service does not answer: {e:#}"),
        }
    };
    assert_eq!(r.status, 409, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json().unwrap()["reason"], "device_unavailable");
    assert_eq!(get(addr, "/api/trials").await, serde_json::json!([]));
    // The latency step without the LED's region: refused, saying what to
    // set, and nothing written.
    step_refused(addr, "latency", "led_px").await;
    // The pendulum step without a camera: refused before the ball is hung,
    // saying it is the camera, and nothing written.
    step_refused(addr, "pendulum", "camera").await;
}

/// Posts calibration `step` and asserts its job fails with a message
/// naming `says`, the step still not done (nothing written).
async fn step_refused(addr: SocketAddr, step: &str, says: &str) {
    let r = http(addr, "POST", &format!("/api/calibration/{step}"), &[], b"")
        .await
        .unwrap();
    assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
    let c = job_end(addr, Duration::from_secs(60)).await;
    assert_eq!(c["job"]["state"], "failed", "{c}");
    assert!(
        c["job"]["message"]
            .as_str()
            .is_some_and(|m| m.contains(says)),
        "{c}"
    );
    assert!(
        c["steps"]
            .as_array()
            .unwrap()
            .iter()
            .any(|s| s["name"] == step && s["done"] == false),
        "{c}"
    );
}

/// The world's truth line of the release during trial record `r` (the
/// coil let go between its start and its end).
fn release_during<'a>(lines: &'a [Value], r: &Value) -> Option<&'a Value> {
    let (t0, t1) = (
        r["started_unix_s"].as_f64()?,
        r["finished_unix_s"].as_f64()?,
    );
    lines.iter().find(|l| {
        l["coil_off_unix_s"]
            .as_f64()
            .is_some_and(|c| c >= t0 && c <= t1)
    })
}

/// Runs `n` trials over REST on a served real lab (more, at most 12 in all,
/// until one is judged: on a starved machine the measured judge may not see
/// a trial, and says so), with an operator's heartbeat, and pairs each with
/// the world's truth file (`truth`) by its coil release: every record
/// finishes; every released trial's release is in the truth; a judged trial
/// is judged by what the lab measured, its contact is the world's, its
/// timing error within 15 ms of the true one and its success the world's
/// (but where the true error lies within the judges' difference of the
/// tolerance). Prints the figures: agreement, |measured - true timing|
/// p50/p95/max, CPU per second of the service and the world.
async fn trials_paired(
    addr: SocketAddr,
    truth: &Path,
    serve: &Proc,
    world: &Proc,
    n: usize,
    ready: &Value,
) {
    let heart = Heartbeat::start(addr);

    let cpu0 = (serve.cpu_s(), world.cpu_s(), Instant::now());
    let mut records = Vec::new();
    // `n` trials, and more (at most 12 in all) until one is judged: on a
    // starved machine the judge may not see a trial (it says so).
    while records.len() < n
        || (records.len() < n.max(12)
            && !records.iter().any(|r: &Value| r["judged_by"] == "measured"))
    {
        wait_ready(addr, Duration::from_secs(60)).await;
        let id = post_trial(addr).await;
        records.push(wait_record(addr, id, Duration::from_secs(60)).await);
    }
    let wall_s = cpu0.2.elapsed().as_secs_f64();
    let cpu = (
        (serve.cpu_s() - cpu0.0) / wall_s,
        (world.cpu_s() - cpu0.1) / wall_s,
    );
    heart.stop().await;

    // Each release is concluded by the world at the next hanging or 8 s
    // after the arm began to move: wait for every done trial's line (an
    // aborted trial may have released too: its line is no count of the
    // others').
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut lines = truth_lines(truth);
    loop {
        let missing: Vec<&Value> = records
            .iter()
            .filter(|r| r["status"] == "done" && release_during(&lines, r).is_none())
            .map(|r| &r["id"])
            .collect();
        if missing.is_empty() {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "no release in the world's truth during trials {missing:?} ({} truth lines: {lines:?})",
            lines.len()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
        lines = truth_lines(truth);
    }

    let mut judged = 0;
    let mut agree = 0;
    let mut deltas = Vec::new();
    let (mut true_successes, mut agree_success) = (0, 0);
    let mut report = Vec::new();
    for r in &records {
        assert_ne!(r["status"], "running", "{r}");
        if r["status"] != "done" {
            report.push(format!(
                "trial {}: {} ({})",
                r["id"], r["status"], r["reason"]
            ));
            continue;
        }
        let t = release_during(&lines, r)
            .unwrap_or_else(|| panic!("no release in the world's truth during trial {r}"));
        if r["judged_by"].is_null() {
            // A trial the measured judge cannot see (the robot's messages
            // paused around the pass or arrival on a starved machine) says so.
            let why = r["reason"].as_str().unwrap_or_default();
            assert!(why.starts_with("not judged (measured)"), "{r}");
            report.push(format!("trial {}: {why}", r["id"]));
            continue;
        }
        assert_eq!(
            r["judged_by"], "measured",
            "a real lab is judged by what it measures: {r}"
        );
        if let Some(why) = t["not_judged"].as_str() {
            // The world judges on its own trace of the release: where it
            // could not, there is nothing to agree with (it says why).
            report.push(format!("trial {}: the world did not judge: {why}", r["id"]));
            continue;
        }
        let m = &r["measured"];
        judged += 1;
        assert_eq!(
            m["torque_signal"], true,
            "the world's robot reports external torques: {r}"
        );
        assert_eq!(m["contact"], t["contact"], "contact: record {r} truth {t}");
        let (me, te) = (
            m["timing_error_ms"].as_f64().unwrap(),
            t["timing_error_ms"].as_f64().unwrap(),
        );
        // The measured judge estimates the pass from the contact and the
        // camera's speed (module docs of `control::measured`): within a few
        // ms of the truth over many trials (`make eval-world` reports the
        // p95); a ball that meets a tool still on its way can put one trial
        // 10 ms apart (seed 1's third release: 3.5 and 10.8 ms in two runs);
        // a clock, sign or pass error is far more than 15 ms.
        assert!(
            (me - te).abs() <= 15.0,
            "measured timing error {me:.2} ms, true {te:.2} ms: record {r} truth {t}"
        );
        // Success agrees, but where the true error lies within the judges'
        // difference of the 20 ms tolerance (either verdict is then right).
        if (te.abs() - 20.0).abs() > (me - te).abs() {
            assert_eq!(r["success"], t["success"], "success: record {r} truth {t}");
        }
        agree += 1;
        deltas.push((me - te).abs());
        true_successes += usize::from(t["success"] == true);
        agree_success += usize::from(r["success"] == t["success"]);
        report.push(format!(
            "trial {}: success {} measured {me:+.2} ms true {te:+.2} ms contact {}",
            r["id"], t["success"], t["contact"]
        ));
    }
    deltas.sort_by(f64::total_cmp);
    let rank = |q: f64| {
        deltas
            .get(((q * deltas.len() as f64).ceil() as usize).saturating_sub(1))
            .copied()
            .unwrap_or(f64::NAN)
    };
    eprintln!(
        "world lab ({} world): {n} trials, {judged} judged, {agree} agree; true successes {true_successes}, \
         the measured judge agrees on success in {agree_success}; |measured - true timing| p50 {:.2} / p95 {:.2} / max {:.2} ms; \
         {wall_s:.0} s, CPU per second: service {:.2}, world {:.2}\n{}",
        ready["world"],
        rank(0.5),
        rank(0.95),
        deltas.last().copied().unwrap_or(f64::NAN),
        cpu.0,
        cpu.1,
        report.join("\n")
    );
    assert!(judged >= 1, "no trial finished to be judged: {report:?}");
}

/// `serve --scenario` runs the world in its own process: a world that is
/// not its beliefs (`[world]`) is a lab to calibrate, so trials are refused
/// (409 `uncalibrated`, no record written) until `--allow-uncalibrated`;
/// then a trial is judged by what the lab measures and the world's truth
/// of it lands in the data folder.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serve_with_a_world_scenario_is_a_real_lab_on_that_world() {
    let _one = ONE_LAB.lock().await;
    let Some(_) = firmware() else {
        return;
    };
    let Some(bin) = isochron_tests::isochron_bin(&[(&["serve", "--help"], "--allow-uncalibrated")])
    else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let scenario = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/reality.toml");
    let serve_in = |data: &Path, extra: &[&str]| {
        let (p, line) = start(
            "isochron serve --scenario",
            Process::new(&bin)
                .arg("serve")
                .args(["--bind", "127.0.0.1:0", "--scenario"])
                .arg(&scenario)
                .arg("--data-dir")
                .arg(data)
                .args(extra),
            "listening on http://",
            Duration::from_secs(60),
        );
        let addr = listening_addr(&line);
        (p, addr)
    };
    let serve = |extra: &[&str]| serve_in(dir.path(), extra);

    let (mut p, addr) = serve(&[]);
    let h = get(addr, "/api/health").await;
    assert_eq!(h["not_ready"]["reason"], "uncalibrated", "{h}");
    let r = http(addr, "POST", "/api/trials", &[], b"").await.unwrap();
    assert_eq!(r.status, 409, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json().unwrap()["reason"], "uncalibrated");
    assert_eq!(get(addr, "/api/trials").await, serde_json::json!([]));
    p.kill();

    // A demo for visitors on the world: its arm needs no operator's hand,
    // so trials start unattended (its own data folder: its releases are
    // not the posted trial's below).
    let demo_dir = tempfile::tempdir().unwrap();
    let (mut p, addr) = serve_in(
        demo_dir.path(),
        &["--allow-uncalibrated", "--demo", "--demo-interval-s", "1"],
    );
    let demo = get(addr, "/api/demo").await;
    assert_eq!(demo["operator_required"], false, "{demo}");
    let deadline = Instant::now() + Duration::from_secs(90);
    loop {
        let demo = get(addr, "/api/demo").await;
        assert_ne!(demo["state"], "operator_needed", "{demo}");
        if demo["trial_id"].is_u64() {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "no demo trial started in 90 s: {demo}; health {}",
            get(addr, "/api/health").await
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    p.kill();

    let (_p, addr) = serve(&["--allow-uncalibrated"]);
    wait_ready(addr, Duration::from_secs(60)).await;
    let id = post_trial(addr).await;
    let rec = wait_record(addr, id, Duration::from_secs(60)).await;
    // A trial the lab could not finish on a starved machine ends aborted
    // with its reason; one that finished is judged by what the lab measures.
    if rec["status"] == "aborted" {
        assert!(
            rec["reason"].as_str().is_some_and(|r| !r.is_empty()),
            "{rec}"
        );
        eprintln!("serve --scenario: the trial was aborted: {}", rec["reason"]);
        return;
    }
    assert_eq!(rec["status"], "done", "{rec}");
    if rec["judged_by"].is_null() {
        // Not judged on a starved machine (the robot's messages paused): it says so.
        assert!(
            rec["reason"]
                .as_str()
                .is_some_and(|r| r.starts_with("not judged (measured)")),
            "{rec}"
        );
        return;
    }
    assert_eq!(rec["judged_by"], "measured", "{rec}");
    let truth = dir.path().join("world-truth.jsonl");
    let deadline = Instant::now() + Duration::from_secs(30);
    while truth_lines(&truth).is_empty() {
        assert!(
            Instant::now() < deadline,
            "no truth line in {}",
            truth.display()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let t = &truth_lines(&truth)[0];
    assert_eq!(t["world"], "reality", "{t}");
    assert_eq!(
        rec["measured"]["contact"], t["contact"],
        "record {rec} truth {t}"
    );
}

/// A served lab strikes (issue #38): `serve --scenario scenarios/strike.toml`
/// runs the reality world in strike mode behind the real interfaces (its
/// contact with the tool's velocity and the world's restitution), and the
/// trial is judged by what the lab measures, as a strike: the measured
/// judge's strike figures (the ball's outgoing speed from the camera's view
/// of the rebound) in the record, the contact as the world's truth line
/// (judged as a strike too) saw it. A starved machine may abort the trial
/// or leave it not judged: each says why.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_served_strike_is_judged_by_measurement_as_the_world_judges_it() {
    let _one = ONE_LAB.lock().await;
    let Some(_) = firmware() else {
        return;
    };
    let Some(bin) = isochron_tests::isochron_bin(&[(&["serve", "--help"], "--allow-uncalibrated")])
    else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let scenario = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/strike.toml");
    let (_p, line) = start(
        "isochron serve --scenario strike",
        Process::new(&bin)
            .arg("serve")
            .args(["--bind", "127.0.0.1:0", "--scenario"])
            .arg(&scenario)
            .arg("--data-dir")
            .arg(dir.path())
            .arg("--allow-uncalibrated"),
        "listening on http://",
        Duration::from_secs(60),
    );
    let addr = listening_addr(&line);
    assert_eq!(get(addr, "/api/params").await["task"]["mode"], "strike");
    wait_ready(addr, Duration::from_secs(60)).await;
    let id = post_trial(addr).await;
    let rec = wait_record(addr, id, Duration::from_secs(90)).await;
    if rec["status"] == "aborted" {
        assert!(
            rec["reason"].as_str().is_some_and(|r| !r.is_empty()),
            "{rec}"
        );
        eprintln!("served strike: the trial was aborted: {}", rec["reason"]);
        return;
    }
    assert_eq!(rec["status"], "done", "{rec}");
    if rec["judged_by"].is_null() {
        // Not judged on a starved machine (the robot's messages paused, the
        // camera lost the rebound): it says so.
        assert!(
            rec["reason"]
                .as_str()
                .is_some_and(|r| r.starts_with("not judged (measured)")),
            "{rec}"
        );
        return;
    }
    assert_eq!(rec["judged_by"], "measured", "{rec}");
    // The measured judge timed a strike.
    let strike = &rec["measured"]["strike"];
    assert_eq!(strike["planned_tool_speed_mps"], 0.5, "{rec}");
    let target = strike["target_ball_speed_mps"].as_f64().unwrap_or(f64::NAN);
    assert!(
        (target - 0.5 * 20f64.to_radians().cos()).abs() < 1e-9,
        "{rec}"
    );
    if rec["measured"]["contact"] == true {
        // A judged contact has its rebound measured.
        assert!(
            strike["ball_speed_mps"].as_f64().is_some_and(|v| v > 0.0),
            "{rec}"
        );
    }
    let truth = dir.path().join("world-truth.jsonl");
    let deadline = Instant::now() + Duration::from_secs(30);
    while truth_lines(&truth).is_empty() {
        assert!(
            Instant::now() < deadline,
            "no truth line in {}",
            truth.display()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let t = &truth_lines(&truth)[0];
    assert!(t["strike"].is_object(), "the world judged no strike: {t}");
    assert_eq!(
        rec["measured"]["contact"], t["contact"],
        "record {rec} truth {t}"
    );
    eprintln!(
        "served strike: measured timing {} ms, speed {} m/s, success {}; truth {} ms, {} m/s, {}",
        rec["measured"]["timing_error_ms"],
        strike["ball_speed_mps"],
        rec["success"],
        t["timing_error_ms"],
        t["strike"]["ball_speed_mps"],
        t["success"]
    );
}

/// The world judges a strike by what physically happened, not by its
/// scenario file's mode: a served lab whose scenario says stop
/// (`strike.toml` with `task.mode = "stop"`), switched to strike over `PUT
/// /api/params`, strikes; the world's truth line is a strike's (the true
/// tool's speed at contact, the ball's outgoing speed) without the aim it
/// cannot know (`aim_known: false`), and the record carries the strike's
/// predicted rebound beside the seen one. A starved machine's trial that was
/// aborted or not judged says so.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stop_lab_switched_to_strike_over_rest_is_judged_as_a_strike_by_the_world() {
    let _one = ONE_LAB.lock().await;
    let Some(_) = firmware() else {
        return;
    };
    let Some(bin) = isochron_tests::isochron_bin(&[(&["serve", "--help"], "--allow-uncalibrated")])
    else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let strike = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/strike.toml"),
    )
    .unwrap();
    assert!(strike.contains("mode = \"strike\""));
    let scenario = dir.path().join("stop.toml");
    std::fs::write(
        &scenario,
        strike.replace("mode = \"strike\"", "mode = \"stop\""),
    )
    .unwrap();
    let data = dir.path().join("data");
    let (_p, line) = start(
        "isochron serve --scenario stop",
        Process::new(&bin)
            .arg("serve")
            .args(["--bind", "127.0.0.1:0", "--scenario"])
            .arg(&scenario)
            .arg("--data-dir")
            .arg(&data)
            .arg("--allow-uncalibrated"),
        "listening on http://",
        Duration::from_secs(60),
    );
    let addr = listening_addr(&line);
    assert_eq!(get(addr, "/api/params").await["task"]["mode"], "stop");
    let r = http(
        addr,
        "PUT",
        "/api/params",
        &[("Content-Type", "application/json")],
        br#"{"task": {"mode": "strike"}}"#,
    )
    .await
    .unwrap();
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(get(addr, "/api/params").await["task"]["mode"], "strike");
    wait_ready(addr, Duration::from_secs(60)).await;
    let id = post_trial(addr).await;
    let rec = wait_record(addr, id, Duration::from_secs(90)).await;
    if rec["status"] == "aborted" {
        assert!(
            rec["reason"].as_str().is_some_and(|r| !r.is_empty()),
            "{rec}"
        );
        eprintln!("switched strike: the trial was aborted: {}", rec["reason"]);
        return;
    }
    assert_eq!(rec["status"], "done", "{rec}");
    let strike = &rec["measured"]["strike"];
    assert!(strike.is_object(), "the lab did not strike: {rec}");
    // The controller's prediction, from its beliefs (restitution 0: the
    // tool's speed along the return).
    let predicted = strike["predicted"]["ball_speed_mps"]
        .as_f64()
        .unwrap_or(f64::NAN);
    assert!(
        (predicted - 0.5 * 20f64.to_radians().cos()).abs() < 1e-9,
        "{rec}"
    );
    let truth = data.join("world-truth.jsonl");
    let deadline = Instant::now() + Duration::from_secs(30);
    while truth_lines(&truth).is_empty() {
        assert!(
            Instant::now() < deadline,
            "no truth line in {}",
            truth.display()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let t = &truth_lines(&truth)[0];
    if t["not_judged"].is_string() {
        eprintln!("switched strike: the world did not judge: {t}");
        return;
    }
    let k = &t["strike"];
    assert!(k.is_object(), "the world judged a stop: {t}");
    assert_eq!(k["aim_known"], false, "{t}");
    assert!(k["target_ball_speed_mps"].is_null(), "{t}");
    if t["contact"] == true {
        // The true tool met the ball at about the planned speed and sent it back.
        let tool = k["tool_speed_mps"].as_f64().unwrap_or(f64::NAN);
        assert!((tool - 0.5).abs() < 0.15, "{t}");
        assert!(k["ball_speed_mps"].as_f64().is_some_and(|v| v > 0.2), "{t}");
        assert_eq!(
            t["success"],
            t["timing_error_ms"]
                .as_f64()
                .is_some_and(|e| e.abs() <= 20.0),
            "{t}"
        );
    }
    eprintln!(
        "switched strike: record {} (measured {} ms, ball predicted {predicted:.3} seen {} m/s); truth {} ms, tool {} m/s, ball {} m/s, success {}",
        rec["success"],
        rec["measured"]["timing_error_ms"],
        strike["ball_speed_mps"],
        t["timing_error_ms"],
        k["tool_speed_mps"],
        k["ball_speed_mps"],
        t["success"]
    );
}

/// `isochron serve` without a config (`make run`'s lab, the dashboard's):
/// a truthful world in the service's process behind a real lab's
/// interfaces, judged by what the lab measures, its calibration records
/// naming that world. Its stand follows each trial's distance and release
/// angle (a REST script's `distance_m`, `release_deg`): the world's ball
/// hangs where the trial's arm goes, so the world's own truth sees the arm
/// meet it at both ends of the range (without the stand, a trial at 0.40 m
/// meets no ball hanging at the range's middle, 0.575 m).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serve_without_a_config_is_a_truthful_world_whose_stand_follows_each_trials_distance() {
    let _one = ONE_LAB.lock().await;
    let Some(_) = firmware() else {
        return;
    };
    let Some(bin) = isochron_tests::isochron_bin(&[(&["serve", "--help"], "--allow-uncalibrated")])
    else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let (_p, line) = start(
        "isochron serve",
        Process::new(&bin)
            .arg("serve")
            .args(["--bind", "127.0.0.1:0", "--data-dir"])
            .arg(dir.path()),
        "listening on http://",
        Duration::from_secs(60),
    );
    let addr = listening_addr(&line);
    wait_ready(addr, Duration::from_secs(60)).await;
    let c = get(addr, "/api/calibration").await;
    assert_eq!(
        c["source"], "the simulated lab: a truthful world (seed 1) behind a real lab's interfaces",
        "{c}"
    );
    assert_eq!(c["trials_refused"], Value::Null, "{c}");
    let truth = dir.path().join("world-truth.jsonl");
    for (distance_m, release_deg) in [(0.40, 15.0), (0.70, 25.0)] {
        let mut starved = 0;
        let rec = loop {
            let body = format!("{{\"distance_m\": {distance_m}, \"release_deg\": {release_deg}}}");
            let deadline = Instant::now() + Duration::from_secs(30);
            let id = loop {
                let r = http(
                    addr,
                    "POST",
                    "/api/trials",
                    &[("Content-Type", "application/json")],
                    body.as_bytes(),
                )
                .await
                .unwrap();
                if r.status == 202 {
                    break r.json().unwrap()["id"].as_u64().unwrap();
                }
                assert!(
                    r.status == 409 && Instant::now() < deadline,
                    "POST /api/trials {body}: {} {}",
                    r.status,
                    String::from_utf8_lossy(&r.body)
                );
                tokio::time::sleep(Duration::from_millis(100)).await;
            };
            let rec = wait_record(addr, id, Duration::from_secs(60)).await;
            if isochron_tests::service::starved(&rec) && starved < 2 {
                // A starved machine's devices ended it: another one.
                starved += 1;
                eprintln!("serve: trial {id} aborted on a starved machine: {rec}");
                continue;
            }
            break rec;
        };
        assert_eq!(rec["status"], "done", "{rec}");
        assert!(
            (rec["distance_m"].as_f64().unwrap() - distance_m).abs() < 1e-9,
            "{rec}"
        );
        // The world's truth of that release: the ball hung where the trial
        // asked (its angle) and the arm met it there.
        let deadline = Instant::now() + Duration::from_secs(30);
        let t = loop {
            let lines = truth_lines(&truth);
            if let Some(t) = release_during(&lines, &rec) {
                break t.clone();
            }
            assert!(
                Instant::now() < deadline,
                "no truth line for {rec} in {}: {lines:?}",
                truth.display()
            );
            tokio::time::sleep(Duration::from_millis(200)).await;
        };
        println!("serve at {distance_m} m: record {rec}\n truth {t}");
        assert_eq!(t["world"], "truthful", "{t}");
        assert!(
            (t["release_angle_deg"].as_f64().unwrap().abs() - release_deg).abs() < 1e-9,
            "{t}"
        );
        if let Some(why) = t["not_judged"].as_str() {
            // The world could not judge its trace of the release (it says
            // why): its contact says nothing then.
            eprintln!("serve at {distance_m} m: the world did not judge: {why}");
            continue;
        }
        assert_eq!(
            t["contact"], true,
            "the arm at {distance_m} m met no ball: {t}"
        );
        // A stop: the tool met the ball at rest, and the world judges a stop
        // (it judges strikes by what happened, whatever the scenario says).
        assert!(t["strike"].is_null(), "a stop judged as a strike: {t}");
        if rec["judged_by"] == "measured" {
            assert_eq!(rec["measured"]["contact"], true, "{rec}");
        } else {
            // Not judged on a starved machine (the robot's messages paused): it says so.
            assert!(
                rec["reason"]
                    .as_str()
                    .is_some_and(|r| r.starts_with("not judged (measured)")),
                "{rec}"
            );
        }
    }
}

/// Bad hardware descriptions get a clear error and change nothing: a world
/// file with an unknown key is refused naming it, no lab configuration
/// written.
#[test]
fn a_world_file_with_an_unknown_key_is_refused_and_nothing_is_written() {
    let Some(bin) = isochron_tests::isochron_bin(&[(&["world", "--help"], "--lab-config")]) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.toml");
    std::fs::write(
        &bad,
        "[world.pendulum]\nlength_error_m = [0.0, 0.01]\nstring_colour = \"red\"\n",
    )
    .unwrap();
    let lab = dir.path().join("lab.toml");
    let out = Process::new(&bin)
        .arg("world")
        .arg("--scenario")
        .arg(&bad)
        .arg("--lab-config")
        .arg(&lab)
        .arg("--truth")
        .arg(dir.path().join("truth.jsonl"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("string_colour"), "{err}");
    assert!(!lab.exists(), "no lab configuration for a refused world");
}

/// A lab configuration pointing at nothing (no controller at its address, a
/// camera URL where nothing listens, a serial port that does not exist): the
/// service starts and answers, `/api/health` names each device and why, a
/// trial is refused with the reason, and no trial is recorded.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lab_config_pointing_at_nothing_names_each_device_and_starts_nothing() {
    let Some(bin) = isochron_tests::isochron_bin(&[(&["serve", "--help"], "--config")]) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // Ports nobody listens on: bound, then let go.
    let free_tcp = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let free_udp = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let tty = dir.path().join("no-such-tty");
    let data = dir.path().join("data");
    let scenario = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml");
    let cfg = dir.path().join("lab.toml");
    std::fs::write(
        &cfg,
        format!(
            "[server]\nbind = \"127.0.0.1:0\"\ndata_dir = {data:?}\n\
             [lab]\nmode = \"real\"\nallow_uncalibrated = true\nscenario = {scenario:?}\ndead_man = false\n\
             [camera]\ndevice = \"http://{free_tcp}/stream.mjpg\"\n\
             [fri]\nlocal_bind = \"127.0.0.1:0\"\ncontroller = \"{free_udp}\"\nperiod_ms = 5\n\
             [magnet]\nport = {tty:?}\n",
        ),
    )
    .unwrap();
    let (_p, line) = start(
        "isochron serve --config (pointing at nothing)",
        Process::new(&bin).args(["serve", "--config"]).arg(&cfg),
        "listening on http://",
        Duration::from_secs(60),
    );
    let addr = listening_addr(&line);
    // Each device is named with why, once each has been tried (the camera's
    // first attempt and the magnet's take a moment).
    let deadline = Instant::now() + Duration::from_secs(30);
    let h = loop {
        let h = get(addr, "/api/health").await;
        let devices = h["devices"].as_array().cloned().unwrap_or_default();
        let named = |d: &str| devices.iter().any(|p| p["device"] == d);
        if (named("robot") && named("camera") && named("magnet")) || Instant::now() > deadline {
            break h;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert_eq!(h["status"], "ok", "{h}");
    assert_eq!(h["ready"], false, "{h}");
    let message = |d: &str| {
        h["devices"]
            .as_array()
            .and_then(|a| a.iter().find(|p| p["device"] == d))
            .and_then(|p| p["message"].as_str())
            .unwrap_or_else(|| panic!("no {d} in {h}"))
            .to_owned()
    };
    assert!(message("robot").contains("no message"), "{h}");
    let camera = message("camera");
    assert!(
        camera.contains(&format!("http://{free_tcp}/stream.mjpg"))
            && camera.contains("nothing answers"),
        "{camera}"
    );
    let magnet = message("magnet");
    assert!(
        magnet.contains(&*tty.to_string_lossy()) && magnet.contains("No such file"),
        "{magnet}"
    );
    // A trial is refused with the reason; nothing is recorded.
    let r = http(addr, "POST", "/api/trials", &[], b"").await.unwrap();
    assert_eq!(r.status, 409, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json().unwrap()["reason"], "robot_not_commanding");
    assert_eq!(get(addr, "/api/trials").await, serde_json::json!([]));
}

/// A real lab straight from `isochron world`'s configuration: uncalibrated,
/// it refuses trials, and a step whose prerequisites are not calibrated
/// (the camera-robot step: the camera and the pendulum) is refused with
/// them named (409 `prerequisites`), nothing written.
async fn refuses_until_calibrated(addr: SocketAddr) {
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut h = get(addr, "/api/health").await;
    while h["not_ready"]["reason"] == "starting" && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(100)).await;
        h = get(addr, "/api/health").await;
    }
    assert_eq!(h["not_ready"]["reason"], "uncalibrated", "{h}");
    let r = http(addr, "POST", "/api/calibration/camera-robot", &[], b"")
        .await
        .unwrap();
    assert_eq!(r.status, 409, "{}", String::from_utf8_lossy(&r.body));
    let body = r.json().unwrap();
    assert_eq!(body["reason"], "prerequisites", "{body}");
    let message = body["error"].as_str().unwrap_or_default();
    assert!(
        message.contains("camera") && message.contains("pendulum"),
        "{body}"
    );
    let status = get(addr, "/api/calibration").await;
    assert!(
        status["steps"]
            .as_array()
            .is_some_and(|s| s.iter().all(|s| s["done"] == false)),
        "{status}"
    );
}

/// The five calibration steps of a real lab and their accuracy, through
/// `isochron world`'s cabinet, webcam and Arduino. The pendulum step moves
/// the arm home, switches the magnet on (the world's operator hangs the
/// ball), lets go, records the free swing through the lab's own camera and
/// fits it; the latency step switches the board's LED and watches it in the
/// frames; the robot step moves A7 in small steps through FRI and fits the
/// measured joint to the commands; the camera step fits the lens to the
/// chessboard the operator holds; the camera-robot step tours the marker
/// disc on the tool. First draw: the lab refuses trials until calibrated,
/// the step's length is the world's, not the believed one, written with its
/// source and taken by the lab's beliefs, and after the five steps the lab
/// runs [`WORLD_CALIB_TRIALS`] trials on what they measured, paired with the
/// world's truth (`trials_paired`: the short version of the real lab end
/// to end; `make eval-world` runs 100 on the same world). Over `WORLD_CALIB_DRAWS` (default 1: `make
/// test`; `make eval-world` takes 10) hidden draws of `scenarios/reality.toml`
/// (seeds 1..=N), each a world process and a lab brought up from its
/// configuration, both steps over REST, and the estimates set against the
/// truth the world printed when it started. A table, one row a draw, then
/// each error's mean and largest. The latency estimate is never earlier than
/// the webcam delivered its frames; how much later (the stream's transport
/// and the lab's decoding, longer on a loaded machine) is reported, and
/// bounded only when `WORLD_CALIB_LATENCY_MAX_MS` says so (`make eval-world`:
/// 20 ms, on a quiet machine).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_calibration_steps_accuracy_over_hidden_draws_of_the_reality_world() {
    let _one = ONE_LAB.lock().await;
    assert!(firmware().is_some(), "the magnet firmware (make firmware)");
    let bin = isochron_tests::isochron_bin(&[
        (&["world", "--help"], "--lab-config"),
        (&["serve", "--help"], "--config"),
    ])
    .expect("the isochron binary");
    let draws: u64 = std::env::var("WORLD_CALIB_DRAWS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    let latency_max_ms: Option<f64> = std::env::var("WORLD_CALIB_LATENCY_MAX_MS")
        .ok()
        .and_then(|v| v.parse().ok());
    let scenario = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/reality.toml");
    let believed = rt_core::params::Scenario::from_file(&scenario)
        .unwrap()
        .pendulum
        .length_m;
    println!(
        "calibration accuracy: {draws} hidden draws of {} through isochron world (reality world)",
        scenario.display()
    );
    println!(
        "calibration accuracy: seed | length est / true (m) | error (mm) | damping est / true (1/s), drag (1/m) \
         | latency est / delivered (ms) | error (ms) | bound (ms) | robot delay est / true (ms) | error (ms)"
    );
    let (mut length_err_mm, mut latency_err_ms, mut robot_err_ms) =
        (Vec::new(), Vec::new(), Vec::new());
    let (mut camera_k1_err, mut camera_corner_px) = (Vec::new(), Vec::new());
    let (mut camera_rot_deg, mut camera_pos_mm) = (Vec::new(), Vec::new());
    for seed in 1..=draws {
        let dir = tempfile::tempdir().unwrap();
        let seed_arg = seed.to_string();
        let (world, serve, addr, ready) =
            world_and_lab(&bin, &scenario, dir.path(), &["--seed", &seed_arg]);
        assert_eq!(ready["world"], "reality", "{ready}");
        if seed == 1 {
            refuses_until_calibrated(addr).await;
        }
        let heart = Heartbeat::start(addr);
        let pendulum = calibrate(addr, "pendulum").await;
        let latency = calibrate(addr, "latency").await;
        let camera = camera_truth(&ready).await;
        let robot = calibrate(addr, "robot").await;
        heart.stop().await;
        let num = |v: &Value, what: &str| {
            v.as_f64()
                .unwrap_or_else(|| panic!("seed {seed}: no {what} in {v}"))
        };
        // The camera step, last (its lens changes what the lab measures):
        // the world's operator holds the board where the job asks.
        let lens = calibrate(addr, "camera").await;
        let (k, t): (
            rt_core::vision::CameraIntrinsics,
            rt_core::vision::CameraIntrinsics,
        ) = (
            serde_json::from_value(lens["intrinsics"].clone())
                .unwrap_or_else(|e| panic!("seed {seed}: the camera step's result {lens}: {e}")),
            serde_json::from_value(ready["camera_intrinsics"].clone())
                .unwrap_or_else(|e| panic!("seed {seed}: the world's camera {ready}: {e}")),
        );
        let (w, h) = (
            num(&lens["width_px"], "width") - 1.0,
            num(&lens["height_px"], "height") - 1.0,
        );
        let corner_err_px = |inset: f64| {
            [
                (inset, inset),
                (w - inset, inset),
                (inset, h - inset),
                (w - inset, h - inset),
            ]
            .iter()
            .map(|&(u, v)| rt_core::vision::undistortion_error_px(&t, &k, u, v))
            .fold(0.0, f64::max)
        };
        let (corner_40, corner_100) = (corner_err_px(40.0), corner_err_px(100.0));
        // As on the simulated world: k1 within the issue's 0.02, the focal
        // lengths and principal point within 5 px, a sharp fit.
        for (what, est, truth) in [
            ("fx", k.fx_px, t.fx_px),
            ("fy", k.fy_px, t.fy_px),
            ("cx", k.cx_px, t.cx_px),
            ("cy", k.cy_px, t.cy_px),
        ] {
            assert!(
                (est - truth).abs() < 5.0,
                "seed {seed}: {what} {est} vs {truth}: {lens}"
            );
        }
        assert!(num(&lens["rms_px"], "rms") < 0.5, "seed {seed}: {lens}");
        assert!(
            lens["views_used"].as_u64().is_some_and(|n| n >= 10),
            "seed {seed}: {lens}"
        );
        camera_k1_err.push(k.k1 - t.k1);
        camera_corner_px.push(corner_100);
        println!(
            "calibration accuracy: {seed} camera: fx {:.1} / {:.1}, cx {:.1} / {:.1}, cy {:.1} / {:.1}, \
             k1 {:+.4} / {:+.4}, k2 {:+.4} / {:+.4}; RMS {:.3} px over {} views; undistortion error 40 / 100 px \
             in from the image's corners {corner_40:.2} / {corner_100:.2} px",
            k.fx_px,
            t.fx_px,
            k.cx_px,
            t.cx_px,
            k.cy_px,
            t.cy_px,
            k.k1,
            t.k1,
            k.k2,
            t.k2,
            num(&lens["rms_px"], "rms"),
            lens["views_used"]
        );
        // The camera-robot step, after the camera step (its lens) and the
        // pendulum step (the rest pixel): the world's operator fits the
        // marker disc to the tool when the job asks; the arm tours the
        // poses through the lab's own FRI; the disc is found in the
        // webcam's frames. Against the world's true camera and ball.
        let heart = Heartbeat::start(addr);
        let cr = calibrate(addr, "camera-robot").await;
        heart.stop().await;
        let (pose, true_pose): (rt_core::vision::CameraPose, rt_core::vision::CameraPose) = (
            serde_json::from_value(cr["camera_pose"].clone())
                .unwrap_or_else(|e| panic!("seed {seed}: the camera-robot result {cr}: {e}")),
            serde_json::from_value(ready["camera_pose"].clone())
                .unwrap_or_else(|e| panic!("seed {seed}: the world's camera pose {ready}: {e}")),
        );
        let rot_deg = rt_core::calibration::extrinsics::rotation_angle_rad(
            &pose.base_from_camera(),
            &true_pose.base_from_camera(),
        )
        .to_degrees();
        let pos_mm = (pose.position() - true_pose.position()).norm() * 1e3;
        let icp_err_mm: [f64; 3] = std::array::from_fn(|i| {
            (num(&cr["intercept_m"][i], "intercept") - num(&ready["ball_rest_m"][i], "rest")) * 1e3
        });
        println!(
            "calibration accuracy: {seed} camera-robot: {} of {} marker poses, reprojection RMS \
             {:.3} px; camera rotation error {rot_deg:.3} deg, position error {pos_mm:.2} mm; \
             intercept error x {:+.2} (depth from the believed plane), y {:+.2}, z {:+.2} mm",
            cr["poses"],
            cr["poses_commanded"],
            num(&cr["reprojection_rms_px"], "rms"),
            icp_err_mm[0],
            icp_err_mm[1],
            icp_err_mm[2]
        );
        assert!(
            cr["poses"].as_u64().is_some_and(|n| n >= 8)
                && num(&cr["reprojection_rms_px"], "rms") < 1.0
                && cr["intercept_depth_from"] == "plane",
            "seed {seed}: {cr}"
        );
        // The simulated world's targets: 0.3 deg and 5 mm for the camera.
        // The intercept point's side and height come from the pendulum
        // step's rest pixel (2-3 mm off here, where the simulated world's
        // touch gives 1-2 mm): within 5 mm. Its depth is the believed
        // plane's: reported.
        assert!(
            rot_deg < 0.3 && pos_mm < 5.0,
            "seed {seed}: camera rotation {rot_deg} deg, position {pos_mm} mm: {cr} vs {true_pose:?}"
        );
        assert!(
            icp_err_mm[1].abs() < 5.0 && icp_err_mm[2].abs() < 5.0,
            "seed {seed}: intercept errors {icp_err_mm:?} mm: {cr}"
        );
        camera_rot_deg.push(rot_deg);
        camera_pos_mm.push(pos_mm);
        if seed == 1 {
            // The lab brought up from nothing runs trials (no
            // `allow_uncalibrated`) on what its steps measured: judged by
            // the measured judge and paired with the world's truth.
            let truth = dir.path().join("truth.jsonl");
            trials_paired(addr, &truth, &serve, &world, WORLD_CALIB_TRIALS, &ready).await;
        }
        if seed == 1 {
            // Seed 1's string is 2 cm shorter than the lab believed: the
            // step measures the world's, writes it with where it was
            // measured, and the lab's beliefs take it.
            let length = num(&pendulum["swing"]["length_m"], "length");
            let true_length = num(&ready["pendulum_length_m"], "true length");
            assert!(
                (believed - true_length).abs() > 0.015 && (length - true_length).abs() < 0.005,
                "length {length} vs the world's {true_length} (believed {believed})"
            );
            let status = get(addr, "/api/calibration").await;
            let file = std::fs::read_to_string(status["file"].as_str().unwrap())
                .expect("the calibration file");
            assert!(file.contains("source = \"the real lab\""), "{file}");
            let p = get(addr, "/api/params").await;
            let taken = p["pendulum"]["length_m"].as_f64().unwrap();
            assert!(
                (taken - length).abs() < 1e-9,
                "beliefs {taken} vs step {length}"
            );
        }
        let (length, true_length) = (
            num(&pendulum["swing"]["length_m"], "length"),
            num(&ready["pendulum_length_m"], "true length"),
        );
        let (lat, drawn, delivered) = (
            num(&latency["latency_ms"], "latency"),
            num(&ready["led_latency_ms"], "drawn latency"),
            num(&camera["led_delivered_latency_ms"], "delivered latency"),
        );
        // The world draws its own contact, within reality.toml's ranges;
        // the judge's beliefs (4 ms, 1 period of 5 ms) are not read from it.
        let (pulse, lag) = (
            num(&ready["contact_pulse_ms"], "contact pulse"),
            num(&ready["torque_lag_ms"], "torque lag"),
        );
        assert!(
            (3.5..=5.0).contains(&pulse) && (4.0..=6.0).contains(&lag),
            "seed {seed}: the world's contact {ready}"
        );
        // The robot step's delay (latency plus servo lag: what the lab's
        // timing takes, `control.latency_prior_ms`) against the world's.
        let (robot_delay, true_delay) = (
            num(&robot["latency_ms"], "robot latency")
                + num(&robot["servo_time_constant_ms"], "servo lag"),
            num(&ready["robot_delay_ms"], "robot delay"),
        );
        if seed == 1 {
            let p = get(addr, "/api/params").await;
            let taken = p["control"]["latency_prior_ms"].as_f64().unwrap();
            assert!(
                (taken - robot_delay).abs() < 1e-6,
                "beliefs {taken} vs step {robot_delay}"
            );
        }
        length_err_mm.push((length - true_length) * 1e3);
        latency_err_ms.push(lat - delivered);
        robot_err_ms.push(robot_delay - true_delay);
        println!(
            "calibration accuracy: {seed} | {length:.4} / {true_length:.4} | {:+.1} | {:.4} / {:.4}, {:.4} \
             | {lat:.2} / {delivered:.2} (drawn {drawn:.2}, {} of {} frames late) | {:+.2} | {:.2} \
             | {robot_delay:.2} / {true_delay:.2} (latency {:.2} + servo {:.2}; the world's {:.2} + {:.2}) | {:+.2}",
            (length - true_length) * 1e3,
            num(&pendulum["swing"]["damping_per_s"], "damping"),
            num(&ready["pendulum_damping_per_s"], "true damping"),
            num(&ready["pendulum_drag_per_m"], "true drag"),
            camera["late_frames"],
            camera["frames"],
            lat - delivered,
            num(&latency["bound_ms"], "bound"),
            num(&robot["latency_ms"], "robot latency"),
            num(&robot["servo_time_constant_ms"], "servo lag"),
            num(&ready["robot_latency_ms"], "true robot latency"),
            num(&ready["robot_servo_lag_ms"], "true servo lag"),
            robot_delay - true_delay
        );
    }
    let summary = |e: &[f64]| {
        let mean = e.iter().map(|v| v.abs()).sum::<f64>() / e.len() as f64;
        let max = e.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
        (mean, max)
    };
    let (l_mean, l_max) = summary(&length_err_mm);
    let (t_mean, t_max) = summary(&latency_err_ms);
    let (r_mean, r_max) = summary(&robot_err_ms);
    println!(
        "calibration accuracy: |length error| mean {l_mean:.1} mm, max {l_max:.1} mm; \
         |latency error| mean {t_mean:.2} ms, max {t_max:.2} ms; |robot delay error| mean {r_mean:.2} ms, \
         max {r_max:.2} ms; |k1 error| max {:.4}, undistortion error 100 px in from the corners max \
         {:.2} px; camera pose error max {:.3} deg, {:.2} mm ({draws} draws)",
        camera_k1_err.iter().fold(0.0_f64, |m, v| m.max(v.abs())),
        camera_corner_px.iter().fold(0.0_f64, |m, v| m.max(*v)),
        camera_rot_deg.iter().fold(0.0_f64, |m, v| m.max(*v)),
        camera_pos_mm.iter().fold(0.0_f64, |m, v| m.max(*v))
    );
    // The robot's delay within 3 ms: what the online estimate starts from
    // (it learns the rest from the motions); a sign or clock error, or a
    // fit of the wrong samples, is tens of ms off.
    assert!(
        r_max <= ROBOT_DELAY_TOLERANCE_MS,
        "robot delay errors (ms): {robot_err_ms:?}"
    );
    // The lens from the board's views through the webcam's JPEG stream:
    // k1 within the issue's target, and what is left of the lens 100 px in
    // from the image's corners within 1.5 px (the simulated world's bound).
    assert!(
        camera_k1_err.iter().all(|e| e.abs() <= 0.02),
        "k1 errors: {camera_k1_err:?}"
    );
    assert!(
        camera_corner_px.iter().all(|&e| e < 1.5),
        "undistortion errors 100 px in from the corners (px): {camera_corner_px:?}"
    );
    // What the lab's timing can live with: the string within 1 cm (0.25% of
    // the period); the latency never earlier than the webcam delivered its
    // frames, and later only by the stream's transport and the lab's
    // decoding (6-7 ms on a quiet machine), which a real camera's latency
    // holds too.
    assert!(l_max < 10.0, "length errors (mm): {length_err_mm:?}");
    assert!(
        latency_err_ms.iter().all(|&e| e >= -2.0),
        "latency estimates earlier than the webcam delivered (ms): {latency_err_ms:?}"
    );
    if let Some(max) = latency_max_ms {
        assert!(
            latency_err_ms.iter().all(|&e| e <= max),
            "latency estimates more than {max} ms later than delivered (ms): {latency_err_ms:?}"
        );
    }
}
