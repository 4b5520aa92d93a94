/**
 * Axis scales and tick labels that fit the values: lengths in millimetres
 * below 1 m, tick labels with as many decimals as their spacing needs (so
 * neighbours never read the same, and never "-0"), and a speed axis fitted to
 * the planned motion rather than to a single sample.
 */

/** The unit a length axis spanning [min, max] metres is shown in. */
export interface LengthUnit {
  unit: "m" | "mm";
  /** Metres -> shown unit. */
  scale: number;
}

/** Millimetres when every value is below 1 m in size, metres otherwise. */
export function lengthUnit(min: number, max: number): LengthUnit {
  const big = Math.max(Math.abs(min), Math.abs(max));
  return Number.isFinite(big) && big < 1 ? { unit: "mm", scale: 1000 } : { unit: "m", scale: 1 };
}

/** Decimals that tell ticks `step` apart (0 for steps >= 1). */
export function decimalsFor(step: number): number {
  if (!(step > 0) || !Number.isFinite(step)) return 0;
  return Math.min(6, Math.max(0, Math.ceil(-Math.log10(step) - 1e-9)));
}

/** Formats tick values (in the shown unit): fixed decimals from their spacing, no "-0". */
export function tickLabels(ticks: readonly number[]): string[] {
  let step = Number.POSITIVE_INFINITY;
  for (let i = 1; i < ticks.length; i++) {
    const d = Math.abs(ticks[i] - ticks[i - 1]);
    if (d > 0) step = Math.min(step, d);
  }
  const dec = decimalsFor(Number.isFinite(step) ? step : Math.abs(ticks[0] ?? 1) || 1);
  return ticks.map((v) => {
    const s = v.toFixed(dec);
    return /^-0(\.0*)?$/.test(s) ? s.slice(1) : s;
  });
}

/**
 * A length axis' range, metres: the data's, but at least `minSpanM` wide
 * around its middle (a ball at rest moves by fractions of a millimetre).
 */
export function lengthRange(min: number | null, max: number | null, minSpanM = 0.01): [number, number] {
  if (min === null || max === null || !Number.isFinite(min) || !Number.isFinite(max)) return [-minSpanM / 2, minSpanM / 2];
  const mid = (min + max) / 2;
  const half = Math.max((max - min) / 2 * 1.1, minSpanM / 2);
  return [mid - half, mid + half];
}

/**
 * The path-speed axis' range, m/s: from 0 to the larger of the planned peak
 * and the executed peak, where the executed peak counts at most 1.5 times the
 * planned one (a single bad sample does not rescale the plot; it is drawn
 * clipped). Without a planned motion in view, the executed peak up to 3 m/s
 * (beyond what the arm's tool can do) and at least 0.1 m/s.
 */
export function speedRange(planned: ArrayLike<number>, executed: ArrayLike<number>): [number, number] {
  let p = 0;
  let e = 0;
  for (let i = 0; i < planned.length; i++) if (Number.isFinite(planned[i])) p = Math.max(p, planned[i]);
  for (let i = 0; i < executed.length; i++) if (Number.isFinite(executed[i])) e = Math.max(e, executed[i]);
  const cap = p > 0.01 ? 1.5 * p : 3;
  const top = Math.max(p, Math.min(e, cap), 0.1);
  return [0, top * 1.1];
}
