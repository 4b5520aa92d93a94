/** The FRI panel: version, period and quality of the link, and the last findings of `isochron fri doctor` (GET /api/fri). */
import { call } from "./api";
import type { FriView } from "./types";

interface DoctorFinding {
  code: string;
  severity: "ok" | "info" | "warning" | "problem";
  text: string;
  fix: string[];
}

export interface FriInfo {
  version: string;
  wire: string;
  doctor: { findings?: DoctorFinding[]; session_established?: boolean; listen?: string } | null;
  doctor_t_s: number | null;
}

export class FriPanel {
  private version = "–";
  private lastLink = "";

  constructor(private readonly root: HTMLElement) {}

  /** Reads the version and the doctor's report now and every 10 s. */
  start(): void {
    void this.refresh();
    window.setInterval(() => void this.refresh(), 10_000);
  }

  async refresh(): Promise<void> {
    try {
      this.render(await call<FriInfo>("GET", "/api/fri"));
    } catch {
      // The status line still shows the link; the panel keeps its last report.
    }
  }

  /** The live link, from the state stream. */
  link(f: FriView): void {
    const period = f.period_ms === null || !Number.isFinite(f.period_ms) ? "–" : `${f.period_ms.toFixed(0)} ms`;
    const text = `FRI ${this.version} · ${period} · ${f.quality} · ${f.session}`;
    if (text !== this.lastLink) {
      this.lastLink = text;
      const el = this.root.querySelector<HTMLElement>(".fri-link");
      if (el) el.textContent = text;
    }
  }

  render(info: FriInfo): void {
    this.version = info.version;
    const wire = this.root.querySelector<HTMLElement>(".fri-wire");
    if (wire) wire.textContent = info.wire;
    const list = this.root.querySelector<HTMLUListElement>(".fri-doctor");
    const when = this.root.querySelector<HTMLElement>(".fri-doctor-when");
    if (!list || !when) return;
    list.replaceChildren();
    const findings = info.doctor?.findings ?? [];
    if (!info.doctor) {
      when.textContent = "the doctor has not run: isochron fri doctor --config FILE";
      return;
    }
    const t = info.doctor_t_s ? new Date(info.doctor_t_s * 1000).toLocaleString() : "?";
    when.textContent = `last doctor run ${t}: ${info.doctor.session_established ? "session established" : "no session"}`;
    for (const f of findings) {
      const li = document.createElement("li");
      li.className = `finding ${f.severity}`;
      li.dataset.code = f.code;
      li.textContent = f.text;
      if (f.fix.length) {
        // The steps to check fold away (the panel stays beside the twin).
        const more = document.createElement("details");
        const sum = document.createElement("summary");
        sum.textContent = `what to check (${f.fix.length})`;
        const ul = document.createElement("ul");
        for (const step of f.fix) {
          const s = document.createElement("li");
          s.textContent = step;
          ul.append(s);
        }
        more.append(sum, ul);
        li.append(more);
      }
      list.append(li);
    }
  }
}
