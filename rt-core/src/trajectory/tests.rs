use std::time::Instant;

use nalgebra::Vector3;

use super::*;
use crate::check::ParamError;
use crate::kinematics::analytic::IkError;
use crate::kinematics::iiwa7::{JOINT_NAMES, JOINTS, VELOCITY_LIMIT_RADPS};
use crate::kinematics::numeric::rotation_error;
use crate::kinematics::{Joints, tool_pose, within_limits};

fn lab(d: f64) -> MotionRequest {
    MotionRequest::interception(&TaskParams::default(), d)
}

/// Re-checks a plan independently of the planner's own sampling: drives the
/// per-cycle IK along the path every millisecond, checks the tool pose by FK, the
/// position margin, and the joint speeds by finite differences in time.
fn replay(plan: &MotionPlan, margin_deg: f64) -> [f64; JOINTS] {
    let req = &plan.request;
    let t = req.movement_time_s;
    let n = (t * 1000.0).round() as usize;
    let mut prev = plan.home_q;
    let mut q = Joints::zeros();
    let mut peak = [0.0_f64; JOINTS];
    for k in 0..=n {
        let tau = k as f64 / n as f64;
        let s = req.profile.position(tau);
        plan.joints_at(s, &prev, &mut q).unwrap();
        assert!(
            within_limits(&q, margin_deg.to_radians() - 1e-6),
            "tau {tau}: {q:?}"
        );
        let pose = tool_pose(&q, &req.tool);
        assert!((pose.translation.vector - req.point_at(s)).norm() < 1e-9);
        assert!(rotation_error(&pose.rotation, &plan.tool_rotation).norm() < 1e-9);
        if k > 0 {
            for i in 0..JOINTS {
                let v = (q[i] - prev[i]).abs() / (t / n as f64);
                peak[i] = peak[i].max(v / VELOCITY_LIMIT_RADPS[i]);
            }
        }
        prev = q;
    }
    peak
}

#[test]
fn every_distance_of_the_papers_range_is_feasible_in_1_5_s() {
    let p = TrajectoryParams::default();
    let t0 = Instant::now();
    println!("   d    tilt_deg  psi_deg  worst  binding   margin_deg  shortest_s");
    let mut at_080 = None;
    for i in 0..=45 {
        let d = 0.35 + f64::from(i) * 0.01;
        let plan = plan(&lab(d), &p).unwrap();
        let worst = plan.worst_speed_ratio();
        println!(
            "{d:.2}  {:7.1}  {:7.1}  {:.3}  {} {:<12} {:5.2}  {:.3}",
            plan.tilt_rad.to_degrees(),
            plan.arm_angle_rad.to_degrees(),
            worst,
            JOINT_NAMES[plan.binding.joint],
            plan.binding.limit.name(),
            plan.min_margin_rad.to_degrees(),
            plan.shortest_feasible_s
        );
        assert!(plan.feasible, "d = {d}: {:?}", plan.reason);
        assert!(worst <= 0.9, "d = {d}: {worst}");
        assert!(plan.min_margin_rad >= 5f64.to_radians() - 1e-12, "d = {d}");
        assert!(plan.shortest_feasible_s <= 1.5);
        if i == 45 {
            at_080 = Some(plan);
        }
    }
    println!("46 plans in {:?}", t0.elapsed());
    let plan = at_080.unwrap();
    // IIWA7.md: at d = 0.80 the best achievable ratio is about 0.80, A4 binding.
    let worst = plan.worst_speed_ratio();
    assert!((worst - 0.80).abs() <= 0.02 * 0.80, "{worst}");
    assert_eq!(JOINT_NAMES[plan.binding.joint], "A4");
    assert_eq!(plan.binding.limit, LimitKind::Velocity);
}

#[test]
fn the_planned_motion_replays_exactly_within_its_claims() {
    let p = TrajectoryParams::default();
    for d in [0.35, 0.57, 0.80] {
        let plan = plan(&lab(d), &p).unwrap();
        let peak = replay(&plan, p.position_margin_deg);
        for (i, (pk, planned)) in peak.iter().zip(plan.speed_ratio).enumerate() {
            // Finite differences over 1 ms agree with the planner's derivative.
            assert!(
                (pk - planned).abs() < 2e-3,
                "d {d} joint {i}: replay {pk} plan {planned}"
            );
            assert!(*pk <= p.velocity_fraction + 1e-9);
        }
        // The arm goes home in the posture of the coming motion.
        let home = tool_pose(&plan.home_q, &plan.request.tool);
        assert!((home.translation.vector - Vector3::new(0.30, 0.0, 0.50)).norm() < 1e-9);
        assert!(rotation_error(&home.rotation, &plan.tool_rotation).norm() < 1e-9);
        let end = tool_pose(&plan.end_q, &plan.request.tool);
        assert!((end.translation.vector - Vector3::new(d, 0.0, 0.30)).norm() < 1e-9);
        let mut q = Joints::zeros();
        plan.joints_at(0.0, &plan.home_q, &mut q).unwrap();
        assert!((q - plan.home_q).amax() < 1e-12);
    }
}

#[test]
fn a_planar_elbow_is_refused_from_about_0_75_m_with_a2_binding() {
    let p = TrajectoryParams {
        elbow: ElbowPolicy::Planar,
        ..TrajectoryParams::default()
    };
    for (d, ok) in [(0.60, true), (0.70, true), (0.75, false), (0.80, false)] {
        let plan = plan(&lab(d), &p).unwrap();
        println!(
            "planar d {d}: worst {:.3} {} {}, psi {:.1} tilt {:.1}, {:?}",
            plan.worst_speed_ratio(),
            JOINT_NAMES[plan.binding.joint],
            plan.binding.limit.name(),
            plan.arm_angle_rad.to_degrees(),
            plan.tilt_rad.to_degrees(),
            plan.reason
        );
        assert!(
            plan.arm_angle_rad.abs() < 1e-12
                || (plan.arm_angle_rad.abs() - std::f64::consts::PI).abs() < 1e-12
        );
        assert_eq!(plan.feasible, ok, "d = {d}");
        if !ok {
            assert_eq!(JOINT_NAMES[plan.binding.joint], "A2");
            assert_eq!(plan.binding.limit, LimitKind::Velocity);
            let reason = plan.reason.unwrap();
            assert!(
                matches!(
                    reason,
                    Infeasibility::TooFast {
                        joint: 1,
                        limit: LimitKind::Velocity,
                        ..
                    }
                ),
                "{reason:?}"
            );
            let text = reason.to_string();
            assert!(text.contains("A2") && text.contains("velocity"), "{text}");
        }
    }
}

#[test]
fn too_short_a_duration_is_refused_with_the_shortest_feasible_one() {
    let p = TrajectoryParams::default();
    let mut req = lab(0.80);
    req.movement_time_s = 1.2;
    let plan = plan(&req, &p).unwrap();
    println!("{:?} shortest {}", plan.reason, plan.shortest_feasible_s);
    assert!(!plan.feasible);
    assert_eq!(JOINT_NAMES[plan.binding.joint], "A4");
    assert_eq!(plan.binding.limit, LimitKind::Velocity);
    assert!(
        (plan.shortest_feasible_s - 1.34).abs() < 0.02,
        "{}",
        plan.shortest_feasible_s
    );
    let reason = plan.reason.unwrap();
    let Infeasibility::TooFast {
        joint,
        ratio,
        allowed,
        duration_s,
        shortest_feasible_s,
        ..
    } = reason
    else {
        panic!("{reason:?}")
    };
    assert_eq!((joint, duration_s), (3, 1.2));
    assert!(ratio > allowed, "{ratio} {allowed}");
    assert_eq!(shortest_feasible_s, plan.shortest_feasible_s);
    assert!(reason.to_string().contains("shortest feasible duration"));
    // Taking the shortest feasible duration gives a feasible motion at 90%.
    req.movement_time_s = plan.shortest_feasible_s;
    let again = super::plan::evaluate(&req, &p, plan.tilt_rad, plan.arm_angle_rad).unwrap();
    assert!(again.feasible, "{:?}", again.reason);
    let w = again.worst_speed_ratio();
    assert!(w <= 0.9 && w > 0.899, "{w}");
}

#[test]
fn unreachable_and_invalid_motions_are_refused() {
    let p = TrajectoryParams::default();
    // Out of reach: the error keeps the IK's numbers (distance and reach),
    // and its sentence says them.
    let e = plan(&lab(1.1), &p).unwrap_err();
    let Some(IkError::OutOfReach { distance_m, max_m }) = e.ik().copied() else {
        panic!("{e:?}")
    };
    assert!(distance_m > max_m, "{distance_m} {max_m}");
    assert!(
        matches!(e, PlanError::Unreachable { max_tilt_deg, .. } if max_tilt_deg == p.max_tilt_deg)
    );
    assert!(e.to_string().contains(&format!("{max_m:.3} m")), "{e}");
    let mut req = lab(0.5);
    req.movement_time_s = f64::NAN;
    assert!(
        matches!(plan(&req, &p), Err(PlanError::MovementTime { movement_time_s }) if movement_time_s.is_nan())
    );
    let mut req = lab(0.5);
    req.end_m = req.start_m;
    assert!(matches!(plan(&req, &p), Err(PlanError::PointsCoincide)));
    let bad = TrajectoryParams {
        velocity_fraction: 1.5,
        ..TrajectoryParams::default()
    };
    let e = bad.validate().unwrap_err().to_string();
    assert!(e.contains("trajectory.velocity_fraction"), "{e}");
    assert!(
        matches!(plan(&lab(0.5), &bad), Err(PlanError::Params(ParamError::OutOfRange { field, .. })) if field == "trajectory.velocity_fraction")
    );
}

#[test]
fn the_per_cycle_ik_refuses_a_point_off_the_arm_and_leaves_the_output() {
    let plan = plan(&lab(0.6), &TrajectoryParams::default()).unwrap();
    let mut q = Joints::from_element(0.1);
    assert!(
        plan.joints_for_point(&Vector3::new(2.0, 0.0, 0.3), &plan.home_q, &mut q)
            .is_err()
    );
    assert_eq!(q, Joints::from_element(0.1));
    assert!(
        plan.joints_for_point(&Vector3::new(f64::NAN, 0.0, 0.3), &plan.home_q, &mut q)
            .is_err()
    );
    assert_eq!(q, Joints::from_element(0.1));
}
