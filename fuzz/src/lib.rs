//! The harnesses behind the fuzz targets (see README.md), shared with the seed
//! generator (`examples/seeds.rs`).
//!
//! Every harness asserts properties, not just "no panic": the decoders that
//! reuse their message agree with fresh ones, the client and the simulated
//! controller count exactly the datagrams the codec refuses and ignore them,
//! and whatever they send decodes and stays inside the joint limits.

use std::mem::discriminant;
use std::sync::atomic::Ordering::Relaxed;

use rt_core::fri::codec::{
    command_view, decode_command_message_of, decode_monitoring_message_of, monitoring_view,
};
use rt_core::fri::{
    CommandDecoder, CommandEncoder, ControlStep, FriClient, FriClientParams, Joints, LinkState,
    MonitoringDecoder, MonitoringEncoder, SessionState, StepInput,
};
use rt_core::kinematics::iiwa7::{JOINTS, POSITION_LIMIT_RAD};
use rt_core::sim::kuka::{FriSimParams, SimController};

/// One step of a session script: the first byte says what happens, a payload
/// (2-byte little-endian length, then the bytes) follows for datagrams.
///
/// `op & 3`: 0 = a datagram after `(op >> 2) * 250 us`; 1 = the same without
/// advancing time; 2 = a control/controller action chosen by `op >> 2`;
/// 3 = time passes by `(op >> 2) * 250 us` (the client polls, the controller ticks).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Step<'a> {
    /// A datagram arrives `advance_us` after the previous step.
    Datagram {
        /// Time since the previous step, us.
        advance_us: u64,
        /// The datagram (any bytes).
        bytes: &'a [u8],
    },
    /// An action chosen by the value (0..63).
    Action(u8),
    /// Time passes.
    Wait {
        /// How long, us.
        advance_us: u64,
    },
}

/// Splits fuzz input into steps (a truncated tail becomes a shorter datagram).
pub fn steps(mut data: &[u8]) -> impl Iterator<Item = Step<'_>> {
    std::iter::from_fn(move || {
        let (&op, rest) = data.split_first()?;
        data = rest;
        let arg = op >> 2;
        let advance_us = u64::from(arg) * 250;
        Some(match op & 3 {
            0 | 1 => {
                let len = match data {
                    [a, b, ..] => usize::from(u16::from_le_bytes([*a, *b])),
                    _ => 0,
                };
                data = data.get(2..).unwrap_or_default();
                let len = len.min(data.len());
                let (bytes, rest) = data.split_at(len);
                data = rest;
                Step::Datagram {
                    advance_us: if op & 3 == 0 { advance_us } else { 0 },
                    bytes,
                }
            }
            2 => Step::Action(arg),
            _ => Step::Wait { advance_us },
        })
    })
}

/// Writes a datagram step (the inverse of [`steps`], for seeds).
pub fn push_datagram(out: &mut Vec<u8>, advance_us: u64, bytes: &[u8]) {
    let arg = (advance_us / 250).min(63) as u8;
    out.push(arg << 2);
    out.extend_from_slice(&(bytes.len() as u16).to_le_bytes());
    out.extend_from_slice(bytes);
}

/// Writes an action step.
pub fn push_action(out: &mut Vec<u8>, action: u8) {
    out.push(((action & 63) << 2) | 2);
}

/// Writes a wait step.
pub fn push_wait(out: &mut Vec<u8>, advance_us: u64) {
    out.push((((advance_us / 250).min(63) as u8) << 2) | 3);
}

/// `format!("{:?}")` compares NaN payloads and signed zeros as written.
fn same<T: std::fmt::Debug>(a: &T, b: &T) -> bool {
    format!("{a:?}") == format!("{b:?}")
}

/// Monitoring decode: the reusing decoder agrees with a fresh decode of the
/// same bytes (nothing leaks from earlier datagrams), and an accepted message
/// re-encodes to one that decodes to the same view.
pub fn monitoring_decode(dec: &mut MonitoringDecoder, enc: &mut MonitoringEncoder, data: &[u8]) {
    let reused = dec.decode(data);
    let v = dec.version();
    let fresh = decode_monitoring_message_of(data, v).and_then(|m| monitoring_view(&m, v));
    match (&reused, &fresh) {
        (Ok(a), Ok(b)) => assert!(same(a, b), "reused {a:?}\nfresh {b:?}"),
        (Err(a), Err(b)) => assert_eq!(discriminant(a), discriminant(b), "{a} vs {b}"),
        _ => panic!("reused {reused:?} but fresh {fresh:?}"),
    }
    if let Ok(m) = reused {
        let bytes = enc.encode(&m).expect("a decoded view re-encodes").to_vec();
        let again = dec.decode(&bytes).expect("re-encoded message decodes");
        assert!(same(&again, &m), "round trip {m:?} -> {again:?}");
    }
}

/// Command decode: as [`monitoring_decode`], for the controller's side.
pub fn command_decode(dec: &mut CommandDecoder, enc: &mut CommandEncoder, data: &[u8]) {
    let reused = dec.decode(data);
    let v = dec.version();
    let fresh = decode_command_message_of(data, v).and_then(|m| command_view(&m, v));
    match (&reused, &fresh) {
        (Ok(a), Ok(b)) => assert!(same(a, b), "reused {a:?}\nfresh {b:?}"),
        (Err(a), Err(b)) => assert_eq!(discriminant(a), discriminant(b), "{a} vs {b}"),
        _ => panic!("reused {reused:?} but fresh {fresh:?}"),
    }
    if let Ok(c) = reused {
        let bytes = enc
            .encode(
                c.sequence_counter,
                c.reflected_sequence_counter,
                c.joint_position_rad.as_ref(),
            )
            .expect("a decoded command re-encodes")
            .to_vec();
        // 77 bytes with counters below 128; each counter is a varint of up to 5 bytes.
        // FRI 2.7 frames add 4 bytes of length and 4 of CRC.
        let framing = if v.framed() { 8 } else { 0 };
        let max = framing
            + if c.joint_position_rad.is_some() {
                85
            } else {
                18
            };
        assert!(bytes.len() <= max, "{} bytes", bytes.len());
        let again = dec.decode(&bytes).expect("re-encoded command decodes");
        assert_eq!(again.sequence_counter, c.sequence_counter);
        assert_eq!(
            again.reflected_sequence_counter,
            c.reflected_sequence_counter
        );
        assert!(same(&again.joint_position_rad, &c.joint_position_rad));
    }
}

/// A control whose command the fuzz input chooses: hold, small or huge steps,
/// NaN, infinity, far beyond the limits.
#[derive(Debug, Default)]
struct Wild {
    mode: u8,
    calls: u64,
}

impl ControlStep for Wild {
    fn step(&mut self, input: &StepInput<'_>, command_rad: &mut Joints) {
        self.calls += 1;
        if !input.commanding {
            return;
        }
        let j = usize::from(self.mode / 8) % JOINTS;
        match self.mode % 8 {
            0 => {}
            1 => command_rad[j] += 1e-3,
            2 => command_rad[j] -= 0.5,
            3 => command_rad[j] = f64::NAN,
            4 => command_rad[j] = f64::INFINITY,
            5 => command_rad[j] = -1e300,
            6 => *command_rad = [4.0; JOINTS],
            _ => command_rad[j] = f64::MIN_POSITIVE,
        }
    }
}

/// Inside the joint limits and finite.
fn within_limits(q: &Joints) -> bool {
    q.iter()
        .zip(POSITION_LIMIT_RAD)
        .all(|(v, lim)| v.is_finite() && v.abs() <= lim)
}

/// The client fed a script of arbitrary datagrams: it counts every datagram the
/// codec refuses and ignores it, answers only valid messages (never in IDLE)
/// with a valid command whose counters are right, and with the guard on never
/// sends a position outside the limits, whatever the control asks.
pub fn client_on_datagram(data: &[u8]) {
    let mut client = FriClient::new(FriClientParams::default()).expect("default params");
    let mut control = Wild::default();
    let mut check = MonitoringDecoder::new();
    let mut reply_dec = CommandDecoder::new();
    let mut now_ns: u64 = 1_000_000;
    let mut refused = 0u64;
    let mut replies = 0u64;
    // Every joint position the controller handed over so far was finite and
    // inside the limits (the guard's premise).
    let mut sane = true;
    for step in steps(data) {
        match step {
            Step::Datagram { advance_us, bytes } => {
                now_ns += advance_us * 1000;
                let valid = check.decode(bytes);
                match &valid {
                    Err(_) => refused += 1,
                    Ok(m) => {
                        for q in [
                            m.ipo_joint_position_rad,
                            m.commanded_joint_position_rad,
                            m.measured_joint_position_rad,
                        ]
                        .iter()
                        .flatten()
                        {
                            sane &= within_limits(q);
                        }
                    }
                }
                let reply = client
                    .on_datagram(bytes, now_ns, &mut control)
                    .map(<[u8]>::to_vec);
                let st = client.stats();
                assert_eq!(st.decode_errors.load(Relaxed), refused);
                let Some(reply) = reply else { continue };
                let m = valid.expect("a reply to a refused datagram");
                assert_ne!(m.session_state, SessionState::Idle, "a reply in IDLE");
                let c = reply_dec
                    .decode(&reply)
                    .expect("the client's reply decodes");
                assert_eq!(c.sequence_counter as u64, replies);
                assert_eq!(c.reflected_sequence_counter, m.sequence_counter);
                replies += 1;
                assert_eq!(st.replies.load(Relaxed), replies);
                if client.state() == LinkState::CommandingActive
                    && let Some(q) = c.joint_position_rad
                {
                    // Whatever the control or the controller sent (NaN, 1e300,
                    // far jumps), the command is finite and, from a sane
                    // hand-over, inside the limits.
                    assert!(q.iter().all(|v| v.is_finite()), "command {q:?}");
                    assert!(!sane || within_limits(&q), "guarded command {q:?}");
                }
            }
            Step::Action(a) => control.mode = a,
            Step::Wait { advance_us } => {
                now_ns += advance_us * 1000;
                client.poll(now_ns, &mut control);
            }
        }
    }
    assert_eq!(client.stats().replies.load(Relaxed), replies);
}

/// The simulated controller fed a script of arbitrary replies between its
/// ticks: it counts every reply the codec refuses and ignores it, its own
/// datagrams always decode (7 joints, required fields), and its joints stay
/// finite and inside the limits whatever was commanded.
pub fn sim_on_reply(data: &[u8]) {
    let params = FriSimParams {
        latency_jitter_ms: 0.0,
        ..FriSimParams::default()
    };
    let period_ns = params.period_ns();
    let mut sim = SimController::new(params, 0).expect("default params");
    let mut check = CommandDecoder::new();
    let mut mon = MonitoringDecoder::new();
    let mut now_ns: u64 = 0;
    let mut next_tick: u64 = 0;
    let mut refused = 0u64;
    let stats = std::sync::Arc::clone(sim.stats());
    for step in steps(data) {
        let advance_us = match step {
            Step::Datagram { advance_us, .. } | Step::Wait { advance_us } => advance_us,
            Step::Action(_) => 0,
        };
        now_ns += advance_us * 1000;
        // Every send period that passed: one monitoring message, in time order.
        while next_tick <= now_ns {
            let closed_before = sim.is_closed();
            match sim.tick(next_tick) {
                Some(bytes) => {
                    let m = mon
                        .decode(bytes)
                        .expect("the controller's datagram decodes");
                    let q = m
                        .measured_joint_position_rad
                        .expect("measured positions are always sent");
                    assert!(within_limits(&q), "joints beyond the limits: {q:?}");
                    assert_eq!(
                        m.ipo_joint_position_rad.is_some(),
                        m.session_state.is_commanding()
                    );
                }
                // Nothing is lost by injection here: only a closed session is silent.
                None => assert!(closed_before, "no datagram from an open session"),
            }
            next_tick += period_ns;
        }
        match step {
            Step::Datagram { bytes, .. } => {
                // (A closed session still reads the answers to its messages.)
                if check.decode(bytes).is_err() {
                    refused += 1;
                }
                sim.on_reply(bytes, now_ns);
                assert_eq!(stats.decode_errors.load(Relaxed), refused);
            }
            Step::Action(a) => match a {
                62 => sim.request_close(),
                _ if a % 2 == 0 => sim.request_commanding(),
                _ => {}
            },
            Step::Wait { .. } => {}
        }
        assert!(within_limits(sim.joint_rad()), "{:?}", sim.joint_rad());
    }
}
