//! An in-process fake of the magnet board on a pseudo-terminal pair: the
//! [`FirmwareModel`] behind a real serial port path, for fast tests of the driver's
//! edge cases (silence, resets, stale bytes, unplugging) and for the simulated lab,
//! where the coil switching off (the pin hook) is what releases the pendulum.

use std::{
    io::{self, Read, Write},
    path::{Path, PathBuf},
    sync::{
        Arc,
        atomic::{AtomicBool, AtomicU64, Ordering},
        mpsc::{Receiver, SyncSender, TryRecvError, sync_channel},
    },
    thread::JoinHandle,
    time::{Duration, Instant},
};

use serialport::{SerialPort, TTYPort};

use super::firmware::FirmwareModel;
use crate::magnet::protocol::ResetCause;

/// Called on the fake's thread whenever its coil pin changes: `(on, when)`.
pub type PinHook = Box<dyn FnMut(bool, Instant) + Send>;

enum Ctl {
    Inject(Vec<u8>),
    Reset {
        cause: ResetCause,
        boot_delay: Duration,
    },
}

#[derive(Debug, Default)]
struct State {
    stop: AtomicBool,
    silent: AtomicBool,
    magnet_on: AtomicBool,
    pin_changes: AtomicU64,
    commands: AtomicU64,
    errors: AtomicU64,
}

/// A fake magnet board reachable at a path (a symlink to a pty).
pub struct FakeDevice {
    link: PathBuf,
    state: Arc<State>,
    ctl: Option<SyncSender<Ctl>>,
    thread: Option<JoinHandle<PinHook>>,
    slave: Option<TTYPort>,
    hook: Option<PinHook>,
}

impl std::fmt::Debug for FakeDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FakeDevice")
            .field("link", &self.link)
            .field("state", &self.state)
            .finish_non_exhaustive()
    }
}

impl FakeDevice {
    /// Plugs a fake board in at `link` (replacing whatever is there).
    ///
    /// # Errors
    ///
    /// As [`Self::start_with_pin_hook`].
    pub fn start(link: impl AsRef<Path>) -> io::Result<Self> {
        Self::start_with_pin_hook(link, Box::new(|_, _| {}))
    }

    /// As [`start`](Self::start), calling `hook(on, at)` at every coil switch.
    ///
    /// # Errors
    ///
    /// As [`Self::replug`]: an [`io::Error`] when the pty, the link or the board's
    /// thread cannot be created.
    pub fn start_with_pin_hook(link: impl AsRef<Path>, hook: PinHook) -> io::Result<Self> {
        let mut dev = Self {
            link: link.as_ref().to_path_buf(),
            state: Arc::new(State::default()),
            ctl: None,
            thread: None,
            slave: None,
            hook: Some(hook),
        };
        dev.replug()?;
        Ok(dev)
    }

    /// The port path to give the driver.
    pub fn path(&self) -> &Path {
        &self.link
    }

    /// Whether the coil pin is on.
    pub fn magnet_on(&self) -> bool {
        self.state.magnet_on.load(Ordering::Acquire)
    }

    /// Coil pin changes so far.
    pub fn pin_changes(&self) -> u64 {
        self.state.pin_changes.load(Ordering::Acquire)
    }

    /// Command lines the board answered so far (`OK` or `ERR`).
    pub fn commands(&self) -> u64 {
        self.state.commands.load(Ordering::Acquire)
    }

    /// Command lines the board answered with `ERR` so far.
    pub fn errors(&self) -> u64 {
        self.state.errors.load(Ordering::Acquire)
    }

    /// A silent board reads and drops everything and says nothing (a hung
    /// USB-serial bridge); the coil keeps its state.
    pub fn set_silent(&self, silent: bool) {
        self.state.silent.store(silent, Ordering::Release);
    }

    /// Sends raw bytes to the host as if the board had (stale output, noise).
    ///
    /// # Errors
    ///
    /// [`io::Error`] of kind `NotConnected` when the board is unplugged, `WouldBlock`
    /// when its control queue is full.
    pub fn inject(&self, bytes: &[u8]) -> io::Result<()> {
        self.send(Ctl::Inject(bytes.to_vec()))
    }

    /// Resets the board: coil off at once; the boot banner after `boot_delay`
    /// (an Uno's bootloader waits ~1 s), input ignored until then.
    ///
    /// # Errors
    ///
    /// [`io::Error`] of kind `NotConnected` when the board is unplugged, `WouldBlock`
    /// when its control queue is full.
    pub fn reset(&self, cause: ResetCause, boot_delay: Duration) -> io::Result<()> {
        self.send(Ctl::Reset { cause, boot_delay })
    }

    fn send(&self, c: Ctl) -> io::Result<()> {
        self.ctl
            .as_ref()
            .ok_or_else(|| io::Error::new(io::ErrorKind::NotConnected, "unplugged"))?
            .try_send(c)
            .map_err(|_| io::Error::new(io::ErrorKind::WouldBlock, "fake device busy"))
    }

    /// Unplugs the board: the pty goes away and the path dangles.
    pub fn unplug(&mut self) {
        self.state.stop.store(true, Ordering::Release);
        self.ctl = None;
        if let Some(t) = self.thread.take()
            && let Ok(hook) = t.join()
        {
            self.hook = Some(hook);
        }
        self.slave = None;
        let _ = std::fs::remove_file(&self.link);
        self.state.magnet_on.store(false, Ordering::Release);
    }

    /// Plugs the board (back) in at the same path: a fresh pty, a power-on boot.
    ///
    /// # Errors
    ///
    /// [`io::Error`] when the pty pair cannot be opened or has no name, the symlink at
    /// the link path cannot be made, or the board's thread cannot start.
    pub fn replug(&mut self) -> io::Result<()> {
        self.unplug();
        let (master, slave) = TTYPort::pair().map_err(io::Error::other)?;
        let name = slave
            .name()
            .ok_or_else(|| io::Error::other("the pty has no name"))?;
        let _ = std::fs::remove_file(&self.link);
        std::os::unix::fs::symlink(&name, &self.link)?;
        self.state.stop.store(false, Ordering::Release);
        let (tx, rx) = sync_channel(16);
        let state = Arc::clone(&self.state);
        let hook = self.hook.take().unwrap_or_else(|| Box::new(|_, _| {}));
        let thread = std::thread::Builder::new()
            .name("isochron-magnet-fake".to_owned())
            .spawn(move || run(master, &state, &rx, hook))?;
        self.ctl = Some(tx);
        self.thread = Some(thread);
        self.slave = Some(slave);
        Ok(())
    }
}

impl Drop for FakeDevice {
    fn drop(&mut self) {
        self.unplug();
    }
}

fn run(mut master: TTYPort, state: &State, rx: &Receiver<Ctl>, mut hook: PinHook) -> PinHook {
    let epoch = Instant::now();
    let now_ms = || u64::try_from(epoch.elapsed().as_millis()).unwrap_or(u64::MAX);
    let _ = master.set_timeout(Duration::from_millis(2));
    let mut out = Vec::with_capacity(256);
    let mut model = FirmwareModel::boot(now_ms(), ResetCause::Power, &mut out);
    let mut booting_until: Option<(Instant, Vec<u8>)> = None;
    let mut pin = false;
    let mut buf = [0u8; 256];
    while !state.stop.load(Ordering::Acquire) {
        match rx.try_recv() {
            Ok(Ctl::Inject(bytes)) => out.extend_from_slice(&bytes),
            Ok(Ctl::Reset { cause, boot_delay }) => {
                let mut banner = Vec::new();
                model.reset(now_ms(), cause, &mut banner);
                booting_until = Some((Instant::now() + boot_delay, banner));
            }
            Err(TryRecvError::Empty | TryRecvError::Disconnected) => {}
        }
        if booting_until
            .as_ref()
            .is_some_and(|(t, _)| Instant::now() >= *t)
            && let Some((_, banner)) = booting_until.take()
        {
            out.extend_from_slice(&banner);
        }
        let read = master.read(&mut buf);
        // Read after the bytes arrived: a caller that went silent first is obeyed.
        let silent = state.silent.load(Ordering::Acquire);
        match read {
            Ok(n) if !silent && booting_until.is_none() => {
                for &b in &buf[..n] {
                    model.feed(b, now_ms(), &mut out);
                    check_pin(&model, &mut pin, state, &mut hook);
                }
            }
            Ok(_) => {}
            Err(e) if e.kind() == io::ErrorKind::TimedOut => {}
            Err(_) => std::thread::sleep(Duration::from_millis(2)),
        }
        model.tick(now_ms(), &mut out);
        check_pin(&model, &mut pin, state, &mut hook);
        state.errors.store(model.errors(), Ordering::Release);
        state.commands.store(model.commands(), Ordering::Release);
        if !out.is_empty() {
            if !silent {
                let _ = master.write_all(&out);
            }
            out.clear();
        }
    }
    hook
}

fn check_pin(model: &FirmwareModel, pin: &mut bool, state: &State, hook: &mut PinHook) {
    let on = model.magnet_on();
    if on != *pin {
        *pin = on;
        state.magnet_on.store(on, Ordering::Release);
        state.pin_changes.fetch_add(1, Ordering::AcqRel);
        hook(on, Instant::now());
    }
}
