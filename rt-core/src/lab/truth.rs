//! The true pendulum as the control thread hands it to the simulated camera
//! (a ring of [`TruthUpdate`]s; the camera reads it through [`TruthView`]).

use rtrb::Consumer;

use crate::pendulum::PendulumSim;
use crate::sim::camera::BallState;
use crate::sim::world::TruePendulum;

/// What the control thread tells the simulated camera about the true pendulum.
// The ring's slots are allocated once: the variants stay inline.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone)]
pub enum TruthUpdate {
    /// From now on the camera shows this pendulum (held or swinging).
    Ball(PendulumSim),
    /// The reality lab (`[world]`): from now on the camera sees this true
    /// pendulum (held at arming; again whenever the tool stopped it). The
    /// camera of the reality lab reads it with [`TruthView::world_ball`].
    World(TruePendulum),
    /// Nothing in view.
    Nothing,
}

/// The simulated camera's view of the truth: the latest pendulum the control
/// thread handed over, advanced to each frame's capture time.
#[derive(Debug)]
pub struct TruthView {
    rx: Consumer<TruthUpdate>,
    ball: Option<PendulumSim>,
    world: Option<TruePendulum>,
}

impl TruthView {
    /// Reads updates from `rx`.
    pub fn new(rx: Consumer<TruthUpdate>) -> Self {
        Self {
            rx,
            ball: None,
            world: None,
        }
    }

    fn drain(&mut self) {
        while let Ok(u) = self.rx.pop() {
            (self.ball, self.world) = match u {
                TruthUpdate::Ball(b) => (Some(b), None),
                TruthUpdate::World(b) => (None, Some(b)),
                TruthUpdate::Nothing => (None, None),
            };
        }
    }

    /// The reality lab's true pendulum as last handed over (the camera
    /// advances it to its frames), `None` in a truthful world.
    pub fn world_ball(&mut self) -> Option<&mut TruePendulum> {
        self.drain();
        self.world.as_mut()
    }

    /// The ball at `t_s` (control clock), `None` when nothing is in view.
    pub fn at(&mut self, t_s: f64) -> Option<BallState> {
        self.drain();
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
