// Kestrel live viewer (docs/viewer.md). One WebSocket to the estimator's own
// server (/ws): JSON text messages for the state, binary ones for images and
// point lists. Binary layout (little endian): byte 0 = type, then
//   type 1 (frame): u32 at 4 = JSON length, u32 at 8 = colour JPEG length,
//                   u32 at 12 = depth JPEG length, then the three payloads;
//   types 2-5: u32 at 4 = count, float32 from byte 8:
//     2 poses [t, x, y, z, quality], 3 map points [x, y, z],
//     4 ground truth [x, y, z] (ground-truth frame), 5 keyframes [t, x, y, z, qw, qx, qy, qz].
//   type 6 (dense map, docs/dense.md): u32 at 4 = block count, f32 at 8 = block
//     size [m], f32 at 12 = quantisation range [m]; per block i32 x, y, z, u16 n,
//     n points of u8 qx, qy, qz, r, g, b (position = key * block + q / 255 * range);
//     n = 0: the block is gone. Only changed blocks come; a block replaces its last copy.
// Frames: W of the estimator (z up, gravity along -z); metres, seconds.
'use strict';

const BIN_FRAME = 1, BIN_POSES = 2, BIN_MAP = 3, BIN_GT = 4, BIN_KEYFRAMES = 5, BIN_DENSE = 6;
const FEATURE_DEPTH = 1, FEATURE_MATCHED = 2, FEATURE_INLIER = 4, FEATURE_MAP = 8;
const QUALITY_COLOURS = [[0.55, 0.58, 0.62], [0.82, 0.6, 0.13], [0.35, 0.65, 1.0], [0.97, 0.32, 0.29]];
const PLOT_WINDOW_S = 30;

// What a test (or a curious person in the console) can read.
const kv = window.kestrelViewer = {
  connected: false, estimator: '', hello: null, state: null, framesShown: 0, statesReceived: 0,
  trajectoryPoints: 0, groundTruthPoints: 0, keyframes: 0, mapPoints: 0, webgl: false, renders: 0,
  denseBlocks: 0, densePoints: 0, denseMessages: 0,
  ended: false, paused: false, controlsAvailable: false, errors: [],
};

const $ = (id) => document.getElementById(id);

// ---------------------------------------------------------------- 3-D view
class GrowingLine {
  constructor(scene, material, withColours) {
    this.n = 0;
    this.cap = 0;
    this.withColours = withColours;
    this.geometry = new THREE.BufferGeometry();
    this.object = new THREE.Line(this.geometry, material);
    this.object.frustumCulled = false;
    this.grow(4096);
    scene.add(this.object);
  }
  grow(cap) {
    const pos = new Float32Array(cap * 3);
    if (this.cap > 0) pos.set(this.geometry.getAttribute('position').array.subarray(0, this.n * 3));
    this.geometry.setAttribute('position', new THREE.BufferAttribute(pos, 3));
    if (this.withColours) {
      const col = new Float32Array(cap * 3);
      if (this.cap > 0) col.set(this.geometry.getAttribute('color').array.subarray(0, this.n * 3));
      this.geometry.setAttribute('color', new THREE.BufferAttribute(col, 3));
    }
    this.cap = cap;
  }
  clear() { this.n = 0; this.geometry.setDrawRange(0, 0); }
  push(x, y, z, rgb) {
    if (this.n === this.cap) this.grow(this.cap * 2);
    const p = this.geometry.getAttribute('position');
    p.array[3 * this.n] = x; p.array[3 * this.n + 1] = y; p.array[3 * this.n + 2] = z;
    if (this.withColours) {
      const c = this.geometry.getAttribute('color');
      c.array[3 * this.n] = rgb[0]; c.array[3 * this.n + 1] = rgb[1]; c.array[3 * this.n + 2] = rgb[2];
    }
    this.n++;
  }
  commit() {
    this.geometry.getAttribute('position').needsUpdate = true;
    if (this.withColours) this.geometry.getAttribute('color').needsUpdate = true;
    this.geometry.setDrawRange(0, this.n);
  }
}

const view = {};

function initScene() {
  const host = $('three');
  try {
    view.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  } catch (e) {
    host.innerHTML = '<div class="error3d">The 3-D view needs WebGL, which this browser refused: ' + e.message + '</div>';
    kv.errors.push('webgl: ' + e.message);
    return;
  }
  kv.webgl = true;
  view.renderer.setPixelRatio(window.devicePixelRatio || 1);
  view.renderer.setClearColor(0x101317);
  host.appendChild(view.renderer.domElement);
  view.scene = new THREE.Scene();
  view.camera = new THREE.PerspectiveCamera(50, 1, 0.01, 2000);
  view.camera.up.set(0, 0, 1);
  view.camera.position.set(-2.5, -2.5, 2);
  view.controls = new THREE.OrbitControls(view.camera, view.renderer.domElement);
  view.controls.target.set(0, 0, 0);
  view.controls.update();
  const grid = new THREE.GridHelper(20, 20, 0x3a4048, 0x252a30);
  grid.rotation.x = Math.PI / 2;  // the helper lies in x-z; W's ground is x-y
  view.scene.add(grid);
  view.scene.add(new THREE.AxesHelper(0.5));

  view.traj = new GrowingLine(view.scene, new THREE.LineBasicMaterial({ vertexColors: THREE.VertexColors }), true);
  view.gt = new GrowingLine(view.scene, new THREE.LineBasicMaterial({ color: 0xc9d1d9, transparent: true, opacity: 0.55 }), false);
  view.gt.object.matrixAutoUpdate = false;
  view.gt.object.visible = false;  // until an alignment arrives

  view.kfGeometry = new THREE.BufferGeometry();
  view.kfLines = new THREE.LineSegments(view.kfGeometry, new THREE.LineBasicMaterial({ color: 0xff9f43 }));
  view.kfLines.frustumCulled = false;
  view.scene.add(view.kfLines);

  view.mapGeometry = new THREE.BufferGeometry();
  view.map = new THREE.Points(view.mapGeometry, new THREE.PointsMaterial({ color: 0x9aa4af, size: 2, sizeAttenuation: false }));
  view.map.frustumCulled = false;
  view.scene.add(view.map);

  view.body = new THREE.Group();
  view.body.add(new THREE.AxesHelper(0.3));
  view.scene.add(view.body);

  const resize = () => {
    const w = host.clientWidth, h = Math.max(host.clientHeight, 300);
    view.renderer.setSize(w, h);
    view.camera.aspect = w / h;
    view.camera.updateProjectionMatrix();
  };
  new ResizeObserver(resize).observe(host);
  resize();
  const loop = () => {
    view.controls.update();
    view.renderer.render(view.scene, view.camera);
    kv.renders++;
    requestAnimationFrame(loop);
  };
  requestAnimationFrame(loop);
}

// A small camera pyramid per keyframe, from the camera model in the hello.
let frustumCorners = [[-0.08, -0.06, 0.1], [0.08, -0.06, 0.1], [0.08, 0.06, 0.1], [-0.08, 0.06, 0.1]];
const keyframePoses = [];

function setCamera(cam) {
  if (!cam || !(cam.fx > 0) || !(cam.width > 0)) return;
  const z = 0.1, hw = z * cam.width / 2 / cam.fx, hh = z * cam.height / 2 / cam.fy;
  frustumCorners = [[-hw, -hh, z], [hw, -hh, z], [hw, hh, z], [-hw, hh, z]];
}

function rebuildKeyframes() {
  if (!view.scene) return;
  const segs = new Float32Array(keyframePoses.length * 8 * 2 * 3);
  let k = 0;
  const v = new THREE.Vector3(), q = new THREE.Quaternion();
  for (const kf of keyframePoses) {
    q.set(kf[5], kf[6], kf[7], kf[4]);  // THREE takes x y z w
    const c = frustumCorners.map((p) => v.set(p[0], p[1], p[2]).applyQuaternion(q).add(new THREE.Vector3(kf[1], kf[2], kf[3])).clone());
    const o = [kf[1], kf[2], kf[3]];
    for (let i = 0; i < 4; i++) {
      const a = c[i], b = c[(i + 1) % 4];
      segs.set([o[0], o[1], o[2], a.x, a.y, a.z], k); k += 6;
      segs.set([a.x, a.y, a.z, b.x, b.y, b.z], k); k += 6;
    }
  }
  view.kfGeometry.setAttribute('position', new THREE.BufferAttribute(segs, 3));
  view.kfGeometry.setDrawRange(0, k / 3);
}

let followTarget = null;

function onPoses(f, n) {
  if (!view.traj) return;
  for (let i = 0; i < n; i++) {
    const q = Math.max(0, Math.min(3, Math.round(f[5 * i + 4])));
    view.traj.push(f[5 * i + 1], f[5 * i + 2], f[5 * i + 3], QUALITY_COLOURS[q]);
  }
  view.traj.commit();
  kv.trajectoryPoints = view.traj.n;
  if (n > 0) followTarget = new THREE.Vector3(f[5 * (n - 1) + 1], f[5 * (n - 1) + 2], f[5 * (n - 1) + 3]);
}

function onGroundTruth(f, n) {
  if (!view.gt) return;
  for (let i = 0; i < n; i++) view.gt.push(f[3 * i], f[3 * i + 1], f[3 * i + 2]);
  view.gt.commit();
  kv.groundTruthPoints = view.gt.n;
}

function onAlign(m) {
  if (!view.gt) return;
  const R = m.R, t = m.t;
  view.gt.object.matrix.set(R[0], R[1], R[2], t[0], R[3], R[4], R[5], t[1], R[6], R[7], R[8], t[2], 0, 0, 0, 1);
  view.gt.object.matrixWorldNeedsUpdate = true;
  view.gt.object.visible = $('show-gt').checked;
  kv.aligned = true;
}

function onMap(f, n) {
  if (!view.mapGeometry) return;
  view.mapGeometry.setAttribute('position', new THREE.BufferAttribute(new Float32Array(f), 3));
  view.mapGeometry.setDrawRange(0, n);
  kv.mapPoints = n;
}

// The dense map: one small point cloud per block, replaced when the block
// comes again (the stream sends a block whole, never a part of one).
const denseBlocks = new Map();
let denseMaterial = null;

function onDense(buf) {
  const dv = new DataView(buf);
  const count = dv.getUint32(4, true), block = dv.getFloat32(8, true), range = dv.getFloat32(12, true);
  let at = 16;
  kv.denseMessages++;
  if (!denseMaterial) denseMaterial = new THREE.PointsMaterial({ size: 3, sizeAttenuation: false, vertexColors: THREE.VertexColors });
  for (let r = 0; r < count && at + 14 <= buf.byteLength; r++) {
    const kx = dv.getInt32(at, true), ky = dv.getInt32(at + 4, true), kz = dv.getInt32(at + 8, true);
    const n = dv.getUint16(at + 12, true);
    at += 14;
    if (at + 6 * n > buf.byteLength) break;
    const key = kx + ',' + ky + ',' + kz;
    const old = denseBlocks.get(key);
    if (old) {
      kv.densePoints -= old.n;
      if (view.scene) view.scene.remove(old.object);
      old.object.geometry.dispose();
      denseBlocks.delete(key);
    }
    if (n > 0) {
      const q = new Uint8Array(buf, at, 6 * n);
      const pos = new Float32Array(3 * n), col = new Float32Array(3 * n);
      const ox = kx * block, oy = ky * block, oz = kz * block, k = range / 255;
      for (let i = 0; i < n; i++) {
        pos[3 * i] = ox + q[6 * i] * k; pos[3 * i + 1] = oy + q[6 * i + 1] * k; pos[3 * i + 2] = oz + q[6 * i + 2] * k;
        col[3 * i] = q[6 * i + 3] / 255; col[3 * i + 1] = q[6 * i + 4] / 255; col[3 * i + 2] = q[6 * i + 5] / 255;
      }
      const g = new THREE.BufferGeometry();
      g.setAttribute('position', new THREE.BufferAttribute(pos, 3));
      g.setAttribute('color', new THREE.BufferAttribute(col, 3));
      const object = new THREE.Points(g, denseMaterial);
      object.visible = !$('show-dense') || $('show-dense').checked;
      if (view.scene) view.scene.add(object);
      denseBlocks.set(key, { object, n });
      kv.densePoints += n;
    }
    at += 6 * n;
  }
  kv.denseBlocks = denseBlocks.size;
}

function clearDense() {
  for (const b of denseBlocks.values()) { if (view.scene) view.scene.remove(b.object); b.object.geometry.dispose(); }
  denseBlocks.clear();
  kv.denseBlocks = kv.densePoints = 0;
}

$('show-dense').onchange = () => { for (const b of denseBlocks.values()) b.object.visible = $('show-dense').checked; };

function onKeyframes(f, n) {
  for (let i = 0; i < n; i++) keyframePoses.push(Array.from(f.subarray(8 * i, 8 * i + 8)));
  kv.keyframes = keyframePoses.length;
  rebuildKeyframes();
}

function updateBody(s) {
  if (!view.body) return;
  view.body.position.set(s.p[0], s.p[1], s.p[2]);
  view.body.quaternion.set(s.q[1], s.q[2], s.q[3], s.q[0]);
  if ($('follow').checked && followTarget) {
    const d = followTarget.clone().sub(view.controls.target);
    view.controls.target.add(d);
    view.camera.position.add(d);
  }
}

function resetScene() {
  if (view.traj) { view.traj.clear(); view.gt.clear(); view.gt.object.visible = false; }
  keyframePoses.length = 0;
  rebuildKeyframes();
  if (view.mapGeometry) view.mapGeometry.setDrawRange(0, 0);
  clearDense();
  Object.assign(kv, { trajectoryPoints: 0, groundTruthPoints: 0, keyframes: 0, mapPoints: 0, aligned: false });
  for (const p of Object.values(plots)) p.clear();
}

// ---------------------------------------------------------------- images
let rgbUrl = null, depthUrl = null, lastMeta = null;

function showFrame(buf) {
  const dv = new DataView(buf);
  const lj = dv.getUint32(4, true), lr = dv.getUint32(8, true), ld = dv.getUint32(12, true);
  const meta = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 16, lj)));
  if (lr > 0) {
    const url = URL.createObjectURL(new Blob([new Uint8Array(buf, 16 + lj, lr)], { type: 'image/jpeg' }));
    const img = $('rgb');
    img.onload = () => {
      if (rgbUrl) URL.revokeObjectURL(rgbUrl);
      rgbUrl = url;
      lastMeta = meta;
      drawFeatures();
      kv.framesShown++;
      img.dataset.frames = String(kv.framesShown);
    };
    img.src = url;
  }
  if (ld > 0) {
    const url = URL.createObjectURL(new Blob([new Uint8Array(buf, 16 + lj + lr, ld)], { type: 'image/jpeg' }));
    const img = $('depth');
    img.onload = () => { if (depthUrl) URL.revokeObjectURL(depthUrl); depthUrl = url; };
    img.src = url;
  }
  $('frame-info').textContent = `frame ${meta.frames} · t ${meta.t.toFixed(2)} s · ${meta.features.length / 3} features`;
}

function drawFeatures() {
  const img = $('rgb'), cv = $('features');
  const w = img.clientWidth, h = img.clientHeight;
  if (cv.width !== w || cv.height !== h) { cv.width = w; cv.height = h; }
  const g = cv.getContext('2d');
  g.clearRect(0, 0, w, h);
  if (!lastMeta || !(lastMeta.width > 0)) return;
  const sx = w / lastMeta.width, sy = h / lastMeta.height, f = lastMeta.features;
  g.lineWidth = 1.5;
  for (let i = 0; i < f.length; i += 3) {
    const x = f[i] * sx, y = f[i + 1] * sy, fl = f[i + 2];
    let colour, filled = true;
    if (fl & FEATURE_MAP) colour = '#ffd33d';
    else if (fl & FEATURE_INLIER) colour = '#3fb950';
    else if (fl & FEATURE_MATCHED) colour = '#f85149';
    else if (!(fl & FEATURE_DEPTH)) { colour = '#d2a8ff'; filled = false; }
    else colour = '#58a6ff';
    g.beginPath();
    g.arc(x, y, filled ? 2.5 : 3, 0, 2 * Math.PI);
    if (filled) { g.fillStyle = colour; g.fill(); } else { g.strokeStyle = colour; g.stroke(); }
  }
}
window.addEventListener('resize', drawFeatures);

// ---------------------------------------------------------------- plots
class Plot {
  constructor(id, unit, colour) { this.cv = $(id); this.unit = unit; this.colour = colour; this.t = []; this.v = []; }
  clear() { this.t = []; this.v = []; this.draw(); }
  add(t, v) {
    if (v === null || v === undefined || !isFinite(v)) return;
    this.t.push(t); this.v.push(v);
    while (this.t.length > 0 && this.t[0] < t - PLOT_WINDOW_S) { this.t.shift(); this.v.shift(); }
    this.draw();
  }
  draw() {
    const cv = this.cv, w = cv.clientWidth, h = cv.clientHeight;
    if (cv.width !== w || cv.height !== h) { cv.width = w; cv.height = h; }
    const g = cv.getContext('2d');
    g.clearRect(0, 0, w, h);
    if (this.v.length < 2) return;
    const t1 = this.t[this.t.length - 1], t0 = t1 - PLOT_WINDOW_S;
    const vmax = Math.max(1e-9, ...this.v) * 1.15;
    g.strokeStyle = '#2e343c';
    g.beginPath(); g.moveTo(0, h - 0.5); g.lineTo(w, h - 0.5); g.stroke();
    g.fillStyle = '#8b949e'; g.font = '10px sans-serif';
    g.fillText(vmax.toPrecision(3) + ' ' + this.unit, 3, 10);
    g.strokeStyle = this.colour; g.lineWidth = 1.3;
    g.beginPath();
    for (let i = 0; i < this.v.length; i++) {
      const x = (this.t[i] - t0) / PLOT_WINDOW_S * w, y = h - 2 - this.v[i] / vmax * (h - 14);
      if (i === 0) g.moveTo(x, y); else g.lineTo(x, y);
    }
    g.stroke();
  }
}
const plots = {
  tracking: new Plot('plot-tracking', 'ms', '#58a6ff'),
  optimizer: new Plot('plot-optimizer', 'ms', '#d2a8ff'),
  imu: new Plot('plot-imu', 'ms', '#3fb950'),
  inliers: new Plot('plot-inliers', '', '#ffd33d'),
};

// ---------------------------------------------------------------- state panel
function fmt(v, digits) { return v === null || v === undefined ? '—' : Number(v).toFixed(digits); }

function rows(table, list) {
  table.innerHTML = list.map(([k, v, bad]) => `<tr${bad ? ' class="bad"' : ''}><td>${k}</td><td>${v}</td></tr>`).join('');
}

// The pipeline's registry by path (docs/threads.md, "Counters"): filled only
// while its table is open (it is long), and when it is opened.
function showPerf(s) {
  if (!s || !s.perf) return;
  const box = $('perf-box');
  box.hidden = false;
  if (!box.open) return;
  rows($('perf-table'), Object.entries(s.perf).map(([k, v]) =>
    typeof v === 'object' ? [k, `${v.count} × ${fmt(v.mean_ms, 2)} ms (max ${fmt(v.max_ms, 2)})`] : [k, v]));
}
$('perf-box').addEventListener('toggle', () => showPerf(kv.state));

function showState(s) {
  kv.state = s;
  kv.statesReceived++;
  kv.estimator = s.estimator;
  $('estimator').textContent = s.estimator;
  const q = $('quality');
  q.textContent = s.quality;
  q.className = 'quality q-' + s.quality;
  const tr = s.track, w = s.window, L = s.latency_ms;
  const speed = Math.hypot(s.v[0], s.v[1], s.v[2]);
  const list = [
    ['estimator', s.estimator],
    ['time', fmt(s.t, 2) + ' s'],
    ['frames', s.frames],
    ['quality', s.quality],
    ['resets', s.reset_counter, s.reset_counter > 0],
    ['position [m]', `${fmt(s.p[0], 3)} ${fmt(s.p[1], 3)} ${fmt(s.p[2], 3)}`],
    ['speed', fmt(speed, 2) + ' m/s'],
  ];
  if (tr) {
    list.push(['tracker', tr.status + (tr.keyframe ? ' (keyframe)' : '')]);
    list.push(['features / with depth', `${tr.detected} / ${tr.with_depth}`]);
    list.push(['matched / inliers', `${tr.matched} / ${tr.inliers}`]);
    list.push(['inlier RMS', fmt(tr.rms_px, 2) + ' px']);
    list.push(['matched area', fmt(100 * tr.area_ratio, 0) + ' %']);
    if (tr.map_inliers > 0) list.push(['map inliers', tr.map_inliers]);
  }
  if (w) {
    list.push(['window solves applied / sent', `${w.applied} / ${w.jobs}`]);
    list.push(['window failures / skipped busy', `${w.failures} / ${w.skipped_busy}`, w.failures > 0]);
  }
  rows($('state-table'), list);
  const d = s.drops, f = s.faults, c = s.counters;
  rows($('faults-table'), [
    ['IMU ring drops', d.imu_ring, d.imu_ring > 0],
    ['frame ring drops', d.frame_ring, d.frame_ring > 0],
    ['frames missing', f.frames_missing, f.frames_missing > 0],
    ['frames out of order', f.out_of_order, f.out_of_order > 0],
    ['frames repeated (frozen)', f.repeated, f.repeated > 0],
    ['frames without depth', f.no_depth, f.no_depth > 0],
    ['IMU gaps', f.imu_gaps, f.imu_gaps > 0],
    ['IMU samples rejected', c.imu_rejected, c.imu_rejected > 0],
    ['viewer snapshots skipped', d.viewer_snapshots],
  ]);
  showPerf(s);
  plots.tracking.add(s.t, L.tracking_max);
  plots.optimizer.add(s.t, L.optimizer);
  plots.imu.add(s.t, L.imu_to_pose_max);
  plots.inliers.add(s.t, tr ? tr.inliers : null);
  $('v-tracking').textContent = fmt(L.tracking_max, 1) + ' ms';
  $('v-optimizer').textContent = L.optimizer === null ? 'n/a' : fmt(L.optimizer, 1) + ' ms';
  $('v-imu').textContent = fmt(L.imu_to_pose_max, 2) + ' ms';
  $('v-inliers').textContent = tr ? tr.inliers : 'n/a';
  updateBody(s);
  $('scene-counts').textContent = `${kv.trajectoryPoints} poses · ${kv.keyframes} keyframes · ${kv.mapPoints} map points` +
    (kv.denseBlocks > 0 ? ` · dense ${kv.densePoints} points in ${kv.denseBlocks} blocks` : '');
}

// ---------------------------------------------------------------- controls
let ws = null;

function command(cmd) { if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify({ cmd })); }
$('btn-pause').onclick = () => command('pause');
$('btn-step').onclick = () => command('step');
$('btn-resume').onclick = () => command('resume');

// http://host:port/?paused holds a lockstep replay from the moment the page
// connects: a person can start stepping from the first frames instead of
// racing a replay that runs faster than real time (and a test can too).
const startPaused = new URLSearchParams(location.search).has('paused');
let startPauseSent = false;

function showControl(m) {
  if (startPaused && !startPauseSent && m.available) {
    startPauseSent = true;
    if (!m.paused) command('pause');
  }
  kv.controlsAvailable = m.available;
  kv.paused = m.paused;
  kv.heldFrame = m.paused ? m.frames : null;
  for (const id of ['btn-pause', 'btn-step', 'btn-resume']) $(id).disabled = !m.available;
  $('btn-pause').classList.toggle('active', m.paused);
  $('control-note').textContent = m.available ? (m.paused ? `paused at frame ${m.frames}` : '') : 'pause/step: --pace lockstep only';
}

$('show-map').onchange = (e) => { if (view.map) view.map.visible = e.target.checked; };
$('show-kf').onchange = (e) => { if (view.kfLines) view.kfLines.visible = e.target.checked; };
$('show-gt').onchange = (e) => { if (view.gt) view.gt.object.visible = e.target.checked && !!kv.aligned; };

// ---------------------------------------------------------------- connection
function onText(m) {
  switch (m.type) {
    case 'hello':
      kv.hello = m;
      kv.estimator = m.estimator;
      kv.ended = false;
      $('banner').hidden = true;
      $('estimator').textContent = m.estimator;
      $('title').textContent = m.title;
      document.title = 'Kestrel · ' + m.estimator + (m.title ? ' · ' + m.title : '');
      $('depth-range').textContent = `${m.depth_range_m[0]}–${m.depth_range_m[1]} m`;
      setCamera(m.camera);
      resetScene();
      break;
    case 'state': showState(m); break;
    case 'control': showControl(m); break;
    case 'align': onAlign(m); break;
    case 'stats':
      $('viewer-stats').textContent = `${m.clients} browser(s) · ${m.kbytes_per_s.toFixed(0)} kB/s · ` +
        `viewer thread ${m.cpu_ms_per_s.toFixed(1)} ms CPU/s · frames sent ${m.frames_sent}, skipped ${m.frames_skipped}`;
      break;
    case 'end':
      kv.ended = true;
      $('banner').textContent = m.summary;
      $('banner').hidden = false;
      break;
    case 'error':
      kv.errors.push(m.message);
      $('control-note').textContent = m.message;
      break;
  }
}

function onBinary(buf) {
  const type = new Uint8Array(buf, 0, 1)[0];
  if (type === BIN_FRAME) { showFrame(buf); return; }
  if (type === BIN_DENSE) { onDense(buf); return; }
  const n = new DataView(buf).getUint32(4, true);
  const stride = { [BIN_POSES]: 5, [BIN_MAP]: 3, [BIN_GT]: 3, [BIN_KEYFRAMES]: 8 }[type];
  if (!stride) return;
  const f = new Float32Array(buf, 8, n * stride);
  if (type === BIN_POSES) onPoses(f, n);
  else if (type === BIN_MAP) onMap(f, n);
  else if (type === BIN_GT) onGroundTruth(f, n);
  else if (type === BIN_KEYFRAMES) onKeyframes(f, n);
}

function connect() {
  const conn = $('conn');
  ws = new WebSocket((location.protocol === 'https:' ? 'wss://' : 'ws://') + location.host + '/ws');
  ws.binaryType = 'arraybuffer';
  ws.onopen = () => { kv.connected = true; conn.textContent = 'live'; conn.className = 'conn conn-ok'; };
  ws.onmessage = (ev) => { if (typeof ev.data === 'string') onText(JSON.parse(ev.data)); else onBinary(ev.data); };
  ws.onclose = (ev) => {
    kv.connected = false;
    kv.lastClose = { code: ev.code, reason: ev.reason, at: performance.now() };
    conn.textContent = kv.ended ? 'finished' : 'disconnected, retrying';
    conn.className = 'conn ' + (kv.ended ? 'conn-wait' : 'conn-down');
    for (const id of ['btn-pause', 'btn-step', 'btn-resume']) $(id).disabled = true;
    setTimeout(connect, kv.ended ? 5000 : 2000);
  };
}

initScene();
connect();
