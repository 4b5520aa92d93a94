//! A strike's predicted rebound (issue #38): what the controller expects
//! the struck ball to do, from its beliefs only (the planned stroke, the
//! filter's pass, the believed restitution, frequency and damping), made
//! once at the commit, never from the world.
//!
//! Along the return (the swing's horizontal, positive against the ball's
//! pass), the ball comes in at `-v_in`, the tool at `+u` (its planned speed
//! times the cosine of the stroke's elevation). A contact of restitution `e`
//! along that normal sends the ball off at
//! `v_out = u + e (u + v_in) = (1 + e) u + e v_in` (`e = 0`: the tool's
//! speed, the strike's target). The string then swings it back as the
//! linearised damped pendulum `x'' = -k x - alpha x'` from the contact
//! point with `x'(0) = v_out`: `x(tau) = v_out / w_d e^(-alpha tau / 2)
//! sin(w_d tau)`, `w_d = sqrt(k - alpha^2 / 4)`, whose first turn (the
//! rebound's amplitude) comes at `tau_t = atan(2 w_d / alpha) / w_d`
//! (`pi / (2 w)` undamped).

use serde::{Deserialize, Serialize};

/// The controller's prediction of a strike's rebound (module docs), and
/// what it used.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ts_rs::TS, utoipa::ToSchema)]
pub struct PredictedRebound {
    /// The believed restitution of ball and tool (`pendulum.contact_restitution`).
    pub restitution: f64,
    /// The planned tool speed at contact along the return (the strike
    /// speed times the cosine of its elevation), m/s.
    pub tool_return_speed_mps: f64,
    /// The ball's speed at the committed pass as the filter predicted it
    /// at the commit, m/s.
    pub ball_in_speed_mps: f64,
    /// The predicted outgoing speed along the return, m/s.
    pub ball_speed_mps: f64,
    /// The pendulum's angular frequency used, `sqrt(k)` (the filter's `k`
    /// at the commit, else the believed `g / l`), rad/s.
    pub omega_radps: f64,
    /// The damping `alpha` used (the filter's, else the believed), 1/s.
    pub damping_per_s: f64,
    /// The rebound's first swing away from the contact point: its lateral
    /// amplitude (damped to its turn), m.
    pub amplitude_m: f64,
    /// From the contact to that turn, s.
    pub turn_s: f64,
}

impl PredictedRebound {
    /// The prediction for a tool at `tool_return_speed_mps` along the
    /// return meeting a ball at `ball_in_speed_mps` (either sign: its size
    /// is used), restitution `restitution` (clamped to 0..1), a pendulum of
    /// `k = omega^2` and damping `alpha`. `None` for a non-finite input, a
    /// non-positive `k`, or a damping at or above critical.
    pub fn new(
        restitution: f64,
        tool_return_speed_mps: f64,
        ball_in_speed_mps: f64,
        k_per_s2: f64,
        damping_per_s: f64,
    ) -> Option<Self> {
        let e = restitution.clamp(0.0, 1.0);
        let (u, v_in) = (tool_return_speed_mps, ball_in_speed_mps.abs());
        let alpha = damping_per_s.max(0.0);
        let wd2 = k_per_s2 - 0.25 * alpha * alpha;
        if !(u.is_finite() && v_in.is_finite() && e.is_finite() && k_per_s2 > 0.0 && wd2 > 0.0) {
            return None;
        }
        let wd = wd2.sqrt();
        let v_out = (1.0 + e) * u + e * v_in;
        let turn_s = if alpha > 0.0 {
            (2.0 * wd / alpha).atan() / wd
        } else {
            std::f64::consts::FRAC_PI_2 / wd
        };
        let mut p = Self {
            restitution: e,
            tool_return_speed_mps: u,
            ball_in_speed_mps: v_in,
            ball_speed_mps: v_out,
            omega_radps: k_per_s2.sqrt(),
            damping_per_s: alpha,
            amplitude_m: 0.0,
            turn_s,
        };
        p.amplitude_m = p.lateral_at(turn_s);
        Some(p)
    }

    /// The damped swing's angular frequency `w_d`, rad/s.
    fn damped_radps(&self) -> f64 {
        let a = self.damping_per_s;
        (self.omega_radps * self.omega_radps - 0.25 * a * a)
            .max(0.0)
            .sqrt()
    }

    /// When the rebound's first swing is back at the contact point, `pi /
    /// w_d` after the contact, s (NaN for a degenerate prediction).
    pub fn back_s(&self) -> f64 {
        let wd = self.damped_radps();
        if wd > 0.0 {
            std::f64::consts::PI / wd
        } else {
            f64::NAN
        }
    }

    /// The ball's predicted lateral offset from the contact point along the
    /// return `tau_s` after the contact (0 before it), m.
    pub fn lateral_at(&self, tau_s: f64) -> f64 {
        let wd = self.damped_radps();
        if tau_s <= 0.0 || wd <= 0.0 {
            return 0.0;
        }
        let a = self.damping_per_s;
        self.ball_speed_mps / wd * (-0.5 * a * tau_s).exp() * (wd * tau_s).sin()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn restitution_zero_leaves_with_the_tools_speed_and_swings_a_quarter_period_out() {
        let k = 9.81 / 1.93;
        let p = PredictedRebound::new(0.0, 0.47, 0.8, k, 0.0).unwrap();
        assert!((p.ball_speed_mps - 0.47).abs() < 1e-12, "{p:?}");
        let w = k.sqrt();
        assert!((p.turn_s - std::f64::consts::FRAC_PI_2 / w).abs() < 1e-12);
        assert!((p.amplitude_m - 0.47 / w).abs() < 1e-12, "{p:?}");
        // The swing turns there: it rises before and falls after.
        assert!(p.lateral_at(p.turn_s - 0.05) < p.amplitude_m);
        assert!(p.lateral_at(p.turn_s + 0.05) < p.amplitude_m);
        assert_eq!(p.lateral_at(-0.1), 0.0);
        // Back at the contact point half a period on.
        assert!((p.back_s() - std::f64::consts::PI / w).abs() < 1e-12);
        assert!(p.lateral_at(p.back_s()).abs() < 1e-12);
    }

    #[test]
    fn restitution_adds_the_balls_own_speed_and_damping_shortens_the_swing() {
        let k = 9.81 / 1.93;
        let p = PredictedRebound::new(0.5, 0.4, -1.0, k, 0.0).unwrap();
        // (1 + e) u + e v_in, whichever way the ball came in.
        assert!(
            (p.ball_speed_mps - (1.5 * 0.4 + 0.5)).abs() < 1e-12,
            "{p:?}"
        );
        let damped = PredictedRebound::new(0.5, 0.4, -1.0, k, 0.3).unwrap();
        assert!(damped.amplitude_m < p.amplitude_m, "{damped:?} {p:?}");
        assert!(damped.turn_s < p.turn_s, "{damped:?} {p:?}");
        // Its turn is the damped swing's maximum.
        let d = 1e-4;
        let x = |t: f64| damped.lateral_at(t);
        assert!(
            x(damped.turn_s) >= x(damped.turn_s - d) && x(damped.turn_s) >= x(damped.turn_s + d)
        );
    }

    #[test]
    fn no_prediction_from_a_bad_belief() {
        assert!(PredictedRebound::new(0.0, f64::NAN, 1.0, 5.0, 0.0).is_none());
        assert!(PredictedRebound::new(0.0, 0.5, 1.0, 0.0, 0.0).is_none());
        assert!(PredictedRebound::new(0.0, 0.5, 1.0, 1.0, 3.0).is_none());
    }
}
