// Bodies dressed in catalogue garments in the page's poses, with and without the pose-corrective
// targets (hook.setCorrectives: influences zeroed), front and turned; PNGs to OUTDIR.
// Usage (a server on loopback, as tests/test_web_client.py starts it):
//   PYTHONPATH=. python -c "import subprocess, sys; from pathlib import Path; from tests.harness import run_server
//   with run_server(Path('/tmp/pc-data'), 'embedded') as s: subprocess.run(['node', 'tests/pose_correctives_shots.mjs',
//       str(s.client.base_url).rstrip('/'), 'tests/artifacts/pose_correctives'] + sys.argv[1:])" [CASES]
// CASES (optional, default "male:200:130:pinstripe:walking"): comma-separated
// gender:height_cm:weight_kg:garment-name-regex[+regex...]:pose.
import { chromium } from 'playwright-core';
import path from 'node:path';
import fs from 'node:fs';
const [base, outdir, spec] = process.argv.slice(2);
const cases = (spec || 'male:200:130:pinstripe:walking').split(',').map((c) => {
  const [gender, h, w, garments, pose] = c.split(':');
  return { gender, h, w, garments: garments.split('+'), pose };
});
fs.mkdirSync(outdir, { recursive: true });
const browser = await chromium.launch({ executablePath: '/usr/bin/chromium',
  args: ['--headless=new', '--no-sandbox', '--enable-unsafe-swiftshader', '--use-angle=swiftshader'] });
const out = {};
const wait = (page, k, ms = 120000) => page.waitForFunction((n) => window.__tryon.loads > n && !window.__tryon.busy, k,
  { timeout: ms });
try {
  const catalogue = await (await fetch(base + '/v1/garments')).json();
  for (const c of cases) {
    const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
    await page.goto(base + '/');
    await page.waitForFunction(() => window.__tryon && window.__tryon.ready, null, { timeout: 60000 });
    let n = await page.evaluate(() => window.__tryon.loads);
    await page.selectOption('#in-gender', c.gender);
    await page.fill('#in-height_cm', c.h);
    await page.fill('#in-weight_kg', c.w);
    await wait(page, n, 60000);
    const names = [];
    for (const re of c.garments) {
      const g = catalogue.find((x) => new RegExp(re, 'i').test(x.name));
      if (!g) throw new Error(`no garment matches ${re}`);
      names.push(g.name.replace(/\W+/g, '-').toLowerCase());
      n = await page.evaluate(() => window.__tryon.loads);
      await page.click(`#catalogue button[data-garment="${g.id}"]`);
      await wait(page, n);
    }
    await page.click(`#poses button[data-pose=${c.pose}]`);
    await page.waitForFunction(() => window.__tryon.poseSource === 'body', null, { timeout: 60000 });
    await page.click(`#poses button[data-pose=${c.pose}]`);
    const tag = `${c.gender[0]}${c.h}-${c.w}-${names.join('+')}-${c.pose}`;
    out[tag] = await page.evaluate(() => window.__tryon.poseCorrectives());
    for (const [view, turn] of [['front', 0], ['left45', 0.8], ['left90', 0.8], ['back', 1.57], ['right90', 1.57]]) {
      await page.evaluate((a) => window.__tryon.orbit(a), turn);
      for (const on of [true, false]) {
        await page.evaluate((x) => window.__tryon.setCorrectives(x), on);
        await page.waitForTimeout(200);
        await page.locator('#viewer').screenshot({ path: path.join(outdir, `${tag}-${view}-${on ? 'after' : 'before'}.png`) });
      }
    }
    await page.close();
  }
} finally { await browser.close(); }
console.log(JSON.stringify(out));
