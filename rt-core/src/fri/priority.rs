//! Real-time priority (`SCHED_FIFO`) for the threads that carry the FRI cycle:
//! the client session (`isochron-fri`) and the simulated controller
//! (`isochron-fri-sim`). Once the process has asked for it ([`enable`], done by
//! the lab runtime that `serve` and `bench` start, and by `fri-sim` and
//! `world`, whose cabinet stands in for a machine of its own) each raises
//! itself when it starts (`thread-priority`, i.e. `pthread_setschedparam`; no
//! `chrt` child process). Other users of the session and the simulated
//! controller (tests) keep the normal policy.
//!
//! Without the privilege (`CAP_SYS_NICE` or an `rtprio` limit) the thread keeps
//! the normal policy and the lab runs: other load on the machine can then delay
//! the FRI cycle (watch the late replies). The first refusal in a process is
//! said once on standard error; later ones are silent.
//!
//! Beyond the priority, a process can [`configure`] the rest of what real-time
//! Linux users do ([`RtTuning`]; `serve` and `bench` take [`RtTuning::auto`]:
//! all of it with two or more CPUs, the priority and locked memory on one;
//! tests keep only the priority): the FRI threads pinned to one CPU (the last of the
//! process's CPUs), every other thread of the process kept off that CPU when
//! there is another one, the process's memory locked (`mlockall`, pages
//! locked as they are first touched) so the FRI thread never waits for a page
//! to come back from swap, and the client session polling its socket from
//! shortly before each expected datagram (`spin`), so that no wake-up of a
//! sleeping thread lies between the datagram and the reply. Each is asked for once, when the lab starts; a
//! refusal is said once and the lab runs without it.

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};

pub use rustix::thread::CpuSet;
use rustix::thread::Pid;

use thread_priority::{
    RealtimeThreadSchedulePolicy, ThreadPriority, ThreadPriorityValue, ThreadSchedulePolicy,
    set_thread_priority_and_policy, thread_native_id,
};

/// Real-time priority of the FRI client thread (`SCHED_FIFO`, 1..99).
pub const FRI_PRIORITY: u8 = 20;
/// Real-time priority of the simulated controller's thread: above the client's,
/// so that on a shared CPU the controller's send is never held up by a client
/// spinning for it ([`RtTuning::spin`]), and the reply wakes the controller at
/// once. (A real controller is a machine of its own.)
pub const SIM_PRIORITY: u8 = FRI_PRIORITY + 1;

/// Threads running now with [`FRI_PRIORITY`] (held by [`RealtimeGuard`]s).
static RAISED: AtomicU64 = AtomicU64::new(0);
/// Whether a refusal was already said.
static REFUSAL_SAID: AtomicBool = AtomicBool::new(false);
/// Whether FRI threads of this process ask for real-time priority.
static ENABLED: AtomicBool = AtomicBool::new(false);
/// Whether FRI client sessions of this process spin before expected datagrams.
static SPIN: AtomicBool = AtomicBool::new(false);

/// Which real-time measures a process takes when its lab starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RtTuning {
    /// `SCHED_FIFO` for the FRI threads.
    pub fifo: bool,
    /// The FRI threads pinned to one CPU (the last of the process's CPUs).
    pub pin: bool,
    /// Every other thread of the process kept off the FRI CPU (needs `pin` and
    /// at least two CPUs).
    pub isolate: bool,
    /// `mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT)`.
    pub mlock: bool,
    /// The FRI client session polls its socket without sleeping from shortly
    /// before each expected datagram until it arrives
    /// ([`crate::fri::session::SPIN_LEAD`]).
    pub spin: bool,
}

impl RtTuning {
    /// Every measure (`serve`, `bench`).
    pub const ALL: Self = Self {
        fifo: true,
        pin: true,
        isolate: true,
        mlock: true,
        spin: true,
    };
    /// The priority only (the default: tests, `fri-sim`, `world`).
    pub const FIFO: Self = Self {
        fifo: true,
        pin: false,
        isolate: false,
        mlock: false,
        spin: false,
    };
    /// None at all.
    pub const NONE: Self = Self {
        fifo: false,
        pin: false,
        isolate: false,
        mlock: false,
        spin: false,
    };

    /// What suits this machine (`serve`, and `bench` unless told): every
    /// measure with two or more CPUs (the FRI threads on the last CPU, the
    /// rest of the process on the others); on one CPU the priority and locked
    /// memory only (spinning there would take the CPU from everything else).
    /// Measured on the 2-core VM of this workplace (`isochron bench`, 10 s at
    /// 1 ms with the whole lab): reply latency p99 about 150 us with
    /// `fifo,mlock` (1-3 late replies per 10,000), 95-145 us with all (0
    /// late); the dashboard keeps 60 fps in the browser test either way.
    pub fn auto() -> Self {
        let cpus = rustix::thread::sched_getaffinity(None)
            .map_or(1, |m| (0..CpuSet::MAX_CPU).filter(|&c| m.is_set(c)).count());
        if cpus >= 2 {
            Self::ALL
        } else {
            Self {
                pin: false,
                isolate: false,
                spin: false,
                ..Self::ALL
            }
        }
    }

    /// Parses `auto`, `all`, `none` or a comma-separated list of `fifo`, `pin`,
    /// `isolate`, `mlock`, `spin` (`isolate` implies `pin`).
    ///
    /// # Errors
    ///
    /// A message naming the word when a list item is not one of the known measures.
    pub fn parse(text: &str) -> Result<Self, String> {
        match text.trim() {
            "auto" => return Ok(Self::auto()),
            "all" => return Ok(Self::ALL),
            "none" => return Ok(Self::NONE),
            _ => {}
        }
        let mut t = Self::NONE;
        for word in text.split(',').map(str::trim) {
            match word {
                "fifo" => t.fifo = true,
                "pin" => t.pin = true,
                "isolate" => {
                    t.pin = true;
                    t.isolate = true;
                }
                "mlock" => t.mlock = true,
                "spin" => t.spin = true,
                other => {
                    return Err(format!(
                        "unknown real-time measure {other:?}: expected auto, all, none or a \
                         comma-separated list of fifo, pin, isolate, mlock, spin"
                    ));
                }
            }
        }
        Ok(t)
    }

    /// The measures as `parse` reads them (`all`, `none` or a list).
    pub fn label(&self) -> String {
        if *self == Self::ALL {
            return "all".into();
        }
        let words: Vec<&str> = [
            (self.fifo, "fifo"),
            (self.pin && !self.isolate, "pin"),
            (self.isolate, "isolate"),
            (self.mlock, "mlock"),
            (self.spin, "spin"),
        ]
        .into_iter()
        .filter_map(|(on, w)| on.then_some(w))
        .collect();
        if words.is_empty() {
            "none".into()
        } else {
            words.join(",")
        }
    }
}

impl Default for RtTuning {
    fn default() -> Self {
        Self::FIFO
    }
}

impl serde::Serialize for RtTuning {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&self.label())
    }
}

/// What this process's lab will ask for ([`configure`]; default [`RtTuning::FIFO`]).
static TUNING: Mutex<RtTuning> = Mutex::new(RtTuning::FIFO);
/// The CPU the FRI threads are pinned to, plus one (0: not pinned).
static FRI_CPU: AtomicUsize = AtomicUsize::new(0);

/// Sets the measures the next [`enable`] takes (before the lab starts).
pub fn configure(tuning: RtTuning) {
    *TUNING
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner) = tuning;
}

/// The measures configured for this process.
pub fn configured() -> RtTuning {
    *TUNING
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// What [`enable`] got, for the reports.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct RtStatus {
    /// The measures asked for (`all`, `none` or a list).
    pub asked: RtTuning,
    /// The CPU the FRI threads run on, when pinned.
    pub fri_cpu: Option<usize>,
    /// Threads moved off the FRI CPU.
    pub isolated_threads: usize,
    /// Whether the memory is locked.
    pub memory_locked: bool,
}

/// From now on, FRI threads started in this process take the [`configure`]d
/// measures (called by the lab runtime when it starts, off the FRI threads).
/// Memory locking and moving the process's other threads off the FRI CPU
/// happen here, once.
pub fn enable() -> RtStatus {
    let tuning = configured();
    ENABLED.store(tuning.fifo, Ordering::Relaxed);
    SPIN.store(tuning.spin, Ordering::Relaxed);
    let mut status = RtStatus {
        asked: tuning,
        ..RtStatus::default()
    };
    if tuning.mlock {
        use rustix::mm::{MlockAllFlags, mlockall};
        use rustix::process::{Resource, getrlimit};
        // With a finite lock limit, MCL_FUTURE would make later allocations fail
        // once the limit is reached: lock only when the limit cannot be reached
        // (`ulimit -l unlimited`; root has CAP_IPC_LOCK and no limit either way).
        let limit = getrlimit(Resource::Memlock);
        let unlimited = limit.current.is_none() || rustix::process::geteuid().is_root();
        if unlimited {
            match mlockall(MlockAllFlags::CURRENT | MlockAllFlags::FUTURE | MlockAllFlags::ONFAULT)
            {
                Ok(()) => status.memory_locked = true,
                Err(e) => say_once(&format!("memory not locked (mlockall: {e})")),
            }
        } else {
            say_once("memory not locked (the memlock limit is finite: ulimit -l)");
        }
    }
    if tuning.pin {
        match rustix::thread::sched_getaffinity(None) {
            Ok(mask) => {
                let cpus: Vec<usize> = (0..CpuSet::MAX_CPU).filter(|&c| mask.is_set(c)).collect();
                if let Some(&fri) = cpus.last() {
                    FRI_CPU.store(fri + 1, Ordering::Relaxed);
                    status.fri_cpu = Some(fri);
                    if tuning.isolate && cpus.len() >= 2 {
                        let mut others = mask;
                        others.unset(fri);
                        status.isolated_threads = keep_threads_off(&others);
                    }
                }
            }
            Err(e) => say_once(&format!("FRI threads not pinned (sched_getaffinity: {e})")),
        }
    } else {
        FRI_CPU.store(0, Ordering::Relaxed);
    }
    status
}

/// Moves every thread of the process to `others` (threads started later
/// inherit the mask of the thread that starts them); FRI threads pin
/// themselves back when they start, and one already pinned to the FRI CPU
/// alone (started after an earlier [`enable`], such as the in-process
/// world's cabinet) stays there. Returns the threads moved.
fn keep_threads_off(others: &CpuSet) -> usize {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
        return 0;
    };
    let mut moved = 0;
    for t in tasks.flatten() {
        let Some(tid) = t
            .file_name()
            .to_str()
            .and_then(|s| s.parse::<i32>().ok())
            .and_then(Pid::from_raw)
        else {
            continue;
        };
        let on_fri_cpu_only = rustix::thread::sched_getaffinity(Some(tid)).is_ok_and(|m| {
            let mut set = (0..CpuSet::MAX_CPU).filter(|&c| m.is_set(c));
            matches!((set.next(), set.next()), (Some(c), None) if !others.is_set(c))
        });
        if on_fri_cpu_only {
            continue;
        }
        if rustix::thread::sched_setaffinity(Some(tid), others).is_ok() {
            moved += 1;
        }
    }
    moved
}

fn say_once(what: &str) {
    if !REFUSAL_SAID.swap(true, Ordering::Relaxed) {
        eprintln!("isochron: {what}; the lab runs without it. Said once.");
    }
}

/// The calling thread's CPUs, to give back later with [`set_current_cpus`]
/// (`None` when the kernel does not say).
pub fn current_cpus() -> Option<CpuSet> {
    rustix::thread::sched_getaffinity(None).ok()
}

/// Lets the calling thread (and the threads and processes it starts from now
/// on) run on `cpus` again, e.g. after [`enable`] kept it off the FRI CPU.
pub fn set_current_cpus(cpus: &CpuSet) {
    if let Err(e) = rustix::thread::sched_setaffinity(None, cpus) {
        say_once(&format!("CPU affinity not restored ({e})"));
    }
}

/// Pins the calling thread to the FRI CPU when the process asked for it.
fn pin_current_thread() {
    let cpu = FRI_CPU.load(Ordering::Relaxed);
    if cpu == 0 {
        return;
    }
    let mut set = CpuSet::new();
    set.set(cpu - 1);
    if let Err(e) = rustix::thread::sched_setaffinity(None, &set) {
        say_once(&format!("FRI thread not pinned to CPU {} ({e})", cpu - 1));
    }
}

/// Held by a thread for as long as it runs: counts it in [`realtime_threads`]
/// while it has real-time priority.
#[derive(Debug)]
pub struct RealtimeGuard {
    raised: bool,
}

impl RealtimeGuard {
    /// Whether the thread got `SCHED_FIFO`.
    pub fn raised(&self) -> bool {
        self.raised
    }
}

impl Drop for RealtimeGuard {
    fn drop(&mut self) {
        if self.raised {
            RAISED.fetch_sub(1, Ordering::Relaxed);
        }
    }
}

/// Once [`enable`]d, gives the calling thread `SCHED_FIFO` at `priority`
/// ([`FRI_PRIORITY`] or [`SIM_PRIORITY`]) when allowed (never fails: without the privilege the thread keeps its policy, and the
/// first refusal in the process is said once on standard error). `thread`
/// names the caller in that message. Keep the guard for the thread's life.
pub fn raise_current_thread(thread: &str, priority: u8) -> RealtimeGuard {
    pin_current_thread();
    if !ENABLED.load(Ordering::Relaxed) {
        return RealtimeGuard { raised: false };
    }
    raise(thread, priority)
}

fn raise(thread: &str, priority: u8) -> RealtimeGuard {
    let result = ThreadPriorityValue::try_from(priority)
        .map_err(|e| e.clone())
        .and_then(|value| {
            set_thread_priority_and_policy(
                thread_native_id(),
                ThreadPriority::Crossplatform(value),
                ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::Fifo),
            )
            .map_err(|e| format!("{e:?}"))
        });
    match result {
        Ok(()) => {
            RAISED.fetch_add(1, Ordering::Relaxed);
            RealtimeGuard { raised: true }
        }
        Err(e) => {
            if !REFUSAL_SAID.swap(true, Ordering::Relaxed) {
                eprintln!(
                    "isochron: {thread} keeps the normal scheduling policy (SCHED_FIFO {priority} \
                     not allowed: {e}); other load can delay the FRI cycle. Said once."
                );
            }
            RealtimeGuard { raised: false }
        }
    }
}

/// Whether FRI client sessions started from now on spin before each expected
/// datagram ([`RtTuning::spin`], once [`enable`]d).
pub fn spin_enabled() -> bool {
    SPIN.load(Ordering::Relaxed)
}

/// FRI threads of this process running now with real-time priority.
pub fn realtime_threads() -> u64 {
    RAISED.load(Ordering::Relaxed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn raising_never_fails_and_the_policy_matches_the_answer() {
        std::thread::Builder::new()
            .name("isochron-prio-test".into())
            .spawn(|| {
                let guard = raise("test", FRI_PRIORITY);
                // Whether it is allowed depends on the machine; the thread's policy
                // and the count must agree with the answer (other tests' FRI
                // threads may be counted too).
                assert!(realtime_threads() >= u64::from(guard.raised()));
                let policy = std::fs::read_to_string("/proc/thread-self/sched").unwrap_or_default();
                if guard.raised() {
                    assert!(
                        policy
                            .lines()
                            .any(|l| l.starts_with("policy") && l.trim_end().ends_with(" 1")),
                        "{policy}"
                    );
                }
                drop(guard);
            })
            .unwrap()
            .join()
            .unwrap();
    }
}
