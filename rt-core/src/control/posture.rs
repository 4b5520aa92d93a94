//! The posture of one interception motion, chosen before it starts: the tool's
//! tilt and the elbow's arm angle (both held for the whole motion) that minimise
//! the peak joint-speed ratio along the straight path, with every joint a margin
//! inside its position limits (IIWA7.md, "Workspace and speed").
//!
//! Tilt `theta` rotates the downward-pointing tool about the base y axis
//! (`theta > 0`: the tool tip leans back towards the base). Arm angle `psi` and
//! the configuration flags are those of `kinematics::analytic`.
//!
//! Not real-time code: it runs once when a trial is armed (a coarse grid, then
//! a fine one around the best cell; a few tens of milliseconds).

use nalgebra::{Rotation3, Translation3, Vector3};

use crate::kinematics::analytic::{ArmFlags, ArmGeometry};
use crate::kinematics::iiwa7::{JOINTS, POSITION_LIMIT_RAD, VELOCITY_LIMIT_RADPS};
use crate::kinematics::{Joints, Pose, Tool};
use crate::trajectory::profile::ProfileKind;

/// The chosen posture and what it costs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Posture {
    /// Tool tilt about the base y axis, radians.
    pub tilt_rad: f64,
    /// Arm angle, radians.
    pub arm_angle_rad: f64,
    /// Configuration flags (signs of q2, q4, q6).
    pub flags: ArmFlags,
    /// Tool orientation held during the motion (base from tool).
    pub orientation: Rotation3<f64>,
    /// Joint vector at the start of the path (home in this posture).
    pub q_home: Joints,
    /// Largest joint speed over its limit along the motion (at the asked duration).
    pub peak_speed_ratio: f64,
    /// The joint with that ratio (0-based).
    pub binding_joint: usize,
    /// Smallest distance of any joint to its position limit along the path, radians.
    pub min_margin_rad: f64,
}

impl Posture {
    /// Shortest duration at which the peak speed stays within `speed_ratio_max`
    /// of the limits (speeds scale with `1 / T`).
    pub fn shortest_duration_s(&self, duration_s: f64, speed_ratio_max: f64) -> f64 {
        duration_s * self.peak_speed_ratio / speed_ratio_max
    }
}

/// Why no posture was found.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum PostureError {
    /// No tilt and arm angle keeps the whole path inside the position limits.
    #[error("no posture keeps the path {margin_deg} deg inside the joint limits")]
    Unreachable {
        /// The margin asked for, degrees.
        margin_deg: f64,
    },
    /// The best posture still exceeds the speed limit ratio.
    #[error(
        "joint A{joint} would reach {ratio:.2} of its speed limit (at most {max:.2}); shortest feasible duration {shortest_s:.3} s"
    )]
    TooFast {
        /// 1-based joint number.
        joint: usize,
        /// Its peak speed ratio.
        ratio: f64,
        /// The allowed ratio.
        max: f64,
        /// Shortest feasible duration, seconds.
        shortest_s: f64,
    },
}

/// Tool orientation for tilt `theta`: pointing down, rotated about base y.
pub fn tool_orientation(tilt_rad: f64) -> Rotation3<f64> {
    Rotation3::from_axis_angle(&Vector3::y_axis(), tilt_rad)
        * Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI)
}

/// The flange pose that puts the tool point at `p` with orientation `r`.
pub fn flange_pose(tool: &Tool, p: &Vector3<f64>, r: &Rotation3<f64>) -> Pose {
    tool.flange_for(&Pose::from_parts(Translation3::from(*p), *r))
}

struct Eval {
    ratio: f64,
    joint: usize,
    margin: f64,
    q0: Joints,
}

#[allow(clippy::too_many_arguments)]
fn evaluate(
    tool: &Tool,
    start: &Vector3<f64>,
    end: &Vector3<f64>,
    r: &Rotation3<f64>,
    psi: f64,
    flags: ArmFlags,
    profile: ProfileKind,
    duration_s: f64,
    samples: usize,
    margin_rad: f64,
) -> Option<Eval> {
    let mut prev = Joints::zeros();
    let mut q = Joints::zeros();
    let mut ratio: f64 = 0.0;
    let mut joint = 0;
    let mut margin = f64::INFINITY;
    let mut q0 = Joints::zeros();
    let mut prev_tau = 0.0;
    for i in 0..=samples {
        let tau = i as f64 / samples as f64;
        let p = start + (end - start) * profile.position(tau);
        let geo = ArmGeometry::new(&flange_pose(tool, &p, r)).ok()?;
        geo.solve(psi, flags, &mut q);
        for j in 0..JOINTS {
            let m = POSITION_LIMIT_RAD[j] - q[j].abs();
            if m < margin_rad {
                return None;
            }
            margin = margin.min(m);
        }
        if i == 0 {
            q0 = q;
        } else {
            let dt = (tau - prev_tau) * duration_s;
            for j in 0..JOINTS {
                let dq = (q[j] - prev[j]).abs();
                if dq > 0.5 {
                    // A jump: a singularity on the way.
                    return None;
                }
                let rj = dq / dt / VELOCITY_LIMIT_RADPS[j];
                if rj > ratio {
                    ratio = rj;
                    joint = j;
                }
            }
        }
        prev = q;
        prev_tau = tau;
    }
    Some(Eval {
        ratio,
        joint,
        margin,
        q0,
    })
}

/// Chooses the posture for a straight-line motion of the tool point from
/// `start_m` to `end_m` in `duration_s` with `profile`, every joint at least
/// `margin_rad` inside its limits, peak speed at most `speed_ratio_max` of the limits.
pub fn plan_posture(
    tool: &Tool,
    start_m: &Vector3<f64>,
    end_m: &Vector3<f64>,
    profile: ProfileKind,
    duration_s: f64,
    margin_rad: f64,
    speed_ratio_max: f64,
) -> Result<Posture, PostureError> {
    let deg = std::f64::consts::PI / 180.0;
    let mut best: Option<(f64, f64, ArmFlags, Eval)> = None;
    let consider = |best: &mut Option<(f64, f64, ArmFlags, Eval)>,
                    tilt: f64,
                    psi: f64,
                    flags: ArmFlags,
                    samples: usize| {
        let r = tool_orientation(tilt);
        if let Some(e) = evaluate(
            tool, start_m, end_m, &r, psi, flags, profile, duration_s, samples, margin_rad,
        ) {
            if best.as_ref().is_none_or(|b| e.ratio < b.3.ratio) {
                *best = Some((tilt, psi, flags, e));
            }
        }
    };
    // Coarse: tilt -30..20 deg by 5, psi all round by 15, elbow-up configurations.
    for ti in -6..=4 {
        for pi in -12..12 {
            for flags in ArmFlags::ALL {
                consider(
                    &mut best,
                    f64::from(ti) * 5.0 * deg,
                    f64::from(pi) * 15.0 * deg,
                    flags,
                    24,
                );
            }
        }
    }
    let Some((t0, p0, f0, _)) = best.as_ref().map(|b| (b.0, b.1, b.2, ())) else {
        return Err(PostureError::Unreachable {
            margin_deg: margin_rad / deg,
        });
    };
    // Fine: +-5 deg of tilt by 1, +-15 deg of psi by 2.5, more samples.
    for ti in -5..=5 {
        for pi in -6..=6 {
            consider(
                &mut best,
                t0 + f64::from(ti) * deg,
                p0 + f64::from(pi) * 2.5 * deg,
                f0,
                60,
            );
        }
    }
    let Some((tilt, psi, flags, e)) = best else {
        return Err(PostureError::Unreachable {
            margin_deg: margin_rad / deg,
        });
    };
    let posture = Posture {
        tilt_rad: tilt,
        arm_angle_rad: psi,
        flags,
        orientation: tool_orientation(tilt),
        q_home: e.q0,
        peak_speed_ratio: e.ratio,
        binding_joint: e.joint,
        min_margin_rad: e.margin,
    };
    if e.ratio > speed_ratio_max {
        return Err(PostureError::TooFast {
            joint: e.joint + 1,
            ratio: e.ratio,
            max: speed_ratio_max,
            shortest_s: posture.shortest_duration_s(duration_s, speed_ratio_max),
        });
    }
    Ok(posture)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::tool_pose;

    #[test]
    fn the_papers_range_is_feasible_at_1_5_s() {
        let tool = Tool::along_z(0.10);
        let home = Vector3::new(0.30, 0.0, 0.50);
        for d in [0.35, 0.55, 0.80] {
            let end = Vector3::new(d, 0.0, 0.30);
            let p = plan_posture(
                &tool,
                &home,
                &end,
                ProfileKind::Hopf,
                1.5,
                5f64.to_radians(),
                0.9,
            )
            .unwrap();
            // The home joint vector puts the tool at home.
            let pose = tool_pose(&p.q_home, &tool);
            assert!((pose.translation.vector - home).norm() < 1e-6, "d={d}");
            assert!(p.peak_speed_ratio < 0.9, "d={d}: {p:?}");
            assert!(p.min_margin_rad >= 5f64.to_radians());
        }
    }
}
