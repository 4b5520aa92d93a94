//! `isochron calibrate` as a user runs it: each step on a scenario's world,
//! through a real lab's service (the world's cabinet, webcam and magnet
//! board behind the interfaces a real lab has), writes its result into the
//! calibration file (other steps kept), `trials --calibration` loads it, and
//! bad input writes nothing.

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

/// The magnet firmware the world's board runs (`make firmware`).
fn assert_firmware_built() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../firmware/magnet/build");
    assert!(
        dir.join("magnet.elf").is_file() && dir.join("magnet-sim").is_file(),
        "the magnet firmware is not built in {} (make firmware)",
        dir.display()
    );
}

/// The robot and latency steps on the paper's truthful world, one after the
/// other into one file: each against the world's truth (the robot's delay
/// within 3 ms; the latency never earlier than the webcam delivered its
/// frames), both kept, stamped with where they were measured, and loaded by
/// `trials --calibration`. On a starved machine the latency step may refuse
/// (its frames too irregular to time the LED, "calibrate when it is
/// quieter", after three tries): then it must have written nothing.
#[test]
fn steps_write_one_file_that_trials_load() {
    assert_firmware_built();
    let dir = temp_dir("steps");
    let file = dir.join("calibration.toml");
    let f = file.to_str().unwrap();
    let source = "simulated world (scenario paper, seed 3) behind a real lab's interfaces";
    let (ok, v, err) = calibrate(&["robot", "--seed", "3", "--out", f, "--json"]);
    assert!(ok, "{err}");
    let e = v["error"]["robot_delay_ms"].as_f64().unwrap();
    assert!(e.abs() < 3.0, "robot delay error {e} ms: {v}");
    assert_eq!(v["source"], source);
    assert!(v["truth"]["robot_delay_ms"].as_f64().unwrap() > 0.0, "{v}");
    let robot_only = std::fs::read_to_string(&file).unwrap();
    let (ok, v, err) = calibrate(&["latency", "--seed", "3", "--out", f, "--json"]);
    if !ok {
        assert!(err.contains("arrive too irregularly"), "{err}");
        assert_eq!(
            std::fs::read_to_string(&file).unwrap(),
            robot_only,
            "a refused step changed the file"
        );
        println!("the latency step refused on a starved machine: {err}");
        let _ = std::fs::remove_dir_all(&dir);
        return;
    }
    let e = v["error"]["camera_latency_ms"].as_f64().unwrap();
    // The stream's transport and the lab's decoding come on top of what the
    // webcam delivered (a few ms quiet, more on a loaded machine).
    assert!(e > -2.0, "camera latency error {e} ms: {v}");
    assert_eq!(v["source"], source);
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
    assert_eq!(robot.source, source);
    assert_eq!(latency.source, source);
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

/// Refusals write nothing: a swing too small (the world's operator hangs
/// the ball 1 degree aside; the service refuses it), a step whose
/// prerequisites are not in the file, arguments out of range, a file that
/// does not parse (not overwritten). Each a single line naming what.
#[test]
fn bad_input_writes_nothing() {
    assert_firmware_built();
    let dir = temp_dir("bad");
    let file = dir.join("calibration.toml");
    let f = file.to_str().unwrap();
    // A swing too small to fit.
    let (ok, _, err) = calibrate(&["pendulum", "--release-deg", "1", "--out", f]);
    assert!(!ok);
    assert!(err.contains("swing too small"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(!file.exists(), "a refused step wrote the file");
    // The camera-robot step needs the lens and the rest point first.
    let (ok, _, err) = calibrate(&["camera-robot", "--out", f]);
    assert!(!ok && err.contains("camera and pendulum"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    let (ok, _, err) = calibrate(&["pendulum", "--release-deg", "nan", "--out", f]);
    assert!(!ok && err.contains("release-deg"), "{err}");
    let (ok, _, err) = calibrate(&["robot", "--release-deg", "20", "--out", f]);
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

/// The contact step on a world whose robot shows a contact 3 FRI periods
/// (15 ms) late with an 8 ms force pulse, while the lab believes 1 period
/// and 4 ms (the measured judge would subtract 7 ms from the pulse's centre
/// where 19 ms are due): after the pendulum step (refused before it), the
/// knocks on the hanging ball learn the sum within 5 ms of the world's,
/// without the camera's clock; the
/// file holds it, stamped with its world, and `trials --calibration` loads
/// it. On a starved machine the robot may leave commanding mid-knock: then
/// the step refuses, saying so, and writes nothing.
#[test]
fn the_contact_step_learns_how_late_the_torques_show_a_contact() {
    assert_firmware_built();
    let dir = temp_dir("contact");
    let scenario = dir.join("contact.toml");
    let paper = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../scenarios/paper.toml"
    ))
    .unwrap()
    .replace("name = \"paper\"", "name = \"contact\"");
    assert!(paper.contains("name = \"contact\""));
    std::fs::write(
        &scenario,
        format!(
            "{paper}\n[world.robot]\ntorque_lag_periods = 3.0\n\n[world.pendulum]\n\
             contact_pulse_ms = 8.0\n"
        ),
    )
    .unwrap();
    let file = dir.join("calibration.toml");
    let f = file.to_str().unwrap();
    let s = scenario.to_str().unwrap();
    // It needs the pendulum's frequency: refused without, nothing written.
    let (ok, _, err) = calibrate(&["contact", "--scenario", s, "--out", f]);
    assert!(!ok && err.contains("pendulum"), "{err}");
    assert!(!file.exists());
    let (ok, _, err) = calibrate(&["pendulum", "--scenario", s, "--seed", "1", "--out", f]);
    if !ok {
        // A machine starved three times over: its frames came too late to
        // stamp (the step says so), nothing written.
        assert!(err.contains("arrive too irregularly"), "{err}");
        assert!(!file.exists(), "a refused step wrote the file");
        println!("the pendulum step refused on a starved machine: {err}");
        let _ = std::fs::remove_dir_all(&dir);
        return;
    }
    let pendulum_only = std::fs::read_to_string(&file).unwrap();
    let (ok, v, err) = calibrate(&[
        "contact",
        "--scenario",
        s,
        "--seed",
        "1",
        "--out",
        f,
        "--json",
    ]);
    if !ok {
        assert!(
            err.contains("left commanding") || err.contains("was interrupted"),
            "{err}"
        );
        assert_eq!(
            std::fs::read_to_string(&file).unwrap(),
            pendulum_only,
            "a refused step changed the file"
        );
        println!("the contact step refused on a starved machine: {err}");
        let _ = std::fs::remove_dir_all(&dir);
        return;
    }
    assert_eq!(v["truth"]["onset_offset_ms"].as_f64(), Some(19.0), "{v}");
    // Within 5 ms of the world's 19 (the beliefs are 12 ms off; the step's
    // target is 3 ms, its three knocks' spread on a busy machine about 2).
    let e = v["error"]["onset_offset_ms"].as_f64().unwrap();
    assert!(e.abs() < 5.0, "onset offset error {e} ms: {v}");
    let speed = v["result"]["knock_speed_mps"].as_f64().unwrap();
    assert!(speed > 0.1 && speed < 1.0, "knock speed {speed} m/s: {v}");
    let cal = rt_core::calibration::CalibrationFile::from_file(&file).unwrap();
    let contact = cal.contact.clone().expect("the contact step is written");
    assert!(
        contact.source.contains("scenario contact"),
        "{}",
        contact.source
    );
    // Laid over the beliefs: lag and half the pulse add up to what it learned.
    let beliefs = cal
        .apply(
            &rt_core::params::Scenario::from_toml_str(&std::fs::read_to_string(&scenario).unwrap())
                .unwrap(),
        )
        .unwrap();
    let sum = beliefs.success.torque_lag_periods * f64::from(beliefs.robot.fri_period_ms)
        + 0.5 * beliefs.success.contact_pulse_ms;
    assert!(
        (sum - contact.result.onset_offset_ms).abs() < 1e-6,
        "{sum} vs {contact:?}"
    );
    let out = isochron()
        .args([
            "trials",
            "--scenario",
            s,
            "--n",
            "1",
            "--json",
            "--calibration",
            f,
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let _ = std::fs::remove_dir_all(&dir);
}
