//! Summary statistics of many trials: percentiles, mean/std, the Wilson score
//! interval of a success rate. Not real-time code (it sorts into a `Vec`).

use serde::Serialize;

/// `p50`, `p95` and `max` of a sample.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct Percentiles {
    /// Median.
    pub p50: f64,
    /// 95th percentile.
    pub p95: f64,
    /// Largest value.
    pub max: f64,
}

/// `mean`, `std`, `min`, `max` of a sample.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct Moments {
    /// Arithmetic mean.
    pub mean: f64,
    /// Population standard deviation.
    pub std: f64,
    /// Smallest value.
    pub min: f64,
    /// Largest value.
    pub max: f64,
}

/// The `q`-quantile (`q` in `[0, 1]`) of an ascending-sorted sample by the one
/// rule of [`crate::quantile`] (numpy's default: linear between the closest
/// ranks); 0 for an empty sample (the summaries' JSON has no NaN).
pub fn quantile_sorted(sorted: &[f64], q: f64) -> f64 {
    crate::quantile::quantile(sorted, q).unwrap_or(0.0)
}

/// Sorts finite values of `values` ascending (non-finite ones are dropped).
fn sorted_finite(values: &[f64]) -> Vec<f64> {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    v.sort_by(f64::total_cmp);
    v
}

impl Percentiles {
    /// Percentiles of the finite values (all zero when there are none).
    pub fn of(values: &[f64]) -> Self {
        let v = sorted_finite(values);
        Self {
            p50: quantile_sorted(&v, 0.50),
            p95: quantile_sorted(&v, 0.95),
            max: v.last().copied().unwrap_or(0.0),
        }
    }
}

impl Moments {
    /// Moments of the finite values (all zero when there are none).
    pub fn of(values: &[f64]) -> Self {
        let v = sorted_finite(values);
        if v.is_empty() {
            return Self::default();
        }
        let n = v.len() as f64;
        let mean = v.iter().sum::<f64>() / n;
        let var = v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / n;
        Self {
            mean,
            std: var.sqrt(),
            min: v[0],
            max: v[v.len() - 1],
        }
    }
}

/// The two-sided 95% normal quantile, `z` with `P(|Z| < z) = 0.95` (1.95996...).
pub fn z95() -> f64 {
    use statrs::distribution::{ContinuousCDF, Normal};
    Normal::standard().inverse_cdf(0.975)
}

/// The Wilson score 95% confidence interval `[lo, hi]` of a success rate with
/// `successes` out of `trials` (`[0, 1]` when there are no trials). (`statrs`
/// has no binomial interval; the normal quantile comes from it.)
///
/// ```
/// use rt_core::control::stats::wilson_ci95;
/// // 93 of 100 (the paper's rate): 86.3% to 96.6%.
/// let [lo, hi] = wilson_ci95(93, 100);
/// assert!((lo - 0.863).abs() < 1e-3 && (hi - 0.966).abs() < 1e-3);
/// assert_eq!(wilson_ci95(0, 0), [0.0, 1.0]);
/// ```
pub fn wilson_ci95(successes: usize, trials: usize) -> [f64; 2] {
    if trials == 0 {
        return [0.0, 1.0];
    }
    let z = z95();
    let n = trials as f64;
    let p = successes.min(trials) as f64 / n;
    let z2 = z * z;
    let denom = 1.0 + z2 / n;
    let centre = (p + z2 / (2.0 * n)) / denom;
    let half = z * (p * (1.0 - p) / n + z2 / (4.0 * n * n)).sqrt() / denom;
    // No successes: the lower end is 0; all: the upper end is 1 (exactly).
    let lo = if successes == 0 {
        0.0
    } else {
        (centre - half).max(0.0)
    };
    let hi = if successes >= trials {
        1.0
    } else {
        (centre + half).min(1.0)
    };
    [lo, hi]
}

/// The two-sided 95% interval `[lo, hi]` of a chi-square variable with `dof`
/// degrees of freedom (its 2.5% and 97.5% quantiles, `statrs`); NaN for a
/// `dof` that is not positive and finite.
pub fn chi_square_interval_95(dof: f64) -> [f64; 2] {
    use statrs::distribution::{ChiSquared, ContinuousCDF};
    match ChiSquared::new(dof) {
        Ok(d) if dof.is_finite() => [d.inverse_cdf(0.025), d.inverse_cdf(0.975)],
        _ => [f64::NAN, f64::NAN],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_interpolate_between_ranks() {
        let v = [1.0, 2.0, 3.0, 4.0, 5.0];
        assert_eq!(quantile_sorted(&v, 0.5), 3.0);
        assert_eq!(quantile_sorted(&v, 0.0), 1.0);
        assert_eq!(quantile_sorted(&v, 1.0), 5.0);
        assert!((quantile_sorted(&v, 0.95) - 4.8).abs() < 1e-12);
        let p = Percentiles::of(&[5.0, f64::NAN, 1.0, 3.0]);
        assert_eq!(p.p50, 3.0);
        assert_eq!(p.max, 5.0);
        assert_eq!(Percentiles::of(&[]), Percentiles::default());
    }

    #[test]
    fn moments_are_population_moments() {
        let m = Moments::of(&[1.0, 3.0]);
        assert_eq!(m.mean, 2.0);
        assert_eq!(m.std, 1.0);
        assert_eq!((m.min, m.max), (1.0, 3.0));
    }

    #[test]
    fn wilson_interval_matches_reference_values() {
        // 298/300: Wilson 95% [0.9760, 0.9982] (the contract's example).
        let [lo, hi] = wilson_ci95(298, 300);
        assert!((lo - 0.9760).abs() < 5e-4, "{lo}");
        assert!((hi - 0.9982).abs() < 5e-4, "{hi}");
        // All successes: the upper end is 1, the lower end below 1.
        let [lo, hi] = wilson_ci95(300, 300);
        assert!(hi > 0.9999 && lo < 0.99 && lo > 0.98, "{lo} {hi}");
        // Zero successes: lower end 0.
        assert_eq!(wilson_ci95(0, 10)[0], 0.0);
        assert_eq!(wilson_ci95(0, 0), [0.0, 1.0]);
    }

    #[test]
    fn chi_square_interval_matches_tables() {
        // chi2(100): 2.5% and 97.5% quantiles 74.222 and 129.561; chi2(3): 0.2158 and 9.3484.
        let [lo, hi] = chi_square_interval_95(100.0);
        assert!(
            (lo - 74.222).abs() < 1e-3 && (hi - 129.561).abs() < 1e-3,
            "{lo} {hi}"
        );
        let [lo, hi] = chi_square_interval_95(3.0);
        assert!(
            (lo - 0.2158).abs() < 1e-4 && (hi - 9.3484).abs() < 1e-4,
            "{lo} {hi}"
        );
        assert!(chi_square_interval_95(0.0)[0].is_nan());
        assert!((z95() - 1.959_964).abs() < 1e-6);
    }
}
