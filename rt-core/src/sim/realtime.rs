//! The real-time runtime over loopback UDP: a simulated robot controller on
//! its own named thread sends FRI monitoring datagrams every period; the
//! control thread blocks on its socket (with a timeout), runs one control step
//! per message and answers with the command datagram. Measures what
//! `isochron bench`'s `loop` section reports.

use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread;
use std::time::{Duration, Instant};

use serde::Serialize;

use super::lab::{INITIAL_JOINTS_DEG, LoopStep};
use super::robot::VirtualRobot;
use crate::control::Controller;
use crate::control::stats::quantile_sorted;
use crate::fri::codec::{CommandEncoder, MAX_DATAGRAM_BYTES, MonitoringDecoder};
use crate::params::Scenario;

/// Reply latency percentiles, microseconds.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct LatencyUs {
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// 99.9th percentile.
    pub p999: f64,
    /// Largest.
    pub max: f64,
}

/// What one real-time loop run measured (CONTRACT.md, `isochron bench`'s `loop`).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct LoopReport {
    /// FRI send period, milliseconds.
    pub period_ms: u32,
    /// Monitoring messages sent.
    pub cycles: u64,
    /// Replies that arrived after the next message was due.
    pub late_replies: u64,
    /// Cycles whose reply never arrived.
    pub missed_cycles: u64,
    /// Send -> reply received, microseconds.
    pub reply_latency_us: LatencyUs,
    /// Control steps longer than the period.
    pub deadline_misses: u64,
}

/// Errors of the real-time runtime.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RealtimeError {
    /// A socket or thread could not be set up.
    #[error("real-time loop: {0}")]
    Io(#[from] std::io::Error),
    /// The controller refused the scenario.
    #[error(transparent)]
    Control(#[from] crate::control::ControlError),
    /// A thread panicked.
    #[error("real-time loop: the {0} thread failed")]
    Thread(&'static str),
}

/// Runs the control thread against the simulated controller over loopback UDP
/// for `duration` at the scenario's FRI period (the controller holds the arm).
pub fn run_loop(scenario: &Scenario, duration: Duration) -> Result<LoopReport, RealtimeError> {
    let period_ms = scenario.robot.fri_period_ms;
    let period = Duration::from_millis(u64::from(period_ms));
    let controller = Controller::new(scenario, period.as_secs_f64())?;
    let ctl_sock = UdpSocket::bind("127.0.0.1:0")?;
    ctl_sock.set_read_timeout(Some(Duration::from_millis(100)))?;
    let ctl_addr = ctl_sock.local_addr()?;
    let robot_sock = UdpSocket::bind("127.0.0.1:0")?;
    let stop = Arc::new(AtomicBool::new(false));
    let epoch = Instant::now();

    let stop_c = Arc::clone(&stop);
    let control = thread::Builder::new()
        .name("isochron-control".to_owned())
        .spawn(move || control_thread(&ctl_sock, controller, &stop_c, epoch, period))?;

    let robot_params = scenario.robot.clone();
    let robot = thread::Builder::new()
        .name("isochron-fri-sim".to_owned())
        .spawn(move || {
            robot_thread(
                &robot_sock,
                ctl_addr,
                &robot_params,
                epoch,
                period,
                duration,
            )
        })?;
    let robot_result = robot
        .join()
        .map_err(|_| RealtimeError::Thread("isochron-fri-sim"));
    stop.store(true, Ordering::Relaxed);
    let misses = control
        .join()
        .map_err(|_| RealtimeError::Thread("isochron-control"))?;
    let mut report = robot_result??;
    report.period_ms = period_ms;
    report.deadline_misses = misses;
    Ok(report)
}

fn control_thread(
    sock: &UdpSocket,
    controller: Controller,
    stop: &AtomicBool,
    epoch: Instant,
    period: Duration,
) -> u64 {
    let mut step = LoopStep::new(controller);
    let mut dec = MonitoringDecoder::new();
    let mut enc = CommandEncoder::new();
    let mut buf = [0u8; MAX_DATAGRAM_BYTES];
    let mut seq = 0u32;
    while !stop.load(Ordering::Relaxed) {
        let Ok((n, from)) = sock.recv_from(&mut buf) else {
            continue;
        };
        let Ok(m) = dec.decode(&buf[..n]) else {
            continue;
        };
        let t = epoch.elapsed().as_secs_f64();
        let q = step.run(t, period.as_secs_f64(), &m);
        if let Ok(reply) = enc.encode(seq, m.sequence_counter, Some(&q)) {
            let _ = sock.send_to(reply, from);
        }
        seq = seq.wrapping_add(1);
    }
    step.deadline_misses
}

fn robot_thread(
    sock: &UdpSocket,
    to: SocketAddr,
    robot: &crate::params::RobotParams,
    epoch: Instant,
    period: Duration,
    duration: Duration,
) -> Result<LoopReport, RealtimeError> {
    let q0 = INITIAL_JOINTS_DEG.map(f64::to_radians);
    let mut sim = VirtualRobot::new(robot, q0, 1);
    let mut buf = [0u8; MAX_DATAGRAM_BYTES];
    let cycles_max = (duration.as_secs_f64() / period.as_secs_f64()).ceil() as u64;
    let mut rtt_us: Vec<f64> = Vec::with_capacity(usize::try_from(cycles_max).unwrap_or(0));
    let mut report = LoopReport::default();
    let start = Instant::now();
    for k in 0..cycles_max {
        let due = start + period * u32::try_from(k).unwrap_or(u32::MAX);
        let now = Instant::now();
        if due > now {
            thread::sleep(due - now);
        }
        let sent_at = Instant::now();
        let now_ns = u64::try_from(sent_at.duration_since(epoch).as_nanos()).unwrap_or(0);
        let seq = sim.next_sequence();
        let Some(bytes) = sim.tick(now_ns) else {
            continue;
        };
        sock.send_to(bytes, to)?;
        report.cycles += 1;
        // Wait for the reply: late after one period, missing after three
        // (counted from the send, so a late wake-up of this thread is not the
        // client's fault).
        let next_due = sent_at + period;
        let give_up = sent_at + period * 3;
        let mut answered = false;
        loop {
            let now = Instant::now();
            if now >= give_up {
                break;
            }
            sock.set_read_timeout(Some((give_up - now).max(Duration::from_micros(50))))?;
            match sock.recv_from(&mut buf) {
                Ok((n, _)) => {
                    let at = Instant::now();
                    let ns = u64::try_from(at.duration_since(epoch).as_nanos()).unwrap_or(0);
                    if sim.on_reply(&buf[..n], ns) != Some(seq) {
                        // A stale answer to an earlier message.
                        continue;
                    }
                    rtt_us.push(at.duration_since(sent_at).as_secs_f64() * 1e6);
                    if at > next_due {
                        report.late_replies += 1;
                    }
                    answered = true;
                    break;
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) => {}
                Err(e) => return Err(e.into()),
            }
        }
        if !answered {
            report.missed_cycles += 1;
        }
    }
    rtt_us.sort_by(f64::total_cmp);
    report.reply_latency_us = LatencyUs {
        p50: quantile_sorted(&rtt_us, 0.5),
        p99: quantile_sorted(&rtt_us, 0.99),
        p999: quantile_sorted(&rtt_us, 0.999),
        max: rtt_us.last().copied().unwrap_or(0.0),
    };
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_loop_answers_every_message_over_loopback() {
        let mut s = Scenario::default();
        s.robot.fri_period_ms = 5;
        let r = run_loop(&s, Duration::from_millis(400)).unwrap();
        assert!(r.cycles >= 70, "{r:?}");
        // A loaded test machine may answer a few late, but must answer.
        assert!(r.missed_cycles * 10 <= r.cycles, "{r:?}");
        assert!(r.reply_latency_us.p50 > 0.0, "{r:?}");
    }
}
