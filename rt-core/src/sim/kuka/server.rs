//! The simulated controller over real UDP, on its own thread (`isochron-fri-sim`).
//!
//! The thread sends a monitoring datagram to the client every send period
//! (absolute schedule; a slot missed by more than a period is counted as an
//! overrun and the schedule restarts from now) and, between sends, waits on its
//! socket for replies (`ppoll`, nanosecond timeout) until the next send time.

use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use super::controller::{FriSimParams, SimController, SimReport, SimStats, WorldRobot};
use crate::check::ParamError;
use crate::fri::net::wait_readable;
use crate::fri::proto::SessionState;

/// How the runner drives the session.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SimRunOptions {
    /// Ask for commanding as soon as the session is MONITORING_READY.
    pub auto_command: bool,
    /// Ask again every time the session is back in MONITORING_READY (a
    /// robot application that loops its FRI motion: `isochron world`'s
    /// cabinet, which outlives the services that connect to it).
    pub keep_commanding: bool,
    /// Close the session (send IDLE) after this long.
    pub duration: Option<Duration>,
    /// Keep the thread at normal priority and unpinned even when the process
    /// asked for real-time measures (`isochron bench` measures an external
    /// client against it: KUKA's example client answers such a controller
    /// fastest).
    pub normal_priority: bool,
}

/// Why the simulated controller could not start.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SimError {
    /// Invalid parameters.
    #[error(transparent)]
    Params(#[from] ParamError),
    /// The socket could not be bound.
    #[error("cannot bind the simulated controller to {addr}: {source}")]
    Bind {
        /// The address asked for.
        addr: SocketAddr,
        /// The reason.
        source: std::io::Error,
    },
    /// Socket or thread setup failed.
    #[error("simulated controller I/O: {0}")]
    Io(#[from] std::io::Error),
    /// The thread did not finish in time.
    #[error("the simulated controller did not finish within {0:?}")]
    Timeout(Duration),
    /// The thread panicked.
    #[error("the simulated controller thread panicked")]
    Panicked,
}

/// Called on the controller's thread after each monitoring message is sent,
/// with the controller (its true joints) and the time since the epoch, ns:
/// the world process's world steps here (`isochron world`).
pub type TickHook = Box<dyn FnMut(&mut SimController, u64) + Send>;

/// A running simulated controller.
#[derive(Debug)]
pub struct SimServer {
    stats: Arc<SimStats>,
    local: SocketAddr,
    epoch: Instant,
    epoch_unix_ns: u64,
    command: Arc<AtomicBool>,
    close: Arc<AtomicBool>,
    pause: Arc<AtomicBool>,
    leave: Arc<AtomicBool>,
    handle: Option<JoinHandle<()>>,
}

impl SimServer {
    /// Binds `bind` and starts sending to `client` every period.
    ///
    /// # Errors
    ///
    /// As [`Self::spawn_with`].
    pub fn spawn(
        params: FriSimParams,
        bind: SocketAddr,
        client: SocketAddr,
        opts: SimRunOptions,
    ) -> Result<Self, SimError> {
        Self::spawn_with(params, bind, client, opts, None, None)
    }

    /// As [`spawn`](Self::spawn), with the reality lab's robot plugged in
    /// (`world`) and `hook` called after each message sent.
    ///
    /// # Errors
    ///
    /// [`SimError::Params`] for invalid `params`; [`SimError::Bind`] when `bind`
    /// cannot be bound; [`SimError::Io`] when the socket or the thread cannot be set up.
    pub fn spawn_with(
        params: FriSimParams,
        bind: SocketAddr,
        client: SocketAddr,
        opts: SimRunOptions,
        world: Option<WorldRobot>,
        hook: Option<TickHook>,
    ) -> Result<Self, SimError> {
        let epoch = Instant::now();
        let epoch_unix_ns = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
        let mut sim = SimController::new(params, epoch_unix_ns)?;
        sim.set_world(world);
        let socket =
            UdpSocket::bind(bind).map_err(|source| SimError::Bind { addr: bind, source })?;
        socket.set_nonblocking(true)?;
        let local = socket.local_addr()?;
        let stats = Arc::clone(sim.stats());
        let command = Arc::new(AtomicBool::new(opts.auto_command));
        let close = Arc::new(AtomicBool::new(false));
        let pause = Arc::new(AtomicBool::new(false));
        let leave = Arc::new(AtomicBool::new(false));
        let hooked = Hooked {
            opts,
            epoch,
            hook,
            leave: Arc::clone(&leave),
        };
        let flags = (Arc::clone(&command), Arc::clone(&close), Arc::clone(&pause));
        let handle = std::thread::Builder::new()
            .name("isochron-fri-sim".into())
            .spawn(move || {
                let _realtime = (!opts.normal_priority).then(|| {
                    crate::fri::priority::raise_current_thread(
                        "isochron-fri-sim",
                        crate::fri::priority::SIM_PRIORITY,
                    )
                });
                run(socket, client, sim, hooked, &flags.0, &flags.1, &flags.2);
            })?;
        Ok(Self {
            stats,
            local,
            epoch,
            epoch_unix_ns,
            command,
            close,
            pause,
            leave,
            handle: Some(handle),
        })
    }

    /// The bound address (replies must come here).
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    /// Time 0 of the controller's clock (its messages' and the hook's times).
    pub fn epoch(&self) -> Instant {
        self.epoch
    }

    /// The Unix time of the epoch, ns.
    pub fn epoch_unix_ns(&self) -> u64 {
        self.epoch_unix_ns
    }

    /// The controller's counters (lock-free).
    pub fn stats(&self) -> &Arc<SimStats> {
        &self.stats
    }

    /// Asks for commanding (taken up once MONITORING_READY).
    pub fn request_commanding(&self) {
        self.command.store(true, Relaxed);
    }

    /// Leaves commanding at the next cycle, as the robot application does
    /// when it ends its FRI motion or an operator stops it
    /// ([`CommandingAbort::Application`](super::CommandingAbort::Application)):
    /// the drives stop where they are, the session goes back to monitoring,
    /// and commands again only when asked ([`Self::request_commanding`]).
    pub fn leave_commanding(&self) {
        self.leave.store(true, Relaxed);
    }

    /// Falls silent (sends nothing) while `true`, as a crashed controller would.
    pub fn set_silent(&self, silent: bool) {
        self.pause.store(silent, Relaxed);
    }

    /// True once the thread has ended.
    pub fn is_finished(&self) -> bool {
        self.handle.as_ref().is_none_or(JoinHandle::is_finished)
    }

    /// Sends IDLE, waits for the thread (at most `timeout`) and reports.
    ///
    /// # Errors
    ///
    /// [`SimError::Timeout`] when the thread does not end within `timeout`;
    /// [`SimError::Panicked`] when it panicked.
    pub fn close(mut self, timeout: Duration) -> Result<SimReport, SimError> {
        self.close.store(true, Relaxed);
        self.join(timeout)
    }

    /// Waits for the thread to end by itself (the run's duration), at most `timeout`.
    ///
    /// # Errors
    ///
    /// [`SimError::Timeout`] when the thread does not end within `timeout`;
    /// [`SimError::Panicked`] when it panicked.
    pub fn wait(mut self, timeout: Duration) -> Result<SimReport, SimError> {
        self.join(timeout)
    }

    fn join(&mut self, timeout: Duration) -> Result<SimReport, SimError> {
        let start = Instant::now();
        while !self.is_finished() {
            if start.elapsed() > timeout {
                return Err(SimError::Timeout(timeout));
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        match self.handle.take() {
            Some(h) => h.join().map_err(|_| SimError::Panicked)?,
            None => return Err(SimError::Panicked),
        }
        Ok(self.stats.report())
    }
}

impl Drop for SimServer {
    fn drop(&mut self) {
        self.close.store(true, Relaxed);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

/// The run's options, epoch and hook.
struct Hooked {
    opts: SimRunOptions,
    epoch: Instant,
    hook: Option<TickHook>,
    /// Set by [`SimServer::leave_commanding`].
    leave: Arc<AtomicBool>,
}

fn run(
    socket: UdpSocket,
    client: SocketAddr,
    mut sim: SimController,
    hooked: Hooked,
    command: &AtomicBool,
    close: &AtomicBool,
    pause: &AtomicBool,
) {
    let Hooked {
        opts,
        epoch,
        mut hook,
        leave,
    } = hooked;
    let period = Duration::from_millis(u64::from(sim.params().fri_period_ms));
    let stats = Arc::clone(sim.stats());
    let mut next_send = Duration::ZERO;
    let mut buf = [0u8; 2048];
    loop {
        let now = epoch.elapsed();
        if now >= next_send {
            let closing = close.load(Relaxed) || opts.duration.is_some_and(|d| now >= d);
            if closing {
                sim.request_close();
            }
            if leave.swap(false, Relaxed) {
                sim.leave_commanding();
            }
            if (command.load(Relaxed) || opts.keep_commanding)
                && sim.state() == SessionState::MonitoringReady
            {
                sim.request_commanding();
                command.store(false, Relaxed);
            }
            let t = now.as_nanos() as u64;
            // Closing always sends IDLE, even while silent.
            if (!pause.load(Relaxed) || closing)
                && let Some(bytes) = sim.tick(t)
            {
                let _ = socket.send_to(bytes, client);
            }
            if let Some(h) = hook.as_mut() {
                h(&mut sim, t);
            }
            if sim.is_closed() {
                drain_replies(&socket, client, &mut sim, epoch, period, &stats, &mut buf);
                break;
            }
            next_send += period;
            if next_send <= now {
                // A whole slot was missed (the thread was not scheduled).
                stats.overruns.fetch_add(1, Relaxed);
                next_send = now + period;
            }
        }
        let wait = next_send.saturating_sub(epoch.elapsed());
        match wait_readable(&socket, wait) {
            Ok(true) => {}
            Ok(false) => continue,
            Err(_) => break,
        }
        // An error here is nothing after all, or an ICMP "port unreachable"
        // (no client yet): go on.
        if let Ok((n, from)) = socket.recv_from(&mut buf) {
            if from != client {
                stats.foreign_datagrams.fetch_add(1, Relaxed);
                continue;
            }
            let t = epoch.elapsed().as_nanos() as u64;
            sim.on_reply(&buf[..n], t);
        }
    }
}

/// How long after IDLE the answers still on their way are read, at least.
/// A client's thread can be kept from the CPU for more than two 2 ms periods
/// on a loaded machine (the answer to the last message before IDLE was once
/// missed beside `stress-ng --cpu 2`).
const DRAIN_MIN: Duration = Duration::from_millis(100);

/// After IDLE, reads the answers still on their way for two periods, at
/// least [`DRAIN_MIN`], so that every answer the client sent to the
/// session's messages is counted (an answer to the last message before
/// IDLE, or answers queued while the thread was not scheduled, would
/// otherwise be left in the socket).
fn drain_replies(
    socket: &UdpSocket,
    client: SocketAddr,
    sim: &mut SimController,
    epoch: Instant,
    period: Duration,
    stats: &SimStats,
    buf: &mut [u8],
) {
    let until = epoch.elapsed() + (2 * period).max(DRAIN_MIN);
    loop {
        let wait = until.saturating_sub(epoch.elapsed());
        if !matches!(wait_readable(socket, wait), Ok(true)) {
            return;
        }
        if let Ok((n, from)) = socket.recv_from(buf) {
            if from != client {
                stats.foreign_datagrams.fetch_add(1, Relaxed);
                continue;
            }
            sim.on_reply(&buf[..n], epoch.elapsed().as_nanos() as u64);
        }
    }
}
