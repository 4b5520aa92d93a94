import { describe, expect, it } from "vitest";
import { describeHealth, parseHealth } from "./health";

describe("health", () => {
  it("accepts the service's answer", () => {
    const h = parseHealth({ status: "ok", version: "0.1.0 (git abc)", uptime_s: 125 });
    expect(h).not.toBeNull();
    expect(describeHealth(h)).toBe("service ok, isochron 0.1.0 (git abc), up 2 min");
  });
  it("refuses malformed answers", () => {
    expect(parseHealth(null)).toBeNull();
    expect(parseHealth({ status: "ok" })).toBeNull();
    expect(parseHealth({ status: "ok", version: "x", uptime_s: "1" })).toBeNull();
    expect(describeHealth(null)).toBe("service unreachable");
  });
});
