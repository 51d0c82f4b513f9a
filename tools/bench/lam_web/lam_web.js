// Drives the original LAM web renderer (npm gaussian-splat-renderer-for-lam) one frame at a time, under a given
// camera, background and ARKit weights, with the skeleton frozen at its rest pose (docs/lam-web.md).
// The Python driver (tools/bench/lam_web.py) serves this page, the renderer and the avatar zip on 127.0.0.1.

const RENDERER_URL = new URL('../renderer/gaussian-splat-renderer-for-lam.module.js', import.meta.url).href;
const TIMEOUT_MS = 300000;

// The 52 ARKit blendshape names (Apple's order), the names a motion file and an app's getExpressionData() use.
const ARKIT_NAMES = [
  'browDownLeft', 'browDownRight', 'browInnerUp', 'browOuterUpLeft', 'browOuterUpRight', 'cheekPuff',
  'cheekSquintLeft', 'cheekSquintRight', 'eyeBlinkLeft', 'eyeBlinkRight', 'eyeLookDownLeft', 'eyeLookDownRight',
  'eyeLookInLeft', 'eyeLookInRight', 'eyeLookOutLeft', 'eyeLookOutRight', 'eyeLookUpLeft', 'eyeLookUpRight',
  'eyeSquintLeft', 'eyeSquintRight', 'eyeWideLeft', 'eyeWideRight', 'jawForward', 'jawLeft', 'jawOpen', 'jawRight',
  'mouthClose', 'mouthDimpleLeft', 'mouthDimpleRight', 'mouthFrownLeft', 'mouthFrownRight', 'mouthFunnel',
  'mouthLeft', 'mouthLowerDownLeft', 'mouthLowerDownRight', 'mouthPressLeft', 'mouthPressRight', 'mouthPucker',
  'mouthRight', 'mouthRollLower', 'mouthRollUpper', 'mouthShrugLower', 'mouthShrugUpper', 'mouthSmileLeft',
  'mouthSmileRight', 'mouthStretchLeft', 'mouthStretchRight', 'mouthUpperUpLeft', 'mouthUpperUpRight',
  'noseSneerLeft', 'noseSneerRight', 'tongueOut',
];

const state = {
  renderer: null,      // the GaussianSplatRenderer instance
  step: null,          // its original per-frame function (GaussianSplatRenderer.prototype.render)
  viewer: null,
  restPose: [],        // [object, position, quaternion, scale] of every node under the animation mixer's root
  animationClips: [],  // the clips of animation.glb the renderer made actions for (tests start one)
  defaultCamera: null, // the renderer's own camera as it set it up
  names: [],           // every weight name accepted: ARKit's and the mesh's morph targets
  weights: {},         // what getExpressionData() hands the renderer (a fresh copy per call)
  width: 0,
  height: 0,
};

function sleep(ms) {
  return new Promise((resolve) => setTimeout(resolve, ms));
}

async function until(predicate, what, timeoutMs = TIMEOUT_MS) {
  const start = performance.now();
  while (!predicate()) {
    if (performance.now() - start > timeoutMs) throw new Error(`timed out after ${timeoutMs} ms waiting for ${what}`);
    await sleep(1);
  }
}

function hexColor(rgb) {
  // [r, g, b] in 0..1 -> 0xRRGGBB (the renderer takes an 8-bit sRGB background)
  return rgb.reduce((acc, c) => acc * 256 + Math.round(Math.min(1, Math.max(0, c)) * 255), 0);
}

function restoreRestPose() {
  for (const [object, position, quaternion, scale] of state.restPose) {
    object.position.copy(position);
    object.quaternion.copy(quaternion);
    object.scale.copy(scale);
  }
}

function freezeAnimation() {
  // No chat state (the AnimationManager never starts a clip), every action stopped, mixer time stopped, and every
  // node under the mixer's root back at its rest pose: the skeleton the splats are skinned with is the rest pose.
  const renderer = state.renderer;
  renderer.getChatState = undefined;
  renderer.mixer.stopAllAction();
  renderer.mixer.timeScale = 0;
  restoreRestPose();
}

function restPoseError() {
  let error = 0;
  for (const [object, position, quaternion, scale] of state.restPose) {
    error = Math.max(error, object.position.distanceTo(position), object.scale.distanceTo(scale),
                     1 - Math.abs(object.quaternion.dot(quaternion)));
  }
  return error;
}

function headBoneMatrix() {
  // The skinning matrix (bone.matrixWorld * boneInverse) of the bone the splat shader moves every splat with.
  const index = state.viewer.splatMesh.material.uniforms.headBoneIndex.value;
  const matrices = state.viewer.skinModel.skeleton.boneMatrices;
  return index >= 0 ? Array.from(matrices.slice(16 * index, 16 * index + 16)) : null;
}

function setSize(width, height) {
  if (width === state.width && height === state.height) return;
  const stage = document.getElementById('stage');
  stage.style.width = `${width}px`;
  stage.style.height = `${height}px`;
  state.viewer.renderer.setPixelRatio(1);
  state.viewer.renderer.setSize(width, height);
  state.width = width;
  state.height = height;
}

function snapshotCamera(camera) {
  return {
    position: camera.position.toArray(), quaternion: camera.quaternion.toArray(),
    fov: camera.fov, aspect: camera.aspect, near: camera.near, far: camera.far,
  };
}

function setCamera(spec) {
  // spec: {position, quaternion [x, y, z, w], fov (vertical, degrees), near, far}; null: the renderer's own camera
  const camera = state.viewer.camera;
  const use = spec || state.defaultCamera;
  camera.position.fromArray(use.position);
  camera.quaternion.fromArray(use.quaternion);
  camera.fov = use.fov;
  camera.near = use.near;
  camera.far = use.far;
  camera.aspect = state.width / state.height;
  camera.updateProjectionMatrix();
  camera.updateMatrixWorld(true);
}

function fullWeights(weights) {
  const full = {};
  for (const name of state.names) full[name] = 0.0;
  for (const [name, value] of Object.entries(weights || {})) {
    if (!(name in full)) throw new Error(`unknown blendshape name ${JSON.stringify(name)}`);
    if (typeof value !== 'number' || !Number.isFinite(value)) throw new Error(`weight ${name} is not a number`);
    full[name] = value;
  }
  return full;
}

function step() {
  // One pass of the renderer's own frame function: motionConfig scaling, setExpression, viewer.update (morph and
  // bone textures, a forced full sort), and its draw, which is skipped here: with SwiftShader a draw is most of a
  // frame's time and render() draws once, after the second pass. Its requestAnimationFrame re-arm is cancelled.
  const viewer = state.viewer;
  const draw = viewer.render;
  viewer.render = () => {};
  try {
    state.step.call(state.renderer);
  } finally {
    viewer.render = draw;
    cancelAnimationFrame(viewer.requestFrameId);
  }
}

function base64(bytes) {
  let binary = '';
  const chunk = 0x8000;
  for (let i = 0; i < bytes.length; i += chunk) binary += String.fromCharCode.apply(null, bytes.subarray(i, i + chunk));
  return btoa(binary);
}

async function load({url, width, height, background = [1, 1, 1]}) {
  const t0 = performance.now();
  const { GaussianSplatRenderer } = await import(RENDERER_URL);
  const stage = document.getElementById('stage');
  stage.style.width = `${width}px`;
  stage.style.height = `${height}px`;
  let loaded;
  const loadedPromise = new Promise((resolve) => { loaded = resolve; });
  const renderer = await GaussianSplatRenderer.getInstance(stage, url, {
    getExpressionData: () => ({...state.weights}),
    backgroundColor: '0x' + hexColor(background).toString(16).padStart(6, '0'),
    loadProgress: (p) => { if (p >= 1) loaded(); },
  });
  if (!renderer || !renderer.viewer) throw new Error('GaussianSplatRenderer.getInstance failed (see the console)');
  state.renderer = renderer;
  state.step = GaussianSplatRenderer.prototype.render;
  state.animationClips = renderer.animManager ? renderer.mixer._actions.map((a) => a.getClip()) : [];
  state.viewer = renderer.viewer;
  // The rest pose, taken before the render loop's first mixer update (the loop starts once the splats are built).
  const root = renderer.mixer.getRoot();
  root.traverse((o) => state.restPose.push([o, o.position.clone(), o.quaternion.clone(), o.scale.clone()]));
  const mesh = state.viewer.skinModel;
  state.names = [...new Set([...ARKIT_NAMES, ...Object.keys(mesh.morphTargetDictionary || {})])];
  state.weights = fullWeights({});
  const tInstance = performance.now();
  await Promise.race([loadedPromise, sleep(TIMEOUT_MS).then(() => { throw new Error('avatar load timed out'); })]);
  const tBuilt = performance.now();
  // Stop the renderer's own loop once the splats are drawable and no sort is in flight.
  await until(() => state.viewer.splatRenderReady && !state.viewer.sortRunning, 'the first sort');
  renderer.render = () => {};  // the loop's requestAnimationFrame callback calls this.render(): it ends here
  cancelAnimationFrame(state.viewer.requestFrameId);
  // The scene fades in over a few hundred frames (an update per frame); run those updates without drawing, so
  // frames are taken in the faded-in state the loop reaches (fadeInComplete = 1: no fade term in the shader).
  let fadeSteps = 0;
  while (state.viewer.splatMesh.visibleRegionChanging) {
    if (++fadeSteps > 100000) throw new Error('the scene fade-in does not end');
    state.viewer.splatMesh.updateVisibleRegionFadeDistance(state.viewer.sceneRevealMode);
  }
  const tFaded = performance.now();
  freezeAnimation();
  state.width = width;
  state.height = height;
  state.viewer.renderer.setPixelRatio(1);
  state.viewer.renderer.setSize(width, height);
  state.defaultCamera = snapshotCamera(state.viewer.camera);
  const boneRoot = state.viewer.boneRoot;
  const parents = [];
  for (let o = boneRoot.parent; o; o = o.parent) parents.push({name: o.name, matrix: o.matrix.toArray()});
  return {
    splatCount: state.viewer.splatMesh.getSplatCount(),
    morphTargets: Object.keys(mesh.morphTargetDictionary || {}),
    bones: mesh.skeleton.bones.length,
    defaultCamera: state.defaultCamera,
    boneRootParents: parents,
    splatMeshMatrix: state.viewer.splatMesh.matrixWorld.toArray(),
    useFlame: !!renderer.useFlame,
    seconds: {modelLoad: (tInstance - t0) / 1000, splatBuild: (tBuilt - tInstance) / 1000,
              fadeIn: (tFaded - tBuilt) / 1000, fadeInSteps: fadeSteps},
  };
}

async function render({weights = {}, camera = null, background = [1, 1, 1], width, height}) {
  const t0 = performance.now();
  const viewer = state.viewer;
  setSize(width || state.width, height || state.height);
  viewer.renderer.setClearColor(hexColor(background), 1.0);
  setCamera(camera);
  state.weights = fullWeights(weights);
  freezeAnimation();
  await until(() => !viewer.sortRunning, 'an earlier sort');
  step();  // sets this frame's weights and textures and starts the sort for this camera
  await until(() => !viewer.sortRunning, 'this frame\'s sort');
  step();  // the same state again: the bone texture sees this frame's matrices
  viewer.render();  // draw with the landed order, in this task, so the drawing buffer is intact for readPixels
  const gl = viewer.renderer.getContext();
  if (gl.drawingBufferWidth !== state.width || gl.drawingBufferHeight !== state.height) {
    throw new Error(`drawing buffer is ${gl.drawingBufferWidth}x${gl.drawingBufferHeight}, ` +
                    `not ${state.width}x${state.height}`);
  }
  const pixels = new Uint8Array(state.width * state.height * 4);
  gl.readPixels(0, 0, state.width, state.height, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
  return {
    width: state.width, height: state.height, rgba: base64(pixels),  // bottom row first (GL order)
    restPoseError: restPoseError(),
    headBoneMatrix: headBoneMatrix(),
    bsWeight: {...viewer.splatMesh.bsWeight},
    camera: snapshotCamera(viewer.camera),
    ms: performance.now() - t0,
  };
}

window.gtLamWeb = { load, render, ARKIT_NAMES, ready: true, state };
