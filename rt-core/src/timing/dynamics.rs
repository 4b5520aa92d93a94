//! The speed dynamics of eq. 20 (corrected) with the Hopf oscillator of eq. 21,
//! integrated jointly with the path progress and the three neurons.

use super::TimingParams;
use super::neurons::{NeuronCoeffs, Neurons, Regime, neuron_rates};

/// State of the speed dynamics: the path speed `a`, the auxiliary `b`, the path
/// progress `s` and the neurons.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpeedState {
    /// Path speed along the straight line, m/s (the paper's `a`, printed `alpha`).
    pub a: f64,
    /// The oscillator's second coordinate, m/s.
    pub b: f64,
    /// Path length covered, metres (`s' = a`).
    pub s: f64,
    /// Neuron activations.
    pub neurons: Neurons,
}

impl SpeedState {
    /// At rest, nothing covered, `u_init` selected.
    pub const fn resting(floor: f64) -> Self {
        Self {
            a: 0.0,
            b: 0.0,
            s: 0.0,
            neurons: Neurons::resting(floor),
        }
    }

    fn to_array(self) -> [f64; 6] {
        [
            self.a,
            self.b,
            self.s,
            self.neurons.u_init,
            self.neurons.u_hopf,
            self.neurons.u_final,
        ]
    }

    fn from_array(x: [f64; 6]) -> Self {
        Self {
            a: x[0],
            b: x[1],
            s: x[2],
            neurons: Neurons {
                u_init: x[3],
                u_hopf: x[4],
                u_final: x[5],
            },
        }
    }
}

/// What the re-planner sets for one integration step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HopfDrive {
    /// Radius and shift `R_h` of the limit cycle, m/s (> 0).
    pub radius_mps: f64,
    /// Angular frequency `omega`, rad/s.
    pub omega_rad_per_s: f64,
    /// Distance to the target at the start of the step, metres (the final
    /// regime's fixed point moves the tool onto the target).
    pub remaining_m: f64,
    /// Which neuron the competitive advantages select.
    pub regime: Regime,
}

/// The speed dynamics' constants; [`SpeedDynamics::step`] is one RK4 step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpeedDynamics {
    lambda: f64,
    c1: f64,
    c2: f64,
    k_final: f64,
    neurons: NeuronCoeffs,
}

impl SpeedDynamics {
    /// From validated parameters.
    pub fn new(p: &TimingParams) -> Self {
        Self {
            lambda: p.hopf_lambda_per_s,
            c1: p.init_gain_per_s,
            c2: p.final_gain_per_s,
            k_final: p.final_position_gain_per_s,
            neurons: NeuronCoeffs {
                inv_tau: 1.0 / p.neuron_time_constant_s,
                mu_on: p.neuron_advantage,
                mu_off: -p.neuron_disadvantage,
                nu: p.neuron_competition,
                floor: p.neuron_floor,
            },
        }
    }

    /// The lowest neuron activation.
    pub fn neuron_floor(&self) -> f64 {
        self.neurons.floor
    }

    /// A neuron's weight in eq. 20: `u^2` measured from the floor,
    /// `((u - floor) / (1 - floor))^2`, so a suppressed neuron weighs exactly 0
    /// (the paper: only one neuron is non-zero at a time).
    pub fn weight(&self, u: f64) -> f64 {
        let f = self.neurons.floor;
        let w = ((u - f) / (1.0 - f)).max(0.0);
        w * w
    }

    /// The right-hand side, with `s0` the progress at the start of the step.
    fn rhs(&self, x: [f64; 6], d: &HopfDrive, s0: f64) -> [f64; 6] {
        let [a, b, s, ui, uh, uf] = x;
        let (ui2, uh2, uf2) = (self.weight(ui), self.weight(uh), self.weight(uf));
        // f_Hopf(a - R_h, b) of eq. 21 with gamma = lambda / R_h^2.
        let r = d.radius_mps;
        let xh = a - r;
        let radial = self.lambda * (1.0 - (xh * xh + b * b) / (r * r));
        let w = d.omega_rad_per_s;
        let fx = radial * xh - w * b;
        let fb = w * xh + radial * b;
        // Final fixed point: rest on the target (speed k_f * remaining distance).
        let a_fix = self.k_final * (d.remaining_m - (s - s0));
        let da = -self.c1 * ui2 * a + uh2 * fx - self.c2 * uf2 * (a - a_fix);
        let db = -self.c1 * ui2 * b + uh2 * fb - self.c2 * uf2 * b;
        let du = neuron_rates([ui, uh, uf], d.regime, &self.neurons);
        [da, db, a, du[0], du[1], du[2]]
    }

    /// One classical Runge-Kutta step of `h` seconds (no allocation).
    ///
    /// `drive.radius_mps` must be > 0 and `h` > 0; [`super::TimedMotion`]
    /// guarantees both.
    pub fn step(&self, state: &mut SpeedState, h: f64, drive: &HopfDrive) {
        let x0 = state.to_array();
        let s0 = x0[2];
        let k1 = self.rhs(x0, drive, s0);
        let k2 = self.rhs(axpy(x0, 0.5 * h, k1), drive, s0);
        let k3 = self.rhs(axpy(x0, 0.5 * h, k2), drive, s0);
        let k4 = self.rhs(axpy(x0, h, k3), drive, s0);
        let mut x = [0.0; 6];
        for i in 0..6 {
            x[i] = x0[i] + h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
        }
        for u in &mut x[3..6] {
            *u = u.max(self.neurons.floor);
        }
        *state = SpeedState::from_array(x);
    }
}

fn axpy(x: [f64; 6], h: f64, k: [f64; 6]) -> [f64; 6] {
    let mut y = x;
    for i in 0..6 {
        y[i] += h * k[i];
    }
    y
}
