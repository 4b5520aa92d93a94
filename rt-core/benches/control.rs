//! Criterion benches of the closed loop: planning a trial's motion (posture and
//! the generator's arrival), one control step in each of its expensive phases
//! (tracking with a fresh measurement, the commit, intercepting; 1 ms FRI
//! period, `control::rig::Rig`), and one whole virtual-time trial (model
//! camera). The per-step distribution over whole trials (p99.9, max, wall
//! clock against CPU time) is `isochron bench`'s `control_step`.

use criterion::{BatchSize, Criterion, criterion_group, criterion_main};
use rt_core::control::{Controller, TrialState};
use rt_core::params::{Scenario, VisionMode};
use rt_core::sim::VirtualLab;
use rt_core::sim::rig::Rig;

/// A rig at 1 ms whose next step is in the phase `until` finds.
fn rig_in(until: impl Fn(&Rig) -> bool) -> Rig {
    let mut s = Scenario::default();
    s.robot.fri_period_ms = 1;
    let mut rig = Rig::new(&s, 0.7, 22.0, 1).unwrap_or_else(|e| panic!("rig: {e}"));
    assert!(rig.run_until(30.0, until), "phase not reached");
    rig
}

fn steps(c: &mut Criterion) {
    let mut g = c.benchmark_group("control_step");
    // Tracking, the step after a camera measurement arrived: the filter
    // update and the crossing search both run (the phase's worst case).
    let mut tracking = rig_in(|r| r.state() == TrialState::Tracking);
    tracking.run_until(1.0, |_| false);
    loop {
        tracking.prepare();
        if tracking.pending_measurements() > 0 {
            break;
        }
        tracking.step_controller();
        tracking.finish();
    }
    g.bench_function("tracking_new_measurement", |b| {
        b.iter_batched_ref(
            || tracking.clone(),
            Rig::step_controller,
            BatchSize::SmallInput,
        );
    });
    // Tracking between measurements: the last prediction is reused.
    let mut quiet = tracking.clone();
    quiet.step_controller();
    quiet.finish();
    quiet.prepare();
    g.bench_function("tracking_between_measurements", |b| {
        b.iter_batched_ref(
            || quiet.clone(),
            Rig::step_controller,
            BatchSize::SmallInput,
        );
    });
    // The step that commits: crossing search, the motion's begin, first sample.
    let mut commit = rig_in(|r| r.state() == TrialState::Tracking);
    assert!(commit.prepare_commit(10.0), "no commit");
    g.bench_function("commit", |b| {
        b.iter_batched_ref(
            || commit.clone(),
            Rig::step_controller,
            BatchSize::SmallInput,
        );
    });
    // Intercepting, half-way: Hopf substeps, IK in the planned posture, guard.
    let mut moving = rig_in(|r| r.state() == TrialState::Intercepting);
    moving.run_until(0.75, |_| false);
    moving.prepare();
    g.bench_function("intercepting", |b| {
        b.iter_batched_ref(
            || moving.clone(),
            Rig::step_controller,
            BatchSize::SmallInput,
        );
    });
    g.finish();
}

fn benches(c: &mut Criterion) {
    let s = Scenario::default();
    c.bench_function("control/plan_0.7m", |b| {
        b.iter(|| Controller::plan(std::hint::black_box(&s), 0.7));
    });
    let mut m = Scenario::default();
    m.camera.vision = VisionMode::Model;
    let mut lab = VirtualLab::new(&m, 1).unwrap_or_else(|e| panic!("lab: {e}"));
    let mut i = 0;
    let mut g = c.benchmark_group("control");
    g.sample_size(10);
    g.bench_function("virtual_trial_model_camera", |b| {
        b.iter(|| {
            i += 1;
            lab.run_trial(i)
        });
    });
    g.finish();
}

criterion_group!(control, steps, benches);
criterion_main!(control);
