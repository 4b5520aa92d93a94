//! The iiwa 7's rigid-body dynamics (recursive Newton-Euler) from the inertial
//! parameters in IIWA7.md (lbr_fri_ros2_stack's iiwa 7 description): the
//! planner's model of the arm: the torques a motion needs, against
//! [`TORQUE_LIMIT_NM`].
//!
//! Frames: each link's frame sits at its parent joint; at q = 0 every frame is
//! parallel to the base (URDF joint origins with no rotation), joint axes
//! z, y, z, -y, z, y, z (the same joint angles as the DH model of
//! `kinematics::iiwa7`). Gravity along -z. Torques in N m, positive about the
//! joint axis.

use nalgebra::{Matrix3, Rotation3, Unit, Vector3};

use super::iiwa7::JOINTS;
#[cfg(doc)]
use super::iiwa7::TORQUE_LIMIT_NM;

/// Joint origins relative to the previous link, m (A1..A7, then the flange).
pub const JOINT_ORIGIN_M: [[f64; 3]; JOINTS + 1] = [
    [0.0, 0.0, 0.1475],
    [0.0, -0.0105, 0.193],
    [0.0, 0.0105, 0.1745],
    [0.0, 0.0105, 0.2255],
    [0.0, -0.0105, 0.1745],
    [0.0, -0.0707, 0.2255],
    [0.0, 0.0705, 0.0909],
    [0.0, 0.0, 0.035],
];

/// Joint axes in their link frame: the URDF's (`iiwa7::URDF_AXES`).
pub const JOINT_AXIS: [[f64; 3]; JOINTS] = super::iiwa7::URDF_AXES;

/// Links 1..7: centre of mass in the link frame (m), mass (kg), inertia about
/// the centre of mass `[ixx, iyy, izz, iyz]` (kg m^2).
pub const LINKS: [([f64; 3], f64, [f64; 4]); JOINTS] = [
    (
        [0.0, -0.0347, 0.1235],
        3.401,
        [0.021502, 0.020512, 0.007587, 0.003828],
    ),
    (
        [0.0, 0.0449, 0.0673],
        3.430,
        [0.021455, 0.020444, 0.007671, 0.003570],
    ),
    (
        [0.0, 0.0296, 0.1365],
        3.995,
        [0.031559, 0.029960, 0.009574, -0.006133],
    ),
    (
        [0.0, -0.0449, 0.0673],
        3.430,
        [0.021454, 0.020443, 0.007670, -0.003570],
    ),
    (
        [0.0, -0.0214, 0.0855],
        2.132,
        [0.012684, 0.010952, 0.005624, 0.003889],
    ),
    (
        [0.0, 0.0710, 0.0021],
        2.312,
        [0.006412, 0.006166, 0.004459, 0.000314],
    ),
    (
        [0.0, 0.0, 0.0099],
        0.339,
        [0.000250, 0.000245, 0.000406, 0.0],
    ),
];

/// Standard gravity, m/s^2.
pub const GRAVITY_MPS2: f64 = 9.81;

/// The arm's inertial model (CAD values times a per-link factor).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArmDynamics {
    mass_kg: [f64; JOINTS],
    com_m: [Vector3<f64>; JOINTS],
    inertia: [Matrix3<f64>; JOINTS],
    /// Point mass at the flange (tool), kg.
    pub tool_mass_kg: f64,
}

impl Default for ArmDynamics {
    fn default() -> Self {
        Self::scaled(&[1.0; JOINTS])
    }
}

impl ArmDynamics {
    /// The CAD model with link `i`'s mass and inertia times `factor[i]`.
    pub fn scaled(factor: &[f64]) -> Self {
        let mut mass_kg = [0.0; JOINTS];
        let mut com_m = [Vector3::zeros(); JOINTS];
        let mut inertia = [Matrix3::zeros(); JOINTS];
        for (i, (c, m, ii)) in LINKS.iter().enumerate() {
            let f = factor.get(i).copied().unwrap_or(1.0);
            mass_kg[i] = m * f;
            com_m[i] = Vector3::from(*c);
            let [ixx, iyy, izz, iyz] = *ii;
            inertia[i] = Matrix3::new(ixx, 0.0, 0.0, 0.0, iyy, iyz, 0.0, iyz, izz) * f;
        }
        Self {
            mass_kg,
            com_m,
            inertia,
            tool_mass_kg: 0.0,
        }
    }

    /// Joint torques for positions `q`, velocities `qd` and accelerations
    /// `qdd` (inverse dynamics, recursive Newton-Euler, no allocation).
    pub fn torques(
        &self,
        q: &[f64; JOINTS],
        qd: &[f64; JOINTS],
        qdd: &[f64; JOINTS],
    ) -> [f64; JOINTS] {
        // Forward pass: frames, velocities and accelerations in the base frame.
        let mut rot = [Matrix3::identity(); JOINTS];
        let mut org = [Vector3::zeros(); JOINTS + 1];
        let mut z = [Vector3::zeros(); JOINTS];
        let mut w = [Vector3::zeros(); JOINTS];
        let mut wd = [Vector3::zeros(); JOINTS];
        let mut a_org = [Vector3::zeros(); JOINTS];
        let mut a_com = [Vector3::zeros(); JOINTS];
        let mut r_parent = Matrix3::identity();
        let mut p_parent = Vector3::zeros();
        let mut w_parent = Vector3::zeros();
        let mut wd_parent = Vector3::zeros();
        // Gravity as an upward acceleration of the base.
        let mut a_parent = Vector3::new(0.0, 0.0, GRAVITY_MPS2);
        for i in 0..JOINTS {
            let p = p_parent + r_parent * Vector3::from(JOINT_ORIGIN_M[i]);
            let axis_local = Vector3::from(JOINT_AXIS[i]);
            let zi = r_parent * axis_local;
            let rel = Rotation3::from_axis_angle(&Unit::new_unchecked(axis_local), q[i]);
            let ri = r_parent * rel.matrix();
            let d = p - p_parent;
            let a_o = a_parent + wd_parent.cross(&d) + w_parent.cross(&w_parent.cross(&d));
            let wi = w_parent + zi * qd[i];
            let wdi = wd_parent + zi * qdd[i] + w_parent.cross(&(zi * qd[i]));
            let rc = ri * self.com_m[i];
            a_com[i] = a_o + wdi.cross(&rc) + wi.cross(&wi.cross(&rc));
            rot[i] = ri;
            org[i] = p;
            z[i] = zi;
            w[i] = wi;
            wd[i] = wdi;
            a_org[i] = a_o;
            r_parent = ri;
            p_parent = p;
            w_parent = wi;
            wd_parent = wdi;
            a_parent = a_o;
        }
        // Flange (tool point mass).
        let flange = p_parent + r_parent * Vector3::from(JOINT_ORIGIN_M[JOINTS]);
        org[JOINTS] = flange;
        let d = flange - p_parent;
        let a_flange = a_parent + wd_parent.cross(&d) + w_parent.cross(&w_parent.cross(&d));
        // Backward pass: forces and moments about each joint's origin.
        let mut f_child = a_flange * self.tool_mass_kg;
        let mut n_child = Vector3::zeros();
        let mut tau = [0.0; JOINTS];
        for i in (0..JOINTS).rev() {
            let f_i = a_com[i] * self.mass_kg[i];
            let i_w = rot[i] * self.inertia[i] * rot[i].transpose();
            let n_i = i_w * wd[i] + w[i].cross(&(i_w * w[i]));
            let rc = rot[i] * self.com_m[i];
            let to_child = org[i + 1] - org[i];
            let f = f_i + f_child;
            let n = n_i + rc.cross(&f_i) + n_child + to_child.cross(&f_child);
            tau[i] = n.dot(&z[i]);
            f_child = f;
            n_child = n;
        }
        tau
    }

    /// The joint-space mass matrix at `q`: column `i` is the torque that
    /// accelerates joint `i` alone at 1 rad/s^2, gravity taken out.
    pub fn mass_matrix(&self, q: &[f64; JOINTS]) -> nalgebra::SMatrix<f64, JOINTS, JOINTS> {
        let zero = [0.0; JOINTS];
        let g = self.torques(q, &zero, &zero);
        let mut m = nalgebra::SMatrix::<f64, JOINTS, JOINTS>::zeros();
        for i in 0..JOINTS {
            let mut e = [0.0; JOINTS];
            e[i] = 1.0;
            let t = self.torques(q, &zero, &e);
            for r in 0..JOINTS {
                m[(r, i)] = t[r] - g[r];
            }
        }
        m
    }
}

/// The flange position of the dynamics model's frames (for a consistency check
/// against the DH kinematics), m.
pub fn flange_position_m(q: &[f64; JOINTS]) -> Vector3<f64> {
    let mut r = Matrix3::identity();
    let mut p = Vector3::zeros();
    for i in 0..JOINTS {
        p += r * Vector3::from(JOINT_ORIGIN_M[i]);
        let axis = Unit::new_unchecked(Vector3::from(JOINT_AXIS[i]));
        r *= Rotation3::from_axis_angle(&axis, q[i]).matrix();
    }
    p + r * Vector3::from(JOINT_ORIGIN_M[JOINTS])
}
