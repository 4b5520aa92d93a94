//! Lock-free counters and latency histograms shared between a real-time thread
//! (the only writer) and any number of readers.

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

use serde::Serialize;

/// Sub-buckets per power of two (relative resolution 2^(1/4) - 1, about 19%).
const SUB: usize = 4;
/// Powers of two covered: 1 ns .. 2^40 ns (about 18 minutes).
const OCTAVES: usize = 40;
const BUCKETS: usize = SUB * OCTAVES + 1;

/// A log-scale histogram of durations in nanoseconds, recorded and read without
/// locks or allocation. Quantiles are reported as the upper edge of their bucket
/// (at most ~19% above the true value); the maximum is exact.
#[derive(Debug)]
pub struct LatencyHistogram {
    buckets: [AtomicU64; BUCKETS],
    count: AtomicU64,
    max_ns: AtomicU64,
}

impl Default for LatencyHistogram {
    fn default() -> Self {
        Self::new()
    }
}

/// Percentiles of a [`LatencyHistogram`], microseconds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Default)]
pub struct LatencySummary {
    /// Samples recorded.
    pub count: u64,
    /// Median, us.
    pub p50: f64,
    /// 99th percentile, us.
    pub p99: f64,
    /// 99.9th percentile, us.
    pub p999: f64,
    /// Largest sample, us.
    pub max: f64,
}

fn bucket_of(ns: u64) -> usize {
    if ns < 2 {
        return ns as usize;
    }
    let octave = 63 - ns.leading_zeros() as usize; // floor(log2)
    let frac = if octave >= 2 {
        ((ns >> (octave - 2)) & 3) as usize
    } else {
        ((ns << (2 - octave)) & 3) as usize
    };
    (octave * SUB + frac + 1).min(BUCKETS - 1)
}

fn bucket_upper_ns(b: usize) -> u64 {
    if b < 2 {
        return b as u64;
    }
    let octave = (b - 1) / SUB;
    let frac = ((b - 1) % SUB) as u64;
    // Upper edge: 2^octave * (1 + (frac + 1) / 4).
    let base = 1u64 << octave.min(62);
    base + (base * (frac + 1)) / SUB as u64
}

impl LatencyHistogram {
    /// An empty histogram.
    pub fn new() -> Self {
        Self {
            buckets: std::array::from_fn(|_| AtomicU64::new(0)),
            count: AtomicU64::new(0),
            max_ns: AtomicU64::new(0),
        }
    }

    /// Records one duration.
    pub fn record_ns(&self, ns: u64) {
        self.buckets[bucket_of(ns)].fetch_add(1, Relaxed);
        self.count.fetch_add(1, Relaxed);
        self.max_ns.fetch_max(ns, Relaxed);
    }

    /// Samples recorded.
    pub fn count(&self) -> u64 {
        self.count.load(Relaxed)
    }

    /// The largest sample, ns.
    pub fn max_ns(&self) -> u64 {
        self.max_ns.load(Relaxed)
    }

    /// The `q`-quantile (0..1), ns (upper edge of its bucket, capped at the max);
    /// 0 when empty.
    pub fn quantile_ns(&self, q: f64) -> u64 {
        let total = self.count();
        if total == 0 {
            return 0;
        }
        let rank = ((q.clamp(0.0, 1.0) * total as f64).ceil() as u64).clamp(1, total);
        let mut seen = 0;
        for (b, c) in self.buckets.iter().enumerate() {
            seen += c.load(Relaxed);
            if seen >= rank {
                return bucket_upper_ns(b).min(self.max_ns());
            }
        }
        self.max_ns()
    }

    /// p50/p99/p99.9/max in microseconds.
    pub fn summary_us(&self) -> LatencySummary {
        let us = |ns: u64| ns as f64 / 1e3;
        LatencySummary {
            count: self.count(),
            p50: us(self.quantile_ns(0.5)),
            p99: us(self.quantile_ns(0.99)),
            p999: us(self.quantile_ns(0.999)),
            max: us(self.max_ns()),
        }
    }
}

/// An `f64` readable and writable without locks.
#[derive(Debug, Default)]
pub struct AtomicF64(AtomicU64);

impl AtomicF64 {
    /// A value.
    pub fn new(v: f64) -> Self {
        Self(AtomicU64::new(v.to_bits()))
    }
    /// Reads it.
    pub fn load(&self) -> f64 {
        f64::from_bits(self.0.load(Relaxed))
    }
    /// Writes it.
    pub fn store(&self, v: f64) {
        self.0.store(v.to_bits(), Relaxed);
    }
}

/// Seven `f64`s readable without locks (each value atomic on its own; a reader
/// may see two consecutive updates mixed, which is fine for display).
#[derive(Debug)]
pub struct AtomicJoints([AtomicF64; 7]);

impl Default for AtomicJoints {
    fn default() -> Self {
        Self(std::array::from_fn(|_| AtomicF64::new(f64::NAN)))
    }
}

impl AtomicJoints {
    /// Reads all seven.
    pub fn load(&self) -> [f64; 7] {
        std::array::from_fn(|i| self.0[i].load())
    }
    /// Writes all seven.
    pub fn store(&self, q: &[f64; 7]) {
        for (a, v) in self.0.iter().zip(q) {
            a.store(*v);
        }
    }
}
