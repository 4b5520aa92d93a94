//! The true pendulum as the control thread hands it to the simulated camera
//! (a ring of [`TruthUpdate`]s; the camera reads it through [`TruthView`]).

use rtrb::Consumer;

use crate::pendulum::PendulumSim;
use crate::sim::camera::BallState;

/// What the control thread tells the simulated camera about the true pendulum.
#[derive(Debug, Clone)]
pub enum TruthUpdate {
    /// From now on the camera shows this pendulum (held or swinging).
    Ball(PendulumSim),
    /// Nothing in view.
    Nothing,
}

/// The simulated camera's view of the truth: the latest pendulum the control
/// thread handed over, advanced to each frame's capture time.
#[derive(Debug)]
pub struct TruthView {
    rx: Consumer<TruthUpdate>,
    ball: Option<PendulumSim>,
}

impl TruthView {
    /// Reads updates from `rx`.
    pub fn new(rx: Consumer<TruthUpdate>) -> Self {
        Self { rx, ball: None }
    }

    /// The ball at `t_s` (control clock), `None` when nothing is in view.
    pub fn at(&mut self, t_s: f64) -> Option<BallState> {
        while let Ok(u) = self.rx.pop() {
            self.ball = match u {
                TruthUpdate::Ball(b) => Some(b),
                TruthUpdate::Nothing => None,
            };
        }
        let ball = self.ball.as_mut()?;
        if t_s > ball.time_s() && ball.advance_to(t_s).is_err() {
            // Too far ahead (a long idle gap): start over from this state.
            return None;
        }
        Some(BallState {
            centre_m: ball.ball_position_m(),
            velocity_mps: ball.ball_velocity_mps(),
        })
    }
}
