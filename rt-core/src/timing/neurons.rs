//! The competitive neural dynamics that select the regime of the speed dynamics.

use serde::Serialize;

/// The three regimes of the speed dynamics (eq. 20), one per neuron.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Regime {
    /// Initial fixed point: at rest before the interception condition.
    Init,
    /// The shifted Hopf limit cycle: the motion itself.
    Hopf,
    /// Final fixed point: at rest on the target after one cycle.
    Final,
}

/// Activations of the three neurons `u_init`, `u_hopf`, `u_final`.
///
/// The selected neuron settles near 1, the others at the floor; switching is a
/// smooth exchange over a few `tau_u`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Neurons {
    /// `u_init`: weight of the initial fixed point.
    pub u_init: f64,
    /// `u_hopf`: weight of the Hopf oscillator.
    pub u_hopf: f64,
    /// `u_final`: weight of the final fixed point.
    pub u_final: f64,
}

impl Neurons {
    /// At rest before any motion: `u_init = 1`, the others at `floor`.
    pub const fn resting(floor: f64) -> Self {
        Self {
            u_init: 1.0,
            u_hopf: floor,
            u_final: floor,
        }
    }

    /// The most active neuron's regime.
    pub fn winner(&self) -> Regime {
        if self.u_hopf > self.u_init && self.u_hopf >= self.u_final {
            Regime::Hopf
        } else if self.u_final > self.u_init && self.u_final > self.u_hopf {
            Regime::Final
        } else {
            Regime::Init
        }
    }

    /// As an array `[u_init, u_hopf, u_final]`.
    pub const fn as_array(&self) -> [f64; 3] {
        [self.u_init, self.u_hopf, self.u_final]
    }
}

/// Constants of the neural dynamics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct NeuronCoeffs {
    /// 1 / tau_u.
    pub inv_tau: f64,
    /// mu of the selected neuron.
    pub mu_on: f64,
    /// mu of the others (<= 0).
    pub mu_off: f64,
    /// nu.
    pub nu: f64,
    /// Lowest activation.
    pub floor: f64,
}

/// `u_i'` for all three neurons:
/// `tau_u u_i' = mu_i u_i - |mu_i| u_i^3 - nu sum_{j != i} u_j^2 u_i`.
pub(crate) fn neuron_rates(u: [f64; 3], regime: Regime, c: &NeuronCoeffs) -> [f64; 3] {
    let sel = match regime {
        Regime::Init => 0,
        Regime::Hopf => 1,
        Regime::Final => 2,
    };
    let sq = [u[0] * u[0], u[1] * u[1], u[2] * u[2]];
    let total = sq[0] + sq[1] + sq[2];
    let mut out = [0.0; 3];
    for i in 0..3 {
        let mu = if i == sel { c.mu_on } else { c.mu_off };
        let others = total - sq[i];
        out[i] = c.inv_tau * (mu * u[i] - mu.abs() * u[i] * sq[i] - c.nu * others * u[i]);
    }
    out
}
