import { describeHealth, parseHealth } from "./health";

const line = document.getElementById("health");

async function refresh(): Promise<void> {
  try {
    const r = await fetch("/api/health");
    const h = r.ok ? parseHealth(await r.json()) : null;
    if (line) line.textContent = describeHealth(h);
  } catch {
    if (line) line.textContent = describeHealth(null);
  }
}

void refresh();
setInterval(() => void refresh(), 5000);
