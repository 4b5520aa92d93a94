//! The simulated robot's dynamics beyond the planner's model
//! ([`crate::kinematics::dynamics`], re-exported here): the drives' reflected
//! rotor inertias against a push at the tool, and the torque-limit trip of
//! KUKA's controller.

pub use crate::kinematics::dynamics::{
    ArmDynamics, GRAVITY_MPS2, JOINT_AXIS, JOINT_ORIGIN_M, LINKS, flange_position_m,
};
use crate::kinematics::iiwa7::{JOINT_NAMES, JOINTS, TORQUE_LIMIT_NM};

/// Reflected rotor inertia of each drive at the joint (rotor inertia times
/// the gear ratio squared), kg m^2: an estimate (IIWA7.md has none; KUKA
/// does not publish them), of the order of a 100-160:1 harmonic drive on a
/// small servo motor. It dominates a wrist joint's inertia against a push
/// at the tool; the contact push uses it ([`Self::push_matrix`]).
pub const ARMATURE_KGM2: [f64; JOINTS] = [0.5, 0.5, 0.3, 0.3, 0.1, 0.1, 0.1];

impl ArmDynamics {
    /// The matrix a push at the tool meets: the mass matrix plus each
    /// drive's reflected rotor inertia ([`ARMATURE_KGM2`]) on its diagonal.
    pub fn push_matrix(&self, q: &[f64; JOINTS]) -> nalgebra::SMatrix<f64, JOINTS, JOINTS> {
        let mut m = self.mass_matrix(q);
        for (i, a) in ARMATURE_KGM2.iter().enumerate() {
            m[(i, i)] += a;
        }
        m
    }
}

/// A joint that needed more torque than its limit.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, thiserror::Error)]
#[error("torque limit: {name} needs {torque_nm:.1} N m, limit {limit_nm:.1} N m")]
pub struct TorqueTrip {
    /// Joint index 0..7.
    pub joint: usize,
    /// Joint name (`A1`..`A7`).
    pub name: &'static str,
    /// The torque needed, N m.
    pub torque_nm: f64,
    /// The limit, N m.
    pub limit_nm: f64,
}

/// Checks `tau` against the iiwa 7's torque limits times `scale`; the first
/// joint over its limit by the largest ratio trips.
///
/// # Errors
///
/// A [`TorqueTrip`] naming the joint most over its limit times `scale`.
pub fn check_torques(tau: &[f64; JOINTS], scale: f64) -> Result<(), TorqueTrip> {
    let mut worst: Option<(usize, f64)> = None;
    for (i, t) in tau.iter().enumerate() {
        let limit = TORQUE_LIMIT_NM[i] * scale;
        let ratio = t.abs() / limit;
        if ratio > 1.0 && worst.is_none_or(|(_, r)| ratio > r) {
            worst = Some((i, ratio));
        }
    }
    match worst {
        None => Ok(()),
        Some((j, _)) => Err(TorqueTrip {
            joint: j,
            name: JOINT_NAMES[j],
            torque_nm: tau[j],
            limit_nm: TORQUE_LIMIT_NM[j] * scale,
        }),
    }
}
