//! `isochron serve` as a child process of a test, driven over REST with a
//! token: started on a free loopback port, its standard error kept in a log
//! file that is printed (its tail) when the test fails, killed when dropped.

use std::ffi::OsStr;
use std::io::{BufRead, BufReader, Read, Seek, SeekFrom};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

/// A trial's abort reasons that a starved machine causes, not the feature a
/// test is for: the simulated lab's camera and magnet board are threads of
/// the service, and beside `stress-ng` a board stayed silent past its
/// timeouts while it held the ball (`magnet_fault`), the frames stopped
/// (`camera_lost`) or no pass was confident in time (`timeout`). Such a
/// trial finished with its reason: no record is lost.
pub const STARVED_ABORTS: [&str; 3] = ["magnet_fault", "camera_lost", "timeout"];

/// Whether a trial record (`GET /api/trials/{id}`) was aborted for one of
/// [`STARVED_ABORTS`].
pub fn starved(record: &Value) -> bool {
    record["status"] == "aborted"
        && record["abort_reason"]
            .as_str()
            .is_some_and(|a| STARVED_ABORTS.contains(&a))
}

/// Why a done trial of a real lab on a simulated world (`isochron serve`
/// without a configuration) may not be judged on a starved machine: the
/// robot's FRI messages paused around the pass or the arrival, or the
/// camera's frames missed the pass. Such a trial says so in its reason.
pub const STARVED_NOT_JUDGED: [&str; 2] = [
    rt_core::lab::step::NOT_JUDGED_ROBOT_GAP,
    rt_core::lab::step::NOT_JUDGED_MEASURED,
];

/// Whether a done trial record was not judged for one of
/// [`STARVED_NOT_JUDGED`] (then `success` and `judged_by` are null).
pub fn not_judged_starved(record: &Value) -> bool {
    record["status"] == "done"
        && record["success"].is_null()
        && record["judged_by"].is_null()
        && record["reason"]
            .as_str()
            .is_some_and(|r| STARVED_NOT_JUDGED.contains(&r))
}

/// Lines of the service's log a failing test prints.
const LOG_TAIL_LINES: usize = 60;

/// A running `isochron serve`.
pub struct Service {
    child: Child,
    /// Where it answers.
    pub addr: SocketAddr,
    log: PathBuf,
}

impl Service {
    /// Starts `isochron serve --bind 127.0.0.1:0 --token TOKEN ARGS` and
    /// waits (60 s at most) until it prints its address. Its standard error
    /// is appended to `log` (a restarted service's after the last one's).
    ///
    /// # Panics
    ///
    /// When it cannot start or does not print its address in time.
    pub fn start<S: AsRef<OsStr>>(bin: &Path, token: &str, log: &Path, args: &[S]) -> Self {
        let err = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(log)
            .unwrap_or_else(|e| panic!("cannot open {}: {e}", log.display()));
        let mut child = Command::new(bin)
            .args(["serve", "--bind", "127.0.0.1:0", "--token", token])
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(err)
            .spawn()
            .expect("isochron serve starts");
        let out = child.stdout.take().unwrap();
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        std::thread::Builder::new()
            .name("isochron-test-serve-out".into())
            .spawn(move || {
                for line in BufReader::new(out).lines().map_while(Result::ok) {
                    if let Some(rest) = line.split("http://").nth(1) {
                        let _ = tx.try_send(rest.trim_end_matches('/').to_owned());
                    }
                }
            })
            .unwrap();
        let mut svc = Self {
            child,
            addr: SocketAddr::from(([127, 0, 0, 1], 0)),
            log: log.to_owned(),
        };
        let printed = rx.recv_timeout(Duration::from_secs(60));
        svc.addr = printed
            .expect("isochron serve prints its address")
            .parse()
            .expect("isochron serve prints host:port");
        svc
    }

    /// Kills it (no shutdown of any kind) and waits for it.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// The last `lines` lines of its standard error so far.
    pub fn log_tail(&self, lines: usize) -> String {
        let Ok(mut f) = std::fs::File::open(&self.log) else {
            return String::new();
        };
        // The tail is in the last 64 KiB of any log the tests write.
        let len = f.metadata().map_or(0, |m| m.len());
        let _ = f.seek(SeekFrom::Start(len.saturating_sub(64 * 1024)));
        let mut text = String::new();
        let _ = f.read_to_string(&mut text);
        let all: Vec<&str> = text.lines().collect();
        all[all.len().saturating_sub(lines)..].join("\n")
    }
}

impl Drop for Service {
    fn drop(&mut self) {
        // Whether it was still running: a service that died is part of why.
        let exited = self.child.try_wait().ok().flatten();
        self.kill();
        if std::thread::panicking() {
            eprintln!(
                "isochron serve at {} ({}); the last {LOG_TAIL_LINES} lines of its log {}:\n{}",
                self.addr,
                exited.map_or_else(|| "running".to_owned(), |s| format!("exited: {s}")),
                self.log.display(),
                self.log_tail(LOG_TAIL_LINES)
            );
        }
    }
}

/// One REST request with a bearer `token` and a JSON body: the status and
/// the body as JSON (`null` when it is not JSON).
///
/// # Errors
///
/// When the service does not answer (refused, reset, or the client's 10 s
/// timeout: see [`timed_out`]).
pub async fn api(
    addr: SocketAddr,
    token: &str,
    method: &str,
    path: &str,
    body: &str,
) -> anyhow::Result<(u16, Value)> {
    let auth = format!("Bearer {token}");
    let r = crate::http(
        addr,
        method,
        path,
        &[
            ("Content-Type", "application/json"),
            ("Authorization", &auth),
        ],
        body.as_bytes(),
    )
    .await?;
    Ok((r.status, r.json().unwrap_or(Value::Null)))
}

/// Whether a request failed because no answer came within the client's
/// timeout (a service stalled on a starved machine, not one that is gone).
pub fn timed_out(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        c.downcast_ref::<reqwest::Error>()
            .is_some_and(reqwest::Error::is_timeout)
    })
}

/// Polls `GET path` until it answers 200 with a body for which `pred`
/// holds (every 10 ms, at most `timeout`); a poll the service does not
/// answer in time is one more poll, a refused connection a failure.
///
/// # Panics
///
/// When `timeout` passes first, or the service is gone.
pub async fn wait_for(
    addr: SocketAddr,
    token: &str,
    path: &str,
    timeout: Duration,
    what: &str,
    pred: impl Fn(&Value) -> bool,
) -> Value {
    let deadline = Instant::now() + timeout;
    loop {
        let last = match api(addr, token, "GET", path, "").await {
            Ok((200, v)) if pred(&v) => return v,
            Ok((code, v)) => format!("{code} {v}"),
            Err(e) if timed_out(&e) => format!("no answer ({e:#})"),
            Err(e) => panic!("{what}: GET {path}: the service does not answer: {e:#}"),
        };
        assert!(
            Instant::now() < deadline,
            "{what}: not within {timeout:?}; last {path}: {last}"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}
