// End-to-end drive of the customer page with playwright-core + Debian's chromium.
// Usage: node tests/web_client.spec.mjs BASE_URL OUTDIR [SCAN_CUSTOMER_ID SCAN_TOKEN]
// -> prints one JSON object (the facts the pytest side asserts); screenshots go to OUTDIR.
import { chromium } from 'playwright-core';
import path from 'node:path';
import fs from 'node:fs';

const [base, outdir, scanId, scanToken] = process.argv.slice(2);
fs.mkdirSync(outdir, { recursive: true });
const out = { screenshots: [], console: [] };
const shot = async (page, name, locator = null) => {
  const p = path.join(outdir, `${name}.png`);
  await page.evaluate(() => window.scrollTo(0, 0));
  if (locator) await page.locator(locator).screenshot({ path: p }); else await page.screenshot({ path: p });
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
const box = async (page, sel) => page.locator(sel).boundingBox();
const wornNow = (page) => page.evaluate(() => window.__tryon.garmentsWorn());
// put on exactly these garments (clicking the catalogue), waiting for the last scene
const wear = async (page, ids) => {
  const worn = await wornNow(page);
  const clicks = [...worn.filter((g) => !ids.includes(g)), ...ids.filter((g) => !worn.includes(g))];
  if (!clicks.length) return;
  const n = await loadsNow(page);
  for (const g of clicks) await page.click(`#catalogue button[data-garment="${g}"]`);
  await waitLoad(page, n);
};
const setBody = async (page, b) => {
  const n = await loadsNow(page);
  await page.selectOption('#in-gender', b.gender);
  await page.fill('#in-height_cm', String(b.height));
  await page.fill('#in-weight_kg', String(b.weight));
  await waitLoad(page, n);
};
const pose = async (page, name) => {
  await page.click(`#poses button[data-pose=${name}]`);
  await page.waitForFunction((p) => window.__tryon.pose === p, name);
};

const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
  args: ['--headless=new', '--no-sandbox', '--enable-unsafe-swiftshader', '--disable-background-networking',
    '--disable-component-update', '--no-first-run', '--use-angle=swiftshader'],
});
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
  page.on('console', (m) => { if (m.type() === 'error') out.console.push(m.text()); });
  page.on('pageerror', (e) => out.console.push(`pageerror: ${e.message}`));
  await page.goto(base + '/');
  await page.waitForFunction(() => window.__tryon && window.__tryon.ready, null, { timeout: 60000 });
  // the instant try-on only until the exact drape's own section below (a drape arriving later
  // would count as a load of whatever step came next)
  out.drapeDefault = await page.evaluate(() => document.querySelector('#drape button[aria-pressed="true"]').dataset.drape);
  await page.evaluate(() => window.__tryon.setDrape('basis'));

  // the layout at 1280x800: the viewer and the catalogue side by side, nothing to scroll, the
  // measurements above the catalogue
  out.layout = {
    viewer: await box(page, '#viewer'), catalogue: await box(page, '#catalogue'),
    measurements: await box(page, '#measurements'),
    firstGarment: await box(page, '#catalogue li:first-child button'),
    scrollHeight: await page.evaluate(() => document.documentElement.scrollHeight),
    innerHeight: await page.evaluate(() => window.innerHeight),
  };

  // the privacy line before anything is stored, and the delete button then
  out.privacyBefore = await page.textContent('#customer-status');
  out.deleteDisabledBefore = await page.isDisabled('#delete');
  await shot(page, '00-start-desktop');

  // the catalogue: the shopper's gender first (the page starts female), "Show all" for the rest
  const listed = (await (await fetch(base + '/v1/garments')).json());
  const genderOf = Object.fromEntries(listed.map((g) => [g.id, g.gender ?? null]));
  const visibleGarments = () => page.evaluate(() => [...document.querySelectorAll('#catalogue li')]
    .filter((li) => !li.hidden && li.offsetParent !== null).map((li) => li.dataset.garment));
  const catalogueState = async () => {
    const ids = await visibleGarments();
    return { genders: ids.map((id) => genderOf[id]), count: ids.length, total: listed.length,
      title: await page.textContent('#catalogue-title'), button: await page.textContent('#catalogue-all'),
      buttonShown: await page.isVisible('#catalogue-all') };
  };
  out.catalogue = { female: await catalogueState() };
  await page.click('#catalogue-all');
  out.catalogue.all = await catalogueState();
  await page.click('#catalogue-all');
  out.catalogue.femaleAgain = await catalogueState();

  // real height on screen: a 150 cm and a 190 cm body (no clothes, A-pose), the projected
  // height of what is drawn in CSS px against its height in metres
  let n;
  out.heightOnScreen = [];
  for (const h of [150, 190]) {
    n = await loadsNow(page);
    await page.fill('#in-height_cm', String(h));
    await waitLoad(page, n);
    const sb = await page.evaluate(() => window.__tryon.sceneScreenBox());
    out.heightOnScreen.push({ cm: h, px: sb.y1 - sb.y0, canvas: sb.height,
      metres: await page.evaluate(() => window.__tryon.sceneWorldHeight()),
      ruler: await page.evaluate(() => window.__tryon.rulerHeight) });
    await shot(page, `height-${h}-desktop`, '#viewer');
  }

  // fill the form
  n = await loadsNow(page);
  await page.selectOption('#in-gender', 'male');
  await page.fill('#in-height_cm', '180');
  await page.fill('#in-weight_kg', '80');
  await waitLoad(page, n);
  out.catalogue.male = await catalogueState();
  await page.click('#catalogue-all'); // the test's outfits mix women's and men's garments
  out.avatar = await page.evaluate(() => ({
    meshes: window.__tryon.meshCount(), skinned: window.__tryon.skinnedMeshCount(),
    bones: window.__tryon.boneNames(), height: window.__tryon.bboxHeight(), values: window.__tryon.values(),
  }));
  out.canvas = await canvasVariation(page);
  await shot(page, '01-avatar');

  // the hair selector: the default style, no hair, a chosen style (a node named "hair" or not)
  const hairNow = async (value) => {
    const k = await loadsNow(page);
    await page.selectOption('#hair', value);
    await waitLoad(page, k);
    return (await page.evaluate(() => window.__tryon.meshNames())).includes('hair');
  };
  out.hair = { labels: await page.evaluate(() => [...document.querySelectorAll('#hair option')].map((o) => o.textContent)),
    defaultShown: (await page.evaluate(() => window.__tryon.meshNames())).includes('hair') };
  out.hair.none = await hairNow('none');
  await shot(page, '01-avatar-no-hair', '#viewer');
  out.hair.chosen = await hairNow(await page.evaluate(() => window.__tryon.hairOptions[0]));
  out.hair.back = await hairNow('');

  // the unit toggle converts the displayed values
  await page.check('input[name=units][value=imperial]');
  out.heightInches = await page.inputValue('#in-height_cm');
  await page.check('input[name=units][value=metric]');

  // a slider: height
  n = await loadsNow(page);
  await page.locator('#sl-height_cm').fill('195');
  out.sliderLabel = await page.textContent('#out-height_cm');  // follows the drag, before the avatar loads
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

  // garments: a top and a bottom of the catalogue (saves the customer automatically)
  const garments = (await (await fetch(base + '/v1/garments')).json()).filter((g) => g.status === 'ready');
  const tops = garments.filter((g) => /shirt|tee|top|blouse|sweater|hoodie|jacket|polo/i.test(g.name));
  const bottoms = garments.filter((g) => /trouser|jean|pant|skirt|short|chino/i.test(g.name));
  if (!tops.length || !bottoms.length) throw new Error(`no top and bottom among ${garments.map((g) => g.name)}`);
  const outfits = [[tops[0], bottoms[0]], [tops[1] || tops[0], bottoms[1] || bottoms[0]]];
  out.outfits = outfits.map((o) => o.map((g) => g.name));
  // the body's adapted poses (GET .../poses) held back until the outfit is worn: meanwhile the
  // page poses with the plain directions, and the correctives (made for the adapted poses) stay 0
  let releasePoses;
  const posesHeld = new Promise((r) => { releasePoses = r; });
  await page.route('**/v1/customers/*/poses', async (route) => { await posesHeld; await route.continue(); });
  await wear(page, [outfits[0][0].id]);
  await wear(page, outfits[0].map((g) => g.id));
  out.dressed = await page.evaluate(() => ({
    meshes: window.__tryon.meshCount(), skinned: window.__tryon.skinnedMeshCount(),
    worn: window.__tryon.garmentsWorn(), customer: window.__tryon.customerId(), bones: window.__tryon.boneNames(),
    pose: window.__tryon.pose, thigh: window.__tryon.boneQuaternion('thigh_l'), names: window.__tryon.meshNames(),
  }));
  out.expectedWorn = outfits[0].map((g) => g.id);
  out.storedId = await page.evaluate(() => localStorage.getItem('tryon.customerId'));
  const token = await page.evaluate(() => localStorage.getItem('tryon.customerToken'));
  out.storedToken = Boolean(token);
  out.poseSourceHeld = await page.evaluate(() => window.__tryon.poseSource);
  out.correctivesHeld = await page.evaluate(() => window.__tryon.poseCorrectives());
  releasePoses();
  await page.waitForFunction(() => window.__tryon.poseSource === 'body', null, { timeout: 60000 });
  await page.unroute('**/v1/customers/*/poses');
  // the garments' pose-corrective targets follow the pose: the current one's at 1, the others at 0
  out.correctivesWalking = await page.evaluate(() => window.__tryon.poseCorrectives());
  await page.click('#poses button[data-pose=hands-on-hips]');
  await page.waitForTimeout(300);
  out.correctivesHips = await page.evaluate(() => window.__tryon.poseCorrectives());
  out.dressedCanvas = await canvasVariation(page);
  out.privacyStored = await page.textContent('#customer-status');
  await shot(page, '03-dressed');

  // sizes: a garment listed in more than one size gets a size picker with the recommended size
  // marked (GET .../fit), the fit in words, the try-on of the chosen size and a fit map; a
  // one-size garment (or a server without sizes) shows none of it
  const sizedGarments = garments.filter((g) => Array.isArray(g.sizes) && g.sizes.length > 1);
  const pickerOf = (id) => page.evaluate((g) => {
    const div = document.querySelector(`#fits .garment-fit[data-garment="${g}"]`);
    if (!div || div.offsetParent === null) return null;
    return { labels: [...div.querySelectorAll('.size-picker button')].map((b) => b.dataset.size),
      recommended: [...div.querySelectorAll('.size-picker button.recommended')].map((b) => b.dataset.size),
      pressed: [...div.querySelectorAll('.size-picker button[aria-pressed="true"]')].map((b) => b.dataset.size),
      words: div.querySelector('.fit-words').textContent, recommendText: div.querySelector('.recommend').textContent };
  }, id);
  out.sizes = { sizedInCatalogue: sizedGarments.length, worn: [] };
  for (const g of outfits[0]) {
    out.sizes.worn.push({ id: g.id, name: g.name, sizes: (g.sizes || []).map((x) => x.label), picker: await pickerOf(g.id) });
  }
  out.sizes.sectionShown = await page.isVisible('#fit-section');
  out.sizes.glbBefore = await page.evaluate(() => window.__tryon.lastGlb);
  if (sizedGarments.length) {
    // wear one sized garment (alone with the first outfit's other piece when that is sized too)
    const g = sizedGarments.find((x) => outfits[0].some((o) => o.id === x.id)) || sizedGarments[0];
    const wornNowIds = await wornNow(page);
    if (!wornNowIds.includes(g.id)) await wear(page, [g.id]);
    await page.waitForSelector(`#fits .garment-fit[data-garment="${g.id}"]`, { timeout: 30000 });
    const cidNow = await page.evaluate(() => window.__tryon.customerId());
    const tok = await page.evaluate(() => localStorage.getItem('tryon.customerToken'));
    const fitRes = await fetch(`${base}/v1/customers/${cidNow}/garments/${g.id}/fit`, { headers: { Authorization: `Bearer ${tok}` } });
    const fit = fitRes.ok ? await fitRes.json() : null;
    const rec = { id: g.id, sizes: g.sizes.map((x) => x.label), fitStatus: fitRes.status, fit, picker: await pickerOf(g.id) };
    await shot(page, 'sizes-01-recommended');
    await page.locator('#fit-section').screenshot({ path: path.join(outdir, 'sizes-01-panel.png') });
    out.screenshots.push(path.join(outdir, 'sizes-01-panel.png'));
    // another size: the try-on asks for it
    const other = rec.sizes.find((l) => l !== (fit && fit.recommended)) || rec.sizes[0];
    n = await loadsNow(page);
    await page.click(`#fits .garment-fit[data-garment="${g.id}"] .size-picker button[data-size="${other}"]`);
    await waitLoad(page, n);
    rec.other = other;
    rec.pickerOther = await pickerOf(g.id);
    rec.glbOther = await page.evaluate(() => window.__tryon.lastGlb);
    rec.wornOther = await wornNow(page);
    rec.wordsExpected = fit ? await page.evaluate(([f, l]) => window.__tryon.fitInWords(f.sizes.find((x) => x.label === l)), [fit, other]) : null;
    await shot(page, 'sizes-02-other-size');
    // the fit maps: vertex colours on the garments
    rec.fitmap = {};
    for (const mode of ['strain', 'ease']) {
      n = await loadsNow(page);
      await page.click(`#fitmap button[data-fitmap="${mode}"]`);
      await waitLoad(page, n);
      rec.fitmap[mode] = { glb: await page.evaluate(() => window.__tryon.lastGlb),
        coloured: await page.evaluate(() => window.__tryon.vertexColourMeshes()),
        legend: await page.isVisible('#fitmap-legend') };
      await shot(page, `sizes-03-fitmap-${mode}`);
    }
    n = await loadsNow(page);
    await page.click('#fitmap button[data-fitmap="off"]');
    await waitLoad(page, n);
    rec.fitmap.off = { coloured: await page.evaluate(() => window.__tryon.vertexColourMeshes()), legend: await page.isVisible('#fitmap-legend') };
    if (fit && fit.recommended !== other) { // back to the recommended size for the rest of the test
      n = await loadsNow(page);
      await page.click(`#fits .garment-fit[data-garment="${g.id}"] .size-picker button[data-size="${fit.recommended}"]`);
      await waitLoad(page, n);
      rec.pressedAfterReset = (await pickerOf(g.id)).pressed;
    }
    out.sizes.sized = rec;
    await wear(page, outfits[0].map((x) => x.id));
  }

  // the exact drape: "Draped on you" swaps in the outfit as draped on this body by the cloth
  // engine (outfit.glb?drape=exact: 202 while the drapes are computed) after the instant try-on
  {
    const before = await page.evaluate(() => window.__tryon.drapes);
    const n0 = await loadsNow(page);
    out.drape = { visible: await page.isVisible('#drape') };
    await page.click('#drape button[data-drape="exact"]');
    await page.waitForFunction((d) => window.__tryon.drapes > d, before, { timeout: 240000 });
    Object.assign(out.drape, { glb: await page.evaluate(() => window.__tryon.lastGlb),
      status: await page.textContent('#drape-status'), loads: (await loadsNow(page)) - n0,
      pressed: await page.getAttribute('#drape button[data-drape="exact"]', 'aria-pressed'),
      privacy: await page.textContent('#customer-status') });
    await shot(page, 'drape-01-exact');
    const n1 = await loadsNow(page);
    await page.click('#drape button[data-drape="basis"]');
    await waitLoad(page, n1);
    out.drape.after = await page.evaluate(() => window.__tryon.lastGlb);
    out.drape.hiddenAfter = await page.textContent('#drape-status');
  }

  // five bodies (and a 208 cm one), two outfits each, front / side / back. The camera keeps
  // the direction the shopper turned it to across avatar changes, and frames every body.
  const bodies = [
    { name: 'w160-55', gender: 'female', height: 160, weight: 55, pose: 'walking' },
    { name: 'm185-80', gender: 'male', height: 185, weight: 80, pose: 'hands-on-hips' },
    { name: 'w165-105', gender: 'female', height: 165, weight: 105, pose: 'arms-down' },
    { name: 'm200-130', gender: 'male', height: 200, weight: 130, pose: 'walking' },
    { name: 'm150-45', gender: 'male', height: 150, weight: 45, pose: 'hands-on-hips' },
    { name: 'm208-110', gender: 'male', height: 208, weight: 110, pose: 'arms-down' },
  ];
  out.bodies = [];
  // where the pose buttons start, in the canvas' pixels (they sit over its bottom edge)
  out.posesTop = (await box(page, '#poses')).y - (await box(page, '#scene')).y;
  const views = [['front', 0], ['side', Math.PI / 2], ['back', Math.PI / 2]];
  for (const b of bodies) {
    const rec = { name: b.name, views: [] };
    if (b.height === 208) { // turned a little before the avatar changes: the direction is kept
      await page.evaluate(() => window.__tryon.orbit(0.6));
      rec.directionBefore = await page.evaluate(() => window.__tryon.cameraDirection());
    }
    await pose(page, 'a-pose');
    await setBody(page, b);
    if (b.height === 208) {
      rec.directionAfter = await page.evaluate(() => window.__tryon.cameraDirection());
      rec.headTurned = await page.evaluate(() => window.__tryon.headTop());
      await shot(page, `body-${b.name}-turned`, '#viewer');
      await page.evaluate(() => window.__tryon.orbit(-0.6));
    }
    rec.height = await page.evaluate(() => window.__tryon.bboxHeight());
    for (const [k, outfit] of outfits.entries()) {
      await wear(page, outfit.map((g) => g.id));
      await pose(page, k === 0 ? 'a-pose' : b.pose);
      const names = await page.evaluate(() => window.__tryon.meshNames());
      for (const [view, turn] of views) {
        await page.evaluate((a) => window.__tryon.orbit(a), turn);
        const v = { outfit: k, view, pose: k === 0 ? 'a-pose' : b.pose, names,
          head: await page.evaluate(() => window.__tryon.headTop()),
          scene: await page.evaluate(() => window.__tryon.sceneScreenBox()),
          metres: await page.evaluate(() => window.__tryon.sceneWorldHeight()) };
        if (view === 'front') {
          v.pixels = {};
          for (const g of outfit) {
            // three.js names nodes as PropertyBinding.sanitizeNodeName does: whitespace -> _, no []./:
            const node = g.name.replace(/\s/g, '_').replace(/[\[\]\.:\/]/g, '');
            const name = names.find((x) => x === node) || names.find((x) => x.startsWith(node));
            v.pixels[g.name] = name ? await page.evaluate((x) => window.__tryon.meshPixels(x), name) : null;
          }
        }
        await shot(page, `body-${b.name}-outfit${k + 1}-${view}`, '#viewer');
        rec.views.push(v);
      }
      await page.evaluate(() => window.__tryon.orbit(-Math.PI)); // back to the front
    }
    out.bodies.push(rec);
  }
  await pose(page, 'a-pose');
  await shot(page, '06-wide-page');

  // a reload remembers the customer and brings back what they entered
  out.customerBeforeReload = await page.evaluate(() => window.__tryon.customerId());
  await page.reload();
  await page.waitForFunction(() => window.__tryon.ready && !window.__tryon.busy, null, { timeout: 60000 });
  out.restored = { customer: await page.evaluate(() => window.__tryon.customerId()),
                   height: await page.inputValue('#in-height_cm'), weight: await page.inputValue('#in-weight_kg') };
  const lastBody = bodies[bodies.length - 1];
  out.restoredExpected = { height: lastBody.height, weight: lastBody.weight };

  // delete my data
  const cid = out.restored.customer;
  const lastToken = await page.evaluate(() => localStorage.getItem('tryon.customerToken'));
  out.customerStatusBefore = (await fetch(`${base}/v1/customers/${cid}`,
    { headers: { Authorization: `Bearer ${lastToken}` } })).status;
  out.customerStatusNoToken = (await fetch(`${base}/v1/customers/${cid}`)).status;
  out.deletedToken = lastToken;
  n = await loadsNow(page);
  await page.click('#delete');
  await waitLoad(page, n);
  out.deletedCustomer = cid;
  out.storedAfterDelete = await page.evaluate(() => localStorage.getItem('tryon.customerId'));
  out.tokenAfterDelete = await page.evaluate(() => localStorage.getItem('tryon.customerToken'));

  // the error path: an impossible height
  await page.fill('#in-height_cm', '20');
  await page.waitForFunction(() => window.__tryon.lastError && !window.__tryon.busy, null, { timeout: 30000 });
  out.inlineError = await page.textContent('#err-height_cm');
  out.lastError = await page.evaluate(() => window.__tryon.lastError);
  await shot(page, '04-error');

  // a phone width
  await page.setViewportSize({ width: 390, height: 844 });
  n = await loadsNow(page);
  await page.fill('#in-height_cm', '170');
  await waitLoad(page, n);
  out.phoneScrollWidth = await page.evaluate(() => document.documentElement.scrollWidth);
  out.phoneHead = await page.evaluate(() => window.__tryon.headTop());
  out.phoneViewer = await box(page, '#viewer');
  out.phoneScene = await page.evaluate(() => window.__tryon.sceneScreenBox());
  out.phoneCanvas = await box(page, '#scene');
  out.phonePoses = await box(page, '#poses');
  out.phoneMeasurements = await box(page, '#measurements');
  out.phoneCatalogue = await box(page, '#catalogue-section');
  await shot(page, '05-phone');
  await page.screenshot({ path: path.join(outdir, '05-phone-full.png'), fullPage: true });
  out.screenshots.push(path.join(outdir, '05-phone-full.png'));
  // phones: a small woman and a large man, dressed (their own gender's clothes)
  const phoneBodies = [{ name: 'w152-48', gender: 'female', height: 152, weight: 48 },
    { name: 'm193-118', gender: 'male', height: 193, weight: 118 }];
  for (const b of phoneBodies) {
    await setBody(page, b);
    const mine = (g) => genderOf[g.id] === b.gender;
    const top = tops.find(mine), bottom = bottoms.find(mine);
    await wear(page, [top, bottom].filter(Boolean).map((g) => g.id));
    await shot(page, `phone-${b.name}`);
    await page.screenshot({ path: path.join(outdir, `phone-${b.name}-full.png`), fullPage: true });
    out.screenshots.push(path.join(outdir, `phone-${b.name}-full.png`));
  }
  out.phoneHeights = await page.evaluate(() => window.__tryon.rulerHeight);
  await page.close();

  // a scan customer (uploaded by the pytest side): the scan edited live over the WebSocket
  if (scanId) {
    const auth = { headers: { Authorization: `Bearer ${scanToken}` } };
    const deadline = Date.now() + 240000;
    let rec;
    for (;;) {
      rec = await (await fetch(`${base}/v1/customers/${scanId}`, auth)).json();
      if (rec.status !== 'fitting' || Date.now() > deadline) break;
      await new Promise((r) => setTimeout(r, 1000));
    }
    out.scanRecord = { status: rec.status, source: rec.source, editable: rec.editable, error: rec.error };
    const ctx = await browser.newContext({ viewport: { width: 1280, height: 800 } });
    const sp = await ctx.newPage();
    sp.on('console', (m) => { if (m.type() === 'error') out.console.push(`scan: ${m.text()}`); });
    sp.on('pageerror', (e) => out.console.push(`pageerror: ${e.message}`));
    await sp.goto(`${base}/?customer=${scanId}&token=${scanToken}`);
    await sp.waitForFunction(() => window.__tryon && window.__tryon.scan.frames >= 1, null, { timeout: 60000 });
    const scanState = () => sp.evaluate(() => ({ ...window.__tryon.scan, view: window.__tryon.scan.view(),
      box: window.__tryon.sceneScreenBox(), size: window.__tryon.scanSize(), head: window.__tryon.headTop(), url: location.href,
      catalogueHidden: document.querySelector('#catalogue-section').hidden }));
    out.scan = { first: await scanState() };
    await shot(sp, 'scan-01-as-scanned');
    const w = Number(await sp.inputValue('#in-weight_kg'));
    out.scan.weightBefore = w;
    let frames = out.scan.first.frames;
    await sp.locator('#sl-weight_kg').fill(String(Math.round(w + 20)));
    await sp.waitForFunction((f) => window.__tryon.scan.frames > f, frames, { timeout: 60000 });
    await sp.waitForTimeout(300);
    await sp.waitForFunction(() => !document.querySelector('#scan-status').textContent.startsWith('Reshaping'), null, { timeout: 60000 });
    out.scan.heavier = await scanState();
    await shot(sp, 'scan-02-heavier');
    frames = out.scan.heavier.frames;
    await sp.click('#poses button[data-pose=arms-down]');
    await sp.waitForFunction((f) => window.__tryon.scan.frames > f, frames, { timeout: 60000 });
    out.scan.posed = await scanState();
    await shot(sp, 'scan-03-arms-down');
    await sp.click('#scan-view button[data-view=body]');
    await sp.waitForFunction(() => window.__tryon.scan.view() === 'body');
    await sp.waitForTimeout(200);
    out.scan.body = await scanState();
    await shot(sp, 'scan-04-fitted-body');
    await ctx.close();
  }
} finally {
  await browser.close();
}
console.log(JSON.stringify(out));
