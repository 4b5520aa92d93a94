// The dashboard in a real browser (Debian's Chromium through playwright-core)
// against a running `isochron serve`. Usage: node e2e/dashboard.mjs URL TOKEN
// Prints one line per check, a JSON line of measurements, and
// "browser: N passed, M failed"; exits non-zero on any failure.
import { existsSync, readFileSync } from "node:fs";
import { chromium } from "playwright-core";

const [base, token] = process.argv.slice(2);
if (!base || !token) {
  console.error("usage: node e2e/dashboard.mjs URL TOKEN");
  process.exit(2);
}
const SOAK_S = Number(process.env.ISOCHRON_SOAK_S ?? 60);
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

const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
  args: [
    "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
    "--no-first-run", "--disable-sync", "--disable-quic", "--enable-precise-memory-info",
  ],
});

async function openPage() {
  const context = await browser.newContext({ viewport: { width: 1400, height: 1000 } });
  const page = await context.newPage();
  const errors = [];
  page.on("console", (m) => {
    if (m.type() === "error") errors.push(m.text());
  });
  page.on("pageerror", (e) => errors.push(String(e)));
  await page.goto(base, { waitUntil: "load" });
  await page.waitForFunction(() => window.__isochron !== undefined, null, { timeout: 60_000 });
  return { context, page, errors };
}

const api = async (method, path, body, withToken = true) => {
  const headers = { "Content-Type": "application/json" };
  if (withToken) headers.Authorization = `Bearer ${token}`;
  const r = await fetch(new URL(path, base), { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  const text = await r.text();
  return { status: r.status, json: text ? JSON.parse(text) : null };
};

/** Origins of the DH frames 0..7 of the iiwa 7 (T_i = Rz(q) Tz(d) Rx(alpha)), base frame. */
function dhOrigins(q) {
  const d = [0.34, 0, 0.4, 0, 0.4, 0, 0.126];
  const alpha = [-Math.PI / 2, Math.PI / 2, Math.PI / 2, -Math.PI / 2, -Math.PI / 2, Math.PI / 2, 0];
  let r = [1, 0, 0, 0, 1, 0, 0, 0, 1]; // row-major rotation
  let p = [0, 0, 0];
  const out = [[0, 0, 0]];
  for (let i = 0; i < 7; i++) {
    p = [p[0] + r[2] * d[i], p[1] + r[5] * d[i], p[2] + r[8] * d[i]];
    const [c, s, ca, sa] = [Math.cos(q[i]), Math.sin(q[i]), Math.cos(alpha[i]), Math.sin(alpha[i])];
    const l = [c, -s * ca, s * sa, s, c * ca, -c * sa, 0, sa, ca];
    const n = new Array(9).fill(0);
    for (let a = 0; a < 3; a++) for (let b = 0; b < 3; b++) for (let k = 0; k < 3; k++) n[a * 3 + b] += r[a * 3 + k] * l[k * 3 + b];
    r = n;
    out.push(p);
  }
  return out;
}

/** A base-frame point through the twin's camera (column-major matrices) to CSS pixels. */
function project(view, [x, y, z]) {
  const mul = (m, v) => [0, 1, 2, 3].map((row) => m[row] * v[0] + m[4 + row] * v[1] + m[8 + row] * v[2] + m[12 + row] * v[3]);
  const c = mul(view.projection, mul(view.worldToCamera, [x, y, z, 1]));
  return [((c[0] / c[3] + 1) / 2) * view.width, ((1 - c[1] / c[3]) / 2) * view.height];
}

try {
  // Visitor: streams, renders, controls disabled.
  const visitor = await openPage();
  await check("visitor: plots receive data", async () => {
    const p0 = await visitor.page.evaluate(() => window.__isochron.points());
    await visitor.page.waitForFunction(
      (before) => window.__isochron.points().slice(0, 5).every((n, i) => n > before[i] + 5),
      p0,
      { timeout: 60_000 },
    );
  });
  await check("visitor: the 3D view renders", async () => {
    await visitor.page.waitForFunction(() => window.__isochron.twinFrames() > 2, null, { timeout: 60_000 });
  });
  await check("visitor: the URDF twin shows the arm in the measured pose", async () => {
    await visitor.page.waitForFunction(() => window.__isochron.twinLoaded(), null, { timeout: 60_000 });
    // The arm is still while idle: the pose drawn is the one measured.
    const state = (await api("GET", "/api/state", undefined, false)).json;
    const names = ["link_2", "link_4", "link_6", "flange"];
    const probe = await visitor.page.evaluate((n) => window.__isochron.twinProbe(n), names);
    const view = await visitor.page.evaluate(() => window.__isochron.twinView());
    assert(probe && probe.links.length === names.length, `probe ${JSON.stringify(probe)}`);
    probe.q.forEach((q, i) => assert(Math.abs(q - state.robot.q_rad[i]) < 1e-3, `A${i + 1} drawn ${q}, measured ${state.robot.q_rad[i]}`));
    // Forward kinematics from the DH model (IIWA7.md), written here apart from the dashboard:
    // shoulder (DH frame 1) = link_2, elbow (3) = link_4, wrist (5) = link_6, flange (7).
    const origins = dhOrigins(probe.q);
    const want = { link_2: origins[1], link_4: origins[3], link_6: origins[5], flange: origins[7] };
    for (const l of probe.links) {
      const [sx, sy] = project(view, want[l.name]);
      const err = Math.hypot(sx - l.screen[0], sy - l.screen[1]);
      console.log(`  ${l.name}: FK projected (${sx.toFixed(1)}, ${sy.toFixed(1)}) px, drawn (${l.screen[0].toFixed(1)}, ${l.screen[1].toFixed(1)}) px, pixel ${l.rgba}`);
      assert(err < 1.0, `${l.name} drawn ${err.toFixed(2)} px from FK`);
      const [r, g, b] = l.rgba;
      const background = Math.abs(r - 244) + Math.abs(g - 246) + Math.abs(b - 248) < 30;
      assert(!background, `${l.name}: background pixel ${l.rgba} where the arm should be`);
      if (l.name !== "flange") assert(r > b + 60, `${l.name}: pixel ${l.rgba} is not the arm's orange`);
    }
  });
  await check("visitor: controls are disabled, the stop button is not", async () => {
    for (const id of ["btn-arm", "btn-drop", "btn-trial"]) {
      assert(await visitor.page.isDisabled(`#${id}`), `${id} enabled without a token`);
    }
    assert(await visitor.page.isEnabled("#btn-stop"), "stop disabled");
  });
  await check("visitor: the FRI panel shows version, period, quality and the doctor's findings", async () => {
    await visitor.page.waitForFunction(
      () => /^FRI 1\.15 · \d+ ms · \w+/.test(document.querySelector("#fri .fri-link")?.textContent ?? ""),
      null,
      { timeout: 60_000 },
    );
    await visitor.page.waitForSelector('#fri .fri-doctor li.problem[data-code="no_datagrams"]', { timeout: 60_000 });
    const hint = await visitor.page.textContent('#fri .fri-doctor li[data-code="no_datagrams"]');
    assert(hint.includes("ip -br addr"), `no hint in ${hint}`);
  });
  await check("visitor: at 1280, 1400 and 1920 px no panel stands mostly empty or alone beside an empty stretch", async () => {
    const report = {};
    for (const width of [1280, 1400, 1920]) {
      await visitor.page.setViewportSize({ width, height: 1000 });
      await visitor.page.waitForTimeout(300);
      const panels = await visitor.page.evaluate(() => {
        const main = document.querySelector("main").getBoundingClientRect();
        const boxes = [...document.querySelectorAll("main > .panel")].map((el) => {
          const r = el.getBoundingClientRect();
          let bottom = r.top;
          for (const c of el.querySelectorAll(":scope > *")) {
            const cr = c.getBoundingClientRect();
            if (cr.height > 0) bottom = Math.max(bottom, cr.bottom);
          }
          return { name: el.getAttribute("aria-label"), left: r.left, right: r.right, top: r.top, bottom: r.bottom, fill: (bottom - r.top) / r.height };
        });
        return boxes.map((b) => ({
          ...b,
          // Empty width right of the panel on its rows (no other panel there).
          emptyRight: boxes.some((o) => o !== b && o.left >= b.right - 1 && o.top < b.bottom && o.bottom > b.top) ? 0 : main.right - b.right,
        }));
      });
      report[width] = Object.fromEntries(panels.map((p) => [p.name, +p.fill.toFixed(2)]));
      for (const p of panels) {
        assert(p.fill >= 0.75, `${width} px: the ${p.name} panel's content fills ${(p.fill * 100).toFixed(0)}% of it`);
        assert(p.emptyRight < 60, `${width} px: ${p.emptyRight.toFixed(0)} px empty beside the ${p.name} panel`);
      }
    }
    measured.panel_fill = report;
    await visitor.page.setViewportSize({ width: 1400, height: 1000 });
  });
  await check("visitor: the calibration view says what it will show before a step runs", async () => {
    const v = await visitor.page.evaluate(() => {
      const c = document.querySelector("#calibration canvas.cal-view");
      const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
      let light = 0;
      for (let i = 0; i < d.length; i += 4) if (d[i] + d[i + 1] + d[i + 2] > 450) light += 1;
      return { placeholder: c.dataset.placeholder, light };
    });
    assert(v.placeholder === "true" && v.light > 200, JSON.stringify(v));
  });
  await check("visitor: parameters are grouped by section with units and descriptions; the filter box filters", async () => {
    await visitor.page.waitForSelector('.field[data-path="pendulum.length_m"] .field-doc', { state: "attached", timeout: 60_000 });
    const sections = await visitor.page.$$eval("#params details[data-section]", (d) => d.map((x) => x.dataset.section));
    assert(["pendulum", "task", "camera", "robot", "ekf"].every((s) => sections.includes(s)), `sections ${sections}`);
    const unit = await visitor.page.textContent('.field[data-path="pendulum.length_m"] .unit');
    assert(unit.trim() === "(m)", `unit ${unit}`);
    const docs = await visitor.page.$$eval("#params .field", (f) => [f.length, f.filter((x) => (x.querySelector(".field-doc")?.textContent ?? "").length > 5).length]);
    assert(docs[0] > 40 && docs[1] / docs[0] > 0.9, `${docs[1]} of ${docs[0]} fields have a description`);
    await visitor.page.fill("#param-filter", "latency");
    const shown = await visitor.page.$$eval("#params .field", (f) => f.filter((x) => x.offsetParent !== null).map((x) => `${x.dataset.path} ${x.querySelector(".field-doc")?.textContent ?? ""}`));
    assert(shown.length > 0 && shown.length < docs[0] / 3 && shown.every((t) => /latency/i.test(t)), `filter "latency" shows ${shown.length}: ${shown.slice(0, 5)}`);
    await visitor.page.fill("#param-filter", "");
    const hidden = await visitor.page.$$eval("#params .field", (f) => f.filter((x) => x.hidden).length);
    assert(hidden === 0, `${hidden} fields still hidden with the filter cleared`);
  });
  await check("visitor: the executed path speed is filtered, the caption says how, the raw one is a checkbox away", async () => {
    const cap = await visitor.page.textContent("#plot-speed .plot-caption");
    assert(/centered moving average of 9 samples/.test(cap), cap);
    const rawOff = () => visitor.page.evaluate(() => [...document.querySelectorAll("#plot-speed .u-legend .u-series")].find((e) => /raw/.test(e.textContent))?.classList.contains("u-off"));
    assert((await rawOff()) === true, "the raw series is shown by default");
    await visitor.page.check("#speed-raw");
    assert((await rawOff()) === false, "the checkbox does not show the raw series");
    await visitor.page.uncheck("#speed-raw");
  });
  await check("visitor: no console errors", async () => {
    assert(visitor.errors.length === 0, visitor.errors.join(" | "));
  });
  await visitor.context.close();

  // Operator.
  const op = await openPage();
  const { page } = op;
  await page.fill("#token", token);
  await page.click("#token-form button[type=submit]");
  await check("operator: the token enables the controls", async () => {
    await page.waitForFunction(() => !document.querySelector("#btn-trial").disabled, null, { timeout: 60_000 });
  });
  await check("operator: an invalid parameter shows the server's message beside the field, nothing changes", async () => {
    const before = await api("GET", "/api/params");
    await page.fill("#param-filter", "length_m");
    await page.waitForSelector('input[name="pendulum.length_m"]', { timeout: 60_000 });
    await page.fill('input[name="pendulum.length_m"]', "-1");
    await page.click("#params button[type=submit]");
    const slot = '.field-error[data-field="pendulum.length_m"]';
    await page.waitForFunction((s) => document.querySelector(s)?.textContent?.length > 0, slot, { timeout: 60_000 });
    const text = await page.textContent(slot);
    assert(/length_m/.test(text), `message does not name the field: ${text}`);
    const after = await api("GET", "/api/params");
    assert(JSON.stringify(before.json) === JSON.stringify(after.json), "parameters changed");
    await page.fill('input[name="pendulum.length_m"]', String(before.json.pendulum.length_m));
  });
  await check("operator: a parameter changed from its default is marked; set back, the mark goes", async () => {
    const mark = '.field[data-path="success.timing_tolerance_ms"] .changed-mark';
    const was = (await api("GET", "/api/params")).json.success.timing_tolerance_ms;
    await page.fill("#param-filter", "timing_tolerance_ms");
    assert((await page.locator(mark).count()) === 0, "marked before any change");
    await page.fill('input[name="success.timing_tolerance_ms"]', String(was + 5));
    await page.click("#params button[type=submit]");
    await page.waitForSelector(mark, { timeout: 60_000 });
    const title = await page.getAttribute(mark, "title");
    assert(title === `default: ${was}`, `mark's title ${title}`);
    assert((await api("GET", "/api/params")).json.success.timing_tolerance_ms === was + 5, "not saved");
    await page.fill('input[name="success.timing_tolerance_ms"]', String(was));
    await page.click("#params button[type=submit]");
    await page.waitForSelector(mark, { state: "detached", timeout: 60_000 });
    await page.fill("#param-filter", "");
  });
  await check("operator: the Controls panel lists the devices that keep the lab from trials, and none when all deliver", async () => {
    // The simulated lab's devices all deliver once it commands: no list.
    await page.waitForFunction(() => document.querySelector("#devices")?.hidden === true, null, { timeout: 60_000 });
    // A lab whose camera and magnet do not answer (the health answer as a
    // real lab pointing at nothing gives it): each named with why.
    const problems = [
      { device: "camera", message: "the camera delivers no frames: cannot open http://10.0.0.9/mjpg: nothing answers" },
      { device: "magnet", message: "the magnet's board on /dev/ttyACM0 does not answer: No such file or directory" },
    ];
    await page.route("**/api/health", async (route) => {
      const real = await route.fetch();
      const body = { ...(await real.json()), ready: false, devices: problems };
      await route.fulfill({ response: real, json: body });
    });
    await page.waitForFunction(() => document.querySelectorAll("#devices li").length === 2, null, { timeout: 60_000 });
    const items = await page.$$eval("#devices li", (lis) => lis.map((li) => [li.dataset.device, li.textContent]));
    assert(items[0][0] === "camera" && /nothing answers/.test(items[0][1]), JSON.stringify(items));
    assert(items[1][0] === "magnet" && /ttyACM0/.test(items[1][1]), JSON.stringify(items));
    await page.unroute("**/api/health");
    await page.waitForFunction(() => document.querySelector("#devices")?.hidden === true, null, { timeout: 60_000 });
  });
  let rowsBefore = 0;
  await check("operator: Run trial releases the ball", async () => {
    rowsBefore = await page.locator("#trials tbody tr").count();
    await page.click("#btn-trial");
    await page.waitForFunction(() => ["tracking", "intercepting"].includes(window.__isochron.state()), null, { timeout: 60_000 });
  });
  await check("operator: above a running trial's row the summary does not say 'no trials yet'", async () => {
    await page.waitForFunction(() => [...document.querySelectorAll("#trials tbody td[data-col=result]")].some((td) => td.textContent === "running"), null, { timeout: 60_000 });
    const summary = await page.textContent("#trials .summary");
    assert(summary !== "no trials yet" && /running|precisely timed/.test(summary), `summary: ${summary}`);
  });
  await check("operator: the camera view shows changing frames with the ball overlay on the ball", async () => {
    // The canvas's pixels (subsampled luminance), the yellow ball's pixels near the
    // overlay's circle, and what the overlay drew, read in one go (consistent).
    const sample = () =>
      page.evaluate(() => {
        const c = document.querySelector("#camera canvas.frame");
        const cam = window.__isochron.camera();
        const { width: w, height: h } = c;
        if (!w || !h) return { w, h, cam };
        const d = c.getContext("2d").getImageData(0, 0, w, h).data;
        const luma = [];
        let sum = 0, sum2 = 0;
        for (let i = 0; i < w * h; i += 7) {
          const l = 0.299 * d[4 * i] + 0.587 * d[4 * i + 1] + 0.114 * d[4 * i + 2];
          luma.push(l);
          sum += l;
          sum2 += l * l;
        }
        const mean = sum / luma.length;
        const std = Math.sqrt(Math.max(0, sum2 / luma.length - mean * mean));
        // Optic-yellow pixels within 4 radii of the drawn ball.
        let yellow = null;
        const b = cam.drawn.ball;
        if (b) {
          const [bx, by, br] = b;
          const R = 4 * br;
          let n = 0, sx = 0, sy = 0;
          for (let y = Math.max(0, Math.floor(by - R)); y < Math.min(h, by + R); y++) {
            for (let x = Math.max(0, Math.floor(bx - R)); x < Math.min(w, bx + R); x++) {
              const k = 4 * (y * w + x);
              const [r, g, bl] = [d[k], d[k + 1], d[k + 2]];
              if (g > 140 && r > 100 && g - bl > 70 && r - bl > 40) {
                n += 1;
                sx += x;
                sy += y;
              }
            }
          }
          yellow = n > 0 ? { n, x: sx / n, y: sy / n } : { n: 0 };
        }
        return { w, h, cam, luma, mean, std, yellow };
      });
    await page.waitForFunction(() => window.__isochron.camera().frames >= 3, null, { timeout: 60_000 });
    const first = await sample();
    const t0 = Date.now();
    // The frame counter grows at the stream's rate.
    await page.waitForFunction((n) => window.__isochron.camera().frames >= n + 8, first.cam.frames, { timeout: 60_000 });
    const samples = [first];
    for (let i = 0; i < 8; i++) {
      await page.waitForFunction((n) => window.__isochron.camera().frames > n, samples[samples.length - 1].cam.frames, { timeout: 60_000 });
      samples.push(await sample());
    }
    const last = samples[samples.length - 1];
    const fps = ((last.cam.frames - first.cam.frames) * 1000) / (Date.now() - t0);
    assert(last.w >= 160 && last.h >= 90, `canvas ${last.w}x${last.h}`);
    // Not blank: a textured scene, not one colour.
    assert(last.std > 8, `the frame is flat (luminance std ${last.std.toFixed(1)})`);
    // Changes over time: the swinging ball moves pixels (the scene around it is still).
    let changed = 0;
    for (let i = 0; i < first.luma.length; i++) if (Math.abs(first.luma[i] - last.luma[i]) > 25) changed += 1;
    assert(changed >= 5, `frames do not change (${changed} of ${first.luma.length} sampled pixels)`);
    // The ball overlay sits on the yellow ball in the frame it was drawn over.
    const offsets = [];
    for (const s of samples) {
      const b = s.cam.drawn.ball;
      if (!b || !s.yellow || s.yellow.n < 0.25 * Math.PI * (b[2] - 3) ** 2) continue;
      offsets.push({ d: Math.hypot(s.yellow.x - b[0], s.yellow.y - b[1]), r: b[2] - 3 });
    }
    assert(offsets.length >= samples.length / 2, `ball overlay over the ball in ${offsets.length} of ${samples.length} frames`);
    // ... and it is the ball that moves: its pixels travel across the frames.
    const seen = samples.filter((x) => x.yellow && x.yellow.n > 0).map((x) => x.yellow);
    let travel = 0;
    for (const p of seen) for (const q of seen) travel = Math.max(travel, Math.hypot(p.x - q.x, p.y - q.y));
    assert(travel > 2 * offsets[0].r, `the ball moved ${travel.toFixed(1)} px over the frames`);
    offsets.sort((a, b) => a.d - b.d);
    const med = offsets[Math.floor(offsets.length / 2)];
    measured.camera = {
      fps: +fps.toFixed(1),
      frame_px: [last.w, last.h],
      ball_r_px: +med.r.toFixed(1),
      overlay_offset_px: { median: +med.d.toFixed(1), max: +offsets[offsets.length - 1].d.toFixed(1) },
      ball_travel_px: +travel.toFixed(1),
      changed_pixels: changed,
      predicted_points: last.cam.drawn.predicted,
      decode_errors: last.cam.decodeErrors,
    };
    // The rate is reported, not gated (a loaded machine slows it): that the
    // frames advance is what the waits above required.
    // Each frame carries its number, so the overlay is its own detection: off by
    // the detector's error (~1 px), not by the ball's travel between frames.
    assert(med.d <= 3, `ball overlay ${med.d.toFixed(1)} px off the ball (radius ${med.r.toFixed(1)} px)`);
    assert(last.cam.drawn.intercept !== null, "no intercept point drawn");
    assert(samples.some((x) => x.cam.drawn.predicted > 0), "no predicted positions drawn");
  });
  await check("operator: Run trial completes a trial and the history shows it", async () => {
    // Finished, whatever the verdict: hit, miss, or done but not judged (the
    // measured judge says so when it could not see the pass).
    await page.waitForFunction(
      (n) => {
        const rows = document.querySelectorAll("#trials tbody tr");
        const result = rows[0]?.querySelector("td[data-col=result]")?.textContent;
        return rows.length > n && ["hit", "miss", "done", "aborted"].includes(result);
      },
      rowsBefore,
      { timeout: 90_000 },
    );
    measured.history_summary = await page.textContent("#trials .summary");
  });
  await check("operator: the finished trial's row shows the measured judge's verdict, and the world's truth of it is written", async () => {
    const row = await page.evaluate(() => {
      const tr = document.querySelector("#trials tbody tr");
      const cell = (c) => tr?.querySelector(`td[data-col="${c}"]`)?.textContent ?? null;
      return { id: cell("id"), result: cell("result"), judge: cell("judge"), timing: cell("timing"), measured: cell("measured-timing"), contact: cell("contact") };
    });
    measured.trial_row = row;
    const rec = (await api("GET", `/api/trials/${row.id}`, undefined, false)).json;
    // The simulated lab of `serve` is a truthful world behind a real lab's
    // interfaces: the lab judges by what it measures (camera, joint torques).
    if (rec.judged_by == null) {
      // Not judged (the pass not seen on a starved machine): the record says why.
      assert(rec.status === "aborted" || /^not judged \(measured\)/.test(rec.reason ?? ""), `unjudged record: ${JSON.stringify(rec)}`);
      measured.trial_unjudged = rec.reason;
      return;
    }
    const m = rec.measured;
    assert(m && typeof m.timing_error_ms === "number" && typeof m.timing_std_ms === "number", `no measured timing in the record: ${JSON.stringify(rec)}`);
    assert(rec.judged_by === "measured" && row.judge === "measured", `judge: row ${row.judge}, record ${rec.judged_by}`);
    assert(row.result === (rec.success ? "hit" : "miss"), `result ${row.result}, record success ${rec.success}`);
    assert(row.timing === rec.timing_error_ms.toFixed(1), `timing ${row.timing} vs ${rec.timing_error_ms}`);
    const parts = /^([+-]?\d+\.\d) ± (\d+\.\d)$/.exec(row.measured ?? "");
    assert(parts, `measured timing cell reads ${JSON.stringify(row.measured)}`);
    assert(Math.abs(Number(parts[1]) - m.timing_error_ms) <= 0.05 + 1e-9 && Math.abs(Number(parts[2]) - m.timing_std_ms) <= 0.05 + 1e-9,
      `measured cell ${row.measured} vs ${m.timing_error_ms} ± ${m.timing_std_ms} ms`);
    const contact = m.torque_signal === false ? "no torques" : m.contact ? "yes" : "no";
    assert(row.contact === contact, `contact cell ${row.contact}, record ${JSON.stringify(m)}`);
    // The world's own truth of that release (its truth file, one line per
    // release, paired by the coil's release within the trial).
    const dir = process.env.ISOCHRON_DATA_DIR;
    assert(dir, "ISOCHRON_DATA_DIR (the service's data folder) not given");
    const file = `${dir}/world-truth.jsonl`;
    let truth = null;
    for (const t0 = Date.now(); truth === null; ) {
      const lines = existsSync(file) ? readFileSync(file, "utf8").split("\n").filter((l) => l.trim()).map((l) => JSON.parse(l)) : [];
      truth = lines.find((l) => l.coil_off_unix_s >= rec.started_unix_s && l.coil_off_unix_s <= rec.finished_unix_s) ?? null;
      if (truth === null) {
        assert(Date.now() - t0 < 30_000, `no truth line in ${file} for trial ${rec.id} (${lines.length} lines)`);
        await page.waitForTimeout(250);
      }
    }
    measured.trial_measured = { timing_error_ms: m.timing_error_ms, timing_std_ms: m.timing_std_ms, contact: m.contact, torque_signal: m.torque_signal, world_timing_error_ms: truth.timing_error_ms, world_contact: truth.contact, world_not_judged: truth.not_judged };
    assert(truth.world === "truthful", `the served world: ${truth.world}`);
    // How the measured judge agrees with the world's own judgement is
    // reported here, and asserted by the world's tests, which run alone
    // (tests/tests/world): beside a browser and `stress-ng` the world's
    // webcam renders its frames later than it draws them (its camera is then
    // not the truthful one it claims), and the measured judge, which times
    // the pass by the camera, read -67.9 ms for the world's +17.5 ms.
    measured.trial_agreement = truth.not_judged != null
      ? `the world did not judge: ${truth.not_judged}`
      : `contact ${m.contact === truth.contact ? "agrees" : "differs"}; timing measured ${m.timing_error_ms.toFixed(1)} ms, the world's ${truth.timing_error_ms?.toFixed(1)} ms`;
    // The measured judge's columns are named as such.
    const heads = await page.$$eval("#trials thead th", (th) => th.map((x) => x.textContent));
    assert(heads.includes("measured judge: timing (ms)") && heads.includes("measured judge: contact"), heads.join(" | "));
  });
  await check("operator: when the trial ended the speed axis fit the planned peak and the pendulum axis read distinct labels in a unit that fits (mm below 1 m)", async () => {
    await page.waitForFunction(() => window.__isochron.trialEndAxes() !== null, null, { timeout: 60_000 });
    const a = await page.evaluate(() => window.__isochron.trialEndAxes());
    measured.axes_at_trial_end = a;
    const p = a.speed.planned_peak;
    assert(p > 0.05, `no planned motion in the speed plot's window (peak ${p})`);
    assert(a.speed.min === 0, `speed axis starts at ${a.speed.min}`);
    assert(a.speed.max >= p && a.speed.max <= 1.5 * p * 1.1 + 1e-9,
      `speed axis 0..${a.speed.max} m/s for a planned peak of ${p} m/s (executed peak ${a.speed.executed_peak})`);
    const t = a.pendulum.ticks;
    assert(t.length >= 2 && new Set(t).size === t.length, `pendulum tick labels: ${t.join(", ")}`);
    assert(!t.some((x) => /^-0(\.0*)?$/.test(x)), `a tick reads -0: ${t.join(", ")}`);
    // Units that fit the values: millimetres while everything in view is below 1 m,
    // metres only when the view reaches 1 m (a 1.93 m pendulum released at 35 deg
    // swings 1.1 m to the side).
    const size = Math.max(...t.map((x) => Math.abs(Number(x))));
    if (/\(mm\)$/.test(a.pendulum.title)) {
      assert(size < 1000, `pendulum axis in mm with a tick at ${size} mm`);
    } else {
      assert(/\(m\)$/.test(a.pendulum.title), `pendulum title ${a.pendulum.title}`);
      assert(size >= 0.5, `pendulum axis in metres for motions of millimetres: ${t.join(", ")}`);
    }
  });
  await check("operator: during the trial the phase portrait traced the Hopf limit cycle from rest and back", async () => {
    const p = await page.evaluate(() => window.__isochron.phase());
    measured.phase = {
      points: p.points,
      max_a_mps: +p.max_a.toFixed(3),
      b_range: [+p.min_b.toFixed(3), +p.max_b.toFixed(3)],
      first: p.first.map((v) => +v.toFixed(3)),
      last: p.last.map((v) => +v.toFixed(3)),
    };
    assert(p.motions >= 1 && p.points >= 30, `portrait has ${p.points} points over ${p.motions} motions`);
    // Peak path speed 2 R_h: a real motion, not the rest point.
    assert(p.max_a > 0.05, `peak a ${p.max_a}`);
    // The limit cycle is a circle of radius R_h = max_a / 2 around (R_h, 0): b goes
    // down to -R_h and up to +R_h (a line or a stuck point would not).
    const rh = p.max_a / 2;
    assert(p.min_b < -0.6 * rh && p.max_b > 0.6 * rh, `b spans [${p.min_b}, ${p.max_b}], R_h ${rh}`);
    // From rest to the arrival back at rest.
    assert(Math.hypot(...p.first) < 0.3 * rh, `first point ${p.first} is not at rest`);
    assert(Math.hypot(...p.last) < 0.3 * rh, `last point ${p.last} is not at rest`);
  });
  await check("operator: the neuron plot switched u_init -> u_hopf -> u_final, u_hopf for the movement time", async () => {
    const T = (await api("GET", "/api/params")).json.task.movement_time_s;
    const leads = await page.evaluate(() => window.__isochron.neurons());
    const seq = leads.map((l) => l.neuron);
    measured.neuron_leads = leads.map((l) => `${l.neuron} ${(l.t1_s - l.t0_s).toFixed(2)} s`);
    const k = seq.lastIndexOf("hopf");
    assert(k > 0 && seq[k - 1] === "init" && seq[k + 1] === "final", `leads: ${seq.join(" -> ")}`);
    const dur = leads[k].t1_s - leads[k].t0_s;
    assert(Math.abs(dur - T) < 0.15, `u_hopf led for ${dur.toFixed(3)} s, the movement time is ${T} s`);
  });
  await check("operator: the estimate and its 2σ band continue after the trial", async () => {
    await page.waitForTimeout(1_500);
    const a = await page.evaluate(() => window.__isochron.axes());
    assert(a.estimate_finite_last_s > 0.9, `${(a.estimate_finite_last_s * 100).toFixed(0)}% of the last second has an estimate`);
  });
  await check("operator: the page keeps the operator heartbeat", async () => {
    const n0 = await page.evaluate(() => window.__isochron.heartbeats());
    await page.waitForFunction((n) => window.__isochron.heartbeats() >= n + 3, n0, { timeout: 60_000 });
  });
  await check("operator: the emergency stop key stops a running motion", async () => {
    await page.click("#btn-trial");
    await page.waitForFunction(() => window.__isochron.state() === "intercepting", null, { timeout: 90_000 });
    // Every state the page shows from the key on (a short "aborted" followed by
    // the return home must not slip between two polls).
    await page.evaluate(() => {
      window.__seen = [];
      const watch = () => {
        const s = window.__isochron.state();
        if (window.__seen[window.__seen.length - 1] !== s) window.__seen.push(s);
        window.__seenTimer = requestAnimationFrame(watch);
      };
      watch();
    });
    await page.keyboard.press("Escape");
    try {
      await page.waitForFunction(() => window.__seen.some((s) => s === "aborted" || s === "idle"), null, { timeout: 60_000 });
    } catch (e) {
      // Say where it stood: still moving, or ended by itself before the key (a race).
      const now = await api("GET", "/api/state");
      throw new Error(`${e.message}: the page showed ${JSON.stringify(await page.evaluate(() => window.__seen))}, the lab ${now.json.trial_state}`);
    } finally {
      await page.evaluate(() => cancelAnimationFrame(window.__seenTimer));
    }
    const st = await api("GET", "/api/state");
    assert(st.json.trial_state !== "intercepting", `still intercepting: ${st.json.trial_state}`);
  });
  await check("operator: over both trials (arming, returning home, stopping) the executed path speed never spiked", async () => {
    const a = await page.evaluate(() => window.__isochron.axes());
    measured.speed_peaks = a.peaks;
    // The tool of an iiwa 7 does not reach 3 m/s; a spike from timing jitter did (~100 m/s).
    assert(a.peaks.executed < 3, `executed path speed peaked at ${a.peaks.executed} m/s (planned ${a.peaks.planned})`);
  });
  await check("script: a strike posted over REST on this stopping lab shows in the trial history's strike column as its record has it", async () => {
    // The lab comes back ready after the last trial (home, the magnet's
    // board): a refusal while it does is waited out, not a failure.
    let id = null;
    for (const t0 = Date.now(); id === null; ) {
      const r = await api("POST", "/api/trials", { distance_m: 0.6, mode: "strike", strike_speed_mps: 0.45 });
      if (r.status === 202) id = r.json.id;
      else {
        assert(r.status === 409 && Date.now() - t0 < 90_000, `POST a strike: ${r.status} ${JSON.stringify(r.json)}`);
        await page.waitForTimeout(500);
      }
    }
    await page.waitForFunction(
      (want) => {
        const tr = document.querySelector("#trials tbody tr");
        const result = tr?.querySelector("td[data-col=result]")?.textContent;
        return tr?.querySelector("td[data-col=id]")?.textContent === String(want) && ["hit", "miss", "done", "aborted"].includes(result);
      },
      id,
      { timeout: 90_000 },
    );
    const rec = (await api("GET", `/api/trials/${id}`, undefined, false)).json;
    const cellText = await page.textContent('#trials tbody tr td[data-col="strike"]');
    measured.strike_row = { cell: cellText, reason: rec.reason };
    const k = rec.measured?.strike;
    if (rec.status === "aborted" || !k) {
      // A starved machine's trial: ended or not judged, and it says why.
      assert(rec.status === "aborted" || /^not judged \(measured\)/.test(rec.reason ?? ""), `a strike without its figures: ${JSON.stringify(rec)}`);
      return;
    }
    assert(k.planned_tool_speed_mps === 0.45, `planned ${k.planned_tool_speed_mps}: ${JSON.stringify(k)}`);
    const two = (x) => (typeof x === "number" && Number.isFinite(x) ? x.toFixed(2) : "–");
    assert(cellText.startsWith(`tool 0.45 → ${two(k.tool_speed_mps)}, ball ${k.predicted ? `${two(k.predicted.ball_speed_mps)} → ` : ""}`), `strike cell "${cellText}" for ${JSON.stringify(k)}`);
    const p = await api("GET", "/api/params");
    assert(p.json.task.mode === "stop", `the parameters in force changed to ${p.json.task.mode}`);
  });
  // The Calibration panel walks through every step on the simulated lab (its
  // world's webcam, cabinet and board; the world's operator holds the board,
  // fits the marker, hangs the ball where the prompts say and stops it by
  // hand when the contact step asks).
  const STEPS = ["camera", "latency", "pendulum", "camera-robot", "robot", "contact"];
  const calState = (step) => page.locator(`#calibration li[data-step="${step}"] .cal-state`).textContent();
  const calFile = async () => (await api("GET", "/api/calibration")).json;
  await check("operator: the Calibration panel lists the steps in order and refuses a step whose prerequisites are missing", async () => {
    await page.waitForFunction((n) => document.querySelectorAll("#calibration li[data-step]").length === n, STEPS.length, { timeout: 60_000 });
    const order = await page.$$eval("#calibration li[data-step]", (li) => li.map((l) => l.dataset.step));
    assert(JSON.stringify(order) === JSON.stringify(STEPS), `order ${order}`);
    const before = await calFile();
    assert(before.steps.every((s) => !s.done), "a fresh lab has a calibration");
    assert(before.trials_refused === null, "the simulated lab refuses trials");
    assert(/^the simulated lab: a truthful world/.test(before.source), `source: ${before.source}`);
    // Camera-robot needs the camera and the pendulum: the button is disabled
    // and says so; the API refuses.
    const btn = page.locator('#calibration li[data-step="camera-robot"] button');
    assert(await btn.isDisabled(), "camera-robot's button is enabled before the camera step");
    assert(/needs camera/.test(await calState("camera-robot")), await calState("camera-robot"));
    const r = await api("POST", "/api/calibration/camera-robot");
    assert(r.status === 409 && r.json.reason === "prerequisites" && /camera/.test(r.json.error), JSON.stringify(r));
    const after = await calFile();
    assert(JSON.stringify(after.steps) === JSON.stringify(before.steps), "the refused step changed the file");
  });
  // What a person clicks again: a step refused for a passing reason (a
  // starved machine's frames too irregular to time the LED, a board that
  // answered late, a robot that left commanding for a moment).
  const PASSING = /arrive too irregularly|magnet device|left commanding|moving the arm home was stopped/;
  const runStep = async (step) => {
    const t0 = Date.now();
    let job;
    for (let attempt = 1; ; attempt++) {
      const idBefore = (await calFile()).job.id;
      await page.click(`#calibration li[data-step="${step}"] button`);
      for (;;) {
        job = (await calFile()).job;
        if (job.id > idBefore && job.state !== "running") break;
        assert(Date.now() - t0 < 240_000 * attempt, `calibrate ${step}: still running after ${(Date.now() - t0) / 1000} s`);
        await page.waitForTimeout(200);
      }
      if (job.state === "done" || attempt >= 3 || !PASSING.test(job.message || "")) break;
      console.log(`calibrate ${step}: refused for a passing reason (attempt ${attempt}), clicked again: ${job.message}`);
    }
    assert(job.state === "done", `calibrate ${step}: ${job.state}: ${job.message}`);
    assert(job.step === step && job.progress === 1, JSON.stringify(job).slice(0, 300));
    await page.waitForFunction((s) => document.querySelector(`#calibration li[data-step="${s}"]`)?.dataset.done === "true", step, { timeout: 60_000 });
    // The page shows this job finished (a step run again was already done:
    // its row says so before the page has drawn the new job's view).
    await page.waitForFunction((id) => {
      const m = document.querySelector("#calibration .cal-message");
      return m?.dataset.job === String(id) && m.dataset.state === "done";
    }, job.id, { timeout: 60_000 });
    const pts = Number(await page.getAttribute("#calibration canvas.cal-view", "data-points"));
    assert(pts > 0, `calibrate ${step}: the view shows no points`);
    const text = await calState(step);
    assert(/✓/.test(text) && !/–/.test(text.split("·").slice(1).join("")), `calibrate ${step}: the row shows ${text}`);
    measured[`calibrate_${step}_s`] = (Date.now() - t0) / 1000;
    return job;
  };
  const RUN = STEPS;
  await check("operator: the Calibration panel runs every step in order and shows each result; on the truthful world they measure its truth", async () => {
    // The truthful world's robot and contact are what the fresh lab believes.
    const truth = (await api("GET", "/api/params")).json;
    for (const step of RUN) await runStep(step);
    const s = await calFile();
    assert(s.steps.filter((x) => RUN.includes(x.name)).every((x) => x.done && x.record && x.record.revision && x.record.date), JSON.stringify(s.steps).slice(0, 400));
    const result = (name) => s.steps.find((x) => x.name === name).record.result;
    // The camera-robot step meets the rest pixel's ray with the swing plane
    // where the pendulum hangs (the trials moved the stand: on the
    // configured plane instead the offset came out ~1 cm at 0.40 m).
    const off = result("camera-robot").intercept_offset_m;
    const offMm = Math.hypot(...off) * 1000;
    measured.intercept_offset_mm = +offMm.toFixed(2);
    measured.intercept_m = result("camera-robot").intercept_m.map((v) => +v.toFixed(4));
    assert(offMm < 5, `camera-robot: intercept offset ${off.map((v) => (v * 1000).toFixed(1)).join(", ")} mm on a truthful world`);
    // The knock's torque onset: the torque estimate's lag plus half the pulse.
    const due = truth.success.torque_lag_periods * truth.robot.fri_period_ms + truth.success.contact_pulse_ms / 2;
    const got = result("contact").onset_offset_ms;
    measured.contact_onset_offset_ms = { got: +got.toFixed(2), due };
    assert(Math.abs(got - due) < 5, `contact: onset offset ${got.toFixed(2)} ms, the truthful world's ${due} ms`);
  });
  await check("operator: a calibration step run again shows what changed; a swing too small is refused and writes nothing", async () => {
    // The LED step again (fresh switch phases and frame noise: its numbers move).
    const job = await runStep("latency");
    assert(job.first === false && job.changes.length > 0, `first ${job.first}, changes ${JSON.stringify(job.changes)}`);
    await page.waitForFunction(() => document.querySelectorAll("#calibration .cal-changes tr").length > 0, null, { timeout: 60_000 });
    const cap = await page.textContent("#calibration .cal-changes caption");
    assert(cap.includes(`changes from the last calibration (${job.changes.length})`), cap);
    const before = (await calFile()).steps.find((x) => x.name === "pendulum").record;
    const r = await api("POST", "/api/calibration/pendulum", { release_deg: 1 });
    assert(r.status === 202, JSON.stringify(r));
    let j;
    for (const t0 = Date.now(); ; ) {
      j = (await calFile()).job;
      if (j.id === r.json.id && j.state !== "running") break;
      assert(Date.now() - t0 < 120_000, "the small swing still runs");
      await page.waitForTimeout(200);
    }
    assert(j.state === "failed" && /swing too small/.test(j.message), `${j.state}: ${j.message}`);
    await page.waitForFunction(() => /swing too small/.test(document.querySelector("#calibration .cal-message")?.textContent ?? ""), null, { timeout: 60_000 });
    const after = (await calFile()).steps.find((x) => x.name === "pendulum").record;
    assert(JSON.stringify(after) === JSON.stringify(before), "the refused swing changed the file");
    const bad = await api("POST", "/api/calibration/pendulum", { release_deg: "x" });
    assert(bad.status === 400 && bad.json.field === "release_deg", JSON.stringify(bad));
  });
  await check("operator: no console errors (beyond the refusals the checks provoke)", async () => {
    // The invalid parameter and the stop provoke 4xx answers by design; the browser
    // logs each as "Failed to load resource". Anything else is an error.
    const unexpected = op.errors.filter((e) => !/Failed to load resource: the server responded with a status of 4(00|09|22)/.test(e));
    assert(unexpected.length === 0, unexpected.join(" | "));
  });

  // Soak: heap growth and frame rate while streaming.
  // The frame rate is a benchmark figure: reported here, gated only when
  // ISOCHRON_SOAK_FPS_MIN is set (`make soak`), never in `make test`, where a
  // loaded machine would make a sound tree red.
  const FPS_MIN = process.env.ISOCHRON_SOAK_FPS_MIN ? Number(process.env.ISOCHRON_SOAK_FPS_MIN) : null;
  await check(`soak: over ${SOAK_S} s the heap grows < 20% after 10 s${FPS_MIN ? ` and fps > ${FPS_MIN}` : ""}`, async () => {
    const cdp = await page.context().newCDPSession(page);
    const heap = async () => {
      await cdp.send("HeapProfiler.collectGarbage");
      return (await cdp.send("Runtime.getHeapUsage")).usedSize;
    };
    await page.waitForTimeout(10_000);
    const h10 = await heap();
    const c10 = await page.evaluate(() => window.__isochron.cost());
    const t10 = Date.now();
    const fps = [];
    const end = Date.now() + (SOAK_S - 10) * 1000;
    while (Date.now() < end) {
      await page.waitForTimeout(5_000);
      fps.push(await page.evaluate(() => window.__isochron.fps()));
    }
    const hEnd = await heap();
    const cEnd = await page.evaluate(() => window.__isochron.cost());
    const wall = (Date.now() - t10) / 1000;
    // Main-thread time the views take, ms per second of wall time.
    measured.view_ms_per_s = Object.fromEntries(
      ["plots", "twin", "camera", "status"].map((k) => [k, +((cEnd[k] - c10[k]) / wall).toFixed(1)]),
    );
    measured.heap_mb_10s = +(h10 / 1e6).toFixed(2);
    measured.heap_mb_end = +(hEnd / 1e6).toFixed(2);
    measured.heap_growth = +((hEnd - h10) / h10).toFixed(3);
    measured.fps_min = +Math.min(...fps).toFixed(1);
    measured.fps_mean = +(fps.reduce((a, b) => a + b, 0) / fps.length).toFixed(1);
    assert(measured.heap_growth <= 0.2, `heap grew ${(measured.heap_growth * 100).toFixed(1)}%`);
    if (FPS_MIN !== null) assert(measured.fps_min > FPS_MIN, `fps fell to ${measured.fps_min}`);
  });
  if (process.env.ISOCHRON_SCREENSHOT) {
    await page.screenshot({ path: process.env.ISOCHRON_SCREENSHOT, fullPage: false });
  }
  await op.context.close();
} finally {
  await browser.close();
}

console.log(JSON.stringify({ measured }));
const passed = results.filter(([, ok]) => ok).length;
console.log(`browser: ${passed} passed, ${results.length - passed} failed`);
process.exit(passed === results.length ? 0 : 1);
