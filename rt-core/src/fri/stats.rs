//! Lock-free counters and latency histograms shared between a real-time thread
//! (the only writer) and any number of readers.

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

use serde::Serialize;

/// Bits of the sub-bucket index: each power of two is cut into `2^SUB_BITS`
/// equal sub-buckets (the layout of an HDR histogram with 2-3 significant digits).
const SUB_BITS: u32 = 7;
/// Sub-buckets per power of two (128): a bucket is at most 1/128 (0.78%) of its
/// lower edge wide, so its midpoint is within 0.4% of any value in it.
const SUB: usize = 1 << SUB_BITS;
/// Largest power of two covered: 2^40 ns (about 18 minutes); longer samples go
/// to the last bucket (the maximum stays exact).
const MAX_OCTAVE: usize = 40;
/// Values below `SUB` ns have a bucket each; every octave from `SUB_BITS` to
/// `MAX_OCTAVE` has `SUB` buckets.
const BUCKETS: usize = SUB + (MAX_OCTAVE + 1 - SUB_BITS as usize) * SUB;

/// A histogram of durations in nanoseconds with the layout of an HDR histogram
/// (log-linear: 128 linear sub-buckets per power of two), recorded and read
/// without locks or allocation: one writer (a real-time thread), any number of
/// readers. Quantiles are the midpoint of their bucket, capped at the exact
/// maximum: within 0.4% of the true order statistic (exact below 128 ns).
/// (The `hdrhistogram` crate records through `&mut self`; sharing it between the
/// FRI thread and readers would need a lock or its channel-based `SyncHistogram`,
/// which allocates: neither belongs on the real-time thread.)
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
    if ns < SUB as u64 {
        return ns as usize;
    }
    let octave = 63 - ns.leading_zeros() as usize; // floor(log2), >= SUB_BITS
    if octave > MAX_OCTAVE {
        return BUCKETS - 1;
    }
    // The SUB_BITS bits below the leading one.
    let sub = ((ns >> (octave - SUB_BITS as usize)) as usize) & (SUB - 1);
    SUB + (octave - SUB_BITS as usize) * SUB + sub
}

/// The bucket's lower edge and width, ns.
fn bucket_span_ns(b: usize) -> (u64, u64) {
    if b < SUB {
        return (b as u64, 1);
    }
    let octave = (b - SUB) / SUB + SUB_BITS as usize;
    let sub = ((b - SUB) % SUB) as u64;
    let width = 1u64 << (octave - SUB_BITS as usize);
    ((1u64 << octave) + sub * width, width)
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

    /// Adds every sample of `other` (two measurement windows as one).
    pub fn absorb(&self, other: &LatencyHistogram) {
        for (b, o) in self.buckets.iter().zip(&other.buckets) {
            b.fetch_add(o.load(Relaxed), Relaxed);
        }
        self.count.fetch_add(other.count(), Relaxed);
        self.max_ns.fetch_max(other.max_ns(), Relaxed);
    }

    /// A copy of the counts now: the start of a measurement window
    /// ([`Self::since`]).
    pub fn copy(&self) -> Self {
        let h = Self::new();
        h.absorb(self);
        h
    }

    /// The samples recorded since `start` (a [`Self::copy`] of this
    /// histogram): one window of a running measurement, without what came
    /// before it (a session's start-up). Its maximum is the upper edge of
    /// the highest bucket that grew (within 0.8%), capped at the maximum so far.
    pub fn since(&self, start: &Self) -> Self {
        let h = Self::new();
        let (mut total, mut top) = (0, None);
        for (i, ((d, now), then)) in h
            .buckets
            .iter()
            .zip(&self.buckets)
            .zip(&start.buckets)
            .enumerate()
        {
            let n = now.load(Relaxed).saturating_sub(then.load(Relaxed));
            if n > 0 {
                d.store(n, Relaxed);
                total += n;
                top = Some(i);
            }
        }
        h.count.store(total, Relaxed);
        let max = top.map_or(0, |b| {
            let (lo, width) = bucket_span_ns(b);
            (lo + width - 1).min(self.max_ns())
        });
        h.max_ns.store(max, Relaxed);
        h
    }

    /// The largest sample, ns.
    pub fn max_ns(&self) -> u64 {
        self.max_ns.load(Relaxed)
    }

    /// The `q`-quantile (0..1), ns, by the nearest rank `ceil(q n)` (no
    /// samples are kept to interpolate between ranks, unlike
    /// [`crate::quantile::quantile`]): the midpoint of the rank's bucket (exact
    /// below 128 ns), capped at the maximum; 0 when empty.
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
                let (lo, width) = bucket_span_ns(b);
                return (lo + width / 2).min(self.max_ns());
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
