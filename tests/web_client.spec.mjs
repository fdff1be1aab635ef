// End-to-end drive of the customer page with playwright-core + Debian's chromium.
// Usage: node tests/web_client.spec.mjs BASE_URL OUTDIR -> prints one JSON object (the facts
// the pytest side asserts); screenshots go to OUTDIR.
import { chromium } from 'playwright-core';
import path from 'node:path';
import fs from 'node:fs';

const [base, outdir] = process.argv.slice(2);
fs.mkdirSync(outdir, { recursive: true });
const out = { screenshots: [], console: [] };
const shot = async (page, name) => {
  const p = path.join(outdir, `${name}.png`);
  await page.evaluate(() => window.scrollTo(0, 0));
  await page.screenshot({ path: p });
  out.screenshots.push(p);
  return p;
};
const canvasVariation = async (page) => {
  const buf = await page.locator('#scene').screenshot();
  // PNG decode is not at hand: compare the canvas' own pixels instead (preserveDrawingBuffer).
  const stats = await page.evaluate(() => {
    const c = document.querySelector('#scene');
    const t = document.createElement('canvas');
    t.width = 64; t.height = 64;
    const ctx = t.getContext('2d');
    ctx.drawImage(c, 0, 0, 64, 64);
    const d = ctx.getImageData(0, 0, 64, 64).data;
    const colours = new Set();
    let min = 255, max = 0;
    for (let i = 0; i < d.length; i += 4) {
      const l = (d[i] + d[i + 1] + d[i + 2]) / 3;
      min = Math.min(min, l); max = Math.max(max, l);
      colours.add(`${d[i] >> 3},${d[i + 1] >> 3},${d[i + 2] >> 3}`);
    }
    return { min, max, colours: colours.size };
  });
  return { ...stats, pngBytes: buf.length };
};
const loadsNow = (page) => page.evaluate(() => window.__tryon.loads);
const waitLoad = (page, after) => page.waitForFunction(
  (n) => window.__tryon && window.__tryon.loads > n && !window.__tryon.busy, after, { timeout: 60000 });

const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
  args: ['--headless=new', '--no-sandbox', '--enable-unsafe-swiftshader', '--disable-background-networking',
    '--disable-component-update', '--no-first-run', '--use-angle=swiftshader'],
});
try {
  const page = await browser.newPage({ viewport: { width: 1200, height: 900 } });
  page.on('console', (m) => { if (m.type() === 'error') out.console.push(m.text()); });
  page.on('pageerror', (e) => out.console.push(`pageerror: ${e.message}`));
  await page.goto(base + '/');
  await page.waitForFunction(() => window.__tryon && window.__tryon.ready, null, { timeout: 60000 });

  // fill the form
  let n = await loadsNow(page);
  await page.selectOption('#in-gender', 'male');
  await page.fill('#in-height_cm', '180');
  await page.fill('#in-weight_kg', '80');
  await waitLoad(page, n);
  out.avatar = await page.evaluate(() => ({
    meshes: window.__tryon.meshCount(), skinned: window.__tryon.skinnedMeshCount(),
    bones: window.__tryon.boneNames(), height: window.__tryon.bboxHeight(), values: window.__tryon.values(),
  }));
  out.canvas = await canvasVariation(page);
  await shot(page, '01-avatar');

  // the unit toggle converts the displayed values
  await page.check('input[name=units][value=imperial]');
  out.heightInches = await page.inputValue('#in-height_cm');
  await page.check('input[name=units][value=metric]');

  // a slider: height
  n = await loadsNow(page);
  await page.locator('#sl-height_cm').fill('195');
  await waitLoad(page, n);
  out.heightAfterSlider = await page.evaluate(() => window.__tryon.bboxHeight());
  out.formAfterSlider = await page.inputValue('#in-height_cm');

  // a pose preset
  out.boneBefore = await page.evaluate(() => window.__tryon.boneQuaternion('upper_arm_l'));
  await page.click('#poses button[data-pose=walking]');
  out.boneAfter = await page.evaluate(() => window.__tryon.boneQuaternion('upper_arm_l'));
  out.thighAfter = await page.evaluate(() => window.__tryon.boneQuaternion('thigh_l'));
  out.pose = await page.evaluate(() => window.__tryon.pose);
  await shot(page, '02-walking');

  // garments: T-shirt and trousers (saves the customer automatically)
  const garments = await (await fetch(base + '/v1/garments')).json();
  const byName = Object.fromEntries(garments.map((g) => [g.name, g.id]));
  n = await loadsNow(page);
  await page.click(`#catalogue button[data-garment="${byName.tshirt}"]`);
  await waitLoad(page, n);
  n = await loadsNow(page);
  await page.click(`#catalogue button[data-garment="${byName.trousers}"]`);
  await waitLoad(page, n);
  out.dressed = await page.evaluate(() => ({
    meshes: window.__tryon.meshCount(), skinned: window.__tryon.skinnedMeshCount(),
    worn: window.__tryon.garmentsWorn(), customer: window.__tryon.customerId(), bones: window.__tryon.boneNames(),
    pose: window.__tryon.pose, thigh: window.__tryon.boneQuaternion('thigh_l'),
  }));
  out.expectedWorn = [byName.tshirt, byName.trousers];
  out.storedId = await page.evaluate(() => localStorage.getItem('tryon.customerId'));
  await page.click('#poses button[data-pose=hands-on-hips]');
  await page.waitForTimeout(300);
  out.dressedCanvas = await canvasVariation(page);
  await shot(page, '03-dressed');

  // a reload remembers the customer and brings back what they entered
  await page.reload();
  await page.waitForFunction(() => window.__tryon.ready && !window.__tryon.busy, null, { timeout: 60000 });
  out.restored = { customer: await page.evaluate(() => window.__tryon.customerId()),
                   height: await page.inputValue('#in-height_cm'), weight: await page.inputValue('#in-weight_kg') };

  // delete my data
  const cid = out.dressed.customer;
  out.customerStatusBefore = (await fetch(`${base}/v1/customers/${cid}`)).status;
  n = await loadsNow(page);
  await page.click('#delete');
  await waitLoad(page, n);
  out.deletedCustomer = cid;
  out.storedAfterDelete = await page.evaluate(() => localStorage.getItem('tryon.customerId'));

  // the error path: an impossible height
  await page.fill('#in-height_cm', '20');
  await page.waitForFunction(() => window.__tryon.lastError && !window.__tryon.busy, null, { timeout: 30000 });
  out.inlineError = await page.textContent('#err-height_cm');
  out.lastError = await page.evaluate(() => window.__tryon.lastError);
  await shot(page, '04-error');

  // a phone width
  await page.setViewportSize({ width: 390, height: 844 });
  await page.fill('#in-height_cm', '170');
  await page.waitForTimeout(1200);
  out.phoneScrollWidth = await page.evaluate(() => document.documentElement.scrollWidth);
  await shot(page, '05-phone');
} finally {
  await browser.close();
}
console.log(JSON.stringify(out));
