// Load a GLB with three.js (GLTFLoader + AnimationMixer) in headless Chromium, print named nodes' world positions
// at the requested clip times as one JSON object, and save a PNG screenshot of one rendered frame.
//
//   node check.mjs --glb FILE --times 0,0.5,1.3 --nodes pelvis,head,left_wrist --screenshot out.png
//                  [--time-for-screenshot 1.0] [--timeout 90] [--chromium /usr/bin/chromium]
//
// A local http server on 127.0.0.1 serves the page, three's modules (node_modules/three, via an importmap) and
// the GLB; Chromium is Debian's (`apt-get install -y chromium chromium-driver`), started by playwright-core.
// Exit status 0 on success, 2 for bad arguments, 1 for any other failure (message on stderr).
import fs from 'node:fs';
import http from 'node:http';
import path from 'node:path';
import { fileURLToPath } from 'node:url';
import { openPage } from './browser.mjs';

const HERE = path.dirname(fileURLToPath(import.meta.url));
const THREE_DIR = path.join(HERE, 'node_modules', 'three');
const WIDTH = 960;
const HEIGHT = 720;
const TYPES = { '.html': 'text/html', '.js': 'text/javascript', '.glb': 'model/gltf-binary' };
const PAGE = `<!doctype html>
<html><head><meta charset="utf-8"><link rel="icon" href="data:,"><title>lsgan three-check</title>
<style>html, body { margin: 0; background: #e8ecf0; font: 16px sans-serif; }</style>
<script type="importmap">{"imports": {"three": "/three/build/three.module.js",
                                     "three/addons/": "/three/examples/jsm/"}}</script>
<script type="module">import { run } from '/page.js'; window.lsganRun = run;</script>
</head><body></body></html>`;

class UsageError extends Error {}

function parseArgs(argv) {
  const opts = { timeout: 90, chromium: process.env.CHROMIUM || '/usr/bin/chromium' };
  const keys = { '--glb': 'glb', '--times': 'times', '--nodes': 'nodes', '--screenshot': 'screenshot',
    '--time-for-screenshot': 'screenshotTime', '--timeout': 'timeout', '--chromium': 'chromium' };
  for (let i = 0; i < argv.length; i += 2) {
    const key = keys[argv[i]];
    if (!key) throw new UsageError(`unknown argument ${argv[i]}`);
    if (i + 1 >= argv.length) throw new UsageError(`${argv[i]} needs a value`);
    opts[key] = argv[i + 1];
  }
  for (const need of ['glb', 'times', 'nodes', 'screenshot']) {
    if (opts[need] === undefined) throw new UsageError(`--${need} is required`);
  }
  const number = (text, what) => {
    const x = Number(text);
    if (text.trim() === '' || !Number.isFinite(x) || x < 0) {
      throw new UsageError(`${what} must be a non-negative number, got "${text}"`);
    }
    return x;
  };
  opts.times = opts.times.split(',').map((t) => number(t, '--times'));
  opts.nodes = opts.nodes.split(',').map((n) => n.trim()).filter(Boolean);
  if (!opts.nodes.length) throw new UsageError('--nodes names no node');
  opts.screenshotTime = opts.screenshotTime === undefined ? opts.times[0]
    : number(opts.screenshotTime, '--time-for-screenshot');
  opts.timeout = number(String(opts.timeout), '--timeout');
  if (!fs.existsSync(opts.glb)) throw new UsageError(`no GLB file at ${opts.glb}`);
  return opts;
}

// Serve the page, page.js, the GLB and files below node_modules/three; everything else is a 404.
function serve(glbPath, onMissing) {
  const server = http.createServer((req, res) => {
    const url = decodeURIComponent(new URL(req.url, 'http://localhost').pathname);
    let file = null;
    if (url === '/') {
      res.writeHead(200, { 'Content-Type': TYPES['.html'] });
      res.end(PAGE);
      return;
    }
    if (url === '/page.js') file = path.join(HERE, 'page.js');
    else if (url === '/model.glb') file = glbPath;
    else if (url.startsWith('/three/')) {
      const resolved = path.resolve(THREE_DIR, '.' + url.slice('/three'.length));
      if (resolved.startsWith(THREE_DIR + path.sep)) file = resolved;
    }
    if (!file || !fs.existsSync(file) || !fs.statSync(file).isFile()) {
      onMissing(url);
      res.writeHead(404, { 'Content-Type': 'text/plain' });
      res.end('not found');
      return;
    }
    res.writeHead(200, { 'Content-Type': TYPES[path.extname(file)] || 'application/octet-stream' });
    fs.createReadStream(file).pipe(res);
  });
  return new Promise((resolve, reject) => {
    server.once('error', reject);
    server.listen(0, '127.0.0.1', () => resolve(server));
  });
}

async function check(opts, cleanup) {
  if (!fs.existsSync(path.join(THREE_DIR, 'build', 'three.module.js'))) {
    throw new Error(`three.js is not installed in ${HERE}: run \`npm ci\` there`);
  }
  const missing = [];
  const pageErrors = [];
  let broken;
  const failed = new Promise((resolve, reject) => { broken = reject; });
  failed.catch(() => {});
  const server = await serve(path.resolve(opts.glb), (url) => {
    missing.push(url);
    broken(new Error(`the page asked for ${url}, which the local server does not have`));
  });
  cleanup.push(() => new Promise((resolve) => { server.closeAllConnections(); server.close(resolve); }));
  const base = `http://127.0.0.1:${server.address().port}`;

  const { browser, page } = await openPage(opts, WIDTH, HEIGHT);
  cleanup.unshift(() => browser.close());
  page.on('pageerror', (err) => {
    pageErrors.push(err.message);
    broken(new Error('the page threw'));
  });
  page.on('console', (msg) => {
    if (msg.type() === 'error') process.stderr.write(`[browser ${msg.type()}] ${msg.text()}\n`);
  });

  const explain = (err) => {
    const notes = [];
    if (pageErrors.length) notes.push(`page errors: ${pageErrors.join('; ')}`);
    if (missing.length) notes.push(`not found on the local server: ${missing.join(', ')}`);
    return new Error([err.message.split('\n')[0], ...notes].join('\n'));
  };
  try {
    await page.goto(base + '/');
    // A module that fails to load never defines lsganRun: stop at the first 404 or page error instead of waiting.
    await Promise.race([page.waitForFunction(() => typeof window.lsganRun === 'function'), failed]);
    const result = await page.evaluate((args) => window.lsganRun(args), {
      url: base + '/model.glb', times: opts.times, nodes: opts.nodes, screenshotTime: opts.screenshotTime,
      width: WIDTH, height: HEIGHT,
    });
    if (pageErrors.length) throw new Error('the page threw');
    fs.mkdirSync(path.dirname(path.resolve(opts.screenshot)), { recursive: true });
    await page.screenshot({ path: opts.screenshot });
    return result;
  } catch (err) {
    throw explain(err);
  }
}

async function main() {
  let opts;
  try {
    opts = parseArgs(process.argv.slice(2));
  } catch (err) {
    process.stderr.write(`check.mjs: ${err.message}\n`);
    process.exit(err instanceof UsageError ? 2 : 1);
  }
  const cleanup = [];
  let finishing = false;
  // Close the browser and server (each step given a few seconds), then exit; only the first caller counts,
  // so a timeout's teardown does not also report the failures it causes.
  const finish = async (code, message) => {
    if (finishing) return;
    finishing = true;
    if (message) process.stderr.write(`check.mjs: ${message}\n`);
    for (const step of cleanup) {
      await Promise.race([step().catch(() => {}), new Promise((resolve) => setTimeout(resolve, 5000))]);
    }
    process.exit(code);
  };
  const timer = setTimeout(() => finish(1, `timed out after ${opts.timeout} s`), opts.timeout * 1000);
  try {
    const result = await check(opts, cleanup);
    clearTimeout(timer);
    if (!finishing) process.stdout.write(JSON.stringify(result) + '\n');
    await finish(0);
  } catch (err) {
    clearTimeout(timer);
    await finish(1, err.message);
  }
}

main();
