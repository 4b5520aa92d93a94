/** The REST API (CONTRACT.md, "HTTP"), with the session's bearer token. */

import type { TrialRecord } from "./generated/types";

const TOKEN_KEY = "isochron.token";

export function getToken(): string {
  return sessionStorage.getItem(TOKEN_KEY) ?? "";
}

export function setToken(token: string): void {
  if (token) sessionStorage.setItem(TOKEN_KEY, token);
  else sessionStorage.removeItem(TOKEN_KEY);
}

/** An API error: the server's message and, when it names one, the field. */
export class ApiError extends Error {
  constructor(
    message: string,
    readonly status: number,
    readonly field?: string,
  ) {
    super(message);
  }
}

/** Reads `{"error": "...", "field": "..."}` from an error response. */
export async function errorOf(r: Response): Promise<ApiError> {
  try {
    const j = (await r.json()) as { error?: unknown; field?: unknown };
    const msg = typeof j.error === "string" ? j.error : `HTTP ${r.status}`;
    return new ApiError(msg, r.status, typeof j.field === "string" ? j.field : undefined);
  } catch {
    return new ApiError(`HTTP ${r.status}`, r.status);
  }
}

export async function call<T>(method: string, path: string, body?: unknown): Promise<T> {
  const headers: Record<string, string> = {};
  const token = getToken();
  if (token) headers.Authorization = `Bearer ${token}`;
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const r = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  if (!r.ok) throw await errorOf(r);
  const text = await r.text();
  return (text ? JSON.parse(text) : {}) as T;
}

/** One trial's record, as `GET /api/trials` lists them (generated from `server::records::TrialRecord`). */
export type { TrialRecord } from "./generated/types";

/** The verdict of a trial: `hit`, `miss` (aborted counts as a miss) or `null` while unfinished. */
export function verdict(t: Pick<TrialRecord, "id" | "status"> & { success?: boolean | null; reason?: string | null }): "hit" | "miss" | null {
  if (t.status === "running" || t.status === "interrupted") return null;
  if (t.status === "aborted") return "miss";
  return typeof t.success === "boolean" ? (t.success ? "hit" : "miss") : null;
}

/** `v` with its sign (`+1.2`, `-0.4`, `0.0`: never `-0.0`). */
export function signed(v: number, digits: number): string {
  const s = Math.abs(v).toFixed(digits);
  if (Number(s) === 0) return s;
  return v > 0 ? `+${s}` : `-${s}`;
}

/** What a trial row shows of its judges: which one gave the verdict, and the
 * measured judge's figures (signed timing error ± its std in ms; whether the
 * external joint torques showed a contact, or that they carried no signal). */
export function judgeCells(t: Pick<TrialRecord, "judged_by" | "measured">): {
  judge: string;
  measuredTiming: string;
  contact: string;
} {
  const m = t.measured;
  const e = m?.timing_error_ms;
  const sd = m?.timing_std_ms;
  const measuredTiming =
    typeof e === "number" && Number.isFinite(e)
      ? typeof sd === "number" && Number.isFinite(sd)
        ? `${signed(e, 1)} ± ${sd.toFixed(1)}`
        : signed(e, 1)
      : "–";
  const contact = !m ? "–" : m.torque_signal === false ? "no torques" : m.contact ? "yes" : "no";
  return { judge: t.judged_by ?? "–", measuredTiming, contact };
}

/** What a trial row shows of a strike (issue #38) as the measured judge saw
 * it, m/s: the tool's speed at contact, planned → measured, and the ball's
 * outgoing speed, predicted (the controller's rebound at its commit, from its
 * beliefs) → seen (the camera's rebound), with the seen one's error against
 * the target (`not returned` when the ball went on); `–` for a stop or an
 * unmeasured figure. A record without a prediction shows the seen speed alone. */
export function strikeCell(t: Pick<TrialRecord, "measured">): string {
  const k = t.measured?.strike;
  if (!k) return "–";
  const v = (x: number | null | undefined): string => (typeof x === "number" && Number.isFinite(x) ? x.toFixed(2) : "–");
  const tool = `tool ${v(k.planned_tool_speed_mps)} → ${v(k.tool_speed_mps)}`;
  const e = k.speed_error;
  const predicted = k.predicted ? `${v(k.predicted.ball_speed_mps)} → ` : "";
  const seen = typeof k.ball_speed_mps === "number" && Number.isFinite(k.ball_speed_mps);
  const ball = !seen
    ? `ball ${predicted}–`
    : !k.returned
      ? `ball ${predicted}${v(k.ball_speed_mps)} not returned`
      : typeof e === "number" && Number.isFinite(e)
        ? `ball ${predicted}${v(k.ball_speed_mps)} (${signed(e * 100, 0)}%)`
        : `ball ${predicted}${v(k.ball_speed_mps)}`;
  return `${tool}, ${ball}`;
}

/** The strike trials of `trials` (newest first, as `GET /api/trials` lists
 * them), at most `n`, as the demo page lists them for visitors: the trial's
 * id, whether it hit, and its strike cell. */
export function strikeLines(trials: TrialRecord[], n: number): { id: number; hit: boolean | null; text: string }[] {
  return trials
    .filter((t) => t.status === "done" && t.measured?.strike)
    .slice(0, n)
    .map((t) => ({ id: t.id, hit: t.success, text: strikeCell(t) }));
}

/** `GET /api/trials` answers a list, or an object holding one. */
export function trialList(v: unknown): TrialRecord[] {
  if (Array.isArray(v)) return v as TrialRecord[];
  if (v && typeof v === "object") {
    for (const k of ["trials", "items", "records"]) {
      const a = (v as Record<string, unknown>)[k];
      if (Array.isArray(a)) return a as TrialRecord[];
    }
  }
  return [];
}
