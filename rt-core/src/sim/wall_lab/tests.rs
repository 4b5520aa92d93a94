use super::*;
use std::sync::atomic::Ordering;
use std::time::Instant;

#[test]
fn the_loop_answers_every_message_over_loopback() {
    let mut s = Scenario::default();
    s.robot.fri_period_ms = 5;
    let r = run_loop(&s, Duration::from_millis(400)).unwrap();
    assert!(r.cycles >= 70, "{r:?}");
    // A loaded test machine may answer a few late, but must answer.
    assert!(r.missed_cycles * 10 <= r.cycles, "{r:?}");
    assert!(r.reply_latency_us.p50 > 0.0, "{r:?}");
    // The histograms hold the window only (not the session's start-up):
    // at most one sample per cycle (a loaded machine may miss some).
    for (what, h) in [
        ("reply", r.reply_latency_us),
        ("client", r.client_us),
        ("step", r.client_step_us),
        ("send", r.client_send_us),
    ] {
        assert!(
            2 * h.count >= r.cycles && h.count <= r.cycles + 3,
            "{what}: {} samples in {} cycles",
            h.count,
            r.cycles
        );
    }
    // The client's stages lie inside its receive -> send.
    assert!(
        r.client_step_us.p50 > 0.0 && r.client_send_us.p50 > 0.0,
        "{r:?}"
    );
    assert!(r.client_step_us.p50 < r.client_us.p50, "{r:?}");
    assert!(r.client_send_us.p50 < r.client_us.p50, "{r:?}");
}

#[test]
fn a_trial_runs_through_the_udp_session_camera_and_magnet_and_is_judged() {
    use crate::bridge::{Command, Event, FriSessionState, TrialState};
    let (control, mut end) = crate::bridge::bridge(crate::bridge::BridgeCapacity::default());
    let lab = LabRuntime::start(simulated(Scenario::default(), 5), control, None).unwrap();
    lab.wait_commanding(Duration::from_secs(10)).unwrap();
    // An emergency stop while idle does not spoil the next trial.
    end.stop.request_stop();
    std::thread::sleep(Duration::from_millis(50));
    let id = end
        .commands
        .send(Command::RunTrial {
            trial_id: 9,
            setup: crate::bridge::TrialSetup::default(),
        })
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(40);
    let (mut acked, mut states, mut result) = (false, Vec::new(), None);
    while result.is_none() {
        assert!(Instant::now() < deadline, "no result; states {states:?}");
        while let Some(a) = end.acks.pop() {
            assert_eq!((a.id, a.outcome), (id, Ok(())));
            acked = true;
        }
        while end.telemetry.pop().is_some() {}
        while let Some(e) = end.events.pop() {
            match e.event {
                // (After the result the driver resets to Idle: not this trial's.)
                Event::StateChanged { to, .. } if result.is_none() => states.push(to),
                Event::StateChanged { .. } => {}
                Event::TrialFinished { result: r } => result = Some(r),
                Event::Aborted { reason, detail } if e.trial_id != 0 => panic!(
                    "aborted: {reason:?} ({detail}) after {states:?}: {:?}",
                    sim_server(&lab).unwrap().stats().report()
                ),
                Event::Aborted { .. } => {}
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let r = result.unwrap();
    let snap = *end.latest.read();
    let vision = lab.vision_stats().unwrap();
    let found = vision.found.load(Ordering::Relaxed);
    println!(
        "{r:?}; {states:?}; camera found the ball in {found} frames; {:?}",
        snap.fri
    );
    assert!(acked);
    assert_eq!(
        states,
        [
            TrialState::Aborted,
            TrialState::Arming,
            TrialState::Armed,
            TrialState::Released,
            TrialState::Tracking,
            TrialState::Intercepting,
            TrialState::Holding,
            TrialState::Done
        ]
    );
    assert!(r.success, "{r:?}");
    assert!(found > 20, "{found}");
    assert_eq!(snap.fri.session, FriSessionState::CommandingActive);
    assert!(snap.fri.reply_latency_us > 0.0, "{:?}", snap.fri);
    // The ball was released by the magnet: the fake board switched on, then off.
    assert!(fake_magnet(&lab).unwrap().pin_changes() >= 2);
    assert!(!fake_magnet(&lab).unwrap().magnet_on());
    let step = lab.stop().unwrap();
    assert_eq!(step.inner().controller().counters().limit_violations(), 0);

    // The same seed and world on the virtual clock (the same trial
    // driver, links in-process): the same draw and the same judged
    // timing error within one FRI period.
    let s = Scenario::default();
    let mut virt = crate::sim::VirtualLab::new(&s, 5).unwrap();
    assert_eq!(virt.vision_used(), "full");
    let v = virt.run_trial(0);
    let vj = v.judgement.unwrap();
    let period_ms = f64::from(s.robot.fri_period_ms);
    println!(
        "timing error: wall clock {:.3} ms, virtual clock {:.3} ms (FRI period {period_ms} ms)",
        r.timing_error_ms, vj.timing_error_ms
    );
    assert!(v.success, "{v:?}");
    assert_eq!(v.distance_m, r.distance_m);
    assert!(
        (vj.timing_error_ms - r.timing_error_ms).abs() <= period_ms,
        "wall {r:?}, virtual {v:?}"
    );
}
