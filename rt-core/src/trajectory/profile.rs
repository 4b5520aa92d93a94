//! Closed-form normalised path profiles of a timed point-to-point motion.
//!
//! `tau = t / T` in `[0, 1]`; `s(tau)` is the fraction of the path covered, with
//! `s(0) = 0`, `s(1) = 1`. Velocities and accelerations are with respect to `tau`:
//! multiply by `D / T` and `D / T^2` for a path of length `D` metres and duration
//! `T` seconds.
//!
//! These are the reference shapes. The Hopf dynamics in `timing` produce the
//! sinusoidal one by integration; planners and feasibility checks use the closed form.

use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;

/// Which velocity profile a motion follows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProfileKind {
    /// The paper's: one cycle of the shifted Hopf oscillator, `v = R_h (1 - cos(omega t))`.
    #[default]
    Hopf,
    /// Minimum jerk (Flash and Hogan): `s = 10 tau^3 - 15 tau^4 + 6 tau^5`.
    MinJerk,
}

impl ProfileKind {
    /// Fraction of the path covered at `tau` (clamped to `[0, 1]`).
    pub fn position(self, tau: f64) -> f64 {
        let t = tau.clamp(0.0, 1.0);
        match self {
            Self::Hopf => t - (TAU * t).sin() / TAU,
            Self::MinJerk => t * t * t * (10.0 + t * (-15.0 + 6.0 * t)),
        }
    }

    /// `ds/dtau` at `tau` (zero outside `[0, 1]`).
    pub fn velocity(self, tau: f64) -> f64 {
        if !(0.0..=1.0).contains(&tau) {
            return 0.0;
        }
        match self {
            Self::Hopf => 1.0 - (TAU * tau).cos(),
            Self::MinJerk => 30.0 * tau * tau * (1.0 - tau) * (1.0 - tau),
        }
    }

    /// `d^2 s / dtau^2` at `tau` (zero outside `[0, 1]`).
    pub fn acceleration(self, tau: f64) -> f64 {
        if !(0.0..=1.0).contains(&tau) {
            return 0.0;
        }
        match self {
            Self::Hopf => TAU * (TAU * tau).sin(),
            Self::MinJerk => 60.0 * tau * (1.0 - tau) * (1.0 - 2.0 * tau),
        }
    }

    /// The largest `ds/dtau` over the motion (at `tau = 0.5` for both shapes).
    pub fn peak_velocity(self) -> f64 {
        self.velocity(0.5)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_shapes_start_and_end_at_rest_and_cover_the_path() {
        for k in [ProfileKind::Hopf, ProfileKind::MinJerk] {
            assert_eq!(k.position(0.0), 0.0);
            assert!((k.position(1.0) - 1.0).abs() < 1e-12);
            assert!(k.velocity(0.0).abs() < 1e-12 && k.velocity(1.0).abs() < 1e-12);
            // Velocity is the derivative of position.
            let h = 1e-6;
            for i in 1..100 {
                let tau = f64::from(i) / 100.0;
                let num = (k.position(tau + h) - k.position(tau - h)) / (2.0 * h);
                assert!((num - k.velocity(tau)).abs() < 1e-6, "{k:?} at {tau}");
                let num_a = (k.velocity(tau + h) - k.velocity(tau - h)) / (2.0 * h);
                assert!((num_a - k.acceleration(tau)).abs() < 1e-5, "{k:?} at {tau}");
            }
        }
        assert_eq!(ProfileKind::Hopf.peak_velocity(), 2.0);
        assert_eq!(ProfileKind::MinJerk.peak_velocity(), 1.875);
    }
}
