//! The lab's lifecycle over real sockets: `isochron serve` (the simulated
//! lab) as its own process, driven over REST as a script drives it, its
//! WebSocket read as the dashboard reads it.
//!
//! - The natural script (post the next trial the moment the state shows the
//!   last one `done`) loses no record (`ISOCHRON_POST_ON_DONE_TRIALS`,
//!   default 3; the acceptance: 50).
//! - Random REST sequences (trial, stop, arm, disarm, magnet, parameters,
//!   heartbeat, calibration steps, health) at random delays for
//!   `ISOCHRON_LIFECYCLE_SERVED_S` (default 8 s; `make fuzz`: minutes): every
//!   accepted trial has one record that finishes and one end event on the
//!   WebSocket, none is left `running` once the lab is idle, no record exists
//!   for a refused trial, no limit violation, the service still answers.
//! - A service killed mid-trial closes that record at its next start as
//!   `aborted`, `service_restarted`.
//!
//! A request the service does not answer within the client's 10 s (a stall
//! on a starved machine) is what it is to any client: its effect unknown (a
//! trial's post: at most one record the script has no id of), and the
//! service must answer again. A failing test prints the tail of the
//! service's log.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use isochron_tests::service::{Service, api, starved, timed_out};
use isochron_tests::{TrialEnds, isochron_bin};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::Value;

const TOKEN: &str = "lifecycle-token";

fn bin() -> Option<PathBuf> {
    isochron_bin(&[(&["serve", "--help"], "--data-dir")])
}

/// `isochron serve` on a free loopback port with a token and the data
/// directory `dir/data`, its log `dir/serve.log`.
fn serve(bin: &Path, dir: &Path) -> Service {
    let data = dir.join("data");
    Service::start(
        bin,
        TOKEN,
        &dir.join("serve.log"),
        &[Path::new("--data-dir"), &data],
    )
}

/// One request; the test fails when the service does not answer.
async fn request(addr: SocketAddr, method: &str, path: &str, body: &str) -> (u16, Value) {
    api(addr, TOKEN, method, path, body)
        .await
        // `{e:#}`: the cause too (a timeout: the service stalled; refused: it
        // is gone).
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

fn finished(r: &Value) -> bool {
    matches!(r["status"].as_str(), Some("done" | "aborted"))
}

/// Waits until the state stream shows trial `id` `done` (inside its
/// after-done trace, its record not yet concluded), or its record finished
/// (aborted, or the `done` was missed between two polls). Returns whether
/// `done` was seen.
async fn wait_trial_end(addr: SocketAddr, id: u64, timeout: Duration) -> bool {
    let deadline = Instant::now() + timeout;
    loop {
        let s = poll(addr, "/api/state").await;
        if s["trial_id"] == id && s["trial_state"] == "done" {
            return true;
        }
        let r = poll(addr, &format!("/api/trials/{id}")).await;
        if finished(&r) {
            return false;
        }
        assert!(
            Instant::now() < deadline,
            "trial {id} did not end within {timeout:?}: state {} {}, record {r}",
            s["trial_id"],
            s["trial_state"]
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// One poll's `GET path`: its body, or `null` when the service did not
/// answer within the client's timeout (a stalled service is polled again;
/// one that is gone fails the test).
async fn poll(addr: SocketAddr, path: &str) -> Value {
    match api(addr, TOKEN, "GET", path, "").await {
        Ok((_, v)) => v,
        Err(e) if timed_out(&e) => Value::Null,
        Err(e) => panic!("GET {path}: the service does not answer: {e:#}"),
    }
}

async fn ready(addr: SocketAddr, timeout: Duration) -> Value {
    wait_for(addr, "/api/health", timeout, "the lab takes a trial", |h| {
        h["ready"] == true
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn trials_posted_the_moment_the_last_shows_done_each_finish() {
    let Some(bin) = bin() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let svc = serve(&bin, tmp.path());
    let addr = svc.addr;
    let h = ready(addr, Duration::from_secs(30)).await;
    assert_eq!(h["not_ready"], Value::Null, "{h}");
    let mut ends = TrialEnds::connect(addr).await;
    let n: usize = std::env::var("ISOCHRON_POST_ON_DONE_TRIALS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    let (mut ids, mut on_done) = (Vec::new(), 0);
    // Trials posted while the state showed the one before done.
    let (mut posted_on_done, mut last_seen_done) = (Vec::new(), false);
    // Posts answered 503 `no_answer` (a starved control thread, beside
    // `stress-ng`), with the trial's id: its record stays until the loop's
    // late answer settles it (it runs and finishes, or it goes).
    let mut unanswered = Vec::new();
    // Posts without an answer within the client's timeout (a stalled
    // service): each may have made a record this script has no id of.
    let mut posts_unanswered = 0usize;
    // Until a trial posted on done ran to done (a post answered late still
    // has its id, one never answered has none; a starved machine's lab may
    // end one by its own checks, below), three more at most.
    let mut ran_on_done = false;
    let mut i = 0;
    while i < n || (!ran_on_done && i < n + 3) {
        i += 1;
        let (code, body) = match api(addr, TOKEN, "POST", "/api/trials", "").await {
            Ok(answer) => answer,
            Err(e) if timed_out(&e) => {
                eprintln!("trial {i}: no answer: {e:#}");
                posts_unanswered += 1;
                ready(addr, Duration::from_secs(60)).await;
                last_seen_done = false;
                continue;
            }
            Err(e) => panic!("POST /api/trials: the service does not answer: {e:#}"),
        };
        if code == 503 && body["reason"] == "no_answer" {
            let id = body["id"].as_u64().expect("the unanswered trial's id");
            unanswered.push(id);
            if last_seen_done {
                posted_on_done.push(id);
            }
            ready(addr, Duration::from_secs(60)).await;
            last_seen_done = false;
            continue;
        }
        if code == 409 && body["reason"] == "robot_not_commanding" {
            // A starved machine's FRI session left commanding after the
            // lab said it was ready (its quality dipped): refused, saying
            // so, not the race this test is for. Posted again once ready.
            eprintln!("trial {i}: {body}");
            ready(addr, Duration::from_secs(60)).await;
            last_seen_done = false;
            continue;
        }
        if code != 202 {
            // Say which device or state refused it.
            let (_, h) = request(addr, "GET", "/api/health", "").await;
            let (_, s) = request(addr, "GET", "/api/state", "").await;
            panic!(
                "trial {i}: {code} {body}; health {h}; camera {}",
                s["camera"]
            );
        }
        let id = body["id"].as_u64().unwrap();
        ids.push(id);
        if last_seen_done {
            posted_on_done.push(id);
        }
        // While it runs the lab says it is busy (and why), and a trial is refused.
        let (_, h) = request(addr, "GET", "/api/health", "").await;
        if h["ready"] == false {
            assert!(h["not_ready"]["reason"].is_string(), "{h}");
            assert!(h["not_ready"]["message"].is_string(), "{h}");
        }
        // The next trial the moment the state shows this one done (inside its
        // after-done trace), or once its record finished.
        let was_posted_on_done = last_seen_done;
        last_seen_done = wait_trial_end(addr, id, Duration::from_secs(60)).await;
        on_done += usize::from(last_seen_done);
        ran_on_done |= was_posted_on_done && last_seen_done;
    }
    ends.wait_all(&ids, Duration::from_secs(30)).await;
    let list = wait_for(
        addr,
        "/api/trials?limit=1000",
        Duration::from_secs(30),
        "every record finished",
        |l| l.as_array().is_some_and(|a| a.iter().all(finished)),
    )
    .await;
    let list = list.as_array().unwrap();
    println!(
        "post on done: {i} trials posted ({on_done} inside the after-done trace); records: {:?}",
        list.iter()
            .map(|r| (r["id"].as_u64(), r["status"].as_str()))
            .collect::<Vec<_>>()
    );
    // Every posted trial has a record; beside them, only late-answered ones
    // and at most one a post without an answer.
    let listed: Vec<u64> = list.iter().filter_map(|r| r["id"].as_u64()).collect();
    let unexplained = listed
        .iter()
        .filter(|id| !ids.contains(id) && !unanswered.contains(id))
        .count();
    assert!(
        ids.iter().all(|id| listed.contains(id)) && unexplained <= posts_unanswered,
        "records {listed:?} for trials {ids:?} (answered late: {unanswered:?}, \
         posts without an answer: {posts_unanswered})"
    );
    ends.wait_all(&listed, Duration::from_secs(30)).await;
    for r in list {
        // Done; or, on a starved machine (the simulated lab's camera and
        // magnet board are threads of the service, four labs and
        // `stress-ng` beside it), ended by the lab's own checks: no
        // confident pass in time, no frames, or a board silent past its
        // timeouts while it held the ball (seen once in a streak: the
        // first trial, 8 s after the service started). Never refused,
        // lost or left open.
        assert!(r["status"] == "done" || starved(r), "{r}");
        let id = r["id"].as_u64().unwrap();
        assert_eq!(ends.count(id), 1, "one end event for trial {id}");
    }
    assert!(
        on_done > 0,
        "no trial was posted while the state showed done"
    );
    // A trial posted inside the one before's after-done trace runs to the end.
    assert!(
        list.iter().any(|r| r["status"] == "done"
            && r["id"]
                .as_u64()
                .is_some_and(|id| posted_on_done.contains(&id))),
        "no trial posted on done ran to done: {posted_on_done:?}"
    );
}

#[derive(Debug, Clone, Copy)]
enum Action {
    Trial,
    TrialOnDone,
    Stop,
    Arm,
    Disarm,
    Magnet(bool),
    Params,
    Heartbeat,
    Calibration(&'static str),
    Health,
}

fn pick(rng: &mut ChaCha8Rng) -> Action {
    const STEPS: [&str; 5] = ["camera", "latency", "pendulum", "camera-robot", "robot"];
    match rng.random_range(0..100) {
        0..22 => Action::Trial,
        22..40 => Action::TrialOnDone,
        40..47 => Action::Stop,
        47..55 => Action::Arm,
        55..63 => Action::Disarm,
        63..66 => Action::Magnet(true),
        66..74 => Action::Magnet(false),
        74..82 => Action::Params,
        82..88 => Action::Heartbeat,
        88..92 => Action::Calibration(STEPS[rng.random_range(0..STEPS.len())]),
        _ => Action::Health,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn random_rest_sequences_lose_no_trial_record() {
    let Some(bin) = bin() else { return };
    let seconds: f64 = std::env::var("ISOCHRON_LIFECYCLE_SERVED_S")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(8.0);
    let seed: u64 = std::env::var("ISOCHRON_LIFECYCLE_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    let tmp = tempfile::tempdir().unwrap();
    let svc = serve(&bin, tmp.path());
    let addr = svc.addr;
    ready(addr, Duration::from_secs(30)).await;
    let mut ends = TrialEnds::connect(addr).await;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (mut accepted, mut refused, mut commands) = (Vec::new(), 0u32, 0u32);
    // Trials whose POST got 503 `no_answer` (a starved control thread), by
    // id: their record stays until the loop's late answer settles it (it
    // runs and finishes, or it goes).
    let mut unanswered = Vec::new();
    // Trial posts the service did not answer at all within the client's
    // timeout: each may have made a record the script has no id of.
    let mut posts_unanswered = 0usize;
    let mut codes: BTreeMap<String, u32> = BTreeMap::new();
    let mut log = Vec::new();
    let t0 = Instant::now();
    while t0.elapsed().as_secs_f64() < seconds {
        let action = pick(&mut rng);
        log.push(format!("{:.2} s {action:?}", t0.elapsed().as_secs_f64()));
        if let (Action::TrialOnDone, Some(&id)) = (action, accepted.last()) {
            wait_trial_end(addr, id, Duration::from_secs(60)).await;
        }
        let (method, path, body) = match action {
            Action::Trial | Action::TrialOnDone => {
                ("POST", "/api/trials".to_owned(), String::new())
            }
            Action::Stop => ("POST", "/api/stop".to_owned(), String::new()),
            Action::Arm => ("POST", "/api/arm".to_owned(), String::new()),
            Action::Disarm => ("POST", "/api/disarm".to_owned(), String::new()),
            Action::Magnet(on) => ("POST", "/api/magnet".to_owned(), format!("{{\"on\":{on}}}")),
            Action::Params => (
                "PUT",
                "/api/params".to_owned(),
                format!(
                    "{{\"task\":{{\"movement_time_s\":{:.3}}}}}",
                    rng.random_range(1.4..2.0)
                ),
            ),
            Action::Heartbeat => ("POST", "/api/heartbeat".to_owned(), String::new()),
            Action::Calibration(step) => {
                ("POST", format!("/api/calibration/{step}"), "{}".to_owned())
            }
            Action::Health => ("GET", "/api/health".to_owned(), String::new()),
        };
        commands += 1;
        let (code, v) = match api(addr, TOKEN, method, &path, &body).await {
            Ok(answer) => answer,
            // No answer within the client's 10 s: a service stalled on a
            // starved machine. What the request did is unknown here, as to
            // any client whose request timed out (a trial's post may have
            // made a record: counted); the service must answer again.
            Err(e) if timed_out(&e) => {
                log.push(format!("no answer: {e:#}"));
                if path == "/api/trials" {
                    posts_unanswered += 1;
                }
                wait_for(
                    addr,
                    "/api/health",
                    Duration::from_secs(60),
                    "an answer again",
                    |_| true,
                )
                .await;
                continue;
            }
            Err(e) => panic!(
                "{method} {path}: the service does not answer: {e:#}\n{}",
                log.join("; ")
            ),
        };
        // A 5xx only as the service's answer to a control loop that did not
        // answer within its 3 s (beside `stress-ng`: it waited for a done
        // trial's after-done trace, then planned), never a crash.
        let no_answer = code == 503 && v["reason"] == "no_answer";
        assert!(
            code < 500 || no_answer,
            "{method} {path} {body}: {code} {v}\n{}",
            log.join("; ")
        );
        *codes.entry(format!("{method} {path} {code}")).or_default() += 1;
        if path == "/api/trials" {
            if code == 202 {
                accepted.push(v["id"].as_u64().unwrap());
            } else if no_answer {
                unanswered.push(v["id"].as_u64().expect("the unanswered trial's id"));
            } else {
                assert_eq!(code, 409, "{v}");
                assert!(v["reason"].is_string(), "a refusal says why: {v}");
                refused += 1;
            }
        }
        let ms = match rng.random_range(0..10) {
            0..4 => rng.random_range(0..50),
            4..8 => rng.random_range(50..800),
            _ => rng.random_range(800..3000),
        };
        tokio::time::sleep(Duration::from_millis(ms)).await;
    }
    // The end of the script: a stop, then the lab settles.
    let (code, _) = request(addr, "POST", "/api/stop", "").await;
    assert_eq!(code, 200);
    let h = ready(addr, Duration::from_secs(60)).await;
    ends.wait_all(&accepted, Duration::from_secs(30)).await;
    let list = wait_for(
        addr,
        "/api/trials?limit=1000",
        Duration::from_secs(30),
        "no record left running",
        |l| l.as_array().is_some_and(|a| a.iter().all(finished)),
    )
    .await;
    let list = list.as_array().unwrap();
    let mut ids: Vec<u64> = list.iter().filter_map(|r| r["id"].as_u64()).collect();
    ids.sort_unstable();
    let (done, aborted) = (
        list.iter().filter(|r| r["status"] == "done").count(),
        list.iter().filter(|r| r["status"] == "aborted").count(),
    );
    println!(
        "served lifecycle fuzz (seed {seed}, {seconds} s): {commands} commands, {} trials \
         accepted ({done} done, {aborted} aborted), {refused} refused, {} answered late, \
         {posts_unanswered} without an answer; health {h}; answers {codes:?}",
        accepted.len(),
        unanswered.len()
    );
    // Every accepted trial has a record; beside them, only trials the
    // loop answered late (accepted then), and at most one a post without an
    // answer. Each finished, each with one end.
    ends.wait_all(&ids, Duration::from_secs(30)).await;
    let mut want = accepted.clone();
    want.sort_unstable();
    let unexplained = ids
        .iter()
        .filter(|id| !want.contains(id) && !unanswered.contains(id))
        .count();
    assert!(
        want.iter().all(|id| ids.contains(id)) && unexplained <= posts_unanswered,
        "records {ids:?} vs accepted trials {want:?} (answered late: {unanswered:?}, \
         posts without an answer: {posts_unanswered})\n{}",
        log.join("; ")
    );
    for r in list {
        let id = r["id"].as_u64().unwrap();
        assert!(r["reason"].is_string(), "{r}");
        assert!(
            r["limit_violations"].as_u64().unwrap_or(0) == 0,
            "limit violations: {r}"
        );
        assert_eq!(
            ends.count(id),
            1,
            "one end event for trial {id}\n{}",
            log.join("; ")
        );
    }
    // Ends of trials that were not accepted (an event without a trial id aside).
    let unknown: Vec<u64> = ends
        .ids()
        .into_iter()
        .filter(|i| *i != 0 && !ids.contains(i))
        .collect();
    assert!(
        unknown.is_empty(),
        "end events for unknown trials {unknown:?}"
    );
    let (_, st) = request(addr, "GET", "/api/state", "").await;
    assert_eq!(st["counters"]["limit_violations"], 0, "{}", st["counters"]);
    assert_eq!(st["trial_id"], 0, "the idle lab shows no trial: {st}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_trial_running_when_the_service_dies_is_closed_at_the_next_start() {
    let Some(bin) = bin() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let mut svc = serve(&bin, tmp.path());
    ready(svc.addr, Duration::from_secs(30)).await;
    let (code, body) = request(svc.addr, "POST", "/api/trials", "").await;
    assert_eq!(code, 202, "{body}");
    let id = body["id"].as_u64().unwrap();
    let (_, r) = request(svc.addr, "GET", &format!("/api/trials/{id}"), "").await;
    assert_eq!(r["status"], "running", "{r}");
    // Killed (no shutdown of any kind) while the trial runs.
    svc.kill();
    let svc = serve(&bin, tmp.path());
    let (code, r) = request(svc.addr, "GET", &format!("/api/trials/{id}"), "").await;
    assert_eq!(code, 200, "{r}");
    assert_eq!(r["status"], "aborted", "{r}");
    assert_eq!(r["abort_reason"], "service_restarted", "{r}");
    assert_eq!(r["success"], false, "{r}");
    assert!(r["finished_unix_s"].is_number(), "{r}");
    assert_eq!(
        r["reason"],
        "aborted (service_restarted): the service stopped while the trial ran"
    );
}
