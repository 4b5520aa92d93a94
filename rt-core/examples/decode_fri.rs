//! Decode an FRI datagram: the controller's monitoring message of a
//! commanding session, encoded as KUKA's FRI 2.7 frames it (4-byte length,
//! protobuf, CRC-32), decoded back into the fixed-size view the client acts
//! on; then the same bytes with one bit flipped, which the decoder refuses
//! before reading any field.
//!
//! Run: `cargo run -p rt-core --example decode_fri`, or pass a datagram as
//! hex (`cargo run -p rt-core --example decode_fri -- 0a0b...`) and optionally
//! a version (`--version 1.15`; 2.7 by default) to decode your own capture.
//! It exits non-zero when the round trip changes a field or the flipped bit
//! is accepted.

use rt_core::fri::codec::{Monitoring, MonitoringDecoder, MonitoringEncoder, UnixTime};
use rt_core::fri::{ConnectionQuality, FriVersion, SessionState};

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(text: &str) -> Result<Vec<u8>, String> {
    let text = text.trim();
    if text.len() % 2 != 0 {
        return Err(format!("odd number of hex digits ({})", text.len()));
    }
    (0..text.len())
        .step_by(2)
        .map(|i| {
            u8::from_str_radix(&text[i..i + 2], 16).map_err(|e| format!("not hex at {i}: {e}"))
        })
        .collect()
}

fn version_of(name: &str) -> Result<FriVersion, String> {
    FriVersion::ALL
        .into_iter()
        .find(|v| v.name() == name)
        .ok_or_else(|| format!("unknown FRI version {name} (1.11, 1.14, 1.15, 1.16, 2.5, 2.7)"))
}

fn show(m: &Monitoring) {
    println!(
        "  sequence {} (answers command {}), {:?}, quality {:?}, period {} ms",
        m.sequence_counter,
        m.reflected_sequence_counter,
        m.session_state,
        m.quality,
        m.send_period_ms
    );
    if let Some(q) = m.measured_joint_position_rad {
        let deg: Vec<String> = q.iter().map(|v| format!("{:.2}", v.to_degrees())).collect();
        println!("  measured joints (deg): [{}]", deg.join(", "));
    }
    if let Some(t) = m.external_torque_nm {
        let nm: Vec<String> = t.iter().map(|v| format!("{v:.2}")).collect();
        println!("  external torques (N m): [{}]", nm.join(", "));
    }
    if let Some(t) = m.timestamp {
        println!("  controller time {}.{:09} s", t.sec, t.nanosec);
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut version = FriVersion::V2_7;
    let mut datagram = None;
    let mut i = 0;
    while i < args.len() {
        if args[i] == "--version" {
            version = version_of(args.get(i + 1).ok_or("--version needs a value")?)?;
            i += 2;
        } else {
            datagram = Some(unhex(&args[i])?);
            i += 1;
        }
    }
    let mut decoder = MonitoringDecoder::with_version(version);
    if let Some(bytes) = datagram {
        let m = decoder.decode(&bytes)?;
        println!(
            "FRI {} monitoring message, {} bytes:",
            version.name(),
            bytes.len()
        );
        show(&m);
        return Ok(());
    }

    // A commanding session's message, as the controller sends it.
    let sent = Monitoring {
        sequence_counter: 4711,
        reflected_sequence_counter: 4710,
        session_state: SessionState::CommandingActive,
        quality: ConnectionQuality::Excellent,
        send_period_ms: 5,
        measured_joint_position_rad: Some([0.0, 0.52, 0.0, -1.31, 0.0, 0.87, 0.0]),
        measured_torque_nm: Some([0.1, -12.4, 0.3, 6.2, -0.1, 0.9, 0.0]),
        commanded_joint_position_rad: Some([0.0, 0.52, 0.0, -1.31, 0.0, 0.87, 0.0]),
        external_torque_nm: Some([0.0, 0.4, 0.0, -0.2, 0.0, 0.05, 0.0]),
        timestamp: Some(UnixTime::from_ns(1_764_835_200_123_456_789)),
        ipo_joint_position_rad: Some([0.0, 0.52, 0.0, -1.31, 0.0, 0.87, 0.0]),
        ..Monitoring::default()
    };
    let mut encoder = MonitoringEncoder::with_version(version);
    let bytes = encoder.encode(&sent)?.to_vec();
    println!(
        "FRI {} monitoring datagram, {} bytes:",
        version.name(),
        bytes.len()
    );
    println!("  {}", hex(&bytes));
    let got = decoder.decode(&bytes)?;
    println!("decoded:");
    show(&got);
    for (name, a, b) in [
        (
            "measured joints",
            sent.measured_joint_position_rad,
            got.measured_joint_position_rad,
        ),
        (
            "external torques",
            sent.external_torque_nm,
            got.external_torque_nm,
        ),
    ] {
        if a != b {
            return Err(format!("{name} changed in the round trip: {a:?} -> {b:?}").into());
        }
    }
    if (got.sequence_counter, got.session_state) != (sent.sequence_counter, sent.session_state) {
        return Err("the header changed in the round trip".into());
    }

    // One bit flipped in the middle of the message.
    let mut broken = bytes.clone();
    let mid = broken.len() / 2;
    broken[mid] ^= 0x10;
    match decoder.decode(&broken) {
        Ok(_) => Err("a datagram with a flipped bit was accepted".into()),
        Err(e) => {
            println!("one bit flipped at byte {mid}: refused ({e})");
            Ok(())
        }
    }
}
