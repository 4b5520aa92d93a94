//! Acceptance tests of issue #4 (run with `--nocapture` to see the numbers).

use nalgebra::{UnitQuaternion, Vector3};

use super::*;
use crate::trajectory::profile::ProfileKind;

const T: f64 = 1.5;

fn home() -> Vector3<f64> {
    Vector3::new(0.30, 0.0, 0.50)
}

/// Towards the pendulum and down to the intercept height.
fn dir() -> Vector3<f64> {
    Vector3::new(1.0, 0.0, -0.45).normalize()
}

fn tool_down() -> UnitQuaternion<f64> {
    UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0)
}

fn params(kind: ProfileKind) -> TimingParams {
    TimingParams {
        profile: kind,
        ..TimingParams::default()
    }
}

/// One recorded step: the command and the simulated robot.
#[derive(Clone, Copy)]
struct Rec {
    t: f64,
    cmd: MotionSample,
    robot_m: Vector3<f64>,
}

/// A scripted trial: a simulated robot whose path speed is `factor(t)` times
/// the commanded one (a slow-down it does not catch up by itself), fed back as
/// the measured position when `feedback`; an optional target move.
struct Trial {
    p: TimingParams,
    target: Vector3<f64>,
    dt: f64,
    t_end: f64,
    factor: fn(f64) -> f64,
    feedback: bool,
    /// The robot executes `factor * commanded velocity` (else position steps).
    velocity_plant: bool,
    retarget: Option<(f64, Vector3<f64>)>,
}

impl Trial {
    fn new(kind: ProfileKind, distance: f64, dt: f64) -> Self {
        Self {
            p: params(kind),
            target: home() + dir() * distance,
            dt,
            t_end: T + 0.5,
            factor: |_| 1.0,
            feedback: false,
            velocity_plant: false,
            retarget: None,
        }
    }

    fn run(&self) -> (Vec<Rec>, TimedMotion) {
        let mut m = TimedMotion::new(self.p.clone()).unwrap();
        m.reset(&home()).unwrap();
        let mut out = MotionSample::default();
        m.sample(&mut out);
        let mut recs = vec![Rec {
            t: 0.0,
            cmd: out,
            robot_m: home(),
        }];
        m.begin(&home(), &self.target, &tool_down(), T).unwrap();
        let mut robot = home();
        let mut last_cmd = home();
        let mut last_vel = Vector3::zeros();
        let mut t = 0.0;
        let mut moved = false;
        while t < self.t_end - 1e-9 {
            if let Some((t_move, new_target)) = self.retarget {
                if !moved && t >= t_move - 1e-9 {
                    m.retarget(&new_target).unwrap();
                    moved = true;
                }
            }
            let meas = self.feedback.then_some(robot);
            m.step(self.dt, meas.as_ref(), &mut out).unwrap();
            if self.velocity_plant {
                // Trapezoidal: the robot's speed changes linearly over a period.
                robot += (self.factor)(t) * 0.5 * (last_vel + out.velocity_mps) * self.dt;
            } else {
                robot += (self.factor)(t) * (out.position_m - last_cmd);
            }
            last_cmd = out.position_m;
            last_vel = out.velocity_mps;
            t += self.dt;
            recs.push(Rec {
                t: out.t_s,
                cmd: out,
                robot_m: robot,
            });
        }
        (recs, m)
    }
}

/// Arrival of the robot's progress along the straight line (fit of the ideal profile).
fn arrival_along_line(kind: ProfileKind, recs: &[Rec], target: Vector3<f64>) -> ArrivalFit {
    let d = (target - home()).norm();
    let u = (target - home()) / d;
    let t: Vec<f64> = recs.iter().map(|r| r.t).collect();
    let s: Vec<f64> = recs.iter().map(|r| (r.robot_m - home()).dot(&u)).collect();
    fit_arrival(kind, d, T, &t, &s).unwrap()
}

/// Arrival of the robot's path length (curved paths after a re-target).
fn arrival_along_path(kind: ProfileKind, recs: &[Rec]) -> ArrivalFit {
    let mut len = 0.0;
    let mut s = vec![0.0];
    for w in recs.windows(2) {
        len += (w[1].robot_m - w[0].robot_m).norm();
        s.push(len);
    }
    let t: Vec<f64> = recs.iter().map(|r| r.t).collect();
    fit_arrival(kind, len, T, &t, &s).unwrap()
}

/// Largest change of the commanded velocity (finite differences of the
/// commanded positions) between consecutive steps, as an acceleration, m/s^2.
fn max_command_accel(recs: &[Rec], dt: f64) -> f64 {
    let v: Vec<Vector3<f64>> = recs
        .windows(2)
        .map(|w| (w[1].cmd.position_m - w[0].cmd.position_m) / dt)
        .collect();
    v.windows(2)
        .map(|w| (w[1] - w[0]).norm() / dt)
        .fold(0.0, f64::max)
}

/// Largest change of the commanded velocity output between consecutive
/// steps, as an acceleration, m/s^2.
fn max_velocity_change(recs: &[Rec], dt: f64) -> f64 {
    recs.windows(2)
        .map(|w| (w[1].cmd.velocity_mps - w[0].cmd.velocity_mps).norm() / dt)
        .fold(0.0, f64::max)
}

fn at_time(recs: &[Rec], t: f64) -> &Rec {
    recs.iter()
        .min_by(|a, b| (a.t - t).abs().total_cmp(&(b.t - t).abs()))
        .unwrap()
}

#[test]
fn movement_time_does_not_depend_on_distance() {
    for kind in [ProfileKind::Hopf, ProfileKind::MinJerk] {
        let mut arrivals = Vec::new();
        let mut worst_end_err: f64 = 0.0;
        let mut worst_end_speed: f64 = 0.0;
        let mut worst_err_at_t: f64 = 0.0;
        for i in 0..=9 {
            let d = 0.35 + 0.05 * f64::from(i);
            let trial = Trial::new(kind, d, 0.005);
            let (recs, m) = trial.run();
            arrivals.push(arrival_along_line(kind, &recs, trial.target).arrival_s);
            let last = recs.last().unwrap();
            assert_eq!(m.phase(), MotionPhase::Arrived);
            worst_end_err = worst_end_err.max((last.cmd.position_m - trial.target).norm());
            worst_end_speed = worst_end_speed.max(last.cmd.velocity_mps.norm());
            let at_t = at_time(&recs, T);
            worst_err_at_t = worst_err_at_t.max((at_t.cmd.position_m - trial.target).norm());
        }
        let lo = arrivals.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = arrivals.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        eprintln!(
            "{kind:?}: D 0.35..0.80 m, T = 1.5 s: arrival {lo:.6}..{hi:.6} s, spread {:.2e} ms, \
             |arrival - T| <= {:.3} ms; position error at T {:.3e} m; at rest (T + 0.5 s): \
             error {:.3e} m, speed {:.3e} m/s",
            (hi - lo) * 1e3,
            (lo - T).abs().max((hi - T).abs()) * 1e3,
            worst_err_at_t,
            worst_end_err,
            worst_end_speed
        );
        assert!(hi - lo <= 1e-3, "{kind:?}: arrival spread {} s", hi - lo);
        assert!((lo - T).abs() <= 1e-3 && (hi - T).abs() <= 1e-3);
        assert!(
            worst_end_err < 1e-3,
            "{kind:?}: end error {worst_end_err} m"
        );
        assert!(
            worst_end_speed < 1e-3,
            "{kind:?}: end speed {worst_end_speed} m/s"
        );
    }
}

#[test]
fn velocity_follows_the_hopf_closed_form_and_neurons_switch_once() {
    let d = 0.7;
    let dt = 0.001;
    let (recs, _) = Trial::new(ProfileKind::Hopf, d, dt).run();
    let r_h = d / T;
    let w = std::f64::consts::TAU / T;
    let mut sq = 0.0;
    let mut n = 0.0;
    for r in recs.iter().filter(|r| r.t <= T + 1e-9) {
        let ideal = r_h * (1.0 - (w * r.t).cos());
        sq += (r.cmd.path_speed_mps - ideal).powi(2);
        n += 1.0;
    }
    let rms_rel = (sq / n).sqrt() / (2.0 * r_h);
    // The same comparison with ProfileKind, the shared closed form.
    let peak = recs
        .iter()
        .map(|r| r.cmd.path_speed_mps)
        .fold(0.0, f64::max);
    eprintln!(
        "Hopf D = 0.7 m: RMS(a - R_h (1 - cos wt)) = {:.3} % of the peak; peak {peak:.4} m/s \
         (closed form {:.4})",
        rms_rel * 100.0,
        ProfileKind::Hopf.peak_velocity() * d / T
    );
    assert!(rms_rel < 0.01, "RMS {rms_rel}");

    // Winner sequence: Init -> Hopf -> Final, once each.
    let mut seq = vec![recs[0].cmd.regime];
    let mut switch_t = Vec::new();
    for r in &recs {
        if *seq.last().unwrap() != r.cmd.regime {
            seq.push(r.cmd.regime);
            switch_t.push(r.t);
        }
    }
    eprintln!("neurons: winners {seq:?} switching at {switch_t:?} s");
    assert_eq!(seq, [Regime::Init, Regime::Hopf, Regime::Final]);
    // Exactly one neuron active away from the switches, never two above 0.5.
    for r in &recs {
        let u = r.cmd.neurons.as_array();
        assert!(
            u.iter().filter(|&&x| x > 0.5).count() <= 1,
            "{u:?} at {}",
            r.t
        );
        if switch_t.iter().all(|ts| (r.t - ts).abs() > 0.03) {
            assert_eq!(
                u.iter().filter(|&&x| x > 0.95).count(),
                1,
                "{u:?} at {}",
                r.t
            );
            assert_eq!(
                u.iter().filter(|&&x| x < 0.02).count(),
                2,
                "{u:?} at {}",
                r.t
            );
        }
    }
}

fn slow_halfway(t: f64) -> f64 {
    if (0.75..0.85).contains(&t) { 0.8 } else { 1.0 }
}

#[test]
fn a_disturbance_halfway_still_arrives_on_time() {
    for kind in [ProfileKind::Hopf, ProfileKind::MinJerk] {
        for dt in [0.001, 0.005, 0.01] {
            let mut trial = Trial::new(kind, 0.7, dt);
            trial.factor = slow_halfway;
            trial.feedback = true;
            trial.velocity_plant = true;
            let (recs, _) = trial.run();
            let fit = arrival_along_line(kind, &recs, trial.target);
            let at_t = at_time(&recs, T);
            let err_t = (at_t.robot_m - trial.target).norm();
            let acc = max_velocity_change(&recs, dt);
            // Without the feedback the slow-down is never made up.
            trial.feedback = false;
            let (open, _) = trial.run();
            let open_fit = arrival_along_line(kind, &open, trial.target);
            let open_err = (at_time(&open, T).robot_m - trial.target).norm();
            eprintln!(
                "{kind:?} dt {dt}: 20% slower for 100 ms at T/2: robot at T {err_t:.2e} m from \
                 the target; whole-motion fit arrival error {:.3} ms; max command accel \
                 {acc:.2} m/s^2 (open loop: {open_err:.2e} m, fit {:.3} ms)",
                (fit.arrival_s - T) * 1e3,
                (open_fit.arrival_s - T) * 1e3,
            );
            assert!(
                err_t < 1e-3,
                "{kind:?} {dt}: robot {err_t} m from the target at T"
            );
            assert!(open_err > 0.01, "the disturbance must matter: {open_err}");
            assert!(
                (fit.arrival_s - T).abs() < (open_fit.arrival_s - T).abs(),
                "{kind:?} {dt}: {fit:?} vs open loop {open_fit:?}"
            );
            assert!(acc < 5.0, "{kind:?} {dt}: command acceleration {acc}");
        }
    }
}

#[test]
fn a_target_moved_at_half_time_is_reached_on_time_with_continuous_velocity() {
    for kind in [ProfileKind::Hopf, ProfileKind::MinJerk] {
        let dt = 0.005;
        let mut trial = Trial::new(kind, 0.7, dt);
        let moved = trial.target + Vector3::new(0.0, 0.05, 0.0);
        trial.retarget = Some((T / 2.0, moved));
        let (recs, _) = trial.run();
        let at_t = at_time(&recs, T);
        let err_t = (at_t.cmd.position_m - moved).norm();
        let speed_t = at_t.cmd.velocity_mps.norm();
        let fit = arrival_along_path(kind, &recs);
        let acc = max_command_accel(&recs, dt);
        // The same move without the target filter: the direction jumps.
        trial.p.target_smoothing_s = 0.0;
        let (raw, _) = trial.run();
        let raw_acc = max_command_accel(&raw, dt);
        eprintln!(
            "{kind:?}: target moved 5 cm at T/2: at T error {err_t:.2e} m, speed {speed_t:.2e} \
             m/s; path arrival error {:.3} ms; max command accel {acc:.2} m/s^2 (unfiltered \
             re-target: {raw_acc:.2} m/s^2)",
            (fit.arrival_s - T) * 1e3
        );
        assert!(err_t < 1e-3, "{kind:?}: error at T {err_t}");
        assert!(speed_t < 0.01, "{kind:?}: speed at T {speed_t}");
        assert!((fit.arrival_s - T).abs() < 0.005, "{kind:?}: {fit:?}");
        assert!(acc < 5.0, "{kind:?}: command acceleration {acc}");
        assert!(raw_acc > 10.0, "the unfiltered jump must show: {raw_acc}");
    }
}

#[test]
fn every_fri_period_from_1_to_10_ms_gives_the_same_arrival() {
    for kind in [ProfileKind::Hopf, ProfileKind::MinJerk] {
        let mut arrivals = Vec::new();
        let mut worst_err: f64 = 0.0;
        for ms in 1..=10 {
            let trial = Trial::new(kind, 0.7, f64::from(ms) * 1e-3);
            let (recs, _) = trial.run();
            assert!(
                recs.iter()
                    .all(|r| r.cmd.position_m.iter().all(|v| v.is_finite()))
            );
            arrivals.push(arrival_along_line(kind, &recs, trial.target).arrival_s);
            worst_err = worst_err.max((recs.last().unwrap().cmd.position_m - trial.target).norm());
        }
        let lo = arrivals.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = arrivals.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        eprintln!(
            "{kind:?}: periods 1..10 ms: arrival {lo:.6}..{hi:.6} s, spread {:.3e} ms, end \
             error <= {worst_err:.2e} m",
            (hi - lo) * 1e3
        );
        assert!(hi - lo <= 1e-3, "{kind:?}: spread {}", hi - lo);
        assert!(worst_err < 1e-3);
    }
}

#[test]
fn the_path_is_a_straight_line_with_the_orientation_held() {
    let trial = Trial::new(ProfileKind::Hopf, 0.6, 0.002);
    let (recs, _) = trial.run();
    let u = dir();
    for r in &recs {
        let off = r.cmd.position_m - home();
        let lateral = (off - u * off.dot(&u)).norm();
        assert!(lateral < 1e-9, "off the line by {lateral} m at {}", r.t);
        if r.cmd.phase != MotionPhase::Idle {
            assert_eq!(r.cmd.orientation, tool_down());
        }
        assert!(r.cmd.path_speed_mps > -1e-6, "backwards at {}", r.t);
    }
}

#[test]
fn min_jerk_peaks_lower_than_hopf_for_the_same_trial() {
    let peak = |kind| {
        let (recs, _) = Trial::new(kind, 0.7, 0.001).run();
        recs.iter()
            .map(|r| r.cmd.path_speed_mps)
            .fold(0.0, f64::max)
    };
    let (h, j) = (peak(ProfileKind::Hopf), peak(ProfileKind::MinJerk));
    eprintln!("D = 0.7 m, T = 1.5 s: peak path speed Hopf {h:.4} m/s, min-jerk {j:.4} m/s");
    assert!((h - 2.0 * 0.7 / T).abs() / h < 0.01, "{h}");
    assert!((j - 1.875 * 0.7 / T).abs() / j < 0.005, "{j}");
}

#[test]
fn bad_input_is_refused_and_changes_nothing() {
    let mut m = TimedMotion::new(TimingParams::default()).unwrap();
    let mut out = MotionSample::default();
    assert_eq!(
        m.retarget(&Vector3::new(0.5, 0.0, 0.3)),
        Err(TimingError::NotStarted)
    );
    let nan = Vector3::new(f64::NAN, 0.0, 0.0);
    let target = home() + dir() * 0.7;
    for (start, target, dur) in [
        (nan, target, T),
        (home(), nan, T),
        (home(), target, f64::NAN),
        (home(), target, 0.0),
        (home(), target, -1.0),
        (home(), target, 100.0),
        (home(), home(), T),
    ] {
        let before = m.clone();
        assert!(m.begin(&start, &target, &tool_down(), dur).is_err());
        assert_eq!(m, before);
    }
    m.begin(&home(), &target, &tool_down(), T).unwrap();
    m.step(0.005, None, &mut out).unwrap();
    let before = m.clone();
    assert_eq!(
        m.begin(&home(), &target, &tool_down(), T),
        Err(TimingError::Busy)
    );
    for dt in [f64::NAN, f64::INFINITY, 0.0, -0.001, 0.5] {
        assert!(m.step(dt, None, &mut out).is_err(), "{dt}");
    }
    assert!(m.step(0.005, Some(&nan), &mut out).is_err());
    assert!(m.retarget(&nan).is_err());
    assert!(m.retime(f64::NAN).is_err());
    assert!(m.retime(0.0).is_err());
    assert_eq!(m, before);
    let e = m.step(-1.0, None, &mut out).unwrap_err().to_string();
    assert!(e.contains("dt_s"), "{e}");
}

#[test]
fn a_retimed_motion_arrives_at_the_new_time() {
    for kind in [ProfileKind::Hopf, ProfileKind::MinJerk] {
        let mut m = TimedMotion::new(params(kind)).unwrap();
        let target = home() + dir() * 0.5;
        m.begin(&home(), &target, &tool_down(), T).unwrap();
        let mut out = MotionSample::default();
        let mut last_v = Vector3::zeros();
        let mut max_accel: f64 = 0.0;
        let (mut left_at_old, mut left_at_new) = (0.0, 0.0);
        for i in 1..=400 {
            if i == 100 {
                m.retime(1.6).unwrap();
            }
            m.step(0.005, None, &mut out).unwrap();
            max_accel = max_accel.max((out.velocity_mps - last_v).norm() / 0.005);
            last_v = out.velocity_mps;
            if i == 300 {
                left_at_old = (out.position_m - target).norm();
            }
            if i == 320 {
                left_at_new = (out.position_m - target).norm();
                assert_eq!(out.arrival_time_s, 1.6);
            }
        }
        eprintln!(
            "{kind:?} re-timed 1.5 -> 1.6 s at 0.5 s: {left_at_old:.2e} m left at 1.5 s, \
             {left_at_new:.2e} m at 1.6 s; max command accel {max_accel:.2} m/s^2"
        );
        assert!(
            left_at_old > 3e-4,
            "{kind:?}: arrived early ({left_at_old} m left at 1.5 s)"
        );
        assert!(
            left_at_new < 1e-4,
            "{kind:?}: {left_at_new} m left at 1.6 s"
        );
        assert!(max_accel < 2.0, "{kind:?}: {max_accel}");
    }
}

#[test]
fn fit_recovers_a_known_arrival() {
    let t: Vec<f64> = (0..400).map(|i| f64::from(i) * 0.005).collect();
    let s: Vec<f64> = t
        .iter()
        .map(|t| 0.6 * ProfileKind::Hopf.position((t - 0.1234) / T))
        .collect();
    let fit = fit_arrival(ProfileKind::Hopf, 0.6, T, &t, &s).unwrap();
    assert!((fit.arrival_s - (0.1234 + T)).abs() < 1e-6, "{fit:?}");
    assert!(fit_arrival(ProfileKind::Hopf, 0.6, T, &t[..2], &s[..2]).is_err());
    assert!(fit_arrival(ProfileKind::Hopf, 0.6, T, &t, &s[..10]).is_err());
    assert!(fit_arrival(ProfileKind::Hopf, f64::NAN, T, &t, &s).is_err());
}

#[test]
fn params_validate_and_name_the_field() {
    TimingParams::default().validate().unwrap();
    let bad = TimingParams {
        hopf_lambda_per_s: f64::NAN,
        ..TimingParams::default()
    };
    assert_eq!(
        bad.validate().unwrap_err().field(),
        Some("timing.hopf_lambda_per_s")
    );
    let bad = TimingParams {
        neuron_competition: 1.0,
        ..TimingParams::default()
    };
    assert_eq!(
        bad.validate().unwrap_err().field(),
        Some("timing.neuron_competition")
    );
    let bad = TimingParams {
        max_substep_s: 0.01,
        ..TimingParams::default()
    };
    assert_eq!(
        bad.validate().unwrap_err().field(),
        Some("timing.max_substep_s")
    );
    assert!(TimedMotion::new(bad).is_err());
    let p: TimingParams =
        toml::from_str("profile = \"min_jerk\"\nhopf_lambda_per_s = 10.0").unwrap();
    assert_eq!(p.profile, ProfileKind::MinJerk);
    assert_eq!(p.hopf_lambda_per_s, 10.0);
    assert!(toml::from_str::<TimingParams>("hopf_lambda = 10.0").is_err());
    assert!(toml::from_str::<TimingParams>("profile = \"spline\"").is_err());
}

#[test]
fn seeded_random_motions_end_on_the_target_at_rest_on_time() {
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let mut worst_accel_ratio: f64 = 0.0;
    let mut worst_err: f64 = 0.0;
    for case in 0..64 {
        let kind = if case % 2 == 0 {
            ProfileKind::Hopf
        } else {
            ProfileKind::MinJerk
        };
        let duration: f64 = rng.random_range(0.5..3.0);
        let distance: f64 = rng.random_range(0.05..1.2);
        let dt = f64::from(rng.random_range(1..=10_u32)) * 1e-3;
        let u = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        )
        .normalize();
        let start = home();
        let mut target = start + u * distance;
        // The filter's refinements: a few cm, less for short paths, by 0.6 T.
        let shift = Vector3::new(
            rng.random_range(-0.03..0.03),
            rng.random_range(-0.03..0.03),
            rng.random_range(-0.03..0.03),
        ) * (distance / 0.5).min(1.0);
        let t_move = rng.random_range(0.2..0.6) * duration;
        // Every other case of each profile: a 20% slow-down for 100 ms, fed back.
        let disturbed = case % 4 >= 2;
        let t_slow = rng.random_range(0.2..0.6) * duration;
        let mut m = TimedMotion::new(params(kind)).unwrap();
        m.begin(&start, &target, &tool_down(), duration).unwrap();
        let mut out = MotionSample::default();
        let mut robot = start;
        let mut last_v = Vector3::zeros();
        let mut at_end = None;
        let mut moved = false;
        let mut max_accel: f64 = 0.0;
        while out.t_s < duration + 0.5 {
            if !moved && out.t_s >= t_move {
                target += shift;
                m.retarget(&target).unwrap();
                moved = true;
            }
            let t = out.t_s;
            let meas = disturbed.then_some(robot);
            m.step(dt, meas.as_ref(), &mut out).unwrap();
            assert!(out.position_m.iter().all(|v| v.is_finite()), "case {case}");
            let factor = if disturbed && (t_slow..t_slow + 0.1).contains(&t) {
                0.8
            } else {
                1.0
            };
            robot += factor * 0.5 * (last_v + out.velocity_mps) * dt;
            max_accel = max_accel.max((out.velocity_mps - last_v).norm() / dt);
            last_v = out.velocity_mps;
            if at_end.is_none() && out.t_s >= duration - 1e-9 {
                at_end = Some((out, robot));
            }
        }
        let (at_end, robot_at_end) = at_end.unwrap();
        let err = if disturbed {
            (robot_at_end - target).norm()
        } else {
            (at_end.position_m - target).norm()
        };
        worst_err = worst_err.max(err);
        // Peak path acceleration of the nominal profile.
        let nominal_accel = match kind {
            ProfileKind::Hopf => std::f64::consts::TAU,
            ProfileKind::MinJerk => 10.0 / 3.0_f64.sqrt(),
        } * distance
            / (duration * duration);
        worst_accel_ratio = worst_accel_ratio.max(max_accel / nominal_accel);
        assert!(
            err < 1e-3,
            "case {case} {kind:?} D {distance:.3} T {duration:.2} dt {dt} disturbed {disturbed}: \
             {err} m off at T"
        );
        assert_eq!(out.phase, MotionPhase::Arrived, "case {case}");
        assert!(out.velocity_mps.norm() < 1e-3, "case {case}: still moving");
        assert!((out.position_m - target).norm() < 1e-4, "case {case}");
    }
    eprintln!(
        "64 seeded random motions (D 0.05..1.2 m, T 0.5..3 s, dt 1..10 ms, target moved up to \
         5.2 cm by 0.6 T, half disturbed): worst error at T {worst_err:.2e} m, worst peak acceleration \
         {worst_accel_ratio:.2} x the undisturbed profile's"
    );
    assert!(worst_accel_ratio < 3.0, "{worst_accel_ratio}");
}
