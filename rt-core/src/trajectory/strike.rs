//! Strike mode's stroke (issue #38): the tool meets the ball at the planned
//! moment with a chosen speed along a chosen direction, then brakes to rest,
//! timed by the same oscillator as the stop mode's motion.
//!
//! **The stroke is one cycle of the Hopf oscillator along a straight line**
//! through the intercept point `P`, from a start `S = P - D_a u` (where the
//! arm waits, armed) to a brake point `B = P + D_b u`. The path speed is the
//! stop mode's `v(t) = r (1 - cos(w t))`; contact comes at the phase `phi_a =
//! w T` of the cycle (`T`: the movement time), not at its end:
//!
//! ```text
//! speed at contact   v_s = r (1 - cos phi_a)
//! approach           D_a = (r / w) (phi_a - sin phi_a)          (in T = phi_a / w)
//! brake              D_b = (r / w) (2 pi - phi_a + sin phi_a)   (in (2 pi - phi_a) / w)
//! ```
//!
//! So the contact moment is fixed by the oscillator's phase whatever the
//! distance (isochrony), the speed at contact is set by the cycle's radius,
//! and the rest of the cycle brakes to rest with the same smooth profile (the
//! stop mode is `phi_a = 2 pi`: contact at the end of the cycle, at rest).
//! For the planner the whole stroke is an ordinary Hopf motion `S -> B` of
//! duration `2 pi / w`, checked by [`super::plan`] (posture, joint speeds,
//! accelerations, position margins); [`torque_check`] adds the joint torques
//! along it (recursive Newton-Euler, [`crate::kinematics::dynamics`], with
//! the tool's mass at the flange) against the iiwa 7's limits.
//!
//! `phi_a` trades approach against brake: contact at the peak speed (`pi`)
//! needs `D_a = D_b = v_s T / 2`; later contact shortens the brake and
//! lengthens the approach. [`largest_strike_speed`] searches both.
//!
//! Frames and units: robot base frame, metres, seconds; the strike
//! direction `u` lies in the swing plane (the plane `x = P_x`, the ball
//! swinging along `y`): `u = (0, s cos(theta), sin(theta))`, `s` the sign of
//! the ball's return (against its pass), `theta` the elevation
//! (`task.strike_direction_deg`).

use std::f64::consts::TAU;

use nalgebra::Vector3;

use super::path::MotionRequest;
use super::plan::{Infeasibility, MotionPlan, PlanError, TrajectoryParams, nearest_variant, plan};
use super::profile::ProfileKind;
use crate::kinematics::analytic::{ArmFlags, ArmGeometry, IkError, wrap_angle};
use crate::kinematics::dynamics::ArmDynamics;
use crate::kinematics::iiwa7::{JOINT_NAMES, JOINTS, TORQUE_LIMIT_NM};
use crate::kinematics::{Joints, Tool};

/// Contact phases the search tries, as fractions of the cycle: from the
/// peak speed (1/2) to near the end (a short brake).
pub const CONTACT_PHASES: [f64; 5] = [0.5, 0.6, 0.7, 0.8, 0.9];

/// The sign of `y` a struck ball returns along, as the controller strikes
/// (`control::Controller::plan`): it meets only passes towards `+y` and
/// returns them towards `-y` (the stroke's start `S`, where the arm waits
/// from arming on, must be known before the release; the ball may be
/// released on either side). `S` lies on the `+y` side of the intercept
/// point, in the swing's way unless the strike rises
/// (`task.strike_direction_deg > 0` puts `S` below the swing, and the ball
/// swings over the waiting tool: `scenarios/strike.toml` rises 20 degrees).
pub const STRIKE_RETURN_SIGN: f64 = -1.0;

/// The tool's mass the controller's torque check assumes, kg (a 10 cm
/// aluminium rod with a 6 cm disc and its mount; `isochron kin plan
/// --strike`'s default).
pub const STRIKE_TOOL_MASS_KG: f64 = 0.2;

/// Why a stroke cannot be built or checked.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum StrikeError {
    /// A number of the stroke is out of its range.
    #[error("strike: {what} = {value} ({bound})")]
    OutOfRange {
        /// Which number.
        what: &'static str,
        /// Its value.
        value: f64,
        /// What it must be.
        bound: &'static str,
    },
    /// The torque check's joint path left the arm's reach (a posture the
    /// planner found along its samples, not between them).
    #[error("strike: the torque check's joint path: {0}")]
    Ik(#[from] IkError),
    /// The planner refused the request.
    #[error(transparent)]
    Plan(#[from] PlanError),
}

/// Why a stroke may not run as asked.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum StrikeRefusal {
    /// Out of the arm's reach somewhere along the stroke.
    #[error(transparent)]
    Unreachable(PlanError),
    /// A joint's position margin, speed or acceleration.
    #[error(transparent)]
    Kinematics(Infeasibility),
    /// A joint's torque.
    #[error(
        "torque: {} needs {peak_nm:.1} N m, {:.0}% of its {:.0} N m limit (allowed {:.0}%)",
        JOINT_NAMES[*joint], ratio * 100.0, TORQUE_LIMIT_NM[*joint], allowed * 100.0
    )]
    Torque {
        /// The joint (0 = A1).
        joint: usize,
        /// Its largest |torque| along the stroke, N m.
        peak_nm: f64,
        /// That over its limit.
        ratio: f64,
        /// The share of the limit allowed.
        allowed: f64,
    },
    /// The stroke's start, where the arm waits armed, lies in the ball's
    /// swing: the ball would meet the waiting tool before the pass.
    #[error(
        "the stroke's start, where the arm waits, is {clearance_m:.3} m from the swing's arc \
         (needs {need_m:.3} m: ball radius, tool disc, margin): let the strike rise \
         (task.strike_direction_deg > 0) or shorten its approach"
    )]
    InTheSwing {
        /// The arc's height above the start (negative: below it), metres.
        clearance_m: f64,
        /// The clearance needed, metres.
        need_m: f64,
    },
}

/// The room the arm's waiting place needs beside the ball's swing, beyond
/// the ball's radius and the tool's disc, metres.
pub const STRIKE_SWING_CLEARANCE_M: f64 = 0.01;

/// Where the arm waits armed, the stroke's start `S`, must be out of the
/// ball's swing: the believed arc through the intercept point in the swing
/// plane (a pendulum of `length_m`), at least `need_m` away along z.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SwingClearance {
    /// The believed pendulum length, metres.
    pub length_m: f64,
    /// The clearance needed (ball radius, tool disc, [`STRIKE_SWING_CLEARANCE_M`]), metres.
    pub need_m: f64,
}

impl SwingClearance {
    /// The clearance a pendulum of `length_m` needs for a ball of
    /// `ball_radius_m` and a tool disc of `tool_radius_m`.
    pub fn new(length_m: f64, ball_radius_m: f64, tool_radius_m: f64) -> Self {
        Self {
            length_m,
            need_m: ball_radius_m + tool_radius_m + STRIKE_SWING_CLEARANCE_M,
        }
    }

    /// [`StrikeRefusal::InTheSwing`] when `stroke`'s start lies within the
    /// needed clearance of the arc, else `None`.
    pub fn check(&self, stroke: &Stroke) -> Option<StrikeRefusal> {
        let (p, s, l) = (stroke.contact_m, stroke.request.start_m, self.length_m);
        let dy = s.y - p.y;
        if dy.abs() >= l {
            return None;
        }
        let arc_z = p.z + l - (l * l - dy * dy).sqrt();
        let clearance_m = arc_z - s.z;
        (clearance_m.abs() < self.need_m).then_some(StrikeRefusal::InTheSwing {
            clearance_m,
            need_m: self.need_m,
        })
    }
}

/// One stroke: where it starts, meets the ball and ends, and when.
#[derive(Debug, Clone, PartialEq)]
pub struct Stroke {
    /// The whole cycle as a motion `S -> B` (Hopf profile, duration `2 pi / w`).
    pub request: MotionRequest,
    /// The intercept point `P`, metres.
    pub contact_m: Vector3<f64>,
    /// The strike direction `u` (unit).
    pub direction: Vector3<f64>,
    /// Tool speed at contact, m/s.
    pub speed_mps: f64,
    /// Contact time from the start, seconds (the movement time).
    pub contact_s: f64,
    /// Contact phase as a fraction of the cycle (`phi_a / 2 pi`).
    pub contact_fraction: f64,
    /// Approach length `|P - S|`, metres.
    pub approach_m: f64,
    /// Brake length `|B - P|`, metres.
    pub brake_m: f64,
}

impl Stroke {
    /// The stroke through `contact_m` along `direction` (normalised here)
    /// meeting the ball at `speed_mps` after `movement_time_s`, contact at
    /// `contact_fraction` of the cycle (in (0, 1)), with `tool`.
    ///
    /// # Errors
    ///
    /// [`StrikeError::OutOfRange`] for a speed or movement time that is not positive,
    /// a contact fraction outside (0, 1), a zero or non-finite direction, or a
    /// non-finite contact point.
    pub fn new(
        contact_m: Vector3<f64>,
        direction: Vector3<f64>,
        speed_mps: f64,
        movement_time_s: f64,
        contact_fraction: f64,
        tool: Tool,
    ) -> Result<Self, StrikeError> {
        let bad = |what, value, bound| StrikeError::OutOfRange { what, value, bound };
        if !(speed_mps.is_finite() && speed_mps > 0.0) {
            return Err(bad("speed_mps", speed_mps, "must be > 0"));
        }
        if !(movement_time_s.is_finite() && movement_time_s > 0.0) {
            return Err(bad("movement_time_s", movement_time_s, "must be > 0"));
        }
        if !(contact_fraction > 0.0 && contact_fraction < 1.0) {
            return Err(bad(
                "contact_fraction",
                contact_fraction,
                "must be in (0, 1)",
            ));
        }
        let norm = direction.norm();
        if !(norm.is_finite() && norm > 1e-9) {
            return Err(bad("direction's length", norm, "must be finite and > 0"));
        }
        if let Some(v) = contact_m.iter().find(|v| !v.is_finite()) {
            return Err(bad("contact_m", *v, "must be finite"));
        }
        let u = direction / norm;
        let phi = TAU * contact_fraction;
        let w = phi / movement_time_s;
        let r = speed_mps / (1.0 - phi.cos());
        let approach_m = r / w * (phi - phi.sin());
        let brake_m = r / w * (TAU - phi + phi.sin());
        Ok(Self {
            request: MotionRequest {
                start_m: contact_m - u * approach_m,
                end_m: contact_m + u * brake_m,
                movement_time_s: TAU / w,
                profile: ProfileKind::Hopf,
                tool,
            },
            contact_m,
            direction: u,
            speed_mps,
            contact_s: movement_time_s,
            contact_fraction,
            approach_m,
            brake_m,
        })
    }

    /// Path speed at time `t_s` from the start, m/s (zero outside the cycle).
    pub fn speed_at(&self, t_s: f64) -> f64 {
        let t = self.request.movement_time_s;
        let d = self.request.length_m();
        self.request.profile.velocity(t_s / t) * d / t
    }

    /// Distance along the stroke at time `t_s`, metres.
    pub fn position_at(&self, t_s: f64) -> f64 {
        let t = self.request.movement_time_s;
        self.request.profile.position(t_s / t) * self.request.length_m()
    }
}

/// The strike direction in the swing plane: `return_sign` (+1 or -1) is the
/// sign of `y` the ball leaves along, `elevation_deg` its angle above the
/// horizontal.
pub fn strike_direction(return_sign: f64, elevation_deg: f64) -> Vector3<f64> {
    let (s, c) = elevation_deg.to_radians().sin_cos();
    Vector3::new(0.0, return_sign.signum() * c, s)
}

/// The joint torques a planned motion needs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TorqueCheck {
    /// Each joint's largest |torque| along the motion, N m.
    pub peak_nm: [f64; JOINTS],
    /// `peak_nm` over the joint's limit.
    pub ratio: [f64; JOINTS],
    /// The joint with the largest ratio.
    pub worst_joint: usize,
}

impl TorqueCheck {
    /// The largest ratio.
    pub fn worst_ratio(&self) -> f64 {
        self.ratio[self.worst_joint]
    }
}

/// The torques of `planned` (the posture [`plan`] chose for `request`) along
/// the path every `dt_s`, by recursive Newton-Euler on `arm` (gravity
/// included): joint velocities and accelerations by central differences of
/// the tracked joint path.
///
/// # Errors
///
/// [`StrikeError::Ik`] when a point of the path leaves the arm's reach.
pub fn torque_check(
    request: &MotionRequest,
    planned: &MotionPlan,
    arm: &ArmDynamics,
    dt_s: f64,
) -> Result<TorqueCheck, StrikeError> {
    let t_end = request.movement_time_s;
    let n = ((t_end / dt_s).ceil() as usize).max(2);
    let h = t_end / n as f64;
    let base = ArmFlags::ALL[0];
    let mut path: Vec<Joints> = Vec::with_capacity(n + 1);
    let mut prev = planned.home_q;
    for k in 0..=n {
        let tau = k as f64 / n as f64;
        let p = request.point_at(request.profile.position(tau));
        let g = ArmGeometry::new(&request.flange_pose_for(&p, &planned.tool_rotation))?;
        let mut q = Joints::zeros();
        g.solve(planned.arm_angle_rad, base, &mut q);
        q = nearest_variant(&q, &prev);
        path.push(q);
        prev = q;
    }
    let mut peak_nm = [0.0; JOINTS];
    for k in 0..=n {
        let (a, b) = (k.saturating_sub(1), (k + 1).min(n));
        let q0 = path[k];
        let mut q = [0.0; JOINTS];
        let mut qd = [0.0; JOINTS];
        let mut qdd = [0.0; JOINTS];
        for i in 0..JOINTS {
            q[i] = q0[i];
            let fwd = wrap_angle(path[b][i] - q0[i]);
            let bwd = wrap_angle(q0[i] - path[a][i]);
            let span = (b - a) as f64 * h;
            qd[i] = (fwd + bwd) / span;
            // At the ends the motion is at rest (Hopf starts and ends at rest).
            qdd[i] = if a == k || b == k {
                0.0
            } else {
                (fwd - bwd) / (h * h)
            };
        }
        let tau = arm.torques(&q, &qd, &qdd);
        for i in 0..JOINTS {
            peak_nm[i] = f64::max(peak_nm[i], tau[i].abs());
        }
    }
    let mut ratio = [0.0; JOINTS];
    let mut worst_joint = 0;
    for i in 0..JOINTS {
        ratio[i] = peak_nm[i] / TORQUE_LIMIT_NM[i];
        if ratio[i] > ratio[worst_joint] {
            worst_joint = i;
        }
    }
    Ok(TorqueCheck {
        peak_nm,
        ratio,
        worst_joint,
    })
}

/// A stroke, its posture and torques, and whether it may run.
#[derive(Debug, Clone)]
pub struct StrikePlan {
    /// The stroke.
    pub stroke: Stroke,
    /// The planner's posture and kinematic check of the whole cycle (none
    /// when the stroke leaves the arm's reach).
    pub plan: Option<MotionPlan>,
    /// The torques along it (none when the posture is already refused).
    pub torque: Option<TorqueCheck>,
    /// Whether the stroke may run: kinematically feasible and every torque
    /// within `torque_fraction` of its limit.
    pub feasible: bool,
    /// Why not.
    pub reason: Option<StrikeRefusal>,
}

/// The share of each joint's torque limit a stroke may use (the rest is the
/// margin for the model's errors: CAD inertias, the tool, friction).
pub const TORQUE_FRACTION: f64 = 0.8;

/// Plans `stroke`: the posture and kinematic limits by [`plan`], then the
/// torques along it with `tool_mass_kg` at the flange.
///
/// # Errors
///
/// [`StrikeError::Plan`] when [`plan`] refuses the request (an unreachable stroke is
/// a refused plan, not an error); [`StrikeError::Ik`] as [`torque_check`].
pub fn plan_strike(
    stroke: Stroke,
    params: &TrajectoryParams,
    tool_mass_kg: f64,
) -> Result<StrikePlan, StrikeError> {
    let planned = match plan(&stroke.request, params) {
        Ok(p) => p,
        Err(e) if e.is_unreachable() => {
            return Ok(StrikePlan {
                stroke,
                plan: None,
                torque: None,
                feasible: false,
                reason: Some(StrikeRefusal::Unreachable(e)),
            });
        }
        Err(e) => return Err(e.into()),
    };
    if !planned.feasible {
        let reason = planned.reason.map(StrikeRefusal::Kinematics);
        return Ok(StrikePlan {
            stroke,
            plan: Some(planned),
            torque: None,
            feasible: false,
            reason,
        });
    }
    let mut arm = ArmDynamics::default();
    arm.tool_mass_kg = tool_mass_kg;
    let dt = (params.sample_period_ms * 1e-3).max(1e-3);
    let torque = torque_check(&stroke.request, &planned, &arm, dt)?;
    let ok = torque.worst_ratio() <= TORQUE_FRACTION;
    let j = torque.worst_joint;
    let reason = (!ok).then_some(StrikeRefusal::Torque {
        joint: j,
        peak_nm: torque.peak_nm[j],
        ratio: torque.ratio[j],
        allowed: TORQUE_FRACTION,
    });
    Ok(StrikePlan {
        stroke,
        plan: Some(planned),
        torque: Some(torque),
        feasible: ok,
        reason,
    })
}

/// The largest feasible strike speed through a point.
#[derive(Debug, Clone)]
pub struct StrikeLimit {
    /// The largest feasible tool speed at contact found, m/s (0: none).
    pub speed_mps: f64,
    /// The plan at that speed (its contact phase the best one found).
    pub best: Option<StrikePlan>,
    /// Why the next faster stroke was refused (what binds).
    pub binding: Option<StrikeRefusal>,
}

/// What [`largest_strike_speed`] searches over.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StrikeSearch {
    /// Contact this long after the stroke's start, seconds.
    pub movement_time_s: f64,
    /// The tool on the flange.
    pub tool: Tool,
    /// The tool's mass, at the flange, kg.
    pub tool_mass_kg: f64,
    /// The fastest stroke tried, m/s.
    pub max_speed_mps: f64,
    /// The search's resolution, m/s.
    pub resolution_mps: f64,
    /// The ball's swing the waiting arm must stay out of (`None`: not checked).
    pub swing: Option<SwingClearance>,
}

/// The largest tool speed at contact (to `search.resolution_mps`, at most
/// `search.max_speed_mps`) at which a stroke through `contact_m` along
/// `direction` is feasible, over the contact phases [`CONTACT_PHASES`];
/// bisection per phase (feasibility falls with speed: longer strokes, faster
/// joints, larger torques).
///
/// # Errors
///
/// The errors of [`Stroke::new`] and [`plan_strike`] for a tried speed and phase
/// (e.g. [`StrikeError::OutOfRange`] for a bad direction or contact point).
pub fn largest_strike_speed(
    contact_m: Vector3<f64>,
    direction: Vector3<f64>,
    search: &StrikeSearch,
    params: &TrajectoryParams,
) -> Result<StrikeLimit, StrikeError> {
    let StrikeSearch {
        movement_time_s,
        tool,
        tool_mass_kg,
        max_speed_mps,
        resolution_mps,
        swing,
    } = *search;
    let mut out = StrikeLimit {
        speed_mps: 0.0,
        best: None,
        binding: None,
    };
    // Feasible, or why not.
    let attempt =
        |v: f64, f: f64| -> Result<Result<StrikePlan, Option<StrikeRefusal>>, StrikeError> {
            let stroke = Stroke::new(contact_m, direction, v, movement_time_s, f, tool)?;
            let p = plan_strike(stroke, params, tool_mass_kg)?;
            if !p.feasible {
                return Ok(Err(p.reason));
            }
            Ok(match swing.and_then(|c| c.check(&p.stroke)) {
                Some(why) => Err(Some(why)),
                None => Ok(p),
            })
        };
    for f in CONTACT_PHASES {
        let (mut lo, mut hi) = (0.0, max_speed_mps);
        let mut best_here: Option<StrikePlan> = None;
        match attempt(hi, f)? {
            Ok(p) => {
                lo = hi;
                best_here = Some(p);
            }
            Err(mut why) => {
                if hi <= out.speed_mps {
                    continue;
                }
                while hi - lo > resolution_mps {
                    let mid = 0.5 * (lo + hi);
                    match attempt(mid, f)? {
                        Ok(p) => {
                            lo = mid;
                            best_here = Some(p);
                        }
                        Err(w) => {
                            hi = mid;
                            why = w;
                        }
                    }
                }
                if lo > out.speed_mps {
                    out.binding = why;
                }
            }
        }
        if lo > out.speed_mps {
            out.speed_mps = lo;
            out.best = best_here;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::trajectory::TaskParams;

    fn tool() -> Tool {
        Tool::along_z(0.1)
    }

    #[test]
    fn the_cycle_meets_the_ball_at_the_movement_time_with_the_chosen_speed() {
        let p = Vector3::new(0.6, 0.0, 0.3);
        for f in CONTACT_PHASES {
            let s = Stroke::new(p, strike_direction(-1.0, 10.0), 0.4, 1.5, f, tool()).unwrap();
            // At the contact time the tool is at P, moving at the chosen speed.
            let at = s.request.start_m
                + (s.request.end_m - s.request.start_m).normalize() * s.position_at(s.contact_s);
            assert!((at - p).norm() < 1e-9, "phase {f}: {at:?}");
            assert!((s.speed_at(s.contact_s) - 0.4).abs() < 1e-9, "phase {f}");
            // The cycle ends at rest at B.
            let t_end = s.request.movement_time_s;
            assert!(s.speed_at(t_end).abs() < 1e-9);
            assert!((s.position_at(t_end) - s.approach_m - s.brake_m).abs() < 1e-9);
            // The direction is the chosen one, in the swing plane.
            let u = (s.request.end_m - s.request.start_m).normalize();
            assert!((u - s.direction).norm() < 1e-12 && u.x.abs() < 1e-12);
        }
        // Contact at the peak: approach and brake both v T / 2.
        let s = Stroke::new(p, strike_direction(1.0, 0.0), 0.4, 1.5, 0.5, tool()).unwrap();
        assert!((s.approach_m - 0.3).abs() < 1e-12 && (s.brake_m - 0.3).abs() < 1e-12);
    }

    #[test]
    fn bad_strokes_are_refused() {
        let p = Vector3::new(0.6, 0.0, 0.3);
        let u = strike_direction(-1.0, 0.0);
        assert!(Stroke::new(p, u, 0.0, 1.5, 0.5, tool()).is_err());
        assert!(Stroke::new(p, u, f64::NAN, 1.5, 0.5, tool()).is_err());
        assert!(Stroke::new(p, u, 0.5, 0.0, 0.5, tool()).is_err());
        assert!(Stroke::new(p, u, 0.5, 1.5, 1.0, tool()).is_err());
        assert!(Stroke::new(p, Vector3::zeros(), 0.5, 1.5, 0.5, tool()).is_err());
    }

    #[test]
    fn gravity_alone_matches_the_static_torques_and_speed_adds_to_them() {
        // A stroke at rest (tiny speed) needs the gravity torques only; a
        // faster one needs more on some joint.
        let task = TaskParams::default();
        let p = task.intercept_m(0.6);
        let u = strike_direction(-1.0, 0.0);
        let params = TrajectoryParams::default();
        let slow = plan_strike(
            Stroke::new(p, u, 0.01, 1.5, 0.5, tool()).unwrap(),
            &params,
            0.0,
        )
        .unwrap();
        let t = slow.torque.unwrap();
        let arm = ArmDynamics::default();
        let zero = [0.0; JOINTS];
        let q: [f64; JOINTS] = slow.plan.as_ref().unwrap().home_q.into();
        let g = arm.torques(&q, &zero, &zero);
        for (i, (peak, gi)) in t.peak_nm.iter().zip(g).enumerate() {
            assert!(*peak >= gi.abs() - 1e-6, "joint {i}");
            assert!(*peak < gi.abs() + 2.0, "joint {i}: {peak} vs {gi}");
        }
        let fast = plan_strike(
            Stroke::new(p, u, 0.6, 0.6, 0.5, tool()).unwrap(),
            &params,
            0.0,
        )
        .unwrap();
        if let Some(tf) = fast.torque {
            assert!(
                (0..JOINTS).any(|i| tf.peak_nm[i] > t.peak_nm[i] + 0.5),
                "{tf:?} vs {t:?}"
            );
        }
    }

    #[test]
    fn the_largest_strike_speed_is_feasible_and_a_faster_one_is_not() {
        let task = TaskParams::default();
        let p = task.intercept_m(0.6);
        let u = strike_direction(-1.0, 0.0);
        let params = TrajectoryParams::default();
        let search = StrikeSearch {
            movement_time_s: 1.0,
            tool: tool(),
            tool_mass_kg: 0.2,
            max_speed_mps: 3.0,
            resolution_mps: 0.05,
            swing: None,
        };
        let limit = largest_strike_speed(p, u, &search, &params).unwrap();
        assert!(limit.speed_mps > 0.0, "{:?}", limit.binding);
        let best = limit.best.as_ref().unwrap();
        assert!(best.feasible);
        assert!(
            best.plan
                .as_ref()
                .unwrap()
                .speed_ratio
                .iter()
                .all(|r| *r <= params.velocity_fraction + 1e-9)
        );
        assert!(best.torque.unwrap().worst_ratio() <= TORQUE_FRACTION);
        // 0.1 m/s faster fails at every contact phase.
        for f in CONTACT_PHASES {
            let s = Stroke::new(p, u, limit.speed_mps + 0.1, 1.0, f, tool()).unwrap();
            assert!(!plan_strike(s, &params, 0.2).unwrap().feasible, "phase {f}");
        }
        assert!(limit.binding.is_some());
    }
}
