// Headless three.js renderer (Chromium through playwright-core): the catalogue build's previews
// and a customer's view of any GLB.
// Usage: node worker/build/preview.mjs SCENES.json OUTDIR
//    or: node worker/build/preview.mjs --glb OUTDIR A.glb [B.glb ...]   (env VIEWS, default
//        "front,side,back,face"; WIDTH, HEIGHT, default 500 x 900)
// SCENES.json: [{name, views: ["front", "side", "back", "face"], width, height, meshes: [{name,
//   positions (base64 float32 xyz), normals (base64 float32), uvs (base64 float32, glTF convention:
//   origin top-left), indices (base64 uint32), color [r, g, b, a] linear, roughness, metalness,
//   map {mime, data (base64)}, normalMap {mime, data}, alphaMode (OPAQUE|MASK|BLEND), alphaCutoff,
//   doubleSided}]} or {name, views, width, height, glb (base64 GLB bytes), loaded by three.js's
//   GLTFLoader as a shop's viewer would; "face*" views frame its head)]. Writes
//   OUTDIR/<name>-<view>.png; prints a JSON summary {images, errors, scenes: {name: {meshes,
//   skinned, textured, bbox}}} (page errors included).
import { chromium } from 'playwright-core';
import fs from 'node:fs';
import path from 'node:path';
import { fileURLToPath } from 'node:url';

const args = process.argv.slice(2);
let scenes, outdir;
if (args[0] === '--glb') {
  outdir = args[1];
  const views = (process.env.VIEWS || 'front,side,back,face').split(',');
  const width = Number(process.env.WIDTH || 500), height = Number(process.env.HEIGHT || 900);
  scenes = args.slice(2).map((f) => ({ name: path.basename(f, '.glb'), views, width, height,
    glb: fs.readFileSync(f).toString('base64') }));
} else {
  outdir = args[1];
  scenes = JSON.parse(fs.readFileSync(args[0], 'utf8'));
}
fs.mkdirSync(outdir, { recursive: true });
const here = path.dirname(fileURLToPath(import.meta.url));
const three = path.resolve(here, '..', '..', 'node_modules', 'three');

const html = `<!doctype html><html><body style="margin:0;background:#fff">
<canvas id="c"></canvas>
<script type="importmap">{"imports": {"three": "http://preview.local/three/build/three.module.js",
  "three/addons/": "http://preview.local/three/examples/jsm/"}}</script>
<script type="module">
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
const b64 = (s, T) => { const bin = atob(s); const u = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) u[i] = bin.charCodeAt(i); return new T(u.buffer); };
const tex = async (t, srgb) => {
  const img = new Image(); img.src = 'data:' + t.mime + ';base64,' + t.data; await img.decode();
  const x = new THREE.Texture(img); x.flipY = false;  // glTF convention: UV origin top-left
  x.colorSpace = srgb ? THREE.SRGBColorSpace : THREE.NoColorSpace; x.anisotropy = 4;
  x.wrapS = x.wrapT = THREE.ClampToEdgeWrapping; x.needsUpdate = true; return x; };
window.render = async (scene, view) => {
  const canvas = document.getElementById('c');
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  renderer.setSize(scene.width || 700, scene.height || 1000, false);
  renderer.outputColorSpace = THREE.SRGBColorSpace;
  renderer.toneMapping = THREE.NeutralToneMapping;
  const s = new THREE.Scene(); s.background = new THREE.Color(0xf2f2f2);
  s.add(new THREE.HemisphereLight(0xffffff, 0x8a8f99, 1.5));
  const key = new THREE.DirectionalLight(0xffffff, 1.6); key.position.set(1.5, 3, 2.5); s.add(key);
  const rim = new THREE.DirectionalLight(0xffffff, 0.5); rim.position.set(-2, 1.5, -2.5); s.add(rim);
  const box = new THREE.Box3();
  const info = { meshes: [], skinned: 0, textured: 0 };
  if (scene.glb) {
    const gltf = await new GLTFLoader().parseAsync(b64(scene.glb, Uint8Array).buffer, '');
    s.add(gltf.scene);
    gltf.scene.traverse((o) => { if (o.isMesh) { o.frustumCulled = false; info.meshes.push(o.name);
      if (o.isSkinnedMesh) info.skinned += 1; if (o.material.map) info.textured += 1; } });
    gltf.scene.updateMatrixWorld(true);
    box.setFromObject(gltf.scene, true);
    info.bbox = [box.min.toArray(), box.max.toArray()];
  }
  for (const m of scene.meshes || []) {
    const g = new THREE.BufferGeometry();
    g.setAttribute('position', new THREE.BufferAttribute(b64(m.positions, Float32Array), 3));
    g.setAttribute('normal', new THREE.BufferAttribute(b64(m.normals, Float32Array), 3));
    if (m.uvs) g.setAttribute('uv', new THREE.BufferAttribute(b64(m.uvs, Float32Array), 2));
    g.setIndex(new THREE.BufferAttribute(b64(m.indices, Uint32Array), 1));
    const c = m.color || [0.8, 0.8, 0.8, 1];
    const mat = new THREE.MeshStandardMaterial({ color: new THREE.Color(c[0], c[1], c[2]),
      roughness: m.roughness ?? 0.85, metalness: m.metalness ?? 0, side: m.doubleSided ? THREE.DoubleSide : THREE.FrontSide });
    if (m.map) mat.map = await tex(m.map, true);
    if (m.normalMap) mat.normalMap = await tex(m.normalMap, false);
    if (m.alphaMode === 'MASK') { mat.alphaTest = m.alphaCutoff ?? 0.5; }
    if (m.alphaMode === 'BLEND') { mat.transparent = true; mat.opacity = c[3]; mat.depthWrite = false; }
    const mesh = new THREE.Mesh(g, mat); mesh.name = m.name; mesh.renderOrder = m.renderOrder || 0;
    s.add(mesh); if (!m.noFrame) box.expandByObject(mesh);
  }
  const size = box.getSize(new THREE.Vector3()), ctr = box.getCenter(new THREE.Vector3());
  const aspect = (scene.width || 700) / (scene.height || 1000);
  const cam = new THREE.PerspectiveCamera(scene.fov || 22, aspect, 0.01, 50);
  const dirs = { front: [0, 0, 1], back: [0, 0, -1], side: [1, 0, 0], left: [-1, 0, 0],
                 threequarter: [0.7, 0.05, 0.7], below: [0, -0.8, 1], under: [0, -1, 0.15], flank: [1, -0.3, 0.1], armpit: [0.6, 0.1, 1], face: [0, 0, 1], top: [0, 1, 0.3],
                 faceside: [1, 0, 0.35], facequarter: [0.7, 0.05, 0.7], faceback: [0, 0.2, -1] };
  const d = new THREE.Vector3(...(dirs[view] || dirs.front)).normalize();
  let target = ctr, dist;
  if (scene.target) target = new THREE.Vector3(...scene.target);
  let half = Math.max(size.y / 2, size.x / 2 / aspect) * 1.08;
  if (scene.glb && view.startsWith('face')) {  // a GLB's head: 12 cm under the top, 16 cm each way
    target = new THREE.Vector3(ctr.x, box.max.y - 0.12, ctr.z + 0.02); half = 0.16;
  }
  dist = scene.distance || half / Math.tan(THREE.MathUtils.degToRad((scene.fov || 22) / 2));
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
  for (const scene of scenes) {
    const page = await browser.newPage({ viewport: { width: scene.width || 700, height: scene.height || 1000 } });
    page.on('pageerror', (e) => out.errors.push(`${scene.name}: ${e.message}`));
    page.on('console', (m) => { if (m.type() === 'error') out.errors.push(`${scene.name}: ${m.text()}`); });
    await page.route('http://preview.local/**', async (route) => {
      const rel = new URL(route.request().url()).pathname.replace(/^\/three\//, '');
      const file = path.join(three, rel);
      if (!file.startsWith(three) || !fs.existsSync(file)) return route.fulfill({ status: 404, body: '' });
      return route.fulfill({ status: 200, contentType: 'text/javascript', body: fs.readFileSync(file) });
    });
    await page.route('http://preview.local/index.html', (r) => r.fulfill({ status: 200, contentType: 'text/html', body: html }));
    await page.goto('http://preview.local/index.html');
    await page.waitForFunction(() => window.ready === true, null, { timeout: 60000 });
    for (const view of scene.views || ['front']) {
      out.scenes[scene.name] = await page.evaluate(async ([s, v]) => window.render(s, v), [scene, view]);
      const p = path.join(outdir, `${scene.name}-${view}.png`);
      await page.locator('#c').screenshot({ path: p });
      out.images.push(p);
    }
    await page.close();
  }
} finally {
  await browser.close();
}
console.log(JSON.stringify(out));
