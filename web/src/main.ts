import "./style.css";
import { call } from "./api";
import { CalibrationPanel } from "./calibration";
import { CameraView, type OverlayDrawn } from "./camera";
import { Link, wsUrl, type LinkStatus } from "./connection";
import { Controls, ParamsPanel } from "./controls";
import type { Lead } from "./hopf";
import { Plots } from "./plots";
import { FriPanel } from "./fri";
import { fmt } from "./stats";
import { TrialsView } from "./trials";
import { DEFAULT_GEOMETRY, Twin } from "./twin";
import { trialStateText, type ServerMessage, type StateMessage } from "./types";

const $ = <T extends HTMLElement>(id: string) => document.getElementById(id) as T;

const toast = $<HTMLElement>("toast");
let toastTimer: number | undefined;
function notify(text: string, kind: "info" | "error" = "info"): void {
  toast.textContent = text;
  toast.className = `toast ${kind}`;
  window.clearTimeout(toastTimer);
  toastTimer = window.setTimeout(() => (toast.className = "toast hidden"), 6000);
}

const plots = new Plots($("plots"), $<HTMLCanvasElement>("phase"));
const twin = new Twin($("twin"));
const camera = new CameraView($("camera"));
const trials = new TrialsView($("trials"));
const params = new ParamsPanel($<HTMLFormElement>("params"), notify, $<HTMLInputElement>("param-filter"));
const controls = new Controls(notify, () => {
  void trials.refresh();
  void calibration.refresh();
});
const fri = new FriPanel($("fri"));
fri.start();
const calibration = new CalibrationPanel($("calibration"), notify, () => controls.canCommand());
calibration.start();

let latest: StateMessage | null = null;
let lastTrialState = "";
/** The axes as they were when the latest trial ended (the browser test reads them). */
let trialEndAxes: ReturnType<Plots["axes"]> | null = null;

function onMessage(m: ServerMessage): void {
  switch (m.type) {
    case "hello":
      controls.tokenRequired = m.token_required;
      controls.refresh();
      $("version").textContent = `isochron ${m.version}`;
      break;
    case "state":
      latest = m;
      plots.update(m);
      twin.update(m);
      camera.update(m);
      if (m.trial_state !== lastTrialState) {
        lastTrialState = m.trial_state;
        if (m.trial_state === "done" || m.trial_state === "aborted") void trials.refresh();
        if (m.trial_state === "done") {
          // After the next repaint, so the axes include the motion's last samples.
          requestAnimationFrame(() => requestAnimationFrame(() => requestAnimationFrame(() => (trialEndAxes = plots.axes()))));
        }
      }
      break;
    case "event":
      if (m.event.kind === "aborted") notify(`trial aborted: ${m.message ?? String(m.event.reason)}`, "error");
      if (m.event.kind === "trial_finished") void trials.refresh();
      break;
  }
}

function onStatus(s: LinkStatus): void {
  const banner = $("banner");
  banner.hidden = s === "open";
  banner.textContent = s === "lost" ? "Connection to the lab lost: reconnecting…" : "Connecting to the lab…";
  document.body.classList.toggle("disconnected", s !== "open");
}

/** Sets an element's text only when it changes (no layout work for the same text). */
function set(id: string, text: string): void {
  const el = $(id);
  if (el.textContent !== text) el.textContent = text;
}

function status(s: StateMessage): void {
  set("st-trial", trialStateText(s));
  const st = $("st-trial");
  if (st.dataset.state !== s.trial_state) st.dataset.state = s.trial_state;
  set("st-fri", `${s.fri.session} · ${s.fri.quality}`);
  fri.link(s.fri);
  set("st-rtt", fmt(s.fri.reply_latency_us, 0, "µs"));
  set("st-magnet", s.magnet);
  set("st-latency", fmt(s.robot.actuation_latency_ms, 1, "ms"));
  set("st-step", `${fmt(s.timing.step_us, 1)} / ${fmt(s.timing.step_max_us, 1)} µs`);
  set("st-misses", String(s.timing.deadline_misses + s.fri.missed_cycles));
  set("st-rejected", String(s.camera?.rejected ?? "–"));
  set("st-camera", s.camera?.lost ? "lost: no frames" : "delivering");
  $("st-camera").classList.toggle("bad", s.camera?.lost === true);
  const ahead = (s.pendulum.crossing_t_s ?? Number.NaN) - s.t_s;
  set("st-pass", ahead >= 0 ? `in ${fmt(ahead, 2, "s")} ± ${fmt((s.pendulum.crossing_sigma_s ?? NaN) * 1000, 1, "ms")}` : "–");
}

const link = new Link(wsUrl("/ws"), onMessage, onStatus);
link.start();

// Paint at the display's rate, whatever the stream's rate; the heavy views at a
// fraction of it, so the page stays above 30 fps on a slow machine without a GPU:
// the 3D twin every other frame (and only when something moved), the five plots
// every fourth (15 Hz at 60 fps: a 12 s window scrolls ~4 px per repaint). On
// a 2-core VM with software rendering, plots every other frame held the page
// at 25-29 fps; every fourth, 36-41 fps (the browser test's soak).
let frames = 0;
let tick = 0;
let fps = 0;
let fpsT0 = performance.now();
let statusAt = 0;
/** Main-thread milliseconds spent per view since the page loaded (the soak test reports them). */
const cost = { plots: 0, twin: 0, camera: 0, status: 0, frames: 0 };
function frame(now: number): void {
  tick += 1;
  const t0 = performance.now();
  if (tick % 4 === 0) plots.draw();
  else if (tick % 2 === 1) twin.draw(now);
  const t1 = performance.now();
  camera.draw(now);
  const t2 = performance.now();
  // The status line's numbers at 10 Hz (faster is unreadable): frames where nothing
  // else changed then give the compositor nothing to redraw.
  if (latest && now - statusAt >= 100) {
    statusAt = now;
    status(latest);
  }
  const t3 = performance.now();
  if (tick % 4 === 0) cost.plots += t1 - t0;
  else if (tick % 2 === 1) cost.twin += t1 - t0;
  cost.camera += t2 - t1;
  cost.status += t3 - t2;
  cost.frames += 1;
  frames += 1;
  if (now - fpsT0 >= 1000) {
    fps = (frames * 1000) / (now - fpsT0);
    frames = 0;
    fpsT0 = now;
  }
  requestAnimationFrame(frame);
}
requestAnimationFrame(frame);

async function loadGeometry(): Promise<void> {
  await params.load();
  const p = params.params as { pendulum?: Record<string, number>; task?: Record<string, unknown> };
  camera.lengthM = p.pendulum?.length_m ?? DEFAULT_GEOMETRY.length_m;
  twin.geometry = {
    length_m: p.pendulum?.length_m ?? DEFAULT_GEOMETRY.length_m,
    ball_radius_m: p.pendulum?.ball_radius_m ?? DEFAULT_GEOMETRY.ball_radius_m,
    intercept_height_m: (p.task?.intercept_height_m as number) ?? DEFAULT_GEOMETRY.intercept_height_m,
    home_m: (p.task?.home_m as [number, number, number]) ?? DEFAULT_GEOMETRY.home_m,
    tool_length_m: (p.task?.tool_length_m as number) ?? DEFAULT_GEOMETRY.tool_length_m,
  };
}
void loadGeometry();
twin.loadRobot().catch((e: unknown) => notify(`3D arm: ${String(e)}`, "error"));
void trials.refresh();
void call("GET", "/api/health").catch(() => onStatus("lost"));

/** What the browser tests read. */
declare global {
  interface Window {
    __isochron: {
      points: () => number[];
      twinFrames: () => number;
      twinLoaded: () => boolean;
      twinProbe: (names: string[]) => ReturnType<Twin["probe"]>;
      twinView: () => ReturnType<Twin["view"]>;
      fps: () => number;
      received: () => number;
      state: () => string;
      phase: () => ReturnType<Plots["phaseStats"]>;
      neurons: () => Lead[];
      camera: () => { received: number; frames: number; decodeErrors: number; fps: number; drawn: OverlayDrawn };
      cost: () => typeof cost;
      axes: () => ReturnType<Plots["axes"]>;
      trialEndAxes: () => ReturnType<Plots["axes"]> | null;
      heartbeats: () => number;
    };
  }
}
window.__isochron = {
  points: () => plots.pointCounts(),
  twinFrames: () => twin.frames,
  twinLoaded: () => twin.robotLoaded,
  twinProbe: (names: string[]) => twin.probe(names),
  twinView: () => twin.view(),
  fps: () => fps,
  received: () => link.received,
  state: () => latest?.trial_state ?? "",
  phase: () => plots.phaseStats(),
  neurons: () => plots.neuronLeads(),
  camera: () => ({
    received: camera.received,
    frames: camera.frames,
    decodeErrors: camera.decodeErrors,
    fps: camera.fps(),
    drawn: camera.drawn,
  }),
  cost: () => ({ ...cost }),
  axes: () => plots.axes(),
  trialEndAxes: () => trialEndAxes,
  heartbeats: () => controls.heartbeats,
};
