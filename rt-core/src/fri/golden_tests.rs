//! Golden bytes per FRI version (`golden/fri-<v>.hex`, written by
//! `golden/make_golden.py` from the schemas, not by this codec), framing and
//! the CRC check in front of the control step.

use std::sync::atomic::Ordering::Relaxed;

use super::client::{ControlStep, FriClient, FriClientParams, StepInput};
use super::codec::*;
use super::proto::*;
use super::version::FriVersion;

fn fixture(v: FriVersion, name: &str) -> Vec<u8> {
    let text = match v {
        FriVersion::V1_11 => include_str!("golden/fri-1.11.hex"),
        FriVersion::V1_14 => include_str!("golden/fri-1.14.hex"),
        FriVersion::V1_15 => include_str!("golden/fri-1.15.hex"),
        FriVersion::V1_16 => include_str!("golden/fri-1.16.hex"),
        FriVersion::V2_5 => include_str!("golden/fri-2.5.hex"),
        FriVersion::V2_7 => include_str!("golden/fri-2.7.hex"),
    };
    let hex = text
        .lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' '))
        .unwrap_or_else(|| panic!("{name} in fri-{v}.hex"));
    (0..hex.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).unwrap())
        .collect()
}

const Q: Joints = [0.1, -0.2, 0.3, -1.4, 0.5, 0.6, -0.7];
const QC: Joints = [0.11, -0.21, 0.31, -1.41, 0.51, 0.61, -0.71];
const FORCE: Wrench = [1.5, -2.0, 3.25, 0.125, -0.5, 0.0];

/// The view behind the golden monitoring message (every version's encoder is
/// given all fields; it writes those its version defines).
fn golden_view() -> Monitoring {
    Monitoring {
        sequence_counter: 7,
        reflected_sequence_counter: 6,
        session_state: SessionState::MonitoringWait,
        quality: ConnectionQuality::Good,
        send_period_ms: 5,
        receive_multiplier: 1,
        measured_joint_position_rad: Some(Q),
        commanded_joint_position_rad: Some(QC),
        external_force: Some(FORCE),
        ..Monitoring::default()
    }
}

#[test]
fn every_version_writes_and_reads_its_golden_bytes() {
    for v in FriVersion::ALL {
        let golden = fixture(v, "monitoring");
        let mut enc = MonitoringEncoder::with_version(v);
        assert_eq!(enc.encode(&golden_view()).unwrap(), &golden[..], "FRI {v}");
        let m = MonitoringDecoder::with_version(v).decode(&golden).unwrap();
        let expected = Monitoring {
            commanded_joint_position_rad: v.has_commanded_joint_position().then_some(QC),
            external_force: v.has_external_force().then_some(FORCE),
            ..golden_view()
        };
        assert_eq!(m, expected, "FRI {v}");

        let mut cenc = CommandEncoder::with_version(v);
        let header_only = fixture(v, "command_header_only");
        assert_eq!(
            cenc.encode(1, 2, None).unwrap(),
            &header_only[..],
            "FRI {v}"
        );
        let position = fixture(v, "command_position");
        assert_eq!(
            cenc.encode(3, 7, Some(&Q)).unwrap(),
            &position[..],
            "FRI {v}"
        );
        assert_eq!(position.len(), if v.framed() { 85 } else { 77 });
        let c = CommandDecoder::with_version(v).decode(&position).unwrap();
        assert_eq!(
            (
                c.sequence_counter,
                c.reflected_sequence_counter,
                c.joint_position_rad
            ),
            (3, 7, Some(Q))
        );
    }
}

#[test]
fn a_decoder_of_one_version_skips_fields_its_schema_lacks() {
    // A 1.15 message read as 2.5: commandedJointPosition (monitorData 3) is not
    // a 2.5 field, so it is not seen; the client then hands over from others.
    let m = MonitoringDecoder::with_version(FriVersion::V2_5)
        .decode(&fixture(FriVersion::V1_15, "monitoring"))
        .unwrap();
    assert_eq!(m.commanded_joint_position_rad, None);
    assert_eq!(m.measured_joint_position_rad, Some(Q));
    // 2.7's externalForce is not read by an older decoder.
    let mut bare = fixture(FriVersion::V2_7, "monitoring");
    bare.truncate(bare.len() - 4);
    bare.drain(..4);
    let m = MonitoringDecoder::with_version(FriVersion::V2_5)
        .decode(&bare)
        .unwrap();
    assert_eq!(m.external_force, None);
    // 1.x transformations have 12 values, 2.x quaternions 7.
    let mut msg = decode_monitoring_message(&fixture(FriVersion::V1_15, "monitoring")).unwrap();
    msg.requested_transformations.push(Transformation {
        name: Some("tool".into()),
        matrix: vec![0.0; 7],
        timestamp: None,
    });
    let bytes = msg.encode_to_vec();
    assert!(matches!(
        decode_monitoring_message(&bytes),
        Err(CodecError::ValueCount { expected: 12, .. })
    ));
    assert!(decode_monitoring_message_of(&bytes, FriVersion::V2_5).is_ok());
}

#[test]
fn framing_mismatches_are_refused_both_ways() {
    let framed = fixture(FriVersion::V2_7, "monitoring");
    let bare = fixture(FriVersion::V1_15, "monitoring");
    assert!(
        MonitoringDecoder::with_version(FriVersion::V1_15)
            .decode(&framed)
            .is_err()
    );
    assert!(matches!(
        MonitoringDecoder::with_version(FriVersion::V2_7).decode(&bare),
        Err(CodecError::Frame(_))
    ));
    let mut short = framed.clone();
    short.pop();
    assert!(matches!(
        MonitoringDecoder::with_version(FriVersion::V2_7).decode(&short),
        Err(CodecError::Frame(super::framing::FrameError::Length { .. }))
    ));
}

#[derive(Default)]
struct CountSteps {
    steps: u32,
}

impl ControlStep for CountSteps {
    fn step(&mut self, _input: &StepInput<'_>, _command_rad: &mut Joints) {
        self.steps += 1;
    }
}

/// The acceptance check: a 2.7 datagram with one flipped bit is rejected by the
/// CRC, counted, and never reaches the control step; every bit position is tried.
#[test]
fn a_flipped_bit_in_a_2_7_datagram_is_counted_and_never_reaches_the_control_step() {
    let params = FriClientParams {
        version: FriVersion::V2_7,
        ..FriClientParams::default()
    };
    let mut client = FriClient::new(params).unwrap();
    let mut ctl = CountSteps::default();
    let good = fixture(FriVersion::V2_7, "monitoring");
    assert!(client.on_datagram(&good, 1_000_000, &mut ctl).is_some());
    assert_eq!(ctl.steps, 1);
    // Bits of the protobuf message and of the CRC: the CRC check refuses them.
    let crc_bits = 32..(good.len() * 8);
    for (i, bit) in crc_bits.clone().enumerate() {
        let mut bad = good.clone();
        bad[bit / 8] ^= 1 << (bit % 8);
        let t = 2_000_000 + i as u64 * 1_000;
        assert!(client.on_datagram(&bad, t, &mut ctl).is_none(), "bit {bit}");
    }
    let n = crc_bits.len() as u64;
    let st = std::sync::Arc::clone(client.stats());
    assert_eq!(
        ctl.steps, 1,
        "a corrupted datagram reached the control step"
    );
    assert_eq!(st.crc_errors.load(Relaxed), n);
    // Bits of the length field: refused by the length check.
    for bit in 0..32 {
        let mut bad = good.clone();
        bad[bit / 8] ^= 1 << (bit % 8);
        assert!(client.on_datagram(&bad, 9_000_000_000, &mut ctl).is_none());
    }
    assert_eq!(ctl.steps, 1);
    assert_eq!(st.frame_length_errors.load(Relaxed), 32);
    assert_eq!(st.decode_errors.load(Relaxed), n + 32);
    assert_eq!(st.snapshot().crc_errors, n);
    assert_eq!(st.snapshot().version, "2.7");
}

use prost::Message as _;
