use std::f64::consts::PI;

use nalgebra::{Matrix3, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::analytic::{self, ArmFlags, ArmGeometry, IkError};
use super::iiwa7::{JOINTS, POSITION_LIMIT_RAD};
use super::numeric::{self, NumericIk, pose_error};
use super::*;

fn random_q(rng: &mut ChaCha8Rng) -> Joints {
    Joints::from_fn(|i, _| rng.random_range(-1.0..1.0) * POSITION_LIMIT_RAD[i])
}

fn rot_err(a: &Pose, b: &Pose) -> f64 {
    numeric::rotation_error(&a.rotation, &b.rotation).norm()
}

#[test]
fn fk_matches_the_two_check_poses_of_iiwa7_md() {
    let p = flange_pose(&Joints::zeros());
    assert!((p.translation.vector - Vector3::new(0.0, 0.0, 1.266)).norm() < 1e-9);
    assert!((p.rotation.matrix() - Matrix3::identity()).norm() < 1e-9);
    let q = Joints::from([0.0, PI / 6.0, 0.0, -PI / 3.0, 0.0, PI / 2.0, 0.0]);
    let p = flange_pose(&q);
    assert!(
        (p.translation.vector - Vector3::new(0.6, 0.0, 0.560_410_162)).norm() < 1e-9,
        "{}",
        p.translation.vector
    );
    let r = Matrix3::new(-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0);
    assert!((p.rotation.matrix() - r).norm() < 1e-9);
    // Frame origins: shoulder 0.34, elbow 0.74, wrist 1.14 at q = 0.
    let mut f = [Pose::identity(); JOINTS + 1];
    frames(&Joints::zeros(), &mut f);
    for (i, z) in [(1, 0.34), (3, 0.74), (5, 1.14)] {
        assert!((f[i].translation.vector - Vector3::new(0.0, 0.0, z)).norm() < 1e-12);
    }
}

#[test]
fn jacobian_matches_finite_differences_of_fk() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let tool = Tool::default();
    for _ in 0..50 {
        let q = random_q(&mut rng);
        let mut j = Jacobian::zeros();
        let base = jacobian(&q, &tool, &mut j);
        assert!((base.translation.vector - tool_pose(&q, &tool).translation.vector).norm() < 1e-12);
        let h = 1e-5;
        for k in 0..JOINTS {
            let (mut qp, mut qm) = (q, q);
            qp[k] += h;
            qm[k] -= h;
            let (tp, tm) = (tool_pose(&qp, &tool), tool_pose(&qm, &tool));
            let dv = (tp.translation.vector - tm.translation.vector) / (2.0 * h);
            let dw = numeric::rotation_error(&tp.rotation, &tm.rotation) / (2.0 * h);
            assert!((dv - j.fixed_view::<3, 1>(0, k)).norm() < 1e-6, "joint {k}");
            assert!((dw - j.fixed_view::<3, 1>(3, k)).norm() < 1e-6, "joint {k}");
        }
    }
}

#[test]
fn analytic_ik_recovers_the_joint_vector_from_its_arm_angle_and_flags() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let mut worst: f64 = 0.0;
    for _ in 0..10_000 {
        let q = random_q(&mut rng);
        let pose = flange_pose(&q);
        let geo = ArmGeometry::new(&pose).unwrap();
        let mut out = Joints::zeros();
        geo.solve(arm_angle(&q), ArmFlags::of(&q), &mut out);
        // Near the shoulder/wrist singularities (q2 or q6 near 0) q1+q3 / q5+q7 are
        // what is defined; compare poses there and joints elsewhere.
        if q[1].abs() > 1e-3 && q[5].abs() > 1e-3 && q[3].abs() > 1e-3 {
            let d = (out - q).amax();
            worst = worst.max(d);
        }
        let back = flange_pose(&out);
        assert!((back.translation.vector - pose.translation.vector).norm() < 1e-9);
        assert!(rot_err(&back, &pose) < 1e-8);
    }
    assert!(worst < 1e-6, "largest joint difference {worst}");
}

#[test]
fn ik_round_trip_on_10000_random_joint_vectors() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let n = 10_000;
    let (mut solved, mut max_pos, mut max_rot) = (0, 0.0_f64, 0.0_f64);
    for _ in 0..n {
        let q = random_q(&mut rng);
        let pose = flange_pose(&q);
        if let Ok(sol) = analytic::solve(&pose, None, 0.0) {
            assert!(within_limits(&sol.q, 0.0), "{:?}", sol.q);
            let back = flange_pose(&sol.q);
            let pe = (back.translation.vector - pose.translation.vector).norm();
            let re = rot_err(&back, &pose);
            max_pos = max_pos.max(pe);
            max_rot = max_rot.max(re);
            if pe < 1e-4 && re < 1e-3 {
                solved += 1;
            }
        }
    }
    let rate = f64::from(solved) / f64::from(n);
    println!(
        "round trip: {solved}/{n} solved, max pos err {max_pos:.2e} m, max rot err {max_rot:.2e} rad"
    );
    assert!(rate >= 0.999, "solved {rate}");
    assert!(max_pos < 1e-4 && max_rot < 1e-3);
}

#[test]
fn seeded_ik_continues_the_seed_exactly() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    for _ in 0..1000 {
        let q = random_q(&mut rng);
        let pose = flange_pose(&q);
        let sol = analytic::solve(&pose, Some(&q), 0.0).unwrap();
        let back = flange_pose(&sol.q);
        assert!((back.translation.vector - pose.translation.vector).norm() < 1e-9);
        if q[1].abs() > 1e-3 && q[5].abs() > 1e-3 {
            assert!((sol.q - q).amax() < 1e-6);
        }
    }
}

#[test]
fn unreachable_poses_are_refused_with_the_reason() {
    let far = Pose::translation(1.5, 0.0, 0.3);
    assert!(matches!(
        ArmGeometry::new(&far),
        Err(IkError::OutOfReach { .. })
    ));
    assert!(matches!(
        analytic::solve(&far, None, 0.0),
        Err(IkError::OutOfReach { .. })
    ));
    let nan = Pose::translation(f64::NAN, 0.0, 0.3);
    assert!(matches!(ArmGeometry::new(&nan), Err(IkError::NotFinite)));
    // Wrist 0.2 m from the shoulder: reachable only with |q4| > 120 deg.
    let near = Pose::translation(0.2, 0.0, 0.34 + 0.126);
    match analytic::solve(&near, None, 0.0) {
        Err(IkError::NoFeasibleArmAngle { joint, .. }) => assert_eq!(joint, 3),
        other => panic!("{other:?}"),
    }
}

#[test]
fn feasible_arm_angle_intervals_are_exactly_the_feasible_ones() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let margin = 5f64.to_radians();
    for _ in 0..100 {
        let q = random_q(&mut rng);
        let geo = ArmGeometry::new(&flange_pose(&q)).unwrap();
        for flags in ArmFlags::ALL {
            let mut iv = [(0.0, 0.0); 16];
            let n = geo.feasible_arm_angles(flags, margin, &mut iv);
            let mut out = Joints::zeros();
            for &(lo, hi) in &iv[..n] {
                assert!(lo <= hi);
                for k in 0..=10 {
                    let psi = lo + (hi - lo) * f64::from(k) / 10.0;
                    geo.solve(psi, flags, &mut out);
                    assert!(within_limits(&out, margin - 1e-7), "{psi} in [{lo}, {hi}]");
                }
                // Just outside a boundary that is not +-pi, a joint is over its margin.
                if lo > -PI + 1e-6 {
                    geo.solve(lo - 1e-6, flags, &mut out);
                    assert!(!within_limits(&out, margin));
                }
                if hi < PI - 1e-6 {
                    geo.solve(hi + 1e-6, flags, &mut out);
                    assert!(!within_limits(&out, margin));
                }
            }
        }
    }
}

#[test]
fn numeric_ik_converges_from_a_nearby_seed_and_stays_within_limits() {
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let ik = NumericIk::default();
    let mut ok = 0;
    for _ in 0..500 {
        let q = random_q(&mut rng) * 0.9;
        let target = tool_pose(&q, &ik.tool);
        let seed = q + Joints::from_fn(|_, _| rng.random_range(-0.05..0.05));
        let mut out = Joints::zeros();
        if let Ok(r) = ik.solve(&target, &seed, &mut out) {
            assert!(within_limits(&out, 0.0));
            assert!(r.pos_err_m < 1e-6 && r.rot_err_rad < 1e-6);
            let e = pose_error(&target, &tool_pose(&out, &ik.tool));
            assert!(e.norm() < 1e-6);
            ok += 1;
        }
    }
    println!("numeric: {ok}/500 converged");
    assert!(ok >= 495, "{ok}/500 converged");
}

#[test]
fn numeric_ik_reports_an_unreachable_target() {
    let ik = NumericIk::default();
    let mut out = Joints::zeros();
    let target = Pose::translation(2.0, 0.0, 0.3);
    let seed = Joints::from([0.0, 0.5, 0.0, -1.4, 0.0, 1.2, 0.0]);
    assert!(matches!(
        ik.solve(&target, &seed, &mut out),
        Err(IkError::NotConverged { .. })
    ));
    assert!(within_limits(&out, 0.0));
}

#[test]
fn params_validate_names_the_field() {
    let mut p = KinematicsParams::default();
    p.validate().unwrap();
    p.tool_offset_m[2] = f64::NAN;
    let e = p.validate().unwrap_err();
    assert!(e.to_string().contains("kinematics.tool_offset_m[2]"), "{e}");
    assert!(
        (KinematicsParams::default()
            .tool()
            .flange_from_tool
            .translation
            .vector
            .z
            - 0.1)
            .abs()
            < 1e-15
    );
}
