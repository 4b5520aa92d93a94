//! The real-lab calibration steps' motions when the robot leaves commanding
//! during one: the controller ends the motion where it is and the lab asks
//! the robot to command again. The camera-robot tour's moves
//! (`server::calibration::move_to_pose`) and the pendulum step's move home
//! are sent again once it does; the robot step fits what its excitation
//! recorded until then, or excites again when that was too little.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use rt_core::bridge::{FriSessionState, Snapshot};
use rt_core::params::Scenario;
use server::LabOptions;

/// The lab's latest snapshot once `ok` holds for it (polled every 10 ms).
async fn wait_for(
    lab: &server::Lab,
    what: &str,
    timeout: Duration,
    ok: impl Fn(&Snapshot) -> bool,
) -> Snapshot {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some((s, _)) = lab.latest()
            && ok(&s)
        {
            return s;
        }
        assert!(
            Instant::now() < deadline,
            "{what}: not within {timeout:?}; last {:?}",
            lab.latest()
                .map(|(s, _)| (s.fri, s.robot.q_cmd_rad, s.trial_state))
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// The wall-clock simulated lab once its robot commands, with its latest
/// state then.
async fn commanding_lab() -> (Arc<server::Lab>, rt_core::lab::LabRuntime, Snapshot) {
    let (lab, runtime) =
        server::runtime::start_simulated(Scenario::default(), None, LabOptions::default(), 1)
            .unwrap();
    runtime.wait_commanding(Duration::from_secs(30)).unwrap();
    let s = wait_for(&lab, "commanding", Duration::from_secs(30), |s| {
        s.fri.session == FriSessionState::CommandingActive && s.counters.steps > 100
    })
    .await;
    (lab, runtime, s)
}

/// Waits until the running step's message says `needle`.
async fn job_says(desk: &server::calibration::CalibrationDesk, needle: &str) {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let s = serde_json::to_value(desk.status().unwrap()).unwrap();
        if s["job"]["message"]
            .as_str()
            .is_some_and(|m| m.contains(needle))
        {
            return;
        }
        assert!(
            s["job"]["state"] == "running" && Instant::now() < deadline,
            "the step did not say `{needle}`: {s}"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_move_cut_by_the_robot_leaving_commanding_is_sent_again_and_reaches_its_pose() {
    let (lab, runtime, s) = commanding_lab().await;
    let robot = rt_core::sim::wall_lab::sim_server(&runtime).expect("the simulated controller");
    let start = s.robot.q_rad;
    // A1 turned by 1 rad: a slow move of several seconds.
    let mut target = start;
    target[0] += 1.0;
    let mover = {
        let lab = Arc::clone(&lab);
        tokio::spawn(async move { server::calibration::move_to_pose(&lab, &target).await })
    };
    wait_for(&lab, "the move under way", Duration::from_secs(30), |s| {
        s.robot.q_cmd_rad[0] > start[0] + 0.02
    })
    .await;
    robot.leave_commanding();
    let cut = wait_for(
        &lab,
        "the robot leaving commanding",
        Duration::from_secs(30),
        |s| s.fri.commanding_lost >= 1,
    )
    .await;
    assert!(
        cut.robot.q_cmd_rad[0] < target[0] - 0.05,
        "the move ended before the robot left commanding: {:?}",
        cut.robot.q_cmd_rad
    );
    // The controller ended the move where it was; the lab asks the robot to
    // command again (as an operator would), and the step sends the move again.
    let moved = tokio::time::timeout(Duration::from_secs(180), mover)
        .await
        .expect("move_to_pose returns")
        .unwrap();
    moved.expect("the move, sent again, reaches its pose");
    let end = lab.latest().unwrap().0;
    for (j, (q, t)) in end.robot.q_cmd_rad.iter().zip(&target).enumerate() {
        assert!(
            (q - t).abs() < 1e-9,
            "A{}: commanded {q}, target {t}",
            j + 1
        );
    }
    assert_eq!(end.fri.commanding_lost, 1, "{:?}", end.fri);
    lab.shutdown();
    drop(runtime);
}

/// The robot step's job once it ended: its status.
async fn job_end(desk: &server::calibration::CalibrationDesk) -> serde_json::Value {
    let deadline = Instant::now() + Duration::from_secs(180);
    loop {
        let s = serde_json::to_value(desk.status().unwrap()).unwrap();
        if s["job"]["state"] != "running" {
            return s;
        }
        assert!(Instant::now() < deadline, "the robot step did not end: {s}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// The robot step (`run_real_robot`) when the robot leaves commanding during
/// its excitation: cut after 1 s (too little to fit) it waits for commanding
/// and excites again; cut after 4 s it fits what was recorded until then.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_robot_step_fits_an_excitation_cut_late_and_excites_again_after_one_cut_early() {
    use server::calibration::{CalibrationDesk, REAL_ROBOT_MIN_S, Step, run_real_robot};
    let (lab, runtime, _) = commanding_lab().await;
    let robot = rt_core::sim::wall_lab::sim_server(&runtime).expect("the simulated controller");
    let tmp = tempfile::tempdir().unwrap();
    let desk = Arc::new(CalibrationDesk::new(
        tmp.path().join("calibration.toml"),
        Box::new(|_| None),
    ));
    // What says the machine starved the wall-clock loop (a reply after its
    // deadline or never, a send slot missed): the delay then truly varies.
    let starved = || {
        let st = robot.stats();
        st.late_replies.load(Ordering::Relaxed)
            + st.missing_replies.load(Ordering::Relaxed)
            + st.overruns.load(Ordering::Relaxed)
    };
    let starved_before = starved();
    let mut latencies = Vec::new();
    for (cut_after_s, lost) in [(1.0, 1), (REAL_ROBOT_MIN_S + 0.8, 2)] {
        let id = desk.claim(Step::Robot).unwrap();
        let step = {
            let (lab, desk) = (Arc::clone(&lab), Arc::clone(&desk));
            let scenario = Scenario::default();
            tokio::spawn(async move { run_real_robot(&lab, &desk, id, &scenario).await })
        };
        // The excitation's first state in the tap, then `cut_after_s` of it.
        let deadline = Instant::now() + Duration::from_secs(30);
        while lab.tap_len() == 0 {
            assert!(Instant::now() < deadline, "the excitation did not start");
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        let t0 = lab.latest().unwrap().0.t_s;
        wait_for(
            &lab,
            "the excitation under way",
            Duration::from_secs(30),
            |s| s.t_s >= t0 + cut_after_s,
        )
        .await;
        robot.leave_commanding();
        if cut_after_s < REAL_ROBOT_MIN_S {
            // The step says it excites again, and does once the lab
            // commands again.
            job_says(&desk, "again once it commands").await;
        }
        let s = job_end(&desk).await;
        step.await.unwrap();
        assert_eq!(s["job"]["state"], "done", "{s}");
        let message = s["job"]["message"].as_str().unwrap();
        let fitted_on_part = message.contains("the robot left commanding then");
        assert_eq!(
            fitted_on_part,
            cut_after_s >= REAL_ROBOT_MIN_S,
            "cut after {cut_after_s} s: {message}"
        );
        // What the lab believes from it: the delay and the servo lag together.
        let r = &s["job"]["result"];
        let latency =
            r["latency_ms"].as_f64().unwrap() + r["servo_time_constant_ms"].as_f64().unwrap();
        assert!(latency.is_finite() && latency > 0.0, "{s}");
        println!("robot step cut after {cut_after_s:.1} s: {message}");
        latencies.push((latency, r["latency_std_ms"].as_f64().unwrap()));
        assert_eq!(lab.latest().unwrap().0.fri.commanding_lost, lost);
        assert!(
            s["steps"]
                .as_array()
                .unwrap()
                .iter()
                .any(|x| x["name"] == "robot" && x["done"] == true),
            "the record is not written: {s}"
        );
    }
    // The part of an excitation measures the same robot as a whole one
    // (within 3 ms and the fits' 3 sigma), unless the machine starved the
    // loop meanwhile (its replies late or missing: that robot's delay moved).
    let [(a, sa), (b, sb)] = [latencies[0], latencies[1]];
    let starved_replies = starved() - starved_before;
    let tolerance = 3.0 + 3.0 * sa.hypot(sb);
    assert!(
        (a - b).abs() < tolerance || starved_replies > 0,
        "whole excitation {a:.2} ms, its first part {b:.2} ms (tolerance {tolerance:.2} ms; no \
         reply late or missing)"
    );
    println!(
        "whole excitation {a:.2} ms, its first part {b:.2} ms; replies late or missing, slots \
         missed: {starved_replies}"
    );
    lab.shutdown();
    drop(runtime);
}

/// The pendulum step's first move (the arm home, out of the swing) when the
/// robot leaves commanding on the way: sent home again once it commands.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_pendulum_steps_move_home_cut_by_the_robot_leaving_commanding_is_sent_again() {
    use rt_core::bridge::TrialState;
    use server::calibration::{CalibrationDesk, Step, run_real_pendulum};
    let (lab, runtime, s) = commanding_lab().await;
    let robot = rt_core::sim::wall_lab::sim_server(&runtime).expect("the simulated controller");
    // The arm away from home first: the way back takes seconds.
    let mut away = s.robot.q_rad;
    away[0] += 0.8;
    server::calibration::move_to_pose(&lab, &away)
        .await
        .expect("the arm moves away");
    let tmp = tempfile::tempdir().unwrap();
    let desk = Arc::new(CalibrationDesk::new(
        tmp.path().join("calibration.toml"),
        Box::new(|_| None),
    ));
    let id = desk.claim(Step::Pendulum).unwrap();
    let step = {
        let (lab, desk) = (Arc::clone(&lab), Arc::clone(&desk));
        tokio::spawn(async move {
            run_real_pendulum(&lab, &desk, id, &Scenario::default(), 10.0, None).await
        })
    };
    let deadline = Instant::now() + Duration::from_secs(30);
    while lab.latest().is_none_or(|(s, _)| {
        !(s.trial_state == TrialState::Arming && (s.robot.q_cmd_rad[0] - away[0]).abs() > 0.05)
    }) {
        assert!(
            Instant::now() < deadline,
            "the arm does not move home: {:?}",
            desk.status().unwrap().job
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    robot.leave_commanding();
    wait_for(
        &lab,
        "the move home stopped",
        Duration::from_secs(30),
        |s| s.fri.commanding_lost >= 1,
    )
    .await;
    // The step says so and sends the arm home again; it gets there.
    job_says(&desk, "sending it home again").await;
    let home = wait_for(&lab, "the arm home", Duration::from_secs(60), |s| {
        s.trial_state == TrialState::Armed
    })
    .await;
    assert_eq!(home.fri.commanding_lost, 1, "{:?}", home.fri);
    assert!(
        (home.robot.q_cmd_rad[0] - away[0]).abs() > 0.3,
        "A1 did not go home: {:?}",
        home.robot.q_cmd_rad
    );
    // The rest of the step (the swing of a ball no one hung) is not this
    // test's: it ends as it ends.
    tokio::time::timeout(Duration::from_secs(120), step)
        .await
        .expect("the pendulum step ends")
        .unwrap();
    lab.shutdown();
    drop(runtime);
}
