#![doc = include_str!("README.md")]

pub mod figure;

use crate::check::ParamError;
use crate::ekf::{Ekf, EkfError, EkfParams, MeasureOutcome, Prediction, ProcessNoiseModel};
use crate::params::Scenario;
use crate::pendulum::{PendulumGeometry, PendulumModel};
use serde::Serialize;
use std::path::Path;

/// Why a recording cannot be tuned on.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum TuneError {
    /// The CSV reader refused the text (at `line`, when it knows).
    #[error("recording: {reason}")]
    Csv {
        /// The line, 1-based, when the reader knows it.
        line: Option<u64>,
        /// The CSV reader's message.
        reason: String,
    },
    /// No header line.
    #[error("recording: empty file")]
    Empty,
    /// Neither the trial recording's nor the plain series' columns.
    #[error(
        "recording: needs columns measured_t_s and measured_x_m (a trial recording) or t_s and x_m"
    )]
    MissingColumns,
    /// A row with fewer cells than the header.
    #[error("recording: line {line}: too few columns")]
    TooFewColumns {
        /// The line, 1-based.
        line: u64,
    },
    /// A cell that is not a number, or not a finite one.
    #[error(
        "recording: line {line}: column {column:?} = {raw:?} is not a {}number",
        if *parsed { "finite " } else { "" }
    )]
    BadNumber {
        /// The line, 1-based.
        line: u64,
        /// The column's name (from the header).
        column: String,
        /// The cell as written.
        raw: String,
        /// True when it parsed, as NaN or an infinity.
        parsed: bool,
    },
    /// A capture time before the previous one.
    #[error("recording: line {line}: capture time {t_s} goes back before {previous_s}")]
    TimeGoesBack {
        /// The line, 1-based.
        line: u64,
        /// The capture time on it, seconds.
        t_s: f64,
        /// The previous capture time, seconds.
        previous_s: f64,
    },
    /// A trial recording that never gets past arming: no release.
    #[error(
        "recording: the trial recording never leaves the states before the release \
         (idle, arming, armed): the ball was not released"
    )]
    NotReleased,
    /// Too few measurements to estimate two noise parameters.
    #[error("recording has {0} measurements; at least {MIN_MEASUREMENTS} are needed")]
    TooShort(usize),
    /// The ball does not swing in the recording: nothing to tell the process from
    /// the measurement noise.
    #[error(
        "recording shows no swing: the lateral position spans {:.1} mm, less than {:.1} mm \
         (a hanging or held ball cannot be tuned on; record a released swing)",
        1e3 * span_m,
        1e3 * needed_m
    )]
    NoMotion {
        /// Largest minus smallest lateral position, metres.
        span_m: f64,
        /// The span a swing must exceed, metres.
        needed_m: f64,
    },
    /// Bad parameters.
    #[error(transparent)]
    Params(#[from] ParamError),
    /// The filter refused the data.
    #[error(transparent)]
    Filter(#[from] EkfError),
}

/// The CSV reader's error, with its line when it knows it.
fn csv_error(e: csv::Error) -> TuneError {
    TuneError::Csv {
        line: e.position().map(csv::Position::line),
        reason: e.to_string(),
    }
}

/// Fewest measurements `tune` works on (about 10 s at 30 fps).
pub const MIN_MEASUREMENTS: usize = 300;

/// Smallest lateral span (max - min) of a recording `tune` accepts as a swing, metres.
pub const MIN_SWING_SPAN_M: f64 = 0.01;

/// Trial states after the release (`trial_state` in a service recording).
const RELEASED_STATES: [&str; 5] = ["released", "tracking", "intercepting", "holding", "done"];

/// Lateral measurements of the swinging ball: capture times and positions.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Series {
    /// Capture times, seconds, strictly increasing.
    pub t_s: Vec<f64>,
    /// Lateral positions `l sin(phi)`, metres.
    pub z_m: Vec<f64>,
}

impl Series {
    /// Reads a CSV recording: either the service's trial recording (columns
    /// `measured_t_s`, `measured_x_m` and optionally `measured_valid` and
    /// `trial_state`, one row per control step, each measurement repeated until the
    /// next) or a plain file with columns `t_s` and `x_m` (one row per measurement).
    ///
    /// From a trial recording only the measurements captured after the ball was
    /// released are kept (the first row in a state after `armed` gives the release
    /// time): while the magnet holds it the ball does not follow the pendulum's
    /// dynamics. Rows without a measurement (`measured_valid` 0) are skipped; a
    /// measurement that is not a finite number is an error naming the line.
    ///
    /// # Errors
    ///
    /// [`TuneError::Csv`] when the CSV reader refuses the text; [`TuneError::Empty`],
    /// [`TuneError::MissingColumns`], [`TuneError::TooFewColumns`],
    /// [`TuneError::BadNumber`] or [`TuneError::TimeGoesBack`] naming the bad line;
    /// [`TuneError::NotReleased`] for a trial recording without a release.
    pub fn from_csv(text: &str) -> Result<Self, TuneError> {
        let mut reader = csv::ReaderBuilder::new()
            .comment(Some(b'#'))
            .trim(csv::Trim::All)
            .flexible(true)
            .from_reader(text.as_bytes());
        let names: Vec<String> = reader
            .headers()
            .map_err(csv_error)?
            .iter()
            .map(str::to_owned)
            .collect();
        if names.iter().all(String::is_empty) {
            return Err(TuneError::Empty);
        }
        let find = |n: &str| names.iter().position(|h| *h == n);
        let (ti, zi, vi, si) = match (find("measured_t_s"), find("measured_x_m")) {
            (Some(t), Some(z)) => (t, z, find("measured_valid"), find("trial_state")),
            _ => match (find("t_s"), find("x_m")) {
                (Some(t), Some(z)) => (t, z, None, None),
                _ => {
                    return Err(TuneError::MissingColumns);
                }
            },
        };
        let step_t = find("t_s").filter(|_| si.is_some());
        let mut s = Series::default();
        // Trial recordings: the release time, once a row is past `armed`.
        let mut released_at: Option<f64> = None;
        let mut saw_state = false;
        for row in reader.records() {
            let cells = row.map_err(csv_error)?;
            let no = cells.position().map_or(0, csv::Position::line);
            let cell = |i: usize| -> Result<f64, TuneError> {
                let raw = cells.get(i).ok_or(TuneError::TooFewColumns { line: no })?;
                let bad = |parsed: bool| TuneError::BadNumber {
                    line: no,
                    column: names.get(i).map_or("?", String::as_str).to_owned(),
                    raw: raw.to_owned(),
                    parsed,
                };
                let v = raw.parse::<f64>().map_err(|_| bad(false))?;
                if v.is_finite() { Ok(v) } else { Err(bad(true)) }
            };
            if let Some(si) = si {
                saw_state = true;
                let state = cells.get(si).unwrap_or("");
                if released_at.is_none() && RELEASED_STATES.contains(&state) {
                    // The first row after the release: its step time, or failing
                    // that the measurement it carries.
                    released_at = Some(match step_t {
                        Some(i) => cell(i)?,
                        None => f64::NEG_INFINITY,
                    });
                }
            }
            if let Some(v) = vi {
                let valid = cells.get(v).unwrap_or("");
                if matches!(valid, "0" | "false" | "") {
                    continue;
                }
            }
            let (t, z) = (cell(ti)?, cell(zi)?);
            if saw_state {
                match released_at {
                    // Captured while the magnet still held the ball.
                    Some(r) if t >= r => {}
                    _ => continue,
                }
            }
            match s.t_s.last() {
                Some(&last) if t == last => continue, // repeated until the next frame
                Some(&last) if t < last => {
                    return Err(TuneError::TimeGoesBack {
                        line: no,
                        t_s: t,
                        previous_s: last,
                    });
                }
                _ => {}
            }
            s.t_s.push(t);
            s.z_m.push(z);
        }
        if saw_state && released_at.is_none() {
            return Err(TuneError::NotReleased);
        }
        Ok(s)
    }

    /// Refuses a series `tune` cannot work on: too few measurements, or a ball
    /// that does not swing (the lateral span must exceed [`MIN_SWING_SPAN_M`] and
    /// twenty times the noise seen in the second differences).
    ///
    /// # Errors
    ///
    /// [`TuneError::TooShort`] with fewer than [`MIN_MEASUREMENTS`] measurements;
    /// [`TuneError::NoMotion`] when the lateral span is too small for the noise.
    pub fn check_tunable(&self) -> Result<(), TuneError> {
        if self.len() < MIN_MEASUREMENTS {
            return Err(TuneError::TooShort(self.len()));
        }
        let (lo, hi) = self
            .z_m
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &z| {
                (a.min(z), b.max(z))
            });
        // White noise of std r gives second differences of std r sqrt(6); the
        // swing's own curvature adds little at camera rates.
        let mut d2: Vec<f64> = self
            .z_m
            .windows(3)
            .map(|w| (w[2] - 2.0 * w[1] + w[0]).abs())
            .collect();
        d2.sort_by(f64::total_cmp);
        let median = d2.get(d2.len() / 2).copied().unwrap_or(0.0);
        // Median of |N(0, 6 r^2)| is 0.674 sqrt(6) r.
        let noise = median / (0.674 * 6f64.sqrt());
        let needed = MIN_SWING_SPAN_M.max(20.0 * noise);
        let span = hi - lo;
        if span > needed {
            Ok(())
        } else {
            Err(TuneError::NoMotion {
                span_m: span,
                needed_m: needed,
            })
        }
    }

    /// Number of measurements.
    pub fn len(&self) -> usize {
        self.t_s.len()
    }

    /// True when there is no measurement.
    pub fn is_empty(&self) -> bool {
        self.t_s.is_empty()
    }

    /// Mean spacing of the capture times, seconds.
    pub fn mean_interval_s(&self) -> f64 {
        match (self.t_s.first(), self.t_s.last()) {
            (Some(a), Some(b)) if self.len() > 1 => (b - a) / (self.len() - 1) as f64,
            _ => f64::NAN,
        }
    }

    /// Every `stride`-th measurement from the `offset`-th.
    pub fn thinned(&self, stride: usize, offset: usize) -> Self {
        let stride = stride.max(1);
        Self {
            t_s: self
                .t_s
                .iter()
                .skip(offset)
                .step_by(stride)
                .copied()
                .collect(),
            z_m: self
                .z_m
                .iter()
                .skip(offset)
                .step_by(stride)
                .copied()
                .collect(),
        }
    }
}

/// The shortest spacing of the measurements the likelihood is taken over,
/// seconds: a camera faster than 30 fps (the paper's) is tuned on its frames
/// thinned to at most this rate (`TuneReport::stride`). A detector's errors
/// are correlated from frame to frame: the ball crosses the pixel grid
/// slowly, and blur and the tracked window change slowly (lag-1
/// autocorrelation 0.3-0.65 at 60 fps on rendered frames, under 0.3 at
/// every second frame). A filter can follow such errors if they are dense,
/// and over a few short recordings the most likely fit then trades
/// measurement noise for process noise: three 60 fps trials once gave
/// measurement noise 0.134 mm (the detector's truth 0.193 mm) and
/// `accel_psd` 7.1e-5 (truth 0), a filter that missed 14 trials in 100 (by
/// the gate and by never committing) where the lab's own made none. Thinned
/// to every second frame, the same recordings give 0.192 mm and 7e-13.
pub const MIN_LIKELIHOOD_SPACING_S: f64 = 1.0 / 30.0;

/// The stride that thins measurements `mean_interval_s` apart to at least
/// [`MIN_LIKELIHOOD_SPACING_S`] (rounded to the nearest; at least 1).
pub fn likelihood_stride(mean_interval_s: f64) -> usize {
    let k = (MIN_LIKELIHOOD_SPACING_S / mean_interval_s).round();
    if k.is_finite() && k >= 1.0 {
        (k as usize).min(16)
    } else {
        1
    }
}

/// The two noise parameters `tune` estimates.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct NoiseEstimate {
    /// Lateral measurement noise, metres (`R = measurement_noise_m^2`).
    pub measurement_noise_m: f64,
    /// Process noise: `accel_psd_rad2ps3` (continuous model) or `accel_var_rad2ps4`
    /// (the paper's sigma), whichever the filter's `process_noise_model` uses.
    pub process_noise: f64,
    /// Name of the parameter `process_noise` is.
    pub process_noise_param: &'static str,
}

/// Consistency of a filter on a recording: its innovations should be white with the
/// variance it predicts.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Consistency {
    /// Measurements fused (the NIS is averaged over these).
    pub fused: usize,
    /// Measurements gated out.
    pub rejected: usize,
    /// Mean normalised innovation squared (1 for a consistent filter).
    pub nis_mean: f64,
    /// Two-sided 95% bounds for `nis_mean` of a consistent filter with `fused` samples.
    pub nis_bounds_95: [f64; 2],
    /// Whether `nis_mean` lies within the bounds.
    pub nis_consistent: bool,
    /// Lag-one autocorrelation of the normalised innovations (0 when white).
    pub innovation_autocorr_lag1: f64,
    /// Negative log-likelihood of the innovations per measurement.
    pub nll_per_measurement: f64,
}

/// What [`tune`] found.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TuneReport {
    /// Recordings used.
    pub recordings: usize,
    /// Measurements used.
    pub measurements: usize,
    /// Mean capture interval, seconds.
    pub mean_interval_s: f64,
    /// The parameters before tuning.
    pub before: NoiseEstimate,
    /// Consistency before tuning.
    pub before_consistency: Consistency,
    /// The estimate.
    pub estimate: NoiseEstimate,
    /// Consistency with the estimate.
    pub consistency: Consistency,
    /// The likelihood was taken over every `stride`-th measurement of each
    /// recording (`stride` interleaved series; [`MIN_LIKELIHOOD_SPACING_S`]).
    pub stride: usize,
    /// Likelihood evaluations the search took.
    pub evaluations: usize,
}

/// Two-sided 95% bounds of the mean of `n` chi-square(1) samples: the sum is
/// chi-square(n), so its 2.5% and 97.5% quantiles divided by `n`.
pub fn nis_bounds_95(n: usize) -> [f64; 2] {
    if n == 0 {
        return [f64::NAN, f64::NAN];
    }
    let [lo, hi] = crate::control::stats::chi_square_interval_95(n as f64);
    [lo / n as f64, hi / n as f64]
}

/// Sums over the innovations of one or more filter passes.
#[derive(Debug, Default)]
struct Innovations {
    fused: usize,
    rejected: usize,
    nis_sum: f64,
    nll: f64,
    /// Normalised innovations, per recording (the autocorrelation is taken within each).
    normalised: Vec<Vec<f64>>,
}

impl Innovations {
    fn consistency(&self, gate_nis: f64) -> Consistency {
        let nis_mean = if self.fused > 0 {
            self.nis_sum / self.fused as f64
        } else {
            f64::NAN
        };
        let bounds = nis_bounds_95(self.fused);
        Consistency {
            fused: self.fused,
            rejected: self.rejected,
            nis_mean,
            nis_bounds_95: bounds,
            nis_consistent: nis_mean >= bounds[0] && nis_mean <= bounds[1],
            innovation_autocorr_lag1: autocorr_lag1(&self.normalised),
            // Rejected measurements carry the gate's worth of surprise, so a filter
            // that rejects much cannot look likely.
            nll_per_measurement: (self.nll + self.rejected as f64 * 0.5 * gate_nis)
                / (self.fused + self.rejected).max(1) as f64,
        }
    }
}

/// One pass of a fresh filter over one series, adding to `acc`.
fn pass(
    series: &Series,
    params: &EkfParams,
    model: PendulumModel,
    geometry: PendulumGeometry,
    acc: &mut Innovations,
    mut each: impl FnMut(usize, &Prediction, MeasureOutcome, f64, f64, &Ekf),
) -> Result<(), TuneError> {
    let mut ekf = Ekf::new(params.clone(), model, geometry)?;
    let r = params.measurement_noise_m.powi(2);
    let mut pred = Prediction::default();
    let mut nus: Vec<f64> = Vec::with_capacity(series.len());
    for (i, (&t, &z)) in series.t_s.iter().zip(&series.z_m).enumerate() {
        let running = ekf.is_initialised() && ekf.predict_at(t, &mut pred).is_ok();
        let (nu, s) = if running {
            (z - pred.lateral_m, pred.lateral_std_m.powi(2) + r)
        } else {
            (f64::NAN, f64::NAN)
        };
        let outcome = ekf.measure(t, z)?;
        match outcome {
            MeasureOutcome::Fused { nis } if running && s > 0.0 => {
                acc.fused += 1;
                acc.nis_sum += nis;
                acc.nll += 0.5 * (s.ln() + nu * nu / s + std::f64::consts::TAU.ln());
                nus.push(nu / s.sqrt());
            }
            MeasureOutcome::Rejected { .. } => acc.rejected += 1,
            _ => {}
        }
        if running {
            each(i, &pred, outcome, nu, s, &ekf);
        }
    }
    acc.normalised.push(nus);
    Ok(())
}

/// One pass of the filter over the series with the given parameters.
///
/// Calls `each(i, prediction_before, outcome, innovation, innovation_variance)` per
/// measurement after the filter is running, for figures.
///
/// # Errors
///
/// [`TuneError::Params`] for invalid `params`; [`TuneError::Filter`] when the
/// filter refuses its set-up or a measurement.
pub fn run_filter(
    series: &Series,
    params: &EkfParams,
    model: PendulumModel,
    geometry: PendulumGeometry,
    each: impl FnMut(usize, &Prediction, MeasureOutcome, f64, f64, &Ekf),
) -> Result<Consistency, TuneError> {
    params.validate()?;
    let mut acc = Innovations::default();
    pass(series, params, model, geometry, &mut acc, each)?;
    Ok(acc.consistency(params.gate_nis))
}

/// The filter over several recordings (a fresh filter for each, as each trial
/// starts one), their innovations pooled.
///
/// # Errors
///
/// [`TuneError::Params`] for invalid `params`; [`TuneError::Filter`] when the
/// filter refuses its set-up or a measurement.
pub fn run_filters(
    recordings: &[Series],
    params: &EkfParams,
    model: PendulumModel,
    geometry: PendulumGeometry,
) -> Result<Consistency, TuneError> {
    params.validate()?;
    let mut acc = Innovations::default();
    for series in recordings {
        pass(
            series,
            params,
            model,
            geometry,
            &mut acc,
            |_, _, _, _, _, _| {},
        )?;
    }
    Ok(acc.consistency(params.gate_nis))
}

/// Lag-one autocorrelation of the pooled sequences, pairs taken within each.
fn autocorr_lag1(seqs: &[Vec<f64>]) -> f64 {
    let n: usize = seqs.iter().map(Vec::len).sum();
    if n < 3 {
        return f64::NAN;
    }
    let m = seqs.iter().flatten().sum::<f64>() / n as f64;
    let var: f64 = seqs.iter().flatten().map(|v| (v - m).powi(2)).sum();
    let cov: f64 = seqs
        .iter()
        .flat_map(|x| x.windows(2))
        .map(|w| (w[0] - m) * (w[1] - m))
        .sum();
    if var > 0.0 { cov / var } else { f64::NAN }
}

fn process_noise(p: &EkfParams) -> (f64, &'static str) {
    match p.process_noise_model {
        ProcessNoiseModel::Continuous => (p.accel_psd_rad2ps3, "accel_psd_rad2ps3"),
        ProcessNoiseModel::Paper => (p.accel_var_rad2ps4, "accel_var_rad2ps4"),
    }
}

/// `params` with the two noise parameters replaced.
pub fn with_noise(params: &EkfParams, r_std_m: f64, q: f64) -> EkfParams {
    let mut p = params.clone();
    p.measurement_noise_m = r_std_m;
    match p.process_noise_model {
        ProcessNoiseModel::Continuous => p.accel_psd_rad2ps3 = q,
        ProcessNoiseModel::Paper => p.accel_var_rad2ps4 = q,
    }
    p
}

/// Estimates the measurement noise and the process noise of `params`' noise model by
/// maximising the likelihood of the filter's innovations over the recording
/// (Nelder-Mead on the logarithms of both), then reports the consistency of the
/// result. `params` supplies everything else (model, gate, damping estimation) and
/// the starting point of the search.
///
/// # Errors
///
/// As [`tune_recordings`].
pub fn tune(
    series: &Series,
    params: &EkfParams,
    model: PendulumModel,
    geometry: PendulumGeometry,
) -> Result<TuneReport, TuneError> {
    tune_recordings(std::slice::from_ref(series), params, model, geometry)
}

/// [`tune`] over several recordings of the same lab (e.g. one per trial, as the
/// service records them): each is run by a fresh filter and the likelihoods of
/// all their innovations are maximised together. Every recording must show a
/// swing, and together they must hold at least [`MIN_MEASUREMENTS`].
///
/// # Errors
///
/// [`TuneError::TooShort`] with fewer than [`MIN_MEASUREMENTS`] measurements in all;
/// [`TuneError::NoMotion`] when a recording does not swing; [`TuneError::Params`] or
/// [`TuneError::Filter`] as [`run_filters`].
pub fn tune_recordings(
    recordings: &[Series],
    params: &EkfParams,
    model: PendulumModel,
    geometry: PendulumGeometry,
) -> Result<TuneReport, TuneError> {
    let measurements: usize = recordings.iter().map(Series::len).sum();
    if measurements < MIN_MEASUREMENTS {
        return Err(TuneError::TooShort(measurements));
    }
    for series in recordings {
        match series.check_tunable() {
            Ok(()) | Err(TuneError::TooShort(_)) => {}
            Err(e) => return Err(e),
        }
    }
    params.validate()?;
    // Wide gate while searching: a too-small R must not hide its misfit by rejecting.
    let mut search = params.clone();
    search.gate_nis = 1e6;
    let before_consistency = run_filters(recordings, params, model, geometry)?;
    let mean_interval_s = {
        let (span, gaps) =
            recordings
                .iter()
                .filter(|s| s.len() > 1)
                .fold((0.0, 0usize), |(sp, g), s| {
                    (
                        sp + s.mean_interval_s() * (s.len() - 1) as f64,
                        g + s.len() - 1,
                    )
                });
        if gaps > 0 {
            span / gaps as f64
        } else {
            f64::NAN
        }
    };
    // The likelihood over frames at most 30 per second apart
    // (`MIN_LIKELIHOOD_SPACING_S`): each recording split into `stride`
    // interleaved series, each run by a fresh filter, so every measurement
    // counts once.
    let stride = likelihood_stride(mean_interval_s);
    let thinned: Vec<Series> = recordings
        .iter()
        .flat_map(|s| (0..stride).map(move |o| s.thinned(stride, o)))
        .collect();
    let (q0, q_name) = process_noise(params);
    let mut evaluations = 0usize;
    let mut cost = |x: [f64; 2]| -> f64 {
        evaluations += 1;
        let p = with_noise(&search, x[0].exp(), x[1].exp());
        if p.validate().is_err() {
            return f64::INFINITY;
        }
        run_filters(&thinned, &p, model, geometry).map_or(f64::INFINITY, |c| {
            if c.nll_per_measurement.is_finite() {
                c.nll_per_measurement
            } else {
                f64::INFINITY
            }
        })
    };
    // Start from the given values, and from a coarse grid if they are far off.
    let mut best = [params.measurement_noise_m.ln(), q0.max(1e-12).ln()];
    let mut best_cost = cost(best);
    for dr in [-2.0_f64, 0.0, 2.0] {
        for dq in [-4.0_f64, -2.0, 0.0, 2.0, 4.0] {
            let x = [best[0] + dr, best[1] + dq];
            let c = cost(x);
            if c < best_cost {
                best_cost = c;
                best = x;
            }
        }
    }
    let found = nelder_mead(&mut cost, best, [0.5, 1.0], 1e-7, 200);
    let estimate_params = with_noise(params, found[0].exp(), found[1].exp());
    estimate_params.validate()?;
    let consistency = run_filters(recordings, &estimate_params, model, geometry)?;
    Ok(TuneReport {
        recordings: recordings.len(),
        measurements,
        mean_interval_s,
        before: NoiseEstimate {
            measurement_noise_m: params.measurement_noise_m,
            process_noise: q0,
            process_noise_param: q_name,
        },
        before_consistency,
        estimate: NoiseEstimate {
            measurement_noise_m: found[0].exp(),
            process_noise: found[1].exp(),
            process_noise_param: q_name,
        },
        consistency,
        stride,
        evaluations,
    })
}

/// Minimises `f` over two variables by the Nelder-Mead simplex method.
fn nelder_mead(
    f: &mut impl FnMut([f64; 2]) -> f64,
    start: [f64; 2],
    step: [f64; 2],
    tol: f64,
    max_iter: usize,
) -> [f64; 2] {
    let mut pts = [
        start,
        [start[0] + step[0], start[1]],
        [start[0], start[1] + step[1]],
    ];
    let mut val = pts.map(&mut *f);
    for _ in 0..max_iter {
        // Order best..worst.
        let mut idx = [0usize, 1, 2];
        idx.sort_by(|&a, &b| val[a].total_cmp(&val[b]));
        pts = idx.map(|i| pts[i]);
        val = idx.map(|i| val[i]);
        if (val[2] - val[0]).abs() <= tol * (val[0].abs() + tol) {
            break;
        }
        let c = [
            f64::midpoint(pts[0][0], pts[1][0]),
            f64::midpoint(pts[0][1], pts[1][1]),
        ];
        let along = |k: f64| [c[0] + k * (pts[2][0] - c[0]), c[1] + k * (pts[2][1] - c[1])];
        let xr = along(-1.0);
        let fr = f(xr);
        if fr < val[0] {
            let xe = along(-2.0);
            let fe = f(xe);
            (pts[2], val[2]) = if fe < fr { (xe, fe) } else { (xr, fr) };
        } else if fr < val[1] {
            (pts[2], val[2]) = (xr, fr);
        } else {
            let xc = if fr < val[2] { along(-0.5) } else { along(0.5) };
            let fc = f(xc);
            if fc < val[2].min(fr) {
                (pts[2], val[2]) = (xc, fc);
            } else {
                for i in 1..3 {
                    pts[i] = [
                        f64::midpoint(pts[0][0], pts[i][0]),
                        f64::midpoint(pts[0][1], pts[i][1]),
                    ];
                    val[i] = f(pts[i]);
                }
            }
        }
    }
    let best = (0..3)
        .min_by(|&a, &b| val[a].total_cmp(&val[b]))
        .unwrap_or(0);
    pts[best]
}

/// The tuned parameters as a scenario fragment (`[ekf]` section) the service loads.
pub fn params_toml(params: &EkfParams, report: &TuneReport) -> String {
    let p = with_noise(
        params,
        report.estimate.measurement_noise_m,
        report.estimate.process_noise,
    );
    let body = toml::to_string_pretty(&p).unwrap_or_default();
    format!(
        "# EKF noise estimated by `isochron tune` from {} measurements\n\
         # (mean NIS {:.3}, 95% bounds [{:.3}, {:.3}]).\n[ekf]\n{body}",
        report.measurements,
        report.consistency.nis_mean,
        report.consistency.nis_bounds_95[0],
        report.consistency.nis_bounds_95[1],
    )
}

/// Lays a parameter file (a partial scenario in TOML, e.g. the `[ekf]` file
/// [`params_toml`] writes) over `scenario`: the keys it sets replace the scenario's,
/// section by section; every other key keeps the scenario's value. The file is
/// checked like a scenario file (unknown keys, types and ranges refused, naming
/// the line and field) and so is the result; on error nothing is returned.
///
/// # Errors
///
/// [`ParamError::Parse`] for bad TOML, a wrong type or an unknown key (in the file
/// or the merge); a validation error naming the first bad field of the file or the result.
pub fn overlay_params(scenario: &Scenario, text: &str) -> Result<Scenario, ParamError> {
    // Alone first: its errors then name the file's line and field.
    Scenario::from_toml_str(text)?;
    let patch: toml::Table = toml::from_str(text).map_err(|e| ParamError::parse(&e))?;
    let mut merged = toml::Table::try_from(scenario).map_err(|e| ParamError::parse(&e))?;
    merge_tables(&mut merged, patch);
    let out: Scenario = merged
        .try_into()
        .map_err(|e: toml::de::Error| ParamError::parse(&e))?;
    out.validate()?;
    Ok(out)
}

/// [`overlay_params`] with a file; errors name the file.
///
/// # Errors
///
/// [`ParamError::Io`] when the file cannot be read; otherwise as
/// [`overlay_params`], with the file named.
pub fn overlay_params_file(scenario: &Scenario, path: &Path) -> Result<Scenario, ParamError> {
    let text = std::fs::read_to_string(path).map_err(|e| ParamError::Io {
        path: path.display().to_string(),
        reason: e.to_string(),
    })?;
    overlay_params(scenario, &text).map_err(|e| e.in_file(path))
}

fn merge_tables(into: &mut toml::Table, patch: toml::Table) {
    for (k, v) in patch {
        match (into.get_mut(&k), v) {
            (Some(toml::Value::Table(a)), toml::Value::Table(b)) => merge_tables(a, b),
            (_, v) => {
                into.insert(k, v);
            }
        }
    }
}

#[cfg(test)]
mod tests;
