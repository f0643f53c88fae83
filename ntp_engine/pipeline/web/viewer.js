// The result page's 3D view (RESULT/index.html, written by ntp_engine/io/result_page.py): the
// asset's .glb drawn by three.js with a movable point light and a turntable, and `renderLinear`,
// the hook the browser check (check.mjs) drives to render a view as linear floats.
//
// Frames: the .glb is +Y up (glTF); the scene's `world` group turns it back to ntp's world frame
// (metres, z up; x_ntp = x_gltf, y_ntp = -z_gltf, z_ntp = y_gltf), so poses and light positions
// from the engine (OpenCV camera-from-world, docs/design.md) are used as they are.
// Light units: a PointLight of intensity I (three.js: candela, decay 2) gives irradiance I cos / d^2,
// as the engine's isotropic point emitter of drive I does; both draw rho_d / pi for the diffuse.
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const TURNTABLE_RAD_PER_S = (2 * Math.PI) / 12; // one turn in 12 s
const VIEW_DISTANCE = 4; // camera and light stand this many bounding radii from the centre (the relight rig's)
const WHITE_RADIANCE = 0.8; // a white diffuse patch facing the light reads this before display

function base64Bytes(text) {
  const raw = atob(text);
  const out = new Uint8Array(raw.length);
  for (let i = 0; i < raw.length; i++) out[i] = raw.charCodeAt(i);
  return out;
}

function bytesBase64(bytes) {
  let s = '';
  const step = 0x8000;
  for (let i = 0; i < bytes.length; i += step) s += String.fromCharCode.apply(null, bytes.subarray(i, i + step));
  return btoa(s);
}

// The projection of an OpenCV pinhole (pixel centres at integer coordinates) as a GL matrix.
function intrinsicProjection(fx, fy, cx, cy, width, height, near, far) {
  const m = new THREE.Matrix4();
  m.set(
    (2 * fx) / width, 0, 1 - (2 * (cx + 0.5)) / width, 0,
    0, (2 * fy) / height, (2 * (cy + 0.5)) / height - 1, 0,
    0, 0, -(far + near) / (far - near), (-2 * far * near) / (far - near),
    0, 0, -1, 0,
  );
  return m;
}

// Camera-to-world of a three.js camera (x right, y up, looking down -z) from an OpenCV
// camera-from-world pose `pose` (16 numbers, row-major).
function cameraWorld(pose) {
  const cv = new THREE.Matrix4().fromArray(pose).transpose(); // fromArray reads column-major
  const flip = new THREE.Matrix4().makeScale(1, -1, -1);
  return cv.invert().multiply(flip);
}

export async function start() {
  const data = JSON.parse(document.getElementById('ntp-data').textContent);
  const canvas = document.getElementById('ntp-canvas');
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  renderer.outputColorSpace = THREE.SRGBColorSpace;
  renderer.toneMapping = THREE.AgXToneMapping; // the relight preview's view transform

  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0x000000);
  const world = new THREE.Group();
  world.rotation.x = Math.PI / 2; // glTF's +Y up -> ntp's +Z up
  const turntable = new THREE.Group(); // turns about ntp's z through the object's centre
  turntable.add(world);
  scene.add(turntable);

  const gltf = await new GLTFLoader().parseAsync(base64Bytes(data.glb).buffer, '');
  world.add(gltf.scene);
  scene.updateMatrixWorld(true);
  const sphere = new THREE.Box3().setFromObject(gltf.scene).getBoundingSphere(new THREE.Sphere());
  // the object's centre on the turntable's axis: turn the world group about it
  turntable.position.copy(sphere.center);
  world.position.sub(sphere.center);
  const radius = Math.max(sphere.radius, 1e-3);

  const camera = new THREE.PerspectiveCamera(30, 1, radius / 100, radius * 100);
  camera.up.set(0, 0, 1);
  camera.position.copy(sphere.center).add(new THREE.Vector3(0, -1, 0.45).normalize().multiplyScalar(VIEW_DISTANCE * radius));
  const controls = new OrbitControls(camera, canvas);
  controls.target.copy(sphere.center);
  controls.update();

  const lightDistance = VIEW_DISTANCE * radius;
  const light = new THREE.PointLight(0xffffff, WHITE_RADIANCE * Math.PI * lightDistance ** 2, 0, 2);
  scene.add(light);
  const ambient = new THREE.HemisphereLight(0xffffff, 0x202020, 0.15); // so the unlit side is not black
  scene.add(ambient);

  const state = { azimuth: 30, elevation: 35, turntable: false, exposure: 0 };
  function placeLight() {
    const az = THREE.MathUtils.degToRad(state.azimuth);
    const el = THREE.MathUtils.degToRad(state.elevation);
    const dir = new THREE.Vector3(Math.cos(el) * Math.sin(az), -Math.cos(el) * Math.cos(az), Math.sin(el));
    light.position.copy(sphere.center).addScaledVector(dir, lightDistance);
  }

  function resize() {
    const w = canvas.clientWidth || 640;
    const h = canvas.clientHeight || 480;
    if (canvas.width !== w || canvas.height !== h) {
      renderer.setSize(w, h, false);
      camera.aspect = w / h;
      camera.updateProjectionMatrix();
    }
  }

  let last = performance.now();
  let paused = false; // while renderLinear holds the scene
  function frame(now) {
    const dt = Math.min((now - last) / 1000, 0.1);
    last = now;
    if (!paused) {
      if (state.turntable) turntable.rotation.z += TURNTABLE_RAD_PER_S * dt;
      resize();
      renderer.toneMappingExposure = 2 ** state.exposure;
      controls.update();
      renderer.render(scene, camera);
    }
    requestAnimationFrame(frame);
  }

  function bind(id, key, parse) {
    const el = document.getElementById(id);
    if (!el) return;
    const read = () => {
      state[key] = parse(el);
      placeLight();
    };
    el.addEventListener('input', read);
    read();
  }
  bind('ntp-light-azimuth', 'azimuth', (el) => Number(el.value));
  bind('ntp-light-elevation', 'elevation', (el) => Number(el.value));
  bind('ntp-exposure', 'exposure', (el) => Number(el.value));
  bind('ntp-turntable', 'turntable', (el) => el.checked);
  placeLight();
  requestAnimationFrame(frame);

  // Shader ablations for the browser check's attribution of a residual: [chunk, from, to] text
  // replacements in three.js' own shader chunks (none in normal use).
  function ablate(patches) {
    const key = JSON.stringify(patches || []);
    gltf.scene.traverse((node) => {
      if (!node.isMesh) return;
      for (const material of Array.isArray(node.material) ? node.material : [node.material]) {
        if (material.userData.ntpAblation === key) continue;
        material.userData.ntpAblation = key;
        material.onBeforeCompile = (shader) => {
          for (const [chunk, from, to] of patches || []) {
            const text = THREE.ShaderChunk[chunk];
            if (!text || !text.includes(from)) throw new Error(`ablation: ${chunk} has no '${from}'`);
            shader.fragmentShader = shader.fragmentShader.replace(`#include <${chunk}>`, text.replace(from, to));
          }
        };
        material.customProgramCacheKey = () => key;
        material.needsUpdate = true;
      }
    });
  }

  // One view as linear RGB floats (no tone mapping, no colour-space conversion, one sample per
  // pixel: the engine's renderer traces one ray through each pixel centre). spec: width, height,
  // fx, fy, cx, cy, pose (OpenCV camera-from-world, 16 numbers row-major, ntp's world frame),
  // light {position [x, y, z] world, intensity [r, g, b]}, optional patches (``ablate``). Returns {width, height, rgba: base64
  // float32, rows top to bottom}.
  function renderLinear(spec) {
    paused = true;
    ablate(spec.patches);
    const view = new THREE.PerspectiveCamera();
    cameraWorld(spec.pose).decompose(view.position, view.quaternion, view.scale);
    view.updateMatrixWorld(true);
    const near = radius / 100;
    const far = radius * 100 + view.position.distanceTo(sphere.center);
    view.projectionMatrix.copy(intrinsicProjection(spec.fx, spec.fy, spec.cx, spec.cy, spec.width, spec.height, near, far));
    view.projectionMatrixInverse.copy(view.projectionMatrix).invert();
    const held = { angle: turntable.rotation.z, ambient: ambient.visible, light: light.visible, tone: renderer.toneMapping };
    turntable.rotation.z = 0;
    ambient.visible = false;
    light.visible = false;
    const probe = new THREE.PointLight(0xffffff, 1, 0, 2);
    const [r, g, b] = spec.light.intensity;
    const peak = Math.max(r, g, b, 1e-30);
    probe.color.setRGB(r / peak, g / peak, b / peak, THREE.LinearSRGBColorSpace);
    probe.intensity = peak;
    probe.position.fromArray(spec.light.position);
    scene.add(probe);
    const target = new THREE.WebGLRenderTarget(spec.width, spec.height, { type: THREE.FloatType, samples: 0 });
    renderer.toneMapping = THREE.NoToneMapping;
    renderer.setRenderTarget(target);
    renderer.render(scene, view);
    const pixels = new Float32Array(spec.width * spec.height * 4);
    renderer.readRenderTargetPixels(target, 0, 0, spec.width, spec.height, pixels);
    renderer.setRenderTarget(null);
    target.dispose();
    scene.remove(probe);
    turntable.rotation.z = held.angle;
    ambient.visible = held.ambient;
    light.visible = held.light;
    renderer.toneMapping = held.tone;
    ablate([]);
    paused = false;
    // GL rows run bottom to top
    const rows = new Float32Array(pixels.length);
    const stride = spec.width * 4;
    for (let y = 0; y < spec.height; y++) rows.set(pixels.subarray((spec.height - 1 - y) * stride, (spec.height - y) * stride), y * stride);
    return { width: spec.width, height: spec.height, rgba: bytesBase64(new Uint8Array(rows.buffer)) };
  }

  return { renderLinear, state, placeLight };
}

window.ntpViewer = { ready: start().then((api) => Object.assign(window.ntpViewer, api)) };
window.ntpViewer.ready.catch((err) => {
  console.error(`ntp viewer: ${err && err.message ? err.message : err}`);
  const note = document.getElementById('ntp-viewer-error');
  if (note) note.textContent = `The 3D view could not start: ${err && err.message ? err.message : err}`;
});
