//! `isochron fri doctor` as a user runs it (the built binary), against the
//! simulated controller over loopback UDP with each connection failure
//! injected: it names the cause (the first, worst finding) and exits 0 only
//! when a session could be established.

use std::net::{SocketAddr, UdpSocket};
use std::path::PathBuf;
use std::process::Command;
use std::time::Duration;

use rt_core::fri::FriVersion;
use rt_core::sim::kuka::{FriSimParams, SimRunOptions, SimServer};

fn isochron() -> Option<PathBuf> {
    isochron_tests::isochron_bin(&[(&["fri", "doctor", "--help"], "--scan-ports")])
}

/// Distinct free loopback UDP ports (all bound at once, read and released).
fn free_ports<const N: usize>() -> [u16; N] {
    let sockets: Vec<UdpSocket> = (0..N)
        .map(|_| UdpSocket::bind("127.0.0.1:0").unwrap())
        .collect();
    std::array::from_fn(|i| sockets[i].local_addr().unwrap().port())
}

struct Case {
    name: &'static str,
    /// The controller (`None`: nothing is sent).
    sim: Option<FriSimParams>,
    /// The controller sends to the doctor's port + this.
    port_offset: u16,
    /// What the config expects.
    period_ms: u32,
    version: FriVersion,
    /// The first finding's code.
    cause: &'static str,
    ok: bool,
}

fn run_case(bin: &PathBuf, case: &Case) -> (serde_json::Value, bool) {
    // A port released by `free_ports` can be taken by another process
    // before the controller binds it: then new ports, a few times.
    let mut tries = 0;
    let (listen, other, controller, server) = loop {
        let [listen, other, ctl_port] = free_ports::<3>();
        let controller = SocketAddr::from(([127, 0, 0, 1], ctl_port));
        let target_port = if case.port_offset == 0 { listen } else { other };
        let server = case.sim.clone().map(|p| {
            SimServer::spawn(
                p,
                controller,
                SocketAddr::from(([127, 0, 0, 1], target_port)),
                SimRunOptions {
                    auto_command: false,
                    duration: None,
                    normal_priority: false,
                    keep_commanding: false,
                },
            )
        });
        match server.transpose() {
            Ok(server) => break (listen, other, controller, server),
            Err(e) => {
                tries += 1;
                assert!(tries < 5, "{}: the controller cannot bind: {e}", case.name);
            }
        }
    };
    let data = tempdir(case.name);
    let out = Command::new(bin)
        .args(["fri", "doctor", "--json", "--seconds", "1.5"])
        .args(["--listen", &format!("127.0.0.1:{listen}")])
        .args(["--controller", &controller.to_string()])
        .args(["--period-ms", &case.period_ms.to_string()])
        .args(["--fri-version", case.version.name()])
        .args(["--scan-ports", &other.to_string()])
        .args(["--data-dir", data.to_str().unwrap()])
        .output()
        .unwrap();
    if let Some(s) = server {
        let _ = s.close(Duration::from_secs(2));
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    let report: serde_json::Value = serde_json::from_str(stdout.trim())
        .unwrap_or_else(|e| panic!("{}: not JSON ({e}): {stdout}", case.name));
    // The dashboard's copy is the same report.
    let saved: serde_json::Value =
        serde_json::from_slice(&std::fs::read(data.join("fri-doctor.json")).unwrap()).unwrap();
    assert_eq!(saved, report);
    let _ = std::fs::remove_dir_all(&data);
    (report, out.status.success())
}

fn tempdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("isochron-fri-doctor-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn the_doctor_names_each_injected_failure_and_passes_a_good_link() {
    let Some(bin) = isochron() else { return };
    let sim = |f: fn(&mut FriSimParams)| {
        let mut p = FriSimParams {
            fri_period_ms: 5,
            ..FriSimParams::default()
        };
        f(&mut p);
        Some(p)
    };
    let cases = [
        Case {
            name: "good",
            sim: sim(|_| {}),
            port_offset: 0,
            period_ms: 5,
            version: FriVersion::V1_15,
            cause: "session_established",
            ok: true,
        },
        Case {
            name: "good-2.7",
            sim: sim(|p| p.fri_version = FriVersion::V2_7),
            port_offset: 0,
            period_ms: 5,
            version: FriVersion::V2_7,
            cause: "session_established",
            ok: true,
        },
        Case {
            name: "nothing-sent",
            sim: None,
            port_offset: 0,
            period_ms: 5,
            version: FriVersion::V1_15,
            cause: "no_datagrams",
            ok: false,
        },
        Case {
            name: "wrong-port",
            sim: sim(|_| {}),
            port_offset: 1,
            period_ms: 5,
            version: FriVersion::V1_15,
            cause: "wrong_port",
            ok: false,
        },
        Case {
            name: "wrong-period",
            sim: sim(|p| p.fri_period_ms = 2),
            port_offset: 0,
            period_ms: 5,
            version: FriVersion::V1_15,
            cause: "period_mismatch",
            ok: false,
        },
        Case {
            name: "wrong-version",
            sim: sim(|p| p.fri_version = FriVersion::V2_7),
            port_offset: 0,
            period_ms: 5,
            version: FriVersion::V1_15,
            cause: "version_mismatch",
            ok: false,
        },
        Case {
            name: "replies-dropped",
            sim: sim(|p| p.reply_loss = 1.0),
            port_offset: 0,
            period_ms: 5,
            version: FriVersion::V1_15,
            cause: "replies_unanswered",
            ok: false,
        },
    ];
    // The cases run side by side (each on its own ports): 1.5 s in all.
    let results: Vec<(serde_json::Value, bool)> = std::thread::scope(|s| {
        let hs: Vec<_> = cases
            .iter()
            .map(|c| s.spawn(|| run_case(&bin, c)))
            .collect();
        hs.into_iter().map(|h| h.join().unwrap()).collect()
    });
    for (case, (report, ok)) in cases.iter().zip(&results) {
        let findings = report["findings"].as_array().unwrap();
        let codes: Vec<&str> = findings
            .iter()
            .map(|f| f["code"].as_str().unwrap())
            .collect();
        eprintln!(
            "{}: exit ok {ok}, findings {codes:?}, period {} ms, jitter p99 {} us, version {}",
            case.name,
            report["measured_period_ms"],
            report["jitter_p99_us"],
            report["seen_version"]
        );
        if case.ok {
            // Warnings (jitter on a loaded machine) may come first; no problem may.
            assert!(codes.contains(&case.cause), "{}: {report:#}", case.name);
            assert!(
                findings.iter().all(|f| f["severity"] != "problem"),
                "{}: {report:#}",
                case.name
            );
        } else {
            assert_eq!(
                codes.first().copied(),
                Some(case.cause),
                "{}: {report:#}",
                case.name
            );
        }
        assert_eq!(*ok, case.ok, "{}: exit status; {report:#}", case.name);
        assert_eq!(report["session_established"], case.ok, "{}", case.name);
        if !case.ok {
            // A cause comes with what to do about it.
            assert!(
                !findings[0]["fix"].as_array().unwrap().is_empty(),
                "{}",
                case.name
            );
        }
    }
    // The plain words say where to look.
    let (nothing, _) = &results[2];
    let fix = nothing["findings"][0]["fix"].to_string();
    for hint in [
        "ip -br addr",
        "ip route get",
        "tcpdump",
        "nft",
        "--network host",
    ] {
        assert!(fix.contains(hint), "no `{hint}` in {fix}");
    }
    let (wrong_version, _) = &results[5];
    assert!(
        wrong_version["findings"][0]["fix"][0]
            .as_str()
            .unwrap()
            .contains("fri.version = \"2.7\""),
        "{wrong_version:#}"
    );
    let (wrong_period, _) = &results[4];
    assert!(
        wrong_period["findings"][0]["fix"][0]
            .as_str()
            .unwrap()
            .contains("fri.period_ms = 2"),
        "{wrong_period:#}"
    );
}
