//! **Deprecated**: superseded by the simulated KUKA controller
//! [`crate::fri::SimController`], which the virtual-time lab
//! ([`super::VirtualLab`]) runs through the FRI client session. Kept only
//! while `server/src/simlab.rs` and [`super::realtime`] still use it; do not
//! use it in new code.
//!
//! The simulated robot driven in virtual time: a KUKA controller's joint
//! servo behind FRI. Monitoring datagrams are encoded and command datagrams
//! decoded with the real FRI codec; a command reaches the joints after the
//! robot's latency (with uniform jitter, never reordered) and the joints follow
//! their setpoint through a first-order servo lag. A commanded step beyond a
//! joint's speed limit, or a setpoint beyond its position limit, is counted as
//! a violation (the real controller would trip).

use std::collections::VecDeque;

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::fri::codec::{CommandDecoder, Joints, Monitoring, MonitoringEncoder, UnixTime};
use crate::fri::proto::{ConnectionQuality, SessionState};
use crate::kinematics::iiwa7::{JOINTS, POSITION_LIMIT_RAD, VELOCITY_LIMIT_RADPS};
use crate::params::RobotParams;

/// Servo time constant of the simulated joints, seconds.
pub const SERVO_TIME_CONSTANT_S: f64 = 0.005;

/// The simulated robot (see the module documentation).
#[derive(Debug)]
pub struct VirtualRobot {
    period_ns: u64,
    latency_ns: f64,
    jitter_ns: f64,
    q: Joints,
    setpoint: Joints,
    last_command: Option<Joints>,
    pending: VecDeque<(u64, Joints)>,
    last_apply_ns: u64,
    t_ns: u64,
    rng: ChaCha8Rng,
    enc: MonitoringEncoder,
    dec: CommandDecoder,
    seq: u32,
    reflected: u32,
    /// Commands beyond a speed or position limit.
    pub violations: u64,
    /// Datagrams that did not decode.
    pub decode_errors: u64,
    /// Commands received.
    pub commands: u64,
}

impl VirtualRobot {
    /// A robot at rest at `q0`, with the scenario's period and latency, seeded.
    pub fn new(robot: &RobotParams, q0: Joints, seed: u64) -> Self {
        Self {
            period_ns: u64::from(robot.fri_period_ms) * 1_000_000,
            latency_ns: robot.latency_ms * 1e6,
            jitter_ns: robot.latency_jitter_ms.min(robot.latency_ms) * 1e6,
            q: q0,
            setpoint: q0,
            last_command: None,
            pending: VecDeque::with_capacity(1024),
            last_apply_ns: 0,
            t_ns: 0,
            rng: ChaCha8Rng::seed_from_u64(seed),
            enc: MonitoringEncoder::new(),
            dec: CommandDecoder::new(),
            seq: 0,
            reflected: 0,
            violations: 0,
            decode_errors: 0,
            commands: 0,
        }
    }

    /// True joint positions, radians.
    pub fn joints(&self) -> &Joints {
        &self.q
    }

    /// The send period, nanoseconds.
    pub fn period_ns(&self) -> u64 {
        self.period_ns
    }

    fn servo_to(&mut self, t_ns: u64) {
        if t_ns <= self.t_ns {
            return;
        }
        let dt = (t_ns - self.t_ns) as f64 * 1e-9;
        let a = 1.0 - (-dt / SERVO_TIME_CONSTANT_S).exp();
        for j in 0..JOINTS {
            self.q[j] += a * (self.setpoint[j] - self.q[j]);
        }
        self.t_ns = t_ns;
    }

    /// Advances the joints to `now_ns` and returns the monitoring datagram
    /// (COMMANDING_ACTIVE) due then, or `None` if it could not be encoded.
    pub fn tick(&mut self, now_ns: u64) -> Option<&[u8]> {
        while let Some(&(at, sp)) = self.pending.front() {
            if at > now_ns {
                break;
            }
            self.servo_to(at);
            self.setpoint = sp;
            self.pending.pop_front();
        }
        self.servo_to(now_ns);
        let seq = self.seq;
        self.seq = self.seq.wrapping_add(1);
        let m = Monitoring {
            sequence_counter: seq,
            reflected_sequence_counter: self.reflected,
            session_state: SessionState::CommandingActive,
            quality: ConnectionQuality::Excellent,
            send_period_ms: u32::try_from(self.period_ns / 1_000_000).unwrap_or(1),
            receive_multiplier: 1,
            measured_joint_position_rad: Some(self.q),
            commanded_joint_position_rad: Some(self.setpoint),
            ipo_joint_position_rad: Some(self.setpoint),
            timestamp: Some(UnixTime::from_ns(now_ns)),
            ..Monitoring::default()
        };
        self.enc.encode(&m).ok()
    }

    /// Takes a command datagram that arrived at `now_ns`; returns the sequence
    /// counter of the monitoring message it answers (`None` if it did not decode).
    pub fn on_reply(&mut self, bytes: &[u8], now_ns: u64) -> Option<u32> {
        let c = match self.dec.decode(bytes) {
            Ok(c) => c,
            Err(_) => {
                self.decode_errors += 1;
                return None;
            }
        };
        self.reflected = c.sequence_counter;
        let answers = Some(c.reflected_sequence_counter);
        let Some(q) = c.joint_position_rad else {
            return answers;
        };
        self.commands += 1;
        let period_s = self.period_ns as f64 * 1e-9;
        let prev = self.last_command.unwrap_or(self.setpoint);
        let bad = (0..JOINTS).any(|j| {
            !q[j].is_finite()
                || q[j].abs() > POSITION_LIMIT_RAD[j]
                || (q[j] - prev[j]).abs() > VELOCITY_LIMIT_RADPS[j] * period_s * 1.001
        });
        if bad {
            self.violations += 1;
            return answers;
        }
        self.last_command = Some(q);
        let jitter = if self.jitter_ns > 0.0 {
            self.rng.random_range(-self.jitter_ns..=self.jitter_ns)
        } else {
            0.0
        };
        let at = now_ns + (self.latency_ns + jitter).max(0.0) as u64;
        // Never reordered.
        let at = at.max(self.last_apply_ns);
        self.last_apply_ns = at;
        self.pending.push_back((at, q));
        answers
    }

    /// The sequence counter the next monitoring message will carry.
    pub fn next_sequence(&self) -> u32 {
        self.seq
    }
}
