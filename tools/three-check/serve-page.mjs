// Drive the `lsgan serve` page in headless Chromium as a person would, and print what happened as one JSON object.
//
//   node serve-page.mjs --url http://127.0.0.1:8000/ --text "a person walks forward" --screenshot out.png
//                       [--action NAME] [--frames N] [--api-key KEY] [--expect-error] [--no-download] [--enter]
//                       [--draw "dx,dy dx,dy ..."] [--continue] [--timeout 90] [--chromium /usr/bin/chromium]
//
// Loads the page, types the sentence (or picks the action), clicks Generate (with --enter: presses Enter in the
// text box instead) and then, by default, waits until the
// page's state is "playing" and window.lsganViewer.frame has advanced twice, reads the latency line and the GLB/BVH
// download links, clicks both and reports the files the browser saved (name, size, first bytes), saves a
// screenshot, and then checks the view's controls: space pauses, a drag orbits, the wheel zooms, space plays. With --api-key the first Generate is expected to be refused (401): it types the key into the field
// the page then shows and clicks Generate again. With --expect-error the request is expected to fail: it waits for
// the state "error" and reports the one-line message the page shows. Throughout it records every request the page
// makes, the failed ones (non-2xx or network errors), console errors and uncaught page errors.
//
// With --draw, before Generate it clicks "Draw a path" and drags the mouse on the view from its centre (where the
// figure starts, seen from above) through the given offsets in CSS pixels; it reports the path the page sent
// ("sent_path", one [x, z] per frame) and the root of the motion that came back ("root", [x, y, z] per frame).
// With --continue it then ticks "continue the motion shown", generates again and reports that motion's first five
// poses as "continued_poses" beside the first one's last five as "last_poses" ([5][22][3] each; the report stays
// small: a pipe takes only so much before the process exits).
//
// The report's "problems" lists what went wrong; the exit status is 0 when it is empty, 1 otherwise, 2 for bad
// arguments. Expected, not problems: with --expect-error a 4xx answer to POST /v1/generate, with --api-key the 401
// answers before the key is typed, and Chromium's console line about each. Chromium is Debian's, started by
// playwright-core exactly as check.mjs starts it.
import fs from 'node:fs';
import path from 'node:path';
import { openPage } from './browser.mjs';

const WIDTH = 1280;
const HEIGHT = 800;
// Chromium's own console line for a fetch answered with an error status.
const FAILED_LOAD = /^Failed to load resource: the server responded with a status of (\d{3})/;

class UsageError extends Error {}

function parseArgs(argv) {
  const opts = { timeout: 90, chromium: process.env.CHROMIUM || '/usr/bin/chromium', expectError: false,
    download: true };
  const keys = { '--url': 'url', '--text': 'text', '--action': 'action', '--frames': 'frames',
    '--api-key': 'apiKey', '--screenshot': 'screenshot', '--timeout': 'timeout', '--chromium': 'chromium',
    '--draw': 'draw' };
  for (let i = 0; i < argv.length; i++) {
    if (argv[i] === '--expect-error') { opts.expectError = true; continue; }
    if (argv[i] === '--no-download') { opts.download = false; continue; }
    if (argv[i] === '--enter') { opts.enter = true; continue; }
    if (argv[i] === '--continue') { opts.continue = true; continue; }
    const key = keys[argv[i]];
    if (!key) throw new UsageError(`unknown argument ${argv[i]}`);
    if (i + 1 >= argv.length) throw new UsageError(`${argv[i]} needs a value`);
    opts[key] = argv[++i];
  }
  if (!opts.url) throw new UsageError('--url is required');
  if (opts.text === undefined && opts.action === undefined) throw new UsageError('--text or --action is required');
  opts.timeout = Number(opts.timeout);
  if (!Number.isFinite(opts.timeout) || opts.timeout <= 0) throw new UsageError('--timeout must be a positive number');
  opts.origin = new URL(opts.url).origin;
  return opts;
}

async function drive(opts, report, cleanup) {
  const { browser, page } = await openPage(opts, WIDTH, HEIGHT);
  cleanup.push(() => browser.close());

  page.on('request', (req) => report.requests.push(`${req.method()} ${req.url()}`));
  page.on('response', (res) => {
    if (res.status() >= 400) {
      report.failed_requests.push({ method: res.request().method(), url: res.url(), status: res.status() });
    }
  });
  page.on('requestfailed', (req) => {
    report.failed_requests.push({ method: req.method(), url: req.url(), status: null,
      failure: req.failure()?.errorText });
  });
  page.on('console', (msg) => { if (msg.type() === 'error') report.console_errors.push(msg.text()); });
  page.on('pageerror', (err) => report.page_errors.push(err.message));

  const state = () => page.evaluate(() => document.body.dataset.state);
  await page.goto(opts.url, { waitUntil: 'load' });
  // The page has read /v1/info once the model line is filled in (or it shows an error).
  await page.waitForFunction(() => document.body.dataset.state === 'error'
    || !document.querySelector('#model-line').textContent.startsWith('Loading'));
  report.page_title = await page.title();

  if (opts.action !== undefined) {
    await page.selectOption('#action', opts.action);
  } else {
    await page.click('#text');
    await page.keyboard.type(opts.text, { delay: 5 });
  }
  if (opts.frames !== undefined) await page.fill('#frames', String(opts.frames));
  if (opts.draw !== undefined) report.drag = await drawPath(page, opts.draw);
  let clicked = Date.now();
  if (opts.apiKey !== undefined) {
    // Refused without the key: the page shows its field. Type the key and try again.
    await Promise.all([page.waitForResponse((r) => r.status() === 401), page.click('#generate')]);
    await page.waitForSelector('#api-key', { state: 'visible' });
    await page.waitForFunction(() => document.body.dataset.state === 'error');
    report.error_before_key = await page.textContent('#error');
    report.key_typed_after = report.failed_requests.length;
    await page.fill('#api-key', opts.apiKey);
    clicked = Date.now();
  }
  // Wait for the answer to the page's POST /v1/generate, whatever it is, before judging the page's state.
  const answered = (r) => r.request().method() === 'POST' && new URL(r.url()).pathname === '/v1/generate';
  const submit = opts.enter && opts.action === undefined ? page.press('#text', 'Enter') : page.click('#generate');
  const [response] = await Promise.all([page.waitForResponse(answered), submit]);
  if (opts.draw !== undefined || opts.continue) await readControl(page, response, report, opts, answered);

  if (opts.expectError) {
    await page.waitForFunction(() => document.body.dataset.state === 'error');
    report.state = await state();
    report.error_text = await page.textContent('#error');
    report.error_visible = await page.isVisible('#error');
  } else {
    await page.waitForFunction(() => ['playing', 'error'].includes(document.body.dataset.state));
    report.seconds_to_playing = (Date.now() - clicked) / 1000;
    report.state = await state();
    if (report.state === 'error') report.error_text = await page.textContent('#error');
    // Sample the viewer until its frame has changed twice (three different frames seen in a row).
    const deadline = Date.now() + Math.min(20, opts.timeout / 2) * 1000;
    let changes = 0;
    while (report.state === 'playing' && changes < 2 && Date.now() < deadline) {
      const s = await page.evaluate(() => ({ ...window.lsganViewer }));
      const last = report.frame_samples[report.frame_samples.length - 1];
      if (last !== undefined && s.frame !== last) changes += 1;
      report.frame_samples.push(s.frame);
      report.viewer = s;
      await page.waitForTimeout(120);
    }
    report.frames_advanced = changes >= 2;
    report.latency_text = (await page.textContent('#latency')).trim();
    report.downloads = {
      glb: await page.getAttribute('#download-glb', 'href'),
      bvh: await page.getAttribute('#download-bvh', 'href'),
    };
    if (opts.download && report.state === 'playing') {
      report.saved = {};
      for (const kind of ['glb', 'bvh']) {
        const [download] = await Promise.all([page.waitForEvent('download'), page.click(`#download-${kind}`)]);
        const file = await download.path();
        const bytes = fs.readFileSync(file);
        report.saved[kind] = { filename: download.suggestedFilename(), bytes: bytes.length,
          head: bytes.subarray(0, 16).toString('latin1') };
      }
    }
  }
  report.canvas_box = await page.locator('#view').boundingBox();
  report.viewport = { width: WIDTH, height: HEIGHT };
  if (opts.screenshot) {
    fs.mkdirSync(path.dirname(path.resolve(opts.screenshot)), { recursive: true });
    await page.screenshot({ path: opts.screenshot });
    report.screenshot = path.resolve(opts.screenshot);
  }
  if (report.state === 'playing') report.interaction = await interact(page, report.canvas_box);
}

// Press "Draw a path" and drag from the view's centre through the offsets "dx,dy dx,dy ..." (CSS pixels).
async function drawPath(page, offsets) {
  const steps = offsets.trim().split(/\s+/).map((pair) => pair.split(',').map(Number));
  if (!steps.length || steps.some((p) => p.length !== 2 || !p.every(Number.isFinite))) {
    throw new UsageError(`--draw wants "dx,dy dx,dy ...", not ${JSON.stringify(offsets)}`);
  }
  await page.click('#draw-path');
  const box = await page.locator('#view').boundingBox();
  const [cx, cy] = [box.x + box.width / 2, box.y + box.height / 2];
  await page.mouse.move(cx, cy);
  await page.mouse.down();
  for (const [dx, dy] of steps) await page.mouse.move(cx + dx, cy + dy, { steps: 25 });
  await page.mouse.up();
  return { start: [cx, cy], steps, path_line: (await page.textContent('#path-line')).trim() };
}

// The path the page sent and the root that came back; with opts.continue, a second Generate continuing it.
async function readControl(page, response, report, opts, answered) {
  const sent = JSON.parse(response.request().postData() || '{}');
  report.sent_path = sent.path ?? null;
  report.sent_facing = sent.facing ?? false;
  const first = response.ok() ? (await response.json()).motions[0] : null;
  report.root = first ? first.joints.map((pose) => pose[0]) : null;
  if (!opts.continue || !first) return;
  report.last_poses = first.joints.slice(-5);
  await page.waitForFunction(() => document.body.dataset.state === 'playing');
  await page.check('#continue');
  const [again] = await Promise.all([page.waitForResponse(answered), page.click('#generate')]);
  const body = JSON.parse(again.request().postData() || '{}');
  report.continue_from = body.continue_from ?? null;
  report.continue_sent_path = body.path ?? null;
  const answer = again.ok() ? await again.json() : null;
  report.continued_poses = answer ? answer.motions[0].joints.slice(0, 5) : null;
  report.placement = answer ? answer.placement : null;
  await page.waitForFunction(() => ['playing', 'error'].includes(document.body.dataset.state));
}

// Space on the focused view pauses; a drag orbits and the wheel zooms (the paused frame looks different after
// each); space plays again.
async function interact(page, box) {
  const viewer = () => page.evaluate(() => ({ ...window.lsganViewer, state: document.body.dataset.state }));
  const pixels = async () => (await page.locator('#view').screenshot()).toString('base64');
  const out = {};
  await page.focus('#view');
  await page.keyboard.press(' ');
  const paused = await viewer();
  out.paused = !paused.playing && paused.state === 'idle';
  const still = await pixels();
  const [cx, cy] = [box.x + box.width / 2, box.y + box.height / 2];
  await page.mouse.move(cx, cy);
  await page.mouse.down();
  await page.mouse.move(cx + 120, cy - 40, { steps: 4 });
  await page.mouse.up();
  const orbited = await pixels();
  out.drag_changed_view = orbited !== still;
  await page.mouse.wheel(0, -300);
  await page.waitForTimeout(100);
  out.wheel_changed_view = (await pixels()) !== orbited;
  out.frame_held = (await viewer()).frame === paused.frame;
  await page.keyboard.press(' ');
  const resumed = await viewer();
  out.resumed = resumed.playing && resumed.state === 'playing';
  return out;
}

// What went wrong, judged from the report.
function problems(opts, report) {
  const out = [];
  const beforeKey = report.key_typed_after ?? 0;
  const expectedFailure = (f, i) => (opts.expectError && f.method === 'POST' && f.status >= 400 && f.status < 500
    && new URL(f.url).pathname === '/v1/generate') || (opts.apiKey !== undefined && f.status === 401 && i < beforeKey);
  const unexpectedFailures = report.failed_requests.filter((f, i) => !expectedFailure(f, i));
  const expectedStatuses = new Set(report.failed_requests.filter(expectedFailure).map((f) => String(f.status)));
  report.unexpected_console_errors = report.console_errors.filter((text) => {
    const m = FAILED_LOAD.exec(text);
    return !(m && expectedStatuses.has(m[1]));
  });
  report.outside_requests = report.requests.filter((r) => {
    const url = r.slice(r.indexOf(' ') + 1);
    return !url.startsWith(opts.origin + '/') && !url.startsWith('data:') && !url.startsWith('blob:' + opts.origin);
  });
  if (report.page_errors.length) out.push(`the page threw: ${report.page_errors.join('; ')}`);
  if (report.unexpected_console_errors.length) {
    out.push(`console errors: ${report.unexpected_console_errors.join('; ')}`);
  }
  if (unexpectedFailures.length) {
    const lines = unexpectedFailures.map((f) => `${f.method} ${f.url} ${f.status ?? f.failure}`);
    out.push(`failed requests: ${lines.join('; ')}`);
  }
  if (report.outside_requests.length) {
    out.push(`requests outside ${opts.origin}: ${report.outside_requests.join('; ')}`);
  }
  if (opts.expectError) {
    if (report.state !== 'error') out.push(`state is ${report.state}, not error`);
    if (!report.error_visible || !report.error_text?.trim()) out.push('no error message is shown');
    if (!report.failed_requests.some(expectedFailure)) out.push('POST /v1/generate did not fail with a 4xx');
  } else {
    if (report.state !== 'playing') {
      out.push(`state is ${report.state}, not playing${report.error_text ? ` (${report.error_text})` : ''}`);
    }
    const failedSteps = Object.entries(report.interaction || {}).filter(([, ok]) => !ok).map(([step]) => step);
    if (report.state === 'playing' && failedSteps.length) out.push(`interaction failed: ${failedSteps.join(', ')}`);
    if (!report.frames_advanced) {
      out.push(`the viewer's frame did not advance: ${JSON.stringify(report.frame_samples)}`);
    }
    if (!report.latency_text || !/\d+(\.\d+)? ms/.test(report.latency_text)) out.push('no latency is shown');
    for (const kind of ['glb', 'bvh']) {
      const href = report.downloads?.[kind] || '';
      if (!new RegExp(`^/v1/motions/[^/]+\\.${kind}$`).test(href)) out.push(`the ${kind} link is "${href}"`);
      const saved = report.saved?.[kind];
      if (opts.download && !(saved?.bytes > 0)) out.push(`the ${kind} download saved no file`);
    }
    if (opts.apiKey !== undefined && !report.error_before_key?.trim()) out.push('no error was shown before the key');
  }
  return out;
}

async function main() {
  let opts;
  try {
    opts = parseArgs(process.argv.slice(2));
  } catch (err) {
    process.stderr.write(`serve-page.mjs: ${err.message}\n`);
    process.exit(err instanceof UsageError ? 2 : 1);
  }
  const report = { url: opts.url, expect_error: opts.expectError, requests: [], failed_requests: [],
    console_errors: [], page_errors: [], frame_samples: [] };
  const cleanup = [];
  let finished = false;
  // Close the browser (given a few seconds), print the report, exit; only the first caller counts.
  const finish = async (fatal) => {
    if (finished) return;
    finished = true;
    for (const step of cleanup) {
      await Promise.race([step().catch(() => {}), new Promise((resolve) => setTimeout(resolve, 5000))]);
    }
    report.problems = problems(opts, report);
    if (fatal) report.problems.unshift(fatal);
    process.stdout.write(JSON.stringify(report) + '\n');
    if (report.problems.length) process.stderr.write(`serve-page.mjs: ${report.problems.join('\n')}\n`);
    process.exit(report.problems.length ? 1 : 0);
  };
  const timer = setTimeout(() => finish(`timed out after ${opts.timeout} s`), opts.timeout * 1000);
  try {
    await drive(opts, report, cleanup);
    clearTimeout(timer);
    await finish(null);
  } catch (err) {
    clearTimeout(timer);
    await finish(err.message.split('\n')[0]);
  }
}

main();
