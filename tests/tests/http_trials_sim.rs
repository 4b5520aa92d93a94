//! `POST /api/trials` in the simulated lab: the real closed loop (control step,
//! FRI codec, simulated robot, camera model, ground-truth pendulum, judging)
//! in real time behind the service, as `isochron serve` runs it.

use std::{
    sync::Arc,
    time::{Duration, Instant},
};

use isochron_tests::http;
use rt_core::params::Scenario;
use server::{AppState, LabOptions, Records, app, runtime::start_simulated};

#[tokio::test]
async fn a_trial_in_the_simulated_lab_is_judged_recorded_and_survives_a_restart() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let records = Arc::new(Records::open(&data).unwrap());
    let (lab, sim) = start_simulated(
        Scenario::default(),
        Some(Arc::clone(&records)),
        LabOptions::default(),
        7,
    )
    .unwrap();
    let web = data.join("web");
    std::fs::create_dir_all(&web).unwrap();
    let state = AppState::new(web)
        .with_lab(Arc::clone(&lab))
        .with_records(Arc::clone(&records));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let server = tokio::spawn(async move {
        let _ = axum::serve(server::tuned_listener(listener), app(Arc::new(state))).await;
    });
    let deadline = Instant::now() + Duration::from_secs(10);
    // The FRI session over loopback UDP reaches COMMANDING_ACTIVE.
    while lab
        .latest()
        .is_none_or(|(s, _)| s.fri.session != rt_core::bridge::FriSessionState::CommandingActive)
    {
        assert!(
            Instant::now() < deadline,
            "the simulated lab's FRI session is not commanding: {:?}",
            lab.latest().map(|(s, _)| s.fri)
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let st = http(addr, "GET", "/api/state", &[], b"")
        .await
        .unwrap()
        .json()
        .unwrap();
    assert_eq!(st["trial_state"], "idle");
    assert_eq!(st["fri"]["session"], "commanding_active");

    let r = http(addr, "POST", "/api/trials", &[], b"").await.unwrap();
    assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
    let id = r.json().unwrap()["id"].as_u64().unwrap();
    // A second one while it runs is refused.
    let r = http(addr, "POST", "/api/trials", &[], b"").await.unwrap();
    assert_eq!(r.status, 409);
    let deadline = Instant::now() + Duration::from_secs(60);
    // The timing system as the dashboard sees it: the oscillator's real state
    // and neurons, and the planned path speed, while the arm moves.
    let (mut max_planned, mut max_a, mut hopf_won) = (0.0f64, 0.0f64, false);
    let rec = loop {
        if let Some((s, _)) = lab.latest()
            && s.trial_state == rt_core::bridge::TrialState::Intercepting
        {
            assert!(s.hopf.a.is_finite() && s.hopf.b.is_finite(), "{:?}", s.hopf);
            max_planned = max_planned.max(s.path.speed_planned_mps);
            max_a = max_a.max(s.hopf.a);
            hopf_won |= s.hopf.u_hopf > s.hopf.u_init && s.hopf.u_hopf > s.hopf.u_final;
        }
        let rec = records.get(id).unwrap().unwrap();
        if rec.status != "running" {
            break rec;
        }
        assert!(Instant::now() < deadline, "trial {id} did not end");
        tokio::time::sleep(Duration::from_millis(10)).await;
    };
    println!(
        "simulated trial: {rec:?}; peak planned speed {max_planned:.3} m/s, peak a {max_a:.3}"
    );
    assert!(max_planned > 0.1, "planned path speed {max_planned}");
    assert!(max_a > 0.1, "Hopf a {max_a}");
    assert!(hopf_won, "u_hopf never won while intercepting");
    assert_eq!(rec.status, "done", "{rec:?}");
    let timing = rec.timing_error_ms.unwrap();
    let position = rec.position_error_m.unwrap();
    assert!(timing.is_finite() && position.is_finite(), "{rec:?}");
    assert_eq!(
        rec.success,
        Some(timing <= 20.0 && position <= 0.02 && rec.limit_violations == Some(0))
    );
    assert!(rec.samples > 300, "a few seconds at 200 Hz: {rec:?}");
    server.abort();
    lab.shutdown();
    drop(sim);

    // The record and its recordings survive a restart.
    let records = Arc::new(Records::open(&data).unwrap());
    let again = records.get(id).unwrap().unwrap();
    assert_eq!(again, rec);
    let csv = std::fs::read_to_string(records.recording_path(id)).unwrap();
    assert_eq!(csv.lines().count() as u64, rec.samples + 1);
    assert!(csv.contains("intercepting"));
    let mcap = server::records::csv_to_mcap(&records.recording_path(id)).unwrap();
    let n = mcap::MessageStream::new(&mcap).unwrap().count();
    assert_eq!(n as u64, rec.samples);
}
