//! Predict a pendulum pass: a released pendulum (the ground-truth simulator) is
//! seen for one second by a 30 fps camera with 2 mm of lateral noise; the
//! extended Kalman filter fuses those readings and predicts the next passes of
//! the ball through the bottom, which are then compared with the truth.
//!
//! Run: `cargo run -p rt-core --example predict_pass`. It exits non-zero when
//! a predicted pass is more than 5 ms from the true one.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rt_core::ekf::{Crossing, Ekf, EkfParams, PassDirection};
use rt_core::pendulum::{PendulumGeometry, PendulumModel, PendulumSim};

/// Standard normal draw (Box-Muller).
fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.random::<f64>().max(1e-300);
    let u2: f64 = rng.random::<f64>();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // The paper's pendulum: 1.93 m string, intercept point 0.6 m in front of
    // the robot's base, 0.3 m above it.
    let model = PendulumModel {
        length_m: 1.93,
        gravity_mps2: 9.81,
        damping_per_s: 0.03,
    };
    let geometry = PendulumGeometry::new(model.length_m, 0.6, 0.3)?;

    // The truth: held at 20 degrees, released at t = 0.
    let mut truth = PendulumSim::held_at(model, geometry, 20f64.to_radians(), 0.0)?;
    truth.release(0.0)?;

    // The filter believes the same model; it learns the swing from the camera.
    let mut ekf = Ekf::new(EkfParams::default(), model, geometry)?;
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let frame_s = 1.0 / 30.0;
    let mut t = 0.0;
    let mut fused = 0;
    while t <= 1.0 {
        truth.advance_to(t)?;
        let z_m = truth.lateral_m() + 0.002 * gauss(&mut rng);
        ekf.measure(t, z_m)?;
        fused += 1;
        t += frame_s;
    }
    truth.advance_to(1.0)?;
    println!("fused {fused} camera readings over 1 s");

    // The next three passes through the bottom, predicted from t = 1 s.
    let mut passes = [Crossing::default(); 3];
    let n = ekf.crossings(1.0, 0.0, PassDirection::Any, &mut passes)?;
    let mut worst_ms: f64 = 0.0;
    for pass in &passes[..n] {
        // The true pass: the truth runs on from the previous one.
        let ahead_s = pass.t_s - truth.time_s() + 0.2;
        let true_s = truth
            .next_crossing_s(0.0, ahead_s)
            .ok_or("the true ball does not pass in time")?;
        truth.advance_to(true_s + 0.05)?;
        let err_ms = (pass.t_s - true_s) * 1e3;
        worst_ms = worst_ms.max(err_ms.abs());
        println!(
            "pass predicted at {:.4} s (std {:.2} ms, {:+.2} m/s), true {:.4} s: error {:+.2} ms",
            pass.t_s,
            pass.time_std_s * 1e3,
            pass.lateral_velocity_mps,
            true_s,
            err_ms
        );
    }
    if n == 0 || worst_ms > 5.0 {
        return Err(format!("{n} passes predicted, worst error {worst_ms:.2} ms").into());
    }
    println!("{n} passes predicted, worst error {worst_ms:.2} ms");
    Ok(())
}
