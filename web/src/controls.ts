import { ApiError, call, getToken, setToken } from "./api";

type Notify = (text: string, kind?: "info" | "error") => void;

/** How often the page asks which devices keep the lab from running trials, ms. */
const DEVICES_MS = 2000;

/** A device that keeps the lab from running trials (`/api/health`'s `devices`). */
interface DeviceProblem {
  device: string;
  message: string;
}

/** How often the page sends its operator heartbeat, ms (well inside the dead-man time). */
const HEARTBEAT_MS = 200;

/** The buttons, the token field and the emergency stop (Space or Escape). */
export class Controls {
  private readonly buttons: HTMLButtonElement[];
  tokenRequired = true;
  /** Operator heartbeats the server accepted (the dead-man, `POST /api/heartbeat`). */
  heartbeats = 0;

  constructor(
    private readonly notify: Notify,
    private readonly onChange: () => void,
  ) {
    const $ = <T extends HTMLElement>(id: string) => document.getElementById(id) as T;
    this.buttons = ["btn-arm", "btn-disarm", "btn-magnet-on", "btn-drop", "btn-trial"].map((id) => $<HTMLButtonElement>(id));
    const tokenInput = $<HTMLInputElement>("token");
    tokenInput.value = getToken();
    $<HTMLFormElement>("token-form").addEventListener("submit", (e) => {
      e.preventDefault();
      setToken(tokenInput.value.trim());
      this.refresh();
      this.onChange();
      this.notify(getToken() ? "token stored for this browser session" : "token cleared: visitor mode");
    });
    const act = (id: string, label: string, method: string, path: string, body?: unknown) =>
      $<HTMLButtonElement>(id).addEventListener("click", () => void this.send(label, method, path, body));
    act("btn-arm", "arm", "POST", "/api/arm");
    act("btn-disarm", "disarm", "POST", "/api/disarm");
    act("btn-magnet-on", "magnet on", "POST", "/api/magnet", { on: true });
    act("btn-drop", "drop", "POST", "/api/magnet", { on: false });
    act("btn-trial", "run trial", "POST", "/api/trials");
    $<HTMLButtonElement>("btn-stop").addEventListener("click", () => void this.stop());
    document.addEventListener("keydown", (e) => {
      const target = e.target as HTMLElement | null;
      const typing = target && (target.tagName === "INPUT" || target.tagName === "TEXTAREA" || target.tagName === "SELECT");
      if (e.key === "Escape" || (e.key === " " && !typing && target?.tagName !== "BUTTON")) {
        e.preventDefault();
        void this.stop();
      }
    });
    this.refresh();
    // The devices that keep the lab from running trials, each with why
    // (`/api/health`'s `devices`: the robot's FRI session, a camera that
    // delivers nothing, a magnet board that does not answer).
    const pollDevices = () =>
      call("GET", "/api/health")
        .then((h) => this.showDevices((h as { devices?: DeviceProblem[] }).devices ?? []))
        .catch(() => undefined);
    void pollDevices();
    window.setInterval(() => void pollDevices(), DEVICES_MS);
    // The operator dead-man: while this page can command, it tells the lab an
    // operator is watching (the lab stops a running motion when no operator's
    // heartbeat came within its dead-man time, 1 s by default in the real lab).
    let inFlight = false;
    window.setInterval(() => {
      if (!this.canCommand() || inFlight) return;
      inFlight = true;
      call("POST", "/api/heartbeat")
        .then(() => (this.heartbeats += 1))
        .catch(() => undefined)
        .finally(() => (inFlight = false));
    }, HEARTBEAT_MS);
  }

  /** Lists the devices' problems (hidden when there are none). */
  showDevices(problems: DeviceProblem[]): void {
    const list = document.getElementById("devices");
    if (!list) return;
    list.replaceChildren(
      ...problems.map((p) => {
        const li = document.createElement("li");
        li.dataset.device = p.device;
        const name = document.createElement("strong");
        name.textContent = `${p.device}: `;
        li.append(name, p.message);
        return li;
      }),
    );
    list.hidden = problems.length === 0;
  }

  /** True when commands may be sent (a token is set, or the server needs none). */
  canCommand(): boolean {
    return !this.tokenRequired || getToken() !== "";
  }

  refresh(): void {
    const on = this.canCommand();
    for (const b of this.buttons) b.disabled = !on;
    document.body.classList.toggle("visitor", !on);
    const mode = document.getElementById("mode");
    if (mode) mode.textContent = on ? "operator" : "visitor (read-only: enter the token to command)";
  }

  async stop(): Promise<void> {
    try {
      await call("POST", "/api/stop");
      this.notify("emergency stop sent");
    } catch (e) {
      this.notify(`stop failed: ${(e as Error).message}`, "error");
    }
  }

  private async send(label: string, method: string, path: string, body?: unknown): Promise<void> {
    try {
      const r = await call<{ id?: number }>(method, path, body);
      this.notify(r.id !== undefined ? `${label}: trial ${r.id} started` : `${label}: ok`);
      this.onChange();
    } catch (e) {
      const err = e as ApiError;
      this.notify(`${label}: ${err.message}`, "error");
    }
  }
}

/** The unit a parameter's key names by its suffix (the project's naming rule), or "". */
export function unitOf(key: string): string {
  const units: [RegExp, string][] = [
    [/_mps2$/, "m/s²"],
    [/_mps$/, "m/s"],
    [/_radps$/, "rad/s"],
    [/_per_s$/, "1/s"],
    [/_mm$/, "mm"],
    [/_ms$/, "ms"],
    [/_us$/, "µs"],
    [/_ns$/, "ns"],
    [/_m$/, "m"],
    [/_s$/, "s"],
    [/_deg$/, "deg"],
    [/_rad$/, "rad"],
    [/_hz$/, "Hz"],
    [/_px$/, "px"],
    [/^fps$/, "frames/s"],
  ];
  return units.find(([re]) => re.test(key))?.[1] ?? "";
}

/** What the OpenAPI document says of each `section.key`: its description and built-in default. */
export type ParamSchema = Record<string, { description?: string; default?: unknown }>;

/** Reads the partial scenario's schema of `PUT /api/params` into `section.key` entries. */
export function paramSchema(openapi: unknown): ParamSchema {
  const out: ParamSchema = {};
  const doc = openapi as { paths?: Record<string, { put?: { requestBody?: { content?: Record<string, { schema?: unknown }> } } }> };
  const schema = doc.paths?.["/api/params"]?.put?.requestBody?.content?.["application/json"]?.schema as
    | { properties?: Record<string, { description?: string; properties?: Record<string, { description?: string; default?: unknown }> }> }
    | undefined;
  for (const [section, sec] of Object.entries(schema?.properties ?? {})) {
    if (sec.description) out[section] = { description: sec.description };
    for (const [key, prop] of Object.entries(sec.properties ?? {})) {
      out[`${section}.${key}`] = { description: prop.description, default: prop.default };
    }
  }
  return out;
}

const show = (v: unknown): string => (Array.isArray(v) ? v.join(", ") : typeof v === "object" && v !== null ? JSON.stringify(v) : String(v));

/**
 * The parameters panel: one input per value, grouped by section, each with its
 * unit, its description from the schema and a mark when it differs from the
 * built-in default; a filter box; the server's validation errors beside the field.
 */
export class ParamsPanel {
  private current: Record<string, Record<string, unknown>> = {};
  private schema: ParamSchema = {};
  private filterText = "";

  constructor(
    private readonly form: HTMLFormElement,
    private readonly notify: Notify,
    filter: HTMLInputElement | null = null,
  ) {
    form.addEventListener("submit", (e) => {
      e.preventDefault();
      void this.save();
    });
    filter?.addEventListener("input", () => {
      this.filterText = filter.value.trim().toLowerCase();
      this.applyFilter();
    });
  }

  /** The parameters as last loaded. */
  get params(): Record<string, Record<string, unknown>> {
    return this.current;
  }

  async load(): Promise<void> {
    try {
      const [current, openapi] = await Promise.all([
        call<Record<string, Record<string, unknown>>>("GET", "/api/params"),
        call<unknown>("GET", "/api/openapi.json").catch(() => null),
      ]);
      this.current = current;
      if (openapi) this.schema = paramSchema(openapi);
      this.render();
    } catch (e) {
      this.notify(`parameters: ${(e as Error).message}`, "error");
    }
  }

  private render(): void {
    const fields = this.form.querySelector(".fields") as HTMLElement;
    const open = new Set((Array.from(fields.querySelectorAll("details[open]")) as HTMLElement[]).map((d) => d.dataset.section));
    fields.replaceChildren();
    for (const [section, values] of Object.entries(this.current)) {
      if (typeof values !== "object" || values === null || Array.isArray(values)) continue;
      const fs = document.createElement("details");
      fs.dataset.section = section;
      fs.open = open.has(section);
      const lg = document.createElement("summary");
      lg.textContent = section;
      const secDoc = this.schema[section]?.description;
      if (secDoc) {
        const d = document.createElement("span");
        d.className = "muted";
        d.textContent = ` · ${secDoc.replace(/\.$/, "")}`;
        lg.append(d);
      }
      const count = document.createElement("span");
      count.className = "muted section-count";
      lg.append(count);
      fs.append(lg);
      let changedHere = 0;
      for (const [key, value] of Object.entries(values)) {
        const path = `${section}.${key}`;
        const meta = this.schema[path] ?? {};
        const row = document.createElement("div");
        row.className = "field";
        row.dataset.path = path;
        const label = document.createElement("label");
        const id = `param-${section}-${key}`;
        label.htmlFor = id;
        label.textContent = key;
        const unit = unitOf(key);
        if (unit) {
          const u = document.createElement("span");
          u.className = "unit";
          u.textContent = ` (${unit})`;
          label.append(u);
        }
        const input = document.createElement("input");
        input.id = id;
        input.name = path;
        input.value = show(value);
        input.dataset.kind = Array.isArray(value) ? "array" : typeof value;
        const changed = meta.default !== undefined && JSON.stringify(meta.default) !== JSON.stringify(value);
        row.classList.toggle("changed", changed);
        if (changed) {
          changedHere += 1;
          const mark = document.createElement("span");
          mark.className = "changed-mark";
          mark.textContent = "changed";
          mark.title = `default: ${show(meta.default)}`;
          label.append(" ", mark);
        }
        const err = document.createElement("span");
        err.className = "field-error";
        err.setAttribute("role", "alert");
        err.dataset.field = path;
        row.append(label, input);
        if (meta.description) {
          const d = document.createElement("small");
          d.className = "field-doc";
          d.textContent = meta.description;
          row.append(d);
        }
        row.append(err);
        fs.append(row);
      }
      const n = Object.keys(values).length;
      count.textContent = ` · ${n} values${changedHere ? `, ${changedHere} changed` : ""}`;
      if (changedHere) {
        const mark = document.createElement("span");
        mark.className = "changed-mark";
        mark.textContent = "changed";
        lg.append(" ", mark);
      }
      fields.append(fs);
    }
    this.applyFilter();
  }

  /** Shows only the fields whose name, section or description holds the filter's text. */
  private applyFilter(): void {
    const q = this.filterText;
    for (const fs of Array.from(this.form.querySelectorAll("details")) as HTMLDetailsElement[]) {
      let any = false;
      for (const row of Array.from(fs.querySelectorAll(".field")) as HTMLElement[]) {
        const text = `${row.dataset.path ?? ""} ${row.querySelector(".field-doc")?.textContent ?? ""}`.toLowerCase();
        const hit = q === "" || text.includes(q);
        row.hidden = !hit;
        any ||= hit;
      }
      fs.hidden = !any;
      // A filter opens the sections it finds something in.
      if (q !== "") fs.open = any;
    }
  }

  private collect(): Record<string, Record<string, unknown>> {
    const out: Record<string, Record<string, unknown>> = JSON.parse(JSON.stringify(this.current));
    for (const input of Array.from(this.form.querySelectorAll("input[name]")) as HTMLInputElement[]) {
      const [section, key] = input.name.split(".");
      const raw = input.value.trim();
      let v: unknown = raw;
      if (input.dataset.kind === "number") v = raw === "" ? raw : Number.isNaN(Number(raw)) ? raw : Number(raw);
      else if (input.dataset.kind === "array") v = raw.split(",").map((x) => (Number.isNaN(Number(x)) ? x.trim() : Number(x)));
      else if (input.dataset.kind === "boolean") v = raw === "true";
      if (out[section]) out[section][key] = v;
    }
    return out;
  }

  async save(): Promise<void> {
    for (const el of Array.from(this.form.querySelectorAll(".field-error"))) el.textContent = "";
    try {
      this.current = await call("PUT", "/api/params", this.collect());
      this.render();
      this.notify("parameters saved");
    } catch (e) {
      const err = e as ApiError;
      const slot = err.field ? (this.form.querySelector(`.field-error[data-field="${CSS.escape(err.field)}"]`) as HTMLElement | null) : null;
      if (slot) slot.textContent = err.message;
      this.notify(`parameters not saved: ${err.message}`, "error");
    }
  }
}
