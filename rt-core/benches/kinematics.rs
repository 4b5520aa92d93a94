//! Criterion benches of the kinematics hot paths (numbers for the report and for
//! `isochron bench`): FK, Jacobian, one analytic IK solve, one warm-started numeric
//! IK step, and a posture plan.

use std::hint::black_box;
use std::time::Instant;

use criterion::{Criterion, criterion_group};
use rt_core::kinematics::{
    ArmFlags, ArmGeometry, Jacobian, Joints, NumericIk, Tool, arm_angle, flange_pose, jacobian,
    tool_pose,
};
use rt_core::params::TaskParams;
use rt_core::trajectory::{MotionRequest, TrajectoryParams, plan};

fn kinematics(c: &mut Criterion) {
    let q = Joints::from([0.3, 0.7, -0.4, -1.3, 0.5, 1.0, -0.2]);
    let tool = Tool::default();
    c.bench_function("fk_flange", |b| b.iter(|| flange_pose(black_box(&q))));
    let mut j = Jacobian::zeros();
    c.bench_function("jacobian_tool", |b| {
        b.iter(|| jacobian(black_box(&q), &tool, &mut j));
    });
    let pose = flange_pose(&q);
    let (psi, flags) = (arm_angle(&q), ArmFlags::of(&q));
    let mut out = Joints::zeros();
    c.bench_function("ik_analytic_solve", |b| {
        b.iter(|| {
            let geo = ArmGeometry::new(black_box(&pose))?;
            geo.solve_within(psi, flags, 0.0, &mut out)
        });
    });
    let ik = NumericIk::new(tool);
    let target = tool_pose(&q, &tool);
    // The previous cycle's answer, 1 mm-ish away (0.002 rad on every joint).
    let prev = q.add_scalar(0.002);
    c.bench_function("ik_numeric_warm_step", |b| {
        b.iter(|| {
            let mut qq = prev;
            ik.step(black_box(&target), &mut qq)
        });
    });
    c.bench_function("ik_numeric_warm_solve", |b| {
        b.iter(|| ik.solve(black_box(&target), &prev, &mut out));
    });
}

fn planning(c: &mut Criterion) {
    let req = MotionRequest::interception(&TaskParams::default(), 0.80);
    let params = TrajectoryParams::default();
    let mut g = c.benchmark_group("plan");
    g.sample_size(10);
    g.bench_function("posture_plan_d080", |b| {
        b.iter(|| plan(black_box(&req), &params));
    });
    g.finish();
    let Ok(p) = plan(&req, &params) else {
        return;
    };
    let mut out = Joints::zeros();
    let prev = p.home_q;
    c.bench_function("plan_joints_at_per_cycle", |b| {
        b.iter(|| p.joints_at(black_box(0.37), &prev, &mut out));
    });
}

/// Per-call latency distribution of one analytic IK solve (pose -> joints at a
/// given arm angle, with the limit check) over poses along the lab's path:
/// criterion reports means, the contract wants the tail.
fn ik_percentiles() {
    let req = MotionRequest::interception(&TaskParams::default(), 0.80);
    let Ok(p) = plan(&req, &TrajectoryParams::default()) else {
        return;
    };
    let n = 200_000;
    let mut ns = Vec::with_capacity(n);
    let mut q = p.home_q;
    for k in 0..n {
        let s = (k % 1500) as f64 / 1500.0;
        let prev = q;
        let t0 = Instant::now();
        let r = p.joints_at(black_box(s), &prev, &mut q);
        ns.push(t0.elapsed().as_nanos() as u64);
        black_box(r).ok();
    }
    ns.sort_unstable();
    let pct = |f: f64| ns[((n as f64 * f) as usize).min(n - 1)] as f64 / 1e3;
    println!(
        "ik_solve_us (per-cycle analytic, {n} calls): p50 {:.3} p99 {:.3} p999 {:.3} max {:.3}",
        pct(0.5),
        pct(0.99),
        pct(0.999),
        ns[n - 1] as f64 / 1e3
    );
}

criterion_group!(benches, kinematics, planning);

fn main() {
    benches();
    ik_percentiles();
    Criterion::default().configure_from_args().final_summary();
}
