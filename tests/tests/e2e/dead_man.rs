//! The operator dead-man in the simulated lab with it turned on (as the real
//! lab has it by default): an operator keeps a heartbeat (`POST
//! /api/heartbeat`) while a trial runs; when it stops while the arm moves, the
//! motion stops (abort `operator_lost`) within the dead-man time plus one FRI
//! period of the last heartbeat, the arm comes to rest, and the trial is
//! recorded as aborted for that reason. With heartbeats a trial is not stopped.

use std::{
    sync::Arc,
    time::{Duration, Instant},
};

use isochron_tests::{ServedLab, http};
use rt_core::{bridge::TrialState, params::Scenario};

const TIMEOUT_S: f64 = 0.25;

#[tokio::test]
async fn a_missed_heartbeat_stops_the_moving_arm_within_the_dead_man_time_and_is_recorded() {
    let data = std::env::temp_dir().join(format!("isochron-deadman-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&data);
    let scenario = Scenario::default();
    let period_s = f64::from(scenario.robot.fri_period_ms) * 1e-3;
    let mut setup = rt_core::sim::wall_lab::simulated(scenario, 11);
    setup.operator_timeout_s = Some(TIMEOUT_S);
    let served = ServedLab::start(setup, &data).await;
    // Commanding, and the lab would take a trial.
    served.until_ready().await;
    let (addr, lab, records) = (
        served.addr,
        Arc::clone(&served.lab),
        Arc::clone(&served.records),
    );
    let mut events = lab.subscribe_events();
    let beat = || async {
        let r = http(addr, "POST", "/api/heartbeat", &[], b"")
            .await
            .unwrap();
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        r.json().unwrap()["t_s"].as_f64().unwrap()
    };
    // A heartbeat with a body that is not `{}` is refused like any command.
    let r = http(addr, "POST", "/api/heartbeat", &[], b"{\"x\":1}")
        .await
        .unwrap();
    assert_eq!(r.status, 400);

    beat().await;
    let r = http(addr, "POST", "/api/trials", &[], b"").await.unwrap();
    assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
    let id = r.json().unwrap()["id"].as_u64().unwrap();
    // Heartbeats every 50 ms keep the trial alive through arming, release and
    // tracking, until the arm moves to intercept (longer than the dead-man time).
    let deadline = Instant::now() + Duration::from_secs(40);
    let mut last_beat = beat().await;
    let started = Instant::now();
    loop {
        let s = lab.latest().unwrap().0;
        assert!(
            !matches!(s.trial_state, TrialState::Aborted | TrialState::Done),
            "the trial ended while heartbeats came: {:?}",
            records.get(id).unwrap()
        );
        if s.trial_state == TrialState::Intercepting && s.path.speed_executed_mps > 0.05 {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "never intercepting: {:?}",
            s.trial_state
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
        last_beat = beat().await;
    }
    assert!(
        started.elapsed().as_secs_f64() > 2.0 * TIMEOUT_S,
        "heartbeats kept it alive longer than the dead-man time"
    );
    // The operator goes silent while the arm moves.
    let aborted_at = loop {
        let msg = tokio::time::timeout(Duration::from_secs(5), events.recv())
            .await
            .expect("no abort within 5 s of the last heartbeat")
            .unwrap();
        let v: serde_json::Value = serde_json::from_str(msg.as_str()).unwrap();
        if v.to_string().contains("operator_lost") {
            break v["t_s"].as_f64().unwrap();
        }
    };
    let after = aborted_at - last_beat;
    assert!(
        after > TIMEOUT_S,
        "stopped {after:.4} s after the last heartbeat, before the dead-man time"
    );
    // The motion decelerates to rest (the lab's clock says how fast; the
    // wall-clock deadline only bounds a busy machine's wait).
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let s = lab.latest().unwrap().0;
        if s.path.speed_executed_mps < 1e-3 && s.t_s > aborted_at + 0.2 {
            assert_eq!(s.counters.operator_timeouts, 1);
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the arm is still moving at {} m/s",
            s.path.speed_executed_mps
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    // Recorded.
    let deadline = Instant::now() + Duration::from_secs(5);
    let rec = loop {
        let rec = records.get(id).unwrap().unwrap();
        if rec.status != "running" {
            break rec;
        }
        assert!(
            Instant::now() < deadline,
            "trial {id} not recorded as ended"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    };
    assert_eq!(rec.status, "aborted", "{rec:?}");
    assert_eq!(
        rec.abort_reason.as_deref(),
        Some("operator_lost"),
        "{rec:?}"
    );
    // The stop came at the first control step past the dead-man time: the
    // step before it (one row per step in the recording) was within it. The
    // steps come one FRI period apart, so the stop is within the dead-man
    // time + one period (+ the lateness of a late controller message, which
    // the recording shows; on this shared machine it is printed).
    let csv = std::fs::read_to_string(records.recording_path(id)).unwrap();
    // The file may still be written to: a last line cut short is skipped.
    let table = isochron_tests::CsvTable::parse(&csv).unwrap();
    let t_col = table.column("t_s").unwrap();
    let prev = table
        .rows
        .iter()
        .filter_map(|r| r.get(t_col)?.parse::<f64>().ok())
        .filter(|&t| t < aborted_at)
        .fold(f64::NEG_INFINITY, f64::max);
    let gap = aborted_at - prev;
    println!(
        "dead-man {TIMEOUT_S} s, FRI period {period_s} s: stopped {after:.4} s after the last \
         heartbeat (step gap {:.2} ms)",
        gap * 1e3
    );
    assert!(
        prev <= last_beat + TIMEOUT_S + 1e-6,
        "a step at {prev:.4} s was already past the dead-man time (last heartbeat {last_beat:.4} s)"
    );
    if gap <= period_s * 1.2 {
        assert!(
            after <= TIMEOUT_S + period_s * 1.2,
            "stopped {after:.4} s after the last heartbeat (dead-man {TIMEOUT_S} s + period {period_s} s)"
        );
    }
    served.stop();
    let _ = std::fs::remove_dir_all(&data);
}
