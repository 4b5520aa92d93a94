//! Numeric inverse kinematics: damped least squares, warm-started.
//!
//! One step: `dq = J^T (J J^T + lambda^2 I)^-1 e`, with `lambda^2 = |e|^2 / 2 +
//! damping^2` (Sugihara's Levenberg-Marquardt weighting), `e` the tool pose error
//! (position in metres, rotation as the axis-angle vector of `R_target R^T`, both
//! in the base frame), the step clipped to `max_step_rad` per joint and the result
//! clamped into the position limits. Everything is fixed-size: no allocation.

use nalgebra::{Matrix6, Rotation3, Vector3, Vector6};

use super::analytic::IkError;
use super::iiwa7::{JOINTS, POSITION_LIMIT_RAD};
use super::{Jacobian, Joints, Pose, Tool, fk};

/// A damped-least-squares solver for one tool.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NumericIk {
    /// The tool whose frame is driven to the target.
    pub tool: Tool,
    /// Damping floor (metres-radians), keeps steps bounded near singularities.
    pub damping: f64,
    /// Largest change of any joint per step, radians.
    pub max_step_rad: f64,
    /// Iterations allowed per solve.
    pub max_iterations: usize,
    /// Position tolerance, metres.
    pub tolerance_m: f64,
    /// Rotation tolerance, radians.
    pub tolerance_rad: f64,
}

impl Default for NumericIk {
    fn default() -> Self {
        Self::new(Tool::default())
    }
}

/// What a numeric solve achieved.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NumericReport {
    /// Iterations used.
    pub iterations: usize,
    /// Final position error, metres.
    pub pos_err_m: f64,
    /// Final rotation error, radians.
    pub rot_err_rad: f64,
}

/// The rotation vector (axis times angle, base frame) taking `current` to `target`.
///
/// Accurate for small angles too (`atan2` of the skew part instead of `acos` of the
/// trace, which loses half the digits near zero).
pub fn rotation_error(target: &Rotation3<f64>, current: &Rotation3<f64>) -> Vector3<f64> {
    let m = target.matrix() * current.matrix().transpose();
    let v = Vector3::new(
        m[(2, 1)] - m[(1, 2)],
        m[(0, 2)] - m[(2, 0)],
        m[(1, 0)] - m[(0, 1)],
    ) * 0.5;
    let s = v.norm();
    let c = 0.5 * (m.trace() - 1.0);
    if c > -0.99 {
        if s < 1e-300 {
            return Vector3::zeros();
        }
        v * (s.atan2(c) / s)
    } else {
        // Near pi the skew part vanishes; nalgebra's log handles that case.
        Rotation3::from_matrix_unchecked(m).scaled_axis()
    }
}

/// Pose error `[dp; dtheta]` of `current` towards `target`, base frame.
pub fn pose_error(target: &Pose, current: &Pose) -> Vector6<f64> {
    let dp = target.translation.vector - current.translation.vector;
    let dr = rotation_error(&target.rotation, &current.rotation);
    Vector6::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z)
}

impl NumericIk {
    /// A solver with the defaults: damping floor 1e-4, 0.2 rad per step, 100 iterations,
    /// 1e-9 m and 1e-9 rad.
    pub fn new(tool: Tool) -> Self {
        Self {
            tool,
            damping: 1e-4,
            max_step_rad: 0.2,
            max_iterations: 100,
            tolerance_m: 1e-9,
            tolerance_rad: 1e-9,
        }
    }

    /// One damped-least-squares step from `q` (updated in place) towards the tool
    /// pose `target`; returns the position and rotation errors before the step.
    pub fn step(&self, target: &Pose, q: &mut Joints) -> (f64, f64) {
        let mut j = Jacobian::zeros();
        let current = fk::jacobian(q, &self.tool, &mut j);
        let e = pose_error(target, &current);
        let pos = e.fixed_rows::<3>(0).norm();
        let rot = e.fixed_rows::<3>(3).norm();
        // Levenberg-Marquardt damping after Sugihara (2011): proportional to the squared
        // error far from the target (robust), vanishing near it (fast final convergence),
        // with a floor `damping^2` that keeps the system definite at singularities.
        let lambda2 = 0.5 * e.norm_squared() + self.damping * self.damping;
        let jjt: Matrix6<f64> = j * j.transpose() + Matrix6::identity() * lambda2;
        let y = match jjt.cholesky() {
            Some(ch) => ch.solve(&e),
            None => return (pos, rot),
        };
        let mut dq: Joints = j.transpose() * y;
        let biggest = dq.amax();
        if biggest > self.max_step_rad {
            dq *= self.max_step_rad / biggest;
        }
        for i in 0..JOINTS {
            let lim = POSITION_LIMIT_RAD[i];
            q[i] = (q[i] + dq[i]).clamp(-lim, lim);
        }
        (pos, rot)
    }

    /// Iterates [`Self::step`] from `seed` until within tolerance; the answer (always
    /// within the position limits) is written into `out`.
    ///
    /// # Errors
    ///
    /// [`IkError::NotFinite`] for a target with NaN or infinite entries;
    /// [`IkError::NotConverged`] when the iterations end outside the tolerance.
    pub fn solve(
        &self,
        target: &Pose,
        seed: &Joints,
        out: &mut Joints,
    ) -> Result<NumericReport, IkError> {
        let t = target.translation.vector;
        if !(t.iter().all(|v| v.is_finite())
            && target.rotation.matrix().iter().all(|v| v.is_finite()))
        {
            return Err(IkError::NotFinite);
        }
        *out = *seed;
        for i in 0..JOINTS {
            let lim = POSITION_LIMIT_RAD[i];
            out[i] = out[i].clamp(-lim, lim);
        }
        for it in 0..self.max_iterations {
            let (pos, rot) = self.step(target, out);
            if pos <= self.tolerance_m && rot <= self.tolerance_rad {
                // `step` moved once more after measuring; re-measure honestly.
                let e = pose_error(target, &fk::tool_pose(out, &self.tool));
                return Ok(NumericReport {
                    iterations: it + 1,
                    pos_err_m: e.fixed_rows::<3>(0).norm(),
                    rot_err_rad: e.fixed_rows::<3>(3).norm(),
                });
            }
        }
        let e = pose_error(target, &fk::tool_pose(out, &self.tool));
        let (pos, rot) = (e.fixed_rows::<3>(0).norm(), e.fixed_rows::<3>(3).norm());
        if pos <= self.tolerance_m && rot <= self.tolerance_rad {
            Ok(NumericReport {
                iterations: self.max_iterations,
                pos_err_m: pos,
                rot_err_rad: rot,
            })
        } else {
            Err(IkError::NotConverged {
                pos_err_m: pos,
                rot_err_rad: rot,
            })
        }
    }
}
