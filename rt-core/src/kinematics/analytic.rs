//! Analytic inverse kinematics by arm angle (Shimizu et al. 2008; Faria et al. 2018).
//!
//! For a flange pose the wrist centre `W` is fixed; the shoulder `S` is fixed; so
//! `|q4|` follows from `|SW|` alone and the elbow lies on a circle about the line
//! `SW`. The arm angle `psi` is the elbow's angle on that circle, measured about
//! `u = SW/|SW|` (right-handed) from the reference direction `v0`, the component of
//! the base z axis perpendicular to `u` (elbow "up"; `psi = 0` puts the elbow in the
//! vertical plane through the base axis and `W`). When `SW` is vertical, `v0` falls
//! back to the base x axis.
//!
//! Every geometric arm (S, E, W and the flange) has eight joint solutions, chosen by
//! the signs of q2, q4 and q6 ([`ArmFlags`]). Because rotating the elbow about `SW`
//! rotates frame 3 rigidly, `R03(psi) = As sin psi + Bs cos psi + Cs` and
//! `R47(psi) = Aw sin psi + Bw cos psi + Cw`, with the six matrices computed once per
//! pose ([`ArmGeometry`]); each joint is then an `atan2`/`acos` of a few affine
//! terms, so one solve costs well under a microsecond and sweeping `psi` is cheap.

use std::f64::consts::PI;

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use super::iiwa7::{DH_D_M, JOINT_NAMES, JOINTS, POSITION_LIMIT_RAD};
use super::{Joints, Pose, fk};

/// Shoulder height above the base, metres.
pub const SHOULDER_Z_M: f64 = DH_D_M[0];
/// Shoulder to elbow, metres.
pub const UPPER_ARM_M: f64 = DH_D_M[2];
/// Elbow to wrist centre, metres.
pub const FOREARM_M: f64 = DH_D_M[4];
/// Wrist centre to flange, metres.
pub const WRIST_FLANGE_M: f64 = DH_D_M[6];
/// Largest shoulder-wrist distance (arm stretched), metres.
pub const MAX_REACH_M: f64 = UPPER_ARM_M + FOREARM_M;

/// Why an inverse-kinematics request has no acceptable answer.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum IkError {
    /// The pose has NaN or infinite entries.
    #[error("the pose is not finite")]
    NotFinite,
    /// The wrist centre is farther from the shoulder than the stretched arm.
    #[error(
        "out of reach: the wrist centre is {distance_m:.4} m from the shoulder, the arm reaches {max_m:.3} m"
    )]
    OutOfReach {
        /// Shoulder to wrist centre, metres.
        distance_m: f64,
        /// The stretched arm's length, metres.
        max_m: f64,
    },
    /// The wrist centre coincides with the shoulder: the arm angle is undefined.
    #[error("singular: the wrist centre is at the shoulder")]
    WristAtShoulder,
    /// A joint of the solution is outside its (margin-shrunk) position limit.
    #[error("{} = {:.2} deg is outside its limit of +-{:.2} deg", JOINT_NAMES[*joint], value_rad.to_degrees(), limit_rad.to_degrees())]
    JointLimit {
        /// Index of the joint (0 = A1).
        joint: usize,
        /// The joint's value, radians.
        value_rad: f64,
        /// The limit it had to stay within, radians.
        limit_rad: f64,
    },
    /// No arm angle and configuration keeps every joint within its limits.
    #[error("no arm angle keeps every joint within its limits (closest: {} by {:.2} deg)", JOINT_NAMES[*joint], excess_rad.to_degrees())]
    NoFeasibleArmAngle {
        /// The joint that came closest to fitting but still failed.
        joint: usize,
        /// How far it stayed outside, radians.
        excess_rad: f64,
    },
    /// The numeric solver did not reach the tolerance.
    #[error(
        "did not converge: position error {pos_err_m:.2e} m, rotation error {rot_err_rad:.2e} rad"
    )]
    NotConverged {
        /// Remaining position error, metres.
        pos_err_m: f64,
        /// Remaining rotation error, radians.
        rot_err_rad: f64,
    },
}

/// The configuration flags: signs of q2, q4 and q6 (`true` = positive or zero).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct ArmFlags {
    /// q2 >= 0.
    pub q2_positive: bool,
    /// q4 >= 0.
    pub q4_positive: bool,
    /// q6 >= 0.
    pub q6_positive: bool,
}

impl ArmFlags {
    /// All eight configurations.
    pub const ALL: [Self; 8] = {
        let mut all = [Self {
            q2_positive: true,
            q4_positive: true,
            q6_positive: true,
        }; 8];
        let mut i = 0;
        while i < 8 {
            all[i] = Self {
                q2_positive: i & 1 == 0,
                q4_positive: i & 2 == 0,
                q6_positive: i & 4 == 0,
            };
            i += 1;
        }
        all
    };

    /// The flags of a joint vector.
    pub fn of(q: &Joints) -> Self {
        Self {
            q2_positive: q[1] >= 0.0,
            q4_positive: q[3] >= 0.0,
            q6_positive: q[5] >= 0.0,
        }
    }

    /// Signs as `[+-1, +-1, +-1]` for q2, q4, q6.
    pub fn signs(self) -> [i8; 3] {
        let s = |b: bool| if b { 1 } else { -1 };
        [
            s(self.q2_positive),
            s(self.q4_positive),
            s(self.q6_positive),
        ]
    }
}

/// Wraps an angle into `(-pi, pi]`.
#[inline]
pub fn wrap_angle(a: f64) -> f64 {
    let w = (a + PI).rem_euclid(2.0 * PI) - PI;
    if w <= -PI { w + 2.0 * PI } else { w }
}

/// Reference direction `v0` for the shoulder-wrist direction `u` (see the module doc).
#[inline]
fn reference_direction(u: &Vector3<f64>) -> Vector3<f64> {
    let v = Vector3::z() - u * u.z;
    let n = v.norm();
    if n > 1e-9 {
        v / n
    } else {
        let v = Vector3::x() - u * u.x;
        v / v.norm()
    }
}

/// The arm angle psi of a joint vector (radians, `(-pi, pi]`), as defined in the
/// module doc. Together with [`ArmFlags::of`] it gives back `q` through
/// [`ArmGeometry::solve`].
pub fn arm_angle(q: &Joints) -> f64 {
    let mut f = [Pose::identity(); JOINTS + 1];
    fk::frames(q, &mut f);
    let s = f[1].translation.vector;
    let e = f[3].translation.vector;
    let w = f[5].translation.vector;
    let sw = w - s;
    let n = sw.norm();
    if n < 1e-12 {
        return 0.0;
    }
    let u = sw / n;
    let v0 = reference_direction(&u);
    let se = e - s;
    let perp = se - u * se.dot(&u);
    wrap_angle(perp.dot(&u.cross(&v0)).atan2(perp.dot(&v0)))
}

#[inline]
fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Everything about one flange pose that does not depend on the arm angle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArmGeometry {
    a_s: Matrix3<f64>,
    b_s: Matrix3<f64>,
    c_s: Matrix3<f64>,
    a_w: Matrix3<f64>,
    b_w: Matrix3<f64>,
    c_w: Matrix3<f64>,
    q4_abs: f64,
    sw_m: f64,
}

impl ArmGeometry {
    /// Prepares the solution for `base_from_flange`.
    ///
    /// # Errors
    ///
    /// [`IkError::NotFinite`] for a pose with NaN or infinite entries;
    /// [`IkError::OutOfReach`] when the wrist centre is beyond the stretched arm;
    /// [`IkError::WristAtShoulder`] when it coincides with the shoulder.
    pub fn new(base_from_flange: &Pose) -> Result<Self, IkError> {
        let r07 = base_from_flange.rotation.matrix();
        let p = base_from_flange.translation.vector;
        if !(p.iter().all(|v| v.is_finite()) && r07.iter().all(|v| v.is_finite())) {
            return Err(IkError::NotFinite);
        }
        let w = p - r07.column(2) * WRIST_FLANGE_M;
        let sw = w - Vector3::new(0.0, 0.0, SHOULDER_Z_M);
        let l = sw.norm();
        if l > MAX_REACH_M + 1e-12 {
            return Err(IkError::OutOfReach {
                distance_m: l,
                max_m: MAX_REACH_M,
            });
        }
        if l < 1e-9 {
            return Err(IkError::WristAtShoulder);
        }
        let (dse, dew) = (UPPER_ARM_M, FOREARM_M);
        let c4 = ((l * l - dse * dse - dew * dew) / (2.0 * dse * dew)).clamp(-1.0, 1.0);
        let q4_abs = c4.acos();
        let u = sw / l;
        let v0 = reference_direction(&u);
        let cb = ((dse * dse + l * l - dew * dew) / (2.0 * dse * l)).clamp(-1.0, 1.0);
        let sb = (1.0 - cb * cb).max(0.0).sqrt();
        // Frame 3 at psi = 0 for q4 >= 0: y3 along the upper arm, z3 the joint-4 axis.
        let y3 = u * cb + v0 * sb;
        let z3 = v0.cross(&u);
        let x3 = y3.cross(&z3);
        let r03 = Matrix3::from_columns(&[x3, y3, z3]);
        let ux = skew(&u);
        let a_s = ux * r03;
        let c_s = u * (u.transpose() * r03);
        let b_s = r03 - c_s;
        let (s4, c4) = q4_abs.sin_cos();
        let r34 = Matrix3::new(c4, 0.0, -s4, s4, 0.0, c4, 0.0, -1.0, 0.0);
        let r43 = r34.transpose();
        let a_w = r43 * a_s.transpose() * r07;
        let b_w = r43 * b_s.transpose() * r07;
        let c_w = r43 * c_s.transpose() * r07;
        Ok(Self {
            a_s,
            b_s,
            c_s,
            a_w,
            b_w,
            c_w,
            q4_abs,
            sw_m: l,
        })
    }

    /// Shoulder to wrist-centre distance, metres.
    pub fn shoulder_wrist_m(&self) -> f64 {
        self.sw_m
    }

    /// `|q4|`, which depends on the shoulder-wrist distance only, radians.
    pub fn q4_abs_rad(&self) -> f64 {
        self.q4_abs
    }

    /// The joint vector for arm angle `psi` and configuration `flags`, written into
    /// `out`, without any limit check (see [`Self::solve_within`]).
    #[inline]
    pub fn solve(&self, psi: f64, flags: ArmFlags, out: &mut Joints) {
        let (s, c) = psi.sin_cos();
        let e = |a: &Matrix3<f64>, b: &Matrix3<f64>, k: &Matrix3<f64>, i: usize, j: usize| {
            a[(i, j)] * s + b[(i, j)] * c + k[(i, j)]
        };
        let (a, b, k) = (&self.a_s, &self.b_s, &self.c_s);
        let g2 = if flags.q2_positive { 1.0 } else { -1.0 };
        let g6 = if flags.q6_positive { 1.0 } else { -1.0 };
        let r11 = e(a, b, k, 1, 1);
        let r01 = e(a, b, k, 0, 1);
        let r21 = e(a, b, k, 2, 1);
        let r22 = e(a, b, k, 2, 2);
        let r20 = e(a, b, k, 2, 0);
        let mut q1 = (g2 * r11).atan2(g2 * r01);
        let q2 = g2 * r21.clamp(-1.0, 1.0).acos();
        let mut q3 = (-g2 * r22).atan2(-g2 * r20);
        let (a, b, k) = (&self.a_w, &self.b_w, &self.c_w);
        let w12 = e(a, b, k, 1, 2);
        let w02 = e(a, b, k, 0, 2);
        let w22 = e(a, b, k, 2, 2);
        let w21 = e(a, b, k, 2, 1);
        let w20 = e(a, b, k, 2, 0);
        let mut q5 = (g6 * w12).atan2(g6 * w02);
        let q6 = g6 * w22.clamp(-1.0, 1.0).acos();
        let q7 = (g6 * w21).atan2(-g6 * w20);
        let mut q4 = self.q4_abs;
        if !flags.q4_positive {
            q3 = wrap_angle(q3 + PI);
            q4 = -q4;
            q5 = wrap_angle(q5 + PI);
        }
        // atan2 of (0, 0) at the shoulder singularity (q2 = 0) gives q1 = 0; the
        // decomposition then puts the whole rotation into q3, which is still exact.
        q1 = wrap_angle(q1);
        *out = Joints::from([q1, q2, q3, q4, q5, q6, q7]);
    }

    /// Like [`Self::solve`], then checks every joint against its position limit
    /// shrunk by `margin_rad`.
    ///
    /// # Errors
    ///
    /// [`IkError::JointLimit`] for the first joint outside its limit shrunk by `margin_rad`.
    #[inline]
    pub fn solve_within(
        &self,
        psi: f64,
        flags: ArmFlags,
        margin_rad: f64,
        out: &mut Joints,
    ) -> Result<(), IkError> {
        self.solve(psi, flags, out);
        check_limits(out, margin_rad)
    }

    /// The feasible arm-angle intervals for `flags` with every joint at least
    /// `margin_rad` inside its limit, written into `out` as `(lo, hi)` radians with
    /// `lo <= hi`; returns how many (at most 16). An interval that wraps through `pi`
    /// is split in two. Found by sampling psi every degree, subdividing any cell in
    /// which a joint moves more than 0.05 rad (near the shoulder and wrist
    /// singularities joints swing fast with psi), and bisecting each boundary to
    /// 1e-9 rad. At an exact singularity (q2 = 0 or q6 = 0) the solution of one
    /// configuration jumps by pi in q1 and q3 (or q5 and q7) inside an interval.
    pub fn feasible_arm_angles(
        &self,
        flags: ArmFlags,
        margin_rad: f64,
        out: &mut [(f64, f64); 16],
    ) -> usize {
        const N: usize = 360;
        let step = 2.0 * PI / N as f64;
        let mut scan = Scan {
            geo: self,
            flags,
            margin_rad,
            out,
            n: 0,
            start: None,
        };
        let mut qa = Joints::zeros();
        self.solve(-PI, flags, &mut qa);
        let mut oka = check_limits(&qa, margin_rad).is_ok();
        if oka {
            scan.start = Some(-PI);
        }
        let mut a = -PI;
        let mut qb = Joints::zeros();
        for i in 1..=N {
            let b = -PI + step * i as f64;
            self.solve(b, flags, &mut qb);
            let okb = check_limits(&qb, margin_rad).is_ok();
            scan.cell(a, &qa, oka, b, &qb, okb, 0);
            (a, qa, oka) = (b, qb, okb);
        }
        if let Some(lo) = scan.start {
            scan.push(lo, PI);
        }
        scan.n
    }
}

/// State of [`ArmGeometry::feasible_arm_angles`]' scan.
struct Scan<'a> {
    geo: &'a ArmGeometry,
    flags: ArmFlags,
    margin_rad: f64,
    out: &'a mut [(f64, f64); 16],
    n: usize,
    start: Option<f64>,
}

impl Scan<'_> {
    fn ok(&self, psi: f64, q: &mut Joints) -> bool {
        self.geo.solve(psi, self.flags, q);
        check_limits(q, self.margin_rad).is_ok()
    }

    fn push(&mut self, lo: f64, hi: f64) {
        if self.n < self.out.len() {
            self.out[self.n] = (lo, hi);
            self.n += 1;
        }
    }

    #[expect(
        clippy::too_many_arguments,
        reason = "one recursion step: both ends of the interval and their solutions"
    )]
    fn cell(&mut self, a: f64, qa: &Joints, oka: bool, b: f64, qb: &Joints, okb: bool, depth: u32) {
        if depth < 30 && (qb - qa).amax() > 0.05 {
            let m = 0.5 * (a + b);
            let mut qm = Joints::zeros();
            let okm = self.ok(m, &mut qm);
            self.cell(a, qa, oka, m, &qm, okm, depth + 1);
            self.cell(m, &qm, okm, b, qb, okb, depth + 1);
            return;
        }
        if oka == okb {
            return;
        }
        let (mut lo, mut hi) = (a, b);
        let mut q = Joints::zeros();
        for _ in 0..32 {
            let mid = 0.5 * (lo + hi);
            if self.ok(mid, &mut q) == oka {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        if okb {
            self.start = Some(hi);
        } else if let Some(s) = self.start.take() {
            self.push(s, lo);
        }
    }
}

/// `|v| <= limit`, false for NaN.
#[inline]
fn inside(v: f64, limit: f64) -> bool {
    v.abs() <= limit
}

/// Checks every joint against its position limit shrunk by `margin_rad`.
///
/// # Errors
///
/// [`IkError::JointLimit`] for the first joint outside its limit shrunk by `margin_rad`.
#[inline]
pub fn check_limits(q: &Joints, margin_rad: f64) -> Result<(), IkError> {
    for i in 0..JOINTS {
        let limit = POSITION_LIMIT_RAD[i] - margin_rad;
        if !inside(q[i], limit) {
            return Err(IkError::JointLimit {
                joint: i,
                value_rad: q[i],
                limit_rad: limit,
            });
        }
    }
    Ok(())
}

/// A solution of [`solve`]: the joints and how they were chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IkSolution {
    /// The joint vector, radians.
    pub q: Joints,
    /// Its arm angle, radians.
    pub arm_angle_rad: f64,
    /// Its configuration.
    pub flags: ArmFlags,
}

/// Solves `base_from_flange` with every joint at least `margin_rad` inside its limits.
///
/// With a `seed`, the answer is the solution nearest to it (joint space): first the
/// seed's own arm angle and flags (exact continuation, as a per-cycle tracker wants),
/// otherwise the nearest feasible arm angle over all flags. Without a seed, the arm
/// angle and flags that keep the joints farthest from their limits. Cost: one
/// `ArmGeometry` plus up to 8 x 360 cheap evaluations (tens of microseconds) when
/// the seed's own arm angle does not fit.
///
/// # Errors
///
/// As [`ArmGeometry::new`] for a pose that is not finite or out of reach;
/// [`IkError::NoFeasibleArmAngle`] when no arm angle and flags keep every joint
/// within its limits; [`IkError::JointLimit`] when the refined solution leaves them.
pub fn solve(
    base_from_flange: &Pose,
    seed: Option<&Joints>,
    margin_rad: f64,
) -> Result<IkSolution, IkError> {
    let geo = ArmGeometry::new(base_from_flange)?;
    let mut q = Joints::zeros();
    if let Some(seed) = seed {
        let flags = ArmFlags::of(seed);
        let psi = arm_angle(seed);
        if geo.solve_within(psi, flags, margin_rad, &mut q).is_ok() {
            return Ok(IkSolution {
                q,
                arm_angle_rad: psi,
                flags,
            });
        }
    }
    const N: usize = 360;
    let step = 2.0 * PI / N as f64;
    let seed_psi = seed.map(arm_angle);
    // Score: larger is better. With a seed: minus the joint distance; without: the
    // smallest limit margin.
    let score = |q: &Joints| -> f64 {
        match seed {
            Some(s) => -(q - s).norm(),
            None => super::min_position_margin(q).0,
        }
    };
    let mut best: Option<(f64, f64, ArmFlags)> = None;
    let mut closest = (f64::INFINITY, 0usize);
    for flags in ArmFlags::ALL {
        for i in 0..N {
            let psi = -PI + step * (i as f64 + 0.5);
            geo.solve(psi, flags, &mut q);
            let (m, joint) = super::min_position_margin(&q);
            if m >= margin_rad {
                let sc = score(&q);
                if best.is_none_or(|b| sc > b.0) {
                    best = Some((sc, psi, flags));
                }
            } else if margin_rad - m < closest.0 {
                closest = (margin_rad - m, joint);
            }
        }
    }
    let Some((_, psi0, flags)) = best else {
        return Err(IkError::NoFeasibleArmAngle {
            joint: closest.1,
            excess_rad: closest.0,
        });
    };
    // Refine within one grid step by golden-section search on the score, keeping
    // feasibility (the grid point itself is feasible).
    let mut psi_best = psi0;
    geo.solve(psi0, flags, &mut q);
    let mut sc_best = score(&q);
    if let Some(sp) = seed_psi {
        // The seed's own arm angle, clamped into the feasible cell, is the natural target.
        let d = wrap_angle(sp - psi0).clamp(-step, step);
        let cand = psi0 + d;
        geo.solve(cand, flags, &mut q);
        if check_limits(&q, margin_rad).is_ok() && score(&q) > sc_best {
            psi_best = cand;
            sc_best = score(&q);
        }
    }
    let (mut lo, mut hi) = (psi_best - step, psi_best + step);
    let g = 0.618_033_988_749_894_9;
    for _ in 0..30 {
        let m1 = hi - g * (hi - lo);
        let m2 = lo + g * (hi - lo);
        let f = |p: f64, q: &mut Joints| {
            geo.solve(p, flags, q);
            if check_limits(q, margin_rad).is_ok() {
                score(q)
            } else {
                f64::NEG_INFINITY
            }
        };
        let (f1, f2) = (f(m1, &mut q), f(m2, &mut q));
        if f1.max(f2) > sc_best {
            sc_best = f1.max(f2);
            psi_best = if f1 > f2 { m1 } else { m2 };
        }
        if f1 > f2 { hi = m2 } else { lo = m1 }
    }
    geo.solve(psi_best, flags, &mut q);
    check_limits(&q, margin_rad)?;
    Ok(IkSolution {
        q,
        arm_angle_rad: wrap_angle(psi_best),
        flags,
    })
}
