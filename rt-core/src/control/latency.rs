//! Online estimate of the robot's command-to-motion latency from FRI's measured
//! joint positions against the joint commands this controller sent.
//!
//! Model: the joint position measured at cycle `k` equals the command computed at
//! cycle `k - L` (`L >= 1` cycles, fractional after interpolation). For every lag
//! `L` in `1..LATENCY_LAGS` the estimator keeps an exponentially forgotten sum of
//! squared differences `|q_meas[k] - q_cmd[k - L]|^2`; the estimate is the
//! minimising lag, refined by a parabola through its neighbours, times the FRI
//! period. Samples count only while the commands move (at rest every lag fits
//! equally well and would only wash out what the last motion taught). A
//! first-order servo lag of time constant `tau` shows up as about `tau` of extra
//! delay, which is what the interception timing must compensate anyway.
//!
//! Real-time: fixed arrays, no allocation; one `observe` costs `7 * LATENCY_LAGS`
//! multiply-adds.

use crate::kinematics::iiwa7::JOINTS;

/// Longest lag the estimator considers, in FRI cycles (exclusive).
pub const LATENCY_LAGS: usize = 160;

/// The estimator's state (see the module documentation).
#[derive(Debug, Clone)]
pub struct LatencyEstimator {
    period_s: f64,
    prior_s: f64,
    cmd: [[f64; JOINTS]; LATENCY_LAGS],
    head: usize,
    len: usize,
    cost: [f64; LATENCY_LAGS],
    lag_weight: [f64; LATENCY_LAGS],
    weight: f64,
    forget: f64,
    min_speed_radps: f64,
    min_weight: f64,
    estimate_s: f64,
    informative: u64,
    observed: u64,
}

/// A copy of the estimator's outputs (for snapshots and the dashboard).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LatencyReport {
    /// The latency used for timing: the estimate when confident, else the prior, seconds.
    pub latency_s: f64,
    /// Whether enough motion has been seen to trust the estimate.
    pub confident: bool,
    /// Measurements that carried information (the commands were moving).
    pub informative_samples: u64,
    /// All measurements observed.
    pub observed_samples: u64,
}

impl LatencyEstimator {
    /// A fresh estimator for an FRI period of `period_s`; until it has seen enough
    /// motion it reports `prior_s`. `memory_s` is the time constant of the
    /// forgetting (in seconds of motion).
    pub fn new(period_s: f64, prior_s: f64, memory_s: f64) -> Self {
        let period_s = if period_s.is_finite() && period_s > 0.0 {
            period_s
        } else {
            0.005
        };
        let memory_cycles = (memory_s / period_s).max(10.0);
        Self {
            period_s,
            prior_s: if prior_s.is_finite() {
                prior_s.max(0.0)
            } else {
                0.0
            },
            cmd: [[0.0; JOINTS]; LATENCY_LAGS],
            head: 0,
            len: 0,
            cost: [0.0; LATENCY_LAGS],
            lag_weight: [0.0; LATENCY_LAGS],
            weight: 0.0,
            forget: 1.0 - 1.0 / memory_cycles,
            min_speed_radps: 0.02,
            // About a quarter second of motion.
            min_weight: (0.25 / period_s).max(20.0),
            estimate_s: prior_s.max(0.0),
            informative: 0,
            observed: 0,
        }
    }

    /// Whether `other` estimates under the same settings (period, prior,
    /// memory): what it learned then holds here too.
    pub fn same_settings(&self, other: &Self) -> bool {
        self.period_s == other.period_s
            && self.prior_s == other.prior_s
            && self.forget == other.forget
            && self.min_speed_radps == other.min_speed_radps
            && self.min_weight == other.min_weight
    }

    /// The FRI period this estimator counts lags in, seconds.
    pub fn period_s(&self) -> f64 {
        self.period_s
    }

    fn cmd_back(&self, lag: usize) -> &[f64; JOINTS] {
        // lag 1 = the newest command; lag < len <= LATENCY_LAGS.
        &self.cmd[(self.head + LATENCY_LAGS - lag) % LATENCY_LAGS]
    }

    /// Records the joint command sent in this cycle (call once per cycle, after
    /// [`observe`](Self::observe)).
    pub fn commanded(&mut self, q_cmd: &[f64; JOINTS]) {
        self.cmd[self.head] = *q_cmd;
        self.head = (self.head + 1) % LATENCY_LAGS;
        self.len = (self.len + 1).min(LATENCY_LAGS);
    }

    /// Folds in the joint positions measured in this cycle (before this cycle's
    /// command is recorded).
    pub fn observe(&mut self, q_meas: &[f64; JOINTS]) {
        self.observed += 1;
        if self.len < 3 || !q_meas.iter().all(|v| v.is_finite()) {
            return;
        }
        // Informative only while the recent commands move.
        let a = self.cmd_back(1);
        let b = self.cmd_back(2);
        let step = a
            .iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max);
        if step < self.min_speed_radps * self.period_s {
            return;
        }
        self.informative += 1;
        self.weight = self.weight * self.forget + 1.0;
        for lag in 1..LATENCY_LAGS {
            // Lags longer than the history so far are not scored; each lag's
            // cost is a (forgotten) mean over the samples that scored it.
            self.cost[lag] *= self.forget;
            self.lag_weight[lag] *= self.forget;
            if lag < self.len {
                let c = self.cmd_back(lag);
                self.cost[lag] += q_meas
                    .iter()
                    .zip(c)
                    .map(|(m, c)| (m - c) * (m - c))
                    .sum::<f64>();
                self.lag_weight[lag] += 1.0;
            }
        }
        self.refresh();
    }

    /// Mean cost of a lag, or infinity when it was scored by less than half
    /// of the informative samples.
    fn mean_cost(&self, lag: usize) -> f64 {
        let w = self.lag_weight[lag];
        if w > 0.5 * self.weight && w > 0.0 {
            self.cost[lag] / w
        } else {
            f64::INFINITY
        }
    }

    fn refresh(&mut self) {
        let mut best = 1;
        for lag in 2..LATENCY_LAGS {
            if self.mean_cost(lag) < self.mean_cost(best) {
                best = lag;
            }
        }
        let mut frac = 0.0;
        if best > 1 && best + 1 < LATENCY_LAGS {
            let (cm, c0, cp) = (
                self.mean_cost(best - 1),
                self.mean_cost(best),
                self.mean_cost(best + 1),
            );
            let den = cm - 2.0 * c0 + cp;
            if den.is_finite() && den > 1e-300 {
                frac = (0.5 * (cm - cp) / den).clamp(-0.5, 0.5);
            }
        }
        // `best` is at most LATENCY_LAGS (160): exact as f64.
        self.estimate_s = (best as f64 + frac) * self.period_s;
    }

    /// Whether enough motion has been seen to trust the estimate.
    pub fn confident(&self) -> bool {
        self.weight >= self.min_weight
    }

    /// The latency to compensate: the estimate when confident, else the prior, seconds.
    pub fn latency_s(&self) -> f64 {
        if self.confident() {
            self.estimate_s
        } else {
            self.prior_s
        }
    }

    /// The current outputs.
    pub fn report(&self) -> LatencyReport {
        LatencyReport {
            latency_s: self.latency_s(),
            confident: self.confident(),
            informative_samples: self.informative,
            observed_samples: self.observed,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A robot that follows the commands `delay_cycles` later through a
    /// first-order lag of `tau_s`, with measurement noise.
    fn run(period_s: f64, delay_cycles: usize, tau_s: f64, noise: f64) -> LatencyEstimator {
        let mut est = LatencyEstimator::new(period_s, 0.0, 5.0);
        let mut sent: Vec<[f64; JOINTS]> = Vec::new();
        let mut q = [0.0; JOINTS];
        let mut rng = 12345u64;
        let mut noise_draw = || {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((rng >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2.0 * noise
        };
        let steps = (4.0 / period_s) as usize;
        for k in 0..steps {
            let t = k as f64 * period_s;
            // The robot: target = command from delay_cycles ago.
            if k >= delay_cycles && !sent.is_empty() {
                let target = sent[k - delay_cycles];
                let a = period_s / (tau_s + period_s);
                for j in 0..JOINTS {
                    q[j] += a * (target[j] - q[j]);
                }
            }
            let mut meas = q;
            for m in &mut meas {
                *m += noise_draw();
            }
            est.observe(&meas);
            let mut c = [0.0; JOINTS];
            for (j, v) in c.iter_mut().enumerate() {
                *v = 0.4 * (1.0 + j as f64 * 0.1) * (1.0 - (1.3 * t).cos());
            }
            est.commanded(&c);
            sent.push(c);
        }
        est
    }

    #[test]
    fn a_pure_delay_is_found_to_within_a_fraction_of_a_cycle() {
        for (period, delay) in [(0.005, 5usize), (0.001, 25), (0.010, 3)] {
            let est = run(period, delay, 0.0, 1e-5);
            assert!(est.confident());
            let want = delay as f64 * period;
            assert!(
                (est.latency_s() - want).abs() < 0.5 * period,
                "period {period}: got {} want {want}",
                est.latency_s()
            );
        }
    }

    #[test]
    fn a_servo_lag_adds_its_time_constant() {
        let est = run(0.005, 4, 0.010, 1e-5);
        let want = 4.0 * 0.005 + 0.010;
        assert!(
            (est.latency_s() - want).abs() < 0.004,
            "{}",
            est.latency_s()
        );
    }

    #[test]
    fn without_motion_the_prior_is_used() {
        let mut est = LatencyEstimator::new(0.005, 0.012, 5.0);
        for _ in 0..1000 {
            est.observe(&[0.1; JOINTS]);
            est.commanded(&[0.1; JOINTS]);
        }
        assert!(!est.confident());
        assert_eq!(est.latency_s(), 0.012);
        assert_eq!(est.report().informative_samples, 0);
        assert_eq!(est.report().observed_samples, 1000);
    }
}
