/** Wilson score interval for a binomial proportion (95% by default). */
export function wilson(successes: number, n: number, z = 1.959964): [number, number] {
  if (!(n > 0) || successes < 0 || successes > n) return [Number.NaN, Number.NaN];
  const p = successes / n;
  const z2 = z * z;
  const denom = 1 + z2 / n;
  const centre = (p + z2 / (2 * n)) / denom;
  const half = (z * Math.sqrt((p * (1 - p)) / n + z2 / (4 * n * n))) / denom;
  return [Math.max(0, centre - half), Math.min(1, centre + half)];
}

/** `0.9933` -> `"99.3%"`. */
export function pct(p: number, digits = 1): string {
  return Number.isFinite(p) ? `${(p * 100).toFixed(digits)}%` : "–";
}

/** A number with a unit, or a dash for missing values. */
export function fmt(v: number | null | undefined, digits: number, unit = ""): string {
  return typeof v === "number" && Number.isFinite(v) ? `${v.toFixed(digits)}${unit ? " " + unit : ""}` : "–";
}
