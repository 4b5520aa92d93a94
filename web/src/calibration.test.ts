import { describe, expect, it } from "vitest";
import { headline } from "./calibration";

describe("calibration headline", () => {
  it("reads the step's figures from its result, with units", () => {
    expect(headline("pendulum", { swing: { length_m: 1.95123, length_std_m: 0.0002, damping_per_s: 0.0312 } })).toBe(
      "length 1.9512 m ± 0.20 mm, damping 0.0312 /s",
    );
    expect(headline("robot", { latency_ms: 8.3, servo_time_constant_ms: 4.78, bandwidth_hz: 33.3 })).toBe(
      "latency 8.30 ms, servo lag 4.78 ms (33.3 Hz)",
    );
  });
  it("reads the camera step's nested intrinsics", () => {
    expect(headline("camera", { intrinsics: { fx_px: 915.23, k1: 0.00935 }, rms_px: 0.0976 })).toBe("fx 915.2 px, k1 0.0094, RMS 0.098 px");
  });
  it("shows a dash for a missing or non-finite figure, nothing without a result", () => {
    expect(headline("latency", { latency_ms: null, bound_ms: 1, spread_ms: Number.NaN })).toBe("– ± 1.00 ms, spread –");
    expect(headline("latency", null)).toBe("");
    expect(headline("unknown-step", { a: 1 })).toBe("");
  });
});
