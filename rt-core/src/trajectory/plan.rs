//! Posture planning and feasibility of a timed straight-line motion (before it starts).
//!
//! A posture is the tool's tilt (held orientation, [`tool_rotation`]) plus the arm
//! angle and configuration flags (held along the path). For a posture, the joint
//! path `q(s)` follows from the analytic IK; with the profile `s(tau)`,
//! `dq/dt = q'(s) s'(tau) / T` and `d2q/dt2 = (q''(s) s'^2 + q'(s) s'') / T^2`, so the
//! peak speeds scale with `1/T` and the accelerations with `1/T^2`, and the shortest
//! feasible duration follows from one evaluation. `q'` and `q''` are central
//! differences in `s` (step 1e-4 of the path).
//!
//! The planner minimises that shortest feasible duration (the peak joint speed
//! relative to its limit whenever velocity binds, as it does in the paper's lab)
//! subject to every joint staying `position_margin_deg` inside its limit along the
//! whole path: a coarse grid over tilt (5 deg) and arm angle (5 deg) on 16 samples,
//! a pattern search from the best cells on 40 samples, then the honest check on the
//! chosen posture sampled every `sample_period_ms`.

use std::f64::consts::PI;

use nalgebra::{Rotation3, Vector3};
use serde::{Deserialize, Serialize};

use super::path::{MotionRequest, tool_rotation};
use crate::check::{self, ParamError};
use crate::kinematics::analytic::{ArmFlags, ArmGeometry, IkError, check_limits, wrap_angle};
use crate::kinematics::iiwa7::{
    ACCELERATION_LIMIT_RADPS2, JOINT_NAMES, JOINTS, POSITION_LIMIT_RAD, VELOCITY_LIMIT_RADPS,
};
use crate::kinematics::{Joints, Pose};

/// How the arm's redundancy may be used.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ElbowPolicy {
    /// Any arm angle (the planner's choice).
    #[default]
    Free,
    /// The elbow kept in the vertical plane through the base axis (arm angle 0 or 180 deg).
    Planar,
}

/// Planning and feasibility parameters (`[trajectory]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrajectoryParams {
    /// Largest allowed peak joint speed as a fraction of each joint's limit.
    pub velocity_fraction: f64,
    /// Largest allowed peak joint acceleration as a fraction of each joint's
    /// (already conservative) default limit.
    pub acceleration_fraction: f64,
    /// Every joint stays at least this far inside its position limit, degrees.
    pub position_margin_deg: f64,
    /// Sampling period of the final feasibility check, milliseconds.
    pub sample_period_ms: f64,
    /// The tool's tilt is searched within +- this, degrees.
    pub max_tilt_deg: f64,
    /// How the arm's redundancy may be used.
    pub elbow: ElbowPolicy,
}

impl Default for TrajectoryParams {
    fn default() -> Self {
        Self {
            velocity_fraction: 0.9,
            acceleration_fraction: 1.0,
            position_margin_deg: 5.0,
            sample_period_ms: 1.0,
            max_tilt_deg: 40.0,
            elbow: ElbowPolicy::Free,
        }
    }
}

impl TrajectoryParams {
    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first field
    /// that is not finite or outside its range.
    pub fn validate(&self) -> Result<(), ParamError> {
        check::within(
            "trajectory.velocity_fraction",
            self.velocity_fraction,
            0.05,
            1.0,
        )?;
        check::within(
            "trajectory.acceleration_fraction",
            self.acceleration_fraction,
            0.05,
            1.0,
        )?;
        check::within(
            "trajectory.position_margin_deg",
            self.position_margin_deg,
            0.0,
            30.0,
        )?;
        check::within(
            "trajectory.sample_period_ms",
            self.sample_period_ms,
            0.1,
            20.0,
        )?;
        check::within("trajectory.max_tilt_deg", self.max_tilt_deg, 0.0, 80.0)
    }
}

/// Which kind of limit binds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LimitKind {
    /// Joint position (with the margin).
    Position,
    /// Joint speed (with the velocity fraction).
    Velocity,
    /// Joint acceleration (with the acceleration fraction).
    Acceleration,
}

impl LimitKind {
    /// `"position"`, `"velocity"` or `"acceleration"`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Position => "position",
            Self::Velocity => "velocity",
            Self::Acceleration => "acceleration",
        }
    }
}

/// The joint and the limit that bind a motion.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Binding {
    /// Joint index, 0 = A1.
    pub joint: usize,
    /// Which limit.
    pub limit: LimitKind,
}

/// Why a motion cannot be planned at all.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum PlanError {
    /// A start or end point has NaN or infinite coordinates.
    #[error("invalid motion: the start and end points must be finite")]
    NotFinitePoints,
    /// The movement time is not a positive number.
    #[error("invalid motion: movement_time_s = {movement_time_s} must be a positive number")]
    MovementTime {
        /// The refused movement time, seconds.
        movement_time_s: f64,
    },
    /// The start and end points coincide (no direction to move in).
    #[error("invalid motion: the start and end points coincide")]
    PointsCoincide,
    /// The planner's parameters were refused.
    #[error("invalid motion: {0}")]
    Params(#[from] ParamError),
    /// At every tilt the straight line leaves the arm's reach somewhere.
    #[error(
        "unreachable: at every tilt within +-{max_tilt_deg} deg the path leaves the arm's reach ({})",
        .ik.as_ref().map_or_else(|| "no tilt tried".to_owned(), ToString::to_string)
    )]
    Unreachable {
        /// The searched tilt range, degrees.
        max_tilt_deg: f64,
        /// The IK's reason at the last tilt tried (which joint, its value
        /// and limit, or how far out of reach); `None` when no tilt was tried.
        ik: Option<IkError>,
    },
}

impl PlanError {
    /// Whether the motion is out of the arm's reach (rather than an invalid request).
    pub const fn is_unreachable(&self) -> bool {
        matches!(self, Self::Unreachable { .. })
    }

    /// The inverse kinematics' reason, when the motion is out of reach.
    pub const fn ik(&self) -> Option<&IkError> {
        match self {
            Self::Unreachable { ik, .. } => ik.as_ref(),
            _ => None,
        }
    }
}

/// Why a planned posture may not run as asked (a [`MotionPlan`] that is not
/// feasible): the joint, the limit and the numbers.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum Infeasibility {
    /// Some joint comes closer to its position limit than the margin along the path.
    #[error(
        "no posture keeps every joint {margin_deg:.1} deg inside its limits along the path: {} comes within {:.2} deg",
        JOINT_NAMES[*joint], closest_rad.to_degrees()
    )]
    PositionMargin {
        /// The joint closest to its limit (0 = A1).
        joint: usize,
        /// Its smallest distance to the limit along the path, radians.
        closest_rad: f64,
        /// The margin every joint must keep, degrees.
        margin_deg: f64,
    },
    /// A joint would exceed its allowed share of a speed or acceleration limit.
    #[error(
        "{} would reach {:.0}% of its {} limit in {duration_s:.2} s (allowed {:.0}%); the shortest feasible duration is {shortest_feasible_s:.3} s",
        JOINT_NAMES[*joint], ratio * 100.0, limit.name(), allowed * 100.0
    )]
    TooFast {
        /// The binding joint (0 = A1).
        joint: usize,
        /// Which limit binds (velocity or acceleration).
        limit: LimitKind,
        /// Its peak as a fraction of the limit at the asked duration.
        ratio: f64,
        /// The fraction of the limit allowed.
        allowed: f64,
        /// The asked duration, seconds.
        duration_s: f64,
        /// The shortest duration this posture allows, seconds.
        shortest_feasible_s: f64,
    },
}

/// Per-joint peaks of one posture over the path, in normalised time (`tau = t/T`).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Eval {
    /// max |dq/dtau| per joint.
    speed: [f64; JOINTS],
    /// max |d2q/dtau2| per joint.
    accel: [f64; JOINTS],
    /// Per family (flips of the tracked path, see `family_flips`): smallest margin
    /// over the path and its joint.
    margin: [(f64, usize); 8],
    /// The tracked joint vector at the start and at the end of the path.
    home: Joints,
    end: Joints,
}

/// The IK geometries of one tilt at the samples of the path (and `s +- h`).
struct Samples {
    geo: Vec<[ArmGeometry; 3]>,
    sdot: Vec<f64>,
    sddot: Vec<f64>,
}

const H: f64 = 1e-4;

impl Samples {
    fn new(req: &MotionRequest, r: &Rotation3<f64>, n: usize) -> Result<Self, IkError> {
        let mut geo = Vec::with_capacity(n);
        let (mut sdot, mut sddot) = (Vec::with_capacity(n), Vec::with_capacity(n));
        let d = req.end_m - req.start_m;
        for k in 0..n {
            let tau = k as f64 / (n - 1) as f64;
            let s = req.profile.position(tau);
            let g = |s: f64| -> Result<ArmGeometry, IkError> {
                let p: Vector3<f64> = req.start_m + d * s;
                ArmGeometry::new(&req.flange_pose_for(&p, r))
            };
            geo.push([g(s - H)?, g(s)?, g(s + H)?]);
            sdot.push(req.profile.velocity(tau));
            sddot.push(req.profile.acceleration(tau));
        }
        Ok(Self { geo, sdot, sddot })
    }

    /// Evaluates arm angle `psi` along the path. The joint path is tracked by
    /// continuity: at each sample the configuration among the q2/q6 sign flips
    /// nearest to the previous sample's is taken, so a path through the shoulder or
    /// wrist singularity (q2 or q6 crossing zero, as a planar elbow does) is followed
    /// the way the arm moves, not by a jump of q1/q3 or q5/q7 by pi.
    fn eval(&self, psi: f64) -> Eval {
        let base = ArmFlags::ALL[0];
        let mut e = Eval {
            speed: [0.0; JOINTS],
            accel: [0.0; JOINTS],
            margin: [(f64::INFINITY, 0); 8],
            home: Joints::zeros(),
            end: Joints::zeros(),
        };
        let (mut qm, mut q0, mut qp) = (Joints::zeros(), Joints::zeros(), Joints::zeros());
        let mut prev: Option<Joints> = None;
        for (k, g) in self.geo.iter().enumerate() {
            g[1].solve(psi, base, &mut q0);
            if let Some(p) = prev {
                q0 = nearest_variant(&q0, &p);
            }
            g[0].solve(psi, base, &mut qm);
            g[2].solve(psi, base, &mut qp);
            qm = nearest_variant(&qm, &q0);
            qp = nearest_variant(&qp, &q0);
            prev = Some(q0);
            if k == 0 {
                e.home = q0;
            }
            e.end = q0;
            let (sd, sdd) = (self.sdot[k], self.sddot[k]);
            for i in 0..JOINTS {
                let fwd = wrap_angle(qp[i] - q0[i]);
                let bwd = wrap_angle(q0[i] - qm[i]);
                let d1 = (fwd + bwd) / (2.0 * H);
                let d2 = (fwd - bwd) / (H * H);
                e.speed[i] = e.speed[i].max((d1 * sd).abs());
                e.accel[i] = e.accel[i].max((d2 * sd * sd + d1 * sdd).abs());
            }
            // Margins of every family: flipping a flag adds pi to two of
            // q1/q3/q5/q7 and negates q2/q4/q6 (same margins).
            let mut m = [[0.0; 2]; JOINTS];
            for i in 0..JOINTS {
                let lim = POSITION_LIMIT_RAD[i];
                m[i] = [lim - q0[i].abs(), lim - (PI - q0[i].abs())];
            }
            for fi in 0..8 {
                let (f2, f4, f6) = family_flips(fi);
                let alt = [f2, false, f2 ^ f4, false, f4 ^ f6, false, f6];
                for i in 0..JOINTS {
                    let mi = m[i][usize::from(alt[i])];
                    if mi < e.margin[fi].0 {
                        e.margin[fi] = (mi, i);
                    }
                }
            }
        }
        e
    }
}

/// The flips (of q2, q4, q6's signs) that make family `fi` from the tracked one.
fn family_flips(fi: usize) -> (bool, bool, bool) {
    (fi & 1 != 0, fi & 2 != 0, fi & 4 != 0)
}

/// `q` with the q2 / q4 / q6 sign flips applied (the same arm, another configuration).
pub fn flip(q: &Joints, f2: bool, f4: bool, f6: bool) -> Joints {
    let mut r = *q;
    if f2 {
        r[0] = wrap_angle(r[0] + PI);
        r[1] = -r[1];
        r[2] = wrap_angle(r[2] + PI);
    }
    if f4 {
        r[2] = wrap_angle(r[2] + PI);
        r[3] = -r[3];
        r[4] = wrap_angle(r[4] + PI);
    }
    if f6 {
        r[4] = wrap_angle(r[4] + PI);
        r[5] = -r[5];
        r[6] = wrap_angle(r[6] + PI);
    }
    r
}

/// Largest wrapped joint difference.
fn joint_distance(a: &Joints, b: &Joints) -> f64 {
    (0..JOINTS).fold(0.0, |m, i| m.max(wrap_angle(a[i] - b[i]).abs()))
}

/// Among `q` and its q2 / q6 sign flips, the one nearest to `target`.
pub fn nearest_variant(q: &Joints, target: &Joints) -> Joints {
    let mut best = *q;
    let mut dist = joint_distance(q, target);
    for (f2, f6) in [(true, false), (false, true), (true, true)] {
        let v = flip(q, f2, false, f6);
        let d = joint_distance(&v, target);
        if d < dist {
            best = v;
            dist = d;
        }
    }
    best
}

impl Eval {
    /// The family with the largest margin: (index, margin, joint).
    fn best_flags(&self) -> (usize, f64, usize) {
        let mut best = (0, f64::NEG_INFINITY, 0);
        for (i, &(m, j)) in self.margin.iter().enumerate() {
            if m > best.1 {
                best = (i, m, j);
            }
        }
        best
    }

    /// Shortest feasible duration and what binds it.
    fn shortest(&self, p: &TrajectoryParams) -> (f64, Binding) {
        let mut best = (
            0.0,
            Binding {
                joint: 0,
                limit: LimitKind::Velocity,
            },
        );
        for i in 0..JOINTS {
            let tv = self.speed[i] / (p.velocity_fraction * VELOCITY_LIMIT_RADPS[i]);
            let ta =
                (self.accel[i] / (p.acceleration_fraction * ACCELERATION_LIMIT_RADPS2[i])).sqrt();
            if tv > best.0 {
                best = (
                    tv,
                    Binding {
                        joint: i,
                        limit: LimitKind::Velocity,
                    },
                );
            }
            if ta > best.0 {
                best = (
                    ta,
                    Binding {
                        joint: i,
                        limit: LimitKind::Acceleration,
                    },
                );
            }
        }
        best
    }

    /// The search objective: the shortest feasible duration, or a penalty above any
    /// duration when the position margin is not kept.
    fn score(&self, p: &TrajectoryParams) -> f64 {
        let (_, m, _) = self.best_flags();
        let need = p.position_margin_deg.to_radians();
        if m < need {
            1e3 + (need - m)
        } else {
            self.shortest(p).0
        }
    }
}

/// A planned motion: the posture, its feasibility, and the per-cycle IK.
#[derive(Debug, Clone, PartialEq)]
pub struct MotionPlan {
    /// What was asked.
    pub request: MotionRequest,
    /// The tool's tilt about the base y axis (positive: tip leans back), radians.
    pub tilt_rad: f64,
    /// The held tool orientation, `Ry(pi + tilt)`.
    pub tool_rotation: Rotation3<f64>,
    /// The held arm angle, radians.
    pub arm_angle_rad: f64,
    /// The configuration at home (q2 and q6 may change sign along the path when
    /// it passes through a shoulder or wrist singularity; q4's never does).
    pub flags: ArmFlags,
    /// Each joint's peak speed over the motion as a fraction of its velocity limit.
    pub speed_ratio: [f64; JOINTS],
    /// Each joint's peak acceleration as a fraction of its acceleration limit.
    pub acceleration_ratio: [f64; JOINTS],
    /// The smallest distance of any joint to its position limit along the path, radians.
    pub min_margin_rad: f64,
    /// The joint with that smallest margin.
    pub min_margin_joint: usize,
    /// The joint and limit that bind (position when the margin is not kept).
    pub binding: Binding,
    /// The shortest duration this posture allows with the margins; infinite when
    /// the position margin is not kept (no duration helps).
    pub shortest_feasible_s: f64,
    /// Whether the motion may run as asked.
    pub feasible: bool,
    /// Why not (`None` when feasible).
    pub reason: Option<Infeasibility>,
    /// The joint vector at the start of the path: where the arm goes home.
    pub home_q: Joints,
    /// The joint vector at the end of the path.
    pub end_q: Joints,
}

/// The contract's `isochron kin plan --json` object.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlanSummary {
    /// Whether the motion may run as asked.
    pub feasible: bool,
    /// Base axis to intercept point, horizontal, metres.
    pub distance_m: f64,
    /// The asked duration, seconds.
    pub movement_time_s: f64,
    /// Tool tilt, degrees (`null` when unreachable).
    pub tilt_deg: Option<f64>,
    /// Arm angle, degrees.
    pub arm_angle_deg: Option<f64>,
    /// Configuration signs of q2, q4, q6.
    pub flags: Option<[i8; 3]>,
    /// Peak speed / limit per joint at the asked duration.
    pub speed_ratio: Option<[f64; JOINTS]>,
    /// Peak acceleration / limit per joint at the asked duration.
    pub acceleration_ratio: Option<[f64; JOINTS]>,
    /// `"A4"` etc.
    pub binding_joint: Option<&'static str>,
    /// `"velocity"`, `"acceleration"` or `"position"`.
    pub binding_limit: Option<&'static str>,
    /// Smallest position margin along the path, degrees.
    pub min_margin_deg: Option<f64>,
    /// Shortest feasible duration, seconds (`null` when no duration helps).
    pub shortest_feasible_s: Option<f64>,
    /// The home joint vector, radians.
    pub home_q_rad: Option<[f64; JOINTS]>,
    /// Why it is refused.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

impl PlanSummary {
    /// The summary of a planning failure (no posture at all).
    pub fn refused(request: &MotionRequest, error: &PlanError) -> Self {
        Self {
            feasible: false,
            distance_m: request.end_m.x.hypot(request.end_m.y),
            movement_time_s: request.movement_time_s,
            tilt_deg: None,
            arm_angle_deg: None,
            flags: None,
            speed_ratio: None,
            acceleration_ratio: None,
            binding_joint: None,
            binding_limit: None,
            min_margin_deg: None,
            shortest_feasible_s: None,
            home_q_rad: None,
            reason: Some(error.to_string()),
        }
    }
}

impl MotionPlan {
    /// The contract's summary of this plan.
    pub fn summary(&self) -> PlanSummary {
        let r = &self.request;
        PlanSummary {
            feasible: self.feasible,
            distance_m: r.end_m.x.hypot(r.end_m.y),
            movement_time_s: r.movement_time_s,
            tilt_deg: Some(self.tilt_rad.to_degrees()),
            arm_angle_deg: Some(self.arm_angle_rad.to_degrees()),
            flags: Some(self.flags.signs()),
            speed_ratio: Some(self.speed_ratio),
            acceleration_ratio: Some(self.acceleration_ratio),
            binding_joint: Some(JOINT_NAMES[self.binding.joint]),
            binding_limit: Some(self.binding.limit.name()),
            min_margin_deg: Some(self.min_margin_rad.to_degrees()),
            shortest_feasible_s: self
                .shortest_feasible_s
                .is_finite()
                .then_some(self.shortest_feasible_s),
            home_q_rad: Some(self.home_q.into()),
            reason: self.reason.map(|r| r.to_string()),
        }
    }

    /// The worst speed ratio over the joints.
    pub fn worst_speed_ratio(&self) -> f64 {
        self.speed_ratio.iter().fold(0.0, |a, &b| a.max(b))
    }

    /// `base_from_tool` at path fraction `s` (clamped to `[0, 1]`).
    pub fn tool_pose_at(&self, s: f64) -> Pose {
        Pose::from_parts(self.request.point_at(s).into(), self.tool_rotation)
    }

    /// The per-cycle IK ([`Posture::joints_for_point`] in this plan's posture).
    ///
    /// # Errors
    ///
    /// As [`Posture::joints_for_point`].
    pub fn joints_for_point(
        &self,
        p_m: &Vector3<f64>,
        prev: &Joints,
        out: &mut Joints,
    ) -> Result<(), IkError> {
        ik_in_posture(
            &self.request,
            &self.tool_rotation,
            self.arm_angle_rad,
            self.flags,
            p_m,
            prev,
            out,
        )
    }

    /// The posture this plan holds, as a small copyable value for the control
    /// step (the per-cycle IK without the plan's report).
    pub fn posture(&self) -> Posture {
        Posture {
            request: self.request,
            tilt_rad: self.tilt_rad,
            orientation: self.tool_rotation,
            arm_angle_rad: self.arm_angle_rad,
            flags: self.flags,
            q_home: self.home_q,
            peak_speed_ratio: self.worst_speed_ratio(),
            min_margin_rad: self.min_margin_rad,
        }
    }

    /// [`Self::joints_for_point`] at path fraction `s` of the planned line.
    ///
    /// # Errors
    ///
    /// As [`Posture::joints_for_point`].
    pub fn joints_at(&self, s: f64, prev: &Joints, out: &mut Joints) -> Result<(), IkError> {
        self.joints_for_point(&self.request.point_at(s), prev, out)
    }
}

/// The posture of a planned motion (tilt, arm angle, configuration at home),
/// held for the whole motion, and the per-cycle IK in it. `Copy` and
/// allocation-free: what the control step keeps of a [`MotionPlan`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Posture {
    /// The motion it was planned for.
    pub request: MotionRequest,
    /// The tool's tilt about the base y axis, radians.
    pub tilt_rad: f64,
    /// The held tool orientation, `Ry(pi + tilt)` (base from tool).
    pub orientation: Rotation3<f64>,
    /// The held arm angle, radians.
    pub arm_angle_rad: f64,
    /// The configuration at home.
    pub flags: ArmFlags,
    /// The joint vector at the start of the path (home in this posture).
    pub q_home: Joints,
    /// The largest joint speed over its limit along the motion (at the planned duration).
    pub peak_speed_ratio: f64,
    /// The smallest distance of any joint to its position limit along the path, radians.
    pub min_margin_rad: f64,
}

impl Posture {
    /// The per-cycle IK: the joints that put the tool point at `p_m` with the
    /// held orientation, arm angle and q4 sign, in the q2/q6 configuration
    /// nearest to `prev` (the previous cycle's joints; [`Self::q_home`] at the
    /// start), so the arm follows the planned joint path through a shoulder or
    /// wrist singularity. Exact (analytic), allocation-free, under a
    /// microsecond; refuses (and leaves `out` unchanged) a point the arm cannot
    /// reach or a solution outside the joint limits.
    ///
    /// # Errors
    ///
    /// An [`IkError`] when the arm cannot reach `p_m` in this posture
    /// ([`IkError::OutOfReach`], [`IkError::NotFinite`], ...) or a joint leaves its limits
    /// ([`IkError::JointLimit`]).
    pub fn joints_for_point(
        &self,
        p_m: &Vector3<f64>,
        prev: &Joints,
        out: &mut Joints,
    ) -> Result<(), IkError> {
        ik_in_posture(
            &self.request,
            &self.orientation,
            self.arm_angle_rad,
            self.flags,
            p_m,
            prev,
            out,
        )
    }
}

/// The one per-cycle IK of a held posture (see [`Posture::joints_for_point`]).
fn ik_in_posture(
    req: &MotionRequest,
    r: &Rotation3<f64>,
    psi: f64,
    flags: ArmFlags,
    p_m: &Vector3<f64>,
    prev: &Joints,
    out: &mut Joints,
) -> Result<(), IkError> {
    let geo = ArmGeometry::new(&req.flange_pose_for(p_m, r))?;
    let mut q = Joints::zeros();
    geo.solve(psi, flags, &mut q);
    let q = nearest_variant(&q, prev);
    check_limits(&q, 0.0)?;
    *out = q;
    Ok(())
}

fn validate_request(req: &MotionRequest) -> Result<(), PlanError> {
    let finite = req
        .start_m
        .iter()
        .chain(req.end_m.iter())
        .all(|v| v.is_finite());
    if !finite {
        return Err(PlanError::NotFinitePoints);
    }
    if !(req.movement_time_s.is_finite() && req.movement_time_s > 0.0) {
        return Err(PlanError::MovementTime {
            movement_time_s: req.movement_time_s,
        });
    }
    if req.length_m() < 1e-6 {
        return Err(PlanError::PointsCoincide);
    }
    Ok(())
}

/// One candidate posture and its score.
#[derive(Debug, Clone, Copy)]
struct Cand {
    tilt: f64,
    psi: f64,
    score: f64,
}

/// Plans the motion: chooses tilt, arm angle and configuration, then checks the
/// chosen posture along the whole path sampled every `params.sample_period_ms`.
///
/// ```
/// use rt_core::trajectory::{MotionRequest, TaskParams, TrajectoryParams, plan};
/// // The paper's motion: 0.70 m in 1.5 s is feasible on the iiwa 7.
/// let request = MotionRequest::interception(&TaskParams::default(), 0.70);
/// let p = plan(&request, &TrajectoryParams::default()).unwrap();
/// assert!(p.feasible);
/// assert!(p.speed_ratio.iter().all(|r| *r <= 1.0));
/// ```
///
/// # Errors
///
/// [`PlanError::NotFinitePoints`], [`PlanError::MovementTime`] or
/// [`PlanError::PointsCoincide`] for a bad request; [`PlanError::Params`] for bad
/// `params`; [`PlanError::Unreachable`] when the line leaves the arm's reach at every tilt.
pub fn plan(req: &MotionRequest, params: &TrajectoryParams) -> Result<MotionPlan, PlanError> {
    validate_request(req)?;
    params.validate()?;
    let max_tilt = params.max_tilt_deg.to_radians();
    let deg = PI / 180.0;
    let psis: Vec<f64> = match params.elbow {
        ElbowPolicy::Free => (0..72).map(|i| -PI + f64::from(i) * 5.0 * deg).collect(),
        ElbowPolicy::Planar => vec![0.0, PI],
    };
    let tilt_step = if params.elbow == ElbowPolicy::Free {
        5.0
    } else {
        2.5
    } * deg;
    let n_tilts = (2.0 * max_tilt / tilt_step).round().max(0.0) as usize;
    let mut cands: Vec<Cand> = Vec::new();
    let mut last_err: Option<IkError> = None;
    for k in 0..=n_tilts {
        let tilt = -max_tilt + k as f64 * tilt_step;
        let samples = match Samples::new(req, &tool_rotation(tilt), 16) {
            Ok(s) => s,
            Err(e) => {
                last_err = Some(e);
                continue;
            }
        };
        for &psi in &psis {
            let score = samples.eval(psi).score(params);
            cands.push(Cand { tilt, psi, score });
        }
    }
    if cands.is_empty() {
        return Err(PlanError::Unreachable {
            max_tilt_deg: params.max_tilt_deg,
            ik: last_err,
        });
    }
    cands.sort_by(|a, b| a.score.total_cmp(&b.score));
    // Refine the best few distinct cells.
    let mut starts: Vec<Cand> = Vec::new();
    for c in &cands {
        let distinct = starts.iter().all(|s| {
            (s.tilt - c.tilt).abs() > 7.0 * deg || wrap_angle(s.psi - c.psi).abs() > 12.0 * deg
        });
        if distinct {
            starts.push(*c);
        }
        if starts.len() == 3 {
            break;
        }
    }
    let free = params.elbow == ElbowPolicy::Free;
    let mut best = starts[0];
    for s in starts {
        let c = refine(req, params, s, max_tilt, free);
        if c.score < best.score {
            best = c;
        }
    }
    finish(req, params, best.tilt, best.psi)
}

/// Scores one posture on `n` samples (infinite when out of reach).
fn score_at(req: &MotionRequest, p: &TrajectoryParams, tilt: f64, psi: f64, n: usize) -> f64 {
    match Samples::new(req, &tool_rotation(tilt), n) {
        Ok(s) => s.eval(psi).score(p),
        Err(_) => f64::INFINITY,
    }
}

/// Pattern search (8 neighbours, halving steps) from `c` on 40 samples.
fn refine(req: &MotionRequest, p: &TrajectoryParams, c: Cand, max_tilt: f64, free: bool) -> Cand {
    const N: usize = 40;
    let deg = PI / 180.0;
    let mut cur = Cand {
        score: score_at(req, p, c.tilt, c.psi, N),
        ..c
    };
    let mut step = 2.5 * deg;
    while step > 0.02 * deg {
        let mut moved = false;
        for (dt, dp) in [
            (1, 0),
            (-1, 0),
            (0, 1),
            (0, -1),
            (1, 1),
            (1, -1),
            (-1, 1),
            (-1, -1),
        ] {
            if !free && dp != 0 {
                continue;
            }
            let tilt = (cur.tilt + f64::from(dt) * step).clamp(-max_tilt, max_tilt);
            let psi = wrap_angle(cur.psi + f64::from(dp) * step);
            let score = score_at(req, p, tilt, psi, N);
            if score < cur.score {
                cur = Cand { tilt, psi, score };
                moved = true;
            }
        }
        if !moved {
            step *= 0.5;
        }
    }
    cur
}

/// The honest check of the chosen posture, sampled every `sample_period_ms`.
fn finish(
    req: &MotionRequest,
    p: &TrajectoryParams,
    tilt: f64,
    psi: f64,
) -> Result<MotionPlan, PlanError> {
    let t = req.movement_time_s;
    let n = ((t * 1e3 / p.sample_period_ms).ceil() as usize + 1).clamp(101, 20_001);
    let r = tool_rotation(tilt);
    let samples = Samples::new(req, &r, n).map_err(|e| PlanError::Unreachable {
        max_tilt_deg: p.max_tilt_deg,
        ik: Some(e),
    })?;
    let ev = samples.eval(psi);
    let (fi, margin, margin_joint) = ev.best_flags();
    let (f2, f4, f6) = family_flips(fi);
    let home_q = flip(&ev.home, f2, f4, f6);
    let end_q = flip(&ev.end, f2, f4, f6);
    let flags = ArmFlags::of(&home_q);
    let need = p.position_margin_deg.to_radians();
    let (t_min_exact, speed_binding) = ev.shortest(p);
    // Reported rounded up to the next millisecond, so that re-planning at it (with
    // its own sampling) is feasible.
    let t_min = (t_min_exact * 1e3 - 1e-6).ceil() / 1e3;
    let speed_ratio: [f64; JOINTS] =
        std::array::from_fn(|i| ev.speed[i] / (t * VELOCITY_LIMIT_RADPS[i]));
    let acceleration_ratio: [f64; JOINTS] =
        std::array::from_fn(|i| ev.accel[i] / (t * t * ACCELERATION_LIMIT_RADPS2[i]));
    let margin_ok = margin >= need && check_limits(&home_q, need).is_ok();
    let (feasible, binding, shortest, reason) = if !margin_ok {
        (
            false,
            Binding {
                joint: margin_joint,
                limit: LimitKind::Position,
            },
            f64::INFINITY,
            Some(Infeasibility::PositionMargin {
                joint: margin_joint,
                closest_rad: margin,
                margin_deg: p.position_margin_deg,
            }),
        )
    } else if t_min_exact > t * (1.0 + 1e-9) {
        let j = speed_binding.joint;
        let (ratio, allowed) = match speed_binding.limit {
            LimitKind::Acceleration => (acceleration_ratio[j], p.acceleration_fraction),
            _ => (speed_ratio[j], p.velocity_fraction),
        };
        (
            false,
            speed_binding,
            t_min,
            Some(Infeasibility::TooFast {
                joint: j,
                limit: speed_binding.limit,
                ratio,
                allowed,
                duration_s: t,
                shortest_feasible_s: t_min,
            }),
        )
    } else {
        (true, speed_binding, t_min, None)
    };
    Ok(MotionPlan {
        request: *req,
        tilt_rad: tilt,
        tool_rotation: r,
        arm_angle_rad: wrap_angle(psi),
        flags,
        speed_ratio,
        acceleration_ratio,
        min_margin_rad: margin,
        min_margin_joint: margin_joint,
        binding,
        shortest_feasible_s: shortest,
        feasible,
        reason,
        home_q,
        end_q,
    })
}

/// Evaluates a given posture (no search), e.g. to compare with a plan.
///
/// # Errors
///
/// As [`plan`] for a bad request or `params`; [`PlanError::Unreachable`] when the
/// line leaves the arm's reach in the given posture.
pub fn evaluate(
    req: &MotionRequest,
    params: &TrajectoryParams,
    tilt_rad: f64,
    arm_angle_rad: f64,
) -> Result<MotionPlan, PlanError> {
    validate_request(req)?;
    params.validate()?;
    finish(req, params, tilt_rad, arm_angle_rad)
}
