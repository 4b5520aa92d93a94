//! The iiwa 7 URDF (`rt-core/src/kinematics/iiwa7.urdf`) parsed by `urdf-rs`:
//! its forward kinematics, computed from the parsed joints alone, equals the DH
//! model (`kinematics::fk`) to 1e-9 m over random poses, at every joint, the
//! flange and the tool; and its limits are the ones the guard enforces.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rt_core::kinematics::{
    Joints, Pose, Tool, fk,
    iiwa7::{self, JOINTS},
};

/// Forward kinematics from the URDF: every link's pose in the base frame, in
/// chain order from the root (`base`) along the only child at each link.
fn urdf_chain(robot: &urdf_rs::Robot, q: &[f64; JOINTS]) -> Vec<(String, Isometry3<f64>)> {
    let mut out = vec![("base".to_string(), Isometry3::identity())];
    let mut link = "base".to_string();
    let mut t = Isometry3::identity();
    let mut revolute = 0;
    while let Some(j) = robot.joints.iter().find(|j| j.parent.link == link) {
        let o = &j.origin;
        let origin = Isometry3::from_parts(
            Translation3::new(o.xyz[0], o.xyz[1], o.xyz[2]),
            UnitQuaternion::from_euler_angles(o.rpy[0], o.rpy[1], o.rpy[2]),
        );
        t *= origin;
        if matches!(j.joint_type, urdf_rs::JointType::Revolute) {
            let axis = Vector3::new(j.axis.xyz[0], j.axis.xyz[1], j.axis.xyz[2]);
            let axis = nalgebra::Unit::new_normalize(axis);
            t *= UnitQuaternion::from_axis_angle(&axis, q[revolute]);
            revolute += 1;
        }
        link = j.child.link.clone();
        out.push((link.clone(), t));
    }
    out
}

fn random_q(rng: &mut ChaCha8Rng) -> Joints {
    Joints::from_fn(|i, _| {
        let l = iiwa7::POSITION_LIMIT_RAD[i];
        rng.random_range(-l..l)
    })
}

#[test]
fn urdf_forward_kinematics_equals_the_dh_model() {
    let robot = urdf_rs::read_from_string(iiwa7::URDF).expect("the URDF parses");
    let tool = Tool::along_z(0.10);
    let mut rng = ChaCha8Rng::seed_from_u64(22);
    let mut frames = [Pose::identity(); JOINTS + 1];
    let mut worst: f64 = 0.0;
    for _ in 0..2000 {
        let q = random_q(&mut rng);
        let qa: [f64; JOINTS] = std::array::from_fn(|i| q[i]);
        let chain = urdf_chain(&robot, &qa);
        let names: Vec<&str> = chain.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names, iiwa7::URDF_FRAMES, "the chain base -> tool");
        fk::frames(&q, &mut frames);
        // DH frame i sits at joint i+1's origin for the shoulder (1, 2), elbow (3, 4),
        // wrist (5, 6) and flange (7); URDF link i sits at joint i.
        for (dh, urdf) in [(1, 2), (2, 2), (3, 4), (4, 4), (5, 6), (6, 6), (7, 8)] {
            let e = (frames[dh].translation.vector - chain[urdf].1.translation.vector).norm();
            worst = worst.max(e);
            assert!(
                e < 1e-9,
                "DH frame {dh} vs URDF {}: {e} m at {q:?}",
                chain[urdf].0
            );
        }
        // The flange's whole pose (the DH flange frame equals the URDF flange frame).
        let flange = fk::flange_pose(&q);
        let rot = (flange.rotation.inverse() * chain[8].1.rotation).angle();
        assert!(
            rot < 1e-9,
            "flange orientation differs by {rot} rad at {q:?}"
        );
        let tip = fk::tool_pose(&q, &tool);
        let e = (tip.translation.vector - chain[9].1.translation.vector).norm();
        worst = worst.max(e);
        assert!(e < 1e-9, "tool point differs by {e} m at {q:?}");
    }
    eprintln!("largest URDF vs DH difference over 2000 poses: {worst:e} m");
}

#[test]
fn urdf_limits_are_the_guards() {
    let robot = urdf_rs::read_from_string(iiwa7::URDF).expect("the URDF parses");
    let revolute: Vec<_> = robot
        .joints
        .iter()
        .filter(|j| matches!(j.joint_type, urdf_rs::JointType::Revolute))
        .collect();
    assert_eq!(revolute.len(), JOINTS);
    for (i, j) in revolute.iter().enumerate() {
        assert_eq!(j.name, iiwa7::JOINT_NAMES[i]);
        assert!(
            (j.limit.upper - iiwa7::POSITION_LIMIT_RAD[i]).abs() < 1e-9,
            "{}",
            j.name
        );
        assert!(
            (j.limit.lower + iiwa7::POSITION_LIMIT_RAD[i]).abs() < 1e-9,
            "{}",
            j.name
        );
        assert!(
            (j.limit.velocity - iiwa7::VELOCITY_LIMIT_RADPS[i]).abs() < 1e-9,
            "{}",
            j.name
        );
        assert!(
            (j.limit.effort - iiwa7::TORQUE_LIMIT_NM[i]).abs() < 1e-9,
            "{}",
            j.name
        );
    }
    let masses: f64 = robot.links.iter().map(|l| l.inertial.mass.value).sum();
    assert!((masses - 23.9).abs() < 0.1, "total mass {masses} kg");
}

#[test]
fn the_tool_length_is_the_scenarios() {
    let robot = urdf_rs::read_from_string(&iiwa7::urdf_with_tool(0.25)).expect("parses");
    let q = Joints::from_fn(|i, _| 0.3 * (i as f64 + 1.0) - 1.0);
    let qa: [f64; JOINTS] = std::array::from_fn(|i| q[i]);
    let chain = urdf_chain(&robot, &qa);
    let tip = fk::tool_pose(&q, &Tool::along_z(0.25));
    let e = (tip.translation.vector - chain[9].1.translation.vector).norm();
    assert!(e < 1e-9, "tool point differs by {e} m");
}
