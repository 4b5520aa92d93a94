import { ApiError, call, getToken, setToken } from "./api";

type Notify = (text: string, kind?: "info" | "error") => void;

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

/** The parameters panel: one input per number, the server's validation errors beside the field. */
export class ParamsPanel {
  private current: Record<string, Record<string, unknown>> = {};

  constructor(
    private readonly form: HTMLFormElement,
    private readonly notify: Notify,
  ) {
    form.addEventListener("submit", (e) => {
      e.preventDefault();
      void this.save();
    });
  }

  /** The parameters as last loaded. */
  get params(): Record<string, Record<string, unknown>> {
    return this.current;
  }

  async load(): Promise<void> {
    try {
      this.current = await call<Record<string, Record<string, unknown>>>("GET", "/api/params");
      this.render();
    } catch (e) {
      this.notify(`parameters: ${(e as Error).message}`, "error");
    }
  }

  private render(): void {
    const fields = this.form.querySelector(".fields") as HTMLElement;
    fields.replaceChildren();
    for (const [section, values] of Object.entries(this.current)) {
      if (typeof values !== "object" || values === null || Array.isArray(values)) continue;
      const fs = document.createElement("fieldset");
      const lg = document.createElement("legend");
      lg.textContent = section;
      fs.append(lg);
      for (const [key, value] of Object.entries(values)) {
        const path = `${section}.${key}`;
        const row = document.createElement("div");
        row.className = "field";
        const label = document.createElement("label");
        const id = `param-${section}-${key}`;
        label.htmlFor = id;
        label.textContent = key;
        const input = document.createElement("input");
        input.id = id;
        input.name = path;
        input.value = Array.isArray(value) ? value.join(", ") : String(value);
        input.dataset.kind = Array.isArray(value) ? "array" : typeof value;
        const err = document.createElement("span");
        err.className = "field-error";
        err.setAttribute("role", "alert");
        err.dataset.field = path;
        row.append(label, input, err);
        fs.append(row);
      }
      fields.append(fs);
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
