// The demo kiosk page (/demo) in a real browser (Debian's Chromium through
// playwright-core) against `isochron serve --demo`, started here so the test
// can restart it. Usage: node e2e/demo.mjs PATH/TO/isochron
//
// Short (make test): the page shows >= 2 demo trials counted and plotted, its
// captions, no operator control; a calibration step pauses it and the page
// says why; the service is restarted on the same port and the page reconnects
// and goes on counting; no console error (but the refused connections while
// the service is down).
// Soak (ISOCHRON_DEMO_SOAK_S=600, make soak): that many seconds unattended:
// >= ISOCHRON_DEMO_SOAK_TRIALS (default 40) trials, the heap not growing,
// no console error, the frame rate reported (gated only with
// ISOCHRON_SOAK_FPS_MIN). ISOCHRON_DEMO_SCREENSHOT=FILE saves the page.
// Prints one line per check, a JSON line of measurements and
// "demo browser: N passed, M failed"; exits non-zero on any failure.
import { spawn } from "node:child_process";
import { existsSync, mkdtempSync, rmSync } from "node:fs";
import { createServer } from "node:net";
import { tmpdir } from "node:os";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";
import { chromium } from "playwright-core";

const [bin] = process.argv.slice(2);
if (!bin) {
  console.error("usage: node e2e/demo.mjs PATH/TO/isochron");
  process.exit(2);
}
const CHROMIUM = process.env.CHROMIUM ?? "/usr/bin/chromium";
if (!existsSync(CHROMIUM)) {
  console.error(`demo browser test: no Chromium at ${CHROMIUM} (make deps installs it)`);
  process.exit(1);
}
const SOAK_S = Number(process.env.ISOCHRON_DEMO_SOAK_S ?? 0);
const SOAK_TRIALS = Number(process.env.ISOCHRON_DEMO_SOAK_TRIALS ?? 40);
const FPS_MIN = process.env.ISOCHRON_SOAK_FPS_MIN ? Number(process.env.ISOCHRON_SOAK_FPS_MIN) : null;
const INTERVAL_S = process.env.ISOCHRON_DEMO_INTERVAL_S ?? "2";
const webDir = join(dirname(fileURLToPath(import.meta.url)), "..", "dist");
const data = mkdtempSync(join(tmpdir(), "isochron-demo-"));
const token = `demo-${Math.random().toString(36).slice(2)}`;
const results = [];
const measured = {};

async function check(name, fn) {
  const t0 = Date.now();
  try {
    await fn();
    results.push([name, true]);
    console.log(`ok   ${name} (${Date.now() - t0} ms)`);
  } catch (e) {
    results.push([name, false]);
    console.log(`FAIL ${name}: ${e && e.message ? e.message : e}`);
  }
}

function assert(cond, msg) {
  if (!cond) throw new Error(msg);
}

/** A free loopback port (the service restarts on the same one). */
const port = await new Promise((resolve, reject) => {
  const s = createServer();
  s.once("error", reject);
  s.listen(0, "127.0.0.1", () => {
    const p = s.address().port;
    s.close(() => resolve(p));
  });
});
const base = `http://127.0.0.1:${port}/`;

/** `isochron serve --demo` on the port; resolves once it listens. */
function serve() {
  const child = spawn(
    bin,
    ["serve", "--bind", `127.0.0.1:${port}`, "--token", token, "--demo", "--demo-interval-s", INTERVAL_S, "--data-dir", join(data, "db"), "--web-dir", webDir],
    { stdio: ["ignore", "pipe", "pipe"] },
  );
  let err = "";
  child.stderr.on("data", (d) => (err = (err + d).slice(-4000)));
  return new Promise((resolve, reject) => {
    const timer = setTimeout(() => reject(new Error(`isochron serve printed no address in 60 s: ${err}`)), 60_000);
    child.stdout.on("data", (d) => {
      if (String(d).includes("listening on")) {
        clearTimeout(timer);
        resolve(child);
      }
    });
    child.once("exit", (code) => {
      clearTimeout(timer);
      reject(new Error(`isochron serve exited (${code}): ${err}`));
    });
  });
}

function stop(child) {
  return new Promise((resolve) => {
    if (child.exitCode !== null) return resolve();
    child.once("exit", () => resolve());
    child.kill("SIGTERM");
  });
}

const api = async (method, path, body) => {
  const r = await fetch(new URL(path, base), {
    method,
    headers: { "Content-Type": "application/json", Authorization: `Bearer ${token}` },
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  const text = await r.text();
  return { status: r.status, json: text ? JSON.parse(text) : null };
};

let service = await serve();
const browser = await chromium.launch({
  executablePath: CHROMIUM,
  args: ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update", "--no-first-run", "--disable-sync", "--enable-precise-memory-info"],
});
const t0 = Date.now();
try {
  const context = await browser.newContext({ viewport: { width: 1920, height: 1080 } });
  const page = await context.newPage();
  // Console errors with their time: the refused connections while the service
  // is down on purpose are expected, nothing else is.
  const errors = [];
  let down = null;
  page.on("console", (m) => {
    if (m.type() === "error") errors.push({ t: Date.now(), text: m.text() });
  });
  page.on("pageerror", (e) => errors.push({ t: Date.now(), text: String(e) }));
  const unexpected = () =>
    errors.filter(
      (e) =>
        !(down && e.t >= down[0] && e.t <= down[1] && /ERR_CONNECTION_REFUSED|WebSocket connection to .* failed|Failed to load resource/.test(e.text)),
    );
  await page.goto(new URL("demo", base).href, { waitUntil: "load" });
  await page.waitForFunction(() => window.__demo !== undefined, null, { timeout: 60_000 });
  const shown = () => page.evaluate(() => window.__demo.shown());

  await check("demo: no operator controls on the page (no button, input, form or stop)", async () => {
    const n = await page.evaluate(() => document.querySelectorAll("button, input, select, textarea, form, #btn-stop").length);
    assert(n === 0, `${n} controls`);
  });
  await check("demo: every panel has its caption for visitors", async () => {
    const caps = await page.$$eval(".panel", (ps) => ps.map((p) => p.querySelector(".caption")?.textContent?.trim() ?? ""));
    assert(caps.length >= 4 && caps.every((c) => c.length > 60), JSON.stringify(caps));
    const tagline = await page.textContent(".tagline");
    assert(/same time/.test(tagline), tagline);
  });
  await check("demo: >= 2 trials run unattended are counted and plotted, with the 95% interval", async () => {
    await page.waitForFunction(() => window.__demo.shown().trials >= 2 && window.__demo.shown().points >= 2, null, { timeout: 180_000 });
    const count = await page.textContent("#demo-count");
    const ci = await page.textContent("#demo-ci");
    assert(/^\d+ of \d+$/.test(count), count);
    assert(/95% interval \d+% to \d+%/.test(ci), ci);
    measured.first_two_trials_s = (Date.now() - t0) / 1000;
  });
  await check("demo: the twin, the camera and the speed plot are live", async () => {
    const a = await page.evaluate(() => [window.__demo.twinFrames(), window.__demo.cameraFrames(), window.__demo.received()]);
    await page.waitForFunction((b) => window.__demo.twinFrames() > b[0] && window.__demo.cameraFrames() > b[1] && window.__demo.received() > b[2], a, { timeout: 60_000 });
  });
  if (SOAK_S === 0) {
    await check("demo: a calibration step pauses the demo and the page says why; it resumes by itself", async () => {
      for (const end = Date.now() + 120_000; ; ) {
        const r = await api("POST", "/api/calibration/robot");
        if (r.status === 202) break;
        assert(r.status === 409 && Date.now() < end, `calibration: ${JSON.stringify(r)}`);
        await new Promise((res) => setTimeout(res, 10));
      }
      await page.waitForFunction(() => window.__demo.shown().state === "paused", null, { timeout: 60_000 });
      const s = await shown();
      assert(/^Paused: the lab is being calibrated/.test(s.text) && /resumes by itself/.test(s.text), s.text);
      measured.paused_text = s.text;
      await page.waitForFunction(() => ["running", "waiting"].includes(window.__demo.shown().state), null, { timeout: 240_000 });
    });
    await check("demo: the service restarts: the page says it reconnects, then goes on counting", async () => {
      const before = (await shown()).trials;
      down = [Date.now(), Infinity];
      await stop(service);
      await page.waitForFunction(() => window.__demo.shown().state === "connecting", null, { timeout: 60_000 });
      const s = await shown();
      assert(/Reconnecting/.test(s.text), s.text);
      service = await serve();
      await page.waitForFunction((n) => window.__demo.shown().trials > n && window.__demo.shown().state !== "connecting", before, { timeout: 180_000 });
      down[1] = Date.now();
      measured.trials_after_restart = (await shown()).trials;
    });
  } else {
    await check(`demo soak: ${SOAK_S} s unattended: >= ${SOAK_TRIALS} trials, the heap grows < 20% after 30 s${FPS_MIN ? `, fps > ${FPS_MIN}` : ""}`, async () => {
      const cdp = await context.newCDPSession(page);
      const heap = async () => {
        await cdp.send("HeapProfiler.collectGarbage");
        return (await cdp.send("Runtime.getHeapUsage")).usedSize;
      };
      const start = Date.now();
      const trials0 = (await shown()).trials;
      await page.waitForTimeout(30_000);
      const h30 = await heap();
      const fps = [];
      while (Date.now() - start < SOAK_S * 1000) {
        await page.waitForTimeout(10_000);
        fps.push(await page.evaluate(() => window.__demo.fps()));
      }
      const hEnd = await heap();
      const s = await shown();
      measured.soak_s = (Date.now() - start) / 1000;
      measured.soak_trials = s.trials - trials0;
      measured.trials_total = s.trials;
      measured.demo = await page.evaluate(() => window.__demo.status());
      // Why any trial was aborted (reported: a loaded machine can make the lab
      // abort one, e.g. the controller's messages pausing).
      const recs = (await api("GET", "/api/trials?limit=1000")).json ?? [];
      measured.aborted = recs.filter((t) => t.status === "aborted").map((t) => `${t.id}: ${t.reason}`);
      measured.not_successful = recs.filter((t) => t.status === "done" && t.success !== true).map((t) => `${t.id}: ${t.reason}`);
      measured.heap_mb_30s = +(h30 / 1e6).toFixed(2);
      measured.heap_mb_end = +(hEnd / 1e6).toFixed(2);
      measured.heap_growth = +((hEnd - h30) / h30).toFixed(3);
      measured.fps_min = +Math.min(...fps).toFixed(1);
      measured.fps_mean = +(fps.reduce((a, b) => a + b, 0) / fps.length).toFixed(1);
      assert(s.trials - trials0 >= SOAK_TRIALS - 2 && s.trials >= SOAK_TRIALS, `${s.trials} trials`);
      assert(measured.heap_growth <= 0.2, `heap grew ${(measured.heap_growth * 100).toFixed(1)}%`);
      if (FPS_MIN !== null) assert(measured.fps_min > FPS_MIN, `fps fell to ${measured.fps_min}`);
    });
  }
  measured.fps = +(await page.evaluate(() => window.__demo.fps())).toFixed(1);
  if (process.env.ISOCHRON_DEMO_SCREENSHOT) {
    // During a motion: the arm on its way, the speed profile drawing.
    await page.waitForFunction(() => window.__demo.shown().state === "running", null, { timeout: 60_000 }).catch(() => undefined);
    await page.waitForTimeout(4_000);
    await page.screenshot({ path: process.env.ISOCHRON_DEMO_SCREENSHOT, fullPage: false });
    console.log(`screenshot: ${process.env.ISOCHRON_DEMO_SCREENSHOT}`);
  }
  await check("demo: no console errors (beyond refused connections while the service was down)", async () => {
    const u = unexpected();
    assert(u.length === 0, u.map((e) => e.text).join(" | "));
  });
  await context.close();
} finally {
  await browser.close();
  await stop(service);
  rmSync(data, { recursive: true, force: true });
}
measured.wall_s = (Date.now() - t0) / 1000;
console.log(JSON.stringify({ measured }));
const passed = results.filter(([, ok]) => ok).length;
console.log(`demo browser: ${passed} passed, ${results.length - passed} failed`);
process.exit(passed === results.length ? 0 : 1);
