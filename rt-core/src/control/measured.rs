//! The measured judge's pieces (issue #26, deliverable 3): what a real lab can
//! judge from its own measurements, without ground truth.
//!
//! - [`measured_pass`]: the ball's pass through the intercept point from the
//!   camera's detections around it: a straight line fitted by least squares
//!   to the detections either side of the crossing, its root the pass time,
//!   with the root's standard deviation from the detections' noise (delta
//!   method: `var t = sigma^2 (1/n + (t - t_mean)^2 / S_tt) / b^2`, `b` the
//!   fitted speed).
//! - [`torque_contact`]: the contact seen in FRI's external joint torques:
//!   the first sample whose torque vector departs from its pre-contact
//!   baseline (the mean over the samples before `from_s`) by more than a
//!   threshold.
//!
//! Not real-time code: each runs once per trial on the recorded samples.

/// One camera detection: capture time on the control clock (s) and the
/// ball's lateral position along the swing (m, as the filter measures it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sighting {
    /// Capture time, control clock, seconds.
    pub t_s: f64,
    /// Lateral position, metres.
    pub x_m: f64,
}

/// The ball's measured pass through a lateral position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeasuredPass {
    /// When the fitted line crosses the position, seconds.
    pub t_s: f64,
    /// Its standard deviation, seconds.
    pub std_s: f64,
    /// The fitted speed through it, m/s (signed).
    pub speed_m_s: f64,
    /// Detections the line was fitted to.
    pub used: usize,
}

/// The pass through `x0_m` nearest `near_s` from `sightings` (ascending
/// times): each sign change of `x - x0` between consecutive detections is a
/// pass; the one nearest `near_s` is fitted with up to `per_side` detections
/// on each side. `sigma_x_m` is one detection's noise. `None` without a sign
/// change, with fewer than 2 detections per side or a line without slope.
pub fn measured_pass(
    sightings: &[Sighting],
    x0_m: f64,
    near_s: f64,
    sigma_x_m: f64,
    per_side: usize,
) -> Option<MeasuredPass> {
    let crossing = sightings
        .windows(2)
        .enumerate()
        .filter(|(_, w)| {
            let (a, b) = (w[0].x_m - x0_m, w[1].x_m - x0_m);
            (a < 0.0 && b >= 0.0) || (a > 0.0 && b <= 0.0)
        })
        .map(|(i, w)| {
            let (a, b) = (w[0].x_m - x0_m, w[1].x_m - x0_m);
            let t = w[0].t_s + a / (a - b) * (w[1].t_s - w[0].t_s);
            (i, t)
        })
        .min_by(|a, b| (a.1 - near_s).abs().total_cmp(&(b.1 - near_s).abs()))?;
    let (i, _) = crossing;
    // Detections i - per_side + 1 ..= i (before) and i + 1 ..= i + per_side (after).
    if per_side < 2 || i + 1 < per_side || i + per_side >= sightings.len() {
        return None;
    }
    let used = &sightings[i + 1 - per_side..=i + per_side];
    let n = used.len() as f64;
    let t_mean = used.iter().map(|s| s.t_s).sum::<f64>() / n;
    let x_mean = used.iter().map(|s| s.x_m).sum::<f64>() / n;
    let (mut s_tt, mut s_tx) = (0.0, 0.0);
    for s in used {
        let dt = s.t_s - t_mean;
        s_tt += dt * dt;
        s_tx += dt * (s.x_m - x_mean);
    }
    if s_tt <= 0.0 {
        return None;
    }
    let b = s_tx / s_tt;
    if b == 0.0 || !b.is_finite() {
        return None;
    }
    let t = t_mean + (x0_m - x_mean) / b;
    let var = sigma_x_m * sigma_x_m * (1.0 / n + (t - t_mean).powi(2) / s_tt) / (b * b);
    Some(MeasuredPass {
        t_s: t,
        std_s: var.sqrt(),
        speed_m_s: b,
        used: used.len(),
    })
}

/// The first time at or after `from_s` at which the external joint torques
/// (`torques_nm[k]` at `t_s[k]`, ascending) differ from their baseline (the
/// mean of the samples before `from_s`) by more than `threshold_nm` (the
/// Euclidean norm over the joints). `None`: no contact seen (or no baseline).
pub fn torque_contact(
    t_s: &[f64],
    torques_nm: &[[f64; 7]],
    from_s: f64,
    threshold_nm: f64,
) -> Option<f64> {
    let n = t_s.len().min(torques_nm.len());
    let before = t_s[..n].partition_point(|&t| t < from_s);
    if before == 0 {
        return None;
    }
    let mut base = [0.0; 7];
    for tau in &torques_nm[..before] {
        for (b, v) in base.iter_mut().zip(tau) {
            *b += v / before as f64;
        }
    }
    (before..n)
        .find(|&k| {
            let d2: f64 = torques_nm[k]
                .iter()
                .zip(&base)
                .map(|(v, b)| (v - b).powi(2))
                .sum();
            d2.sqrt() > threshold_nm
        })
        .map(|k| t_s[k])
}

#[cfg(test)]
mod tests {
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;

    /// A ball passing `x0` at `t_pass` with speed `v` near the bottom of a
    /// 1.93 m pendulum's swing, seen at 30 fps with `sigma` noise.
    fn swing(t_pass: f64, sigma: f64, seed: u64) -> Vec<Sighting> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let w = (9.81f64 / 1.93).sqrt();
        let amp = 0.3;
        (0..60)
            .map(|k| {
                let t = k as f64 / 30.0;
                let noise: f64 = (0..12).map(|_| rng.random::<f64>()).sum::<f64>() - 6.0;
                Sighting {
                    t_s: t,
                    x_m: 0.05 + amp * (w * (t - t_pass)).sin() + sigma * noise,
                }
            })
            .collect()
    }

    #[test]
    fn the_pass_is_found_within_its_uncertainty_and_the_uncertainty_is_honest() {
        let sigma = 0.002;
        let mut z2 = 0.0;
        let runs = 200;
        for seed in 0..runs {
            let t_pass = 0.9 + 0.013 * seed as f64 % 0.1;
            let s = swing(t_pass, sigma, seed);
            let p = measured_pass(&s, 0.05, 1.0, sigma, 3).unwrap();
            assert_eq!(p.used, 6);
            assert!(p.speed_m_s > 0.5, "{p:?}");
            // About 1 ms for a 2 mm camera at 30 fps and ~0.7 m/s.
            assert!(p.std_s > 2e-4 && p.std_s < 3e-3, "{p:?}");
            let z = (p.t_s - t_pass) / p.std_s;
            assert!(z.abs() < 5.0, "seed {seed}: {p:?} vs {t_pass}");
            z2 += z * z;
        }
        // The straight line through a sine's zero crossing is nearly exact:
        // the normalised errors have unit variance within sampling error.
        let nees = z2 / runs as f64;
        assert!((0.6..1.5).contains(&nees), "{nees}");
    }

    #[test]
    fn no_pass_without_a_crossing_or_enough_detections() {
        let s: Vec<Sighting> = (0..10)
            .map(|k| Sighting {
                t_s: k as f64 * 0.03,
                x_m: 0.1 + k as f64 * 0.01,
            })
            .collect();
        assert_eq!(measured_pass(&s, 0.0, 0.1, 0.002, 3), None);
        // A crossing at the edge of the detections: too few on one side.
        assert_eq!(measured_pass(&s, 0.105, 0.0, 0.002, 3), None);
        assert!(measured_pass(&s, 0.145, 0.1, 0.002, 3).is_some());
    }

    #[test]
    fn contact_is_the_first_departure_from_the_baseline_and_none_without_one() {
        let t: Vec<f64> = (0..400).map(|k| k as f64 * 0.005).collect();
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let quiet: Vec<[f64; 7]> = t
            .iter()
            .map(|_| std::array::from_fn(|j| 2.0 + j as f64 + 0.05 * (rng.random::<f64>() - 0.5)))
            .collect();
        assert_eq!(torque_contact(&t, &quiet, 0.5, 1.0), None);
        let mut hit = quiet.clone();
        for tau in &mut hit[300..310] {
            tau[3] += 4.0;
            tau[5] -= 2.0;
        }
        assert_eq!(torque_contact(&t, &hit, 0.5, 1.0), Some(t[300]));
        // No baseline before `from_s`: nothing is claimed.
        assert_eq!(torque_contact(&t, &hit, 0.0, 1.0), None);
    }
}
