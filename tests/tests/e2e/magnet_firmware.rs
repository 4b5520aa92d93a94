//! The real magnet firmware (`firmware/magnet/magnet.c`) running in simavr
//! (`magnet-sim`), driven by the real serial driver over a pseudo-terminal.
//! The coil pin is observed from the simulator's pin reports, never assumed.
//!
//! `make firmware` (a dependency of `make test`) builds the ELF and the host into
//! `firmware/magnet/build/`. Without them these tests fail under `CI=true` and
//! are skipped, loudly, otherwise.

use std::{
    io::{BufRead, BufReader, Read, Write},
    path::{Path, PathBuf},
    process::{Child, ChildStdin, Command as Process, Stdio},
    sync::{Arc, Condvar, Mutex},
    time::{Duration, Instant},
};

use rt_core::magnet::{
    Command, EventKind, LinkState, MagnetError, MagnetEvent, MagnetHandle, MagnetParams,
    MagnetState, OkReply, ResetCause, SwitchCause,
};

fn build_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../firmware/magnet/build")
}

/// The ELF and the simulator host, or `None` (skip) outside CI.
fn firmware() -> Option<(PathBuf, PathBuf)> {
    let elf = build_dir().join("magnet.elf");
    let host = build_dir().join("magnet-sim");
    if elf.is_file() && host.is_file() {
        return Some((elf, host));
    }
    let msg = format!(
        "magnet firmware or simulator host missing in {} (run `make firmware`; needs gcc-avr, avr-libc, libsimavr-dev)",
        build_dir().display()
    );
    assert!(std::env::var("CI").as_deref() != Ok("true"), "{msg}");
    eprintln!("SKIPPED: {msg}");
    None
}

fn link_path(tag: &str) -> PathBuf {
    tempfile::Builder::new()
        .prefix(&format!("isochron-sim-{tag}-"))
        .tempdir()
        .expect("a temporary directory")
        .keep()
        .join("tty")
}

/// A pin report: pin name, level, simulated time in microseconds.
#[derive(Debug, Clone, PartialEq)]
struct PinReport {
    pin: String,
    level: u8,
    t_us: u64,
}

#[derive(Default)]
struct SimLog {
    ready: bool,
    pins: Vec<PinReport>,
}

/// One simulated Uno behind a pty at `link`.
struct SimBoard {
    child: Child,
    stdin: Option<ChildStdin>,
    log: Arc<(Mutex<SimLog>, Condvar)>,
}

impl SimBoard {
    fn start(elf: &Path, host: &Path, link: &Path) -> Self {
        let mut child = Process::new(host)
            .arg(elf)
            .arg(link)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("start magnet-sim");
        let stdout = child.stdout.take().unwrap();
        let stdin = child.stdin.take();
        let log = Arc::new((Mutex::new(SimLog::default()), Condvar::new()));
        let l = Arc::clone(&log);
        std::thread::Builder::new()
            .name("isochron-test-sim-out".to_owned())
            .spawn(move || {
                for line in BufReader::new(stdout).lines() {
                    let Ok(line) = line else { break };
                    let mut words = line.split_whitespace();
                    let (lock, cv) = &*l;
                    match words.next() {
                        Some("READY") => lock.lock().unwrap().ready = true,
                        Some("PIN") => {
                            let pin = words.next().unwrap_or_default().to_owned();
                            let level = words.next().and_then(|w| w.parse().ok()).unwrap_or(9);
                            let t_us = words
                                .next()
                                .and_then(|w| w.strip_prefix("t_us="))
                                .and_then(|w| w.parse().ok())
                                .unwrap_or(0);
                            lock.lock()
                                .unwrap()
                                .pins
                                .push(PinReport { pin, level, t_us });
                        }
                        _ => continue,
                    }
                    cv.notify_all();
                }
            })
            .unwrap();
        let board = Self { child, stdin, log };
        assert!(
            board.wait(Duration::from_secs(20), |l| l.ready),
            "magnet-sim did not become ready"
        );
        board
    }

    fn wait(&self, timeout: Duration, mut pred: impl FnMut(&SimLog) -> bool) -> bool {
        let (lock, cv) = &*self.log;
        let deadline = Instant::now() + timeout;
        let mut log = lock.lock().unwrap();
        loop {
            if pred(&log) {
                return true;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return false;
            }
            log = cv.wait_timeout(log, left).unwrap().0;
        }
    }

    /// The latest reported level of `pin`.
    fn level(log: &SimLog, pin: &str) -> Option<u8> {
        log.pins
            .iter()
            .rev()
            .find(|p| p.pin == pin)
            .map(|p| p.level)
    }

    /// Waits until both the coil pin (D8) and its LED mirror (D13) are at `level`.
    fn wait_coil(&self, level: u8, timeout: Duration) -> bool {
        self.wait(timeout, |l| {
            Self::level(l, "D8") == Some(level) && Self::level(l, "D13") == Some(level)
        })
    }

    fn pins(&self) -> Vec<PinReport> {
        self.log.0.lock().unwrap().pins.clone()
    }

    fn reset(&mut self) {
        let stdin = self.stdin.as_mut().unwrap();
        stdin.write_all(b"RESET\n").unwrap();
        stdin.flush().unwrap();
    }

    /// An unplug: the process dies at once, the pty with it.
    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for SimBoard {
    fn drop(&mut self) {
        self.kill();
    }
}

fn params(link: &Path) -> MagnetParams {
    MagnetParams {
        port: link.to_string_lossy().into_owned(),
        // Generous: a loaded machine can keep simavr from the CPU for a while
        // (1 s timed out once with the e2e tests four at a time beside
        // `stress-ng --cpu 2`). The driver's own timeout is tested apart.
        command_timeout_ms: 3000.0,
        boot_timeout_ms: 2000.0,
        reconnect_interval_ms: 50.0,
        status_poll_ms: 300.0,
        ..MagnetParams::default()
    }
}

fn events_hook() -> (rt_core::magnet::EventHook, Arc<Mutex<Vec<MagnetEvent>>>) {
    let seen = Arc::new(Mutex::new(Vec::new()));
    let s = Arc::clone(&seen);
    (
        Box::new(move |e: &MagnetEvent| s.lock().unwrap().push(*e)),
        seen,
    )
}

/// Waits (up to 20 s: simavr beside `stress-ng --cpu 2` once took over 5 s
/// from its banner to the driver's first answer) for the driver connected
/// and the magnet's state known.
fn connected(h: &MagnetHandle) {
    let (v, ok) = h.wait_for(Duration::from_secs(20), |v| {
        v.link == LinkState::Connected && v.magnet != MagnetState::Unknown
    });
    assert!(
        ok,
        "the driver never connected to the simulated board: {v:?}"
    );
}

/// The `p`-quantile of a sorted, non-empty sample ([`rt_core::quantile`]).
fn percentile(sorted: &[f64], p: f64) -> f64 {
    rt_core::quantile::quantile(sorted, p).expect("a sample")
}

#[test]
fn on_off_switches_the_pin_and_status_agrees() {
    let Some((elf, host)) = firmware() else {
        return;
    };
    let link = link_path("onoff");
    let board = SimBoard::start(&elf, &host, &link);
    let (hook, events) = events_hook();
    let h = MagnetHandle::spawn_with_hook(params(&link), hook).unwrap();
    connected(&h);
    assert_eq!(h.view().magnet, MagnetState::Off);
    assert!(board.wait_coil(0, Duration::from_secs(10)));

    let s = h.set_magnet(true).unwrap();
    assert!(s.magnet_on);
    assert!(
        board.wait_coil(1, Duration::from_secs(10)),
        "{:?}",
        board.pins()
    );
    assert!(h.status().unwrap().magnet_on);
    assert_eq!(h.view().magnet, MagnetState::On);

    let s = h.set_magnet(false).unwrap();
    assert!(!s.magnet_on);
    assert!(
        board.wait_coil(0, Duration::from_secs(10)),
        "{:?}",
        board.pins()
    );
    let st = h.status().unwrap();
    assert!(!st.magnet_on);
    assert_eq!(st.fw, Some(1));
    // The release hook saw the switch off.
    assert!(events.lock().unwrap().iter().any(|e| e.kind
        == EventKind::Switched {
            on: false,
            cause: SwitchCause::Command
        }));

    // Round trip per command through driver, pty and simulated UART.
    let mut rtt_ms: Vec<f64> = (0..40)
        .map(|_| {
            let a = h.submit(Command::Status).unwrap().wait().unwrap();
            a.rtt.as_secs_f64() * 1000.0
        })
        .collect();
    rtt_ms.sort_by(f64::total_cmp);
    eprintln!(
        "magnet round trip (firmware in simavr): p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms over {} STATUS",
        percentile(&rtt_ms, 0.5),
        percentile(&rtt_ms, 0.99),
        rtt_ms[rtt_ms.len() - 1],
        rtt_ms.len()
    );
    // Each STATUS was answered within the command timeout (or `wait` failed):
    // the round trip's figures are reported above, not gated.
    assert_eq!(rtt_ms.len(), 40);
}

/// The calibration LED (D12): each `LED ON|OFF` moves only D12, once, to the
/// commanded level; the firmware's reported uptime agrees with the simulator's
/// pin time (the pin switched when the firmware said, before it answered); a
/// bad argument is refused and changes nothing.
#[test]
fn the_led_command_switches_d12_only_and_reports_when() {
    let Some((elf, host)) = firmware() else {
        return;
    };
    let link = link_path("led");
    let board = SimBoard::start(&elf, &host, &link);
    let h = MagnetHandle::spawn(params(&link)).unwrap();
    connected(&h);
    assert!(
        board.wait(Duration::from_secs(10), |l| SimBoard::level(l, "D12")
            == Some(0))
    );
    h.set_magnet(true).unwrap();
    assert!(board.wait_coil(1, Duration::from_secs(10)));
    let mut answers = Vec::new();
    let mut rtt_ms = Vec::new();
    for i in 0..10 {
        let on = i % 2 == 0;
        let a = h.set_led(on).unwrap();
        let OkReply::Led { on: got, uptime_ms } = a.reply else {
            panic!("{:?}", a.reply);
        };
        assert_eq!(got, on);
        answers.push((on, uptime_ms));
        rtt_ms.push(a.rtt.as_secs_f64() * 1e3);
        let want = u8::from(on);
        assert!(
            board.wait(Duration::from_secs(10), |l| SimBoard::level(l, "D12")
                == Some(want)),
            "D12 did not follow LED {on}: {:?}",
            board.pins()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let d12: Vec<PinReport> = board
        .pins()
        .into_iter()
        .filter(|p| p.pin == "D12")
        .collect();
    // The initial low report, then exactly one change per command, alternating.
    assert_eq!(d12.len(), 11, "{d12:?}");
    for ((on, uptime_ms), pin) in answers.iter().zip(&d12[1..]) {
        assert_eq!(pin.level, u8::from(*on));
        // The answer's uptime is the firmware's millisecond clock just after the switch.
        let pin_ms = pin.t_us as f64 / 1000.0;
        let diff = f64::from(*uptime_ms) - pin_ms;
        assert!(
            (-1.0..=2.0).contains(&diff),
            "uptime {uptime_ms} ms vs pin {pin_ms:.3} ms"
        );
    }
    // The coil and its mirror never moved.
    let coil: Vec<PinReport> = board
        .pins()
        .into_iter()
        .filter(|p| p.pin == "D8" || p.pin == "D13")
        .collect();
    assert!(coil.iter().rev().take(2).all(|p| p.level == 1), "{coil:?}");
    assert!(
        coil.iter().filter(|p| p.level == 0).count() <= 2,
        "{coil:?}"
    );
    assert!(h.status().unwrap().magnet_on);
    rtt_ms.sort_by(f64::total_cmp);
    eprintln!(
        "LED command round trip (firmware in simavr): p50 {:.2} ms, max {:.2} ms",
        percentile(&rtt_ms, 0.5),
        rtt_ms[rtt_ms.len() - 1]
    );
    // A bad argument: refused, nothing moves.
    let err = h.submit(Command::Raw("LED BLINK".into())).unwrap().wait();
    assert!(
        matches!(&err, Err(MagnetError::Device { code, .. }) if code == "bad-argument"),
        "{err:?}"
    );
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(board.pins().iter().filter(|p| p.pin == "D12").count(), 11);
    h.set_magnet(false).unwrap();
}

#[test]
fn the_hold_limit_switches_the_pin_off_and_the_driver_reports_it() {
    let Some((elf, host)) = firmware() else {
        return;
    };
    let link = link_path("hold");
    let board = SimBoard::start(&elf, &host, &link);
    let (hook, events) = events_hook();
    let h = MagnetHandle::spawn_with_hook(
        MagnetParams {
            hold_limit_s: 1,
            ..params(&link)
        },
        hook,
    )
    .unwrap();
    connected(&h);
    assert_eq!(h.view().hold_max_ms, 1000);
    h.set_magnet(true).unwrap();
    assert!(board.wait_coil(1, Duration::from_secs(10)));
    assert!(
        board.wait_coil(0, Duration::from_secs(4)),
        "the hold limit did not switch the pin off"
    );
    let (v, ok) = h.wait_for(Duration::from_secs(10), |v| v.magnet == MagnetState::Off);
    assert!(ok, "{v:?}");
    let seen: Vec<EventKind> = events.lock().unwrap().iter().map(|e| e.kind).collect();
    let held = seen.iter().find_map(|k| match k {
        EventKind::HoldLimit { held_ms } => Some(*held_ms),
        _ => None,
    });
    assert!(matches!(held, Some(1000..=1010)), "{seen:?}");
    assert!(seen.contains(&EventKind::Switched {
        on: false,
        cause: SwitchCause::HoldLimit
    }));
    // In simulated time the coil was on for the hold limit.
    let pins = board.pins();
    let on = pins
        .iter()
        .rfind(|p| p.pin == "D8" && p.level == 1)
        .unwrap()
        .t_us;
    let off = pins
        .iter()
        .rfind(|p| p.pin == "D8" && p.level == 0)
        .unwrap()
        .t_us;
    let held_us = off - on;
    assert!(
        (995_000..=1_020_000).contains(&held_us),
        "coil on for {held_us} us"
    );
}

#[test]
fn a_watchdog_reset_is_detected_from_the_banner() {
    let Some((elf, host)) = firmware() else {
        return;
    };
    let link = link_path("wdt");
    let board = SimBoard::start(&elf, &host, &link);
    let (hook, events) = events_hook();
    let h = MagnetHandle::spawn_with_hook(
        MagnetParams {
            hold_limit_s: 30,
            ..params(&link)
        },
        hook,
    )
    .unwrap();
    connected(&h);
    assert_ne!(h.view().last_reset, Some(ResetCause::Watchdog));
    h.set_magnet(true).unwrap();
    assert!(board.wait_coil(1, Duration::from_secs(10)));
    // The main loop hangs; the watchdog must reset the board.
    let a = h
        .submit(Command::Raw("TEST HANG".to_owned()))
        .unwrap()
        .wait()
        .unwrap();
    assert_eq!(a.reply, OkReply::Other("HANG".to_owned()));
    let (v, ok) = h.wait_for(Duration::from_secs(4), |v| {
        v.last_reset == Some(ResetCause::Watchdog) && v.magnet == MagnetState::Off
    });
    assert!(ok, "no watchdog reset seen: {v:?}");
    assert!(board.wait_coil(0, Duration::from_secs(10)));
    assert!(events.lock().unwrap().iter().any(|e| e.kind
        == EventKind::Boot {
            reset: ResetCause::Watchdog
        }));
    // The board answers again, with the driver's hold limit restored.
    let (v, ok) = h.wait_for(Duration::from_secs(10), |v| v.hold_max_ms == 30_000);
    assert!(ok, "{v:?}");
    let s = h.status().unwrap();
    assert_eq!(s.reset, Some(ResetCause::Watchdog));
    assert!(!s.magnet_on);
}

#[test]
fn an_external_reset_drops_the_coil_and_is_reported() {
    let Some((elf, host)) = firmware() else {
        return;
    };
    let link = link_path("reset");
    let mut board = SimBoard::start(&elf, &host, &link);
    let h = MagnetHandle::spawn(params(&link)).unwrap();
    connected(&h);
    h.set_magnet(true).unwrap();
    assert!(board.wait_coil(1, Duration::from_secs(10)));
    let before = h.view().events;
    board.reset();
    assert!(board.wait_coil(0, Duration::from_secs(10)));
    let (v, ok) = h.wait_for(Duration::from_secs(10), |v| {
        v.events > before && v.magnet == MagnetState::Off
    });
    assert!(ok, "{v:?}");
    assert!(matches!(
        v.last_event,
        Some(
            EventKind::Switched {
                on: false,
                cause: SwitchCause::Reset
            } | EventKind::Boot { .. }
        )
    ));
}

#[test]
fn killing_the_simulator_is_a_clear_device_lost_and_a_new_one_reconnects() {
    let Some((elf, host)) = firmware() else {
        return;
    };
    let link = link_path("kill");
    let mut board = SimBoard::start(&elf, &host, &link);
    let p = params(&link);
    let h = MagnetHandle::spawn(p.clone()).unwrap();
    connected(&h);
    h.set_magnet(true).unwrap();

    board.kill();
    // Reported as the device lost (not a hang, not a plain timeout).
    let e = h.status().unwrap_err();
    assert!(
        matches!(
            e,
            MagnetError::DeviceLost { .. } | MagnetError::NotConnected { .. }
        ),
        "{e}"
    );
    assert!(e.to_string().contains(&*link.to_string_lossy()), "{e}");
    let (v, ok) = h.wait_for(Duration::from_secs(10), |v| v.link == LinkState::Lost);
    assert!(ok, "{v:?}");
    assert_eq!(
        v.magnet,
        MagnetState::Unknown,
        "a lost device's state is not known"
    );

    // A new board appears on the same path: the driver reconnects by itself.
    let board2 = SimBoard::start(&elf, &host, &link);
    let (v, ok) = h.wait_for(Duration::from_secs(20), |v| {
        v.link == LinkState::Connected && v.magnet == MagnetState::Off
    });
    assert!(ok, "no reconnection: {v:?}");
    assert_eq!(v.connects, 2);
    assert!(h.set_magnet(true).unwrap().magnet_on);
    assert!(board2.wait_coil(1, Duration::from_secs(10)));
}

/// Talks to the simulated board directly (no driver): raw bytes in, lines out.
struct RawPort {
    port: serialport::TTYPort,
    pending: Vec<u8>,
}

impl RawPort {
    fn open(link: &Path) -> Self {
        let port = serialport::new(link.to_string_lossy(), 115_200)
            .timeout(Duration::from_millis(20))
            .open_native()
            .unwrap();
        Self {
            port,
            pending: Vec::new(),
        }
    }

    fn send(&mut self, bytes: &[u8]) {
        self.port.write_all(bytes).unwrap();
        self.port.flush().unwrap();
    }

    /// The next line that is not an event, within `timeout`.
    fn answer(&mut self, timeout: Duration) -> Option<String> {
        let deadline = Instant::now() + timeout;
        loop {
            while let Some(i) = self.pending.iter().position(|&b| b == b'\n') {
                let line: Vec<u8> = self.pending.drain(..=i).collect();
                let text = String::from_utf8_lossy(&line).trim().to_owned();
                if !text.is_empty() && !text.starts_with("EVT") {
                    return Some(text);
                }
            }
            if Instant::now() >= deadline {
                return None;
            }
            let mut buf = [0u8; 256];
            match self.port.read(&mut buf) {
                Ok(n) => self.pending.extend_from_slice(&buf[..n]),
                Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                Err(e) => panic!("read: {e}"),
            }
        }
    }

    fn ask(&mut self, bytes: &[u8]) -> String {
        self.send(bytes);
        self.answer(Duration::from_secs(5))
            .unwrap_or_else(|| panic!("no answer to {:?}", String::from_utf8_lossy(bytes)))
    }
}

#[test]
fn garbage_partial_and_overlong_lines_get_err_and_leave_the_magnet_alone() {
    let Some((elf, host)) = firmware() else {
        return;
    };
    let link = link_path("garbage");
    let board = SimBoard::start(&elf, &host, &link);
    let mut port = RawPort::open(&link);
    assert_eq!(port.ask(b"PING t1\n"), "OK PONG t1");
    assert!(port.ask(b"MAGNET ON\n").starts_with("OK MAGNET magnet=on"));
    assert!(board.wait_coil(1, Duration::from_secs(10)));
    let changes_before = board.pins().len();

    // A seeded burst of random bytes (no newline) ending in one newline.
    let mut x: u32 = 0x1234_5678;
    let noise: Vec<u8> = (0..300)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            match (x & 0xff) as u8 {
                b'\n' => 0x00,
                b => b,
            }
        })
        .collect();
    let mut burst = noise.clone();
    burst.push(b'\n');
    let a = port.ask(&burst);
    assert!(a == "ERR bad-byte" || a == "ERR line-too-long", "{a}");

    for (bytes, want) in [
        (&b"\x00\xff\x1bMAGNET OFF\n"[..], "ERR bad-byte"),
        (b"MAGNET O\n", "ERR bad-argument"),
        (b"MAGNET\n", "ERR bad-argument"),
        (b"magnet off\n", "ERR unknown-command"),
        (b"HOLD 0\n", "ERR bad-argument"),
        (b"HOLD 12345\n", "ERR bad-argument"),
        (b"PING toolongtoken-0123456789\n", "ERR bad-argument"),
        (
            b"MAGNET OFF MAGNET OFF MAGNET OFF MAGNET OFF MAGNET OFF MAGNET OFF\n",
            "ERR line-too-long",
        ),
    ] {
        assert_eq!(
            port.ask(bytes),
            want,
            "{:?}",
            String::from_utf8_lossy(bytes)
        );
    }
    // A partial line, its end arriving later, is one (bad) line.
    port.send(b"MAGNET O");
    assert_eq!(
        port.answer(Duration::from_millis(200)),
        None,
        "a partial line was answered"
    );
    assert_eq!(port.ask(b"FF!\n"), "ERR bad-argument");

    // Nothing of this touched the coil.
    assert_eq!(board.pins().len(), changes_before, "{:?}", board.pins());
    assert!(port.ask(b"STATUS\n").starts_with("OK STATUS magnet=on"));
    // And the board still obeys a good command.
    assert!(
        port.ask(b"MAGNET OFF\r\n")
            .starts_with("OK MAGNET magnet=off")
    );
    assert!(board.wait_coil(0, Duration::from_secs(10)));
}

#[test]
fn a_command_burst_from_two_callers_is_serialised_not_lost() {
    let Some((elf, host)) = firmware() else {
        return;
    };
    let link = link_path("burst");
    let board = SimBoard::start(&elf, &host, &link);
    let h = MagnetHandle::spawn(MagnetParams {
        status_poll_ms: 600_000.0,
        // The property is order and no loss, not speed: 30 exchanges in a
        // row against simavr timed out once at 3 s beside `stress-ng --cpu 2`
        // (session 22's streak), so each gets 10 s here.
        command_timeout_ms: 10_000.0,
        ..params(&link)
    })
    .unwrap();
    connected(&h);
    let answered_before = h.view().commands;
    let callers: Vec<_> = (0..2)
        .map(|c| {
            let h = h.clone();
            std::thread::Builder::new()
                .name(format!("isochron-test-caller-{c}"))
                .spawn(move || {
                    let pending: Vec<_> = (0..15)
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
    assert_eq!(answers.len(), 30);
    assert!(
        answers.iter().all(|(asked, got)| asked == got),
        "{answers:?}"
    );
    let v = h.view();
    assert_eq!(v.commands - answered_before, 30, "{v:?}");
    assert_eq!(v.timeouts, 0);
    // The pin ends where the last answered command left it, as STATUS says.
    let on = h.status().unwrap().magnet_on;
    assert!(board.wait_coil(u8::from(on), Duration::from_secs(10)));
}

/// The `isochron` binary with `magnet`.
fn isochron_bin() -> Option<PathBuf> {
    isochron_tests::isochron_bin(&[(&["magnet", "--help"], "")])
}

fn isochron_magnet(bin: &Path, args: &[&str]) -> (bool, String, String) {
    let out = Process::new(bin)
        .arg("magnet")
        .args(args)
        .stdin(Stdio::null())
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn the_cli_switches_the_simulated_magnet_and_prints_json() {
    let Some((elf, host)) = firmware() else {
        return;
    };
    let Some(bin) = isochron_bin() else { return };
    let link = link_path("cli");
    let board = SimBoard::start(&elf, &host, &link);
    let port = link.to_string_lossy().into_owned();
    for (action, level) in [("on", 1u8), ("status", 1), ("off", 0), ("status", 0)] {
        // simavr shares the machine with the other tests: 10 s for an
        // answer, at opening the port and to each command (a real Uno's 3 s
        // boot budget and 300 ms default are the driver's, tested above):
        // beside `stress-ng` the simulator once answered none of the pings in
        // 3 s, and once not `MAGNET ON` in 2 s.
        let (ok, stdout, stderr) = isochron_magnet(
            &bin,
            &[
                "--port",
                &port,
                "--boot-timeout-ms",
                "10000",
                "--command-timeout-ms",
                "10000",
                action,
            ],
        );
        assert!(ok, "isochron magnet {action}: {stderr}");
        let j: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
        assert_eq!(
            j["magnet"],
            if level == 1 { "on" } else { "off" },
            "{stdout}"
        );
        assert_eq!(j["port"], port.as_str());
        assert!(j["hold_max_ms"].as_u64().unwrap() > 0);
        assert!(j["rtt_ms"].as_f64().unwrap() > 0.0);
        assert!(board.wait_coil(level, Duration::from_secs(10)), "{action}");
    }
}

#[test]
fn the_cli_reports_a_missing_or_silent_device_clearly() {
    let Some(bin) = isochron_bin() else { return };
    let missing = link_path("cli-missing");
    let (ok, stdout, stderr) =
        isochron_magnet(&bin, &["--port", &missing.to_string_lossy(), "status"]);
    assert!(!ok && stdout.is_empty());
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
    assert!(
        stderr.contains(&*missing.to_string_lossy()) && stderr.contains("No such file"),
        "{stderr}"
    );

    // A port where nothing answers (a pty whose other end stays silent).
    let (_master, slave) = serialport::TTYPort::pair().unwrap();
    let silent = serialport::SerialPort::name(&slave).unwrap();
    // It returns with the timeout's error (not hung): "no answer".
    let (ok, _, stderr) = isochron_magnet(
        &bin,
        &[
            "--port",
            &silent,
            "--boot-timeout-ms",
            "300",
            "--command-timeout-ms",
            "100",
            "on",
        ],
    );
    assert!(!ok);
    assert!(
        stderr.contains("no answer") && stderr.contains(&silent),
        "{stderr}"
    );

    // Bad input is refused with the field named.
    let (ok, _, stderr) = isochron_magnet(&bin, &["--port", &silent, "--hold-s", "0", "on"]);
    assert!(!ok && stderr.contains("magnet.hold_limit_s"), "{stderr}");
}
