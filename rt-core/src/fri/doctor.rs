//! `isochron fri doctor`: listens where the FRI client would, answers as the
//! client would, and says in plain words what is wrong with the connection.
//!
//! It binds the client's address (and, to spot a wrong port, the other ports
//! of KUKA's range 30200..30209 on the same address), runs the real
//! [`FriClient`] (holding position, of the configured version) on the
//! datagrams that arrive, and reports: no datagrams at all (with the commands
//! that check interface, route and firewall), datagrams on another port or from
//! an unexpected address, their period and jitter against the configuration,
//! the version they are (framing, fields) against `fri.version`, the session
//! states and quality, and whether the replies are answered (the controller's
//! `reflectedSequenceCounter` follows them). A session counts as established
//! when the controller's datagrams decode as the configured version, the
//! replies are answered and the controller reaches MONITORING_READY (quality
//! GOOD) or later. Not real time: this is a diagnostic tool.

use std::collections::BTreeMap;
use std::io;
use std::net::{SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

use rustix::event::{PollFd, PollFlags, Timespec, poll};
use serde::Serialize;

use super::client::{FriClient, FriClientParams, HoldPosition};
use super::codec::{COMMAND_MESSAGE_ID, CodecError, decode_monitoring_message_of};
use super::framing::unframe;
use super::proto::{ConnectionQuality, SessionState};
use super::version::FriVersion;

/// What the doctor is told (from the lab config and the command line).
#[derive(Debug, Clone, PartialEq)]
pub struct DoctorParams {
    /// Where the client listens (`fri.local_bind`).
    pub listen: SocketAddr,
    /// The controller's address (`fri.controller`); `None`: any sender.
    pub controller: Option<SocketAddr>,
    /// The send period the config expects (`fri.period_ms`).
    pub period_ms: u32,
    /// The FRI version the config expects (`fri.version`).
    pub version: FriVersion,
    /// How long to listen.
    pub duration: Duration,
    /// Other ports to listen on, on the listen address, to spot a wrong port.
    pub scan_ports: Vec<u16>,
    /// Answer the controller as the client would (replies, sessions).
    pub answer: bool,
}

impl Default for DoctorParams {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from(([0, 0, 0, 0], 30200)),
            controller: None,
            period_ms: 5,
            version: FriVersion::default(),
            duration: Duration::from_secs(3),
            scan_ports: (30200..30210).collect(),
            answer: true,
        }
    }
}

/// How bad a finding is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Severity {
    /// All right.
    Ok,
    /// Worth knowing.
    Info,
    /// Works, but should change.
    Warning,
    /// Stops a session.
    Problem,
}

/// One finding, in plain words.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Finding {
    /// A stable name (`no_datagrams`, `wrong_port`, `unexpected_sender`,
    /// `period_mismatch`, `jitter`, `version_mismatch`, `replies_unanswered`,
    /// `no_session`, `session_closed`, `session_established`, `bind_failed`,
    /// `undecodable`).
    pub code: &'static str,
    /// How bad.
    pub severity: Severity,
    /// What was seen.
    pub text: String,
    /// What to do or check (commands, config keys), one step per entry.
    pub fix: Vec<String>,
}

/// Datagrams seen on one port from one sender.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Flow {
    /// The sender.
    pub from: SocketAddr,
    /// The local port they arrived at.
    pub port: u16,
    /// How many.
    pub datagrams: u64,
    /// What they look like (`FRI 2.7 (length + CRC-32 framing)`, ...).
    pub looks_like: String,
}

/// What the doctor saw and concluded.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DoctorReport {
    /// Where it listened.
    pub listen: SocketAddr,
    /// The version it expected.
    pub expected_version: &'static str,
    /// The period it expected, ms.
    pub expected_period_ms: u32,
    /// Seconds it listened.
    pub seconds: f64,
    /// Datagrams by sender and port.
    pub flows: Vec<Flow>,
    /// Datagrams at the listen address from the controller that decoded.
    pub valid_messages: u64,
    /// Datagrams at the listen address that did not decode as the expected version.
    pub decode_errors: u64,
    /// The version the datagrams are, when recognised.
    pub seen_version: Option<String>,
    /// `connectionInfo.sendPeriod`, ms.
    pub send_period_ms: Option<u32>,
    /// Median interval between consecutive controller messages, ms.
    pub measured_period_ms: Option<f64>,
    /// 99th percentile of |interval - sendPeriod|, us.
    pub jitter_p99_us: Option<f64>,
    /// Session states seen, in order of first appearance.
    pub states_seen: Vec<&'static str>,
    /// The last quality seen.
    pub quality: Option<&'static str>,
    /// Replies sent.
    pub replies_sent: u64,
    /// True when the controller's reflectedSequenceCounter followed the replies.
    pub replies_answered: bool,
    /// True when a session could be established (see the module docs).
    pub session_established: bool,
    /// The findings, worst first.
    pub findings: Vec<Finding>,
}

impl DoctorReport {
    /// True when no finding stops a session and one was established.
    pub fn ok(&self) -> bool {
        self.session_established && self.findings.iter().all(|f| f.severity < Severity::Problem)
    }

    /// The report in plain words, one finding per paragraph.
    pub fn to_text(&self) -> String {
        use std::fmt::Write as _;
        let mut s = String::new();
        let _ = writeln!(
            s,
            "isochron fri doctor: listened on {} for {:.1} s, expecting FRI {} every {} ms",
            self.listen, self.seconds, self.expected_version, self.expected_period_ms
        );
        for f in &self.flows {
            let _ = writeln!(
                s,
                "  {} datagrams from {} to port {}: {}",
                f.datagrams, f.from, f.port, f.looks_like
            );
        }
        for f in &self.findings {
            let tag = match f.severity {
                Severity::Ok => "ok",
                Severity::Info => "info",
                Severity::Warning => "WARNING",
                Severity::Problem => "PROBLEM",
            };
            let _ = writeln!(s, "[{tag}] {}", f.text);
            for fix in &f.fix {
                let _ = writeln!(s, "    - {fix}");
            }
        }
        let _ = write!(
            s,
            "{}",
            if self.ok() {
                "result: an FRI session can be established"
            } else {
                "result: no FRI session with this configuration"
            }
        );
        s
    }
}

/// What a datagram's bytes are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WireGuess {
    /// A monitoring message of a 1.x version (1.11..1.16: commandedJointPosition present).
    Fri1x,
    /// A bare monitoring message without commandedJointPosition: 2.5 (or a 1.x without it).
    Fri25,
    /// A 2.7 frame (length and CRC-32 match) holding a monitoring message.
    Fri27,
    /// A command message (another FRI client, or a reply looped back).
    Command,
    /// Not an FRI message of any version.
    Unknown,
}

impl WireGuess {
    /// In words.
    pub fn describe(self) -> &'static str {
        match self {
            Self::Fri1x => {
                "FRI 1.x monitoring (bare protobuf with commandedJointPosition: 1.11..1.16)"
            }
            Self::Fri25 => "FRI 2.5 monitoring (bare protobuf, no commandedJointPosition)",
            Self::Fri27 => "FRI 2.7 monitoring (4-byte length + protobuf + CRC-32)",
            Self::Command => {
                "FRI command messages (identifier 0x34001: another client, not a controller)"
            }
            Self::Unknown => "not FRI monitoring messages of any version",
        }
    }

    /// The version to configure for these datagrams.
    pub fn version(self) -> Option<FriVersion> {
        match self {
            Self::Fri1x => Some(FriVersion::V1_15),
            Self::Fri25 => Some(FriVersion::V2_5),
            Self::Fri27 => Some(FriVersion::V2_7),
            Self::Command | Self::Unknown => None,
        }
    }
}

/// Recognises a datagram's FRI version from its framing and fields.
pub fn sniff(bytes: &[u8]) -> WireGuess {
    if unframe(bytes).is_ok() && decode_monitoring_message_of(bytes, FriVersion::V2_7).is_ok() {
        return WireGuess::Fri27;
    }
    match decode_monitoring_message_of(bytes, FriVersion::V1_15) {
        Ok(m) => {
            let has_commanded = m
                .monitor_data
                .as_ref()
                .and_then(|md| md.commanded_joint_position.as_ref())
                .is_some_and(|j| !j.value.is_empty());
            if has_commanded {
                WireGuess::Fri1x
            } else {
                WireGuess::Fri25
            }
        }
        Err(CodecError::WrongIdentifier { got, .. }) if got == COMMAND_MESSAGE_ID => {
            WireGuess::Command
        }
        Err(_) if super::codec::decode_command_message_of(bytes, FriVersion::V2_7).is_ok() => {
            WireGuess::Command
        }
        Err(_) => WireGuess::Unknown,
    }
}

struct Listener {
    socket: UdpSocket,
    port: u16,
    primary: bool,
}

fn bind_hint(addr: SocketAddr, e: &io::Error) -> Finding {
    let ip = addr.ip();
    let port = addr.port();
    let (text, fix) = match e.kind() {
        io::ErrorKind::AddrNotAvailable => (
            format!("cannot listen on {addr}: {ip} is not an address of this PC ({e})"),
            vec![
                "list this PC's addresses: ip -br addr".into(),
                format!(
                    "set fri.local_bind to this PC's address on the robot's KONI network (e.g. 192.170.10.1:{port}) or 0.0.0.0:{port}"
                ),
            ],
        ),
        io::ErrorKind::AddrInUse => (
            format!("cannot listen on {addr}: the port is in use ({e})"),
            vec![
                format!("see who holds it: ss -ulpn 'sport = :{port}'"),
                "stop `isochron serve` (or the other FRI client) while the doctor runs".into(),
            ],
        ),
        _ => (format!("cannot listen on {addr}: {e}"), vec![]),
    };
    Finding {
        code: "bind_failed",
        severity: Severity::Problem,
        text,
        fix,
    }
}

#[derive(Default)]
struct Seen {
    flows: BTreeMap<(SocketAddr, u16), (u64, WireGuess)>,
    arrivals_ns: Vec<(u64, u32)>,
    valid: u64,
    decode_errors: u64,
    send_period_ms: Option<u32>,
    states: Vec<SessionState>,
    quality: Option<ConnectionQuality>,
    max_reflected: u32,
    reflected_matches: u64,
    replies_sent: u64,
    first_reply_seq_sent: bool,
    ready: bool,
}

/// Runs the doctor: listens for `params.duration` and returns what it found.
/// Only a failure to bind the listen address is reported as a finding without
/// listening; other I/O errors are returned.
///
/// # Errors
///
/// [`io::Error`] when the bound socket's address cannot be read or set
/// non-blocking, polling fails, or (`InvalidInput`) the client refuses the version.
pub fn run(params: &DoctorParams) -> io::Result<DoctorReport> {
    let mut report = DoctorReport {
        listen: params.listen,
        expected_version: params.version.name(),
        expected_period_ms: params.period_ms,
        seconds: params.duration.as_secs_f64(),
        flows: Vec::new(),
        valid_messages: 0,
        decode_errors: 0,
        seen_version: None,
        send_period_ms: None,
        measured_period_ms: None,
        jitter_p99_us: None,
        states_seen: Vec::new(),
        quality: None,
        replies_sent: 0,
        replies_answered: false,
        session_established: false,
        findings: Vec::new(),
    };
    let primary = match UdpSocket::bind(params.listen) {
        Ok(s) => s,
        Err(e) => {
            report.seconds = 0.0;
            report.findings.push(bind_hint(params.listen, &e));
            return Ok(report);
        }
    };
    let listen = primary.local_addr()?;
    report.listen = listen;
    let mut listeners = vec![Listener {
        socket: primary,
        port: listen.port(),
        primary: true,
    }];
    for &port in &params.scan_ports {
        if port == listen.port() {
            continue;
        }
        if let Ok(socket) = UdpSocket::bind(SocketAddr::new(listen.ip(), port)) {
            listeners.push(Listener {
                socket,
                port,
                primary: false,
            });
        }
    }
    for l in &listeners {
        l.socket.set_nonblocking(true)?;
    }

    let client_params = FriClientParams {
        version: params.version,
        ..FriClientParams::default()
    };
    let mut client = FriClient::new(client_params)
        .map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e.to_string()))?;
    let mut control = HoldPosition;
    let mut seen = Seen::default();
    let epoch = Instant::now();
    let mut buf = [0u8; 2048];
    while epoch.elapsed() < params.duration {
        let left = params.duration.saturating_sub(epoch.elapsed());
        let ts = Timespec {
            tv_sec: i64::try_from(left.as_secs()).unwrap_or(i64::MAX),
            tv_nsec: i64::from(left.subsec_nanos()),
        };
        let ready: Vec<usize> = {
            let mut fds: Vec<PollFd<'_>> = listeners
                .iter()
                .map(|l| PollFd::new(&l.socket, PollFlags::IN))
                .collect();
            match poll(&mut fds, Some(&ts)) {
                Ok(_) | Err(rustix::io::Errno::INTR) => {}
                Err(e) => return Err(io::Error::from(e)),
            }
            fds.iter()
                .enumerate()
                .filter(|(_, f)| !f.revents().is_empty())
                .map(|(i, _)| i)
                .collect()
        };
        for i in ready {
            let l = &listeners[i];
            while let Ok((n, from)) = l.socket.recv_from(&mut buf) {
                let t = epoch.elapsed().as_nanos() as u64;
                let bytes = &buf[..n];
                let guess = sniff(bytes);
                let e = seen.flows.entry((from, l.port)).or_insert((0, guess));
                e.0 += 1;
                if guess != WireGuess::Unknown {
                    e.1 = guess;
                }
                if !l.primary {
                    continue;
                }
                // The session as the configured client would run it.
                let m = super::codec::MonitoringDecoder::with_version(params.version).decode(bytes);
                let Ok(m) = m else {
                    seen.decode_errors += 1;
                    continue;
                };
                seen.valid += 1;
                seen.arrivals_ns.push((t, m.sequence_counter));
                seen.send_period_ms = Some(m.send_period_ms);
                if seen.states.last() != Some(&m.session_state)
                    && !seen.states.contains(&m.session_state)
                {
                    seen.states.push(m.session_state);
                }
                seen.quality = Some(m.quality);
                if seen.first_reply_seq_sent && m.reflected_sequence_counter > 0 {
                    seen.reflected_matches += 1;
                    seen.max_reflected = seen.max_reflected.max(m.reflected_sequence_counter);
                }
                if matches!(
                    m.session_state,
                    SessionState::MonitoringReady
                        | SessionState::CommandingWait
                        | SessionState::CommandingActive
                ) {
                    seen.ready = true;
                }
                if params.answer {
                    if let Some(reply) = client.on_datagram(bytes, t, &mut control) {
                        // Replies go where the session would send them.
                        let to = params.controller.unwrap_or(from);
                        if l.socket.send_to(reply, to).is_ok() {
                            seen.replies_sent += 1;
                            seen.first_reply_seq_sent = true;
                        }
                    }
                }
            }
        }
    }
    report.seconds = epoch.elapsed().as_secs_f64();
    conclude(params, listen, &seen, &mut report);
    Ok(report)
}

/// [`crate::quantile::quantile`] of a sorted sample, NaN when it is empty.
fn quantile(sorted: &[f64], q: f64) -> f64 {
    crate::quantile::quantile(sorted, q).unwrap_or(f64::NAN)
}

fn no_datagram_hints(params: &DoctorParams, listen: SocketAddr) -> Vec<String> {
    let port = listen.port();
    let ctl = params
        .controller
        .map_or_else(|| "<controller IP>".to_string(), |c| c.ip().to_string());
    vec![
        format!(
            "is {} an address of the interface cabled to the robot (KONI)? ip -br addr",
            listen.ip()
        ),
        format!("does the route to the controller leave through that interface? ip route get {ctl}"),
        format!("is the controller reachable? ping -c 3 {ctl}"),
        format!("do datagrams reach this PC at all? sudo tcpdump -ni any udp port {port}"),
        format!(
            "is a firewall dropping them? sudo nft list ruleset | grep -n {port}; sudo iptables -S INPUT; allow with: sudo ufw allow {port}/udp"
        ),
        "in Docker: run the container with --network host (FRI answers the sender's address and port)".into(),
        format!(
            "on the robot: the FRI application is running and its FRIConfiguration names this PC's address and port {port}"
        ),
    ]
}

fn conclude(params: &DoctorParams, listen: SocketAddr, seen: &Seen, r: &mut DoctorReport) {
    let mut f: Vec<Finding> = Vec::new();
    r.flows = seen
        .flows
        .iter()
        .map(|(&(from, port), &(n, g))| Flow {
            from,
            port,
            datagrams: n,
            looks_like: g.describe().into(),
        })
        .collect();
    r.valid_messages = seen.valid;
    r.decode_errors = seen.decode_errors;
    r.send_period_ms = seen.send_period_ms;
    r.states_seen = seen.states.iter().map(|s| s.name()).collect();
    r.quality = seen.quality.map(ConnectionQuality::name);
    r.replies_sent = seen.replies_sent;

    let on_listen: Vec<&Flow> = r.flows.iter().filter(|x| x.port == listen.port()).collect();
    let elsewhere: Vec<&Flow> = r
        .flows
        .iter()
        .filter(|x| x.port != listen.port() && x.looks_like != WireGuess::Unknown.describe())
        .collect();

    if r.flows.is_empty() {
        f.push(Finding {
            code: "no_datagrams",
            severity: Severity::Problem,
            text: format!(
                "no datagrams at all in {:.1} s on {} (nor on the other ports of KUKA's range): the controller's datagrams do not reach this PC",
                r.seconds, listen
            ),
            fix: no_datagram_hints(params, listen),
        });
    } else if on_listen.is_empty() {
        for x in &elsewhere {
            f.push(Finding {
                code: "wrong_port",
                severity: Severity::Problem,
                text: format!(
                    "nothing arrives on port {}, but {} datagrams from {} arrive on port {} ({})",
                    listen.port(),
                    x.datagrams,
                    x.from,
                    x.port,
                    x.looks_like
                ),
                fix: vec![
                    format!(
                        "set fri.local_bind to {}:{} in the lab config, or the port in the robot's FRIConfiguration to {}",
                        listen.ip(),
                        x.port,
                        listen.port()
                    ),
                ],
            });
        }
        if elsewhere.is_empty() {
            f.push(Finding {
                code: "undecodable",
                severity: Severity::Problem,
                text: format!(
                    "only datagrams that are not FRI arrived ({} flows), none on port {}",
                    r.flows.len(),
                    listen.port()
                ),
                fix: no_datagram_hints(params, listen),
            });
        }
    }

    // Senders at the listen port.
    if let Some(ctl) = params.controller {
        for x in &on_listen {
            if x.from != ctl && x.looks_like != WireGuess::Command.describe() {
                let what = if x.from.ip() == ctl.ip() {
                    format!("from port {} instead of {}", x.from.port(), ctl.port())
                } else {
                    format!("from {} instead of {}", x.from.ip(), ctl.ip())
                };
                f.push(Finding {
                    code: "unexpected_sender",
                    severity: Severity::Problem,
                    text: format!(
                        "{} datagrams come from {} ({what}); the session answers only fri.controller = {} and would ignore them",
                        x.datagrams, x.from, ctl
                    ),
                    fix: vec![format!("set fri.controller = \"{}\" in the lab config", x.from)],
                });
            }
        }
    }

    // Version.
    let guesses: Vec<WireGuess> = on_listen
        .iter()
        .filter_map(|x| {
            seen.flows
                .get(&(x.from, x.port))
                .map(|(_, g)| *g)
                .filter(|g| g.version().is_some())
        })
        .collect();
    let guess = guesses.first().copied();
    r.seen_version = guess.map(|g| g.describe().to_string());
    if let Some(g) = guess {
        let want = params.version;
        let matches = match g {
            WireGuess::Fri27 => want == FriVersion::V2_7,
            WireGuess::Fri25 => want == FriVersion::V2_5,
            WireGuess::Fri1x => !want.is_2x(),
            _ => true,
        };
        if !matches {
            let severity = if seen.valid == 0 {
                Severity::Problem
            } else {
                // Decodes, but the fields say another version (e.g. 1.15 vs 2.5).
                Severity::Warning
            };
            let to = match g {
                WireGuess::Fri1x => {
                    "1.15 (or the 1.x release of the cabinet: 1.11, 1.14, 1.16)".to_string()
                }
                other => other
                    .version()
                    .map_or_else(String::new, |v| v.name().to_string()),
            };
            f.push(Finding {
                code: "version_mismatch",
                severity,
                text: format!(
                    "the controller speaks {}; fri.version is {} ({})",
                    g.describe(),
                    want,
                    want.wire_summary()
                ),
                fix: vec![format!("set fri.version = \"{to}\" in the lab config")],
            });
        }
    } else if !on_listen.is_empty() && seen.valid == 0 {
        f.push(Finding {
            code: "undecodable",
            severity: Severity::Problem,
            text: format!(
                "{} datagrams arrived on port {} but none is an FRI monitoring message of any version",
                on_listen.iter().map(|x| x.datagrams).sum::<u64>(),
                listen.port()
            ),
            fix: vec!["check that the sender is the robot controller's FRI (tcpdump -X shows the bytes)".into()],
        });
    }

    // Period and jitter.
    if seen.arrivals_ns.len() >= 3 {
        let mut intervals = Vec::new();
        let mut dev = Vec::new();
        for w in seen.arrivals_ns.windows(2) {
            let gap = w[1].1.wrapping_sub(w[0].1);
            if !(1..1000).contains(&gap) {
                continue;
            }
            let dt = (w[1].0 - w[0].0) as f64 / f64::from(gap);
            intervals.push(dt * 1e-6);
            if let Some(p) = seen.send_period_ms {
                dev.push((dt - f64::from(p) * 1e6).abs() * 1e-3);
            }
        }
        intervals.sort_by(f64::total_cmp);
        dev.sort_by(f64::total_cmp);
        let median = quantile(&intervals, 0.5);
        r.measured_period_ms = median.is_finite().then_some(median);
        let p99 = quantile(&dev, 0.99);
        r.jitter_p99_us = p99.is_finite().then_some(p99);
        let sp = seen.send_period_ms.unwrap_or(0);
        if sp != params.period_ms
            || (median - f64::from(params.period_ms)).abs() > 0.25 * f64::from(params.period_ms)
        {
            f.push(Finding {
                code: "period_mismatch",
                severity: Severity::Problem,
                text: format!(
                    "the controller sends every {median:.2} ms (sendPeriod = {sp} ms); fri.period_ms is {}",
                    params.period_ms
                ),
                fix: vec![format!(
                    "set fri.period_ms = {sp} in the lab config, or the send period of the robot application's FRIConfiguration to {} ms",
                    params.period_ms
                )],
            });
        } else {
            f.push(Finding {
                code: "period",
                severity: Severity::Ok,
                text: format!("period {median:.3} ms (sendPeriod {sp} ms), jitter p99 {p99:.0} us"),
                fix: vec![],
            });
        }
        if sp > 0 && p99 > 0.5 * f64::from(sp) * 1e3 {
            f.push(Finding {
                code: "jitter",
                severity: Severity::Warning,
                text: format!(
                    "arrival jitter p99 {p99:.0} us is over half the {sp} ms period: expect late replies and quality drops"
                ),
                fix: vec![
                    "use a dedicated network interface for the robot, no switch or Wi-Fi in between".into(),
                    "check the interface's interrupt coalescing: ethtool -c <iface>".into(),
                ],
            });
        }
    }

    // Replies and the session.
    r.replies_answered = seen.reflected_matches > 0;
    let sessionable = seen.valid > 0 && !f.iter().any(|x| x.severity == Severity::Problem);
    if seen.valid > 0 && params.answer {
        if !r.replies_answered {
            f.push(Finding {
                code: "replies_unanswered",
                severity: Severity::Problem,
                text: format!(
                    "{} replies left for {} but the controller's reflectedSequenceCounter never followed them: the replies do not reach the controller (quality stays {})",
                    seen.replies_sent,
                    params.controller.map_or_else(|| "the sender".to_string(), |c| c.to_string()),
                    r.quality.unwrap_or("unknown")
                ),
                fix: vec![
                    "is an outbound firewall rule dropping them? sudo nft list ruleset; sudo iptables -S OUTPUT".into(),
                    format!(
                        "do they leave through the robot's interface? sudo tcpdump -ni any udp and src port {}",
                        listen.port()
                    ),
                    "in Docker, NAT rewrites the source port: use --network host".into(),
                ],
            });
        } else if !seen.ready {
            f.push(Finding {
                code: "no_session",
                severity: Severity::Problem,
                text: format!(
                    "replies are answered but the controller stayed in {} (quality {}): it does not grade the link GOOD",
                    r.states_seen.last().copied().unwrap_or("?"),
                    r.quality.unwrap_or("?")
                ),
                fix: vec![
                    "late replies: check CPU load and the period (1 ms needs a real-time kernel)".into(),
                ],
            });
        }
    }
    if seen.states.last() == Some(&SessionState::Idle) && !seen.ready {
        f.push(Finding {
            code: "session_closed",
            severity: Severity::Warning,
            text: "the controller only sent IDLE: the robot application closed the FRI session"
                .into(),
            fix: vec!["start the FRI session in the robot application".into()],
        });
    }
    r.session_established = sessionable && r.replies_answered && seen.ready;
    if r.session_established {
        f.push(Finding {
            code: "session_established",
            severity: Severity::Ok,
            text: format!(
                "session established: FRI {} ({}), states {}, quality {}, {} replies answered",
                params.version,
                params.version.wire_summary(),
                r.states_seen.join(" -> "),
                r.quality.unwrap_or("?"),
                seen.replies_sent
            ),
            fix: vec![],
        });
    }
    // Worst first; among equals, in the order found (the cause before its effects).
    f.sort_by_key(|x| std::cmp::Reverse(x.severity));
    r.findings = f;
}
