// The 200/130 man in the pinstripe blouse in the page's walking step, with and without the
// pose-corrective targets (hook.setCorrectives: influences zeroed), front and turned; PNGs to OUTDIR.
// Usage (a server on loopback, as tests/test_web_client.py starts it):
//   PYTHONPATH=. python -c "import subprocess, sys; from pathlib import Path; from tests.harness import run_server
//   with run_server(Path('/tmp/pc-data'), 'embedded') as s: subprocess.run(['node', 'tests/pose_correctives_shots.mjs',
//       str(s.client.base_url).rstrip('/'), 'tests/artifacts/pose_correctives'])"
import { chromium } from 'playwright-core';
import path from 'node:path';
import fs from 'node:fs';
const [base, outdir] = process.argv.slice(2);
fs.mkdirSync(outdir, { recursive: true });
const browser = await chromium.launch({ executablePath: '/usr/bin/chromium',
  args: ['--headless=new', '--no-sandbox', '--enable-unsafe-swiftshader', '--use-angle=swiftshader'] });
const out = {};
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
  await page.goto(base + '/');
  await page.waitForFunction(() => window.__tryon && window.__tryon.ready, null, { timeout: 60000 });
  let n = await page.evaluate(() => window.__tryon.loads);
  await page.selectOption('#in-gender', 'male');
  await page.fill('#in-height_cm', '200');
  await page.fill('#in-weight_kg', '130');
  await page.waitForFunction((k) => window.__tryon.loads > k && !window.__tryon.busy, n, { timeout: 60000 });
  const garments = (await (await fetch(base + '/v1/garments')).json());
  const g = garments.find((x) => /pinstripe/i.test(x.name));
  n = await page.evaluate(() => window.__tryon.loads);
  await page.click(`#catalogue button[data-garment="${g.id}"]`);
  await page.waitForFunction((k) => window.__tryon.loads > k && !window.__tryon.busy, n, { timeout: 120000 });
  await page.click('#poses button[data-pose=walking]');
  await page.waitForFunction(() => window.__tryon.poseSource === 'body', null, { timeout: 60000 });
  await page.click('#poses button[data-pose=walking]');
  out.influences = await page.evaluate(() => window.__tryon.poseCorrectives());
  for (const [view, turn] of [['front', 0], ['left45', 0.8], ['left90', 0.8], ['right45', -2.4], ['right90', -0.8]]) {
    await page.evaluate((a) => window.__tryon.orbit(a), turn);
    for (const on of [true, false]) {
      await page.evaluate((x) => window.__tryon.setCorrectives(x), on);
      await page.waitForTimeout(200);
      await page.locator('#viewer').screenshot({ path: path.join(outdir, `m200-130-blouse-walking-${view}-${on ? 'after' : 'before'}.png`) });
    }
  }
} finally { await browser.close(); }
console.log(JSON.stringify(out));
