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

/// Why a trial could not be judged physically (defined beside the trial
/// driver's [`crate::lab::TruthObserver`]).
pub use crate::lab::truth::PhysicalJudgeError;

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
    })
}
