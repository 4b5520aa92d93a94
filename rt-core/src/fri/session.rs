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

use super::client::{ControlStep, FriClient, FriClientParams, LinkState, SessionStats};
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
                let _realtime = super::priority::raise_current_thread("isochron-fri");
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

fn run<C: ControlStep>(
    socket: UdpSocket,
    mut client: FriClient,
    mut control: C,
    params: &FriSessionParams,
    stop: &AtomicBool,
) -> Result<C, SessionError> {
    let epoch = Instant::now();
    let now_ns = || epoch.elapsed().as_nanos() as u64;
    // Larger than an FRI datagram so oversize ones are seen (and refused).
    let mut buf = [0u8; 2048];
    let stats = Arc::clone(client.stats());
    socket.set_nonblocking(true)?;
    while !stop.load(Relaxed) {
        let timeout = match client.deadline_ns() {
            Some(d) => Duration::from_nanos(d.saturating_sub(now_ns())),
            None => IDLE_POLL,
        };
        if !wait_readable(&socket, timeout)? {
            client.poll(now_ns(), &mut control);
            control.idle(now_ns());
            continue;
        }
        match socket.recv_from(&mut buf) {
            Ok((n, from)) => {
                let t_rx = now_ns();
                if params.controller.is_some_and(|c| c != from) {
                    stats.foreign_datagrams.fetch_add(1, Relaxed);
                    continue;
                }
                let to = params.controller.unwrap_or(from);
                if let Some(reply) = client.on_datagram(&buf[..n], t_rx, &mut control) {
                    if socket.send_to(reply, to).is_err() {
                        stats.send_errors.fetch_add(1, Relaxed);
                    }
                    let took = now_ns().saturating_sub(t_rx);
                    // The threshold after the datagram: the first one sets the period.
                    stats.record_reply_latency(took, client.late_after_ns());
                }
                if params.exit_on_idle && client.state() == LinkState::Idle {
                    break;
                }
            }
            // Nothing after all, an ICMP "port unreachable" from an earlier
            // send, or a signal: check the deadline and go on.
            Err(_) => {
                client.poll(now_ns(), &mut control);
            }
        }
    }
    Ok(control)
}
