use super::*;

/// Parses `text`, expecting a refusal that names `field`.
fn refused(text: &str, field: &str) {
    match Scenario::from_toml_str(text) {
        Ok(s) => panic!("accepted {text:?} as {s:?}"),
        Err(e) => {
            let shown = e.to_string();
            assert!(
                shown.contains(field),
                "error for {text:?} should name {field:?}, got {shown:?}"
            );
            assert!(!shown.contains('\n'), "one-line error expected: {shown:?}");
        }
    }
}

#[test]
fn defaults_are_the_papers_lab_and_valid() {
    let s = Scenario::default();
    s.validate().unwrap();
    assert_eq!(s.pendulum.length_m, 1.93);
    assert_eq!(s.task.movement_time_s, 1.5);
    assert_eq!(s.task.home_m, [0.30, 0.0, 0.50]);
    assert_eq!(s.camera.vision, VisionMode::Full);
    assert_eq!(s.robot.fri_period_ms, 5);
    assert_eq!(s.success.timing_tolerance_ms, 20.0);
}

#[test]
fn empty_file_gives_defaults() {
    assert_eq!(Scenario::from_toml_str("").unwrap(), Scenario::default());
}

#[test]
fn every_rule_names_its_field() {
    let cases: &[(&str, &str)] = &[
        ("name = \"\"", "name"),
        ("[pendulum]\nlength_m = -1.0", "pendulum.length_m"),
        ("[pendulum]\nlength_m = 0.0", "pendulum.length_m"),
        ("[pendulum]\nlength_m = nan", "pendulum.length_m"),
        ("[pendulum]\nlength_m = inf", "pendulum.length_m"),
        ("[pendulum]\ndamping_per_s = -0.1", "pendulum.damping_per_s"),
        ("[pendulum]\ngravity_mps2 = 0.0", "pendulum.gravity_mps2"),
        (
            "[pendulum]\nball_radius_m = -0.03",
            "pendulum.ball_radius_m",
        ),
        (
            "[pendulum]\nrelease_angle_deg = [35.0, 15.0]",
            "pendulum.release_angle_deg",
        ),
        (
            "[pendulum]\nrelease_angle_deg = [15.0, 95.0]",
            "pendulum.release_angle_deg",
        ),
        (
            "[pendulum]\nrelease_angle_deg = [15.0, nan]",
            "pendulum.release_angle_deg",
        ),
        ("[task]\ndistance_m = [0.8, 0.35]", "task.distance_m"),
        ("[task]\ndistance_m = -0.5", "task.distance_m"),
        (
            "[task]\nintercept_height_m = inf",
            "task.intercept_height_m",
        ),
        ("[task]\nhome_m = [0.3, nan, 0.5]", "task.home_m[1]"),
        ("[task]\ntool_length_m = -0.1", "task.tool_length_m"),
        (
            "[task]\ntool_contact_radius_m = -0.01",
            "task.tool_contact_radius_m",
        ),
        ("[task]\nmovement_time_s = 0.0", "task.movement_time_s"),
        ("[task]\nmovement_time_s = -1.5", "task.movement_time_s"),
        ("[task]\nstrike_speed_mps = 0.0", "task.strike_speed_mps"),
        ("[task]\nstrike_speed_mps = -1.0", "task.strike_speed_mps"),
        ("[task]\nstrike_speed_mps = nan", "task.strike_speed_mps"),
        ("[task]\nstrike_speed_mps = inf", "task.strike_speed_mps"),
        ("[task]\nstrike_speed_mps = 50.0", "task.strike_speed_mps"),
        (
            "[task]\nstrike_direction_deg = nan",
            "task.strike_direction_deg",
        ),
        (
            "[task]\nstrike_direction_deg = 90.0",
            "task.strike_direction_deg",
        ),
        (
            "[task]\nstrike_direction_deg = -61.0",
            "task.strike_direction_deg",
        ),
        ("[camera]\nfps = 0.0", "camera.fps"),
        ("[camera]\nwidth_px = 0", "camera.width_px"),
        ("[camera]\nheight_px = 1", "camera.height_px"),
        ("[camera]\nlatency_ms = -5.0", "camera.latency_ms"),
        ("[camera]\nimage_noise = 300.0", "camera.image_noise"),
        ("[camera]\ndrop_rate = 1.5", "camera.drop_rate"),
        ("[camera]\ndrop_rate = -0.1", "camera.drop_rate"),
        ("[camera]\ndrop_rate = 0.95", "camera.drop_rate"),
        ("[robot]\nfri_period_ms = 0", "robot.fri_period_ms"),
        ("[robot]\nfri_period_ms = 101", "robot.fri_period_ms"),
        ("[robot]\nlatency_ms = -1.0", "robot.latency_ms"),
        (
            "[robot]\nlatency_jitter_ms = nan",
            "robot.latency_jitter_ms",
        ),
        (
            "[success]\nposition_tolerance_m = 0.0",
            "success.position_tolerance_m",
        ),
        (
            "[success]\ntiming_tolerance_ms = -20.0",
            "success.timing_tolerance_ms",
        ),
        (
            "[success]\ncontact_pulse_ms = 0.0",
            "success.contact_pulse_ms",
        ),
        (
            "[success]\ncontact_pulse_ms = nan",
            "success.contact_pulse_ms",
        ),
        (
            "[success]\ntorque_lag_periods = -1.0",
            "success.torque_lag_periods",
        ),
        (
            "[world.pendulum]\ncontact_pulse_ms = [0.1, 4.0]",
            "world.pendulum.contact_pulse_ms",
        ),
        (
            "[world.pendulum]\ncontact_restitution = 1.5",
            "world.pendulum.contact_restitution",
        ),
        (
            "[world.pendulum]\ncontact_restitution = nan",
            "world.pendulum.contact_restitution",
        ),
        (
            "[world.robot]\ntorque_lag_periods = [1.0, 11.0]",
            "world.robot.torque_lag_periods",
        ),
    ];
    for (text, field) in cases {
        refused(text, field);
    }
}

#[test]
fn unknown_key_is_refused_with_its_name_and_line() {
    let text = "name = \"x\"\n[pendulum]\nlenght_m = 1.5\n";
    let e = Scenario::from_toml_str(text).unwrap_err();
    // The error keeps where (line and key) apart from the parser's message;
    // read from a file, it names the file too.
    let ParamError::Parse {
        path: None,
        line: Some(3),
        key: Some(key),
        message,
    } = &e
    else {
        panic!("{e:?}")
    };
    assert_eq!(key, "pendulum.lenght_m");
    assert!(message.contains("lenght_m"), "{message}");
    let in_file = e.clone().in_file(std::path::Path::new("/x/s.toml"));
    assert_eq!(
        in_file.to_string(),
        format!("/x/s.toml: line 3: pendulum.lenght_m: {message}")
    );
    let e = e.to_string();
    assert!(e.contains("lenght_m"), "{e}");
    assert!(e.contains("line 3"), "{e}");
    assert!(e.contains("pendulum.lenght_m"), "{e}");
    refused("[pendulum]\nlenght_m = 1.5", "lenght_m");
    refused("[cammera]\nfps = 30.0", "cammera");
}

#[test]
fn wrong_types_are_refused() {
    refused("[pendulum]\nlength_m = \"long\"", "pendulum.length_m");
    refused("[camera]\nvision = \"magic\"", "camera.vision");
    refused("[task]\nmode = \"smash\"", "task.mode");
    refused("[task]\nmode = 1", "task.mode");
    refused("[task]\nhome_m = [0.3, 0.0]", "home_m");
    refused("[camera]\nwidth_px = -1280", "width_px");
}

#[test]
fn a_single_number_is_a_fixed_range() {
    let s = Scenario::from_toml_str("[task]\ndistance_m = 0.7").unwrap();
    assert_eq!(s.task.distance_m, RangeParam::fixed(0.7));
}

#[test]
fn the_papers_scenario_file_round_trips() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml");
    let s = Scenario::from_file(&path).unwrap();
    assert_eq!(
        s,
        Scenario::default(),
        "paper.toml must state the paper's lab"
    );
    let again = Scenario::from_toml_str(&s.to_toml_string()).unwrap();
    assert_eq!(again, s);
}

#[test]
fn the_task_mode_is_stop_unless_asked_and_strike_round_trips() {
    assert_eq!(Scenario::default().task.mode, TaskMode::Stop);
    let s = Scenario::from_toml_str(
        "[task]\nmode = \"strike\"\nstrike_speed_mps = 0.8\nstrike_direction_deg = -10.0\n",
    )
    .unwrap();
    assert_eq!(s.task.mode, TaskMode::Strike);
    assert_eq!(s.task.strike_speed_mps, 0.8);
    assert_eq!(s.task.strike_direction_deg, -10.0);
    assert!(s.to_toml_string().contains("mode = \"strike\""));
    let again = Scenario::from_toml_str(&s.to_toml_string()).unwrap();
    assert_eq!(again, s);
    // JSON (`GET`/`PUT /api/params`) says the same.
    let json = serde_json::to_value(&s).unwrap();
    assert_eq!(json["task"]["mode"], "strike");
    let back: Scenario = serde_json::from_value(json).unwrap();
    assert_eq!(back, s);
}

#[test]
fn the_believed_restitution_is_zero_unless_asked_and_checked_by_name() {
    assert_eq!(Scenario::default().pendulum.contact_restitution, 0.0);
    let s = Scenario::from_toml_str("[pendulum]\ncontact_restitution = 0.4\n").unwrap();
    assert_eq!(s.pendulum.contact_restitution, 0.4);
    assert_eq!(s.beliefs().pendulum.contact_restitution, 0.4);
    for bad in ["1.5", "-0.1", "nan"] {
        let e = Scenario::from_toml_str(&format!("[pendulum]\ncontact_restitution = {bad}\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("pendulum.contact_restitution"), "{bad}: {e}");
    }
}

#[test]
fn missing_file_is_a_clear_error() {
    let e = Scenario::from_file(Path::new("/nonexistent/x.toml")).unwrap_err();
    assert!(e.to_string().contains("/nonexistent/x.toml"));
}

#[test]
fn the_new_scenario_sections_are_validated_by_name() {
    let field = |text: &str| Scenario::from_toml_str(text).unwrap_err().to_string();
    assert!(field("[control]\nguard_margin_deg = 100").contains("control.guard_margin_deg"));
    assert!(field("[ekf]\nmeasurement_noise_m = -1").contains("ekf.measurement_noise_m"));
    assert!(field("[timing]\nbogus = 1").contains("bogus"));
    let s = Scenario::from_toml_str("[control]\nhold_time_s = 0.5").unwrap();
    assert_eq!(s.control.hold_time_s, 0.5);
    let again = Scenario::from_toml_str(&s.to_toml_string()).unwrap();
    assert_eq!(again, s);
}

#[test]
fn the_controllers_beliefs_are_its_sections_and_refused_by_the_same_names() {
    // The default beliefs are the default scenario's.
    assert_eq!(
        Scenario::default().beliefs(),
        crate::control::Beliefs::default()
    );
    let mut s = Scenario::default();
    s.robot.fri_period_ms = 7;
    s.control.hold_time_s = 0.5;
    s.world = Some(world::WorldParams::default());
    let b = s.beliefs();
    assert_eq!(b.fri_period_ms, 7);
    assert_eq!(b.control, s.control);
    assert_eq!(
        (&b.pendulum, &b.task, &b.ekf, &b.timing),
        (&s.pendulum, &s.task, &s.ekf, &s.timing)
    );
    // A bad section the controller reads: the same error as the scenario's.
    for text in [
        "[pendulum]\nlength_m = -1",
        "[task]\nintercept_height_m = 9",
        "[robot]\nfri_period_ms = 0",
        "[robot]\nfri_period_ms = 101",
        "[ekf]\nmeasurement_noise_m = -1",
        "[control]\nhold_time_s = -1",
    ] {
        let s: Scenario = toml::from_str(text).unwrap();
        let whole = s.validate().unwrap_err().to_string();
        assert_eq!(
            s.beliefs().validate().unwrap_err().to_string(),
            whole,
            "{text}"
        );
        let c = crate::control::Controller::new(&s.beliefs(), 0.005).unwrap_err();
        assert_eq!(c.to_string(), whole, "{text}");
    }
}
