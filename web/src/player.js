// The browser player's public API: a bundle in, frames out, the stages of the Python runtime's TalkingHead
// (docs/web.md):
//
//   const player = await Player.load(bytes, { name: 'speaker.gtb', width: 512, height: 512 });
//   const drive = await player.driveFromAudioFile(wavBytes);      // or driveFromMotion(file), driveFromAudio(...)
//   const stream = await player.openAudioStream();                // or audio pushed as it arrives:
//   await stream.push(samples); ... await stream.end();          //   stream.drive() holds the frames ready
//   const frame = await player.renderFrame(drive, 0);             // {pixels: Uint8Array RGB, width, height, timings}
//   await player.renderToCanvas(drive, 0, canvas);                 // the same frame drawn on a 2D canvas
//   player.release();
//
// Per frame: the deform graph (onnxruntime-web) -> pack, cull, depth sort and draw runs in a Worker
// (sort_worker.js) -> WebGL2 splatting (splat.js) -> read back. What is not done yet: docs/web.md.

import { BundleError, readBundle } from './bundle.js';
import { Camera, drawnSize } from './camera.js';
import {
  AudioError, blendshapeParams, decodeAudio, Drive, DriveError, flameParams, motionAtFps, readMotion, parseMotion,
  resampleAudio, roundHalfEven, trackRow, translateAudio,
} from './drive.js';
import { flameMotionAtFps, flameMotionFromTable, parseFlameMotion, readFlameMotion, withExpressions } from './flame_motion.js';
import { ARKIT_BLENDSHAPES, FEATURES_PER_FRAME, TABLE_POSE_COLUMNS } from './generated.js';
import { GraphBackendError, GraphSessions } from './graphs.js';
import { compositeFrame } from './composite.js';
import { ReferenceClip } from './reference.js';
import { RenderError, WebGLSplatter } from './splat.js';
import { AudioStream } from './stream.js';

export { AudioError, BundleError, Camera, DriveError, GraphBackendError, RenderError };

const firstBytes = (bytes) => (bytes instanceof ArrayBuffer ? new Uint8Array(bytes, 0, Math.min(bytes.byteLength, 4))
  : bytes instanceof Uint8Array ? bytes.subarray(0, 4) : new Uint8Array(0));

/** Whether a motion's bytes are a zip (an npz). */
const isZip = (bytes) => { const b = firstBytes(bytes); return b[0] === 0x50 && b[1] === 0x4b; };

/** Whether a motion's bytes start as a JSON object (after a UTF-8 byte order mark or whitespace). */
const isJson = (bytes) => /^(\ufeff|\s)*\{/.test(new TextDecoder().decode(firstBytes(bytes)));

/** The rig and timing of a bundle: FLAME speaker ('speaker') or ARKit speaker ('rig'). */
function rigOf(bundle) {
  const m = bundle.manifest;
  if (m.rig !== undefined) {
    const rig = m.rig;
    const names = rig?.blendshapes ?? ARKIT_BLENDSHAPES;
    if (!(rig && rig.kind === 'arkit' && Array.isArray(names) && Number.isInteger(rig.fps) && rig.fps > 0
          && Number.isInteger(rig.sample_rate) && rig.sample_rate > 0)) {
      throw new BundleError(`${bundle.name}: manifest has no valid rig`);
    }
    const sameOrder = names.length === ARKIT_BLENDSHAPES.length && names.every((n, i) => n === ARKIT_BLENDSHAPES[i]);
    return { kind: 'arkit', fps: rig.fps, sampleRate: rig.sample_rate, samplesPerFrame: rig.sample_rate / rig.fps,
      names: sameOrder ? ARKIT_BLENDSHAPES : names };
  }
  const speaker = m.speaker;
  const strides = speaker?.translator?.conv_strides ?? [5, 2, 2, 2, 2, 2, 2];
  const samplesPerFrame = strides.reduce((a, b) => a * b, 1) * FEATURES_PER_FRAME;
  if (!(speaker && Number.isInteger(speaker.fps) && Number.isInteger(speaker.sample_rate)
        && Number.isInteger(speaker.n_expr))) {
    throw new BundleError(`${bundle.name}: manifest has no valid speaker config`);
  }
  if (speaker.sample_rate !== samplesPerFrame * speaker.fps) {
    throw new BundleError(`${bundle.name}: manifest has no valid speaker config: sample_rate ${speaker.sample_rate} `
      + `must be ${samplesPerFrame} x fps ${speaker.fps}`);
  }
  return { kind: 'flame', fps: speaker.fps, sampleRate: speaker.sample_rate, samplesPerFrame, nExpr: speaker.n_expr };
}

/** The bundle's runtime_defaults as the player uses them (sdk/render_settings.py names and defaults). */
function renderSettings(bundle, overrides) {
  const d = { render_scale: 1.0, render_target: 'float32', sort_interval: 1, sort_key_bits: 32, max_draw_pixels: null,
    ...(bundle.manifest.runtime_defaults ?? {}), ...overrides };
  if (!(d.render_scale >= 0.1 && d.render_scale <= 1) || !['float32', 'float16', 'uint8'].includes(d.render_target)
      || ![16, 32].includes(d.sort_key_bits) || !(Number.isInteger(d.sort_interval) && d.sort_interval >= 1
      && d.sort_interval <= 60) || !(d.max_draw_pixels === null
      || (Number.isInteger(d.max_draw_pixels) && d.max_draw_pixels >= 1))) {
    throw new BundleError(`${bundle.name}: manifest 'runtime_defaults' is invalid: ${JSON.stringify(d).slice(0, 200)}`);
  }
  return d;
}

/** Depth sorts on a module Worker, one frame at a time. */
class SortWorker {
  constructor() {
    this.worker = new Worker(new URL('./sort_worker.js', import.meta.url), { type: 'module' });
    this.pending = new Map();
    this.next = 0;
    this.worker.onmessage = ({ data }) => {
      const { resolve, reject } = this.pending.get(data.id);
      this.pending.delete(data.id);
      if (data.error) reject(new RenderError(`depth sort failed: ${data.error}`));
      else resolve(data);
    };
    this.worker.onerror = (event) => {
      for (const { reject } of this.pending.values()) reject(new RenderError(`the sort worker failed: ${event.message}`));
      this.pending.clear();
    };
  }

  prepare(gaussians, camera, maxPointSize, keyBits, interval) {
    const id = this.next++;
    const plain = { R: camera.R, t: camera.t, fx: camera.fx, fy: camera.fy, width: camera.width, height: camera.height,
      near: camera.near };
    const transfer = Object.values(gaussians).map((a) => a.buffer);
    return new Promise((resolve, reject) => {
      this.pending.set(id, { resolve, reject });
      this.worker.postMessage({ id, gaussians, camera: plain, limits: camera.fovClampLimits(), maxPointSize, keyBits,
        interval }, transfer);
    });
  }

  terminate() {
    this.worker.terminate();
  }
}

/** The reference clip a player composites into (null: the bare head), per Player.load's `composite` option. */
async function openReference(bundle, graphs, poseTrack, options) {
  const hasClip = bundle.manifest.reference !== undefined && bundle.manifest.reference !== null;
  const composite = options.composite ?? (hasClip && graphs.has('inpaint'));
  if (!composite) return null;
  if (!hasClip) {
    throw new RenderError(`${bundle.name}: composite: true needs a bundle with a reference clip (docs/compositing.md)`);
  }
  if (!graphs.has('inpaint')) {
    throw new RenderError(`${bundle.name}: this bundle composites with the OpenCV fallback (it has no inpainting `
      + 'graph), which the page lacks: composite: false plays the bare head');
  }
  if (options.camera !== undefined) {
    throw new RenderError("a composited frame is seen through the reference clip's camera; pass composite: false "
      + 'to draw the bare head through your own camera');
  }
  const clipCamera = bundle.manifest.reference.camera ?? {};
  const size = options.width !== undefined || options.height !== undefined
    ? [options.width ?? clipCamera.width, options.height ?? clipCamera.height] : null;
  const reference = await ReferenceClip.open(bundle, size);
  if (!poseTrack || poseTrack.rows !== reference.count) {
    throw new BundleError(`${bundle.name}: the reference clip has ${reference.count} frames but the pose track has `
      + `${poseTrack ? poseTrack.rows : 0} rows`);
  }
  return reference;
}

export class Player {
  constructor(fields) {
    Object.assign(this, fields);
  }

  /**
   * Load a bundle (ArrayBuffer, Uint8Array, or a URL to fetch) and make it ready to draw. Options: `name` (labels
   * errors), `width`/`height` (the output size; the bundle camera is resized to it), `camera` (a Camera or its
   * dict, replacing the bundle's), `background` ([r, g, b]), `renderTarget`/`renderScale`/`sortKeyBits`/
   * `sortInterval` (override the bundle's runtime_defaults, docs/precision.md), `pointSprites` (false: quads only),
   * `canvas` (the WebGL2 canvas; default an OffscreenCanvas), `composite` (a bundle with a reference clip and an
   * inpainting graph draws audio's frames into the clip by default, as the Python runtime does: docs/compositing.md;
   * false: the bare head), and the graph options of GraphSessions.open (`graphs`: 'auto', 'wasm' or 'webgpu';
   * `threads`; or `ort` with `executionProviders`).
   */
  static async load(source, options = {}) {
    const timings = {};
    let start = performance.now();
    let bytes = source;
    let name = options.name;
    if (typeof source === 'string' || source instanceof URL) {
      const response = await fetch(source);
      if (!response.ok) throw new BundleError(`${source}: cannot fetch the bundle (HTTP ${response.status})`);
      bytes = await response.arrayBuffer();
      name = name ?? String(source).split('/').pop();
    }
    const bundle = await readBundle(bytes, { name: name ?? 'bundle' });
    timings.read = (performance.now() - start) / 1000;
    const rig = rigOf(bundle);
    start = performance.now();
    const graphs = await GraphSessions.open(bundle, options);
    timings.graphs = (performance.now() - start) / 1000;
    if (!graphs.has('deform')) throw new BundleError(`${bundle.name}: bundle lacks the 'deform' graph`);
    const track = (bufferName) => {
      if (!bundle.hasBuffer(bufferName)) return null;
      const { dtype, shape, data } = bundle.buffer(bufferName);
      if (dtype !== 'float32' || shape.length !== 2 || shape[0] < 1) {
        throw new BundleError(`${bundle.name}: buffer '${bufferName}' is ${dtype} [${shape.join(', ')}], expected float32 [T >= 1, D]`);
      }
      return { data, rows: shape[0], width: shape[1] };
    };
    const poseTrack = track('pose_track');
    if (poseTrack && poseTrack.width !== 6) throw new BundleError(`${bundle.name}: buffer 'pose_track' is not [T, 6]`);
    const settings = renderSettings(bundle, Object.fromEntries(Object.entries({
      render_target: options.renderTarget, render_scale: options.renderScale, sort_key_bits: options.sortKeyBits,
      sort_interval: options.sortInterval,
    }).filter(([, v]) => v !== undefined)));
    const background = options.background ?? bundle.manifest.background ?? [1, 1, 1];
    if (!(Array.isArray(background) && background.length === 3 && background.every(Number.isFinite))) {
      throw new BundleError(`${bundle.name}: manifest 'background' must be 3 finite numbers (RGB)`);
    }
    const splatter = new WebGLSplatter({ canvas: options.canvas ?? null, renderTarget: settings.render_target,
      pointSprites: options.pointSprites ?? true });
    start = performance.now();
    const reference = await openReference(bundle, graphs, poseTrack, options);
    if (reference) timings.reference = (performance.now() - start) / 1000;
    const player = new Player({ bundle, rig, graphs, poseTrack, motionTrack: track('motion_track'), settings,
      background, splatter, sorter: new SortWorker(), reference, loadTimings: timings, lastTimings: null });
    if (reference) player.setCamera(reference.outputCamera);
    else player.setCamera(options.camera ?? Camera.fromDict(bundle.manifest.camera), options.width, options.height);
    return player;
  }

  get fps() { return this.rig.fps; }

  /** Whether audio's frames are composited into the bundle's reference clip (Player.load's `composite`). */
  get composited() { return this.reference !== null; }

  get sampleRate() { return this.rig.sampleRate; }

  /** [width, height] of this player's frames. */
  get frameSize() { return [this.camera.width, this.camera.height]; }

  /** Draw through `camera` (a Camera or its dict), resized to width x height when given. */
  setCamera(camera, width, height) {
    let c = camera instanceof Camera ? camera : Camera.fromDict(camera);
    if (width !== undefined || height !== undefined) c = c.resized(width ?? c.width, height ?? c.height);
    this.camera = c;
  }

  /** The head's centre [3]: the median of its rest-pose Gaussians (the point the Python runtime's
   * `orbited_camera` swings about); orbit with `player.setCamera(player.camera.orbited(yaw, pitch, centre))`. */
  async headCentre() {
    const names = this.rig.names ?? ARKIT_BLENDSHAPES;
    const width = this.rig.kind === 'flame' ? this.rig.nExpr + 3 : names.length;
    const rest = new Drive({ rig: this.rig.kind, rows: new Float32Array(width), width, frames: 1, rigNames: names });
    const { data } = (await this.graphs.run('deform', rest.graphInputs(0, this.camera.center()))).means;
    const centre = [0, 1, 2].map((axis) => {
      const values = [];
      for (let i = 0; i + 2 < data.length; i += 3) {
        if (Number.isFinite(data[i]) && Number.isFinite(data[i + 1]) && Number.isFinite(data[i + 2])) {
          values.push(data[i + axis]);
        }
      }
      values.sort((a, b) => a - b);
      const mid = values.length >> 1;
      return values.length % 2 ? values[mid] : (values[mid - 1] + values[mid]) / 2;
    });
    if (!centre.every(Number.isFinite)) throw new RenderError('the rest pose has no finite Gaussian to orbit about');
    return centre;
  }

  /** The drive of an audio clip: mono float32 `samples` at `sampleRate` (resampled to the speaker's rate). */
  async driveFromAudio(samples, sampleRate) {
    const audio = await resampleAudio(samples, sampleRate, this.sampleRate);
    return this._translate(audio);
  }

  /** The drive of an encoded audio file (WAV, MP3, ...: what the browser decodes), at the speaker's rate. */
  async driveFromAudioFile(bytes) {
    return this._translate(await decodeAudio(bytes, this.sampleRate));
  }

  async _translate(audio) {
    if (!this.graphs.has('translator')) {
      throw new DriveError(`${this.bundle.name}: this bundle has no translator graph (an avatar without an audio `
        + 'model), so it cannot turn audio into frames: drive it with a motion');
    }
    const start = performance.now();
    const run = (chunk) => this.graphs.run('translator', { audio: { data: chunk, dims: [1, chunk.length] } });
    const paramsOf = this.rig.kind === 'arkit' ? blendshapeParams : flameParams;
    const { rows, width, frames } = await translateAudio(run, audio, this.rig.samplesPerFrame, { paramsOf });
    this.translateSeconds = (performance.now() - start) / 1000;
    return this._drive(rows, width, frames, true);
  }

  /**
   * Audio pushed as it arrives, through the bundle's streaming translator (docs/web.md, "Streaming audio"):
   * `await stream.push(samples)` (mono float32 at `player.sampleRate`) and `await stream.end()` return the frames
   * ready; `stream.drive()` is their drive. A DriveError for a bundle without a streaming graph.
   */
  async openAudioStream() {
    const rowsOf = this.rig.kind === 'flame' ? (out) => flameParams(out, out.expression.dims[1])
      : (out) => ({ rows: out.blendshapes.data, width: out.blendshapes.dims[2] });
    return AudioStream.open(this.graphs, this.bundle, { rowsOf, rigSamplesPerFrame: this.rig.samplesPerFrame,
      makeDrive: (rows, width, frames) => this._drive(rows, width, frames, true) });
  }

  /**
   * The drive of a motion: for an ARKit speaker a motion file (LAM's JSON: text or bytes) or its parsed JSON; for a
   * FLAME speaker a FLAME motion npz (GaussianAvatars' flame_param.npz keys; bytes, at the speaker's fps, the head
   * following the motion's own pose) or its arrays ({expr, rotation, neck_pose, jaw_pose, eyes_pose, translation}:
   * rows of numbers). null: the bundle's own motion track.
   */
  driveFromMotion(motion = null, where = 'motion file') {
    if (this.rig.kind === 'flame') return this._flameMotionDrive(motion, where);
    let parsed;
    if (motion === null) {
      if (!this.motionTrack) throw new DriveError(`${this.bundle.name}: the avatar ships no motion track; give a motion file`);
      parsed = { weights: Float32Array.from(this.motionTrack.data), frames: this.motionTrack.rows, fps: this.fps };
      if (this.motionTrack.width !== ARKIT_BLENDSHAPES.length) throw new DriveError('motion_track is not [T, 52]');
    } else if (typeof motion === 'string' || motion instanceof Uint8Array || motion instanceof ArrayBuffer) {
      if (isZip(motion)) {
        throw new DriveError(`${where}: an npz motion holds FLAME parameters; this ARKit speaker takes ARKit weights `
          + "(LAM's JSON motion files)");
      }
      parsed = readMotion(motion instanceof ArrayBuffer ? new Uint8Array(motion) : motion, where);
    } else {
      parsed = parseMotion(motion, where);
    }
    const { weights, frames } = motionAtFps(parsed, this.fps);
    return this._drive(weights, ARKIT_BLENDSHAPES.length, frames);
  }

  _flameMotionDrive(motion, where) {
    let parsed;
    if (motion === null) {
      if (!this.motionTrack) {
        throw new DriveError(`${this.bundle.name}: the speaker ships no motion track; give a FLAME motion npz `
          + "(GaussianAvatars' flame_param.npz keys)");
      }
      const { data, rows, width } = this.motionTrack;
      parsed = flameMotionFromTable(data, rows, width, this.fps);
    } else if (typeof motion === 'string' || isJson(motion)) {
      throw new DriveError(`${where}: a JSON motion holds ARKit weights; this FLAME speaker takes a FLAME motion npz `
        + "(GaussianAvatars' flame_param.npz keys)");
    } else if (motion instanceof Uint8Array || motion instanceof ArrayBuffer) {
      parsed = readFlameMotion(motion, this.fps, where);
    } else {
      parsed = parseFlameMotion(motion, this.fps, where);
    }
    const { table, frames, nExpr } = flameMotionAtFps(withExpressions(parsed, this.rig.nExpr), this.fps);
    return new Drive({ rig: 'flame', rows: table, width: nExpr + TABLE_POSE_COLUMNS, frames, flameMotion: true });
  }

  /** The drive of ARKit weights given directly: `weights` [frames * 52] in ARKIT_BLENDSHAPES order (an array, or
   * a list of 52-value rows) at `fps` (default the speaker's), resampled to the speaker's fps. */
  driveFromWeights(weights, fps = this.fps) {
    const rows = Array.isArray(weights) && Array.isArray(weights[0]) ? weights : null;
    const frames = rows ? rows.map((w) => ({ weights: w })) : [];
    if (!rows) {
      const flat = Array.from(weights);
      if (flat.length === 0 || flat.length % ARKIT_BLENDSHAPES.length) {
        throw new DriveError(`weights must be frames x ${ARKIT_BLENDSHAPES.length} ARKit values, got ${flat.length}`);
      }
      for (let i = 0; i < flat.length; i += ARKIT_BLENDSHAPES.length) {
        frames.push({ weights: flat.slice(i, i + ARKIT_BLENDSHAPES.length) });
      }
    }
    return this.driveFromMotion({ names: ARKIT_BLENDSHAPES, metadata: { fps }, frames }, 'weights');
  }

  /** A drive on the bundle's pose track; `fromAudio`: frame i sees the reference clip's picture at i. */
  _drive(rows, width, frames, fromAudio = false) {
    const drive = new Drive({ rig: this.rig.kind, rows, width, frames, poseTrack: this.poseTrack?.data ?? null,
      rigNames: this.rig.names ?? ARKIT_BLENDSHAPES });
    drive.followsClip = fromAudio;
    return drive;
  }

  /** Frame `index` of `drive` -> {pixels, width, height, timings} (`output` as WebGLSplatter.draw: 'uint8' RGB
   * top row first, 'float', 'rgba_float'). timings: graphs, sort, upload, draw, readback in seconds. */
  async renderFrame(drive, index, { output = 'uint8' } = {}) {
    if (this.reference && drive.followsClip) {
      if (output !== 'uint8') {
        throw new RenderError(`composited frames are uint8 RGB; output '${output}' needs the bare head: `
          + 'Player.load(..., { composite: false })');
      }
      return this._compositedFrame(drive, index);
    }
    return this._headFrame(drive, index, output);
  }

  /** Frame `index` of an audio drive composited into the reference clip's picture at that frame (the clip played
   * forth and back, as the pose track): the head's premultiplied render, the picture, its mask and F. */
  async _compositedFrame(drive, index) {
    const head = await this._headFrame(drive, index, 'rgba_float');
    let start = performance.now();
    const row = trackRow(this.reference.count, index);
    const [picture, mask] = await Promise.all([this.reference.frame(row), this.reference.mask(row)]);
    const timings = { ...head.timings, reference: (performance.now() - start) / 1000 };
    start = performance.now();
    const { width, height } = head;
    const inpaint = async ({ image, mask: masks, coverage }, h, w) => (await this.graphs.run('inpaint', {
      image: { data: image, dims: [1, 3, h, w] }, mask: { data: masks, dims: [1, 1, h, w] },
      coverage: { data: coverage, dims: [1, 1, h, w] } })).inpainted.data;
    const pixels = await compositeFrame(head.pixels, picture, mask, width, height, inpaint);
    timings.composite = (performance.now() - start) / 1000;
    this.lastTimings = timings;
    return { pixels, width, height, timings, splats: head.splats };
  }

  async _headFrame(drive, index, output) {
    const timings = {};
    let start = performance.now();
    const out = await this.graphs.run('deform', drive.graphInputs(index, this.camera.center()));
    timings.graphs = (performance.now() - start) / 1000;
    const [width, height] = this.frameSize;
    const drawSize = drawnSize(this.settings, width, height);
    const camera = drawSize[0] === width && drawSize[1] === height ? this.camera : this.camera.resized(...drawSize);
    start = performance.now();
    // Copies the worker may own (onnxruntime-web's output tensors are views into its wasm memory).
    const gaussians = { means: out.means.data.slice(), cov3d: out.cov3d.data.slice(), rgb: out.rgb.data.slice(),
      opacity: out.opacity.data.slice() };
    const prepared = await this.sorter.prepare(gaussians, camera, this.splatter.maxPointSize,
      this.settings.sort_key_bits, this.settings.sort_interval);
    timings.sort = (performance.now() - start) / 1000;
    const frame = await this.splatter.draw(prepared, camera, this.background, { output, outputSize: [width, height] });
    Object.assign(timings, frame.timings);
    this.lastTimings = timings;
    return { ...frame, timings, splats: prepared.rows.length / 13 };
  }

  /** Frame `index` of `drive` drawn on a 2D `canvas` (resized to the frame). */
  async renderToCanvas(drive, index, canvas) {
    const frame = await this.renderFrame(drive, index);
    const rgba = new Uint8ClampedArray(frame.width * frame.height * 4);
    for (let i = 0, j = 0; j < frame.pixels.length; i += 4, j += 3) {
      rgba[i] = frame.pixels[j];
      rgba[i + 1] = frame.pixels[j + 1];
      rgba[i + 2] = frame.pixels[j + 2];
      rgba[i + 3] = 255;
    }
    canvas.width = frame.width;
    canvas.height = frame.height;
    canvas.getContext('2d').putImageData(new ImageData(rgba, frame.width, frame.height), 0, 0);
    return frame;
  }

  release() {
    this.sorter.terminate();
    this.splatter.release();
    return this.graphs.release();
  }
}
