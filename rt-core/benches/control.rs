//! Criterion benches of the closed loop: planning a trial's motion (posture and
//! the generator's arrival) and one whole virtual-time trial through the trial
//! driver (model camera). The per-step distribution over whole trials (p99.9,
//! max, wall clock against CPU time, per phase) is `isochron bench`'s
//! `control_step`.

use criterion::{Criterion, criterion_group, criterion_main};
use rt_core::control::Controller;
use rt_core::params::{Scenario, VisionMode};
use rt_core::sim::VirtualLab;

fn benches(c: &mut Criterion) {
    let s = Scenario::default().beliefs();
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

criterion_group!(control, benches);
criterion_main!(control);
