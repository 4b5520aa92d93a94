//! `isochron calibrate` as a user runs it: each step on the simulated world writes
//! its result into the calibration file (other steps kept), `trials --calibration`
//! loads it, and bad input writes nothing.

use crate::isochron;

fn temp_dir(tag: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("isochron-calib-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn calibrate(args: &[&str]) -> (bool, serde_json::Value, String) {
    let out = isochron().arg("calibrate").args(args).output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    let v = serde_json::from_str(stdout.trim()).unwrap_or(serde_json::Value::Null);
    (out.status.success(), v, stderr)
}

#[test]
fn steps_write_one_file_that_trials_load() {
    let dir = temp_dir("steps");
    let file = dir.join("calibration.toml");
    let f = file.to_str().unwrap();
    let (ok, v, err) = calibrate(&["latency", "--seed", "3", "--out", f, "--json"]);
    assert!(ok, "{err}");
    let e = v["error"]["camera_latency_ms"].as_f64().unwrap();
    assert!(e.abs() < 2.0, "camera latency error {e} ms: {v}");
    assert_eq!(v["source"], "simulated world (scenario paper, seed 3)");
    let (ok, v, err) = calibrate(&["robot", "--seed", "3", "--out", f, "--json"]);
    assert!(ok, "{err}");
    let e = v["error"]["robot_latency_ms"].as_f64().unwrap();
    assert!(e.abs() < 1.0, "robot latency error {e} ms: {v}");
    let text = std::fs::read_to_string(&file).unwrap();
    let cal = rt_core::calibration::CalibrationFile::from_toml_str(&text).unwrap();
    let latency = cal.latency.expect("the latency step is kept");
    let robot = cal.robot.expect("the robot step is written");
    assert!(latency.revision.contains("git"), "{}", latency.revision);
    assert!(
        latency.date.ends_with('Z') && latency.date.len() == 20,
        "{}",
        latency.date
    );
    assert!(text.contains("spread_ms") && text.contains("residual_rms_rad"));

    // trials lays it over the beliefs: the latency prior the controller starts from.
    let out = isochron()
        .args(["trials", "--scenario"])
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../scenarios/paper.toml"
        ))
        .args(["--n", "1", "--json", "--calibration", f])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(robot.result.servo_time_constant_ms > 0.0);

    // A broken calibration file is refused by trials, naming the key.
    std::fs::write(dir.join("bad.toml"), "[pendulum]\nlength = 2\n").unwrap();
    let out = isochron()
        .args(["trials", "--scenario"])
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../scenarios/paper.toml"
        ))
        .args(["--n", "1", "--calibration"])
        .arg(dir.join("bad.toml"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("length"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_input_writes_nothing() {
    let dir = temp_dir("bad");
    let file = dir.join("calibration.toml");
    let f = file.to_str().unwrap();
    // A swing too small to fit.
    let (ok, _, err) = calibrate(&["pendulum", "--release-deg", "1", "--out", f]);
    assert!(!ok);
    assert!(err.contains("swing too small"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(!file.exists(), "a refused step wrote the file");
    // The chessboard never in view.
    let (ok, _, err) = calibrate(&["camera", "--board-out-of-view", "--out", f]);
    assert!(!ok && err.contains("no board visible"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    let (ok, _, err) = calibrate(&["pendulum", "--release-deg", "nan", "--out", f]);
    assert!(!ok && err.contains("release-deg"), "{err}");
    assert!(!file.exists());
    // An existing file that does not parse is not overwritten.
    std::fs::write(&file, "[latency]\nbogus = 1\n").unwrap();
    let (ok, _, err) = calibrate(&["robot", "--out", f]);
    assert!(!ok && err.contains("bogus"), "{err}");
    assert_eq!(
        std::fs::read_to_string(&file).unwrap(),
        "[latency]\nbogus = 1\n"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// camera-robot on reality.toml: the camera's pose and the intercept point into
/// the file beside the other steps, `trials` lays it over the beliefs; a covered
/// marker is refused with the reason and the file is left as it was.
#[test]
fn camera_robot_writes_its_section_and_refuses_a_hidden_marker() {
    let dir = temp_dir("camera-robot");
    let file = dir.join("calibration.toml");
    let f = file.to_str().unwrap();
    let reality = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenarios/reality.toml");
    let (ok, _, err) = calibrate(&["latency", "--scenario", reality, "--out", f]);
    assert!(ok, "{err}");
    let before = std::fs::read_to_string(&file).unwrap();
    // Covered marker: refused, one line naming it, the file untouched.
    let (ok, _, err) = calibrate(&[
        "camera-robot",
        "--scenario",
        reality,
        "--hide-marker",
        "--out",
        f,
    ]);
    assert!(!ok);
    assert!(err.contains("marker never seen"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert_eq!(std::fs::read_to_string(&file).unwrap(), before);

    let (ok, v, err) = calibrate(&[
        "camera-robot",
        "--scenario",
        reality,
        "--seed",
        "2",
        "--out",
        f,
        "--json",
    ]);
    assert!(ok, "{err}");
    let e = &v["error"];
    assert!(e["camera_rotation_deg"].as_f64().unwrap() < 0.3, "{v}");
    assert!(e["camera_position_mm"].as_f64().unwrap() < 5.0, "{v}");
    assert!(e["intercept_mm"].as_f64().unwrap() < 3.0, "{v}");
    let cal = rt_core::calibration::CalibrationFile::from_file(&file).unwrap();
    assert!(cal.latency.is_some(), "the latency step is kept");
    let c = cal
        .camera_robot
        .clone()
        .expect("the camera-robot step is written");
    assert!(c.result.poses >= 12 && c.result.reprojection_rms_px < 1.0);
    let s = rt_core::params::Scenario::from_file(std::path::Path::new(reality)).unwrap();
    let applied = cal.apply(&s).unwrap();
    assert_eq!(applied.camera.pose, Some(c.result.camera_pose));
    assert_eq!(applied.task.intercept_offset_m, c.result.intercept_offset_m);

    let out = isochron()
        .args(["trials", "--scenario", reality])
        .args(["--n", "2", "--json", "--calibration", f])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// camera on reality.toml: the lens within the k1 target into the
/// file's `[camera]` section, which the lab's beliefs then carry.
#[test]
fn camera_writes_its_section() {
    let dir = temp_dir("camera");
    let file = dir.join("calibration.toml");
    let f = file.to_str().unwrap();
    let reality = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenarios/reality.toml");
    let (ok, v, err) = calibrate(&[
        "camera",
        "--scenario",
        reality,
        "--seed",
        "2",
        "--out",
        f,
        "--json",
    ]);
    assert!(ok, "{err}");
    let e = &v["error"];
    assert!(e["k1"].as_f64().unwrap().abs() <= 0.02, "{v}");
    assert!(e["fx_px"].as_f64().unwrap().abs() < 5.0, "{v}");
    assert!(e["cx_px"].as_f64().unwrap().abs() < 5.0, "{v}");
    let cal = rt_core::calibration::CalibrationFile::from_file(&file).unwrap();
    let c = cal.camera.clone().expect("the camera step is written");
    assert!(
        c.result.rms_px < 0.5 && c.result.views_used >= 16,
        "{:?}",
        c.result
    );
    let s = rt_core::params::Scenario::from_file(std::path::Path::new(reality)).unwrap();
    let applied = cal.apply(&s).unwrap();
    assert_eq!(applied.camera.intrinsics, Some(c.result.intrinsics));
    let _ = std::fs::remove_dir_all(&dir);
}
