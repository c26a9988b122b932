// torchcage view: the page. Shows the mesh and its cage, lets the user select and move cage
// vertices (direct drag in the view plane, or a gizmo that moves, rotates and scales the selection
// about its centre), and sends each pose to the server, which answers the deformed mesh (one
// product with coordinates computed once). Scripts drive the same server through /api/*; the
// page follows their poses by polling /api/status. window.torchcage is a hook for tests.
import * as THREE from 'three';

const { OrbitControls, TransformControls } = THREE; // the vendored bundle exports both add-ons

const $ = (id) => document.getElementById(id);
const CAGE_COLOR = 0xe0731f;
const MESH_COLOR = 0x8fb3d9;
const VERTEX_COLOR = new THREE.Color(0xb4530c);
const SELECTED_COLOR = new THREE.Color(0x1a56db);
const PICK_RADIUS = 12; // pixels

const state = {
  ready: false,
  V: 0,
  rest: null, // Float64Array (3V)
  pose: null, // Float64Array (3V), what the page shows
  selection: new Set(),
  version: 0, // the server's pose counter as this page last knew it
  coordinates: -1, // the server's count of finished computations
  history: [],
  hindex: -1,
  inflight: false,
  pending: false,
  roundTrip: null,
  meshUpdate: null,
  idleWaiters: [],
};

// ------------------------------------------------------------------ server
// The server serves this page with a per-session secret; every POST carries it (and a JSON body),
// which another web page open in the same browser cannot read or forge.
const TOKEN = document.querySelector('meta[name="torchcage-token"]').content;

async function request(url, options = {}) {
  const headers = { 'X-Torchcage-Token': TOKEN, ...(options.headers || {}) };
  if (options.body !== undefined) headers['Content-Type'] = 'application/json';
  const r = await fetch(url, { ...options, headers });
  if (!r.ok) {
    let message = `${r.status} ${r.statusText}`;
    try { message = (await r.json()).error || message; } catch (e) { /* not JSON */ }
    throw new Error(message);
  }
  return r;
}
const getJSON = async (url) => (await request(url)).json();
const postJSON = async (url, body) => (await request(url, { method: 'POST', body: JSON.stringify(body) })).json();

function note(text, isError = false) {
  $('message').textContent = text;
  $('message').className = isError ? 'error' : '';
}

// ------------------------------------------------------------------ scene
const viewport = $('viewport');
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
renderer.setSize(window.innerWidth, window.innerHeight);
viewport.appendChild(renderer.domElement);
const canvas = renderer.domElement;
const scene = new THREE.Scene();
scene.background = new THREE.Color(0xf4f5f7);
const camera = new THREE.PerspectiveCamera(40, window.innerWidth / window.innerHeight, 0.01, 1000);
scene.add(camera);
scene.add(new THREE.HemisphereLight(0xffffff, 0x667788, 1.6));
const headlight = new THREE.DirectionalLight(0xffffff, 1.8);
headlight.position.set(0.3, 0.6, 1);
camera.add(headlight);

let mesh = null; // THREE.Mesh or THREE.Points
let cageLines = null;
let cagePoints = null;
let cageFaces = null;
let edges = null; // Uint32Array (2E)

let needsRender = true;
const render = () => { needsRender = true; };
renderer.setAnimationLoop(() => {
  if (!needsRender) return;
  needsRender = false;
  renderer.render(scene, camera);
});
window.addEventListener('resize', () => {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight);
  render();
});

// Our pointer handlers go first: a press on a cage vertex stops the orbit and gizmo handlers.
canvas.addEventListener('pointerdown', onPointerDown);
canvas.addEventListener('pointermove', onPointerMove);
canvas.addEventListener('pointerup', onPointerUp);
const orbit = new OrbitControls(camera, canvas);
orbit.addEventListener('change', render);
const pivot = new THREE.Object3D();
scene.add(pivot);
const gizmo = new TransformControls(camera, canvas);
gizmo.setSize(0.8);
scene.add(gizmo.getHelper());
gizmo.addEventListener('change', render);
gizmo.addEventListener('dragging-changed', (e) => { orbit.enabled = !e.value; });

function vertex(array, i) {
  return new THREE.Vector3(array[3 * i], array[3 * i + 1], array[3 * i + 2]);
}

function buildScene(data) {
  const up = { x: [1, 0, 0], y: [0, 1, 0], z: [0, 0, 1] }[data.up] || [0, 0, 1];
  camera.up.set(...up);
  state.V = data.cage.vertices.length;
  state.rest = Float64Array.from(data.cage.rest.flat());
  state.pose = Float64Array.from(data.cage.vertices.flat());
  edges = Uint32Array.from(data.cage.edges.flat());

  const positions = Float32Array.from(data.mesh.vertices.flat());
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(positions, 3));
  if (data.mesh.faces.length) {
    geometry.setIndex(new THREE.BufferAttribute(Uint32Array.from(data.mesh.faces.flat()), 1));
    geometry.computeVertexNormals();
    mesh = new THREE.Mesh(geometry, new THREE.MeshStandardMaterial({
      color: MESH_COLOR, roughness: 0.65, metalness: 0.0, side: THREE.DoubleSide,
      polygonOffset: true, polygonOffsetFactor: 1, polygonOffsetUnits: 1,
    }));
  } else {
    mesh = new THREE.Points(geometry, new THREE.PointsMaterial({ color: 0x3c6fb0, size: 2, sizeAttenuation: false }));
  }
  scene.add(mesh);

  const lineGeometry = new THREE.BufferGeometry();
  lineGeometry.setAttribute('position', new THREE.BufferAttribute(new Float32Array(edges.length * 3), 3));
  cageLines = new THREE.LineSegments(lineGeometry, new THREE.LineBasicMaterial({ color: CAGE_COLOR }));
  scene.add(cageLines);

  const tris = [];
  for (const f of data.cage.faces) for (let k = 1; k + 1 < f.length; k++) tris.push(f[0], f[k], f[k + 1]);
  const faceGeometry = new THREE.BufferGeometry();
  faceGeometry.setAttribute('position', new THREE.BufferAttribute(new Float32Array(state.V * 3), 3));
  faceGeometry.setIndex(tris);
  cageFaces = new THREE.Mesh(faceGeometry, new THREE.MeshBasicMaterial({
    color: CAGE_COLOR, transparent: true, opacity: 0.05, depthWrite: false, side: THREE.DoubleSide,
  }));
  scene.add(cageFaces);

  const pointGeometry = new THREE.BufferGeometry();
  pointGeometry.setAttribute('position', new THREE.BufferAttribute(new Float32Array(state.V * 3), 3));
  pointGeometry.setAttribute('color', new THREE.BufferAttribute(new Float32Array(state.V * 3), 3));
  cagePoints = new THREE.Points(pointGeometry, new THREE.PointsMaterial({
    size: 9, sizeAttenuation: false, vertexColors: true, depthTest: false,
  }));
  cagePoints.renderOrder = 10;
  scene.add(cagePoints);

  updateCage();
  frame();
  for (const [key, name] of Object.entries(data.methods)) {
    const option = document.createElement('option');
    option.value = key;
    option.textContent = name;
    $('method').appendChild(option);
  }
  $('method').value = data.method;
  state.version = data.version;
  pushHistory();
}

function frame() {
  const box = new THREE.Box3().setFromBufferAttribute(cagePoints.geometry.attributes.position);
  box.union(new THREE.Box3().setFromBufferAttribute(mesh.geometry.attributes.position));
  const sphere = box.getBoundingSphere(new THREE.Sphere());
  const r = Math.max(sphere.radius, 1e-9);
  const distance = 1.15 * r / Math.sin(THREE.MathUtils.degToRad(camera.fov / 2));
  const up = camera.up.clone();
  const side = Math.abs(up.z) > 0.5 ? new THREE.Vector3(1, -1.4, 0) : new THREE.Vector3(1.4, 0, 1);
  side.addScaledVector(up, -side.dot(up)).normalize();
  const direction = side.addScaledVector(up, 0.45).normalize();
  camera.position.copy(sphere.center).addScaledVector(direction, distance);
  camera.near = distance / 100;
  camera.far = distance * 100;
  camera.updateProjectionMatrix();
  orbit.target.copy(sphere.center);
  orbit.update();
  render();
}

function updateCage() {
  const p = state.pose;
  const line = cageLines.geometry.attributes.position;
  for (let e = 0; e < edges.length; e++) {
    const i = edges[e];
    line.array[3 * e] = p[3 * i]; line.array[3 * e + 1] = p[3 * i + 1]; line.array[3 * e + 2] = p[3 * i + 2];
  }
  line.needsUpdate = true;
  cageLines.geometry.computeBoundingSphere();
  for (const g of [cagePoints.geometry, cageFaces.geometry]) {
    g.attributes.position.array.set(p);
    g.attributes.position.needsUpdate = true;
    g.computeBoundingSphere();
  }
  const colors = cagePoints.geometry.attributes.color;
  for (let i = 0; i < state.V; i++) {
    (state.selection.has(i) ? SELECTED_COLOR : VERTEX_COLOR).toArray(colors.array, 3 * i);
  }
  colors.needsUpdate = true;
  showInfo();
  render();
}

function setMesh(positions) {
  const t0 = performance.now();
  const attribute = mesh.geometry.attributes.position;
  if (positions.length !== attribute.array.length) return note('the server sent a mesh of another size', true);
  attribute.array.set(positions);
  attribute.needsUpdate = true;
  if (mesh.isMesh) mesh.geometry.computeVertexNormals();
  mesh.geometry.computeBoundingSphere();
  state.meshUpdate = performance.now() - t0;
  render();
}

function showInfo() {
  const rt = state.roundTrip === null ? '' : ` · pose round trip ${state.roundTrip.toFixed(0)} ms`;
  const n = mesh.geometry.attributes.position.count;
  $('info').textContent = `${state.V} cage vertices, ${n.toLocaleString()} ${mesh.isMesh ? 'mesh vertices' : 'points'} · `
    + `${state.selection.size} selected${rt}`;
  $('undo').disabled = state.hindex <= 0;
  $('redo').disabled = state.hindex >= state.history.length - 1;
}

// ------------------------------------------------------------------ selection and dragging
function screenOf(i) {
  const rect = canvas.getBoundingClientRect();
  const v = vertex(state.pose, i).project(camera);
  return { x: rect.left + (v.x + 1) / 2 * rect.width, y: rect.top + (1 - v.y) / 2 * rect.height, depth: v.z };
}

function pick(clientX, clientY) {
  let best = -1;
  let bestScore = Infinity;
  for (let i = 0; i < state.V; i++) {
    const s = screenOf(i);
    if (s.depth < -1 || s.depth > 1) continue;
    const d = Math.hypot(s.x - clientX, s.y - clientY);
    const score = d + s.depth; // nearer vertices win ties
    if (d <= PICK_RADIUS && score < bestScore) { best = i; bestScore = score; }
  }
  return best;
}

function selectionCentre() {
  const c = new THREE.Vector3();
  for (const i of state.selection) c.add(vertex(state.pose, i));
  return c.divideScalar(Math.max(1, state.selection.size));
}

function setSelection(indices) {
  state.selection = new Set([...indices].filter((i) => Number.isInteger(i) && i >= 0 && i < state.V));
  placeGizmo();
  updateCage();
}

function placeGizmo() {
  if (!state.selection.size) { gizmo.detach(); render(); return; }
  pivot.position.copy(selectionCentre());
  pivot.quaternion.identity();
  pivot.scale.set(1, 1, 1);
  pivot.updateMatrixWorld(true);
  gizmo.attach(pivot);
  render();
}

let drag = null;
let press = null;

function planePoint(plane, clientX, clientY) {
  const rect = canvas.getBoundingClientRect();
  const ndc = new THREE.Vector2((clientX - rect.left) / rect.width * 2 - 1, -(clientY - rect.top) / rect.height * 2 + 1);
  const ray = new THREE.Raycaster();
  ray.setFromCamera(ndc, camera);
  return ray.ray.intersectPlane(plane, new THREE.Vector3());
}

function onPointerDown(event) {
  if (!state.ready || event.button !== 0) return;
  if (gizmo.object && gizmo.axis !== null) return; // the gizmo's handle is under the pointer
  const i = pick(event.clientX, event.clientY);
  if (i < 0) { press = { x: event.clientX, y: event.clientY, shift: event.shiftKey }; return; }
  event.stopImmediatePropagation(); // no orbit, no gizmo: this press is ours
  event.preventDefault();
  if (event.shiftKey) {
    const next = new Set(state.selection);
    if (next.has(i)) next.delete(i); else next.add(i);
    setSelection(next);
    if (!next.has(i)) return;
  } else if (!state.selection.has(i)) {
    setSelection([i]);
  }
  const normal = camera.getWorldDirection(new THREE.Vector3());
  const plane = new THREE.Plane().setFromNormalAndCoplanarPoint(normal, vertex(state.pose, i));
  const origin = planePoint(plane, event.clientX, event.clientY);
  if (!origin) return;
  drag = { plane, origin, start: state.pose.slice(), moved: false };
  try { canvas.setPointerCapture(event.pointerId); } catch (e) { /* a synthetic pointer */ }
}

function onPointerMove(event) {
  if (!drag) return;
  event.stopImmediatePropagation();
  const p = planePoint(drag.plane, event.clientX, event.clientY);
  if (!p) return;
  const delta = p.sub(drag.origin);
  for (const i of state.selection) {
    for (let k = 0; k < 3; k++) state.pose[3 * i + k] = drag.start[3 * i + k] + delta.getComponent(k);
  }
  drag.moved = true;
  placeGizmo();
  updateCage();
  sendPose();
}

function onPointerUp(event) {
  if (drag) {
    event.stopImmediatePropagation();
    try { canvas.releasePointerCapture(event.pointerId); } catch (e) { /* a synthetic pointer */ }
    if (drag.moved) pushHistory();
    drag = null;
    return;
  }
  if (press && Math.hypot(event.clientX - press.x, event.clientY - press.y) < 4 && !press.shift) setSelection([]);
  press = null;
}

// The gizmo moves the pivot; the selection follows by the pivot's motion since the press.
let gizmoStart = null;
gizmo.addEventListener('mouseDown', () => {
  pivot.updateMatrixWorld(true);
  gizmoStart = { pose: state.pose.slice(), inverse: pivot.matrixWorld.clone().invert() };
});
gizmo.addEventListener('objectChange', () => {
  if (!gizmoStart) return;
  pivot.updateMatrixWorld(true);
  applyMatrix(pivot.matrixWorld.clone().multiply(gizmoStart.inverse), gizmoStart.pose);
});
gizmo.addEventListener('mouseUp', () => {
  if (!gizmoStart) return;
  gizmoStart = null;
  pushHistory();
  placeGizmo();
});

function applyMatrix(matrix, start) {
  for (const i of state.selection) {
    const v = vertex(start, i).applyMatrix4(matrix);
    state.pose[3 * i] = v.x; state.pose[3 * i + 1] = v.y; state.pose[3 * i + 2] = v.z;
  }
  updateCage();
  sendPose();
}

function setMode(mode) {
  gizmo.setMode(mode);
  for (const m of ['translate', 'rotate', 'scale']) $(`mode-${m}`).classList.toggle('active', m === mode);
  render();
}

// ------------------------------------------------------------------ poses
function poseRows() {
  const rows = [];
  for (let i = 0; i < state.V; i++) rows.push([state.pose[3 * i], state.pose[3 * i + 1], state.pose[3 * i + 2]]);
  return rows;
}

// One request in flight; the newest pose goes next (drags send faster than a server answers).
async function sendPose() {
  if (state.inflight) { state.pending = true; return; }
  state.inflight = true;
  state.pending = false;
  const t0 = performance.now();
  try {
    const r = await request('/api/pose?format=f32&wait=0', {
      method: 'POST', body: JSON.stringify({ vertices: poseRows() }),
    });
    if (r.status === 200) {
      state.version = Number(r.headers.get('X-Pose-Version'));
      setMesh(new Float32Array(await r.arrayBuffer()));
      state.roundTrip = performance.now() - t0;
      showInfo();
    } else {
      state.version = (await r.json()).version; // the coordinates are computing: the mesh follows
    }
  } catch (err) {
    note(`pose refused: ${err.message}`, true);
  }
  state.inflight = false;
  if (state.pending) sendPose(); else settle();
}

function settle() {
  if (state.inflight || state.pending) return;
  const waiters = state.idleWaiters;
  state.idleWaiters = [];
  for (const resolve of waiters) resolve();
}

const idle = () => new Promise((resolve) => { state.idleWaiters.push(resolve); settle(); });

function setPose(values) {
  state.pose = Float64Array.from(values);
  placeGizmo();
  updateCage();
}

function pushHistory() {
  state.history = state.history.slice(0, state.hindex + 1);
  state.history.push(state.pose.slice());
  state.hindex = state.history.length - 1;
  showInfo();
}

function step(offset) {
  const k = state.hindex + offset;
  if (k < 0 || k >= state.history.length) return;
  state.hindex = k;
  setPose(state.history[k]);
  sendPose();
}

function reset() {
  setPose(state.rest);
  pushHistory();
  sendPose();
}

async function refreshMesh() {
  const r = await request('/api/deformed?format=f32&wait=0');
  if (r.status === 200) setMesh(new Float32Array(await r.arrayBuffer()));
}

// ------------------------------------------------------------------ status and scripts' poses
function showStatus(s) {
  const bar = $('bar');
  $('progress').classList.toggle('busy', s.state === 'computing' && !s.total);
  bar.style.width = s.state === 'computing' ? (s.total ? `${(100 * s.done) / s.total}%` : '') : '100%';
  const time = s.state === 'computing' ? ` (${s.seconds.toFixed(0)} s)` : '';
  const text = s.state === 'computing' ? `computing ${s.method_name}: ${s.message}${time}` : s.message;
  $('status').textContent = text + (s.warnings.length ? ` · warning: ${s.warnings.join(' ')}` : '');
  $('status').className = s.state === 'failed' ? 'failed' : '';
  if ($('method').value !== s.method) $('method').value = s.method;
}

async function poll() {
  try {
    const s = await getJSON('/api/status');
    showStatus(s);
    if (s.state === 'ready' && s.coordinates !== state.coordinates) {
      state.coordinates = s.coordinates;
      await refreshMesh();
    }
    if (s.version !== state.version && !state.inflight && !state.pending && !drag && !gizmoStart) {
      const p = await getJSON('/api/pose'); // a script set this pose
      if (!state.inflight && !state.pending && !drag && !gizmoStart) {
        state.version = p.version;
        setPose(p.vertices.flat());
        pushHistory();
        await refreshMesh();
      }
    }
  } catch (err) {
    $('status').textContent = `the server does not answer (${err.message})`;
    $('status').className = 'failed';
  }
  setTimeout(poll, 400);
}

// ------------------------------------------------------------------ buttons and keys
for (const m of ['translate', 'rotate', 'scale']) $(`mode-${m}`).addEventListener('click', () => setMode(m));
$('undo').addEventListener('click', () => step(-1));
$('redo').addEventListener('click', () => step(1));
$('reset').addEventListener('click', reset);
$('select-all').addEventListener('click', () => setSelection([...Array(state.V).keys()]));
$('select-none').addEventListener('click', () => setSelection([]));
$('method').addEventListener('change', async () => {
  try {
    showStatus(await postJSON('/api/method', { method: $('method').value }));
  } catch (err) {
    note(`cannot switch: ${err.message}`, true);
  }
});
$('save').addEventListener('click', async () => {
  await idle();
  try {
    const paths = await postJSON('/api/save', {});
    note(`saved ${paths.cage} and ${paths.mesh}`);
  } catch (err) {
    note(`not saved: ${err.message}`, true);
  }
});
$('load').addEventListener('change', async (event) => {
  const file = event.target.files[0];
  event.target.value = '';
  if (!file) return;
  await idle();
  try {
    const r = await postJSON('/api/load?wait=0', { obj: await file.text() });
    state.version = r.version;
    setPose(r.cage.flat());
    pushHistory();
    if (r.vertices) setMesh(Float32Array.from(r.vertices.flat()));
    note(`loaded ${file.name}`);
  } catch (err) {
    note(`not loaded: ${err.message}`, true);
  }
});
window.addEventListener('keydown', (event) => {
  if (event.target.tagName === 'SELECT' || event.target.tagName === 'INPUT') return;
  const key = event.key.toLowerCase();
  if ((event.ctrlKey || event.metaKey) && key === 'z') { step(event.shiftKey ? 1 : -1); event.preventDefault(); return; }
  if ((event.ctrlKey || event.metaKey) && key === 'y') { step(1); event.preventDefault(); return; }
  if (event.ctrlKey || event.metaKey || event.altKey) return;
  if (key === 'g' || key === 't') setMode('translate');
  else if (key === 'r') setMode('rotate');
  else if (key === 's') setMode('scale');
  else if (key === 'a') setSelection([...Array(state.V).keys()]);
  else if (key === 'escape') setSelection([]);
});

// ------------------------------------------------------------------ the test hook
// Drives the page through its own code: dragVertex dispatches pointer events on the canvas, so the
// picking, the drag and the pose requests run as for a person's mouse.
function dispatch(type, x, y) {
  canvas.dispatchEvent(new PointerEvent(type, {
    clientX: x, clientY: y, button: 0, buttons: type === 'pointerup' ? 0 : 1, pointerId: 1,
    pointerType: 'mouse', isPrimary: true, bubbles: true, cancelable: true,
  }));
}

window.torchcage = {
  get ready() { return state.ready; },
  get version() { return state.version; },
  get roundTrip() { return state.roundTrip; },
  get meshUpdate() { return state.meshUpdate; }, // ms to take a new mesh (copy, normals)
  pose: () => Array.from(state.pose),
  selection: () => [...state.selection].sort((a, b) => a - b),
  meshPositions: () => Array.from(mesh.geometry.attributes.position.array),
  screenOf,
  select: (indices) => setSelection(indices),
  async dragVertex(i, dx, dy, steps = 5) {
    const s = screenOf(i);
    dispatch('pointerdown', s.x, s.y);
    for (let k = 1; k <= steps; k++) dispatch('pointermove', s.x + (dx * k) / steps, s.y + (dy * k) / steps);
    dispatch('pointerup', s.x + dx, s.y + dy);
    await idle();
    return Array.from(state.pose);
  },
  async transformSelection(elements) {
    applyMatrix(new THREE.Matrix4().fromArray(elements), state.pose.slice());
    pushHistory();
    placeGizmo();
    await idle();
    return Array.from(state.pose);
  },
  async undo() { step(-1); await idle(); },
  async redo() { step(1); await idle(); },
  async reset() { reset(); await idle(); },
  idle,
};

// ------------------------------------------------------------------ start
(async () => {
  try {
    buildScene(await getJSON('/api/scene'));
    state.ready = true;
    document.body.dataset.ready = 'true';
    poll();
  } catch (err) {
    $('status').textContent = `cannot load the scene: ${err.message}`;
    $('status').className = 'failed';
  }
})();
