//! The FRI session's spin (`RtTuning::spin`, taken by `serve` and `bench`), in
//! a process of its own (the measures are process-wide): the session polls
//! for each expected datagram without sleeping, answers every one, spends a
//! bounded share of its CPU doing so, and gives a spin up when the controller
//! is silent, answering again when it comes back. And the control's
//! `after_reply` work runs after the reply has left.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use rt_core::fri::client::{ControlStep, SessionStats, StepInput};
use rt_core::fri::codec::Joints;
use rt_core::fri::priority::{self, RtTuning};
use rt_core::fri::{FriClientParams, FriSession, FriSessionParams, HoldPosition};
use rt_core::sim::kuka::{FriSimParams, SimRunOptions, SimServer};

fn wait_for(what: &str, timeout: Duration, mut cond: impl FnMut() -> bool) {
    let deadline = Instant::now() + timeout;
    while !cond() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// The simulated controller at 1 ms on loopback, commanding as soon as it can.
fn controller(client: SocketAddr, normal_priority: bool) -> SimServer {
    SimServer::spawn(
        FriSimParams {
            fri_period_ms: 1,
            ..FriSimParams::default()
        },
        SocketAddr::from(([127, 0, 0, 1], 0)),
        client,
        SimRunOptions {
            auto_command: true,
            duration: None,
            normal_priority,
            keep_commanding: false,
        },
    )
    .unwrap()
}

#[test]
fn the_session_spins_for_expected_datagrams_answers_all_and_gives_up_on_silence() {
    priority::configure(RtTuning::parse("spin").unwrap());
    let status = priority::enable();
    assert!(status.asked.spin && !status.asked.fifo, "{status:?}");
    assert!(priority::spin_enabled());
    let loopback = SocketAddr::from(([127, 0, 0, 1], 0));
    let session = FriSession::spawn(
        FriSessionParams {
            bind: loopback,
            client: FriClientParams::default(),
            ..FriSessionParams::default()
        },
        HoldPosition,
    )
    .unwrap();
    let sim = controller(session.local_addr(), false);
    let stats = std::sync::Arc::clone(session.stats());
    wait_for("1,000 replies", Duration::from_secs(10), || {
        stats.replies.load(Relaxed) >= 1_000
    });
    // Measured over a window of 1,000 more messages.
    let (r0, s0, t0) = (
        stats.replies.load(Relaxed),
        stats.spin_ns.load(Relaxed),
        Instant::now(),
    );
    let sent0 = sim.stats().messages_sent.load(Relaxed);
    wait_for("1,000 more replies", Duration::from_secs(10), || {
        stats.replies.load(Relaxed) >= r0 + 1_000
    });
    let spun = stats.spin_ns.load(Relaxed) - s0;
    let window = t0.elapsed().as_nanos() as u64;
    let sent = sim.stats().messages_sent.load(Relaxed) - sent0;
    let replied = stats.replies.load(Relaxed) - r0;
    assert!(spun > 0, "the session never spun");
    // The spin starts 40 us before the expected arrival and ends with it (or
    // 150 us after): far from the whole period.
    assert!(
        spun < window / 3,
        "spun {spun} ns of {window} ns: more than a third of the time"
    );
    assert!(replied + 2 >= sent, "{replied} replies to {sent} messages");
    assert_eq!(stats.missed_cycles.load(Relaxed), 0);

    // The controller falls silent (in a real cell: a network hiccup): the
    // spin for the expected message gives up, and the session notices the
    // silence, which it cannot while it spins (only a datagram or the give-up
    // time ends a spin); held 20 ms more, then the session answers again
    // when messages come back. On a loaded machine the give-up may come
    // just before the silence (the controller's last message was late, and
    // then none came): counted since the start, not since the silence.
    let silences = stats.silences.load(Relaxed);
    sim.set_silent(true);
    wait_for("the silence noticed", Duration::from_secs(30), || {
        stats.silences.load(Relaxed) > silences
    });
    assert!(stats.spins_gave_up.load(Relaxed) > 0, "no spin gave up");
    std::thread::sleep(Duration::from_millis(20));
    sim.set_silent(false);
    let r1 = stats.replies.load(Relaxed);
    wait_for("replies after the silence", Duration::from_secs(5), || {
        stats.replies.load(Relaxed) >= r1 + 100
    });
    drop(sim);
    drop(session);
    // The stages of receive -> send: every reply's send, every message's
    // step, each inside its reply's time.
    let replies = stats.replies.load(Relaxed);
    assert_eq!(stats.send_latency.count(), replies);
    assert!(
        stats.step_latency.count() >= replies,
        "{} steps",
        stats.step_latency.count()
    );
    let max = stats.reply_latency.max_ns();
    assert!(stats.send_latency.max_ns() <= max && stats.step_latency.max_ns() <= max);
    assert!(stats.send_latency.quantile_ns(0.5) > 0);
}

/// A control that checks, after each reply, that the reply has left: the
/// work a lab does in `after_reply` (its snapshot, its trial bookkeeping)
/// never delays the reply.
struct AfterTheReply {
    stats: Arc<OnceLock<Arc<SessionStats>>>,
    steps: Arc<AtomicU64>,
    after: Arc<AtomicU64>,
    early: Arc<AtomicU64>,
}

impl ControlStep for AfterTheReply {
    fn step(&mut self, _input: &StepInput<'_>, _command_rad: &mut Joints) {
        self.steps.fetch_add(1, Relaxed);
    }

    fn after_reply(&mut self) {
        let steps = self.steps.load(Relaxed);
        self.after.fetch_add(1, Relaxed);
        // Every step so far had its reply sent (`send_latency` is recorded
        // once `send_to` returned).
        if let Some(st) = self.stats.get()
            && st.send_latency.count() < steps
        {
            self.early.fetch_add(1, Relaxed);
        }
    }
}

#[test]
fn the_controls_after_reply_work_runs_once_each_datagram_after_its_reply_left() {
    let loopback = SocketAddr::from(([127, 0, 0, 1], 0));
    let stats = Arc::new(OnceLock::new());
    let (steps, after, early) = (
        Arc::new(AtomicU64::new(0)),
        Arc::new(AtomicU64::new(0)),
        Arc::new(AtomicU64::new(0)),
    );
    let session = FriSession::spawn(
        FriSessionParams {
            bind: loopback,
            client: FriClientParams::default(),
            ..FriSessionParams::default()
        },
        AfterTheReply {
            stats: Arc::clone(&stats),
            steps: Arc::clone(&steps),
            after: Arc::clone(&after),
            early: Arc::clone(&early),
        },
    )
    .unwrap();
    let _ = stats.set(Arc::clone(session.stats()));
    let sim = controller(session.local_addr(), true);
    wait_for("300 replies", Duration::from_secs(10), || {
        session.stats().replies.load(Relaxed) >= 300
    });
    drop(sim);
    drop(session);
    let (steps, after) = (steps.load(Relaxed), after.load(Relaxed));
    assert!(steps >= 300, "{steps} steps");
    // Once per datagram: the steps, plus the datagrams without a step.
    assert!(
        after >= steps,
        "{after} after-reply calls for {steps} steps"
    );
    assert_eq!(early.load(Relaxed), 0, "work ran before its reply was sent");
}
