//! The control step allocates nothing: whole trials of control steps run
//! under a counting global allocator (`allocation-counter`, per thread), and
//! every step after arming is measured on its own.

use allocation_counter::measure;
use rt_core::control::TrialState;
use rt_core::params::Scenario;
use rt_core::sim::rig::Rig;

/// Runs `trials` whole trials and returns (steps, allocations in steps,
/// worst allocations in one step, steps per state seen).
fn count(s: &Scenario, distance_m: f64, angle_deg: f64, trials: u64) -> (u64, u64, u64, [u64; 4]) {
    let mut rig = Rig::new(s, distance_m, angle_deg, 7).unwrap();
    let (mut steps, mut total, mut worst) = (0u64, 0u64, 0u64);
    let mut seen = [0u64; 4];
    let end = rig.t_s() + 60.0 * trials as f64;
    while rig.trials() < trials && rig.t_s() < end {
        rig.prepare();
        let before = rig.state();
        let info = measure(|| rig.step_controller());
        total += info.count_total;
        worst = worst.max(info.count_total);
        steps += 1;
        match (before, rig.state()) {
            (TrialState::Arming, _) => seen[0] += 1,
            (TrialState::Tracking, TrialState::Intercepting) => seen[2] += 1,
            (TrialState::Tracking, _) => seen[1] += 1,
            (TrialState::Intercepting | TrialState::Holding, _) => seen[3] += 1,
            _ => {}
        }
        rig.finish();
    }
    assert_eq!(rig.trials(), trials, "the trials did not finish");
    assert_eq!(rig.controller().counters().aborts, 0);
    (steps, total, worst, seen)
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
fn the_control_step_never_allocates_after_arming() {
    let mut s = Scenario::default();
    s.robot.fri_period_ms = 1;
    for (d, angle) in [(0.35, 15.0), (0.8, -25.0)] {
        let (steps, total, worst, seen) = count(&s, d, angle, 2);
        assert!(steps > 8_000, "{steps} steps");
        // Every phase of a trial ran: arming, tracking, the commit, the motion.
        assert!(seen.iter().all(|&n| n > 0), "{seen:?}");
        assert_eq!(seen[2], 2, "{seen:?}");
        assert_eq!(
            total, 0,
            "{total} allocations over {steps} steps (worst step {worst})"
        );
    }
    // The paper's 5 ms period with a 25 ms robot latency.
    let mut s = Scenario::default();
    s.robot.latency_ms = 25.0;
    let (steps, total, worst, _) = count(&s, 0.6, 20.0, 2);
    assert_eq!(
        total, 0,
        "{total} allocations over {steps} steps (worst step {worst})"
    );
}
