//! Magnet driver: one command's round trip through the driver thread, the reader
//! thread and a pty, against the in-process fake device and, when `make firmware`
//! has built it, the real firmware in simavr (where the UART's 115200 baud is
//! simulated, so long answers cost their wire time: ~87 us per byte).
//! Also the lock-free view read that real-time callers use.
#![allow(
    missing_docs,
    reason = "a criterion bench: its generated main has no docs"
)]

use std::{
    hint::black_box,
    path::{Path, PathBuf},
    process::{Child, Command as Process, Stdio},
    time::{Duration, Instant},
};

use criterion::{Criterion, criterion_group, criterion_main};
use rt_core::magnet::{Command, LinkState, MagnetHandle, MagnetParams, MagnetState};
use rt_core::sim::magnet::FakeDevice;

fn link(tag: &str) -> PathBuf {
    tempfile::Builder::new()
        .prefix(&format!("isochron-bench-{tag}-"))
        .tempdir()
        .expect("a temporary directory")
        .keep()
        .join("tty")
}

fn driver(port: &Path) -> MagnetHandle {
    let h = MagnetHandle::spawn(MagnetParams {
        port: port.to_string_lossy().into_owned(),
        status_poll_ms: 600_000.0,
        ..MagnetParams::default()
    })
    .expect("driver");
    let (v, ok) = h.wait_for(Duration::from_secs(5), |v| {
        v.link == LinkState::Connected && v.magnet != MagnetState::Unknown
    });
    assert!(ok, "not connected: {v:?}");
    h
}

fn round_trips(c: &mut Criterion, name: &str, h: &MagnetHandle) {
    c.bench_function(&format!("magnet_ping_round_trip_{name}"), |b| {
        b.iter(|| {
            black_box(
                h.submit(Command::Ping("b1".to_owned()))
                    .unwrap()
                    .wait()
                    .unwrap(),
            )
        });
    });
    c.bench_function(&format!("magnet_status_round_trip_{name}"), |b| {
        b.iter(|| black_box(h.status().unwrap()));
    });
    c.bench_function(&format!("magnet_switch_round_trip_{name}"), |b| {
        let mut on = false;
        b.iter(|| {
            on = !on;
            black_box(h.set_magnet(on).unwrap())
        });
    });
}

fn simavr(port: &Path) -> Option<Child> {
    let build = Path::new(env!("CARGO_MANIFEST_DIR")).join("../firmware/magnet/build");
    let (elf, host) = (build.join("magnet.elf"), build.join("magnet-sim"));
    if !(elf.is_file() && host.is_file()) {
        eprintln!("magnet bench: no firmware build (make firmware); simavr benches skipped");
        return None;
    }
    let _ = std::fs::remove_file(port);
    let child = Process::new(host)
        .arg(elf)
        .arg(port)
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .ok()?;
    let deadline = Instant::now() + Duration::from_secs(5);
    while !port.exists() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(5));
    }
    Some(child)
}

fn bench(c: &mut Criterion) {
    let fake_path = link("fake");
    let _fake = FakeDevice::start(&fake_path).expect("fake device");
    let h = driver(&fake_path);
    round_trips(c, "fake", &h);
    c.bench_function("magnet_view_read", |b| b.iter(|| black_box(h.view())));
    drop(h);

    let sim_path = link("sim");
    if let Some(mut child) = simavr(&sim_path) {
        let h = driver(&sim_path);
        round_trips(c, "simavr", &h);
        drop(h);
        let _ = child.kill();
        let _ = child.wait();
        let _ = std::fs::remove_file(&sim_path);
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default()
        .sample_size(30)
        .warm_up_time(Duration::from_millis(300))
        .measurement_time(Duration::from_secs(2));
    targets = bench
}
criterion_main!(benches);
