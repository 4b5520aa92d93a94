//! The simulated camera in `model` mode: frames at the scenario's rate, each
//! lost with `drop_rate`, the ball's lateral position measured with Gaussian
//! noise, delivered `latency_ms` after capture.

use rand::{Rng, RngExt};

use crate::control::Sighting;
use crate::params::CameraParams;

/// Standard deviation of a `model`-mode measurement, metres (about a pixel's
/// footprint at the swing plane for the default camera).
pub const MODEL_NOISE_M: f64 = 0.002;

/// The reality lab's light on the ball below which the `model` camera finds
/// no ball: at this gain the rendered ball's brightest half stays above the
/// detector's value floor (0.30; the ball's shading spans 0.55-1.0 of its
/// colour's value 0.92), below it the ball breaks up
/// (`sim::world::tests`, the full detector either side of it).
pub const MODEL_MIN_GAIN: f64 = 0.45;

/// A frame schedule and the measurements in flight.
#[derive(Debug, Clone)]
pub struct ModelCamera {
    period_s: f64,
    latency_s: f64,
    drop_rate: f64,
    next_capture_s: f64,
    noise_m: f64,
    in_flight: std::collections::VecDeque<(f64, Sighting)>,
    /// Frames captured.
    pub frames: u64,
    /// Frames lost.
    pub dropped: u64,
}

impl ModelCamera {
    /// A camera whose first frame is captured at `first_capture_s`.
    pub fn new(p: &CameraParams, first_capture_s: f64) -> Self {
        Self {
            period_s: 1.0 / p.fps,
            latency_s: p.latency_ms * 1e-3,
            drop_rate: p.drop_rate,
            next_capture_s: first_capture_s,
            noise_m: MODEL_NOISE_M,
            in_flight: std::collections::VecDeque::with_capacity(64),
            frames: 0,
            dropped: 0,
        }
    }

    /// The next capture time, seconds.
    pub fn next_capture_s(&self) -> f64 {
        self.next_capture_s
    }

    /// Captures the frame due now, given the true lateral position at that time.
    pub fn capture<R: Rng>(&mut self, true_lateral_m: f64, rng: &mut R) {
        let t = self.next_capture_s;
        self.next_capture_s += self.period_s;
        self.frames += 1;
        if self.drop_rate > 0.0 && rng.random_bool(self.drop_rate.min(1.0)) {
            self.dropped += 1;
            return;
        }
        let z = true_lateral_m + self.noise_m * gaussian(rng);
        self.in_flight.push_back((
            t + self.latency_s,
            Sighting {
                t_capture_s: t,
                lateral_m: z,
            },
        ));
    }

    /// Advances the frame schedule without capturing (another camera took the frame).
    pub fn skip(&mut self) {
        self.next_capture_s += self.period_s;
        self.frames += 1;
    }

    /// Moves the measurements available by `t_s` into `out`.
    pub fn deliver(&mut self, t_s: f64, out: &mut Vec<Sighting>) {
        while let Some(&(avail, m)) = self.in_flight.front() {
            if avail > t_s {
                break;
            }
            out.push(m);
            self.in_flight.pop_front();
        }
    }
}

/// A standard normal draw (Box-Muller).
pub fn gaussian<R: Rng>(rng: &mut R) -> f64 {
    let u1: f64 = rng.random_range(f64::MIN_POSITIVE..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}
