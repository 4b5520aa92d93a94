//! The real-time client session: a named thread owning the UDP socket.
//!
//! The thread waits on the socket with `ppoll` until the controller's deadline
//! (or a short poll while there is no link), hands each datagram to
//! [`FriClient`], sends the reply to the address the datagram came from (as
//! KUKA's client does) or to a configured controller address, and measures the
//! receive -> send time. Counters live in [`SessionStats`], read without locks.

use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use super::client::{
    ControlStep, FriClient, FriClientParams, LinkState, SessionStats, StepInput, StopReason,
};
use super::codec::Joints;
use super::net::wait_readable;
use crate::check::ParamError;

/// Where the session listens and whom it answers.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FriSessionParams {
    /// Local address (KUKA's client: `0.0.0.0:30200`; port 0 picks a free one).
    pub bind: SocketAddr,
    /// The controller; `None`: reply to whoever sent the last datagram. With
    /// an address, datagrams from elsewhere are counted and ignored.
    pub controller: Option<SocketAddr>,
    /// End the thread when the controller sends IDLE (KUKA's example clients do).
    pub exit_on_idle: bool,
    /// The client's state machine, guard and timing.
    pub client: FriClientParams,
}

impl Default for FriSessionParams {
    fn default() -> Self {
        Self {
            bind: SocketAddr::from(([0, 0, 0, 0], 30200)),
            controller: None,
            exit_on_idle: false,
            client: FriClientParams::default(),
        }
    }
}

/// Why a session could not start or ended badly.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SessionError {
    /// Invalid parameters.
    #[error(transparent)]
    Params(#[from] ParamError),
    /// The socket could not be set up.
    #[error("cannot bind the FRI socket {addr}: {source}")]
    Bind {
        /// The address asked for.
        addr: SocketAddr,
        /// The reason.
        source: std::io::Error,
    },
    /// A socket or thread operation failed.
    #[error("FRI session I/O: {0}")]
    Io(#[from] std::io::Error),
    /// The session thread panicked.
    #[error("the FRI session thread panicked")]
    Panicked,
}

/// While there is no link, wake this often to check the stop flag.
const IDLE_POLL: Duration = Duration::from_millis(20);

/// A running client session (thread `isochron-fri`).
#[derive(Debug)]
pub struct FriSession<C> {
    stop: Arc<AtomicBool>,
    stats: Arc<SessionStats>,
    local: SocketAddr,
    handle: Option<JoinHandle<Result<C, SessionError>>>,
}

impl<C: ControlStep + Send + 'static> FriSession<C> {
    /// Binds the socket and starts the session thread with `control`.
    ///
    /// # Errors
    ///
    /// [`SessionError::Params`] for invalid client parameters; [`SessionError::Bind`]
    /// when the socket cannot be bound; [`SessionError::Io`] when its address cannot be
    /// read or the thread cannot be started.
    pub fn spawn(params: FriSessionParams, control: C) -> Result<Self, SessionError> {
        let client = FriClient::new(params.client.clone())?;
        let socket = UdpSocket::bind(params.bind).map_err(|source| SessionError::Bind {
            addr: params.bind,
            source,
        })?;
        let local = socket.local_addr()?;
        let stop = Arc::new(AtomicBool::new(false));
        let stats = Arc::clone(client.stats());
        let thread_stop = Arc::clone(&stop);
        let handle = std::thread::Builder::new()
            .name("isochron-fri".into())
            .spawn(move || {
                let _realtime = super::priority::raise_current_thread(
                    "isochron-fri",
                    super::priority::FRI_PRIORITY,
                );
                run(socket, client, control, &params, &thread_stop)
            })?;
        Ok(Self {
            stop,
            stats,
            local,
            handle: Some(handle),
        })
    }

    /// The bound local address.
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    /// The session's counters (lock-free).
    pub fn stats(&self) -> &Arc<SessionStats> {
        &self.stats
    }

    /// True once the thread has ended (IDLE with `exit_on_idle`, or stopped).
    pub fn is_finished(&self) -> bool {
        self.handle.as_ref().is_none_or(JoinHandle::is_finished)
    }

    /// Stops the thread (within one receive timeout) and returns the control.
    ///
    /// # Errors
    ///
    /// [`SessionError::Io`] when the session thread's socket failed;
    /// [`SessionError::Panicked`] when the thread panicked.
    pub fn stop(mut self) -> Result<C, SessionError> {
        self.stop.store(true, Relaxed);
        match self.handle.take() {
            Some(h) => h.join().map_err(|_| SessionError::Panicked)?,
            None => Err(SessionError::Panicked),
        }
    }
}

impl<C> Drop for FriSession<C> {
    fn drop(&mut self) {
        self.stop.store(true, Relaxed);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

/// With [`super::priority::spin_enabled`], the session stops sleeping this long
/// before the next datagram is expected and polls the socket without blocking
/// until it comes: the datagram is taken the moment it lands, with no wake-up
/// of a sleeping thread (on a virtual machine that wake-up is most of the round
/// trip: an idle CPU's halt and an inter-processor interrupt).
pub const SPIN_LEAD: Duration = Duration::from_micros(40);
/// A spin gives up this long after the expected arrival (the controller is
/// late): the thread sleeps on the socket again until the datagram or the
/// silence deadline.
pub const SPIN_PAST: Duration = Duration::from_micros(150);
/// Each period the expected arrival may move this much later than the
/// earliest arrivals say (it follows a controller whose clock runs slow).
const SPIN_CREEP_NS: u64 = 1_000;

/// When the next datagram is expected: the earliest arrival phase seen,
/// creeping later by [`SPIN_CREEP_NS`] a period so that it follows the
/// controller's clock. Late arrivals (the controller's own jitter) do not
/// move it later than that.
#[derive(Debug, Default, Clone, Copy)]
struct Arrival {
    /// The expected arrival of the next datagram, ns of the session's clock.
    next_ns: Option<u64>,
}

impl Arrival {
    fn on_datagram(&mut self, t_rx: u64, period_ns: u64) {
        if period_ns == 0 {
            self.next_ns = None;
            return;
        }
        let from_this = t_rx + period_ns;
        self.next_ns = Some(match self.next_ns {
            // A stale expectation (a gap, a new period) is replaced.
            Some(prev) if prev + period_ns > t_rx && prev < t_rx + period_ns => {
                (prev + period_ns + SPIN_CREEP_NS).min(from_this)
            }
            _ => from_this,
        });
    }
}

/// The control step timed by wall clock into [`SessionStats::step_latency`]
/// (one clock read before and after: the client itself has no clock).
struct Timed<'a, C> {
    inner: C,
    stats: &'a SessionStats,
}

impl<C: ControlStep> ControlStep for Timed<'_, C> {
    fn step(&mut self, input: &StepInput<'_>, command_rad: &mut Joints) {
        let t = Instant::now();
        self.inner.step(input, command_rad);
        self.stats
            .step_latency
            .record_ns(t.elapsed().as_nanos() as u64);
    }

    fn stop(&mut self, reason: StopReason) {
        self.inner.stop(reason);
    }

    fn after_reply(&mut self) {
        self.inner.after_reply();
    }

    fn idle(&mut self, now_ns: u64) {
        self.inner.idle(now_ns);
    }
}

fn run<C: ControlStep>(
    socket: UdpSocket,
    client: FriClient,
    control: C,
    params: &FriSessionParams,
    stop: &AtomicBool,
) -> Result<C, SessionError> {
    let stats = Arc::clone(client.stats());
    let mut control = Timed {
        inner: control,
        stats: &stats,
    };
    run_timed(socket, client, &mut control, params, stop)?;
    Ok(control.inner)
}

fn run_timed<C: ControlStep>(
    socket: UdpSocket,
    mut client: FriClient,
    control: &mut C,
    params: &FriSessionParams,
    stop: &AtomicBool,
) -> Result<(), SessionError> {
    let epoch = Instant::now();
    let now_ns = || epoch.elapsed().as_nanos() as u64;
    // Larger than an FRI datagram so oversize ones are seen (and refused).
    let mut buf = [0u8; 2048];
    let stats = Arc::clone(client.stats());
    let spin = super::priority::spin_enabled();
    let lead_ns = SPIN_LEAD.as_nanos() as u64;
    let past_ns = SPIN_PAST.as_nanos() as u64;
    let mut arrival = Arrival::default();
    // The expected arrival whose spin ended without a datagram.
    let mut spun: Option<u64> = None;
    socket.set_nonblocking(true)?;
    while !stop.load(Relaxed) {
        let now = now_ns();
        let deadline = client.deadline_ns();
        let expected = arrival.next_ns.filter(|&e| spin && spun != Some(e));
        let received = match expected {
            Some(e) if now + lead_ns >= e => {
                // Spin: poll without blocking until the datagram or the give-up time.
                let until = e + past_ns;
                let got = loop {
                    if let Ok(got) = socket.recv_from(&mut buf) {
                        break Some(got);
                    }
                    // Nothing yet (or an ICMP "port unreachable" from an
                    // earlier send, or a signal): go on until the give-up time.
                    if now_ns() >= until || stop.load(Relaxed) {
                        spun = Some(e);
                        stats.spins_gave_up.fetch_add(1, Relaxed);
                        break None;
                    }
                    std::hint::spin_loop();
                };
                stats
                    .spin_ns
                    .fetch_add(now_ns().saturating_sub(now), Relaxed);
                got
            }
            _ => {
                let wake = match (deadline, expected) {
                    (Some(d), Some(e)) => Some(d.min(e.saturating_sub(lead_ns))),
                    (d, e) => d.or(e.map(|e| e.saturating_sub(lead_ns))),
                };
                let timeout = match wake {
                    Some(w) => Duration::from_nanos(w.saturating_sub(now)),
                    None => IDLE_POLL,
                };
                if !wait_readable(&socket, timeout)? {
                    // Woken to spin: not a timeout.
                    if expected.is_some_and(|e| now_ns() + lead_ns >= e)
                        && deadline.is_none_or(|d| now_ns() < d)
                    {
                        continue;
                    }
                    client.poll(now_ns(), control);
                    control.idle(now_ns());
                    continue;
                }
                // Nothing after all (an error): an ICMP "port unreachable"
                // from an earlier send, or a signal: check the deadline and go on.
                let got = socket.recv_from(&mut buf).ok();
                if got.is_none() {
                    client.poll(now_ns(), control);
                }
                got
            }
        };
        let Some((n, from)) = received else {
            continue;
        };
        let t_rx = now_ns();
        if params.controller.is_some_and(|c| c != from) {
            stats.foreign_datagrams.fetch_add(1, Relaxed);
            continue;
        }
        let to = params.controller.unwrap_or(from);
        if let Some(reply) = client.on_datagram(&buf[..n], t_rx, control) {
            let t_send = now_ns();
            if socket.send_to(reply, to).is_err() {
                stats.send_errors.fetch_add(1, Relaxed);
            }
            let t_sent = now_ns();
            stats.send_latency.record_ns(t_sent.saturating_sub(t_send));
            let took = t_sent.saturating_sub(t_rx);
            // The threshold after the datagram: the first one sets the period.
            stats.record_reply_latency(took, client.late_after_ns());
        }
        control.after_reply();
        arrival.on_datagram(t_rx, client.receive_period_ns());
        if params.exit_on_idle && client.state() == LinkState::Idle {
            break;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    const P: u64 = 1_000_000;

    #[test]
    fn the_expected_arrival_follows_the_earliest_arrivals_and_creeps_after_a_slow_clock() {
        let mut a = Arrival::default();
        a.on_datagram(10 * P, 0);
        assert_eq!(a.next_ns, None, "no period yet: nothing expected");
        a.on_datagram(10 * P, P);
        assert_eq!(a.next_ns, Some(11 * P));
        // A late arrival (the controller's jitter) does not move it later than
        // one creep.
        a.on_datagram(11 * P + 80_000, P);
        assert_eq!(a.next_ns, Some(12 * P + SPIN_CREEP_NS));
        // An early one pulls it back at once.
        a.on_datagram(12 * P - 5_000, P);
        assert_eq!(a.next_ns, Some(13 * P - 5_000));
        // A controller whose period is 10 us longer than believed: the
        // expectation creeps after it (1 us a period), never runs ahead of it.
        let mut t = 13 * P - 5_000;
        for _ in 0..100 {
            t += P + 10_000;
            a.on_datagram(t, P);
            assert!(a.next_ns.unwrap() <= t + P, "ahead of the arrivals");
        }
        // After a gap of several periods the old phase is dropped.
        a.on_datagram(t + 7 * P + 300_000, P);
        assert_eq!(a.next_ns, Some(t + 8 * P + 300_000));
    }
}
