//! The true pendulum: a spherical pendulum (the ball may swing out of the
//! plane) in Cartesian coordinates with the string as a constraint, linear
//! damping, quadratic air drag, pivot friction and small disturbances.
//!
//! State: ball centre `x` and velocity `v` in the robot base frame (m, m/s).
//! With `r = x - pivot`, `|r| = L`:
//!
//! ```text
//! a_free = g + a_drag + a_damp + a_fric + a_dist
//!   a_drag = -(rho Cd A / 2m) |v| v        (A = pi R^2)
//!   a_damp = -alpha v                      (the believed model's eq. 8 term)
//!   a_fric = -mu v / |v|  (smoothed below 1 mm/s)
//! a      = a_free - r (|v|^2 + r . a_free) / L^2   (string tension)
//! ```
//!
//! RK4 steps of at most 1 ms; after each step `x` is put back on the sphere and
//! `v` on its tangent plane. The ball can hit a disc (the tool): its velocity
//! along the contact normal is reversed with a restitution (the ball stops or
//! bounces off).

use nalgebra::Vector3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::sim::camera::gaussian;

/// Largest integration step, seconds.
pub const MAX_STEP_S: f64 = 1e-3;
/// A disturbance is held this long, seconds.
pub const DISTURBANCE_HOLD_S: f64 = 0.05;

/// The physical constants of one true pendulum.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruePendulumParams {
    /// Pivot, base frame, m.
    pub pivot_m: Vector3<f64>,
    /// True length pivot -> ball centre, m.
    pub length_m: f64,
    /// Gravity, m/s^2 (acts along -z).
    pub gravity_mps2: f64,
    /// Linear damping alpha, 1/s.
    pub damping_per_s: f64,
    /// Drag factor `rho Cd A / (2 m)`, 1/m.
    pub drag_per_m: f64,
    /// Pivot friction as a tangential deceleration, m/s^2.
    pub friction_mps2: f64,
    /// Standard deviation of the horizontal disturbance, m/s^2.
    pub disturbance_mps2: f64,
    /// Ball radius, m.
    pub ball_radius_m: f64,
    /// Coefficient of restitution of ball and tool (0: the ball stops
    /// against the tool), `world.pendulum.contact_restitution`.
    pub restitution: f64,
}

impl TruePendulumParams {
    /// The drag factor of a sphere: `rho Cd pi R^2 / (2 m)`, 1/m.
    pub fn drag_factor(air_density_kgpm3: f64, cd: f64, radius_m: f64, mass_kg: f64) -> f64 {
        air_density_kgpm3 * cd * std::f64::consts::PI * radius_m * radius_m / (2.0 * mass_kg)
    }
}

/// A disc the ball can hit (the tool's contact disc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Disc {
    /// Centre, base frame, m.
    pub centre_m: Vector3<f64>,
    /// Unit normal.
    pub normal: Vector3<f64>,
    /// Radius, m.
    pub radius_m: f64,
}

impl Disc {
    /// The shortest distance from `p` to the disc, and the unit direction from
    /// the disc's nearest point to `p`.
    pub fn distance(&self, p: &Vector3<f64>) -> (f64, Vector3<f64>) {
        let d = p - self.centre_m;
        let h = d.dot(&self.normal);
        let radial = d - self.normal * h;
        let rn = radial.norm();
        let nearest = if rn <= self.radius_m {
            self.centre_m + radial
        } else {
            self.centre_m + radial * (self.radius_m / rn)
        };
        let to_p = p - nearest;
        let dist = to_p.norm();
        let dir = if dist > 1e-12 {
            to_p / dist
        } else if h >= 0.0 {
            self.normal
        } else {
            -self.normal
        };
        (dist, dir)
    }
}

/// The true pendulum.
#[derive(Debug, Clone)]
pub struct TruePendulum {
    p: TruePendulumParams,
    x: Vector3<f64>,
    v: Vector3<f64>,
    t_s: f64,
    held: bool,
    rng: ChaCha8Rng,
    dist: Vector3<f64>,
    dist_until_s: f64,
    hits: u32,
}

impl TruePendulum {
    /// Held at rest by the magnet at `angle_rad` in the swing plane (positive:
    /// towards +y, as `pendulum::PendulumGeometry`) and `out_of_plane_rad`
    /// towards +x, at time `t_s`.
    pub fn held_at(
        p: TruePendulumParams,
        angle_rad: f64,
        out_of_plane_rad: f64,
        t_s: f64,
        seed: u64,
    ) -> Self {
        let dir = Vector3::new(
            out_of_plane_rad.sin() * angle_rad.cos(),
            angle_rad.sin() * out_of_plane_rad.cos(),
            -angle_rad.cos() * out_of_plane_rad.cos(),
        )
        .normalize();
        Self {
            p,
            x: p.pivot_m + dir * p.length_m,
            v: Vector3::zeros(),
            t_s,
            held: true,
            rng: ChaCha8Rng::seed_from_u64(seed),
            dist: Vector3::zeros(),
            dist_until_s: f64::NEG_INFINITY,
            hits: 0,
        }
    }

    /// Lets the ball go at `t_s` (no earlier than the current time).
    pub fn release(&mut self, t_s: f64) {
        self.advance_to(t_s);
        self.held = false;
    }

    /// `true` while the magnet holds the ball.
    pub fn is_held(&self) -> bool {
        self.held
    }

    /// Current time, s.
    pub fn time_s(&self) -> f64 {
        self.t_s
    }

    /// Ball centre, base frame, m.
    pub fn ball_position_m(&self) -> Vector3<f64> {
        self.x
    }

    /// Ball velocity, m/s.
    pub fn ball_velocity_mps(&self) -> Vector3<f64> {
        self.v
    }

    /// The constants.
    pub fn params(&self) -> &TruePendulumParams {
        &self.p
    }

    /// How often the ball has hit a disc.
    pub fn hits(&self) -> u32 {
        self.hits
    }

    /// Energy per unit mass relative to rest, J/kg.
    pub fn energy_per_kg(&self) -> f64 {
        let rest_z = self.p.pivot_m.z - self.p.length_m;
        0.5 * self.v.norm_squared() + self.p.gravity_mps2 * (self.x.z - rest_z)
    }

    fn accel(&self, x: &Vector3<f64>, v: &Vector3<f64>) -> Vector3<f64> {
        let p = &self.p;
        let speed = v.norm();
        let mut a = Vector3::new(0.0, 0.0, -p.gravity_mps2);
        a -= v * (p.drag_per_m * speed + p.damping_per_s);
        if p.friction_mps2 > 0.0 {
            // Coulomb friction, smoothed below 1 mm/s so the ODE stays Lipschitz.
            let s = (speed / 1e-3).tanh();
            if speed > 1e-12 {
                a -= v * (p.friction_mps2 * s / speed);
            }
        }
        a += self.dist;
        let r = x - p.pivot_m;
        let l2 = r.norm_squared();
        a - r * ((v.norm_squared() + r.dot(&a)) / l2)
    }

    fn step(&mut self, h: f64) {
        let (x0, v0) = (self.x, self.v);
        let k1v = self.accel(&x0, &v0);
        let k1x = v0;
        let k2v = self.accel(&(x0 + k1x * (h / 2.0)), &(v0 + k1v * (h / 2.0)));
        let k2x = v0 + k1v * (h / 2.0);
        let k3v = self.accel(&(x0 + k2x * (h / 2.0)), &(v0 + k2v * (h / 2.0)));
        let k3x = v0 + k2v * (h / 2.0);
        let k4v = self.accel(&(x0 + k3x * h), &(v0 + k3v * h));
        let k4x = v0 + k3v * h;
        let x = x0 + (k1x + k2x * 2.0 + k3x * 2.0 + k4x) * (h / 6.0);
        let v = v0 + (k1v + k2v * 2.0 + k3v * 2.0 + k4v) * (h / 6.0);
        // Back onto the sphere and its tangent plane.
        let r = (x - self.p.pivot_m).normalize();
        self.x = self.p.pivot_m + r * self.p.length_m;
        self.v = v - r * v.dot(&r);
    }

    fn refresh_disturbance(&mut self) {
        if self.p.disturbance_mps2 > 0.0 && self.t_s >= self.dist_until_s {
            let s = self.p.disturbance_mps2;
            self.dist = Vector3::new(
                s * gaussian(&mut self.rng),
                s * gaussian(&mut self.rng),
                0.0,
            );
            self.dist_until_s = self.t_s + DISTURBANCE_HOLD_S;
        }
    }

    /// Advances to `t_s` (never backwards: an earlier time changes nothing).
    pub fn advance_to(&mut self, t_s: f64) {
        if t_s.is_nan() || t_s <= self.t_s || !t_s.is_finite() {
            return;
        }
        if self.held {
            self.t_s = t_s;
            return;
        }
        while self.t_s < t_s {
            self.refresh_disturbance();
            let mut h = (t_s - self.t_s).min(MAX_STEP_S);
            if self.p.disturbance_mps2 > 0.0 {
                h = h.min((self.dist_until_s - self.t_s).max(1e-9));
            }
            self.step(h);
            self.t_s += h;
        }
        self.t_s = t_s;
    }

    /// The next time (within `max_s`) the ball centre's `y` crosses `y_m`,
    /// found on a copy (bisection inside each step).
    pub fn next_crossing_s(&self, y_m: f64, max_s: f64) -> Option<f64> {
        if self.held {
            return None;
        }
        let mut a = self.clone();
        let end = self.t_s + max_s;
        while a.t_s < end {
            let mut b = a.clone();
            b.advance_to((a.t_s + MAX_STEP_S).min(end));
            let fa = a.x.y - y_m;
            let fb = b.x.y - y_m;
            if fa != 0.0 && fa.signum() != fb.signum() {
                let (mut lo, mut hi) = (a.t_s, b.t_s);
                for _ in 0..50 {
                    let mid = 0.5 * (lo + hi);
                    let mut m = a.clone();
                    m.advance_to(mid);
                    if (m.x.y - y_m).signum() == fa.signum() {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                return Some(0.5 * (lo + hi));
            }
            a = b;
        }
        None
    }

    /// If the ball touches `disc` (moving with `disc_velocity_mps`) and moves
    /// into it, reflects its relative velocity along the contact normal with
    /// `restitution` (0: it stops against the disc) and pushes it out of
    /// contact. Returns `true` on a hit.
    pub fn collide(
        &mut self,
        disc: &Disc,
        disc_velocity_mps: &Vector3<f64>,
        restitution: f64,
    ) -> bool {
        if self.held {
            return false;
        }
        let (dist, n) = disc.distance(&self.x);
        if dist > self.p.ball_radius_m {
            return false;
        }
        let rel = self.v - disc_velocity_mps;
        let vn = rel.dot(&n);
        if vn >= 0.0 {
            return false;
        }
        self.v -= n * ((1.0 + restitution) * vn);
        self.x += n * (self.p.ball_radius_m - dist);
        let r = (self.x - self.p.pivot_m).normalize();
        self.x = self.p.pivot_m + r * self.p.length_m;
        self.v -= r * self.v.dot(&r);
        self.hits += 1;
        true
    }
}
