//! `isochron tune` as a user runs it.

use rt_core::pendulum::{PendulumGeometry, PendulumModel, PendulumSim};

use crate::isochron;

fn temp_dir(tag: &str) -> std::path::PathBuf {
    tempfile::Builder::new()
        .prefix(&format!("isochron-tune-{tag}-"))
        .tempdir()
        .expect("a temporary directory")
        .keep()
}

/// 40 s of a 1.93 m pendulum at 30 fps with 2 mm of deterministic pseudo-noise.
fn write_recording(path: &std::path::Path) {
    let model = PendulumModel {
        length_m: 1.93,
        gravity_mps2: 9.81,
        damping_per_s: 0.03,
    };
    let geometry = PendulumGeometry::new(1.93, 0.6, 0.3).unwrap();
    let mut sim =
        PendulumSim::free(model, geometry, nalgebra::Vector2::new(0.4, 0.0), 0.0).unwrap();
    let mut seed: u64 = 12345;
    let mut uniform = || {
        seed = seed
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut text = String::from("t_s,x_m\n");
    for k in 0..1200 {
        let t = f64::from(k) / 30.0;
        sim.advance_to(t).unwrap();
        // Sum of 12 uniforms: approximately normal, std 1.
        let n: f64 = (0..12).map(|_| uniform()).sum::<f64>() - 6.0;
        text.push_str(&format!("{t},{}\n", sim.lateral_m() + 0.002 * n));
    }
    std::fs::write(path, text).unwrap();
}

#[test]
fn tune_writes_parameters_and_the_figure() {
    let dir = temp_dir("ok");
    let rec = dir.join("swing.csv");
    write_recording(&rec);
    let out = isochron()
        .args(["tune", "--json", "--recording"])
        .arg(&rec)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let j: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let r = j["estimate"]["measurement_noise_m"].as_f64().unwrap();
    assert!((r / 0.002 - 1.0).abs() < 0.2, "R std {r}");
    assert_eq!(j["measurements"], 1200);
    let params = std::fs::read_to_string(dir.join("swing.ekf.toml")).unwrap();
    assert!(params.contains("[ekf]") && params.contains("measurement_noise_m"));
    let svg = std::fs::read_to_string(dir.join("swing.fig4.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("Kalman gain"));
}

#[test]
fn tune_starts_from_the_scenarios_filter_and_keeps_its_other_settings() {
    let dir = temp_dir("scenario");
    let rec = dir.join("swing.csv");
    write_recording(&rec);
    let scenario = dir.join("lab.toml");
    std::fs::write(
        &scenario,
        "name = \"lab\"\n[ekf]\nprocess_noise_model = \"paper\"\nmeasurement_noise_m = 0.005\n\
         accel_var_rad2ps4 = 1e-4\ngate_nis = 16.0\nestimate_damping = false\n",
    )
    .unwrap();
    let out = isochron()
        .args(["tune", "--json", "--scenario"])
        .arg(&scenario)
        .arg("--recording")
        .arg(&rec)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let j: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    // The search started from the scenario's values, in its noise model.
    assert_eq!(j["before"]["measurement_noise_m"], 0.005);
    assert_eq!(j["before"]["process_noise"], 1e-4);
    assert_eq!(j["estimate"]["process_noise_param"], "accel_var_rad2ps4");
    let r = j["estimate"]["measurement_noise_m"].as_f64().unwrap();
    assert!((r / 0.002 - 1.0).abs() < 0.2, "R std {r}");
    // The file: the scenario's [ekf], the two estimates replaced.
    let text = std::fs::read_to_string(dir.join("swing.ekf.toml")).unwrap();
    let file: toml::Table = toml::from_str(&text).unwrap();
    let ekf = file["ekf"].as_table().unwrap();
    assert_eq!(ekf["process_noise_model"].as_str(), Some("paper"));
    assert_eq!(ekf["gate_nis"].as_float(), Some(16.0));
    assert_eq!(ekf["estimate_damping"].as_bool(), Some(false));
    assert_eq!(ekf["measurement_noise_m"].as_float(), Some(r));
    assert_ne!(ekf["accel_var_rad2ps4"].as_float(), Some(1e-4));
}

#[test]
fn tune_refuses_bad_recordings_with_one_line_and_writes_nothing() {
    let dir = temp_dir("bad");
    // 20 s of a ball hanging still, with 2 mm of noise.
    let mut still = String::from("t_s,x_m\n");
    for k in 0..600 {
        let n = f64::from((k * 7919) % 13) / 13.0 - 0.5;
        still.push_str(&format!("{},{}\n", f64::from(k) / 30.0, 0.004 * n));
    }
    let mut nan = std::fs::read_to_string({
        let p = dir.join("ok.csv");
        write_recording(&p);
        p
    })
    .unwrap();
    nan = nan.replacen("\n0.5,", "\nNaN,", 1);
    assert!(nan.contains("NaN,"));
    for (name, text, needle) in [
        ("cols.csv", "a,b\n1,2\n".to_owned(), "measured_x_m"),
        (
            "short.csv",
            "t_s,x_m\n0,0.1\n0.033,0.1\n".to_owned(),
            "at least",
        ),
        ("word.csv", "t_s,x_m\n0,zero\n".to_owned(), "line 2"),
        ("nan.csv", nan, "not a finite number"),
        ("still.csv", still, "no swing"),
        ("empty.csv", String::new(), "empty"),
    ] {
        let rec = dir.join(name);
        std::fs::write(&rec, text).unwrap();
        let out = isochron()
            .args(["tune", "--recording"])
            .arg(&rec)
            .output()
            .unwrap();
        assert!(!out.status.success(), "{name} accepted");
        let err = String::from_utf8_lossy(&out.stderr);
        let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("isochron:")).collect();
        assert_eq!(lines.len(), 1, "{err}");
        assert!(lines[0].contains(needle), "{name}: {err}");
        let stem = name.trim_end_matches(".csv");
        for written in [".ekf.toml", ".fig4.svg"] {
            let p = dir.join(format!("{stem}{written}"));
            assert!(
                !p.exists(),
                "{} written for a refused recording",
                p.display()
            );
        }
    }
    let out = isochron()
        .args(["tune", "--recording", "/nonexistent/rec.csv"])
        .output()
        .unwrap();
    assert!(!out.status.success());
}
