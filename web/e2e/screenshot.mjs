// The README's screenshot: the dashboard in headless Chromium during a trial
// in the simulated lab, taken just after the arm arrived (the speed profile,
// the neurons and the phase portrait then show the whole motion).
// Usage: node e2e/screenshot.mjs URL TOKEN OUT.png
import { chromium } from "playwright-core";

const [base, token, out] = process.argv.slice(2);
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
  await page.waitForFunction(() => window.__isochron !== undefined, null, { timeout: 10_000 });
  await page.fill("#token", token);
  await page.click("#token-form button[type=submit]");
  await page.waitForFunction(() => !document.querySelector("#btn-trial").disabled, null, { timeout: 5_000 });
  // A first trial fills the history; the second one is photographed.
  for (let i = 0; i < 2; i++) {
    await page.click("#btn-trial");
    await page.waitForFunction(() => window.__isochron.state() === "intercepting", null, { timeout: 90_000 });
    await page.waitForFunction(() => ["holding", "done", "idle", "aborted"].includes(window.__isochron.state()), null, {
      timeout: 30_000,
    });
    if (i === 0) await page.waitForFunction(() => window.__isochron.state() === "idle", null, { timeout: 30_000 });
  }
  // Half a second after the arrival: the pendulum still swings, the plots hold the motion.
  await page.waitForTimeout(500);
  await page.screenshot({ path: out, fullPage: false });
  console.log(`screenshot: ${out}`);
} finally {
  await browser.close();
}
