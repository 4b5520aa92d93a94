//! The contact of ball and tool as the robot feels it: FRI's external joint
//! torques (issue #26, the measured judge's "impact condition").
//!
//! When the true ball meets the true tool's disc (the collision of the
//! trial driver's truth, `sim::truth::SimTruth`,
//! [`super::TruePendulum::collide`]) the tool receives the
//! impulse that changed the ball's velocity, `-m dv` (ball mass
//! `world.pendulum.ball_mass_kg`), as a half-sine force pulse of the
//! session's `world.pendulum.contact_pulse_ms` from the contact (its exact
//! time between two control steps, found there). The robot reports, with each
//! monitoring message, the pulse's mean force over the period since its last
//! message, the session's `world.robot.torque_lag_periods` FRI periods late
//! (the estimate's filtering: a contact between two messages shows in the next ones, split
//! between them as its pulse falls), mapped to the joints by the transposed Jacobian of the contact
//! point, `tau = J^T F` (`tau_i = z_i . ((p - o_i) x F)` over the iiwa's
//! joint axes at the true joint angles), plus white noise of
//! [`EXTERNAL_TORQUE_NOISE_NM`] per joint (a torque-sensing robot's external
//! torque estimate at rest; no model error of the arm's own dynamics).
//!
//! A 57 g ball stopped from 0.7 m/s carries 0.04 N s: over 4 ms a mean force
//! of 10 N, a few N m at the shoulder and elbow joints.

use nalgebra::Vector3;
use rand::Rng;

use super::pendulum::{Disc, TruePendulum};
use crate::fri::codec::Joints;
use crate::kinematics::iiwa7::JOINTS;
use crate::kinematics::{Pose, frames};
use crate::sim::camera::gaussian;

/// Standard deviation of the reported external torque of each joint, N m.
pub const EXTERNAL_TORQUE_NOISE_NM: f64 = 0.2;

/// One contact of ball and tool.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Contact {
    /// When the contact began, control clock, seconds.
    pub t_s: f64,
    /// Where the force acts (on the disc), base frame, metres.
    pub point_m: Vector3<f64>,
    /// The impulse the tool receives, newton seconds.
    pub impulse_ns: Vector3<f64>,
    /// How long its force pulse lasts, seconds (`world.pendulum.contact_pulse_ms`).
    pub duration_s: f64,
}

impl Contact {
    /// The pulse's mean force over `[a_s, b_s]`, newtons (the whole impulse
    /// over the interval when it is empty or inverted and holds the pulse).
    pub fn mean_force_n(&self, a_s: f64, b_s: f64) -> Vector3<f64> {
        // Impulse delivered by time t: J (1 - cos(pi u)) / 2, u = (t - t0) / D.
        let part = |t: f64| {
            let u = ((t - self.t_s) / self.duration_s.max(1e-6)).clamp(0.0, 1.0);
            0.5 * (1.0 - (std::f64::consts::PI * u).cos())
        };
        let dt = b_s - a_s;
        if dt <= 0.0 {
            return Vector3::zeros();
        }
        self.impulse_ns * ((part(b_s) - part(a_s)) / dt)
    }

    /// Whether the pulse is over by `t_s`.
    pub fn over_by(&self, t_s: f64) -> bool {
        t_s >= self.t_s + self.duration_s
    }
}

/// The joint torques `J^T F` of a force `force_n` acting at `point_m` on
/// the arm at joint angles `q` (the iiwa's joint axes), N m.
pub fn joint_torques(q: &Joints, point_m: &Vector3<f64>, force_n: &Vector3<f64>) -> Joints {
    let mut f = [Pose::identity(); JOINTS + 1];
    frames(&crate::kinematics::Joints::from(*q), &mut f);
    std::array::from_fn(|i| {
        let z = f[i].rotation.matrix().column(2).into_owned();
        let r = point_m - f[i].translation.vector;
        z.dot(&r.cross(force_n))
    })
}

/// The external torques the robot reports for the period `[a_s, b_s]`
/// (contact time, the sensing lag already taken off): the contacts' (when
/// any) plus the sensing noise.
pub fn external_torques<R: Rng>(
    q: &Joints,
    contacts: &[Option<Contact>],
    a_s: f64,
    b_s: f64,
    rng: &mut R,
) -> Joints {
    let mut tau = [0.0; JOINTS];
    for c in contacts.iter().flatten() {
        let part = joint_torques(q, &c.point_m, &c.mean_force_n(a_s, b_s));
        for (t, p) in tau.iter_mut().zip(part) {
            *t += p;
        }
    }
    for v in &mut tau {
        *v += EXTERNAL_TORQUE_NOISE_NM * gaussian(rng);
    }
    tau
}

/// The true ball and its ghost (the same ball without the tool in its way:
/// t* and the physical judge's contact are found on it), stopped by the true
/// tool's contact disc. One piece for the trial driver's truth
/// (`sim::truth::SimTruth`) on the virtual clock
/// and the world process on the wall clock: the ball is released at
/// `drop_at` (the coil's switch plus the residual magnetism's delay), every
/// step it meets the disc at the contact's exact time (bisected to 1 us on
/// copies of the ball, the disc's centre interpolated) and leaves it with the
/// impulse of the contact (the relative velocity along the contact normal
/// reversed and scaled by the world's restitution,
/// `world.pendulum.contact_restitution`: 0, the default, stops the ball
/// against the disc; the disc's own velocity included, so a moving tool
/// strikes the ball), and the contact is handed on as the robot's force pulse.
#[derive(Debug, Clone)]
pub struct BallOnTool {
    /// The true ball.
    pub ball: TruePendulum,
    /// The ball without the tool in its way.
    pub ghost: TruePendulum,
    /// When the ball drops, s (`None`: held until told).
    pub drop_at: Option<f64>,
    last_disc: Option<Disc>,
    before: Option<TruePendulum>,
}

impl BallOnTool {
    /// A held (or hanging) ball and its ghost, both `ball`.
    pub fn new(ball: TruePendulum) -> Self {
        Self {
            ghost: ball.clone(),
            ball,
            drop_at: None,
            last_disc: None,
            before: None,
        }
    }

    /// Moves ball and ghost to `t_s` (the ball free of the tool; `meet`
    /// then stops it against the disc).
    pub fn advance(&mut self, t_s: f64) {
        if t_s > self.ghost.time_s() {
            self.before = Some(self.ball.clone());
            advance_true_ball(&mut self.ball, self.drop_at, t_s);
            advance_true_ball(&mut self.ghost, self.drop_at, t_s);
        }
    }

    /// The tool's disc is `disc` at `t_s` (one step of `period_s` after the
    /// previous one): a ball that met it since is stopped at that moment, and
    /// the contact (its time, where the force acts, the impulse on a ball of
    /// `mass_kg`, a force pulse of `pulse_s`) is returned.
    pub fn meet(
        &mut self,
        t_s: f64,
        disc: Disc,
        period_s: f64,
        mass_kg: f64,
        pulse_s: f64,
    ) -> Option<Contact> {
        let last = self.last_disc.unwrap_or(disc);
        let v_disc = (disc.centre_m - last.centre_m) / period_s;
        self.last_disc = Some(disc);
        let radius_m = self.ball.params().ball_radius_m;
        let mut contact_at = t_s;
        if let Some(before) = self.before.take()
            && touching(&self.ball, &disc, &v_disc, radius_m)
            && let Some(tc) =
                first_touch(&before, self.drop_at, &last, &disc, &v_disc, t_s, radius_m)
        {
            let mut at = before;
            advance_true_ball(&mut at, self.drop_at, tc);
            self.ball = at;
            contact_at = tc;
        }
        let contact_disc = disc_at(&last, &disc, t_s - contact_at, period_s);
        let restitution = self.ball.params().restitution;
        let v_before = self.ball.ball_velocity_mps();
        let hit = self.ball.collide(&contact_disc, &v_disc, restitution);
        let dv = self.ball.ball_velocity_mps() - v_before;
        let contact_ball_m = self.ball.ball_position_m();
        if contact_at < t_s {
            advance_true_ball(&mut self.ball, self.drop_at, t_s);
            // Still pressed against the disc at the step (a ball that
            // bounced off moves away from it: no second hit).
            let _ = self.ball.collide(&disc, &v_disc, restitution);
        }
        hit.then(|| {
            let (_, n) = contact_disc.distance(&contact_ball_m);
            Contact {
                t_s: contact_at,
                point_m: contact_ball_m - n * radius_m,
                impulse_ns: -dv * mass_kg,
                duration_s: pulse_s,
            }
        })
    }
}

/// Whether the true ball of radius `radius_m` touches `disc` (moving at
/// `v_disc`) and moves into it.
fn touching(ball: &TruePendulum, disc: &Disc, v_disc: &Vector3<f64>, radius_m: f64) -> bool {
    let (dist, n) = disc.distance(&ball.ball_position_m());
    dist <= radius_m && (ball.ball_velocity_mps() - v_disc).dot(&n) < 0.0
}

/// The disc `ago_s` before the step that moved it from `last` to `now` over
/// `period_s` (its centre interpolated linearly; the normal of `now`).
fn disc_at(last: &Disc, now: &Disc, ago_s: f64, period_s: f64) -> Disc {
    let f = (1.0 - ago_s / period_s).clamp(0.0, 1.0);
    Disc {
        centre_m: last.centre_m + (now.centre_m - last.centre_m) * f,
        ..*now
    }
}

/// When the ball that was `before` (not touching the disc `last`) first
/// touches the disc moving from `last` to `now` by `t_s`: bisected to a
/// microsecond on copies of the ball. `None` when it already touched.
fn first_touch(
    before: &TruePendulum,
    drop_at: Option<f64>,
    last: &Disc,
    now: &Disc,
    v_disc: &Vector3<f64>,
    t_s: f64,
    radius_m: f64,
) -> Option<f64> {
    let (mut lo, mut hi) = (before.time_s(), t_s);
    let period_s = hi - lo;
    if period_s <= 0.0 || touching(before, last, v_disc, radius_m) {
        return None;
    }
    while hi - lo > 1e-6 {
        let mid = 0.5 * (lo + hi);
        let mut probe = before.clone();
        advance_true_ball(&mut probe, drop_at, mid);
        if touching(
            &probe,
            &disc_at(last, now, t_s - mid, period_s),
            v_disc,
            radius_m,
        ) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    Some(hi)
}

/// Advances a true pendulum to `t_s`, dropping the ball at `drop_at`.
pub fn advance_true_ball(ball: &mut TruePendulum, drop_at: Option<f64>, t_s: f64) {
    if let Some(tr) = drop_at
        && tr <= t_s
        && ball.is_held()
    {
        ball.release(tr.max(ball.time_s()));
    }
    ball.advance_to(t_s);
}

#[cfg(test)]
mod tests {
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::kinematics::{Jacobian, Tool, jacobian};
    use crate::sim::world::pendulum::TruePendulumParams;

    /// A 1.93 m pendulum hanging at (0.6, 0, 0.3) with restitution `e`,
    /// released from 10 degrees at t = 0.
    fn swinging(e: f64) -> TruePendulum {
        let length_m = 1.93;
        let p = TruePendulumParams {
            pivot_m: Vector3::new(0.6, 0.0, 0.3 + length_m),
            length_m,
            gravity_mps2: 9.81,
            damping_per_s: 0.0,
            drag_per_m: 0.0,
            friction_mps2: 0.0,
            disturbance_mps2: 0.0,
            ball_radius_m: 0.0335,
            restitution: e,
        };
        let mut b = TruePendulum::held_at(p, 10f64.to_radians(), 0.0, 0.0, 1);
        b.release(0.0);
        b
    }

    /// A vertical disc (normal along y) moving at `tool_mps` along y meets
    /// the ball at the bottom of its swing (its centre at y = 0 at the
    /// pass): returns the ball's y velocity before (at the pass) and right
    /// after the contact, m/s.
    fn strike(e: f64, tool_mps: f64) -> (f64, f64) {
        let ghost = swinging(e);
        let t_pass = ghost.next_crossing_s(0.0, 2.0).unwrap();
        let mut at = ghost.clone();
        at.advance_to(t_pass);
        let v_in = at.ball_velocity_mps().y;
        // The disc's face touches the ball at the pass, on the side the
        // ball moves to, and moves against it at `tool_mps`.
        let side = v_in.signum();
        let r = ghost.params().ball_radius_m;
        let u = -side * tool_mps;
        let disc = |t: f64| Disc {
            centre_m: Vector3::new(0.6, side * r + u * (t - t_pass), 0.3),
            normal: Vector3::y(),
            radius_m: 0.05,
        };
        let mut on = BallOnTool::new(ghost);
        on.drop_at = Some(0.0);
        let dt = 0.001;
        let mut t = t_pass - 0.1;
        on.advance(t);
        let _ = on.meet(t, disc(t), dt, 0.057, 0.004);
        while t < t_pass + 0.1 {
            t += dt;
            on.advance(t);
            if let Some(c) = on.meet(t, disc(t), dt, 0.057, 0.004) {
                assert!((c.t_s - t_pass).abs() < 2e-4, "{} vs {t_pass}", c.t_s);
                // The impulse on the tool is the ball's change of momentum, reversed.
                let v_out = on.ball.ball_velocity_mps().y;
                assert!(
                    (-c.impulse_ns.y / 0.057 - (v_out - v_in)).abs() < 0.02,
                    "{c:?}"
                );
                return (v_in, v_out);
            }
        }
        panic!("no contact");
    }

    #[test]
    fn a_striking_tool_sends_the_ball_off_with_the_restitution_of_their_approach() {
        for e in [0.0, 0.3, 0.5, 0.8] {
            let (v_in, v_out) = strike(e, 1.0);
            let side = v_in.signum();
            // Along the normal: the relative velocity reversed, times e:
            // v_out - v_tool = -e (v_in - v_tool), v_tool = -side * 1 m/s.
            let v_tool = -side;
            let expect = v_tool - e * (v_in - v_tool);
            assert!(
                (v_out - expect).abs() < 0.01,
                "e = {e}: {v_out} vs {expect} (in {v_in})"
            );
            // The ball returns, faster than the tool when e > 0.
            assert!(v_out * side < 0.0 && v_out.abs() >= 1.0 - 1e-3, "{v_out}");
        }
    }

    #[test]
    fn restitution_zero_stops_the_ball_against_a_resting_tool_as_before() {
        let (v_in, v_out) = strike(0.0, 0.0);
        assert!(v_in.abs() > 0.5, "{v_in}");
        assert!(v_out.abs() < 1e-3, "{v_out}");
        // A resting tool and restitution e: the ball bounces back at e v_in.
        let (v_in, v_out) = strike(0.5, 0.0);
        assert!((v_out + 0.5 * v_in).abs() < 0.01, "{v_out} vs {v_in}");
    }

    fn q() -> Joints {
        [0.3, 0.6, -0.2, -1.2, 0.1, 0.9, 0.0]
    }

    fn norm(t: &Joints) -> f64 {
        t.iter().map(|v| v * v).sum::<f64>().sqrt()
    }

    #[test]
    fn the_torques_are_the_transposed_jacobian_of_the_contact_point() {
        let tool = Tool::along_z(0.2);
        let mut j = Jacobian::zeros();
        let pose = jacobian(&crate::kinematics::Joints::from(q()), &tool, &mut j);
        let p = pose.translation.vector;
        let f = Vector3::new(3.0, -8.0, 1.5);
        let tau = joint_torques(&q(), &p, &f);
        for (i, t) in tau.iter().enumerate() {
            let expect = j.fixed_view::<3, 1>(0, i).dot(&f);
            assert!((t - expect).abs() < 1e-9, "joint {i}: {t} vs {expect}");
        }
    }

    #[test]
    fn the_pulse_carries_the_impulse_and_is_seen_only_with_a_contact() {
        let c = Contact {
            t_s: 1.0012,
            point_m: Vector3::new(0.6, 0.0, 0.6),
            // A 57 g ball stopped from 0.7 m/s along y.
            impulse_ns: Vector3::new(0.0, 0.057 * 0.7, 0.0),
            duration_s: 0.004,
        };
        // The means over the periods add up to the impulse.
        let period = 0.005;
        let total: Vector3<f64> = (0..4)
            .map(|k| {
                let a = 1.0 + f64::from(k) * period;
                c.mean_force_n(a, a + period) * period
            })
            .sum();
        assert!((total - c.impulse_ns).norm() < 1e-12, "{total}");
        assert!(c.over_by(1.0012 + c.duration_s) && !c.over_by(1.003));
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        // Without a contact: noise only, the norm of seven joints' noise
        // stays far below the judge's threshold.
        let mut quiet_max: f64 = 0.0;
        for k in 0..20_000 {
            let a = f64::from(k) * period;
            let tau = external_torques(&q(), &[None], a, a + period, &mut rng);
            quiet_max = quiet_max.max(norm(&tau));
        }
        assert!(quiet_max < 1.5, "{quiet_max}");
        // With one: the period holding most of the pulse stands out.
        let tau = external_torques(&q(), &[Some(c)], 1.0, 1.005, &mut rng);
        assert!(norm(&tau) > 3.0, "{tau:?}");
        // After the pulse, noise again.
        let tau = external_torques(&q(), &[Some(c)], 1.010, 1.015, &mut rng);
        assert!(norm(&tau) < 1.5, "{tau:?}");
    }
}
