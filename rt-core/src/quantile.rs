//! The one quantile rule for every percentile isochron reports (trial
//! summaries, the evaluation report, runs, `isochron bench`, the FRI doctor),
//! so a p95 is the same number wherever it is computed.
//!
//! The rule is numpy's default (`numpy.quantile(x, q)`, method `"linear"`,
//! Hyndman and Fan's type 7): with the sample sorted ascending, `x[0..n]`, and
//! `h = (n - 1) q`, the quantile is `x[floor(h)] + (h - floor(h)) (x[floor(h) +
//! 1] - x[floor(h)])`: linear between the two closest ranks, exactly `x[0]` at
//! `q = 0` and `x[n - 1]` at `q = 1`. An empty sample has none (`None`): the
//! caller says what an empty figure is (a summary's 0, a report's "–").
//!
//! Not this rule: the FRI latency histogram
//! (`fri::stats::LatencyHistogram::quantile_ns`) keeps no samples (it is filled
//! allocation-free on the real-time thread), so it cannot interpolate between
//! ranks: it takes the nearest rank (`ceil(q n)`, Hyndman and Fan's type 1) and
//! reports the midpoint of the bucket holding it, capped at the maximum: exact
//! below 128 ns, within 0.4% of that order statistic above. Its figures (the
//! FRI loop's `reply_latency_us`, `rtt_us`) are therefore never more than one
//! rank (plus the 0.4%) from this rule's; `fri::tests` checks both bounds.

/// The `q`-quantile (`q` in `[0, 1]`, clamped) of the ascending-sorted
/// `sorted`, numpy's default rule (see the module); `None` when it is empty.
///
/// ```
/// use rt_core::quantile::quantile;
/// assert_eq!(quantile(&[1.0, 2.0, 3.0, 4.0], 0.5), Some(2.5));
/// assert_eq!(quantile(&[], 0.5), None);
/// ```
#[must_use]
pub fn quantile(sorted: &[f64], q: f64) -> Option<f64> {
    let n = sorted.len();
    let last = n.checked_sub(1)?;
    let h = q.clamp(0.0, 1.0) * last as f64;
    // h is in [0, n - 1]: its floor is an index.
    let lo = h.floor() as usize;
    let hi = (lo + 1).min(last);
    Some(sorted[lo] + (h - lo as f64) * (sorted[hi] - sorted[lo]))
}

/// [`quantile`] of the finite values of `values` in any order (sorted here).
#[must_use]
pub fn quantile_of(values: &[f64], q: f64) -> Option<f64> {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    v.sort_by(f64::total_cmp);
    quantile(&v, q)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn it_is_numpys_default_rule() {
        // Each value is what numpy.quantile(x, q) (method "linear") gives.
        let cases: [(&[f64], f64, f64); 9] = [
            (&[1.0, 2.0, 3.0, 4.0], 0.5, 2.5),
            (&[1.0, 2.0, 3.0, 4.0, 5.0], 0.95, 4.8),
            (&[10.0, 20.0, 30.0, 40.0], 0.95, 38.5),
            (&[1.0, 2.0, 3.0], 0.25, 1.5),
            (&[1.0, 2.0, 3.0], 0.0, 1.0),
            (&[1.0, 2.0, 3.0], 1.0, 3.0),
            (&[7.0], 0.99, 7.0),
            (&[0.0, 1.0], 0.999, 0.999),
            (&[-3.0, -1.0, 2.0, 2.0, 9.0], 0.3, -0.4),
        ];
        for (x, q, want) in cases {
            let got = quantile(x, q).unwrap();
            assert!(
                (got - want).abs() < 1e-12,
                "{x:?} at {q}: {got}, numpy {want}"
            );
        }
        // 101 evenly spaced values: the q-quantile is 100 q exactly, at every q.
        let v: Vec<f64> = (0..=100).map(f64::from).collect();
        for k in 0..=1000 {
            let q = f64::from(k) / 1000.0;
            assert!((quantile(&v, q).unwrap() - 100.0 * q).abs() < 1e-9, "{q}");
        }
    }

    #[test]
    fn empty_samples_have_none_and_order_does_not_matter() {
        assert_eq!(quantile(&[], 0.5), None);
        assert_eq!(quantile_of(&[f64::NAN, f64::INFINITY], 0.5), None);
        assert_eq!(quantile_of(&[4.0, f64::NAN, 1.0, 3.0, 2.0], 0.5), Some(2.5));
        // q outside [0, 1] is clamped.
        assert_eq!(quantile(&[1.0, 2.0], -1.0), Some(1.0));
        assert_eq!(quantile(&[1.0, 2.0], 2.0), Some(2.0));
    }
}
