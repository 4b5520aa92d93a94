import { describe, expect, it } from "vitest";
import { decimalsFor, lengthRange, lengthUnit, speedRange, tickLabels } from "./axes";

describe("length axis", () => {
  it("shows millimetres below 1 m and metres from 1 m", () => {
    expect(lengthUnit(-0.0004, 0.0003).unit).toBe("mm");
    expect(lengthUnit(-0.3, 0.3)).toEqual({ unit: "mm", scale: 1000 });
    expect(lengthUnit(-1.2, 0.3).unit).toBe("m");
  });
  it("labels ticks with the decimals their spacing needs, all distinct, never -0", () => {
    // A ball at rest in a metre axis read "0, -0, -0" before.
    const m = [-0.0004, -0.0002, 0, 0.0002, 0.0004];
    const mm = tickLabels(m.map((v) => v * 1000));
    expect(mm).toEqual(["-0.4", "-0.2", "0.0", "0.2", "0.4"]);
    expect(new Set(mm).size).toBe(mm.length);
    expect(tickLabels([-100, -50, 0, 50])).toEqual(["-100", "-50", "0", "50"]);
    expect(tickLabels([-1e-7, 0])).not.toContain("-0");
    expect(decimalsFor(0.25)).toBe(1);
    expect(decimalsFor(0.05)).toBe(2);
    expect(decimalsFor(5)).toBe(0);
  });
  it("keeps a useful span around a ball at rest", () => {
    const [a, b] = lengthRange(-0.0001, 0.0001);
    expect(b - a).toBeCloseTo(0.01, 12);
    const [c, d] = lengthRange(-0.2, 0.3);
    expect(c).toBeLessThan(-0.2);
    expect(d).toBeGreaterThan(0.3);
  });
});

describe("speed axis", () => {
  it("fits the planned peak and ignores a spike of the executed speed", () => {
    const planned = [0, 0.5, 1.2, 0.5, 0];
    const executed = [0, 0.48, 1.19, 100, 0];
    const [lo, hi] = speedRange(planned, executed);
    expect(lo).toBe(0);
    expect(hi).toBeGreaterThanOrEqual(1.2);
    expect(hi).toBeLessThanOrEqual(1.5 * 1.2 * 1.1 + 1e-9);
  });
  it("recovers once the spike has left the window", () => {
    expect(speedRange([0, 0], [0, 0.02])[1]).toBeCloseTo(0.11, 9);
  });
});
