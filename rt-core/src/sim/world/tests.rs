//! One test per world effect: each acts, by the amount its physics predicts.

use nalgebra::{Vector2, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::*;
use crate::kinematics::fk::tool_pose;
use crate::kinematics::iiwa7::JOINTS;
use crate::kinematics::{Joints, Tool};
use crate::params::{RangeParam, Scenario};
use crate::vision::{CameraIntrinsics, CameraPose, SwingPlaneCalibration};

fn pend(length_m: f64) -> TruePendulumParams {
    TruePendulumParams {
        pivot_m: Vector3::new(0.6, 0.0, 0.3 + length_m),
        length_m,
        gravity_mps2: 9.81,
        damping_per_s: 0.0,
        drag_per_m: 0.0,
        friction_mps2: 0.0,
        disturbance_mps2: 0.0,
        ball_radius_m: 0.0335,
        restitution: 0.0,
    }
}

/// Times of successive upward crossings of y = 0 and the peak |y| between them.
fn swing(p: TruePendulumParams, angle_deg: f64, oop_deg: f64, span_s: f64) -> (Vec<f64>, Vec<f64>) {
    let mut b = TruePendulum::held_at(p, angle_deg.to_radians(), oop_deg.to_radians(), 0.0, 1);
    b.release(0.0);
    let mut crossings = Vec::new();
    let mut peaks = Vec::new();
    let mut peak: f64 = 0.0;
    let mut t = 0.0;
    while t < span_s {
        let tc = b.next_crossing_s(0.0, span_s - t);
        let Some(tc) = tc else { break };
        // Peak on the way (sampled at 1 ms).
        while b.time_s() + 1e-3 < tc {
            let tn = b.time_s() + 1e-3;
            b.advance_to(tn);
            peak = peak.max(b.ball_position_m().y.abs());
        }
        b.advance_to(tc + 1e-6);
        crossings.push(tc);
        peaks.push(peak);
        peak = 0.0;
        t = b.time_s();
    }
    (crossings, peaks)
}

#[test]
fn length_error_changes_the_period_as_sqrt_of_length() {
    // Small swing (2 deg): T = 2 pi sqrt(L / g) (1 + a^2/16).
    for l in [1.93, 1.95] {
        let (c, _) = swing(pend(l), 2.0, 0.0, 12.0);
        let period = (c[c.len() - 1] - c[0]) / ((c.len() - 1) as f64 / 2.0);
        let a = 2f64.to_radians();
        let expected = std::f64::consts::TAU * (l / 9.81).sqrt() * (1.0 + a * a / 16.0);
        assert!(
            (period - expected).abs() < 2e-5,
            "L {l}: {period} vs {expected}"
        );
    }
    // +2 cm of string: the period grows by about 5 ms.
    let t1 = swing(pend(1.93), 2.0, 0.0, 12.0).0;
    let t2 = swing(pend(1.95), 2.0, 0.0, 12.0).0;
    let d = (t2[8] - t2[0]) / 4.0 - (t1[8] - t1[0]) / 4.0;
    assert!(
        (d - 0.0145).abs() < 0.002 || (d - 0.0073).abs() < 0.002,
        "{d}"
    );
}

#[test]
fn quadratic_drag_loses_amplitude_by_the_predicted_amount() {
    // Per cycle, quadratic drag k|v|v takes dA = (8/3) k A^2 off the arc
    // amplitude A (energy balance over one sinusoidal cycle).
    let mut p = pend(1.93);
    let k = TruePendulumParams::drag_factor(1.2, 0.55, 0.0335, 0.057);
    assert!((k - 0.0204).abs() < 2e-4, "{k}");
    p.drag_per_m = k;
    let angle = 10.0;
    let (_, peaks) = swing(p, angle, 0.0, 30.0);
    let (_, free) = swing(pend(1.93), angle, 0.0, 30.0);
    // The swing's peak lateral after n half-cycles.
    let a0 = 1.93 * angle.to_radians(); // arc amplitude
    let n_cycles = 5.0;
    let mut a = a0;
    for _ in 0..(n_cycles as usize * 50) {
        a -= (8.0 / 3.0) * k * a * a / 50.0;
    }
    // peaks[i] is the peak before crossing i (upward crossings every full
    // cycle, downward ones in between: crossings alternate).
    let i = (2.0 * n_cycles) as usize;
    let measured_arc = 1.93 * (peaks[i] / 1.93).asin();
    assert!(
        free[i] > 0.99 * 1.93 * angle.to_radians().sin(),
        "no drag: no loss"
    );
    assert!(
        (measured_arc - a).abs() < 0.08 * (a0 - a),
        "after {n_cycles} cycles: {measured_arc} m, predicted {a} m (from {a0} m)"
    );
}

#[test]
fn linear_damping_and_pivot_friction_act() {
    let mut p = pend(1.93);
    p.damping_per_s = 0.03;
    let (_, peaks) = swing(p, 10.0, 0.0, 20.0);
    // Amplitude ~ exp(-alpha t / 2).
    let t_peak: f64 = 10.0 * 2.79 / 2.0;
    let pred = 1.93 * 10f64.to_radians().sin() * (-0.03 * t_peak / 2.0).exp();
    assert!(
        (peaks[10] - pred).abs() < 0.01 * pred,
        "{} vs {pred}",
        peaks[10]
    );
    // Coulomb friction: linear decay, 4 mu / w^2 of arc per cycle.
    let mut q = pend(1.93);
    q.friction_mps2 = 0.01;
    let (_, fp) = swing(q, 10.0, 0.0, 20.0);
    let w2 = 9.81 / 1.93;
    let per_cycle = 4.0 * 0.01 / w2;
    let lost = 1.93 * 10f64.to_radians() - 1.93 * (fp[10] / 1.93).asin();
    assert!(
        (lost - 5.0 * per_cycle).abs() < 0.1 * 5.0 * per_cycle,
        "{lost} vs {}",
        5.0 * per_cycle
    );
}

#[test]
fn an_out_of_plane_release_swings_out_of_the_plane() {
    let p = pend(1.93);
    let mut b = TruePendulum::held_at(p, 20f64.to_radians(), 1f64.to_radians(), 0.0, 1);
    let x0 = b.ball_position_m().x - 0.6;
    assert!(
        (x0 - 1.93 * 1f64.to_radians().sin() * 20f64.to_radians().cos()).abs() < 1e-3,
        "{x0}"
    );
    b.release(0.0);
    let mut xs: Vec<f64> = Vec::new();
    for k in 1..3000 {
        b.advance_to(f64::from(k) * 1e-3);
        xs.push(b.ball_position_m().x - 0.6);
        let r = (b.ball_position_m() - p.pivot_m).norm();
        assert!((r - 1.93).abs() < 1e-9, "string length {r}");
    }
    let max = xs.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    assert!(max > 0.02 && max < 0.04, "out of plane: {max} m");
    // In the plane, nothing leaves it.
    let mut c = TruePendulum::held_at(p, 20f64.to_radians(), 0.0, 0.0, 1);
    c.release(0.0);
    c.advance_to(3.0);
    assert!((c.ball_position_m().x - 0.6).abs() < 1e-12);
}

#[test]
fn disturbances_push_the_ball_and_are_seeded() {
    let mut p = pend(1.93);
    p.disturbance_mps2 = 0.05;
    let run = |seed| {
        let mut b = TruePendulum::held_at(p, 0.0, 0.0, 0.0, seed);
        b.release(0.0);
        b.advance_to(5.0);
        b.ball_position_m()
    };
    let a = run(1);
    assert_eq!(a, run(1));
    assert_ne!(a, run(2));
    // From rest it moves (both in and out of the plane).
    assert!((a.y).abs() > 1e-4 && (a.x - 0.6).abs() > 1e-4, "{a}");
}

#[test]
fn a_release_delay_holds_the_ball_longer() {
    let mut s = Scenario::default();
    let mut w = WorldParams::default();
    w.pendulum.release_delay_ms = Some(RangeParam::new(20.0, 40.0));
    s.world = Some(w);
    let rest = Vector3::new(0.6, 0.0, 0.3);
    let world = World::for_trial(&s, 1, 0, &rest).unwrap();
    let d = world.trial.release_delay_s;
    assert!((0.020..=0.040).contains(&d), "{d}");
    // The ball held until pin + delay has not moved at the pin time + delay/2.
    let mut b = TruePendulum::held_at(world.pendulum, 0.3, 0.0, 0.0, 1);
    let start = b.ball_position_m();
    b.advance_to(d / 2.0);
    assert_eq!(b.ball_position_m(), start);
    b.release(d);
    b.advance_to(d + 0.05);
    assert_ne!(b.ball_position_m(), start);
}

#[test]
fn an_unset_release_delay_is_the_believed_one() {
    // A world without `release_delay_ms` has the magnet the controller
    // believes (as every unset key is the belief): 15 ms believed, 15 ms drawn.
    let mut s = Scenario::default();
    s.control.release_delay_prior_ms = 15.0;
    s.world = Some(WorldParams::default());
    let rest = Vector3::new(0.6, 0.0, 0.3);
    for i in 0..3 {
        let world = World::for_trial(&s, 1, i, &rest).unwrap();
        assert!((world.trial.release_delay_s - 0.015).abs() < 1e-12);
    }
    // Believed none: none.
    s.control.release_delay_prior_ms = 0.0;
    assert_eq!(
        World::for_trial(&s, 1, 0, &rest)
            .unwrap()
            .trial
            .release_delay_s,
        0.0
    );
}

#[test]
fn the_ball_is_stopped_by_the_tool_disc() {
    // A disc facing the swing at the rest point, its normal along -y (the
    // ball comes from +y): with restitution 0 the ball stops against it.
    let p = pend(1.93);
    let mut b = TruePendulum::held_at(p, 15f64.to_radians(), 0.0, 0.0, 1);
    b.release(0.0);
    let disc = Disc {
        centre_m: Vector3::new(0.6, -0.04, 0.3),
        normal: Vector3::new(0.0, 1.0, 0.0),
        radius_m: 0.03,
    };
    let mut min_y = f64::INFINITY;
    for k in 1..3000 {
        b.advance_to(f64::from(k) * 1e-3);
        b.collide(&disc, &Vector3::zeros(), 0.0);
        min_y = min_y.min(b.ball_position_m().y);
    }
    assert!(b.hits() >= 1);
    // Never through the disc: the ball centre stays a radius away from it.
    assert!(min_y > -0.04 + 0.0335 - 1.5e-3, "{min_y}");
    // Without the disc it swings through to the other side.
    let mut c = TruePendulum::held_at(p, 15f64.to_radians(), 0.0, 0.0, 1);
    c.release(0.0);
    c.advance_to(1.4);
    assert!(c.ball_position_m().y < -0.45, "{}", c.ball_position_m());
}

fn camera() -> WorldCamera {
    WorldCamera::truthful(
        CameraPose::default(),
        CameraIntrinsics::from_hfov(1280, 720, 70.0),
        720,
        0.035,
    )
}

#[test]
fn frames_are_stamped_as_the_webcam_source_stamps_them() {
    let mut c = camera();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let f = c.timing(1.0, &mut rng);
    assert!(
        (f.t_stamp_s - 1.0).abs() < 1e-12,
        "truthful: stamp = capture"
    );
    // The camera is 12 ms slower than believed, with up to 4 ms jitter: every
    // stamp is late by 12..16 ms.
    c.latency_offset_s = 0.012;
    c.jitter_s = 0.004;
    let errs: Vec<f64> = (0..200)
        .map(|k| {
            let t = f64::from(k) / 30.0;
            let f = c.timing(t, &mut rng);
            assert!((f.t_delivered_s - f.t_stamp_s - 0.035).abs() < 1e-12);
            f.t_stamp_s - t
        })
        .collect();
    let lo = errs.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = errs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    assert!(
        lo >= 0.012 - 1e-12 && hi <= 0.016 + 1e-12 && hi - lo > 0.003,
        "{lo} {hi}"
    );
}

#[test]
fn no_frame_reaches_the_host_before_its_last_row_is_read_and_sent() {
    let mut c = camera();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    c.exposure_s = 0.004;
    c.rolling_shutter_s = 0.025;
    c.transfer_s = 0.002;
    c.frame_jitter_s = 0.001;
    c.jitter_s = 0.004;
    // Drawn 29.7..33.7 ms after the slot: often before the last row is read
    // and sent (31 ms after the exposure's start, 30..32 after the slot).
    c.latency_offset_s = 0.0297 - 0.035;
    let (mut floored, mut free) = (0, 0);
    for k in 0..600 {
        let slot = f64::from(k) / 30.0;
        let f = c.timing(slot, &mut rng);
        let after_start = f.t_delivered_s - f.t_start_s;
        assert!(after_start >= 0.031 - 1e-12, "{after_start}");
        assert!((f.t_delivered_s - f.t_stamp_s - 0.035).abs() < 1e-12);
        if (after_start - 0.031).abs() < 1e-12 {
            floored += 1;
        } else {
            // Not floored: the drawn latency and jitter, as before.
            let after_slot = f.t_delivered_s - slot;
            assert!(
                (0.0297 - 1e-12..=0.0337 + 1e-12).contains(&after_slot),
                "{after_slot}"
            );
            free += 1;
        }
    }
    assert!(
        floored > 100 && free > 100,
        "floored {floored}, free {free}"
    );
    // A latency past the readout is untouched: delivery = slot + L + j.
    c.latency_offset_s = 0.010;
    for k in 0..200 {
        let slot = f64::from(k) / 30.0;
        let after_slot = c.timing(slot, &mut rng).t_delivered_s - slot;
        assert!(
            (0.045 - 1e-12..=0.049 + 1e-12).contains(&after_slot),
            "{after_slot}"
        );
    }
}

#[test]
fn rolling_shutter_shifts_a_moving_balls_row_time_and_place() {
    let mut c = camera();
    let rest = Vector3::new(0.6, 0.0, 0.3);
    // Ball moving along +y at 2 m/s; it is below the image centre's row.
    let ball = |t: f64| rest + Vector3::new(0.0, 2.0 * t, 0.0);
    let s0 = c.sight(0.0, ball).unwrap();
    assert_eq!(s0.t_row_s, 0.0);
    c.rolling_shutter_s = 0.030;
    let s1 = c.sight(0.0, ball).unwrap();
    let expected = s1.px.y / 720.0 * 0.030;
    assert!(
        (s1.t_row_s - expected).abs() < 1e-6 && s1.t_row_s > 0.01,
        "{s1:?}"
    );
    // The ball is seen where it was at its row's time: 2 m/s * t_row further.
    let cal = SwingPlaneCalibration::from_pose(c.intrinsics, &c.believed_pose, &rest, 0.0335);
    let y0 = cal.lateral_m(s0.px.x, s0.px.y).unwrap();
    let y1 = cal.lateral_m(s1.px.x, s1.px.y).unwrap();
    assert!(((y1 - y0) - 2.0 * s1.t_row_s).abs() < 1e-4, "{y0} {y1}");
}

#[test]
fn exposure_smears_the_ball_to_its_mid_exposure_place() {
    let mut c = camera();
    let rest = Vector3::new(0.6, 0.0, 0.3);
    let ball = |t: f64| rest + Vector3::new(0.0, 2.0 * t, 0.0);
    c.exposure_s = 0.010;
    let s = c.sight(0.0, ball).unwrap();
    let cal = SwingPlaneCalibration::from_pose(c.intrinsics, &c.believed_pose, &rest, 0.0335);
    let y = cal.lateral_m(s.px.x, s.px.y).unwrap();
    // Centroid of a uniform smear: the middle of the exposure (1 cm).
    assert!((y - 0.010).abs() < 2e-4, "{y}");
}

#[test]
fn lens_distortion_and_pose_error_move_the_measured_lateral() {
    let rest = Vector3::new(0.6, 0.0, 0.3);
    let cal = {
        let c = camera();
        SwingPlaneCalibration::from_pose(c.intrinsics, &c.believed_pose, &rest, 0.0335)
    };
    let at = rest + Vector3::new(0.0, 0.4, 0.1);
    let measure = |c: &WorldCamera| {
        let s = c.sight(0.0, |_| at).unwrap();
        cal.lateral_m(s.px.x, s.px.y).unwrap()
    };
    let truthful = measure(&camera());
    assert!((truthful - 0.4).abs() < 1e-9, "{truthful}");
    // Barrel distortion pulls off-centre points towards the image centre:
    // the offset from where the optical axis meets the plane (y = 0.25)
    // shrinks by (1 + k1 r^2), r^2 the normalised radius squared.
    let mut d = camera();
    d.distortion = [-0.1, 0.0, 0.0, 0.0];
    let yd = measure(&d);
    let r2 = (0.15f64 / 1.6).powi(2) + (0.05f64 / 1.6).powi(2);
    let predicted = 0.25 + 0.15 * (1.0 - 0.1 * r2);
    assert!(
        (yd - predicted).abs() < 2e-6 && yd < 0.4 - 1e-4,
        "{yd} vs {predicted}"
    );
    // Tangential distortion acts too.
    let mut t = camera();
    t.distortion = [0.0, 0.0, 0.0, 0.005];
    assert!((measure(&t) - 0.4).abs() > 1e-4, "{}", measure(&t));
    // One degree of yaw error moves it by about distance * 1 deg.
    let mut p = camera();
    p.base_from_camera =
        nalgebra::Rotation3::from_euler_angles(0.0, 0.0, 1f64.to_radians()) * p.base_from_camera;
    let yp = measure(&p);
    assert!(
        ((yp - 0.4).abs() - 1.6 * 1f64.to_radians()).abs() < 0.01,
        "{yp}"
    );
    // The equivalent centre renders where the true camera sees the ball.
    let s = d.sight(0.0, |_| at).unwrap();
    let eq = d.equivalent_centre_m(&s.px, &at);
    let back = cal
        .intrinsics
        .project(&d.believed_pose.to_camera(&eq))
        .unwrap();
    assert!((back - Vector2::new(s.px.x, s.px.y)).norm() < 1e-6);
}

#[test]
fn robot_latency_drifts_within_a_session_and_changes_between_sessions() {
    let mut w = WorldParams::default();
    w.robot.latency_ms = Some(RangeParam::new(5.0, 25.0));
    w.robot.latency_drift_ms = RangeParam::fixed(2.0);
    let s0 = w.draw_session(1, 0, 8.0);
    let s1 = w.draw_session(1, 1, 8.0);
    assert_ne!(s0.robot_latency_s, s1.robot_latency_s);
    assert_eq!(s0, w.draw_session(1, 0, 8.0));
    let m = LatencyModel::from_session(&s0, 0.0);
    let vals: Vec<f64> = (0..600).map(|k| m.latency_s(f64::from(k))).collect();
    let lo = vals.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = vals.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    assert!((hi - lo - 0.004).abs() < 2e-4, "drift span {lo}..{hi}");
    // Sessions group trials.
    assert_eq!(w.session_of(19), 0);
    assert_eq!(w.session_of(20), 1);
}

fn session(omega_hz: f64, zeta: f64) -> SessionDraw {
    let mut w = WorldParams::default();
    w.robot.servo_natural_hz = RangeParam::fixed(omega_hz);
    w.robot.servo_damping_ratio = RangeParam::fixed(zeta);
    w.draw_session(1, 0, 8.0)
}

#[test]
fn the_second_order_servo_lags_by_two_zeta_v_over_omega() {
    let s = session(10.0, 0.7);
    let mut j = WorldJoints::new([0.0; JOINTS], &s, 0.005, 1.0, false, 0.0, 1);
    j.set_interpolation_s(1e-3);
    // A ramp of 0.5 rad/s on A1 for 2 s, in 1 ms steps.
    let v = 0.5;
    for k in 1..=2000 {
        let t = f64::from(k) * 1e-3;
        let mut sp = [0.0; JOINTS];
        sp[0] = v * t;
        j.integrate(&sp, 1e-3);
    }
    let lag = v * 2.0 - j.q()[0];
    let w = std::f64::consts::TAU * 10.0;
    assert!((lag - 2.0 * 0.7 * v / w).abs() < 2e-4, "lag {lag}");
    // Faster: the lag grows in proportion.
    let mut j2 = WorldJoints::new([0.0; JOINTS], &s, 0.005, 1.0, false, 0.0, 1);
    j2.set_interpolation_s(1e-3);
    for k in 1..=2000 {
        let mut sp = [0.0; JOINTS];
        sp[0] = 2.0 * v * f64::from(k) * 1e-3;
        j2.integrate(&sp, 1e-3);
    }
    assert!(((2.0 * v * 2.0 - j2.q()[0]) / lag - 2.0).abs() < 0.01);
}

#[test]
fn measured_positions_are_noisy_around_the_truth() {
    let s = session(10.0, 0.7);
    let mut j = WorldJoints::new([0.1; JOINTS], &s, 0.005, 1.0, false, 1e-4, 3);
    let n = 2000;
    let mut sum2 = 0.0;
    for _ in 0..n {
        let m = j.measured();
        sum2 += (m[2] - 0.1) * (m[2] - 0.1);
    }
    let std = (sum2 / f64::from(n)).sqrt();
    assert!((std - 1e-4).abs() < 1e-5, "{std}");
    assert_eq!(j.q(), &[0.1; JOINTS]);
}

#[test]
fn the_dynamics_give_gravity_torques_equal_to_the_potential_gradient() {
    let dyn_ = ArmDynamics::default();
    let q = [0.3, 0.7, -0.4, -1.2, 0.5, 0.9, 0.2];
    let z = [0.0; JOINTS];
    let tau = dyn_.torques(&q, &z, &z);
    // Potential energy sum m g z_com, differentiated numerically.
    let pot = |q: &[f64; JOINTS]| {
        let mut r = nalgebra::Matrix3::identity();
        let mut p = Vector3::zeros();
        let mut v = 0.0;
        #[expect(clippy::needless_range_loop, reason = "four tables by the same index")]
        for i in 0..JOINTS {
            p += r * Vector3::from(dynamics::JOINT_ORIGIN_M[i]);
            let axis = nalgebra::Unit::new_unchecked(Vector3::from(dynamics::JOINT_AXIS[i]));
            r *= nalgebra::Rotation3::from_axis_angle(&axis, q[i]).matrix();
            let (c, m, _) = dynamics::LINKS[i];
            v += m * 9.81 * (p + r * Vector3::from(c)).z;
        }
        v
    };
    for i in 0..JOINTS {
        let mut a = q;
        let mut b = q;
        a[i] += 1e-6;
        b[i] -= 1e-6;
        let g = (pot(&a) - pot(&b)) / 2e-6;
        assert!((tau[i] - g).abs() < 1e-4, "A{}: {} vs {g}", i + 1, tau[i]);
    }
    // The dynamics' frames are the DH model's: same flange.
    let f = dynamics::flange_position_m(&q);
    let d = tool_pose(&Joints::from(q), &Tool::none())
        .translation
        .vector;
    assert!((f - d).norm() < 1e-3, "{f} vs {d}");
}

#[test]
fn the_mass_matrix_is_symmetric_and_positive() {
    let dyn_ = ArmDynamics::default();
    let q = [0.1, 0.5, 0.2, -1.0, 0.3, 0.8, 0.0];
    let z = [0.0; JOINTS];
    let g = dyn_.torques(&q, &z, &z);
    let mut m = nalgebra::SMatrix::<f64, JOINTS, JOINTS>::zeros();
    for j in 0..JOINTS {
        let mut e = [0.0; JOINTS];
        e[j] = 1.0;
        let t = dyn_.torques(&q, &z, &e);
        for i in 0..JOINTS {
            m[(i, j)] = t[i] - g[i];
        }
    }
    assert!((m - m.transpose()).abs().max() < 1e-9);
    assert!(m.cholesky().is_some());
    // A heavier arm (inertia error) needs proportionally more torque.
    let heavy = ArmDynamics::scaled(&[1.1; 8]);
    let t = heavy.torques(&q, &z, &z);
    assert!((t[1] / g[1] - 1.1).abs() < 1e-9);
}

#[test]
fn a_torque_trip_aborts_a_too_fast_motion_and_names_the_joint() {
    let s = session(30.0, 0.7);
    let q0 = [0.0, 0.5, 0.0, -1.0, 0.0, 1.0, 0.0];
    // A sudden 0.5 rad step on A2: the servo's acceleration needs far more than 176 N m.
    let mut j = WorldJoints::new(q0, &s, 0.005, 1.0, true, 0.0, 1);
    let mut sp = q0;
    sp[1] += 0.5;
    let trip = j.integrate(&sp, 0.01).expect("trips");
    assert_eq!(trip.name, "A2");
    assert!(trip.torque_nm.abs() > 176.0, "{trip}");
    assert!(trip.to_string().contains("A2"), "{trip}");
    // Once tripped, the drives hold: no more motion.
    let q_trip = *j.q();
    j.integrate(&sp, 0.1);
    assert_eq!(j.q(), &q_trip);
    // A gentle step within the limits does not trip.
    let mut k = WorldJoints::new(q0, &s, 0.005, 1.0, true, 0.0, 1);
    // (through the drive's interpolator, as FRI commands arrive)
    k.set_interpolation_s(0.2);
    let mut small = q0;
    small[1] += 0.002;
    let r = k.integrate(&small, 0.5);
    assert!(r.is_none(), "{r:?}");
    assert!(k.peak_torque_ratio()[1] > 0.1 && k.peak_torque_ratio()[1] < 1.0);
}

#[test]
fn geometry_errors_move_the_true_tool_and_intercept_point() {
    let q = [0.0, 0.5, 0.0, -1.2, 0.0, 1.0, 0.0];
    let nominal = TrueArm::nominal(0.10, 0.03);
    let model = tool_pose(&Joints::from(q), &Tool::along_z(0.10))
        .translation
        .vector;
    assert!((nominal.tool_point(&q) - model).norm() < 1e-12);
    let mut w = WorldParams::default();
    w.geometry.tool_length_error_m = RangeParam::fixed(0.005);
    w.geometry.dh_length_error_m = RangeParam::fixed(0.001);
    w.geometry.intercept_error_m = RangeParam::fixed(0.003);
    let s = w.draw_session(1, 0, 8.0);
    let arm = TrueArm::from_session(0.10, 0.03, &s);
    let moved = (arm.tool_point(&q) - model).norm();
    assert!(moved > 0.003 && moved < 0.015, "{moved}");
    let rest = Vector3::new(0.6, 0.0, 0.3);
    let ti = true_intercept_m(&rest, &s);
    assert!(((ti - rest).norm() - 0.003 * 3f64.sqrt()).abs() < 1e-12);
    // The disc sits at the tool point, normal along the tool axis.
    let d = arm.disc(&q);
    assert!((d.centre_m - arm.tool_point(&q)).norm() < 1e-12);
    assert!((d.normal.norm() - 1.0).abs() < 1e-12);
}

#[test]
fn the_physical_judge_times_the_settling_and_needs_contact() {
    // Tool moving along +x to (0.6, 0, 0.3) and settling at t = 1.0 s; the
    // ball passes y = 0 there at t* = 1.010 s.
    let disc_at = |x: f64| Disc {
        centre_m: Vector3::new(x, 0.0, 0.3 + 0.0335 + 0.01),
        normal: Vector3::new(0.0, 0.0, 1.0),
        radius_m: 0.03,
    };
    let mut trace = Vec::new();
    for k in 0..300 {
        let t = f64::from(k) * 5e-3;
        let u = (t / 1.0).min(1.0);
        let x = 0.3 + 0.3 * (u - (std::f64::consts::TAU * u).sin() / std::f64::consts::TAU);
        trace.push(WorldSample {
            t_s: t,
            ball_m: Vector3::new(0.6, 1.5 * (1.010 - t), 0.3),
            disc: disc_at(x),
        });
    }
    let j = judge_physical(&trace, &[1.010, 2.4], 1.0, 0.0335, 20.0).unwrap();
    assert_eq!(j.t_star_s, 1.010);
    // Settling within 2 mm happens before the profile's end: early, signed.
    assert!(
        j.timing_error_ms < -10.0 && j.timing_error_ms > -200.0,
        "{j:?}"
    );
    // The disc is 1 cm above the ball: no contact.
    assert!(
        j.contact_s.is_none() && (j.min_gap_m - 0.01).abs() < 1e-3,
        "{j:?}"
    );
    assert!(!j.hit_in_time);
    // Lower the disc onto the ball: contact in the pass.
    for s in &mut trace {
        s.disc.centre_m.z -= 0.015;
    }
    let j2 = judge_physical(&trace, &[1.010, 2.4], 1.0, 0.0335, 200.0).unwrap();
    assert!(j2.contact_s.is_some() && j2.hit_in_time, "{j2:?}");
    // A committed pass nearer the second pass judges that one (no contact then).
    let j3 = judge_physical(&trace, &[1.010, 2.4], 2.3, 0.0335, 2000.0).unwrap();
    assert_eq!(j3.t_star_s, 2.4);
    assert!(j3.contact_s.is_none());
}

#[test]
fn world_keys_are_validated_and_unknown_ones_refused() {
    let ok = Scenario::from_toml_str(
        "[world.camera]\nlatency_ms = [5.0, 15.0]\n[world.robot]\nlatency_ms = [5, 20]\n",
    )
    .unwrap();
    let w = ok.world.unwrap();
    assert_eq!(w.camera.latency_ms, RangeParam::new(5.0, 15.0));
    let e = Scenario::from_toml_str("[world.camera]\nlatncy_ms = 5.0\n").unwrap_err();
    assert!(e.to_string().contains("latncy_ms"), "{e}");
    let e =
        Scenario::from_toml_str("[world.pendulum]\ndrag_coefficient = [0.6, 0.5]\n").unwrap_err();
    assert_eq!(e.field(), Some("world.pendulum.drag_coefficient"), "{e}");
    let e = Scenario::from_toml_str("[world.robot]\ntorque_limit_scale = -1\n").unwrap_err();
    assert_eq!(e.field(), Some("world.robot.torque_limit_scale"), "{e}");
    // The new keys: a saturation is 0 (none) or a real limit; losses are
    // fractions; NaN nowhere.
    for (toml, field) in [
        (
            "[world.robot]\nvelocity_limit_scale = 0.01\n",
            "world.robot.velocity_limit_scale",
        ),
        (
            "[world.robot]\nacceleration_limit_scale = nan\n",
            "world.robot.acceleration_limit_scale",
        ),
        (
            "[world.robot]\npacket_loss = [0.0, 0.9]\n",
            "world.robot.packet_loss",
        ),
        (
            "[world.robot]\nmessage_latency_ms = -1.0\n",
            "world.robot.message_latency_ms",
        ),
        (
            "[world.camera]\nshadow_depth = 1.0\n",
            "world.camera.shadow_depth",
        ),
        (
            "[world.camera]\nclock_drift_ppm = [0.0, 5000.0]\n",
            "world.camera.clock_drift_ppm",
        ),
    ] {
        let e = Scenario::from_toml_str(toml).unwrap_err();
        assert_eq!(e.field(), Some(field), "{toml}: {e}");
    }
    let off = Scenario::from_toml_str("[world.robot]\nvelocity_limit_scale = 0.0\n").unwrap();
    assert_eq!(off.world.unwrap().robot.velocity_limit_scale, 0.0);
    // No [world]: a truthful world, and the resolved scenario says nothing of one.
    let t = Scenario::from_toml_str("name = \"x\"\n").unwrap();
    assert!(t.world.is_none());
    assert!(!t.to_toml_string().contains("world"));
    assert!(World::for_trial(&t, 1, 0, &Vector3::zeros()).is_none());
    // An empty [world] is the truthful world made explicit.
    let e = Scenario::from_toml_str("[world]\n").unwrap();
    let tw = World::for_trial(&e, 1, 0, &Vector3::new(0.6, 0.0, 0.3)).unwrap();
    assert_eq!(tw.intercept_m, Vector3::new(0.6, 0.0, 0.3));
    assert_eq!(tw.pendulum.length_m, 1.93);
    assert_eq!(tw.session.robot_latency_s, 0.008);
}

#[test]
fn frame_time_jitter_errs_the_stamps_both_ways_and_clock_drift_changes_the_frame_rate() {
    let mut c = camera();
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    c.frame_jitter_s = 0.003;
    // The exposure wanders either side of its slot; the delivery (and so the
    // stamp) keeps the slot: stamp minus true exposure start takes both signs.
    let errs: Vec<f64> = (0..400)
        .map(|k| {
            let slot = f64::from(k) / 30.0;
            let f = c.timing(slot, &mut rng);
            assert!((f.t_stamp_s - slot).abs() < 1e-12);
            f.t_stamp_s - f.t_start_s
        })
        .collect();
    let lo = errs.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = errs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    assert!((-0.003 - 1e-12..-0.002).contains(&lo), "{lo}");
    assert!(hi > 0.002 && hi <= 0.003 + 1e-12, "{hi}");
    // A camera clock 500 ppm fast delivers 500 ppm more frames.
    assert_eq!(c.frame_period_s(1.0 / 30.0), 1.0 / 30.0);
    c.clock_drift = 500e-6;
    let frames_per_hour = 3600.0 / c.frame_period_s(1.0 / 30.0);
    assert!(
        (frames_per_hour - 108_000.0 * 1.0005).abs() < 1e-6,
        "{frames_per_hour}"
    );
    // From the session's draw.
    let mut w = WorldParams::default();
    w.camera.clock_drift_ppm = RangeParam::fixed(-200.0);
    w.camera.frame_jitter_ms = RangeParam::fixed(2.0);
    let s = w.draw_session(1, 0, 8.0);
    let c = WorldCamera::from_session(
        CameraPose::default(),
        CameraIntrinsics::from_hfov(1280, 720, 70.0),
        720,
        0.035,
        &s,
    );
    assert!((c.clock_drift + 200e-6).abs() < 1e-15 && (c.frame_jitter_s - 0.002).abs() < 1e-15);
}

#[test]
fn the_light_on_the_ball_follows_auto_exposure_flicker_and_passing_shadows() {
    let mut c = camera();
    assert_eq!(c.light_gain(1.234), 1.0, "truthful: as believed");
    // Auto-exposure: +-20% with a 10 s period.
    c.exposure_gain = (0.2, 10.0, 0.0);
    assert!((c.light_gain(2.5) - 1.2).abs() < 1e-12);
    assert!((c.light_gain(7.5) - 0.8).abs() < 1e-12);
    c.exposure_gain = (0.0, 10.0, 0.0);
    // Flicker at 100 Hz: a short exposure sees it, one of exactly a flicker
    // period averages it away.
    c.flicker = 0.3;
    c.exposure_s = 0.0;
    assert!((c.light_gain(0.0025) - 1.3).abs() < 1e-9);
    c.exposure_s = 0.01;
    assert!((c.light_gain(0.0025) - 1.0).abs() < 1e-9);
    c.flicker = 0.0;
    // Shadows: depth 0.6 for 0.5-1.5 s in about half of the 10 s windows.
    c.shadow = (0.6, 7);
    let n = 100_000;
    let mut dark = 0;
    for k in 0..n {
        let t = f64::from(k) * 0.01;
        let g = c.light_gain(t);
        if g < 1.0 {
            assert!((g - 0.4).abs() < 1e-12, "{g}");
            dark += 1;
        }
    }
    let frac = f64::from(dark) / f64::from(n);
    assert!((0.02..0.09).contains(&frac), "in shadow {frac}");
    // The same schedule for the same seed, another for another.
    let c2 = WorldCamera {
        shadow: (0.6, 8),
        ..c
    };
    let differs = (0..10_000).any(|k| {
        let t = f64::from(k) * 0.1;
        c.shadow_at(t) != c2.shadow_at(t)
    });
    assert!(differs);
}

#[test]
fn the_arm_hides_the_ball_standing_in_the_line_of_sight() {
    let c = camera();
    let arm = TrueArm::nominal(0.10, 0.03);
    let q = [0.0, 0.6, 0.0, -1.2, 0.0, 0.8, 0.0];
    let pts = arm.points(&q);
    // The last point is the tool point, the one before it the flange.
    assert!((pts[JOINTS + 1] - arm.tool_point(&q)).norm() < 1e-12);
    assert!((pts[JOINTS] - arm.flange(&q).0).norm() < 1e-12);
    // A ball straight behind the elbow, seen from the camera: hidden.
    let elbow = pts[3];
    let behind = c.position_m + (elbow - c.position_m) * 1.5;
    assert!(c.occluded(&pts, &behind));
    // The same ball 0.5 m to the side: seen.
    let aside = behind + Vector3::new(0.0, -0.5, 0.0);
    assert!(!c.occluded(&pts, &aside));
    // A ball in front of the arm (between it and the camera): seen.
    let before = c.position_m + (elbow - c.position_m) * 0.5;
    assert!(!c.occluded(&pts, &before));
}

#[cfg(feature = "opencv")]
#[test]
fn the_detector_loses_a_ball_in_too_little_light_where_the_model_camera_does() {
    use crate::sim::camera::{BallState, SimCamera, SimCameraParams, model::MODEL_MIN_GAIN};
    use crate::vision::{Detector, DetectorParams};
    let s = Scenario::default();
    let params = SimCameraParams::default();
    let mut cam = SimCamera::new(&s.camera, &params, s.pendulum.ball_radius_m, 1).unwrap();
    let ball = BallState {
        centre_m: Vector3::new(s.task.distance_m.lerp(0.5), 0.1, s.task.intercept_height_m),
        velocity_mps: Vector3::zeros(),
    };
    let mut found = |gain: f64| {
        let mut det = Detector::new(DetectorParams::default()).unwrap();
        cam.set_ball_gain(gain);
        (0..4)
            .filter(|&k| {
                let img = cam.render(Some(&ball)).unwrap();
                det.detect(img, f64::from(k) / 30.0).unwrap().is_some()
            })
            .count()
    };
    assert_eq!(found(1.0), 4);
    assert_eq!(
        found(MODEL_MIN_GAIN + 0.1),
        4,
        "still found above the model's floor"
    );
    assert_eq!(found(0.2), 0, "lost well below it");
}

#[test]
fn saturated_drives_cap_the_joint_speed_and_acceleration() {
    let q0 = [0.0, 0.5, 0.0, -1.0, 0.0, 1.0, 0.0];
    let vmax = crate::kinematics::iiwa7::VELOCITY_LIMIT_RADPS;
    for omega_hz in [0.0, 12.0] {
        let s = session(omega_hz, 0.7);
        let mut j = WorldJoints::new(q0, &s, 0.005, 1.0, false, 0.0, 1);
        j.set_interpolation_s(1e-3);
        j.set_saturation(0.5, 2.0);
        let amax = 2.0 * crate::kinematics::iiwa7::ACCELERATION_LIMIT_RADPS2[0];
        // A 0.6 rad step on A1: unsaturated, far faster than half its limit.
        let mut sp = q0;
        sp[0] += 0.6;
        let (mut peak_v, mut peak_a, mut prev_v) = (0.0f64, 0.0f64, 0.0);
        for _ in 0..3000 {
            j.integrate(&sp, 1e-3);
            let v = j.qd()[0];
            peak_v = peak_v.max(v.abs());
            peak_a = peak_a.max(((v - prev_v) / 1e-3).abs());
            prev_v = v;
        }
        assert!(peak_v <= 0.5 * vmax[0] + 1e-9, "{omega_hz} Hz: {peak_v}");
        assert!(
            peak_v > 0.45 * vmax[0],
            "{omega_hz} Hz: saturated at the cap {peak_v}"
        );
        assert!(peak_a <= amax + 1e-6, "{omega_hz} Hz: {peak_a}");
        assert!(j.saturated() > 0);
        assert!(
            (j.q()[0] - sp[0]).abs() < 1e-3,
            "{omega_hz} Hz: arrives {}",
            j.q()[0]
        );
        // Without saturation the same step is faster than the cap.
        let mut free = WorldJoints::new(q0, &s, 0.005, 1.0, false, 0.0, 1);
        free.set_interpolation_s(1e-3);
        let mut fastest = 0.0f64;
        for _ in 0..300 {
            free.integrate(&sp, 1e-3);
            fastest = fastest.max(free.qd()[0].abs());
        }
        assert!(fastest > 0.5 * vmax[0], "{omega_hz} Hz: {fastest}");
        assert_eq!(free.saturated(), 0);
    }
}

#[test]
fn a_first_order_servo_trips_on_torque_too() {
    let s = session(0.0, 0.7);
    let q0 = [0.0, 0.5, 0.0, -1.0, 0.0, 1.0, 0.0];
    // A 0.5 rad jump on A2 through a 5 ms first-order lag: ~100 rad/s in a
    // millisecond, far beyond A2's torque.
    let mut j = WorldJoints::new(q0, &s, 0.005, 1.0, true, 0.0, 1);
    j.set_interpolation_s(1e-3);
    let mut sp = q0;
    sp[1] += 0.5;
    let trip = j.integrate(&sp, 1e-3).expect("trips");
    assert_eq!(trip.name, "A2", "{trip}");
    // A slow ramp does not trip, and its gravity load shows in the peaks.
    let mut k = WorldJoints::new(q0, &s, 0.005, 1.0, true, 0.0, 1);
    k.set_interpolation_s(1e-3);
    for n in 1..=1000 {
        let mut r = q0;
        r[1] += 0.1 * f64::from(n) * 1e-3;
        assert!(k.integrate(&r, 1e-3).is_none());
    }
    assert!(k.peak_torque_ratio()[1] > 0.05 && k.peak_torque_ratio()[1] < 1.0);
    // Split into many tiny steps (the controller's due times), the same
    // motion does not read as an infinite acceleration.
    let mut m = WorldJoints::new(q0, &s, 0.005, 1.0, true, 0.0, 1);
    m.set_interpolation_s(1e-3);
    for n in 1..=1000 {
        let mut r = q0;
        r[1] += 0.1 * f64::from(n) * 1e-3;
        assert!(m.integrate(&r, 1e-6).is_none());
        assert!(m.integrate(&r, 1e-3 - 1e-6).is_none());
    }
}

#[test]
fn the_stiffest_most_damped_servo_a_world_may_draw_is_stable_and_lags_as_predicted() {
    let top = crate::params::world::MAX_SERVO_NATURAL_HZ;
    for zeta in [0.2, 0.7, 3.0] {
        let s = session(top, zeta);
        let mut j = WorldJoints::new([0.0; JOINTS], &s, 0.005, 1.0, false, 0.0, 1);
        j.set_interpolation_s(1e-3);
        let v = 0.5;
        for k in 1..=1000 {
            let mut sp = [0.0; JOINTS];
            sp[0] = v * f64::from(k) * 1e-3;
            j.integrate(&sp, 1e-3);
            assert!(
                j.q()[0].is_finite() && j.qd()[0].abs() < 10.0,
                "zeta {zeta}: diverges"
            );
        }
        let w = std::f64::consts::TAU * top;
        let expected = 2.0 * zeta * v / w;
        let lag = v * 1.0 - j.q()[0];
        assert!(
            (lag - expected).abs() < 0.05 * expected,
            "zeta {zeta}: lag {lag} vs {expected}"
        );
        // A step settles.
        let mut st = WorldJoints::new([0.0; JOINTS], &s, 0.005, 1.0, false, 0.0, 1);
        let mut sp = [0.0; JOINTS];
        sp[0] = 0.1;
        st.integrate(&sp, 0.5);
        assert!((st.q()[0] - 0.1).abs() < 1e-6, "zeta {zeta}: {}", st.q()[0]);
    }
    // Above the top the world is refused.
    let mut w = WorldParams::default();
    w.robot.servo_natural_hz = RangeParam::fixed(top + 1.0);
    assert!(w.validate().is_err());
}

#[test]
fn a_contact_pushes_the_arm_and_the_servo_pulls_it_back() {
    let q0 = [0.0, 0.6, 0.0, -1.2, 0.0, 0.8, 0.0];
    let arm = TrueArm::nominal(0.10, 0.03);
    let point = arm.tool_point(&q0);
    // A 57 g ball at 1.5 m/s stopping against the tool: 0.085 N s along +x.
    let impulse = Vector3::new(0.085, 0.0, 0.0);
    let s = session(12.0, 0.8);
    let mut rigid = WorldJoints::new(q0, &s, 0.005, 1.0, false, 0.0, 1);
    rigid.push(&point, &impulse);
    assert_eq!(rigid.qd(), &[0.0; JOINTS], "contact push off: nothing");
    let mut j = WorldJoints::new(q0, &s, 0.005, 1.0, false, 0.0, 1);
    j.set_contact_push(true);
    j.push(&point, &impulse);
    // The joint velocities carry the impulse: (M + A) dq' = J^T p.
    let m = crate::sim::world::ArmDynamics::default().push_matrix(&q0);
    let tau = crate::sim::world::contact::joint_torques(&q0, &point, &impulse);
    let back = m * nalgebra::SVector::<f64, JOINTS>::from(*j.qd());
    for i in 0..JOINTS {
        assert!((back[i] - tau[i]).abs() < 1e-9, "joint {i}");
    }
    // The tool moves along the push, a little, and comes back.
    let mut peak = 0.0f64;
    for _ in 0..100 {
        j.integrate(&q0, 1e-3);
        peak = peak.max((arm.tool_point(j.q()) - point).x);
    }
    assert!(peak > 1e-5, "pushed {peak} m");
    for _ in 0..900 {
        j.integrate(&q0, 1e-3);
    }
    assert!((arm.tool_point(j.q()) - point).norm() < 1e-6, "pulled back");
}

#[test]
fn the_strike_judge_times_the_tools_crossing_and_the_balls_outgoing_speed() {
    // A tool striking towards -y at 0.5 m/s crosses the intercept point's
    // y = 0 at t = 1.004 s; the ball (the ghost) passes it towards +y at
    // t* = 1.000 s, so they meet; the true ball left the tool at 0.45 m/s
    // towards -y after a first touch at 0.97 s and one more push.
    let disc_at = |y: f64| Disc {
        centre_m: Vector3::new(0.6, y, 0.3),
        normal: Vector3::new(0.0, 0.0, 1.0),
        radius_m: 0.03,
    };
    let trace: Vec<WorldSample> = (0..400)
        .map(|k| {
            let t = f64::from(k) * 5e-3;
            WorldSample {
                t_s: t,
                ball_m: Vector3::new(0.6, 1.5 * (t - 1.0), 0.3),
                disc: disc_at(-0.5 * (t - 1.004)),
            }
        })
        .collect();
    let hits = [
        (0.97, Vector3::new(0.0, -0.40, 0.0)),
        (0.975, Vector3::new(0.0, -0.45, 0.001)),
        // A touch on a later swing: not this strike's.
        (1.9, Vector3::new(0.0, 2.0, 0.0)),
    ];
    let aim = StrikeAim {
        planned_tool_speed_mps: 0.5,
        target_ball_speed_mps: 0.5,
        return_sign: -1.0,
        predicted: None,
    };
    let j = judge_strike(&trace, &hits, &[1.0, 2.4], 1.0, 0.0335, 20.0, 0.0, &aim).unwrap();
    assert_eq!(j.t_star_s, 1.0);
    assert!((j.arrival_s - 1.004).abs() < 1e-6, "{j:?}");
    assert!((j.timing_error_ms - 4.0).abs() < 1e-3, "{j:?}");
    assert!(j.contact_s.is_some() && j.hit_in_time, "{j:?}");
    let s = j.strike.unwrap();
    assert!((s.tool_speed_mps - 0.5).abs() < 1e-9, "{s:?}");
    assert!((s.ball_speed_mps - 0.45).abs() < 1e-5, "{s:?}");
    assert!((s.speed_error + 0.1).abs() < 1e-4, "{s:?}");
    assert!(s.direction_error_deg < 0.2 && s.speed_ok, "{s:?}");
    // Too slow by more than 20%, or the ball not returned: not in speed.
    let slow = [(0.97, Vector3::new(0.0, -0.35, 0.0))];
    let j = judge_strike(&trace, &slow, &[1.0, 2.4], 1.0, 0.0335, 20.0, 0.0, &aim).unwrap();
    assert!(!j.strike.unwrap().speed_ok);
    let on = [(0.97, Vector3::new(0.0, 0.5, 0.0))];
    let j = judge_strike(&trace, &on, &[1.0, 2.4], 1.0, 0.0335, 20.0, 0.0, &aim).unwrap();
    let s = j.strike.unwrap();
    assert!(!s.speed_ok && s.direction_error_deg > 179.0, "{s:?}");
    // No true contact: no outgoing speed.
    let j = judge_strike(&trace, &[], &[1.0, 2.4], 1.0, 0.0335, 20.0, 0.0, &aim).unwrap();
    let s = j.strike.unwrap();
    assert!(s.ball_speed_mps.is_nan() && !s.speed_ok, "{s:?}");
}
