//! The Calibration panel's API on the simulated lab as `isochron serve` runs
//! it: `GET /api/calibration` (the steps in order, their prerequisites, the
//! job and what it sees), `POST /api/calibration/{step}` (refusals that change
//! nothing; a step that writes its result into the calibration file and hands
//! the new beliefs to the running lab).

use std::{
    sync::Arc,
    time::{Duration, Instant},
};

use isochron_tests::http;
use rt_core::{calibration::CalibrationFile, params::Scenario};
use server::{
    AppState, LabOptions, app,
    calibration::{CalibrationDesk, Step, changes},
    runtime::start_simulated,
};

async fn get(addr: std::net::SocketAddr, path: &str) -> serde_json::Value {
    http(addr, "GET", path, &[], b"")
        .await
        .unwrap()
        .json()
        .unwrap()
}

/// Waits until the lab's robot commands (the robot step runs through FRI).
async fn until_commanding(lab: &server::Lab) {
    let deadline = Instant::now() + Duration::from_secs(60);
    while !lab.latest().is_some_and(|(s, _)| {
        s.fri.session == rt_core::bridge::FriSessionState::CommandingActive
            && s.counters.steps > 100
    }) {
        assert!(Instant::now() < deadline, "the robot does not command");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// A robot step refused for a passing reason: the robot was not
/// commanding, or left commanding (a starved machine's FRI).
fn passing(job: &serde_json::Value) -> bool {
    job["state"] == "failed"
        && job["message"]
            .as_str()
            .is_some_and(|m| m.contains("does not command") || m.contains("left commanding"))
}

/// The robot step posted once the robot commands and followed to its end;
/// posted again (at most 3 times in all) when refused for a passing reason.
async fn robot_step(addr: std::net::SocketAddr, lab: &server::Lab) -> (u64, serde_json::Value) {
    for _ in 0..3 {
        until_commanding(lab).await;
        let r = http(addr, "POST", "/api/calibration/robot", &[], b"")
            .await
            .unwrap();
        assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
        let id = r.json().unwrap()["id"].as_u64().unwrap();
        let job = finished(addr, id, Duration::from_secs(60)).await;
        if !passing(&job) {
            return (id, job);
        }
        println!("robot step refused for a passing reason, posted again: {job}");
    }
    panic!("the robot step was refused three times");
}

/// Waits for the job `id` to leave `running`; returns the job.
async fn finished(addr: std::net::SocketAddr, id: u64, within: Duration) -> serde_json::Value {
    let deadline = Instant::now() + within;
    loop {
        let job = get(addr, "/api/calibration").await["job"].clone();
        if job["id"].as_u64() == Some(id) && job["state"] != "running" {
            return job;
        }
        assert!(Instant::now() < deadline, "job {id} still running: {job}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn calibration_steps_run_on_the_simulated_lab_refusals_change_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("calibration.toml");
    let (lab, _sim) = start_simulated(Scenario::default(), None, LabOptions::default(), 3).unwrap();
    // Trials are refused until the robot step is in the file (a rule like the
    // real lab's, here to see it lift when the step lands).
    let desk = Arc::new(CalibrationDesk::new(
        file.clone(),
        Box::new(|f: &CalibrationFile| f.robot.is_none().then(|| "robot not calibrated".into())),
    ));
    let state = AppState::new(tmp.path().join("web"))
        .with_lab(Arc::clone(&lab))
        .with_calibration(Arc::clone(&desk));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move {
        let _ = axum::serve(server::tuned_listener(listener), app(Arc::new(state))).await;
    });

    // The steps in the order a lab runs them, with their prerequisites.
    let s = get(addr, "/api/calibration").await;
    let names: Vec<&str> = s["steps"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x["name"].as_str().unwrap())
        .collect();
    assert_eq!(
        names,
        [
            "camera",
            "latency",
            "pendulum",
            "camera-robot",
            "robot",
            "contact"
        ]
    );
    assert_eq!(
        s["steps"][3]["missing"],
        serde_json::json!(["camera", "pendulum"])
    );
    assert_eq!(s["job"]["state"], "idle");
    assert_eq!(s["trials_refused"], "robot not calibrated");

    // Refusals: nothing is written, the job stays idle.
    for (path, body, status, what) in [
        (
            "/api/calibration/camera-robot",
            &b""[..],
            409,
            "prerequisites",
        ),
        ("/api/calibration/nope", b"", 404, "no calibration step"),
        ("/api/calibration/robot", b"[1]", 400, "JSON object"),
        ("/api/calibration/robot", br#"{"bogus": 1}"#, 400, "bogus"),
        (
            "/api/calibration/robot",
            br#"{"release_deg": 20}"#,
            400,
            "release_deg",
        ),
        (
            "/api/calibration/pendulum",
            br#"{"release_deg": "x"}"#,
            400,
            "release_deg",
        ),
        (
            "/api/calibration/pendulum",
            br#"{"release_deg": 1e9}"#,
            400,
            "release_deg",
        ),
        ("/api/calibration/robot", b"{", 400, "malformed"),
    ] {
        let r = http(
            addr,
            "POST",
            path,
            &[("content-type", "application/json")],
            body,
        )
        .await
        .unwrap();
        let text = String::from_utf8_lossy(&r.body).to_string();
        assert_eq!(
            r.status,
            status,
            "{path} {}: {text}",
            String::from_utf8_lossy(body)
        );
        assert!(text.contains(what), "{path}: {text}");
    }
    assert!(!file.exists(), "a refused step wrote the calibration file");
    assert_eq!(get(addr, "/api/calibration").await["job"]["state"], "idle");
    let r = http(addr, "POST", "/api/trials", &[], b"").await.unwrap();
    assert_eq!(r.status, 409);
    assert_eq!(r.json().unwrap()["reason"], "uncalibrated");

    // The robot step: accepted, a second start while it runs is refused (busy),
    // a trial too (calibrating); it ends done with what it saw.
    let prior_before = lab.params().control.latency_prior_ms;
    until_commanding(&lab).await;
    let r = http(addr, "POST", "/api/calibration/robot", &[], b"")
        .await
        .unwrap();
    assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
    let id = r.json().unwrap()["id"].as_u64().unwrap();
    let again = http(addr, "POST", "/api/calibration/robot", &[], b"")
        .await
        .unwrap();
    let trial = http(addr, "POST", "/api/trials", &[], b"").await.unwrap();
    let mut job = finished(addr, id, Duration::from_secs(60)).await;
    let mut id = id;
    if passing(&job) {
        (id, job) = robot_step(addr, &lab).await;
    }
    assert_eq!(
        again.status,
        409,
        "{}",
        String::from_utf8_lossy(&again.body)
    );
    assert_eq!(again.json().unwrap()["reason"], "busy");
    assert_eq!(trial.status, 409);
    assert_eq!(job["state"], "done", "{job}");
    assert_eq!(job["progress"], 1.0);
    assert_eq!(job["first"], true);
    let view = &job["view"];
    assert_eq!(view["kind"], "series");
    assert!(view["points"].as_array().unwrap().len() > 100, "{view}");
    assert!(view["fit"].as_array().unwrap().len() > 100);

    // The file holds the result with its stamp; the lab believes it; trials are
    // no longer refused.
    let f = CalibrationFile::from_file(&file).unwrap();
    let rec = f.robot.as_ref().expect("robot section");
    assert!(rec.revision.contains("0.1.0"), "{}", rec.revision);
    assert!(rec.date.ends_with('Z'));
    let want = rec.result.latency_ms + rec.result.servo_time_constant_ms;
    assert_eq!(job["result"]["latency_ms"], rec.result.latency_ms);
    let deadline = Instant::now() + Duration::from_secs(5);
    while (lab.params().control.latency_prior_ms - want).abs() > 1e-9 {
        assert!(
            Instant::now() < deadline,
            "the lab did not take the calibration"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_ne!(prior_before, want);
    let s = get(addr, "/api/calibration").await;
    assert_eq!(s["steps"][4]["done"], true);
    assert_eq!(
        s["steps"][4]["record"]["result"]["latency_ms"],
        rec.result.latency_ms
    );
    assert!(s["trials_refused"].is_null(), "{s}");

    // Run again: what changed from the last calibration.
    let (id2, job) = robot_step(addr, &lab).await;
    assert!(id2 > id, "{id2} after {id}");
    assert_eq!(job["state"], "done", "{job}");
    assert_eq!(job["first"], false);
    // Exactly the numbers that differ between the two results, with their
    // values (the simulated controller takes commands on its cycle, so two
    // runs may agree to the last digit: then there are none).
    let ch = job["changes"].as_array().unwrap();
    let f2 = CalibrationFile::from_file(&file).unwrap();
    let want = changes(
        &serde_json::to_value(&rec.result).unwrap(),
        &serde_json::to_value(f2.robot.unwrap().result).unwrap(),
    );
    assert_eq!(ch.len(), want.len(), "{ch:?} vs {want:?}");
    for (c, w) in ch.iter().zip(&want) {
        assert_eq!(c["key"], w.key.as_str());
        assert_eq!(
            (c["before"].as_f64(), c["after"].as_f64()),
            (Some(w.before), Some(w.after))
        );
        assert_ne!(w.before, w.after);
    }
}

#[test]
fn a_real_lab_desk_refuses_steps_whose_prerequisites_are_missing_and_changes_lists_numbers() {
    let tmp = tempfile::tempdir().unwrap();
    let desk = CalibrationDesk::new(tmp.path().join("c.toml"), Box::new(|_| None));
    // Every step runs on a real lab; the camera-robot step needs the camera
    // step (the lens) and the pendulum step (the rest pixel) first.
    let e = desk.claim(Step::CameraRobot).unwrap_err();
    assert!(
        e.to_string().contains("camera") && e.to_string().contains("pendulum"),
        "{e}"
    );
    assert!(!desk.running());
    assert_eq!(
        Step::CameraRobot.prerequisites(),
        [Step::Camera, Step::Pendulum]
    );
    assert!(Step::Camera.prerequisites().is_empty());
    // The pendulum's free swing runs on a real lab without the camera step
    // (the configuration's intrinsics stand in for it).
    assert!(Step::Pendulum.prerequisites().is_empty());
    // So does the LED's latency (through the LED's region of the image).
    assert!(Step::Latency.prerequisites().is_empty());
    // And the robot's excitation (through FRI alone).
    assert!(Step::Robot.prerequisites().is_empty());
    let id = desk
        .claim(Step::Pendulum)
        .expect("the pendulum step on a real lab");
    assert!(desk.running());
    // A failed step writes nothing and says why.
    let scenario = rt_core::params::Scenario::default();
    assert!(
        desk.conclude(
            id,
            Step::Pendulum,
            &scenario,
            Err(anyhow::anyhow!(
                "calibrate pendulum: the camera delivers no frames"
            )),
            "the real lab"
        )
        .is_none()
    );
    assert!(!desk.running());
    assert!(!desk.path().exists(), "nothing written");
    assert!(desk.status().unwrap().job.message.contains("no frames"));
    let a = serde_json::json!({"x": 1.0, "s": {"y": [1.0, 2.0]}, "t": "a", "only_a": 3.0});
    let b = serde_json::json!({"x": 1.0, "s": {"y": [1.0, 2.5]}, "t": "b", "only_b": 4.0});
    let c = changes(&a, &b);
    assert_eq!(c.len(), 1);
    assert_eq!(c[0].key, "s.y[1]");
    assert_eq!((c[0].before, c[0].after), (2.0, 2.5));
}

/// A trial and a calibration step posted at the same moment: at most one
/// starts (each checks that the other is not running, then starts, as one
/// step). Before the start gate both passed their checks: a demo trial ran
/// beside the calibration step that was to pause it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_trial_and_a_calibration_step_posted_together_never_both_start() {
    let tmp = tempfile::tempdir().unwrap();
    let records = Arc::new(server::Records::open(&tmp.path().join("data")).unwrap());
    let (lab, _sim) = start_simulated(
        Scenario::default(),
        Some(Arc::clone(&records)),
        LabOptions::default(),
        3,
    )
    .unwrap();
    let desk = Arc::new(CalibrationDesk::new(
        tmp.path().join("calibration.toml"),
        Box::new(|_: &CalibrationFile| None),
    ));
    let state = AppState::new(tmp.path().join("web"))
        .with_lab(Arc::clone(&lab))
        .with_records(records)
        .with_calibration(desk);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move {
        let _ = axum::serve(server::tuned_listener(listener), app(Arc::new(state))).await;
    });

    let (mut trials, mut steps, mut neither, mut own) = (0, 0, 0, 0);
    let mut round = 0;
    while trials + steps < 6 {
        round += 1;
        // Both free: the lab ready for a trial and no step running.
        let deadline = Instant::now() + Duration::from_secs(60);
        while get(addr, "/api/health").await["ready"] != true
            || get(addr, "/api/calibration").await["job"]["state"] == "running"
        {
            assert!(
                Instant::now() < deadline,
                "round {round}: the lab never got free"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let (trial, step) = tokio::join!(
            http(addr, "POST", "/api/trials", &[], b""),
            http(addr, "POST", "/api/calibration/robot", &[], b"")
        );
        let (trial, step) = (trial.unwrap(), step.unwrap());
        let (t, s) = (trial.json().unwrap(), step.json().unwrap());
        if trial.status == 202 && step.status == 202 {
            // Both may start one after the other only when the step ended
            // at once: refused because the robot did not command (a busy
            // machine's FRI) before the trial took the gate.
            let job = finished(addr, s["id"].as_u64().unwrap(), Duration::from_secs(60)).await;
            assert!(
                passing(&job),
                "round {round}: both started: trial {t}, step {s}, the step's job {job}"
            );
            neither += 1;
            assert!(neither <= 10, "round {round}: {t} {s}");
            let id = t["id"].as_u64().unwrap();
            let deadline = Instant::now() + Duration::from_secs(60);
            while get(addr, &format!("/api/trials/{id}")).await["status"] == "running" {
                assert!(Instant::now() < deadline, "trial {id} never ended");
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            continue;
        }
        assert!(
            !(trial.status == 202 && step.status == 202),
            "round {round}: both started: trial {t}, step {s}"
        );
        // The one refused says the other runs.
        for (code, body) in [(trial.status, &t), (step.status, &s)] {
            assert!(code == 202 || code == 409, "round {round}: {code} {body}");
        }
        if trial.status == 202 {
            trials += 1;
            let id = t["id"].as_u64().unwrap();
            assert_eq!(step.status, 409, "{s}");
            let deadline = Instant::now() + Duration::from_secs(60);
            while get(addr, &format!("/api/trials/{id}")).await["status"] == "running" {
                assert!(Instant::now() < deadline, "trial {id} never ended");
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        } else if step.status != 202 {
            // Neither: the trial refused for a reason of its own (the robot
            // not commanding for a moment on a busy machine), not for the
            // step. Another round, a bounded number of times.
            neither += 1;
            assert_ne!(t["reason"], "calibrating", "round {round}: {t} {s}");
            assert!(neither <= 10, "round {round}: neither started: {t} {s}");
        } else {
            steps += 1;
            // Refused for the step, or for a reason of the control loop's
            // own that it met first (a plan still pending on a busy machine).
            if t["reason"] != "calibrating" {
                own += 1;
                assert!(
                    ["busy", "robot_not_commanding", "device_unavailable"]
                        .contains(&t["reason"].as_str().unwrap_or_default()),
                    "round {round}: {t}"
                );
            }
            finished(addr, s["id"].as_u64().unwrap(), Duration::from_secs(60)).await;
        }
    }
    println!(
        "posted together {round} times: {trials} trials and {steps} steps started, never both \
         ({neither} rounds neither; {own} steps beside a trial refused for its own reason)"
    );
}
