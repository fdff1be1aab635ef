// The customer page: measurements -> live skinned avatar (three.js), shape sliders, pose
// presets, the garment catalogue, hair, live editing of an uploaded scan (WebSocket) and the
// customer's own data (save / delete).
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { MeshoptDecoder } from 'three/addons/libs/meshopt_decoder.module.js';

const GLB = 'model/gltf-binary';
const CM_PER_IN = 2.54;
const KG_PER_LB = 0.45359237;
const DEBOUNCE_MS = 400;
const CUSTOMER_KEY = 'tryon.customerId';
const TOKEN_KEY = 'tryon.customerToken'; // the customer's secret (Authorization: Bearer), kept with the id
const DEFAULTS = { gender: 'female', height_cm: 168 };
const FRAME_MARGIN = 0.84;      // the framed scene fills at most this share of the view (each way)
const START_DIRECTION = [0, 0.06, 1]; // camera -> target direction before the shopper orbits
const BACKGROUND = 0xe7eaf0;
const SCAN_COLOUR = 0xb8a99a;   // an uploaded scan carries no material: a neutral clay
const EDIT_EPSILON = 0.05;      // cm/kg: a slider this close to the fitted value is not an edit
// Bodies keep their real height on screen: the camera frames a standing figure of the body
// model's tallest height (GET /v1/body-model, height_cm max) whatever the body, so a 150 cm and
// a 190 cm body differ on screen as they do in life; a ruler beside the body marks the height.
const FRAME_REFERENCE_FALLBACK_M = 2.1;
const FRAME_REFERENCE_WIDTH_M = 0.9;  // the framed figure's width and depth (the body's own box when wider)
const FRAME_REFERENCE_DEPTH_M = 0.5;
const RULER_GAP_M = 0.12;       // the ruler stands this far to the side of the body's box
const MAIN_FIELDS = ['gender', 'height_cm', 'weight_kg', 'chest_cm', 'waist_cm', 'hip_cm']; // the rest: "More measurements"

const $ = (sel) => document.querySelector(sel);
const state = {
  attributes: [],          // from GET /v1/body-model
  values: { ...DEFAULTS }, // API units (cm, kg); a missing key = not given (estimated)
  units: 'metric',
  garments: [],            // the catalogue
  worn: [],                // chosen garment ids
  hair: '',                // chosen hair ('' = the server's default for the gender, 'none' = none)
  customerId: localStorage.getItem(CUSTOMER_KEY),
  customerToken: localStorage.getItem(TOKEN_KEY),
  customerStale: false,    // measurements changed since the customer was saved
  pose: 'a-pose',
  scan: null,              // the customer record of an uploaded scan (live editing), else null
  view: 'scan',            // scan customers: 'scan' (edited live) | 'body' | 'scan-pose' (body as scanned)
  catalogueAll: false,     // the catalogue shows every garment, not only the customer's gender (and unisex)
  sizes: {},               // garment id -> the size label the shopper picked
  fits: new Map(),         // `${customer}|${garment}` -> GET .../fit answer, or null (404: no sizes there)
  fitmap: 'off',           // 'off' | 'strain' | 'ease': vertex colours on the garments (?fitmap=)
  drape: 'exact',          // 'exact': after the instant try-on, the garments as draped on this body (?drape=exact) | 'basis'
};

// ---- three.js scene -----------------------------------------------------------------------
const canvas = $('#scene');
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
renderer.outputColorSpace = THREE.SRGBColorSpace;
renderer.toneMapping = THREE.NeutralToneMapping; // keeps cloth colours close to their base colour
renderer.toneMappingExposure = 1.0;
renderer.shadowMap.enabled = true;
renderer.shadowMap.type = THREE.PCFShadowMap;
const scene = new THREE.Scene();
scene.background = new THREE.Color(BACKGROUND);
const camera = new THREE.PerspectiveCamera(35, 1, 0.05, 60);
camera.position.set(0, 1.0, 4.2);
const controls = new OrbitControls(camera, canvas);
controls.target.set(0, 0.9, 0);
controls.enableDamping = false;
controls.listenToKeyEvents(canvas); // arrow keys when the canvas has focus
controls.addEventListener('change', () => { orientRuler(); render(); });

// Lighting for cloth: a sky/ground hemisphere for soft fill, a warm key light that casts a soft
// shadow on the floor, a cool rim light from behind to separate the silhouette.
const hemi = new THREE.HemisphereLight(0xf2f5ff, 0x8d8478, 1.5);
scene.add(hemi);
const key = new THREE.DirectionalLight(0xfff3e6, 2.4);
key.position.set(1.4, 3.2, 2.2);
key.castShadow = true;
key.shadow.mapSize.set(1024, 1024);
key.shadow.radius = 4;
key.shadow.bias = -0.0004;
key.shadow.normalBias = 0.02;
scene.add(key, key.target);
const rim = new THREE.DirectionalLight(0xe6eeff, 0.9);
rim.position.set(-2, 2.4, -2.2);
scene.add(rim);
const fill = new THREE.DirectionalLight(0xffffff, 0.5);
fill.position.set(-2.2, 1.2, 1.8);
scene.add(fill);

// The floor: a disc that receives the key light's shadow, and a blurred contact shadow (a
// radial gradient) right under the feet so the avatar stands on it rather than floats.
const floor = new THREE.Mesh(new THREE.CircleGeometry(1.6, 64),
  new THREE.MeshStandardMaterial({ color: 0xd3d7df, roughness: 0.95 }));
floor.rotation.x = -Math.PI / 2;
floor.receiveShadow = true;
scene.add(floor);
function contactShadowTexture() {
  const c = document.createElement('canvas');
  c.width = c.height = 128;
  const g = c.getContext('2d');
  const grad = g.createRadialGradient(64, 64, 0, 64, 64, 64);
  grad.addColorStop(0, 'rgba(0,0,0,0.55)');
  grad.addColorStop(0.45, 'rgba(0,0,0,0.28)');
  grad.addColorStop(1, 'rgba(0,0,0,0)');
  g.fillStyle = grad;
  g.fillRect(0, 0, 128, 128);
  const t = new THREE.CanvasTexture(c);
  t.colorSpace = THREE.SRGBColorSpace;
  return t;
}
const contact = new THREE.Mesh(new THREE.PlaneGeometry(1, 1),
  new THREE.MeshBasicMaterial({ map: contactShadowTexture(), transparent: true, depthWrite: false, toneMapped: false }));
contact.rotation.x = -Math.PI / 2;
contact.position.y = 0.002;
contact.renderOrder = 1;
scene.add(contact);

const loader = new GLTFLoader();
loader.setMeshoptDecoder(MeshoptDecoder);
let current = null; // the loaded glTF scene (avatar, or avatar + garments)
let rest = new Map(); // bone -> rest quaternion
let scanMesh = null; // scan customers: the scan, edited live over the WebSocket

function meshes() { const out = []; current?.traverse((o) => { if (o.isMesh) out.push(o); }); return out; }
function bones() { const out = []; current?.traverse((o) => { if (o.isBone) out.push(o); }); return out; }
function shown() { return scanMesh && scanMesh.visible ? scanMesh : current; } // what the viewer frames
function avatarMesh() { const m = meshes(); return m.find((x) => x.name === 'avatar') || m[0] || null; }

function resize() {
  const w = canvas.clientWidth || 1, h = canvas.clientHeight || 1;
  renderer.setSize(w, h, false);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
  frame();
}
function render() { renderer.render(scene, camera); }
new ResizeObserver(resize).observe(canvas);

// Box of what is drawn now (skinned vertices as posed, not the bind pose).
function visibleBox(obj) {
  const box = new THREE.Box3();
  if (!obj) return box;
  obj.updateMatrixWorld(true);
  obj.traverse((o) => { if (o.isMesh && o.visible) box.expandByObject(o, true); });
  return box;
}

// Frame the shown scene: target its box centre, keep the direction the shopper orbited to, and
// step back until all 8 box corners lie within FRAME_MARGIN of the view (both ways). Also
// fits the floor, the contact shadow and the key light's shadow camera to the body.
function frame() {
  const obj = shown();
  if (!obj) { render(); return; }
  const body = visibleBox(obj);
  if (body.isEmpty()) { render(); return; }
  placeRuler(body);
  // the framed box: the body's, grown to a reference figure standing where the body stands
  const bc = body.getCenter(new THREE.Vector3());
  const box = body.clone().union(new THREE.Box3(
    new THREE.Vector3(bc.x - FRAME_REFERENCE_WIDTH_M / 2, body.min.y, bc.z - FRAME_REFERENCE_DEPTH_M / 2),
    new THREE.Vector3(bc.x + FRAME_REFERENCE_WIDTH_M / 2, body.min.y + referenceHeight(), bc.z + FRAME_REFERENCE_DEPTH_M / 2)));
  if (ruler.visible) box.expandByPoint(ruler.position.clone().addScaledVector(ruler.userData.right, 0.25));
  const centre = box.getCenter(new THREE.Vector3()), size = body.getSize(new THREE.Vector3());
  const dir = camera.position.clone().sub(controls.target);
  if (dir.lengthSq() < 1e-8) dir.set(...START_DIRECTION);
  dir.normalize();
  // camera basis for that direction
  const back = dir, right = new THREE.Vector3().crossVectors(camera.up, back).normalize();
  if (right.lengthSq() < 1e-8) right.set(1, 0, 0);
  const up = new THREE.Vector3().crossVectors(back, right);
  const tanV = Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)) * FRAME_MARGIN;
  const tanH = tanV * camera.aspect;
  let dist = 0.5;
  const p = new THREE.Vector3();
  for (let i = 0; i < 8; i += 1) {
    p.set(i & 1 ? box.max.x : box.min.x, i & 2 ? box.max.y : box.min.y, i & 4 ? box.max.z : box.min.z).sub(centre);
    const depth = p.dot(back); // towards the camera
    dist = Math.max(dist, depth + Math.abs(p.dot(up)) / tanV, depth + Math.abs(p.dot(right)) / tanH);
  }
  controls.target.copy(centre);
  camera.position.copy(centre).addScaledVector(back, dist);
  camera.near = Math.max(0.02, dist / 100); camera.far = dist * 20;
  camera.updateProjectionMatrix();
  controls.update();
  // the floor under the feet
  const feet = body.min.y;
  floor.position.set(bc.x, feet, bc.z);
  contact.position.set(bc.x, feet + 0.002, bc.z);
  contact.scale.set(Math.max(0.5, size.x * 0.75), Math.max(0.4, size.z * 1.6), 1);
  const reach = Math.max(size.x, size.y, size.z);
  key.target.position.copy(bc);
  key.position.copy(bc).add(new THREE.Vector3(1.4, 3.2, 2.2).normalize().multiplyScalar(reach * 2));
  const sc = key.shadow.camera;
  sc.left = sc.bottom = -reach * 0.9; sc.right = sc.top = reach * 0.9;
  sc.near = reach * 0.5; sc.far = reach * 4;
  sc.updateProjectionMatrix();
  hook.frames += 1;
  render();
}

function referenceHeight() {
  const h = state.attributes.find((a) => a.name === 'height_cm');
  return h && Number.isFinite(h.max) ? h.max / 100 : FRAME_REFERENCE_FALLBACK_M;
}

// The height mark: a ruler (a tick every 10 cm, a label every 50 cm) standing on the floor beside
// the body, and a marker at the top of the body's head with its height.
const ruler = new THREE.Group();
let rulerLabel = null; // the body's height, at the top of its head
ruler.name = 'ruler';
scene.add(ruler);
function labelSprite(text, heightM, colour = '#3a4a6b') {
  const c = document.createElement('canvas');
  const g = c.getContext('2d');
  const px = 48;
  g.font = `600 ${px}px system-ui, sans-serif`;
  c.width = Math.ceil(g.measureText(text).width) + 16; c.height = px + 16;
  g.font = `600 ${px}px system-ui, sans-serif`;
  g.fillStyle = colour; g.textBaseline = 'middle';
  g.fillText(text, 8, c.height / 2);
  const t = new THREE.CanvasTexture(c);
  t.colorSpace = THREE.SRGBColorSpace;
  const s = new THREE.Sprite(new THREE.SpriteMaterial({ map: t, depthTest: false, toneMapped: false }));
  s.scale.set(heightM * c.width / c.height, heightM, 1);
  s.center.set(0, 0.5);
  s.renderOrder = 3;
  return s;
}
function buildRuler(topM) {
  ruler.traverse((o) => { if (o.geometry) o.geometry.dispose(); if (o.material) { o.material.map?.dispose(); o.material.dispose(); } });
  ruler.clear();
  rulerLabel = null;
  const mat = new THREE.MeshBasicMaterial({ color: 0x3a4a6b, toneMapped: false });
  const bar = new THREE.Mesh(new THREE.BoxGeometry(0.008, topM, 0.008), mat);
  bar.position.y = topM / 2;
  ruler.add(bar);
  for (let cm = 0; cm <= topM * 100 + 1e-6; cm += 10) {
    const major = cm % 50 === 0;
    const tick = new THREE.Mesh(new THREE.BoxGeometry(major ? 0.06 : 0.03, 0.004, 0.004), mat);
    tick.position.set(major ? 0.03 : 0.015, cm / 100, 0);
    ruler.add(tick);
    if (major && cm > 0) { const l = labelSprite(`${cm}`, 0.045); l.position.set(0.07, cm / 100, 0); ruler.add(l); }
  }
  const head = new THREE.Mesh(new THREE.BoxGeometry(0.14, 0.006, 0.006), new THREE.MeshBasicMaterial({ color: 0xc2410c, toneMapped: false }));
  head.name = 'ruler-head';
  ruler.add(head);
  ruler.userData.top = topM;
}
// The ruler stands to the camera's right of the body, facing the camera, wherever the shopper
// turned it (never between the camera and the body).
let rulerBody = null;
function orientRuler() {
  if (!rulerBody) return;
  const back = camera.position.clone().sub(controls.target);
  back.y = 0;
  if (back.lengthSq() < 1e-8) back.set(0, 0, 1);
  back.normalize();
  const right = new THREE.Vector3(back.z, 0, -back.x); // up x back
  const c = rulerBody.getCenter(new THREE.Vector3()), p = new THREE.Vector3();
  let reach = 0;
  for (let i = 0; i < 8; i += 1) {
    p.set(i & 1 ? rulerBody.max.x : rulerBody.min.x, 0, i & 4 ? rulerBody.max.z : rulerBody.min.z).sub(c);
    reach = Math.max(reach, p.dot(right));
  }
  ruler.position.copy(c).addScaledVector(right, reach + RULER_GAP_M);
  ruler.position.y = rulerBody.min.y;
  ruler.rotation.set(0, Math.atan2(back.x, back.z), 0); // its ticks towards the camera's right
  ruler.userData.right = right;
}
function placeRuler(body) {
  const top = Math.ceil(referenceHeight() * 10) / 10;
  if (ruler.userData.top !== top) buildRuler(top);
  const m = scanMesh && scanMesh.visible ? scanMesh : avatarMesh();
  const own = m ? visibleBox(m) : body;
  const h = own.max.y - body.min.y;
  rulerBody = body;
  orientRuler();
  const head = ruler.getObjectByName('ruler-head');
  head.position.set(-0.05, h, 0);
  const inches = Math.round(h * 100 / CM_PER_IN);
  const text = state.units === 'metric' ? `${Math.round(h * 100)} cm` : `${Math.floor(inches / 12)}' ${inches % 12}"`;
  if (!rulerLabel || rulerLabel.userData.text !== text) {
    if (rulerLabel) { ruler.remove(rulerLabel); rulerLabel.material.map.dispose(); rulerLabel.material.dispose(); }
    rulerLabel = labelSprite(text, 0.06, '#c2410c');
    rulerLabel.userData.text = text;
    ruler.add(rulerLabel);
  }
  rulerLabel.center.set(1, 0); // left of the ruler, above the marker (the ruler's own labels are on its right)
  rulerLabel.position.set(-0.02, h + 0.008, 0);
  ruler.visible = h > 0.3;
  hook.rulerHeight = h;
}

function dressUp(root) {
  const body = avatarOf(root);
  root.traverse((o) => {
    if (!o.isMesh) return;
    o.frustumCulled = false;
    o.castShadow = true;
    o.receiveShadow = true;
    const isAvatar = o === body;
    // a fit map (?fitmap=strain|ease) comes as vertex colours (COLOR_0): shown as they are, not
    // multiplied by the garment's colour or texture
    const fitColours = !isAvatar && state.fitmap !== 'off' && o.geometry?.getAttribute('color');
    for (const m of [].concat(o.material)) {
      if (fitColours) { m.vertexColors = true; m.map = null; m.color?.set(0xffffff); }
      // cloth is seen from both sides (sleeves, hems, open jackets); the body only from outside
      if (!isAvatar) m.side = THREE.DoubleSide;
      m.shadowSide = THREE.FrontSide;
      if (m.map) m.map.anisotropy = renderer.capabilities.getMaxAnisotropy();
      m.needsUpdate = true;
    }
  });
}
function avatarOf(root) {
  let first = null, named = null;
  root.traverse((o) => { if (o.isMesh) { first ??= o; if (o.name === 'avatar') named = o; } });
  return named || first;
}

async function showGlb(buffer) {
  const gltf = await loader.parseAsync(buffer, '');
  if (current) { scene.remove(current); disposeTree(current); }
  current = gltf.scene;
  dressUp(current);
  scene.add(current);
  rest = new Map(bones().map((b) => [b, b.quaternion.clone()]));
  applyPose(state.pose);
  if (scanMesh) current.visible = state.view !== 'scan';
  frame();
  hook.loads += 1;
  render();
}

function disposeTree(obj) {
  obj.traverse((o) => {
    if (o.geometry) o.geometry.dispose();
    if (o.material) [].concat(o.material).forEach((m) => { if (m.map) m.map.dispose(); m.dispose(); });
  });
}

// ---- test hook ----------------------------------------------------------------------------
// Screen box (CSS px, relative to the canvas) of a world box's 8 corners.
function screenBox(box) {
  const w = canvas.clientWidth, h = canvas.clientHeight, v = new THREE.Vector3();
  let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
  for (let i = 0; i < 8; i += 1) {
    v.set(i & 1 ? box.max.x : box.min.x, i & 2 ? box.max.y : box.min.y, i & 4 ? box.max.z : box.min.z).project(camera);
    const x = (v.x + 1) / 2 * w, y = (1 - v.y) / 2 * h;
    x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y);
  }
  return { x0, y0, x1, y1, width: w, height: h };
}
// The highest vertex of the body (the top of the head), as drawn, projected to the canvas.
function headTop() {
  const m = scanMesh && scanMesh.visible ? scanMesh : avatarMesh();
  if (!m) return null;
  m.updateMatrixWorld(true);
  const v = new THREE.Vector3(), top = new THREE.Vector3(0, -Infinity, 0);
  const n = m.geometry.getAttribute('position').count;
  for (let i = 0; i < n; i += 1) {
    m.getVertexPosition(i, v); v.applyMatrix4(m.matrixWorld);
    if (v.y > top.y) top.copy(v);
  }
  const world = top.toArray();
  top.project(camera);
  return { x: (top.x + 1) / 2 * canvas.clientWidth, y: (1 - top.y) / 2 * canvas.clientHeight, world,
    width: canvas.clientWidth, height: canvas.clientHeight };
}
// Share of the pixels inside a mesh's screen box that change when that mesh is hidden (it is
// drawn, and not hidden under another one), and the share that differ from the background.
function meshPixels(name) {
  const m = meshes().find((x) => x.name === name);
  if (!m) return null;
  const sb = screenBox(visibleBox(m));
  const read = () => {
    render();
    const t = document.createElement('canvas');
    t.width = canvas.clientWidth; t.height = canvas.clientHeight;
    const ctx = t.getContext('2d');
    ctx.drawImage(canvas, 0, 0, t.width, t.height);
    const x0 = Math.max(0, Math.floor(sb.x0)), y0 = Math.max(0, Math.floor(sb.y0));
    const x1 = Math.min(t.width, Math.ceil(sb.x1)), y1 = Math.min(t.height, Math.ceil(sb.y1));
    return { d: ctx.getImageData(x0, y0, Math.max(1, x1 - x0), Math.max(1, y1 - y0)).data, bg: ctx.getImageData(2, 2, 1, 1).data };
  };
  const on = read();
  m.visible = false;
  const off = read();
  m.visible = true;
  render();
  let changed = 0, notBg = 0;
  const px = on.d.length / 4;
  for (let i = 0; i < on.d.length; i += 4) {
    const dOn = Math.abs(on.d[i] - off.d[i]) + Math.abs(on.d[i + 1] - off.d[i + 1]) + Math.abs(on.d[i + 2] - off.d[i + 2]);
    if (dOn > 12) changed += 1;
    const dBg = Math.abs(on.d[i] - on.bg[0]) + Math.abs(on.d[i + 1] - on.bg[1]) + Math.abs(on.d[i + 2] - on.bg[2]);
    if (dBg > 12) notBg += 1;
  }
  return { changed: changed / px, notBackground: notBg / px, box: sb };
}
const hook = {
  ready: false, busy: false, loads: 0, frames: 0, lastError: null, pose: 'a-pose',
  meshCount: () => meshes().length,
  meshNames: () => meshes().map((m) => m.name),
  skinnedMeshCount: () => meshes().filter((m) => m.isSkinnedMesh).length,
  boneNames: () => [...new Set(bones().map((b) => b.name))],
  garmentsWorn: () => [...state.worn],
  customerId: () => state.customerId,
  bboxHeight: () => (current ? new THREE.Box3().setFromObject(current).getSize(new THREE.Vector3()).y : 0),
  boneQuaternion: (name) => { const b = bones().find((x) => x.name === name); return b ? b.quaternion.toArray() : null; },
  values: () => ({ ...state.values }),
  headTop,
  sceneScreenBox: () => screenBox(visibleBox(shown())),
  sceneWorldHeight: () => visibleBox(shown()).getSize(new THREE.Vector3()).y,
  meshPixels,
  cameraDirection: () => camera.position.clone().sub(controls.target).normalize().toArray(),
  orbit: (azimuth) => { // turn the camera about the vertical through the target (radians), as a drag would
    const off = camera.position.clone().sub(controls.target).applyAxisAngle(new THREE.Vector3(0, 1, 0), azimuth);
    camera.position.copy(controls.target).add(off); controls.update(); orientRuler(); render();
  },
  hair: () => state.hair,
  scanSize: () => (scanMesh ? new THREE.Box3().setFromObject(scanMesh).getSize(new THREE.Vector3()).toArray() : null),
  scan: { frames: 0, kind: null, vertices: 0, faces: 0, sent: 0, view: () => state.view, errors: [] },
};
window.__tryon = hook;

// ---- poses: rotate bones by name so that each segment points in a target direction --------
// The presets live in poses.json (shared with the service: service/model/body/poses.py): world
// directions (Y up, the body faces +Z, the character's left = +X) of segments bone -> child.
// For a saved customer the service adapts them to the body (GET /v1/customers/{id}/poses: more
// shoulder abduction so arms stay out of the torso); those local rotations (axis-angle, rest
// frames = world axes) are used when they have arrived, the directions otherwise.
let PRESETS = null; // poses.json
const bodyPoses = new Map(); // customer id -> {pose: {bone: [x, y, z]}} | 'loading' | 'failed'
const presetsLoaded = fetch('poses.json').then((r) => r.json()).then((p) => { PRESETS = p; applyPose(state.pose); })
  .catch(() => { PRESETS = { order: [], child: {}, poses: {} }; });
hook.presetsLoaded = presetsLoaded;
hook.poseSource = 'directions';

function presetTargets(name) {
  const p = PRESETS?.poses?.[name];
  if (!p) return {};
  const out = { ...(p.targets || {}) };
  if (p.mirror) for (const [k, [x, y, z]] of Object.entries(p.targets || {})) if (k.endsWith('_l')) out[k.replace(/_l$/, '_r')] = [-x, y, z];
  return out;
}

function customerPoses() {
  const id = state.customerId;
  if (!id || state.customerStale) return null;
  const hit = bodyPoses.get(id);
  if (hit && typeof hit === 'object') return hit;
  if (!hit) {
    bodyPoses.set(id, 'loading');
    api(`/v1/customers/${id}/poses`, asCustomer()).then((r) => r.json()).then((p) => {
      bodyPoses.set(id, p);
      if (state.customerId === id) applyPose(state.pose);
    }).catch(() => bodyPoses.set(id, 'failed'));
  }
  return null;
}

// Pose-corrective morph targets (outfit.glb?pose_correctives=1): a garment may carry one target
// per preset, `pose:<name>`, that keeps it outside the body in that pose; the current pose's at
// influence 1, the others at 0. Meshes without them (the avatar, older GLBs) are left alone.
// The targets are made for the body's adapted poses (GET /v1/customers/{id}/poses), so while the
// page poses with the plain directions (the adapted ones not arrived yet) every target is at 0:
// name null.
let correctivesOn = true; // off: every pose target at 0 (hook.setCorrectives, to compare)
function setPoseCorrectives(name) {
  for (const m of meshes()) {
    const dict = m.morphTargetDictionary, inf = m.morphTargetInfluences;
    if (!dict || !inf) continue;
    for (const [key, i] of Object.entries(dict)) {
      if (key.startsWith('pose:')) inf[i] = correctivesOn && key === `pose:${name}` ? 1 : 0;
    }
  }
}
hook.setCorrectives = (on) => {
  correctivesOn = Boolean(on); setPoseCorrectives(hook.poseSource === 'body' ? state.pose : null); render();
};
// {mesh name: {target name: influence}} of the meshes that have pose-corrective targets
hook.poseCorrectives = () => Object.fromEntries(meshes().filter((m) => m.morphTargetDictionary
  && Object.keys(m.morphTargetDictionary).some((k) => k.startsWith('pose:'))).map((m) => [m.name,
  Object.fromEntries(Object.entries(m.morphTargetDictionary).map(([k, i]) => [k, m.morphTargetInfluences[i]]))]));

function applyPose(name) {
  state.pose = name; hook.pose = name;
  if (!current) return;
  // Every bone of that name (the outfit scene shares one skeleton; if a garment carried its
  // own copy of the joints it gets the same rotations).
  for (const [b, q] of rest) b.quaternion.copy(q);
  current.updateMatrixWorld(true);
  const byName = new Map();
  for (const b of bones()) { if (!byName.has(b.name)) byName.set(b.name, []); byName.get(b.name).push(b); }
  const adapted = customerPoses()?.[name];
  if (adapted) {
    const axis = new THREE.Vector3();
    for (const [boneName, rv] of Object.entries(adapted)) {
      const angle = Math.hypot(...rv);
      if (!byName.has(boneName) || angle < 1e-9) continue;
      const q = new THREE.Quaternion().setFromAxisAngle(axis.set(...rv).divideScalar(angle), angle);
      for (const b of byName.get(boneName)) b.quaternion.copy(rest.get(b)).multiply(q);
    }
    hook.poseSource = 'body';
    setPoseCorrectives(name);
    current.updateMatrixWorld(true);
    render();
    return;
  }
  hook.poseSource = 'directions';
  setPoseCorrectives(null);
  const targets = presetTargets(name);
  const a = new THREE.Vector3(), c = new THREE.Vector3(), pq = new THREE.Quaternion(), wq = new THREE.Quaternion();
  for (const boneName of PRESETS?.order || []) {
    const childName = PRESETS.child[boneName];
    if (!targets[boneName] || !byName.has(boneName) || !byName.has(childName)) continue;
    const bone = byName.get(boneName)[0], child = byName.get(childName)[0];
    bone.getWorldPosition(a); child.getWorldPosition(c);
    const from = c.sub(a).normalize(), to = new THREE.Vector3(...targets[boneName]).normalize();
    const delta = new THREE.Quaternion().setFromUnitVectors(from, to);
    bone.getWorldQuaternion(wq);
    bone.parent.getWorldQuaternion(pq);
    const local = pq.invert().multiply(delta.multiply(wq));
    for (const b of byName.get(boneName)) b.quaternion.copy(local);
    current.updateMatrixWorld(true);
  }
  render();
}

document.querySelectorAll('#poses button').forEach((btn) => btn.addEventListener('click', () => {
  document.querySelectorAll('#poses button').forEach((x) => x.setAttribute('aria-pressed', String(x === btn)));
  applyPose(btn.dataset.pose);
}));

// A pose changes the body's extent (arms out, a step): frame again, and a scan follows the pose.
document.querySelectorAll('#poses button').forEach((btn) => btn.addEventListener('click', () => {
  if (state.scan) { scanPoseChosen = true; reframeScan = true; sendScanEdit(); }
  frame();
}));

// ---- hair (the server's looks, when it lists them) ----------------------------------------
// GET /v1/looks may answer a list, or an object with a list of hair styles; each an id string
// or {id, name, kind|type|category}. Anything but 200 (or no hair in it) hides the selector.
function hairOptions(body) {
  const list = Array.isArray(body) ? body : (body?.hair || body?.looks || body?.items || []);
  const out = [];
  for (const item of Array.isArray(list) ? list : []) {
    if (typeof item === 'string') { out.push({ id: item, name: item }); continue; }
    if (!item || typeof item !== 'object' || !item.id) continue;
    const kind = item.kind || item.type || item.category;
    if (kind && !/hair/i.test(String(kind))) continue;
    out.push({ id: String(item.id), name: String(item.name || item.label || item.id) });
  }
  return out;
}

async function buildHair() {
  const section = $('#hair-section');
  let options = [];
  try {
    const r = await fetch('/v1/looks');
    if (r.ok) options = hairOptions(await r.json());
  } catch { /* no looks: no selector */ }
  section.hidden = options.length === 0;
  hook.hairOptions = options.map((o) => o.id);
  if (!options.length) return;
  const sel = $('#hair');
  sel.innerHTML = '';
  // no hair= on the URL is the server's default style for the body's gender; 'none' is no hair
  sel.add(new Option('Default style', ''));
  sel.add(new Option('No hair', 'none'));
  for (const o of options) sel.add(new Option(o.name.replace(/[_-]+/g, ' '), o.id));
  sel.value = state.hair;
  sel.addEventListener('change', () => { state.hair = sel.value; refresh(); });
}

// Every GLB the page shows is asked for meshopt-compressed (EXT_meshopt_compression over
// KHR_mesh_quantization, decoded by three.js's MeshoptDecoder): about half the bytes of the
// plain GLB (a tee and jeans outfit with the avatar 1.75 -> 0.91 MB), which is most of what a
// shopper on a phone waits for.
const GLB_COMPRESSION = 'meshopt';
function compressed(url) {
  return `${url}${url.includes('?') ? '&' : '?'}compression=${GLB_COMPRESSION}`;
}

function withHair(url) {
  if (!state.hair) return url;
  return `${url}${url.includes('?') ? '&' : '?'}hair=${encodeURIComponent(state.hair)}`;
}

// ---- scan customers: the uploaded scan, edited live over the WebSocket --------------------
// Protocol (service/api/customers.py): a JSON head {vertices, faces, kind}, then the faces
// (uint32 F x 3) and the current vertices (float32 n x 3); each JSON edit {measurements, pose}
// sent is answered by a float32 vertex frame, or a JSON {error: 422, detail}.
let ws = null, wsHead = null, wsFaces = null, inFlight = false, pending = false, scanPoseChosen = false, reframeScan = false;

function scanEdits() {
  const fitted = state.scan?.measurements || {};
  const m = {};
  for (const a of state.attributes) {
    if (a.unit === null) continue; // gender cannot change
    const v = state.values[a.name], f = fitted[a.name];
    if (typeof v === 'number' && (typeof f !== 'number' || Math.abs(v - f) > EDIT_EPSILON)) m[a.name] = Math.round(v * 100) / 100;
  }
  return m;
}

// The page's pose presets as the edit API wants them: each bone's rotation, local to its
// parent, as axis-angle (the avatar's bones are at identity in the rest pose). Until the
// shopper picks a pose the scan keeps its own (pose {} = as fitted).
function scanPose() {
  if (!scanPoseChosen || !current) return {};
  const out = {}, seen = new Set();
  for (const b of bones()) {
    if (seen.has(b.name)) continue;
    seen.add(b.name);
    const q = b.quaternion.clone().normalize();
    if (q.w < 0) q.set(-q.x, -q.y, -q.z, -q.w);
    const angle = 2 * Math.acos(Math.min(1, q.w)), s = Math.sqrt(Math.max(0, 1 - q.w * q.w));
    out[b.name] = s < 1e-6 ? [0, 0, 0] : [q.x / s * angle, q.y / s * angle, q.z / s * angle].map((x) => Math.round(x * 1e5) / 1e5);
  }
  return out;
}

function sendScanEdit() {
  if (!ws || ws.readyState !== WebSocket.OPEN || !wsFaces) { pending = true; return; }
  if (inFlight) { pending = true; return; }
  inFlight = true; pending = false;
  ws.send(JSON.stringify({ measurements: scanEdits(), pose: scanPose() }));
  hook.scan.sent += 1;
  $('#scan-status').textContent = 'Reshaping your scan…';
}

function scanFrame(buf) {
  const v = new Float32Array(buf);
  const first = !scanMesh;
  if (!scanMesh) {
    const g = new THREE.BufferGeometry();
    g.setAttribute('position', new THREE.BufferAttribute(v, 3));
    g.setIndex(new THREE.BufferAttribute(wsFaces, 1));
    g.computeVertexNormals();
    scanMesh = new THREE.Mesh(g, new THREE.MeshStandardMaterial({ color: SCAN_COLOUR, roughness: 0.85, side: THREE.DoubleSide }));
    scanMesh.name = 'scan';
    scanMesh.castShadow = scanMesh.receiveShadow = true;
    scanMesh.frustumCulled = false;
    scene.add(scanMesh);
  } else {
    const attr = scanMesh.geometry.getAttribute('position');
    if (attr.array.length === v.length) { attr.array.set(v); attr.needsUpdate = true; } else {
      scanMesh.geometry.setAttribute('position', new THREE.BufferAttribute(v, 3));
    }
    scanMesh.geometry.computeVertexNormals();
    scanMesh.geometry.computeBoundingBox();  // the cached boxes would keep the first frame's size
    scanMesh.geometry.computeBoundingSphere();
  }
  // frame the first frame and after a pose; not while a slider is dragged (no camera jumps)
  if (first || reframeScan) { reframeScan = false; setView(state.view); } else render();
  hook.scan.frames += 1;
}

function openScanSocket() {
  if (ws) ws.close();
  wsHead = null; wsFaces = null; inFlight = false;
  const proto = location.protocol === 'https:' ? 'wss' : 'ws';
  const url = `${proto}://${location.host}/v1/customers/${encodeURIComponent(state.customerId)}/edit/ws?token=${encodeURIComponent(state.customerToken || '')}`;
  const sock = new WebSocket(url);
  ws = sock;
  sock.binaryType = 'arraybuffer';
  sock.onmessage = (ev) => {
    if (ws !== sock) return;
    if (typeof ev.data === 'string') {
      const msg = JSON.parse(ev.data);
      if (msg.error) {
        inFlight = false;
        hook.scan.errors.push(msg);
        showError(new ApiError(msg.error, { detail: msg.detail }));
        if (pending) sendScanEdit();
        return;
      }
      wsHead = msg;
      Object.assign(hook.scan, { kind: msg.kind, vertices: msg.vertices, faces: msg.faces });
      return;
    }
    if (!wsFaces) { wsFaces = new Uint32Array(ev.data); return; }
    inFlight = false;
    clearErrors();
    scanFrame(ev.data);
    $('#scan-status').textContent = wsHead?.kind === 'scan'
      ? 'Your scan, clothes and all: move the sliders or pick a pose to reshape it.'
      : 'Your avatar: move the sliders or pick a pose to reshape it.';
    if (pending) sendScanEdit();
  };
  sock.onclose = (ev) => {
    if (ws !== sock) return;
    ws = null;
    if (ev.code === 4404 || ev.code === 4409) $('#scan-status').textContent = ev.reason || 'Your scan cannot be edited now.';
  };
}

// The view toggle: the live-edited scan, the fitted body, or the fitted body in the scan's pose
// (GET avatar.glb?pose=scan, offered only where the server answers it).
async function setView(view) {
  state.view = view;
  document.querySelectorAll('#scan-view button').forEach((b) => b.setAttribute('aria-pressed', String(b.dataset.view === view)));
  if (scanMesh) scanMesh.visible = view === 'scan';
  if (current) current.visible = view !== 'scan';
  frame();
}

async function loadScanBody(view) {
  const q = view === 'scan-pose' ? '?pose=scan' : '';
  const r = await api(compressed(withHair(`/v1/customers/${state.customerId}/avatar.glb${q}`)), asCustomer());
  await showGlb(await r.arrayBuffer());
}

document.querySelectorAll('#scan-view button').forEach((btn) => btn.addEventListener('click', async () => {
  const view = btn.dataset.view;
  try {
    if (view !== 'scan') await loadScanBody(view);
    await setView(view);
  } catch (err) { showError(err); }
}));

// Does the server offer the body in the scan's pose? (404/422 or anything else: no button.)
async function offerScanPose() {
  const btn = $('#scan-view button[data-view="scan-pose"]');
  btn.hidden = true;
  try {
    const r = await fetch(`/v1/customers/${state.customerId}/avatar.glb?pose=scan`, asCustomer({ method: 'GET' }));
    if (r.ok) {
      // a server without the option ignores the parameter: only a different body counts
      const plain = await fetch(`/v1/customers/${state.customerId}/avatar.glb`, asCustomer());
      const [a, b] = [new Uint8Array(await r.arrayBuffer()), new Uint8Array(await plain.arrayBuffer())];
      btn.hidden = a.length === b.length && a.every((x, i) => x === b[i]);
    }
  } catch { /* keep it hidden */ }
  hook.scan.scanPoseOffered = !btn.hidden;
}

function leaveScan() {
  clearTimeout(scanPoll);
  if (ws) { const s = ws; ws = null; s.close(); }
  if (scanMesh) { scene.remove(scanMesh); scanMesh.geometry.dispose(); scanMesh.material.dispose(); scanMesh = null; }
  state.scan = null; state.view = 'scan'; scanPoseChosen = false;
  privacyText();
  document.body.classList.remove('scan-customer');
  $('#scan-section').hidden = true; $('#catalogue-section').hidden = false; $('#save').hidden = false;
  state.values = { ...DEFAULTS };
  buildForm();
}

let scanPoll = null;
async function startScan(rec) {
  state.scan = rec;
  privacyText();
  document.body.classList.add('scan-customer');
  $('#save').hidden = true; // saving measurements would replace the scan by a measured body
  $('#scan-section').hidden = false;
  $('#catalogue-section').hidden = true; // clothes are tried on the measured body, not on a clothed scan
  if (rec.status === 'fitting') {
    $('#scan-status').textContent = 'Your scan is being fitted; this takes about a minute…';
    clearTimeout(scanPoll);
    scanPoll = setTimeout(async () => {
      try { await startScan(await api(`/v1/customers/${state.customerId}`, asCustomer()).then((r) => r.json())); } catch (err) { showError(err); }
    }, 3000);
    return;
  }
  if (rec.status === 'failed') { $('#scan-status').textContent = `Your scan could not be fitted: ${rec.error || 'unknown error'}`; return; }
  state.values = { ...(rec.measurements || {}) };
  buildForm();
  $('#loading').hidden = false;
  try { await loadScanBody('body'); } catch (err) { showError(err); }
  $('#loading').hidden = true;
  state.view = 'scan';
  if (current) current.visible = false;
  openScanSocket();
  offerScanPose();
  hook.ready = true;
}

// ---- units --------------------------------------------------------------------------------
function factor(unit) {
  if (state.units === 'metric') return 1;
  return unit === 'cm' ? 1 / CM_PER_IN : unit === 'kg' ? 1 / KG_PER_LB : 1;
}
function displayUnit(unit) { return state.units === 'metric' ? unit : ({ cm: 'in', kg: 'lb' }[unit] || unit); }
const toDisplay = (v, unit) => Math.round(v * factor(unit) * 10) / 10;
const toApi = (v, unit) => v / factor(unit);

// ---- the form and sliders -----------------------------------------------------------------
function buildForm() {
  const fields = $('#fields'), more = $('#fields-more'), sliders = $('#sliders');
  fields.innerHTML = ''; more.innerHTML = ''; sliders.innerHTML = '';
  for (const a of state.attributes) {
    const div = document.createElement('div');
    div.className = 'field'; div.id = `field-${a.name}`;
    const label = document.createElement('label');
    label.htmlFor = `in-${a.name}`;
    let input;
    if (a.unit === null) {
      input = document.createElement('select');
      for (const [v, t] of [['', 'not given'], ['female', 'female'], ['male', 'male']]) input.add(new Option(t, v));
      label.textContent = a.name;
    } else {
      input = document.createElement('input');
      input.type = 'number'; input.step = '0.1'; input.inputMode = 'decimal';
      label.innerHTML = `${a.name.replace(/_(cm|kg)$/, '').replace(/_/g, ' ')} (<span class="u" data-unit="${a.unit}"></span>)`;
    }
    input.id = `in-${a.name}`; input.name = a.name;
    input.setAttribute('aria-describedby', `hint-${a.name} err-${a.name}`);
    const hint = document.createElement('span');
    hint.className = 'hint'; hint.id = `hint-${a.name}`;
    const err = document.createElement('p');
    err.className = 'error'; err.id = `err-${a.name}`; err.setAttribute('aria-live', 'polite');
    div.append(label, input, hint, err);
    (MAIN_FIELDS.includes(a.name) ? fields : more).append(div);
    input.addEventListener('input', () => {
      const raw = input.value.trim();
      if (raw === '') delete state.values[a.name];
      else state.values[a.name] = a.unit === null ? raw : toApi(Number(raw), a.unit);
      syncSliders();
      if (a.name === 'gender') filterCatalogue();
      changed();
    });
    if (a.unit !== null && a.min !== null && a.max !== null) {
      const row = document.createElement('div');
      row.className = 'slider';
      const sl = document.createElement('input');
      sl.type = 'range'; sl.id = `sl-${a.name}`; sl.dataset.name = a.name;
      const sLabel = document.createElement('label');
      sLabel.htmlFor = sl.id; sLabel.textContent = a.name.replace(/_(cm|kg)$/, '').replace(/_/g, ' ');
      const out = document.createElement('output'); out.htmlFor = sl.id; out.id = `out-${a.name}`;
      row.append(sLabel, sl, out);
      sliders.append(row);
      sl.addEventListener('input', () => {
        state.values[a.name] = toApi(Number(sl.value), a.unit);
        out.textContent = `${sl.value} ${displayUnit(a.unit)}`;  // the label follows the drag
        syncForm(); changed();
      });
    }
  }
  syncForm(); syncSliders();
}

function syncForm() {
  for (const a of state.attributes) {
    const input = document.getElementById(`in-${a.name}`);
    const v = state.values[a.name];
    if (a.unit === null) { input.value = v ?? ''; } else {
      input.value = v === undefined ? '' : toDisplay(v, a.unit);
      input.min = toDisplay(a.min, a.unit); input.max = toDisplay(a.max, a.unit);
    }
    // the hint: the accepted range; the description (how to measure) as the field's tooltip
    const hint = document.getElementById(`hint-${a.name}`);
    hint.textContent = a.unit === null ? 'optional' : `${toDisplay(a.min, a.unit)}-${toDisplay(a.max, a.unit)} ${displayUnit(a.unit)}`;
    hint.title = a.description; input.title = a.description;
    document.querySelector(`label[for="in-${a.name}"]`).title = a.description;
  }
  document.querySelectorAll('.u').forEach((s) => { s.textContent = displayUnit(s.dataset.unit); });
}

function syncSliders() {
  for (const a of state.attributes) {
    const sl = document.getElementById(`sl-${a.name}`);
    if (!sl) continue;
    sl.min = toDisplay(a.min, a.unit); sl.max = toDisplay(a.max, a.unit); sl.step = '0.1';
    const v = state.values[a.name];
    const shown = v === undefined ? (a.min + a.max) / 2 : Math.min(a.max, Math.max(a.min, v));
    sl.value = toDisplay(shown, a.unit);
    document.getElementById(`out-${a.name}`).textContent =
      v === undefined ? 'auto' : `${toDisplay(v, a.unit)} ${displayUnit(a.unit)}`;
  }
}

document.querySelectorAll('input[name=units]').forEach((r) => r.addEventListener('change', () => {
  state.units = r.value; syncForm(); syncSliders(); frame(); // the ruler's height label too
}));
$('#measurements').addEventListener('submit', (e) => { e.preventDefault(); if (state.scan) sendScanEdit(); else refresh(); });

// ---- API ----------------------------------------------------------------------------------
function measurements() {
  const m = {};
  for (const [k, v] of Object.entries(state.values)) m[k] = typeof v === 'number' ? Math.round(v * 100) / 100 : v;
  return m;
}

class ApiError extends Error { constructor(status, body) { super(`HTTP ${status}`); this.status = status; this.body = body; } }

// Every customer route needs the customer's token.
function asCustomer(opts = {}, token = state.customerToken) {
  return { ...opts, headers: { ...(opts.headers || {}), ...(token ? { Authorization: `Bearer ${token}` } : {}) } };
}

async function api(path, opts = {}) {
  const r = await fetch(path, opts);
  if (!r.ok) {
    let body = null;
    try { body = await r.json(); } catch { /* not JSON */ }
    throw new ApiError(r.status, body);
  }
  return r;
}

function clearErrors() {
  document.querySelectorAll('.error').forEach((e) => { e.textContent = ''; });
  document.querySelectorAll('.field.invalid').forEach((e) => e.classList.remove('invalid'));
}

function showError(err) {
  const messages = [];
  if (err instanceof ApiError && err.status === 422 && Array.isArray(err.body?.detail)) {
    for (const d of err.body.detail) {
      const field = d.loc?.[d.loc.length - 1];
      const el = document.getElementById(`err-${field}`);
      if (el) { el.textContent = d.msg; el.parentElement.classList.add('invalid'); } else { $('#general-error').textContent = d.msg; }
      messages.push(`${field}: ${d.msg}`);
    }
  } else {
    const msg = err instanceof ApiError ? (typeof err.body?.detail === 'string' ? err.body.detail : err.message) : String(err);
    $('#general-error').textContent = msg;
    messages.push(msg);
  }
  hook.lastError = messages.join('; ');
}

let timer = null;
function changed() {
  if (state.scan) { sendScanEdit(); return; } // a scan is reshaped live, never re-created
  if (state.customerId) state.customerStale = true;
  clearTimeout(timer);
  hook.busy = true; // a refresh is due: the avatar shown is not yet the one entered
  timer = setTimeout(refresh, DEBOUNCE_MS);
}

async function saveCustomer() {
  const r = await api('/v1/customers', { method: 'POST', headers: { 'Content-Type': 'application/json' },
    body: JSON.stringify({ measurements: measurements() }) });
  const c = await r.json();
  setCustomer(c.id, c.token);
  state.customerStale = false;
}

// Customers are immutable in the API: updating the measurements of a saved customer is done
// by deleting the old record and creating a new one (the id changes; localStorage follows).
async function updateCustomer() {
  const old = state.customerId, oldToken = state.customerToken;
  await saveCustomer();
  if (old) await fetch(`/v1/customers/${old}`, asCustomer({ method: 'DELETE' }, oldToken));
}

function setCustomer(id, token) {
  state.customerId = id;
  state.customerToken = id ? token : null;
  if (id) localStorage.setItem(CUSTOMER_KEY, id); else localStorage.removeItem(CUSTOMER_KEY);
  if (id && token) localStorage.setItem(TOKEN_KEY, token); else localStorage.removeItem(TOKEN_KEY);
  privacyText();
  $('#delete').disabled = !id;
  $('#save').textContent = id ? 'Update my saved data' : 'Save me';
}

// What the service keeps about the shopper, said as it is: nothing until they save or try a
// garment on; then their measurements and the body shape made from them (the shape weights),
// and the garments' drapes on that body (?drape=exact), under a random id, with a token that only this browser keeps (localStorage; the service keeps
// a hash of it), until they delete it (the service has no expiry for customers).
function privacyText() {
  const p = $('#customer-status');
  const what = state.scan
    ? `your scan${state.scan.editable ? ' (the uploaded mesh)' : ''}, the measurements and body shape (shape weights) fitted to it`
    : 'your measurements and the body shape made from them (shape weights)';
  const draped = state.scan ? '' : ', and the clothes as draped on that body';
  p.textContent = state.customerId
    ? `Stored on our server: ${what}${draped}, under the random id ${state.customerId}, until you delete it. `
      + 'The key to it (a token) is kept only in this browser (localStorage); anyone with it can see your body. '
      + '"Delete my data" removes both.'
    : 'Nothing is stored yet: your avatar is made and forgotten. When you try on clothes or press "Save me", '
      + 'we store your measurements and the body shape made from them (shape weights) under a random id, '
      + 'with the key to it (a token) kept in this browser (localStorage), until you delete it.';
  hook.privacy = p.textContent;
}

let generation = 0;
async function refresh() {
  clearTimeout(timer);
  timer = null;
  if (state.scan) { // hair on a scan customer: the fitted body views only
    if (state.view !== 'scan') { try { await loadScanBody(state.view); } catch (err) { showError(err); } }
    return;
  }
  const gen = ++generation;
  hook.busy = true;
  $('#loading').hidden = false;
  try {
    let r;
    if (state.worn.length) {
      if (!state.customerId) await saveCustomer();
      else if (state.customerStale) await updateCustomer();
      await loadFits();
      if (gen !== generation) return;
      const url = compressed(withHair(`/v1/customers/${state.customerId}/outfit.glb?garments=${state.worn.join(',')}${fitQuery()}&pose_correctives=1`));
      hook.lastGlb = url;
      r = await api(url, asCustomer());
    } else {
      if (state.customerId && state.customerStale) await updateCustomer();
      r = await api(compressed(withHair('/v1/avatars')), { method: 'POST', headers: { 'Content-Type': 'application/json', Accept: GLB },
        body: JSON.stringify({ measurements: measurements() }) });
    }
    const buf = await r.arrayBuffer();
    if (gen !== generation) return; // a newer request is on its way
    clearErrors();
    hook.lastError = null;
    await showGlb(buf);
    showFits();
    hook.ready = true;
    showDrape();
    if (state.worn.length && state.drape === 'exact') refineDrape(gen, hook.lastGlb);
  } catch (err) {
    if (gen !== generation) return;
    if (err instanceof ApiError && err.status === 404 && state.customerId) setCustomer(null); // forgotten server-side
    clearErrors();
    showError(err);
  } finally {
    if (gen === generation) { hook.busy = timer !== null; $('#loading').hidden = true; } // another refresh due?
  }
}

// ---- the exact drape ----------------------------------------------------------------------
// The instant try-on (the clothing basis, milliseconds) shows first; then the same outfit with
// each garment draped on this body by the cloth simulation at its own size (outfit.glb?drape=exact:
// 202 while the drapes are computed, a few seconds a garment, then the scene), swapped in unless
// the shopper has moved on. A drape that cannot be had leaves the instant try-on, and says so.
const DRAPE_POLL_MS = 700;
const DRAPE_WAIT_MS = 120000;
function showDrape(text = '') {
  $('#drape').hidden = !state.worn.length || Boolean(state.scan);
  document.querySelectorAll('#drape button').forEach((b) => b.setAttribute('aria-pressed', String(b.dataset.drape === state.drape)));
  $('#drape-status').textContent = text;
}
async function refineDrape(gen, url) {
  const exact = `${url}&drape=exact`;
  hook.draping = true;
  showDrape('Draping the cloth on your body…');
  const t0 = performance.now();
  try {
    for (;;) {
      if (gen !== generation || state.drape !== 'exact') return;
      const r = await fetch(exact, asCustomer());
      if (r.status === 202 || r.status === 429) { // being draped, or this browser's other drapes first
        if (performance.now() - t0 > DRAPE_WAIT_MS) { showDrape('The cloth is taking long: showing the instant try-on.'); return; }
        await new Promise((res) => { setTimeout(res, DRAPE_POLL_MS); });
        continue;
      }
      if (!r.ok) { showDrape('Showing the instant try-on.'); return; }
      const buf = await r.arrayBuffer();
      if (gen !== generation || state.drape !== 'exact') return;
      await showGlb(buf);
      hook.lastGlb = exact;
      hook.drapes += 1;
      showDrape('Draped on your body.');
      return;
    }
  } catch {
    if (gen === generation) showDrape('Showing the instant try-on.');
  } finally {
    if (gen === generation) hook.draping = false;
  }
}
hook.drapes = 0;
hook.setDrape = (mode) => { state.drape = mode; showDrape(); };
document.querySelectorAll('#drape button').forEach((b) => b.addEventListener('click', () => {
  state.drape = b.dataset.drape; showDrape(); refresh();
}));

// ---- catalogue ----------------------------------------------------------------------------
function cssColor(c) {
  if (Array.isArray(c)) return `rgb(${c.slice(0, 3).map((x) => Math.round(x * 255)).join(',')})`;
  return typeof c === 'string' ? c : '#888';
}

// The customer's gender (given in the form) first: their garments and the unisex ones, then,
// behind "Show all", the others. Without a gender every garment shows. A worn garment always shows.
function shopperGender() { const g = state.values.gender; return g === 'female' || g === 'male' ? g : null; }
function forShopper(g, gender) { return !gender || !g.gender || g.gender === gender || g.gender === 'unisex'; }
function filterCatalogue() {
  const gender = shopperGender();
  const all = state.catalogueAll || !gender;
  let hidden = 0;
  for (const li of document.querySelectorAll('#catalogue li')) {
    const g = state.garments.find((x) => x.id === li.dataset.garment);
    const mine = g && forShopper(g, gender);
    li.hidden = !(all || mine || state.worn.includes(li.dataset.garment));
    li.classList.toggle('other', Boolean(gender) && !mine);
    if (!mine) hidden += 1;
  }
  // the shopper's gender first, then unisex, then the others (each in the catalogue's order)
  const ul = $('#catalogue');
  const rank = (li) => { const g = garment(li.dataset.garment); return !g || !gender ? 0 : g.gender === gender ? 0 : forShopper(g, gender) ? 1 : 2; };
  const index = new Map(state.garments.map((g, i) => [g.id, i]));
  [...ul.children].sort((a, b) => rank(a) - rank(b) || index.get(a.dataset.garment) - index.get(b.dataset.garment))
    .forEach((li) => ul.append(li));
  const btn = $('#catalogue-all');
  btn.hidden = !gender || hidden === 0;
  btn.setAttribute('aria-pressed', String(state.catalogueAll));
  btn.textContent = state.catalogueAll ? `Only ${gender === 'female' ? "women's" : "men's"} and unisex`
    : `Show all (${state.garments.length})`;
  $('#catalogue-title').textContent = gender && !state.catalogueAll ? `Clothes for ${gender === 'female' ? 'women' : 'men'}` : 'Clothes';
}
$('#catalogue-all').addEventListener('click', () => { state.catalogueAll = !state.catalogueAll; filterCatalogue(); });

function buildCatalogue() {
  const ul = $('#catalogue');
  ul.innerHTML = '';
  for (const g of state.garments) {
    const li = document.createElement('li');
    li.dataset.garment = g.id;
    const btn = document.createElement('button');
    btn.type = 'button'; btn.dataset.garment = g.id; btn.setAttribute('aria-pressed', 'false');
    const img = document.createElement('img');
    img.className = 'thumb'; img.alt = ''; img.id = `thumb-${g.id}`;
    img.style.background = cssColor(g.color);
    img.src = 'data:image/gif;base64,R0lGODlhAQABAAAAACH5BAEKAAEALAAAAAABAAEAAAICTAEAOw==';
    const name = document.createElement('span');
    name.textContent = g.name;
    btn.append(img, name);
    if (Array.isArray(g.sizes) && g.sizes.length > 1) {
      const sz = document.createElement('span');
      sz.className = 'sizes';
      sz.dataset.range = sz.textContent = `${g.sizes[0].label}-${g.sizes[g.sizes.length - 1].label}`;
      btn.append(sz);
    }
    btn.addEventListener('click', () => {
      const on = !state.worn.includes(g.id);
      state.worn = on ? [...state.worn, g.id] : state.worn.filter((x) => x !== g.id);
      btn.setAttribute('aria-pressed', String(on));
      filterCatalogue();
      refresh();
    });
    li.append(btn); ul.append(li);
  }
  filterCatalogue();
}

// One small offscreen renderer draws each garment's mean shape once into an <img> (basis.glb
// without its morph targets: a fraction of the bytes).
async function thumbnails() {
  const size = 96;
  const r = new THREE.WebGLRenderer({ antialias: true, alpha: true, preserveDrawingBuffer: true });
  r.setSize(size, size, false);
  const cam = new THREE.PerspectiveCamera(30, 1, 0.01, 20);
  for (const g of state.garments) {
    try {
      const gltf = await loader.loadAsync(compressed(`/v1/garments/${g.id}/basis.glb?components=0`)); // the mean garment alone
      const s = new THREE.Scene();
      s.add(new THREE.HemisphereLight(0xffffff, 0x666666, 2), gltf.scene);
      const light = new THREE.DirectionalLight(0xffffff, 1.5); light.position.set(1, 2, 3); s.add(light);
      const box = new THREE.Box3().setFromObject(gltf.scene);
      const c = box.getCenter(new THREE.Vector3()), sz = box.getSize(new THREE.Vector3());
      const d = (Math.max(sz.x, sz.y) * 0.6) / Math.tan(THREE.MathUtils.degToRad(15));
      cam.position.set(c.x, c.y, c.z + d); cam.lookAt(c);
      r.render(s, cam);
      const img = document.getElementById(`thumb-${g.id}`);
      if (img) { img.src = r.domElement.toDataURL('image/png'); img.style.background = '#fff'; }
      disposeTree(gltf.scene);
    } catch { /* keep the colour swatch */ }
  }
  r.dispose();
}

// ---- sizes and fit ------------------------------------------------------------------------
// A garment in sizes lists them (`sizes: [{label, measurements}]`, `fabric`, `base_size`); the
// customer's fit of each (GET /v1/customers/{cid}/garments/{gid}/fit: recommended, and per size a
// verdict and the regions' ease and strain) drives a size picker with the recommended size
// marked, the fit in words, and the try-on of the chosen size (outfit.glb?sizes=, in the order of
// ?garments=). A one-size garment, or a server whose fit answers 404, shows no size UI.
const VERDICT_ORDER = ['too_tight', 'tight', 'loose', 'too_loose'];
const GIRTH_WORDS = { too_tight: 'too tight', tight: 'tight', loose: 'loose', too_loose: 'too loose' };
const LENGTH_WORDS = { too_tight: 'much too short', tight: 'short', loose: 'long', too_loose: 'much too long' };
const SIZE_WORDS = { too_tight: 'too small', tight: 'snug', fit: 'fits', loose: 'roomy', too_loose: 'too big' };
const REGION_NAMES = { chest: 'chest', bust: 'bust', waist: 'waist', hip: 'hips', hips: 'hips', thigh: 'thighs',
  upper_arm: 'upper arms', shoulder: 'shoulders', shoulders: 'shoulders', neck: 'neck', calf: 'calves', seat: 'seat' };
const LENGTH_NAMES = { sleeve: 'sleeves', inseam: 'legs', leg: 'legs', hem: 'hem', length: 'length', rise: 'rise', torso: 'body' };
const FITMAP_LEGEND = {
  strain: { css: 'linear-gradient(to right, #2f5bd3, #2ca02c, #d62b2b)', labels: ['at rest', 'stretched', "at the fabric's limit"] },
  ease: { css: 'linear-gradient(to right, #d62b2b, #2ca02c, #2f5bd3)', labels: ['presses the body', 'fits', 'hangs loose'] },
};

function sized(g) { return Array.isArray(g?.sizes) && g.sizes.length > 1; }
function garment(id) { return state.garments.find((g) => g.id === id); }
function fitOf(id) { return state.fits.get(`${state.customerId}|${id}`) ?? null; }
function sizeOf(id) { // the size tried on: picked, else recommended, else the only one
  const g = garment(id), fit = fitOf(id);
  const labels = (g?.sizes || []).map((x) => x.label);
  if (state.sizes[id] && labels.includes(state.sizes[id])) return state.sizes[id];
  if (fit?.recommended) return fit.recommended;
  return labels.length === 1 ? labels[0] : null;
}

async function loadFits() {
  const cid = state.customerId;
  await Promise.all(state.worn.filter((id) => sized(garment(id)) && !state.fits.has(`${cid}|${id}`)).map(async (id) => {
    try {
      const r = await fetch(`/v1/customers/${cid}/garments/${id}/fit`, asCustomer());
      if (r.ok) state.fits.set(`${cid}|${id}`, await r.json());
      else if (r.status === 404 || r.status === 422) state.fits.set(`${cid}|${id}`, null); // no sizes there
    } catch { /* not now: no size UI this time */ }
  }));
}

// ?sizes= (every worn garment's size, when at least one has a fit) and ?fitmap=
function fitQuery() {
  const fitted = state.worn.some((id) => fitOf(id));
  if (!fitted) return '';
  const labels = state.worn.map(sizeOf);
  let q = labels.every(Boolean) ? `&sizes=${labels.map(encodeURIComponent).join(',')}` : '';
  if (state.fitmap !== 'off') q += `&fitmap=${state.fitmap}`;
  return q;
}

function regionName(region) {
  const r = String(region).toLowerCase().replace(/_(cm|girth|length)$/, '');
  if (LENGTH_NAMES[r]) return { name: LENGTH_NAMES[r], length: true };
  return { name: REGION_NAMES[r] || r.replace(/_/g, ' '), length: false };
}
function joinWords(list) { return list.length < 2 ? list.join('') : `${list.slice(0, -1).join(', ')} and ${list[list.length - 1]}`; }
// "tight at the hips and waist, loose at the chest; the sleeves are long"
function fitInWords(size) {
  const girths = [], lengths = [];
  for (const v of VERDICT_ORDER) {
    const rs = (size.regions || []).filter((r) => r.verdict === v).map((r) => regionName(r.region));
    const g = [...new Set(rs.filter((r) => !r.length).map((r) => r.name))];
    const l = [...new Set(rs.filter((r) => r.length).map((r) => r.name))];
    if (g.length) girths.push(`${GIRTH_WORDS[v]} at the ${joinWords(g)}`);
    if (l.length) lengths.push(`the ${joinWords(l)} ${l.length > 1 || /s$/.test(l[0]) ? 'are' : 'is'} ${LENGTH_WORDS[v]}`);
  }
  const text = [girths.join(', '), lengths.join(', ')].filter(Boolean).join('; ');
  return text ? text[0].toUpperCase() + text.slice(1) + '.' : 'Fits well everywhere.';
}

function showFits() {
  const box = $('#fits');
  box.innerHTML = '';
  const shown = state.worn.filter((id) => sized(garment(id)) && fitOf(id));
  // a worn garment's card says the size tried on, the others their size range
  document.querySelectorAll('#catalogue .sizes').forEach((sp) => {
    const id = sp.closest('button').dataset.garment;
    sp.textContent = shown.includes(id) && sizeOf(id) ? `size ${sizeOf(id)}` : sp.dataset.range;
  });
  $('#fit-section').hidden = shown.length === 0 || Boolean(state.scan);
  for (const id of shown) {
    const g = garment(id), fit = fitOf(id), chosen = sizeOf(id);
    const div = document.createElement('div');
    div.className = 'garment-fit'; div.dataset.garment = id;
    const h = document.createElement('h3');
    h.textContent = g.name;
    if (g.fabric) { const f = document.createElement('span'); f.className = 'fabric'; f.textContent = g.fabric; h.append(' ', f); }
    const picker = document.createElement('div');
    picker.className = 'size-picker'; picker.setAttribute('role', 'group'); picker.setAttribute('aria-label', `Size of ${g.name}`);
    const bySize = new Map((fit.sizes || []).map((x) => [x.label, x]));
    for (const { label } of g.sizes) {
      const b = document.createElement('button');
      b.type = 'button'; b.dataset.size = label;
      b.setAttribute('aria-pressed', String(label === chosen));
      b.textContent = label;
      const verdict = bySize.get(label)?.verdict;
      b.title = verdict ? `${label}: ${SIZE_WORDS[verdict] || verdict}` : label;
      if (label === fit.recommended) {
        b.classList.add('recommended');
        const badge = document.createElement('span'); badge.className = 'badge'; badge.textContent = 'best fit';
        b.append(badge);
        b.setAttribute('aria-label', `${label}, recommended`);
      }
      b.addEventListener('click', () => { state.sizes[id] = label; showFits(); refresh(); });
      picker.append(b);
    }
    const words = document.createElement('p');
    words.className = 'fit-words';
    const size = bySize.get(chosen);
    words.textContent = size ? `Size ${chosen} ${SIZE_WORDS[size.verdict] ? `(${SIZE_WORDS[size.verdict]})` : ''}: ${fitInWords(size)}` : '';
    const rec = document.createElement('p');
    rec.className = 'recommend';
    // every size tight or short somewhere: the recommended one is the closest, and says so
    const recTight = ['too_tight', 'tight'].includes(bySize.get(fit.recommended)?.verdict);
    rec.textContent = !fit.recommended ? ''
      : recTight ? `No size fits you everywhere; ${fit.recommended} comes closest.` : `We recommend ${fit.recommended} for you.`;
    div.append(h, picker, words, rec);
    box.append(div);
  }
  document.querySelectorAll('#fitmap button').forEach((b) => b.setAttribute('aria-pressed', String(b.dataset.fitmap === state.fitmap)));
  const legend = FITMAP_LEGEND[state.fitmap];
  $('#fitmap-legend').hidden = !legend;
  if (legend) {
    $('#legend-bar').style.background = legend.css;
    $('#legend-labels').innerHTML = '';
    for (const t of legend.labels) { const sp = document.createElement('span'); sp.textContent = t; $('#legend-labels').append(sp); }
  }
}
document.querySelectorAll('#fitmap button').forEach((b) => b.addEventListener('click', () => {
  state.fitmap = b.dataset.fitmap; showFits(); refresh();
}));
hook.fitInWords = fitInWords;
hook.vertexColourMeshes = () => meshes().filter((m) => m.geometry.getAttribute('color')
  && [].concat(m.material).every((x) => x.vertexColors)).map((m) => m.name);

// ---- account ------------------------------------------------------------------------------
$('#save').addEventListener('click', async () => {
  try {
    if (state.customerId) await updateCustomer(); else await saveCustomer();
    clearErrors(); hook.lastError = null;
  } catch (err) { showError(err); }
});
$('#delete').addEventListener('click', async () => {
  const id = state.customerId;
  if (!id) return;
  try {
    await api(`/v1/customers/${id}`, asCustomer({ method: 'DELETE' }));
  } catch (err) { if (!(err instanceof ApiError && err.status === 404)) { showError(err); return; } }
  setCustomer(null);
  state.customerStale = false;
  if (state.scan) leaveScan();
  if (state.worn.length) { // nothing to dress without a customer
    state.worn = [];
    document.querySelectorAll('#catalogue button').forEach((b) => b.setAttribute('aria-pressed', 'false'));
    filterCatalogue();
  }
  showFits();
  refresh();
});

// A remembered customer (localStorage) brings back the measurements they entered (not the
// estimated ones); a customer deleted elsewhere is forgotten.
async function restoreCustomer() {
  if (!state.customerId) return null;
  try {
    const rec = await api(`/v1/customers/${state.customerId}`, asCustomer()).then((r) => r.json());
    if (rec.source === 'scan') return rec;
    const estimated = new Set(rec.estimated || []);
    const given = Object.fromEntries(Object.entries(rec.measurements || {}).filter(([k]) => !estimated.has(k)));
    if (Object.keys(given).length) state.values = given;
  } catch (err) {
    if (err instanceof ApiError && err.status === 404) setCustomer(null); else showError(err);
  }
  return null;
}

// A link from an upload (e.g. a retailer's app after a scan): /?customer=ID&token=TOKEN (query
// or hash). The page keeps them like a saved customer and drops them from the address bar.
function customerFromLink() {
  const params = new URLSearchParams(location.hash.slice(1) || location.search.slice(1));
  const id = params.get('customer'), token = params.get('token');
  if (!id || !token) return;
  setCustomer(id, token);
  history.replaceState(null, '', location.pathname);
}

// ---- start --------------------------------------------------------------------------------
async function start() {
  setCustomer(state.customerId, state.customerToken);
  customerFromLink();
  try {
    const [model, garments] = await Promise.all([api('/v1/body-model').then((r) => r.json()),
      api('/v1/garments').then((r) => r.json())]);
    state.attributes = model.attributes;
    state.garments = garments;
  } catch (err) { showError(err); return; }
  const scanRecord = await restoreCustomer();
  buildForm();
  buildCatalogue();
  buildHair();
  resize();
  if (scanRecord) await startScan(scanRecord); else await refresh();
  thumbnails();
}
start();
