//! `lab.mode = "real"` of `isochron serve --config`: the same real-time runtime
//! with the drivers of the real lab, here pointed at stand-ins that speak the
//! same protocols: a KUKA controller (the simulated one, over UDP at the
//! configured address), a camera (a rendered MJPG video at the configured
//! device path) and the magnet board (the fake board behind a pty at the
//! configured port). The lab starts, the FRI session reaches
//! COMMANDING_ACTIVE, the snapshot shows the camera's detections and the
//! magnet answers.

use std::{
    net::{SocketAddr, UdpSocket},
    time::{Duration, Instant},
};

use rt_core::{
    bridge::{FriSessionState, MagnetState},
    params::Scenario,
    sim::camera::{BallState, SimCamera, SimCameraParams},
    sim::kuka::{FriSimParams, SimRunOptions, SimServer},
    sim::magnet::FakeDevice,
    vision::Recorder,
};
use server::{
    LabOptions,
    config::{LabMode, ServeConfig},
};

fn free_udp_port() -> SocketAddr {
    UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
}

#[test]
fn the_real_lab_config_runs_the_runtime_with_a_controller_a_video_camera_and_a_serial_magnet() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let scenario = Scenario::default();

    // The camera: a rendered video of the ball swinging at 0.6 m.
    let video = dir.join("pendulum.avi");
    // The camera that filmed it is where the config says (beside the
    // pivot's line and above the ball's rest height, as the simulated camera).
    let filmed = SimCameraParams::default();
    let pose = filmed.pose;
    let mut cam = SimCamera::new(
        &scenario.camera,
        &filmed,
        scenario.pendulum.ball_radius_m,
        1,
    )
    .unwrap();
    let mut rec = Recorder::create(&video, 1280, 720, 30.0).unwrap();
    for i in 0..60 {
        let y = 0.25 * (f64::from(i) * 0.15).sin();
        let ball = BallState::from_arrays([0.6, y, 0.30], [0.0, 0.0, 0.0]);
        rec.write(cam.render(Some(&ball)).unwrap()).unwrap();
    }
    rec.finish().unwrap();

    // The robot controller and the magnet board at their configured places.
    let client = free_udp_port();
    let robot = SimServer::spawn(
        FriSimParams::default(),
        SocketAddr::from(([127, 0, 0, 1], 0)),
        client,
        SimRunOptions {
            auto_command: true,
            duration: None,
            normal_priority: false,
            // A robot application that asks for commanding again when a late
            // answer (a busy machine) drops the session to MONITORING_READY.
            keep_commanding: true,
        },
    )
    .unwrap();
    // The board's answers may wait on a busy machine (the tests run four at
    // a time): the driver waits 2 s for one (its 300 ms default is the
    // magnet driver's own tests').
    let board = FakeDevice::start(dir.join("ttyMAGNET")).unwrap();

    let toml = format!(
        "[lab]\nmode = \"real\"\n\
         [fri]\nlocal_bind = \"{client}\"\ncontroller = \"{}\"\nperiod_ms = 5\n\
         [camera]\ndevice = \"{}\"\n\
         [magnet]\nport = \"{}\"\ncommand_timeout_ms = 2000.0\n\
         [calibration]\nfocal_length_px = 914.0\nprincipal_point_px = [640.0, 360.0]\n\
         plane_distance_m = 1.6\npivot_m = [0.6, 0.0, 2.23]\n\
         [calibration.camera_pose]\nposition_m = [{}, {}, {}]\n\
         yaw_deg = {}\npitch_deg = {}\nroll_deg = {}\n",
        robot.local_addr(),
        video.display(),
        board.path().display(),
        pose.position_m[0],
        pose.position_m[1],
        pose.position_m[2],
        pose.yaw_deg,
        pose.pitch_deg,
        pose.roll_deg,
    );
    let cfg = ServeConfig::from_toml_str(&toml).unwrap();
    assert_eq!(cfg.lab.mode, LabMode::Real);
    let setup = server::serve::real_lab(&cfg, scenario, 1).unwrap();
    let (lab, sim) = server::runtime::start_lab(setup, None, LabOptions::default()).unwrap();

    sim.wait_commanding(Duration::from_secs(10)).unwrap();
    assert!(
        robot
            .stats()
            .reached(rt_core::fri::SessionState::CommandingActive)
    );
    let deadline = Instant::now() + Duration::from_secs(30);
    let snap = loop {
        if let Some((s, _)) = lab.latest()
            && s.counters.measurements > 10
            && s.magnet != MagnetState::Unknown
            && s.fri.session == FriSessionState::CommandingActive
        {
            break s;
        }
        assert!(
            Instant::now() < deadline,
            "no detections, magnet state or commanding session: {:?}",
            lab.latest().map(|(s, _)| (s.counters, s.magnet, s.fri))
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    println!(
        "real lab: fri {:?}, {} measurements, last {:?}, magnet {:?}",
        snap.fri, snap.counters.measurements, snap.pendulum.measured, snap.magnet
    );
    assert!(snap.pendulum.measured.valid);
    assert!(
        snap.pendulum.measured.x_m.abs() < 0.5,
        "{:?}",
        snap.pendulum.measured
    );
    assert_eq!(snap.magnet, MagnetState::Off);
    // The lateral positions follow the filmed ball (y = 0.25 sin(0.15 i) m,
    // looped): both sides of the swing, never beyond it. A camera pose that
    // disagrees with the camera shifts or scales them.
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    let deadline = Instant::now() + Duration::from_secs(10);
    while !(lo < -0.2 && hi > 0.2) {
        assert!(
            Instant::now() < deadline,
            "measured lateral positions only span {lo:.3}..{hi:.3} m"
        );
        if let Some((s, _)) = lab.latest() {
            let x = s.pendulum.measured.x_m;
            assert!(x.abs() < 0.27, "lateral {x:.3} m beyond the filmed swing");
            lo = lo.min(x);
            hi = hi.max(x);
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    println!("real lab: measured lateral positions span {lo:.3}..{hi:.3} m");
    // The magnet goes through the driver on the configured port.
    sim.magnet().set_magnet(true).unwrap();
    assert!(board.magnet_on());
    lab.shutdown();
    drop(sim);
}

/// A lab's beliefs never hold a `[world]`: a parameter file with one is
/// refused at start with the reason and where a world is served (`serve
/// --scenario`, `isochron world`), before anything listens.
#[test]
fn serve_refuses_a_scenario_with_a_world_and_says_where_it_runs() {
    let Some(bin) = isochron_tests::isochron_bin(&[(&["serve", "--help"], "--params")]) else {
        return;
    };
    let reality =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/reality.toml");
    let dir = std::env::temp_dir().join(format!("isochron-serve-world-{}", std::process::id()));
    let out = std::process::Command::new(&bin)
        .args(["serve", "--bind", "127.0.0.1:0", "--data-dir"])
        .arg(&dir)
        .arg("--params")
        .arg(&reality)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(err.contains("isochron serve --scenario"), "{err}");
    assert!(
        !String::from_utf8_lossy(&out.stdout).contains("listening"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
