use std::sync::{Arc, atomic::Ordering};
use std::time::{Duration, Instant};

use super::*;
use crate::params::Scenario;

fn snap(seq: u64) -> Snapshot {
    let mut s = Snapshot {
        seq,
        t_s: seq as f64 * 1e-3,
        ..Snapshot::default()
    };
    // Every field derived from seq: a torn read would mix two steps.
    s.robot.q_rad = [seq as f64; 7];
    s.pendulum.x_m = seq as f64;
    s.counters.steps = seq;
    s
}

fn consistent(s: &Snapshot) -> bool {
    s.robot.q_rad.iter().all(|&q| q == s.seq as f64)
        && s.pendulum.x_m == s.seq as f64
        && s.counters.steps == s.seq
}

#[test]
fn latest_value_is_the_last_published() {
    let (mut c, mut s) = bridge(BridgeCapacity::default());
    assert!(!s.latest.updated());
    assert_eq!(s.latest.read().seq, 0);
    for i in 1..=5 {
        c.publish(&snap(i));
    }
    assert!(s.latest.updated());
    assert_eq!(s.latest.read().seq, 5);
    assert!(!s.latest.updated());
    assert_eq!(s.stats.read().published, 5);
}

#[test]
fn a_full_telemetry_ring_is_counted_not_waited_on() {
    let cap = BridgeCapacity {
        telemetry: 8,
        ..BridgeCapacity::default()
    };
    let (mut c, mut s) = bridge(cap);
    for i in 1..=13 {
        c.publish(&snap(i));
    }
    assert_eq!(s.stats.read().telemetry_overflows, 5);
    // The oldest eight were kept, in order; the latest value is still the newest.
    let got: Vec<u64> = std::iter::from_fn(|| s.telemetry.pop())
        .map(|x| x.seq)
        .collect();
    assert_eq!(got, (1..=8).collect::<Vec<_>>());
    assert_eq!(s.latest.read().seq, 13);
}

#[test]
fn events_overflow_is_counted() {
    let cap = BridgeCapacity {
        events: 2,
        ..BridgeCapacity::default()
    };
    let (mut c, mut s) = bridge(cap);
    let ev = |to| EventRecord {
        t_s: 1.0,
        trial_id: 3,
        event: Event::StateChanged {
            from: TrialState::Idle,
            to,
        },
    };
    assert!(c.emit(ev(TrialState::Arming)));
    assert!(c.emit(ev(TrialState::Armed)));
    assert!(!c.emit(ev(TrialState::Released)));
    assert_eq!(s.stats.read().event_overflows, 1);
    assert_eq!(s.events.pop(), Some(ev(TrialState::Arming)));
    assert_eq!(s.events.pop(), Some(ev(TrialState::Armed)));
    assert_eq!(s.events.pop(), None);
}

#[test]
fn commands_are_acknowledged_by_id_and_old_params_come_back() {
    let (mut c, mut s) = bridge(BridgeCapacity::default());
    let a = s.commands.send(Command::Arm).unwrap();
    let mut new = Scenario::default();
    new.task.movement_time_s = 1.2;
    let b = s
        .commands
        .send(Command::SetParams(Box::new(new.clone())))
        .unwrap();
    assert_ne!(a, b);

    // The control side: refuse the first, swap in the second.
    let mut current = Box::new(Scenario::default());
    let first = c.next_command().unwrap();
    assert_eq!((first.id, first.command), (a, Command::Arm));
    assert!(c.ack(first.id, Err(Refusal::ChecksFailed), None));
    let second = c.next_command().unwrap();
    let Command::SetParams(p) = second.command else {
        panic!("expected SetParams")
    };
    let old = std::mem::replace(&mut current, p);
    assert!(c.ack(second.id, Ok(()), Some(old)));
    assert!(c.next_command().is_none());
    assert_eq!(current.task.movement_time_s, 1.2);

    let ack1 = s.acks.pop().unwrap();
    assert_eq!((ack1.id, ack1.outcome), (a, Err(Refusal::ChecksFailed)));
    let ack2 = s.acks.pop().unwrap();
    assert_eq!((ack2.id, ack2.outcome), (b, Ok(())));
    assert_eq!(ack2.returned.unwrap().task.movement_time_s, 1.5);
}

#[test]
fn a_full_command_ring_hands_the_command_back() {
    let cap = BridgeCapacity {
        commands: 2,
        ..BridgeCapacity::default()
    };
    let (_c, mut s) = bridge(cap);
    s.commands.send(Command::Arm).unwrap();
    s.commands.send(Command::Disarm).unwrap();
    assert_eq!(s.commands.send(Command::Stop), Err(Command::Stop));
    assert_eq!(s.stats.read().command_overflows, 1);
}

#[test]
fn abandoned_control_end_is_visible() {
    let (c, s) = bridge(BridgeCapacity::default());
    assert!(!s.commands.is_abandoned());
    drop(c);
    assert!(s.commands.is_abandoned());
}

/// Two real threads: the reader never sees a torn snapshot, sees the sequence
/// only move forward, and the recorder gets every published snapshot in order
/// except exactly the counted overflows.
#[test]
fn across_threads_snapshots_are_whole_and_nothing_is_lost_uncounted() {
    const N: u64 = 50_000;
    let cap = BridgeCapacity {
        telemetry: 64,
        ..BridgeCapacity::default()
    };
    let (mut c, mut s) = bridge(cap);
    let producer = std::thread::Builder::new()
        .name("isochron-test-control".into())
        .spawn(move || {
            for i in 1..=N {
                c.publish(&snap(i));
            }
            c
        })
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut last_latest = 0;
    let mut last_tele = 0;
    let mut received = 0u64;
    loop {
        let l = *s.latest.read();
        assert!(consistent(&l), "torn snapshot {l:?}");
        assert!(l.seq >= last_latest);
        last_latest = l.seq;
        while let Some(t) = s.telemetry.pop() {
            assert!(consistent(&t));
            assert!(t.seq > last_tele, "out of order");
            last_tele = t.seq;
            received += 1;
        }
        if producer.is_finished() && s.telemetry.is_empty() {
            break;
        }
        assert!(Instant::now() < deadline, "producer did not finish");
        std::thread::yield_now();
    }
    let _c = producer.join().unwrap();
    assert_eq!(s.latest.read().seq, N);
    let stats = s.stats.read();
    assert_eq!(stats.published, N);
    assert_eq!(received + stats.telemetry_overflows, N);
}

#[test]
fn frames_drop_when_full_and_are_counted() {
    let stats = Arc::new(BridgeStats::default());
    let (mut tx, mut rx) = frame_channel(2, Arc::clone(&stats));
    for i in 0..4u64 {
        tx.send(Frame {
            frame: i + 1,
            t_us: i,
            jpeg: vec![0xff, 0xd8],
        });
    }
    assert_eq!(stats.frame_overflows.load(Ordering::Relaxed), 2);
    assert_eq!(rx.pop().map(|f| f.t_us), Some(0));
    assert_eq!(rx.pop().map(|f| f.t_us), Some(1));
    assert_eq!(rx.pop(), None);
}

#[test]
fn horizon_is_bounded_and_serialises_only_its_points() {
    let mut s = Snapshot::default();
    for i in 0..HORIZON_POINTS + 3 {
        let pushed = s.pendulum.horizon.push(HorizonPoint {
            t_s: i as f64,
            x_m: 0.1,
            sigma_m: 0.01,
        });
        assert_eq!(pushed, i < HORIZON_POINTS);
    }
    s.pendulum.horizon.len = 3;
    let j = serde_json::to_value(s).unwrap();
    assert_eq!(j["pendulum"]["horizon"].as_array().unwrap().len(), 3);
    assert_eq!(j["pendulum"]["horizon"][2]["t_s"], 2.0);
}

#[test]
fn snapshot_json_uses_snake_case_and_null_for_unknown() {
    let mut s = Snapshot {
        trial_state: TrialState::Intercepting,
        ..Snapshot::default()
    };
    s.fri.session = FriSessionState::CommandingActive;
    let j = serde_json::to_value(s).unwrap();
    assert_eq!(j["trial_state"], "intercepting");
    assert_eq!(j["fri"]["session"], "commanding_active");
    assert_eq!(j["magnet"], "unknown");
    assert!(j["path"]["arrival_t_s"].is_null(), "NaN is null");
    assert_eq!(j["robot"]["q_rad"].as_array().unwrap().len(), 7);
    for key in [
        "pendulum", "hopf", "path", "robot", "fri", "timing", "counters",
    ] {
        assert!(j[key].is_object(), "{key}");
    }
    let ev = EventRecord {
        t_s: 2.0,
        trial_id: 1,
        event: Event::Aborted {
            reason: AbortKind::CameraLost,
            detail: "no frame for 0.5 s",
        },
    };
    let j = serde_json::to_value(ev).unwrap();
    assert_eq!(j["event"]["kind"], "aborted");
    assert_eq!(j["event"]["reason"], "camera_lost");
    assert_eq!(j["event"]["detail"], "no frame for 0.5 s");
}

#[test]
fn states_have_names_and_motion_flags() {
    for st in TrialState::ALL {
        assert_eq!(serde_json::to_value(st).unwrap(), st.as_str());
    }
    for r in [
        AbortKind::CameraLost,
        AbortKind::OperatorLost,
        AbortKind::Stop,
    ] {
        assert_eq!(serde_json::to_value(r).unwrap(), r.as_str());
    }
    for r in [
        Refusal::MotionRunning,
        Refusal::NotArmed,
        Refusal::DeviceUnavailable,
    ] {
        assert_eq!(serde_json::to_value(r).unwrap(), r.as_str());
    }
    assert!(TrialState::Intercepting.arm_in_motion());
    assert!(!TrialState::Armed.arm_in_motion());
    assert!(TrialState::Armed.busy());
    assert!(!TrialState::Done.busy());
}

#[test]
fn a_stop_request_is_seen_once_even_with_a_full_command_ring() {
    let cap = BridgeCapacity {
        commands: 1,
        ..BridgeCapacity::default()
    };
    let (mut c, mut s) = bridge(cap);
    s.commands.send(Command::Arm).unwrap();
    assert!(s.commands.send(Command::Stop).is_err());
    assert!(!c.take_stop_request());
    let stop = s.stop.clone();
    stop.request_stop();
    assert!(c.take_stop_request());
    assert!(!c.take_stop_request());
    assert_eq!(s.stats.read().stop_requests, 1);
}

#[test]
fn the_camera_view_projects_the_swinging_ball_where_the_camera_sees_it() {
    use crate::vision::{CameraIntrinsics, CameraPose, SwingPlaneCalibration};
    use nalgebra::Vector3;
    let mut k = CameraIntrinsics::from_hfov(1280, 720, 70.0);
    k.k1 = -0.05; // a little barrel distortion, as a webcam has
    let pose = CameraPose {
        yaw_deg: 8.0,
        pitch_deg: 5.0,
        ..CameraPose::default()
    };
    let rest = Vector3::new(0.62, 0.0, 0.3);
    let cal = SwingPlaneCalibration::from_pose(k, &pose, &rest, 0.0335);
    let mut view = CameraView::default();
    assert_eq!(view.project_lateral(0.1, 1.93), None, "no calibration yet");
    view.set_calibration(&cal, 1280, 720);
    let l = 1.93;
    for x in [-0.9, -0.3, 0.0, 0.25, 0.8] {
        // The ball centre on its circle, base frame, seen through the camera.
        let phi = f64::asin(x / l);
        let ball = rest + Vector3::new(0.0, l * phi.sin(), l * (1.0 - phi.cos()));
        let want = k.project(&pose.to_camera(&ball)).unwrap();
        let got = view.project_lateral(x, l).unwrap();
        assert!(
            (got[0] - want.x).abs() < 1e-9 && (got[1] - want.y).abs() < 1e-9,
            "x {x}: {got:?} vs {want:?}"
        );
        // And the calibration maps that pixel back to the same lateral position.
        let back = cal.lateral_m(got[0], got[1]).unwrap();
        assert!((back - x).abs() < 1e-6, "x {x}: back {back}");
    }
    assert_eq!(view.project_lateral(2.0, l), None, "beyond the string");
    // The latest frame's detection, and the JSON the dashboard reads.
    let m = crate::vision::Measurement {
        frame: 42,
        t_capture_s: 3.5,
        found: true,
        x_px: 700.5,
        y_px: 400.25,
        r_px: 11.0,
        ..Default::default()
    };
    view.set_frame(&m);
    let s = Snapshot {
        camera: view,
        ..Snapshot::default()
    };
    let v: serde_json::Value = serde_json::to_value(s).unwrap();
    let c = &v["camera"];
    assert_eq!(c["width_px"], 1280);
    assert_eq!(c["frame"], 42);
    assert_eq!(c["found"], true);
    assert_eq!(c["x_px"], 700.5);
    assert_eq!(c["up_c"].as_array().unwrap().len(), 3);
}
