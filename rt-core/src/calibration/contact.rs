//! The contact step: how late FRI's external joint torques show a contact
//! and how long its force pulse lasts (the measured judge's beliefs
//! `success.torque_lag_periods` and `success.contact_pulse_ms`, issue #35),
//! learned from a knock on the hanging ball without the camera's clock.
//!
//! The knock: the ball hangs still at its rest point; the tool, moving along
//! the swing (base `y`, direction `sigma = +-1`), meets it at `t1` and stops
//! a little past it at `y_stop`; the ball swings out with amplitude `A` and
//! comes back to meet the stopped tool, on the same face, at `t2`. The
//! torques show both contacts as pulses; fitted by the pulse model below,
//! each gives its apparent onset `c_i = t_i + L` (`L` the torques' lag) and
//! both the pulse length `D`. The lag cancels in `t2 - t1 = c2 - c1`, and
//! the pendulum's free swing between the contacts ties the tool's position
//! at the first contact to its stop:
//!
//! `y_tool(t1) = y_stop - sigma A sin(omega (c2 - c1))`
//!
//! (the ball at rest at `t1`; `omega` the calibrated pendulum frequency;
//! `A` the amplitude of the swing between the contacts as the camera sees
//! it: a length, so the camera's latency does not enter, only its scale).
//! `t1` is where the measured tool track reaches that position; `L = c1 -
//! t1`. Neither the camera's clock nor the ball's or the tool's geometry
//! enters (the same face meets the same ball twice). An error `e` in `A`
//! moves `L` by `e sin(omega (c2 - c1)) / v` (`v` the knock's speed); a
//! ball swinging by `a0` before the knock by up to `2 a0 / v`.
//!
//! The pulse model, as FRI's external torque estimate reports a short
//! contact: a half-sine force pulse of impulse `J` and length `D` from `t0`;
//! each message at `t_k` reports its mean over the period since the last
//! message, `L` late, mapped to the joints along a fixed direction `u`:
//! `tau_k . u = J (F(t_k - L - t0) - F(t_(k-1) - L - t0)) / (t_k - t_(k-1))`,
//! `F(s) = (1 - cos(pi clamp(s / D, 0, 1))) / 2`. `c = t0 + L` and `D` are
//! found by a grid search over both pulses (one `D`, each pulse its own `c`
//! and `J`, `J` by linear least squares). With messages longer than the
//! pulse the split of `L + D / 2` into `L` and `D` is weakly determined;
//! the measured judge subtracts only the sum (`control::measured::
//! contact_onset`), which the knock determines.

use serde::{Deserialize, Serialize};

use super::CalibrationError;
use crate::control::measured::Sighting;

/// What the fit needs of one knock.
#[derive(Debug, Clone, Copy)]
pub struct KnockRecording<'a> {
    /// Robot message times, control clock, s (ascending).
    pub t_s: &'a [f64],
    /// The measured tool point along the swing (base `y`), m, per message.
    pub tool_y_m: &'a [f64],
    /// FRI's external joint torques, N m, per message.
    pub torques_nm: &'a [[f64; 7]],
    /// The camera's detections of the ball (lateral along the swing, m):
    /// still for [`REST_WINDOW_S`] before the knock, then its swing.
    pub sightings: &'a [Sighting],
    /// When the knock's move began, control clock, s: the torques before
    /// it (the arm at rest) are the baseline.
    pub knock_start_s: f64,
    /// The pendulum's angular frequency as believed (calibrated), rad/s.
    pub omega_radps: f64,
    /// The pendulum's length as believed, m (the large-angle term).
    pub length_m: f64,
    /// Its viscous damping `alpha`, 1/s (calibrated; the swing's envelope
    /// decays as `exp(-alpha t / 2)`).
    pub damping_per_s: f64,
    /// The knock's direction along base `y`: `+1` or `-1`.
    pub sigma: f64,
}

/// The contact step's result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ContactCalibration {
    /// How late the torques' pulse centre shows a contact, `L + D / 2`, ms
    /// (what the measured judge subtracts).
    pub onset_offset_ms: f64,
    /// Its standard deviation (the onsets' fits and the amplitude's), ms.
    pub onset_offset_std_ms: f64,
    /// The fitted pulse length `D`, ms.
    pub pulse_ms: f64,
    /// The range of `D` within one standard deviation of the fit, ms.
    pub pulse_range_ms: [f64; 2],
    /// The torques' lag `L = onset_offset - D / 2`, ms.
    pub torque_lag_ms: f64,
    /// The same in FRI periods (the belief's unit).
    pub torque_lag_periods: f64,
    /// The robot's message period, ms (median).
    pub period_ms: f64,
    /// The tool's speed along the swing at the first contact, m/s.
    pub knock_speed_mps: f64,
    /// Between the two contacts, s.
    pub return_s: f64,
    /// The swing's amplitude between them (camera), m.
    pub amplitude_m: f64,
    /// The swing's fitted angular frequency between the contacts, rad/s.
    pub swing_omega_radps: f64,
    /// The restitution the amplitude implies, `A omega / v - 1` (0: the
    /// ball left with the tool's speed).
    pub implied_restitution: f64,
    /// Root mean square of the pulse fit's residuals along the pulse's direction, N m.
    pub residual_rms_nm: f64,
    /// The torque noise along that direction at rest, N m.
    pub noise_nm: f64,
    /// Each knock's onset offset, ms (one: this fit's own).
    pub knock_offsets_ms: Vec<f64>,
}

const WHAT: &str = "contact (knock)";
/// The whitened departure (chi-square over the 7 joints, of one sample or
/// of two consecutive ones summed) a contact must exceed; the noise alone
/// passes it about once in 10^8 samples.
pub const CONTACT_CHI2: f64 = 55.0;
/// Least samples of the arm at rest before the knock (the baseline).
pub const MIN_BASELINE: usize = 40;
/// The longest pulse searched, s.
pub const MAX_PULSE_S: f64 = 0.030;
/// The shortest pulse searched, s.
pub const MIN_PULSE_S: f64 = 0.0005;
/// Least camera detections of the swing between the contacts.
pub const MIN_SIGHTINGS: usize = 12;
/// The ball at rest: the camera's detections this long before the knock, s.
pub const REST_WINDOW_S: f64 = 2.0;
/// The tool's largest speed at the second contact, m/s (it must have stopped).
pub const MAX_STOP_SPEED_MPS: f64 = 0.005;

/// The impulse share a half-sine pulse of length `d` has delivered `s` after its start.
fn share(s: f64, d: f64) -> f64 {
    let u = (s / d).clamp(0.0, 1.0);
    0.5 * (1.0 - (std::f64::consts::PI * u).cos())
}

/// One pulse's samples along its direction: `(t_prev, t, value)`.
struct Pulse {
    samples: Vec<(f64, f64, f64)>,
    /// The first sample's time that departs from the baseline.
    first_s: f64,
}

impl Pulse {
    /// The least sum of squares over the onset grid at pulse length `d`:
    /// `(sse, c, j)`.
    fn best_at(&self, d: f64, step_s: f64) -> (f64, f64, f64) {
        let (lo, hi) = (self.first_s - MAX_PULSE_S - 0.05, self.first_s);
        let n = ((hi - lo) / step_s).ceil() as usize;
        let ss: f64 = self.samples.iter().map(|s| s.2 * s.2).sum();
        let mut best = (f64::INFINITY, f64::NAN, f64::NAN);
        for i in 0..=n {
            let c = lo + i as f64 * step_s;
            let (mut sg, mut gg) = (0.0, 0.0);
            for &(a, b, v) in &self.samples {
                let g = (share(b - c, d) - share(a - c, d)) / (b - a);
                sg += v * g;
                gg += g * g;
            }
            if gg <= 0.0 {
                continue;
            }
            let j = (sg / gg).max(0.0);
            let sse = ss - 2.0 * j * sg + j * j * gg;
            if sse < best.0 {
                best = (sse, c, j);
            }
        }
        best
    }
}

/// The onset offset, the pulse length and the lag from one knock.
///
/// # Errors
///
/// [`CalibrationError::NotFinite`] for a non-finite sample;
/// [`CalibrationError::TooFewSamples`] without a baseline of
/// [`MIN_BASELINE`] messages before the knock or with fewer than
/// [`MIN_SIGHTINGS`] detections of the swing between the contacts;
/// [`CalibrationError::ContactNotSeen`] when the torques do not show both
/// contacts; [`CalibrationError::FitFailed`] when the tool had not stopped
/// when the ball came back, never reached the position of the first
/// contact, or the pulse centre comes out more than half a period before
/// the contact or 0.2 s after it.
pub fn fit_knock(r: &KnockRecording<'_>) -> Result<ContactCalibration, CalibrationError> {
    let n = r.t_s.len().min(r.tool_y_m.len()).min(r.torques_nm.len());
    for k in 0..n {
        if !r.t_s[k].is_finite()
            || !r.tool_y_m[k].is_finite()
            || r.torques_nm[k].iter().any(|v| !v.is_finite())
        {
            return Err(CalibrationError::NotFinite {
                what: WHAT,
                index: k,
            });
        }
    }
    let usable = r.omega_radps.is_finite()
        && r.omega_radps > 0.0
        && r.damping_per_s.is_finite()
        && r.knock_start_s.is_finite();
    if !usable {
        return Err(CalibrationError::FitFailed {
            what: WHAT,
            reason: "the pendulum's frequency or the knock's start is not a number".into(),
        });
    }
    let (t, y, tau) = (&r.t_s[..n], &r.tool_y_m[..n], &r.torques_nm[..n]);
    let before = t.partition_point(|&s| s < r.knock_start_s);
    if before < MIN_BASELINE {
        return Err(CalibrationError::TooFewSamples {
            what: WHAT,
            got: before,
            need: MIN_BASELINE,
        });
    }
    // The baseline: each joint's mean and spread with the arm at rest.
    let mut mean = [0.0; 7];
    for s in &tau[..before] {
        for (m, v) in mean.iter_mut().zip(s) {
            *m += v / before as f64;
        }
    }
    let mut sd = [0.0; 7];
    for s in &tau[..before] {
        for ((d, v), m) in sd.iter_mut().zip(s).zip(&mean) {
            *d += (v - m).powi(2) / (before - 1) as f64;
        }
    }
    for d in &mut sd {
        *d = d.sqrt().max(1e-6);
    }
    // A sample's whitened departure, or the pair's with the one before
    // (a pulse split between two messages), whichever is larger.
    let chi2 = |k: usize| -> f64 {
        let one: f64 = (0..7)
            .map(|j| ((tau[k][j] - mean[j]) / sd[j]).powi(2))
            .sum();
        let pair: f64 = if k > 0 {
            (0..7)
                .map(|j| {
                    (tau[k][j] + tau[k - 1][j] - 2.0 * mean[j]).powi(2) / (2.0 * sd[j] * sd[j])
                })
                .sum()
        } else {
            0.0
        };
        one.max(pair)
    };
    let mut periods: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
    periods.sort_by(f64::total_cmp);
    let period_s = periods.get(periods.len() / 2).copied().unwrap_or(f64::NAN);
    if period_s.is_nan() || period_s <= 0.0 {
        return Err(CalibrationError::TooFewSamples {
            what: WHAT,
            got: n,
            need: MIN_BASELINE + 2,
        });
    }
    // The two contacts: the first departure after the start, and the first
    // a quarter period of the swing after the first pulse.
    let half_swing_s = std::f64::consts::PI / r.omega_radps;
    let first = (before..n).find(|&k| chi2(k) > CONTACT_CHI2);
    let second = first.and_then(|k1| {
        let after = t[k1] + 0.25 * half_swing_s;
        (k1..n).find(|&k| t[k] >= after && chi2(k) > CONTACT_CHI2)
    });
    let (Some(k1), Some(k2)) = (first, second) else {
        return Err(CalibrationError::ContactNotSeen {
            seen: usize::from(first.is_some()),
        });
    };
    let span = (MAX_PULSE_S / period_s).ceil() as usize + 2;
    let pulse = |k0: usize| -> Pulse {
        let (a, b) = (k0.saturating_sub(2).max(1), (k0 + span).min(n - 1));
        // Its direction: the departures of the pulse's strongest samples.
        let mut dir = [0.0; 7];
        for s in &tau[k0..=(k0 + 2).min(b)] {
            for (d, (v, m)) in dir.iter_mut().zip(s.iter().zip(&mean)) {
                *d += v - m;
            }
        }
        let norm = dir.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-12);
        let samples = (a..=b)
            .map(|k| {
                let v: f64 = (0..7).map(|j| (tau[k][j] - mean[j]) * dir[j] / norm).sum();
                (t[k - 1], t[k], v)
            })
            .collect();
        Pulse {
            samples,
            first_s: t[k0],
        }
    };
    let pulses = [pulse(k1), pulse(k2)];
    // The noise along the first pulse's direction at rest.
    let dir1 = {
        let mut dir = [0.0; 7];
        for s in &tau[k1..=(k1 + 2).min(n - 1)] {
            for (d, (v, m)) in dir.iter_mut().zip(s.iter().zip(&mean)) {
                *d += v - m;
            }
        }
        let norm = dir.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-12);
        dir.map(|d| d / norm)
    };
    let noise_nm = {
        let var: f64 = tau[..before]
            .iter()
            .map(|s| {
                (0..7)
                    .map(|j| (s[j] - mean[j]) * dir1[j])
                    .sum::<f64>()
                    .powi(2)
            })
            .sum::<f64>()
            / (before - 1) as f64;
        var.sqrt()
    };
    // The grid: D from MIN_PULSE_S to MAX_PULSE_S by 0.25 ms, onsets by 0.05 ms.
    let d_steps = ((MAX_PULSE_S - MIN_PULSE_S) / 2.5e-4).round() as usize;
    let mut profile = Vec::with_capacity(d_steps + 1);
    for i in 0..=d_steps {
        let d = MIN_PULSE_S + i as f64 * 2.5e-4;
        let a = pulses[0].best_at(d, 5e-5);
        let b = pulses[1].best_at(d, 5e-5);
        profile.push((a.0 + b.0, d, a.1, b.1));
    }
    let &(sse, pulse_s, c1, c2) =
        profile
            .iter()
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .ok_or(CalibrationError::FitFailed {
                what: WHAT,
                reason: "no pulse length fits".into(),
            })?;
    let var = noise_nm.powi(2).max(1e-12);
    let within: Vec<f64> = profile
        .iter()
        .filter(|p| p.0 - sse <= var)
        .map(|p| p.1)
        .collect();
    let pulse_range_s = [
        within.iter().copied().fold(pulse_s, f64::min),
        within.iter().copied().fold(pulse_s, f64::max),
    ];
    let used: usize = pulses.iter().map(|p| p.samples.len()).sum();
    let residual_rms_nm = (sse.max(0.0) / used as f64).sqrt();
    // Each onset's spread: the onsets within one standard deviation of the
    // fit at the fitted pulse length.
    let onset_std = |p: &Pulse, c_best: f64| -> f64 {
        let best = p.best_at(pulse_s, 5e-5).0;
        let (lo, hi) = (p.first_s - MAX_PULSE_S - 0.05, p.first_s);
        let steps = ((hi - lo) / 5e-5).ceil() as usize;
        let ss: f64 = p.samples.iter().map(|s| s.2 * s.2).sum();
        let mut spread: f64 = 0.0;
        for i in 0..=steps {
            let c = lo + i as f64 * 5e-5;
            let (mut sg, mut gg) = (0.0, 0.0);
            for &(a, b, v) in &p.samples {
                let g = (share(b - c, pulse_s) - share(a - c, pulse_s)) / (b - a);
                sg += v * g;
                gg += g * g;
            }
            if gg <= 0.0 {
                continue;
            }
            let j = (sg / gg).max(0.0);
            if ss - 2.0 * j * sg + j * j * gg - best <= var {
                spread = spread.max((c - c_best).abs());
            }
        }
        spread.max(0.25 * 5e-5)
    };
    let (c1_std, c2_std) = (onset_std(&pulses[0], c1), onset_std(&pulses[1], c2));
    let return_s = c2 - c1;
    // The tool had stopped before the ball came back: where it stood (its
    // track from 0.3 to 0.2 s before the second onset, before the touch
    // whatever the lag up to 0.2 s; a compliant arm gives way at the touch).
    let (a, b) = (
        t.partition_point(|&s| s < c2 - 0.3),
        t.partition_point(|&s| s < c2 - 0.2),
    );
    if b < a + 2 {
        return Err(CalibrationError::FitFailed {
            what: WHAT,
            reason: "no tool track before the ball came back".into(),
        });
    }
    let m = (b - a) as f64;
    let (tm, ym) = (
        t[a..b].iter().sum::<f64>() / m,
        y[a..b].iter().sum::<f64>() / m,
    );
    let (mut stt, mut sty) = (0.0, 0.0);
    for (ti, yi) in t[a..b].iter().zip(&y[a..b]) {
        stt += (ti - tm).powi(2);
        sty += (ti - tm) * (yi - ym);
    }
    let stop_speed = if stt > 0.0 { (sty / stt).abs() } else { 0.0 };
    if stop_speed > MAX_STOP_SPEED_MPS {
        return Err(CalibrationError::FitFailed {
            what: WHAT,
            reason: format!(
                "the tool still moved at {stop_speed:.3} m/s before the ball came back (it must \
                 stand still)"
            ),
        });
    }
    let y_stop = ym;
    // The ball at rest before the knock, as the camera sees it.
    let resting: Vec<f64> = r
        .sightings
        .iter()
        .filter(|s| {
            s.t_s < r.knock_start_s && s.t_s >= r.knock_start_s - REST_WINDOW_S && s.x_m.is_finite()
        })
        .map(|s| s.x_m)
        .collect();
    if resting.len() < MIN_SIGHTINGS {
        return Err(CalibrationError::TooFewSamples {
            what: "contact (knock): the ball at rest before the knock",
            got: resting.len(),
            need: MIN_SIGHTINGS,
        });
    }
    let rest_m = resting.iter().sum::<f64>() / resting.len() as f64;
    // The swing between the contacts as the camera sees it: its amplitude.
    let free: Vec<&Sighting> = r
        .sightings
        .iter()
        .filter(|s| s.t_s.is_finite() && s.x_m.is_finite())
        .filter(|s| s.t_s > c1 + 0.1 && s.t_s < c2 - 0.05)
        .collect();
    if free.len() < MIN_SIGHTINGS {
        return Err(CalibrationError::TooFewSamples {
            what: "contact (knock): the swing between the contacts",
            got: free.len(),
            need: MIN_SIGHTINGS,
        });
    }
    // The damped swing from the first contact (its envelope referred to
    // the first onset: the camera's time offset moves it by exp(-alpha
    // delta / 2), negligible), its frequency fitted too: within 10% of the
    // belief, the least squares of the linear rest of the model.
    let half_alpha = 0.5 * r.damping_per_s.max(0.0);
    let fit_at = |w: f64| -> Option<(f64, [f64; 2])> {
        let mut ata = nalgebra::Matrix2::<f64>::zeros();
        let mut atb = nalgebra::Vector2::<f64>::zeros();
        let row = |s: &Sighting| {
            let tau = s.t_s - c1;
            let (p, env) = (w * tau, (-half_alpha * tau).exp());
            nalgebra::Vector2::new(env * p.sin(), env * p.cos())
        };
        for s in &free {
            let a = row(s);
            ata += a * a.transpose();
            atb += a * (s.x_m - rest_m);
        }
        let c = ata.lu().solve(&atb)?;
        let sse = free
            .iter()
            .map(|s| (s.x_m - rest_m - row(s).dot(&c)).powi(2))
            .sum();
        Some((sse, [c[0], c[1]]))
    };
    let w0 = (r.omega_radps.powi(2) - half_alpha.powi(2))
        .max(1e-6)
        .sqrt();
    let grid = (0..=40).map(|i| w0 * (0.9 + 0.005 * f64::from(i)));
    let (mut lo, mut hi) = {
        let best = grid
            .filter_map(|w| fit_at(w).map(|(e, _)| (e, w)))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .ok_or(CalibrationError::FitFailed {
                what: WHAT,
                reason: "the swing between the contacts does not fit a sine".into(),
            })?;
        (best.1 - 0.005 * w0, best.1 + 0.005 * w0)
    };
    let g = 0.5 * (5f64.sqrt() - 1.0);
    for _ in 0..40 {
        let (a, b) = (hi - g * (hi - lo), lo + g * (hi - lo));
        let ea = fit_at(a).map_or(f64::INFINITY, |f| f.0);
        let eb = fit_at(b).map_or(f64::INFINITY, |f| f.0);
        if ea < eb {
            hi = b;
        } else {
            lo = a;
        }
    }
    let w_seen = 0.5 * (lo + hi);
    let (sse_swing, coef) = fit_at(w_seen).ok_or(CalibrationError::FitFailed {
        what: WHAT,
        reason: "the swing between the contacts does not fit a sine".into(),
    })?;
    let amplitude_m = coef[0].hypot(coef[1]);
    // The frequency the geometry takes is the believed (calibrated) one,
    // slowed for this swing's angle `theta0` by `theta0^2 / 16`: near the
    // half period the return's place moves by `A T` per rad/s, and the
    // camera's own fit of a little over a third of a period is good to a
    // few tenths of a percent only (reported as `swing_omega_radps`).
    let theta0 = amplitude_m / r.length_m.max(0.1);
    let w = w0 * (1.0 - theta0 * theta0 / 16.0);
    if (w_seen / w - 1.0).abs() > 0.01 {
        return Err(CalibrationError::FitFailed {
            what: WHAT,
            reason: format!(
                "the ball swung at {w_seen:.4} rad/s between the contacts, the pendulum is \
                 believed to swing at {w:.4} rad/s: more than 1% apart (calibrate the pendulum)"
            ),
        });
    }
    let amp_resid = (sse_swing / (free.len() - 3).max(1) as f64).sqrt();
    let amp_std = amp_resid * (2.0 / free.len() as f64).sqrt();
    // The ball's displacement from its rest when it came back.
    let sin = (-half_alpha * return_s).exp() * (w * return_s).sin();
    let target = y_stop - r.sigma * amplitude_m * sin;
    // The last crossing of the target before the first onset, on the way in.
    let k_cross = (1..=t.partition_point(|&s| s <= c1 + 0.5 * period_s).min(n - 1))
        .rev()
        .find(|&k| {
            let (a, b) = (r.sigma * (y[k - 1] - target), r.sigma * (y[k] - target));
            a < 0.0 && b >= 0.0
        })
        .ok_or(CalibrationError::FitFailed {
            what: WHAT,
            reason: format!(
                "the tool never reached y = {target:.4} m (the first contact's place by the \
                 ball's return) before the first contact was seen"
            ),
        })?;
    let (ya, yb) = (y[k_cross - 1], y[k_cross]);
    let t1 = t[k_cross - 1] + (target - ya) / (yb - ya) * (t[k_cross] - t[k_cross - 1]);
    let knock_speed_mps = (yb - ya).abs() / (t[k_cross] - t[k_cross - 1]);
    let lag_s = c1 - t1;
    let onset_offset_s = lag_s + 0.5 * pulse_s;
    if !(-0.5 * period_s..=0.2).contains(&onset_offset_s) {
        return Err(CalibrationError::FitFailed {
            what: WHAT,
            reason: format!(
                "the torques' pulse centre came out {:.1} ms after the contact (the ball was not \
                 still, or its swing was misread)",
                onset_offset_s * 1e3
            ),
        });
    }
    // Along the pulse lengths the fit cannot tell apart (within one
    // standard deviation), how far the offset moves.
    let ridge_s = profile
        .iter()
        .filter(|p| p.0 - sse <= var)
        .map(|&(_, d, a, b)| {
            let ret = b - a;
            let sin_d = (-half_alpha * ret).exp() * (w * ret).sin();
            let moved = r.sigma * amplitude_m * (sin_d - sin);
            (a + 0.5 * d - (c1 + 0.5 * pulse_s) + moved / knock_speed_mps.max(1e-6)).abs()
        })
        .fold(0.0, f64::max);
    let onset_offset_std_s = (c1_std.powi(2)
        + ridge_s.powi(2)
        + (amp_std * sin / knock_speed_mps.max(1e-6)).powi(2)
        + (amplitude_m * w * (w * return_s).cos() * (c2_std.powi(2) + c1_std.powi(2)).sqrt()
            / knock_speed_mps.max(1e-6))
        .powi(2))
    .sqrt();
    Ok(ContactCalibration {
        onset_offset_ms: onset_offset_s * 1e3,
        onset_offset_std_ms: onset_offset_std_s * 1e3,
        pulse_ms: pulse_s * 1e3,
        pulse_range_ms: [pulse_range_s[0] * 1e3, pulse_range_s[1] * 1e3],
        torque_lag_ms: lag_s * 1e3,
        torque_lag_periods: lag_s / period_s,
        period_ms: period_s * 1e3,
        knock_speed_mps,
        return_s,
        amplitude_m,
        implied_restitution: amplitude_m * w / knock_speed_mps.max(1e-6) - 1.0,
        swing_omega_radps: w_seen,
        residual_rms_nm,
        noise_nm,
        knock_offsets_ms: vec![onset_offset_s * 1e3],
    })
}

/// Several knocks' fits as one: the figures averaged, the onset offset's
/// standard deviation the larger of the knocks' spread and their own
/// (each over the square root of their number); the knocks' offsets kept.
/// `None` without a knock.
pub fn combine(knocks: &[ContactCalibration]) -> Option<ContactCalibration> {
    let first = knocks.first()?;
    let n = knocks.len() as f64;
    let mean = |f: fn(&ContactCalibration) -> f64| knocks.iter().map(f).sum::<f64>() / n;
    let offset = mean(|k| k.onset_offset_ms);
    let spread = if knocks.len() > 1 {
        (knocks
            .iter()
            .map(|k| (k.onset_offset_ms - offset).powi(2))
            .sum::<f64>()
            / (n - 1.0))
            .sqrt()
    } else {
        0.0
    };
    let own = (knocks
        .iter()
        .map(|k| k.onset_offset_std_ms.powi(2))
        .sum::<f64>()
        / n)
        .sqrt();
    let pulse = mean(|k| k.pulse_ms);
    let lag = offset - 0.5 * pulse;
    Some(ContactCalibration {
        onset_offset_ms: offset,
        onset_offset_std_ms: spread.max(own) / n.sqrt(),
        pulse_ms: pulse,
        pulse_range_ms: [
            knocks
                .iter()
                .map(|k| k.pulse_range_ms[0])
                .fold(f64::INFINITY, f64::min),
            knocks
                .iter()
                .map(|k| k.pulse_range_ms[1])
                .fold(0.0, f64::max),
        ],
        torque_lag_ms: lag,
        torque_lag_periods: lag / first.period_ms.max(1e-6),
        period_ms: mean(|k| k.period_ms),
        knock_speed_mps: mean(|k| k.knock_speed_mps),
        return_s: mean(|k| k.return_s),
        amplitude_m: mean(|k| k.amplitude_m),
        swing_omega_radps: mean(|k| k.swing_omega_radps),
        implied_restitution: mean(|k| k.implied_restitution),
        residual_rms_nm: mean(|k| k.residual_rms_nm),
        noise_nm: mean(|k| k.noise_nm),
        knock_offsets_ms: knocks.iter().map(|k| k.onset_offset_ms).collect(),
    })
}

impl ContactCalibration {
    /// The beliefs to lay over a lab's whose FRI period is `period_ms`:
    /// `(torque_lag_periods, contact_pulse_ms)` keeping their sum `L + D /
    /// 2` (a lag that would come out negative is 0 and the pulse twice the
    /// offset; both within the beliefs' ranges: at most 10 periods, 0.5-50
    /// ms).
    pub fn beliefs(&self, period_ms: f64) -> (f64, f64) {
        let offset = self.onset_offset_ms.max(0.25);
        let pulse = self.pulse_ms.clamp(0.5, (2.0 * offset).min(50.0));
        let lag_ms = (offset - 0.5 * pulse).max(0.0);
        ((lag_ms / period_ms.max(1e-3)).min(10.0), pulse)
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::sim::world::contact::{BallOnTool, Contact, external_torques};
    use crate::sim::world::pendulum::{Disc, TruePendulum, TruePendulumParams};

    /// A knock as the world makes it (its ball, contact and torque model):
    /// a 1.93 m pendulum hanging still at y = 0 (restitution `e`), a
    /// face-on disc moving along +y in a 0.6 s minimum-jerk move from 15 cm
    /// before the touch to 2 cm past it, from t = 0.5 s (0.33 m/s at the
    /// touch); the robot reports
    /// every 5 ms the pulse's mean over its period `lag_s` late, plus 0.2 N m
    /// of noise; the camera sees the ball at 60 Hz with 0.5 mm of noise,
    /// stamped `stamp_error_s` late. The tool point sits 0.1 m from the
    /// disc's centre along y (the geometry must cancel).
    struct Knock {
        t_s: Vec<f64>,
        tool_y_m: Vec<f64>,
        torques_nm: Vec<[f64; 7]>,
        sightings: Vec<Sighting>,
        omega_radps: f64,
    }

    fn knock(e: f64, lag_s: f64, pulse_s: f64, stamp_error_s: f64, seed: u64) -> Knock {
        let length_m = 1.93;
        let p = TruePendulumParams {
            pivot_m: Vector3::new(0.6, 0.0, 0.3 + length_m),
            length_m,
            gravity_mps2: 9.81,
            damping_per_s: 0.03,
            drag_per_m: 0.0,
            friction_mps2: 0.0,
            disturbance_mps2: 0.0,
            ball_radius_m: 0.0335,
            restitution: e,
        };
        let mut ball = TruePendulum::held_at(p, 0.0, 0.0, 0.0, 1);
        ball.release(0.0);
        let r = 0.0335;
        let (y0, y1, start, dur) = (-r - 0.15, -r + 0.02, 0.5, 0.6);
        let disc_y = |t: f64| {
            let u = ((t - start) / dur).clamp(0.0, 1.0);
            y0 + (y1 - y0) * u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)
        };
        let disc = |t: f64| Disc {
            centre_m: Vector3::new(0.6, disc_y(t), 0.3),
            normal: Vector3::y(),
            radius_m: 0.05,
        };
        let mut on = BallOnTool::new(ball);
        on.drop_at = Some(0.0);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let q = [0.3, 0.6, -0.2, -1.2, 0.1, 0.9, 0.0];
        let mut contacts: Vec<Option<Contact>> = Vec::new();
        let mut out = Knock {
            t_s: Vec::new(),
            tool_y_m: Vec::new(),
            torques_nm: Vec::new(),
            sightings: Vec::new(),
            omega_radps: (9.81 / length_m).sqrt(),
        };
        let (dt, period) = (0.001, 0.005);
        let mut last_msg = 0.0;
        let mut next_frame = 0.0;
        let mut k = 0_u32;
        while f64::from(k) * dt < 3.4 {
            k += 1;
            let t = f64::from(k) * dt;
            on.advance(t);
            if let Some(c) = on.meet(t, disc(t), dt, 0.057, pulse_s) {
                contacts.push(Some(c));
            }
            if k % 5 == 0 {
                let tau = external_torques(&q, &contacts, last_msg - lag_s, t - lag_s, &mut rng);
                last_msg = t;
                out.t_s.push(t);
                out.tool_y_m.push(disc_y(t) + 0.1);
                out.torques_nm.push(tau);
            }
            if t >= next_frame {
                next_frame += 1.0 / 60.0;
                out.sightings.push(Sighting {
                    t_s: t + stamp_error_s,
                    x_m: on.ball.ball_position_m().y
                        + 5e-4 * crate::sim::camera::gaussian(&mut rng),
                });
            }
        }
        let _ = period;
        out
    }

    fn fit(k: &Knock) -> Result<ContactCalibration, CalibrationError> {
        fit_knock(&KnockRecording {
            t_s: &k.t_s,
            tool_y_m: &k.tool_y_m,
            torques_nm: &k.torques_nm,
            sightings: &k.sightings,
            knock_start_s: 0.5,
            omega_radps: k.omega_radps,
            length_m: 1.93,
            damping_per_s: 0.03,
            sigma: 1.0,
        })
    }

    #[test]
    fn a_knock_learns_the_torques_onset_offset_whatever_the_cameras_clock() {
        // Two periods' lag and a 6 ms pulse: the judge subtracts 13 ms.
        let mut fits = Vec::new();
        for (seed, stamp_error_s) in [(1, 0.0), (2, 0.045), (3, -0.02)] {
            let mut k = knock(0.0, 0.010, 0.006, stamp_error_s, seed);
            // Before the still window the ball swung widely (until a hand
            // stopped it): not its rest.
            let swung: Vec<Sighting> = (0..120)
                .map(|i| {
                    let t = -4.0 + f64::from(i) / 60.0;
                    Sighting {
                        t_s: t,
                        x_m: 0.4 * (2.25 * t).sin(),
                    }
                })
                .collect();
            k.sightings.splice(0..0, swung);
            let c = fit(&k).unwrap();
            // Within 3 ms (the default beliefs, a period and a 4 ms
            // pulse, would subtract 7 ms), and within 3 of its standard
            // deviations.
            let err = c.onset_offset_ms - 13.0;
            assert!(
                err.abs() < 3.0 && err.abs() < 3.0 * c.onset_offset_std_ms,
                "seed {seed}: {c:?}"
            );
            assert!((c.period_ms - 5.0).abs() < 1e-9, "{c:?}");
            assert!(c.implied_restitution.abs() < 0.05, "{c:?}");
            // The beliefs keep the sum.
            let (lag_periods, pulse_ms) = c.beliefs(c.period_ms);
            let sum = lag_periods * c.period_ms + 0.5 * pulse_ms;
            assert!((sum - c.onset_offset_ms).abs() < 1e-9, "{sum} vs {c:?}");
            fits.push(c);
        }
        // Three knocks as one: the mean, its spread over the square root.
        let all = combine(&fits).unwrap();
        let mean = fits.iter().map(|c| c.onset_offset_ms).sum::<f64>() / 3.0;
        assert!((all.onset_offset_ms - mean).abs() < 1e-9);
        assert_eq!(all.knock_offsets_ms.len(), 3);
        assert!(all.onset_offset_std_ms > 0.0);
        assert!((all.torque_lag_ms + 0.5 * all.pulse_ms - all.onset_offset_ms).abs() < 1e-9);
        assert!(combine(&[]).is_none());
        // No lag and a 3 ms pulse: 1.5 ms; a bouncing ball (the camera's
        // amplitude carries the restitution).
        let c = fit(&knock(0.5, 0.0, 0.003, 0.03, 4)).unwrap();
        assert!((c.onset_offset_ms - 1.5).abs() < 3.0, "{c:?}");
        assert!((c.implied_restitution - 0.5).abs() < 0.1, "{c:?}");
    }

    #[test]
    fn a_knock_without_the_return_or_with_bad_samples_is_refused() {
        let mut k = knock(0.0, 0.005, 0.004, 0.0, 5);
        // The record ends before the ball comes back.
        let cut = k.t_s.partition_point(|&t| t < 2.0);
        let short = Knock {
            t_s: k.t_s[..cut].to_vec(),
            tool_y_m: k.tool_y_m[..cut].to_vec(),
            torques_nm: k.torques_nm[..cut].to_vec(),
            sightings: k.sightings.clone(),
            omega_radps: k.omega_radps,
        };
        assert!(matches!(
            fit(&short),
            Err(CalibrationError::ContactNotSeen { seen: 1 })
        ));
        // Torques without any contact: none seen.
        let quiet = knock(0.0, 0.005, 0.004, 0.0, 6);
        let mut q2 = Knock {
            torques_nm: quiet.torques_nm[..10].repeat(quiet.t_s.len() / 10 + 1)[..quiet.t_s.len()]
                .to_vec(),
            ..quiet
        };
        q2.sightings.clear();
        assert!(matches!(
            fit(&q2),
            Err(CalibrationError::ContactNotSeen { seen: 0 })
        ));
        // A NaN torque.
        k.torques_nm[100][3] = f64::NAN;
        assert!(matches!(
            fit(&k),
            Err(CalibrationError::NotFinite { index: 100, .. })
        ));
    }
}
