//! The true lab geometry: the arm's true kinematics (DH link lengths and joint
//! zero offsets off the model's), the true tool length and the true intercept
//! point (the ball at rest).
//!
//! True forward kinematics: the DH chain of `kinematics::iiwa7` with
//! `d_i + dd_i` and `q_i + dq_i`; the tool point `tool_length` along the
//! flange's z axis. The contact disc sits at the tool point, its normal along
//! the tool axis.

use nalgebra::{Matrix3, Vector3};

use super::params::SessionDraw;
use super::pendulum::Disc;
use crate::kinematics::iiwa7::{DH_ALPHA_RAD, DH_D_M, JOINTS};

/// The arm and tool as they really are.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrueArm {
    /// DH link lengths d_i, m.
    pub d_m: [f64; JOINTS],
    /// Joint zero offsets (true angle = reported + offset), rad.
    pub offset_rad: [f64; JOINTS],
    /// Tool length along flange z, m.
    pub tool_length_m: f64,
    /// Contact disc radius, m.
    pub disc_radius_m: f64,
}

impl TrueArm {
    /// The arm of the model with a tool of `tool_length_m` (a truthful world).
    pub fn nominal(tool_length_m: f64, disc_radius_m: f64) -> Self {
        Self {
            d_m: DH_D_M,
            offset_rad: [0.0; JOINTS],
            tool_length_m,
            disc_radius_m,
        }
    }

    /// The session's arm: the believed tool length plus the drawn errors.
    pub fn from_session(believed_tool_m: f64, disc_radius_m: f64, s: &SessionDraw) -> Self {
        let mut d_m = DH_D_M;
        for (d, e) in d_m.iter_mut().zip(s.dh_length_error_m) {
            *d += e;
        }
        Self {
            d_m,
            offset_rad: s.joint_offset_error_rad,
            tool_length_m: believed_tool_m + s.tool_length_error_m,
            disc_radius_m,
        }
    }

    /// Flange position and rotation for joint readings `q`.
    pub fn flange(&self, q: &[f64; JOINTS]) -> (Vector3<f64>, Matrix3<f64>) {
        let mut r = Matrix3::identity();
        let mut p = Vector3::zeros();
        for i in 0..JOINTS {
            p += r.column(2) * self.d_m[i];
            let (s, c) = (q[i] + self.offset_rad[i]).sin_cos();
            let (sa, ca) = DH_ALPHA_RAD[i].sin_cos();
            r *= Matrix3::new(c, -s * ca, s * sa, s, c * ca, -c * sa, 0.0, sa, ca);
        }
        (p, r)
    }

    /// The arm's points for joint readings `q`: the base, each joint's
    /// origin along the chain, the flange and the tool point, m.
    pub fn points(&self, q: &[f64; JOINTS]) -> [Vector3<f64>; JOINTS + 2] {
        let mut out = [Vector3::zeros(); JOINTS + 2];
        let mut r = Matrix3::identity();
        let mut p = Vector3::zeros();
        for i in 0..JOINTS {
            p += r.column(2) * self.d_m[i];
            out[i + 1] = p;
            let (s, c) = (q[i] + self.offset_rad[i]).sin_cos();
            let (sa, ca) = DH_ALPHA_RAD[i].sin_cos();
            r *= Matrix3::new(c, -s * ca, s * sa, s, c * ca, -c * sa, 0.0, sa, ca);
        }
        out[JOINTS + 1] = p + r.column(2) * self.tool_length_m;
        out
    }

    /// The true tool point, m.
    pub fn tool_point(&self, q: &[f64; JOINTS]) -> Vector3<f64> {
        let (p, r) = self.flange(q);
        p + r.column(2) * self.tool_length_m
    }

    /// The true contact disc for joint positions `q`.
    pub fn disc(&self, q: &[f64; JOINTS]) -> Disc {
        let (p, r) = self.flange(q);
        let n = r.column(2).into_owned();
        Disc {
            centre_m: p + n * self.tool_length_m,
            normal: n,
            radius_m: self.disc_radius_m,
        }
    }
}

/// The true intercept point (ball at rest): the believed one plus the session's error.
pub fn true_intercept_m(believed_m: &Vector3<f64>, s: &SessionDraw) -> Vector3<f64> {
    believed_m + Vector3::from(s.intercept_error_m)
}
