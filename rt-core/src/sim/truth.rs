//! The ground truth of a simulated lab: [`SimTruth`], the trial driver's
//! [`TruthObserver`] (the driver holds no truth of its own: `lab/truth.rs`),
//! and the true pendulum as it reaches the simulated camera (a ring of
//! [`TruthUpdate`]s; the camera reads it through [`TruthView`]).
//!
//! A truthful world's true ball is the pendulum the controller's model
//! describes (`pendulum::PendulumSim`); the reality lab's (`[world]`) is
//! `world::TruePendulum` on the true tool (`world::contact::BallOnTool`: the
//! contact bisected between two steps, the ball stopped against the disc,
//! the impulse handed to the simulated robot), judged by the physical judge
//! (`world::judge_physical`).

use std::sync::Arc;

use nalgebra::Vector3;
use rtrb::{Consumer, Producer};

use super::camera::BallState;
use super::world::contact::BallOnTool;
use super::world::judge::judge_strike;
use super::world::{Contact, TruePendulum, World, WorldSample, judge_physical};
use crate::bridge::Refusal;
use crate::control::Commit;
use crate::fri::codec::Joints;
use crate::fri::stats::AtomicJoints;
use crate::lab::TRIAL_TIMEOUT_S;
use crate::lab::truth::{
    MAX_PASSES, PhysicalJudgeError, PhysicalVerdict, StrikeAim, TrialStart, TruthObserver,
};
use crate::pendulum::{PendulumGeometry, PendulumModel, PendulumSim};

/// What the control thread tells the simulated camera about the true pendulum.
#[expect(
    clippy::large_enum_variant,
    reason = "the ring's slots are allocated once: the variants stay inline"
)]
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

/// The true pendulum of a simulated trial (inline: a trial starts without
/// allocating).
#[expect(
    clippy::large_enum_variant,
    reason = "inline, so that a trial starts without allocating"
)]
enum TrueBall {
    /// A truthful world: the pendulum the controller's model describes
    /// (`released`: the coil let go; `intercept_y_m`: the planned
    /// intercept point's `y`, where its passes are counted).
    Ideal {
        ball: PendulumSim,
        released: bool,
        intercept_y_m: f64,
    },
    /// The reality lab (`[world]`).
    World(WorldBall),
}

/// The reality lab's trial: the world's draw and its true ball on the
/// true tool.
struct WorldBall {
    world: World,
    on_tool: BallOnTool,
    /// The true ball's mass (its impulse on the tool), kg.
    mass_kg: f64,
}

/// The simulated lab's ground truth behind the trial driver (see the module
/// documentation): the true ball of the current trial, its passes, the
/// reality lab's contacts (to the simulated robot) and trace (for the
/// physical judge).
pub struct SimTruth {
    to_camera: Producer<TruthUpdate>,
    /// The scenario's `[world]` is simulated (the virtual-time lab: its
    /// camera and robot simulate it too); `false`: a truthful world.
    world: bool,
    /// The simulated robot's true joint angles at each message (the virtual
    /// lab; `None`: the measured ones stand for them).
    joints: Option<Arc<AtomicJoints>>,
    /// The reality lab's contacts of ball and tool, for the simulated
    /// robot's external torques (`None`: no world robot to tell).
    contacts: Option<Producer<Contact>>,
    ball: Option<TrueBall>,
    /// The reality lab's trace of the true world (ghost ball, true disc).
    world_trace: Vec<WorldSample>,
    /// The passes' times, for the physical judge.
    pass_times: Vec<f64>,
    /// The reality lab's true contacts this trial: their times and the true
    /// ball's velocity after each (a strike's outgoing velocity).
    hits: Vec<(f64, Vector3<f64>)>,
}

impl std::fmt::Debug for SimTruth {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimTruth")
            .field("world", &self.world)
            .finish_non_exhaustive()
    }
}

impl SimTruth {
    /// The truth of a lab whose controller runs every `period_s`: the camera
    /// is told through `to_camera`; `world`: the scenario's `[world]` is
    /// simulated (else a truthful world); `joints`: the simulated robot's
    /// true joints; `contacts`: where the reality lab's contacts go.
    pub fn new(
        to_camera: Producer<TruthUpdate>,
        world: bool,
        joints: Option<Arc<AtomicJoints>>,
        contacts: Option<Producer<Contact>>,
        period_s: f64,
    ) -> Self {
        let trace_len = (TRIAL_TIMEOUT_S / period_s) as usize + 1000;
        Self {
            to_camera,
            world,
            joints,
            contacts,
            ball: None,
            world_trace: Vec::with_capacity(trace_len),
            pass_times: Vec::with_capacity(MAX_PASSES),
            hits: Vec::with_capacity(MAX_HITS),
        }
    }
}

/// True contacts kept per trial (a ball pressed against the disc counts one
/// per step).
const MAX_HITS: usize = 1024;

impl TruthObserver for SimTruth {
    fn hang(&mut self, s: &TrialStart<'_>) -> Result<(), Refusal> {
        let world = if self.world {
            // The truth hangs where the uncalibrated lab puts it (plus the
            // world's error), whatever the beliefs say.
            World::for_trial(
                s.scenario,
                s.seed,
                s.index,
                &Vector3::new(s.plan.distance_m, 0.0, s.scenario.task.intercept_height_m),
            )
        } else {
            None
        };
        let ball = if let Some(w) = world {
            let ball = TruePendulum::held_at(
                w.pendulum,
                s.draw.release_angle_deg.to_radians(),
                w.trial.out_of_plane_rad,
                s.t_s,
                w.trial.seed,
            );
            TrueBall::World(WorldBall {
                world: w,
                on_tool: BallOnTool::new(ball),
                mass_kg: s
                    .scenario
                    .world
                    .as_ref()
                    .map_or(0.0, |pw| pw.pendulum.ball_mass_kg),
            })
        } else {
            let sc = s.scenario;
            let model = PendulumModel::from_params(&sc.pendulum).map_err(|_| Refusal::Invalid)?;
            let geometry = PendulumGeometry::new(
                sc.pendulum.length_m,
                s.draw.distance_m,
                sc.task.intercept_height_m,
            )
            .map_err(|_| Refusal::Invalid)?;
            TrueBall::Ideal {
                ball: PendulumSim::held_at(
                    model,
                    geometry,
                    s.draw.release_angle_deg.to_radians(),
                    s.t_s,
                )
                .map_err(|_| Refusal::Invalid)?,
                released: false,
                intercept_y_m: s.plan.intercept_m.y,
            }
        };
        self.ball = Some(ball);
        self.world_trace.clear();
        self.hits.clear();
        Ok(())
    }

    fn show(&mut self) {
        let update = match &self.ball {
            Some(TrueBall::Ideal { ball, .. }) => TruthUpdate::Ball(ball.clone()),
            Some(TrueBall::World(w)) => TruthUpdate::World(w.on_tool.ball.clone()),
            None => return,
        };
        let _ = self.to_camera.push(update);
    }

    fn release(&mut self, t: f64) {
        match self.ball.as_mut() {
            Some(TrueBall::Ideal { ball, released, .. }) => {
                *released = true;
                let at = t.max(ball.time_s());
                if ball.release(at).is_ok() {
                    let _ = self.to_camera.push(TruthUpdate::Ball(ball.clone()));
                }
            }
            // Residual magnetism holds the ball a little longer (the
            // simulated camera knows the same drop time from the switch).
            Some(TrueBall::World(w)) => {
                w.on_tool.drop_at = Some(t + w.world.trial.release_delay_s);
            }
            None => {}
        }
    }

    fn true_joints(&self) -> Option<Joints> {
        self.joints.as_ref().map(|q| q.load())
    }

    fn step(
        &mut self,
        t: f64,
        q_true: &Joints,
        period_s: f64,
        commit: Option<&Commit>,
        passes: &mut Vec<(f64, Vector3<f64>)>,
        at_predicted: &mut Option<Vector3<f64>>,
    ) -> Vector3<f64> {
        match self.ball.as_mut() {
            Some(TrueBall::Ideal {
                ball,
                released,
                intercept_y_m,
            }) => {
                if *released && t > ball.time_s() {
                    // Exact times between the last step and this one: the true
                    // passes through the intercept point's `y` (roots of the true
                    // pendulum, found on a copy), and the true ball centre at the
                    // committed prediction's pass time (the filter's own tests
                    // measure it so; at t* both are the intercept point by
                    // definition).
                    let y = *intercept_y_m;
                    if let Some(tp) = ball.next_crossing_s(y, t - ball.time_s())
                        && passes.len() < MAX_PASSES
                    {
                        let mut at = ball.clone();
                        if at.advance_to(tp).is_ok() {
                            passes.push((tp, at.ball_position_m()));
                        }
                    }
                    if let Some(c) = commit
                        && at_predicted.is_none()
                        && c.predicted_pass_s >= ball.time_s()
                        && c.predicted_pass_s < t
                    {
                        let mut at = ball.clone();
                        if at.advance_to(c.predicted_pass_s).is_ok() {
                            *at_predicted = Some(at.ball_position_m());
                        }
                    }
                    let _ = ball.advance_to(t);
                }
                ball.ball_position_m()
            }
            Some(TrueBall::World(w)) => {
                // The same, on the ghost (the ball without the tool in its
                // way) and the true intercept point.
                let ghost = &w.on_tool.ghost;
                if t > ghost.time_s() {
                    let y = w.world.intercept_m.y;
                    if let Some(tp) = ghost.next_crossing_s(y, t - ghost.time_s())
                        && passes.len() < MAX_PASSES
                    {
                        let mut at = ghost.clone();
                        at.advance_to(tp);
                        passes.push((tp, at.ball_position_m()));
                    }
                    if let Some(c) = commit
                        && at_predicted.is_none()
                        && c.predicted_pass_s >= ghost.time_s()
                        && c.predicted_pass_s < t
                        && !ghost.is_held()
                    {
                        let mut at = ghost.clone();
                        at.advance_to(c.predicted_pass_s);
                        *at_predicted = Some(at.ball_position_m());
                    }
                    w.on_tool.advance(t);
                }
                // The true tool (the world's kinematics at the robot's true
                // joints); the ball stops against its disc.
                let disc = w.world.arm.disc(q_true);
                if let Some(contact) = w.on_tool.meet(
                    t,
                    disc,
                    period_s,
                    w.mass_kg,
                    w.world.session.contact_pulse_s,
                ) {
                    if self.hits.len() < MAX_HITS {
                        self.hits
                            .push((contact.t_s, w.on_tool.ball.ball_velocity_mps()));
                    }
                    // The camera sees the ball where the tool stopped it.
                    let _ = self
                        .to_camera
                        .push(TruthUpdate::World(w.on_tool.ball.clone()));
                    // The robot feels the impulse that stopped it.
                    if let Some(contacts) = self.contacts.as_mut() {
                        let _ = contacts.push(contact);
                    }
                }
                if self.world_trace.len() < self.world_trace.capacity() {
                    self.world_trace.push(WorldSample {
                        t_s: t,
                        ball_m: w.on_tool.ghost.ball_position_m(),
                        disc,
                    });
                }
                w.on_tool.ball.ball_position_m()
            }
            None => Vector3::from_element(f64::NAN),
        }
    }

    fn ball_m(&self) -> Option<Vector3<f64>> {
        match self.ball.as_ref()? {
            TrueBall::Ideal { ball, .. } => Some(ball.ball_position_m()),
            TrueBall::World(w) => Some(w.on_tool.ball.ball_position_m()),
        }
    }

    fn intercept_m(&self) -> Option<Vector3<f64>> {
        match self.ball.as_ref()? {
            TrueBall::Ideal { .. } => None,
            TrueBall::World(w) => Some(w.world.intercept_m),
        }
    }

    /// The physical judge on the true world; its `position_error_m` the
    /// tool-ball distance at t* (the trace's nearest sample).
    fn judge_physical(
        &mut self,
        passes: &[(f64, Vector3<f64>)],
        committed_pass_s: f64,
        tolerance_ms: f64,
        strike: Option<&StrikeAim>,
    ) -> Option<Result<PhysicalVerdict, PhysicalJudgeError>> {
        let Some(TrueBall::World(w)) = self.ball.as_ref() else {
            return None;
        };
        self.pass_times.clear();
        self.pass_times.extend(passes.iter().map(|p| p.0));
        let radius_m = w.world.pendulum.ball_radius_m;
        Some(
            match strike {
                Some(aim) => judge_strike(
                    &self.world_trace,
                    &self.hits,
                    &self.pass_times,
                    committed_pass_s,
                    radius_m,
                    tolerance_ms,
                    w.world.intercept_m.y,
                    aim,
                ),
                None => judge_physical(
                    &self.world_trace,
                    &self.pass_times,
                    committed_pass_s,
                    radius_m,
                    tolerance_ms,
                ),
            }
            .map(|p| {
                let at = self
                    .world_trace
                    .iter()
                    .min_by(|a, b| {
                        (a.t_s - p.t_star_s)
                            .abs()
                            .total_cmp(&(b.t_s - p.t_star_s).abs())
                    })
                    .map_or(f64::NAN, |s| (s.disc.centre_m - s.ball_m).norm());
                PhysicalVerdict {
                    judgement: p,
                    position_error_m: at,
                }
            }),
        )
    }
}
