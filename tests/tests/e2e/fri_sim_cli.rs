//! `isochron fri-sim` as a user runs it: the built binary sends to a real FRI
//! client session over loopback UDP, and its JSON summary (CONTRACT.md) agrees
//! with what the client counted. Bad input gives a one-line error and sends nothing.
//! A client that behaves as KUKA's client SDK application does completes sessions.

use std::io::Read;
use std::net::{SocketAddr, UdpSocket};
use std::path::PathBuf;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::{Duration, Instant};

use rt_core::fri::{
    CommandEncoder, ControlStep, FriClientParams, FriSession, FriSessionParams, Joints, LinkState,
    MonitoringDecoder, SessionState, StepInput, StopReason,
};
use rt_core::sim::kuka::{FriSimParams, SimRunOptions, SimServer};

/// The `isochron` binary with `fri-sim`.
fn isochron() -> Option<PathBuf> {
    isochron_tests::isochron_bin(&[(&["fri-sim", "--help"], "")])
}

/// Waits for `cond`, polling every millisecond, at most `timeout`.
fn wait_for(what: &str, timeout: Duration, mut cond: impl FnMut() -> bool) {
    let start = Instant::now();
    while !cond() {
        assert!(
            start.elapsed() < timeout,
            "timed out after {timeout:?} waiting for {what}"
        );
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// Waits for the process to exit, at most `timeout` (killed after that).
fn wait_exit(child: &mut Child, timeout: Duration) -> ExitStatus {
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status;
        }
        if start.elapsed() > timeout {
            child.kill().ok();
            child.wait().ok();
            panic!("isochron fri-sim did not exit within {timeout:?}");
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// A free loopback UDP port (bound, read and released).
fn free_port() -> u16 {
    UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Moves A1 and A4 a little (a 0.05 rad sine at 1 Hz around the hand-over
/// position) and counts what it was asked to do.
#[derive(Debug, Default)]
struct Wiggle {
    start: Option<Joints>,
    steps: u64,
    max_offset_rad: f64,
    calls: Arc<AtomicU64>,
    stops: Vec<StopReason>,
}

impl ControlStep for Wiggle {
    fn step(&mut self, input: &StepInput<'_>, command_rad: &mut Joints) {
        self.calls.fetch_add(1, Relaxed);
        if !input.commanding {
            return;
        }
        let s = *self.start.get_or_insert(*command_rad);
        self.steps += 1;
        let t = self.steps as f64 * input.receive_period_s;
        let off = 0.05 * (std::f64::consts::TAU * t).sin();
        command_rad[0] = s[0] + off;
        command_rad[3] = s[3] - off;
        self.max_offset_rad = self.max_offset_rad.max(off.abs());
    }

    fn stop(&mut self, reason: StopReason) {
        self.stops.push(reason);
    }
}

#[test]
fn fri_sim_runs_a_session_with_a_real_client_and_reports_json() {
    let Some(bin) = isochron() else { return };
    let (period_ms, duration_s) = (5u32, 1.5f64);
    // The client binds the wildcard address, as KUKA's client SDK does
    // (`0.0.0.0:30200`), and answers whoever sent the datagram (no host set).
    let calls = Arc::new(AtomicU64::new(0));
    let session = FriSession::spawn(
        FriSessionParams {
            bind: SocketAddr::from(([0, 0, 0, 0], 0)),
            controller: None,
            exit_on_idle: false,
            client: FriClientParams::default(),
        },
        Wiggle {
            calls: Arc::clone(&calls),
            ..Wiggle::default()
        },
    )
    .unwrap();
    let client = SocketAddr::from(([127, 0, 0, 1], session.local_addr().port()));
    let cl = Arc::clone(session.stats());
    let controller = SocketAddr::from(([127, 0, 0, 1], free_port()));
    let mut child = Command::new(&bin)
        .args(["fri-sim", "--bind", &controller.to_string()])
        .args(["--client", &client.to_string()])
        .args(["--period-ms", &period_ms.to_string()])
        .args(["--duration-s", &duration_s.to_string(), "--json"])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    wait_for(
        "COMMANDING_ACTIVE at the client",
        Duration::from_secs(5),
        || cl.state() == LinkState::CommandingActive,
    );
    let status = wait_exit(&mut child, Duration::from_secs_f64(duration_s + 10.0));
    let ran = t0.elapsed();
    let (mut out, mut err) = (String::new(), String::new());
    child
        .stdout
        .take()
        .unwrap()
        .read_to_string(&mut out)
        .unwrap();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    assert!(status.success(), "fri-sim failed: {err}");
    wait_for("IDLE at the client", Duration::from_secs(10), || {
        cl.state() == LinkState::Idle
    });
    let control = session.stop().unwrap();
    let st = cl.snapshot();
    eprintln!("fri-sim ran {ran:?}: {out}\nclient {st:?}");

    // One JSON object on stdout, nothing else.
    assert_eq!(out.trim().lines().count(), 1, "{out}");
    let j: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    let n = |k: &str| {
        j[k].as_u64()
            .unwrap_or_else(|| panic!("{k} missing or not a count: {out}"))
    };
    let (sent, replies) = (n("messages_sent"), n("replies"));
    let (late, missing, violations) = (n("late_replies"), n("missing_replies"), n("violations"));
    let states: Vec<&str> = j["states_reached"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s.as_str().unwrap())
        .collect();
    // Walked in order, closed with IDLE at the end.
    assert_eq!(
        states,
        [
            "MONITORING_WAIT",
            "MONITORING_READY",
            "COMMANDING_WAIT",
            "COMMANDING_ACTIVE",
            "IDLE"
        ]
    );
    assert_eq!(violations, 0, "{out}");
    // At most one message per period for the duration, plus the closing IDLE
    // (a loaded machine's stall loses slots: one stall counts one overrun
    // however many periods it lasts, so fewer is no fault of the session).
    let periods = (duration_s * 1e3 / f64::from(period_ms)).round() as u64;
    let overruns = n("overruns");
    assert!(
        sent <= periods + 2 && sent > 0,
        "{sent} messages for {periods} periods ({overruns} overruns)"
    );
    // Loopback loses nothing: the client saw every message, answered all but
    // IDLE, and the controller counted what the client sent (the very last
    // reply may still be in flight when IDLE goes out).
    assert_eq!(st.received, sent, "client received vs messages_sent");
    assert_eq!(st.decode_errors, 0);
    assert_eq!(st.replies, sent - 1, "every message but IDLE is answered");
    assert!(
        replies <= st.replies && st.replies <= replies + 1,
        "controller counted {replies}, client sent {}",
        st.replies
    );
    assert_eq!(n("decode_errors"), 0);
    assert_eq!(n("client_sequence_errors"), 0);
    assert_eq!(n("aborts"), 0, "{out}");
    // Late and missing replies are graded, not gated: a loaded machine makes
    // them (the benchmark reports them; `isochron bench`).
    assert!(late + missing <= sent, "{late} late, {missing} missing");
    // The client counts a reply late only when it took longer than half a period.
    if st.reply_latency.max < f64::from(period_ms) * 1e3 * 0.5 {
        assert_eq!(st.late_replies, 0, "{st:?}");
    }
    // Round trip: one sample per graded reply, ordered, loopback-fast.
    let rtt = &j["rtt_us"];
    let f = |k: &str| {
        rtt[k]
            .as_f64()
            .unwrap_or_else(|| panic!("rtt_us.{k}: {out}"))
    };
    let (p50, p99, max) = (f("p50"), f("p99"), f("max"));
    assert!(rtt["count"].as_u64().unwrap() + 1 >= replies, "{out}");
    assert!(0.0 < p50 && p50 <= p99 && p99 <= max, "{rtt}");
    assert!(p50 < 1_000.0, "median round trip {p50} us on loopback");
    assert!(max < f64::from(period_ms) * 1e3 * 20.0, "{rtt}");
    // The control moved the joints: commands every reply in COMMANDING_ACTIVE,
    // and the controller applied them.
    assert_eq!(calls.load(Relaxed), st.received - 1, "one step per message");
    assert_eq!(control.steps, st.commands);
    assert!(st.commands > 150, "{} commands", st.commands);
    assert!(n("commands_accepted") + 1 >= st.commands);
    assert!(control.max_offset_rad > 0.04);
    assert_eq!(st.guard_step + st.guard_position + st.guard_non_finite, 0);
    assert_eq!(control.stops.last(), Some(&StopReason::SessionClosed));
    assert_eq!(j["final_state"], "IDLE");
}

#[test]
fn fri_sim_refuses_bad_input_with_one_line_and_sends_nothing() {
    let Some(bin) = isochron() else { return };
    let listener = UdpSocket::bind("127.0.0.1:0").unwrap();
    listener.set_nonblocking(true).unwrap();
    let client = listener.local_addr().unwrap().to_string();
    for (args, names) in [
        (vec!["--period-ms", "0"], "--period-ms"),
        (vec!["--period-ms", "101"], "--period-ms"),
        (vec!["--duration-s=-1"], "--duration-s"),
        (vec!["--duration-s", "NaN"], "--duration-s"),
        (vec!["--packet-loss", "1.5"], "packet_loss"),
    ] {
        let mut child = Command::new(&bin)
            .args([
                "fri-sim",
                "--bind",
                "127.0.0.1:0",
                "--client",
                &client,
                "--json",
            ])
            .args(&args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let status = wait_exit(&mut child, Duration::from_secs(10));
        let (mut out, mut err) = (String::new(), String::new());
        child
            .stdout
            .take()
            .unwrap()
            .read_to_string(&mut out)
            .unwrap();
        child
            .stderr
            .take()
            .unwrap()
            .read_to_string(&mut err)
            .unwrap();
        assert!(!status.success(), "{args:?} was accepted: {out}");
        assert_eq!(err.trim().lines().count(), 1, "{args:?}: {err}");
        assert!(err.contains(names), "{args:?}: {err}");
        assert!(out.trim().is_empty(), "{args:?}: {out}");
    }
    // Nothing was sent to the client.
    let mut buf = [0u8; 2048];
    let e = listener.recv_from(&mut buf).unwrap_err();
    assert_eq!(e.kind(), std::io::ErrorKind::WouldBlock);
}

/// What [`kuka_like_client`] saw.
#[derive(Debug, Default)]
struct KukaRun {
    received: u64,
    replies: u64,
    idle_seen: bool,
    states: Vec<SessionState>,
    overlay_max_rad: f64,
}

/// A client that behaves as KUKA's FRI client SDK application does with its
/// default `LBRClient` and a joint sine overlay (as its LBRJointSineOverlay
/// example): bound to the wildcard address, no host configured (answers the
/// address the last datagram came from), `lastSendCounter >= receiveMultiplier`
/// (counted from the first message it gets), `sequenceCounter` from 0,
/// `reflectedSequenceCounter` = the answered message's; MONITORING_*: echoes
/// the commanded positions; COMMANDING_WAIT: the ipo positions; ACTIVE: ipo +
/// a 0.04 rad, 1 Hz sine on A4; IDLE: sends nothing and exits.
fn kuka_like_client(sock: &UdpSocket, timeout: Duration) -> KukaRun {
    sock.set_read_timeout(Some(Duration::from_millis(500)))
        .unwrap();
    let mut dec = MonitoringDecoder::new();
    let mut enc = CommandEncoder::new();
    let mut buf = [0u8; 2048];
    let (mut seq, mut last_send_counter, mut phase) = (0u32, 0u32, 0.0f64);
    let mut run = KukaRun::default();
    let deadline = Instant::now() + timeout;
    while Instant::now() < deadline {
        let Ok((n, from)) = sock.recv_from(&mut buf) else {
            continue;
        };
        let m = dec
            .decode(&buf[..n])
            .expect("the controller's datagram decodes");
        run.received += 1;
        if run.states.last() != Some(&m.session_state) {
            run.states.push(m.session_state);
        }
        let joints = match m.session_state {
            SessionState::Idle => {
                run.idle_seen = true;
                break;
            }
            SessionState::MonitoringWait | SessionState::MonitoringReady => {
                m.commanded_joint_position_rad
            }
            SessionState::CommandingWait => m.ipo_joint_position_rad,
            SessionState::CommandingActive => m.ipo_joint_position_rad.map(|mut q| {
                phase += f64::from(m.send_period_ms) * 1e-3;
                let off = 0.04 * (std::f64::consts::TAU * phase).sin();
                q[3] += off;
                run.overlay_max_rad = run.overlay_max_rad.max(off.abs());
                q
            }),
        };
        last_send_counter += 1;
        if last_send_counter >= m.receive_multiplier {
            last_send_counter = 0;
            let reply = enc
                .encode(seq, m.sequence_counter, joints.as_ref())
                .unwrap();
            sock.send_to(reply, from).unwrap();
            seq += 1;
            run.replies += 1;
        }
    }
    run
}

/// A KUKA-style client application started after `isochron fri-sim` (whose
/// first messages meet a closed port) completes a session against it.
#[test]
fn a_kuka_style_client_started_late_completes_a_session_against_fri_sim() {
    let Some(bin) = isochron() else { return };
    // A busy machine (the whole suite beside it) can starve the client for
    // milliseconds: fri-sim's connection quality falls and it aborts the
    // commanding (seen: 9 late replies, 8 overruns, "connection quality fell
    // to FAIR"). That is the robot's rule working, not this session's fault:
    // such a run is run again (at most 4 tries); any other outcome is judged.
    for attempt in 1..=4 {
        let (run, out, j) = kuka_client_started_late(&bin);
        let starved = j["aborts"] == 1
            && j["abort_reason"]
                .as_str()
                .is_some_and(|r| r.contains("connection quality"))
            && (j["late_replies"].as_u64().unwrap_or(0) > 0
                || j["overruns"].as_u64().unwrap_or(0) > 0);
        if starved && attempt < 4 {
            eprintln!("attempt {attempt}: a starved session, run again: {out}");
            continue;
        }
        check_kuka_client_started_late(&run, &out, &j);
        return;
    }
}

fn kuka_client_started_late(bin: &std::path::Path) -> (KukaRun, String, serde_json::Value) {
    let port = free_port();
    let controller = SocketAddr::from(([127, 0, 0, 1], free_port()));
    let mut child = Command::new(bin)
        .args(["fri-sim", "--bind", &controller.to_string()])
        .args(["--client", &format!("127.0.0.1:{port}")])
        .args(["--period-ms", "2", "--duration-s", "1.5", "--json"])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // The controller sends to a closed port for a while (ICMP port unreachable
    // comes back to it); this delay creates that case, nothing waits on it.
    std::thread::sleep(Duration::from_millis(200));
    let sock = UdpSocket::bind(SocketAddr::from(([0, 0, 0, 0], port))).unwrap();
    let run = kuka_like_client(&sock, Duration::from_secs(10));
    let status = wait_exit(&mut child, Duration::from_secs(10));
    let mut out = String::new();
    child
        .stdout
        .take()
        .unwrap()
        .read_to_string(&mut out)
        .unwrap();
    assert!(status.success());
    eprintln!("KUKA-style client: {run:?}\n{out}");
    let j: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    (run, out, j)
}

fn check_kuka_client_started_late(run: &KukaRun, out: &str, j: &serde_json::Value) {
    assert!(run.idle_seen, "{run:?}");
    assert_eq!(
        run.states,
        [
            SessionState::MonitoringWait,
            SessionState::MonitoringReady,
            SessionState::CommandingWait,
            SessionState::CommandingActive,
            SessionState::Idle
        ]
    );
    assert!(run.overlay_max_rad > 0.03);
    // Messages sent before the client listened were never answered; all
    // later ones were, and the controller counted every answer.
    assert_eq!(j["replies"], run.replies);
    assert_eq!(j["decode_errors"], 0);
    assert_eq!(j["client_sequence_errors"], 0);
    assert_eq!(j["mirror_mismatches"], 0);
    // A stall on a loaded machine can make a reply answer an older message:
    // counted as stale (not timed), never a fault of the session.
    assert!(j["stale_replies"].as_u64().unwrap() <= run.replies, "{out}");
    assert_eq!(j["violations"], 0);
    assert_eq!(j["aborts"], 0, "{out}");
    assert!(j["commands_accepted"].as_u64().unwrap() > 100, "{out}");
}

/// The same client with receiveMultiplier 2 against the controller that
/// expects every other answer; it starts late, so it counts from another
/// message than the controller does.
#[test]
fn a_kuka_style_client_with_receive_multiplier_2_started_late() {
    let sock = UdpSocket::bind(SocketAddr::from(([0, 0, 0, 0], 0))).unwrap();
    let client = SocketAddr::from(([127, 0, 0, 1], sock.local_addr().unwrap().port()));
    let params = FriSimParams {
        fri_period_ms: 2,
        receive_multiplier: 2,
        ..FriSimParams::default()
    };
    let opts = SimRunOptions {
        auto_command: true,
        duration: Some(Duration::from_millis(1500)),
        normal_priority: false,
        keep_commanding: false,
    };
    let server = SimServer::spawn(params, "127.0.0.1:0".parse().unwrap(), client, opts).unwrap();
    let sim = Arc::clone(server.stats());
    // Let one message (seq 0) pass unread: the client counts from seq 1.
    let mut buf = [0u8; 2048];
    sock.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
    let (n, _) = sock.recv_from(&mut buf).unwrap();
    assert_eq!(
        MonitoringDecoder::new()
            .decode(&buf[..n])
            .unwrap()
            .sequence_counter,
        0
    );
    let run = kuka_like_client(&sock, Duration::from_secs(10));
    let report = server.wait(Duration::from_secs(5)).unwrap();
    eprintln!("receiveMultiplier 2: {run:?}\n{report:?}");
    assert!(run.idle_seen);
    assert!(
        run.states.contains(&SessionState::CommandingActive),
        "{run:?}"
    );
    assert_eq!(report.replies, run.replies);
    assert!(run.replies * 2 + 2 >= run.received, "{run:?}");
    // Stale replies (answering an older message after a stall) are counted, not a fault.
    assert!(report.stale_replies <= report.replies, "{report:?}");
    assert_eq!(report.aborts, 0, "{report:?}");
    assert!(sim.commands_accepted.load(Relaxed) > 100, "{report:?}");
}

/// A client whose answers trail by one message (it answers each message when
/// the next one arrives): its answer to the last message before IDLE leaves
/// after the controller sent IDLE, and the controller still counts it, so its
/// count of answers equals the client's (the answers in flight at the close are
/// read for two periods after it).
#[test]
fn answers_in_flight_when_the_session_closes_are_counted() {
    let sock = UdpSocket::bind(SocketAddr::from(([127, 0, 0, 1], 0))).unwrap();
    let client = sock.local_addr().unwrap();
    let params = FriSimParams {
        fri_period_ms: 2,
        late_after_periods: 3.0,
        ..FriSimParams::default()
    };
    let opts = SimRunOptions {
        auto_command: false,
        duration: Some(Duration::from_millis(300)),
        normal_priority: false,
        keep_commanding: false,
    };
    let server = SimServer::spawn(params, "127.0.0.1:0".parse().unwrap(), client, opts).unwrap();
    sock.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
    let mut dec = MonitoringDecoder::new();
    let mut enc = CommandEncoder::new();
    let mut buf = [0u8; 2048];
    let (mut pending, mut seq, mut sent) = (None::<(u32, SocketAddr)>, 0u32, 0u64);
    let mut idle = false;
    while !idle {
        let (n, from) = sock.recv_from(&mut buf).expect("the controller sends");
        let m = dec.decode(&buf[..n]).unwrap();
        if let Some((reflected, to)) = pending.take() {
            sock.send_to(enc.encode(seq, reflected, None).unwrap(), to)
                .unwrap();
            seq += 1;
            sent += 1;
        }
        idle = m.session_state == SessionState::Idle;
        pending = Some((m.sequence_counter, from));
    }
    let report = server.wait(Duration::from_secs(5)).unwrap();
    assert!(sent > 50, "{sent}");
    assert_eq!(report.replies, sent, "{report:?}");
    // A stall of either thread on a loaded machine (the controller's
    // overruns, or this test's own thread, at normal priority beside the
    // other tests, answering more than a period late) can make an answer
    // reach the controller after a newer message: counted as stale, not lost
    // (`replies == sent` above). Seen: 1 stale of 147 beside 2 overruns, and
    // 1 of 150 with none (this thread stalled).
    assert!(report.stale_replies * 10 <= report.replies, "{report:?}");
    assert_eq!(report.decode_errors, 0, "{report:?}");
}
