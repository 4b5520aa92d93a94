/** The Calibration panel: the steps in the order a lab runs them, each with its
 * prerequisites, its last result and what changed; the running step's live view
 * (board corners, LED brightness, the swing and its fit, marker poses, the
 * excited joint) from `GET /api/calibration`, started with
 * `POST /api/calibration/{step}`. */

import { ApiError, call } from "./api";
import type { CalibrationStatus, StepStatus, StepView } from "./generated/types";

type Notify = (text: string, kind?: "info" | "error") => void;

/** Poll while a step runs, ms (the view is for the eye); idle, rarely. */
const POLL_RUNNING_MS = 250;
const POLL_IDLE_MS = 3000;

/** The camera frame the image views are drawn in, pixels. */
const FRAME_W = 1280;
const FRAME_H = 720;

/** A step's headline figures from its result (what a lab checks first). */
export function headline(name: string, result: Record<string, unknown> | null | undefined): string {
  if (!result) return "";
  const num = (path: string): number | null => {
    let v: unknown = result;
    for (const k of path.split(".")) v = v && typeof v === "object" ? (v as Record<string, unknown>)[k] : undefined;
    return typeof v === "number" && Number.isFinite(v) ? v : null;
  };
  const f = (v: number | null, d: number, unit: string) => (v === null ? "–" : `${v.toFixed(d)}${unit ? ` ${unit}` : ""}`);
  switch (name) {
    case "camera":
      return `fx ${f(num("intrinsics.fx_px"), 1, "px")}, k1 ${f(num("intrinsics.k1"), 4, "")}, RMS ${f(num("rms_px"), 3, "px")}`;
    case "latency":
      return `${f(num("latency_ms"), 2, "ms")} ± ${f(num("bound_ms"), 2, "ms")}, spread ${f(num("spread_ms"), 2, "ms")}`;
    case "pendulum":
      return `length ${f(num("swing.length_m"), 4, "m")} ± ${f((num("swing.length_std_m") ?? NaN) * 1000, 2, "mm")}, damping ${f(num("swing.damping_per_s"), 4, "/s")}`;
    case "camera-robot":
      return `reprojection ${f(num("reprojection_rms_px"), 3, "px")}, ${f(num("poses"), 0, "poses")}`;
    case "robot":
      return `latency ${f(num("latency_ms"), 2, "ms")}, servo lag ${f(num("servo_time_constant_ms"), 2, "ms")} (${f(num("bandwidth_hz"), 1, "Hz")})`;
    case "contact":
      return `contact shown ${f(num("onset_offset_ms"), 1, "ms")} ± ${f(num("onset_offset_std_ms"), 1, "ms")} late (lag ${f(num("torque_lag_periods"), 2, "periods")}, pulse ${f(num("pulse_ms"), 1, "ms")})`;
    default:
      return "";
  }
}

/** Draws a step's view: image points in the camera frame, or a time series
 * with autoscaled axes; the fit as a line (series) or crosses (image). */
export function drawView(canvas: HTMLCanvasElement, view: StepView | null, running = false): void {
  const ctx = canvas.getContext("2d");
  if (!ctx) return;
  const { width: w, height: h } = canvas;
  ctx.clearRect(0, 0, w, h);
  ctx.fillStyle = "#10151c";
  ctx.fillRect(0, 0, w, h);
  if (!view) {
    // Say what the view will show, rather than an empty black box.
    ctx.fillStyle = "#c9d1d9";
    ctx.font = "14px system-ui, sans-serif";
    ctx.textAlign = "center";
    const lines = [
      running ? "The step is measuring: its points appear here." : "No step has run yet.",
      "Run a step: this view then shows what it measures,",
      "the chessboard corners or tool marker in the camera image,",
      "the LED's switch times, the swing and the fitted model, or the knock's torques.",
    ];
    lines.forEach((l, i) => ctx.fillText(l, w / 2, h / 2 - 30 + 22 * i));
    ctx.textAlign = "left";
    return;
  }
  const pad = 24;
  let sx: (x: number) => number;
  let sy: (y: number) => number;
  if (view.kind === "image") {
    const k = Math.min(w / FRAME_W, h / FRAME_H);
    const ox = (w - FRAME_W * k) / 2;
    const oy = (h - FRAME_H * k) / 2;
    ctx.strokeStyle = "#3a4656";
    ctx.strokeRect(ox, oy, FRAME_W * k, FRAME_H * k);
    sx = (x) => ox + x * k;
    sy = (y) => oy + y * k;
  } else {
    const all = [...view.points, ...view.fit];
    if (all.length === 0) return;
    let [x0, x1, y0, y1] = [Infinity, -Infinity, Infinity, -Infinity];
    for (const [x, y] of all) {
      x0 = Math.min(x0, x);
      x1 = Math.max(x1, x);
      y0 = Math.min(y0, y);
      y1 = Math.max(y1, y);
    }
    if (x1 - x0 < 1e-9) x1 = x0 + 1;
    if (y1 - y0 < 1e-12) y1 = y0 + 1e-6;
    sx = (x) => pad + ((x - x0) / (x1 - x0)) * (w - 2 * pad);
    sy = (y) => h - pad - ((y - y0) / (y1 - y0)) * (h - 2 * pad);
    ctx.fillStyle = "#8a97a8";
    ctx.font = "11px sans-serif";
    ctx.fillText(`${x0.toFixed(2)} s`, pad, h - 6);
    ctx.fillText(`${x1.toFixed(2)} s`, w - pad - 40, h - 6);
    ctx.fillText(y1.toPrecision(4), 2, pad - 8);
    ctx.fillText(y0.toPrecision(4), 2, h - pad + 12);
  }
  ctx.fillStyle = "#4fc3f7";
  for (const [x, y] of view.points) ctx.fillRect(sx(x) - 1.5, sy(y) - 1.5, 3, 3);
  ctx.strokeStyle = "#ffb74d";
  ctx.lineWidth = 1.5;
  if (view.kind === "series") {
    ctx.beginPath();
    view.fit.forEach(([x, y], i) => (i === 0 ? ctx.moveTo(sx(x), sy(y)) : ctx.lineTo(sx(x), sy(y))));
    ctx.stroke();
  } else {
    for (const [x, y] of view.fit) {
      ctx.beginPath();
      ctx.moveTo(sx(x) - 4, sy(y));
      ctx.lineTo(sx(x) + 4, sy(y));
      ctx.moveTo(sx(x), sy(y) - 4);
      ctx.lineTo(sx(x), sy(y) + 4);
      ctx.stroke();
    }
  }
}

export class CalibrationPanel {
  status: CalibrationStatus | null = null;
  private timer: number | undefined;
  private readonly list: HTMLElement;
  private readonly canvas: HTMLCanvasElement;
  private drawnView = "";

  constructor(
    private readonly root: HTMLElement,
    private readonly notify: Notify,
    private readonly canCommand: () => boolean,
  ) {
    this.list = root.querySelector(".cal-steps") as HTMLElement;
    this.canvas = root.querySelector("canvas.cal-view") as HTMLCanvasElement;
    drawView(this.canvas, null);
    this.canvas.dataset.placeholder = "true";
  }

  start(): void {
    void this.refresh();
  }

  async refresh(): Promise<void> {
    window.clearTimeout(this.timer);
    try {
      this.status = await call<CalibrationStatus>("GET", "/api/calibration");
      this.render();
    } catch (e) {
      const msg = this.root.querySelector(".cal-message") as HTMLElement;
      msg.textContent = `calibration unavailable: ${(e as Error).message}`;
    }
    const running = this.status?.job.state === "running";
    this.timer = window.setTimeout(() => void this.refresh(), running ? POLL_RUNNING_MS : POLL_IDLE_MS);
  }

  async run(step: string): Promise<void> {
    try {
      await call("POST", `/api/calibration/${step}`);
      this.notify(`calibration step ${step} started`);
    } catch (e) {
      const err = e as ApiError;
      this.notify(`calibrate ${step}: ${err.message}`, "error");
    }
    await this.refresh();
  }

  private render(): void {
    const s = this.status;
    if (!s) return;
    (this.root.querySelector(".cal-file") as HTMLElement).textContent = `${s.file} · ${s.source}`;
    const refused = this.root.querySelector(".cal-refused") as HTMLElement;
    refused.hidden = !s.trials_refused;
    refused.textContent = s.trials_refused ?? "";
    const job = s.job;
    const running = job.state === "running";
    this.list.replaceChildren(...s.steps.map((st, i) => this.row(st, i, running)));
    const progress = this.root.querySelector("progress") as HTMLProgressElement;
    progress.value = job.progress;
    progress.hidden = job.state === "idle";
    const msg = this.root.querySelector(".cal-message") as HTMLElement;
    msg.dataset.state = job.state;
    msg.dataset.job = String(job.id);
    msg.textContent = job.step ? `${job.step}: ${job.state}${job.message ? ` · ${job.message}` : ""}` : "no step run since the service started";
    const key = JSON.stringify([job.id, job.progress, job.view?.points.length, job.view?.fit.length, job.state]);
    if (key !== this.drawnView) {
      this.drawnView = key;
      drawView(this.canvas, job.view ?? null, running);
      this.canvas.dataset.placeholder = job.view ? "" : "true";
      this.canvas.dataset.points = String(job.view?.points.length ?? 0);
      this.canvas.dataset.fit = String(job.view?.fit.length ?? 0);
      this.canvas.dataset.kind = job.view?.kind ?? "";
    }
    const changes = this.root.querySelector(".cal-changes") as HTMLElement;
    changes.replaceChildren();
    if (job.state === "done") {
      const cap = document.createElement("caption");
      cap.textContent = job.first ? `${job.step}: first calibration` : `${job.step}: changes from the last calibration (${job.changes.length})`;
      changes.append(cap);
      for (const c of job.changes.slice(0, 12)) {
        const tr = document.createElement("tr");
        for (const v of [c.key, c.before.toPrecision(6), c.after.toPrecision(6), (c.after - c.before).toPrecision(3)]) {
          const td = document.createElement("td");
          td.textContent = v;
          tr.append(td);
        }
        changes.append(tr);
      }
    }
  }

  private row(st: StepStatus, i: number, running: boolean): HTMLElement {
    const li = document.createElement("li");
    li.dataset.step = st.name;
    li.dataset.done = String(st.done);
    const title = document.createElement("span");
    title.className = "cal-title";
    title.textContent = `${i + 1}. ${st.title}`;
    const state = document.createElement("span");
    state.className = "cal-state";
    const rec = st.record as { date?: string; result?: Record<string, unknown> } | null;
    state.textContent = st.done ? `✓ ${rec?.date ?? ""} · ${headline(st.name, rec?.result)}` : st.missing.length ? `needs ${st.missing.join(", ")}` : "not calibrated";
    const btn = document.createElement("button");
    btn.textContent = st.done ? "Run again" : "Run";
    btn.disabled = running || st.missing.length > 0 || !this.canCommand();
    btn.title = st.missing.length ? `calibrate ${st.missing.join(", ")} first` : `run the ${st.name} step`;
    btn.addEventListener("click", () => void this.run(st.name));
    li.append(title, state, btn);
    return li;
  }
}
