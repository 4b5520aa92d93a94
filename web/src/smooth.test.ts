import { describe, expect, it } from "vitest";
import { centeredMovingAverage } from "./smooth";

describe("centeredMovingAverage", () => {
  it("keeps a constant and a straight line (no lag in the middle)", () => {
    expect(centeredMovingAverage([2, 2, 2, 2, 2], 2)).toEqual([2, 2, 2, 2, 2]);
    const line = [0, 1, 2, 3, 4, 5, 6, 7, 8];
    const out = centeredMovingAverage(line, 2);
    for (let i = 2; i < 7; i++) expect(out[i]).toBeCloseTo(line[i], 12);
  });
  it("takes out alternating noise", () => {
    const noisy = Array.from({ length: 40 }, (_, i) => 1 + (i % 2 === 0 ? 0.5 : -0.5));
    const out = centeredMovingAverage(noisy, 4);
    for (let i = 4; i < 36; i++) expect(Math.abs((out[i] as number) - 1)).toBeLessThanOrEqual(0.5 / 9 + 1e-12);
  });
  it("skips gaps and keeps them as gaps", () => {
    const out = centeredMovingAverage([1, null, 3, Number.NaN, 5], 1);
    expect(out).toEqual([1, null, 3, null, 5]);
  });
  it("reuses its output array", () => {
    const out: (number | null)[] = [9, 9, 9, 9, 9, 9];
    expect(centeredMovingAverage([1, 1], 3, out)).toBe(out);
    expect(out).toEqual([1, 1]);
  });
});
