// A small 3D view of a joint sequence (T frames x J joints x [x, y, z], y up, metres) on a Canvas 2D.
//
// Perspective projection from an orbiting camera (drag or arrow keys to orbit, wheel or +/- to zoom, space to pause,
// Home to reset), a ground grid on y = 0, the root's path on the ground, bones as lines from each joint to its
// parent coloured by kinematic chain, joints as dots, and the bones' shadow on the ground. The camera follows the
// root's horizontal position so walking motions stay in view. Everything is drawn back to front (painter's
// algorithm), which is enough for a stick figure.
//
// Drawing mode (setDrawing(true)): the camera looks down on the start from above, and a drag draws a path on the
// ground instead of orbiting (the pointer's ray cut with y = 0); the path, shifted to start at the origin where
// every motion starts, goes to onPath and stays drawn in orange beside the motion.

const FOV = 45 * Math.PI / 180;
const NEAR = 0.05;
const GRID_STEP = 0.5;      // metres between grid lines
const GRID_HALF = 6;        // metres the grid reaches around the target
const BONE_RADIUS = 0.022;  // metres: bones are drawn this thick at their distance
const JOINT_RADIUS = 0.03;
const DEFAULT_CAMERA = { azimuth: 35 * Math.PI / 180, elevation: 20 * Math.PI / 180, distance: 4 };
const DRAW_CAMERA = { azimuth: Math.PI, elevation: 1.25, distance: 7 };  // above and behind the start, facing +z
const DRAW_STEP = 0.02;     // metres between the points of a drawn path
const PATH_COLOUR = 'rgba(230, 120, 20, 0.9)';
const FALLBACK_COLOUR = '#3c3c3c';

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const normalize = (a) => { const n = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / n, a[1] / n, a[2] / n]; };
const clamp = (x, lo, hi) => Math.min(hi, Math.max(lo, x));

export class Viewer {
  /** @param {HTMLCanvasElement} canvas  @param {{onFrame?: (status) => void}} options */
  constructor(canvas, { onFrame, onPath } = {}) {
    this.canvas = canvas;
    this.ctx = canvas.getContext('2d');
    this.onFrame = onFrame || (() => {});
    this.onPath = onPath || (() => {});
    this.drawing = false;     // drawing mode: a drag draws a path
    this.drawn = null;        // the drawn path: [[x, z], ...] from the origin, metres
    // What the page (and its browser test) can read; updated in place while playing.
    this.status = { frame: 0, frames: 0, playing: false };
    this.joints = null;
    this.fps = 20;
    this.bones = [];          // [{joint, parent, colour}]
    this.camera = { ...DEFAULT_CAMERA };
    this.startedAt = 0;
    this.dirty = true;
    this.hint = '';
    this.setSkeleton({ parents: [], chains: [], chain_colours: [] });
    this.listen();
    new ResizeObserver(() => { this.dirty = true; }).observe(canvas);
    requestAnimationFrame((now) => this.tick(now));
  }

  /** Bones from the skeleton in /v1/info: each joint to its parent, coloured by the chain holding that bone. */
  setSkeleton({ parents, chains, chain_colours: colours }) {
    const colourOf = new Map();
    chains.forEach((chain, c) => {
      for (let k = 1; k < chain.length; k++) colourOf.set(`${chain[k - 1]}-${chain[k]}`, colours[c] || FALLBACK_COLOUR);
    });
    this.bones = parents.flatMap((parent, joint) => (parent < 0 ? [] : [{
      joint, parent, colour: colourOf.get(`${parent}-${joint}`) || FALLBACK_COLOUR,
    }]));
    this.dirty = true;
  }

  setHint(text) { this.hint = text; this.dirty = true; }

  /** Play ``joints`` (T x J x 3) in a loop at ``fps``, from frame 0. */
  play(joints, fps) {
    this.joints = joints;
    this.fps = fps > 0 ? fps : 20;
    const heights = joints.map((frame) => frame[0][1]);
    this.targetHeight = clamp(heights.reduce((a, b) => a + b, 0) / heights.length, 0.3, 1.5);
    // The root's path on the ground.
    this.path = joints.map((frame) => [frame[0][0], 0, frame[0][2]]);
    Object.assign(this.status, { frame: 0, frames: joints.length, playing: true });
    this.startedAt = performance.now();
    this.dirty = true;
    this.onFrame(this.status);
  }

  setPlaying(playing) {
    if (!this.joints || playing === this.status.playing) return;
    this.status.playing = playing;
    // Resume from the frame shown.
    if (playing) this.startedAt = performance.now() - (this.status.frame / this.fps) * 1000;
    this.dirty = true;
    this.onFrame(this.status);
  }

  toggle() { this.setPlaying(!this.status.playing); }

  resetCamera() { this.camera = { ...(this.drawing ? DRAW_CAMERA : DEFAULT_CAMERA) }; this.dirty = true; }

  /** Drawing mode on or off: on, the camera looks down on the start and a drag draws a path. */
  setDrawing(on) {
    this.drawing = Boolean(on);
    this.canvas.classList.toggle('drawing', this.drawing);
    this.resetCamera();
  }

  /** The drawn path ([[x, z], ...] from the origin) or null; shown in orange on the ground. */
  setPath(points) { this.drawn = points && points.length > 1 ? points : null; this.dirty = true; }

  // The ground point (y = 0) under a pointer event, or null when its ray does not go down to the ground.
  groundAt(event) {
    const rect = this.canvas.getBoundingClientRect();
    const dpr = window.devicePixelRatio || 1;
    const height = Math.max(1, Math.round(this.canvas.clientHeight * dpr));
    const width = Math.max(1, Math.round(this.canvas.clientWidth * dpr));
    const cam = this.view(height);
    const px = (event.clientX - rect.left) * dpr - width / 2;
    const py = height / 2 - (event.clientY - rect.top) * dpr;
    const ray = [0, 1, 2].map((k) => cam.forward[k] * cam.focal + cam.right[k] * px + cam.up[k] * py);
    if (ray[1] >= -1e-9) return null;
    const t = -cam.eye[1] / ray[1];
    return [cam.eye[0] + t * ray[0], cam.eye[2] + t * ray[2]];
  }

  listen() {
    const c = this.canvas;
    let last = null;
    let stroke = null;
    c.addEventListener('pointerdown', (e) => {
      last = [e.clientX, e.clientY];
      c.setPointerCapture(e.pointerId);
      if (this.drawing) {
        const p = this.groundAt(e);
        stroke = p ? [p] : null;
      }
    });
    c.addEventListener('pointermove', (e) => {
      if (!last) return;
      if (this.drawing) {
        const p = stroke && this.groundAt(e);
        const end = stroke && stroke[stroke.length - 1];
        if (p && Math.hypot(p[0] - end[0], p[1] - end[1]) >= DRAW_STEP) {
          stroke.push(p);
          this.setPath(stroke.map(([x, z]) => [x - stroke[0][0], z - stroke[0][1]]));
        }
      } else {
        this.orbit((e.clientX - last[0]) * 0.008, (e.clientY - last[1]) * 0.008);
      }
      last = [e.clientX, e.clientY];
    });
    const end = () => {
      if (stroke) {
        if (stroke.length < 2) this.setPath(null);  // a click or a scribble under DRAW_STEP draws nothing
        this.onPath(this.drawn, { stroke: true });
      }
      last = null;
      stroke = null;
    };
    c.addEventListener('pointerup', end);
    c.addEventListener('pointercancel', end);
    c.addEventListener('wheel', (e) => {
      e.preventDefault();
      this.zoom(Math.exp(e.deltaY * 0.001));
    }, { passive: false });
    c.addEventListener('keydown', (e) => {
      const keys = {
        ArrowLeft: () => this.orbit(-0.1, 0), ArrowRight: () => this.orbit(0.1, 0),
        ArrowUp: () => this.orbit(0, -0.08), ArrowDown: () => this.orbit(0, 0.08),
        '+': () => this.zoom(1 / 1.1), '=': () => this.zoom(1 / 1.1), '-': () => this.zoom(1.1),
        ' ': () => this.toggle(), Home: () => this.resetCamera(),
      };
      if (keys[e.key]) { e.preventDefault(); keys[e.key](); }
    });
  }

  orbit(dAzimuth, dElevation) {
    this.camera.azimuth -= dAzimuth;
    this.camera.elevation = clamp(this.camera.elevation + dElevation, 0.02, 1.5);
    this.dirty = true;
  }

  zoom(factor) { this.camera.distance = clamp(this.camera.distance * factor, 1, 25); this.dirty = true; }

  tick(now) {
    if (this.joints && this.status.playing) {
      // rAF's timestamp is the frame's start, which can precede the performance.now() that started playing.
      const elapsed = Math.max(0, now - this.startedAt) / 1000;
      const frame = Math.floor(elapsed * this.fps) % this.joints.length;
      if (frame !== this.status.frame) {
        this.status.frame = frame;
        this.dirty = true;
        this.onFrame(this.status);
      }
    }
    if (this.dirty) { this.dirty = false; this.draw(); }
    requestAnimationFrame((t) => this.tick(t));
  }

  // The camera: its eye, orthonormal axes and focal length in pixels, for a canvas of the given height.
  view(height) {
    const pose = this.joints && !this.drawing ? this.joints[this.status.frame] : null;
    const target = pose ? [pose[0][0], this.targetHeight, pose[0][2]] : [0, this.drawing ? 0 : 0.9, 0];
    const { azimuth, elevation, distance } = this.camera;
    const eye = [target[0] + distance * Math.cos(elevation) * Math.sin(azimuth),
      target[1] + distance * Math.sin(elevation), target[2] + distance * Math.cos(elevation) * Math.cos(azimuth)];
    const forward = normalize(sub(target, eye));
    const right = normalize(cross(forward, [0, 1, 0]));
    const up = cross(right, forward);
    return { target, eye, forward, right, up, focal: height / 2 / Math.tan(FOV / 2) };
  }

  draw() {
    const { canvas, ctx } = this;
    const dpr = window.devicePixelRatio || 1;
    const width = Math.max(1, Math.round(canvas.clientWidth * dpr));
    const height = Math.max(1, Math.round(canvas.clientHeight * dpr));
    if (canvas.width !== width || canvas.height !== height) { canvas.width = width; canvas.height = height; }
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.clearRect(0, 0, width, height);
    ctx.lineCap = 'round';
    const cam = this.view(height);
    const toCamera = (p) => {
      const d = sub(p, cam.eye);
      return [dot(d, cam.right), dot(d, cam.up), dot(d, cam.forward)];
    };
    const toScreen = (c) => [width / 2 + (cam.focal * c[0]) / c[2], height / 2 - (cam.focal * c[1]) / c[2]];
    // A segment in camera space, cut at the near plane; null when wholly behind it.
    const segment = (a, b) => {
      if (a[2] < NEAR && b[2] < NEAR) return null;
      const cut = (p, q) => {
        const s = (NEAR - p[2]) / (q[2] - p[2]);
        return [p[0] + s * (q[0] - p[0]), p[1] + s * (q[1] - p[1]), NEAR];
      };
      if (a[2] < NEAR) a = cut(a, b);
      if (b[2] < NEAR) b = cut(b, a);
      return [toScreen(a), toScreen(b)];
    };
    const line = (a, b, colour, lineWidth) => {
      const s = segment(toCamera(a), toCamera(b));
      if (!s) return;
      ctx.strokeStyle = colour;
      ctx.lineWidth = lineWidth;
      ctx.beginPath();
      ctx.moveTo(s[0][0], s[0][1]);
      ctx.lineTo(s[1][0], s[1][1]);
      ctx.stroke();
    };

    // Ground grid around the target, fading with distance, the world axes a little darker.
    const cx = Math.round(cam.target[0] / GRID_STEP) * GRID_STEP;
    const cz = Math.round(cam.target[2] / GRID_STEP) * GRID_STEP;
    const thin = Math.max(1, dpr);
    for (let k = -GRID_HALF; k <= GRID_HALF + 1e-9; k += GRID_STEP) {
      ctx.globalAlpha = 1 - Math.abs(k) / (GRID_HALF + GRID_STEP);
      const x = cx + k;
      const z = cz + k;
      line([x, 0, cz - GRID_HALF], [x, 0, cz + GRID_HALF], Math.abs(x) < 1e-6 ? '#a9b1b9' : '#d5dade', thin);
      line([cx - GRID_HALF, 0, z], [cx + GRID_HALF, 0, z], Math.abs(z) < 1e-6 ? '#a9b1b9' : '#d5dade', thin);
    }
    ctx.globalAlpha = 1;
    if (this.drawn) {
      for (let t = 1; t < this.drawn.length; t++) {
        const [a, b] = [this.drawn[t - 1], this.drawn[t]];
        line([a[0], 0.002, a[1]], [b[0], 0.002, b[1]], PATH_COLOUR, 4 * thin);
      }
    }

    if (!this.joints) {
      if (this.hint) {
        ctx.fillStyle = '#5c6670';
        ctx.font = `${Math.round(15 * dpr)}px system-ui, sans-serif`;
        ctx.textAlign = 'center';
        ctx.fillText(this.hint, width / 2, height / 2);
      }
      return;
    }
    const pose = this.joints[this.status.frame];

    // The root's path: all of it faint, the part walked so far stronger.
    const frame = this.status.frame;
    for (let t = 1; t < this.path.length; t++) {
      const colour = t <= frame ? 'rgba(30, 140, 30, 0.8)' : 'rgba(120, 200, 120, 0.45)';
      line(this.path[t - 1], this.path[t], colour, 2 * thin);
    }
    // Shadow: the bones flattened onto the ground.
    for (const bone of this.bones) {
      const a = pose[bone.parent];
      const b = pose[bone.joint];
      line([a[0], 0.001, a[2]], [b[0], 0.001, b[2]], 'rgba(0, 0, 0, 0.10)', 4 * thin);
    }

    // Bones and joints, far to near.
    const cameraPose = pose.map(toCamera);
    const items = [];
    for (const bone of this.bones) {
      const a = cameraPose[bone.parent];
      const b = cameraPose[bone.joint];
      items.push({ depth: (a[2] + b[2]) / 2 + 0.01, bone, a, b });
    }
    cameraPose.forEach((c, joint) => items.push({ depth: c[2], joint, c }));
    items.sort((p, q) => q.depth - p.depth);
    for (const item of items) {
      if (item.depth < NEAR) continue;
      if (item.bone) {
        const s = segment(item.a, item.b);
        if (!s) continue;
        ctx.strokeStyle = item.bone.colour;
        ctx.lineWidth = Math.max(1.5 * dpr, (2 * BONE_RADIUS * cam.focal) / item.depth);
        ctx.beginPath();
        ctx.moveTo(s[0][0], s[0][1]);
        ctx.lineTo(s[1][0], s[1][1]);
        ctx.stroke();
      } else {
        const [x, y] = toScreen(item.c);
        ctx.fillStyle = '#1d2125';
        ctx.beginPath();
        ctx.arc(x, y, Math.max(2 * dpr, (JOINT_RADIUS * cam.focal) / item.depth), 0, 2 * Math.PI);
        ctx.fill();
      }
    }
  }
}
