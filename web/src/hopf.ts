/**
 * The timing system as the dashboard shows it: the Hopf oscillator's (a, b)
 * over the last motion, and which of the three neurons leads.
 *
 * `a` is the planned path speed (m/s); the limit cycle is the circle of radius
 * R_h = D / T centred on (R_h, 0), run once from rest (0, 0) through b < 0 and
 * back (rt-core/src/timing/README.md).
 */

import type { HopfView } from "./types";

/** The (a, b) points of the last motion: cleared when a motion starts, kept after it ends. */
export class PhaseTrail {
  readonly capacity: number;
  readonly a: Float64Array;
  readonly b: Float64Array;
  private len = 0;
  private wasActive = false;
  /** Motions seen (a new one clears the trail). */
  motions = 0;

  constructor(capacity = 2000) {
    if (!Number.isInteger(capacity) || capacity < 2) throw new Error("capacity must be >= 2");
    this.capacity = capacity;
    this.a = new Float64Array(capacity);
    this.b = new Float64Array(capacity);
  }

  get length(): number {
    return this.len;
  }

  /** Takes one state's Hopf view; returns true when the trail changed. */
  push(h: HopfView): boolean {
    const active = h.active === true;
    const rising = active && !this.wasActive;
    const falling = !active && this.wasActive;
    this.wasActive = active;
    if (rising) {
      this.len = 0;
      this.motions += 1;
    }
    // While moving, and the first state after (the arrival back at rest).
    if (!active && !falling) return false;
    if (!Number.isFinite(h.a) || !Number.isFinite(h.b)) return rising;
    if (this.len === this.capacity) {
      // A motion longer than the capacity: keep the newest points.
      this.a.copyWithin(0, 1);
      this.b.copyWithin(0, 1);
      this.len -= 1;
    }
    this.a[this.len] = h.a;
    this.b[this.len] = h.b;
    this.len += 1;
    return true;
  }

  clear(): void {
    this.len = 0;
    this.wasActive = false;
  }

  /** Summary for the tests and the label: extremes and the largest |(a, b)|. */
  stats(): {
    points: number;
    max_a: number;
    min_b: number;
    max_b: number;
    max_radius: number;
    first: number[];
    last: number[];
  } {
    let maxA = 0, minB = 0, maxB = 0, maxR = 0;
    for (let i = 0; i < this.len; i++) {
      const a = this.a[i], b = this.b[i];
      maxA = Math.max(maxA, a);
      minB = Math.min(minB, b);
      maxB = Math.max(maxB, b);
      maxR = Math.max(maxR, Math.hypot(a, b));
    }
    const n = this.len;
    return {
      points: n,
      max_a: maxA,
      min_b: minB,
      max_b: maxB,
      max_radius: maxR,
      first: n > 0 ? [this.a[0], this.b[0]] : [],
      last: n > 0 ? [this.a[n - 1], this.b[n - 1]] : [],
    };
  }
}

/** The neurons, in the order of the plot's columns. */
export const NEURONS = ["init", "hopf", "final"] as const;

/** One stretch of time during which one neuron led. */
export interface Lead {
  neuron: (typeof NEURONS)[number];
  t0_s: number;
  t1_s: number;
}

/**
 * Which neuron led when: `cols` are the neuron plot's columns (t, u_init,
 * u_hopf, u_final); consecutive samples with the same leader are merged.
 * Samples with a missing value are skipped.
 */
export function leads(cols: ArrayLike<number>[]): Lead[] {
  const [t, ...u] = cols;
  const out: Lead[] = [];
  for (let k = 0; k < t.length; k++) {
    let best = -1, bestV = -Infinity;
    for (let i = 0; i < NEURONS.length; i++) {
      const v = u[i][k];
      if (!Number.isFinite(v)) {
        best = -1;
        break;
      }
      if (v > bestV) {
        bestV = v;
        best = i;
      }
    }
    if (best < 0) continue;
    const last = out[out.length - 1];
    if (last && last.neuron === NEURONS[best]) last.t1_s = t[k];
    else out.push({ neuron: NEURONS[best], t0_s: t[k], t1_s: t[k] });
  }
  return out;
}
