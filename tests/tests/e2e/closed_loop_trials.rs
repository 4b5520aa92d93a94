//! The closed loop in virtual time: a handful of trials of the paper's lab and
//! of other labs, judged on ground truth (the 300-trial numbers are measured with
//! the release binary, see README.md).

use std::path::Path;

use rt_core::control::{Summary, TrialRecord};
use rt_core::params::{Scenario, VisionMode};
use rt_core::sim::VirtualLab;

fn scenario(name: &str) -> Scenario {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scenarios")
        .join(name);
    Scenario::from_file(&path).unwrap()
}

fn run(s: &Scenario, seed: u64, n: usize) -> Vec<TrialRecord> {
    let mut lab = VirtualLab::new(s, seed).unwrap();
    (0..n).map(|i| lab.run_trial(i)).collect()
}

fn report(rs: &[TrialRecord]) -> String {
    rs.iter()
        .map(|r| serde_json::to_string(r).unwrap())
        .collect::<Vec<_>>()
        .join("\n")
}

#[test]
fn the_papers_lab_hits_across_its_range_without_limit_violations() {
    let mut s = scenario("paper.toml");
    s.camera.vision = VisionMode::Model;
    let rs = run(&s, 1, 8);
    let sum = Summary::of(&s.name, &rs, 0.0);
    assert!(sum.successes >= 7, "{}", report(&rs));
    assert_eq!(sum.limit_violations, 0, "{}", report(&rs));
    assert_eq!(sum.aborted, 0, "{}", report(&rs));
    assert!(sum.timing_error_ms.p95 < 10.0, "{}", report(&rs));
    // Isochrony: the same movement time whatever the distance.
    assert!(sum.movement_time_s.std < 0.002, "{}", report(&rs));
    assert!(
        sum.distance_m.max - sum.distance_m.min > 0.2,
        "{}",
        report(&rs)
    );
}

#[test]
fn the_same_seed_gives_the_same_trials() {
    let mut s = scenario("paper.toml");
    s.camera.vision = VisionMode::Model;
    let strip = |mut r: TrialRecord| {
        r.deadline_misses = 0; // wall-clock dependent
        r.preempted_steps = 0;
        r
    };
    let a: Vec<_> = run(&s, 42, 2).into_iter().map(strip).collect();
    let b: Vec<_> = run(&s, 42, 2).into_iter().map(strip).collect();
    assert_eq!(a, b);
    let c: Vec<_> = run(&s, 43, 2).into_iter().map(strip).collect();
    assert_ne!(a[0].distance_m, c[0].distance_m);
}

#[test]
fn an_unknown_robot_latency_is_estimated_and_compensated() {
    let mut s = scenario("robot_latency_25ms.toml");
    s.camera.vision = VisionMode::Model;
    let rs = run(&s, 3, 4);
    let hits = rs.iter().filter(|r| r.success).count();
    assert!(hits >= 4, "{}", report(&rs));
    // 25 ms of delay plus the servo's lag: the estimate must see it.
    assert!(
        rs.iter().all(|r| r.latency_estimate_ms > 22.0),
        "{}",
        report(&rs)
    );
}

#[test]
fn other_labs_work_without_retuning() {
    for name in [
        "pendulum_1_2m.toml",
        "pendulum_2_5m.toml",
        "camera_15fps.toml",
        "camera_60fps.toml",
        "movement_2s.toml",
        "fri_1ms.toml",
        "fri_10ms.toml",
        "worst_lab.toml",
    ] {
        let mut s = scenario(name);
        s.camera.vision = VisionMode::Model;
        let rs = run(&s, 5, 3);
        let hits = rs.iter().filter(|r| r.success).count();
        assert!(hits >= 3, "{name}:\n{}", report(&rs));
        assert!(
            rs.iter().all(|r| r.limit_violations == 0),
            "{name}:\n{}",
            report(&rs)
        );
    }
}

#[test]
fn an_unreachable_distance_is_refused_with_its_reason() {
    let mut s = scenario("paper.toml");
    s.camera.vision = VisionMode::Model;
    s.task.distance_m = rt_core::params::RangeParam::fixed(1.15);
    let rs = run(&s, 1, 1);
    assert!(!rs[0].success);
    let why = rs[0].failure.as_deref().unwrap();
    assert!(why.contains("infeasible"), "{why}");
    assert!(rs[0].judgement.is_none());
}

#[test]
fn a_trial_with_rendered_frames_and_the_detector_hits() {
    let s = scenario("paper.toml");
    assert_eq!(s.camera.vision, VisionMode::Full);
    let mut lab = VirtualLab::new(&s, 11).unwrap();
    assert_eq!(lab.vision_used(), "full");
    let rs: Vec<_> = (0..2).map(|i| lab.run_trial(i)).collect();
    assert!(rs.iter().all(|r| r.success), "{}", report(&rs));
}
