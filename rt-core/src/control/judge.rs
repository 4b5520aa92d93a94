//! Judging a trial on ground truth (CONTRACT.md, "`isochron trials --json` summary").
//!
//! - `t*`: when the true ball centre passes the intercept point (its lateral
//!   coordinate `y` crosses the intercept point's, linearly interpolated between
//!   samples); of several passes, the one nearest the tool's arrival.
//! - *arrival*: the end of the ideal profile (the planned shape) that best fits,
//!   in least squares, the tool's measured progress along its path; *start* is
//!   that fit's start. The fit adjusts both the start and the duration (starting
//!   from the planned duration): with the duration held fixed, `movement_time_s`
//!   would be the plan by construction and say nothing about the executed motion.
//! - `timing_error_ms = |arrival - t*|`, `position_error_m = |tool(t*) - ball(t*)|`,
//!   `movement_time_s = arrival - start`.
//!
//! Not real-time code: it runs once per trial on the recorded trace.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::trajectory::profile::ProfileKind;

/// What was recorded during one trial, one sample per control cycle (times in
/// the simulation's clock, seconds; positions in the robot base frame, metres).
#[derive(Debug, Clone, Default)]
pub struct TrialTrace {
    /// Sample times, ascending.
    pub t_s: Vec<f64>,
    /// The tool point from the robot's *measured* joint angles (forward kinematics).
    pub tool_m: Vec<Vector3<f64>>,
    /// The true ball centre.
    pub ball_m: Vec<Vector3<f64>>,
}

impl TrialTrace {
    /// An empty trace with room for `n` samples.
    pub fn with_capacity(n: usize) -> Self {
        Self {
            t_s: Vec::with_capacity(n),
            tool_m: Vec::with_capacity(n),
            ball_m: Vec::with_capacity(n),
        }
    }

    /// Appends one sample.
    pub fn push(&mut self, t_s: f64, tool_m: Vector3<f64>, ball_m: Vector3<f64>) {
        self.t_s.push(t_s);
        self.tool_m.push(tool_m);
        self.ball_m.push(ball_m);
    }

    /// Removes every sample, keeping the memory.
    pub fn clear(&mut self) {
        self.t_s.clear();
        self.tool_m.clear();
        self.ball_m.clear();
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.t_s.len()
    }

    /// `true` without samples.
    pub fn is_empty(&self) -> bool {
        self.t_s.is_empty()
    }
}

/// The planned motion the trace is judged against.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlannedMotion {
    /// Tool point where the motion starts (home), metres.
    pub start_m: Vector3<f64>,
    /// Tool point where the motion ends (its last target), metres.
    pub end_m: Vector3<f64>,
    /// The profile's shape.
    pub profile: ProfileKind,
    /// Planned duration, seconds.
    pub duration_s: f64,
    /// When the motion command began, seconds (the fit's first guess).
    pub commanded_start_s: f64,
}

/// The ground-truth verdict on one motion.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Judgement {
    /// When the ball centre passed the intercept point, seconds.
    pub t_star_s: f64,
    /// Start of the best-fitting ideal profile, seconds.
    pub start_s: f64,
    /// End of the best-fitting ideal profile, seconds.
    pub arrival_s: f64,
    /// `|arrival - t*|`, milliseconds.
    pub timing_error_ms: f64,
    /// Tool point to ball centre at `t*`, metres.
    pub position_error_m: f64,
    /// `arrival - start`, seconds.
    pub movement_time_s: f64,
    /// Root-mean-square residual of the profile fit, metres.
    pub fit_rms_m: f64,
}

/// Why a trace could not be judged.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum JudgeError {
    /// Fewer than 3 samples, or mismatched lengths.
    #[error("the trace has too few samples")]
    TooFewSamples,
    /// The planned path is shorter than 1 mm, or its duration not positive.
    #[error("the planned motion is degenerate (no length or no duration)")]
    DegenerateMotion,
    /// The tool did not move along its path.
    #[error("the tool never moved along its path")]
    NoMotion,
    /// The ball never passed the intercept point during the trace.
    #[error("the ball never passed the intercept point")]
    NoPass,
}

/// Least-squares fit of `D * s((t - t0) / T)` to progress samples over `t0` and
/// `T` (Levenberg-Marquardt from the given guesses). Returns `(t0, T, rms)`.
pub fn fit_profile(
    profile: ProfileKind,
    distance_m: f64,
    times_s: &[f64],
    progress_m: &[f64],
    start_guess_s: f64,
    duration_guess_s: f64,
) -> (f64, f64, f64) {
    let cost = |t0: f64, dur: f64| -> f64 {
        times_s
            .iter()
            .zip(progress_m)
            .map(|(t, p)| {
                let r = distance_m * profile.position((t - t0) / dur) - p;
                r * r
            })
            .sum()
    };
    // Coarse scan of the start (the cost has flat regions far from the motion).
    let mut t0 = start_guess_s;
    let mut dur = duration_guess_s;
    let mut best = cost(t0, dur);
    for k in -40..=40 {
        let cand = start_guess_s + f64::from(k) * 0.01 * duration_guess_s;
        let c = cost(cand, dur);
        if c < best {
            best = c;
            t0 = cand;
        }
    }
    let mut lambda = 1e-3;
    for _ in 0..100 {
        // Normal equations of the 2-parameter Gauss-Newton step.
        let (mut a00, mut a01, mut a11, mut g0, mut g1) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for (t, p) in times_s.iter().zip(progress_m) {
            let tau = (t - t0) / dur;
            let r = distance_m * profile.position(tau) - p;
            let ds = distance_m * profile.velocity(tau) / dur;
            let j0 = -ds;
            let j1 = -ds * tau;
            a00 += j0 * j0;
            a01 += j0 * j1;
            a11 += j1 * j1;
            g0 += j0 * r;
            g1 += j1 * r;
        }
        let mut improved = false;
        for _ in 0..10 {
            let m00 = a00 * (1.0 + lambda) + 1e-12;
            let m11 = a11 * (1.0 + lambda) + 1e-12;
            let det = m00 * m11 - a01 * a01;
            if det.abs() < 1e-300 {
                break;
            }
            let d0 = -(m11 * g0 - a01 * g1) / det;
            let d1 = -(m00 * g1 - a01 * g0) / det;
            let (n0, n1) = (t0 + d0, (dur + d1).max(1e-3));
            let c = cost(n0, n1);
            if c < best {
                best = c;
                t0 = n0;
                dur = n1;
                lambda = (lambda * 0.3).max(1e-9);
                improved = d0.abs() > 1e-9 || d1.abs() > 1e-9;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    let n = times_s.len().max(1) as f64;
    (t0, dur, (best / n).sqrt())
}

/// Linear interpolation of `values` at `t` (clamped to the ends).
fn interp(t_s: &[f64], values: &[Vector3<f64>], t: f64) -> Vector3<f64> {
    let i = t_s.partition_point(|&x| x < t);
    if i == 0 {
        return values[0];
    }
    if i >= t_s.len() {
        return values[values.len() - 1];
    }
    let (ta, tb) = (t_s[i - 1], t_s[i]);
    let u = if tb > ta { (t - ta) / (tb - ta) } else { 0.0 };
    values[i - 1] + (values[i] - values[i - 1]) * u
}

/// Times the ball's `y` crosses `intercept_y_m`, linearly interpolated.
pub fn pass_times(trace: &TrialTrace, intercept_y_m: f64, out: &mut Vec<f64>) {
    out.clear();
    for i in 1..trace.len() {
        let a = trace.ball_m[i - 1].y - intercept_y_m;
        let b = trace.ball_m[i].y - intercept_y_m;
        if (a < 0.0 && b >= 0.0) || (a > 0.0 && b <= 0.0) {
            let u = a / (a - b);
            out.push(trace.t_s[i - 1] + u * (trace.t_s[i] - trace.t_s[i - 1]));
        }
    }
}

/// Working memory of [`judge_into`] (allocated once: judging then allocates
/// nothing as long as the trace fits the capacity).
#[derive(Debug, Clone, Default)]
pub struct JudgeScratch {
    times: Vec<f64>,
    progress: Vec<f64>,
    passes: Vec<f64>,
}

impl JudgeScratch {
    /// Room for a trace of `n` samples.
    pub fn with_capacity(n: usize) -> Self {
        Self {
            times: Vec::with_capacity(n),
            progress: Vec::with_capacity(n),
            passes: Vec::with_capacity(256),
        }
    }
}

/// Judges one motion of a trial against the truth in `trace`.
///
/// # Errors
///
/// As [`judge_into`].
pub fn judge(
    trace: &TrialTrace,
    motion: &PlannedMotion,
    intercept_m: &Vector3<f64>,
) -> Result<Judgement, JudgeError> {
    judge_into(trace, motion, intercept_m, &mut JudgeScratch::default())
}

/// The ideal profile that best fits the tool's progress along `motion`'s
/// path (the samples from a quarter of the duration before the command to
/// half of it after the planned end): `(start, duration, rms)`, as
/// [`judge_into`] fits it (the arrival is start + duration). The measured
/// judge fits the tool point of the measured joints the same way (the
/// movement time a real lab reports).
///
/// # Errors
///
/// [`JudgeError::DegenerateMotion`] for a motion without length or
/// duration; [`JudgeError::TooFewSamples`] for fewer than 3 samples in the
/// window; [`JudgeError::NoMotion`] when the tool never moved half way.
pub fn fit_movement(
    samples: impl Iterator<Item = (f64, Vector3<f64>)>,
    motion: &PlannedMotion,
    scratch: &mut JudgeScratch,
) -> Result<(f64, f64, f64), JudgeError> {
    let path = motion.end_m - motion.start_m;
    let distance_m = path.norm();
    if distance_m < 1e-3 || motion.duration_s.is_nan() || motion.duration_s <= 0.0 {
        return Err(JudgeError::DegenerateMotion);
    }
    let dir = path / distance_m;
    // Progress along the path from motion start: samples from just before the
    // command to a little after the planned end.
    let lo = motion.commanded_start_s - 0.25 * motion.duration_s;
    let hi = motion.commanded_start_s + 1.5 * motion.duration_s;
    let JudgeScratch {
        times, progress, ..
    } = scratch;
    times.clear();
    progress.clear();
    for (t, tool) in samples {
        if t >= lo && t <= hi {
            times.push(t);
            progress.push((tool - motion.start_m).dot(&dir));
        }
    }
    if times.len() < 3 {
        return Err(JudgeError::TooFewSamples);
    }
    let moved = progress.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if moved < 0.5 * distance_m {
        return Err(JudgeError::NoMotion);
    }
    Ok(fit_profile(
        motion.profile,
        distance_m,
        times,
        progress,
        motion.commanded_start_s,
        motion.duration_s,
    ))
}

/// [`judge`] with its working memory in `scratch` (the trial driver judges on
/// the control thread without allocating).
///
/// # Errors
///
/// [`JudgeError::TooFewSamples`] for fewer than 3 samples or mismatched lengths;
/// [`JudgeError::DegenerateMotion`] for a motion without length or duration;
/// [`JudgeError::NoMotion`] when the tool never moved; [`JudgeError::NoPass`] when
/// the ball never passed the intercept point.
pub fn judge_into(
    trace: &TrialTrace,
    motion: &PlannedMotion,
    intercept_m: &Vector3<f64>,
    scratch: &mut JudgeScratch,
) -> Result<Judgement, JudgeError> {
    let n = trace.len();
    if n < 3 || trace.tool_m.len() != n || trace.ball_m.len() != n {
        return Err(JudgeError::TooFewSamples);
    }
    let (start_s, dur_s, rms) = fit_movement(
        (0..n).map(|i| (trace.t_s[i], trace.tool_m[i])),
        motion,
        scratch,
    )?;
    let arrival_s = start_s + dur_s;
    let passes = &mut scratch.passes;
    passes.clear();
    pass_times(trace, intercept_m.y, passes);
    let t_star_s = passes
        .iter()
        .copied()
        .min_by(|a, b| (a - arrival_s).abs().total_cmp(&(b - arrival_s).abs()))
        .ok_or(JudgeError::NoPass)?;
    let tool = interp(&trace.t_s, &trace.tool_m, t_star_s);
    let ball = interp(&trace.t_s, &trace.ball_m, t_star_s);
    Ok(Judgement {
        t_star_s,
        start_s,
        arrival_s,
        timing_error_ms: (arrival_s - t_star_s).abs() * 1e3,
        position_error_m: (tool - ball).norm(),
        movement_time_s: dur_s,
        fit_rms_m: rms,
    })
}

/// Re-judges a strike's motion (issue #38) on the truthful world: its
/// arrival is when the tool point crosses `intercept_m`'s `y` along
/// `return_sign` (the stroke meets the ball there and brakes beyond it),
/// the crossing nearest `near_s` (the committed pass); `t*` the ball's pass
/// nearest it; the timing error `|crossing - t*|`, the position error the
/// tool-ball distance at `t*`, the movement time `crossing - start`.
/// `None` (the stop mode's figures stay) when the tool never crossed or the
/// ball never passed.
pub fn judge_strike_crossing(
    j: &Judgement,
    trace: &TrialTrace,
    intercept_m: &Vector3<f64>,
    return_sign: f64,
    near_s: f64,
    scratch: &mut JudgeScratch,
) -> Option<Judgement> {
    let s = return_sign.signum();
    let ahead = |i: usize| (trace.tool_m[i].y - intercept_m.y) * s;
    let crossing = (1..trace.len())
        .filter(|&i| ahead(i - 1) < 0.0 && ahead(i) >= 0.0)
        .map(|i| {
            let (a, b) = (ahead(i - 1), ahead(i));
            let u = -a / (b - a).max(1e-12);
            trace.t_s[i - 1] + u * (trace.t_s[i] - trace.t_s[i - 1])
        })
        .min_by(|a, b| (a - near_s).abs().total_cmp(&(b - near_s).abs()))?;
    let passes = &mut scratch.passes;
    pass_times(trace, intercept_m.y, passes);
    let t_star_s = passes
        .iter()
        .copied()
        .min_by(|a, b| (a - crossing).abs().total_cmp(&(b - crossing).abs()))?;
    let tool = interp(&trace.t_s, &trace.tool_m, t_star_s);
    let ball = interp(&trace.t_s, &trace.ball_m, t_star_s);
    Some(Judgement {
        t_star_s,
        arrival_s: crossing,
        timing_error_ms: (crossing - t_star_s).abs() * 1e3,
        position_error_m: (tool - ball).norm(),
        movement_time_s: crossing - j.start_s,
        ..*j
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_strike_arrives_when_the_tool_crosses_the_intercept_point() {
        // The tool moves towards -y at 0.5 m/s, crossing y = 0 at 1.002 s;
        // the ball passes it towards +y at 1.0 s and again at 2.4 s.
        let mut trace = TrialTrace::with_capacity(600);
        for k in 0..600 {
            let t = f64::from(k) * 5e-3;
            let ball_y = if t < 1.7 {
                1.5 * (t - 1.0)
            } else {
                -1.5 * (t - 2.4)
            };
            trace.push(
                t,
                Vector3::new(0.6, -0.5 * (t - 1.002), 0.3),
                Vector3::new(0.6, ball_y, 0.3),
            );
        }
        let stop = Judgement {
            t_star_s: 2.4,
            start_s: -0.5,
            arrival_s: 2.5,
            timing_error_ms: 100.0,
            position_error_m: 0.5,
            movement_time_s: 3.0,
            fit_rms_m: 1e-4,
        };
        let p = Vector3::new(0.6, 0.0, 0.3);
        let mut scratch = JudgeScratch::default();
        let j = judge_strike_crossing(&stop, &trace, &p, -1.0, 1.01, &mut scratch).unwrap();
        assert!((j.arrival_s - 1.002).abs() < 1e-9, "{j:?}");
        assert!((j.t_star_s - 1.0).abs() < 1e-9, "{j:?}");
        assert!((j.timing_error_ms - 2.0).abs() < 1e-6, "{j:?}");
        assert!((j.position_error_m - 0.001).abs() < 1e-6, "{j:?}");
        assert!((j.movement_time_s - 1.502).abs() < 1e-9, "{j:?}");
        assert_eq!((j.start_s, j.fit_rms_m), (stop.start_s, stop.fit_rms_m));
        // A tool moving the other way never crosses along the return.
        assert!(judge_strike_crossing(&stop, &trace, &p, 1.0, 1.0, &mut scratch).is_none());
    }

    /// A synthetic trial: the ball swings `y = A sin(w (t - t_pass))` through the
    /// intercept point; the tool follows an ideal profile from `start` lasting `dur`.
    fn synthetic(
        kind: ProfileKind,
        t_start: f64,
        dur: f64,
        t_pass: f64,
        lateral_offset: f64,
    ) -> (TrialTrace, PlannedMotion, Vector3<f64>) {
        let home = Vector3::new(0.3, 0.0, 0.5);
        let target = Vector3::new(0.7, 0.0, 0.3);
        let intercept = target;
        let mut tr = TrialTrace::default();
        let w = std::f64::consts::TAU / 2.8;
        for k in 0..800 {
            let t = f64::from(k) * 0.005;
            let s = kind.position((t - t_start) / dur);
            let tool = home + (target - home) * s + Vector3::new(0.0, lateral_offset, 0.0);
            let ball = intercept + Vector3::new(0.0, 0.5 * (w * (t - t_pass)).sin(), 0.0);
            tr.push(t, tool, ball);
        }
        let plan = PlannedMotion {
            start_m: home,
            end_m: target,
            profile: kind,
            duration_s: 1.5,
            commanded_start_s: 0.9,
        };
        (tr, plan, intercept)
    }

    #[test]
    fn a_perfect_motion_has_no_error() {
        for kind in [ProfileKind::Hopf, ProfileKind::MinJerk] {
            let (tr, plan, ip) = synthetic(kind, 1.0, 1.5, 2.5, 0.0);
            let j = judge(&tr, &plan, &ip).unwrap();
            assert!((j.t_star_s - 2.5).abs() < 1e-9, "{j:?}");
            assert!((j.arrival_s - 2.5).abs() < 1e-6, "{j:?}");
            assert!((j.start_s - 1.0).abs() < 1e-6, "{j:?}");
            assert!(j.timing_error_ms < 1e-3, "{j:?}");
            assert!(j.position_error_m < 1e-9, "{j:?}");
            assert!((j.movement_time_s - 1.5).abs() < 1e-6, "{j:?}");
        }
    }

    #[test]
    fn a_late_slow_motion_is_measured_as_such() {
        // Starts 30 ms late and lasts 1.52 s: arrives 50 ms after the pass.
        let (tr, plan, ip) = synthetic(ProfileKind::Hopf, 1.03, 1.52, 2.5, 0.0);
        let j = judge(&tr, &plan, &ip).unwrap();
        assert!((j.timing_error_ms - 50.0).abs() < 0.05, "{j:?}");
        assert!((j.movement_time_s - 1.52).abs() < 1e-5, "{j:?}");
        // At t* the tool has not arrived yet: a position error too.
        assert!(j.position_error_m > 5e-5, "{j:?}");
    }

    #[test]
    fn a_lateral_offset_is_a_position_error() {
        let (tr, plan, ip) = synthetic(ProfileKind::Hopf, 1.0, 1.5, 2.5, 0.015);
        let j = judge(&tr, &plan, &ip).unwrap();
        assert!((j.position_error_m - 0.015).abs() < 1e-9, "{j:?}");
        assert!(j.timing_error_ms < 1e-3, "{j:?}");
    }

    #[test]
    fn degenerate_traces_are_refused() {
        let (tr, mut plan, ip) = synthetic(ProfileKind::Hopf, 1.0, 1.5, 2.5, 0.0);
        assert_eq!(
            judge(&TrialTrace::default(), &plan, &ip),
            Err(JudgeError::TooFewSamples)
        );
        let far = plan;
        plan.end_m = plan.start_m;
        assert_eq!(judge(&tr, &plan, &ip), Err(JudgeError::DegenerateMotion));
        // A tool that never moves.
        let mut still = tr.clone();
        for p in &mut still.tool_m {
            *p = far.start_m;
        }
        assert_eq!(judge(&still, &far, &ip), Err(JudgeError::NoMotion));
        // A ball that never passes.
        let mut parked = tr;
        for b in &mut parked.ball_m {
            *b = ip + Vector3::new(0.0, 0.3, 0.0);
        }
        assert_eq!(judge(&parked, &far, &ip), Err(JudgeError::NoPass));
    }
}
