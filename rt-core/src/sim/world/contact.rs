//! The contact of ball and tool as the robot feels it: FRI's external joint
//! torques (issue #26, the measured judge's "impact condition").
//!
//! When the true ball meets the true tool's disc (the trial driver's
//! collision, [`super::TruePendulum::collide`]) the tool receives the
//! impulse that changed the ball's velocity, `-m dv` (ball mass
//! `world.pendulum.ball_mass_kg`), as a half-sine force pulse of
//! [`CONTACT_DURATION_S`] from the contact (its exact time between two
//! control steps, found by the trial driver). The robot reports, with each
//! monitoring message, the pulse's mean force over the period since its last
//! message, [`TORQUE_LAG_PERIODS`] FRI periods late (the estimate's
//! filtering: a contact between two messages shows in the next ones, split
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

use crate::fri::codec::Joints;
use crate::kinematics::iiwa7::JOINTS;
use crate::kinematics::{Pose, frames};
use crate::sim::camera::gaussian;

/// Duration of a contact's force pulse, seconds.
pub const CONTACT_DURATION_S: f64 = 0.004;
/// The external torque estimate shows a contact's force this many FRI
/// periods late (its filtering): a contact that begins between two messages
/// shows, in the next messages, the part of its pulse after a period.
pub const TORQUE_LAG_PERIODS: f64 = 1.0;
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
}

impl Contact {
    /// The pulse's mean force over `[a_s, b_s]`, newtons (the whole impulse
    /// over the interval when it is empty or inverted and holds the pulse).
    pub fn mean_force_n(&self, a_s: f64, b_s: f64) -> Vector3<f64> {
        // Impulse delivered by time t: J (1 - cos(pi u)) / 2, u = (t - t0) / D.
        let part = |t: f64| {
            let u = ((t - self.t_s) / CONTACT_DURATION_S).clamp(0.0, 1.0);
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
        t_s >= self.t_s + CONTACT_DURATION_S
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

#[cfg(test)]
mod tests {
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::kinematics::{Jacobian, Tool, jacobian};

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
        };
        // The means over the periods add up to the impulse.
        let period = 0.005;
        let total: Vector3<f64> = (0..4)
            .map(|k| {
                let a = 1.0 + k as f64 * period;
                c.mean_force_n(a, a + period) * period
            })
            .sum();
        assert!((total - c.impulse_ns).norm() < 1e-12, "{total}");
        assert!(c.over_by(1.0012 + CONTACT_DURATION_S) && !c.over_by(1.003));
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        // Without a contact: noise only, the norm of seven joints' noise
        // stays far below the judge's threshold.
        let mut quiet_max: f64 = 0.0;
        for k in 0..20_000 {
            let a = k as f64 * period;
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
