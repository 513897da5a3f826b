// Driver of the CesiumJS check: serve cesium.html, CesiumJS (npm `cesium`, Build/Cesium) and a
// 3D Tiles directory over HTTP (npm http-server) on a free localhost port, open the page in
// headless Chromium (puppeteer-core, Debian chromium, WebGL through SwiftShader), wait for its
// report, print it as one JSON line (and write a screenshot when asked).
// usage: node cesium_check.mjs TILESET_DIR [SHOT_PNG]   exit 0 when the tiles loaded and drew
import fs from 'node:fs';
import os from 'node:os';
import path from 'node:path';
import { execFileSync } from 'node:child_process';
import { createRequire } from 'node:module';
import { fileURLToPath } from 'node:url';

const require = createRequire(import.meta.url);
const here = path.dirname(fileURLToPath(import.meta.url));
const [dir, shot] = process.argv.slice(2);
const fail = (msg) => { console.log(JSON.stringify({ loaded: false, error: msg })); process.exit(1); };
if (!dir || !fs.existsSync(path.join(dir, 'tileset.json'))) fail(`no tileset.json in ${dir}`);
let chromium = process.env.CHROMIUM_BIN || (fs.existsSync('/usr/lib/chromium/chromium') ? '/usr/lib/chromium/chromium' : null);
if (!chromium) { try { chromium = execFileSync('sh', ['-c', 'command -v chromium']).toString().trim(); } catch { fail('chromium not found'); } }
const root = fs.mkdtempSync(path.join(os.tmpdir(), 'cesium-check-'));
fs.symlinkSync(here, path.join(root, 'web'));
fs.symlinkSync(path.join(here, 'node_modules/cesium/Build/Cesium'), path.join(root, 'cesium'));
fs.symlinkSync(path.resolve(dir), path.join(root, 'data'));
const { createServer } = require('http-server');
const server = createServer({ root, cache: -1, showDir: false, gzip: false, brotli: false });
process.on('exit', () => { try { server.close(); } catch {} try { fs.rmSync(root, { recursive: true, force: true }); } catch {} });
await new Promise((res, rej) => { server.server.once('error', rej); server.listen(0, '127.0.0.1', res); });
const port = server.server.address().port;
const puppeteer = (await import('puppeteer-core')).default;
const consoleLines = [];
let browser;
try {
  browser = await puppeteer.launch({
    executablePath: chromium, headless: true,
    args: ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--ignore-gpu-blocklist', '--window-size=800,600', '--hide-scrollbars', '--mute-audio'],
    defaultViewport: { width: 800, height: 600, deviceScaleFactor: 1 }, timeout: 30000,
  });
  const page = await browser.newPage();
  page.on('console', (m) => { if (consoleLines.length < 30) consoleLines.push(`${m.type()}: ${m.text()}`); });
  page.on('pageerror', (e) => { if (consoleLines.length < 30) consoleLines.push(`pageerror: ${e.message}`); });
  await page.goto(`http://127.0.0.1:${port}/web/cesium.html`, { waitUntil: 'load', timeout: 30000 });
  await page.waitForFunction(() => document.title === 'done', { timeout: 90000, polling: 250 });
  const report = JSON.parse(await page.$eval('#report', (el) => el.textContent));
  if (shot) await page.screenshot({ path: shot });
  report.console = consoleLines;
  report.chromium = await browser.version();
  await browser.close();
  console.log(JSON.stringify(report));
  process.exit(report.loaded ? 0 : 1);
} catch (e) {
  if (browser) { try { await browser.close(); } catch {} }
  console.log(JSON.stringify({ loaded: false, error: String(e && e.message || e), console: consoleLines }));
  process.exit(1);
}
