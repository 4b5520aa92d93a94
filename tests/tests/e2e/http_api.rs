//! The REST API on a real port over the real bridge: validation, access control,
//! parameters, commands, trials with records and recordings, OpenAPI.

use crate::http_support;

use std::{sync::atomic::Ordering, time::Duration};

use http_support::{start_service, start_service_in, temp_dir, trial_state, wait_for};
use isochron_tests::http;
use rt_core::bridge::TrialState;
use serde_json::{Value, json};
use server::LabOptions;

const TOKEN: &str = "s3cret-token";
const AUTH: (&str, &str) = ("Authorization", "Bearer s3cret-token");

fn opts() -> LabOptions {
    LabOptions::default()
}

#[tokio::test]
async fn bad_input_to_every_mutating_endpoint_is_a_4xx_naming_the_field_and_changes_nothing() {
    let svc = start_service(Some(TOKEN), opts()).await;
    let params_before = http(svc.addr, "GET", "/api/params", &[], b"")
        .await
        .unwrap();
    assert_eq!(params_before.status, 200);
    let big = vec![b' '; 1024 * 1024];
    let mut big_json = b"{\"on\": true, \"pad\": \"".to_vec();
    big_json.extend(std::iter::repeat_n(b'x', 1024 * 1024));
    big_json.extend(b"\"}");
    // (method, path, body, status, field)
    type Case<'a> = (&'a str, &'a str, Vec<u8>, u16, Option<&'a str>);
    let cases: Vec<Case> = vec![
        ("PUT", "/api/params", b"{".to_vec(), 400, None),
        ("PUT", "/api/params", b"not json".to_vec(), 400, None),
        ("PUT", "/api/params", b"[1, 2]".to_vec(), 400, None),
        (
            "PUT",
            "/api/params",
            br#"{"task": {"movement_time_s": "fast"}}"#.to_vec(),
            400,
            Some("task.movement_time_s"),
        ),
        (
            "PUT",
            "/api/params",
            br#"{"pendulum": {"length_m": "NaN"}}"#.to_vec(),
            400,
            Some("pendulum.length_m"),
        ),
        (
            "PUT",
            "/api/params",
            br#"{"pendulum": {"length_m": "inf"}}"#.to_vec(),
            400,
            Some("pendulum.length_m"),
        ),
        (
            "PUT",
            "/api/params",
            br#"{"pendulum": {"length_m": 1e999}}"#.to_vec(),
            400,
            Some("pendulum.length_m"),
        ),
        (
            "PUT",
            "/api/params",
            br#"{"task": {"movement_time_s": -1.0}}"#.to_vec(),
            400,
            Some("task.movement_time_s"),
        ),
        (
            "PUT",
            "/api/params",
            br#"{"task": {"movment_time_s": 1.2}}"#.to_vec(),
            400,
            Some("task.movment_time_s"),
        ),
        (
            "PUT",
            "/api/params",
            br#"{"bogus": 1}"#.to_vec(),
            400,
            Some("bogus"),
        ),
        // The reality lab's [world] runs on the virtual clock only: the
        // real-time lab would silently stay a truthful world.
        (
            "PUT",
            "/api/params",
            br#"{"world": {"camera": {"latency_ms": [-5.0, 15.0]}}}"#.to_vec(),
            400,
            Some("world"),
        ),
        (
            "PUT",
            "/api/params",
            br#"{"camera": {"width_px": 1.5}}"#.to_vec(),
            400,
            Some("camera.width_px"),
        ),
        (
            "PUT",
            "/api/params",
            br#"{"camera": {"drop_rate": 2.0}}"#.to_vec(),
            400,
            Some("camera.drop_rate"),
        ),
        (
            "PUT",
            "/api/params",
            br#"{"task": {"distance_m": [0.9, 0.5]}}"#.to_vec(),
            400,
            Some("task.distance_m"),
        ),
        (
            "PUT",
            "/api/params",
            br#"{"task": {"home_m": [0.3, 0.0]}}"#.to_vec(),
            400,
            Some("task.home_m"),
        ),
        (
            "PUT",
            "/api/params",
            br#"{"task": {"movement_time_s": null}}"#.to_vec(),
            400,
            Some("task.movement_time_s"),
        ),
        // Strike mode's keys (issue #38): an unknown mode, a speed that is
        // not > 0, an elevation beyond 60 degrees.
        (
            "PUT",
            "/api/params",
            br#"{"task": {"mode": "smash"}}"#.to_vec(),
            400,
            Some("task.mode"),
        ),
        (
            "PUT",
            "/api/params",
            br#"{"task": {"mode": "strike", "strike_speed_mps": 0.0}}"#.to_vec(),
            400,
            Some("task.strike_speed_mps"),
        ),
        (
            "PUT",
            "/api/params",
            br#"{"task": {"strike_direction_deg": 90.0}}"#.to_vec(),
            400,
            Some("task.strike_direction_deg"),
        ),
        ("PUT", "/api/params", big.clone(), 413, None),
        ("POST", "/api/magnet", b"{".to_vec(), 400, None),
        ("POST", "/api/magnet", b"{}".to_vec(), 400, Some("on")),
        (
            "POST",
            "/api/magnet",
            br#"{"on": "yes"}"#.to_vec(),
            400,
            Some("on"),
        ),
        (
            "POST",
            "/api/magnet",
            br#"{"on": 1}"#.to_vec(),
            400,
            Some("on"),
        ),
        (
            "POST",
            "/api/magnet",
            br#"{"on": true, "volts": 12}"#.to_vec(),
            400,
            Some("volts"),
        ),
        ("POST", "/api/magnet", b"".to_vec(), 400, None),
        ("POST", "/api/magnet", big_json.clone(), 413, None),
        ("POST", "/api/arm", b"{".to_vec(), 400, None),
        (
            "POST",
            "/api/arm",
            br#"{"force": true}"#.to_vec(),
            400,
            Some("force"),
        ),
        ("POST", "/api/arm", big.clone(), 413, None),
        ("POST", "/api/disarm", br"[]".to_vec(), 400, None),
        (
            "POST",
            "/api/disarm",
            br#"{"now": 1}"#.to_vec(),
            400,
            Some("now"),
        ),
        ("POST", "/api/disarm", big.clone(), 413, None),
        ("POST", "/api/trials", b"{".to_vec(), 400, None),
        (
            "POST",
            "/api/trials",
            br#"{"n": 5}"#.to_vec(),
            400,
            Some("n"),
        ),
        ("POST", "/api/trials", big.clone(), 413, None),
        ("GET", "/api/trials/abc", vec![], 400, Some("id")),
        ("GET", "/api/trials/0", vec![], 400, Some("id")),
        (
            "GET",
            "/api/trials/-3/recording.csv",
            vec![],
            400,
            Some("id"),
        ),
        ("GET", "/api/trials?limit=0", vec![], 400, Some("limit")),
        ("GET", "/api/trials?limit=1001", vec![], 400, Some("limit")),
        (
            "GET",
            "/api/trials?limit=99999999999",
            vec![],
            400,
            Some("limit"),
        ),
        ("GET", "/api/trials?limit=", vec![], 400, Some("limit")),
        // Random bytes, a lone newline, JSON null: not an empty body nor `{}`.
        (
            "POST",
            "/api/disarm",
            vec![0x9f, 0x00, 0xc3, 0x28, 0xff, 0x7b, 0x0a],
            400,
            None,
        ),
        ("POST", "/api/disarm", b"\n".to_vec(), 400, None),
        ("POST", "/api/disarm", b"null".to_vec(), 400, None),
        ("POST", "/api/arm", b"null".to_vec(), 400, None),
        ("POST", "/api/trials", b"[]".to_vec(), 400, None),
        (
            "POST",
            "/api/heartbeat",
            br#"{"n": 1}"#.to_vec(),
            400,
            Some("n"),
        ),
        ("GET", "/api/trials?limit=many", vec![], 400, Some("limit")),
        ("GET", "/api/trials/12345", vec![], 404, None),
    ];
    for (method, path, body, status, field) in &cases {
        let ct = ("Content-Type", "application/json");
        let r = http(svc.addr, method, path, &[AUTH, ct], body)
            .await
            .unwrap();
        let what = format!(
            "{method} {path} {:?}",
            String::from_utf8_lossy(&body[..body.len().min(60)])
        );
        assert_eq!(
            r.status,
            *status,
            "{what}: {}",
            String::from_utf8_lossy(&r.body)
        );
        let j = r
            .json()
            .unwrap_or_else(|e| panic!("{what}: error body is not JSON: {e}"));
        assert!(
            j["error"].as_str().is_some_and(|s| !s.is_empty()),
            "{what}: {j}"
        );
        assert_eq!(j["field"].as_str(), *field, "{what}: {j}");
    }
    // A body in another media type is refused before it is read (415).
    for (path, body) in [
        ("/api/disarm", &b"\x9f\x00random"[..]),
        ("/api/arm", b"{}"),
        ("/api/magnet", br#"{"on": false}"#),
        ("/api/trials", b"{}"),
    ] {
        let ct = ("Content-Type", "application/octet-stream");
        let r = http(svc.addr, "POST", path, &[AUTH, ct], body)
            .await
            .unwrap();
        assert_eq!(
            r.status,
            415,
            "{path}: {}",
            String::from_utf8_lossy(&r.body)
        );
        assert!(r.json().unwrap()["error"].is_string());
    }
    // Nothing changed: parameters, the lab's state, and the control thread got no command.
    let params_after = http(svc.addr, "GET", "/api/params", &[], b"")
        .await
        .unwrap();
    assert_eq!(params_after.json().unwrap(), params_before.json().unwrap());
    assert_eq!(svc.test_lab.stats.commands.load(Ordering::Relaxed), 0);
    let state = http(svc.addr, "GET", "/api/state", &[], b"")
        .await
        .unwrap()
        .json()
        .unwrap();
    assert_eq!(state["trial_state"], "idle");
    assert_eq!(state["magnet"], "unknown");
    let trials = http(svc.addr, "GET", "/api/trials", &[], b"")
        .await
        .unwrap()
        .json()
        .unwrap();
    assert_eq!(trials, json!([]));
}

#[tokio::test]
async fn without_the_token_commands_are_401_and_nothing_happens_with_it_they_work() {
    let svc = start_service(Some(TOKEN), opts()).await;
    let commands: [(&str, &str, &[u8]); 6] = [
        (
            "PUT",
            "/api/params",
            br#"{"task": {"movement_time_s": 1.2}}"#,
        ),
        ("POST", "/api/arm", b""),
        ("POST", "/api/disarm", b""),
        ("POST", "/api/magnet", br#"{"on": false}"#),
        ("POST", "/api/trials", b""),
        // A malformed body still gets 401 first: nothing is parsed for strangers.
        ("POST", "/api/magnet", b"{"),
    ];
    for wrong in [
        None,
        Some("Bearer nope"),
        Some("Basic czNjcmV0LXRva2Vu"),
        Some("Bearer "),
    ] {
        for (method, path, body) in &commands {
            let headers: Vec<(&str, &str)> = wrong.iter().map(|w| ("Authorization", *w)).collect();
            let r = http(svc.addr, method, path, &headers, body).await.unwrap();
            assert_eq!(r.status, 401, "{method} {path} with {wrong:?}");
            assert_eq!(r.header("www-authenticate"), Some("Bearer"));
            assert_eq!(r.json().unwrap()["field"], "authorization");
        }
    }
    assert_eq!(svc.test_lab.stats.commands.load(Ordering::Relaxed), 0);
    assert_eq!(trial_state(&svc), TrialState::Idle);
    let p = http(svc.addr, "GET", "/api/params", &[], b"")
        .await
        .unwrap()
        .json()
        .unwrap();
    assert_eq!(p["task"]["movement_time_s"], 1.5);
    assert_eq!(
        http(svc.addr, "GET", "/api/trials", &[], b"")
            .await
            .unwrap()
            .json()
            .unwrap(),
        json!([])
    );
    // Viewers can watch.
    for path in [
        "/api/state",
        "/api/params",
        "/api/trials",
        "/api/health",
        "/api/openapi.json",
    ] {
        assert_eq!(
            http(svc.addr, "GET", path, &[], b"").await.unwrap().status,
            200,
            "{path}"
        );
    }

    // With the token they work.
    let r = http(
        svc.addr,
        "PUT",
        "/api/params",
        &[AUTH],
        br#"{"task": {"movement_time_s": 1.2}}"#,
    )
    .await
    .unwrap();
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json().unwrap()["task"]["movement_time_s"], 1.2);
    let r = http(svc.addr, "POST", "/api/arm", &[AUTH], b"")
        .await
        .unwrap();
    assert_eq!(r.status, 200);
    assert_eq!(
        r.json().unwrap(),
        json!({"accepted": true, "command": "arm"})
    );
    wait_for(Duration::from_secs(5), || {
        trial_state(&svc) == TrialState::Armed
    })
    .await;
    let r = http(
        svc.addr,
        "POST",
        "/api/magnet",
        &[AUTH],
        br#"{"on": false}"#,
    )
    .await
    .unwrap();
    assert_eq!(r.status, 200);
    wait_for(Duration::from_secs(5), || {
        svc.lab
            .latest()
            .is_some_and(|(s, _)| s.magnet == rt_core::bridge::MagnetState::Off)
    })
    .await;
    // Refused by the lab in its state: 409 with the reason.
    let r = http(svc.addr, "POST", "/api/arm", &[AUTH], b"{}")
        .await
        .unwrap();
    assert_eq!(r.status, 409);
    assert_eq!(r.json().unwrap()["reason"], "busy");
    let r = http(svc.addr, "POST", "/api/disarm", &[AUTH], b"")
        .await
        .unwrap();
    assert_eq!(r.status, 200);
    wait_for(Duration::from_secs(5), || {
        trial_state(&svc) == TrialState::Idle
    })
    .await;
    let r = http(svc.addr, "POST", "/api/disarm", &[AUTH], b"")
        .await
        .unwrap();
    assert_eq!(r.status, 409);
    assert_eq!(r.json().unwrap()["reason"], "not_armed");

    // Stop always works: no token, any body, any state.
    let before = svc.test_lab.stats.stops.load(Ordering::Relaxed);
    for body in [&b""[..], b"{", b"{\"x\": 1}"] {
        let r = http(svc.addr, "POST", "/api/stop", &[], body)
            .await
            .unwrap();
        assert_eq!(r.status, 200);
        let j = r.json().unwrap();
        assert_eq!(j["accepted"], true);
        assert_eq!(j["acknowledged"], true);
    }
    assert_eq!(svc.test_lab.stats.stops.load(Ordering::Relaxed), before + 3);
}

#[tokio::test]
async fn stop_aborts_a_running_trial_without_a_token() {
    let svc = start_service(Some(TOKEN), opts()).await;
    let r = http(svc.addr, "POST", "/api/trials", &[AUTH], b"")
        .await
        .unwrap();
    assert_eq!(r.status, 202);
    let id = r.json().unwrap()["id"].as_u64().unwrap();
    wait_for(Duration::from_secs(5), || {
        trial_state(&svc) == TrialState::Released
    })
    .await;
    let r = http(svc.addr, "POST", "/api/stop", &[], b"").await.unwrap();
    assert_eq!(r.status, 200);
    wait_for(Duration::from_secs(5), || {
        trial_state(&svc) == TrialState::Aborted
    })
    .await;
    let records = std::sync::Arc::clone(&svc.records);
    wait_for(Duration::from_secs(5), || {
        records
            .get(id)
            .unwrap()
            .is_some_and(|t| t.status == "aborted")
    })
    .await;
    let rec = http(svc.addr, "GET", &format!("/api/trials/{id}"), &[], b"")
        .await
        .unwrap()
        .json()
        .unwrap();
    assert_eq!(rec["status"], "aborted");
    assert_eq!(rec["abort_reason"], "stop");
    assert_eq!(rec["success"], false);
}

#[tokio::test]
async fn a_page_of_another_origin_cannot_command_the_lab() {
    let svc = start_service(None, opts()).await;
    let evil = ("Origin", "http://evil.example");
    let r = http(svc.addr, "POST", "/api/arm", &[evil], b"")
        .await
        .unwrap();
    assert_eq!(r.status, 403);
    assert!(r.header("access-control-allow-origin").is_none());
    assert_eq!(svc.test_lab.stats.commands.load(Ordering::Relaxed), 0);
    // The service's own page (same origin) may.
    let own = format!("http://{}", svc.addr);
    let r = http(
        svc.addr,
        "POST",
        "/api/arm",
        &[("Origin", own.as_str())],
        b"",
    )
    .await
    .unwrap();
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    // Without a token (loopback service), commands are open to local tools.
    let r = http(svc.addr, "POST", "/api/disarm", &[], b"")
        .await
        .unwrap();
    assert_eq!(r.status, 200);
}

#[tokio::test]
async fn risky_parameter_changes_are_refused_while_a_trial_runs() {
    let svc = start_service(None, opts()).await;
    let r = http(svc.addr, "POST", "/api/trials", &[], b"")
        .await
        .unwrap();
    assert_eq!(r.status, 202);
    wait_for(Duration::from_secs(5), || trial_state(&svc).busy()).await;
    let r = http(
        svc.addr,
        "PUT",
        "/api/params",
        &[],
        br#"{"task": {"movement_time_s": 1.1}}"#,
    )
    .await
    .unwrap();
    assert_eq!(r.status, 409, "{}", String::from_utf8_lossy(&r.body));
    let j = r.json().unwrap();
    assert_eq!(j["field"], "task.movement_time_s");
    // Judging tolerances do not move the arm: allowed.
    let r = http(
        svc.addr,
        "PUT",
        "/api/params",
        &[],
        br#"{"success": {"timing_tolerance_ms": 15.0}}"#,
    )
    .await
    .unwrap();
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let p = http(svc.addr, "GET", "/api/params", &[], b"")
        .await
        .unwrap()
        .json()
        .unwrap();
    assert_eq!(p["task"]["movement_time_s"], 1.5);
    assert_eq!(p["success"]["timing_tolerance_ms"], 15.0);
}

#[tokio::test]
async fn a_trial_is_recorded_survives_a_restart_and_its_recordings_open() {
    let data = temp_dir("restart");
    let id;
    {
        let svc = start_service_in(data.clone(), None, opts()).await;
        let r = http(svc.addr, "POST", "/api/trials", &[], b"")
            .await
            .unwrap();
        assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
        id = r.json().unwrap()["id"].as_u64().unwrap();
        let path = format!("/api/trials/{id}");
        let running = http(svc.addr, "GET", &path, &[], b"")
            .await
            .unwrap()
            .json()
            .unwrap();
        assert_eq!(running["status"], "running");
        let records = std::sync::Arc::clone(&svc.records);
        wait_for(Duration::from_secs(10), || {
            records.get(id).unwrap().is_some_and(|t| t.status == "done")
        })
        .await;
    }
    // A new service over the same data directory.
    let svc = start_service_in(data, None, opts()).await;
    let rec = http(svc.addr, "GET", &format!("/api/trials/{id}"), &[], b"")
        .await
        .unwrap();
    assert_eq!(rec.status, 200);
    let rec = rec.json().unwrap();
    assert_eq!(rec["status"], "done");
    assert_eq!(rec["success"], true);
    assert_eq!(rec["timing_error_ms"], 1.5);
    assert_eq!(rec["position_error_m"], 0.004);
    let samples = rec["samples"].as_u64().unwrap();
    // Arming .. Holding: 6 states of 40 steps each, recorded at the control rate.
    assert!(samples >= 200, "{rec}");
    let list = http(svc.addr, "GET", "/api/trials", &[], b"")
        .await
        .unwrap()
        .json()
        .unwrap();
    assert_eq!(list[0]["id"], id);

    let csv = http(
        svc.addr,
        "GET",
        &format!("/api/trials/{id}/recording.csv"),
        &[],
        b"",
    )
    .await
    .unwrap();
    assert_eq!(csv.status, 200);
    assert_eq!(csv.header("content-type"), Some("text/csv"));
    let text = String::from_utf8(csv.body).unwrap();
    let table = isochron_tests::CsvTable::parse(&text).unwrap();
    assert_eq!(table.header[0], "trial_state");
    assert!(table.column("q7_rad").is_ok() && table.column("u_hopf").is_ok());
    assert_eq!(table.rows.len() as u64, samples);
    assert!(table.rows.iter().all(|r| r.len() == table.header.len()));
    let times = table.numbers("t_s").unwrap();
    assert!(
        times.windows(2).all(|w| w[1] > w[0]),
        "rows in time order, no gaps in order"
    );
    let states: std::collections::BTreeSet<&str> =
        table.rows.iter().filter_map(|r| r.get(0)).collect();
    for s in ["arming", "released", "tracking", "intercepting", "holding"] {
        assert!(states.contains(s), "{s} recorded: {states:?}");
    }

    let mcap = http(
        svc.addr,
        "GET",
        &format!("/api/trials/{id}/recording.mcap"),
        &[],
        b"",
    )
    .await
    .unwrap();
    assert_eq!(mcap.status, 200);
    // The live recording (written during the trial with Foxglove's schemas;
    // tests/tests/e2e/foxglove.rs checks every channel in detail): it opens, the
    // arm's transforms and joint states are there, and each channel's log
    // times never go backwards.
    let msgs: Vec<_> = mcap::MessageStream::new(&mcap.body)
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    let mut per_topic = std::collections::BTreeMap::<String, Vec<u64>>::default();
    for m in &msgs {
        per_topic
            .entry(m.channel.topic.clone())
            .or_default()
            .push(m.log_time);
    }
    for topic in ["/tf", "/joint_states"] {
        let times = per_topic.get(topic).map_or(&[][..], Vec::as_slice);
        assert!(
            !times.is_empty(),
            "{topic} recorded: {:?}",
            per_topic.keys()
        );
        assert!(
            times.len() as u64 <= samples,
            "{topic}: at most one per control step"
        );
        assert!(
            times.windows(2).all(|w| w[1] >= w[0]),
            "{topic} in time order"
        );
    }
    let tf = msgs.iter().find(|m| m.channel.topic == "/tf").unwrap();
    assert_eq!(
        tf.channel.schema.as_ref().unwrap().name,
        "foxglove.FrameTransforms"
    );
}

#[tokio::test]
async fn without_demo_mode_the_demo_status_says_off_and_the_parameters_schema_describes_each_field()
{
    let svc = start_service(None, opts()).await;
    let r = http(svc.addr, "GET", "/api/demo", &[], b"").await.unwrap();
    assert_eq!(r.status, 200);
    let d = r.json().unwrap();
    assert_eq!(d["enabled"], false, "{d}");
    assert_eq!(d["state"], "off", "{d}");
    assert!(d["message"].as_str().unwrap().contains("--demo"), "{d}");
    let doc = http(svc.addr, "GET", "/api/openapi.json", &[], b"")
        .await
        .unwrap()
        .json()
        .unwrap();
    let schema =
        &doc["paths"]["/api/params"]["put"]["requestBody"]["content"]["application/json"]["schema"];
    let len = &schema["properties"]["pendulum"]["properties"]["length_m"];
    assert_eq!(len["default"], 1.93, "{len}");
    assert!(
        len["description"]
            .as_str()
            .unwrap()
            .contains("Pivot to ball centre"),
        "{len}"
    );
    // Every section's every field has its default and a description.
    let mut fields = 0;
    for (section, sec) in schema["properties"].as_object().unwrap() {
        for (key, p) in sec["properties"].as_object().into_iter().flatten() {
            fields += 1;
            assert!(!p["default"].is_null(), "{section}.{key}: no default");
            assert!(
                p["description"].as_str().is_some_and(|d| d.len() > 3),
                "{section}.{key}: no description"
            );
        }
    }
    assert!(fields > 40, "{fields} fields");
}

#[tokio::test]
async fn the_openapi_document_validates_and_lists_every_endpoint() {
    let svc = start_service(None, opts()).await;
    let r = http(svc.addr, "GET", "/api/openapi.json", &[], b"")
        .await
        .unwrap();
    assert_eq!(r.status, 200);
    let doc = r.json().unwrap();
    assert!(doc["openapi"].as_str().unwrap().starts_with("3.1"));
    assert!(doc["info"]["title"].is_string() && doc["info"]["version"].is_string());
    let expected = [
        ("get", "/api/health"),
        ("get", "/api/state"),
        ("get", "/api/fri"),
        ("get", "/api/params"),
        ("put", "/api/params"),
        ("post", "/api/arm"),
        ("post", "/api/disarm"),
        ("post", "/api/magnet"),
        ("post", "/api/stop"),
        ("post", "/api/heartbeat"),
        ("get", "/api/calibration"),
        ("post", "/api/calibration/{step}"),
        ("post", "/api/trials"),
        ("get", "/api/trials"),
        ("get", "/api/trials/{id}"),
        ("get", "/api/trials/{id}/recording.csv"),
        ("get", "/api/trials/{id}/recording.mcap"),
        ("post", "/api/runs"),
        ("get", "/api/runs"),
        ("get", "/api/runs/{id}"),
        ("delete", "/api/runs/{id}"),
        ("get", "/api/demo"),
        ("get", "/api/robot.urdf"),
        ("get", "/api/openapi.json"),
        ("get", "/ws"),
        ("get", "/ws/camera"),
    ];
    let paths = doc["paths"].as_object().unwrap();
    let mut listed = 0;
    for (path, item) in paths {
        for (method, op) in item.as_object().unwrap() {
            listed += 1;
            assert!(
                expected.contains(&(method.as_str(), path.as_str())),
                "unexpected {method} {path}"
            );
            let responses = op["responses"].as_object().unwrap();
            assert!(!responses.is_empty(), "{method} {path} has responses");
            for (code, resp) in responses {
                assert!(code.len() == 3 && code.parse::<u16>().is_ok(), "{code}");
                assert!(resp["description"].is_string(), "{method} {path} {code}");
            }
            // Path parameters are declared.
            for name in ["id", "step"] {
                if path.contains(&format!("{{{name}}}")) {
                    let params = op["parameters"].as_array().unwrap();
                    assert!(
                        params.iter().any(|p| p["name"] == name
                            && p["in"] == "path"
                            && p["required"] == true)
                    );
                }
            }
        }
    }
    assert_eq!(listed, expected.len(), "every endpoint, once");
    for (method, path) in expected {
        assert!(
            doc["paths"][path][method].is_object(),
            "{method} {path} listed"
        );
    }
    // Commands declare the bearer scheme; every $ref resolves.
    assert_eq!(
        doc["components"]["securitySchemes"]["bearer"]["scheme"],
        "bearer"
    );
    assert!(doc["paths"]["/api/arm"]["post"]["security"].is_array());
    fn refs(v: &Value, out: &mut Vec<String>) {
        match v {
            Value::Object(m) => {
                for (k, x) in m {
                    if k == "$ref" {
                        out.push(x.as_str().unwrap().to_owned());
                    } else {
                        refs(x, out);
                    }
                }
            }
            Value::Array(a) => a.iter().for_each(|x| refs(x, out)),
            _ => {}
        }
    }
    let mut all = Vec::new();
    refs(&doc, &mut all);
    assert!(!all.is_empty());
    for r in all {
        let ptr = r.strip_prefix('#').unwrap();
        assert!(doc.pointer(ptr).is_some(), "dangling $ref {r}");
    }
}

#[tokio::test]
async fn without_a_lab_state_and_commands_are_503_json() {
    let state = server::AppState::new(temp_dir("web"));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(
        async move { axum::serve(listener, server::app(std::sync::Arc::new(state))).await },
    );
    for (m, p) in [
        ("GET", "/api/state"),
        ("POST", "/api/arm"),
        ("POST", "/api/stop"),
        ("GET", "/api/trials"),
    ] {
        let r = http(addr, m, p, &[], b"").await.unwrap();
        assert_eq!(r.status, 503, "{m} {p}");
        assert!(r.json().unwrap()["error"].is_string());
    }
}

/// A trial's start the control loop answers only after the service stopped
/// waiting (a starved machine; here no wait at all): 503 `no_answer` with the
/// trial's id, whose record then finishes as any other; a run follows such
/// trials to their end.
#[tokio::test]
async fn a_start_answered_late_names_its_trial_whose_record_finishes_and_runs_follow_it() {
    let svc = start_service(
        None,
        LabOptions {
            ack_timeout: Duration::ZERO,
            ..opts()
        },
    )
    .await;
    let records = std::sync::Arc::clone(&svc.records);
    let finished = |id: u64| {
        let records = std::sync::Arc::clone(&records);
        move || {
            records
                .get(id)
                .unwrap()
                .is_some_and(|t| t.status != "running")
        }
    };
    // The loop may answer within the poll on rare occasions: then the trial
    // is accepted (202), runs, and the next try is made.
    let mut late = None;
    for _ in 0..20 {
        let r = http(svc.addr, "POST", "/api/trials", &[], b"")
            .await
            .unwrap();
        let v = r.json().unwrap();
        let id = v["id"]
            .as_u64()
            .unwrap_or_else(|| panic!("{} {v}", r.status));
        if r.status == 503 {
            assert_eq!(v["reason"], "no_answer", "{v}");
            assert_eq!(v["error"], "the control loop did not answer in time");
            late = Some(id);
            break;
        }
        assert_eq!(r.status, 202, "{v}");
        wait_for(Duration::from_secs(30), finished(id)).await;
    }
    let id = late.expect("every start was answered within no time at all");
    wait_for(Duration::from_secs(30), finished(id)).await;
    let rec = http(svc.addr, "GET", &format!("/api/trials/{id}"), &[], b"")
        .await
        .unwrap()
        .json()
        .unwrap();
    assert_eq!(rec["status"], "done", "{rec}");

    // A run of two: each start answered late, each trial followed to its end.
    let r = http(svc.addr, "POST", "/api/runs", &[], br#"{"n": 2}"#)
        .await
        .unwrap();
    assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
    let run = r.json().unwrap()["id"].as_u64().unwrap();
    let mut last = Value::Null;
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while std::time::Instant::now() < deadline {
        last = http(svc.addr, "GET", &format!("/api/runs/{run}"), &[], b"")
            .await
            .unwrap()
            .json()
            .unwrap();
        if last["status"] != "running" {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(last["status"], "done", "{last}");
    let ids: Vec<u64> = last["trial_ids"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(Value::as_u64)
        .collect();
    assert_eq!(ids.len(), 2, "{last}");
    for t in ids {
        let rec = records.get(t).unwrap().unwrap();
        assert_eq!(rec.status, "done", "trial {t}");
    }
}
