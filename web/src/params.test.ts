import { describe, expect, it } from "vitest";
import { paramSchema, unitOf } from "./controls";

describe("the Parameters panel's units and schema", () => {
  it("reads the unit from the key's suffix", () => {
    expect(unitOf("length_m")).toBe("m");
    expect(unitOf("latency_ms")).toBe("ms");
    expect(unitOf("speed_mps")).toBe("m/s");
    expect(unitOf("gravity_mps2")).toBe("m/s²");
    expect(unitOf("damping_per_s")).toBe("1/s");
    expect(unitOf("release_angle_deg")).toBe("deg");
    expect(unitOf("width_px")).toBe("px");
    expect(unitOf("fps")).toBe("frames/s");
    expect(unitOf("vision")).toBe("");
  });
  it("takes each section.key's description and default from PUT /api/params' schema", () => {
    const doc = {
      paths: {
        "/api/params": {
          put: {
            requestBody: {
              content: {
                "application/json": {
                  schema: {
                    properties: {
                      pendulum: {
                        description: "The pendulum.",
                        properties: { length_m: { description: "Pivot to ball centre, metres.", default: 1.93, type: "number" } },
                      },
                    },
                  },
                },
              },
            },
          },
        },
      },
    };
    const s = paramSchema(doc);
    expect(s["pendulum.length_m"]).toEqual({ description: "Pivot to ball centre, metres.", default: 1.93 });
    expect(s.pendulum.description).toBe("The pendulum.");
    expect(paramSchema({})).toEqual({});
  });
});
