//! Unit and property tests of the FRI codec, guard, client and simulated controller.

use proptest::prelude::*;
use prost::Message;

use super::codec::*;
use super::proto::*;

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
        assert_eq!(monitoring_view(&full).unwrap(), m);
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
