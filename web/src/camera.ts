import { Link, wsUrl } from "./connection";
import { num, type CameraInfo, type StateMessage } from "./types";

/**
 * Pixel (in the full camera image) of the ball centre at lateral position
 * `x_m` = l sin(phi) of a pendulum of length `length_m`: the point
 * `rest + x lateral + l (1 - cos phi) up` in the camera frame through the
 * pinhole with radial distortion (rt_core::bridge::CameraView::project_lateral).
 * `null` without a calibration, beyond the string, or behind the camera.
 */
export function projectLateral(c: CameraInfo, x_m: number, length_m: number): [number, number] | null {
  if (!c.width_px || !(length_m > 0) || !(Math.abs(x_m) <= length_m)) return null;
  const lift = length_m - Math.sqrt(length_m * length_m - x_m * x_m);
  const p = [0, 1, 2].map((i) => num(c.rest_c_m[i]) + x_m * num(c.lateral_c[i]) + lift * num(c.up_c[i]));
  if (!(p[2] > 1e-6)) return null;
  const x = p[0] / p[2], y = p[1] / p[2];
  const r2 = x * x + y * y;
  const d = 1 + c.k1 * r2 + c.k2 * r2 * r2;
  const u = c.fx_px * x * d + c.cx_px, v = c.fy_px * y * d + c.cy_px;
  return Number.isFinite(u) && Number.isFinite(v) ? [u, v] : null;
}

/** Frames per second over the arrivals of the last `windowMs`. */
export class RateMeter {
  private readonly times: Float64Array;
  private head = 0;
  private count = 0;

  constructor(capacity = 128, private readonly windowMs = 2000) {
    this.times = new Float64Array(capacity);
  }

  tick(nowMs: number): void {
    this.times[this.head] = nowMs;
    this.head = (this.head + 1) % this.times.length;
    this.count = Math.min(this.count + 1, this.times.length);
  }

  rate(nowMs: number): number {
    let n = 0, oldest = nowMs;
    for (let i = 0; i < this.count; i++) {
      const t = this.times[(this.head - 1 - i + this.times.length) % this.times.length];
      if (nowMs - t > this.windowMs) break;
      n += 1;
      oldest = t;
    }
    if (n < 2) return 0;
    // n arrivals span n - 1 intervals; an idle stream decays through nowMs.
    return (n - 1) / (Math.max(nowMs - oldest, 1) / 1000);
  }
}

/** How much later than its frame a detection may arrive and still be matched to it, ms
 * (frames without the server's tag only). */
const MATCH_MS = 20;
/** How long a tagged frame waits for its own detection before the nearest one is drawn, ms. */
const WAIT_MS = 200;

/**
 * The frame number and capture time (control clock, µs) the service writes into
 * each `/ws/camera` JPEG as a leading COM segment (`isochron frame=N t_us=T`),
 * or null for a JPEG without it.
 */
export function frameTag(bytes: Uint8Array): { frame: number; t_us: number } | null {
  if (bytes.length < 6 || bytes[0] !== 0xff || bytes[1] !== 0xd8 || bytes[2] !== 0xff || bytes[3] !== 0xfe) return null;
  const len = (bytes[4] << 8) | bytes[5];
  if (len < 2 || len > 256 || 4 + len > bytes.length) return null;
  const text = String.fromCharCode(...bytes.subarray(6, 4 + len));
  const m = /^isochron frame=(\d+) t_us=(\d+)$/.exec(text);
  return m ? { frame: Number(m[1]), t_us: Number(m[2]) } : null;
}

/** What the overlay drew last, in the frame's pixels (the browser test reads it). */
export interface OverlayDrawn {
  ball: [number, number, number] | null;
  predicted: number;
  intercept: [number, number] | null;
}

/**
 * The camera view: JPEG frames from `/ws/camera`, decoded off the main thread
 * (`createImageBitmap`; while one decodes only the newest waiting frame is
 * kept), drawn on a canvas; above it an overlay canvas with the detected ball,
 * the predicted positions and the intercept point, placed with the camera
 * calibration the state messages carry.
 */
export class CameraView {
  private readonly image: HTMLCanvasElement;
  private readonly overlay: HTMLCanvasElement;
  private readonly info: HTMLElement | null;
  private readonly host: HTMLElement;
  private readonly link: Link;
  private bitmap: ImageBitmap | null = null;
  private pending: { blob: Blob; at: number; tag: number | null } | null = null;
  private decoding = false;
  private imageDirty = false;
  private overlayDirty = true;
  private latest: StateMessage | null = null;
  /** Recent detections (one per processed camera frame) and when their state arrived. */
  private readonly detections: { at: number; cam: CameraInfo }[] = [];
  /** When the shown frame arrived, and its number (null: the frame carried none). */
  private shownAt = Number.NaN;
  private shownTag: number | null = null;
  private readonly meter = new RateMeter();
  private lastFrameAt = Number.NaN;
  private infoAt = 0;
  /** Pendulum length, metres (from the parameters), for the projection. */
  lengthM = Number.NaN;
  /** Frames received, shown, and refused by the decoder. */
  received = 0;
  frames = 0;
  decodeErrors = 0;
  drawn: OverlayDrawn = { ball: null, predicted: 0, intercept: null };

  constructor(host: HTMLElement) {
    this.host = host;
    this.image = host.querySelector("canvas.frame") as HTMLCanvasElement;
    this.overlay = host.querySelector("canvas.overlay") as HTMLCanvasElement;
    this.info = document.getElementById("camera-info");
    host.classList.add("waiting");
    this.link = new Link(
      wsUrl("/ws/camera"),
      () => {},
      (s) => host.classList.toggle("offline", s !== "open"),
      (data) => this.receive(data),
    );
    this.link.start();
  }

  /** Frames per second shown, over the last two seconds. */
  fps(now = performance.now()): number {
    return this.meter.rate(now);
  }

  private receive(data: ArrayBuffer): void {
    this.received += 1;
    const at = performance.now();
    const tag = frameTag(new Uint8Array(data, 0, Math.min(data.byteLength, 64)))?.frame ?? null;
    const blob = new Blob([data], { type: "image/jpeg" });
    if (this.decoding) {
      this.pending = { blob, at, tag }; // an older waiting frame is dropped
      return;
    }
    this.decode(blob, at, tag);
  }

  private decode(blob: Blob, at: number, tag: number | null): void {
    this.decoding = true;
    createImageBitmap(blob)
      .then((bmp) => {
        this.bitmap?.close();
        this.bitmap = bmp;
        this.shownAt = at;
        this.shownTag = tag;
        this.imageDirty = true;
        this.overlayDirty = true;
        this.frames += 1;
        const now = performance.now();
        this.meter.tick(now);
        this.lastFrameAt = now;
      })
      .catch(() => {
        this.decodeErrors += 1;
      })
      .finally(() => {
        this.decoding = false;
        const next = this.pending;
        this.pending = null;
        if (next) this.decode(next.blob, next.at, next.tag);
      });
  }

  update(s: StateMessage): void {
    this.latest = s;
    // The overlay is redrawn with each new frame (not each state): it belongs to the
    // picture, and repainting a canvas at the state rate costs the page frames.
    const c = s.camera;
    const last = this.detections[this.detections.length - 1];
    if (c && c.width_px && (!last || last.cam.frame !== c.frame)) {
      if (this.detections.length === 32) this.detections.shift();
      this.detections.push({ at: performance.now(), cam: c });
    }
  }

  /**
   * The detection of the shown frame. A tagged frame (the service names each
   * frame's number) takes the detection of that number; `undefined` while it may
   * still arrive (a frame and its detection leave the lab in the same tick but on
   * two sockets), after `WAIT_MS` the nearest number. An untagged frame takes the
   * newest detection that arrived no later than shortly after it.
   */
  private detectionOfShown(now: number): CameraInfo | null | undefined {
    const tag = this.shownTag;
    if (tag !== null) {
      let nearest: CameraInfo | null = null;
      for (const d of this.detections) {
        if (d.cam.frame === tag) return d.cam;
        if (!nearest || Math.abs(d.cam.frame - tag) < Math.abs(nearest.frame - tag)) nearest = d.cam;
      }
      const newest = this.detections[this.detections.length - 1]?.cam.frame ?? -1;
      if (newest < tag && now - this.shownAt < WAIT_MS) return undefined;
      return nearest;
    }
    for (let i = this.detections.length - 1; i >= 0; i--) {
      if (this.detections[i].at <= this.shownAt + MATCH_MS) return this.detections[i].cam;
    }
    // Every kept detection is newer than the frame: the oldest is the nearest.
    return this.detections[0]?.cam ?? null;
  }

  /** Repaints what changed (called once per animation frame). */
  draw(now = performance.now()): void {
    const bmp = this.bitmap;
    if (bmp && this.imageDirty) {
      this.imageDirty = false;
      for (const c of [this.image, this.overlay]) {
        if (c.width !== bmp.width || c.height !== bmp.height) {
          c.width = bmp.width;
          c.height = bmp.height;
        }
      }
      this.image.getContext("2d")?.drawImage(bmp, 0, 0);
      this.host.classList.remove("waiting");
    }
    if (this.overlayDirty && bmp) {
      const d = this.detectionOfShown(now);
      if (d !== undefined) {
        this.overlayDirty = false;
        this.drawOverlay(bmp.width, bmp.height, d);
      }
    }
    if (this.info && now - this.infoAt > 250) {
      this.infoAt = now;
      const age = Math.max(0, now - this.lastFrameAt); // rAF's time is the frame's start
      this.info.textContent = Number.isFinite(age)
        ? `${this.fps(now).toFixed(1)} fps · frame ${this.frames} · ${age < 10_000 ? `${Math.round(age)} ms ago` : "stalled"}`
        : "no frames yet";
    }
  }

  private drawOverlay(w: number, h: number, d: CameraInfo | null): void {
    const ctx = this.overlay.getContext("2d");
    if (!ctx) return;
    ctx.clearRect(0, 0, w, h);
    this.drawn = { ball: null, predicted: 0, intercept: null };
    const s = this.latest;
    const cal = s?.camera;
    if (!s || !cal || !cal.width_px) return;
    const k = w / cal.width_px; // the stream may be downscaled
    const L = this.lengthM;
    ctx.lineWidth = Math.max(2, w / 320);
    // Predicted positions (the filter's horizon), a dashed path with dots.
    const pts: [number, number][] = [];
    for (const p of s.pendulum.horizon) {
      const q = projectLateral(cal, p.x_m, L);
      if (q) pts.push([q[0] * k, q[1] * k]);
    }
    if (pts.length > 0) {
      ctx.strokeStyle = "rgba(86,180,233,0.9)";
      ctx.setLineDash([4, 4]);
      ctx.beginPath();
      pts.forEach(([x, y], i) => (i === 0 ? ctx.moveTo(x, y) : ctx.lineTo(x, y)));
      ctx.stroke();
      ctx.setLineDash([]);
      ctx.fillStyle = "#56B4E9";
      for (const [x, y] of pts) {
        ctx.beginPath();
        ctx.arc(x, y, Math.max(2.5, w / 256), 0, 2 * Math.PI);
        ctx.fill();
      }
    }
    this.drawn.predicted = pts.length;
    // The intercept point: the ball's rest position.
    const ip = projectLateral(cal, 0, L);
    if (ip) {
      const [x, y] = [ip[0] * k, ip[1] * k];
      const r = Math.max(8, w / 60);
      ctx.strokeStyle = "#009E73";
      ctx.beginPath();
      ctx.moveTo(x - r, y);
      ctx.lineTo(x + r, y);
      ctx.moveTo(x, y - r);
      ctx.lineTo(x, y + r);
      ctx.stroke();
      ctx.font = `bold ${Math.max(11, w / 45)}px system-ui, sans-serif`;
      ctx.lineWidth = 3;
      ctx.strokeStyle = "rgba(0,0,0,0.75)";
      ctx.strokeText("intercept", x + r + 3, y + r);
      ctx.fillStyle = "#7fe0c0";
      ctx.fillText("intercept", x + r + 3, y + r);
      ctx.lineWidth = Math.max(2, w / 320);
      this.drawn.intercept = [x, y];
    }
    // The detected ball, as of the shown frame.
    if (d && d.found && Number.isFinite(num(d.x_px)) && Number.isFinite(num(d.y_px))) {
      const [x, y] = [num(d.x_px) * k, num(d.y_px) * k];
      const r = Math.max(5, num(d.r_px) * k + 3);
      ctx.strokeStyle = "#D55E00";
      ctx.beginPath();
      ctx.arc(x, y, r, 0, 2 * Math.PI);
      ctx.stroke();
      this.drawn.ball = [x, y, r];
    }
  }
}
