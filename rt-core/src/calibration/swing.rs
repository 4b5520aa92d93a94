//! The free-swing fit: a released pendulum's lateral track -> effective length
//! (large-angle corrected), damping, rest offset.

use serde::{Deserialize, Serialize};

use super::{CalibrationError, lsq};
use crate::pendulum::{PendulumModel, PendulumState};

/// One measurement of the swinging ball.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SwingSample {
    /// Capture time (middle of the exposure), seconds.
    pub t_s: f64,
    /// Lateral position on the swing plane, metres (base +y, zero at the believed rest point).
    pub lateral_m: f64,
}

/// Smallest swing amplitude the fit accepts, metres (about 1.5 deg on a 1.9 m pendulum).
pub const MIN_AMPLITUDE_M: f64 = 0.05;
/// Shortest recording the fit accepts, in small-angle periods.
pub const MIN_PERIODS: f64 = 3.0;
/// Fewest samples the fit accepts.
pub const MIN_SAMPLES: usize = 60;

/// A ball within this of the recording's first sample has not left the
/// magnet yet, metres: the step's hold check (`server::calibration`) calls
/// a ball still when it moves less than 3 mm in a second.
pub const HELD_BAND_M: f64 = 0.003;

/// The largest residual RMS of a free swing's fit, as a share of its
/// amplitude (a camera's noise is about a thousandth of it; a swing fitted
/// with a second of the held ball before it leaves 17%).
pub const MAX_RESIDUAL_SHARE: f64 = 0.05;

/// The samples from where the ball leaves the magnet: a recording begins
/// when the magnet is told to let go, and its board may answer late (a
/// serial link, a busy machine), so the first samples may show the ball
/// still held. Drops the leading samples within [`HELD_BAND_M`] of the
/// first but the last of them (the ball starts from rest there). `s` is
/// sorted by time.
pub fn from_release(s: &[SwingSample]) -> &[SwingSample] {
    let Some(first) = s.first() else {
        return s;
    };
    match s
        .iter()
        .position(|x| (x.lateral_m - first.lateral_m).abs() > HELD_BAND_M)
    {
        Some(moved) => &s[moved.saturating_sub(1)..],
        None => s,
    }
}
/// Largest RK4 sub-step of the model inside the fit, seconds.
const FIT_STEP_S: f64 = 2e-3;

/// The fitted swing.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SwingFit {
    /// Effective length (pivot to ball centre) of the model `phi'' = -(g/l) sin phi -
    /// alpha phi'` that best explains the track: the large-angle period is built in.
    pub length_m: f64,
    /// One standard deviation of `length_m`.
    pub length_std_m: f64,
    /// Viscous damping alpha, 1/s.
    pub damping_per_s: f64,
    /// One standard deviation of `damping_per_s`.
    pub damping_std_per_s: f64,
    /// The angle at the first sample, radians.
    pub start_angle_rad: f64,
    /// The angular rate at the first sample, rad/s.
    #[serde(default)]
    pub start_rate_radps: f64,
    /// Where the ball hangs at rest relative to the believed rest point, metres (lateral).
    pub rest_offset_m: f64,
    /// Small-angle period `2 pi sqrt(l/g)` of the fitted length, seconds.
    pub small_angle_period_s: f64,
    /// Period at the first sample's amplitude (large-angle), seconds.
    pub period_at_start_s: f64,
    /// Root mean square of the lateral residuals, metres.
    pub residual_rms_m: f64,
    /// Samples fitted.
    pub samples: usize,
    /// Seconds of swing fitted.
    pub duration_s: f64,
}

/// One detection of the swinging ball: when, where on the swing plane, where
/// in the image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackedSwingSample {
    /// Capture time (middle of the exposure), seconds.
    pub t_s: f64,
    /// Lateral position on the swing plane, metres (base +y, zero at the believed rest point).
    pub lateral_m: f64,
    /// The ball's centre in the image, pixels (column, row).
    pub px: [f64; 2],
}

/// A track's detections on the camera's frame grid
/// ([`super::latency::frame_grid`]). Each frame's stamp is its delivery
/// less the camera's latency, and a busy host or stream delivers frames
/// late: in bursts after a stall, stamped together (at the swing's 1.8 m/s
/// a frame stamped 100 ms late is 18 cm off the swing, and the fit refuses
/// the whole swing as no free swing). Kept: the frames delivered within half
/// a frame period of their capture slot's on-time delivery, each stamped at
/// its slot (its lateness taken off: the stream's jitter too); a late
/// frame's slot is a guess (a frame of its burst may be missing), so it is
/// dropped. `frame_period_s` is the camera's nominal frame period.
///
/// # Errors
///
/// [`CalibrationError::NotFinite`] for a non-finite stamp or a bad period;
/// [`CalibrationError::LateFrames`] when fewer than [`MIN_ON_TIME_SHARE`]
/// of the frames came on time (calibrate when the host is quieter).
pub fn on_frame_grid(
    track: &[TrackedSwingSample],
    frame_period_s: f64,
) -> Result<Vec<TrackedSwingSample>, CalibrationError> {
    const WHAT: &str = "pendulum swing (frame stamps)";
    if !(frame_period_s.is_finite() && frame_period_s > 0.0) {
        return Err(CalibrationError::NotFinite {
            what: WHAT,
            index: 0,
        });
    }
    if let Some(index) = track.iter().position(|s| !s.t_s.is_finite()) {
        return Err(CalibrationError::NotFinite { what: WHAT, index });
    }
    if track.len() < 3 {
        return Ok(track.to_vec());
    }
    let mut sorted = track.to_vec();
    sorted.sort_by(|a, b| a.t_s.total_cmp(&b.t_s));
    let stamps: Vec<f64> = sorted.iter().map(|s| s.t_s).collect();
    let g = super::latency::frame_grid(&stamps, frame_period_s);
    let on_time: Vec<TrackedSwingSample> = sorted
        .iter()
        .zip(&g.lateness_s)
        .filter(|(_, late)| **late < 0.5 * g.period_s)
        .map(|(s, late)| TrackedSwingSample {
            t_s: s.t_s - late,
            ..*s
        })
        .collect();
    if (on_time.len() as f64) < MIN_ON_TIME_SHARE * sorted.len() as f64 {
        return Err(CalibrationError::LateFrames {
            what: "the pendulum's swing",
            late: sorted.len() - on_time.len(),
            frames: sorted.len(),
            period_ms: g.period_s * 1e3,
        });
    }
    Ok(on_time)
}

/// The least share of a swing's frames [`on_frame_grid`] needs on time.
pub const MIN_ON_TIME_SHARE: f64 = 0.5;

/// Fewest passes through the fitted rest point the pendulum step needs.
pub const MIN_REST_PASSES: usize = 5;

/// The pendulum step from a recorded free swing alone (a real lab, where no
/// one need hold the ball still): the swing fit; the rest point's image
/// position where the track passes the fitted rest point (the bottom of the
/// arc: at each pass, between the two detections on either side of it at most
/// two frames apart, interpolated linearly; the passes averaged: a chord of
/// 6 cm misses the arc's bottom by 0.2 mm); the swing's axis in the image.
/// Refused as [`fit_swing`] refuses, and with fewer than [`MIN_REST_PASSES`]
/// passes.
///
/// # Errors
///
/// As [`fit_swing`], and [`CalibrationError::NotFinite`] for a non-finite pixel;
/// [`CalibrationError::TooFewSamples`] with fewer than [`MIN_REST_PASSES`] passes
/// through the rest point.
pub fn pendulum_from_swing(
    track: &[TrackedSwingSample],
    gravity_mps2: f64,
    length_guess_m: f64,
) -> Result<super::file::PendulumCalibration, CalibrationError> {
    let samples: Vec<SwingSample> = track
        .iter()
        .map(|s| SwingSample {
            t_s: s.t_s,
            lateral_m: s.lateral_m,
        })
        .collect();
    let swing = fit_swing(&samples, gravity_mps2, length_guess_m)?;
    for (index, s) in track.iter().enumerate() {
        if !(s.px[0].is_finite() && s.px[1].is_finite()) {
            return Err(CalibrationError::NotFinite {
                what: "pendulum swing (image)",
                index,
            });
        }
    }
    let mut sorted: Vec<&TrackedSwingSample> = track.iter().collect();
    sorted.sort_by(|a, b| a.t_s.total_cmp(&b.t_s));
    // Frame spacing: the median gap between detections.
    let mut gaps: Vec<f64> = sorted.windows(2).map(|w| w[1].t_s - w[0].t_s).collect();
    gaps.sort_by(f64::total_cmp);
    let frame_s = gaps.get(gaps.len() / 2).copied().unwrap_or(0.0);
    let b = swing.rest_offset_m;
    let rest: Vec<(f64, f64)> = sorted
        .windows(2)
        .filter(|w| {
            let (d0, d1) = (w[0].lateral_m - b, w[1].lateral_m - b);
            d0 * d1 <= 0.0 && d0 != d1 && w[1].t_s - w[0].t_s <= 2.5 * frame_s
        })
        .map(|w| {
            let (d0, d1) = (w[0].lateral_m - b, w[1].lateral_m - b);
            let a = d0 / (d0 - d1);
            (
                w[0].px[0] + a * (w[1].px[0] - w[0].px[0]),
                w[0].px[1] + a * (w[1].px[1] - w[0].px[1]),
            )
        })
        .collect();
    if rest.len() < MIN_REST_PASSES {
        return Err(CalibrationError::TooFewSamples {
            what: "pendulum rest point (passes of the track through the fitted rest point)",
            got: rest.len(),
            need: MIN_REST_PASSES,
        });
    }
    let (mu, mv, su, sv) = mean_std(&rest);
    let all: Vec<(f64, f64)> = track.iter().map(|s| (s.px[0], s.px[1])).collect();
    Ok(super::file::PendulumCalibration {
        swing,
        rest_px: [mu, mv],
        rest_std_px: [su, sv],
        swing_image_angle_deg: principal_angle_deg(&all),
    })
}

/// Fits the damped pendulum to a free swing's samples (any order; sorted here),
/// from where the ball leaves the magnet ([`from_release`]).
/// `gravity_mps2` is the local gravity; `length_guess_m` a starting length (the
/// tape measure). Refuses too few samples, too short a recording, too small a
/// swing, and samples a free swing does not explain.
///
/// # Errors
///
/// [`CalibrationError::NotFinite`], [`CalibrationError::TooFewSamples`],
/// [`CalibrationError::TooShort`] or [`CalibrationError::SwingTooSmall`] for bad,
/// too few, too short or too small samples; [`CalibrationError::FitFailed`] for a
/// bad gravity or length guess, a fit that does not converge or a non-physical length;
/// [`CalibrationError::PoorFit`] for residuals over [`MAX_RESIDUAL_SHARE`] of the amplitude.
pub fn fit_swing(
    samples: &[SwingSample],
    gravity_mps2: f64,
    length_guess_m: f64,
) -> Result<SwingFit, CalibrationError> {
    const WHAT: &str = "pendulum swing";
    for (index, s) in samples.iter().enumerate() {
        if !s.t_s.is_finite() || !s.lateral_m.is_finite() {
            return Err(CalibrationError::NotFinite { what: WHAT, index });
        }
    }
    if samples.len() < MIN_SAMPLES {
        return Err(CalibrationError::TooFewSamples {
            what: WHAT,
            got: samples.len(),
            need: MIN_SAMPLES,
        });
    }
    if !(gravity_mps2.is_finite() && gravity_mps2 > 0.0 && length_guess_m > 0.05) {
        return Err(CalibrationError::FitFailed {
            what: WHAT,
            reason: format!("bad gravity {gravity_mps2} or length guess {length_guess_m}"),
        });
    }
    let mut s = samples.to_vec();
    s.sort_by(|a, b| a.t_s.total_cmp(&b.t_s));
    let s = from_release(&s).to_vec();
    if s.len() < MIN_SAMPLES {
        return Err(CalibrationError::TooFewSamples {
            what: WHAT,
            got: s.len(),
            need: MIN_SAMPLES,
        });
    }
    let t0 = s[0].t_s;
    let duration_s = s[s.len() - 1].t_s - t0;
    let need_s = MIN_PERIODS * std::f64::consts::TAU * (length_guess_m / gravity_mps2).sqrt();
    if duration_s < need_s {
        return Err(CalibrationError::TooShort {
            what: WHAT,
            got_s: duration_s,
            need_s,
        });
    }
    let (lo, hi) = s
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| {
            (lo.min(x.lateral_m), hi.max(x.lateral_m))
        });
    let amplitude_m = 0.5 * (hi - lo);
    if amplitude_m < MIN_AMPLITUDE_M {
        return Err(CalibrationError::SwingTooSmall {
            amplitude_m,
            min_m: MIN_AMPLITUDE_M,
        });
    }
    // Starting point: offset = mid-range, period from upward zero crossings, decay
    // from the first and last peaks, state from the first samples.
    let b0 = 0.5 * (hi + lo);
    let crossings: Vec<f64> = s
        .windows(2)
        .filter(|w| w[0].lateral_m - b0 < 0.0 && w[1].lateral_m - b0 >= 0.0)
        .map(|w| {
            let (a, c) = (w[0].lateral_m - b0, w[1].lateral_m - b0);
            w[0].t_s + (w[1].t_s - w[0].t_s) * (-a / (c - a))
        })
        .collect();
    let mut length0 = length_guess_m;
    if crossings.len() >= 2 {
        let period = (crossings[crossings.len() - 1] - crossings[0]) / (crossings.len() - 1) as f64;
        let amp0 = (amplitude_m / length_guess_m).clamp(0.0, 1.0).asin();
        // Period grows by ~ (1 + a^2/16) at amplitude a.
        let t_small = period / (1.0 + amp0 * amp0 / 16.0);
        let l = gravity_mps2 * (t_small / std::f64::consts::TAU).powi(2);
        if l.is_finite() && l > 0.1 && l < 20.0 {
            length0 = l;
        }
    }
    let period0 = std::f64::consts::TAU * (length0 / gravity_mps2).sqrt();
    let peak = |from: f64, to: f64| {
        s.iter()
            .filter(|x| x.t_s >= from && x.t_s < to)
            .map(|x| (x.lateral_m - b0).abs())
            .fold(0.0, f64::max)
    };
    let first = peak(t0, t0 + period0);
    let last = peak(t0 + duration_s - period0, t0 + duration_s + 1.0);
    let span = (duration_s - period0).max(period0);
    let alpha0 = if first > 0.0 && last > 0.0 {
        (2.0 * (first / last).ln() / span).clamp(0.0, 1.0)
    } else {
        0.0
    };
    // Initial angle and rate from a quadratic through the first few samples.
    let k = 3.min(s.len() - 1);
    let y0 = (s[0].lateral_m - b0) / length0;
    let rate = (s[k].lateral_m - s[0].lateral_m) / (s[k].t_s - s[0].t_s).max(1e-6) / length0;
    let phi0 = y0.clamp(-0.99, 0.99).asin();
    let start = [length0, alpha0, phi0, rate / phi0.cos().max(0.1), b0];
    let scale = [1e-5, 1e-6, 1e-6, 1e-6, 1e-6];

    // Fit over a growing window: two periods, five, then everything (keeps the
    // phase from slipping by a whole cycle).
    let mut p = start.to_vec();
    let mut result = None;
    for periods in [2.0, 5.0, f64::INFINITY] {
        let end = t0 + periods * period0;
        let window: Vec<SwingSample> = s.iter().copied().filter(|x| x.t_s <= end).collect();
        if window.len() <= p.len() + 2 {
            continue;
        }
        let r = lsq::levenberg_marquardt(&p, &scale, window.len(), 60, |q, r| {
            residuals(q, &window, t0, gravity_mps2, r)
        });
        match r {
            Some(fit) => {
                p.clone_from(&fit.params);
                result = Some(fit);
            }
            None => {
                return Err(CalibrationError::FitFailed {
                    what: WHAT,
                    reason: "the least-squares fit did not converge".into(),
                });
            }
        }
        if end >= t0 + duration_s {
            break;
        }
    }
    let Some(fit) = result else {
        return Err(CalibrationError::FitFailed {
            what: WHAT,
            reason: "no window to fit".into(),
        });
    };
    let [
        length_m,
        damping_per_s,
        start_angle_rad,
        start_rate_radps,
        rest_offset_m,
    ] = [
        fit.params[0],
        fit.params[1],
        fit.params[2],
        fit.params[3],
        fit.params[4],
    ];
    if !(length_m > 0.05 && length_m < 20.0 && damping_per_s.is_finite()) {
        return Err(CalibrationError::FitFailed {
            what: WHAT,
            reason: format!("non-physical length {length_m:.4} m"),
        });
    }
    if fit.rms.is_nan() || fit.rms > MAX_RESIDUAL_SHARE * amplitude_m {
        return Err(CalibrationError::PoorFit {
            what: WHAT,
            residual_m: fit.rms,
            amplitude_m,
            limit_share: MAX_RESIDUAL_SHARE,
        });
    }
    let small = std::f64::consts::TAU * (length_m / gravity_mps2).sqrt();
    let amp =
        (fit.params[2].powi(2) + (fit.params[3] * small / std::f64::consts::TAU).powi(2)).sqrt();
    Ok(SwingFit {
        length_m,
        length_std_m: fit.std[0],
        damping_per_s,
        damping_std_per_s: fit.std[1],
        start_angle_rad,
        start_rate_radps,
        rest_offset_m,
        small_angle_period_s: small,
        period_at_start_s: large_angle_period_s(small, amp),
        residual_rms_m: fit.rms,
        samples: s.len(),
        duration_s,
    })
}

/// The exact period of an undamped pendulum at amplitude `amplitude_rad`:
/// `T0 * 2 K(sin(a/2)) / pi`, with `K` by the arithmetic-geometric mean.
pub fn large_angle_period_s(small_angle_period_s: f64, amplitude_rad: f64) -> f64 {
    let k = (0.5 * amplitude_rad).sin();
    let (mut a, mut g) = (1.0, (1.0 - k * k).max(0.0).sqrt());
    for _ in 0..30 {
        let (an, gn) = (0.5 * (a + g), (a * g).sqrt());
        a = an;
        g = gn;
    }
    small_angle_period_s / a
}

fn residuals(p: &[f64], s: &[SwingSample], t0: f64, g: f64, r: &mut [f64]) -> bool {
    let (l, alpha, phi0, w0, b) = (p[0], p[1], p[2], p[3], p[4]);
    if !(l > 0.05 && l < 50.0 && alpha.abs() < 5.0 && phi0.abs() < 3.0 && w0.abs() < 50.0) {
        return false;
    }
    let model = PendulumModel {
        length_m: l,
        gravity_mps2: g,
        damping_per_s: alpha,
    };
    let mut state = PendulumState::new(phi0, w0);
    let mut t = t0;
    for (ri, x) in r.iter_mut().zip(s) {
        state = model.integrate(state, x.t_s - t, FIT_STEP_S, 0.0);
        t = x.t_s;
        *ri = l * state[0].sin() + b - x.lateral_m;
    }
    true
}

/// Mean and standard deviation of image points: `(mean u, mean v, std u, std v)`.
pub fn mean_std(points: &[(f64, f64)]) -> (f64, f64, f64, f64) {
    let n = points.len().max(1) as f64;
    let mu = points.iter().map(|p| p.0).sum::<f64>() / n;
    let mv = points.iter().map(|p| p.1).sum::<f64>() / n;
    let su = (points.iter().map(|p| (p.0 - mu).powi(2)).sum::<f64>() / n).sqrt();
    let sv = (points.iter().map(|p| (p.1 - mv).powi(2)).sum::<f64>() / n).sqrt();
    (mu, mv, su, sv)
}

/// Angle of the track's principal axis from the image x axis, degrees (-90..90).
pub fn principal_angle_deg(points: &[(f64, f64)]) -> f64 {
    let (mu, mv, _, _) = mean_std(points);
    let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
    for (u, v) in points {
        sxx += (u - mu).powi(2);
        syy += (v - mv).powi(2);
        sxy += (u - mu) * (v - mv);
    }
    0.5 * (2.0 * sxy).atan2(sxx - syy).to_degrees()
}
