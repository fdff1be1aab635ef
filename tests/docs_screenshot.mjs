// The README's pictures of the customer page: a woman wearing the first two catalogue garments
// (docs/img/page.png: the page as it opens on a desktop) and the same try-on with the page's
// "Size and fit" section in view (docs/img/fit.png).
// Usage: node tests/docs_screenshot.mjs BASE_URL PAGE.png [FIT.png] (against `tryon serve`).
import { chromium } from 'playwright-core';
const [base, out, outFit] = process.argv.slice(2);
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
  args: ['--headless=new', '--no-sandbox', '--enable-unsafe-swiftshader', '--use-angle=swiftshader'],
});
const page = await browser.newPage({ viewport: { width: 1280, height: 860 } });
await page.goto(base + '/');
await page.waitForFunction(() => window.__tryon && window.__tryon.ready, null, { timeout: 120000 });
const loads = () => page.evaluate(() => window.__tryon.loads);
const wait = (n) => page.waitForFunction((k) => window.__tryon.loads > k && !window.__tryon.busy, n, { timeout: 180000 });
let n = await loads();
await page.selectOption('#in-gender', 'female');
await page.fill('#in-height_cm', '168');
await page.fill('#in-weight_kg', '62');
await wait(n);
const buttons = await page.locator('#catalogue button[data-garment]').all();
for (const b of buttons.slice(0, 2)) { n = await loads(); await b.click(); await wait(n); }
await page.waitForTimeout(1500);
await page.screenshot({ path: out });
if (outFit) {
  await page.locator('#fit-section').scrollIntoViewIfNeeded();
  await page.waitForTimeout(1500);
  await page.screenshot({ path: outFit });
}
await browser.close();
