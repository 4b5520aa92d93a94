//! EKF hot paths: one filter step, one horizon prediction, one crossing-time solve,
//! one motion plan. Also prints p50/p99 of single filter steps timed one by one.

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group, criterion_main};
use rt_core::ekf::{Crossing, Ekf, EkfParams, MotionRequest, PassDirection, Prediction};
use rt_core::pendulum::{PendulumGeometry, PendulumModel, PendulumSim};

const L: f64 = 1.93;

fn setup() -> (Ekf, Vec<(f64, f64)>) {
    let model = PendulumModel {
        length_m: L,
        gravity_mps2: 9.81,
        damping_per_s: 0.03,
    };
    let geom = PendulumGeometry::new(L, 0.6, 0.3).unwrap();
    let mut sim = PendulumSim::held_at(model, geom, 30f64.to_radians(), 0.0).unwrap();
    sim.release(0.0).unwrap();
    // 4096 frames at 30 Hz with a deterministic +-1.5 mm pseudo-noise.
    let mut meas = Vec::with_capacity(4096);
    for i in 0..4096 {
        let t = f64::from(i) / 30.0;
        sim.advance_to(t).unwrap();
        let noise = 0.0015 * (f64::from(i * 7919 % 1000) / 500.0 - 1.0);
        meas.push((t, sim.lateral_m() + noise));
    }
    (Ekf::new(EkfParams::default(), model, geom).unwrap(), meas)
}

/// A filter that has seen the first `n` measurements.
fn warmed(n: usize) -> (Ekf, Vec<(f64, f64)>) {
    let (mut ekf, meas) = setup();
    for &(t, z) in &meas[..n] {
        ekf.measure(t, z).unwrap();
    }
    (ekf, meas)
}

fn print_step_percentiles() {
    let (mut ekf, meas) = setup();
    let mut ns = Vec::with_capacity(40 * 4096);
    for _ in 0..40 {
        ekf.reset();
        ekf.measure(meas[0].0, meas[0].1).unwrap();
        ekf.measure(meas[1].0, meas[1].1).unwrap();
        for &(t, z) in &meas[2..] {
            let s = Instant::now();
            black_box(ekf.measure(black_box(t), black_box(z)).unwrap());
            ns.push(s.elapsed().as_nanos() as f64);
        }
    }
    let mut empty = Vec::with_capacity(100_000);
    for _ in 0..100_000 {
        let s = Instant::now();
        empty.push(black_box(s).elapsed().as_nanos() as f64);
    }
    ns.sort_by(f64::total_cmp);
    empty.sort_by(f64::total_cmp);
    let p = |v: &[f64], q: f64| v[((q * v.len() as f64) as usize).min(v.len() - 1)];
    println!(
        "ekf_step_ns (timed one by one, {} steps): p50 {:.0} p99 {:.0} max {:.0} \
         (clock overhead p50 {:.0})",
        ns.len(),
        p(&ns, 0.5),
        p(&ns, 0.99),
        p(&ns, 1.0),
        p(&empty, 0.5)
    );
}

fn benches(c: &mut Criterion) {
    print_step_percentiles();

    let (mut ekf, meas) = setup();
    c.bench_function("ekf_step (predict 33 ms + iterated update)", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            let mut done = 0u64;
            while done < iters {
                ekf.reset();
                ekf.measure(meas[0].0, meas[0].1).unwrap();
                ekf.measure(meas[1].0, meas[1].1).unwrap();
                let n = ((iters - done) as usize).min(meas.len() - 2);
                let start = Instant::now();
                for &(t, z) in &meas[2..2 + n] {
                    black_box(ekf.measure(black_box(t), black_box(z)).unwrap());
                }
                total += start.elapsed();
                done += n as u64;
            }
            total
        });
    });

    let (ekf, meas) = warmed(90);
    let now = meas[89].0 + 0.035;
    let mut horizon = [Prediction::default(); 300];
    c.bench_function("ekf_predict_horizon (300 x 20 ms)", |b| {
        b.iter(|| {
            black_box(
                ekf.predict_horizon(black_box(now), 0.02, &mut horizon)
                    .unwrap(),
            )
        });
    });
    let mut one = Prediction::default();
    c.bench_function("ekf_predict_at (1.5 s ahead)", |b| {
        b.iter(|| ekf.predict_at(black_box(now + 1.5), &mut one).unwrap());
    });
    let mut pass = [Crossing::default(); 1];
    c.bench_function("ekf_crossing (first bottom pass >= 1.5 s ahead)", |b| {
        b.iter(|| {
            ekf.crossings(black_box(now + 1.5), 0.0, PassDirection::Any, &mut pass)
                .unwrap()
        });
    });
    let req = MotionRequest {
        lateral_m: 0.0,
        duration_s: 1.5,
        latency_s: 0.008,
        pass_index: 0,
        direction: PassDirection::Any,
    };
    c.bench_function("ekf_plan_motion (1.5 s motion)", |b| {
        b.iter(|| ekf.plan_motion(black_box(now), &req).unwrap());
    });
}

criterion_group!(ekf_benches, benches);
criterion_main!(ekf_benches);
