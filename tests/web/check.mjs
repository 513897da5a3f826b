// Driver for potree_check.sh: serve tests/web and the octree directory over HTTP (with Range
// support, npm http-server) on a free localhost port, open the check page in headless Chromium
// (puppeteer-core, system chromium), wait for the page's report, take a screenshot, write JSON.
//
// usage: node check.mjs DIR OUT_JSON [SHOT_PNG]
// env:   CHROMIUM_BIN (default /usr/lib/chromium/chromium, else chromium on PATH)
//        POTREE_CHECK_TIMEOUT_MS (page loading timeout, default 30000)
//        POTREE_CHECK_QUERY (extra query string for the page, e.g. "color=white&size=2")
import fs from 'node:fs';
import os from 'node:os';
import path from 'node:path';
import { execFileSync } from 'node:child_process';
import { createRequire } from 'node:module';
import { fileURLToPath } from 'node:url';

const require = createRequire(import.meta.url);
const here = path.dirname(fileURLToPath(import.meta.url));
const [dir, outJson, shot] = process.argv.slice(2);
if (!dir || !outJson) {
  console.error('usage: node check.mjs DIR OUT_JSON [SHOT_PNG]');
  process.exit(2);
}
const W = 800, H = 600;
const pageTimeout = parseInt(process.env.POTREE_CHECK_TIMEOUT_MS || '30000', 10);
const t0 = Date.now();

function write(report) {
  report.wall_ms = Date.now() - t0;
  fs.writeFileSync(outJson, JSON.stringify(report, null, 2) + '\n');
  console.log(JSON.stringify(report));
}
function fail(msg, extra = {}) {
  write({ loaded: false, points: 0, nodes: 0, node_points_sum: 0, covered_pixels: 0,
    width: W, height: H, error: msg, ...extra });
  process.exit(1);
}

function findChromium() {
  if (process.env.CHROMIUM_BIN) return process.env.CHROMIUM_BIN;
  if (fs.existsSync('/usr/lib/chromium/chromium')) return '/usr/lib/chromium/chromium';
  for (const name of ['chromium', 'chromium-browser', 'google-chrome']) {
    try { return execFileSync('sh', ['-c', `command -v ${name}`]).toString().trim(); } catch {}
  }
  return null;
}

if (!fs.existsSync(path.join(here, 'dist', 'main.js'))) fail('tests/web/dist/main.js missing: run tests/web/install.sh');
if (!fs.existsSync(dir) || !fs.statSync(dir).isDirectory()) fail(`not a directory: ${dir}`);
const chromium = findChromium();
if (!chromium) fail('chromium not found (apt-get install -y chromium)');

// One server root: web -> tests/web, data -> DIR (http-server follows symlinks).
const root = fs.mkdtempSync(path.join(os.tmpdir(), 'potree-check-'));
fs.symlinkSync(here, path.join(root, 'web'));
fs.symlinkSync(path.resolve(dir), path.join(root, 'data'));
const { createServer } = require('http-server');
const server = createServer({ root, cache: -1, showDir: false, gzip: false, brotli: false, cors: false });
const cleanup = () => {
  try { server.close(); } catch {}
  try { fs.rmSync(root, { recursive: true, force: true }); } catch {}
};
process.on('exit', cleanup);
for (const sig of ['SIGINT', 'SIGTERM']) process.on(sig, () => { cleanup(); process.exit(130); });

await new Promise((res, rej) => { server.server.once('error', rej); server.listen(0, '127.0.0.1', res); });
const port = server.server.address().port;
const extra = process.env.POTREE_CHECK_QUERY ? '&' + process.env.POTREE_CHECK_QUERY : '';
const url = `http://127.0.0.1:${port}/web/index.html?url=/data/&w=${W}&h=${H}&timeout=${pageTimeout}${extra}`;

const puppeteer = (await import('puppeteer-core')).default;
let browser;
const consoleLines = [];
try {
  browser = await puppeteer.launch({
    executablePath: chromium,
    headless: true, // = --headless=new
    args: ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader',
      '--ignore-gpu-blocklist', `--window-size=${W},${H}`, '--hide-scrollbars', '--mute-audio'],
    defaultViewport: { width: W, height: H, deviceScaleFactor: 1 },
    timeout: 30000,
  });
  const page = await browser.newPage();
  page.on('console', (m) => { if (consoleLines.length < 40) consoleLines.push(`${m.type()}: ${m.text()}`); });
  page.on('pageerror', (e) => { if (consoleLines.length < 40) consoleLines.push(`pageerror: ${e.message}`); });
  await page.goto(url, { waitUntil: 'load', timeout: 15000 });
  try {
    await page.waitForFunction(() => document.title === 'done', { timeout: pageTimeout + 15000, polling: 200 });
  } catch (e) {
    fail(`page did not finish: ${e.message}`, { console: consoleLines });
  }
  const report = JSON.parse(await page.$eval('#report', (el) => el.textContent));
  if (shot) await page.screenshot({ path: shot, clip: { x: 0, y: 0, width: W, height: H } });
  report.console = consoleLines;
  report.chromium = await browser.version();
  await browser.close();
  browser = null;
  write(report);
  process.exit(report.loaded ? 0 : 1);
} catch (e) {
  if (browser) { try { await browser.close(); } catch {} }
  fail(`browser run failed: ${e && e.message || e}`, { console: consoleLines });
}
