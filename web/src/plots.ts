import uPlot from "uplot";
import "uplot/dist/uPlot.min.css";
import { lengthRange, lengthUnit, speedRange, tickLabels } from "./axes";
import { leads, PhaseTrail, type Lead } from "./hopf";
import { SeriesWindow } from "./series";
import { centeredMovingAverage, SMOOTH_HALF } from "./smooth";
import { num, type StateMessage } from "./types";

/** Okabe-Ito: distinguishable with the common colour-vision deficiencies. */
export const COLORS = {
  orange: "#E69F00",
  sky: "#56B4E9",
  green: "#009E73",
  yellow: "#F0E442",
  blue: "#0072B2",
  red: "#D55E00",
  purple: "#CC79A7",
  grey: "#777777",
};
const JOINT_COLORS = [COLORS.blue, COLORS.orange, COLORS.green, COLORS.red, COLORS.purple, COLORS.sky, COLORS.grey];

const WINDOW_S = 12;
const CAPACITY = 1200;

interface Chart {
  plot: uPlot;
  win: SeriesWindow;
  row: (s: StateMessage) => number[];
  /** Turns the window's columns into the plotted series (default: as they are). */
  shape?: (cols: (number | null)[][]) => (number | null)[][];
}

function size(el: HTMLElement): { width: number; height: number } {
  return { width: Math.max(240, el.clientWidth - 8), height: 170 };
}

/** Legends name the series; live values under a hover cursor would read "--" most of the time. */
const LEGEND: uPlot.Legend = { live: false };

function line(label: string, stroke: string, extra: Partial<uPlot.Series> = {}): uPlot.Series {
  return { label, stroke, width: 1.5, points: { show: false }, ...extra };
}

/** The live plots; `update` takes each state message, `draw` repaints (once per frame). */
export class Plots {
  private charts: Chart[] = [];
  private latest: StateMessage | null = null;
  private dirty = false;
  private phase: CanvasRenderingContext2D | null;
  private phaseTrail = new PhaseTrail();
  private phaseDirty = true;
  private pendulumTitle: HTMLElement | null = null;
  /** The largest planned and executed path speeds since the page loaded, m/s. */
  private peaks = { planned: 0, executed: 0 };

  constructor(root: HTMLElement, phaseCanvas: HTMLCanvasElement) {
    this.phase = phaseCanvas.getContext("2d");
    const host = (id: string, title: string): HTMLElement => {
      const box = document.createElement("section");
      box.className = "plot";
      box.id = id;
      box.setAttribute("aria-label", title);
      const h = document.createElement("h3");
      h.textContent = title;
      box.append(h);
      root.insertBefore(box, root.querySelector(".phase-panel"));
      return box;
    };
    const xRange = (): uPlot.Range.MinMax => {
      const now = this.latest?.t_s ?? 0;
      const horizon = this.latest?.pendulum.horizon;
      const future = horizon && horizon.length > 0 ? Math.max(0, horizon[horizon.length - 1].t_s - now) : 0;
      return [now - WINDOW_S, now + Math.min(future, 3)];
    };
    const timeScale: uPlot.Scale = { time: false, range: () => xRange() };

    // 1. Pendulum: measured vs estimated, uncertainty band, predicted horizon.
    // Values stay in metres; the axis shows millimetres below 1 m (the title says which).
    {
      const el = host("plot-pendulum", "Pendulum: lateral position x = l sin φ (mm)");
      this.pendulumTitle = el.querySelector("h3");
      const plot = new uPlot(
        {
          ...size(el),
          legend: LEGEND,
          scales: { x: timeScale, y: { range: (_u, min, max) => lengthRange(min, max) } },
          axes: [
            {},
            {
              size: 56,
              space: 22,
              values: (u, splits) => {
                const unit = lengthUnit(u.scales.y.min ?? 0, u.scales.y.max ?? 0);
                return tickLabels(splits.map((v) => v * unit.scale));
              },
            },
          ],
          series: [
            { label: "t (s)" },
            line("measured", COLORS.orange, { width: 0, points: { show: true, size: 4, fill: COLORS.orange } }),
            line("estimated", COLORS.blue),
            line("+2σ", COLORS.sky, { dash: [4, 4], width: 1 }),
            line("−2σ", COLORS.sky, { dash: [4, 4], width: 1 }),
          ],
          bands: [{ series: [3, 4], fill: "rgba(86,180,233,0.15)" }],
          hooks: { draw: [(u) => this.drawHorizon(u)] },
        },
        [[], [], [], [], []],
        el,
      );
      this.charts.push({
        plot,
        win: new SeriesWindow(5, CAPACITY),
        row: (s) => {
          const p = s.pendulum;
          const fresh = p.measured.valid && s.t_s - p.measured.t_s < 0.2;
          const sig = num(p.sigma_x_m);
          return [s.t_s, fresh ? p.measured.x_m : Number.NaN, p.x_m, p.x_m + 2 * sig, p.x_m - 2 * sig];
        },
      });
    }
    // 2. Path speed: planned vs executed, arrival marked. The axis fits the
    // planned motion in view (a lone executed sample cannot stretch it). The
    // executed speed is drawn through a centered moving average (smooth.ts);
    // the raw samples on request (the checkbox under the plot).
    {
      const el = host("plot-speed", "Path speed: planned (Hopf) vs executed (m/s)");
      const win = new SeriesWindow(3, CAPACITY);
      const smoothed: (number | null)[] = [];
      const shaped: (number | null)[][] = [[], [], [], []];
      const plot = new uPlot(
        {
          ...size(el),
          legend: LEGEND,
          scales: {
            x: { time: false },
            y: {
              range: () => {
                const d = win.data();
                return speedRange(d[1], d[2]);
              },
            },
          },
          series: [
            { label: "t (s)" },
            line("planned (Hopf)", COLORS.blue),
            line(`executed, mean of ${2 * SMOOTH_HALF + 1} samples`, COLORS.red, { width: 2, dash: [6, 3] }),
            line("executed, raw", COLORS.grey, { width: 1, show: false }),
          ],
          hooks: { draw: [(u) => this.drawArrival(u)] },
        },
        [[], [], [], []],
        el,
      );
      const caption = document.createElement("p");
      caption.className = "plot-caption";
      const toggle = document.createElement("label");
      const box = document.createElement("input");
      box.type = "checkbox";
      box.id = "speed-raw";
      box.addEventListener("change", () => {
        plot.setSeries(3, { show: box.checked });
        this.dirty = true;
      });
      toggle.append(box, " show the raw executed speed");
      caption.append(
        `Executed: the measured tool path differentiated at the 100 Hz state rate, drawn as a centered moving average of ${2 * SMOOTH_HALF + 1} samples (±${SMOOTH_HALF * 10} ms, no lag). `,
        toggle,
      );
      el.append(caption);
      this.charts.push({
        plot,
        win,
        row: (s) => [s.t_s, s.path.speed_planned_mps, s.path.speed_executed_mps],
        shape: (cols) => {
          shaped[0] = cols[0];
          shaped[1] = cols[1];
          shaped[2] = centeredMovingAverage(cols[2], SMOOTH_HALF, smoothed);
          shaped[3] = cols[2];
          return shaped;
        },
      });
    }
    // 3. Neurons.
    {
      const el = host("plot-neurons", "Neurons: u_init, u_Hopf, u_final");
      const plot = new uPlot(
        {
          ...size(el),
          legend: LEGEND,
          scales: { x: { time: false }, y: { range: [-0.1, 1.1] } },
          series: [{ label: "t (s)" }, line("u_init", COLORS.orange), line("u_Hopf", COLORS.blue), line("u_final", COLORS.green)],
        },
        [[], [], [], []],
        el,
      );
      this.charts.push({
        plot,
        win: new SeriesWindow(4, CAPACITY),
        row: (s) => [s.t_s, s.hopf.u_init, s.hopf.u_hopf, s.hopf.u_final],
      });
    }
    // 4. Joints against their limits.
    {
      const el = host("plot-joints", "Joints: q / limit (±1 = position limit)");
      const plot = new uPlot(
        {
          ...size(el),
          legend: LEGEND,
          scales: { x: { time: false }, y: { range: [-1.05, 1.05] } },
          series: [{ label: "t (s)" }, ...JOINT_COLORS.map((c, i) => line(`A${i + 1}`, c))],
        },
        [[], [], [], [], [], [], [], []],
        el,
      );
      this.charts.push({
        plot,
        win: new SeriesWindow(8, CAPACITY),
        row: (s) => [s.t_s, ...s.robot.q_rad.map((q, i) => q / (s.robot.q_limit_rad[i] || Math.PI))],
      });
    }
    // 5. Loop timing.
    {
      const el = host("plot-timing", "Control loop: step and period (µs)");
      const plot = new uPlot(
        {
          ...size(el),
          legend: LEGEND,
          scales: { x: { time: false } },
          series: [{ label: "t (s)" }, line("step", COLORS.purple), line("period", COLORS.grey)],
        },
        [[], [], []],
        el,
      );
      this.charts.push({
        plot,
        win: new SeriesWindow(3, CAPACITY),
        row: (s) => [s.t_s, s.timing.step_us, s.timing.period_mean_us],
      });
    }
    // Sizes are known only once every box is in the grid: set them now and on resize.
    const fit = () => {
      for (const c of this.charts) c.plot.setSize(size(c.plot.root.parentElement as HTMLElement));
    };
    new ResizeObserver(fit).observe(root);
    fit();
  }

  /** Takes one state message (cheap: no drawing). */
  update(s: StateMessage): void {
    if (this.latest && s.t_s < this.latest.t_s - 1) {
      // The lab restarted its clock: start the plots afresh.
      for (const c of this.charts) c.win.clear();
      this.phaseTrail.clear();
      this.phaseDirty = true;
    }
    this.latest = s;
    for (const c of this.charts) c.win.push(c.row(s));
    if (Number.isFinite(s.path.speed_planned_mps)) this.peaks.planned = Math.max(this.peaks.planned, s.path.speed_planned_mps);
    if (Number.isFinite(s.path.speed_executed_mps)) this.peaks.executed = Math.max(this.peaks.executed, s.path.speed_executed_mps);
    if (this.phaseTrail.push(s.hopf)) this.phaseDirty = true;
    this.dirty = true;
  }

  /** Repaints if anything arrived since the last call. */
  draw(): void {
    if (!this.dirty) return;
    this.dirty = false;
    for (const c of this.charts) {
      const cols = c.win.plotData();
      c.plot.setData((c.shape ? c.shape(cols) : cols) as uPlot.AlignedData);
    }
    const y = this.charts[0].plot.scales.y;
    const unit = lengthUnit(y.min ?? 0, y.max ?? 0).unit;
    const title = `Pendulum: lateral position x = l sin φ (${unit})`;
    if (this.pendulumTitle && this.pendulumTitle.textContent !== title) this.pendulumTitle.textContent = title;
    if (this.phaseDirty) {
      this.phaseDirty = false;
      this.drawPhase();
    }
  }

  /** Points held per plot (the browser test watches them grow). */
  pointCounts(): number[] {
    return [...this.charts.map((c) => c.win.length), this.phaseTrail.length];
  }

  /** The phase portrait's points over the last motion (the browser test reads them). */
  phaseStats(): ReturnType<PhaseTrail["stats"]> & { motions: number } {
    return { ...this.phaseTrail.stats(), motions: this.phaseTrail.motions };
  }

  /**
   * What the axes show (the browser test reads them): the pendulum axis' tick
   * labels as drawn and its title; the speed axis' range and the planned and
   * executed peaks in view; the share of finite estimates over the last second.
   */
  axes(): {
    pendulum: { title: string; ticks: string[] };
    speed: { min: number; max: number; planned_peak: number; executed_peak: number };
    estimate_finite_last_s: number;
    peaks: { planned: number; executed: number };
  } {
    const pend = this.charts[0];
    const speed = this.charts[1];
    const ticks = ((pend.plot.axes[1] as unknown as { _values?: (string | number)[] })._values ?? []).map(String);
    const d = speed.win.data();
    const peak = (c: Float64Array) => c.reduce((m, v) => (Number.isFinite(v) ? Math.max(m, v) : m), 0);
    const pd = pend.win.data();
    const n = pd[0].length;
    const tEnd = n > 0 ? pd[0][n - 1] : 0;
    let seen = 0;
    let finite = 0;
    for (let i = n - 1; i >= 0 && pd[0][i] > tEnd - 1; i--) {
      seen += 1;
      if (Number.isFinite(pd[2][i]) && Number.isFinite(pd[3][i])) finite += 1;
    }
    return {
      pendulum: { title: this.pendulumTitle?.textContent ?? "", ticks },
      speed: {
        min: speed.plot.scales.y.min ?? Number.NaN,
        max: speed.plot.scales.y.max ?? Number.NaN,
        planned_peak: peak(d[1]),
        executed_peak: peak(d[2]),
      },
      estimate_finite_last_s: seen > 0 ? finite / seen : 0,
      peaks: { ...this.peaks },
    };
  }

  /** Which neuron led when, over the neuron plot's window. */
  neuronLeads(): Lead[] {
    return leads(this.charts[2].win.data());
  }

  private drawHorizon(u: uPlot): void {
    const h = this.latest?.pendulum.horizon;
    if (!h || h.length < 2) return;
    const ctx = u.ctx;
    ctx.save();
    ctx.beginPath();
    ctx.rect(u.bbox.left, u.bbox.top, u.bbox.width, u.bbox.height);
    ctx.clip();
    ctx.fillStyle = "rgba(0,114,178,0.12)";
    ctx.beginPath();
    h.forEach((p, i) => {
      const x = u.valToPos(p.t_s, "x", true), y = u.valToPos(p.x_m + 2 * p.sigma_m, "y", true);
      if (i === 0) ctx.moveTo(x, y);
      else ctx.lineTo(x, y);
    });
    for (let i = h.length - 1; i >= 0; i--) {
      ctx.lineTo(u.valToPos(h[i].t_s, "x", true), u.valToPos(h[i].x_m - 2 * h[i].sigma_m, "y", true));
    }
    ctx.fill();
    ctx.strokeStyle = COLORS.blue;
    ctx.setLineDash([2, 3]);
    ctx.lineWidth = 2;
    ctx.beginPath();
    h.forEach((p, i) => {
      const x = u.valToPos(p.t_s, "x", true), y = u.valToPos(p.x_m, "y", true);
      if (i === 0) ctx.moveTo(x, y);
      else ctx.lineTo(x, y);
    });
    ctx.stroke();
    const tc = num(this.latest?.pendulum.crossing_t_s);
    if (Number.isFinite(tc)) this.vline(u, tc, COLORS.green, "pass");
    ctx.restore();
  }

  private drawArrival(u: uPlot): void {
    const ta = num(this.latest?.path.arrival_t_s);
    const ts = num(this.latest?.path.start_t_s);
    if (Number.isFinite(ts)) this.vline(u, ts, COLORS.grey, "start");
    // One line lower, so the two labels never overlap on a short motion.
    if (Number.isFinite(ta)) this.vline(u, ta, COLORS.green, "arrival", 1);
  }

  private vline(u: uPlot, t: number, color: string, label: string, row = 0): void {
    const x = u.valToPos(t, "x", true);
    if (x < u.bbox.left || x > u.bbox.left + u.bbox.width) return;
    const ctx = u.ctx;
    ctx.save();
    ctx.strokeStyle = color;
    ctx.lineWidth = 2;
    ctx.setLineDash([]);
    ctx.beginPath();
    ctx.moveTo(x, u.bbox.top);
    ctx.lineTo(x, u.bbox.top + u.bbox.height);
    ctx.stroke();
    ctx.fillStyle = color;
    ctx.font = `${12 * devicePixelRatio}px system-ui, sans-serif`;
    ctx.fillText(label, x + 4, u.bbox.top + (14 + 15 * row) * devicePixelRatio);
    ctx.restore();
  }

  private drawPhase(): void {
    const ctx = this.phase;
    if (!ctx) return;
    const { width: w, height: h } = ctx.canvas;
    ctx.clearRect(0, 0, w, h);
    const t = this.phaseTrail;
    const n = t.length;
    const st = t.stats();
    // Equal scales on both axes, fitted to the points and the origin (rest).
    let a0 = 0, a1 = 0.05, b0 = -0.025, b1 = 0.025;
    for (let i = 0; i < n; i++) {
      a0 = Math.min(a0, t.a[i]);
      a1 = Math.max(a1, t.a[i]);
      b0 = Math.min(b0, t.b[i]);
      b1 = Math.max(b1, t.b[i]);
    }
    const pad = 18;
    const s = Math.min((w - 2 * pad) / (a1 - a0), (h - 2 * pad) / (b1 - b0));
    const cx = w / 2 - ((a0 + a1) / 2) * s, cy = h / 2 + ((b0 + b1) / 2) * s;
    const X = (a: number) => cx + a * s, Y = (b: number) => cy - b * s;
    ctx.strokeStyle = "#bbb";
    ctx.lineWidth = 1;
    ctx.beginPath();
    ctx.moveTo(0, cy);
    ctx.lineTo(w, cy);
    ctx.moveTo(cx, 0);
    ctx.lineTo(cx, h);
    ctx.stroke();
    ctx.fillStyle = "#555";
    ctx.font = "12px system-ui, sans-serif";
    ctx.textAlign = "right";
    ctx.fillText("a: path speed (m/s)", w - 4, cy + 14);
    ctx.textAlign = "left";
    ctx.fillText("b", cx + 4, 12);
    if (n === 0) {
      ctx.textAlign = "center";
      ctx.fillText("no motion yet: the arc appears during a trial", w / 2, h - 6);
      ctx.textAlign = "left";
      return;
    }
    // The ideal limit cycle for this motion's peak speed 2 R_h: radius R_h around (R_h, 0).
    const rh = st.max_a / 2;
    if (rh > 1e-3) {
      ctx.strokeStyle = COLORS.grey;
      ctx.setLineDash([3, 4]);
      ctx.beginPath();
      ctx.arc(X(rh), Y(0), rh * s, 0, 2 * Math.PI);
      ctx.stroke();
      ctx.setLineDash([]);
    }
    ctx.strokeStyle = COLORS.blue;
    ctx.lineWidth = 2;
    ctx.beginPath();
    for (let i = 0; i < n; i++) {
      if (i === 0) ctx.moveTo(X(t.a[i]), Y(t.b[i]));
      else ctx.lineTo(X(t.a[i]), Y(t.b[i]));
    }
    ctx.stroke();
    ctx.fillStyle = COLORS.grey;
    ctx.beginPath();
    ctx.arc(X(t.a[0]), Y(t.b[0]), 3, 0, 2 * Math.PI);
    ctx.fill();
    ctx.fillStyle = COLORS.red;
    ctx.beginPath();
    ctx.arc(X(t.a[n - 1]), Y(t.b[n - 1]), 4, 0, 2 * Math.PI);
    ctx.fill();
    ctx.fillStyle = "#555";
    ctx.fillText(`peak a ${st.max_a.toFixed(2)} m/s · R_h ${rh.toFixed(2)}`, 4, h - 6);
  }
}
