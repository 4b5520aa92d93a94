//! Real-time priority (`SCHED_FIFO`) for the threads that carry the FRI cycle:
//! the client session (`isochron-fri`) and the simulated controller
//! (`isochron-fri-sim`). Once the process has asked for it ([`enable`], done by
//! the lab runtime that `serve` and `bench` start) each raises itself when it
//! starts (`thread-priority`, i.e. `pthread_setschedparam`; no `chrt` child
//! process). Other users of the session and the simulated controller (tests,
//! `fri-sim`) keep the normal policy, as before.
//!
//! Without the privilege (`CAP_SYS_NICE` or an `rtprio` limit) the thread keeps
//! the normal policy and the lab runs: other load on the machine can then delay
//! the FRI cycle (watch the late replies). The first refusal in a process is
//! said once on standard error; later ones are silent.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use thread_priority::{
    RealtimeThreadSchedulePolicy, ThreadPriority, ThreadPriorityValue, ThreadSchedulePolicy,
    set_thread_priority_and_policy, thread_native_id,
};

/// Real-time priority of the FRI threads (`SCHED_FIFO`, 1..99).
pub const FRI_PRIORITY: u8 = 20;

/// Threads running now with [`FRI_PRIORITY`] (held by [`RealtimeGuard`]s).
static RAISED: AtomicU64 = AtomicU64::new(0);
/// Whether a refusal was already said.
static REFUSAL_SAID: AtomicBool = AtomicBool::new(false);
/// Whether FRI threads of this process ask for real-time priority.
static ENABLED: AtomicBool = AtomicBool::new(false);

/// From now on, FRI threads started in this process ask for `SCHED_FIFO`.
pub fn enable() {
    ENABLED.store(true, Ordering::Relaxed);
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

/// Once [`enable`]d, gives the calling thread `SCHED_FIFO` at [`FRI_PRIORITY`]
/// when allowed (never fails: without the privilege the thread keeps its policy, and the
/// first refusal in the process is said once on standard error). `thread`
/// names the caller in that message. Keep the guard for the thread's life.
pub fn raise_current_thread(thread: &str) -> RealtimeGuard {
    if !ENABLED.load(Ordering::Relaxed) {
        return RealtimeGuard { raised: false };
    }
    raise(thread)
}

fn raise(thread: &str) -> RealtimeGuard {
    let result = ThreadPriorityValue::try_from(FRI_PRIORITY)
        .map_err(|e| e.to_string())
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
                    "isochron: {thread} keeps the normal scheduling policy (SCHED_FIFO {FRI_PRIORITY} \
                     not allowed: {e}); other load can delay the FRI cycle. Said once."
                );
            }
            RealtimeGuard { raised: false }
        }
    }
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
                let guard = raise("test");
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
