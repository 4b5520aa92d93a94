//! The serial driver: a named thread that owns the port, one command in flight.

use std::{
    collections::VecDeque,
    io::{Read, Write},
    sync::{
        Arc,
        atomic::{AtomicBool, Ordering},
        mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError, sync_channel},
    },
    thread::JoinHandle,
    time::{Duration, Instant},
};

use serialport::{SerialPort, TTYPort};

use super::{
    MagnetError, MagnetParams,
    protocol::{Command, DeviceEvent, DeviceStatus, Line, OkReply, parse_line},
    view::{EventKind, LinkState, MagnetState, MagnetView, SwitchCause, ViewCell},
};

/// Requests waiting for the magnet thread (callers beyond this get [`MagnetError::Busy`]).
pub const QUEUE_CAPACITY: usize = 32;
/// Longest line accepted from the device; longer ones are cut and skipped.
const MAX_DEVICE_LINE: usize = 256;

/// A successful answer with its round-trip time.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Answer {
    /// What the device said.
    pub reply: OkReply,
    /// From writing the command to reading its answer.
    pub rtt: Duration,
    /// When the command was written to the port.
    pub sent: Instant,
}

impl Answer {
    /// The device's state, for `MAGNET` and `STATUS` answers.
    pub fn status(&self) -> Option<DeviceStatus> {
        match &self.reply {
            OkReply::Magnet(s) | OkReply::Status(s) => Some(*s),
            _ => None,
        }
    }
}

/// Something that happened, with the time it was seen (passed to the hook).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MagnetEvent {
    /// When it happened: for a switch by command, when the command's last byte
    /// reached the board (write time + wire time, at most the round trip; the
    /// pin switches then); for
    /// the rest, when the driver read the device's line.
    pub at: Instant,
    /// What happened.
    pub kind: EventKind,
}

/// Called on the magnet thread for every event (keep it short and non-blocking).
pub type EventHook = Box<dyn FnMut(&MagnetEvent) + Send>;

type ReplyTx = SyncSender<Result<Answer, MagnetError>>;

struct Request {
    cmd: Command,
    reply: ReplyTx,
}

enum Inbox {
    Request(Request),
    Line {
        conn: u64,
        text: String,
        at: Instant,
    },
    Lost {
        conn: u64,
        reason: String,
    },
    Stop,
}

/// A request on its way: poll it or wait for it.
#[derive(Debug)]
pub struct Pending {
    rx: Receiver<Result<Answer, MagnetError>>,
}

impl Pending {
    /// The answer if it has arrived (never blocks).
    pub fn try_get(&self) -> Option<Result<Answer, MagnetError>> {
        match self.rx.try_recv() {
            Ok(r) => Some(r),
            Err(std::sync::mpsc::TryRecvError::Empty) => None,
            Err(std::sync::mpsc::TryRecvError::Disconnected) => Some(Err(MagnetError::Stopped)),
        }
    }

    /// Waits for the answer. The magnet thread answers every request (with an
    /// error after its timeout at the latest), so this always returns.
    ///
    /// # Errors
    ///
    /// The error the magnet thread answered with ([`MagnetError::NotConnected`],
    /// [`MagnetError::DeviceLost`], [`MagnetError::Timeout`], [`MagnetError::Device`],
    /// [`MagnetError::Busy`] when its queue was full); [`MagnetError::Stopped`] when
    /// the thread stopped before answering.
    pub fn wait(self) -> Result<Answer, MagnetError> {
        self.rx.recv().unwrap_or(Err(MagnetError::Stopped))
    }
}

struct Shared {
    view: ViewCell,
    /// Why the link last failed (cleared on connecting), for people: read
    /// off the real-time path ([`MagnetHandle::problem`]).
    last_error: std::sync::Mutex<Option<String>>,
    stop: AtomicBool,
    tx: SyncSender<Inbox>,
    thread: std::sync::Mutex<Option<JoinHandle<()>>>,
}

impl Drop for Shared {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
        let _ = self.tx.try_send(Inbox::Stop);
        if let Ok(mut t) = self.thread.lock()
            && let Some(h) = t.take()
        {
            let _ = h.join();
        }
    }
}

/// The driver's handle: cheap to clone, usable from any thread. Requests never
/// block the caller ([`submit`](Self::submit)); the state is read lock-free
/// ([`view`](Self::view)). The thread stops when the last clone is dropped.
#[derive(Clone)]
pub struct MagnetHandle {
    shared: Arc<Shared>,
    epoch: Instant,
    port: Arc<str>,
    baud: u32,
}

impl std::fmt::Debug for MagnetHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MagnetHandle")
            .field("port", &self.port)
            .field("view", &self.view())
            .finish_non_exhaustive()
    }
}

impl MagnetHandle {
    /// Validates `params` and starts the `isochron-magnet` thread, which opens the
    /// port, resynchronises, sets the hold limit, asks the state, and from then on
    /// keeps the view current and reconnects whenever the device comes back.
    ///
    /// # Errors
    ///
    /// As [`Self::spawn_with_hook`].
    pub fn spawn(params: MagnetParams) -> Result<Self, MagnetError> {
        Self::spawn_with_hook(params, Box::new(|_| {}))
    }

    /// As [`spawn`](Self::spawn), calling `hook` on the magnet thread for every
    /// event: the simulated lab releases its pendulum on
    /// `EventKind::Switched { on: false, .. }` at `event.at`.
    ///
    /// # Errors
    ///
    /// [`MagnetError::Params`] for invalid `params`; [`MagnetError::Spawn`] when the
    /// thread cannot start (a missing device is not an error: the thread reconnects).
    pub fn spawn_with_hook(params: MagnetParams, hook: EventHook) -> Result<Self, MagnetError> {
        params.validate()?;
        let (tx, rx) = sync_channel(QUEUE_CAPACITY + 64);
        let epoch = Instant::now();
        let port: Arc<str> = Arc::from(params.port.as_str());
        let baud = params.baud;
        let shared = Arc::new(Shared {
            view: ViewCell::new(&MagnetView::default()),
            last_error: std::sync::Mutex::new(None),
            stop: AtomicBool::new(false),
            tx: tx.clone(),
            thread: std::sync::Mutex::new(None),
        });
        let worker = Worker {
            params,
            rx,
            tx,
            shared: Arc::downgrade(&shared),
            epoch,
            view: MagnetView::default(),
            conn: None,
            next_conn_id: 0,
            queue: VecDeque::new(),
            hook,
            ping_counter: 0,
            next_connect: epoch,
            next_poll: epoch,
            need_config: false,
            last_error: None,
        };
        let handle = std::thread::Builder::new()
            .name("isochron-magnet".to_owned())
            .spawn(move || worker.run())
            .map_err(|e| MagnetError::Spawn { kind: e.kind() })?;
        if let Ok(mut t) = shared.thread.lock() {
            *t = Some(handle);
        }
        Ok(Self {
            shared,
            epoch,
            port,
            baud,
        })
    }

    /// Queues a command without blocking; [`MagnetError::Busy`] when the queue is full.
    ///
    /// # Errors
    ///
    /// [`MagnetError::Busy`] when the queue is full; [`MagnetError::Stopped`] when the
    /// magnet thread has stopped.
    pub fn submit(&self, cmd: Command) -> Result<Pending, MagnetError> {
        let (reply, rx) = sync_channel(1);
        match self
            .shared
            .tx
            .try_send(Inbox::Request(Request { cmd, reply }))
        {
            Ok(()) => Ok(Pending { rx }),
            Err(TrySendError::Full(_)) => Err(MagnetError::Busy),
            Err(TrySendError::Disconnected(_)) => Err(MagnetError::Stopped),
        }
    }

    /// Switches the magnet and returns the state the device reports (blocking).
    ///
    /// # Errors
    ///
    /// As [`Self::submit`] and [`Pending::wait`]; [`MagnetError::Protocol`] when the
    /// answer carries no device state.
    pub fn set_magnet(&self, on: bool) -> Result<DeviceStatus, MagnetError> {
        let a = self.submit(Command::Magnet(on))?.wait()?;
        a.status()
            .ok_or_else(|| MagnetError::Protocol(a.reply.clone()))
    }

    /// Switches the calibration LED (blocking). The answer carries the command's
    /// send time and round trip: the LED switched within them (half the round trip
    /// is the usual estimate of when).
    ///
    /// # Errors
    ///
    /// As [`Self::submit`] and [`Pending::wait`]; [`MagnetError::Protocol`] when the
    /// answer is not an LED answer in the asked state.
    pub fn set_led(&self, on: bool) -> Result<Answer, MagnetError> {
        let a = self.submit(Command::Led(on))?.wait()?;
        match a.reply {
            OkReply::Led { on: got, .. } if got == on => Ok(a),
            ref other => Err(MagnetError::Protocol(other.clone())),
        }
    }

    /// Asks the device's state (blocking).
    ///
    /// # Errors
    ///
    /// As [`Self::submit`] and [`Pending::wait`]; [`MagnetError::Protocol`] when the
    /// answer carries no device state.
    pub fn status(&self) -> Result<DeviceStatus, MagnetError> {
        let a = self.submit(Command::Status)?.wait()?;
        a.status()
            .ok_or_else(|| MagnetError::Protocol(a.reply.clone()))
    }

    /// Sets the coil's maximum hold time, seconds (blocking); returns it in ms.
    ///
    /// # Errors
    ///
    /// As [`Self::submit`] and [`Pending::wait`]; [`MagnetError::Protocol`] when the
    /// answer is not a hold answer.
    pub fn set_hold_limit(&self, seconds: u16) -> Result<u32, MagnetError> {
        match self.submit(Command::Hold(seconds))?.wait()?.reply {
            OkReply::Hold { hold_max_ms } => Ok(hold_max_ms),
            other => Err(MagnetError::Protocol(other)),
        }
    }

    /// The latest state, lock-free (retries while the magnet thread is mid-write,
    /// which takes nanoseconds unless it is preempted).
    pub fn view(&self) -> MagnetView {
        loop {
            if let Some(v) = self.shared.view.try_read() {
                return v;
            }
            std::hint::spin_loop();
        }
    }

    /// The latest state in a bounded number of attempts, for real-time callers:
    /// `None` if the magnet thread was writing every time (try again next cycle).
    pub fn try_view(&self) -> Option<MagnetView> {
        (0..4).find_map(|_| self.shared.view.try_read())
    }

    /// The instant the view's `*_at_ns` times count from.
    pub fn epoch(&self) -> Instant {
        self.epoch
    }

    /// The configured port path.
    pub fn port(&self) -> &str {
        &self.port
    }

    /// How long `bytes` take on the wire at the configured baud (10 bits
    /// each: start, 8 data, stop), seconds.
    pub fn wire_s(&self, bytes: usize) -> f64 {
        bytes as f64 * 10.0 / f64::from(self.baud.max(1))
    }

    /// What keeps the board from answering, as a sentence naming the port
    /// (`None` while it is connected): why the last connection attempt or
    /// the link failed, or that it is still connecting. Locks briefly: not
    /// for the control thread.
    pub fn problem(&self) -> Option<String> {
        let v = self.try_view()?;
        if v.link == LinkState::Connected {
            return None;
        }
        let why = self
            .shared
            .last_error
            .lock()
            .ok()
            .and_then(|e| e.clone())
            .unwrap_or_else(|| "connecting".to_owned());
        Some(format!(
            "the magnet's board on {} does not answer: {why}",
            self.port
        ))
    }

    /// Waits until `pred` holds for the view (polling every millisecond) or
    /// `timeout` passes; returns the last view and whether `pred` held.
    pub fn wait_for(
        &self,
        timeout: Duration,
        mut pred: impl FnMut(&MagnetView) -> bool,
    ) -> (MagnetView, bool) {
        let deadline = Instant::now() + timeout;
        loop {
            let v = self.view();
            if pred(&v) {
                return (v, true);
            }
            if Instant::now() >= deadline {
                return (v, false);
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }
}

struct Conn {
    id: u64,
    port: TTYPort,
    alive: Arc<AtomicBool>,
}

impl Drop for Conn {
    fn drop(&mut self) {
        self.alive.store(false, Ordering::Release);
    }
}

struct Worker {
    params: MagnetParams,
    rx: Receiver<Inbox>,
    tx: SyncSender<Inbox>,
    shared: std::sync::Weak<Shared>,
    epoch: Instant,
    view: MagnetView,
    conn: Option<Conn>,
    next_conn_id: u64,
    queue: VecDeque<Request>,
    hook: EventHook,
    ping_counter: u32,
    next_connect: Instant,
    next_poll: Instant,
    need_config: bool,
    last_error: Option<String>,
}

/// How one exchange ended.
enum Exchange {
    Answer(Answer),
    DeviceErr(String),
    Timeout,
    Lost(String),
}

fn ms(v: f64) -> Duration {
    Duration::from_secs_f64(v / 1000.0)
}

impl Worker {
    fn run(mut self) {
        loop {
            if self.stopping() {
                break;
            }
            if self.conn.is_none() && Instant::now() >= self.next_connect {
                self.connect();
                continue;
            }
            if self.conn.is_some() && self.need_config {
                self.configure();
                continue;
            }
            if let Some(req) = self.queue.pop_front() {
                self.serve(req);
                continue;
            }
            if self.conn.is_some() && Instant::now() >= self.next_poll {
                self.poll_status();
                continue;
            }
            let wake = if self.conn.is_some() {
                self.next_poll
            } else {
                self.next_connect
            };
            let wait = wake.saturating_duration_since(Instant::now());
            match self.rx.recv_timeout(wait) {
                Ok(Inbox::Stop) | Err(RecvTimeoutError::Disconnected) => break,
                Ok(msg) => self.idle_message(msg),
                Err(RecvTimeoutError::Timeout) => {}
            }
        }
        for req in self.queue.drain(..) {
            let _ = req.reply.try_send(Err(MagnetError::Stopped));
        }
    }

    fn stopping(&self) -> bool {
        self.shared
            .upgrade()
            .is_none_or(|s| s.stop.load(Ordering::Acquire))
    }

    fn now_ns(&self, at: Instant) -> u64 {
        u64::try_from(at.saturating_duration_since(self.epoch).as_nanos()).unwrap_or(u64::MAX)
    }

    fn publish(&self) {
        if let Some(s) = self.shared.upgrade() {
            s.view.publish(&self.view);
        }
    }

    fn event(&mut self, at: Instant, kind: EventKind) {
        self.view.last_event = Some(kind);
        self.view.last_event_at_ns = self.now_ns(at);
        self.view.events += 1;
        self.publish();
        (self.hook)(&MagnetEvent { at, kind });
    }

    fn set_known(&mut self, on: bool, at: Instant, cause: SwitchCause) {
        let new = if on {
            MagnetState::On
        } else {
            MagnetState::Off
        };
        let old = self.view.magnet;
        self.view.magnet = new;
        if old != new {
            self.view.changed_at_ns = self.now_ns(at);
            // A first report after connecting is knowledge, not a switch.
            if old != MagnetState::Unknown || cause == SwitchCause::Command {
                self.event(at, EventKind::Switched { on, cause });
                return;
            }
        }
        self.publish();
    }

    fn lost(&mut self, reason: &str) -> MagnetError {
        self.conn = None;
        self.need_config = false;
        self.set_last_error(Some(reason));
        self.next_connect = Instant::now() + ms(self.params.reconnect_interval_ms);
        let was = self.view.link;
        self.view.link = LinkState::Lost;
        self.view.magnet = MagnetState::Unknown;
        if was == LinkState::Lost {
            self.publish();
        } else {
            self.event(Instant::now(), EventKind::Lost);
        }
        MagnetError::DeviceLost {
            port: self.params.port.clone(),
            reason: reason.to_owned(),
        }
    }

    fn idle_message(&mut self, msg: Inbox) {
        match msg {
            Inbox::Request(req) => self.queue.push_back(req),
            Inbox::Line { conn, text, at } => {
                if self.is_current(conn) {
                    self.unsolicited(&text, at);
                }
            }
            Inbox::Lost { conn, reason } => {
                if self.is_current(conn) {
                    let _ = self.lost(&reason);
                }
            }
            Inbox::Stop => {}
        }
    }

    fn is_current(&self, conn: u64) -> bool {
        self.conn.as_ref().is_some_and(|c| c.id == conn)
    }

    /// A line that answers nothing: events are applied, the rest counted.
    fn unsolicited(&mut self, text: &str, at: Instant) {
        if let Line::Event(e) = parse_line(text) {
            self.device_event(e, at);
        } else {
            self.view.stray_lines += 1;
            self.publish();
        }
    }

    fn device_event(&mut self, e: DeviceEvent, at: Instant) {
        match e {
            DeviceEvent::Boot {
                reset, hold_max_ms, ..
            } => {
                self.view.last_reset = Some(reset);
                self.view.hold_max_ms = hold_max_ms;
                self.event(at, EventKind::Boot { reset });
                self.set_known(false, at, SwitchCause::Reset);
                // The reset restored the default hold limit.
                self.need_config = true;
            }
            DeviceEvent::HoldLimit { held_ms } => {
                self.event(at, EventKind::HoldLimit { held_ms });
                self.set_known(false, at, SwitchCause::HoldLimit);
            }
        }
    }

    fn connect(&mut self) {
        let opened = serialport::new(self.params.port.as_str(), self.params.baud)
            .timeout(Duration::from_millis(50))
            .open_native();
        let port = match opened {
            Ok(p) => p,
            Err(e) => {
                self.fail_connect(&format!("cannot open {}: {e}", self.params.port));
                return;
            }
        };
        let reader = match port.try_clone_native() {
            Ok(r) => r,
            Err(e) => {
                self.fail_connect(&format!("cannot clone {}: {e}", self.params.port));
                return;
            }
        };
        // Bytes waiting from before we opened are stale.
        let _ = port.clear(serialport::ClearBuffer::All);
        self.next_conn_id += 1;
        let id = self.next_conn_id;
        let alive = Arc::new(AtomicBool::new(true));
        let tx = self.tx.clone();
        let alive_r = Arc::clone(&alive);
        let spawned = std::thread::Builder::new()
            .name("isochron-magnet-rx".to_owned())
            .spawn(move || read_lines(reader, id, &alive_r, &tx));
        if let Err(e) = spawned {
            self.fail_connect(&format!("cannot start the reader thread: {e}"));
            return;
        }
        self.conn = Some(Conn { id, port, alive });
        match self.resync(ms(self.params.boot_timeout_ms)) {
            Ok(()) => {
                // Connected means configured and the state known.
                self.configure();
                if self.conn.is_some() {
                    self.set_last_error(None);
                    self.view.link = LinkState::Connected;
                    self.view.connects += 1;
                    self.event(Instant::now(), EventKind::Connected);
                }
            }
            Err(reason) => {
                self.conn = None;
                self.fail_connect(&reason);
            }
        }
    }

    fn fail_connect(&mut self, reason: &str) {
        self.conn = None;
        self.next_connect = Instant::now() + ms(self.params.reconnect_interval_ms);
        if self.view.link == LinkState::Connected {
            let _ = self.lost(reason);
            return;
        }
        if self.view.connects > 0 {
            self.view.link = LinkState::Lost;
        }
        self.view.magnet = MagnetState::Unknown;
        self.publish();
        // Requests while disconnected are refused at once.
        while let Ok(msg) = self.rx.try_recv() {
            match msg {
                Inbox::Request(req) => {
                    let _ = req.reply.try_send(Err(MagnetError::NotConnected {
                        port: self.params.port.clone(),
                        reason: reason.to_owned(),
                    }));
                }
                Inbox::Stop => {
                    self.stop_soon();
                    break;
                }
                _ => {}
            }
        }
        self.set_last_error(Some(reason));
    }

    fn set_last_error(&mut self, reason: Option<&str>) {
        self.last_error = reason.map(str::to_owned);
        if let Some(s) = self.shared.upgrade()
            && let Ok(mut e) = s.last_error.lock()
        {
            e.clone_from(&self.last_error);
        }
    }

    fn stop_soon(&self) {
        if let Some(s) = self.shared.upgrade() {
            s.stop.store(true, Ordering::Release);
        }
    }

    /// Sends a fresh `PING` until its `PONG` comes back (skipping stale lines,
    /// applying events) or `budget` passes.
    fn resync(&mut self, budget: Duration) -> Result<(), String> {
        let deadline = Instant::now() + budget;
        let per_try = ms(self.params.command_timeout_ms);
        // End any partial line the device may hold.
        if let Some(c) = self.conn.as_mut() {
            let _ = c.port.write_all(b"\n");
        }
        loop {
            self.ping_counter = self.ping_counter.wrapping_add(1);
            let token = format!("s{}", self.ping_counter);
            let cmd = Command::Ping(token);
            let until = (Instant::now() + per_try).min(deadline);
            match self.exchange(&cmd, until) {
                Exchange::Answer(_) => return Ok(()),
                Exchange::Lost(r) => return Err(r),
                Exchange::DeviceErr(_) | Exchange::Timeout => {}
            }
            if Instant::now() >= deadline {
                return Err(format!(
                    "no answer from {} within {:.0} ms (not the magnet firmware, or no device)",
                    self.params.port,
                    budget.as_secs_f64() * 1000.0
                ));
            }
        }
    }

    /// Writes `cmd` and waits until `until` for its answer. Requests arriving
    /// meanwhile are queued; events are applied; stale answers skipped.
    fn exchange(&mut self, cmd: &Command, until: Instant) -> Exchange {
        let Some(conn) = self.conn.as_mut() else {
            return Exchange::Lost("not connected".to_owned());
        };
        let id = conn.id;
        let mut bytes = cmd.line().into_bytes();
        bytes.push(b'\n');
        let sent = Instant::now();
        if let Err(e) = conn.port.write_all(&bytes).and_then(|()| conn.port.flush()) {
            return Exchange::Lost(format!("write failed: {e}"));
        }
        loop {
            let wait = until.saturating_duration_since(Instant::now());
            let msg = match self.rx.recv_timeout(wait) {
                Ok(m) => m,
                Err(RecvTimeoutError::Timeout) => return Exchange::Timeout,
                Err(RecvTimeoutError::Disconnected) => return Exchange::Lost("stopped".to_owned()),
            };
            match msg {
                Inbox::Request(req) => {
                    if self.queue.len() < QUEUE_CAPACITY {
                        self.queue.push_back(req);
                    } else {
                        let _ = req.reply.try_send(Err(MagnetError::Busy));
                    }
                }
                Inbox::Stop => {
                    self.stop_soon();
                    return Exchange::Lost("driver stopping".to_owned());
                }
                Inbox::Lost { conn, reason } if conn == id => return Exchange::Lost(reason),
                Inbox::Lost { .. } => {}
                Inbox::Line { conn, text, at } if conn == id => match parse_line(&text) {
                    Line::Ok(ok) if cmd.expects(&ok) => {
                        let rtt = at.saturating_duration_since(sent);
                        self.view.last_rtt_us = u32::try_from(rtt.as_micros()).unwrap_or(u32::MAX);
                        self.view.commands += 1;
                        return Exchange::Answer(Answer {
                            reply: ok,
                            rtt,
                            sent,
                        });
                    }
                    Line::Err(code) if !matches!(cmd, Command::Ping(_)) => {
                        self.view.commands += 1;
                        return Exchange::DeviceErr(code);
                    }
                    Line::Event(e) => self.device_event(e, at),
                    _ => {
                        self.view.stray_lines += 1;
                    }
                },
                Inbox::Line { .. } => {}
            }
        }
    }

    /// Runs one command for a caller, keeping the view and the link honest.
    fn run_command(&mut self, cmd: &Command) -> Result<Answer, MagnetError> {
        if self.conn.is_none() {
            return Err(MagnetError::NotConnected {
                port: self.params.port.clone(),
                reason: self
                    .last_error
                    .clone()
                    .unwrap_or_else(|| "not connected yet".to_owned()),
            });
        }
        let timeout = ms(self.params.command_timeout_ms);
        match self.exchange(cmd, Instant::now() + timeout) {
            Exchange::Answer(a) => {
                let (at, cause) = if matches!(cmd, Command::Magnet(_)) {
                    // The pin switched when the command's last byte arrived,
                    // before the answer was sent back.
                    (
                        a.sent + self.wire_time(cmd.line().len() + 1).min(a.rtt),
                        SwitchCause::Command,
                    )
                } else {
                    (Instant::now(), SwitchCause::Status)
                };
                if let Some(s) = a.status() {
                    self.view.hold_max_ms = s.hold_max_ms;
                    if let Some(r) = s.reset {
                        self.view.last_reset = Some(r);
                    }
                    self.set_known(s.magnet_on, at, cause);
                } else if let OkReply::Hold { hold_max_ms } = a.reply {
                    self.view.hold_max_ms = hold_max_ms;
                    self.publish();
                } else {
                    self.publish();
                }
                Ok(a)
            }
            Exchange::DeviceErr(code) => {
                self.publish();
                Err(MagnetError::Device {
                    command: cmd.line(),
                    code,
                })
            }
            Exchange::Lost(reason) => Err(self.lost(&reason)),
            Exchange::Timeout => {
                self.view.timeouts += 1;
                self.publish();
                // Silent: a late answer may still come; make sure the next
                // command starts clean, or give the link up.
                if let Err(reason) = self.resync(ms(self.params.boot_timeout_ms)) {
                    let _ = self.lost(&reason);
                }
                Err(MagnetError::Timeout {
                    port: self.params.port.clone(),
                    command: cmd.line(),
                    timeout_ms: self.params.command_timeout_ms,
                })
            }
        }
    }

    /// How long `bytes` take on the wire (10 bits each at the configured baud).
    fn wire_time(&self, bytes: usize) -> Duration {
        Duration::from_secs_f64(bytes as f64 * 10.0 / f64::from(self.params.baud))
    }

    fn serve(&mut self, req: Request) {
        let r = self.run_command(&req.cmd);
        self.next_poll = Instant::now() + ms(self.params.status_poll_ms);
        let _ = req.reply.try_send(r);
    }

    fn configure(&mut self) {
        self.need_config = false;
        let hold = Command::Hold(self.params.hold_limit_s);
        if self.run_command(&hold).is_ok() {
            let _ = self.run_command(&Command::Status);
        }
        self.next_poll = Instant::now() + ms(self.params.status_poll_ms);
    }

    fn poll_status(&mut self) {
        let _ = self.run_command(&Command::Status);
        self.next_poll = Instant::now() + ms(self.params.status_poll_ms);
    }
}

/// The reader thread: splits the byte stream into lines for the magnet thread
/// until the port fails or the connection is dropped.
fn read_lines(mut port: TTYPort, conn: u64, alive: &AtomicBool, tx: &SyncSender<Inbox>) {
    let mut buf = [0u8; 256];
    let mut line: Vec<u8> = Vec::with_capacity(MAX_DEVICE_LINE);
    let mut overlong = false;
    while alive.load(Ordering::Acquire) {
        match port.read(&mut buf) {
            Ok(0) => {
                let _ = tx.send(Inbox::Lost {
                    conn,
                    reason: "the device closed the port (unplugged?)".to_owned(),
                });
                return;
            }
            Ok(n) => {
                let at = Instant::now();
                for &b in &buf[..n] {
                    if b == b'\n' {
                        if !overlong {
                            let text = String::from_utf8_lossy(&line).trim_end().to_owned();
                            if !text.is_empty() && tx.send(Inbox::Line { conn, text, at }).is_err()
                            {
                                return;
                            }
                        }
                        line.clear();
                        overlong = false;
                    } else if line.len() < MAX_DEVICE_LINE {
                        line.push(b);
                    } else {
                        overlong = true;
                    }
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => {
                let _ = tx.send(Inbox::Lost {
                    conn,
                    reason: format!("device lost (unplugged?): {e}"),
                });
                return;
            }
        }
    }
}
