import uPlot from "uplot";
import { call, judgeCells, strikeCell, trialList, verdict, type TrialRecord } from "./api";
import { COLORS } from "./plots";
import { fmt, pct, wilson } from "./stats";

/** The trial history: success rate with its 95% interval, per-trial numbers, recordings. */
export class TrialsView {
  private plot: uPlot | null = null;
  trials: TrialRecord[] = [];

  constructor(private readonly root: HTMLElement) {}

  private again: number | undefined;

  async refresh(): Promise<void> {
    try {
      this.trials = trialList(await call<unknown>("GET", "/api/trials"));
    } catch {
      return;
    }
    this.render();
    // The service writes a trial's record just after announcing its end: while one
    // is still running here, look again shortly (once per second at most).
    window.clearTimeout(this.again);
    if (this.trials.some((t) => t.status === "running")) this.again = window.setTimeout(() => void this.refresh(), 1000);
  }

  private render(): void {
    const judged = this.trials.filter((t) => verdict(t) !== null);
    const ok = judged.filter((t) => verdict(t) === "hit").length;
    const [lo, hi] = wilson(ok, judged.length);
    const summary = this.root.querySelector(".summary") as HTMLElement;
    const running = this.trials.filter((t) => t.status === "running");
    summary.textContent = judged.length
      ? `${ok} of ${judged.length} precisely timed: ${pct(ok / judged.length)} (95% CI ${pct(lo)}–${pct(hi)})`
      : running.length
        ? `trial ${running.map((t) => t.id).join(", ")} running: none judged yet`
        : this.trials.length
          ? `${this.trials.length} trials, none judged (aborted or not judged)`
          : "no trials yet";
    // In a truthful world the verdict is the truth's; the measured judge's
    // columns are what a real lab would see of the same trials.
    const note = this.root.querySelector(".judge-note") as HTMLElement | null;
    if (note) {
      const truthful = judged.length > 0 && judged.every((t) => t.judged_by === "truth");
      note.hidden = !truthful;
      note.textContent = truthful
        ? "Truthful simulated world: each verdict and its timing error are judged on the ground truth. The two \"measured judge\" columns are what a real lab's measured judge (camera and joint torques) says of the same trials, shown for comparison only."
        : "";
    }
    const body = this.root.querySelector("tbody") as HTMLElement;
    body.replaceChildren();
    const newestFirst = [...this.trials].sort((a, b) => b.id - a.id);
    for (const t of newestFirst) {
      const v = verdict(t);
      const j = judgeCells(t);
      const tr = document.createElement("tr");
      // The judged timing error is the verdict's judge's (the truth in a
      // simulated lab, the measured one in a real lab); the measured judge's
      // figures stand beside it in every lab.
      const cells: [string, string][] = [
        ["id", String(t.id)],
        ["result", v ?? t.status ?? "…"],
        ["judge", j.judge],
        ["distance", fmt(t.distance_m, 3)],
        ["timing", fmt(t.timing_error_ms, 1)],
        ["measured-timing", j.measuredTiming],
        ["contact", j.contact],
        ["strike", strikeCell(t)],
        ["position", fmt(t.position_error_m != null ? t.position_error_m * 1000 : null, 1)],
        ["movement", fmt(t.movement_time_s, 3)],
        ["reason", t.abort_reason ?? ""],
      ];
      for (const [name, c] of cells) {
        const td = document.createElement("td");
        td.dataset.col = name;
        td.textContent = c;
        if (name === "reason" && t.reason) td.title = t.reason;
        tr.append(td);
      }
      const dl = document.createElement("td");
      for (const ext of ["csv", "mcap"]) {
        const a = document.createElement("a");
        a.href = `/api/trials/${t.id}/recording.${ext}`;
        a.textContent = ext.toUpperCase();
        a.download = `trial-${t.id}.${ext}`;
        dl.append(a, " ");
      }
      const show = document.createElement("button");
      show.textContent = "plot";
      show.addEventListener("click", () => void this.plotTrial(t.id));
      dl.append(show);
      tr.append(dl);
      if (v) tr.classList.add(v);
      body.append(tr);
    }
  }

  /** Plots a trial's recorded path speed (or its first signals) from its CSV. */
  async plotTrial(id: number): Promise<void> {
    const r = await fetch(`/api/trials/${id}/recording.csv`);
    const host = this.root.querySelector(".trial-plot") as HTMLElement;
    if (!r.ok) {
      host.textContent = `no recording for trial ${id}`;
      return;
    }
    const { header, cols } = parseCsv(await r.text());
    const t = header.findIndex((h) => h === "t_s");
    const wanted = header
      .map((h, i) => [h, i] as const)
      .filter(([h, i]) => i !== t && /speed|progress/.test(h))
      .slice(0, 4);
    const pick = wanted.length ? wanted : header.map((h, i) => [h, i] as const).filter(([, i]) => i !== t).slice(0, 3);
    const palette = [COLORS.blue, COLORS.red, COLORS.green, COLORS.orange];
    this.plot?.destroy();
    host.replaceChildren();
    const title = document.createElement("h3");
    title.textContent = `Trial ${id}`;
    host.append(title);
    this.plot = new uPlot(
      {
        width: Math.max(300, host.clientWidth - 8),
        height: 200,
        scales: { x: { time: false } },
        series: [{ label: "t (s)" }, ...pick.map(([h], i) => ({ label: h, stroke: palette[i % 4], width: 1.5 }))],
      },
      [cols[t >= 0 ? t : 0], ...pick.map(([, i]) => cols[i])] as uPlot.AlignedData,
      host,
    );
  }
}

/** Numeric CSV with a header row; non-numbers become NaN. */
export function parseCsv(text: string): { header: string[]; cols: number[][] } {
  const lines = text.split(/\r?\n/).filter((l) => l.length > 0 && !l.startsWith("#"));
  const header = (lines.shift() ?? "").split(",").map((h) => h.trim());
  const cols = header.map(() => [] as number[]);
  for (const l of lines) {
    const v = l.split(",");
    for (let i = 0; i < header.length; i++) cols[i].push(Number(v[i] ?? Number.NaN));
  }
  return { header, cols };
}
