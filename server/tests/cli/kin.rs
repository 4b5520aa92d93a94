//! `isochron kin fk|ik|plan` as a user runs it.

use std::io::Write;
use std::process::{Output, Stdio};

use serde_json::Value;

use crate::isochron;

/// Runs `isochron kin <args>` with `input` on stdin.
fn kin(args: &[&str], input: &str) -> Output {
    let mut child = isochron()
        .arg("kin")
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    child
        .stdin
        .take()
        .unwrap()
        .write_all(input.as_bytes())
        .unwrap();
    child.wait_with_output().unwrap()
}

fn json_lines(out: &Output) -> Vec<Value> {
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

const LIMITS_DEG: [f64; 7] = [170.0, 120.0, 170.0, 120.0, 170.0, 120.0, 175.0];

fn within_limits(q: &[Value]) -> bool {
    q.len() == 7
        && q.iter()
            .zip(LIMITS_DEG)
            .all(|(v, l)| v.as_f64().unwrap().abs() <= l.to_radians())
}

#[test]
fn fk_prints_the_check_pose_of_iiwa7_md() {
    let out = kin(
        &["fk"],
        "0, 0.5235987755982988, 0, -1.0471975511965976, 0, 1.5707963267948966, 0\n0 0 0 0 0 0 0\n",
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines = json_lines(&out);
    assert_eq!(lines.len(), 2);
    let p = lines[0]["p_m"].as_array().unwrap();
    let want = [0.6, 0.0, 0.560_410_162];
    for (a, b) in p.iter().zip(want) {
        assert!((a.as_f64().unwrap() - b).abs() < 1e-9);
    }
    assert!((lines[0]["R"][2][2].as_f64().unwrap() + 1.0).abs() < 1e-12);
    assert!((lines[1]["p_m"][2].as_f64().unwrap() - 1.266).abs() < 1e-12);
}

#[test]
fn ik_solves_reachable_poses_and_refuses_unreachable_ones_without_a_solution() {
    let input = concat!(
        r#"{"p_m":[0.6,0,0.560410162],"R":[[-1,0,0],[0,1,0],[0,0,-1]]}"#,
        "\n",
        r#"{"p_m":[1.5,0,0.3],"R":[[-1,0,0],[0,1,0],[0,0,-1]]}"#,
        "\n",
        // Reachable only with A4 beyond its limit (wrist 0.2 m from the shoulder).
        r#"{"p_m":[0.2,0,0.466],"R":[[1,0,0],[0,1,0],[0,0,1]]}"#,
        "\n",
        r#"{"p_m":[0.5,0.1,0.4],"R":[[-1,0,0],[0,1,0],[0,0,-1]],"seed_rad":[0,0.5,0,-1.4,0,1.2,0]}"#,
        "\n",
    );
    let out = kin(&["ik"], input);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines = json_lines(&out);
    assert_eq!(lines.len(), 4);
    for i in [0, 3] {
        assert_eq!(lines[i]["ok"], true, "{}", lines[i]);
        assert!(within_limits(lines[i]["q_rad"].as_array().unwrap()));
        assert!(lines[i]["pos_err_m"].as_f64().unwrap() < 1e-9);
        assert!(lines[i]["rot_err_rad"].as_f64().unwrap() < 1e-9);
    }
    for i in [1, 2] {
        assert_eq!(lines[i]["ok"], false, "{}", lines[i]);
        assert!(lines[i]["q_rad"].is_null());
        assert!(!lines[i]["reason"].as_str().unwrap().is_empty());
    }
    assert!(
        lines[1]["reason"]
            .as_str()
            .unwrap()
            .contains("out of reach")
    );
    assert!(lines[2]["reason"].as_str().unwrap().contains("A4"));
    // The seeded answer continues the seed's configuration.
    let q = lines[3]["q_rad"].as_array().unwrap();
    assert!(q[3].as_f64().unwrap() < 0.0 && q[1].as_f64().unwrap() > 0.0);
}

#[test]
fn malformed_lines_are_named_and_fail_the_run() {
    let input = concat!(
        "not json\n",
        r#"{"p_m":[0.6,0,0.5],"R":[[1,0,0],[0,2,0],[0,0,1]]}"#,
        "\n",
        r#"{"p_m":[0.6,0,0.5],"R":[[-1,0,0],[0,1,0],[0,0,-1]],"oops":1}"#,
        "\n",
        r#"{"p_m":[0.6,0,0.560410162],"R":[[-1,0,0],[0,1,0],[0,0,-1]]}"#,
        "\n",
    );
    let out = kin(&["ik"], input);
    assert!(!out.status.success());
    let lines = json_lines(&out);
    assert_eq!(lines.len(), 4);
    assert!(
        lines[0]["error"]
            .as_str()
            .unwrap()
            .starts_with("line 1: bad JSON")
    );
    assert!(
        lines[1]["error"]
            .as_str()
            .unwrap()
            .contains("not a rotation")
    );
    assert!(lines[2]["error"].as_str().unwrap().contains("oops"));
    assert_eq!(lines[3]["ok"], true);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(err.contains("3 malformed"), "{err}");
    let out = kin(&["fk"], "1 2 3 x 5 6 7\n");
    assert!(!out.status.success());
    assert!(
        json_lines(&out)[0]["error"]
            .as_str()
            .unwrap()
            .contains("\"x\"")
    );
}

#[test]
fn plan_reports_the_posture_and_refuses_too_short_a_duration() {
    let out = kin(&["plan", "--distance-m", "0.8", "--json"], "");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    for key in [
        "feasible",
        "distance_m",
        "movement_time_s",
        "tilt_deg",
        "arm_angle_deg",
        "speed_ratio",
        "binding_joint",
        "min_margin_deg",
        "shortest_feasible_s",
    ] {
        assert!(v.get(key).is_some(), "{key} missing in {v}");
    }
    assert_eq!(v["feasible"], true);
    assert_eq!(v["binding_joint"], "A4");
    assert!(v["min_margin_deg"].as_f64().unwrap() >= 5.0);
    let worst = v["speed_ratio"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .fold(0.0, f64::max);
    assert!(worst <= 0.9);

    let out = kin(
        &[
            "plan",
            "--distance-m",
            "0.8",
            "--movement-time-s",
            "1.2",
            "--json",
        ],
        "",
    );
    assert!(!out.status.success());
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["feasible"], false);
    let shortest = v["shortest_feasible_s"].as_f64().unwrap();
    assert!((shortest - 1.34).abs() < 0.02, "{shortest}");
    assert!(v["reason"].as_str().unwrap().contains("A4"));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("infeasible"), "{err}");

    let out = kin(&["plan", "--distance-m", "nan"], "");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--distance-m"));
}

#[test]
fn plan_strike_prints_the_largest_feasible_strike_speed_and_refuses_a_faster_one() {
    let out = kin(&["plan", "--distance-m", "0.7", "--strike", "--json"], "");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v = &json_lines(&out)[0];
    assert_eq!(v["mode"], "strike");
    let vmax = v["largest_speed_mps"].as_f64().unwrap();
    assert!(vmax > 0.1, "{v}");
    let best = &v["largest"];
    assert_eq!(best["feasible"], true);
    assert!((best["speed_mps"].as_f64().unwrap() - vmax).abs() < 1e-9);
    // Contact at the movement time; every joint within its speed and torque share.
    assert!((best["contact_s"].as_f64().unwrap() - 1.5).abs() < 1e-9);
    for r in best["speed_ratio"].as_array().unwrap() {
        assert!(r.as_f64().unwrap() <= 0.9 + 1e-9);
    }
    for r in best["torque_ratio"].as_array().unwrap() {
        assert!(r.as_f64().unwrap() <= 0.8);
    }
    assert!(v["binding"].is_string(), "what binds a faster stroke: {v}");

    // Half the largest speed is feasible (exit 0); twice it is refused.
    let half = format!("{:.3}", vmax / 2.0);
    let ok = kin(
        &[
            "plan",
            "--distance-m",
            "0.7",
            "--strike",
            "--strike-speed-mps",
            &half,
        ],
        "",
    );
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let twice = format!("{:.3}", (vmax * 2.0).min(2.9));
    let refused = kin(
        &[
            "plan",
            "--distance-m",
            "0.7",
            "--strike",
            "--strike-speed-mps",
            &twice,
        ],
        "",
    );
    assert!(!refused.status.success());
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("infeasible strike"),
        "{}",
        String::from_utf8_lossy(&refused.stderr)
    );
    // Bad input: a clear error, no plan.
    for bad in [
        ["--strike-speed-mps", "NaN"],
        ["--strike-direction-deg", "90"],
    ] {
        let out = kin(
            &["plan", "--distance-m", "0.7", "--strike", bad[0], bad[1]],
            "",
        );
        assert!(!out.status.success(), "{bad:?}");
        assert!(out.stdout.is_empty(), "{bad:?}");
        assert!(
            String::from_utf8_lossy(&out.stderr).contains(bad[0].trim_start_matches('-')),
            "{bad:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
}
