/** The service's `GET /api/health` answer. */
export interface Health {
  status: string;
  version: string;
  uptime_s: number;
}

/** Checks that a JSON value is a health answer. */
export function parseHealth(value: unknown): Health | null {
  if (typeof value !== "object" || value === null) return null;
  const v = value as Record<string, unknown>;
  if (typeof v.status !== "string" || typeof v.version !== "string") return null;
  if (typeof v.uptime_s !== "number" || !Number.isFinite(v.uptime_s)) return null;
  return { status: v.status, version: v.version, uptime_s: v.uptime_s };
}

/** One line for a person: service state, version and uptime. */
export function describeHealth(h: Health | null): string {
  if (h === null) return "service unreachable";
  const minutes = Math.floor(h.uptime_s / 60);
  return `service ${h.status}, isochron ${h.version}, up ${minutes} min`;
}
