//! Camera latency by light: an LED in view is switched at known times; the
//! first frame that shows each switch bounds the capture -> delivery latency.

use serde::{Deserialize, Serialize};

use super::CalibrationError;

/// One frame's LED reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LedFrame {
    /// When the frame reached the host, seconds (host clock).
    pub t_delivered_s: f64,
    /// Mean brightness of the LED's region, any unit (0..255 for 8-bit images).
    pub brightness: f64,
}

/// One commanded LED switch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LedEdge {
    /// When the host wrote the command, seconds (host clock).
    pub t_sent_s: f64,
    /// Command -> firmware echo round trip, seconds (the firmware switches the pin
    /// before it answers).
    pub round_trip_s: f64,
    /// Time the command's bytes take on the wire (bytes x 10 bits / baud), seconds.
    pub command_wire_s: f64,
    /// Time the answer's bytes take on the wire, seconds.
    pub answer_wire_s: f64,
    /// The state commanded.
    pub on: bool,
}

/// The estimated camera latency.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LedLatency {
    /// Mean capture (middle of the exposure) -> delivery latency, milliseconds.
    pub latency_ms: f64,
    /// Half the width of the interval every consistent switch allows, milliseconds
    /// (the estimate's resolution).
    pub bound_ms: f64,
    /// Standard deviation of the delivery times around the frame grid, milliseconds
    /// (the latency's spread from frame to frame).
    pub spread_ms: f64,
    /// Mean delay from sending a switch to the pin switching, milliseconds: the
    /// command's wire time plus half of what the round trip leaves after both wire
    /// times (the USB and firmware latencies, taken as equal both ways).
    pub serial_one_way_ms: f64,
    /// Frame period measured from the delivery times, milliseconds.
    pub frame_period_ms: f64,
    /// Switches commanded.
    pub edges: usize,
    /// Switches seen by the camera (a clean old-state frame followed by a new-state frame).
    pub edges_seen: usize,
    /// Switches consistent with the estimate.
    pub edges_consistent: usize,
    /// Frames read.
    pub frames: usize,
}

/// Sending a switch -> the pin switching: the command's wire time plus half of
/// the round trip's remainder after both wire times (never negative).
pub fn switch_delay_s(e: &LedEdge) -> f64 {
    let (early, late) = switch_window_s(e);
    0.5 * (early + late)
}

/// The earliest and latest the pin can have switched after sending, seconds:
/// once the command's bytes were on the wire, and before the answer's bytes
/// started back (the firmware switches before it answers). A round trip the
/// host read late (a loaded machine, a slow USB frame) widens the window and
/// leaves its middle uncertain; the window itself still holds the switch.
pub fn switch_window_s(e: &LedEdge) -> (f64, f64) {
    let early = e.command_wire_s.min(e.round_trip_s);
    let late = (e.round_trip_s - e.answer_wire_s).max(early);
    (early, late)
}

/// When to send `n` switches: the frame grid ([`frame_grid`]) is fitted from `deliveries` (delivery
/// times of frames seen before the first switch, host clock, in order), and switch
/// `i` is sent at a phase `(p_i + u) / n` of a frame period after a grid point, the
/// `p_i` a random permutation of `0..n` and `u` uniform: random phases that cover
/// the period evenly (the latency window then shrinks like `T / n` for certain,
/// not only on average). Switches are 7 or 8 frames apart (> 0.2 s at 30 fps, more
/// than any latency to measure). `uniform()` draws from [0, 1).
pub fn plan_switches(
    deliveries: &[f64],
    frame_period_s: f64,
    n: usize,
    mut uniform: impl FnMut() -> f64,
) -> Vec<f64> {
    let Some(&last) = deliveries.last() else {
        return Vec::new();
    };
    // The grid of the on-time frames (`frame_grid`).
    let g = frame_grid(deliveries, frame_period_s);
    let (a, period) = (g.a_s, g.period_s);
    let mut perm: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        let j = ((uniform() * (i + 1) as f64) as usize).min(i);
        perm.swap(i, j);
    }
    let mut k = ((last - a) / period).ceil() + 4.0;
    perm.iter()
        .map(|&p| {
            k += if uniform() < 0.5 { 7.0 } else { 8.0 };
            a + period * (k + (p as f64 + uniform()) / n as f64)
        })
        .collect()
}

/// The capture slots of frames delivered at `deliveries` (in order, host
/// clock) by a camera with the nominal period `period_s`, on the clock of
/// its on-time frames: frame `i` was captured in slot `slots[i]`, the
/// on-time frames of slot `k` arrive at `a_s + period_s k`, and frame `i`
/// came `lateness_s[i]` after that.
///
/// A frame leaves the camera after its exposure and readout, and a busy
/// host or stream can only add to that: delivery is late by a one-sided,
/// often heavy-tailed amount. Slots rounded from `(t - t_first) / T` go
/// wrong when frames come more than half a period later than the first
/// (and the whole grid slips): a starved webcam stream delivering 12 ms
/// late plus an exponential tail of 20 ms put a latency 18 ms short, with
/// a bound of 0.7 ms. Here the slots come from the densest phase of the
/// deliveries (where the on-time frames gather), each frame in the latest
/// slot that its delivery allows (from a quarter period before that phase)
/// and before the next frame's slot (a frame over three quarters of a
/// period late is followed by on-time ones), and the grid is the
/// least-squares line through the on-time half.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameGrid {
    /// Each frame's capture slot.
    pub slots: Vec<f64>,
    /// The on-time frames' delivery at slot 0, s.
    pub a_s: f64,
    /// The measured frame period, s.
    pub period_s: f64,
    /// How late each frame came after its slot's on-time delivery, s.
    pub lateness_s: Vec<f64>,
}

/// [`FrameGrid`] of `deliveries` (at least one; `period_s` > 0).
pub fn frame_grid(deliveries: &[f64], period_s: f64) -> FrameGrid {
    let n = deliveries.len();
    let Some(&t0) = deliveries.first() else {
        return FrameGrid {
            slots: Vec::new(),
            a_s: 0.0,
            period_s,
            lateness_s: Vec::new(),
        };
    };
    // The densest phase: the start of the window of an eighth of a period
    // holding the most deliveries (modulo the period).
    let phase: Vec<f64> = deliveries
        .iter()
        .map(|t| (t - t0).rem_euclid(period_s))
        .collect();
    let width = period_s / 8.0;
    let mut best = (0usize, 0.0);
    for &p in &phase {
        let count = phase
            .iter()
            .filter(|&&q| (q - p).rem_euclid(period_s) < width)
            .count();
        if count > best.0 {
            best = (count, p);
        }
    }
    // Slots: the latest each delivery allows (up to a quarter period before
    // the phase still counts: on-time frames scatter about it), each before
    // the next frame's.
    let origin = t0 + best.1 - 0.25 * period_s;
    let mut slots: Vec<f64> = deliveries
        .iter()
        .map(|t| ((t - origin) / period_s).floor())
        .collect();
    for i in (0..n.saturating_sub(1)).rev() {
        slots[i] = slots[i].min(slots[i + 1] - 1.0);
    }
    // The grid through the on-time half (twice: the first line is the phase's).
    let (mut a, mut period) = (origin, period_s);
    for _ in 0..2 {
        let mut late: Vec<(f64, usize)> = deliveries
            .iter()
            .zip(&slots)
            .enumerate()
            .map(|(i, (t, k))| (t - (a + period * k), i))
            .collect();
        late.sort_by(|x, y| x.0.total_cmp(&y.0));
        let half: Vec<usize> = late[..n.div_ceil(2)].iter().map(|&(_, i)| i).collect();
        let m = half.len() as f64;
        let mk = half.iter().map(|&i| slots[i]).sum::<f64>() / m;
        let mt = half.iter().map(|&i| deliveries[i]).sum::<f64>() / m;
        let (mut sxy, mut sxx) = (0.0, 0.0);
        for &i in &half {
            sxy += (slots[i] - mk) * (deliveries[i] - mt);
            sxx += (slots[i] - mk) * (slots[i] - mk);
        }
        if sxx > 0.0 {
            period = sxy / sxx;
        }
        a = mt - period * mk;
    }
    let lateness_s = deliveries
        .iter()
        .zip(&slots)
        .map(|(t, k)| t - (a + period * k))
        .collect();
    FrameGrid {
        slots,
        a_s: a,
        period_s: period,
        lateness_s,
    }
}

/// Round trips within this of the fastest of a run are the board's usual ones
/// (USB frames and the firmware's loop vary by about a millisecond): their
/// switch is taken at the middle of its window ([`switch_delay_s`]). A slower
/// one was read late or answered late, and its switch is only known to lie
/// in its window ([`switch_window_s`]).
pub const USUAL_ROUND_TRIP_SPREAD_S: f64 = 0.002;

/// The largest spread of the frames' lateness ([`frame_grid`]) the
/// estimate takes, in frame periods: beyond it frames late by more than
/// three quarters of a period come in runs, their slots are guessed wrong
/// and the latency comes out short (18.9 ms short at a spread of 1.1
/// periods in a synthetic stream; within 0.9 ms up to 0.66).
pub const MAX_SPREAD_PERIODS: f64 = 0.75;

/// Smallest brightness difference between the LED's off and on levels, in the
/// brightness unit (8-bit: 255).
pub const MIN_CONTRAST: f64 = 20.0;

/// Estimates the latency. `frame_period_s` is the nominal frame period (the fps the
/// camera was opened with); frames are in delivery order (lost ones are simply absent).
///
/// # Errors
///
/// [`CalibrationError::NotFinite`] for a non-finite frame or edge (or a negative
/// round trip or wire time); [`CalibrationError::TooFewSamples`] with fewer than
/// 20 frames; [`CalibrationError::FitFailed`] for a bad frame period;
/// [`CalibrationError::LedNotSeen`] when the brightness has too little contrast or
/// fewer than 3 (or half the) switches are seen.
pub fn estimate_led_latency(
    frames: &[LedFrame],
    edges: &[LedEdge],
    frame_period_s: f64,
) -> Result<LedLatency, CalibrationError> {
    const WHAT: &str = "LED latency";
    for (index, f) in frames.iter().enumerate() {
        if !f.t_delivered_s.is_finite() || !f.brightness.is_finite() {
            return Err(CalibrationError::NotFinite { what: WHAT, index });
        }
    }
    for (index, e) in edges.iter().enumerate() {
        let wires = [e.command_wire_s, e.answer_wire_s];
        if !e.t_sent_s.is_finite()
            || !e.round_trip_s.is_finite()
            || e.round_trip_s < 0.0
            || wires.iter().any(|w| !w.is_finite() || *w < 0.0)
        {
            return Err(CalibrationError::NotFinite { what: WHAT, index });
        }
    }
    if frames.len() < 20 {
        return Err(CalibrationError::TooFewSamples {
            what: WHAT,
            got: frames.len(),
            need: 20,
        });
    }
    if !(frame_period_s.is_finite() && frame_period_s > 0.0) {
        return Err(CalibrationError::FitFailed {
            what: WHAT,
            reason: format!("bad frame period {frame_period_s}"),
        });
    }
    // On/off levels: the 5th and 95th percentiles; threshold half way (a frame
    // whose exposure is half lit reads half way: the switch at mid-exposure).
    let mut b: Vec<f64> = frames.iter().map(|f| f.brightness).collect();
    b.sort_by(f64::total_cmp);
    let lo = b[b.len() / 20];
    let hi = b[b.len() - 1 - b.len() / 20];
    if hi - lo < MIN_CONTRAST {
        return Err(CalibrationError::LedNotSeen {
            edges: edges.len(),
            seen: 0,
        });
    }
    let threshold = 0.5 * (lo + hi);
    let lit: Vec<bool> = frames.iter().map(|f| f.brightness > threshold).collect();

    // The frame grid (`frame_grid`): the capture slots on the on-time
    // frames' delivery clock, and how late each frame came on top.
    let deliveries: Vec<f64> = frames.iter().map(|f| f.t_delivered_s).collect();
    let g = frame_grid(&deliveries, frame_period_s);
    let (ks, period, a) = (&g.slots, g.period_s, g.a_s);
    let grid = |k: f64| a + period * k;
    let n = frames.len() as f64;
    let mean_late = g.lateness_s.iter().sum::<f64>() / n;
    let spread = (g
        .lateness_s
        .iter()
        .map(|l| (l - mean_late).powi(2))
        .sum::<f64>()
        / (n - 2.0).max(1.0))
    .sqrt();
    if spread.is_nan() || spread > MAX_SPREAD_PERIODS * period {
        return Err(CalibrationError::IrregularFrames {
            what: "the LED",
            spread_ms: spread * 1e3,
            period_ms: period * 1e3,
            limit_ms: MAX_SPREAD_PERIODS * period * 1e3,
        });
    }

    // Each switch seen: the last frame with the old state and the first with the new
    // one bound the latency L: grid(k_old) - L < t_switch <= grid(k_new) - L, with
    // t_switch the middle of its window after a usual round trip, anywhere in it
    // after a slow one (`USUAL_ROUND_TRIP_SPREAD_S`): a switch whose answer was
    // read late allows more latencies, never a wrong one.
    let fastest = edges
        .iter()
        .map(|e| e.round_trip_s)
        .fold(f64::INFINITY, f64::min);
    let mut intervals = Vec::with_capacity(edges.len());
    let mut one_way_sum = 0.0;
    for e in edges {
        let (mut early, mut late) = switch_window_s(e);
        one_way_sum += 0.5 * (early + late);
        if e.round_trip_s <= fastest + USUAL_ROUND_TRIP_SPREAD_S {
            early = 0.5 * (early + late);
            late = early;
        }
        // Frames delivered after the command was sent (only they can show it).
        let start = frames.partition_point(|f| f.t_delivered_s <= e.t_sent_s);
        let Some(offset) = lit[start..].iter().position(|&l| l == e.on) else {
            continue;
        };
        let i_new = start + offset;
        if i_new == 0 || lit[i_new - 1] == e.on {
            continue;
        }
        let lo_l = grid(ks[i_new - 1]) - (e.t_sent_s + late);
        let hi_l = grid(ks[i_new]) - (e.t_sent_s + early);
        if lo_l < hi_l {
            intervals.push((lo_l, hi_l));
        }
    }
    let seen = intervals.len();

    if seen < 3.max(edges.len() / 2) {
        return Err(CalibrationError::LedNotSeen {
            edges: edges.len(),
            seen,
        });
    }
    // The latency allowed by the most switches: sweep the interval ends.
    let mut events: Vec<(f64, i32)> = intervals
        .iter()
        .flat_map(|&(l, h)| [(l, 1), (h, -1)])
        .collect();
    events.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
    let (mut count, mut best, mut best_lo, mut best_hi) = (0, 0, 0.0, 0.0);
    for (i, &(t, d)) in events.iter().enumerate() {
        count += d;
        if count > best {
            best = count;
            best_lo = t;
            best_hi = events.get(i + 1).map_or(t, |e| e.0);
        }
    }
    // The switches time the on-time frames; the frames came that much
    // later on average.
    let latency = 0.5 * (best_lo + best_hi) + mean_late;
    Ok(LedLatency {
        latency_ms: latency * 1e3,
        bound_ms: (0.5 * (best_hi - best_lo) + spread / n.sqrt()) * 1e3,
        spread_ms: spread * 1e3,
        serial_one_way_ms: one_way_sum / edges.len().max(1) as f64 * 1e3,
        frame_period_ms: period * 1e3,
        edges: edges.len(),
        edges_seen: seen,
        edges_consistent: usize::try_from(best).unwrap_or(0),
        frames: frames.len(),
    })
}
