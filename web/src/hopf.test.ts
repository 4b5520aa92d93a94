import { describe, expect, it } from "vitest";
import { leads, PhaseTrail } from "./hopf";
import type { HopfView } from "./types";

const view = (active: boolean, a: number, b: number): HopfView => ({ active, a, b, u_init: 0, u_hopf: 0, u_final: 0 });

describe("phase trail", () => {
  it("keeps exactly the last motion's arc, from rest round the limit cycle and back", () => {
    const t = new PhaseTrail(100);
    const rh = 0.15;
    expect(t.push(view(false, 0, 0))).toBe(false); // at rest: nothing to draw
    for (let k = 0; k <= 40; k++) {
      const w = (2 * Math.PI * k) / 40;
      t.push(view(true, rh * (1 - Math.cos(w)), -rh * Math.sin(w)));
    }
    expect(t.push(view(false, 0, 0))).toBe(true); // the arrival closes it
    expect(t.push(view(false, 0, 0))).toBe(false); // then the trail is kept as it is
    const s = t.stats();
    expect(s.points).toBe(42);
    expect(s.max_a).toBeCloseTo(2 * rh, 9);
    expect(s.min_b).toBeCloseTo(-rh, 9);
    expect(s.max_b).toBeCloseTo(rh, 9);
    expect(t.motions).toBe(1);
    // The next motion starts afresh.
    t.push(view(true, 0.01, -0.01));
    expect(t.length).toBe(1);
    expect(t.motions).toBe(2);
  });
  it("skips missing values and never grows past its capacity", () => {
    const t = new PhaseTrail(4);
    t.push(view(true, Number.NaN, 0));
    expect(t.length).toBe(0);
    for (let k = 0; k < 10; k++) t.push(view(true, k, 0));
    expect(t.length).toBe(4);
    expect(Array.from(t.a.subarray(0, 4))).toEqual([6, 7, 8, 9]);
  });
});

describe("neuron leads", () => {
  it("merges the samples into init -> hopf -> final with their times", () => {
    const t = [0, 1, 2, 3, 4, 5];
    const ui = [1, 1, 0.01, 0.01, 0.01, 0.01];
    const uh = [0, 0, 1, 1, 0.01, 0.01];
    const uf = [0, 0, 0.01, 0.01, 1, 1];
    const l = leads([t, ui, uh, uf]);
    expect(l.map((x) => x.neuron)).toEqual(["init", "hopf", "final"]);
    expect(l[1]).toEqual({ neuron: "hopf", t0_s: 2, t1_s: 3 });
  });
  it("skips samples with a missing value", () => {
    expect(leads([[0, 1], [1, Number.NaN], [0, 1], [0, 0]]).map((x) => x.neuron)).toEqual(["init"]);
  });
});
