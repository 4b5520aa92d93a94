use super::figure::fig4_data;
use super::*;
use crate::pendulum::PendulumSim;
use nalgebra::Vector2;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    // Box-Muller.
    let u1: f64 = rng.random_range(f64::EPSILON..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn lab() -> (PendulumModel, PendulumGeometry) {
    let model = PendulumModel {
        length_m: 1.93,
        gravity_mps2: 9.81,
        damping_per_s: 0.03,
    };
    (model, PendulumGeometry::new(1.93, 0.6, 0.3).unwrap())
}

/// A swing recorded at `fps` for `duration_s` with white measurement noise of
/// `r_std_m` and a piecewise-constant random angular acceleration of variance `sigma`.
fn recording(seed: u64, fps: f64, duration_s: f64, r_std_m: f64, sigma: f64) -> Series {
    let (model, geometry) = lab();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut sim =
        PendulumSim::free(model, geometry, Vector2::new(25f64.to_radians(), 0.0), 0.0).unwrap();
    let dt = 1.0 / fps;
    let n = (duration_s * fps) as usize;
    let mut s = Series::default();
    for k in 0..n {
        let t = k as f64 * dt;
        s.t_s.push(t);
        s.z_m.push(sim.lateral_m() + r_std_m * gauss(&mut rng));
        sim.advance_to_with_accel(t + dt, sigma.sqrt() * gauss(&mut rng))
            .unwrap();
    }
    s
}

fn paper_filter() -> EkfParams {
    EkfParams {
        process_noise_model: ProcessNoiseModel::Paper,
        estimate_damping: false,
        // Deliberately wrong starting values.
        measurement_noise_m: 0.006,
        accel_var_rad2ps4: 1e-4,
        ..EkfParams::default()
    }
}

#[test]
fn tune_recovers_known_noise_within_20_percent_and_is_consistent() {
    let (r_true, sigma_true) = (0.002, 0.01);
    let series = recording(7, 30.0, 120.0, r_true, sigma_true);
    let (model, geometry) = lab();
    let report = tune(&series, &paper_filter(), model, geometry).unwrap();
    let r_err = report.estimate.measurement_noise_m / r_true - 1.0;
    let q_err = report.estimate.process_noise / sigma_true - 1.0;
    eprintln!(
        "R std {:.5} m ({:+.1}%), sigma {:.5} ({:+.1}%), NIS {:.3} in [{:.3}, {:.3}], {} evaluations",
        report.estimate.measurement_noise_m,
        100.0 * r_err,
        report.estimate.process_noise,
        100.0 * q_err,
        report.consistency.nis_mean,
        report.consistency.nis_bounds_95[0],
        report.consistency.nis_bounds_95[1],
        report.evaluations
    );
    assert!(r_err.abs() < 0.2, "measurement noise off by {r_err}");
    assert!(q_err.abs() < 0.2, "process noise off by {q_err}");
    assert!(
        report.consistency.nis_consistent,
        "{:?}",
        report.consistency
    );
    assert!(!report.before_consistency.nis_consistent);
    assert!(report.consistency.innovation_autocorr_lag1.abs() < 0.1);
    assert_eq!(report.estimate.process_noise_param, "accel_var_rad2ps4");
}

#[test]
fn tuned_toml_loads_back_as_ekf_params() {
    let series = recording(3, 30.0, 20.0, 0.002, 0.01);
    let (model, geometry) = lab();
    let report = tune(&series, &paper_filter(), model, geometry).unwrap();
    let text = params_toml(&paper_filter(), &report);
    #[derive(serde::Deserialize)]
    struct File {
        ekf: EkfParams,
    }
    let back: File = toml::from_str(&text).unwrap();
    back.ekf.validate().unwrap();
    assert_eq!(
        back.ekf.measurement_noise_m,
        report.estimate.measurement_noise_m
    );
    assert_eq!(back.ekf.accel_var_rad2ps4, report.estimate.process_noise);
}

#[test]
fn too_short_a_recording_is_refused() {
    let series = recording(1, 30.0, 5.0, 0.002, 0.01);
    let (model, geometry) = lab();
    let e = tune(&series, &paper_filter(), model, geometry).unwrap_err();
    assert!(matches!(e, TuneError::TooShort(150)), "{e}");
}

#[test]
fn reads_both_csv_shapes() {
    let plain = Series::from_csv("t_s,x_m\n0.0,0.1\n0.033,0.09\n").unwrap();
    assert_eq!(plain.t_s, vec![0.0, 0.033]);
    // A service recording: the held ball (captured before the release) is left
    // out, rows without a measurement are skipped, repeats are folded.
    let rec = Series::from_csv(
        "trial_state,t_s,seq,measured_valid,measured_t_s,measured_x_m\n\
         arming,0.000,0,0,NaN,NaN\n\
         armed,0.005,1,1,0.001,0.3\n\
         released,0.010,2,1,0.001,0.3\n\
         released,0.015,3,1,0.012,0.2999\n\
         tracking,0.020,4,1,0.012,0.2999\n\
         tracking,0.045,5,1,0.034,0.29\n",
    )
    .unwrap();
    assert_eq!(rec.t_s, vec![0.012, 0.034]);
    assert_eq!(rec.z_m, vec![0.2999, 0.29]);
    let e = Series::from_csv(
        "trial_state,t_s,measured_valid,measured_t_s,measured_x_m\n\
         arming,0.000,0,NaN,NaN\n\
         armed,0.005,1,0.001,0.3\n",
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("not released"), "{e}");
}

#[test]
fn a_measurement_that_is_not_finite_is_refused_naming_the_line() {
    for text in [
        "t_s,x_m\n0.0,0.1\n0.033,NaN\n",
        "t_s,x_m\n0.0,0.1\n0.033,inf\n",
        "t_s,x_m\n0.0,0.1\nNaN,0.1\n",
        "trial_state,t_s,measured_valid,measured_t_s,measured_x_m\n\
         released,0.000,1,0.001,0.3\n\
         tracking,0.005,1,0.003,NaN\n",
    ] {
        let e = Series::from_csv(text).unwrap_err().to_string();
        assert!(
            e.contains("line 3") && e.contains("not a finite number"),
            "{e}"
        );
    }
}

#[test]
fn a_recording_without_a_swing_is_refused() {
    // The ball hanging still, seen with 2 mm of noise for 20 s.
    let (model, geometry) = lab();
    let mut still = recording(2, 30.0, 20.0, 0.002, 0.0);
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    for z in &mut still.z_m {
        *z = 0.002 * gauss(&mut rng);
    }
    let e = tune(&still, &paper_filter(), model, geometry).unwrap_err();
    assert!(matches!(e, TuneError::NoMotion { .. }), "{e}");
    assert!(e.to_string().contains("no swing"), "{e}");
    // A swing of the same length passes the same check.
    recording(2, 30.0, 20.0, 0.002, 0.0)
        .check_tunable()
        .unwrap();
}

#[test]
fn several_short_recordings_are_tuned_together() {
    // Four trials of 4 s each: too short alone, enough together.
    let (r_true, sigma_true) = (0.002, 0.01);
    let recs: Vec<Series> = (0..4)
        .map(|k| recording(20 + k, 30.0, 4.0, r_true, sigma_true))
        .collect();
    let (model, geometry) = lab();
    assert!(matches!(
        tune(&recs[0], &paper_filter(), model, geometry),
        Err(TuneError::TooShort(120))
    ));
    let report = tune_recordings(&recs, &paper_filter(), model, geometry).unwrap();
    assert_eq!(report.recordings, 4);
    assert_eq!(report.measurements, 480);
    let r_err = report.estimate.measurement_noise_m / r_true - 1.0;
    assert!(r_err.abs() < 0.2, "measurement noise off by {r_err}");
    assert!(
        report.consistency.nis_consistent,
        "{:?}",
        report.consistency
    );
}

#[test]
fn a_params_file_overlays_only_the_keys_it_sets() {
    let mut base = Scenario {
        name: "lab".into(),
        ..Scenario::default()
    };
    base.pendulum.length_m = 2.5;
    base.ekf.gate_nis = 16.0;
    let text = "[ekf]\nmeasurement_noise_m = 0.003\naccel_psd_rad2ps3 = 2e-7\n";
    let s = overlay_params(&base, text).unwrap();
    assert_eq!(s.ekf.measurement_noise_m, 0.003);
    assert_eq!(s.ekf.accel_psd_rad2ps3, 2e-7);
    assert_eq!(s.ekf.gate_nis, 16.0);
    assert_eq!(s.pendulum.length_m, 2.5);
    assert_eq!(s.name, "lab");
    // Bad files change nothing and say why.
    let e = overlay_params(&base, "[ekf]\nmeasurement_noise = 0.003\n").unwrap_err();
    assert!(e.to_string().contains("measurement_noise"), "{e}");
    let e = overlay_params(&base, "[ekf]\nmeasurement_noise_m = -1.0\n").unwrap_err();
    assert_eq!(e.field(), Some("ekf.measurement_noise_m"));
    let e = overlay_params_file(&base, Path::new("/nonexistent/p.toml")).unwrap_err();
    assert!(e.to_string().contains("/nonexistent/p.toml"), "{e}");
    // The tuned file round-trips through the overlay.
    let series = recording(3, 30.0, 20.0, 0.002, 0.01);
    let (model, geometry) = lab();
    let report = tune(&series, &paper_filter(), model, geometry).unwrap();
    let s = overlay_params(&base, &params_toml(&paper_filter(), &report)).unwrap();
    assert_eq!(
        s.ekf.measurement_noise_m,
        report.estimate.measurement_noise_m
    );
    assert_eq!(s.ekf.accel_var_rad2ps4, report.estimate.process_noise);
    assert_eq!(s.ekf.process_noise_model, ProcessNoiseModel::Paper);
    assert_eq!(s.pendulum.length_m, 2.5);
}

#[test]
fn bad_csv_names_the_line_and_column() {
    let e = Series::from_csv("t_s,x_m\n0.0,abc\n").unwrap_err();
    // The error keeps the line, the column and the cell.
    assert_eq!(
        e,
        TuneError::BadNumber {
            line: 2,
            column: "x_m".into(),
            raw: "abc".into(),
            parsed: false,
        }
    );
    let e = e.to_string();
    assert!(e.contains("line 2") && e.contains("x_m"), "{e}");
    let e = Series::from_csv("a,b\n1,2\n").unwrap_err().to_string();
    assert!(e.contains("measured_x_m"), "{e}");
    let e = Series::from_csv("t_s,x_m\n1.0,0.1\n0.5,0.1\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("goes back"), "{e}");
    assert_eq!(Series::from_csv(""), Err(TuneError::Empty));
}

#[test]
fn nis_bounds_match_chi_square_quantiles() {
    // chi2(100) 2.5% and 97.5% quantiles are 74.22 and 129.56.
    let [lo, hi] = nis_bounds_95(100);
    assert!((lo - 0.7422).abs() < 0.002, "{lo}");
    assert!((hi - 1.2956).abs() < 0.002, "{hi}");
}

#[test]
fn figure_has_every_panel_and_a_300_step_prediction() {
    let series = recording(5, 30.0, 15.0, 0.002, 0.001);
    let (model, geometry) = lab();
    let mut p = paper_filter();
    p.measurement_noise_m = 0.002;
    let d = fig4_data(&series, &p, model, geometry).unwrap();
    assert_eq!(d.prediction_t_s.len(), figure::PREDICTION_STEPS);
    assert_eq!(d.t_s.len(), d.estimate_deg.len());
    // The estimate follows the measured angle closely.
    let n = d.t_s.len();
    let rms = (d.measured_deg[n / 2..]
        .iter()
        .zip(&d.estimate_deg[n / 2..])
        .map(|(a, b)| (a - b).powi(2))
        .sum::<f64>()
        / (n - n / 2) as f64)
        .sqrt();
    assert!(rms < 0.1, "estimate rms {rms} deg");
}

/// A swing without process noise recorded at `fps` whose measurement errors
/// are correlated from frame to frame (AR(1) with lag-1 autocorrelation
/// `rho`, marginal std `r_std_m`), as a detector's on a fast camera.
fn recording_with_correlated_errors(
    seed: u64,
    fps: f64,
    duration_s: f64,
    r_std_m: f64,
    rho: f64,
    angle_deg: f64,
) -> Series {
    let (model, geometry) = lab();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut sim = PendulumSim::free(
        model,
        geometry,
        Vector2::new(angle_deg.to_radians(), 0.0),
        0.0,
    )
    .unwrap();
    let dt = 1.0 / fps;
    let mut e = r_std_m * gauss(&mut rng);
    let mut s = Series::default();
    for k in 0..(duration_s * fps) as usize {
        let t = k as f64 * dt;
        sim.advance_to(t).unwrap();
        s.t_s.push(t);
        s.z_m.push(sim.lateral_m() + e);
        e = rho * e + r_std_m * (1.0 - rho * rho).sqrt() * gauss(&mut rng);
    }
    s
}

#[test]
fn the_likelihood_stride_thins_fast_cameras_to_30_fps() {
    assert_eq!(likelihood_stride(1.0 / 30.0), 1);
    assert_eq!(likelihood_stride(1.0 / 15.0), 1);
    assert_eq!(likelihood_stride(1.0 / 60.0), 2);
    // 60 fps with a few frames lost (the service's recordings: 17.8 ms).
    assert_eq!(likelihood_stride(0.0178), 2);
    assert_eq!(likelihood_stride(1.0 / 120.0), 4);
    assert_eq!(likelihood_stride(f64::NAN), 1);
    let s = recording(1, 30.0, 1.0, 0.0, 0.0);
    let parts: Vec<Series> = (0..3).map(|o| s.thinned(3, o)).collect();
    assert_eq!(parts.iter().map(Series::len).sum::<usize>(), s.len());
    assert_eq!(parts[1].t_s[..2], [s.t_s[1], s.t_s[4]]);
}

/// Three short 60 fps trials whose detector errors are correlated from frame
/// to frame (lag-1 0.6) and no process noise, in 8 draws: the most likely fit
/// over every frame takes part of the errors for process noise (the filter
/// follows them): `accel_psd` 2-3e-6 in 4 draws of 8, more than the lab's
/// default 1e-6, with the measurement noise 16-19% low. Over every second
/// frame: at most 6e-8, and the measurement noise within 7%.
#[test]
fn correlated_errors_of_a_fast_camera_are_not_taken_for_process_noise() {
    let r_true = 0.0002;
    let (model, geometry) = lab();
    let filter = EkfParams {
        estimate_damping: false,
        ..EkfParams::default()
    };
    for draw in 0..8u64 {
        let recs: Vec<Series> = [24.0, 12.0, 18.0]
            .iter()
            .zip(0u64..)
            .map(|(&angle, i)| {
                recording_with_correlated_errors(100 + 10 * draw + i, 60.0, 3.0, r_true, 0.6, angle)
            })
            .collect();
        let report = tune_recordings(&recs, &filter, model, geometry).unwrap();
        let r_err = report.estimate.measurement_noise_m / r_true - 1.0;
        eprintln!(
            "draw {draw}, stride {}: R std {:.4} mm ({:+.1}%), accel_psd {:.3e}",
            report.stride,
            1e3 * report.estimate.measurement_noise_m,
            100.0 * r_err,
            report.estimate.process_noise,
        );
        assert_eq!(report.stride, 2);
        assert!(
            r_err.abs() < 0.12,
            "draw {draw}: measurement noise off by {r_err}"
        );
        assert!(
            report.estimate.process_noise < 3e-7,
            "draw {draw}: process noise {:e} from correlated errors alone",
            report.estimate.process_noise
        );
    }
}
