// Browser side of check.mjs: load a GLB with three.js, pose it with an AnimationMixer at the requested times,
// read named nodes' world positions, then render one frame for the screenshot.
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';

const TRACE_SAMPLES = 120;

function load(url) {
  return new Promise((resolve, reject) => {
    new GLTFLoader().load(url, resolve, undefined,
      (err) => reject(new Error(`GLTFLoader could not load ${url}: ${err && err.message ? err.message : err}`)));
  });
}

// Pose the scene at clip time t: the action's time is set directly and the mixer applied with a zero step,
// so looping and clamping never move it.
function poseAt(scene, mixer, action, t) {
  action.time = t;
  mixer.update(0);
  scene.updateMatrixWorld(true);
}

// The scene's box in the current pose; skinned meshes cache their box, so it is recomputed from the bones.
function boxOf(scene) {
  scene.traverse((o) => { if (o.isSkinnedMesh) o.computeBoundingBox(); });
  return new THREE.Box3().setFromObject(scene);
}

function makeRenderer(width, height) {
  try {
    const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    renderer.setPixelRatio(1);
    renderer.setSize(width, height);
    return renderer;
  } catch (err) {
    console.error(`no WebGL renderer: ${err.message}`);
    return null;
  }
}

// A Scene (GLTFLoader's gltf.scene is a Group) holding the model and two lights; the camera on the skeleton's
// 3/4 front (+Z is forward) at the screenshot time; a 0.5 m ground grid around the origin, large enough for the
// whole motion; and the first node's ground trace over the clip.
function stage(model, motionBox, poseBox, trace, width, height) {
  const scene = new THREE.Scene();
  scene.add(model);
  scene.background = new THREE.Color(0xe8ecf0);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x667788, 2.0));
  const sun = new THREE.DirectionalLight(0xffffff, 2.0);
  sun.position.set(3, 6, 4);
  scene.add(sun);

  const floor = motionBox.min.y;
  const reach = Math.max(Math.abs(motionBox.min.x), Math.abs(motionBox.max.x),
    Math.abs(motionBox.min.z), Math.abs(motionBox.max.z), 1);
  const size = 2 * Math.ceil(reach + 1);
  const grid = new THREE.GridHelper(size, size * 2, 0x445566, 0x99a4b0);
  grid.position.y = floor;
  scene.add(grid);
  if (trace.length > 1) {
    const points = trace.map((p) => new THREE.Vector3(p.x, floor + 0.002, p.z));
    scene.add(new THREE.Line(new THREE.BufferGeometry().setFromPoints(points),
      new THREE.LineBasicMaterial({ color: 0x2266cc })));
  }

  const centre = poseBox.getCenter(new THREE.Vector3());
  const radius = Math.max(poseBox.getBoundingSphere(new THREE.Sphere()).radius, 0.5);
  const camera = new THREE.PerspectiveCamera(40, width / height, 0.01, 1000);
  const distance = 1.15 * radius / Math.sin(THREE.MathUtils.degToRad(20));
  camera.position.copy(centre).add(new THREE.Vector3(0.55, 0.35, 1).normalize().multiplyScalar(distance));
  camera.lookAt(centre);
  return { scene, camera };
}

export async function run({ url, times, nodes, screenshotTime, width, height }) {
  const gltf = await load(url);
  const scene = gltf.scene;
  if (!gltf.animations.length) throw new Error('the GLB holds no animation');
  const clip = gltf.animations[0];

  const found = {};
  for (const name of nodes) {
    const obj = scene.getObjectByName(name);
    if (!obj) {
      const names = [];
      scene.traverse((o) => { if (o.name) names.push(o.name); });
      throw new Error(`no node named "${name}" in the GLB; its nodes are: ${names.join(', ')}`);
    }
    found[name] = { type: obj.type, parent: obj.parent ? obj.parent.name : null };
  }
  let meshCount = 0;
  let skinnedMeshCount = 0;
  scene.traverse((o) => {
    if (o.isMesh) meshCount += 1;
    if (o.isSkinnedMesh) skinnedMeshCount += 1;
  });

  const mixer = new THREE.AnimationMixer(scene);
  const action = mixer.clipAction(clip);
  action.play();

  const positions = Object.fromEntries(nodes.map((name) => [name, []]));
  const v = new THREE.Vector3();
  for (const t of times) {
    poseAt(scene, mixer, action, t);
    for (const name of nodes) {
      scene.getObjectByName(name).getWorldPosition(v);
      positions[name].push([v.x, v.y, v.z]);
    }
  }

  const motionBox = new THREE.Box3();
  const trace = [];
  const traced = nodes.length ? scene.getObjectByName(nodes[0]) : scene;
  for (let i = 0; i <= TRACE_SAMPLES; i += 1) {
    poseAt(scene, mixer, action, clip.duration * i / TRACE_SAMPLES);
    motionBox.union(boxOf(scene));
    trace.push(traced.getWorldPosition(new THREE.Vector3()));
  }
  poseAt(scene, mixer, action, screenshotTime);
  const poseBox = boxOf(scene);

  const renderer = makeRenderer(width, height);
  if (renderer) {
    document.body.appendChild(renderer.domElement);
    const { scene: world, camera } = stage(scene, motionBox, poseBox, trace, width, height);
    renderer.render(world, camera);
  } else {
    document.body.textContent = 'WebGL is unavailable in this browser: nothing was rendered.';
  }

  return {
    nodes: found,
    times,
    positions,
    clip_duration: clip.duration,
    clip_name: clip.name,
    mesh_count: meshCount,
    skinned_mesh_count: skinnedMeshCount,
    screenshot_time: screenshotTime,
    webgl: renderer !== null,
    three_revision: THREE.REVISION,
  };
}
