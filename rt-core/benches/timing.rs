//! Criterion benches of the timing module: one dynamics step and one full
//! trajectory sample (one FRI period of `TimedMotion::step`).

use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{UnitQuaternion, Vector3};
use rt_core::timing::{
    HopfDrive, MotionSample, Regime, SpeedDynamics, SpeedState, TimedMotion, TimingParams,
};
use std::hint::black_box;

fn dynamics_step(c: &mut Criterion) {
    let p = TimingParams::default();
    let dynamics = SpeedDynamics::new(&p);
    let drive = HopfDrive {
        radius_mps: 0.7 / 1.5,
        omega_rad_per_s: std::f64::consts::TAU / 1.5,
        remaining_m: 0.35,
        regime: Regime::Hopf,
    };
    let mut state = SpeedState::resting(p.neuron_floor);
    c.bench_function("timing/dynamics_rk4_step", |b| {
        b.iter(|| {
            dynamics.step(black_box(&mut state), black_box(0.001), black_box(&drive));
            if state.s > 0.7 {
                state = SpeedState::resting(p.neuron_floor);
            }
        });
    });
}

fn motion_sample(c: &mut Criterion) {
    for (name, dt) in [
        ("timing/motion_step_1ms", 0.001),
        ("timing/motion_step_5ms", 0.005),
        ("timing/motion_step_10ms", 0.010),
    ] {
        let Ok(mut motion) = TimedMotion::new(TimingParams::default()) else {
            return;
        };
        let start = Vector3::new(0.30, 0.0, 0.50);
        let target = Vector3::new(0.95, 0.0, 0.30);
        let q = UnitQuaternion::identity();
        let mut out = MotionSample::default();
        let begin = |m: &mut TimedMotion| {
            let _ = m.reset(&start);
            let _ = m.begin(&start, &target, &q, 1.5);
        };
        begin(&mut motion);
        c.bench_function(name, |b| {
            b.iter(|| {
                // Stay in the moving phase, where the re-plan runs.
                if out.t_s > 1.3 {
                    begin(&mut motion);
                }
                let _ = motion.step(black_box(dt), None, black_box(&mut out));
            });
        });
    }
}

criterion_group!(benches, dynamics_step, motion_sample);
criterion_main!(benches);
