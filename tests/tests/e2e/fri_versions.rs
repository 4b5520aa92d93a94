//! Every FRI version, both directions (issue #25): the simulated controller of
//! each version against isochron's client of that version, over real loopback
//! UDP at 1 and 5 ms, and the controller's and client's datagrams read by an
//! independent decoder of each version's schema written here from the
//! published field tables (not the codec under test: its own wire walker, its
//! own bitwise CRC-32, strict about fields a version does not define).

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant};

use rt_core::fri::{
    ControlStep, FriClient, FriClientParams, FriSession, FriSessionParams, FriVersion, Joints,
    LinkState, SessionState, StepInput,
};
use rt_core::sim::kuka::{FriSimParams, SimController, SimRunOptions, SimServer};

// ---------------------------------------------------------------------------
// The independent decoder.

#[derive(Debug, Clone, Copy, PartialEq)]
enum Kind {
    Varint,
    Double,
    Str,
    Msg(&'static str),
}

/// One field of one message: `(message, tag, name, kind, required, repeated, in_version)`.
type FieldDef = (
    &'static str,
    u64,
    &'static str,
    Kind,
    bool,
    bool,
    fn(&str) -> bool,
);

fn all(_: &str) -> bool {
    true
}
fn v1(v: &str) -> bool {
    v.starts_with("1.")
}
fn v2(v: &str) -> bool {
    v.starts_with("2.")
}
fn with_io(v: &str) -> bool {
    v != "1.11"
}
fn upto_25(v: &str) -> bool {
    v != "2.7"
}
fn only_27(v: &str) -> bool {
    v == "2.7"
}

use Kind::*;

/// The schemas of FRI 1.11, 1.14-1.16, 2.5 and 2.7 (FRI.md's table, issue #25's
/// differences, the SDKs' generated message files).
const SCHEMA: &[FieldDef] = &[
    ("Monitoring", 1, "header", Msg("Header"), true, false, all),
    (
        "Monitoring",
        2,
        "robotInfo",
        Msg("RobotInfo"),
        false,
        false,
        all,
    ),
    (
        "Monitoring",
        3,
        "monitorData",
        Msg("MonitorData"),
        false,
        false,
        all,
    ),
    (
        "Monitoring",
        4,
        "connectionInfo",
        Msg("ConnectionInfo"),
        false,
        false,
        all,
    ),
    (
        "Monitoring",
        5,
        "ipoData",
        Msg("IpoData"),
        false,
        false,
        all,
    ),
    (
        "Monitoring",
        6,
        "requestedTransformations",
        Msg("Transformation"),
        false,
        true,
        all,
    ),
    (
        "Monitoring",
        15,
        "endOfMessageData",
        Msg("EndOf"),
        false,
        false,
        upto_25,
    ),
    ("Command", 1, "header", Msg("Header"), true, false, all),
    (
        "Command",
        2,
        "commandData",
        Msg("CommandData"),
        false,
        false,
        all,
    ),
    (
        "Command",
        15,
        "endOfMessageData",
        Msg("EndOf"),
        false,
        false,
        upto_25,
    ),
    ("Header", 1, "messageIdentifier", Varint, true, false, all),
    ("Header", 2, "sequenceCounter", Varint, true, false, all),
    (
        "Header",
        3,
        "reflectedSequenceCounter",
        Varint,
        true,
        false,
        all,
    ),
    (
        "ConnectionInfo",
        1,
        "sessionState",
        Varint,
        true,
        false,
        all,
    ),
    ("ConnectionInfo", 2, "quality", Varint, true, false, all),
    ("ConnectionInfo", 3, "sendPeriod", Varint, false, false, all),
    (
        "ConnectionInfo",
        4,
        "receiveMultiplier",
        Varint,
        false,
        false,
        all,
    ),
    ("RobotInfo", 1, "numberOfJoints", Varint, false, false, all),
    ("RobotInfo", 2, "safetyState", Varint, false, false, all),
    ("RobotInfo", 5, "driveState", Varint, false, true, all),
    ("RobotInfo", 6, "operationMode", Varint, false, false, all),
    ("RobotInfo", 7, "controlMode", Varint, false, false, all),
    (
        "MonitorData",
        1,
        "measuredJointPosition",
        Msg("JointValues"),
        false,
        false,
        all,
    ),
    (
        "MonitorData",
        2,
        "measuredTorque",
        Msg("JointValues"),
        false,
        false,
        all,
    ),
    (
        "MonitorData",
        3,
        "commandedJointPosition",
        Msg("JointValues"),
        false,
        false,
        v1,
    ),
    (
        "MonitorData",
        4,
        "commandedTorque",
        Msg("JointValues"),
        false,
        false,
        all,
    ),
    (
        "MonitorData",
        5,
        "externalTorque",
        Msg("JointValues"),
        false,
        false,
        all,
    ),
    (
        "MonitorData",
        6,
        "externalForce",
        Msg("CartesianVector"),
        false,
        false,
        only_27,
    ),
    (
        "MonitorData",
        8,
        "readIORequest",
        Msg("IoValue"),
        false,
        true,
        with_io,
    ),
    (
        "MonitorData",
        9,
        "measuredCartesianPose",
        Msg("Transformation"),
        false,
        false,
        v2,
    ),
    (
        "MonitorData",
        10,
        "measuredRedundancyInformation",
        Msg("Redundancy"),
        false,
        false,
        v2,
    ),
    (
        "MonitorData",
        15,
        "timestamp",
        Msg("TimeStamp"),
        false,
        false,
        all,
    ),
    (
        "IpoData",
        1,
        "jointPosition",
        Msg("JointValues"),
        false,
        false,
        all,
    ),
    (
        "IpoData",
        2,
        "cartesianPose",
        Msg("Transformation"),
        false,
        false,
        v2,
    ),
    (
        "IpoData",
        3,
        "redundancyInformation",
        Msg("Redundancy"),
        false,
        false,
        v2,
    ),
    (
        "IpoData",
        10,
        "clientCommandMode",
        Varint,
        false,
        false,
        all,
    ),
    ("IpoData", 11, "overlayType", Varint, false, false, all),
    (
        "IpoData",
        12,
        "trackingPerformance",
        Double,
        false,
        false,
        all,
    ),
    (
        "CommandData",
        1,
        "jointPosition",
        Msg("JointValues"),
        false,
        false,
        all,
    ),
    (
        "CommandData",
        2,
        "cartesianWrenchFeedForward",
        Msg("CartesianVector"),
        false,
        false,
        all,
    ),
    (
        "CommandData",
        3,
        "jointTorque",
        Msg("JointValues"),
        false,
        false,
        all,
    ),
    (
        "CommandData",
        4,
        "commandedTransformations",
        Msg("Transformation"),
        false,
        true,
        all,
    ),
    (
        "CommandData",
        5,
        "writeIORequest",
        Msg("IoValue"),
        false,
        true,
        with_io,
    ),
    (
        "CommandData",
        6,
        "cartesianPose",
        Msg("Transformation"),
        false,
        false,
        v2,
    ),
    (
        "CommandData",
        7,
        "redundancyInformation",
        Msg("Redundancy"),
        false,
        false,
        v2,
    ),
    ("JointValues", 1, "value", Double, false, true, all),
    ("CartesianVector", 1, "element", Double, false, true, all),
    ("TimeStamp", 1, "sec", Varint, true, false, all),
    ("TimeStamp", 2, "nanosec", Varint, true, false, all),
    ("Transformation", 1, "name", Str, true, false, all),
    ("Transformation", 2, "matrix", Double, false, true, all),
    (
        "Transformation",
        3,
        "timestamp",
        Msg("TimeStamp"),
        false,
        false,
        all,
    ),
    ("Redundancy", 1, "strategy", Varint, true, false, v2),
    ("Redundancy", 2, "value", Double, true, false, v2),
    ("IoValue", 1, "name", Str, true, false, with_io),
    ("IoValue", 2, "type", Varint, true, false, with_io),
    ("IoValue", 3, "direction", Varint, true, false, with_io),
    ("IoValue", 4, "digitalValue", Varint, false, false, with_io),
    ("IoValue", 5, "analogValue", Double, false, false, with_io),
    ("EndOf", 1, "messageLength", Varint, false, false, upto_25),
    (
        "EndOf",
        2,
        "messageChecksum",
        Msg("Checksum"),
        false,
        false,
        upto_25,
    ),
    ("Checksum", 1, "crc32", Varint, false, false, upto_25),
];

/// A decoded message: field name -> values (numbers, or nested messages).
#[derive(Debug, Default, Clone)]
struct Node {
    fields: BTreeMap<&'static str, Vec<Val>>,
}

#[derive(Debug, Clone)]
enum Val {
    U(u64),
    F(f64),
    /// A string (checked to be UTF-8).
    S,
    M(Node),
}

impl Node {
    fn u(&self, path: &[&str]) -> Option<u64> {
        match self.get(path)? {
            Val::U(x) => Some(*x),
            _ => None,
        }
    }
    fn get(&self, path: &[&str]) -> Option<&Val> {
        let (first, rest) = path.split_first()?;
        let v = self.fields.get(*first)?.first()?;
        if rest.is_empty() {
            return Some(v);
        }
        match v {
            Val::M(n) => n.get(rest),
            _ => None,
        }
    }
    fn doubles(&self, path: &[&str], field: &str) -> Option<Vec<f64>> {
        match self.get(path)? {
            Val::M(n) => Some(
                n.fields
                    .get(field)
                    .map(|vs| {
                        vs.iter()
                            .map(|v| match v {
                                Val::F(x) => *x,
                                _ => f64::NAN,
                            })
                            .collect()
                    })
                    .unwrap_or_default(),
            ),
            _ => None,
        }
    }
}

fn varint(b: &mut &[u8]) -> Result<u64, String> {
    let mut x = 0u64;
    for i in 0..10 {
        let (&byte, rest) = b.split_first().ok_or("truncated varint")?;
        *b = rest;
        x |= u64::from(byte & 0x7f) << (7 * i);
        if byte & 0x80 == 0 {
            return Ok(x);
        }
    }
    Err("varint too long".into())
}

fn take<'a>(b: &mut &'a [u8], n: usize) -> Result<&'a [u8], String> {
    if b.len() < n {
        return Err(format!("truncated: {n} bytes wanted, {} left", b.len()));
    }
    let (h, t) = b.split_at(n);
    *b = t;
    Ok(h)
}

/// Decodes `bytes` as message `msg` of FRI `v`; any field the version's schema
/// lacks, a wrong wire type or a missing required field is an error.
fn decode(mut b: &[u8], msg: &str, v: &str) -> Result<Node, String> {
    let mut node = Node::default();
    while !b.is_empty() {
        let key = varint(&mut b)?;
        let (tag, wt) = (key >> 3, (key & 7) as u8);
        let def = SCHEMA
            .iter()
            .find(|f| f.0 == msg && f.1 == tag && (f.6)(v))
            .ok_or_else(|| format!("{msg} field {tag} is not in FRI {v}'s schema"))?;
        let (name, kind, repeated) = (def.2, def.3, def.5);
        let vals = node.fields.entry(name).or_default();
        match (kind, wt) {
            (Varint, 0) => vals.push(Val::U(varint(&mut b)?)),
            (Double, 1) => {
                let d = take(&mut b, 8)?;
                vals.push(Val::F(f64::from_le_bytes(d.try_into().unwrap())));
            }
            (Double, 2) if repeated => {
                let n = varint(&mut b)? as usize;
                let mut p = take(&mut b, n)?;
                if n % 8 != 0 {
                    return Err(format!("{msg}.{name}: packed length {n}"));
                }
                while !p.is_empty() {
                    let d = take(&mut p, 8)?;
                    vals.push(Val::F(f64::from_le_bytes(d.try_into().unwrap())));
                }
            }
            (Str, 2) => {
                let n = varint(&mut b)? as usize;
                let s = take(&mut b, n)?;
                std::str::from_utf8(s).map_err(|e| e.to_string())?;
                vals.push(Val::S);
            }
            (Msg(sub), 2) => {
                let n = varint(&mut b)? as usize;
                let inner = take(&mut b, n)?;
                vals.push(Val::M(decode(inner, sub, v)?));
            }
            _ => return Err(format!("{msg}.{name}: wire type {wt}")),
        }
        if !repeated && vals.len() > 1 {
            // proto2 allows it (last wins), KUKA's encoders never write it.
            return Err(format!("{msg}.{name} written twice"));
        }
    }
    for f in SCHEMA.iter().filter(|f| f.0 == msg && f.4 && (f.6)(v)) {
        if !node.fields.contains_key(f.2) {
            return Err(format!("{msg}.{} is required", f.2));
        }
    }
    Ok(node)
}

/// CRC-32 (zlib), bit by bit.
fn crc32_bitwise(data: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &byte in data {
        crc ^= u32::from(byte);
        for _ in 0..8 {
            let lsb = crc & 1;
            crc >>= 1;
            if lsb != 0 {
                crc ^= 0xEDB8_8320;
            }
        }
    }
    !crc
}

/// The protobuf bytes of a datagram of FRI `v` (2.7: checks length and CRC).
fn unframe<'a>(d: &'a [u8], v: &str) -> Result<&'a [u8], String> {
    if d.len() > 1500 {
        return Err(format!("{} bytes", d.len()));
    }
    if v != "2.7" {
        return Ok(d);
    }
    if d.len() < 8 {
        return Err("shorter than a frame".into());
    }
    let len = u32::from_le_bytes(d[..4].try_into().unwrap()) as usize;
    if len + 8 != d.len() {
        return Err(format!("length field {len}, datagram {}", d.len()));
    }
    let body = &d[4..4 + len];
    let crc = u32::from_le_bytes(d[4 + len..].try_into().unwrap());
    if crc != crc32_bitwise(body) {
        return Err("CRC mismatch".into());
    }
    Ok(body)
}

fn monitoring(d: &[u8], v: &str) -> Result<Node, String> {
    let n = decode(unframe(d, v)?, "Monitoring", v)?;
    if n.u(&["header", "messageIdentifier"]) != Some(0x24_5142) {
        return Err("not the monitoring identifier".into());
    }
    if n.get(&["connectionInfo"]).is_none() {
        return Err("no connectionInfo".into());
    }
    Ok(n)
}

fn command(d: &[u8], v: &str) -> Result<Node, String> {
    let n = decode(unframe(d, v)?, "Command", v)?;
    if n.u(&["header", "messageIdentifier"]) != Some(0x3_4001) {
        return Err("not the command identifier".into());
    }
    Ok(n)
}

// ---------------------------------------------------------------------------
// Virtual time: every datagram of a whole session through the independent decoder.

#[derive(Default)]
struct Ramp {
    steps: u64,
}

impl ControlStep for Ramp {
    fn step(&mut self, input: &StepInput<'_>, command_rad: &mut Joints) {
        if input.commanding {
            self.steps += 1;
            command_rad[0] += 0.2 * input.receive_period_s;
        }
    }
}

#[test]
fn each_versions_controller_and_client_datagrams_decode_with_an_independent_decoder() {
    for version in FriVersion::ALL {
        let v = version.name();
        let sim_params = FriSimParams {
            fri_version: version,
            fri_period_ms: 2,
            ..FriSimParams::default()
        };
        let period_ns = sim_params.period_ns();
        let mut sim = SimController::new(sim_params, 1_790_000_000_000_000_000).unwrap();
        sim.request_commanding();
        let mut client = FriClient::new(FriClientParams {
            version,
            ..FriClientParams::default()
        })
        .unwrap();
        let mut ctl = Ramp::default();
        let mut states = std::collections::BTreeSet::new();
        let (mut monitored, mut commands, mut positions) = (0, 0, 0);
        let mut t = 0u64;
        while let Some(m) = sim.tick(t).map(<[u8]>::to_vec) {
            let n = monitoring(&m, v).unwrap_or_else(|e| panic!("FRI {v} monitoring: {e}"));
            monitored += 1;
            let state = n.u(&["connectionInfo", "sessionState"]).unwrap();
            states.insert(state);
            let measured = n.doubles(&["monitorData", "measuredJointPosition"], "value");
            assert_eq!(measured.map(|q| q.len()), Some(7), "FRI {v}");
            let commanded = n.doubles(&["monitorData", "commandedJointPosition"], "value");
            assert_eq!(commanded.map(|q| q.len()), v1(v).then_some(7), "FRI {v}");
            let force = n.doubles(&["monitorData", "externalForce"], "element");
            assert_eq!(force.map(|f| f.len()), only_27(v).then_some(6), "FRI {v}");
            if state == 3 || state == 4 {
                let ipo = n.doubles(&["ipoData", "jointPosition"], "value");
                assert_eq!(ipo.map(|q| q.len()), Some(7), "FRI {v}");
            }
            if let Some(r) = client.on_datagram(&m, t + 50_000, &mut ctl) {
                let c = command(r, v).unwrap_or_else(|e| panic!("FRI {v} command: {e}"));
                commands += 1;
                assert_eq!(
                    c.u(&["header", "reflectedSequenceCounter"]),
                    n.u(&["header", "sequenceCounter"])
                );
                match c.doubles(&["commandData", "jointPosition"], "value") {
                    Some(q) => {
                        assert_eq!(q.len(), 7);
                        assert!(state == 3 || state == 4, "a position in state {state}");
                        positions += 1;
                    }
                    // From 2.5 and in MONITORING_*: header-only replies.
                    None => assert!(state == 1 || state == 2, "no position in state {state}"),
                }
                sim.on_reply(r, t + 100_000);
            }
            t += period_ns;
            if ctl.steps == 50 {
                sim.request_close();
            }
            assert!(t < 10_000_000_000, "FRI {v}: no commanding");
        }
        assert_eq!(
            states.into_iter().collect::<Vec<_>>(),
            [0, 1, 2, 3, 4],
            "FRI {v}"
        );
        assert_eq!(client.stats().decode_errors.load(Relaxed), 0, "FRI {v}");
        assert_eq!(sim.stats().report().violations, 0, "FRI {v}");
        eprintln!(
            "FRI {v}: {monitored} monitoring messages, {commands} replies ({positions} with positions) decoded independently"
        );
    }
}

#[test]
fn the_independent_decoder_is_strict_about_versions() {
    // A 1.15 controller's message is not a 2.5 message (commandedJointPosition),
    // nor a 2.7 one (no frame); a 2.7 one is not a 1.15 one.
    let sim = |version: FriVersion| {
        let mut s = SimController::new(
            FriSimParams {
                fri_version: version,
                ..FriSimParams::default()
            },
            0,
        )
        .unwrap();
        s.tick(0).unwrap().to_vec()
    };
    let m115 = sim(FriVersion::V1_15);
    let m27 = sim(FriVersion::V2_7);
    let m25 = sim(FriVersion::V2_5);
    assert!(monitoring(&m115, "1.15").is_ok());
    assert!(monitoring(&m115, "2.5").is_err());
    assert!(monitoring(&m115, "2.7").is_err());
    assert!(monitoring(&m27, "1.15").is_err());
    assert!(
        monitoring(&m25, "1.15").is_ok(),
        "2.5 has no field 1.15 lacks"
    );
    let mut flipped = m27.clone();
    flipped[20] ^= 0x10;
    assert_eq!(monitoring(&flipped, "2.7").unwrap_err(), "CRC mismatch");
}

// ---------------------------------------------------------------------------
// Real UDP: every pairing at 1 and 5 ms.

fn loopback() -> SocketAddr {
    SocketAddr::from(([127, 0, 0, 1], 0))
}

fn wait_for(what: &str, timeout: Duration, mut cond: impl FnMut() -> bool) {
    let start = Instant::now();
    while !cond() {
        assert!(
            start.elapsed() < timeout,
            "timed out after {timeout:?} waiting for {what}"
        );
        std::thread::sleep(Duration::from_millis(1));
    }
}

#[test]
fn every_version_completes_a_session_over_udp_at_1_and_5_ms() {
    let mut lines = Vec::new();
    for version in FriVersion::ALL {
        for period_ms in [1u32, 5] {
            let v = version.name();
            let session = FriSession::spawn(
                FriSessionParams {
                    bind: loopback(),
                    client: FriClientParams {
                        version,
                        ..FriClientParams::default()
                    },
                    ..FriSessionParams::default()
                },
                Ramp::default(),
            )
            .unwrap();
            let server = SimServer::spawn(
                FriSimParams {
                    fri_version: version,
                    fri_period_ms: period_ms,
                    ..FriSimParams::default()
                },
                loopback(),
                session.local_addr(),
                SimRunOptions {
                    auto_command: true,
                    duration: None,
                    normal_priority: false,
                    // A controller that dropped out of commanding on a
                    // starved machine (late replies) asks again: the
                    // session's protocol is what is tested here, not the
                    // machine's timing.
                    keep_commanding: true,
                },
            )
            .unwrap();
            let sim = Arc::clone(server.stats());
            let cl = Arc::clone(session.stats());
            wait_for(
                &format!("FRI {v} {period_ms} ms: COMMANDING_ACTIVE"),
                Duration::from_secs(30),
                || {
                    sim.state() == SessionState::CommandingActive
                        && cl.state() == LinkState::CommandingActive
                },
            );
            // 20 commands applied in COMMANDING_ACTIVE, then the controller closes.
            let before = sim.commands_applied.load(Relaxed);
            wait_for(
                &format!("FRI {v} {period_ms} ms: commands"),
                Duration::from_secs(30),
                || sim.commands_applied.load(Relaxed) >= before + 20,
            );
            let report = server.close(Duration::from_secs(2)).unwrap();
            wait_for(
                &format!("FRI {v} {period_ms} ms: IDLE"),
                Duration::from_secs(2),
                || cl.state() == LinkState::Idle,
            );
            let _ = session.stop().unwrap();
            let st = cl.snapshot();
            lines.push(format!(
                "FRI {v} {period_ms} ms: {} messages, {} replies, {} commands, decode errors client {} controller {}, late {}, violations {}, states {}",
                st.received,
                report.replies,
                st.commands,
                st.decode_errors,
                report.decode_errors,
                st.late_replies,
                report.violations,
                report.states_reached.join(" -> ")
            ));
            assert_eq!(
                st.decode_errors, 0,
                "FRI {v} {period_ms} ms: client decode errors"
            );
            assert_eq!(
                report.decode_errors, 0,
                "FRI {v} {period_ms} ms: controller decode errors"
            );
            assert_eq!(report.violations, 0, "FRI {v} {period_ms} ms");
            assert_eq!(st.version, v);
            assert_eq!(
                report.states_reached.first().copied(),
                Some("MONITORING_WAIT")
            );
            assert!(
                report.states_reached.contains(&"COMMANDING_ACTIVE"),
                "FRI {v} {period_ms} ms: {:?}",
                report.states_reached
            );
            assert_eq!(
                report.states_reached.last().copied(),
                Some("IDLE"),
                "FRI {v} {period_ms} ms"
            );
        }
    }
    for l in lines {
        eprintln!("{l}");
    }
}
