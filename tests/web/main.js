// Headless check page: load a Potree 2.0 octree (metadata.json, hierarchy.bin, octree.bin)
// with potree-core, render it top-down with an orthographic camera, and write a JSON report
// into <pre id="report">, then set document.title = 'done'.
//
// Query string:
//   url      base URL of the octree directory (default "/data/"); metadata.json is read from it
//   w, h     canvas size in CSS px = device px (default 800x600)
//   timeout  give up loading after this many ms (default 30000)
//   settle   loading counts as finished after this many ms without change (default 1000)
//   budget   point budget (default 1e8, i.e. every node)
//   size     point size in px, fixed size (default 1)
//   color    rgb | white (default: rgb when the octree has an rgb attribute, else white)
//   fit      tight | cube: fit the view to the points' extent (the position attribute's
//            min/max in metadata.json, default) or to the octree's cubic boundingBox

import { Box3, Color, OrthographicCamera, Scene, Vector3, WebGLRenderer } from 'three';
import { Potree, PointSizeType, PointShape } from 'potree-core';

const SRGB = 1; // potree-core's ColorEncoding.SRGB (declared in its .d.ts, not exported at run time)

const q = new URLSearchParams(location.search);
const W = parseInt(q.get('w') || '800', 10);
const H = parseInt(q.get('h') || '600', 10);
const TIMEOUT_MS = parseInt(q.get('timeout') || '30000', 10);
const SETTLE_MS = parseInt(q.get('settle') || '1000', 10);
const BUDGET = Number(q.get('budget') || '1e8');
const POINT_SIZE = Number(q.get('size') || '1');
let base = q.get('url') || '/data/';
if (!base.endsWith('/')) base += '/';

const errors = [];
const note = (msg) => { if (errors.length < 50) errors.push(String(msg)); };
window.addEventListener('error', (e) => note('page error: ' + (e.message || e)));
window.addEventListener('unhandledrejection', (e) => note('unhandled rejection: ' + (e.reason && e.reason.stack || e.reason)));

// potree-core swallows fetch failures (it retries the node every frame) and never hears
// of a worker that throws (the node stays "loading" forever), so watch both here.
const NativeWorker = window.Worker;
window.Worker = class extends NativeWorker {
  constructor(...args) {
    super(...args);
    this.addEventListener('error', (e) => note('decoder worker error: ' + (e.message || 'unknown')));
  }
};
let rangeRequests = 0;
const requestManager = {
  getUrl: async (u) => `${base}${u}`,
  fetch: async (input, init) => {
    let res;
    try {
      res = await fetch(input, init);
    } catch (e) {
      note(`fetch ${input}: ${e}`);
      throw e;
    }
    const range = init && init.headers && init.headers.Range;
    if (range) rangeRequests++;
    if (!res.ok) {
      note(`fetch ${input}${range ? ' ' + range : ''}: HTTP ${res.status}`);
      throw new Error(`HTTP ${res.status} for ${input}`);
    }
    if (range && res.status !== 206) {
      note(`fetch ${input} ${range}: server ignored the Range header (HTTP ${res.status})`);
      throw new Error('no range support');
    }
    return res;
  },
};

const canvas = document.getElementById('c');
canvas.width = W; canvas.height = H;
canvas.style.width = W + 'px'; canvas.style.height = H + 'px';
const report = {
  loaded: false, points: 0, nodes: 0, node_points_sum: 0, covered_pixels: 0,
  width: W, height: H, error: null,
};

function finish(extra) {
  Object.assign(report, extra);
  if (!report.error && errors.length) report.error = errors[0];
  report.errors = errors;
  const pre = document.getElementById('report');
  pre.textContent = JSON.stringify(report);
  document.title = 'done';
}

function walk(root) {
  // Every node the loader knows (the hierarchy grows as proxy chunks load).
  const s = { known: 0, loaded: 0, loading: 0, points: 0, nodePoints: 0, maxLevel: 0 };
  const stack = [root];
  while (stack.length) {
    const n = stack.pop();
    if (!n) continue;
    s.known++;
    if (n.loading) s.loading++;
    if (n.loaded && n.geometry) {
      s.loaded++;
      const pos = n.geometry.getAttribute('position');
      s.points += pos ? pos.count : 0;
      s.nodePoints += n.numPoints || 0;
      s.maxLevel = Math.max(s.maxLevel, n.level || 0);
    }
    for (const c of n.children || []) if (c) stack.push(c);
  }
  return s;
}

function countCovered(gl) {
  // Background is cleared to alpha 0, points write alpha 1, so alpha marks coverage
  // whatever the points' colour.
  const px = new Uint8Array(W * H * 4);
  gl.readPixels(0, 0, W, H, gl.RGBA, gl.UNSIGNED_BYTE, px);
  let n = 0;
  for (let i = 3; i < px.length; i += 4) if (px[i] !== 0) n++;
  return n;
}

async function main() {
  let renderer;
  try {
    renderer = new WebGLRenderer({ canvas, antialias: false, alpha: true, preserveDrawingBuffer: true });
  } catch (e) {
    finish({ error: 'WebGL unavailable: ' + e });
    return;
  }
  renderer.setPixelRatio(1);
  renderer.setSize(W, H, false);
  renderer.setClearColor(new Color(0x000000), 0);
  const gl = renderer.getContext();
  report.webgl = (typeof WebGL2RenderingContext !== 'undefined' && gl instanceof WebGL2RenderingContext) ? 2 : 1;

  const potree = new Potree();
  potree.pointBudget = BUDGET;
  potree.maxNumNodesLoading = 8;

  let pco;
  let meta;
  try {
    meta = await (await requestManager.fetch(await requestManager.getUrl('metadata.json'))).json();
    pco = await potree.loadPointCloud('metadata.json', requestManager);
  } catch (e) {
    finish({ error: 'loading metadata.json failed: ' + (e && e.message || e) });
    return;
  }
  report.metadata_points = meta.points;
  report.encoding = meta.encoding;

  pco.minNodePixelSize = 0; // load nodes however small they project: all of them
  const mat = pco.material;
  mat.pointSizeType = PointSizeType.FIXED;
  mat.size = POINT_SIZE;
  mat.minSize = POINT_SIZE;
  mat.shape = PointShape.SQUARE;
  // potree-core 2.0.15's sRGB<->linear helpers in the vertex shader have mix() arguments swapped
  // (the default input sRGB / output linear turns any channel above ~0.08 white), and its
  // "new format" (Potree 2.0) shader always colours by the rgba attribute whatever
  // pointColorType says. Equal encodings skip the conversion: stored RGB goes to the canvas as is.
  mat.inputColorEncoding = SRGB;
  mat.outputColorEncoding = SRGB;
  const hasRgb = (meta.attributes || []).some((a) => a.name === 'rgb');
  const color = q.get('color') || (hasRgb ? 'rgb' : 'white');
  if (color === 'white') {
    mat.onBeforeCompile = (sh) => {
      sh.fragmentShader = sh.fragmentShader.replace('fragColor = vec4(color, vOpacity);', 'fragColor = vec4(1.0, 1.0, 1.0, 1.0);');
    };
    mat.customProgramCacheKey = () => 'potree-check-white';
    mat.needsUpdate = true;
  }
  report.color = color;

  const scene = new Scene();
  scene.add(pco);
  pco.updateMatrixWorld(true);

  // Top view, orthographic, fitted to the cloud's bounding box (x right, y up, looking down -z).
  const cube = new Box3().copy(pco.pcoGeometry.boundingBox).applyMatrix4(pco.matrixWorld);
  const posAttr = (meta.attributes || []).find((a) => a.name === 'position');
  const fit = q.get('fit') || 'tight';
  let box = cube;
  if (fit === 'tight' && posAttr && posAttr.min && posAttr.max) {
    box = new Box3(new Vector3(...posAttr.min), new Vector3(...posAttr.max));
  }
  report.fit = box === cube ? 'cube' : 'tight';
  const c = box.getCenter(new Vector3());
  const size = box.getSize(new Vector3());
  const sx = Math.max(size.x, 1e-9), sy = Math.max(size.y, 1e-9);
  let halfW = sx / 2, halfH = sy / 2;
  if (halfW / halfH > W / H) halfH = halfW * H / W; else halfW = halfH * W / H;
  const camera = new OrthographicCamera(-halfW, halfW, halfH, -halfH, 0.01, size.z + 2 + size.z * 0.1);
  camera.up.set(0, 1, 0);
  camera.position.set(c.x, c.y, box.max.z + 1);
  camera.lookAt(c.x, c.y, box.min.z);
  camera.updateProjectionMatrix();
  camera.updateMatrixWorld(true);
  report.bbox = { min: box.min.toArray(), max: box.max.toArray() };

  window.__check = { pco, renderer, scene, camera, potree, report };
  const t0 = performance.now();
  let last = null;
  let lastChange = t0;
  let frames = 0;
  const frame = () => {
    // Visibility update only: it picks and starts the node loads. Drawing every frame would
    // cost seconds per frame on SwiftShader (CPU) once a cloud has ~1e6 points; draw once at the end.
    frames++;
    potree.updatePointClouds([pco], camera, renderer);
    const s = walk(pco.pcoGeometry.root);
    const key = `${s.known}/${s.loaded}/${s.loading}/${pco.pcoGeometry.numNodesLoading}`;
    const now = performance.now();
    if (key !== last) { last = key; lastChange = now; }
    const quiet = now - lastChange >= SETTLE_MS;
    const complete = s.loaded === s.known && s.loading === 0 && pco.pcoGeometry.numNodesLoading === 0;
    const timedOut = now - t0 >= TIMEOUT_MS;
    if ((complete && quiet) || (errors.length && quiet) || timedOut) {
      // One last update + render so every loaded node is in the scene, then count pixels.
      const tr = performance.now();
      potree.updatePointClouds([pco], camera, renderer);
      renderer.render(scene, camera);
      const covered = countCovered(gl);
      report.render_ms = Math.round(performance.now() - tr);
      report.frames = frames;
      const ok = complete && errors.length === 0;
      finish({
        loaded: ok,
        points: s.points,
        nodes: s.loaded,
        node_points_sum: s.nodePoints,
        covered_pixels: covered,
        hierarchy_nodes: s.known,
        pending_nodes: s.known - s.loaded,
        max_level: s.maxLevel,
        visible_nodes: pco.visibleNodes.length,
        range_requests: rangeRequests,
        load_ms: Math.round(lastChange - t0),
        error: ok ? null : (errors[0] || (timedOut
          ? `timeout after ${TIMEOUT_MS} ms: ${s.known - s.loaded} of ${s.known} nodes not loaded`
          : `${s.known - s.loaded} of ${s.known} nodes not loaded`)),
      });
      return;
    }
    requestAnimationFrame(frame);
  };
  requestAnimationFrame(frame);
}

main().catch((e) => finish({ error: 'page failed: ' + (e && e.stack || e) }));
