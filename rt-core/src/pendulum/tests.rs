use super::*;

fn model(alpha: f64) -> PendulumModel {
    PendulumModel {
        length_m: 1.93,
        gravity_mps2: 9.81,
        damping_per_s: alpha,
    }
}

fn geom() -> PendulumGeometry {
    PendulumGeometry::new(1.93, 0.6, 0.3).unwrap()
}

/// Exact period of the undamped pendulum released from rest at `a` rad:
/// `4 K(sin(a/2)) / omega0`, with `K` from the arithmetic-geometric mean.
fn exact_period(m: &PendulumModel, a: f64) -> f64 {
    let k = (a / 2.0).sin();
    let (mut x, mut y) = (1.0_f64, (1.0 - k * k).sqrt());
    for _ in 0..30 {
        let (nx, ny) = (0.5 * (x + y), (x * y).sqrt());
        x = nx;
        y = ny;
    }
    let kk = std::f64::consts::PI / (2.0 * x);
    4.0 * kk / m.omega0_sq().sqrt()
}

#[test]
fn energy_is_conserved_without_damping() {
    let m = model(0.0);
    let mut sim = PendulumSim::held_at(m, geom(), 35f64.to_radians(), 0.0).unwrap();
    sim.release(0.0).unwrap();
    let e0 = m.energy(sim.state());
    let mut worst = 0.0_f64;
    for i in 1..=600 {
        sim.advance_to(f64::from(i) * 0.1).unwrap();
        worst = worst.max(((m.energy(sim.state()) - e0) / e0).abs());
    }
    // 60 s at 1 ms RK4 steps.
    assert!(worst < 1e-9, "relative energy drift {worst}");
}

#[test]
fn damping_removes_energy_at_the_expected_rate() {
    // For small angles E ~ E0 exp(-alpha t).
    let m = model(0.05);
    let mut sim = PendulumSim::held_at(m, geom(), 2f64.to_radians(), 0.0).unwrap();
    sim.release(0.0).unwrap();
    let e0 = m.energy(sim.state());
    let period = exact_period(&m, 2f64.to_radians());
    sim.advance_to(10.0 * period).unwrap();
    let ratio = m.energy(sim.state()) / e0;
    let expected = (-0.05 * 10.0 * period).exp();
    assert!(
        (ratio / expected - 1.0).abs() < 2e-3,
        "{ratio} vs {expected}"
    );
}

#[test]
fn period_matches_the_exact_large_angle_period() {
    let m = model(0.0);
    for deg in [5.0_f64, 20.0, 35.0] {
        let a = deg.to_radians();
        let mut sim = PendulumSim::held_at(m, geom(), a, 0.0).unwrap();
        sim.release(0.0).unwrap();
        // From rest at +a, the bottom is reached after a quarter period.
        let t_quarter = sim.next_crossing_s(0.0, 5.0).unwrap();
        let exact = exact_period(&m, a);
        assert!(
            (4.0 * t_quarter - exact).abs() < 1e-7,
            "{deg} deg: {} vs {exact}",
            4.0 * t_quarter
        );
    }
    // And the small-angle formula holds for small angles.
    assert!((exact_period(&m, 1e-4) / m.small_angle_period_s() - 1.0).abs() < 1e-8);
}

#[test]
fn held_ball_stays_then_swings_from_rest() {
    let m = model(0.03);
    let mut sim = PendulumSim::held_at(m, geom(), 0.4, 0.0).unwrap();
    sim.advance_to(1.0).unwrap();
    assert!(sim.is_held());
    assert_eq!(sim.state(), Vector2::new(0.4, 0.0));
    sim.release(1.5).unwrap();
    assert_eq!(sim.time_s(), 1.5);
    assert_eq!(sim.state(), Vector2::new(0.4, 0.0));
    sim.advance_to(1.6).unwrap();
    // Gravity pulls a positive angle back towards zero.
    assert!(sim.state()[0] < 0.4 && sim.state()[1] < 0.0);
}

#[test]
fn geometry_signs_and_rest_position() {
    let g = geom();
    let rest = g.rest_position_m();
    assert!((rest - Vector3::new(0.6, 0.0, 0.3)).norm() < 1e-12);
    assert!((g.ball_position_m(0.0) - rest).norm() < 1e-12);
    // Positive phi: ball towards +y and up; lateral = y = l sin(phi).
    let p = g.ball_position_m(0.3);
    assert!(p.y > 0.0 && p.z > rest.z);
    assert!((p.x - 0.6).abs() < 1e-12, "the swing plane is x = distance");
    assert!((g.lateral_m(0.3) - p.y).abs() < 1e-12);
    assert!(((p - g.pivot_m).norm() - 1.93).abs() < 1e-12);
    // Velocity is the derivative of position.
    let h = 1e-6;
    let fd = (g.ball_position_m(0.3 + h) - g.ball_position_m(0.3 - h)) / (2.0 * h);
    assert!((g.ball_velocity_mps(0.3, 1.0) - fd).norm() < 1e-8);
    assert!((g.position_jacobian(0.3) - fd).norm() < 1e-8);
}

#[test]
fn bad_input_is_refused_and_changes_nothing() {
    let m = model(0.03);
    let mut sim = PendulumSim::held_at(m, geom(), 0.3, 0.0).unwrap();
    sim.release(0.0).unwrap();
    sim.advance_to(1.0).unwrap();
    let before = sim.clone();
    assert!(matches!(
        sim.advance_to(0.5),
        Err(SimError::TimeBackwards { .. })
    ));
    assert!(sim.advance_to(f64::NAN).is_err());
    assert!(matches!(sim.advance_to(1e12), Err(SimError::TooFar { .. })));
    assert!(sim.advance_to_with_accel(2.0, f64::INFINITY).is_err());
    assert_eq!(sim, before);
    assert!(PendulumSim::held_at(m, geom(), f64::NAN, 0.0).is_err());
    let err = PendulumGeometry::new(1.93, 5.0, 0.3).unwrap_err();
    assert_eq!(err.field(), Some("task.distance_m"));
    let err = m.with_damping(f64::NAN).unwrap_err();
    assert_eq!(err.field(), Some("pendulum.damping_per_s"));
}

#[test]
fn model_from_params_validates() {
    let p = PendulumParams::default();
    let m = PendulumModel::from_params(&p).unwrap();
    assert_eq!(m.length_m, 1.93);
    let bad = PendulumParams {
        length_m: -1.0,
        ..p
    };
    assert_eq!(
        PendulumModel::from_params(&bad).unwrap_err().field(),
        Some("pendulum.length_m")
    );
}
