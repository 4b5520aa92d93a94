//! The FRI session's spin (`RtTuning::spin`, taken by `serve` and `bench`), in
//! a process of its own (the measures are process-wide): the session polls
//! for each expected datagram without sleeping, answers every one, spends a
//! bounded share of its CPU doing so, and gives a spin up when the controller
//! is silent, answering again when it comes back.

use std::net::SocketAddr;
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant};

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
    let sim = SimServer::spawn(
        FriSimParams {
            fri_period_ms: 1,
            ..FriSimParams::default()
        },
        loopback,
        session.local_addr(),
        SimRunOptions {
            auto_command: true,
            duration: None,
            normal_priority: false,
        },
    )
    .unwrap();
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

    // The controller falls silent for 20 ms (in a real cell: a network
    // hiccup): the spin for the expected message gives up, and the session
    // answers again when messages come back.
    let gave_up = stats.spins_gave_up.load(Relaxed);
    sim.set_silent(true);
    wait_for("a spin given up", Duration::from_secs(5), || {
        stats.spins_gave_up.load(Relaxed) > gave_up
    });
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
