//! The calibration tour's moves through the control loop
//! (`server::calibration::move_to_pose`, the camera-robot step's poses) when
//! the robot leaves commanding during one: the controller ends the move where
//! it is, the lab asks the robot to command again, and the step sends the
//! move again once it does.

use std::sync::Arc;
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_move_cut_by_the_robot_leaving_commanding_is_sent_again_and_reaches_its_pose() {
    let (lab, runtime) =
        server::runtime::start_simulated(Scenario::default(), None, LabOptions::default(), 1)
            .unwrap();
    runtime.wait_commanding(Duration::from_secs(30)).unwrap();
    let robot = rt_core::sim::wall_lab::sim_server(&runtime).expect("the simulated controller");
    let s = wait_for(&lab, "commanding", Duration::from_secs(30), |s| {
        s.fri.session == FriSessionState::CommandingActive && s.counters.steps > 100
    })
    .await;
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
