import { describe, expect, it } from "vitest";
import { frameTag, projectLateral, RateMeter } from "./camera";
import type { CameraInfo } from "./types";

// A camera 2 m in front of the rest position, looking along base +x: the image's
// right is base -y, its down is base -z (rt-core's vision calibration conventions).
const cam: CameraInfo = {
  width_px: 1280, height_px: 720, frame: 1, t_s: 0, found: false,
  lost: false, rejected: 0, x_px: null, y_px: null, r_px: null,
  fx_px: 1000, fy_px: 1000, cx_px: 640, cy_px: 360, k1: 0, k2: 0,
  rest_c_m: [0, 0, 2], lateral_c: [-1, 0, 0], up_c: [0, -1, 0],
};

describe("camera projection", () => {
  it("puts the rest position at the principal point and a swung ball left of and above it", () => {
    expect(projectLateral(cam, 0, 1)).toEqual([640, 360]);
    // x = 0.5 m on a 1 m pendulum: lifted by 1 - cos(30 deg) = 0.134 m.
    const [u, v] = projectLateral(cam, 0.5, 1) as [number, number];
    expect(u).toBeCloseTo(640 - 1000 * 0.25, 9);
    expect(v).toBeCloseTo(360 - 1000 * (1 - Math.sqrt(0.75)) / 2, 9);
  });
  it("applies the radial distortion as OpenCV does", () => {
    const d = { ...cam, k1: -0.1, k2: 0.01 };
    const [u] = projectLateral(d, 0.5, 1) as [number, number];
    const x = -0.25, y = -(1 - Math.sqrt(0.75)) / 2, r2 = x * x + y * y;
    expect(u).toBeCloseTo(640 + 1000 * x * (1 - 0.1 * r2 + 0.01 * r2 * r2), 9);
  });
  it("refuses what it cannot place", () => {
    expect(projectLateral({ ...cam, width_px: 0 }, 0, 1)).toBeNull();
    expect(projectLateral(cam, 1.5, 1)).toBeNull();
    expect(projectLateral(cam, 0, Number.NaN)).toBeNull();
    expect(projectLateral({ ...cam, rest_c_m: [0, 0, -2] }, 0, 1)).toBeNull();
    expect(projectLateral({ ...cam, rest_c_m: [null, 0, 2] }, 0, 1)).toBeNull();
  });
});

describe("rate meter", () => {
  it("measures the arrival rate and decays when the stream stops", () => {
    const m = new RateMeter(64, 2000);
    for (let i = 0; i <= 24; i++) m.tick(1000 + i * 83.3);
    const end = 1000 + 24 * 83.3;
    expect(m.rate(end)).toBeCloseTo(12, 0);
    expect(m.rate(end + 5000)).toBe(0);
    expect(new RateMeter().rate(0)).toBe(0);
  });
});

describe("frame tag", () => {
  const tagged = (text: string, rest = [0xff, 0xdb, 0x00, 0x43]): Uint8Array => {
    const t = [...text].map((c) => c.charCodeAt(0));
    const len = t.length + 2;
    return Uint8Array.from([0xff, 0xd8, 0xff, 0xfe, len >> 8, len & 0xff, ...t, ...rest]);
  };
  it("reads the frame number and capture time the service writes", () => {
    expect(frameTag(tagged("isochron frame=1234 t_us=98765432"))).toEqual({ frame: 1234, t_us: 98765432 });
  });
  it("returns null for a JPEG without it, another comment, or a length past the bytes", () => {
    expect(frameTag(Uint8Array.from([0xff, 0xd8, 0xff, 0xdb, 0x00, 0x43]))).toBeNull();
    expect(frameTag(tagged("made by a camera"))).toBeNull();
    const cut = tagged("isochron frame=1 t_us=2").subarray(0, 12);
    expect(frameTag(cut)).toBeNull();
    expect(frameTag(new Uint8Array(0))).toBeNull();
  });
});
