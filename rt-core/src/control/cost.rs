//! What one control step costs, by wall clock and by the calling thread's CPU
//! time, so that a step the machine preempted is told apart from a step whose
//! own computation overran the FRI period.
//!
//! - [`StepClock`] brackets a step: `Instant` plus `CLOCK_THREAD_CPUTIME_ID`
//!   (two `clock_gettime` calls at each end; no allocation, lock or log). The
//!   CPU time's read is a system call (1.4 us of a 5 us step of the real-time
//!   lab, p50, on this workplace's VM): [`StepClock::start_wall`] skips it, and
//!   the real-time lab uses it.
//! - [`StepCost::lateness`] classifies it: a **deadline miss** is a step whose
//!   CPU time exceeded the period (the step's own work); a **preempted** step
//!   took longer than the period by wall clock only (the thread was
//!   descheduled or interrupted while the step ran).
//! - [`StepTimings`] is a preallocated, pre-touched buffer of per-step records
//!   for benches: recording never allocates or page-faults; when full, further
//!   steps are counted as dropped.

use std::time::Instant;

use super::state::TrialState;

/// The calling thread's CPU time, nanoseconds (`CLOCK_THREAD_CPUTIME_ID`;
/// 0 where the clock is missing, so every step then counts as on time by CPU).
pub fn thread_cpu_ns() -> u64 {
    cpu_time::ThreadTime::try_now().map_or(0, |t| {
        u64::try_from(t.as_duration().as_nanos()).unwrap_or(u64::MAX)
    })
}

/// A started measurement of one step.
#[derive(Debug, Clone, Copy)]
pub struct StepClock {
    wall: Instant,
    /// The thread's CPU time at the start; `None`: not read ([`Self::start_wall`]).
    cpu_ns: Option<u64>,
}

impl StepClock {
    /// Starts measuring now, by wall clock and the thread's CPU time.
    pub fn start() -> Self {
        Self {
            wall: Instant::now(),
            cpu_ns: Some(thread_cpu_ns()),
        }
    }

    /// Starts measuring now by wall clock only: no system call (reading the
    /// thread's CPU time is one, on Linux not served by the vDSO). The cost's
    /// CPU time is then its wall time, so a step longer than the period counts
    /// as an overrun whether it computed or was preempted.
    pub fn start_wall() -> Self {
        Self {
            wall: Instant::now(),
            cpu_ns: None,
        }
    }

    /// Stops measuring: what the step cost since [`Self::start`].
    pub fn stop(&self) -> StepCost {
        let wall = u64::try_from(self.wall.elapsed().as_nanos()).unwrap_or(u64::MAX);
        let cpu = self
            .cpu_ns
            .map_or(wall, |c| thread_cpu_ns().saturating_sub(c));
        StepCost {
            wall_ns: wall,
            cpu_ns: cpu,
        }
    }
}

/// The cost of one step.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct StepCost {
    /// Wall-clock duration, nanoseconds.
    pub wall_ns: u64,
    /// CPU time of the calling thread during the step, nanoseconds (the wall
    /// time when it was not read: [`StepClock::start_wall`]).
    pub cpu_ns: u64,
}

/// How a step fared against its period.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Lateness {
    /// Done within the period by wall clock.
    OnTime,
    /// Longer than the period by wall clock, but its own computation (CPU
    /// time) fitted: the thread was preempted.
    Preempted,
    /// Its own computation took longer than the period: a deadline miss.
    Overrun,
}

impl StepCost {
    /// Classifies the step against a period of `period_ns`.
    pub fn lateness(&self, period_ns: u64) -> Lateness {
        if self.cpu_ns > period_ns {
            Lateness::Overrun
        } else if self.wall_ns > period_ns {
            Lateness::Preempted
        } else {
            Lateness::OnTime
        }
    }
}

/// One recorded step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepRecord {
    /// What it cost.
    pub cost: StepCost,
    /// The trial state before the step.
    pub before: TrialState,
    /// The trial state after the step.
    pub after: TrialState,
}

const EMPTY_RECORD: StepRecord = StepRecord {
    cost: StepCost {
        wall_ns: 0,
        cpu_ns: 0,
    },
    before: TrialState::Idle,
    after: TrialState::Idle,
};

/// A fixed-capacity record of step costs (for benches): allocated and touched
/// up front, so recording a step neither allocates nor faults a page in.
#[derive(Debug, Clone)]
pub struct StepTimings {
    buf: Vec<StepRecord>,
    len: usize,
    dropped: u64,
}

impl StepTimings {
    /// Room for `capacity` steps, every slot written once now.
    pub fn with_capacity(capacity: usize) -> Self {
        // `vec![x; n]` writes every element (x is not zero bits), so the pages
        // are resident before the first step is recorded.
        Self {
            buf: vec![EMPTY_RECORD; capacity],
            len: 0,
            dropped: 0,
        }
    }

    /// Records one step; counts it as dropped when full.
    pub fn record(&mut self, r: StepRecord) {
        if let Some(slot) = self.buf.get_mut(self.len) {
            *slot = r;
            self.len += 1;
        } else {
            self.dropped += 1;
        }
    }

    /// The recorded steps, oldest first.
    pub fn records(&self) -> &[StepRecord] {
        &self.buf[..self.len]
    }

    /// Steps not recorded because the buffer was full.
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    /// Forgets the records (keeps the buffer).
    pub fn clear(&mut self) {
        self.len = 0;
        self.dropped = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn a_step_is_a_miss_only_when_its_own_computation_overran() {
        let ms = 1_000_000;
        let c = |wall_ns, cpu_ns| StepCost { wall_ns, cpu_ns };
        assert_eq!(c(200_000, 190_000).lateness(ms), Lateness::OnTime);
        assert_eq!(c(4 * ms, 2_000).lateness(ms), Lateness::Preempted);
        assert_eq!(c(3 * ms, 2 * ms).lateness(ms), Lateness::Overrun);
        assert_eq!(c(ms, ms).lateness(ms), Lateness::OnTime);
    }

    #[test]
    fn thread_cpu_time_counts_work_and_not_sleep() {
        // Sleeping: the wall clock advances, this thread's CPU time hardly.
        let clock = StepClock::start();
        std::thread::sleep(Duration::from_millis(30));
        let slept = clock.stop();
        assert!(slept.wall_ns >= 30_000_000, "{slept:?}");
        assert!(slept.cpu_ns < 10_000_000, "{slept:?}");
        assert_eq!(slept.lateness(20_000_000), Lateness::Preempted);
        // Spinning: CPU time advances (at least a little; the machine is shared).
        let clock = StepClock::start();
        let until = Instant::now() + Duration::from_millis(30);
        let mut x = 0u64;
        while Instant::now() < until {
            x = std::hint::black_box(x.wrapping_add(1));
        }
        let spun = clock.stop();
        assert!(spun.cpu_ns > 1_000_000, "{spun:?}");
        assert!(spun.cpu_ns <= spun.wall_ns + 1_000_000, "{spun:?}");
        // By wall clock only (no CPU-time read): the same sleep is a miss,
        // a short step on time.
        let clock = StepClock::start_wall();
        std::thread::sleep(Duration::from_millis(30));
        let slept = clock.stop();
        assert_eq!(slept.cpu_ns, slept.wall_ns);
        assert_eq!(slept.lateness(20_000_000), Lateness::Overrun);
        let quick = StepClock::start_wall().stop();
        assert_eq!(quick.lateness(20_000_000), Lateness::OnTime);
    }

    #[test]
    fn timings_keep_their_capacity_and_count_what_did_not_fit() {
        let mut t = StepTimings::with_capacity(3);
        let cap = t.buf.capacity();
        for i in 0..5u64 {
            t.record(StepRecord {
                cost: StepCost {
                    wall_ns: i,
                    cpu_ns: i,
                },
                before: TrialState::Tracking,
                after: TrialState::Tracking,
            });
        }
        assert_eq!(t.records().len(), 3);
        assert_eq!(t.records()[2].cost.wall_ns, 2);
        assert_eq!(t.dropped(), 2);
        assert_eq!(t.buf.capacity(), cap);
        t.clear();
        assert!(t.records().is_empty());
    }
}
