/**
 * The executed path speed is the measured tool path differentiated at the
 * state stream's rate (100 Hz): its noise is the difference of two noisy
 * positions 10 ms apart. The plots show it through a centered moving average
 * (no lag: each point is the mean of the samples `half` before and after it;
 * near the window's newest end the window shrinks to what has arrived), with
 * the raw samples on request.
 */

/** Samples on each side of the centered moving average (±4: 9 samples, 90 ms at 100 Hz). */
export const SMOOTH_HALF = 4;

/**
 * Centered moving average of `src` over `2 half + 1` samples into `out`
 * (resized, reused): gaps (null or non-finite) are skipped and stay gaps.
 */
export function centeredMovingAverage(
  src: ArrayLike<number | null>,
  half: number,
  out: (number | null)[] = [],
): (number | null)[] {
  const n = src.length;
  out.length = n;
  let sum = 0;
  let count = 0;
  const val = (i: number): number | null => {
    const v = src[i];
    return typeof v === "number" && Number.isFinite(v) ? v : null;
  };
  // Running sum over [i - half, i + half].
  for (let k = 0; k < Math.min(half, n); k++) {
    const v = val(k);
    if (v !== null) {
      sum += v;
      count += 1;
    }
  }
  for (let i = 0; i < n; i++) {
    const add = i + half;
    if (add < n) {
      const v = val(add);
      if (v !== null) {
        sum += v;
        count += 1;
      }
    }
    const drop = i - half - 1;
    if (drop >= 0) {
      const v = val(drop);
      if (v !== null) {
        sum -= v;
        count -= 1;
      }
    }
    out[i] = val(i) === null || count === 0 ? null : sum / count;
  }
  return out;
}
