//! Arrival time by least squares (CONTRACT.md's definition): the end time of
//! the ideal profile, of the planned shape, length and duration, that best fits
//! the measured progress along the path.
//!
//! Not real-time code: used to judge motions (tests, trial results).

use super::TimingError;
use crate::trajectory::profile::ProfileKind;

/// The best-fitting start and arrival of an ideal profile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArrivalFit {
    /// Start of the fitted profile, seconds (same clock as the samples).
    pub start_s: f64,
    /// `start_s + duration`, seconds.
    pub arrival_s: f64,
    /// Root-mean-square residual of the fit, metres.
    pub rms_m: f64,
}

/// Fits `distance_m * kind.position((t - t0) / duration_s)` to the samples
/// `(times_s[i], progress_m[i])` over the start `t0` and returns it.
///
/// Refuses mismatched or short (< 3) sample slices, non-finite samples and a
/// non-positive distance or duration.
///
/// # Errors
///
/// [`TimingError::OutOfRange`] for a distance or duration that is not finite and
/// positive, or fewer than 3 (or mismatched) samples; [`TimingError::NotFinite`]
/// for a non-finite sample.
pub fn fit_arrival(
    kind: ProfileKind,
    distance_m: f64,
    duration_s: f64,
    times_s: &[f64],
    progress_m: &[f64],
) -> Result<ArrivalFit, TimingError> {
    if !(distance_m.is_finite() && distance_m > 0.0) {
        return Err(TimingError::OutOfRange {
            what: "distance_m",
            value: distance_m,
            bound: "must be finite and > 0",
        });
    }
    if !(duration_s.is_finite() && duration_s > 0.0) {
        return Err(TimingError::OutOfRange {
            what: "duration_s",
            value: duration_s,
            bound: "must be finite and > 0",
        });
    }
    if times_s.len() != progress_m.len() || times_s.len() < 3 {
        return Err(TimingError::OutOfRange {
            what: "number of samples",
            value: times_s.len().min(progress_m.len()) as f64,
            bound: "needs at least 3 samples and as many times as progress values",
        });
    }
    if !times_s.iter().chain(progress_m).all(|v| v.is_finite()) {
        return Err(TimingError::NotFinite { what: "samples" });
    }
    let cost = |t0: f64| -> f64 {
        times_s
            .iter()
            .zip(progress_m)
            .map(|(t, s)| {
                let e = s - distance_m * kind.position((t - t0) / duration_s);
                e * e
            })
            .sum()
    };
    let (t_lo, t_hi) = times_s
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &t| {
            (lo.min(t), hi.max(t))
        });
    // Coarse grid, then golden-section refinement around the best point.
    let (lo, hi) = (t_lo - duration_s, t_hi);
    let n = 400;
    let step = (hi - lo) / f64::from(n);
    let mut best = lo;
    let mut best_cost = f64::INFINITY;
    for i in 0..=n {
        let t0 = lo + step * f64::from(i);
        let c = cost(t0);
        if c < best_cost {
            best_cost = c;
            best = t0;
        }
    }
    let (mut a, mut b) = (best - step, best + step);
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let mut x1 = b - g * (b - a);
    let mut x2 = a + g * (b - a);
    let (mut f1, mut f2) = (cost(x1), cost(x2));
    for _ in 0..100 {
        if f1 < f2 {
            b = x2;
            x2 = x1;
            f2 = f1;
            x1 = b - g * (b - a);
            f1 = cost(x1);
        } else {
            a = x1;
            x1 = x2;
            f1 = f2;
            x2 = a + g * (b - a);
            f2 = cost(x2);
        }
        if b - a < 1e-9 {
            break;
        }
    }
    let t0 = 0.5 * (a + b);
    let rms = (cost(t0) / times_s.len() as f64).sqrt();
    Ok(ArrivalFit {
        start_s: t0,
        arrival_s: t0 + duration_s,
        rms_m: rms,
    })
}
