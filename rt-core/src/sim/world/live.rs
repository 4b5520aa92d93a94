//! The world as a lab's hardware meets it, on any clock: the world process
//! (`isochron world`) runs it on the wall clock behind FRI, a webcam stream
//! and the magnet firmware; its tests run it on a virtual clock.
//!
//! It knows only what the hardware does, never what the service thinks:
//!
//! - **The coil** (`coil`): when the magnet's coil switches on, the
//!   operator hangs the ball on it (a new release: its world drawn for the
//!   release's index, the ball held at a release angle drawn from the
//!   scenario's range, either side, or at the angle the lab's stand asked);
//!   when it switches off, the ball drops
//!   after the world's release delay (residual magnetism).
//! - **The arm** (`step`): every controller cycle the true tool's disc (the
//!   world's kinematics at the robot's true joints) meets the true ball
//!   (`contact::BallOnTool`); a contact is returned for the robot's
//!   external torques.
//! - **The truth** (`take_truth`): each release ends with a
//!   [`ReleaseTruth`], judged physically without the service's prediction:
//!   the arrival is the first time after the release at which the true tool,
//!   having moved, holds still (within [`judge::SETTLE_M`] for
//!   [`HOLD_S`]); t* is the true pass nearest it; contact and success as
//!   `judge::judge_physical`. A struck release (issue #38: whatever the
//!   scenario's mode, the true tool meeting the ball moving along the swing
//!   against it at [`STRIKE_TOOL_SPEED_MPS`] or faster, as a served lab
//!   switched to strike over `PUT /api/params` does; a tool at rest is a
//!   stop even in a strike scenario) is judged as a strike
//!   (`judge::judge_strike`): the arrival is the true tool's crossing of the
//!   true intercept point's `y` along the return, t* the true pass nearest
//!   the first contact (without one, nearest that crossing), and the ball's
//!   outgoing speed after the contact against the scenario's target
//!   (`task.strike_speed_mps` along the swing's horizontal) when the
//!   scenario says strike, else reported without one (`aim_known: false`),
//!   in [`ReleaseTruth::strike`]. A release ends [`RECORD_S`] after the arm
//!   began to move (or the drop, if later), [`MAX_RECORD_S`] after the drop
//!   at the latest, or when the coil switches on again.
//!
//! One session for the world's life (its robot, camera and geometry are
//! drawn once: session 0); the pendulum's per-release draws follow the
//! release index. A scenario without `[world]` runs as a truthful world
//! (`WorldParams::default()`: every draw the belief).

use nalgebra::Vector3;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use super::contact::{BallOnTool, Contact};
use super::judge::{self, SETTLE_M, StrikeAim, WorldSample};
use super::{TruePendulum, World, WorldParams};
use crate::control::report::StrikeJudgement;
use crate::fri::codec::Joints;
use crate::params::{Scenario, TaskMode};
use crate::trajectory::strike::STRIKE_RETURN_SIGN;

/// A release's truth is concluded this long after the arm began to move
/// (or the ball dropped, if later), s; an arm that has not moved is waited
/// for until [`MAX_RECORD_S`].
pub const RECORD_S: f64 = 8.0;
/// ... and at the latest this long after the ball dropped, whether the arm
/// moved or not, s (a lab that waits long for its prediction, as a starved
/// machine's did 9.7 s, still has its motion in the record).
pub const MAX_RECORD_S: f64 = 30.0;
/// The arrival: the true tool holds within `SETTLE_M` for this long, s.
pub const HOLD_S: f64 = 0.2;
/// The arm counts as moving once its tool is this far from where it was at the drop, m.
pub const MOVED_M: f64 = 0.05;
/// Most samples of a release's world trace (`MAX_RECORD_S` at 1 ms and more).
const TRACE_CAP: usize = 32_768;
/// Most true passes kept per release.
const PASS_CAP: usize = 64;
/// Most contacts kept per release.
const HIT_CAP: usize = 64;

const ANGLE_STREAM: u64 = 0x6c69_7665_616e_676c;

/// What the world saw of one release.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReleaseTruth {
    /// Release index (0, 1, ...) in the world's life.
    pub index: usize,
    /// When the coil switched off, world clock, s.
    pub coil_off_s: f64,
    /// When the ball dropped (coil off + the residual magnetism's delay), s.
    pub drop_s: f64,
    /// The release angle the operator hung the ball at (signed), degrees.
    pub release_angle_deg: f64,
    /// The true pass through the true intercept point nearest the arrival, s.
    pub t_star_s: Option<f64>,
    /// When the true tool came to rest at its target, s.
    pub arrival_s: Option<f64>,
    /// `arrival - t*`, ms (negative: early).
    pub timing_error_ms: Option<f64>,
    /// The ball met the tool in t*'s pass.
    pub contact: bool,
    /// When it did (the first sample touching), s.
    pub contact_s: Option<f64>,
    /// Contact and |timing error| within the scenario's tolerance.
    pub success: bool,
    /// Why the release was not judged (the arm never moved or never settled,
    /// the ball never passed), else `None`.
    pub not_judged: Option<String>,
    /// A strike's figures (strike mode): then `arrival_s` is the true
    /// tool's crossing of the intercept point and `success` needs the
    /// outgoing speed too.
    pub strike: Option<StrikeJudgement>,
}

struct Release {
    index: usize,
    angle_deg: f64,
    coil_off_s: f64,
    drop_s: f64,
    /// When the arm's disc first stood [`MOVED_M`] from where it was at the drop, s.
    moved_s: Option<f64>,
    passes: Vec<f64>,
    trace: Vec<WorldSample>,
    /// The contacts: their times and the true ball's velocity after each.
    hits: Vec<(f64, Vector3<f64>)>,
}

/// The world of a lab's hardware (module docs).
pub struct LiveWorld {
    scenario: Scenario,
    seed: u64,
    believed_intercept_m: Vector3<f64>,
    next_index: usize,
    world: World,
    on_tool: BallOnTool,
    release: Option<Release>,
    done: Vec<ReleaseTruth>,
    last_t_s: Option<f64>,
    /// The release angle the lab's stand asked for the next hang, degrees
    /// (`lab::Stand`; `None`: drawn from the scenario's range).
    asked_hang_deg: Option<f64>,
}

impl std::fmt::Debug for LiveWorld {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LiveWorld")
            .field("next_index", &self.next_index)
            .finish_non_exhaustive()
    }
}

impl LiveWorld {
    /// The world of `scenario` (its `[world]`, or a truthful one) for a lab
    /// whose pendulum is believed to hang at rest at `believed_intercept_m`;
    /// the ball hangs at rest at `t_s`.
    pub fn new(
        scenario: &Scenario,
        seed: u64,
        believed_intercept_m: Vector3<f64>,
        t_s: f64,
    ) -> Self {
        let mut scenario = scenario.clone();
        scenario.world.get_or_insert_with(WorldParams::default);
        let world = World::in_session(&scenario, seed, 0, 0, &believed_intercept_m)
            .unwrap_or_else(|| unreachable!("the scenario has a [world]"));
        let mut ball = TruePendulum::held_at(world.pendulum, 0.0, 0.0, t_s, world.trial.seed);
        ball.release(t_s);
        Self {
            scenario,
            seed,
            believed_intercept_m,
            next_index: 0,
            world,
            on_tool: BallOnTool::new(ball),
            release: None,
            done: Vec::new(),
            last_t_s: None,
            asked_hang_deg: None,
        }
    }

    /// The world's session draws and the current release's (for the robot,
    /// the camera and the geometry).
    pub fn world(&self) -> &World {
        &self.world
    }

    /// The true ball.
    pub fn ball(&self) -> &TruePendulum {
        &self.on_tool.ball
    }

    /// Releases the world has begun (hung the ball for).
    pub fn releases(&self) -> usize {
        self.next_index
    }

    /// The simulated lab's stand (`lab::Stand`) moves the pendulum at `t_s`
    /// so that the ball hangs at rest `distance_m` from the robot's base
    /// (along the same bearing, at the same height), and the hands hang the
    /// ball at `hang_deg` (signed; `None`: drawn from the scenario's range).
    /// A ball at rest moves now; a ball held on the magnet moves with the
    /// magnet, and is hung again at a newly asked angle; a swinging release
    /// keeps its place, and the next hang is at the new one.
    pub fn place_stand(&mut self, t_s: f64, distance_m: f64, hang_deg: Option<f64>) {
        let asked = hang_deg.filter(|a| a.is_finite() && a.abs() < 89.0);
        let new_angle = asked.is_some() && asked != self.asked_hang_deg;
        if asked.is_some() {
            self.asked_hang_deg = asked;
        }
        let b = self.believed_intercept_m;
        let r = b.x.hypot(b.y);
        let moved = distance_m.is_finite() && distance_m > 0.0 && (r - distance_m).abs() >= 1e-9;
        if moved {
            let (ux, uy) = if r > 1e-9 {
                (b.x / r, b.y / r)
            } else {
                (1.0, 0.0)
            };
            self.believed_intercept_m = Vector3::new(ux * distance_m, uy * distance_m, b.z);
        }
        if !moved && !new_angle {
            return;
        }
        let held = self.on_tool.ball.is_held() && self.on_tool.drop_at.is_none();
        let index = match self.release.as_mut() {
            Some(r) if held => {
                if new_angle && let Some(a) = asked {
                    r.angle_deg = a;
                }
                r.index
            }
            // Swinging: it keeps its place.
            Some(_) => return,
            // At rest (or its last release recorded): the operator moves
            // the stand and stills the ball there.
            None if moved => self.next_index.saturating_sub(1),
            None => return,
        };
        if let Some(w) = World::in_session(
            &self.scenario,
            self.seed,
            0,
            index,
            &self.believed_intercept_m,
        ) {
            self.world = w;
        }
        let angle_deg = self.release.as_ref().filter(|_| held).map(|r| r.angle_deg);
        let mut ball = TruePendulum::held_at(
            self.world.pendulum,
            angle_deg.unwrap_or(0.0).to_radians(),
            if angle_deg.is_some() {
                self.world.trial.out_of_plane_rad
            } else {
                0.0
            },
            t_s,
            self.world.trial.seed,
        );
        if angle_deg.is_none() {
            ball.release(t_s);
        }
        self.on_tool = BallOnTool::new(ball);
    }

    /// The operator stops the ball by hand at `t_s` (the contact step asks
    /// it to hang still): it hangs at rest where the stand stands (the
    /// release in progress ends, as when the ball is hung again). A ball
    /// held on the magnet stays there.
    pub fn steady(&mut self, t_s: f64) {
        if self.on_tool.ball.is_held() && self.on_tool.drop_at.is_none() {
            return;
        }
        // Hanging still already (hands that stop a still ball change nothing).
        let p = &self.world.pendulum;
        let bottom = p.pivot_m - Vector3::z() * p.length_m;
        let b = &self.on_tool.ball;
        if b.ball_velocity_mps().norm() < 1e-6 && (b.ball_position_m() - bottom).norm() < 1e-6 {
            return;
        }
        self.conclude();
        // Where the stand stands now (it may have moved while the ball swung).
        if let Some(w) = World::in_session(
            &self.scenario,
            self.seed,
            0,
            self.next_index.saturating_sub(1),
            &self.believed_intercept_m,
        ) {
            self.world = w;
        }
        let mut ball =
            TruePendulum::held_at(self.world.pendulum, 0.0, 0.0, t_s, self.world.trial.seed);
        ball.release(t_s);
        self.on_tool = BallOnTool::new(ball);
    }

    /// The coil switched on (`true`) or off at `t_s`.
    pub fn coil(&mut self, on: bool, t_s: f64) {
        let held = self.on_tool.ball.is_held();
        if on {
            if held && self.on_tool.drop_at.is_none() {
                return;
            }
            // The operator takes the ball and hangs it on the magnet.
            self.conclude();
            let index = self.next_index;
            self.next_index += 1;
            if let Some(w) = World::in_session(
                &self.scenario,
                self.seed,
                0,
                index,
                &self.believed_intercept_m,
            ) {
                self.world = w;
            }
            let angle_deg = self
                .asked_hang_deg
                .unwrap_or_else(|| self.release_angle_deg(index));
            let ball = TruePendulum::held_at(
                self.world.pendulum,
                angle_deg.to_radians(),
                self.world.trial.out_of_plane_rad,
                t_s,
                self.world.trial.seed,
            );
            self.on_tool = BallOnTool::new(ball);
            self.release = Some(Release {
                index,
                angle_deg,
                coil_off_s: f64::NAN,
                drop_s: f64::NAN,
                moved_s: None,
                passes: Vec::with_capacity(PASS_CAP),
                trace: Vec::with_capacity(TRACE_CAP),
                hits: Vec::with_capacity(HIT_CAP),
            });
        } else if held
            && self.on_tool.drop_at.is_none()
            && let Some(r) = self.release.as_mut()
        {
            let drop_s = t_s + self.world.trial.release_delay_s;
            self.on_tool.drop_at = Some(drop_s);
            r.coil_off_s = t_s;
            r.drop_s = drop_s;
        }
    }

    /// One controller cycle at `t_s` with the robot's true joints `q_true`:
    /// moves the ball, meets the tool, records the release. Returns the
    /// contact the robot feels, if the ball met the tool.
    pub fn step(&mut self, t_s: f64, q_true: &Joints) -> Option<Contact> {
        let period_s = self.last_t_s.map_or(1e-3, |l| (t_s - l).max(1e-6));
        if self.last_t_s.is_some_and(|l| t_s <= l) {
            return None;
        }
        self.last_t_s = Some(t_s);
        let y = self.world.intercept_m.y;
        if let Some(r) = self.release.as_mut() {
            let ghost = &self.on_tool.ghost;
            if !ghost.is_held()
                && let Some(tp) = ghost.next_crossing_s(y, t_s - ghost.time_s())
                && r.passes.len() < PASS_CAP
            {
                r.passes.push(tp);
            }
        }
        self.on_tool.advance(t_s);
        let disc = self.world.arm.disc(q_true);
        let mass_kg = self
            .scenario
            .world
            .as_ref()
            .map_or(0.0, |w| w.pendulum.ball_mass_kg);
        let contact = self.on_tool.meet(
            t_s,
            disc,
            period_s,
            mass_kg,
            self.world.session.contact_pulse_s,
        );
        let mut over = false;
        if let Some(r) = self.release.as_mut()
            && r.drop_s.is_finite()
        {
            if let Some(c) = contact.as_ref()
                && r.hits.len() < HIT_CAP
            {
                r.hits.push((c.t_s, self.on_tool.ball.ball_velocity_mps()));
            }
            if r.trace.len() < TRACE_CAP {
                r.trace.push(WorldSample {
                    t_s,
                    ball_m: self.on_tool.ghost.ball_position_m(),
                    disc,
                });
            }
            if r.moved_s.is_none()
                && r.trace
                    .first()
                    .is_some_and(|f| (disc.centre_m - f.disc.centre_m).norm() > MOVED_M)
            {
                r.moved_s = Some(t_s);
            }
            // Until RECORD_S after the arm's motion began; an arm that has
            // not moved yet may still (MAX_RECORD_S after the drop at most).
            over = r.moved_s.is_some_and(|m| t_s > m.max(r.drop_s) + RECORD_S)
                || t_s > r.drop_s + MAX_RECORD_S;
        }
        if over {
            self.conclude();
        }
        contact
    }

    /// The releases concluded since the last call, oldest first.
    pub fn take_truth(&mut self) -> Vec<ReleaseTruth> {
        std::mem::take(&mut self.done)
    }

    /// Concludes the release in progress (if the ball dropped), as at the end
    /// of the world's life.
    pub fn finish(&mut self) {
        self.conclude();
    }

    fn release_angle_deg(&self, index: usize) -> f64 {
        let mix = self
            .seed
            .wrapping_mul(0x9E37_79B9_7F4A_7C15)
            .wrapping_add((index as u64).wrapping_mul(0xD1B5_4A32_D192_ED03))
            ^ ANGLE_STREAM;
        let mut rng = ChaCha8Rng::seed_from_u64(mix);
        let a = self
            .scenario
            .pendulum
            .release_angle_deg
            .lerp(rng.random_range(0.0..=1.0));
        if rng.random_bool(0.5) { a } else { -a }
    }

    fn conclude(&mut self) {
        let Some(r) = self.release.take() else {
            return;
        };
        if !r.drop_s.is_finite() {
            // Never dropped: nothing to tell.
            return;
        }
        let tolerance_ms = self.scenario.success.timing_tolerance_ms;
        let radius_m = self.world.pendulum.ball_radius_m;
        let mut truth = ReleaseTruth {
            index: r.index,
            coil_off_s: r.coil_off_s,
            drop_s: r.drop_s,
            release_angle_deg: r.angle_deg,
            t_star_s: None,
            arrival_s: None,
            timing_error_ms: None,
            contact: false,
            contact_s: None,
            success: false,
            not_judged: None,
            strike: None,
        };
        if let Some(aim) = self.strike_aim(&r) {
            self.judge_strike(&r, &aim, &mut truth);
            self.done.push(truth);
            return;
        }
        match settled_at(&r.trace) {
            Err(why) => truth.not_judged = Some(why.into()),
            Ok((arrival_guess, end)) => {
                match judge::judge_physical(
                    &r.trace[..=end],
                    &r.passes,
                    arrival_guess,
                    radius_m,
                    tolerance_ms,
                ) {
                    Ok(p) => {
                        // The contact on the whole trace (the arm may have
                        // settled before the pass): t*'s pass window.
                        let contact_s = judge::judge_physical(
                            &r.trace,
                            &r.passes,
                            p.t_star_s,
                            radius_m,
                            tolerance_ms,
                        )
                        .ok()
                        .and_then(|full| full.contact_s);
                        truth.t_star_s = Some(p.t_star_s);
                        truth.arrival_s = Some(p.arrival_s);
                        truth.timing_error_ms = Some(p.timing_error_ms);
                        truth.contact = contact_s.is_some();
                        truth.contact_s = contact_s;
                        truth.success =
                            contact_s.is_some() && p.timing_error_ms.abs() <= tolerance_ms;
                    }
                    Err(e) => truth.not_judged = Some(e.to_string()),
                }
            }
        }
        self.done.push(truth);
    }
}

impl LiveWorld {
    /// Whether a release is judged as a strike, and against what. What
    /// physically happened decides ([`struck_along`]: the true tool moving
    /// along the swing, against the ball, at [`STRIKE_TOOL_SPEED_MPS`] or
    /// faster at the first contact, or crossing the intercept point so
    /// without one), whatever the scenario's mode (the service may switch
    /// it over `PUT /api/params` either way); a struck release is judged
    /// against the scenario's aim when its file says `task.mode =
    /// "strike"`, else with an aim the world cannot know (the planned speed
    /// and target are the service's): NaN, so the truth says `aim_known:
    /// false` and its success is the contact in time alone. `None`: a stop.
    fn strike_aim(&self, r: &Release) -> Option<StrikeAim> {
        let task = &self.scenario.task;
        let return_sign = struck_along(r, self.world.intercept_m.y)?;
        if task.mode == TaskMode::Strike {
            return Some(StrikeAim {
                planned_tool_speed_mps: task.strike_speed_mps,
                target_ball_speed_mps: task.strike_speed_mps
                    * task.strike_direction_deg.to_radians().cos(),
                return_sign: STRIKE_RETURN_SIGN,
                predicted: None,
            });
        }
        Some(StrikeAim {
            planned_tool_speed_mps: f64::NAN,
            target_ball_speed_mps: f64::NAN,
            return_sign,
            predicted: None,
        })
    }

    /// A strike release's truth (module docs): `judge::judge_strike` with
    /// `aim`, the pass nearest the first contact after the drop (or the
    /// true tool's crossing of the intercept point).
    fn judge_strike(&self, r: &Release, aim: &StrikeAim, truth: &mut ReleaseTruth) {
        let y = self.world.intercept_m.y;
        let sign = aim.return_sign;
        let crossing = r.trace.windows(2).find_map(|w| {
            let ahead = |s: &WorldSample| (s.disc.centre_m.y - y) * sign;
            (ahead(&w[0]) < 0.0 && ahead(&w[1]) >= 0.0).then_some(w[1].t_s)
        });
        let Some(near_s) = r
            .hits
            .iter()
            .find(|h| h.0 >= r.drop_s)
            .map(|h| h.0)
            .or(crossing)
        else {
            truth.not_judged =
                Some("the tool neither met the ball nor crossed the intercept point".into());
            return;
        };
        match judge::judge_strike(
            &r.trace,
            &r.hits,
            &r.passes,
            near_s,
            self.world.pendulum.ball_radius_m,
            self.scenario.success.timing_tolerance_ms,
            y,
            aim,
        ) {
            Ok(p) => {
                truth.t_star_s = Some(p.t_star_s);
                truth.arrival_s = Some(p.arrival_s).filter(|a| a.is_finite());
                truth.timing_error_ms = Some(p.timing_error_ms).filter(|e| e.is_finite());
                truth.contact = p.contact_s.is_some();
                truth.contact_s = p.contact_s;
                // Without the aim the world judges what it can: the contact
                // in time (the outgoing speed is reported, not judged).
                truth.success =
                    p.hit_in_time && p.strike.is_some_and(|k| k.speed_ok || !k.aim_known);
                truth.strike = p.strike;
            }
            Err(e) => truth.not_judged = Some(e.to_string()),
        }
    }
}

/// The true tool's speed along the swing's horizontal (`y`), against the
/// ball, from which a release whose scenario does not say strike is judged
/// as one, m/s. A stop's tool meets the ball at rest (a Hopf profile ends
/// at rest: 20 ms late, the tolerance, it still moves at about 1 mm/s; even
/// 200 ms late, 0.12 m/s along a path that runs towards the pendulum, `x`,
/// with a few centimetres of `y` at most: under 0.03 m/s along `y`); a
/// strike meets it at `strike_speed_mps * cos(elevation)` along the return
/// (0.47 m/s for the default 0.5 m/s rising 20 deg).
pub const STRIKE_TOOL_SPEED_MPS: f64 = 0.1;

/// The span the true tool's and ball's velocities are read over before a
/// contact (the chord ends at the touching sample), s.
const STRIKE_CHORD_S: f64 = 0.01;

/// Whether the release was struck, from what physically happened: at the
/// first contact after the drop the true tool moved along the swing's
/// horizontal against the ball's approach (the ball's velocity before the
/// touch, its free swing's) at [`STRIKE_TOOL_SPEED_MPS`] or faster; without
/// a contact, the tool crossed the intercept point's `y` that fast (a
/// stroke that missed the ball). The return's sign of `y`, or `None`: a
/// stop (or no motion along the swing).
fn struck_along(r: &Release, intercept_y_m: f64) -> Option<f64> {
    let trace = &r.trace;
    let chord = |k: usize| -> Option<(Vector3<f64>, Vector3<f64>)> {
        let t = trace.get(k)?.t_s;
        let i = trace[..k]
            .iter()
            .rposition(|s| s.t_s <= t - STRIKE_CHORD_S)?;
        let dt = (t - trace[i].t_s).max(1e-9);
        Some((
            (trace[k].disc.centre_m - trace[i].disc.centre_m) / dt,
            (trace[k].ball_m - trace[i].ball_m) / dt,
        ))
    };
    if let Some(hit) = r.hits.iter().find(|h| h.0 >= r.drop_s) {
        let k = trace.iter().rposition(|s| s.t_s <= hit.0)?;
        let (tool, ball) = chord(k)?;
        // Against the ball's approach (a ball nearly at rest: along the tool's).
        let sign = if ball.y.abs() > 1e-3 {
            -ball.y.signum()
        } else {
            tool.y.signum()
        };
        return (tool.y * sign >= STRIKE_TOOL_SPEED_MPS).then_some(sign);
    }
    let ahead = |s: &WorldSample| s.disc.centre_m.y - intercept_y_m;
    let k = (1..trace.len()).find(|&k| {
        let (a, b) = (ahead(&trace[k - 1]), ahead(&trace[k]));
        (a < 0.0) != (b < 0.0)
            && chord(k).is_some_and(|(tool, _)| tool.y.abs() >= STRIKE_TOOL_SPEED_MPS)
    })?;
    chord(k).map(|(tool, _)| tool.y.signum())
}

/// Where the tool first holds still after moving: the sample at which it
/// starts holding (an estimate of the arrival) and the index of the hold's
/// last sample (within `SETTLE_M` of where it was `HOLD_S` after it began,
/// before the tool leaves again: the judge's trace ends there, its final
/// point).
fn settled_at(trace: &[WorldSample]) -> Result<(f64, usize), &'static str> {
    let first = trace
        .first()
        .ok_or("the world saw no step after the drop")?;
    let start = trace
        .iter()
        .position(|s| (s.disc.centre_m - first.disc.centre_m).norm() > MOVED_M)
        .ok_or("the arm did not move after the release")?;
    for i in start..trace.len() {
        let Some(end) = trace[i..]
            .iter()
            .position(|s| s.t_s >= trace[i].t_s + HOLD_S)
            .map(|k| i + k)
        else {
            break;
        };
        let at = trace[end].disc.centre_m;
        if trace[i..=end]
            .iter()
            .all(|s| (s.disc.centre_m - at).norm() <= SETTLE_M)
        {
            // The final point is where the tool rests last before it leaves
            // (home again): the end of the hold, as a judge that watches the
            // arm until it returns sees it.
            let last = trace[end..]
                .iter()
                .position(|s| (s.disc.centre_m - at).norm() > SETTLE_M)
                .map_or(trace.len() - 1, |k| end + k - 1);
            return Ok((trace[i].t_s, last));
        }
    }
    Err("the arm did not come to rest after moving")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::world::TrueArm;

    fn joints_reaching(arm: &TrueArm, target: &Vector3<f64>) -> Joints {
        // A crude search over two joints is enough for a test: the tool near
        // `target` (within a few cm), from the lab's home posture.
        let mut best = ([0.0, 0.6, 0.0, -1.2, 0.0, 0.9, 0.0], f64::INFINITY);
        for a in 0..60 {
            for b in 0..60 {
                let q = [
                    0.0,
                    -0.2 + f64::from(a) * 0.025,
                    0.0,
                    -2.0 + f64::from(b) * 0.03,
                    0.0,
                    0.9,
                    0.0,
                ];
                let d = (arm.tool_point(&q) - target).norm();
                if d < best.1 {
                    best = (q, d);
                }
            }
        }
        best.0
    }

    fn lab() -> (Scenario, Vector3<f64>) {
        let s = Scenario::default();
        let intercept = Vector3::new(s.task.distance_m.lerp(0.5), 0.0, s.task.intercept_height_m);
        (s, intercept)
    }

    #[test]
    fn a_release_without_the_arm_is_not_judged_and_the_ball_swings_through_the_rest_point() {
        let (s, intercept) = lab();
        let mut w = LiveWorld::new(&s, 1, intercept, 0.0);
        let home = [0.0, 0.3, 0.0, -1.5, 0.0, 0.9, 0.0];
        w.coil(true, 0.1);
        assert!(w.ball().is_held());
        w.coil(false, 1.0);
        let mut t = 0.1;
        let mut min_dist = f64::INFINITY;
        while t < 1.0 + MAX_RECORD_S + 0.1 {
            t += 0.005;
            assert!(w.step(t, &home).is_none(), "the arm at home is never hit");
            min_dist = min_dist.min((w.ball().ball_position_m() - w.world().intercept_m).norm());
        }
        // The ball passes through its rest point (the true intercept point).
        assert!(min_dist < 0.01, "{min_dist}");
        let truth = w.take_truth();
        assert_eq!(truth.len(), 1);
        let r = &truth[0];
        assert_eq!(r.index, 0);
        assert!((r.coil_off_s - 1.0).abs() < 1e-12);
        // A truthful world drops after the believed release delay.
        let delay = r.drop_s - r.coil_off_s;
        assert!(
            (delay - s.control.release_delay_prior_ms * 1e-3).abs() < 1e-9,
            "{delay}"
        );
        assert!(!r.success);
        assert_eq!(
            r.not_judged.as_deref(),
            Some("the arm did not move after the release")
        );
    }

    #[test]
    fn the_stand_moves_the_ball_at_rest_and_on_the_magnet_and_the_next_hang_takes_the_asked_angle()
    {
        let (s, intercept) = lab();
        let mut w = LiveWorld::new(&s, 1, intercept, 0.0);
        let home = [0.0, 0.3, 0.0, -1.5, 0.0, 0.9, 0.0];
        let horizontal = |w: &LiveWorld| w.world().intercept_m.x.hypot(w.world().intercept_m.y);
        // At rest: the ball moves now, and rests over the new intercept point.
        w.place_stand(0.1, intercept.x + 0.1, None);
        assert!((horizontal(&w) - (intercept.x + 0.1)).abs() < 1e-9);
        w.step(0.2, &home);
        let rest = (w.ball().ball_position_m() - w.world().intercept_m).norm();
        assert!(rest < 1e-6, "{rest}");
        // The next hang at the asked angle (the lab's trial), at the stand's place.
        w.place_stand(0.3, intercept.x + 0.1, Some(-20.0));
        w.coil(true, 0.4);
        assert!(w.ball().is_held());
        let out = w.ball().ball_position_m() - w.world().intercept_m;
        let angle = out.y.atan2(s.pendulum.length_m - out.z).to_degrees();
        assert!((angle.abs() - 20.0).abs() < 0.5, "{angle}");
        // Held on the magnet: the ball moves with the stand, at its angle.
        let before = w.ball().ball_position_m() - w.world().intercept_m;
        w.place_stand(0.5, intercept.x - 0.05, None);
        assert!((horizontal(&w) - (intercept.x - 0.05)).abs() < 1e-9);
        let after = w.ball().ball_position_m() - w.world().intercept_m;
        assert!((after - before).norm() < 1e-9, "{before} {after}");
        // Another angle asked while it is held (the pendulum step's prompt):
        // hung again there.
        w.place_stand(0.55, intercept.x - 0.05, Some(1.0));
        let out = w.ball().ball_position_m() - w.world().intercept_m;
        let angle = out.y.atan2(s.pendulum.length_m - out.z).to_degrees();
        assert!((angle.abs() - 1.0).abs() < 0.1, "{angle}");
        assert!(w.ball().is_held());
        // Swinging: the release keeps its place; the next hang is at the new one.
        w.coil(false, 0.6);
        w.step(1.0, &home);
        let swinging = w.world().intercept_m;
        w.place_stand(1.1, intercept.x, None);
        assert_eq!(w.world().intercept_m, swinging);
        w.coil(true, 1.2);
        assert!((horizontal(&w) - intercept.x).abs() < 1e-9);
        assert_eq!(
            w.take_truth().len(),
            1,
            "the swinging release was concluded"
        );
    }

    #[test]
    fn a_release_is_recorded_past_the_arms_late_motion_and_judged() {
        // The arm moves 12 s after the drop (a lab that waited long for its
        // prediction): the release is still recorded, and the arm that
        // settled is judged, not cut off at RECORD_S after the drop.
        let (s, intercept) = lab();
        let mut w = LiveWorld::new(&s, 4, intercept, 0.0);
        let home = [0.0, 0.3, 0.0, -1.5, 0.0, 0.9, 0.0];
        let arm = w.world().arm;
        let there = joints_reaching(&arm, &w.world().intercept_m);
        w.coil(true, 0.0);
        w.coil(false, 0.5);
        let moves = 0.5 + 12.0;
        let mut t = 0.0;
        loop {
            assert!(t < 0.5 + MAX_RECORD_S + 1.0, "no truth by {t} s");
            t += 0.005;
            w.step(t, if t < moves { &home } else { &there });
            if let Some(r) = w.take_truth().pop() {
                assert!(t >= moves + RECORD_S, "concluded at {t} s");
                assert!(t < moves + RECORD_S + 0.01, "concluded at {t} s");
                let arrival = r.arrival_s.expect("the arm's arrival is judged");
                assert!((arrival - moves).abs() < 0.05, "{r:?}");
                assert_eq!(r.not_judged, None, "{r:?}");
                return;
            }
        }
    }

    #[test]
    fn a_tool_at_the_intercept_point_is_hit_felt_and_judged_on_the_true_pass() {
        // Early by 300 ms: contact, not in time; by 5 ms: a success.
        // A scenario that says strike (a lab switched to stop over REST)
        // still has its resting tool judged as a stop.
        for mode in [TaskMode::Stop, TaskMode::Strike] {
            for (early_s, success) in [(0.3, false), (0.005, true)] {
                hit_and_judge(early_s, success, mode);
            }
        }
    }

    fn hit_and_judge(early_s: f64, success: bool, mode: TaskMode) {
        let (mut s, intercept) = lab();
        s.task.mode = mode;
        let mut w = LiveWorld::new(&s, 2, intercept, 0.0);
        let home = [0.0, 0.3, 0.0, -1.5, 0.0, 0.9, 0.0];
        let arm = w.world().arm;
        let at_intercept = joints_reaching(&arm, &w.world().intercept_m);
        let reach = (arm.tool_point(&at_intercept) - w.world().intercept_m).norm();
        assert!(
            reach < 0.03,
            "the test's posture reaches {reach} m from the intercept"
        );
        w.coil(true, 0.0);
        w.coil(false, 0.5);
        // Find the first pass of the free ball (no arm in the way).
        let mut probe = LiveWorld::new(&s, 2, intercept, 0.0);
        probe.coil(true, 0.0);
        probe.coil(false, 0.5);
        let mut t = 0.0;
        let mut first_pass = None;
        let mut last_y = probe.ball().ball_position_m().y - probe.world().intercept_m.y;
        while t < 5.0 && first_pass.is_none() {
            t += 0.001;
            probe.step(t, &home);
            let y = probe.ball().ball_position_m().y - probe.world().intercept_m.y;
            if !probe.ball().is_held() && y.signum() != last_y.signum() {
                first_pass = Some(t);
            }
            last_y = y;
        }
        let first_pass = first_pass.expect("the free ball passes the intercept point");
        // The arm jumps to the intercept point `early_s` before the pass (it
        // was home until then) and stays.
        let arrive = first_pass - early_s;
        let mut contacts = Vec::new();
        let mut t = 0.0;
        while t < arrive + RECORD_S + 0.1 {
            t += 0.001;
            let q = if t < arrive { home } else { at_intercept };
            if let Some(c) = w.step(t, &q) {
                contacts.push(c);
            }
        }
        assert!(!contacts.is_empty(), "the ball met the tool");
        let c = contacts[0];
        assert!(
            (c.t_s - first_pass).abs() < 0.1,
            "{} vs {first_pass}",
            c.t_s
        );
        if early_s > 0.1 {
            // The impulse on a tool at rest: a 57 g ball stopped from about
            // 1 m/s, 0.01-0.2 N s (a tool jumping onto the ball gives more).
            let j = c.impulse_ns.norm();
            assert!((0.005..0.2).contains(&j), "{j}");
        }
        let truth = w.take_truth();
        assert_eq!(truth.len(), 1, "{truth:?}");
        let r = &truth[0];
        assert!(r.not_judged.is_none(), "{r:?}");
        assert!(r.contact, "{r:?}");
        // t* is the first true pass; the arrival is the jump (a step), so
        // the timing error is `-early_s`.
        let t_star = r.t_star_s.unwrap();
        assert!(
            (t_star - first_pass).abs() < 0.002,
            "{t_star} vs {first_pass}"
        );
        let err = r.timing_error_ms.unwrap();
        assert!((err + early_s * 1e3).abs() < 3.0, "{err}");
        assert_eq!(r.success, success, "{r:?}");
        // A tool at rest stops the ball: judged as a stop.
        assert!(r.strike.is_none(), "{r:?}");
    }

    #[test]
    fn a_strike_release_is_judged_at_the_tools_crossing_with_the_balls_outgoing_speed() {
        // Strike mode: the tool sweeps along -y through the intercept point
        // at 0.5 m/s (the base joint turning), crossing it `late_s` after a
        // pass towards +y; the truth is the strike's: the crossing against
        // t*, the ball sent back. A world whose scenario says stop (a served
        // lab switched to strike over PUT /api/params) judges the same
        // sweep as a strike by what happened, without the aim it cannot
        // know: the speeds reported, the contact in time its success.
        for (late_s, in_time, mode) in [
            (0.005, true, TaskMode::Strike),
            (0.06, false, TaskMode::Strike),
            (0.005, true, TaskMode::Stop),
            (0.06, false, TaskMode::Stop),
        ] {
            let (mut s, intercept) = lab();
            s.task.mode = mode;
            s.task.strike_speed_mps = 0.5;
            s.task.strike_direction_deg = 0.0;
            let home = [0.0, 0.3, 0.0, -1.5, 0.0, 0.9, 0.0];
            // The free ball's first pass towards +y (no arm in the way).
            let mut probe = LiveWorld::new(&s, 2, intercept, 0.0);
            probe.coil(true, 0.0);
            probe.coil(false, 0.5);
            let (mut t, mut pass) = (0.0, None);
            let mut last_y = probe.ball().ball_position_m().y - intercept.y;
            while t < 8.0 && pass.is_none() {
                t += 0.001;
                probe.step(t, &home);
                let y = probe.ball().ball_position_m().y - intercept.y;
                if !probe.ball().is_held() && last_y < 0.0 && y >= 0.0 {
                    pass = Some(t);
                }
                last_y = y;
            }
            let pass = pass.expect("a pass towards +y");
            let mut w = LiveWorld::new(&s, 2, intercept, 0.0);
            let arm = w.world().arm;
            let at = joints_reaching(&arm, &intercept);
            // The base angle at which the disc's centre is at the intercept's y.
            let y_at = |a: f64| {
                let mut q = at;
                q[0] = a;
                arm.disc(&q).centre_m.y - intercept.y
            };
            let (mut lo, mut hi) = (at[0] - 0.3, at[0] + 0.3);
            for _ in 0..60 {
                let mid = 0.5 * (lo + hi);
                if y_at(mid) < 0.0 {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            let radius = arm.tool_point(&at).xy().norm();
            let omega = 0.5 / radius;
            let cross = pass + late_s;
            let q_at = |t: f64| {
                let mut q = at;
                q[0] = hi - (omega * (t - cross)).clamp(-0.25, 0.25);
                q
            };
            w.coil(true, 0.0);
            w.coil(false, 0.5);
            let mut t = 0.0;
            while t < cross + RECORD_S + 0.5 {
                t += 0.001;
                w.step(t, &if t < cross - 1.0 { home } else { q_at(t) });
            }
            let truth = w.take_truth();
            assert_eq!(truth.len(), 1, "{truth:?}");
            let r = &truth[0];
            assert!(r.not_judged.is_none() && r.contact, "{r:?}");
            let k = r.strike.expect("judged as a strike");
            let t_star = r.t_star_s.unwrap_or(f64::NAN);
            assert!((t_star - pass).abs() < 0.002, "{t_star} vs {pass}");
            let err = r.timing_error_ms.unwrap_or(f64::NAN);
            assert!((err - late_s * 1e3).abs() < 2.0, "{err}: {r:?}");
            assert!((k.tool_speed_mps - 0.5).abs() < 0.05, "{k:?}");
            // Sent back along -y (restitution 0: with the tool's speed
            // along the contact's normal).
            assert!(
                k.ball_speed_mps > 0.1 && k.direction_error_deg < 90.0,
                "{k:?}"
            );
            if mode == TaskMode::Strike {
                assert!(k.aim_known, "{k:?}");
                assert_eq!(k.target_ball_speed_mps, 0.5, "{k:?}");
                assert_eq!(r.success, in_time && k.speed_ok, "{r:?}");
            } else {
                // The aim is the service's: not known, not judged.
                assert!(!k.aim_known && !k.speed_ok, "{k:?}");
                assert!(k.target_ball_speed_mps.is_nan(), "{k:?}");
                assert_eq!(r.success, in_time, "{r:?}");
            }
        }
    }

    #[test]
    fn the_coil_switching_on_again_concludes_the_release_and_hangs_a_new_one() {
        let (s, intercept) = lab();
        let mut w = LiveWorld::new(&s, 3, intercept, 0.0);
        let home = [0.0, 0.3, 0.0, -1.5, 0.0, 0.9, 0.0];
        w.coil(true, 0.0);
        let first = w.ball().ball_position_m();
        w.coil(false, 0.2);
        for k in 1..400 {
            w.step(0.2 + f64::from(k) * 0.005, &home);
        }
        assert!(w.take_truth().is_empty(), "the release is still recorded");
        w.coil(true, 2.5);
        assert_eq!(w.take_truth().len(), 1);
        assert_eq!(w.releases(), 2);
        assert!(w.ball().is_held());
        // Held again; a second "on" changes nothing.
        let held = w.ball().ball_position_m();
        w.coil(true, 2.6);
        assert_eq!(w.ball().ball_position_m(), held);
        assert_eq!(w.releases(), 2);
        // Both held positions are at the pendulum's length from its pivot.
        let l = w.world().pendulum.length_m;
        let pivot = w.world().pendulum.pivot_m;
        assert!(((first - pivot).norm() - l).abs() < 1e-9);
        assert!(((held - pivot).norm() - l).abs() < 1e-9);
    }

    #[test]
    fn the_hands_stop_a_swinging_ball_where_it_hangs_and_leave_a_held_one() {
        let (s, intercept) = lab();
        let mut w = LiveWorld::new(&s, 3, intercept, 0.0);
        let home = [0.0, 0.3, 0.0, -1.5, 0.0, 0.9, 0.0];
        let rest = w.ball().ball_position_m();
        // Held on the magnet: steadying changes nothing.
        w.coil(true, 0.0);
        let held = w.ball().ball_position_m();
        w.steady(0.1);
        assert!(w.ball().is_held());
        assert_eq!(w.ball().ball_position_m(), held);
        // Swinging: it hangs still at its rest point, the release recorded.
        w.coil(false, 0.2);
        for k in 1..300 {
            w.step(0.2 + f64::from(k) * 0.005, &home);
        }
        assert!(w.ball().ball_velocity_mps().norm() > 0.05);
        w.steady(1.8);
        assert_eq!(w.take_truth().len(), 1);
        for k in 1..200 {
            w.step(1.8 + f64::from(k) * 0.005, &home);
        }
        assert!(w.ball().ball_velocity_mps().norm() < 1e-9);
        assert!((w.ball().ball_position_m() - rest).norm() < 1e-9);
    }
}
