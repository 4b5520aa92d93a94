//! Child processes of the end-to-end tests: started, waited on until they
//! say they are ready, killed when dropped; and where the magnet firmware is.

use std::{
    io::{BufRead, BufReader},
    path::{Path, PathBuf},
    process::{Child, Command as Process, Stdio},
    sync::mpsc,
    time::Duration,
};

/// A child process killed when dropped.
pub struct Proc {
    child: Child,
    /// Held open: the simavr host stops at the end of its input.
    _stdin: Option<std::process::ChildStdin>,
}

impl Proc {
    /// A started process (its input closed or not piped).
    pub fn from_child(child: Child) -> Self {
        Self {
            child,
            _stdin: None,
        }
    }

    /// Kills the process and waits for it.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Its process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// CPU time it has used so far (user + system), seconds (Linux; 0
    /// where `/proc` does not tell).
    pub fn cpu_s(&self) -> f64 {
        let stat =
            std::fs::read_to_string(format!("/proc/{}/stat", self.child.id())).unwrap_or_default();
        // Fields after the command's closing parenthesis: utime is the 12th, stime the 13th.
        let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
        let f: Vec<f64> = rest
            .split_whitespace()
            .map(|v| v.parse().unwrap_or(0.0))
            .collect();
        let ticks = f.get(11).copied().unwrap_or(0.0) + f.get(12).copied().unwrap_or(0.0);
        ticks / 100.0
    }

    /// Whether it still runs.
    pub fn alive(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill();
    }
}

/// The magnet firmware and its simavr host (`make firmware`): `None` (a
/// skip, said on stderr) when missing, a failure under `CI=true`.
pub fn firmware() -> Option<(PathBuf, PathBuf)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../firmware/magnet/build");
    let (elf, host) = (dir.join("magnet.elf"), dir.join("magnet-sim"));
    if elf.is_file() && host.is_file() {
        return Some((elf, host));
    }
    let msg = format!(
        "magnet firmware or simulator host missing in {} (run `make firmware`)",
        dir.display()
    );
    assert!(std::env::var("CI").as_deref() != Ok("true"), "{msg}");
    eprintln!("SKIPPED: {msg}");
    None
}

/// Starts a process and waits until a line of its standard output contains
/// `ready` (returns that line); its later output is drained.
pub fn start(
    name: &'static str,
    cmd: &mut Process,
    ready: &str,
    timeout: Duration,
) -> (Proc, String) {
    let mut child = cmd
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {name}: {e}"));
    let out = child.stdout.take().unwrap();
    let stdin = child.stdin.take();
    let (tx, rx) = mpsc::sync_channel(1);
    let ready = ready.to_owned();
    let _ = std::thread::Builder::new()
        .name("isochron-test-out".into())
        .spawn(move || {
            let mut sent = false;
            for line in BufReader::new(out).lines() {
                let Ok(line) = line else { break };
                if !sent && line.contains(&ready) {
                    let _ = tx.send(line);
                    sent = true;
                }
            }
        });
    let mut p = Proc {
        child,
        _stdin: stdin,
    };
    if let Ok(line) = rx.recv_timeout(timeout) {
        (p, line)
    } else {
        let alive = p.alive();
        panic!("{name} did not become ready within {timeout:?} (alive: {alive})")
    }
}
