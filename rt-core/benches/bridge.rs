//! The control side of the bridge: what one control step pays to publish.
#![allow(
    missing_docs,
    reason = "a criterion bench: its generated main has no docs"
)]

use criterion::{Criterion, criterion_group, criterion_main};
use rt_core::bridge::{BridgeCapacity, Snapshot, bridge};
use std::hint::black_box;

fn publish(c: &mut Criterion) {
    let (mut control, mut server) = bridge(BridgeCapacity::default());
    let mut s = Snapshot::default();
    c.bench_function("bridge_publish_and_drain", |b| {
        b.iter(|| {
            s.seq += 1;
            control.publish(black_box(&s));
            black_box(control.next_command());
            black_box(server.telemetry.pop());
        });
    });
    c.bench_function("bridge_publish_ring_full", |b| {
        b.iter(|| {
            s.seq += 1;
            control.publish(black_box(&s));
        });
    });
    black_box(server.latest.read());
}

criterion_group!(benches, publish);
criterion_main!(benches);
