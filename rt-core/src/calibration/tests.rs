use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::latency::LedFrame;
use super::robot::JointSample;
use super::*;
use crate::pendulum::{PendulumModel, PendulumState};

fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.random_range(1e-12..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// A free swing from `release_deg`, sampled at 30 Hz with `noise_m` lateral noise.
fn swing(length_m: f64, alpha: f64, release_deg: f64, secs: f64, noise_m: f64) -> Vec<SwingSample> {
    let model = PendulumModel {
        length_m,
        gravity_mps2: 9.81,
        damping_per_s: alpha,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut s = PendulumState::new(release_deg.to_radians(), 0.0);
    let mut out = Vec::new();
    let dt = 1.0 / 30.0;
    let mut t = 0.0;
    while t < secs {
        // Start sampling a little after the release (frames are not synchronised).
        s = model.integrate(s, dt, 1e-3, 0.0);
        t += dt;
        if rng.random_range(0.0..1.0) < 0.05 {
            continue; // dropped frame
        }
        out.push(SwingSample {
            t_s: t + 0.2,
            lateral_m: length_m * s[0].sin() + 0.004 + noise_m * gauss(&mut rng),
        });
    }
    out
}

#[test]
fn frames_a_busy_host_delivered_late_are_stamped_at_their_slots_and_the_swing_fits() {
    // A 30 fps camera whose frames a starved host took in bursts: every
    // 0.7 s a stall of 100-300 ms, the frames captured in it stamped at
    // its end (delivery less the latency), plus 1 ms of stream jitter.
    let (l, rest) = (1.93, 0.004);
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let clean: Vec<swing::TrackedSwingSample> = swing(l, 0.03, 25.0, 20.0, 0.0005)
        .into_iter()
        .map(|s| swing::TrackedSwingSample {
            t_s: s.t_s,
            lateral_m: s.lateral_m,
            px: [640.0 + 600.0 * (s.lateral_m - rest), 360.0],
        })
        .collect();
    let mut stalled = clean.clone();
    let mut stall_end = 0.0;
    for s in &mut stalled {
        let t = s.t_s;
        if t > stall_end && (t % 0.7) < 1.0 / 30.0 {
            stall_end = t + rng.random_range(0.1..0.3);
        }
        s.t_s = if t < stall_end { stall_end } else { t } + 1e-3 * gauss(&mut rng).abs();
    }
    let late = stalled
        .iter()
        .zip(&clean)
        .filter(|(a, b)| a.t_s - b.t_s > 0.05)
        .count();
    assert!(late > 60, "{late} frames late");
    // Taken at their delivery stamps, the swing is no free swing (or a wrong one).
    match swing::pendulum_from_swing(&stalled, 9.81, 1.9) {
        Err(CalibrationError::PoorFit { .. }) => {}
        Ok(c) => assert!((c.swing.length_m - l).abs() > 3e-3, "{}", c.swing.length_m),
        Err(e) => panic!("{e}"),
    }
    // On the frame grid: the length within 1 mm, as from the clean stamps.
    let regridded = swing::on_frame_grid(&stalled, 1.0 / 30.0).expect("the grid");
    assert!(
        regridded.len() + late <= stalled.len() + 5,
        "{} kept",
        regridded.len()
    );
    let c = swing::pendulum_from_swing(&regridded, 9.81, 1.9).expect("the step");
    assert!((c.swing.length_m - l).abs() < 1e-3, "{}", c.swing.length_m);
    // A clean track keeps its fit (its stamps move by the jitter only).
    let c = swing::pendulum_from_swing(
        &swing::on_frame_grid(&clean, 1.0 / 30.0).unwrap(),
        9.81,
        1.9,
    )
    .expect("the clean step");
    assert!((c.swing.length_m - l).abs() < 1e-3, "{}", c.swing.length_m);
    // A host stalled most of the time (300 ms of every 400): most frames
    // come in bursts, too few on time to trust the grid: refused.
    let mut busy = clean.clone();
    let mut stall_end = 0.0;
    for s in &mut busy {
        let t = s.t_s;
        if t > stall_end && (t % 0.4) < 1.0 / 30.0 {
            stall_end = t + rng.random_range(0.28..0.32);
        }
        s.t_s = if t < stall_end { stall_end } else { t };
    }
    let e = swing::on_frame_grid(&busy, 1.0 / 30.0).map(|v| v.len());
    assert!(
        matches!(&e, Err(CalibrationError::LateFrames { .. }))
            && e.as_ref().is_err_and(|e| {
                e.to_string()
                    .contains("arrive too irregularly to time the pendulum's swing")
            }),
        "{e:?}"
    );
    // Bad input: a NaN stamp, a bad period.
    let mut nan = clean.clone();
    nan[4].t_s = f64::NAN;
    assert!(matches!(
        swing::on_frame_grid(&nan, 1.0 / 30.0),
        Err(CalibrationError::NotFinite { index: 4, .. })
    ));
    assert!(swing::on_frame_grid(&clean, f64::NAN).is_err());
    assert!(swing::on_frame_grid(&clean, 0.0).is_err());
}

#[test]
fn a_recorded_swing_alone_gives_the_pendulum_step_rest_pixel_and_axis() {
    // A camera 1.5 m before the plane, 900 px focal length, its image x along
    // the swing, tilted 3 deg: the ball's image from its lateral and height.
    let (l, b) = (1.93, 0.004);
    let (f, cx, cy, tilt) = (900.0, 640.0, 360.0, 3f64.to_radians());
    let image = |lat: f64, up: f64| {
        let (u, v) = (f * lat / 1.5, -f * up / 1.5);
        [
            cx + u * tilt.cos() - v * tilt.sin(),
            cy + u * tilt.sin() + v * tilt.cos(),
        ]
    };
    let track: Vec<swing::TrackedSwingSample> = swing(l, 0.03, 25.0, 20.0, 0.0005)
        .into_iter()
        .map(|s| {
            let phi = ((s.lateral_m - b) / l).clamp(-1.0, 1.0).asin();
            swing::TrackedSwingSample {
                t_s: s.t_s,
                lateral_m: s.lateral_m,
                px: image(s.lateral_m - b, l * (1.0 - phi.cos())),
            }
        })
        .collect();
    let c = swing::pendulum_from_swing(&track, 9.81, 1.9).expect("the step");
    assert!((c.swing.length_m - l).abs() < 1e-3, "{}", c.swing.length_m);
    let want = image(0.0, 0.0);
    // The rest pixel: where the ball hangs.
    assert!(
        (c.rest_px[0] - want[0]).abs() < 1.0 && (c.rest_px[1] - want[1]).abs() < 1.0,
        "rest {:?} vs {want:?}",
        c.rest_px
    );
    assert!(
        (c.swing_image_angle_deg - 3.0).abs() < 0.5,
        "{}",
        c.swing_image_angle_deg
    );
    // Too few passes near the rest point (a track that never comes back to
    // it): refused, naming what.
    let one_side: Vec<_> = track
        .iter()
        .copied()
        .filter(|s| s.lateral_m > 0.05)
        .collect();
    let e = swing::pendulum_from_swing(&one_side, 9.81, 1.9).unwrap_err();
    assert!(e.to_string().contains("pendulum"), "{e}");
    // A NaN pixel is refused.
    let mut nan = track.clone();
    nan[7].px[1] = f64::NAN;
    assert!(matches!(
        swing::pendulum_from_swing(&nan, 9.81, 1.9),
        Err(CalibrationError::NotFinite { index: 7, .. })
    ));
}

#[test]
fn swing_fit_recovers_length_and_damping_at_large_angles() {
    for (l, release) in [(1.93, 35.0), (1.96, 15.0), (1.2, 25.0)] {
        let samples = swing(l, 0.03, release, 20.0, 0.0005);
        let fit = fit_swing(&samples, 9.81, 1.93).expect("fit");
        assert!(
            (fit.length_m - l).abs() < 1e-3,
            "length {} vs {l} (release {release})",
            fit.length_m
        );
        assert!(
            (fit.damping_per_s - 0.03).abs() < 2e-3,
            "damping {}",
            fit.damping_per_s
        );
        assert!(
            (fit.rest_offset_m - 0.004).abs() < 5e-4,
            "offset {}",
            fit.rest_offset_m
        );
        assert!(fit.residual_rms_m < 0.001);
        // The large-angle correction matters: a small-angle reading of the period
        // would be this far off at 35 deg.
        let naive = 9.81 * (fit.period_at_start_s / std::f64::consts::TAU).powi(2);
        if release > 30.0 {
            assert!(naive - l > 0.03, "naive {naive}");
        }
    }
}

#[test]
fn swing_fit_refuses_bad_input() {
    let small = swing(1.93, 0.03, 1.0, 20.0, 0.0005);
    assert!(matches!(
        fit_swing(&small, 9.81, 1.93),
        Err(CalibrationError::SwingTooSmall { .. })
    ));
    let short = swing(1.93, 0.03, 20.0, 3.0, 0.0005);
    assert!(matches!(
        fit_swing(&short, 9.81, 1.93),
        Err(CalibrationError::TooShort { .. })
    ));
    assert!(matches!(
        fit_swing(&short[..10], 9.81, 1.93),
        Err(CalibrationError::TooFewSamples { .. })
    ));
    let mut nan = swing(1.93, 0.03, 20.0, 20.0, 0.0005);
    nan[7].lateral_m = f64::NAN;
    assert!(matches!(
        fit_swing(&nan, 9.81, 1.93),
        Err(CalibrationError::NotFinite { index: 7, .. })
    ));
}

/// Frames of a camera with `latency_s` (+- 1 ms Gaussian jitter) looking at an LED
/// switched by `edges` (each taking effect half its round trip after it is sent).
fn led_frames(latency_s: f64, edges: &[LedEdge], visible: bool, seed: u64) -> Vec<LedFrame> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let period = 1.0 / 30.0;
    let exposure = 0.006;
    let phase = rng.random_range(0.0..period);
    let lit_fraction = |t_mid: f64| {
        // Fraction of [t_mid - e/2, t_mid + e/2] with the LED on.
        let n = 60;
        let mut on = 0;
        for i in 0..n {
            let t = t_mid - 0.5 * exposure + exposure * (f64::from(i) + 0.5) / f64::from(n);
            let state = edges
                .iter()
                .rev()
                .find(|e| e.t_sent_s + latency::switch_delay_s(e) <= t)
                .is_some_and(|e| e.on);
            on += i32::from(state);
        }
        f64::from(on) / f64::from(n)
    };
    (0..600)
        .filter_map(|k| {
            let t_c = phase + f64::from(k) * period;
            if rng.random_range(0.0..1.0) < 0.02 {
                return None;
            }
            let f = if visible { lit_fraction(t_c) } else { 0.0 };
            Some(LedFrame {
                t_delivered_s: t_c + latency_s + 0.001 * gauss(&mut rng),
                brightness: 40.0 + 180.0 * f + 3.0 * gauss(&mut rng),
            })
        })
        .collect()
}

fn led_edges(seed: u64) -> Vec<LedEdge> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // The frames of `led_frames` are delivered on this grid (phase drawn first
    // from the same seed, latency added); the host sees the first second of them.
    let phase = ChaCha8Rng::seed_from_u64(seed).random_range(0.0..1.0 / 30.0);
    let early: Vec<f64> = (0..25)
        .map(|k| phase + 0.035 + f64::from(k) / 30.0)
        .collect();
    let sends = latency::plan_switches(&early, 1.0 / 30.0, 40, || rng.random_range(0.0..1.0));
    assert_eq!(sends.len(), 40);
    assert!(sends.windows(2).all(|w| w[1] - w[0] > 0.2));
    sends
        .iter()
        .enumerate()
        .map(|(i, &t)| LedEdge {
            t_sent_s: t,
            round_trip_s: rng.random_range(0.0015..0.0035),
            command_wire_s: 0.0,
            answer_wire_s: 0.0,
            on: i % 2 == 0,
        })
        .collect()
}

#[test]
fn led_latency_within_2_ms() {
    for (seed, latency) in [(1, 0.035), (2, 0.062), (3, 0.021)] {
        let edges = led_edges(seed);
        let frames = led_frames(latency, &edges, true, seed);
        let est = estimate_led_latency(&frames, &edges, 1.0 / 30.0).expect("estimate");

        assert!(
            (est.latency_ms - latency * 1e3).abs() < 2.0,
            "{} vs {}",
            est.latency_ms,
            latency * 1e3
        );
        assert!(est.edges_seen >= 35, "{est:?}");
        assert!(
            (est.spread_ms - 1.0).abs() < 0.3,
            "spread {}",
            est.spread_ms
        );
        assert!((est.frame_period_ms - 33.333).abs() < 0.05);
    }
}

/// A loaded host reads some answers late: the round trips it notes are 6-14 ms
/// longer than the board's, while the pins switched on time. Taking half the
/// noted round trip puts those switches 3-7 ms late and the latency as much
/// short, with a bound that claims better than a millisecond (seed 9: 4.3 ms
/// short, +- 0.07 ms). Their windows still hold the true switch: the estimate
/// stays within 2 ms while two in five are late, and the truth within its
/// bound (plus the frames' 1 ms delivery jitter) while three in five are.
#[test]
fn led_latency_holds_when_the_host_reads_answers_late() {
    for (late_share, within_ms) in [(0.4, Some(2.0)), (0.6, None)] {
        for (seed, latency) in [(4, 0.035), (5, 0.048), (6, 0.027), (7, 0.035), (9, 0.04)] {
            let edges = led_edges(seed);
            let frames = led_frames(latency, &edges, true, seed);
            let mut rng = ChaCha8Rng::seed_from_u64(seed + 100);
            let read_late: Vec<LedEdge> = edges
                .iter()
                .map(|e| {
                    let mut e = *e;
                    if rng.random_range(0.0..1.0) < late_share {
                        e.round_trip_s += rng.random_range(0.006..0.014);
                    }
                    e
                })
                .collect();
            let est = estimate_led_latency(&frames, &read_late, 1.0 / 30.0).expect("estimate");
            let err_ms = est.latency_ms - latency * 1e3;
            assert!(
                err_ms.abs() <= est.bound_ms + 1.0 && within_ms.is_none_or(|w| err_ms.abs() < w),
                "{late_share} late, seed {seed}: {err_ms:+.2} ms off: {est:?}"
            );
            assert!(est.edges_consistent >= 35, "{est:?}");
        }
    }
}

#[test]
fn led_never_seen_is_refused() {
    let edges = led_edges(1);
    let frames = led_frames(0.035, &edges, false, 1);
    let e = estimate_led_latency(&frames, &edges, 1.0 / 30.0).unwrap_err();
    assert!(
        matches!(e, CalibrationError::LedNotSeen { seen: 0, .. }),
        "{e}"
    );
    assert!(e.to_string().contains("LED never seen"));
}

/// Commands every 5 ms (a small chirp); the joint follows after `latency` with a
/// first-order lag `tau`; measured every 5 ms with a little noise.
fn excitation(latency: f64, tau: f64) -> (Vec<JointSample>, Vec<JointSample>) {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let dt = 0.005;
    let commands: Vec<JointSample> = (0..600)
        .map(|k| {
            let t = f64::from(k) * dt;
            let f = 0.5 + 2.0 * t / 3.0;
            JointSample {
                t_s: t,
                q_rad: 0.02 * (std::f64::consts::TAU * f * t).sin(),
            }
        })
        .collect();
    // Fine simulation of the truth at 0.1 ms, with +-2 ms uniform jitter per command.
    let due: Vec<f64> = commands
        .iter()
        .map(|c| c.t_s + latency + rng.random_range(-0.002..0.002))
        .collect();
    let mut q = 0.0;
    let mut sp = 0.0;
    let mut measured = Vec::new();
    let h = 1e-4;
    let mut k = 0;
    for i in 0..=30_000 {
        let t = f64::from(i) * h;
        while k < commands.len() && due[k] <= t {
            sp = commands[k].q_rad;
            k += 1;
        }
        q += (sp - q) * (1.0 - (-h / tau).exp());
        if i % 50 == 25 {
            measured.push(JointSample {
                t_s: t,
                q_rad: q + 1e-5 * gauss(&mut rng),
            });
        }
    }
    (commands, measured)
}

#[test]
fn robot_latency_within_1_ms() {
    for (latency, tau) in [(0.008, 0.005), (0.025, 0.005), (0.003, 0.012)] {
        let (c, m) = excitation(latency, tau);
        let fit = fit_robot_latency(&c, &m).expect("fit");
        assert!(
            (fit.latency_ms - latency * 1e3).abs() < 1.0,
            "latency {} vs {}",
            fit.latency_ms,
            latency * 1e3
        );
        assert!(
            (fit.servo_time_constant_ms - tau * 1e3).abs() < 1.5,
            "tau {}",
            fit.servo_time_constant_ms
        );
    }
    let (c, m) = excitation(0.008, 0.005);
    let still: Vec<JointSample> = m.iter().map(|s| JointSample { q_rad: 0.1, ..*s }).collect();
    assert!(matches!(
        fit_robot_latency(&c, &still),
        Err(CalibrationError::NoResponse { .. })
    ));
}

#[test]
fn calibration_file_round_trip_and_apply() {
    let samples = swing(1.95, 0.03, 25.0, 20.0, 0.0005);
    let fit = fit_swing(&samples, 9.81, 1.93).expect("fit");
    let file = CalibrationFile {
        camera: None,
        pendulum: Some(StepRecord {
            date: "2026-12-01T17:00:00Z".into(),
            revision: "test".into(),
            source: "test".into(),
            result: file::PendulumCalibration {
                swing: fit,
                rest_px: [640.0, 360.0],
                rest_std_px: [0.1, 0.1],
                swing_image_angle_deg: 0.5,
            },
        }),
        latency: None,
        robot: None,
        ..CalibrationFile::default()
    };
    let text = file.to_toml_string();
    let back = CalibrationFile::from_toml_str(&text).expect("parse");
    assert_eq!(back, file);
    let s = back
        .apply(&crate::params::Scenario::default())
        .expect("apply");
    assert!((s.pendulum.length_m - 1.95).abs() < 1e-3);
    assert!(CalibrationFile::from_toml_str("[pendulum]\nbogus = 1\n").is_err());
}

fn camera_record() -> StepRecord<CameraCalibration> {
    StepRecord {
        date: "2026-12-02T08:00:00Z".into(),
        revision: "test".into(),
        source: "test".into(),
        result: CameraCalibration {
            width_px: 1280,
            height_px: 720,
            intrinsics: crate::vision::CameraIntrinsics {
                k1: -0.21,
                k2: 0.08,
                p1: 0.001,
                p2: -0.0005,
                ..crate::vision::CameraIntrinsics::default()
            },
            std_dev: [1.0, 1.0, 1.5, 1.5, 0.002, 0.003, 0.0005, 0.0005],
            rms_px: 0.11,
            per_view_rms_px: vec![0.1; 12],
            views_used: 12,
            views_shown: 15,
            board: Chessboard::default(),
        },
    }
}

/// The camera section round-trips, makes the lab believe the calibrated lens,
/// and is refused for a camera of another size; a file without it still reads.
#[test]
fn camera_section_round_trip_and_apply() {
    let file = CalibrationFile {
        camera: Some(camera_record()),
        ..CalibrationFile::default()
    };
    let text = file.to_toml_string();
    assert!(text.contains("[camera.result.intrinsics]"), "{text}");
    let back = CalibrationFile::from_toml_str(&text).expect("parse");
    assert_eq!(back, file);
    let before = crate::params::Scenario::default();
    assert_eq!(before.camera.intrinsics, None);
    let s = back.apply(&before).expect("apply");
    let k = s.camera.believed_intrinsics(70.0);
    assert_eq!((k.k1, k.k2, k.p1, k.p2), (-0.21, 0.08, 0.001, -0.0005));
    // The scenario with the lens is a valid scenario file.
    let again = crate::params::Scenario::from_toml_str(&s.to_toml_string()).expect("scenario");
    assert_eq!(again.camera.intrinsics, Some(k));
    let mut small = before.clone();
    small.camera.width_px = 640;
    small.camera.height_px = 480;
    let e = back.apply(&small).unwrap_err();
    assert_eq!(e.field(), Some("camera.intrinsics"));
    assert!(e.to_string().contains("1280x720"), "{e}");
}

#[cfg(feature = "opencv")]
mod the_intrinsics_fit {
    use nalgebra::{Rotation3, Vector3};

    use super::super::CalibrationError;
    use super::super::intrinsics::{BoardView, Chessboard, MIN_VIEWS, fit_intrinsics};
    use crate::vision::CameraIntrinsics;

    /// Views of the board projected exactly (no rendering) through `k`.
    fn views(k: &CameraIntrinsics, n: usize) -> Vec<BoardView> {
        let board = Chessboard::default();
        (0..n)
            .map(|i| {
                let a = i as f64 * 2.4;
                let rot = Rotation3::from_euler_angles(0.5 * a.cos(), 0.5 * a.sin(), 0.2 * a.sin());
                let t = Vector3::new(
                    0.25 * (1.3 * a).sin() - 0.12,
                    0.15 * (0.7 * a).cos() - 0.08,
                    0.7 + 0.05 * i as f64,
                );
                let corners = board
                    .object_points()
                    .iter()
                    .map(|p| {
                        let uv = k.project(&(rot * Vector3::from(*p) + t)).unwrap();
                        [uv.x, uv.y]
                    })
                    .collect();
                BoardView {
                    corners_px: Some(corners),
                }
            })
            .collect()
    }

    #[test]
    fn exact_corners_give_the_lens_back() {
        let k = CameraIntrinsics {
            fx_px: 910.0,
            fy_px: 912.0,
            cx_px: 645.0,
            cy_px: 355.0,
            k1: -0.2,
            k2: 0.07,
            p1: 0.001,
            p2: -0.002,
        };
        let fit = fit_intrinsics(&Chessboard::default(), &views(&k, 12), 1280, 720).expect("fit");
        let c = &fit.calibration;
        let e = &c.intrinsics;
        assert!(c.rms_px < 1e-3, "RMS {}", c.rms_px);
        assert!(
            (e.fx_px - k.fx_px).abs() < 0.05 && (e.cx_px - k.cx_px).abs() < 0.05,
            "{e:?}"
        );
        assert!(
            (e.k1 - k.k1).abs() < 1e-4 && (e.k2 - k.k2).abs() < 1e-3,
            "{e:?}"
        );
        assert!(
            (e.p1 - k.p1).abs() < 1e-5 && (e.p2 - k.p2).abs() < 1e-5,
            "{e:?}"
        );
        assert_eq!(
            (c.views_used, c.per_view_rms_px.len(), fit.reprojected.len()),
            (12, 12, 12)
        );
    }

    #[test]
    fn bad_input_is_refused() {
        let k = CameraIntrinsics::default();
        let board = Chessboard::default();
        let none = vec![BoardView { corners_px: None }; 15];
        let e = fit_intrinsics(&board, &none, 1280, 720).unwrap_err();
        assert!(
            matches!(e, CalibrationError::BoardNotSeen { shown: 15, .. }),
            "{e}"
        );
        assert!(e.to_string().starts_with("no board visible"), "{e}");
        let mut few = views(&k, MIN_VIEWS - 1);
        few.extend(none.iter().cloned());
        let e = fit_intrinsics(&board, &few, 1280, 720).unwrap_err();
        assert!(
            matches!(
                e,
                CalibrationError::TooFewSamples {
                    got: 7,
                    need: 8,
                    ..
                }
            ),
            "{e}"
        );
        let mut short = views(&k, 10);
        if let Some(c) = short[3].corners_px.as_mut() {
            c.pop();
        }
        assert!(matches!(
            fit_intrinsics(&board, &short, 1280, 720).unwrap_err(),
            CalibrationError::FitFailed { .. }
        ));
        let mut nan = views(&k, 10);
        if let Some(c) = nan[2].corners_px.as_mut() {
            c[5][1] = f64::NAN;
        }
        assert!(matches!(
            fit_intrinsics(&board, &nan, 1280, 720).unwrap_err(),
            CalibrationError::NotFinite { .. }
        ));
        // Corners that belong to no camera (a shuffled view) blow the RMS.
        let mut wrong = views(&k, 10);
        if let Some(c) = wrong[4].corners_px.as_mut() {
            c.reverse();
            c.swap(0, 20);
            c.swap(7, 40);
        }
        let e = fit_intrinsics(&board, &wrong, 1280, 720).unwrap_err();
        assert!(e.to_string().contains("RMS"), "{e}");
    }
}

#[cfg(feature = "opencv")]
mod on_the_simulated_world {
    use super::super::sim_intrinsics::run_camera;
    use super::super::simworld::{
        HiddenWorld, ProcedureError, run_led_latency, run_pendulum, run_robot,
    };
    use super::super::{CalibrationError, CalibrationFile, Chessboard, StepRecord, Unwatched};
    use crate::params::{Scenario, VisionMode};

    fn model_scenario() -> Scenario {
        let mut s = Scenario::default();
        s.camera.vision = VisionMode::Model;
        s
    }

    #[test]
    fn pendulum_length_within_3_mm_and_rest_point_found() {
        let s = model_scenario();
        for seed in [1, 2] {
            let w = HiddenWorld::draw(&s, seed);
            let run = run_pendulum(&s, &w, seed, 25.0, 20.0, &mut super::super::Unwatched)
                .expect("pendulum step");
            let fit = &run.calibration.swing;
            assert!(
                (fit.length_m - run.true_length_m).abs() < 0.003,
                "seed {seed}: length {} vs true {} (belief {})",
                fit.length_m,
                run.true_length_m,
                s.pendulum.length_m
            );
            assert!((fit.damping_per_s - run.true_damping_per_s).abs() < 0.005);
            // The hidden error is big enough that the belief would fail the target.
            assert!((s.pendulum.length_m - run.true_length_m).abs() > 0.003 || seed != 1);
            assert!(
                (run.rest_m[2] - run.true_rest_m[2]).abs() < 0.003,
                "rest height {:?} vs {:?}",
                run.rest_m,
                run.true_rest_m
            );
        }
    }

    /// With `[world]` the truth is the world's session draw (length, damping,
    /// camera and robot latency), and the pendulum step still finds the length.
    #[test]
    fn the_scenario_world_gives_the_truth() {
        let mut s = model_scenario();
        let text = "[pendulum]\nlength_error_m = [-0.05, 0.05]\n\
                    [camera]\nlatency_ms = [5.0, 25.0]\n";
        let w: crate::sim::world::WorldParams = toml::from_str(text).expect("world");
        s.world = Some(w);
        s.validate().expect("valid");
        let truth = HiddenWorld::draw(&s, 4);
        let d = s
            .world
            .as_ref()
            .unwrap()
            .draw_session(4, 0, s.robot.latency_ms);
        assert_eq!(truth.length_error_m, d.length_error_m);
        assert!(truth.length_error_m.abs() > 0.0 && truth.length_error_m.abs() <= 0.05);
        assert!(truth.camera_latency_ms >= s.camera.latency_ms + 5.0);
        let run = run_pendulum(&s, &truth, 4, 25.0, 20.0, &mut super::super::Unwatched)
            .expect("pendulum step");
        assert!(
            (run.calibration.swing.length_m - run.true_length_m).abs() < 0.003,
            "{} vs {}",
            run.calibration.swing.length_m,
            run.true_length_m
        );
    }

    /// The live view of the pendulum step ends with the samples and the fitted
    /// curve, and the curve is the fit: within a few millimetres of every sample.
    #[test]
    fn the_pendulum_view_shows_the_samples_and_the_fitted_swing() {
        let s = model_scenario();
        let w = HiddenWorld::draw(&s, 2);
        let mut views = Vec::new();
        let mut watch = |v: super::super::StepView| views.push(v);
        let run = run_pendulum(&s, &w, 2, 25.0, 20.0, &mut watch).expect("pendulum step");
        assert!(views.len() >= 5, "{} views", views.len());
        assert!(views.windows(2).all(|v| v[1].progress >= v[0].progress));
        assert_eq!(views[0].kind, super::super::ViewKind::Image);
        let last = views.last().unwrap();
        assert_eq!(last.progress, 1.0);
        assert_eq!(last.kind, super::super::ViewKind::Series);
        assert!(last.points.len() > 300 && last.points.len() <= 400);
        assert!(last.fit.len() > 300);
        // Each sample against the curve, linearly interpolated.
        let mut worst: f64 = 0.0;
        for p in &last.points {
            let i = last
                .fit
                .partition_point(|f| f[0] < p[0])
                .clamp(1, last.fit.len() - 1);
            let (a, b) = (last.fit[i - 1], last.fit[i]);
            let y = a[1] + (b[1] - a[1]) * (p[0] - a[0]) / (b[0] - a[0]);
            worst = worst.max((y - p[1]).abs());
        }
        assert!(
            worst < 0.01 + 4.0 * run.calibration.swing.residual_rms_m,
            "the curve is {worst} m off a sample"
        );
    }

    #[test]
    fn a_swing_too_small_is_refused() {
        let s = model_scenario();
        let w = HiddenWorld::draw(&s, 1);
        let e = run_pendulum(&s, &w, 1, 1.0, 20.0, &mut super::super::Unwatched).unwrap_err();
        assert!(
            matches!(
                e,
                ProcedureError::Calibration(CalibrationError::SwingTooSmall { .. })
            ),
            "{e}"
        );
        assert!(e.to_string().contains("swing too small"));
    }

    #[test]
    fn camera_latency_by_led_within_2_ms() {
        let s = Scenario::default();
        for seed in [1, 2] {
            let w = HiddenWorld::draw(&s, seed);
            let run = run_led_latency(&s, &w, seed, 40, true, &mut super::super::Unwatched)
                .expect("latency step");
            assert!(
                (run.result.latency_ms - run.true_latency_ms).abs() < 2.0,
                "seed {seed}: {} vs true {} (belief {})",
                run.result.latency_ms,
                run.true_latency_ms,
                s.camera.latency_ms
            );
        }
        let w = HiddenWorld::draw(&s, 1);
        let e = run_led_latency(&s, &w, 1, 40, false, &mut super::super::Unwatched).unwrap_err();
        assert!(e.to_string().contains("LED never seen"), "{e}");
    }

    #[test]
    fn robot_latency_within_1_ms_through_fri() {
        let s = Scenario::default();
        for seed in [1, 2] {
            let w = HiddenWorld::draw(&s, seed);
            let run = run_robot(&s, &w, seed, 0.02, 4.0, &mut super::super::Unwatched)
                .expect("robot step");
            assert!(
                (run.result.latency_ms - run.true_latency_ms).abs() < 1.0,
                "seed {seed}: {} vs true {}",
                run.result.latency_ms,
                run.true_latency_ms
            );
            assert!(
                (run.result.servo_time_constant_ms - run.true_servo_time_constant_ms).abs() < 1.5,
                "tau {} vs {}",
                run.result.servo_time_constant_ms,
                run.true_servo_time_constant_ms
            );
        }
    }

    fn reality() -> Scenario {
        Scenario::from_toml_str(include_str!("../../../scenarios/reality.toml")).expect("reality")
    }

    /// A world whose lens is strong (k1 = -0.25, k2 = 0.1): the nominal lens
    /// (none) is far off, so the estimate must come from the board.
    fn strong_lens() -> Scenario {
        let mut s = reality();
        if let Some(w) = s.world.as_mut() {
            w.camera.distortion_k1 = crate::params::RangeParam::fixed(-0.25);
            w.camera.distortion_k2 = crate::params::RangeParam::fixed(0.1);
        }
        s.validate().expect("valid");
        s
    }

    /// Board views per camera step.
    const VIEWS: usize = 20;

    fn calibrate(
        s: &Scenario,
        seed: u64,
    ) -> (
        super::super::sim_intrinsics::CameraRun,
        Vec<super::super::StepView>,
    ) {
        let w = HiddenWorld::draw(s, seed);
        let mut seen = Vec::new();
        let run = run_camera(
            s,
            &w,
            seed,
            &Chessboard::default(),
            VIEWS,
            true,
            &mut |v: super::super::StepView| seen.push(v),
        )
        .expect("camera step");
        (run, seen)
    }

    /// On reality.toml's draws the estimate lands within the issue's k1 target
    /// and a few pixels of the true focal length and principal point; each
    /// board view is reported with its corners, and the fit with the
    /// reprojected ones.
    #[test]
    fn camera_intrinsics_on_reality_draws() {
        let s = reality();
        for seed in [1, 2] {
            let (run, seen) = calibrate(&s, seed);
            let (k, t) = (&run.result.intrinsics, &run.truth);
            assert!(
                (k.k1 - t.k1).abs() <= 0.02,
                "seed {seed}: k1 {} vs {}",
                k.k1,
                t.k1
            );
            assert!(
                (k.fx_px - t.fx_px).abs() < 5.0,
                "seed {seed}: fx {} vs {}",
                k.fx_px,
                t.fx_px
            );
            assert!(
                (k.fy_px - t.fy_px).abs() < 5.0,
                "seed {seed}: fy {} vs {}",
                k.fy_px,
                t.fy_px
            );
            assert!(
                (k.cx_px - t.cx_px).abs() < 5.0,
                "seed {seed}: cx {} vs {}",
                k.cx_px,
                t.cx_px
            );
            assert!(
                (k.cy_px - t.cy_px).abs() < 5.0,
                "seed {seed}: cy {} vs {}",
                k.cy_px,
                t.cy_px
            );
            assert!(
                run.result.rms_px < 0.5,
                "seed {seed}: RMS {}",
                run.result.rms_px
            );
            assert!(
                run.result.views_used >= 16,
                "seed {seed}: {} views",
                run.result.views_used
            );
            let corners = Chessboard::default().corners();
            assert_eq!(seen.len(), VIEWS + run.result.views_used);
            assert!(
                seen[..VIEWS]
                    .iter()
                    .filter(|v| v.points.len() == corners)
                    .count()
                    >= 12
            );
            assert!(
                seen[VIEWS..]
                    .iter()
                    .all(|v| v.points.len() == corners && v.fit.len() == corners)
            );
            assert!(seen.iter().all(|v| v.kind == super::super::ViewKind::Image));
        }
    }

    /// A strong lens: k1 within 0.02 of the truth; the lab that believes the
    /// calibration file's lens measures the ball's lateral position near the
    /// image's edges within a millimetre, where the nominal (no lens) belief is
    /// centimetres off; pixels 100 px in from the image's corners, undistorted,
    /// land within 1.5 px of their true pinhole projection (0.13-1.32 px over
    /// 10 draws; the nominal lens: ~55 px).
    #[test]
    fn a_strong_lens_is_measured_and_undone() {
        use crate::sim::camera::SimCameraParams;
        use crate::vision::SwingPlaneCalibration;
        use crate::vision::undistortion_error_px;
        let s = strong_lens();
        let (run, _) = calibrate(&s, 3);
        let (k, t) = (run.result.intrinsics, run.truth);
        assert_eq!((t.k1, t.k2), (-0.25, 0.1));
        assert!((k.k1 - t.k1).abs() <= 0.02, "k1 {} vs {}", k.k1, t.k1);
        assert!((k.k2 - t.k2).abs() <= 0.05, "k2 {} vs {}", k.k2, t.k2);
        // 100 px in from the edges: where the board's outer corners reach
        // (the white margin and the outer squares keep them off the edges).
        for (u, v) in [
            (100.0, 100.0),
            (1179.0, 100.0),
            (100.0, 619.0),
            (1179.0, 619.0),
        ] {
            let e = undistortion_error_px(&t, &k, u, v);
            assert!(e < 1.5, "corner ({u}, {v}): {e} px");
            let nominal =
                undistortion_error_px(&t, &crate::vision::CameraIntrinsics::default(), u, v);
            assert!(
                nominal > 30.0,
                "the lens moves the corner ({u}, {v}) by {nominal} px"
            );
        }
        // The lab's belief after `apply`: the detector's swing-plane conversion.
        let file = CalibrationFile {
            camera: Some(StepRecord {
                date: "d".into(),
                revision: "r".into(),
                source: "s".into(),
                result: run.result.clone(),
            }),
            ..CalibrationFile::default()
        };
        let believed = file.apply(&s).expect("apply");
        let hfov = SimCameraParams::default().hfov_deg;
        assert_eq!(believed.camera.believed_intrinsics(hfov), k);
        // The true camera with the lens only (no pose error), the believed pose.
        let mut w = HiddenWorld::draw(&s, 3);
        w.camera_rotation_error_rad = [0.0; 3];
        w.camera_position_error_m = [0.0; 3];
        let cam = w.world_camera(&s);
        let pose = SimCameraParams::default().pose;
        let rest = nalgebra::Vector3::new(s.task.distance_m.lo, 0.0, s.task.intercept_height_m);
        let r = s.pendulum.ball_radius_m;
        let calibrated = SwingPlaneCalibration::from_pose(k, &pose, &rest, r);
        let nominal =
            SwingPlaneCalibration::from_pose(s.camera.believed_intrinsics(hfov), &pose, &rest, r);
        let (mut worst_cal, mut worst_nom, mut edge) = (0.0f64, 0.0f64, 0.0f64);
        for y in [-1.2, -0.9, -0.6, -0.3, 0.0, 0.3, 0.6, 0.9, 1.2] {
            for dz in [-0.3, 0.0, 0.3] {
                let p = rest + nalgebra::Vector3::new(0.0, y, dz);
                let Some(px) = cam.project(&p) else { continue };
                if !(0.0..1280.0).contains(&px.x) || !(0.0..720.0).contains(&px.y) {
                    continue;
                }
                edge = edge.max((px.x - 640.0).abs());
                let lat_c = calibrated.lateral_m(px.x, px.y).expect("on the plane");
                let lat_n = nominal.lateral_m(px.x, px.y).expect("on the plane");
                worst_cal = worst_cal.max((lat_c - y).abs());
                worst_nom = worst_nom.max((lat_n - y).abs());
            }
        }
        assert!(
            edge > 450.0,
            "points reach the image's sides: {edge} px from the centre"
        );
        assert!(worst_cal < 0.001, "calibrated: {worst_cal} m");
        assert!(worst_nom > 0.02, "the nominal lens: {worst_nom} m");
    }

    /// The operator holds the board out of view: "no board visible", no result.
    #[test]
    fn no_board_visible_is_refused() {
        let s = reality();
        let w = HiddenWorld::draw(&s, 1);
        let e = run_camera(
            &s,
            &w,
            1,
            &Chessboard::default(),
            VIEWS,
            false,
            &mut Unwatched,
        )
        .unwrap_err();
        assert!(
            matches!(
                e,
                ProcedureError::Calibration(CalibrationError::BoardNotSeen { shown: VIEWS, .. })
            ),
            "{e}"
        );
        assert!(e.to_string().starts_with("no board visible"), "{e}");
    }
}

#[cfg(feature = "opencv")]
mod camera_robot {
    use crate::calibration::Unwatched;
    use crate::calibration::sim_extrinsics::{CameraRobotOptions, run_camera_robot};
    use crate::calibration::simworld::HiddenWorld;
    use crate::calibration::view::StepView;
    use crate::params::Scenario;

    fn reality() -> Scenario {
        Scenario::from_file(std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../scenarios/reality.toml"
        )))
        .expect("reality.toml")
    }

    /// The tour's targets put the marker on its points, stay inside the
    /// limits, and each move is no longer than the one to the solution
    /// nearest in joint space (`analytic::solve` seeded with the previous
    /// target: the tour's rule before), and all of them together shorter.
    #[test]
    fn the_tour_takes_at_each_pose_the_solution_reached_soonest() {
        use crate::calibration::marker::{
            TARGET_MARGIN_RAD, TOUR_SEED_DEG, marker_believed, tour_points, tour_targets,
        };
        use crate::control::step::move_to_duration_s;
        use crate::kinematics::{self, Joints};
        let s = reality();
        let seed: [f64; 7] = std::array::from_fn(|j| TOUR_SEED_DEG[j].to_radians());
        let points = tour_points(&s);
        let targets = tour_targets(&points, &seed);
        assert!(targets.len() >= 12, "{} poses", targets.len());
        let (mut from, mut tour_s, mut nearest_s) = (Joints::from_column_slice(&seed), 0.0, 0.0);
        let mut at = 0;
        for q in &targets {
            // The point this target is for: the next one the marker reaches.
            let (m, _) = marker_believed(q);
            while (m - points[at]).norm() > 1e-6 {
                at += 1;
                assert!(at < points.len(), "a target off every point: {m}");
            }
            let qv = Joints::from_column_slice(q);
            assert!(kinematics::analytic::check_limits(&qv, TARGET_MARGIN_RAD).is_ok());
            // The solution nearest in joint space for the same flange pose.
            let flange = kinematics::flange_pose(&qv);
            let nearest = kinematics::analytic::solve(&flange, Some(&from), TARGET_MARGIN_RAD)
                .expect("the pose is reachable");
            let (t, t_near) = (
                move_to_duration_s(&from, &qv),
                move_to_duration_s(&from, &nearest.q),
            );
            assert!(t <= t_near + 1e-3, "pose {at}: {t} s for {t_near} s");
            tour_s += t;
            nearest_s += t_near;
            from = qv;
            at += 1;
        }
        assert!(tour_s < nearest_s, "{tour_s} s for {nearest_s} s");
    }

    /// On reality.toml's hidden draws: the camera within 0.3 deg and 5 mm of the
    /// true camera, the intercept point within 3 mm of the true rest point; every
    /// command the tour sent inside the joint limits (by at least 5 degrees).
    #[test]
    fn camera_pose_and_intercept_within_targets_on_reality_draws() {
        let s = reality();
        for seed in [1, 2, 3] {
            let w = HiddenWorld::draw(&s, seed);
            let mut views: Vec<StepView> = Vec::new();
            let mut watch = |v: StepView| views.push(v);
            let run = run_camera_robot(&s, &w, seed, &CameraRobotOptions::default(), &mut watch)
                .expect("camera-robot step");
            let c = &run.calibration;
            assert!(
                run.camera_rotation_error_deg < 0.3,
                "seed {seed}: rotation error {} deg",
                run.camera_rotation_error_deg
            );
            assert!(
                run.camera_position_error_mm < 5.0,
                "seed {seed}: position error {} mm",
                run.camera_position_error_mm
            );
            assert!(
                run.intercept_error_mm < 3.0,
                "seed {seed}: intercept error {} mm ({:?} vs {:?})",
                run.intercept_error_mm,
                c.intercept_m,
                run.true_intercept_m
            );
            assert!(c.poses >= 12 && c.reprojection_rms_px < 1.0, "{c:?}");
            assert!(run.commands_sent > 1000, "{}", run.commands_sent);
            assert!(
                run.min_command_margin_rad > 5f64.to_radians(),
                "a command came within {} rad of a joint limit",
                run.min_command_margin_rad
            );
            // The live view: one per pose, then the fit with its reprojection.
            assert!(views.len() >= c.poses, "{} views", views.len());
            let last = views.last().expect("views");
            assert!((last.progress - 1.0).abs() < 1e-12);
            assert_eq!(last.points.len(), last.fit.len());
        }
    }

    #[test]
    fn hidden_marker_is_refused() {
        let s = reality();
        let w = HiddenWorld::draw(&s, 4);
        let options = CameraRobotOptions {
            marker_visible: false,
            ..CameraRobotOptions::default()
        };
        let e = run_camera_robot(&s, &w, 4, &options, &mut Unwatched).unwrap_err();
        assert!(e.to_string().contains("marker never seen"), "{e}");
    }
}

/// The camera-robot step's intercept offset is a belief the controller plans
/// with: the planned intercept point moves by it (and the camera pose is refused
/// out of range, naming the field).
#[test]
fn intercept_offset_moves_the_planned_intercept_point() {
    let mut s = crate::params::Scenario::default();
    let plain = crate::control::Controller::plan(&s.beliefs(), 0.6).expect("plan");
    s.task.intercept_offset_m = [0.002, -0.003, 0.001];
    s.validate().expect("valid");
    let moved = crate::control::Controller::plan(&s.beliefs(), 0.6).expect("plan");
    let d = moved.intercept_m - plain.intercept_m;
    assert!(
        (d - nalgebra::Vector3::new(0.002, -0.003, 0.001)).norm() < 1e-12,
        "{d:?}"
    );
    s.task.intercept_offset_m = [0.5, 0.0, 0.0];
    let e = s.validate().unwrap_err();
    assert_eq!(e.field(), Some("task.intercept_offset_m[0]"));
    s.task.intercept_offset_m = [0.0; 3];
    s.camera.pose = Some(crate::vision::CameraPose {
        yaw_deg: 90.0,
        ..crate::vision::CameraPose::default()
    });
    let e = s.validate().unwrap_err();
    assert_eq!(e.field(), Some("camera.pose.yaw_deg"));
}

/// Laying a calibration over a scenario with `[world]` changes what the lab
/// believes, never the simulated truth: the world's offsets stay drawn around
/// the nominal beliefs (`WorldParams::anchor`), also when applied twice.
#[test]
fn a_calibration_moves_the_beliefs_not_the_simulated_world() {
    use crate::sim::world::World;
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/reality.toml");
    let nominal = crate::params::Scenario::from_file(&path).expect("reality.toml");
    let samples = swing(nominal.pendulum.length_m + 0.03, 0.03, 25.0, 20.0, 0.0005);
    let fit = fit_swing(&samples, 9.81, nominal.pendulum.length_m).expect("fit");
    let file = CalibrationFile {
        pendulum: Some(StepRecord {
            date: "2026-12-02T08:00:00Z".into(),
            revision: "test".into(),
            source: "test".into(),
            result: file::PendulumCalibration {
                swing: fit,
                rest_px: [640.0, 360.0],
                rest_std_px: [0.1, 0.1],
                swing_image_angle_deg: 0.0,
            },
        }),
        latency: None,
        robot: None,
        ..CalibrationFile::default()
    };
    let calibrated = file.apply(&nominal).expect("apply");
    let twice = file.apply(&calibrated).expect("apply again");
    assert!((calibrated.pendulum.length_m - nominal.pendulum.length_m - 0.03).abs() < 1e-3);
    let at = nalgebra::Vector3::new(0.5, 0.0, 0.3);
    for index in [0, 25, 61] {
        let truth = World::for_trial(&nominal, 7, index, &at).expect("world");
        for s in [&calibrated, &twice] {
            let w = World::for_trial(s, 7, index, &at).expect("world");
            assert_eq!(w.pendulum.length_m, truth.pendulum.length_m);
            assert_eq!(w.pendulum.damping_per_s, truth.pendulum.damping_per_s);
        }
    }
}

/// A recording that begins while the magnet still holds the ball (its board
/// answered the release late: a serial link on a busy machine): the fit
/// starts where the ball leaves. Once, in `make test` beside `stress-ng`, a
/// world lab's step wrote 1.994 m for a 1.93 m pendulum, residual 0.22 m; a
/// second of held ball before the swing gives 1.966 m, residual 0.085 m.
/// Samples no free swing explains are refused, and nothing is fitted.
#[test]
fn a_swing_recorded_before_the_ball_leaves_is_fitted_from_its_release() {
    let l = 1.93;
    let free = swing(l, 0.03, 15.0, 20.0, 0.0005);
    let held_at = free[0].lateral_m;
    for held_s in [0.0, 0.3, 1.0, 3.0, 6.0] {
        let mut s: Vec<SwingSample> = (0..(held_s * 30.0) as usize)
            .map(|k| SwingSample {
                t_s: free[0].t_s - held_s + k as f64 / 30.0,
                lateral_m: l * 15f64.to_radians().sin() + 0.004 + 0.0005 * ((k % 3) as f64 - 1.0),
            })
            .collect();
        s.extend(free.iter().copied());
        let fit = swing::fit_swing(&s, 9.81, 1.9).expect("the fit");
        assert!(
            (fit.length_m - l).abs() < 1e-3 && fit.residual_rms_m < 0.002,
            "held {held_s} s at {held_at} m: length {} m, residual {} m",
            fit.length_m,
            fit.residual_rms_m
        );
        assert!(
            fit.samples <= free.len() + 1,
            "held {held_s} s: {} samples",
            fit.samples
        );
    }
    // Two seconds of the swing seen 0.2 m off (a mistaken detection, a
    // stalled stream): refused, naming the residual.
    let mut bad = free.clone();
    for x in bad.iter_mut().filter(|x| (8.0..10.0).contains(&x.t_s)) {
        x.lateral_m += 0.2;
    }
    let e = swing::fit_swing(&bad, 9.81, 1.9).unwrap_err();
    assert!(matches!(e, CalibrationError::PoorFit { .. }), "{e}");
    assert!(e.to_string().contains("do not follow a free swing"), "{e}");
}

/// A starved webcam stream: every frame 12 ms late plus a heavy (exponential)
/// tail, delivered in order. The slots rounded from the first frame's delivery
/// put the latency up to 18 ms short (tail 20 ms) with a bound of 0.7 ms; the
/// world lab's step beside `stress-ng` wrote 30.8 ms for 49.0 ms delivered.
/// The estimate is the mean capture -> delivery latency within 2 ms (or its
/// bound plus 1 ms); a tail of 30 ms (frames spread over more than three
/// quarters of a period) may be refused as too irregular, never guessed.
#[test]
fn led_latency_holds_when_frames_come_late_by_a_heavy_tail() {
    for seed in 1..=4u64 {
        for tail_ms in [2.0, 5.0, 10.0, 15.0, 20.0, 30.0] {
            let edges = led_edges(seed);
            let mut frames = led_frames(0.030, &edges, true, seed);
            let mut rng = ChaCha8Rng::seed_from_u64(seed + 7);
            let base: Vec<f64> = frames.iter().map(|f| f.t_delivered_s).collect();
            for f in &mut frames {
                let u: f64 = rng.random_range(1e-9..1.0);
                f.t_delivered_s += 0.012 - tail_ms * 1e-3 * u.ln();
            }
            // Delivered in order, as a stream does (a late frame holds up the next).
            for i in 1..frames.len() {
                frames[i].t_delivered_s = frames[i].t_delivered_s.max(frames[i - 1].t_delivered_s);
            }
            let late: f64 = frames
                .iter()
                .zip(&base)
                .map(|(f, b)| f.t_delivered_s - b)
                .sum();
            let truth_ms = 30.0 + 1e3 * late / frames.len() as f64;
            let est = match estimate_led_latency(&frames, &edges, 1.0 / 30.0) {
                Ok(est) => est,
                // Too irregular to slot the frames: refused, never a guess.
                Err(CalibrationError::IrregularFrames { spread_ms, .. }) if tail_ms >= 30.0 => {
                    eprintln!("seed {seed}, tail {tail_ms} ms: refused, spread {spread_ms:.1} ms");
                    assert!(spread_ms > 25.0);
                    continue;
                }
                Err(e) => panic!("seed {seed}, tail {tail_ms} ms: {e}"),
            };
            let err = est.latency_ms - truth_ms;
            eprintln!(
                "seed {seed}, tail {tail_ms} ms: {:.2} ms for {truth_ms:.2} ({err:+.2}, bound {:.2}, spread {:.2}, {}/{} switches)",
                est.latency_ms, est.bound_ms, est.spread_ms, est.edges_consistent, est.edges_seen
            );
            assert!(
                err.abs() < 2.0_f64.max(est.bound_ms + 1.0),
                "seed {seed}, tail {tail_ms} ms: {err:+.2} ms off: {est:?}"
            );
        }
    }
}
