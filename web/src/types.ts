/**
 * Messages of `/ws` (server/README.md). Their types are generated from the Rust
 * types (`rt_core::bridge::Snapshot`, `server::lab::StateMessage`, ...) into
 * `generated/types.ts` by ts-rs: run `make types` after changing them
 * (`cargo test` fails while the file is stale). A number that may be NaN in
 * Rust is `null` in JSON.
 */
import type { AbortView, CameraView, EventMessage, Hello, StateMessage } from "./generated/types";

export type {
  EventMessage,
  FriView,
  HopfView,
  HorizonPoint,
  LoopTiming,
  PathView,
  PendulumView,
  RobotView,
  StateMessage,
  TrialState,
} from "./generated/types";

/**
 * The camera's latest detection in the full camera image's pixels, and the
 * swing plane's calibration (rt_core::bridge::CameraView). `width_px` 0: no camera.
 */
export type CameraInfo = CameraView;

export type HelloMessage = Hello;

/** Why the last trial was aborted (`Snapshot.abort`): `reason` null while none was. */
export type AbortInfo = AbortView;

/** The trial state as the dashboard shows it: an abort says why. */
export function trialStateText(s: {
  trial_state: string;
  abort?: Pick<AbortInfo, "message" | "detail"> & { reason: string | null };
}): string {
  const a = s.abort;
  if (s.trial_state !== "aborted" || !a || !a.reason) return s.trial_state;
  return `aborted: ${a.reason} (${a.message}${a.detail ? `: ${a.detail}` : ""})`;
}

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
