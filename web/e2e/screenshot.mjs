// The README's screenshot: the dashboard in headless Chromium during a trial
// in the simulated lab, taken late in the arm's motion (the speed profile, the
// neurons and the phase portrait then show nearly all of it).
// Usage: node e2e/screenshot.mjs URL TOKEN OUT.png [twin]
// With `twin`, only the 3D view (the arm from its URDF) is photographed.
import { chromium } from "playwright-core";

const [base, token, out, part] = process.argv.slice(2);
if (!base || !token || !out) {
  console.error("usage: node e2e/screenshot.mjs URL TOKEN OUT.png");
  process.exit(2);
}
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
  args: ["--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-sync"],
});
try {
  const page = await browser.newPage({ viewport: { width: 1400, height: 1050 } });
  await page.goto(base, { waitUntil: "load" });
  await page.waitForFunction(() => window.__isochron !== undefined, null, { timeout: 60_000 });
  await page.fill("#token", token);
  await page.click("#token-form button[type=submit]");
  await page.waitForFunction(() => !document.querySelector("#btn-trial").disabled, null, { timeout: 60_000 });
  // A first trial fills the history; the second one is photographed.
  for (let i = 0; i < 2; i++) {
    await page.click("#btn-trial");
    await page.waitForFunction(() => window.__isochron.state() === "intercepting", null, { timeout: 90_000 });
    if (i === 0) await page.waitForFunction(() => window.__isochron.state() === "idle", null, { timeout: 60_000 });
  }
  // Most of the way through the motion: the speed profile and the phase portrait's
  // arc nearly complete, the Hopf neuron leading, the ball swinging towards the arm.
  const T = await page.evaluate(async () => (await (await fetch("/api/params")).json()).task.movement_time_s);
  await page.waitForTimeout(800 * T);
  await page.evaluate(() => (document.getElementById("toast").className = "toast hidden"));
  if (part === "twin") {
    await page.waitForFunction(() => window.__isochron.twinLoaded(), null, { timeout: 60_000 });
    await page.locator("#twin").screenshot({ path: out });
  } else {
    await page.screenshot({ path: out, fullPage: false });
  }
  console.log(`screenshot: ${out}`);
} finally {
  await browser.close();
}
