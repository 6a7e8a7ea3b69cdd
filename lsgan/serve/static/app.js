// The lsgan serve page: read /v1/info, send /v1/generate, play the motion in the viewer, offer its downloads.
// document.body.dataset.state is "idle" | "loading" | "playing" | "error"; window.lsganViewer is the viewer's
// {frame, frames, playing}, for people poking at the console and for the browser test. A path drawn on the ground
// (Draw a path) goes with the next Generate as one point per frame; "continue" sends the motion shown as
// continue_from instead.
import { Viewer } from '/static/viewer.js';

const $ = (id) => document.getElementById(id);
const KEY_STORE = 'lsgan-api-key';
const ui = {
  form: $('controls'), modelLine: $('model-line'), text: $('text'), textField: $('text-field'),
  action: $('action'), actionField: $('action-field'), frames: $('frames'), seconds: $('seconds'),
  seed: $('seed'), seedRandom: $('seed-random'), keyField: $('key-field'), key: $('api-key'),
  generate: $('generate'), error: $('error'), latency: $('latency'),
  glb: $('download-glb'), bvh: $('download-bvh'), canvas: $('view'), play: $('play'), frameLabel: $('frame-label'),
  pathField: $('path-field'), draw: $('draw-path'), clearPath: $('clear-path'), pathLine: $('path-line'),
  continue: $('continue'), facing: $('facing'),
};

let info = null;
let fps = 20;
let drawn = null;      // the drawn path, [[x, z], ...] metres from the origin
let shownId = null;    // the id of the motion shown, for "continue"

const viewer = new Viewer(ui.canvas, { onFrame: showFrame, onPath: setPath });
window.lsganViewer = viewer.status;
viewer.setHint('Describe a motion and press Generate');

function setState(state) { document.body.dataset.state = state; }

function showError(message) {
  const line = String(message).split('\n')[0].trim() || 'something went wrong';
  ui.error.textContent = line;
  ui.error.title = line;
  ui.error.hidden = false;
  setState('error');
}

function clearError() { ui.error.hidden = true; ui.error.textContent = ''; }

function showFrame(status) {
  ui.frameLabel.textContent = status.frames
    ? `frame ${status.frame + 1} / ${status.frames} · ${(status.frame / fps).toFixed(2)} s` : '';
  ui.play.textContent = status.playing ? 'Pause' : 'Play';
  ui.play.setAttribute('aria-pressed', String(!status.playing));
  if (status.frames && document.body.dataset.state !== 'loading' && document.body.dataset.state !== 'error') {
    setState(status.playing ? 'playing' : 'idle');
  }
}

function pathLength(points) {
  let length = 0;
  for (let k = 1; k < points.length; k++) {
    length += Math.hypot(points[k][0] - points[k - 1][0], points[k][1] - points[k - 1][1]);
  }
  return length;
}

// The drawn path as one ground point per frame: evenly spaced along it over the motion's frames, to the millimetre.
function perFrame(points, frames) {
  const along = [0];
  for (let k = 1; k < points.length; k++) {
    along.push(along[k - 1] + Math.hypot(points[k][0] - points[k - 1][0], points[k][1] - points[k - 1][1]));
  }
  const total = along[along.length - 1];
  const rows = [];
  let k = 1;
  for (let f = 0; f < frames; f++) {
    const s = frames > 1 ? (total * f) / (frames - 1) : 0;
    while (k < points.length - 1 && along[k] < s) k += 1;
    const span = along[k] - along[k - 1];
    const w = span > 0 ? Math.min(1, Math.max(0, (s - along[k - 1]) / span)) : 1;
    rows.push([0, 1].map((i) => Number((points[k - 1][i] + w * (points[k][i] - points[k - 1][i])).toFixed(3))));
  }
  return rows;
}

// The motion's length: the frames field, or the server's default when it is empty.
function lengthAsked() {
  const frames = Number.parseInt(ui.frames.value, 10);
  return Number.isFinite(frames) ? frames : (info && info.default_frames) || NaN;
}

function describePath() {
  const frames = lengthAsked();
  if (!drawn) {
    ui.pathLine.textContent = '';
    return;
  }
  const length = pathLength(drawn);
  const speed = Number.isFinite(frames) && frames > 1 ? length / ((frames - 1) / fps) : NaN;
  ui.pathLine.textContent = `${length.toFixed(2)} m` + (Number.isFinite(speed) ? `, ${speed.toFixed(2)} m/s` : '')
    + (info && info.control ? ` (this model goes up to ${info.control.max_speed_m_s.toFixed(1)} m/s)` : '');
}

function setPath(points, { stroke = false } = {}) {
  drawn = points && points.length > 1 ? points : null;
  viewer.setPath(drawn);
  ui.clearPath.disabled = !drawn || ui.continue.checked;
  describePath();
  if (stroke && !drawn) ui.pathLine.textContent = 'Too short to be a path: drag further across the ground.';
}

function setDrawing(on) {
  ui.draw.setAttribute('aria-pressed', String(on));
  viewer.setDrawing(on);
}

function apiKey() { return sessionStorage.getItem(KEY_STORE) || ''; }

function headers(extra = {}) {
  const key = apiKey();
  return key ? { ...extra, Authorization: `Bearer ${key}` } : extra;
}

class ApiError extends Error {}

// fetch + the API's error convention: a non-2xx answer carries {"error": "one line"}. A 401 asks for the key.
async function api(path, options = {}) {
  let response;
  try {
    response = await fetch(path, { ...options, headers: headers(options.headers) });
  } catch (err) {
    throw new ApiError(`could not reach the server (${err.message})`);
  }
  if (response.ok) return response;
  let message = `${response.status} ${response.statusText}`.trim();
  try {
    const body = await response.json();
    if (body && typeof body.error === 'string') message = body.error;
  } catch { /* not JSON: keep the status line */ }
  if (response.status === 401) {
    ui.keyField.hidden = false;
    ui.key.focus();
    message = apiKey() ? 'the API key was refused: check it and try again'
      : 'this server needs an API key: enter it in the field below';
  }
  throw new ApiError(message);
}

function updateSeconds() {
  const frames = Number.parseInt(ui.frames.value, 10);
  ui.seconds.textContent = Number.isFinite(frames) ? `${(frames / fps).toFixed(2)} s at ${fps} fps` : '';
}

async function loadInfo() {
  try {
    info = await (await api('/v1/info')).json();
  } catch (err) {
    ui.modelLine.textContent = 'Could not read the model description.';
    showError(err.message);
    return false;
  }
  fps = info.fps || 20;
  const action = info.condition === 'action';
  ui.textField.hidden = action;
  ui.actionField.hidden = !action;
  if (action) {
    ui.action.replaceChildren(...(info.actions || []).map((name) => new Option(name, name)));
  }
  ui.frames.min = info.min_frames;
  ui.frames.max = info.max_frames;
  ui.frames.value = info.default_frames;
  updateSeconds();
  ui.pathField.hidden = !info.control;
  ui.modelLine.textContent = `${action ? 'Action' : 'Text'}-conditioned model · `
    + `${info.min_frames}–${info.max_frames} frames at ${fps} fps`;
  if (info.skeleton) viewer.setSkeleton(info.skeleton);
  if (info.auth && !apiKey()) ui.keyField.hidden = false;
  return true;
}

function setDownload(link, url) {
  link.href = url;
  link.download = '';  // Save, do not open; the server's Content-Disposition names the file.
  link.removeAttribute('aria-disabled');
}

// The file name of a download: Content-Disposition's, else the URL's last part.
function filenameOf(response, url) {
  const named = /filename="?([^";]+)"?/i.exec(response.headers.get('Content-Disposition') || '');
  return named ? named[1] : url.split('/').pop();
}

// With an API key, links cannot carry the header: fetch the file and hand the browser a blob instead.
async function download(event) {
  const link = event.currentTarget;
  if (!apiKey() || !link.href) return;
  event.preventDefault();
  try {
    const response = await api(link.getAttribute('href'));
    const filename = filenameOf(response, link.getAttribute('href'));
    const url = URL.createObjectURL(await response.blob());
    const a = Object.assign(document.createElement('a'), { href: url, download: filename });
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
  } catch (err) {
    showError(err.message);
  }
}

// How far the motion is from its constraints, as the server measured it.
function missed(control) {
  if (!control) return '';
  const cm = (m) => `${(100 * m.max).toFixed(1)} cm`;
  const parts = [];
  if (control.path_m) parts.push(`path missed by ${cm(control.path_m)} at most`);
  if (control.keyframes_m) parts.push(`keyframes by ${cm(control.keyframes_m)}`);
  return parts.length ? ` · ${parts.join(', ')}` : '';
}

function ms(x) { return typeof x === 'number' ? `${x < 10 ? x.toFixed(1) : Math.round(x)} ms` : '–'; }

async function generate() {
  if (document.body.dataset.state === 'loading') return;
  if (!ui.keyField.hidden && ui.key.value.trim()) sessionStorage.setItem(KEY_STORE, ui.key.value.trim());
  clearError();
  setState('loading');
  ui.generate.disabled = true;
  try {
    // Without the description yet (the server wanted a key, or was not up): read it first.
    if (!info && !(await loadInfo())) return;
    const body = { num: 1 };
    if (info.condition === 'action') body.action = ui.action.value;
    else body.text = ui.text.value;
    const frames = Number.parseInt(ui.frames.value, 10);
    if (Number.isFinite(frames)) body.frames = frames;
    if (!ui.seedRandom.checked && ui.seed.value.trim() !== '') body.seed = Number(ui.seed.value);
    if (ui.continue.checked && shownId) body.continue_from = shownId;
    else if (drawn && Number.isFinite(lengthAsked())) {
      body.path = perFrame(drawn, lengthAsked());
      if (ui.facing.checked) body.facing = true;
    }

    ui.latency.textContent = 'Generating…';
    const started = performance.now();
    const result = await (await api('/v1/generate', {
      method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body),
    })).json();
    const roundTrip = performance.now() - started;
    const motion = result.motions[0];
    const t = result.timings_ms || {};
    ui.latency.textContent = `Round trip ${ms(roundTrip)} · server ${ms(t.total)} (queue ${ms(t.queue)}, `
      + `text ${ms(t.text)}, generator ${ms(t.generator)}, decoder ${ms(t.decoder)}`
      + `${t.control ? `, constraints ${ms(t.control)}` : ''}; batch of ${result.batch_size}) · seed ${result.seed}`
      + missed(motion.control);
    if (ui.seedRandom.checked) ui.seed.value = result.seed;  // Untick "random" to get this motion again.
    fps = result.fps || fps;
    shownId = motion.id;
    ui.continue.disabled = false;
    setDrawing(false);
    setDownload(ui.glb, motion.urls.glb);
    setDownload(ui.bvh, motion.urls.bvh);
    ui.play.disabled = false;
    setState('playing');
    viewer.play(motion.joints, fps);
  } catch (err) {
    ui.latency.textContent = '';
    showError(err instanceof ApiError ? err.message : `unexpected answer from the server (${err.message})`);
  } finally {
    ui.generate.disabled = false;
  }
}

ui.form.addEventListener('submit', (event) => { event.preventDefault(); generate(); });
ui.frames.addEventListener('input', () => { updateSeconds(); describePath(); });
ui.draw.addEventListener('click', () => setDrawing(ui.draw.getAttribute('aria-pressed') !== 'true'));
ui.clearPath.addEventListener('click', () => setPath(null));
// Continuing sends no path: a drawn one stays in view (under the motion it made, where the continuation starts).
ui.continue.addEventListener('change', () => {
  ui.draw.disabled = ui.continue.checked;
  ui.clearPath.disabled = ui.continue.checked || !drawn;
  if (ui.continue.checked) setDrawing(false);
});
ui.seedRandom.addEventListener('change', () => { ui.seed.disabled = ui.seedRandom.checked; });
ui.key.value = apiKey();
ui.key.addEventListener('change', () => sessionStorage.setItem(KEY_STORE, ui.key.value.trim()));
ui.glb.addEventListener('click', download);
ui.bvh.addEventListener('click', download);
ui.play.addEventListener('click', () => viewer.toggle());

setState('idle');
loadInfo().then((ok) => { if (ok) setState('idle'); });
