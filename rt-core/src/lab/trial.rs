//! A trial's draw: distance, release angle, wait before release and the
//! camera's frame phase, drawn from `(seed, trial index)` alone.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::params::Scenario;

/// What one trial drew from the seed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrialDraw {
    /// Distance to the intercept point, metres.
    pub distance_m: f64,
    /// Release angle (signed), degrees.
    pub release_angle_deg: f64,
    /// Wait between armed and release, seconds.
    pub release_wait_s: f64,
    /// Phase of the camera's first frame, seconds.
    pub camera_phase_s: f64,
    /// Seed of the trial's own random draws.
    pub seed: u64,
}

/// Draws trial `index` of a run with `seed` (independent of the other trials).
pub fn draw_trial(scenario: &Scenario, seed: u64, index: usize) -> TrialDraw {
    let mix = seed
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add((index as u64).wrapping_mul(0xD1B5_4A32_D192_ED03));
    let mut rng = ChaCha8Rng::seed_from_u64(mix);
    let d = scenario.task.distance_m.lerp(rng.random_range(0.0..=1.0));
    let a = scenario
        .pendulum
        .release_angle_deg
        .lerp(rng.random_range(0.0..=1.0));
    let sign = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
    TrialDraw {
        distance_m: d,
        release_angle_deg: sign * a,
        release_wait_s: rng.random_range(0.2..0.6),
        camera_phase_s: rng.random_range(0.0..1.0 / scenario.camera.fps),
        seed: rng.random(),
    }
}
