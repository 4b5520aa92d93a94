//! Forward kinematics and the geometric Jacobian (allocation-free).

use nalgebra::{Matrix3, Point3, Rotation3, Translation3, Vector3};

use super::iiwa7::{DH_ALPHA_RAD, DH_D_M, JOINTS};
use super::{Jacobian, Joints, Pose, Tool};

/// The local DH rotation `Rz(q) * Rx(alpha)`.
#[inline]
fn local_rotation(q: f64, alpha: f64) -> Matrix3<f64> {
    let (s, c) = q.sin_cos();
    let (sa, ca) = alpha.sin_cos();
    Matrix3::new(c, -s * ca, s * sa, s, c * ca, -c * sa, 0.0, sa, ca)
}

/// All link frames `base_from_frame_i`, i = 0 (base) .. 7 (flange), written into `out`.
///
/// Frame i's z axis is the axis of joint i+1; origins: 1 and 2 at the shoulder
/// (z = 0.34 m), 3 and 4 at the elbow, 5 and 6 at the wrist centre, 7 at the flange.
pub fn frames(q: &Joints, out: &mut [Pose; JOINTS + 1]) {
    let mut r = Matrix3::identity();
    let mut p = Vector3::zeros();
    out[0] = Pose::identity();
    for i in 0..JOINTS {
        p += r.column(2) * DH_D_M[i];
        r *= local_rotation(q[i], DH_ALPHA_RAD[i]);
        out[i + 1] = Pose::from_parts(Translation3::from(p), Rotation3::from_matrix_unchecked(r));
    }
}

/// `base_from_flange` for joint vector `q`.
///
/// ```
/// use rt_core::kinematics::{Joints, flange_pose};
/// // Stretched upright, the flange is 0.34 + 0.40 + 0.40 + 0.126 m above the base.
/// let p = flange_pose(&Joints::zeros()).translation.vector;
/// assert!(p.x.abs() < 1e-12 && p.y.abs() < 1e-12);
/// assert!((p.z - 1.266).abs() < 1e-9);
/// ```
pub fn flange_pose(q: &Joints) -> Pose {
    let mut r = Matrix3::identity();
    let mut p = Vector3::zeros();
    for i in 0..JOINTS {
        p += r.column(2) * DH_D_M[i];
        r *= local_rotation(q[i], DH_ALPHA_RAD[i]);
    }
    Pose::from_parts(Translation3::from(p), Rotation3::from_matrix_unchecked(r))
}

/// `base_from_tool` for joint vector `q` and `tool`.
pub fn tool_pose(q: &Joints, tool: &Tool) -> Pose {
    flange_pose(q) * tool.flange_from_tool
}

/// The geometric Jacobian of the tool point, written into `out`: rows 0..3 the
/// linear velocity (m/s per rad/s), rows 3..6 the angular velocity, both in the base
/// frame. Also returns `base_from_tool`.
pub fn jacobian(q: &Joints, tool: &Tool, out: &mut Jacobian) -> Pose {
    let mut f = [Pose::identity(); JOINTS + 1];
    frames(q, &mut f);
    let tip = f[JOINTS] * tool.flange_from_tool;
    let p_tip: Point3<f64> = tip.translation.vector.into();
    for (i, fi) in f.iter().take(JOINTS).enumerate() {
        let z = fi.rotation.matrix().column(2).into_owned();
        let o = fi.translation.vector;
        let v = z.cross(&(p_tip.coords - o));
        out.fixed_view_mut::<3, 1>(0, i).copy_from(&v);
        out.fixed_view_mut::<3, 1>(3, i).copy_from(&z);
    }
    tip
}
