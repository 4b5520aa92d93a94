use std::{
    path::PathBuf,
    sync::{
        Arc,
        atomic::{AtomicU64, Ordering},
    },
    time::{Duration, Instant},
};

use super::{
    protocol::{Line, parse_line},
    view::ViewCell,
    *,
};
use crate::sim::magnet::{FakeDevice, FirmwareModel};

/// A path for the fake device's link in a fresh private directory (`tempfile`).
fn link_path(tag: &str) -> PathBuf {
    tempfile::Builder::new()
        .prefix(&format!("isochron-fake-{tag}-"))
        .tempdir()
        .expect("a temporary directory")
        .keep()
        .join("tty")
}

fn fast_params(path: &std::path::Path) -> MagnetParams {
    MagnetParams {
        port: path.to_string_lossy().into_owned(),
        command_timeout_ms: 150.0,
        boot_timeout_ms: 600.0,
        reconnect_interval_ms: 50.0,
        status_poll_ms: 200.0,
        ..MagnetParams::default()
    }
}

fn connected(h: &MagnetHandle) -> MagnetView {
    let (v, ok) = h.wait_for(Duration::from_secs(3), |v| {
        v.link == LinkState::Connected && v.magnet != MagnetState::Unknown
    });
    assert!(ok, "never connected: {v:?}");
    v
}

fn feed_all(m: &mut FirmwareModel, bytes: &[u8], now_ms: u64) -> String {
    let mut out = Vec::new();
    for &b in bytes {
        m.feed(b, now_ms, &mut out);
    }
    String::from_utf8(out).unwrap()
}

#[test]
fn parses_answers_and_events() {
    assert_eq!(
        parse_line("OK PONG s7\r"),
        Line::Ok(OkReply::Pong("s7".to_owned()))
    );
    let Line::Ok(OkReply::Status(s)) = parse_line(
        "OK STATUS magnet=on held_ms=12 hold_max_ms=5000 uptime_ms=99 reset=watchdog fw=1",
    ) else {
        panic!("not a status")
    };
    assert!(s.magnet_on);
    assert_eq!((s.held_ms, s.hold_max_ms, s.uptime_ms), (12, 5000, 99));
    assert_eq!(s.reset, Some(ResetCause::Watchdog));
    assert_eq!(
        parse_line("EVT HOLD_LIMIT magnet=off held_ms=1000"),
        Line::Event(DeviceEvent::HoldLimit { held_ms: 1000 })
    );
    assert_eq!(parse_line("ERR bad-byte"), Line::Err("bad-byte".to_owned()));
    // A status without its fields is not a status.
    assert!(matches!(
        parse_line("OK STATUS magnet=maybe"),
        Line::Other(_)
    ));
    assert!(matches!(parse_line("\u{0}\u{ff}garbage"), Line::Other(_)));
}

#[test]
fn model_refuses_bad_lines_without_touching_the_magnet() {
    let mut out = Vec::new();
    let mut m = FirmwareModel::boot(0, ResetCause::Power, &mut out);
    assert!(
        String::from_utf8(out)
            .unwrap()
            .starts_with("EVT BOOT fw=1 reset=power")
    );
    assert!(feed_all(&mut m, b"MAGNET ON\n", 1).starts_with("OK MAGNET magnet=on"));
    for (bad, code) in [
        (&b"\x00\xff\x13MAGNET OFF\n"[..], "ERR bad-byte"),
        (b"MAGNET O\n", "ERR bad-argument"),
        (b"MAGNET OFFF\n", "ERR bad-argument"),
        (b"magnet off\n", "ERR unknown-command"),
        (
            b"MAGNET OFF MAGNET OFF MAGNET OFF MAGNET OFF\n",
            "ERR line-too-long",
        ),
        (b"HOLD 0\n", "ERR bad-argument"),
        (b"HOLD 99999\n", "ERR bad-argument"),
        (b"PING\n", "ERR bad-argument"),
        (b"PING a b\n", "ERR bad-argument"),
    ] {
        let answer = feed_all(&mut m, bad, 2);
        assert_eq!(
            answer,
            format!("{code}\r\n"),
            "{:?}",
            String::from_utf8_lossy(bad)
        );
        assert!(
            m.magnet_on(),
            "{:?} changed the magnet",
            String::from_utf8_lossy(bad)
        );
    }
    // A partial line is completed by the next one: one line, one answer.
    assert_eq!(feed_all(&mut m, b"STA", 3), "");
    assert!(feed_all(&mut m, b"TUS\r\n", 3).starts_with("OK STATUS magnet=on"));
    assert_eq!(
        feed_all(&mut m, b"\n\r\n", 3),
        "",
        "empty lines are ignored"
    );
}

#[test]
fn the_led_command_is_parsed_and_the_model_answers_it() {
    assert_eq!(Command::Led(true).line(), "LED ON");
    assert_eq!(
        parse_line("OK LED led=on uptime_ms=1234\r"),
        Line::Ok(OkReply::Led {
            on: true,
            uptime_ms: 1234
        })
    );
    assert!(matches!(
        parse_line("OK LED led=dim uptime_ms=1"),
        Line::Other(_)
    ));
    assert!(Command::Led(false).expects(&OkReply::Led {
        on: false,
        uptime_ms: 0
    }));
    let mut out = Vec::new();
    let mut m = FirmwareModel::boot(0, ResetCause::Power, &mut out);
    assert_eq!(
        feed_all(&mut m, b"LED ON\n", 5),
        "OK LED led=on uptime_ms=5\r\n"
    );
    assert!(m.led_on() && !m.magnet_on(), "the LED is not the coil");
    assert_eq!(feed_all(&mut m, b"LED BLINK\n", 6), "ERR bad-argument\r\n");
    assert!(m.led_on());
    assert_eq!(
        feed_all(&mut m, b"LED OFF\n", 7),
        "OK LED led=off uptime_ms=7\r\n"
    );
    assert!(!m.led_on());
}

#[test]
fn model_hold_limit_switches_off_and_reports() {
    let mut out = Vec::new();
    let mut m = FirmwareModel::boot(0, ResetCause::Power, &mut out);
    assert_eq!(
        feed_all(&mut m, b"HOLD 2\n", 0),
        "OK HOLD hold_max_ms=2000\r\n"
    );
    feed_all(&mut m, b"MAGNET ON\n", 100);
    // MAGNET ON while on does not extend the hold.
    feed_all(&mut m, b"MAGNET ON\n", 1500);
    let mut out = Vec::new();
    m.tick(2099, &mut out);
    assert!(out.is_empty() && m.magnet_on());
    m.tick(2100, &mut out);
    assert_eq!(
        String::from_utf8(out).unwrap(),
        "EVT HOLD_LIMIT magnet=off held_ms=2000\r\n"
    );
    assert!(!m.magnet_on());
}

#[test]
fn view_round_trips_through_the_sequence_lock() {
    let v = MagnetView {
        link: LinkState::Connected,
        magnet: MagnetState::On,
        changed_at_ns: 123_456_789,
        last_event: Some(EventKind::Switched {
            on: false,
            cause: SwitchCause::HoldLimit,
        }),
        last_event_at_ns: 42,
        events: 7,
        last_reset: Some(ResetCause::Watchdog),
        hold_max_ms: 120_000,
        last_rtt_us: 2100,
        commands: 99,
        timeouts: 3,
        connects: 2,
        stray_lines: 5,
    };
    let cell = ViewCell::new(&MagnetView::default());
    assert_eq!(cell.try_read(), Some(MagnetView::default()));
    cell.publish(&v);
    assert_eq!(cell.try_read(), Some(v));
    for kind in [
        EventKind::Connected,
        EventKind::Lost,
        EventKind::Boot {
            reset: ResetCause::External,
        },
        EventKind::HoldLimit { held_ms: 77 },
    ] {
        let w = MagnetView {
            last_event: Some(kind),
            ..v
        };
        cell.publish(&w);
        assert_eq!(cell.try_read(), Some(w));
    }
}

#[test]
fn readers_never_see_a_torn_view() {
    let cell = Arc::new(ViewCell::new(&MagnetView::default()));
    let enough = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let writer = {
        let cell = Arc::clone(&cell);
        let enough = Arc::clone(&enough);
        std::thread::Builder::new()
            .name("isochron-test-writer".to_owned())
            .spawn(move || {
                let mut i = 0u64;
                while !enough.load(Ordering::Acquire) && i < 50_000_000 {
                    i += 1;
                    cell.publish(&MagnetView {
                        changed_at_ns: i,
                        last_event_at_ns: i,
                        events: i,
                        commands: i,
                        stray_lines: i,
                        ..MagnetView::default()
                    });
                }
            })
            .unwrap()
    };
    let mut reads = 0;
    let mut changes = 0;
    let mut last = 0;
    let deadline = Instant::now() + Duration::from_secs(3);
    while changes < 200 && Instant::now() < deadline {
        if let Some(v) = cell.try_read() {
            reads += 1;
            assert!(
                v.changed_at_ns == v.events
                    && v.events == v.commands
                    && v.commands == v.stray_lines
                    && v.last_event_at_ns == v.events,
                "torn read: {v:?}"
            );
            if v.events != last {
                changes += 1;
                last = v.events;
            }
        }
    }
    enough.store(true, Ordering::Release);
    writer.join().unwrap();
    assert!(
        changes >= 20,
        "only {changes} changes seen in {reads} reads"
    );
}

#[test]
fn params_validation_names_the_field() {
    assert!(MagnetParams::default().validate().is_ok());
    let bad = MagnetParams {
        command_timeout_ms: f64::NAN,
        ..MagnetParams::default()
    };
    assert_eq!(
        bad.validate().unwrap_err().field(),
        Some("magnet.command_timeout_ms")
    );
    let bad = MagnetParams {
        hold_limit_s: 0,
        ..MagnetParams::default()
    };
    assert_eq!(
        bad.validate().unwrap_err().field(),
        Some("magnet.hold_limit_s")
    );
    let bad = MagnetParams::for_port(" ");
    assert_eq!(bad.validate().unwrap_err().field(), Some("magnet.port"));
    assert!(matches!(
        MagnetHandle::spawn(MagnetParams {
            status_poll_ms: -1.0,
            ..MagnetParams::default()
        }),
        Err(MagnetError::Params(_))
    ));
    let e = toml::from_str::<MagnetParams>("command_timeout = 3").unwrap_err();
    assert!(e.to_string().contains("command_timeout"), "{e}");
}

#[test]
fn switches_and_reports_the_true_state_with_release_hook() {
    let path = link_path("switch");
    let released = Arc::new(AtomicU64::new(0));
    let r = Arc::clone(&released);
    let fake = FakeDevice::start_with_pin_hook(
        &path,
        Box::new(move |on, _at| {
            if !on {
                r.fetch_add(1, Ordering::AcqRel);
            }
        }),
    )
    .unwrap();
    // Stale output of a previous session is waiting when the driver opens the port.
    fake.inject(b"OK MAGNET magnet=on held_ms=0 hold_max_ms=1 uptime_ms=1\r\nGARB")
        .unwrap();
    let (tx, rx) = std::sync::mpsc::sync_channel(64);
    let h = MagnetHandle::spawn_with_hook(
        fast_params(&path),
        Box::new(move |e| {
            let _ = tx.try_send(*e);
        }),
    )
    .unwrap();
    let v = connected(&h);
    assert_eq!(v.magnet, MagnetState::Off, "stale bytes were believed");
    assert_eq!(v.hold_max_ms, 120_000);

    let s = h.set_magnet(true).unwrap();
    assert!(s.magnet_on && fake.magnet_on());
    assert_eq!(h.view().magnet, MagnetState::On);
    let before = Instant::now();
    let s = h.set_magnet(false).unwrap();
    assert!(!s.magnet_on && !fake.magnet_on());
    assert_eq!(released.load(Ordering::Acquire), 1);
    let v = h.view();
    assert_eq!(v.magnet, MagnetState::Off);
    assert_eq!(
        v.last_event,
        Some(EventKind::Switched {
            on: false,
            cause: SwitchCause::Command
        })
    );
    let changed = h.epoch() + Duration::from_nanos(v.changed_at_ns);
    assert!(changed >= before && changed <= Instant::now());
    let events: Vec<EventKind> = rx.try_iter().map(|e| e.kind).collect();
    assert!(events.contains(&EventKind::Connected), "{events:?}");
    assert!(events.contains(&EventKind::Switched {
        on: false,
        cause: SwitchCause::Command
    }));
    assert!(v.last_rtt_us > 0);
}

#[test]
fn device_errors_are_reported_and_change_nothing() {
    let path = link_path("err");
    let fake = FakeDevice::start(&path).unwrap();
    let h = MagnetHandle::spawn(fast_params(&path)).unwrap();
    connected(&h);
    h.set_magnet(true).unwrap();
    let e = h
        .submit(Command::Raw("MAGNET SIDEWAYS".to_owned()))
        .unwrap()
        .wait();
    assert_eq!(
        e,
        Err(MagnetError::Device {
            command: "MAGNET SIDEWAYS".to_owned(),
            code: "bad-argument".to_owned()
        })
    );
    assert!(fake.magnet_on());
    assert!(h.status().unwrap().magnet_on);
}

#[test]
fn the_device_own_switch_off_is_seen_from_the_hold_limit_event() {
    let path = link_path("hold");
    let fake = FakeDevice::start(&path).unwrap();
    let h = MagnetHandle::spawn(MagnetParams {
        hold_limit_s: 1,
        ..fast_params(&path)
    })
    .unwrap();
    connected(&h);
    assert_eq!(h.view().hold_max_ms, 1000);
    h.set_magnet(true).unwrap();
    let (v, ok) = h.wait_for(Duration::from_secs(3), |v| v.magnet == MagnetState::Off);
    assert!(ok, "{v:?}");
    assert!(!fake.magnet_on());
    assert!(
        matches!(
            v.last_event,
            Some(EventKind::Switched {
                on: false,
                cause: SwitchCause::HoldLimit
            })
        ),
        "{v:?}"
    );
}

#[test]
fn a_silent_device_times_out_then_the_link_recovers() {
    let path = link_path("silent");
    let fake = FakeDevice::start(&path).unwrap();
    let p = fast_params(&path);
    let h = MagnetHandle::spawn(p.clone()).unwrap();
    connected(&h);
    h.set_magnet(true).unwrap();
    fake.set_silent(true);
    let t0 = Instant::now();
    let e = h.status().unwrap_err();
    let took = t0.elapsed();
    assert!(matches!(e, MagnetError::Timeout { .. }), "{e}");
    // The answer comes after one command timeout plus one failed resynchronisation.
    assert!(
        took < Duration::from_secs_f64((p.command_timeout_ms + p.boot_timeout_ms) / 1000.0 + 0.3),
        "{took:?}"
    );
    let v = h.view();
    assert_eq!(v.link, LinkState::Lost);
    assert_eq!(v.magnet, MagnetState::Unknown);
    assert!(v.timeouts >= 1);
    fake.set_silent(false);
    let (v, ok) = h.wait_for(Duration::from_secs(3), |v| {
        v.link == LinkState::Connected && v.magnet == MagnetState::On
    });
    assert!(ok, "{v:?}");
    assert!(v.connects >= 2);
}

#[test]
fn unplugging_fails_at_once_and_replugging_reconnects() {
    let path = link_path("unplug");
    let mut fake = FakeDevice::start(&path).unwrap();
    let h = MagnetHandle::spawn(fast_params(&path)).unwrap();
    connected(&h);
    fake.unplug();
    let (v, ok) = h.wait_for(Duration::from_secs(2), |v| v.link == LinkState::Lost);
    assert!(ok, "{v:?}");
    assert_eq!(v.magnet, MagnetState::Unknown);
    match h.set_magnet(true) {
        Err(MagnetError::NotConnected { port, reason }) => {
            assert_eq!(port, path.to_string_lossy());
            assert!(!reason.is_empty());
        }
        other => panic!("expected NotConnected, got {other:?}"),
    }
    // Said for people, naming the port, while unplugged; nothing once back.
    let problem = h.problem().expect("a problem while unplugged");
    assert!(problem.contains(&*path.to_string_lossy()), "{problem}");
    fake.replug().unwrap();
    let v = connected(&h);
    assert_eq!(h.problem(), None);
    assert_eq!(v.connects, 2);
    assert!(h.set_magnet(true).unwrap().magnet_on);
    assert!(fake.magnet_on());
}

#[test]
fn a_reset_is_seen_from_the_banner_and_the_hold_limit_restored() {
    let path = link_path("reset");
    let fake = FakeDevice::start(&path).unwrap();
    let h = MagnetHandle::spawn(MagnetParams {
        hold_limit_s: 30,
        ..fast_params(&path)
    })
    .unwrap();
    connected(&h);
    h.set_magnet(true).unwrap();
    fake.reset(ResetCause::External, Duration::from_millis(100))
        .unwrap();
    let (v, ok) = h.wait_for(Duration::from_secs(3), |v| {
        v.last_reset == Some(ResetCause::External) && v.magnet == MagnetState::Off
    });
    assert!(ok, "{v:?}");
    let (v, ok) = h.wait_for(Duration::from_secs(3), |v| v.hold_max_ms == 30_000);
    assert!(ok, "hold limit not restored: {v:?}");
    assert!(!h.status().unwrap().magnet_on);
}

#[test]
fn a_burst_from_two_callers_is_serialised_not_lost() {
    let path = link_path("burst");
    let fake = FakeDevice::start(&path).unwrap();
    let h = MagnetHandle::spawn(MagnetParams {
        status_poll_ms: 60_000.0,
        ..fast_params(&path)
    })
    .unwrap();
    connected(&h);
    let before = fake.commands();
    let callers: Vec<_> = (0..2)
        .map(|c| {
            let h = h.clone();
            std::thread::Builder::new()
                .name(format!("isochron-test-caller-{c}"))
                .spawn(move || {
                    // Submit everything first (non-blocking), then collect.
                    let pending: Vec<_> = (0..12)
                        .map(|i| {
                            let on = (i + c) % 2 == 0;
                            (on, h.submit(Command::Magnet(on)).unwrap())
                        })
                        .collect();
                    pending
                        .into_iter()
                        .map(|(on, p)| (on, p.wait().unwrap().status().unwrap().magnet_on))
                        .collect::<Vec<_>>()
                })
                .unwrap()
        })
        .collect();
    let answers: Vec<(bool, bool)> = callers
        .into_iter()
        .flat_map(|t| t.join().unwrap())
        .collect();
    assert_eq!(answers.len(), 24);
    // Every caller got the answer to its own command, never another's.
    assert!(
        answers.iter().all(|(asked, got)| asked == got),
        "{answers:?}"
    );
    assert!(fake.commands() - before >= 24);
    assert_eq!(fake.errors(), 0, "commands were garbled");
    assert_eq!(h.view().timeouts, 0);
}

#[test]
fn a_missing_device_is_a_clear_error() {
    let path = link_path("missing");
    let h = MagnetHandle::spawn(fast_params(&path)).unwrap();
    let e = h.status().unwrap_err();
    let text = e.to_string();
    assert!(matches!(e, MagnetError::NotConnected { .. }), "{e}");
    assert!(text.contains(&*path.to_string_lossy()), "{text}");
    assert_eq!(h.view().magnet, MagnetState::Unknown);
    // The problem names the port and why (no such file), once tried.
    let deadline = Instant::now() + Duration::from_secs(5);
    let problem = loop {
        let p = h.problem().expect("never connected: a problem");
        if p.contains("No such file") || Instant::now() > deadline {
            break p;
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    assert!(
        problem.contains(&*path.to_string_lossy()) && problem.contains("No such file"),
        "{problem}"
    );
}
