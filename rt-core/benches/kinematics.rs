//! Criterion benches of the kinematics hot paths (numbers for the report and for
//! `isochron bench`): FK, Jacobian, one analytic IK solve, one warm-started numeric
//! IK step, and a posture plan.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use rt_core::kinematics::{
    ArmFlags, ArmGeometry, Jacobian, Joints, NumericIk, Tool, arm_angle, flange_pose, jacobian,
    tool_pose,
};

fn kinematics(c: &mut Criterion) {
    let q = Joints::from([0.3, 0.7, -0.4, -1.3, 0.5, 1.0, -0.2]);
    let tool = Tool::default();
    c.bench_function("fk_flange", |b| b.iter(|| flange_pose(black_box(&q))));
    let mut j = Jacobian::zeros();
    c.bench_function("jacobian_tool", |b| {
        b.iter(|| jacobian(black_box(&q), &tool, &mut j))
    });
    let pose = flange_pose(&q);
    let (psi, flags) = (arm_angle(&q), ArmFlags::of(&q));
    let mut out = Joints::zeros();
    c.bench_function("ik_analytic_solve", |b| {
        b.iter(|| {
            let geo = ArmGeometry::new(black_box(&pose))?;
            geo.solve_within(psi, flags, 0.0, &mut out)
        })
    });
    let ik = NumericIk::new(tool);
    let target = tool_pose(&q, &tool);
    // The previous cycle's answer, 1 mm-ish away (0.002 rad on every joint).
    let prev = q.add_scalar(0.002);
    c.bench_function("ik_numeric_warm_step", |b| {
        b.iter(|| {
            let mut qq = prev;
            ik.step(black_box(&target), &mut qq)
        })
    });
    c.bench_function("ik_numeric_warm_solve", |b| {
        b.iter(|| ik.solve(black_box(&target), &prev, &mut out))
    });
}

criterion_group!(benches, kinematics);
criterion_main!(benches);
