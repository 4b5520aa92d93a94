import { describe, expect, it } from "vitest";
import { SeriesWindow } from "./series";
import { fmt, pct, wilson } from "./stats";
import { parseCsv } from "./trials";
import { num, parseMessage, trialStateText } from "./types";
import { trialList } from "./api";

describe("series window", () => {
  it("keeps the newest rows in order and never grows", () => {
    const w = new SeriesWindow(2, 3);
    for (let i = 0; i < 5; i++) w.push([i, 10 * i]);
    expect(w.length).toBe(3);
    expect(Array.from(w.data()[0])).toEqual([2, 3, 4]);
    expect(Array.from(w.data()[1])).toEqual([20, 30, 40]);
    expect(w.lastX()).toBe(4);
    w.clear();
    expect(w.length).toBe(0);
    expect(Number.isNaN(w.lastX())).toBe(true);
  });
  it("gives uPlot nulls for gaps", () => {
    const w = new SeriesWindow(2, 4);
    w.push([0, 1]);
    w.push([1, Number.NaN]);
    expect(w.plotData()).toEqual([[0, 1], [1, null]]);
  });
  it("refuses rows of the wrong width", () => {
    const w = new SeriesWindow(2, 3);
    expect(() => w.push([1])).toThrow();
    expect(w.length).toBe(0);
  });
});

describe("statistics", () => {
  it("gives the Wilson interval", () => {
    const [lo, hi] = wilson(298, 300);
    expect(lo).toBeCloseTo(0.976, 3);
    expect(hi).toBeCloseTo(0.9982, 3);
    const [l0, h0] = wilson(0, 10);
    expect(l0).toBe(0);
    expect(h0).toBeCloseTo(0.2775, 3);
    expect(wilson(1, 0).every(Number.isNaN)).toBe(true);
  });
  it("formats missing values as a dash", () => {
    expect(fmt(null, 1)).toBe("–");
    expect(fmt(Number.NaN, 1)).toBe("–");
    expect(fmt(1.234, 1, "ms")).toBe("1.2 ms");
    expect(pct(0.9933)).toBe("99.3%");
  });
});

describe("messages", () => {
  const state = {
    type: "state",
    t_s: 1.5,
    pendulum: { horizon: [] },
    hopf: {},
    path: {},
    robot: { q_rad: [0, 0, 0, 0, 0, 0, 0] },
    fri: {},
    timing: {},
  };
  it("accepts state, event and hello messages", () => {
    expect(parseMessage(JSON.stringify(state))?.type).toBe("state");
    expect(parseMessage('{"type":"event","t_s":1,"trial_id":2,"event":{"kind":"aborted"}}')?.type).toBe("event");
    expect(parseMessage('{"type":"hello","t_s":0,"version":"x","state_hz":100,"token_required":true}')?.type).toBe("hello");
  });
  it("refuses garbage", () => {
    expect(parseMessage("not json")).toBeNull();
    expect(parseMessage("[]")).toBeNull();
    expect(parseMessage('{"type":"state","t_s":1}')).toBeNull();
    expect(parseMessage(JSON.stringify({ ...state, robot: { q_rad: [1, 2] } }))).toBeNull();
    expect(parseMessage('{"type":"mystery","t_s":1}')).toBeNull();
  });
  it("reads null as NaN", () => {
    expect(Number.isNaN(num(null))).toBe(true);
    expect(num(2)).toBe(2);
  });
});

describe("trials", () => {
  it("parses numeric CSV", () => {
    const { header, cols } = parseCsv("t_s,speed_planned_mps\n0,0\n0.005,0.01\n");
    expect(header).toEqual(["t_s", "speed_planned_mps"]);
    expect(cols[1]).toEqual([0, 0.01]);
  });
  it("reads the trial list in either shape", () => {
    expect(trialList([{ id: 1 }]).length).toBe(1);
    expect(trialList({ trials: [{ id: 1 }, { id: 2 }] }).length).toBe(2);
    expect(trialList("x")).toEqual([]);
  });
});

import { verdict } from "./api";
describe("trial verdicts", () => {
  it("counts only finished trials, aborted as a miss", () => {
    expect(verdict({ id: 1, status: "running", success: false })).toBeNull();
    expect(verdict({ id: 1, status: "interrupted" })).toBeNull();
    expect(verdict({ id: 1, status: "aborted", success: false })).toBe("miss");
    expect(verdict({ id: 1, status: "done", success: true })).toBe("hit");
    expect(verdict({ id: 1, status: "done", success: false })).toBe("miss");
    expect(verdict({ id: 1, status: "done", success: null, reason: "not judged: real lab" })).toBeNull();
  });
  it("shows why a trial was aborted, not only that it was", () => {
    const abort = { trial_id: 3, reason: "fri_lost", message: "the FRI link to the robot was lost", detail: "the robot controller fell silent (no FRI message)" };
    expect(trialStateText({ trial_state: "aborted", abort })).toBe(
      "aborted: fri_lost (the FRI link to the robot was lost: the robot controller fell silent (no FRI message))",
    );
    expect(trialStateText({ trial_state: "aborted", abort: { ...abort, detail: "" } })).toBe("aborted: fri_lost (the FRI link to the robot was lost)");
    expect(trialStateText({ trial_state: "idle", abort })).toBe("idle");
    expect(trialStateText({ trial_state: "aborted" })).toBe("aborted");
  });
});

import { judgeCells, signed, strikeCell, strikeLines, type TrialRecord } from "./api";
describe("trial judges", () => {
  const m = {
    pass_t_s: 10,
    arrival_t_s: 9.9988,
    timing_error_ms: -1.24,
    timing_std_ms: 0.83,
    contact: true,
    contact_t_s: 10.004,
    success: true,
    torque_signal: true,
  };
  it("shows the measured timing signed with its std and the contact", () => {
    expect(judgeCells({ judged_by: "measured", measured: m })).toEqual({ judge: "measured", measuredTiming: "-1.2 ± 0.8", contact: "yes" });
    expect(judgeCells({ judged_by: "truth", measured: { ...m, timing_error_ms: 3.06, contact: false } })).toEqual({
      judge: "truth",
      measuredTiming: "+3.1 ± 0.8",
      contact: "no",
    });
  });
  it("says when the torques carried no signal and when nothing was measured", () => {
    expect(judgeCells({ judged_by: null, measured: { ...m, contact: false, torque_signal: false } }).contact).toBe("no torques");
    expect(judgeCells({ judged_by: null, measured: { ...m, timing_error_ms: null, timing_std_ms: null } }).measuredTiming).toBe("–");
    expect(judgeCells({ judged_by: null, measured: null })).toEqual({ judge: "–", measuredTiming: "–", contact: "–" });
  });
  it("shows a strike's speeds at contact and none for a stop", () => {
    const strike = {
      planned_tool_speed_mps: 0.5,
      tool_speed_mps: 0.493,
      target_ball_speed_mps: 0.47,
      ball_speed_mps: 0.511,
      ball_speed_std_mps: 0.006,
      speed_error: 0.0876,
      returned: true,
      rebound_used: 10,
      in_time: true,
      speed_ok: true,
    };
    expect(strikeCell({ measured: { ...m, strike } })).toBe("tool 0.50 → 0.49, ball 0.51 (+9%)");
    expect(strikeCell({ measured: { ...m, strike: { ...strike, returned: false } } })).toBe("tool 0.50 → 0.49, ball 0.51 not returned");
    expect(strikeCell({ measured: { ...m, strike: { ...strike, tool_speed_mps: null, ball_speed_mps: null, speed_error: null } } })).toBe("tool 0.50 → –, ball –");
    expect(strikeCell({ measured: m })).toBe("–");
    expect(strikeCell({ measured: null })).toBe("–");
  });
  it("shows a strike's predicted rebound beside the seen one", () => {
    const predicted = {
      restitution: 0,
      tool_return_speed_mps: 0.47,
      ball_in_speed_mps: 1.88,
      ball_speed_mps: 0.47,
      omega_radps: 2.25,
      damping_per_s: 0.03,
      amplitude_m: 0.207,
      turn_s: 0.69,
    };
    const strike = {
      planned_tool_speed_mps: 0.5,
      tool_speed_mps: 0.493,
      target_ball_speed_mps: 0.47,
      ball_speed_mps: 0.511,
      ball_speed_std_mps: 0.006,
      speed_error: 0.0876,
      returned: true,
      rebound_used: 10,
      in_time: true,
      speed_ok: true,
      predicted,
    };
    expect(strikeCell({ measured: { ...m, strike } })).toBe("tool 0.50 → 0.49, ball 0.47 → 0.51 (+9%)");
    expect(strikeCell({ measured: { ...m, strike: { ...strike, returned: false } } })).toBe("tool 0.50 → 0.49, ball 0.47 → 0.51 not returned");
    expect(strikeCell({ measured: { ...m, strike: { ...strike, ball_speed_mps: null, speed_error: null } } })).toBe("tool 0.50 → 0.49, ball 0.47 → –");
    const rec = (id: number, status: string, s: typeof strike | undefined, success: boolean | null) =>
      ({ id, status, success, measured: s ? { ...m, strike: s } : m }) as unknown as TrialRecord;
    const lines = strikeLines([rec(9, "running", strike, null), rec(8, "done", strike, true), rec(7, "done", undefined, true), rec(6, "done", strike, false), rec(5, "done", strike, true)], 2);
    expect(lines).toEqual([
      { id: 8, hit: true, text: "tool 0.50 → 0.49, ball 0.47 → 0.51 (+9%)" },
      { id: 6, hit: false, text: "tool 0.50 → 0.49, ball 0.47 → 0.51 (+9%)" },
    ]);
  });
  it("never writes -0", () => {
    expect(signed(-0.04, 1)).toBe("0.0");
    expect(signed(0.04, 1)).toBe("0.0");
    expect(signed(-0.06, 1)).toBe("-0.1");
  });
});
