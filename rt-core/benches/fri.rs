//! FRI codec: encode + decode of one command and one monitoring message, and one
//! whole client cycle (decode, control step, guard, encode).

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use rt_core::fri::{
    CommandDecoder, CommandEncoder, ConnectionQuality, FriClient, FriClientParams, HoldPosition,
    Monitoring, MonitoringDecoder, MonitoringEncoder, SessionState, UnixTime,
};

fn monitoring(seq: u32) -> Monitoring {
    let q = [0.1, 0.5, -0.2, -1.4, 0.3, 0.9, -0.1];
    Monitoring {
        sequence_counter: seq,
        reflected_sequence_counter: seq,
        session_state: SessionState::CommandingActive,
        quality: ConnectionQuality::Excellent,
        send_period_ms: 1,
        receive_multiplier: 1,
        measured_joint_position_rad: Some(q),
        measured_torque_nm: Some([1.0; 7]),
        commanded_joint_position_rad: Some(q),
        commanded_torque_nm: Some([1.0; 7]),
        external_torque_nm: Some([0.0; 7]),
        timestamp: Some(UnixTime {
            sec: 1_790_000_000,
            nanosec: 1,
        }),
        ipo_joint_position_rad: Some(q),
        ..Monitoring::default()
    }
}

fn codec(c: &mut Criterion) {
    let q = [0.1, 0.5, -0.2, -1.4, 0.3, 0.9, -0.1];
    let mut cenc = CommandEncoder::new();
    let mut cdec = CommandDecoder::new();
    c.bench_function("fri/command encode+decode", |b| {
        let mut seq = 0u32;
        b.iter(|| {
            seq = seq.wrapping_add(1);
            let bytes = cenc.encode(seq, seq, Some(black_box(&q))).unwrap_or(&[]);
            black_box(cdec.decode(bytes).ok());
        });
    });
    let mut menc = MonitoringEncoder::new();
    let mut mdec = MonitoringDecoder::new();
    c.bench_function("fri/monitoring encode+decode", |b| {
        let mut m = monitoring(0);
        b.iter(|| {
            m.sequence_counter = m.sequence_counter.wrapping_add(1);
            let bytes = menc.encode(black_box(&m)).unwrap_or(&[]);
            black_box(mdec.decode(bytes).ok());
        });
    });
    let mut enc = MonitoringEncoder::new();
    let mut datagrams: Vec<Vec<u8>> = Vec::new();
    for s in 0..64 {
        if let Ok(b) = enc.encode(&monitoring(s)) {
            datagrams.push(b.to_vec());
        }
    }
    if let Ok(mut client) = FriClient::new(FriClientParams::default()) {
        let mut ctl = HoldPosition;
        c.bench_function("fri/client cycle (decode, step, guard, encode)", |b| {
            let mut i = 0usize;
            let mut t = 0u64;
            b.iter(|| {
                i = (i + 1) % datagrams.len();
                t += 1_000_000;
                black_box(
                    client
                        .on_datagram(&datagrams[i], t, &mut ctl)
                        .map(<[u8]>::len),
                );
            });
        });
    }
}

criterion_group!(benches, codec);
criterion_main!(benches);
