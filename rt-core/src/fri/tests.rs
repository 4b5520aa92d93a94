//! Unit and property tests of the FRI codec, guard, client and simulated controller.

use proptest::prelude::*;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;

use prost::Message;
use rand::SeedableRng;

use super::codec::*;
use super::proto::*;
use super::version::FriVersion;

fn sample_monitoring(seq: u32, with_ipo: bool) -> Monitoring {
    let q = [0.1, -0.2, 0.3, -1.4, 0.5, 0.6, -0.7];
    Monitoring {
        sequence_counter: seq,
        reflected_sequence_counter: seq.wrapping_sub(1),
        session_state: if with_ipo {
            SessionState::CommandingActive
        } else {
            SessionState::MonitoringReady
        },
        quality: ConnectionQuality::Excellent,
        send_period_ms: 5,
        receive_multiplier: 1,
        safety_state: Some(SafetyState::NormalOperation),
        operation_mode: Some(OperationMode::AutomaticMode),
        control_mode: Some(ControlMode::PositionControlmode),
        drive_state: Some([DriveState::Active; 7]),
        measured_joint_position_rad: Some(q),
        measured_torque_nm: Some([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]),
        commanded_joint_position_rad: Some(q),
        commanded_torque_nm: Some([0.0; 7]),
        external_torque_nm: Some([0.5; 7]),
        external_force: None,
        timestamp: Some(UnixTime {
            sec: 1_790_000_000,
            nanosec: 123_456_789,
        }),
        ipo_joint_position_rad: with_ipo.then_some(q),
        client_command_mode: with_ipo.then_some(ClientCommandMode::Position),
        overlay_type: with_ipo.then_some(OverlayType::Joint),
        tracking_performance: with_ipo.then_some(1.0),
    }
}

#[test]
fn golden_header_only_command() {
    let mut enc = CommandEncoder::new();
    let bytes = enc.encode(0, 0, None).unwrap();
    assert_eq!(
        bytes,
        [0x0a, 0x08, 0x08, 0x81, 0x80, 0x0d, 0x10, 0x00, 0x18, 0x00]
    );
}

#[test]
fn golden_position_command_is_77_bytes_unpacked() {
    let q = [0.0, 0.5, -0.5, 1.0, -1.0, 0.25, -0.25];
    let mut enc = CommandEncoder::new();
    let bytes = enc.encode(0, 7, Some(&q)).unwrap().to_vec();
    assert_eq!(bytes.len(), 77);
    assert_eq!(
        &bytes[..10],
        [0x0a, 0x08, 0x08, 0x81, 0x80, 0x0d, 0x10, 0x00, 0x18, 0x07]
    );
    // commandData (tag 2, 65 bytes) > jointPosition (tag 1, 63 bytes) > 7 x (0x09 + f64 LE).
    assert_eq!(&bytes[10..14], [0x12, 65, 0x0a, 63]);
    for (i, v) in q.iter().enumerate() {
        let at = 14 + 9 * i;
        assert_eq!(bytes[at], 0x09, "value {i} is not written unpacked");
        assert_eq!(&bytes[at + 1..at + 9], v.to_le_bytes());
    }
    // The allocating reference encoder agrees byte for byte.
    assert_eq!(command_message(0, 7, Some(&q)).encode_to_vec(), bytes);
    // And after a header-only reply the encoder still writes the same bytes.
    enc.encode(1, 8, None).unwrap();
    assert_eq!(enc.encode(0, 7, Some(&q)).unwrap(), bytes.as_slice());
}

#[test]
fn large_counters_encode_as_varints() {
    let mut enc = CommandEncoder::new();
    let bytes = enc.encode(300, 1, None).unwrap();
    assert_eq!(&bytes[6..], [0x10, 0xac, 0x02, 0x18, 0x01]);
    assert_eq!(bytes[1], 9);
}

#[test]
fn monitoring_round_trip_and_size() {
    let mut enc = MonitoringEncoder::new();
    let mut dec = MonitoringDecoder::new();
    for with_ipo in [false, true, false] {
        let m = sample_monitoring(42, with_ipo);
        let bytes = enc.encode(&m).unwrap().to_vec();
        assert_eq!(dec.decode(&bytes).unwrap(), m);
        // The reference decoder agrees.
        let full = decode_monitoring_message(&bytes).unwrap();
        assert_eq!(monitoring_view(&full, FriVersion::V1_15).unwrap(), m);
        if with_ipo {
            // FRI.md: "a full monitoring message without IO or transformations about 471 bytes".
            assert!((380..=520).contains(&bytes.len()), "{} bytes", bytes.len());
        } else {
            assert!(
                full.ipo_data.is_none(),
                "ipoData is only sent in COMMANDING_*"
            );
        }
    }
}

#[test]
fn decoder_reuse_does_not_leak_fields_between_datagrams() {
    let mut dec = MonitoringDecoder::new();
    let mut enc = MonitoringEncoder::new();
    let full = enc.encode(&sample_monitoring(1, true)).unwrap().to_vec();
    assert!(dec.decode(&full).unwrap().ipo_joint_position_rad.is_some());
    let bare = Monitoring {
        sequence_counter: 2,
        ..Monitoring::default()
    };
    let bytes = enc.encode(&bare).unwrap().to_vec();
    let got = dec.decode(&bytes).unwrap();
    assert_eq!(got.ipo_joint_position_rad, None);
    assert_eq!(got.measured_joint_position_rad, None);
    assert_eq!(got.timestamp, None);
    assert_eq!(got.sequence_counter, 2);
}

#[test]
fn packed_joint_arrays_decode() {
    // commandData.jointPosition written packed: 0x0a len [8 bytes x 7].
    let q: Joints = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0];
    let mut jv = vec![0x0a, 56];
    for v in q {
        jv.extend_from_slice(&v.to_le_bytes());
    }
    let mut cd = vec![0x0a, jv.len() as u8];
    cd.extend_from_slice(&jv);
    let mut bytes = vec![0x0a, 0x08, 0x08, 0x81, 0x80, 0x0d, 0x10, 0x05, 0x18, 0x03];
    bytes.push(0x12);
    bytes.push(cd.len() as u8);
    bytes.extend_from_slice(&cd);
    let c = CommandDecoder::new().decode(&bytes).unwrap();
    assert_eq!(c.sequence_counter, 5);
    assert_eq!(c.reflected_sequence_counter, 3);
    assert_eq!(c.joint_position_rad, Some(q));
}

#[test]
fn six_joint_values_are_refused() {
    let mut msg = command_message(0, 0, Some(&[0.0; 7]));
    if let Some(cd) = &mut msg.command_data {
        cd.joint_position = Some(JointValues {
            value: vec![0.0; 6],
        });
    }
    let err = CommandDecoder::new()
        .decode(&msg.encode_to_vec())
        .unwrap_err();
    assert_eq!(
        err,
        CodecError::JointCount {
            field: "commandData.jointPosition",
            got: 6
        }
    );
}

#[test]
fn missing_required_fields_are_refused() {
    let mut msg = command_message(0, 0, None);
    msg.header = Some(MessageHeader {
        message_identifier: Some(COMMAND_MESSAGE_ID),
        sequence_counter: Some(0),
        reflected_sequence_counter: None,
    });
    assert_eq!(
        CommandDecoder::new().decode(&msg.encode_to_vec()),
        Err(CodecError::MissingField("header.reflectedSequenceCounter"))
    );
    msg.header = None;
    assert_eq!(
        CommandDecoder::new().decode(&msg.encode_to_vec()),
        Err(CodecError::MissingField("header"))
    );
    let mut m = FriMonitoringMessage::decode(
        MonitoringEncoder::new()
            .encode(&sample_monitoring(3, false))
            .unwrap(),
    )
    .unwrap();
    m.connection_info = Some(ConnectionInfo {
        session_state: Some(1),
        quality: None,
        send_period: Some(5),
        receive_multiplier: None,
    });
    assert_eq!(
        MonitoringDecoder::new().decode(&m.encode_to_vec()),
        Err(CodecError::MissingField("connectionInfo.quality"))
    );
    if let Some(md) = &mut m.monitor_data {
        md.timestamp = Some(TimeStamp {
            sec: Some(1),
            nanosec: None,
        });
    }
    m.connection_info = None;
    assert_eq!(
        MonitoringDecoder::new().decode(&m.encode_to_vec()),
        Err(CodecError::MissingField("connectionInfo"))
    );
}

#[test]
fn wrong_identifier_and_oversize_are_refused() {
    let mut enc = MonitoringEncoder::new();
    let mon = enc.encode(&sample_monitoring(1, false)).unwrap().to_vec();
    assert_eq!(
        CommandDecoder::new().decode(&mon),
        Err(CodecError::WrongIdentifier {
            got: MONITORING_MESSAGE_ID,
            expected: COMMAND_MESSAGE_ID
        })
    );
    let cmd = CommandEncoder::new()
        .encode(0, 0, Some(&[0.0; 7]))
        .unwrap()
        .to_vec();
    assert_eq!(
        MonitoringDecoder::new().decode(&cmd),
        Err(CodecError::WrongIdentifier {
            got: COMMAND_MESSAGE_ID,
            expected: MONITORING_MESSAGE_ID
        })
    );
    let big = vec![0u8; MAX_DATAGRAM_BYTES + 1];
    assert_eq!(
        MonitoringDecoder::new().decode(&big),
        Err(CodecError::TooLong { len: 1501 })
    );
}

#[test]
fn receive_multiplier_zero_means_one() {
    let mut m = sample_monitoring(1, false);
    m.receive_multiplier = 0;
    let bytes = MonitoringEncoder::new().encode(&m).unwrap().to_vec();
    assert_eq!(
        MonitoringDecoder::new()
            .decode(&bytes)
            .unwrap()
            .receive_multiplier,
        1
    );
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

    #[test]
    fn garbage_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..1600)) {
        let _ = MonitoringDecoder::new().decode(&bytes);
        let _ = CommandDecoder::new().decode(&bytes);
        let _ = decode_monitoring_message(&bytes);
        let _ = decode_command_message(&bytes);
    }

    #[test]
    fn truncated_and_mutated_datagrams_never_panic(
        cut in 0usize..600, flip in 0usize..600, xor in 1u8..=255, ipo in any::<bool>()
    ) {
        let mut enc = MonitoringEncoder::new();
        let mut bytes = enc.encode(&sample_monitoring(9, ipo)).unwrap().to_vec();
        let mut dec = MonitoringDecoder::new();
        // Every strict prefix of a datagram whose last field is a joint array is refused
        // or decodes to fewer fields; it must never panic.
        let _ = dec.decode(&bytes[..cut.min(bytes.len())]);
        let i = flip % bytes.len();
        bytes[i] ^= xor;
        let _ = dec.decode(&bytes);
        let mut cmd = CommandEncoder::new().encode(3, 9, Some(&[0.1; 7])).unwrap().to_vec();
        let mut cdec = CommandDecoder::new();
        let cut_c = cut % (cmd.len() + 1);
        let truncated = cdec.decode(&cmd[..cut_c]);
        if cut_c < cmd.len() && cut_c > 0 {
            prop_assert!(truncated.is_err() || truncated.unwrap().joint_position_rad.is_none());
        }
        let j = flip % cmd.len();
        cmd[j] ^= xor;
        let _ = cdec.decode(&cmd);
    }

    #[test]
    fn commands_round_trip(seq in any::<u32>(), refl in any::<u32>(),
                           q in proptest::array::uniform7(-3.0f64..3.0), header_only in any::<bool>()) {
        let mut enc = CommandEncoder::new();
        let bytes = enc.encode(seq, refl, (!header_only).then_some(&q)).unwrap().to_vec();
        let c = CommandDecoder::new().decode(&bytes).unwrap();
        prop_assert_eq!(c.sequence_counter, seq);
        prop_assert_eq!(c.reflected_sequence_counter, refl);
        prop_assert_eq!(c.joint_position_rad, (!header_only).then_some(q));
    }
}

// ---------------------------------------------------------------------------
// Client + simulated controller in virtual time (no sockets, real datagrams).

use super::client::*;
use super::guard::*;
use super::stats::LatencyHistogram;
use crate::kinematics::iiwa7::{POSITION_LIMIT_RAD, VELOCITY_LIMIT_RADPS};
use crate::sim::kuka::controller::*;

/// A test control: in COMMANDING_ACTIVE moves A1 at `speed_radps` from the
/// hand-over position, or jumps by `jump_rad` once after `jump_after` steps.
#[derive(Debug, Default)]
struct Mover {
    start: Option<Joints>,
    steps: u64,
    calls: u64,
    speed_radps: f64,
    jump_rad: Option<f64>,
    jump_after: u64,
    absolute_a1: Option<f64>,
    stops: Vec<StopReason>,
    commands: Vec<(u64, f64)>,
}

impl ControlStep for Mover {
    fn step(&mut self, input: &StepInput<'_>, command_rad: &mut Joints) {
        self.calls += 1;
        if !input.commanding {
            return;
        }
        let s = *self.start.get_or_insert(*command_rad);
        self.steps += 1;
        command_rad[0] = s[0] + self.speed_radps * self.steps as f64 * input.receive_period_s;
        if let Some(j) = self.jump_rad
            && self.steps >= self.jump_after
        {
            command_rad[0] = s[0] + j;
        }
        if let Some(a) = self.absolute_a1 {
            command_rad[0] = a;
        }
        self.commands.push((input.now_ns, command_rad[0]));
    }

    fn stop(&mut self, reason: StopReason) {
        self.stops.push(reason);
    }
}

const MS: u64 = 1_000_000;

struct Rig {
    sim: SimController,
    client: FriClient,
    t_ns: u64,
    /// One-way delay client <-> controller, ns.
    hop_ns: u64,
}

impl Rig {
    fn new(p: FriSimParams, c: FriClientParams) -> Self {
        let mut sim = SimController::new(p, 1_790_000_000_000_000_000).unwrap();
        sim.request_commanding();
        Self {
            sim,
            client: FriClient::new(c).unwrap(),
            t_ns: 0,
            hop_ns: 50_000,
        }
    }

    fn period_ns(&self) -> u64 {
        self.sim.params().period_ns()
    }

    /// Runs `n` controller periods.
    fn run(&mut self, n: u64, ctl: &mut impl ControlStep) {
        for _ in 0..n {
            let t = self.t_ns;
            if let Some(m) = self.sim.tick(t)
                && let Some(r) = self.client.on_datagram(m, t + self.hop_ns, ctl)
            {
                self.sim.on_reply(r, t + 2 * self.hop_ns);
            }
            self.client.poll(t + self.hop_ns, ctl);
            self.t_ns += self.period_ns();
        }
    }

    /// Runs until `cond` or `max` periods; returns the periods run.
    fn run_until(
        &mut self,
        max: u64,
        ctl: &mut impl ControlStep,
        cond: impl Fn(&Self) -> bool,
    ) -> u64 {
        for k in 0..max {
            if cond(self) {
                return k;
            }
            self.run(1, ctl);
        }
        panic!("condition not reached in {max} periods");
    }
}

fn active(r: &Rig) -> bool {
    r.client.state() == LinkState::CommandingActive
}

#[test]
fn virtual_session_walks_the_states_moves_the_joints_and_closes() {
    let mut rig = Rig::new(FriSimParams::default(), FriClientParams::default());
    let mut ctl = Mover {
        speed_radps: 0.2,
        ..Mover::default()
    };
    assert_eq!(rig.sim.state(), SessionState::MonitoringWait);
    assert_eq!(rig.sim.quality(), ConnectionQuality::Fair);
    rig.run_until(200, &mut ctl, active);
    let q0 = rig.sim.joint_rad()[0];
    rig.run(200, &mut ctl); // 1 s at 5 ms
    let moved = rig.sim.joint_rad()[0] - q0;
    // 0.2 rad/s for 1 s, less what is still in the latency + servo lag (~13 ms).
    assert!((0.19..=0.201).contains(&moved), "A1 moved {moved} rad");
    let st = Arc::clone(rig.sim.stats());
    for s in [
        "MONITORING_WAIT",
        "MONITORING_READY",
        "COMMANDING_WAIT",
        "COMMANDING_ACTIVE",
    ] {
        assert!(st.states_reached().contains(&s), "{s} not reached");
    }
    assert_eq!(st.mirror_mismatches.load(Relaxed), 0);
    assert_eq!(st.client_sequence_errors.load(Relaxed), 0);
    assert_eq!(st.violations.load(Relaxed), 0);
    let cs = rig.client.stats().snapshot();
    assert_eq!(cs.replies, st.replies.load(Relaxed));
    assert_eq!(cs.received, st.messages_sent.load(Relaxed));
    assert_eq!(cs.guard_step + cs.guard_position + cs.guard_non_finite, 0);
    assert_eq!(rig.sim.quality(), ConnectionQuality::Excellent);
    // Closing: one IDLE, the client goes quiet and the control is told.
    rig.sim.request_close();
    rig.run(3, &mut ctl);
    assert!(rig.sim.is_closed());
    assert_eq!(rig.client.state(), LinkState::Idle);
    assert_eq!(ctl.stops, vec![StopReason::SessionClosed]);
    assert_eq!(cs.replies, rig.client.stats().snapshot().replies);
    assert!(st.reached(SessionState::Idle));
    // In the order reached: the controller never starts in IDLE, it ends there.
    assert_eq!(
        st.states_reached(),
        [
            "MONITORING_WAIT",
            "MONITORING_READY",
            "COMMANDING_WAIT",
            "COMMANDING_ACTIVE",
            "IDLE"
        ]
    );
}

#[test]
fn the_joints_follow_with_the_configured_latency_and_lag() {
    let p = FriSimParams {
        latency_ms: 8.0,
        latency_jitter_ms: 0.0,
        servo_time_constant_ms: 5.0,
        fri_period_ms: 1,
        ..FriSimParams::default()
    };
    let mut rig = Rig::new(p, FriClientParams::default());
    let mut ctl = Mover {
        speed_radps: 0.5,
        ..Mover::default()
    };
    rig.run_until(500, &mut ctl, active);
    rig.run(400, &mut ctl);
    // On a ramp, position = command delayed by latency + tau (+ the hop).
    let q = rig.sim.joint_rad()[0];
    let now = rig.t_ns - rig.period_ns();
    let (t_cmd, _) = ctl
        .commands
        .iter()
        .rev()
        .find(|(_, a1)| *a1 <= q)
        .copied()
        .unwrap();
    let lag_ms = (now - t_cmd) as f64 / 1e6;
    assert!((12.0..=14.5).contains(&lag_ms), "lag {lag_ms} ms");
}

#[test]
fn guard_clips_a_jump_and_the_controller_stays_in_commanding() {
    let mut rig = Rig::new(FriSimParams::default(), FriClientParams::default());
    let mut ctl = Mover {
        jump_rad: Some(0.5),
        jump_after: 5,
        ..Mover::default()
    };
    rig.run_until(200, &mut ctl, active);
    rig.run(100, &mut ctl);
    let cs = rig.client.stats().snapshot();
    assert!(cs.guard_step > 0);
    assert_eq!(rig.sim.stats().violations.load(Relaxed), 0);
    assert_eq!(rig.sim.state(), SessionState::CommandingActive);
    // The clipped command approaches the target at 95% of the velocity limit.
    let max_step = 0.95 * VELOCITY_LIMIT_RADPS[0] * 0.005;
    for w in ctl.commands.windows(2) {
        assert!((w[1].1 - w[0].1).abs() <= 0.5); // what the control asked for
    }
    let sent = rig.client.stats().commanded_rad.load();
    let start = ctl.start.unwrap()[0];
    assert!(
        (sent[0] - start - 0.5).abs() < 1e-9,
        "reached the target: {}",
        sent[0]
    );
    assert!(max_step > 0.0);
}

#[test]
fn a_forced_jump_aborts_commanding_and_the_client_reports_it() {
    let c = FriClientParams {
        guard_enabled: false,
        ..FriClientParams::default()
    };
    let mut rig = Rig::new(FriSimParams::default(), c);
    let mut ctl = Mover {
        jump_rad: Some(0.5),
        jump_after: 5,
        ..Mover::default()
    };
    rig.run_until(200, &mut ctl, active);
    rig.run(20, &mut ctl);
    let st = rig.sim.stats();
    assert_eq!(st.violations.load(Relaxed), 1);
    match st.last_abort() {
        Some(CommandingAbort::VelocityLimit {
            joint: 0,
            step_rad,
            max_step_rad,
        }) => {
            assert!((step_rad - 0.5).abs() < 1e-9);
            assert!((max_step_rad - VELOCITY_LIMIT_RADPS[0] * 0.005).abs() < 1e-12);
        }
        other => panic!("unexpected abort {other:?}"),
    }
    assert_eq!(rig.sim.state(), SessionState::MonitoringReady);
    assert_eq!(rig.client.stats().snapshot().commanding_lost, 1);
    assert_eq!(
        ctl.stops,
        vec![StopReason::LeftCommanding(SessionState::MonitoringReady)]
    );
    assert!(st.report().abort_reason.unwrap().contains("A1"));
}

#[test]
fn a_position_beyond_the_limit_is_clamped_or_aborts() {
    let beyond = POSITION_LIMIT_RAD[0] + 0.1;
    let p = FriSimParams {
        initial_joint_position_deg: [169.0, 30.0, 0.0, -80.0, 0.0, 60.0, 0.0],
        ..FriSimParams::default()
    };
    for guard_enabled in [true, false] {
        let mut rig = Rig::new(
            p.clone(),
            FriClientParams {
                guard_enabled,
                ..FriClientParams::default()
            },
        );
        let mut ctl = Mover {
            absolute_a1: Some(beyond),
            ..Mover::default()
        };
        rig.run_until(200, &mut ctl, active);
        rig.run(40, &mut ctl);
        let st = rig.sim.stats();
        if guard_enabled {
            assert_eq!(st.violations.load(Relaxed), 0);
            assert!(rig.client.stats().snapshot().guard_position > 0);
            let a1 = rig.client.stats().commanded_rad.load()[0];
            assert!(a1 <= POSITION_LIMIT_RAD[0] - 0.5f64.to_radians() + 1e-12);
        } else {
            assert!(matches!(
                st.last_abort(),
                Some(CommandingAbort::PositionLimit { joint: 0, .. })
            ));
        }
    }
}

#[test]
fn a_nan_command_is_held() {
    let mut rig = Rig::new(FriSimParams::default(), FriClientParams::default());
    let mut ctl = Mover {
        absolute_a1: Some(f64::NAN),
        ..Mover::default()
    };
    rig.run_until(200, &mut ctl, active);
    rig.run(10, &mut ctl);
    assert!(rig.client.stats().snapshot().guard_non_finite >= 10);
    assert_eq!(rig.sim.stats().aborts.load(Relaxed), 0);
}

/// A controller handing over NaN positions (a corrupt but well-formed
/// datagram) never makes the client command NaN: the guard's hold needs a
/// finite previous command, so a non-finite hand-over is not taken.
#[test]
fn a_non_finite_hand_over_is_never_commanded() {
    let mut client = FriClient::new(FriClientParams::default()).unwrap();
    let mut enc = MonitoringEncoder::new();
    let mut dec = CommandDecoder::new();
    let mut ctl = Mover {
        absolute_a1: Some(f64::NAN),
        ..Mover::default()
    };
    let nan = [f64::NAN; 7];
    let mut sent = Vec::new();
    for (k, (state, ipo, commanded)) in [
        (SessionState::MonitoringReady, None, Some(nan)),
        (SessionState::CommandingActive, Some(nan), Some(nan)),
        (SessionState::CommandingActive, Some(nan), None),
        (SessionState::CommandingActive, Some([0.1; 7]), None),
        (SessionState::CommandingActive, Some(nan), None),
    ]
    .into_iter()
    .enumerate()
    {
        let m = Monitoring {
            session_state: state,
            ipo_joint_position_rad: ipo,
            commanded_joint_position_rad: commanded,
            measured_joint_position_rad: Some(nan),
            ..sample_monitoring(k as u32, false)
        };
        let bytes = enc.encode(&m).unwrap().to_vec();
        let reply = client
            .on_datagram(&bytes, k as u64 * 5 * MS, &mut ctl)
            .expect("every message is answered");
        sent.push(dec.decode(reply).unwrap().joint_position_rad);
    }
    // Without a finite hand-over: header-only answers, never NaN; then the
    // finite one is held (the control asks for NaN) and kept.
    assert_eq!(sent[..3], [None, None, None]);
    assert_eq!(sent[3], Some([0.1; 7]));
    assert_eq!(sent[4], Some([0.1; 7]));
    assert_eq!(client.stats().snapshot().guard_non_finite, 2);
}

#[test]
fn a_silent_controller_stops_the_motion_after_two_periods() {
    let mut rig = Rig::new(FriSimParams::default(), FriClientParams::default());
    let mut ctl = Mover::default();
    rig.run_until(200, &mut ctl, active);
    let last_rx = rig.t_ns - rig.period_ns() + rig.hop_ns;
    let p = rig.period_ns();
    assert!(!rig.client.poll(last_rx + 2 * p - 1, &mut ctl));
    assert!(ctl.stops.is_empty());
    assert!(rig.client.poll(last_rx + 2 * p, &mut ctl));
    assert_eq!(ctl.stops, vec![StopReason::ControllerSilent]);
    assert_eq!(rig.client.state(), LinkState::Disconnected);
    assert_eq!(rig.client.stats().snapshot().silences, 1);
    // Only once per silence.
    assert!(!rig.client.poll(last_rx + 10 * p, &mut ctl));
}

#[test]
fn five_percent_loss_is_survived_and_counted() {
    let p = FriSimParams {
        packet_loss: 0.05,
        seed: 7,
        ..FriSimParams::default()
    };
    let mut rig = Rig::new(p, FriClientParams::default());
    let mut ctl = Mover {
        speed_radps: 0.05,
        ..Mover::default()
    };
    rig.run_until(400, &mut ctl, active);
    rig.run(2000, &mut ctl);
    let st = rig.sim.stats();
    let dropped = st.messages_dropped.load(Relaxed);
    assert!((50..=160).contains(&dropped), "dropped {dropped}");
    assert_eq!(st.last_abort(), None);
    assert_eq!(st.commanding_entered.load(Relaxed), 1);
    assert_eq!(st.aborts.load(Relaxed), 0);
    assert_eq!(rig.sim.state(), SessionState::CommandingActive);
    let cs = rig.client.stats().snapshot();
    // Every lost message is a missed cycle for the client and a missing reply
    // for the controller (the last few may still be pending).
    assert!(cs.missed_cycles + 1 >= dropped && cs.missed_cycles <= dropped);
    let missing = st.missing_replies.load(Relaxed);
    assert!(
        missing + 1 >= dropped && missing <= dropped,
        "{missing} vs {dropped}"
    );
    // Two losses in a row leave the client without a message for two periods:
    // it tells the control (which here ignores it), and commanding goes on.
    assert!(ctl.stops.iter().all(|r| *r == StopReason::ControllerSilent));
    assert_eq!(cs.silences as usize, ctl.stops.len());
    assert_eq!(cs.guard_step, 0, "commands stay continuous across the gaps");
}

#[test]
fn losing_half_the_replies_drops_out_of_commanding() {
    let mut rig = Rig::new(FriSimParams::default(), FriClientParams::default());
    let mut ctl = Mover::default();
    rig.run_until(200, &mut ctl, active);
    let mut p = rig.sim.params().clone();
    p.reply_loss = 0.5;
    // Same controller state, lossy return path: rebuild is not possible, so
    // emulate loss by not delivering every other reply.
    for k in 0..100 {
        let t = rig.t_ns;
        if let Some(m) = rig.sim.tick(t)
            && let Some(r) = rig.client.on_datagram(m, t + rig.hop_ns, &mut ctl)
            && k % 2 == 0
        {
            rig.sim.on_reply(r, t + 2 * rig.hop_ns);
        }
        rig.t_ns += rig.period_ns();
    }
    assert!(matches!(
        rig.sim.stats().last_abort(),
        Some(CommandingAbort::QualityDropped { .. })
    ));
    assert!(rig.sim.quality() < ConnectionQuality::Good);
    assert_eq!(rig.client.stats().snapshot().commanding_lost, 1);
    assert!(matches!(ctl.stops[0], StopReason::LeftCommanding(_)));
    assert!(p.validate().is_ok());
}

#[test]
fn late_replies_are_graded_and_degrade_quality() {
    let p = FriSimParams {
        reply_delay_ms: 7.0,
        ..FriSimParams::default()
    };
    let mut rig = Rig::new(p, FriClientParams::default());
    let mut ctl = Mover::default();
    rig.run(100, &mut ctl);
    let st = rig.sim.stats();
    assert!(st.late_replies.load(Relaxed) >= 95);
    assert_eq!(rig.sim.quality(), ConnectionQuality::Poor);
    assert!(!st.reached(SessionState::MonitoringReady));
    let rtt = st.rtt.summary_us();
    assert!((7000.0..=8800.0).contains(&rtt.p50), "{rtt:?}");
}

#[test]
fn receive_multiplier_two_answers_every_other_message() {
    let p = FriSimParams {
        receive_multiplier: 2,
        fri_period_ms: 2,
        ..FriSimParams::default()
    };
    let mut rig = Rig::new(p, FriClientParams::default());
    let mut ctl = Mover {
        speed_radps: 0.1,
        ..Mover::default()
    };
    rig.run_until(400, &mut ctl, active);
    rig.run(200, &mut ctl);
    let st = rig.sim.stats();
    let sent = st.messages_sent.load(Relaxed);
    let replies = st.replies.load(Relaxed);
    assert!(
        replies * 2 <= sent && replies * 2 + 2 >= sent,
        "{replies} of {sent}"
    );
    assert_eq!(st.missing_replies.load(Relaxed), 0);
    assert_eq!(
        ctl.calls, sent,
        "the control steps once per controller message"
    );
    assert_eq!(rig.client.receive_period_ns(), 4 * MS);
    assert_eq!(st.violations.load(Relaxed), 0);
}

/// One protobuf field as it is on the wire: (tag, wire type, payload or varint).
fn wire_fields(mut b: &[u8]) -> Vec<(u64, u8, &[u8], u64)> {
    fn varint(b: &mut &[u8]) -> u64 {
        let mut v = 0u64;
        for shift in (0..64).step_by(7) {
            let (x, rest) = b.split_first().expect("truncated varint");
            *b = rest;
            v |= u64::from(x & 0x7f) << shift;
            if x & 0x80 == 0 {
                break;
            }
        }
        v
    }
    let mut out = Vec::new();
    while !b.is_empty() {
        let key = varint(&mut b);
        let (tag, wt) = (key >> 3, (key & 7) as u8);
        match wt {
            0 => out.push((tag, wt, &b[..0], varint(&mut b))),
            1 => {
                out.push((tag, wt, &b[..8], 0));
                b = &b[8..];
            }
            2 => {
                let n = varint(&mut b) as usize;
                out.push((tag, wt, &b[..n], 0));
                b = &b[n..];
            }
            5 => {
                out.push((tag, wt, &b[..4], 0));
                b = &b[4..];
            }
            _ => panic!("wire type {wt}"),
        }
    }
    out
}

fn field<'a>(fs: &[(u64, u8, &'a [u8], u64)], tag: u64) -> Vec<(u8, &'a [u8], u64)> {
    fs.iter()
        .filter(|f| f.0 == tag)
        .map(|f| (f.1, f.2, f.3))
        .collect()
}

/// A JointValues message as KUKA's client writes and reads it: exactly 7
/// unpacked doubles (tag 1, wire type 1 each).
fn assert_unpacked_joints(what: &str, jv: &[u8]) {
    let fs = wire_fields(jv);
    assert_eq!(fs.len(), 7, "{what}: {} fields", fs.len());
    assert!(fs.iter().all(|f| f.0 == 1 && f.1 == 1), "{what}: {fs:?}");
}

/// Every datagram the simulated controller sends, in every state, is what a
/// real client application decodes: the monitoring identifier, all proto2
/// required fields, sendPeriod and receiveMultiplier, seven drive states as
/// unpacked varints, every joint array as 7 unpacked doubles, a timestamp with
/// both fields, ipoData only in COMMANDING_*, at most 1500 bytes.
#[test]
fn the_controllers_datagrams_are_what_a_kuka_client_reads() {
    let p = FriSimParams {
        receive_multiplier: 2,
        fri_period_ms: 2,
        ..FriSimParams::default()
    };
    let mut rig = Rig::new(p, FriClientParams::default());
    let mut ctl = Mover {
        speed_radps: 0.1,
        ..Mover::default()
    };
    let mut seen = std::collections::BTreeSet::new();
    let mut check = |bytes: &[u8]| {
        assert!(bytes.len() <= MAX_DATAGRAM_BYTES);
        let top = wire_fields(bytes);
        let header = field(&top, 1);
        assert_eq!(header.len(), 1);
        let h = wire_fields(header[0].1);
        assert_eq!(field(&h, 1)[0].2, u64::from(MONITORING_MESSAGE_ID));
        assert_eq!(field(&h, 2).len(), 1, "sequenceCounter");
        assert_eq!(field(&h, 3).len(), 1, "reflectedSequenceCounter");
        let ci = wire_fields(field(&top, 4)[0].1);
        let state = field(&ci, 1)[0].2;
        assert_eq!(field(&ci, 2).len(), 1, "quality");
        assert_eq!(field(&ci, 3)[0].2, 2, "sendPeriod");
        assert_eq!(field(&ci, 4)[0].2, 2, "receiveMultiplier");
        let ri = wire_fields(field(&top, 2)[0].1);
        assert_eq!(field(&ri, 1)[0].2, 7, "numberOfJoints");
        let drives = field(&ri, 5);
        assert_eq!(drives.len(), 7, "driveState");
        assert!(drives.iter().all(|d| d.0 == 0), "driveState unpacked");
        let md = wire_fields(field(&top, 3)[0].1);
        for tag in 1..=5 {
            let jv = field(&md, tag);
            assert_eq!(jv.len(), 1, "monitorData field {tag}");
            assert_unpacked_joints("monitorData", jv[0].1);
        }
        let ts = wire_fields(field(&md, 15)[0].1);
        assert_eq!((field(&ts, 1).len(), field(&ts, 2).len()), (1, 1));
        let ipo = field(&top, 5);
        let commanding = state == 3 || state == 4;
        assert_eq!(
            ipo.len(),
            usize::from(commanding),
            "ipoData in state {state}"
        );
        if commanding {
            let ipo = wire_fields(ipo[0].1);
            assert_unpacked_joints("ipoData", field(&ipo, 1)[0].1);
        }
        seen.insert(state);
    };
    loop {
        let t = rig.t_ns;
        let Some(m) = rig.sim.tick(t).map(<[u8]>::to_vec) else {
            break;
        };
        check(&m);
        if let Some(r) = rig.client.on_datagram(&m, t + rig.hop_ns, &mut ctl) {
            rig.sim.on_reply(r, t + 2 * rig.hop_ns);
        }
        rig.t_ns += rig.period_ns();
        if ctl.steps == 50 {
            rig.sim.request_close();
        }
        assert!(rig.t_ns < 10_000 * MS, "no commanding");
    }
    assert_eq!(seen.into_iter().collect::<Vec<_>>(), [0, 1, 2, 3, 4]);
}

/// A client counts receiveMultiplier from the first message it receives (KUKA's
/// SDK does), so one that starts late, or loses a message, answers other
/// messages than those the controller expects first: still on time, still GOOD.
#[test]
fn receive_multiplier_answers_in_any_phase_are_on_time() {
    for (late_start, loss) in [(1, 0.0), (0, 0.05), (3, 0.05)] {
        let p = FriSimParams {
            receive_multiplier: 2,
            fri_period_ms: 2,
            packet_loss: loss,
            seed: 5,
            ..FriSimParams::default()
        };
        let mut rig = Rig::new(p, FriClientParams::default());
        for _ in 0..late_start {
            // Sent before the client listened.
            let _ = rig.sim.tick(rig.t_ns);
            rig.t_ns += rig.period_ns();
        }
        let mut ctl = Mover {
            speed_radps: 0.1,
            ..Mover::default()
        };
        rig.run_until(400, &mut ctl, active);
        rig.run(500, &mut ctl);
        let st = rig.sim.stats();
        let r = st.report();
        assert_eq!(r.stale_replies, 0, "start {late_start}, loss {loss}: {r:?}");
        assert_eq!(r.late_replies, 0, "{r:?}");
        assert_eq!(r.aborts, 0, "{r:?}");
        assert_eq!(rig.sim.state(), SessionState::CommandingActive);
        // Only answers a lost message made impossible are missing.
        assert!(r.missing_replies <= r.messages_dropped, "{r:?}");
        if loss == 0.0 {
            assert_eq!(r.missing_replies, 0, "{r:?}");
        }
        // The round trip is measured from the answered message: two hops.
        assert!(r.rtt_us.max <= 2.0 * rig.hop_ns as f64 / 1e3 + 1.0, "{r:?}");
    }
}

#[test]
fn garbage_to_either_side_is_counted_and_ignored() {
    let mut rig = Rig::new(FriSimParams::default(), FriClientParams::default());
    let mut ctl = Mover::default();
    rig.run_until(200, &mut ctl, active);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let valid = rig.sim.tick(rig.t_ns).unwrap().to_vec();
    for k in 0..200 {
        let len = rand::RngExt::random_range(&mut rng, 0..1600);
        let junk: Vec<u8> = (0..len).map(|_| rand::RngExt::random(&mut rng)).collect();
        assert!(rig.client.on_datagram(&junk, rig.t_ns, &mut ctl).is_none());
        rig.sim.on_reply(&junk, rig.t_ns);
        let cut = &valid[..k % valid.len()];
        let _ = rig.client.on_datagram(cut, rig.t_ns, &mut ctl);
        rig.sim.on_reply(cut, rig.t_ns);
    }
    assert!(rig.client.stats().snapshot().decode_errors >= 200);
    assert!(rig.sim.stats().decode_errors.load(Relaxed) >= 200);
    rig.t_ns += rig.period_ns();
    rig.run(50, &mut ctl);
    assert_eq!(rig.sim.state(), SessionState::CommandingActive);
    assert_eq!(rig.sim.stats().aborts.load(Relaxed), 0);
}

#[test]
fn two_histograms_absorbed_are_the_histogram_of_both_windows() {
    let (a, b, both) = (
        LatencyHistogram::new(),
        LatencyHistogram::new(),
        LatencyHistogram::new(),
    );
    for v in 1..=1000u64 {
        // Odd samples in one window, even in the other, the second slower.
        let ns = if v % 2 == 1 { v * 1000 } else { v * 3000 };
        if v % 2 == 1 { &a } else { &b }.record_ns(ns);
        both.record_ns(ns);
    }
    a.absorb(&b);
    assert_eq!(a.count(), 1000);
    assert_eq!(a.max_ns(), both.max_ns());
    for q in [0.1, 0.5, 0.9, 0.99, 0.999] {
        assert_eq!(a.quantile_ns(q), both.quantile_ns(q), "q {q}");
    }
    assert_ne!(a.quantile_ns(0.99), b.quantile_ns(0.99));
}

#[test]
fn a_window_of_a_running_histogram_has_only_the_samples_recorded_in_it() {
    let (running, window) = (LatencyHistogram::new(), LatencyHistogram::new());
    // A slow start-up (up to 2 ms), then the window's samples (20-120 us).
    for v in 1..=300u64 {
        running.record_ns(v * 7_000);
    }
    let start = running.copy();
    assert_eq!(start.count(), 300);
    for v in 1..=5000u64 {
        let ns = 20_000 + (v * 7919) % 100_000;
        running.record_ns(ns);
        window.record_ns(ns);
    }
    let w = running.since(&start);
    assert_eq!(w.count(), 5000);
    for q in [0.01, 0.5, 0.9, 0.99] {
        assert_eq!(w.quantile_ns(q), window.quantile_ns(q), "q {q}");
    }
    // In the top bucket the cap is the window's maximum's bucket edge, not
    // the exact maximum: within 0.5%.
    let (a, b) = (w.quantile_ns(0.999), window.quantile_ns(0.999));
    assert!(a.abs_diff(b) * 200 <= b, "{a} vs {b}");
    // The start-up's 2.1 ms is not the window's maximum (120 us is, within
    // its bucket), and the running p99 still sees it.
    let max = w.max_ns();
    assert!(
        max >= window.max_ns() && max < window.max_ns() * 101 / 100,
        "{max}"
    );
    assert!(running.quantile_ns(0.99) > 1_000_000);
    // Nothing since: empty.
    let none = running.since(&running.copy());
    assert_eq!(
        (none.count(), none.max_ns(), none.quantile_ns(0.5)),
        (0, 0, 0)
    );
}

#[test]
fn histogram_quantiles_are_within_one_percent_of_the_exact_order_statistic() {
    let h = LatencyHistogram::new();
    for v in 1..=1000u64 {
        h.record_ns(v * 1000);
    }
    let p50 = h.quantile_ns(0.5) as f64;
    assert!((p50 / 500_000.0 - 1.0).abs() <= 0.01, "{p50}");
    let p99 = h.quantile_ns(0.99) as f64;
    assert!((p99 / 990_000.0 - 1.0).abs() <= 0.01, "{p99}");
    assert_eq!(h.max_ns(), 1_000_000);
    assert_eq!(LatencyHistogram::new().quantile_ns(0.5), 0);

    // Log-uniform samples from 50 ns to 50 ms (the range of FRI round trips,
    // jitter and stalls): every quantile against the sorted samples.
    let h = LatencyHistogram::new();
    let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut v: Vec<u64> = (0..20_000)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            let u = (x >> 11) as f64 / (1u64 << 53) as f64;
            (50.0 * 1e6f64.powf(u)) as u64
        })
        .collect();
    for &s in &v {
        h.record_ns(s);
    }
    v.sort_unstable();
    for q in [0.01, 0.1, 0.5, 0.9, 0.99, 0.999, 1.0] {
        let exact = v[((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1] as f64;
        let got = h.quantile_ns(q) as f64;
        assert!(
            (got / exact - 1.0).abs() <= 0.01,
            "q {q}: {got} ns vs exact {exact} ns"
        );
    }
    // Below 128 ns every value has its own bucket.
    let h = LatencyHistogram::new();
    for s in [3, 77, 127] {
        h.record_ns(s);
    }
    assert_eq!(
        [h.quantile_ns(0.1), h.quantile_ns(0.5), h.quantile_ns(1.0)],
        [3, 77, 127]
    );
    h.record_ns(0);
    h.record_ns(u64::MAX);
    assert_eq!(h.max_ns(), u64::MAX);
    assert!(h.quantile_ns(1.0) > 1 << 40);
}

#[test]
fn guard_never_lets_a_command_exceed_the_limits() {
    let g = CommandGuard::default();
    let prev = [0.0; 7];
    let mut cmd = [10.0, -10.0, f64::NAN, 0.0, 0.0, 0.0, 0.0];
    let out = g.apply(&mut cmd, &prev, 0.005);
    assert!(out.held_non_finite);
    assert_eq!(cmd, prev);
    let mut cmd = [10.0, -10.0, 0.001, 0.0, 0.0, 0.0, 0.0];
    let out = g.apply(&mut cmd, &prev, 0.005);
    assert!(out.clamped_step && !out.held_non_finite);
    let max = g.max_step_rad(0.005);
    assert!((cmd[0] - max[0]).abs() < 1e-15 && (cmd[1] + max[1]).abs() < 1e-15);
    assert_eq!(cmd[2], 0.001);
}

#[test]
fn params_are_validated_naming_the_field() {
    let bad = FriSimParams {
        fri_period_ms: 0,
        ..FriSimParams::default()
    };
    assert_eq!(
        bad.validate().unwrap_err().field(),
        Some("fri_sim.fri_period_ms")
    );
    let bad = FriSimParams {
        packet_loss: f64::NAN,
        ..FriSimParams::default()
    };
    assert_eq!(
        bad.validate().unwrap_err().field(),
        Some("fri_sim.packet_loss")
    );
    let bad = FriSimParams {
        receive_multiplier: 30,
        fri_period_ms: 5,
        ..FriSimParams::default()
    };
    assert_eq!(
        bad.validate().unwrap_err().field(),
        Some("fri_sim.receive_multiplier")
    );
    assert!(SimController::new(bad, 0).is_err());
    let bad = FriClientParams {
        guard: GuardParams {
            velocity_fraction: 1.5,
            ..GuardParams::default()
        },
        ..FriClientParams::default()
    };
    assert_eq!(
        FriClient::new(bad).unwrap_err().field(),
        Some("fri.guard.velocity_fraction")
    );
    let toml_err = toml::from_str::<FriSimParams>("fri_period_mss = 5").unwrap_err();
    assert!(toml_err.to_string().contains("fri_period_mss"));
    let from_robot = FriSimParams::from_robot(&crate::params::RobotParams::default());
    assert_eq!(from_robot, FriSimParams::default());
}

/// A test control: in COMMANDING_ACTIVE moves A1 by `amp_rad` along a smooth
/// bell of `dur_s` (peak speed `amp_rad * pi / dur_s`), then holds.
#[derive(Debug, Default)]
struct Bell {
    start: Option<f64>,
    steps: u64,
    amp_rad: f64,
    dur_s: f64,
    /// The command of every reply, rad.
    commands: Vec<f64>,
}

impl ControlStep for Bell {
    fn step(&mut self, input: &StepInput<'_>, command_rad: &mut Joints) {
        if !input.commanding {
            return;
        }
        let s = *self.start.get_or_insert(command_rad[0]);
        self.steps += 1;
        let x = (self.steps as f64 * input.receive_period_s / self.dur_s).min(1.0);
        command_rad[0] = s + self.amp_rad * (1.0 - (std::f64::consts::PI * x).cos()) / 2.0;
        self.commands.push(command_rad[0]);
    }
}

/// Velocities of a path sampled once per period, rad/s.
fn speeds(path: &[f64], period_s: f64) -> Vec<f64> {
    path.windows(2).map(|w| (w[1] - w[0]) / period_s).collect()
}

/// Root mean square of the step-to-step change of `v`.
fn rms_change(v: &[f64]) -> f64 {
    let d: Vec<f64> = v.windows(2).map(|w| w[1] - w[0]).collect();
    (d.iter().map(|x| x * x).sum::<f64>() / d.len() as f64).sqrt()
}

/// Runs a bell motion of A1 and returns the true A1 at every tick from the
/// first command on, and the control.
fn bell_path(p: FriSimParams) -> (Vec<f64>, Bell, Arc<crate::sim::kuka::SimStats>) {
    let mut rig = Rig::new(p, FriClientParams::default());
    let mut ctl = Bell {
        amp_rad: 0.4,
        dur_s: 1.0,
        ..Bell::default()
    };
    rig.run_until(500, &mut ctl, active);
    let mut path = Vec::new();
    let n = 1.2e3 / f64::from(rig.sim.params().fri_period_ms);
    for _ in 0..n as usize {
        rig.run(1, &mut ctl);
        path.push(rig.sim.joint_rad()[0]);
    }
    let stats = Arc::clone(rig.sim.stats());
    (path, ctl, stats)
}

#[test]
fn latency_jitter_never_time_warps_the_arms_motion() {
    // The default lab: 5 ms periods, 8 ms latency, +-2 ms jitter.
    let jittery = FriSimParams {
        latency_ms: 8.0,
        latency_jitter_ms: 2.0,
        fri_period_ms: 5,
        ..FriSimParams::default()
    };
    let (path, ctl, stats) = bell_path(jittery.clone());
    // Jitter below half a period never moves a command out of its cycle:
    // the path is the one without jitter.
    let (steady, _, _) = bell_path(FriSimParams {
        latency_jitter_ms: 0.0,
        ..jittery
    });
    assert_eq!(path, steady);
    assert_eq!(stats.late_commands.load(Relaxed), 0);
    assert_eq!(stats.held_cycles.load(Relaxed), 0);
    // As smooth as the command (the first-order servo only smooths it), and
    // no faster than it (a first-order servo does not overshoot).
    let v = speeds(&path, 0.005);
    let v_cmd = speeds(&ctl.commands, 0.005);
    let (rough, rough_cmd) = (rms_change(&v), rms_change(&v_cmd));
    assert!(rough <= rough_cmd * 1.01, "{rough} vs {rough_cmd} rad/s");
    let peak = v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let peak_cmd = v_cmd.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    assert!(peak <= peak_cmd * 1.001, "{peak} vs {peak_cmd} rad/s");
    assert!(peak > peak_cmd * 0.95, "{peak} vs {peak_cmd} rad/s");
}

#[test]
fn jitter_beyond_half_a_period_moves_commands_by_whole_cycles() {
    // 1 ms periods with +-2 ms jitter: commands land up to two cycles off
    // their own; the servo sees whole-cycle holds and catch-ups, counted.
    let (path, ctl, stats) = bell_path(FriSimParams {
        latency_ms: 8.0,
        latency_jitter_ms: 2.0,
        fri_period_ms: 1,
        ..FriSimParams::default()
    });
    assert!(stats.late_commands.load(Relaxed) > 0);
    assert!(stats.held_cycles.load(Relaxed) > 0);
    assert!(stats.superseded_commands.load(Relaxed) > 0);
    // Commands shift by at most two cycles each way, so the setpoint is held
    // for at most four cycles: the first-order servo's error stays within its
    // lag plus four commanded steps, its speed (error / tau) within
    // 1 + 4 * 1 ms / 5 ms of the commanded one.
    let peak = speeds(&path, 0.001)
        .iter()
        .fold(0.0f64, |m, x| m.max(x.abs()));
    let peak_cmd = speeds(&ctl.commands, 0.001)
        .iter()
        .fold(0.0f64, |m, x| m.max(x.abs()));
    assert!(
        peak <= peak_cmd * (1.0 + 4.0 / 5.0),
        "{peak} vs {peak_cmd} rad/s"
    );
}

#[test]
fn a_late_reply_holds_its_cycle_once_and_is_counted() {
    let p = FriSimParams {
        latency_ms: 8.0,
        latency_jitter_ms: 0.0,
        servo_time_constant_ms: 5.0,
        fri_period_ms: 5,
        ..FriSimParams::default()
    };
    let mut rig = Rig::new(p, FriClientParams::default());
    let mut ctl = Mover {
        speed_radps: 0.5,
        ..Mover::default()
    };
    rig.run_until(500, &mut ctl, active);
    rig.run(20, &mut ctl);
    let period = rig.period_ns();
    let hop = rig.hop_ns;
    // The setpoint A1 follows, at every tick.
    let mut setpoints = Vec::new();
    let mut late = None;
    for k in 0..40 {
        let t = rig.t_ns;
        if let Some(m) = rig.sim.tick(t)
            && let Some(r) = rig.client.on_datagram(m, t + hop, &mut ctl)
        {
            let r = r.to_vec();
            if k == 10 {
                // This answer reaches the controller after the next message
                // left (its deadline): late.
                late = Some(r);
            } else {
                rig.sim.on_reply(&r, t + 2 * hop);
            }
        }
        setpoints.push(rig.sim.stats().setpoint_rad.load()[0]);
        rig.client.poll(t + hop, &mut ctl);
        rig.t_ns += period;
        if let Some(r) = late.take_if(|_| k == 10) {
            let t = rig.t_ns;
            let m = rig.sim.tick(t).map(<[u8]>::to_vec);
            rig.sim.on_reply(&r, t + hop / 2);
            if let Some(m) = m
                && let Some(r) = rig.client.on_datagram(&m, t + hop, &mut ctl)
            {
                rig.sim.on_reply(r, t + 2 * hop);
            }
            setpoints.push(rig.sim.stats().setpoint_rad.load()[0]);
            rig.client.poll(t + hop, &mut ctl);
            rig.t_ns += period;
        }
    }
    let s = rig.sim.stats();
    assert_eq!(s.late_replies.load(Relaxed), 1);
    assert_eq!(s.late_commands.load(Relaxed), 1);
    assert_eq!(s.held_cycles.load(Relaxed), 1);
    assert_eq!(s.superseded_commands.load(Relaxed), 1);
    assert_eq!(rig.sim.state(), SessionState::CommandingActive);
    // Every cycle the setpoint moves one command step on, except one held
    // cycle, made up by a double step the cycle after.
    let step = 0.5 * 0.005;
    let moves: Vec<f64> = setpoints
        .windows(2)
        .map(|w| ((w[1] - w[0]) / step).round())
        .collect();
    assert_eq!(moves.iter().filter(|m| **m == 0.0).count(), 1, "{moves:?}");
    assert_eq!(moves.iter().filter(|m| **m == 2.0).count(), 1, "{moves:?}");
    assert_eq!(
        moves.iter().filter(|m| **m == 1.0).count(),
        moves.len() - 2,
        "{moves:?}"
    );
    let held = moves.iter().position(|m| *m == 0.0).unwrap();
    assert_eq!(moves[held + 1], 2.0, "{moves:?}");
}

/// The reality lab's robot with `[world.robot]`'s network keys `set` on a
/// truthful world, plugged into `rig`.
fn world_network(rig: &mut Rig, set: impl FnOnce(&mut crate::sim::world::WorldParams)) {
    use crate::params::RangeParam;
    let mut w = crate::sim::world::WorldParams::default();
    // The truthful robot's latency (the rig's), so only the network differs.
    w.robot.latency_ms = Some(RangeParam::fixed(rig.sim.params().latency_ms));
    set(&mut w);
    w.validate().unwrap();
    let session = w.draw_session(3, 0, rig.sim.params().latency_ms);
    let period_s = rig.period_ns() as f64 * 1e-9;
    let robot = WorldRobot::for_session(
        &w,
        &session,
        *rig.sim.joint_rad(),
        rig.sim.params().servo_time_constant_ms * 1e-3,
        period_s,
        0.0,
        [5, 6],
    );
    rig.sim.set_world(Some(robot));
}

#[test]
fn the_reality_labs_network_loses_delays_and_jitters_datagrams() {
    use crate::params::RangeParam;
    let mut rig = Rig::new(FriSimParams::default(), FriClientParams::default());
    let mut ctl = Mover {
        speed_radps: 0.05,
        ..Mover::default()
    };
    let period_ms = rig.period_ns() as f64 * 1e-6;
    world_network(&mut rig, |w| {
        w.robot.packet_loss = RangeParam::fixed(0.02);
        w.robot.reply_loss = RangeParam::fixed(0.015);
        w.robot.message_latency_ms = RangeParam::fixed(0.4);
        w.robot.message_jitter_ms = RangeParam::fixed(0.2);
        // Jitter of 1.5 periods either way: some commands land a cycle late.
        w.robot.command_jitter_ms = RangeParam::fixed(1.5 * period_ms);
    });
    // A message carries what was measured when it left, one latency before
    // the PC gets it: its timestamp is 0.4-0.6 ms before the PC's clock.
    let mut dec = crate::fri::codec::MonitoringDecoder::new();
    let mut lags = Vec::new();
    for _ in 0..50 {
        let t = rig.t_ns;
        if let Some(m) = rig.sim.tick(t) {
            let ts = dec.decode(m).unwrap().timestamp.unwrap();
            let ns = u64::from(ts.sec) * 1_000_000_000 + u64::from(ts.nanosec);
            lags.push(t as f64 - (ns - 1_790_000_000_000_000_000) as f64);
        }
        rig.t_ns += rig.period_ns();
    }
    assert!(lags.len() > 40);
    // (The first message, at time 0, has nothing earlier to carry.)
    assert!(
        lags[1..]
            .iter()
            .all(|l| (0.4e6 - 1.0..=0.6e6 + 1.0).contains(l)),
        "{lags:?}"
    );
    rig.run_until(400, &mut ctl, active);
    rig.run(3000, &mut ctl);
    let st = rig.sim.stats();
    let sent = st.messages_sent.load(Relaxed) as f64;
    let lost = st.messages_dropped.load(Relaxed) as f64 / sent;
    assert!((0.01..0.03).contains(&lost), "monitoring lost {lost}");
    let (replies, dropped) = (
        st.replies.load(Relaxed) as f64,
        st.replies_dropped.load(Relaxed) as f64,
    );
    let lost_back = dropped / (replies + dropped);
    assert!(
        (0.007..0.025).contains(&lost_back),
        "replies lost {lost_back}"
    );
    // Round trip: both ways' latency and jitter plus the rig's two hops.
    let rtt = st.rtt.summary_us();
    assert!((900.0..=1300.0).contains(&rtt.p50), "{rtt:?}");
    assert!(rtt.max <= 1400.0, "{rtt:?}");
    assert!(
        st.late_commands.load(Relaxed) > 100,
        "the command jitter acts"
    );
    // Through all of it, commanding goes on.
    assert_eq!(st.aborts.load(Relaxed), 0, "{:?}", st.last_abort());
    assert_eq!(rig.sim.state(), SessionState::CommandingActive);
}

#[test]
fn a_truthful_world_network_changes_nothing() {
    let run = |with_world: bool| {
        let mut rig = Rig::new(FriSimParams::default(), FriClientParams::default());
        if with_world {
            world_network(&mut rig, |_| {});
        }
        let mut ctl = Mover {
            speed_radps: 0.05,
            ..Mover::default()
        };
        rig.run_until(400, &mut ctl, active);
        rig.run(500, &mut ctl);
        let st = rig.sim.stats();
        (
            st.messages_dropped.load(Relaxed),
            st.replies_dropped.load(Relaxed),
            st.late_commands.load(Relaxed),
            st.rtt.summary_us().max,
        )
    };
    let (lost, lost_back, late, rtt_max) = run(true);
    assert_eq!((lost, lost_back, late), (0, 0, 0));
    assert_eq!(rtt_max, run(false).3);
}

/// A control that moves A1 with the clock (as the trial driver does): after
/// a lost message its next command is two periods further.
#[derive(Debug, Default)]
struct Clocked {
    t0_ns: Option<u64>,
    start: Joints,
    speed_radps: f64,
}

impl ControlStep for Clocked {
    fn step(&mut self, input: &StepInput<'_>, command_rad: &mut Joints) {
        if !input.commanding {
            return;
        }
        if self.t0_ns.is_none() {
            self.t0_ns = Some(input.now_ns);
            self.start = *command_rad;
        }
        let dt = (input.now_ns - self.t0_ns.unwrap_or(input.now_ns)) as f64 * 1e-9;
        command_rad[0] = self.start[0] + self.speed_radps * dt;
    }

    fn stop(&mut self, _reason: StopReason) {}
}

#[test]
fn a_step_over_a_lost_message_may_cover_the_periods_it_spans() {
    let mut rig = Rig::new(FriSimParams::default(), FriClientParams::default());
    // 60% of A1's speed limit: one period's step is inside the guard's 95%,
    // two periods' step is not, unless the guard counts both periods.
    let mut ctl = Clocked {
        speed_radps: 0.6 * VELOCITY_LIMIT_RADPS[0],
        ..Clocked::default()
    };
    rig.run_until(400, &mut ctl, active);
    rig.run(20, &mut ctl);
    let lose = |rig: &mut Rig, n: u64| {
        for _ in 0..n {
            let _ = rig.sim.tick(rig.t_ns);
            rig.t_ns += rig.period_ns();
        }
    };
    // One message lost: the next command is two periods on, at the same speed.
    lose(&mut rig, 1);
    rig.run(20, &mut ctl);
    let cs = rig.client.stats().snapshot();
    assert_eq!(cs.guard_step, 0, "a step over two periods is not clipped");
    assert_eq!(rig.sim.stats().aborts.load(Relaxed), 0, "nor refused");
    assert_eq!(rig.sim.state(), SessionState::CommandingActive);
    // Five lost: the step is clipped to three periods' worth, and the
    // controller takes it.
    lose(&mut rig, 5);
    rig.run(1, &mut ctl);
    assert!(rig.client.stats().snapshot().guard_step >= 1);
    assert_eq!(rig.sim.stats().aborts.load(Relaxed), 0);
}

#[test]
fn the_histogram_quantile_is_the_nearest_rank_within_its_bucket() {
    let exact = |v: &[u64], q: f64| {
        let rank = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len());
        v[rank - 1]
    };
    // Below 128 ns every value has its bucket: the nearest rank exactly, and
    // within one rank of the interpolating rule of every other figure.
    let small: Vec<u64> = (1..=100).collect();
    let h = crate::fri::stats::LatencyHistogram::new();
    for &v in &small {
        h.record_ns(v);
    }
    let as_f64: Vec<f64> = small.iter().map(|&v| v as f64).collect();
    for q in [0.0, 0.1, 0.5, 0.95, 0.99, 0.999, 1.0] {
        assert_eq!(h.quantile_ns(q), exact(&small, q), "q {q}");
        let linear = crate::quantile::quantile(&as_f64, q).unwrap();
        assert!((h.quantile_ns(q) as f64 - linear).abs() <= 1.0, "q {q}");
    }
    // Above: within 0.4% of the nearest rank's value.
    let large: Vec<u64> = (1..=5000u64).map(|i| 1000 + i * i * 37).collect();
    let h = crate::fri::stats::LatencyHistogram::new();
    for &v in &large {
        h.record_ns(v);
    }
    for q in [0.5, 0.9, 0.99, 0.999] {
        let (got, want) = (h.quantile_ns(q) as f64, exact(&large, q) as f64);
        assert!((got - want).abs() <= 0.004 * want, "q {q}: {got} vs {want}");
    }
}
