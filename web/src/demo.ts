// The kiosk page `/demo` for a screen in the lab's hall: the twin, the camera,
// the two plots that tell the story and the running count, with captions a
// visitor reads. No operator controls: it only watches (the service's demo
// runner, `isochron serve --demo`, starts the trials). It reconnects by itself
// and polls `GET /api/demo` for the runner's state and counts.
import "./style.css";
import "./demo.css";
import uPlot from "uplot";
import "uplot/dist/uPlot.min.css";
import { call, strikeLines, trialList, type TrialRecord } from "./api";
import { speedRange } from "./axes";
import { CameraView } from "./camera";
import { Link, wsUrl, type LinkStatus } from "./connection";
import type { DemoStatus } from "./generated/types";
import { COLORS } from "./plots";
import { SeriesWindow } from "./series";
import { centeredMovingAverage, SMOOTH_HALF } from "./smooth";
import { pct } from "./stats";
import { DEFAULT_GEOMETRY, Twin } from "./twin";
import type { ServerMessage, StateMessage } from "./types";

const $ = <T extends HTMLElement>(id: string) => document.getElementById(id) as T;
const DEMO_POLL_MS = 1000;
const WINDOW_S = 8;
/** The planned movement times the demo alternates (server/src/demo.rs). */
const PLANNED_S = [1.5, 2.0];

const twin = new Twin($("twin"));
const camera = new CameraView($("camera"));

let latest: StateMessage | null = null;
let linkStatus: LinkStatus = "connecting";
let demo: DemoStatus | null = null;
let demoError = "";
let toleranceMs = Number.NaN;

/** An axis readable on the page's dark background. */
function axis(label: string): uPlot.Axis {
  return { label, stroke: "#c9d1d9", grid: { stroke: "#30363d", width: 1 }, ticks: { stroke: "#30363d", width: 1 }, labelFont: "600 14px system-ui, sans-serif", font: "13px system-ui, sans-serif" };
}

// The speed plot: planned (Hopf) and executed (smoothed), the last 8 s.
const speedWin = new SeriesWindow(3, 1000);
const smoothed: (number | null)[] = [];
const speedHost = $("demo-speed");
const speedPlot = new uPlot(
  {
    width: Math.max(300, speedHost.clientWidth),
    height: 200,
    legend: { live: false },
    scales: {
      x: { time: false, range: () => [(latest?.t_s ?? 0) - WINDOW_S, latest?.t_s ?? 0] },
      y: { range: () => speedRange(speedWin.data()[1], speedWin.data()[2]) },
    },
    axes: [axis("time (s)"), { ...axis("speed (m/s)"), size: 60 }],
    series: [
      { label: "t (s)" },
      { label: "planned (Hopf)", stroke: COLORS.blue, width: 2.5, points: { show: false } },
      { label: "executed", stroke: COLORS.red, width: 2, dash: [6, 3], points: { show: false } },
    ],
  },
  [[], [], []],
  speedHost,
);

// The isochrony plot: each finished trial's distance against its movement time.
const isoHost = $("demo-isochrony");
let isoPoints = 0;
const isoPlot = new uPlot(
  {
    width: Math.max(300, isoHost.clientWidth),
    height: 200,
    legend: { live: false },
    scales: { x: { time: false, range: [0.3, 0.85] }, y: { range: [1.0, 2.5] } },
    axes: [axis("distance the arm moves (m)"), { ...axis("time taken (s)"), size: 60 }],
    series: [
      { label: "distance (m)" },
      ...PLANNED_S.map((t, i) => ({
        label: `planned ${t.toFixed(1)} s`,
        stroke: [COLORS.blue, COLORS.orange][i],
        fill: [COLORS.blue, COLORS.orange][i],
        paths: () => null,
        points: { show: true, size: 9, fill: [COLORS.blue, COLORS.orange][i] },
      })),
    ],
  },
  [[], [], []],
  isoHost,
);

new ResizeObserver(() => {
  speedPlot.setSize({ width: Math.max(300, speedHost.clientWidth), height: 200 });
  isoPlot.setSize({ width: Math.max(300, isoHost.clientWidth), height: 200 });
}).observe(document.body);

function showTrials(trials: TrialRecord[]): void {
  const done = trials
    .filter((t) => t.status === "done" && Number.isFinite(t.distance_m) && Number.isFinite(t.movement_time_s))
    .sort((a, b) => (a.distance_m as number) - (b.distance_m as number));
  const x: number[] = [];
  const ys: (number | null)[][] = PLANNED_S.map(() => []);
  for (const t of done) {
    const mt = t.movement_time_s as number;
    // The planned time nearest the one measured (the record has the measured one).
    let k = 0;
    PLANNED_S.forEach((p, i) => (Math.abs(mt - p) < Math.abs(mt - PLANNED_S[k]) ? (k = i) : 0));
    x.push(t.distance_m as number);
    ys.forEach((col, i) => col.push(i === k ? mt : null));
  }
  isoPoints = x.length;
  isoPlot.setData([x, ...ys] as uPlot.AlignedData);
  showStrikes(trials);
}

/** The lab's task mode (`GET /api/params`' `task.mode`): the strike panel shows in strike mode, or while strike trials are listed. */
let taskMode = "";
/** The strike lines shown (what the browser tests read). */
let strikesShown: { id: number; hit: boolean | null; text: string }[] = [];
const STRIKES_LISTED = 6;

function showStrikes(trials: TrialRecord[]): void {
  strikesShown = strikeLines(trials, STRIKES_LISTED);
  const panel = $("demo-strike");
  panel.hidden = taskMode !== "strike" && strikesShown.length === 0;
  const list = $("demo-strike-list");
  list.replaceChildren(
    ...strikesShown.map((l) => {
      const li = document.createElement("li");
      li.dataset.hit = String(l.hit);
      li.textContent = `trial ${l.id}${l.hit === true ? " ✓" : l.hit === false ? " ✗" : ""}: ${l.text}`;
      return li;
    }),
  );
  if (strikesShown.length === 0 && taskMode === "strike") {
    const li = document.createElement("li");
    li.textContent = "no strike finished yet";
    list.append(li);
  }
}

let shownTrials = -1;
async function pollDemo(): Promise<void> {
  try {
    demo = await call<DemoStatus>("GET", "/api/demo");
    demoError = "";
    if (demo.trials !== shownTrials) {
      shownTrials = demo.trials;
      showTrials(trialList(await call<unknown>("GET", "/api/trials?limit=200")));
    }
  } catch (e) {
    demoError = (e as Error).message;
  }
  render();
  window.setTimeout(() => void pollDemo(), DEMO_POLL_MS);
}

function set(el: HTMLElement, text: string): void {
  if (el.textContent !== text) el.textContent = text;
}

function render(): void {
  const status = $("demo-status");
  let state: string;
  let text: string;
  // The demo's own status (REST) says what the lab does; the live link
  // only feeds the views: a link reconnecting on a busy machine does not
  // hide a pause.
  if (demoError || (linkStatus !== "open" && demo?.state !== "paused")) {
    state = "connecting";
    text = "Reconnecting to the lab… the demo goes on by itself.";
  } else if (!demo || demo.state === "off") {
    state = "off";
    text = "Demo mode is off: the service was started without --demo.";
  } else {
    state = demo.state;
    const m = demo.message.replace(/^paused: /, "");
    text =
      demo.state === "running"
        ? `Trial running: ${fmtTrial(demo)}`
        : demo.state === "waiting"
          ? demo.next_in_s !== null
            ? `Next trial in ${Math.ceil(demo.next_in_s)} s`
            : "Waiting for the trial that is running to finish"
          : `Paused: ${m}. The demo resumes by itself when the lab is ready.`;
  }
  if (status.dataset.state !== state) status.dataset.state = state;
  set(status, text);
  if (demo) {
    const count = $("demo-count");
    count.dataset.trials = String(demo.trials);
    count.dataset.judged = String(demo.judged);
    set(count, demo.judged ? `${demo.successes} of ${demo.judged}` : "no trials yet");
    const [lo, hi] = demo.success_ci95;
    const tol = Number.isFinite(toleranceMs) ? ` (within ${toleranceMs} ms of the ball)` : "";
    set(
      $("demo-ci"),
      demo.judged
        ? `trials precisely timed${tol}: ${pct(demo.successes / demo.judged, 0)}, 95% interval ${pct(lo, 0)} to ${pct(hi, 0)}`
        : `trials precisely timed${tol}`,
    );
  }
}

function fmtTrial(d: DemoStatus): string {
  const dist = d.next_distance_m;
  return d.message.replace(/^trial \d+: /, "") || (dist !== null ? `${dist.toFixed(2)} m` : "");
}

function onMessage(m: ServerMessage): void {
  if (m.type !== "state") return;
  if (latest && m.t_s < latest.t_s - 1) speedWin.clear(); // the lab restarted its clock
  latest = m;
  twin.update(m);
  camera.update(m);
  speedWin.push([m.t_s, m.path.speed_planned_mps, m.path.speed_executed_mps]);
  speedDirty = true;
}

const link = new Link(wsUrl("/ws"), onMessage, (s) => {
  linkStatus = s;
  render();
});
link.start();

async function loadGeometry(): Promise<void> {
  try {
    const p = await call<{ pendulum?: Record<string, number>; task?: Record<string, unknown>; success?: Record<string, number> }>("GET", "/api/params");
    camera.lengthM = p.pendulum?.length_m ?? DEFAULT_GEOMETRY.length_m;
    taskMode = typeof p.task?.mode === "string" ? p.task.mode : "";
    if (taskMode === "strike") $("demo-strike").hidden = false;
    toleranceMs = p.success?.timing_tolerance_ms ?? Number.NaN;
    twin.geometry = {
      length_m: p.pendulum?.length_m ?? DEFAULT_GEOMETRY.length_m,
      ball_radius_m: p.pendulum?.ball_radius_m ?? DEFAULT_GEOMETRY.ball_radius_m,
      intercept_height_m: (p.task?.intercept_height_m as number) ?? DEFAULT_GEOMETRY.intercept_height_m,
      home_m: (p.task?.home_m as [number, number, number]) ?? DEFAULT_GEOMETRY.home_m,
      tool_length_m: (p.task?.tool_length_m as number) ?? DEFAULT_GEOMETRY.tool_length_m,
    };
  } catch {
    window.setTimeout(() => void loadGeometry(), 2000);
  }
}
void loadGeometry();
twin.loadRobot().catch(() => undefined);
void pollDemo();

// Paint at the display's rate: the twin every other frame, the speed plot every fourth.
let speedDirty = false;
let tick = 0;
let frames = 0;
let fps = 0;
let fpsT0 = performance.now();
function frame(now: number): void {
  tick += 1;
  if (tick % 4 === 0 && speedDirty) {
    speedDirty = false;
    const cols = speedWin.plotData();
    speedPlot.setData([cols[0], cols[1], centeredMovingAverage(cols[2], SMOOTH_HALF, smoothed)] as uPlot.AlignedData);
  } else if (tick % 2 === 1) twin.draw(now);
  camera.draw(now);
  frames += 1;
  if (now - fpsT0 >= 1000) {
    fps = (frames * 1000) / (now - fpsT0);
    frames = 0;
    fpsT0 = now;
  }
  requestAnimationFrame(frame);
}
requestAnimationFrame(frame);

/** What the browser tests read. */
declare global {
  interface Window {
    __demo: {
      status: () => DemoStatus | null;
      shown: () => { state: string; text: string; trials: number; points: number };
      strikes: () => { id: number; hit: boolean | null; text: string }[];
      fps: () => number;
      twinFrames: () => number;
      cameraFrames: () => number;
      received: () => number;
    };
  }
}
window.__demo = {
  status: () => demo,
  shown: () => ({
    state: $("demo-status").dataset.state ?? "",
    text: $("demo-status").textContent ?? "",
    trials: Number($("demo-count").dataset.trials ?? 0),
    points: isoPoints,
  }),
  strikes: () => strikesShown,
  fps: () => fps,
  twinFrames: () => twin.frames,
  cameraFrames: () => camera.frames,
  received: () => link.received,
};
