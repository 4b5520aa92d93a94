//! The whole FRI cycle allocates nothing: every controller message's handling
//! (`FriClient::on_datagram`, which runs the trial driver `LabStep`: bridge
//! commands, magnet events, camera inbox, the control step, truth and judge
//! trace, judging, events and snapshot) runs under a counting global
//! allocator (`allocation-counter`, per thread), over whole trials of the
//! virtual-time lab: the same driver `isochron serve` runs on the wall clock.
//!
//! Allowed: the one message per trial on which the plan arrives and the
//! controller is armed (the trial's filter is built), once per operator
//! action and before the trial's motion.

use allocation_counter::measure;
use rt_core::control::TrialState;
use rt_core::params::{Scenario, VisionMode};
use rt_core::sim::VirtualLab;

#[derive(Debug, Default)]
struct Count {
    messages: u64,
    /// Allocations outside the arming messages.
    allocations: u64,
    /// (state before, state after, allocations) of the first allocating messages.
    where_: Vec<(TrialState, TrialState, u64)>,
    arming: u64,
    /// Messages seen per state before the message.
    per_state: [u64; 4],
}

fn count(s: &Scenario, seed: u64, trials: usize) -> Count {
    let mut lab = VirtualLab::new(s, seed).unwrap();
    let mut c = Count::default();
    let mut log = Vec::with_capacity(64);
    for i in 0..trials {
        let r = lab.run_trial_with(i, &mut |before, f| {
            let mut after = before;
            let info = measure(|| after = f());
            c.messages += 1;
            let arming = after == TrialState::Arming && before != TrialState::Arming;
            if arming {
                c.arming += 1;
            } else {
                c.allocations += info.count_total;
                if info.count_total > 0 && log.len() < log.capacity() {
                    log.push((before, after, info.count_total));
                }
            }
            match before {
                TrialState::Arming | TrialState::Armed => c.per_state[0] += 1,
                TrialState::Released | TrialState::Tracking => c.per_state[1] += 1,
                TrialState::Intercepting | TrialState::Holding => c.per_state[2] += 1,
                TrialState::Done => c.per_state[3] += 1,
                _ => {}
            }
        });
        assert!(r.success, "{r:?}");
    }
    c.where_ = log;
    c
}

#[test]
fn the_counter_sees_an_allocation() {
    // The property below must be able to fail: a step that allocated would count.
    let info = measure(|| {
        let v = std::hint::black_box(vec![1u8; 16]);
        drop(v);
    });
    assert_eq!(info.count_total, 1);
}

#[test]
fn the_whole_fri_cycle_never_allocates_in_a_trial() {
    let mut s = Scenario::default();
    s.camera.vision = VisionMode::Model;
    for (seed, period_ms, latency_ms) in [(7, 1, None), (3, 5, Some(25.0))] {
        s.robot.fri_period_ms = period_ms;
        if let Some(l) = latency_ms {
            s.robot.latency_ms = l;
        }
        let c = count(&s, seed, 2);
        // Every phase of a trial ran: arming, tracking, the motion, done.
        assert!(c.per_state.iter().all(|&n| n > 0), "{c:?}");
        assert_eq!(c.arming, 2, "{c:?}");
        assert_eq!(
            c.allocations, 0,
            "{} allocations over {} messages: {:?}",
            c.allocations, c.messages, c.where_
        );
    }
}

#[test]
fn the_reality_lab_trial_driver_never_allocates_either() {
    // The world's contact, the measured judge's recording and its verdict
    // at the trial's end run in the FRI cycle too.
    let mut s = Scenario::from_toml_str(include_str!("../../scenarios/reality.toml")).unwrap();
    s.camera.vision = VisionMode::Model;
    let c = count(&s, 1, 2);
    assert!(c.per_state.iter().all(|&n| n > 0), "{c:?}");
    assert_eq!(
        c.allocations, 0,
        "{} allocations over {} messages: {:?}",
        c.allocations, c.messages, c.where_
    );
}
