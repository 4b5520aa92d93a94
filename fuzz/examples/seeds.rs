//! Writes the seed corpus (`fuzz/seeds/<target>/`) from real sessions: the
//! codec's golden messages and scripts of a client and the simulated
//! controller walking MONITORING_WAIT .. COMMANDING_ACTIVE .. IDLE.
//!
//! `cargo run --manifest-path fuzz/Cargo.toml --example seeds [-- OUT_DIR]`

use std::collections::BTreeMap;
use std::path::PathBuf;

use isochron_fuzz::{push_action, push_datagram, push_wait};
use rt_core::fri::{
    CommandEncoder, ControlStep, FriClient, FriClientParams, Joints, MonitoringDecoder,
    SessionState, StepInput,
};
use rt_core::sim::kuka::{FriSimParams, SimController};

/// Moves A1 slowly while commanding.
struct Creep;

impl ControlStep for Creep {
    fn step(&mut self, input: &StepInput<'_>, command_rad: &mut Joints) {
        if input.commanding {
            command_rad[0] += 1e-4;
        }
    }
}

/// A whole session in virtual time, driven exactly as `isochron_fuzz::sim_on_reply`
/// drives the controller: returns its script, every monitoring datagram and
/// every reply.
fn session(params: FriSimParams) -> (Vec<u8>, Vec<Vec<u8>>, Vec<Vec<u8>>) {
    let period_ns = params.period_ns();
    let mut sim = SimController::new(params, 0).expect("valid params");
    let mut client = FriClient::new(FriClientParams::default()).expect("valid params");
    let (mut script, mut monitoring, mut replies) = (Vec::new(), Vec::new(), Vec::new());
    let (mut now, mut next_tick, mut active) = (0u64, 0u64, 0);
    let mut pending: Vec<Vec<u8>> = Vec::new();
    let mut advance = |now: u64, sim: &mut SimController, pending: &mut Vec<Vec<u8>>| {
        while next_tick <= now {
            if let Some(b) = sim.tick(next_tick) {
                monitoring.push(b.to_vec());
                let b = b.to_vec();
                if let Some(r) = client.on_datagram(&b, next_tick, &mut Creep) {
                    pending.push(r.to_vec());
                }
            }
            next_tick += period_ns;
        }
    };
    push_action(&mut script, 0);
    advance(now, &mut sim, &mut pending);
    sim.request_commanding();
    while active < 10 {
        push_wait(&mut script, 5_000);
        now += 5_000_000;
        advance(now, &mut sim, &mut pending);
        for r in pending.drain(..) {
            push_datagram(&mut script, 0, &r);
            sim.on_reply(&r, now);
            replies.push(r);
        }
        if sim.state() == SessionState::CommandingActive {
            active += 1;
        }
        assert!(now < 10_000_000_000, "the session never reached commanding");
    }
    push_action(&mut script, 62);
    advance(now, &mut sim, &mut pending);
    sim.request_close();
    push_wait(&mut script, 5_000);
    now += 5_000_000;
    advance(now, &mut sim, &mut pending);
    assert!(sim.is_closed());
    assert_eq!(
        sim.stats()
            .decode_errors
            .load(std::sync::atomic::Ordering::Relaxed),
        0
    );
    (script, monitoring, replies)
}

fn main() -> std::io::Result<()> {
    let out = std::env::args()
        .nth(1)
        .map_or_else(|| PathBuf::from("fuzz/seeds"), PathBuf::from);
    let mut files: BTreeMap<(&str, String), Vec<u8>> = BTreeMap::new();

    // The controller's script: the harness's own parameters.
    let (script, monitoring, replies) = session(FriSimParams {
        latency_jitter_ms: 0.0,
        ..FriSimParams::default()
    });
    files.insert(("sim_on_reply", "session".into()), script);

    // One monitoring datagram per state, the first and last of each.
    let mut dec = MonitoringDecoder::new();
    let mut by_state: BTreeMap<i32, Vec<&Vec<u8>>> = BTreeMap::new();
    for m in &monitoring {
        let s = dec.decode(m).expect("valid").session_state as i32;
        by_state.entry(s).or_default().push(m);
    }
    for (s, ms) in &by_state {
        let name = SessionState::try_from(*s).map_or("unknown", |x| x.name());
        files.insert(
            ("monitoring_decode", format!("{name}-first")),
            ms[0].clone(),
        );
        if ms.len() > 1 {
            files.insert(
                ("monitoring_decode", format!("{name}-last")),
                ms[ms.len() - 1].clone(),
            );
        }
    }
    // Replies: header only, the mirrored hand-over, a command; and golden bytes.
    for (k, r) in replies.iter().enumerate() {
        let kind = match r.len() {
            n if n <= 20 => "header",
            _ if k + 1 == replies.len() => "command",
            _ => continue,
        };
        files
            .entry(("command_decode", kind.into()))
            .or_insert_with(|| r.clone());
    }
    let mut enc = CommandEncoder::new();
    let golden = [0.0, 0.5, -0.5, 1.0, -1.0, 0.25, -0.25];
    files.insert(
        ("command_decode", "golden-77-bytes".into()),
        enc.encode(0, 7, Some(&golden)).expect("encodes").to_vec(),
    );

    // The client's script: a short session (ready after 2 replies), then a
    // control asking for a NaN, and a silence.
    let (_, short, _) = session(FriSimParams {
        ready_after_replies: 2,
        commanding_wait_ms: 5.0,
        ..FriSimParams::default()
    });
    let mut client_script = Vec::new();
    push_action(&mut client_script, 1);
    for (k, m) in short.iter().enumerate() {
        if k + 3 == short.len() {
            push_action(&mut client_script, 3);
        }
        push_datagram(&mut client_script, 5_000, m);
    }
    push_wait(&mut client_script, 12_000);
    files.insert(("client_on_datagram", "session".into()), client_script);

    for ((target, name), bytes) in &files {
        let dir = out.join(target);
        std::fs::create_dir_all(&dir)?;
        std::fs::write(dir.join(name), bytes)?;
        println!("{}/{name}: {} bytes", dir.display(), bytes.len());
    }
    Ok(())
}
