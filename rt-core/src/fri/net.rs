//! Waiting for a datagram with a precise timeout.
//!
//! `SO_RCVTIMEO` (std's `set_read_timeout`) is rounded up to whole kernel
//! jiffies (4 ms at HZ=250), far too coarse for 1 ms FRI periods and a
//! two-period silence deadline. `ppoll` takes a nanosecond timeout served by a
//! high-resolution timer.

use std::io;
use std::net::UdpSocket;
use std::time::Duration;

use rustix::event::{PollFd, PollFlags, Timespec, poll};

/// Waits until `socket` is readable or `timeout` has passed; `Ok(true)` when readable.
///
/// # Errors
///
/// [`io::Error`] when `poll` fails (other than by an interrupt, which is `Ok(false)`).
pub fn wait_readable(socket: &UdpSocket, timeout: Duration) -> io::Result<bool> {
    let ts = Timespec {
        tv_sec: i64::try_from(timeout.as_secs()).unwrap_or(i64::MAX),
        tv_nsec: i64::from(timeout.subsec_nanos()),
    };
    let mut fds = [PollFd::new(socket, PollFlags::IN)];
    match poll(&mut fds, Some(&ts)) {
        Ok(n) => Ok(n > 0),
        Err(rustix::io::Errno::INTR) => Ok(false),
        Err(e) => Err(io::Error::from(e)),
    }
}
