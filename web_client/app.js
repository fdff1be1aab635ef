// The customer page: measurements -> live skinned avatar (three.js), shape sliders, pose
// presets, the garment catalogue and the customer's own data (save / delete).
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { MeshoptDecoder } from 'three/addons/libs/meshopt_decoder.module.js';

const GLB = 'model/gltf-binary';
const CM_PER_IN = 2.54;
const KG_PER_LB = 0.45359237;
const DEBOUNCE_MS = 400;
const CUSTOMER_KEY = 'tryon.customerId';
const DEFAULTS = { gender: 'female', height_cm: 168 };

const $ = (sel) => document.querySelector(sel);
const state = {
  attributes: [],          // from GET /v1/body-model
  values: { ...DEFAULTS }, // API units (cm, kg); a missing key = not given (estimated)
  units: 'metric',
  garments: [],            // the catalogue
  worn: [],                // chosen garment ids
  customerId: localStorage.getItem(CUSTOMER_KEY),
  customerStale: false,    // measurements changed since the customer was saved
  pose: 'a-pose',
};

// ---- test hook ----------------------------------------------------------------------------
const hook = {
  ready: false, busy: false, loads: 0, lastError: null, pose: 'a-pose',
  meshCount: () => meshes().length,
  skinnedMeshCount: () => meshes().filter((m) => m.isSkinnedMesh).length,
  boneNames: () => [...new Set(bones().map((b) => b.name))],
  garmentsWorn: () => [...state.worn],
  customerId: () => state.customerId,
  bboxHeight: () => (current ? new THREE.Box3().setFromObject(current).getSize(new THREE.Vector3()).y : 0),
  boneQuaternion: (name) => { const b = bones().find((x) => x.name === name); return b ? b.quaternion.toArray() : null; },
  values: () => ({ ...state.values }),
};
window.__tryon = hook;

// ---- three.js scene -----------------------------------------------------------------------
const canvas = $('#scene');
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
const scene = new THREE.Scene();
scene.background = new THREE.Color(0xdfe3ea);
const camera = new THREE.PerspectiveCamera(35, 1, 0.05, 50);
camera.position.set(0, 1.0, 4.2);
const controls = new OrbitControls(camera, canvas);
controls.target.set(0, 0.9, 0);
controls.enableDamping = false;
controls.listenToKeyEvents(canvas); // arrow keys when the canvas has focus
controls.addEventListener('change', render);
scene.add(new THREE.HemisphereLight(0xffffff, 0x8a8f99, 1.6));
const key = new THREE.DirectionalLight(0xffffff, 1.8);
key.position.set(1.5, 3, 2.5);
scene.add(key);
const rim = new THREE.DirectionalLight(0xffffff, 0.6);
rim.position.set(-2, 2, -2);
scene.add(rim);
const floor = new THREE.Mesh(new THREE.CircleGeometry(1.5, 48), new THREE.MeshStandardMaterial({ color: 0xb9bfcc }));
floor.rotation.x = -Math.PI / 2;
scene.add(floor);
const loader = new GLTFLoader();
loader.setMeshoptDecoder(MeshoptDecoder);
let current = null; // the loaded glTF scene (avatar, or avatar + garments)
let rest = new Map(); // bone -> rest quaternion

function meshes() { const out = []; current?.traverse((o) => { if (o.isMesh) out.push(o); }); return out; }
function bones() { const out = []; current?.traverse((o) => { if (o.isBone) out.push(o); }); return out; }

function resize() {
  const w = canvas.clientWidth || 1, h = canvas.clientHeight || 1;
  renderer.setSize(w, h, false);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
  render();
}
function render() { renderer.render(scene, camera); }
new ResizeObserver(resize).observe(canvas);

function frame(obj, first) {
  const box = new THREE.Box3().setFromObject(obj);
  const size = box.getSize(new THREE.Vector3()), centre = box.getCenter(new THREE.Vector3());
  if (!first) return;
  const dist = (size.y * 0.62) / Math.tan(THREE.MathUtils.degToRad(camera.fov / 2));
  controls.target.copy(centre);
  camera.position.set(centre.x, centre.y + size.y * 0.05, centre.z + dist);
  controls.update();
}

async function showGlb(buffer) {
  const gltf = await loader.parseAsync(buffer, '');
  const first = current === null;
  if (current) { scene.remove(current); disposeTree(current); }
  current = gltf.scene;
  current.traverse((o) => { if (o.isMesh) { o.frustumCulled = false; } });
  scene.add(current);
  rest = new Map(bones().map((b) => [b, b.quaternion.clone()]));
  applyPose(state.pose);
  frame(current, first);
  hook.loads += 1;
  render();
}

function disposeTree(obj) {
  obj.traverse((o) => {
    if (o.geometry) o.geometry.dispose();
    if (o.material) [].concat(o.material).forEach((m) => m.dispose());
  });
}

// ---- poses: rotate bones by name so that each segment points in a target direction --------
// World directions (Y up, the body faces +Z, the character's left = +X). Segment = bone -> child.
const CHILD = { upper_arm_l: 'forearm_l', forearm_l: 'hand_l', upper_arm_r: 'forearm_r', forearm_r: 'hand_r',
  thigh_l: 'shin_l', shin_l: 'foot_l', thigh_r: 'shin_r', shin_r: 'foot_r' };
const mirror = (d) => Object.fromEntries(Object.entries(d).map(([k, [x, y, z]]) => [k.replace(/_l$/, '_r'), [-x, y, z]]));
const ARMS_DOWN = { upper_arm_l: [0.17, -1, 0], forearm_l: [0.1, -1, 0.08] };
const HIPS = { upper_arm_l: [0.8, -1, -0.05], forearm_l: [-1, -0.5, 0.35] };
const POSES = {
  'a-pose': {},
  'arms-down': { ...ARMS_DOWN, ...mirror(ARMS_DOWN) },
  'walking': {
    upper_arm_l: [0.15, -1, -0.35], forearm_l: [0.1, -1, 0.05], upper_arm_r: [-0.15, -1, 0.35], forearm_r: [-0.1, -1, 0.5],
    thigh_l: [0.03, -1, 0.42], shin_l: [0.02, -1, 0.05], thigh_r: [-0.03, -1, -0.22], shin_r: [-0.02, -1, -0.55],
  },
  'hands-on-hips': { ...HIPS, ...mirror(HIPS) },
};
const ORDER = ['upper_arm_l', 'forearm_l', 'upper_arm_r', 'forearm_r', 'thigh_l', 'shin_l', 'thigh_r', 'shin_r'];

function applyPose(name) {
  state.pose = name; hook.pose = name;
  if (!current) return;
  // Every bone of that name (the outfit scene shares one skeleton; if a garment carried its
  // own copy of the joints it gets the same rotations).
  for (const [b, q] of rest) b.quaternion.copy(q);
  current.updateMatrixWorld(true);
  const byName = new Map();
  for (const b of bones()) { if (!byName.has(b.name)) byName.set(b.name, []); byName.get(b.name).push(b); }
  const targets = POSES[name] || {};
  const a = new THREE.Vector3(), c = new THREE.Vector3(), pq = new THREE.Quaternion(), wq = new THREE.Quaternion();
  for (const boneName of ORDER) {
    if (!targets[boneName] || !byName.has(boneName) || !byName.has(CHILD[boneName])) continue;
    const bone = byName.get(boneName)[0], child = byName.get(CHILD[boneName])[0];
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
  const fields = $('#fields'), sliders = $('#sliders');
  fields.innerHTML = ''; sliders.innerHTML = '';
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
    fields.append(div);
    input.addEventListener('input', () => {
      const raw = input.value.trim();
      if (raw === '') delete state.values[a.name];
      else state.values[a.name] = a.unit === null ? raw : toApi(Number(raw), a.unit);
      syncSliders();
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
    const range = a.unit === null ? '' : ` (${toDisplay(a.min, a.unit)}-${toDisplay(a.max, a.unit)} ${displayUnit(a.unit)})`;
    document.getElementById(`hint-${a.name}`).textContent = `${a.description}${range}; optional`;
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
  state.units = r.value; syncForm(); syncSliders();
}));
$('#measurements').addEventListener('submit', (e) => { e.preventDefault(); refresh(); });

// ---- API ----------------------------------------------------------------------------------
function measurements() {
  const m = {};
  for (const [k, v] of Object.entries(state.values)) m[k] = typeof v === 'number' ? Math.round(v * 100) / 100 : v;
  return m;
}

class ApiError extends Error { constructor(status, body) { super(`HTTP ${status}`); this.status = status; this.body = body; } }

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
  if (state.customerId) state.customerStale = true;
  clearTimeout(timer);
  timer = setTimeout(refresh, DEBOUNCE_MS);
}

async function saveCustomer() {
  const r = await api('/v1/customers', { method: 'POST', headers: { 'Content-Type': 'application/json' },
    body: JSON.stringify({ measurements: measurements() }) });
  const c = await r.json();
  setCustomer(c.id);
  state.customerStale = false;
}

// Customers are immutable in the API: updating the measurements of a saved customer is done
// by deleting the old record and creating a new one (the id changes; localStorage follows).
async function updateCustomer() {
  const old = state.customerId;
  await saveCustomer();
  if (old) await fetch(`/v1/customers/${old}`, { method: 'DELETE' });
}

function setCustomer(id) {
  state.customerId = id;
  if (id) localStorage.setItem(CUSTOMER_KEY, id); else localStorage.removeItem(CUSTOMER_KEY);
  $('#customer-status').textContent = id ? `Saved as customer ${id}.` : 'Not saved: nothing about you is stored.';
  $('#delete').disabled = !id;
  $('#save').textContent = id ? 'Update my saved data' : 'Save me';
}

let generation = 0;
async function refresh() {
  clearTimeout(timer);
  const gen = ++generation;
  hook.busy = true;
  $('#loading').hidden = false;
  try {
    let r;
    if (state.worn.length) {
      if (!state.customerId) await saveCustomer();
      else if (state.customerStale) await updateCustomer();
      r = await api(`/v1/customers/${state.customerId}/outfit.glb?garments=${state.worn.join(',')}`);
    } else {
      if (state.customerId && state.customerStale) await updateCustomer();
      r = await api('/v1/avatars', { method: 'POST', headers: { 'Content-Type': 'application/json', Accept: GLB },
        body: JSON.stringify({ measurements: measurements() }) });
    }
    const buf = await r.arrayBuffer();
    if (gen !== generation) return; // a newer request is on its way
    clearErrors();
    hook.lastError = null;
    await showGlb(buf);
    hook.ready = true;
  } catch (err) {
    if (gen !== generation) return;
    if (err instanceof ApiError && err.status === 404 && state.customerId) setCustomer(null); // forgotten server-side
    clearErrors();
    showError(err);
  } finally {
    if (gen === generation) { hook.busy = false; $('#loading').hidden = true; }
  }
}

// ---- catalogue ----------------------------------------------------------------------------
function cssColor(c) {
  if (Array.isArray(c)) return `rgb(${c.slice(0, 3).map((x) => Math.round(x * 255)).join(',')})`;
  return typeof c === 'string' ? c : '#888';
}

function buildCatalogue() {
  const ul = $('#catalogue');
  ul.innerHTML = '';
  for (const g of state.garments) {
    const li = document.createElement('li');
    const btn = document.createElement('button');
    btn.type = 'button'; btn.dataset.garment = g.id; btn.setAttribute('aria-pressed', 'false');
    const img = document.createElement('img');
    img.className = 'thumb'; img.alt = ''; img.id = `thumb-${g.id}`;
    img.style.background = cssColor(g.color);
    img.src = 'data:image/gif;base64,R0lGODlhAQABAAAAACH5BAEKAAEALAAAAAABAAEAAAICTAEAOw==';
    const name = document.createElement('span');
    name.textContent = g.name;
    btn.append(img, name);
    btn.addEventListener('click', () => {
      const on = !state.worn.includes(g.id);
      state.worn = on ? [...state.worn, g.id] : state.worn.filter((x) => x !== g.id);
      btn.setAttribute('aria-pressed', String(on));
      refresh();
    });
    li.append(btn); ul.append(li);
  }
}

// One small offscreen renderer draws each garment's clothing basis once into an <img>.
async function thumbnails() {
  const size = 96;
  const r = new THREE.WebGLRenderer({ antialias: true, alpha: true, preserveDrawingBuffer: true });
  r.setSize(size, size, false);
  const cam = new THREE.PerspectiveCamera(30, 1, 0.01, 20);
  for (const g of state.garments) {
    try {
      const gltf = await loader.loadAsync(`/v1/garments/${g.id}/basis.glb`);
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
    await api(`/v1/customers/${id}`, { method: 'DELETE' });
  } catch (err) { if (!(err instanceof ApiError && err.status === 404)) { showError(err); return; } }
  setCustomer(null);
  state.customerStale = false;
  if (state.worn.length) { // nothing to dress without a customer
    state.worn = [];
    document.querySelectorAll('#catalogue button').forEach((b) => b.setAttribute('aria-pressed', 'false'));
  }
  refresh();
});

// A remembered customer (localStorage) brings back the measurements they entered (not the
// estimated ones); a customer deleted elsewhere is forgotten.
async function restoreCustomer() {
  if (!state.customerId) return;
  try {
    const rec = await api(`/v1/customers/${state.customerId}`).then((r) => r.json());
    const estimated = new Set(rec.estimated || []);
    const given = Object.fromEntries(Object.entries(rec.measurements || {}).filter(([k]) => !estimated.has(k)));
    if (Object.keys(given).length) state.values = given;
  } catch (err) {
    if (err instanceof ApiError && err.status === 404) setCustomer(null); else showError(err);
  }
}

// ---- start --------------------------------------------------------------------------------
async function start() {
  setCustomer(state.customerId);
  try {
    const [model, garments] = await Promise.all([api('/v1/body-model').then((r) => r.json()),
      api('/v1/garments').then((r) => r.json())]);
    state.attributes = model.attributes;
    state.garments = garments;
  } catch (err) { showError(err); return; }
  await restoreCustomer();
  buildForm();
  buildCatalogue();
  resize();
  await refresh();
  thumbnails();
}
start();
