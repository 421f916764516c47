// sfmloc view: the map's point cloud and cameras, and every live client (pose, trajectory,
// status, latency) from the viewer's server-sent events. Drawing is three.js (vendor/).
// Poses are world_from_cam; the camera frame is x right, y down, z forward (COLMAP).
import * as THREE from './vendor/three.min.js';

const STATUS = {
  TRACKING: '#2ecc71', RELOCALIZED: '#3498db', UNVERIFIED: '#f39c12', LOST: '#e74c3c',
};
const PALETTE = ['#ff6f91', '#ffd166', '#06d6a0', '#4cc9f0', '#c77dff', '#f4a261', '#90be6d',
  '#f15bb5'];
const TRAIL = 2000;  // positions drawn per client
const STALE_S = 3;   // a client without a pose for this long is drawn faded

// State the page shows, also read by tests through the DevTools protocol.
const view = window.sfmlocView = {
  ready: false, error: null, map: null, points: 0, cameras: 0, events: 0, frames: 0,
  connected: false, clients: {},
  screen: (id) => screenOf(id),
};

THREE.ColorManagement.enabled = false;  // point colours are drawn as stored (sRGB bytes)
const container = document.getElementById('scene');
let renderer;
try {
  renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
} catch (e) {
  fail(`WebGL is not available in this browser: ${e.message}`);
  throw e;
}
renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
renderer.setPixelRatio(window.devicePixelRatio || 1);
renderer.setSize(window.innerWidth, window.innerHeight);
renderer.setClearColor('#15171c');
container.appendChild(renderer.domElement);

const scene = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(50, window.innerWidth / window.innerHeight, 0.01, 1e4);
const controls = new THREE.OrbitControls(camera, renderer.domElement);
controls.enableDamping = true;
let mapGroup = new THREE.Group();
scene.add(mapGroup);
let sceneScale = 1;
// Everything is drawn relative to the map's origin (its points' median): float32 on the GPU
// keeps millimetres near it however far the map's frame puts it (coordinates in metres of UTM).
let origin = [0, 0, 0];
const local = (p) => [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]];
const clients = new Map();  // "map/client" -> drawn client

window.addEventListener('resize', () => {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight);
});

function fail(msg) {
  view.error = msg;
  document.getElementById('error').textContent = msg;
}

async function fetchOk(url) {
  const r = await fetch(url);
  if (!r.ok) {
    let msg = `${url}: HTTP ${r.status}`;
    try { msg += `: ${(await r.json()).error}`; } catch (e) { /* not JSON */ }
    throw new Error(msg);
  }
  return r;
}

// Frustum lines (apex, 4 corners, the rectangle) of a camera at the origin looking down +z.
function frustumVertices(tanHalf, depth, out, at = 0) {
  const [tx, ty] = tanHalf;
  const c = [[-tx, -ty], [tx, -ty], [tx, ty], [-tx, ty]].map(([x, y]) => [x * depth, y * depth, depth]);
  const seg = [];
  for (let i = 0; i < 4; i++) seg.push([0, 0, 0], c[i], c[i], c[(i + 1) % 4]);
  // a tick on the top edge (image up, -y) tells the camera's roll
  seg.push([-0.3 * tx * depth, -ty * depth, depth], [0, -1.4 * ty * depth, depth]);
  seg.push([0, -1.4 * ty * depth, depth], [0.3 * tx * depth, -ty * depth, depth]);
  for (const v of seg) { out[at++] = v[0]; out[at++] = v[1]; out[at++] = v[2]; }
  return at;
}
const FRUSTUM_VERTS = 20;

async function loadMap(name) {
  const meta = await (await fetchOk(`/api/maps/${encodeURIComponent(name)}`)).json();
  const buf = await (await fetchOk(`/api/maps/${encodeURIComponent(name)}/points`)).arrayBuffer();
  const n = meta.points_shown;
  if (buf.byteLength !== n * 15) throw new Error(`points of ${name}: ${buf.byteLength} B for ${n} points`);
  scene.remove(mapGroup);
  mapGroup = new THREE.Group();
  const geo = new THREE.BufferGeometry();
  geo.setAttribute('position', new THREE.BufferAttribute(new Float32Array(buf, 0, 3 * n), 3));
  geo.setAttribute('color', new THREE.BufferAttribute(new Uint8Array(buf, 12 * n, 3 * n), 3, true));
  mapGroup.add(new THREE.Points(geo, new THREE.PointsMaterial({
    size: 2.5, sizeAttenuation: false, vertexColors: true,
  })));
  sceneScale = meta.scene_scale;
  origin = meta.origin;
  // The mapping cameras, as small grey frusta.
  const cams = meta.cameras;
  const verts = new Float32Array(cams.length * FRUSTUM_VERTS * 3);
  const fr = new Float32Array(FRUSTUM_VERTS * 3);
  let at = 0;
  for (const c of cams) {
    frustumVertices(c.tan_half, 0.12 * sceneScale, fr);
    const [x, y, z] = c.axes;  // camera axes in the world
    const o = local(c.centre);
    for (let i = 0; i < FRUSTUM_VERTS; i++) {
      const a = fr[3 * i], b = fr[3 * i + 1], d = fr[3 * i + 2];
      for (let k = 0; k < 3; k++) verts[at++] = o[k] + a * x[k] + b * y[k] + d * z[k];
    }
  }
  const cgeo = new THREE.BufferGeometry();
  cgeo.setAttribute('position', new THREE.BufferAttribute(verts, 3));
  mapGroup.add(new THREE.LineSegments(cgeo, new THREE.LineBasicMaterial({ color: '#6b707a' })));
  scene.add(mapGroup);
  // Look at the map from above and aside, "up" being the mapping cameras' up.
  const up = new THREE.Vector3(...meta.up);
  const centre = new THREE.Vector3(0, 0, 0);  // the origin
  const side = new THREE.Vector3().crossVectors(up, Math.abs(up.x) < 0.9
    ? new THREE.Vector3(1, 0, 0) : new THREE.Vector3(0, 1, 0)).normalize();
  camera.up.copy(up);
  camera.near = meta.radius / 500;
  camera.far = meta.radius * 200;
  camera.position.copy(centre).addScaledVector(up, 1.3 * meta.radius)
    .addScaledVector(side, 1.6 * meta.radius);
  camera.updateProjectionMatrix();
  controls.target.copy(centre);
  controls.update();
  view.map = name;
  view.points = n;
  view.cameras = cams.length;
  document.getElementById('maptext').textContent =
    `map ${name} (build ${meta.build_id}): ${meta.n_points.toLocaleString()} points` +
    (n < meta.n_points ? ` (${n.toLocaleString()} drawn)` : '') +
    `, ${cams.length} cameras, scene scale ${meta.scene_scale.toPrecision(3)}`;
  for (const c of clients.values()) { placeClient(c); redrawTrail(c); }
}

function newClient(ev) {
  const colour = PALETTE[clients.size % PALETTE.length];
  const group = new THREE.Group();
  const fgeo = new THREE.BufferGeometry();
  fgeo.setAttribute('position', new THREE.BufferAttribute(new Float32Array(FRUSTUM_VERTS * 3), 3));
  const frustum = new THREE.LineSegments(fgeo, new THREE.LineBasicMaterial({ color: colour }));
  group.add(frustum);
  const dgeo = new THREE.BufferGeometry();
  dgeo.setAttribute('position', new THREE.BufferAttribute(new Float32Array(3), 3));
  const dot = new THREE.Points(dgeo, new THREE.PointsMaterial({
    size: 14, sizeAttenuation: false, color: STATUS.TRACKING, depthTest: false,
  }));
  dot.renderOrder = 2;
  group.add(dot);
  group.visible = false;
  const tgeo = new THREE.BufferGeometry();
  tgeo.setAttribute('position', new THREE.BufferAttribute(new Float32Array(TRAIL * 3), 3));
  tgeo.setDrawRange(0, 0);
  // Drawn over the map: a trajectory runs through the mapping cameras it was localized from.
  const trail = new THREE.Line(tgeo, new THREE.LineBasicMaterial({ color: colour, depthTest: false }));
  trail.frustumCulled = false;
  trail.renderOrder = 1;
  scene.add(group, trail);
  return { id: `${ev.map}/${ev.client}`, map: ev.map, client: ev.client, colour, group, frustum,
    dot, trail, n: 0, world: [], last: null, centre: null, quat: null, seen: performance.now(),
    tanHalf: null, age: 0 };
}

function placeClient(c) {
  const onMap = c.map === view.map;
  c.trail.visible = onMap;
  c.group.visible = onMap && c.centre !== null;
  if (!c.group.visible) return;
  c.group.position.set(...local(c.centre));
  const [x, y, z, w] = c.quat;
  c.group.quaternion.set(x, y, z, w);
  frustumVertices([0.5, 0.375], 0.25 * sceneScale, c.frustum.geometry.attributes.position.array);
  c.frustum.geometry.attributes.position.needsUpdate = true;
  c.frustum.geometry.computeBoundingSphere();
  c.dot.material.color.set(STATUS[c.last.status] || '#ffffff');
}

function addTrail(c, p) {
  if (c.world.length === TRAIL) c.world.shift();
  c.world.push(p);
  const a = c.trail.geometry.attributes.position;
  if (c.n === TRAIL) { a.array.copyWithin(0, 3); c.n--; }
  a.array.set(local(p), 3 * c.n++);
  a.needsUpdate = true;
  c.trail.geometry.setDrawRange(0, c.n);
}

// The trail again, relative to a new map's origin.
function redrawTrail(c) {
  const pts = c.world;
  c.world = [];
  c.n = 0;
  for (const p of pts) addTrail(c, p);
}

function onPose(ev, trail) {
  const id = `${ev.map}/${ev.client}`;
  let c = clients.get(id);
  if (!c) { c = newClient(ev); clients.set(id, c); }
  c.last = ev;
  c.seen = performance.now() - 1000 * (ev.age_s || 0);
  if (trail) { c.n = 0; c.world = []; for (const p of trail) addTrail(c, p); }
  if (ev.centre) {
    c.centre = ev.centre;
    c.quat = ev.quat_xyzw;
    if (!trail) addTrail(c, ev.centre);
  }
  placeClient(c);
  view.clients[ev.client] = {
    map: ev.map, status: ev.status, seq: ev.seq, centre: c.centre, latency_ms: ev.latency_ms,
    rate_hz: ev.rate_hz, inliers: ev.inliers, trail: c.n, poses: ev.n_poses,
  };
  dirty = true;
}

function screenOf(clientId) {
  for (const c of clients.values()) {
    if (c.client !== clientId || !c.centre) continue;
    const v = new THREE.Vector3(...local(c.centre)).project(camera);
    return [(v.x + 1) / 2 * window.innerWidth, (1 - v.y) / 2 * window.innerHeight];
  }
  return null;
}

let dirty = true;
function fmt(x, digits, unit) { return x === null || x === undefined ? '-' : `${x.toFixed(digits)} ${unit}`; }
function renderTable() {
  const rows = [];
  const now = performance.now();
  for (const c of [...clients.values()].sort((a, b) => a.id.localeCompare(b.id))) {
    const ev = c.last;
    const age = (now - c.seen) / 1000;
    const tr = document.createElement('tr');
    if (age > STALE_S) tr.className = 'stale';
    const cells = [
      `<span class="swatch" style="background:${c.colour}"></span>`,
      c.map === view.map ? c.client : `${c.client} (map ${c.map})`,
      `<span style="color:${STATUS[ev.status] || '#fff'}">${ev.status}</span>`,
      fmt(ev.rate_hz, 1, 'Hz'), fmt(ev.latency_ms, 1, 'ms'), String(ev.inliers),
      `${age.toFixed(1)} s ago`, ev.error || ev.message || '',
    ];
    cells.forEach((html, i) => {
      const td = document.createElement('td');
      if (i === 1 || i === 7) td.textContent = html; else td.innerHTML = html;
      if (i >= 3 && i <= 5) td.className = 'num';
      if (i === 7) td.className = 'msg';
      tr.appendChild(td);
    });
    rows.push(tr);
  }
  document.querySelector('#clients tbody').replaceChildren(...rows);
  for (const c of clients.values()) {
    const faded = (now - c.seen) / 1000 > STALE_S;
    c.frustum.material.opacity = c.trail.material.opacity = faded ? 0.35 : 1;
    c.frustum.material.transparent = c.trail.material.transparent = faded;
  }
}

function connect() {
  const es = new EventSource('/events');
  const conn = document.getElementById('conn');
  es.addEventListener('open', () => { view.connected = true; conn.textContent = 'live'; });
  es.addEventListener('error', () => {
    view.connected = false;
    conn.textContent = 'pose stream interrupted, reconnecting...';
  });
  es.addEventListener('snapshot', (m) => {
    for (const ev of JSON.parse(m.data)) onPose(ev, ev.trail);
  });
  es.addEventListener('pose', (m) => { view.events++; onPose(JSON.parse(m.data), null); });
  es.addEventListener('summary', (m) => {
    const s = JSON.parse(m.data);
    const known = new Set();
    for (const x of s.clients) {
      const c = clients.get(`${x.map}/${x.client}`);
      known.add(`${x.map}/${x.client}`);
      if (c) { c.last.rate_hz = x.rate_hz; c.seen = performance.now() - 1000 * x.age_s; }
    }
    for (const [id, c] of clients) {  // silent longer than the viewer's --forget-after
      if (known.has(id)) continue;
      scene.remove(c.group, c.trail);
      clients.delete(id);
      delete view.clients[c.client];
    }
    conn.textContent = `live: ${s.clients.length} client(s), ${s.poses} poses seen` +
      (s.bad_messages ? `, ${s.bad_messages} undecodable (last: ${s.last_bad})` : '');
    dirty = true;
  });
}

async function main() {
  const params = new URLSearchParams(location.search);
  const { maps } = await (await fetchOk('/api/maps')).json();
  const sel = document.getElementById('mapsel');
  for (const m of maps) sel.appendChild(new Option(m, m));
  const name = params.get('map') || maps[0];
  connect();
  if (!name) {
    document.getElementById('maptext').textContent = 'no map bundle under the maps folders';
  } else {
    sel.value = name;
    await loadMap(name);
  }
  sel.addEventListener('change', () => {
    const u = new URL(location.href);
    u.searchParams.set('map', sel.value);
    location.href = u.toString();
  });
  view.ready = true;
}

let lastTable = 0;
renderer.setAnimationLoop((t) => {
  controls.update();
  renderer.render(scene, camera);
  view.frames++;
  if (dirty || t - lastTable > 500) { renderTable(); dirty = false; lastTable = t; }
});
main().catch((e) => fail(String(e.message || e)));
