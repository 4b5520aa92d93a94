/** Messages of `/ws` (server/README.md): a mirror of `rt_core::bridge::Snapshot`. */

export type TrialState =
  | "idle" | "arming" | "armed" | "released" | "tracking"
  | "intercepting" | "holding" | "returning" | "done" | "aborted";

export interface HorizonPoint { t_s: number; x_m: number; sigma_m: number }

export interface PendulumView {
  measured: { valid: boolean; t_s: number; x_m: number };
  phi_rad: number;
  dphi_radps: number;
  sigma_phi_rad: number | null;
  x_m: number;
  sigma_x_m: number | null;
  ball_m: (number | null)[];
  truth_ball_m: (number | null)[];
  crossing_t_s: number | null;
  crossing_sigma_s: number | null;
  horizon: HorizonPoint[];
}

export interface HopfView { active: boolean; a: number; b: number; u_init: number; u_hopf: number; u_final: number }

export interface PathView {
  speed_planned_mps: number;
  speed_executed_mps: number;
  progress_planned: number;
  progress_executed: number;
  length_m: number;
  start_t_s: number | null;
  arrival_t_s: number | null;
  movement_time_s: number | null;
  intercept_m: (number | null)[];
}

export interface RobotView {
  q_rad: number[];
  q_cmd_rad: number[];
  q_limit_rad: number[];
  tool_m: (number | null)[];
  actuation_latency_ms: number | null;
}

export interface FriView {
  session: string;
  quality: string;
  period_ms: number | null;
  reply_latency_us: number | null;
  late_replies: number;
  missed_cycles: number;
}

export interface LoopTiming {
  step_us: number;
  step_max_us: number;
  period_mean_us: number;
  period_max_us: number;
  deadline_misses: number;
}

/**
 * The camera's latest detection in the full camera image's pixels, and the
 * swing plane's calibration (rt_core::bridge::CameraView). `width_px` 0: no camera.
 */
export interface CameraInfo {
  width_px: number;
  height_px: number;
  frame: number;
  t_s: number | null;
  found: boolean;
  /** Detections the detector dropped so far as inconsistent with the track and shape (a fresh count per detector: per trial in the simulated lab). */
  rejected: number;
  x_px: number | null;
  y_px: number | null;
  r_px: number | null;
  fx_px: number;
  fy_px: number;
  cx_px: number;
  cy_px: number;
  k1: number;
  k2: number;
  rest_c_m: (number | null)[];
  lateral_c: (number | null)[];
  up_c: (number | null)[];
}

export interface StateMessage {
  type: "state";
  t_s: number;
  seq: number;
  trial_id: number;
  trial_state: TrialState;
  pendulum: PendulumView;
  hopf: HopfView;
  path: PathView;
  robot: RobotView;
  fri: FriView;
  magnet: string;
  timing: LoopTiming;
  counters: Record<string, number>;
  /** Absent from services older than the camera overlays. */
  camera?: CameraInfo;
}

export interface EventMessage {
  type: "event";
  t_s: number;
  trial_id: number;
  event: { kind: string; [k: string]: unknown };
  message?: string;
}

export interface HelloMessage { type: "hello"; t_s: number; version: string; state_hz: number; token_required: boolean }

export type ServerMessage = StateMessage | EventMessage | HelloMessage;

/** Parses one `/ws` text message; `null` for anything malformed or unknown. */
export function parseMessage(text: string): ServerMessage | null {
  let v: unknown;
  try {
    v = JSON.parse(text);
  } catch {
    return null;
  }
  if (typeof v !== "object" || v === null) return null;
  const m = v as { type?: unknown; t_s?: unknown };
  if (typeof m.t_s !== "number") return null;
  switch (m.type) {
    case "state": {
      const s = v as Partial<StateMessage>;
      if (!s.pendulum || !s.hopf || !s.path || !s.robot || !s.fri || !s.timing) return null;
      if (!Array.isArray(s.robot.q_rad) || s.robot.q_rad.length !== 7) return null;
      return v as StateMessage;
    }
    case "event":
      return typeof (v as EventMessage).event === "object" ? (v as EventMessage) : null;
    case "hello":
      return v as HelloMessage;
    default:
      return null;
  }
}

/** A number for plotting: JSON `null` (the server's NaN) becomes NaN. */
export function num(v: number | null | undefined): number {
  return typeof v === "number" ? v : Number.NaN;
}
