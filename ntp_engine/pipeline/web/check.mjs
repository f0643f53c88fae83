// Drives a result page (RESULT/index.html) in headless Chromium with playwright-core, for the
// browser check (ntp_engine/bench/browser.py) and the page's tests.
//
//   node check.mjs PAGE.html JOB.json OUT_DIR
//
// JOB: {"chromium": path, "views": [renderLinear specs], "screenshots": bool, "page_screenshot":
// bool}. Writes OUT_DIR/
// result.json: {"console_errors": [...], "page_errors": [...], "views": [{width, height, rgba}]}
// and, with screenshots, canvas-start.png, canvas-light.png (the light moved by its slider) and
// canvas-turntable.png (the turntable on for 1 s); with page_screenshot, page.png (the whole
// page). Exit 0 when the page loaded, 1 otherwise.
import { createRequire } from 'node:module';
import fs from 'node:fs';
import path from 'node:path';
import { pathToFileURL } from 'node:url';

const require = createRequire(path.join(process.env.NTP_NODE_MODULES || '.', 'noop.js'));
const { chromium } = require('playwright-core');

const [page_path, job_path, out_dir] = process.argv.slice(2);
const job = JSON.parse(fs.readFileSync(job_path, 'utf8'));
fs.mkdirSync(out_dir, { recursive: true });

// WebGL without a GPU: Chromium's SwiftShader, which it keeps behind this flag
const browser = await chromium.launch({
  executablePath: job.chromium,
  args: ['--enable-unsafe-swiftshader', '--use-angle=swiftshader', '--ignore-gpu-blocklist', '--no-sandbox'],
});
const out = { console_errors: [], page_errors: [], views: [] };
let status = 0;
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 900 } });
  page.on('console', (msg) => { if (msg.type() === 'error') out.console_errors.push(msg.text()); });
  page.on('pageerror', (err) => out.page_errors.push(String(err)));
  page.on('request', (req) => {
    const url = req.url();
    if (!url.startsWith('file:') && !url.startsWith('data:') && !url.startsWith('blob:')) out.page_errors.push(`network request: ${url}`);
  });
  await page.goto(pathToFileURL(path.resolve(page_path)).href);
  await page.waitForFunction(() => window.ntpViewer !== undefined, null, { timeout: 60000 });
  await page.evaluate(() => window.ntpViewer.ready);
  for (const spec of job.views || []) out.views.push(await page.evaluate((s) => window.ntpViewer.renderLinear(s), spec));
  if (job.page_screenshot) await page.screenshot({ path: path.join(out_dir, 'page.png'), fullPage: true });
  if (job.screenshots) {
    const canvas = page.locator('#ntp-canvas');
    const settle = () => page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
    await settle();
    await canvas.screenshot({ path: path.join(out_dir, 'canvas-start.png') });
    await page.evaluate(() => {
      const el = document.getElementById('ntp-light-azimuth');
      el.value = '200';
      el.dispatchEvent(new Event('input'));
    });
    await settle();
    await canvas.screenshot({ path: path.join(out_dir, 'canvas-light.png') });
    await page.locator('#ntp-turntable').check();
    await page.waitForTimeout(1000);
    await settle();
    await canvas.screenshot({ path: path.join(out_dir, 'canvas-turntable.png') });
  }
} catch (err) {
  out.page_errors.push(String(err));
  status = 1;
} finally {
  await browser.close();
}
fs.writeFileSync(path.join(out_dir, 'result.json'), JSON.stringify(out));
process.exit(status);
