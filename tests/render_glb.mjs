// Render GLB files as a customer's viewer would (three.js GLTFLoader in headless Chromium, through
// playwright-core and Debian's chromium): node tests/render_glb.mjs OUTDIR A.glb [B.glb ...]
// Env VIEWS (comma-separated, default "front,side,back,face"), WIDTH, HEIGHT. Writes
// OUTDIR/<glb name>-<view>.png and prints a JSON summary {images, errors, scenes: {name: {meshes,
// skinned, textured, bbox}}} (page errors included). The "face" view frames the head.
import { chromium } from 'playwright-core';
import fs from 'node:fs';
import path from 'node:path';
import { fileURLToPath } from 'node:url';

const [outdir, ...files] = process.argv.slice(2);
fs.mkdirSync(outdir, { recursive: true });
const here = path.dirname(fileURLToPath(import.meta.url));
const three = path.resolve(here, '..', 'node_modules', 'three');
const views = (process.env.VIEWS || 'front,side,back,face').split(',');
const W = Number(process.env.WIDTH || 500), H = Number(process.env.HEIGHT || 900);

const html = `<!doctype html><html><body style="margin:0;background:#fff">
<canvas id="c"></canvas>
<script type="importmap">{"imports": {"three": "http://render.local/three/build/three.module.js",
  "three/addons/": "http://render.local/three/examples/jsm/"}}</script>
<script type="module">
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
window.render = async (b64, view, W, H) => {
  const bin = atob(b64); const u = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) u[i] = bin.charCodeAt(i);
  const gltf = await new GLTFLoader().parseAsync(u.buffer, '');
  const canvas = document.getElementById('c');
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  renderer.setSize(W, H, false);
  renderer.outputColorSpace = THREE.SRGBColorSpace;
  renderer.toneMapping = THREE.NeutralToneMapping;
  const s = new THREE.Scene(); s.background = new THREE.Color(0xf2f2f2);
  s.add(new THREE.HemisphereLight(0xffffff, 0x8a8f99, 1.5));
  const key = new THREE.DirectionalLight(0xffffff, 1.6); key.position.set(1.5, 3, 2.5); s.add(key);
  const rim = new THREE.DirectionalLight(0xffffff, 0.5); rim.position.set(-2, 1.5, -2.5); s.add(rim);
  s.add(gltf.scene);
  const info = { meshes: [], skinned: 0, textured: 0 };
  gltf.scene.traverse((o) => { if (o.isMesh) { o.frustumCulled = false; info.meshes.push(o.name);
    if (o.isSkinnedMesh) info.skinned += 1; if (o.material.map) info.textured += 1; } });
  gltf.scene.updateMatrixWorld(true);
  const box = new THREE.Box3().setFromObject(gltf.scene, true);
  const size = box.getSize(new THREE.Vector3()), ctr = box.getCenter(new THREE.Vector3());
  info.bbox = [box.min.toArray(), box.max.toArray()];
  const cam = new THREE.PerspectiveCamera(22, W / H, 0.01, 50);
  const dirs = { front: [0, 0, 1], back: [0, 0, -1], side: [1, 0, 0], face: [0, 0, 1], faceside: [1, 0, 0.35],
                 facequarter: [0.7, 0.05, 0.7], faceback: [0, 0.2, -1] };
  const d = new THREE.Vector3(...(dirs[view] || dirs.front)).normalize();
  let target = ctr, half = Math.max(size.y / 2, size.x / 2 / (W / H)) * 1.08;
  if (view.startsWith('face')) { target = new THREE.Vector3(ctr.x, box.max.y - 0.12, ctr.z + 0.02); half = 0.16; }
  const dist = half / Math.tan(THREE.MathUtils.degToRad(11));
  cam.position.copy(target).addScaledVector(d, dist); cam.lookAt(target);
  renderer.render(s, cam);
  return info;
};
window.ready = true;
</script></body></html>`;

const out = { images: [], errors: [], scenes: {} };
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
  args: ['--headless=new', '--no-sandbox', '--enable-unsafe-swiftshader', '--use-angle=swiftshader',
    '--disable-background-networking', '--disable-component-update', '--no-first-run'],
});
try {
  for (const file of files) {
    const name = path.basename(file, '.glb');
    const page = await browser.newPage({ viewport: { width: W, height: H } });
    page.on('pageerror', (e) => out.errors.push(`${name}: ${e.message}`));
    page.on('console', (m) => { if (m.type() === 'error') out.errors.push(`${name}: ${m.text()}`); });
    await page.route('http://render.local/**', async (route) => {
      const url = new URL(route.request().url());
      if (url.pathname === '/index.html') return route.fulfill({ status: 200, contentType: 'text/html', body: html });
      const f = path.join(three, url.pathname.replace(/^\/three\//, ''));
      if (!f.startsWith(three) || !fs.existsSync(f)) return route.fulfill({ status: 404, body: '' });
      return route.fulfill({ status: 200, contentType: 'text/javascript', body: fs.readFileSync(f) });
    });
    await page.goto('http://render.local/index.html');
    await page.waitForFunction(() => window.ready === true, null, { timeout: 60000 });
    const b64 = fs.readFileSync(file).toString('base64');
    for (const view of views) {
      out.scenes[name] = await page.evaluate(async ([b, v, w, h]) => window.render(b, v, w, h), [b64, view, W, H]);
      const p = path.join(outdir, `${name}-${view}.png`);
      await page.locator('#c').screenshot({ path: p });
      out.images.push(p);
    }
    await page.close();
  }
} finally {
  await browser.close();
}
console.log(JSON.stringify(out));
