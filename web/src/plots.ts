import uPlot from "uplot";
import "uplot/dist/uPlot.min.css";
import { SeriesWindow } from "./series";
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
}

function size(el: HTMLElement): { width: number; height: number } {
  return { width: Math.max(240, el.clientWidth - 8), height: 170 };
}

function line(label: string, stroke: string, extra: Partial<uPlot.Series> = {}): uPlot.Series {
  return { label, stroke, width: 1.5, points: { show: false }, ...extra };
}

/** The live plots; `update` takes each state message, `draw` repaints (once per frame). */
export class Plots {
  private charts: Chart[] = [];
  private latest: StateMessage | null = null;
  private dirty = false;
  private phase: CanvasRenderingContext2D | null;
  private phaseTrail: SeriesWindow = new SeriesWindow(2, 600);

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
    {
      const el = host("plot-pendulum", "Pendulum: lateral position x = l sin φ (m)");
      const plot = new uPlot(
        {
          ...size(el),
          scales: { x: timeScale },
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
    // 2. Path speed: planned vs executed, arrival marked.
    {
      const el = host("plot-speed", "Path speed: planned vs executed (m/s)");
      const plot = new uPlot(
        {
          ...size(el),
          scales: { x: { time: false } },
          series: [{ label: "t (s)" }, line("planned", COLORS.blue), line("executed", COLORS.red, { dash: [6, 3] })],
          hooks: { draw: [(u) => this.drawArrival(u)] },
        },
        [[], [], []],
        el,
      );
      this.charts.push({
        plot,
        win: new SeriesWindow(3, CAPACITY),
        row: (s) => [s.t_s, s.path.speed_planned_mps, s.path.speed_executed_mps],
      });
    }
    // 3. Neurons.
    {
      const el = host("plot-neurons", "Neurons: u_init, u_Hopf, u_final");
      const plot = new uPlot(
        {
          ...size(el),
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
    }
    this.latest = s;
    for (const c of this.charts) c.win.push(c.row(s));
    this.phaseTrail.push([s.hopf.a, s.hopf.b]);
    this.dirty = true;
  }

  /** Repaints if anything arrived since the last call. */
  draw(): void {
    if (!this.dirty) return;
    this.dirty = false;
    for (const c of this.charts) c.plot.setData(c.win.plotData() as uPlot.AlignedData);
    this.drawPhase();
  }

  /** Points held per plot (the browser test watches them grow). */
  pointCounts(): number[] {
    return [...this.charts.map((c) => c.win.length), this.phaseTrail.length];
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
    if (Number.isFinite(ta)) this.vline(u, ta, COLORS.green, "arrival");
  }

  private vline(u: uPlot, t: number, color: string, label: string): void {
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
    ctx.fillText(label, x + 4, u.bbox.top + 14 * devicePixelRatio);
    ctx.restore();
  }

  private drawPhase(): void {
    const ctx = this.phase;
    if (!ctx) return;
    const { width: w, height: h } = ctx.canvas;
    ctx.clearRect(0, 0, w, h);
    const [a, b] = this.phaseTrail.data();
    let r = 0.05;
    for (let i = 0; i < a.length; i++) r = Math.max(r, Math.abs(a[i]), Math.abs(b[i]));
    const s = (Math.min(w, h) / 2 - 12) / r;
    const cx = w / 2, cy = h / 2;
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
    ctx.fillText("a", w - 12, cy - 4);
    ctx.fillText("b", cx + 4, 12);
    ctx.strokeStyle = COLORS.blue;
    ctx.lineWidth = 2;
    ctx.beginPath();
    for (let i = 0; i < a.length; i++) {
      const x = cx + a[i] * s, y = cy - b[i] * s;
      if (i === 0) ctx.moveTo(x, y);
      else ctx.lineTo(x, y);
    }
    ctx.stroke();
    if (a.length > 0) {
      ctx.fillStyle = COLORS.red;
      ctx.beginPath();
      ctx.arc(cx + a[a.length - 1] * s, cy - b[b.length - 1] * s, 4, 0, 2 * Math.PI);
      ctx.fill();
    }
  }
}
