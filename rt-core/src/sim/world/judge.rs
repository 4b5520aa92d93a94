//! The physical judge: a trial judged on the true world, with the world's
//! kinematics and tool geometry (never the controller's).
//!
//! - **The committed pass.** `t*` is the true ball's pass through the true
//!   intercept point's `y` nearest the pass the controller committed to (its
//!   predicted pass time); the pass's window is half-way to the neighbouring
//!   passes (a quarter period each side when there is none).
//! - **Contact.** The true ball (a sphere of the true radius) meets the true
//!   tool's contact disc (radius `contact_disc_radius_m`, at the tool point,
//!   normal along the tool axis) within the committed pass's window.
//! - **Arrival.** The first time after which the true tool point stays within
//!   `settle_m` (2 mm) of its final point: a physical event, not a profile fit.
//! - **Timing error** `arrival - t*`, signed: negative = the arm was early.
//! - **Success**: contact in the committed pass, `|timing error| <=` the
//!   tolerance, no limit violation or abort (the caller's part).
//!
//! A strike (issue #38, [`judge_strike`]) is judged the same way, but its
//! arrival is the moment the true tool point crosses the true intercept
//! point's `y` along its stroke (the tool passes where it meets the ball;
//! it settles only at the brake point), and the ball's outgoing velocity
//! right after the true contact is held against the target (see
//! [`crate::control::report::StrikeJudgement`]).

use nalgebra::Vector3;

use super::pendulum::Disc;

/// Settling radius of the arrival event, m.
pub const SETTLE_M: f64 = 0.002;

/// One sample of the true world.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WorldSample {
    /// Time, s.
    pub t_s: f64,
    /// True ball centre, m.
    pub ball_m: Vector3<f64>,
    /// True contact disc.
    pub disc: Disc,
}

pub use crate::control::report::PhysicalJudgement;

use crate::control::report::{STRIKE_SPEED_TOLERANCE, StrikeJudgement};
/// Why a trial could not be judged physically (defined beside the trial
/// driver's [`crate::lab::TruthObserver`]).
pub use crate::lab::truth::PhysicalJudgeError;
pub use crate::lab::truth::StrikeAim;

/// How long after the first touch the disc may still push the ball (the
/// outgoing velocity is the one after the last push within it), s.
pub const STRIKE_PUSH_S: f64 = 0.05;

/// Judges a strike: [`judge_physical`]'s contact and `t*`, the arrival the
/// true tool point's crossing of `intercept_y_m` along `aim.return_sign`
/// within the committed pass's window, and the ball's outgoing velocity
/// after the true contacts `hits` (their times and the true ball's
/// velocity after each, as the world's contact gave them) against `aim`.
///
/// # Errors
///
/// As [`judge_physical`].
#[expect(
    clippy::too_many_arguments,
    reason = "the physical judge's inputs plus the strike's; one call site"
)]
pub fn judge_strike(
    trace: &[WorldSample],
    hits: &[(f64, Vector3<f64>)],
    passes: &[f64],
    committed_pass_s: f64,
    ball_radius_m: f64,
    tolerance_ms: f64,
    intercept_y_m: f64,
    aim: &StrikeAim,
) -> Result<PhysicalJudgement, PhysicalJudgeError> {
    let mut p = judge_physical(trace, passes, committed_pass_s, ball_radius_m, tolerance_ms)?;
    let (lo, hi) = pass_window(passes, p.t_star_s);
    let s = aim.return_sign.signum();
    // The tool's crossing of the intercept point's y along the stroke.
    let ahead = |w: &WorldSample| (w.disc.centre_m.y - intercept_y_m) * s;
    let crossing = trace.windows(2).find_map(|w| {
        let (a, b) = (&w[0], &w[1]);
        (a.t_s >= lo && a.t_s <= hi && ahead(a) < 0.0 && ahead(b) >= 0.0).then(|| {
            let f = -ahead(a) / (ahead(b) - ahead(a)).max(1e-12);
            a.t_s + f * (b.t_s - a.t_s)
        })
    });
    let arrival = crossing.unwrap_or(f64::NAN);
    p.arrival_s = arrival;
    p.timing_error_ms = (arrival - p.t_star_s) * 1e3;
    p.hit_in_time = p.contact_s.is_some() && p.timing_error_ms.abs() <= tolerance_ms;
    // The true contact: the first hit in the window, the ball's velocity
    // after the last push within STRIKE_PUSH_S of it.
    let first = hits.iter().find(|h| h.0 >= lo && h.0 <= hi);
    let out = first.and_then(|f| {
        hits.iter()
            .rfind(|h| h.0 >= f.0 && h.0 <= f.0 + STRIKE_PUSH_S)
    });
    let tool_speed_mps = first.map_or(f64::NAN, |f| {
        trace
            .windows(2)
            .find(|w| w[0].t_s <= f.0 && w[1].t_s > f.0)
            .map_or(f64::NAN, |w| {
                (w[1].disc.centre_m - w[0].disc.centre_m).norm() / (w[1].t_s - w[0].t_s)
            })
    });
    let v = out.map_or(Vector3::from_element(f64::NAN), |h| h.1);
    let ball_speed_mps = v.norm();
    let target = aim.target_ball_speed_mps;
    let speed_error = (ball_speed_mps - target) / target;
    let direction_error_deg = (v.y * s / ball_speed_mps)
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees();
    p.strike = Some(StrikeJudgement {
        planned_tool_speed_mps: aim.planned_tool_speed_mps,
        tool_speed_mps,
        target_ball_speed_mps: target,
        ball_speed_mps,
        speed_error,
        direction_error_deg,
        speed_ok: out.is_some() && v.y * s > 0.0 && speed_error.abs() <= STRIKE_SPEED_TOLERANCE,
        aim_known: target.is_finite() && target > 0.0,
        predicted_ball_speed_mps: aim.predicted.map(|k| k.ball_speed_mps),
    });
    Ok(p)
}

/// The committed pass's window around `t_star`: half-way to the
/// neighbouring passes (a quarter period each side when there is none, as
/// [`judge_physical`]).
fn pass_window(passes: &[f64], t_star: f64) -> (f64, f64) {
    let k = passes.iter().position(|p| *p == t_star).unwrap_or(0);
    let half_gap = |other: Option<&f64>| other.map(|o| 0.5 * (o - t_star).abs());
    let before = k.checked_sub(1).and_then(|i| passes.get(i));
    let after = passes.get(k + 1);
    let default_half = half_gap(before).or(half_gap(after)).unwrap_or(0.7);
    (
        t_star - half_gap(before).unwrap_or(default_half),
        t_star + half_gap(after).unwrap_or(default_half),
    )
}

/// Judges `trace` physically. `passes` are the true passes (exact times),
/// `committed_pass_s` the controller's predicted pass, `ball_radius_m` the
/// true ball's, `tolerance_ms` the timing tolerance.
///
/// # Errors
///
/// [`PhysicalJudgeError::TooFewSamples`] for fewer than 2 samples;
/// [`PhysicalJudgeError::NoPass`] when the ball never passed the intercept point.
pub fn judge_physical(
    trace: &[WorldSample],
    passes: &[f64],
    committed_pass_s: f64,
    ball_radius_m: f64,
    tolerance_ms: f64,
) -> Result<PhysicalJudgement, PhysicalJudgeError> {
    if trace.len() < 2 {
        return Err(PhysicalJudgeError::TooFewSamples);
    }
    let (k, &t_star) = passes
        .iter()
        .enumerate()
        .min_by(|a, b| {
            (a.1 - committed_pass_s)
                .abs()
                .total_cmp(&(b.1 - committed_pass_s).abs())
        })
        .ok_or(PhysicalJudgeError::NoPass)?;
    let half_gap = |other: Option<&f64>| other.map(|o| 0.5 * (o - t_star).abs());
    let before = k.checked_sub(1).and_then(|i| passes.get(i));
    let after = passes.get(k + 1);
    let default_half = half_gap(before).or(half_gap(after)).unwrap_or(0.7);
    let lo = t_star - half_gap(before).unwrap_or(default_half);
    let hi = t_star + half_gap(after).unwrap_or(default_half);
    let mut contact_s = None;
    let mut min_gap = f64::INFINITY;
    for s in trace.iter().filter(|s| s.t_s >= lo && s.t_s <= hi) {
        let gap = s.disc.distance(&s.ball_m).0 - ball_radius_m;
        min_gap = min_gap.min(gap);
        if gap <= 0.0 && contact_s.is_none() {
            contact_s = Some(s.t_s);
        }
    }
    let last = trace[trace.len() - 1].disc.centre_m;
    let dist = |s: &WorldSample| (s.disc.centre_m - last).norm();
    // The last sample outside the settling radius; the event lies between it
    // and the next one (interpolated linearly in the distance).
    let arrival = match trace.iter().rposition(|s| dist(s) > SETTLE_M) {
        None => trace[0].t_s,
        Some(i) if i + 1 >= trace.len() => trace[i].t_s,
        Some(i) => {
            let (a, b) = (&trace[i], &trace[i + 1]);
            let (da, db) = (dist(a), dist(b));
            let f = if da > db {
                (da - SETTLE_M) / (da - db)
            } else {
                1.0
            };
            a.t_s + f.clamp(0.0, 1.0) * (b.t_s - a.t_s)
        }
    };
    let err_ms = (arrival - t_star) * 1e3;
    Ok(PhysicalJudgement {
        t_star_s: t_star,
        arrival_s: arrival,
        timing_error_ms: err_ms,
        contact_s,
        min_gap_m: min_gap,
        hit_in_time: contact_s.is_some() && err_ms.abs() <= tolerance_ms,
        strike: None,
    })
}
