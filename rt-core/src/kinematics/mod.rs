#![doc = include_str!("README.md")]

pub mod analytic;
pub mod dynamics;
pub mod fk;
pub mod iiwa7;
pub mod numeric;

#[cfg(test)]
mod tests;

use nalgebra::{IsometryMatrix3, SMatrix, SVector, Translation3, Vector3};
use serde::{Deserialize, Serialize};

use crate::check::{self, ParamError};

pub use analytic::{ArmFlags, ArmGeometry, IkError, arm_angle};
pub use fk::{flange_pose, frames, jacobian, tool_pose};
pub use numeric::{NumericIk, NumericReport};

/// A joint vector `[q1 .. q7]`, radians.
pub type Joints = SVector<f64, { iiwa7::JOINTS }>;

/// The geometric Jacobian: rows 0..3 linear, 3..6 angular velocity, base frame.
pub type Jacobian = SMatrix<f64, 6, { iiwa7::JOINTS }>;

/// A rigid transform (rotation matrix + translation, metres), e.g. `base_from_flange`.
pub type Pose = IsometryMatrix3<f64>;

/// The tool mounted on the flange: the tool point's frame in the flange frame.
///
/// Default: a short gripper, 0.10 m along the flange's z axis, axes parallel to the
/// flange's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tool {
    /// `flange_from_tool`: the tool frame expressed in the flange frame.
    pub flange_from_tool: Pose,
}

impl Default for Tool {
    fn default() -> Self {
        Self::along_z(0.10)
    }
}

impl Tool {
    /// A tool whose point lies `length_m` along the flange's z axis (no rotation).
    pub fn along_z(length_m: f64) -> Self {
        Self {
            flange_from_tool: Pose::from_parts(
                Translation3::new(0.0, 0.0, length_m),
                nalgebra::Rotation3::identity(),
            ),
        }
    }

    /// No tool: the tool point is the flange centre.
    pub fn none() -> Self {
        Self::along_z(0.0)
    }

    /// `base_from_flange` for a wanted `base_from_tool`.
    pub fn flange_for(&self, base_from_tool: &Pose) -> Pose {
        base_from_tool * self.flange_from_tool.inverse()
    }
}

/// Kinematics parameters: the tool.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct KinematicsParams {
    /// Tool point offset in the flange frame, metres (default `[0, 0, 0.10]`).
    pub tool_offset_m: [f64; 3],
}

impl Default for KinematicsParams {
    fn default() -> Self {
        Self {
            tool_offset_m: [0.0, 0.0, 0.10],
        }
    }
}

impl KinematicsParams {
    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] for the first tool offset
    /// component that is not finite or outside -0.5..=0.5 m.
    pub fn validate(&self) -> Result<(), ParamError> {
        for (i, v) in self.tool_offset_m.iter().enumerate() {
            check::within(&format!("kinematics.tool_offset_m[{i}]"), *v, -0.5, 0.5)?;
        }
        Ok(())
    }

    /// The tool these parameters describe.
    pub fn tool(&self) -> Tool {
        let [x, y, z] = self.tool_offset_m;
        Tool {
            flange_from_tool: Pose::from_parts(
                Translation3::from(Vector3::new(x, y, z)),
                nalgebra::Rotation3::identity(),
            ),
        }
    }
}

/// `true` when every joint is within its position limit shrunk by `margin_rad`.
///
/// ```
/// use rt_core::kinematics::{Joints, within_limits};
/// // Stretched upright: every joint at 0, inside every limit.
/// assert!(within_limits(&Joints::zeros(), 0.0));
/// // A4 (joint 4, limit +-120 degrees) at 125 degrees is outside.
/// let mut q = Joints::zeros();
/// q[3] = 125f64.to_radians();
/// assert!(!within_limits(&q, 0.0));
/// ```
pub fn within_limits(q: &Joints, margin_rad: f64) -> bool {
    first_limit_violation(q, margin_rad).is_none()
}

/// The first joint (index) outside its position limit shrunk by `margin_rad`.
pub fn first_limit_violation(q: &Joints, margin_rad: f64) -> Option<usize> {
    match analytic::check_limits(q, margin_rad) {
        Err(IkError::JointLimit { joint, .. }) => Some(joint),
        _ => None,
    }
}

/// The smallest distance of any joint to its position limit (negative when outside),
/// radians, and that joint.
pub fn min_position_margin(q: &Joints) -> (f64, usize) {
    let mut best = (f64::INFINITY, 0);
    for i in 0..iiwa7::JOINTS {
        let m = iiwa7::POSITION_LIMIT_RAD[i] - q[i].abs();
        if m < best.0 {
            best = (m, i);
        }
    }
    best
}

/// Why a pose given as numbers was refused.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum PoseError {
    /// NaN or an infinity.
    #[error("the position and rotation must be finite numbers")]
    NotFinite,
    /// The matrix is not a rotation (to 1e-6).
    #[error(
        "R is not a rotation matrix (|R^T R - I| = {orthogonality:.1e}, det = {determinant:.3})"
    )]
    NotRotation {
        /// Largest entry of `R^T R - I`.
        orthogonality: f64,
        /// The determinant.
        determinant: f64,
    },
}

/// A pose from a position (metres) and a rotation matrix given by rows, checked to
/// be a rotation within 1e-6 and then re-orthonormalised (parse at the boundary).
///
/// # Errors
///
/// [`PoseError::NotFinite`] for a NaN or infinite entry; [`PoseError::NotRotation`]
/// when the matrix is not orthonormal within 1e-6 or is a reflection.
pub fn pose_from_rows(p_m: [f64; 3], r_rows: [[f64; 3]; 3]) -> Result<Pose, PoseError> {
    if !p_m
        .iter()
        .chain(r_rows.iter().flatten())
        .all(|v| v.is_finite())
    {
        return Err(PoseError::NotFinite);
    }
    let m = nalgebra::Matrix3::from_fn(|i, j| r_rows[i][j]);
    let orthogonality = (m.transpose() * m - nalgebra::Matrix3::identity()).amax();
    let determinant = m.determinant();
    if orthogonality > 1e-6 || determinant < 0.0 {
        return Err(PoseError::NotRotation {
            orthogonality,
            determinant,
        });
    }
    let r = nalgebra::Rotation3::from_matrix_eps(&m, 1e-12, 100, nalgebra::Rotation3::identity());
    Ok(Pose::from_parts(Translation3::from(Vector3::from(p_m)), r))
}

/// A pose as a position (metres) and rotation rows.
pub fn pose_to_rows(pose: &Pose) -> ([f64; 3], [[f64; 3]; 3]) {
    let t = pose.translation.vector;
    let m = pose.rotation.matrix();
    (
        [t.x, t.y, t.z],
        std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)])),
    )
}
