//! The KUKA LBR iiwa 7 R800: standard DH parameters and joint limits (IIWA7.md).
//!
//! `T_i = Rz(q_i) * Tz(d_i) * Tx(a_i) * Rx(alpha_i)`, all `a_i = 0`, no offsets.
//! Angles in radians, lengths in metres, speeds in rad/s.

use std::f64::consts::FRAC_PI_2;

/// Number of joints.
pub const JOINTS: usize = 7;

/// Joint names as KUKA writes them.
pub const JOINT_NAMES: [&str; JOINTS] = ["A1", "A2", "A3", "A4", "A5", "A6", "A7"];

/// DH offsets `d_i` along the previous z axis, metres.
pub const DH_D_M: [f64; JOINTS] = [0.340, 0.0, 0.400, 0.0, 0.400, 0.0, 0.126];

/// DH twists `alpha_i` about the new x axis, radians.
pub const DH_ALPHA_RAD: [f64; JOINTS] = [
    -FRAC_PI_2, FRAC_PI_2, FRAC_PI_2, -FRAC_PI_2, -FRAC_PI_2, FRAC_PI_2, 0.0,
];

const fn deg(d: f64) -> f64 {
    d * std::f64::consts::PI / 180.0
}

/// Symmetric position limits `|q_i| <= POSITION_LIMIT_RAD[i]`.
pub const POSITION_LIMIT_RAD: [f64; JOINTS] = [
    deg(170.0),
    deg(120.0),
    deg(170.0),
    deg(120.0),
    deg(170.0),
    deg(120.0),
    deg(175.0),
];

/// Maximum joint speeds, rad/s.
pub const VELOCITY_LIMIT_RADPS: [f64; JOINTS] = [
    deg(98.0),
    deg(98.0),
    deg(100.0),
    deg(130.0),
    deg(140.0),
    deg(180.0),
    deg(180.0),
];

/// Maximum joint torques, N m.
pub const TORQUE_LIMIT_NM: [f64; JOINTS] = [176.0, 176.0, 110.0, 110.0, 110.0, 40.0, 40.0];

/// Conservative default joint acceleration limits, rad/s^2.
///
/// KUKA does not publish acceleration limits for the iiwa 7. These defaults are five
/// times the velocity limit per second (a joint reaches full speed in no less than
/// 0.2 s), modest for an arm of this class. A motion of the paper's lab (0.35..0.80 m
/// in 1.5 s, sinusoidal profile, planned posture) needs at most about half of them
/// (the largest, A4 at d = 0.80 m, 47%; see `trajectory`'s README); at half these
/// values acceleration, not velocity, would bind the far end of the range.
pub const ACCELERATION_LIMIT_RADPS2: [f64; JOINTS] = [
    deg(490.0),
    deg(490.0),
    deg(500.0),
    deg(650.0),
    deg(700.0),
    deg(900.0),
    deg(900.0),
];

/// The arm's URDF (`iiwa7.urdf`, beside this file) with the default 0.10 m tool:
/// links `base`, `link_1` .. `link_7`, `flange`, `tool`; revolute joints named
/// [`JOINT_NAMES`]; at q = 0 it equals the DH model above (the test
/// `rt-core/tests/urdf.rs` checks every frame to 1e-9 m).
pub const URDF: &str = include_str!("iiwa7.urdf");

/// Frame names of the URDF's links from the base to the tool (`base`, `link_1`
/// .. `link_7`, `flange`, `tool`): the frames Foxglove's transforms use.
pub const URDF_FRAMES: [&str; JOINTS + 3] = [
    "base", "link_1", "link_2", "link_3", "link_4", "link_5", "link_6", "link_7", "flange", "tool",
];

/// Height of each URDF joint origin above its parent link's frame, metres
/// (A1 .. A7, then the flange); every origin is on the parent's z axis.
pub const URDF_JOINT_Z_M: [f64; JOINTS + 1] =
    [0.1475, 0.1925, 0.1745, 0.2255, 0.1745, 0.2255, 0.091, 0.035];

/// The URDF's joint axes in their link frames (z, y, z, -y, z, y, z).
pub const URDF_AXES: [[f64; 3]; JOINTS] = [
    [0.0, 0.0, 1.0],
    [0.0, 1.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.0, -1.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.0, 1.0, 0.0],
    [0.0, 0.0, 1.0],
];

/// The URDF with the tool `tool_length_m` along the flange's z axis (the
/// scenario's `task.tool_length_m`).
pub fn urdf_with_tool(tool_length_m: f64) -> String {
    let head = URDF
        .split("  <joint name=\"tool_joint\"")
        .next()
        .unwrap_or(URDF);
    let l = tool_length_m.max(0.0);
    format!(
        "{head}  <joint name=\"tool_joint\" type=\"fixed\">\n    <parent link=\"flange\"/>\n    \
         <child link=\"tool\"/>\n    <origin xyz=\"0 0 {l}\" rpy=\"0 0 0\"/>\n  </joint>\n  \
         <link name=\"tool\">\n    <visual>\n      <origin xyz=\"0 0 {h}\" rpy=\"0 0 0\"/>\n      \
         <geometry><cylinder radius=\"0.012\" length=\"{len}\"/></geometry>\n      \
         <material name=\"dark\"/>\n    </visual>\n  </link>\n</robot>\n",
        h = -l / 2.0,
        len = l.max(1e-3),
    )
}
