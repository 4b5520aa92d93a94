//! The simulated lab's stand and hands: the dashboard's lab moves its
//! pendulum to each trial's distance and hangs the ball at each trial's
//! release angle, as the simulated lab always has (a real lab's pendulum
//! stays where its configuration's pivot puts it, and its ball hangs where
//! its magnet is).
//!
//! The trial driver asks ([`Stand::place`]) before it switches the magnet
//! on; the world (`isochron serve`'s in-process world) reads the request
//! ([`Stand::asked`]) on its own thread and moves its true pendulum there.
//! What the lab asks is a command, like a magnet switch: it tells the world
//! nothing of the lab's beliefs, and the lab learns nothing of the world
//! from it. Wait-free: two atomics, written by the control thread.

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

/// Where the lab asks the pendulum to stand and the ball to hang (module docs).
#[derive(Debug)]
pub struct Stand {
    /// The distance from the robot's base to the ball at rest, m (`f64` bits).
    distance_m: AtomicU64,
    /// The signed release angle, degrees (`f64` bits; NaN: none asked).
    hang_deg: AtomicU64,
    /// How often the hands were asked to stop the ball (it hangs still).
    steadied: AtomicU64,
}

impl Stand {
    /// A stand at `distance_m`, no release angle asked yet.
    pub fn at(distance_m: f64) -> Self {
        Self {
            distance_m: AtomicU64::new(distance_m.to_bits()),
            hang_deg: AtomicU64::new(f64::NAN.to_bits()),
            steadied: AtomicU64::new(0),
        }
    }

    /// Asks for the pendulum at `distance_m` and the next hang at
    /// `release_deg` (signed, degrees). Non-finite values change nothing.
    pub fn place(&self, distance_m: f64, release_deg: f64) {
        if distance_m.is_finite() {
            self.distance_m.store(distance_m.to_bits(), Relaxed);
        }
        if release_deg.is_finite() {
            self.hang_deg.store(release_deg.to_bits(), Relaxed);
        }
    }

    /// Asks the hands to stop the ball: it hangs still (the contact step).
    pub fn steady(&self) {
        self.steadied.fetch_add(1, Relaxed);
    }

    /// How often the hands were asked to stop the ball.
    pub fn steadied(&self) -> u64 {
        self.steadied.load(Relaxed)
    }

    /// The distance asked, m, and the release angle asked, degrees (`None`:
    /// none yet).
    pub fn asked(&self) -> (f64, Option<f64>) {
        let d = f64::from_bits(self.distance_m.load(Relaxed));
        let a = f64::from_bits(self.hang_deg.load(Relaxed));
        (d, a.is_finite().then_some(a))
    }
}

#[cfg(test)]
mod tests {
    use super::Stand;

    #[test]
    fn the_stand_keeps_the_last_finite_request() {
        let s = Stand::at(0.6);
        assert_eq!(s.asked(), (0.6, None));
        s.place(0.5, -25.0);
        assert_eq!(s.asked(), (0.5, Some(-25.0)));
        s.place(f64::NAN, f64::INFINITY);
        assert_eq!(s.asked(), (0.5, Some(-25.0)));
    }
}
