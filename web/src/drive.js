// Audio or a motion -> one drive per video frame (docs/porting.md, sections 2 and 3.1).
//
// Audio: decoded and resampled to the translator's rate by the browser (OfflineAudioContext), mono by averaging
// channels, then run through the translator in the windows of runtime/translate.py (`iter_translate`): 10 s
// windows with 1 s of context each side, a silence gate per window, 20-frame cross-fades at the joins. The
// arithmetic that shapes values (gain, cross-fade) is float32 as in numpy; the browser's resampler is not libsoxr's,
// so audio at another rate than the speaker's agrees with the Python runtime only within the translator's
// tolerance (a file already at the speaker's rate decodes to the same samples).
// Motions: an ARKit motion file (LAM's JSON kinds, sdk/motion.py) or weights, resampled to the speaker's fps.
// Head pose: the bundle's pose track played forth and back (sdk/drive.py `track_row`).

import {
  ARKIT_BLENDSHAPES, CONTEXT_FRAMES, CROSSFADE_FRAMES, DEFAULT_MOTION_FPS, MAX_DRIVE_MAGNITUDE, MAX_MOTION_FILE_BYTES,
  MAX_MOTION_FRAMES, MAX_SAMPLE_MAGNITUDE, SILENCE_GATE_DBFS, SILENCE_GATE_RAMP_DB, TABLE_POSE_COLUMNS, WINDOW_FRAMES,
} from './generated.js';
import { MAX_JSON_DEPTH, nestsDeeperThan } from './bundle.js';

export class DriveError extends Error {
  constructor(message) {
    super(message);
    this.name = 'DriveError';
  }
}

export class AudioError extends Error {
  constructor(message) {
    super(message);
    this.name = 'AudioError';
  }
}

const f32 = Math.fround;

/** Python's round(): halves to even. */
export function roundHalfEven(x) {
  const r = Math.round(x);
  return Math.abs(x % 1) === 0.5 && r % 2 !== 0 ? r - 1 : r;
}

// -- audio ---------------------------------------------------------------------------------------------------

/** Mono float32 samples of an AudioBuffer (channels averaged). */
function mono(buffer) {
  const out = new Float32Array(buffer.length);
  for (let c = 0; c < buffer.numberOfChannels; c++) {
    const data = buffer.getChannelData(c);
    for (let i = 0; i < out.length; i++) out[i] += data[i];
  }
  if (buffer.numberOfChannels > 1) for (let i = 0; i < out.length; i++) out[i] = f32(out[i] / buffer.numberOfChannels);
  return out;
}

/** An encoded audio file (WAV, MP3, ... whatever the browser decodes) -> mono float32 at `rate`. */
export async function decodeAudio(bytes, rate) {
  const context = new OfflineAudioContext(1, 1, rate);
  let buffer;
  try {
    buffer = await context.decodeAudioData(bytes instanceof ArrayBuffer ? bytes.slice(0) : bytes.slice().buffer);
  } catch (error) {
    throw new AudioError(`the audio cannot be decoded (${error?.message ?? error})`);
  }
  const samples = mono(buffer);
  if (!samples.length) throw new AudioError('the audio holds no samples');
  return samples;
}

/** Mono samples at `fromRate` -> `toRate` (round(S * toRate / fromRate) samples), by the browser's resampler. */
export async function resampleAudio(samples, fromRate, toRate) {
  checkSamples(samples);
  if (fromRate === toRate) return Float32Array.from(samples);
  if (!(Number.isInteger(fromRate) && fromRate >= 3000 && fromRate <= 768000)) {
    throw new AudioError(`sample rate ${fromRate} Hz is not one the browser resamples (3000..768000 Hz)`);
  }
  if (!samples.length) throw new AudioError('audio is empty (0 samples)');
  const length = Math.max(1, roundHalfEven(samples.length * toRate / fromRate));
  const context = new OfflineAudioContext(1, length, toRate);
  const source = context.createBufferSource();
  const buffer = context.createBuffer(1, samples.length, fromRate);
  buffer.copyToChannel(Float32Array.from(samples), 0);
  source.buffer = buffer;
  source.connect(context.destination);
  source.start();
  return mono(await context.startRendering());
}

/** Samples must be finite and within 2^31 (sdk/audio.py). */
export function checkSamples(samples) {
  for (let i = 0; i < samples.length; i++) {
    if (!(Math.abs(samples[i]) <= MAX_SAMPLE_MAGNITUDE)) {
      throw new AudioError(`audio sample ${i} is ${samples[i]}: samples must be finite and within ${MAX_SAMPLE_MAGNITUDE}`);
    }
  }
}

// -- translator windows (runtime/translate.py) ---------------------------------------------------------------

/** Gain in [0, 1] of a window's outputs: 1 at or above the gate, 0 at gate - ramp and below. */
export function silenceGain(chunk, gateDbfs = SILENCE_GATE_DBFS, rampDb = SILENCE_GATE_RAMP_DB) {
  if (gateDbfs === null) return 1.0;
  let mean = 0;
  for (const v of chunk) mean += v;
  mean /= chunk.length;
  let power = 0;
  for (const v of chunk) power += (v - mean) * (v - mean);
  const levelDb = 10.0 * Math.log10(power / chunk.length + 1e-30);
  return Math.min(1, Math.max(0, (levelDb - gateDbfs) / rampDb + 1.0));
}

/** [T, D] rows -> [rows, D], linear in time over the same span, frame centres aligned (`resample_rows`). */
export function resampleRows(values, count, width, rows) {
  if (count === rows) return values;
  const out = new Float32Array(rows * width);
  for (let r = 0; r < rows; r++) {
    if (count === 1) {
      out.set(values.subarray(0, width), r * width);
      continue;
    }
    const x = ((r + 0.5) / rows) * count - 0.5; // position among the source frame centres
    const i = Math.min(Math.max(Math.floor(x), 0), count - 2);
    const w = Math.min(Math.max(x - i, 0), 1);
    for (let k = 0; k < width; k++) out[r * width + k] = f32(values[i * width + k] * (1 - w) + values[(i + 1) * width + k] * w);
  }
  return out;
}

/** A FLAME translator's window outputs -> rows [frames, n_expr + 3] (expression then jaw). */
export function flameParams(out, frames) {
  const n = out.expression.dims[2];
  const rows = new Float32Array(frames * (n + 3));
  for (let f = 0; f < frames; f++) {
    rows.set(out.expression.data.subarray(f * n, (f + 1) * n), f * (n + 3));
    rows.set(out.jaw_pose.data.subarray(f * 3, (f + 1) * 3), f * (n + 3) + n);
  }
  return { rows, width: n + 3 };
}

/** An audio-to-ARKit model's window outputs -> rows [frames, K], resampled when its T is not the window's. */
export function blendshapeParams(out, frames) {
  const { data, dims } = out.blendshapes;
  if (dims.length !== 3 || dims[0] !== 1 || dims[1] < 1) {
    throw new AudioError(`the audio model returned blendshapes of shape [${dims.join(', ')}], expected [1, T >= 1, K]`);
  }
  return { rows: resampleRows(data, dims[1], dims[2], frames), width: dims[2] };
}

/**
 * Translate a whole clip: `run(chunk)` runs the translator on one window's float32 samples and returns its
 * outputs; `paramsOf(outputs, frames)` -> {rows, width}. Returns {rows: Float32Array [T * width], width, frames}.
 */
export async function translateAudio(run, audio, samplesPerFrame, { paramsOf = flameParams,
  gateDbfs = SILENCE_GATE_DBFS, windowFrames = WINDOW_FRAMES, contextFrames = CONTEXT_FRAMES,
  crossfadeFrames = CROSSFADE_FRAMES } = {}) {
  const total = Math.ceil(audio.length / samplesPerFrame - 1e-9);
  if (total === 0) throw new AudioError('audio is empty (0 samples)');
  const half = crossfadeFrames >> 1;
  const frameStart = (index) => roundHalfEven(index * samplesPerFrame);
  let out = null;
  let width = 0;
  let previous = null;
  let emitted = 0;
  let lastStop = 0;
  const copyRows = (params, lo, from, to) => {
    out.set(params.subarray((from - lo) * width, (to - lo) * width), from * width);
  };
  for (let start = 0; start < total; start += windowFrames) {
    const stop = Math.min(start + windowFrames, total);
    const lo = Math.max(0, start - contextFrames);
    const hi = Math.min(total, start + windowFrames + contextFrames);
    const a = frameStart(lo);
    const b = frameStart(hi);
    const chunk = new Float32Array(b - a); // the clip's last partial frame: zero-padded
    chunk.set(audio.subarray(a, Math.min(b, audio.length)));
    const result = paramsOf(await run(chunk), hi - lo);
    const gain = f32(silenceGain(chunk, gateDbfs));
    const params = result.rows.map((v) => f32(v * gain));
    if (out === null) {
      width = result.width;
      out = new Float32Array(total * width);
    }
    if (previous !== null) {
      const [prevParams, prevLo] = previous;
      copyRows(prevParams, prevLo, emitted, start - half);
      for (let f = start - half; f < Math.min(start + half, total); f++) {
        const w = f32((f - (start - half) + 0.5) / (2 * half));
        for (let k = 0; k < width; k++) {
          const left = prevParams[(f - prevLo) * width + k];
          const right = params[(f - lo) * width + k];
          out[f * width + k] = f32(f32(f32(1 - w) * left) + f32(w * right));
        }
      }
      emitted = Math.min(start + half, total);
    }
    previous = [params, lo];
    lastStop = stop;
  }
  if (emitted < lastStop) copyRows(previous[0], previous[1], emitted, lastStop);
  return { rows: out, width, frames: total };
}

// -- motions (sdk/motion.py) ---------------------------------------------------------------------------------

const isNumber = (v) => typeof v === 'number' && Number.isFinite(v);

function frameWeights(frame, names, index, where) {
  let weights = frame;
  if (frame !== null && typeof frame === 'object' && !Array.isArray(frame)) {
    if (!('weights' in frame)) return names.map((name) => (Object.hasOwn(frame, name) ? frame[name] : 0.0));
    weights = frame.weights;
  }
  if (!Array.isArray(weights) || weights.length !== names.length) {
    throw new DriveError(`${where}: frame ${index} has ${Array.isArray(weights) ? weights.length : 'no'} weights `
      + `but the file names ${names.length} blendshapes`);
  }
  return weights;
}

function frameRate(data, frames) {
  const fps = data.metadata !== null && typeof data.metadata === 'object' ? data.metadata.fps : undefined;
  if (isNumber(fps) && fps > 0) return fps;
  const times = frames.map((f) => (f !== null && typeof f === 'object' ? f.time : undefined));
  if (times.length >= 2 && times.every(isNumber)) {
    const steps = times.slice(1).map((t, i) => t - times[i]).sort((x, y) => x - y);
    const m = steps.length;
    const step = m % 2 ? steps[(m - 1) / 2] : (steps[m / 2 - 1] + steps[m / 2]) / 2;
    if (step > 0 && Number.isFinite(1.0 / step)) return 1.0 / step;
  }
  return DEFAULT_MOTION_FPS;
}

/** Rows [T, D] at `fps` -> `newFps` over the same duration (`resample_at_fps`): linear in time, the last row held. */
export function resampleAtFps(rows, count, width, fps, newFps) {
  const wanted = count * newFps / fps;
  if (!(wanted <= MAX_MOTION_FRAMES)) {
    throw new DriveError(`a motion of ${count} frames at ${fps} fps would be ${wanted.toPrecision(4)} frames at `
      + `${newFps} fps, over the ${MAX_MOTION_FRAMES} frame limit`);
  }
  const n = Math.max(1, roundHalfEven(wanted));
  const out = new Float64Array(n * width);
  const last = (count - 1) / fps;
  for (let r = 0; r < n; r++) {
    const time = Math.min(r / newFps, last);
    const x = time * fps;
    const i = Math.min(Math.floor(x), Math.max(count - 2, 0));
    const w = count > 1 ? x - i : 0;
    for (let k = 0; k < width; k++) {
      const a = rows[i * width + k];
      const b = count > 1 ? rows[(i + 1) * width + k] : a;
      out[r * width + k] = a + (b - a) * w;
    }
  }
  return { rows: out, frames: n };
}

/** A parsed ARKit motion file -> {weights: Float32Array [T * 52] in ARKIT_BLENDSHAPES order, frames, fps}. */
export function parseMotion(data, where = 'motion') {
  if (data === null || typeof data !== 'object' || !Array.isArray(data.frames)) {
    throw new DriveError(`${where}: an ARKit motion file is a JSON object with a 'frames' list`);
  }
  const frames = data.frames;
  if (!frames.length) throw new DriveError(`${where}: 'frames' is empty`);
  const metadata = data.metadata !== null && typeof data.metadata === 'object' ? data.metadata : {};
  let names = data.names || metadata.blendshape_names;
  const isDict = (f) => f !== null && typeof f === 'object' && !Array.isArray(f);
  if (names === undefined && frames.every((f) => isDict(f) && !('weights' in f))) {
    names = [...new Set(frames.flatMap((f) => Object.keys(f)))].sort();
  }
  if (names === undefined) names = ARKIT_BLENDSHAPES;
  if (!Array.isArray(names) || !names.every((n) => typeof n === 'string')) {
    throw new DriveError(`${where}: 'names' must be a list of blendshape names`);
  }
  const unknown = names.find((n) => !ARKIT_BLENDSHAPES.includes(n));
  if (unknown !== undefined) {
    throw new DriveError(`${where}: unknown blendshape name '${unknown.slice(0, 40)}' in 'names' (ARKit names only)`);
  }
  if (new Set(names).size !== names.length) throw new DriveError(`${where}: 'names' lists a blendshape twice`);
  const columns = names.map((n) => ARKIT_BLENDSHAPES.indexOf(n));
  const width = ARKIT_BLENDSHAPES.length;
  const weights = new Float32Array(frames.length * width);
  frames.forEach((frame, i) => {
    frameWeights(frame, names, i, where).forEach((value, k) => {
      if (typeof value !== 'number') throw new DriveError(`${where}: frame weights must be numbers, one per name`);
      if (!(Math.abs(value) <= MAX_DRIVE_MAGNITUDE)) {
        throw new DriveError(`${where}: motion frame ${i}: ${names[k]} = ${value} is not a finite weight within `
          + `${MAX_DRIVE_MAGNITUDE}`);
      }
      weights[i * width + columns[k]] = value; // float32, as MotionTrack stores it
    });
  });
  const fps = frameRate(data, frames);
  if (!(Number.isFinite(fps) && fps > 0)) throw new DriveError(`${where}: motion fps must be positive, got ${fps}`);
  return { weights, frames: frames.length, fps };
}

/** Motion file text (or bytes) -> parsed motion (`parseMotion`), bounded as sdk/motion.py `load_motion`. */
export function readMotion(text, where = 'motion file') {
  const size = typeof text === 'string' ? text.length : text.byteLength;
  if (size > MAX_MOTION_FILE_BYTES) {
    throw new DriveError(`${where} is ${size} bytes, over the ${MAX_MOTION_FILE_BYTES} byte limit`);
  }
  let data;
  try {
    const json = typeof text === 'string' ? text : new TextDecoder('utf-8', { fatal: true }).decode(text);
    data = JSON.parse(json);
    if (nestsDeeperThan(json, MAX_JSON_DEPTH)) throw new RangeError('the motion file nests too deep');
  } catch (error) {
    const detail = error instanceof RangeError ? 'it nests too deep' : error.message.slice(0, 200);
    throw new DriveError(`${where} is not JSON: ${detail}`);
  }
  return parseMotion(data, where);
}

/** A motion's weights at `fps` (float32 [T * 52]): as MotionTrack.at_fps, unchanged when the rates agree. */
export function motionAtFps(motion, fps) {
  if (Math.abs(fps - motion.fps) < 1e-9) return { weights: motion.weights, frames: motion.frames };
  const { rows, frames } = resampleAtFps(motion.weights, motion.frames, ARKIT_BLENDSHAPES.length, motion.fps, fps);
  return { weights: Float32Array.from(rows), frames };
}

// -- per-frame drive -----------------------------------------------------------------------------------------

/** Row of a track of `count` rows shown at frame `index`: forth and back, no jump (sdk/drive.py `track_row`). */
export function trackRow(count, index) {
  if (count === 1) return 0;
  const period = 2 * (count - 1);
  const phase = index % period;
  return phase < count ? phase : period - phase;
}

function checked(name, values) {
  for (let i = 0; i < values.length; i++) {
    if (!Number.isFinite(values[i])) throw new DriveError(`${name} has non-finite values: ${name}[${i}] = ${values[i]}`);
    if (Math.abs(values[i]) > MAX_DRIVE_MAGNITUDE) {
      throw new DriveError(`${name} exceeds the supported magnitude ${MAX_DRIVE_MAGNITUDE}: ${name}[${i}] = ${values[i]}`);
    }
  }
  return values;
}

/**
 * Per-frame drive rows of one clip: `rows` [frames * width] (FLAME from audio: expression then jaw; FLAME from a
 * motion, `flameMotion`: expression, flame_pose [15] and head translation [3], the motion's own head pose; ARKit:
 * weights in ARKIT_BLENDSHAPES order), plus the head pose track (float32 [T * 6] or null).
 */
export class Drive {
  constructor({ rig, rows, width, frames, poseTrack = null, rigNames = ARKIT_BLENDSHAPES, flameMotion = false }) {
    Object.assign(this, { rig, rows, width, frames, poseTrack, rigNames, flameMotion });
  }

  /** Head rotation and translation of frame `index` (zero without a pose track). */
  headPose(index) {
    if (!this.poseTrack) return { rotation: new Float32Array(3), translation: new Float32Array(3) };
    const r = trackRow(this.poseTrack.length / 6, index);
    return { rotation: this.poseTrack.slice(6 * r, 6 * r + 3), translation: this.poseTrack.slice(6 * r + 3, 6 * r + 6) };
  }

  /** The deform graph's inputs of frame `index` for a camera centred at `center` ([3] doubles). */
  graphInputs(index, center) {
    if (!(Number.isInteger(index) && index >= 0 && index < this.frames)) {
      throw new DriveError(`frame ${index} is outside the drive's ${this.frames} frames`);
    }
    const row = this.rows.subarray(index * this.width, (index + 1) * this.width);
    const pose = this.headPose(index);
    const camera = { data: Float32Array.from(center), dims: [1, 3] };
    const translation = { data: checked('head translation', pose.translation), dims: [1, 3] };
    if (this.rig === 'arkit') {
      const weights = this.rigNames === ARKIT_BLENDSHAPES ? Float32Array.from(row)
        : Float32Array.from(this.rigNames, (name) => row[ARKIT_BLENDSHAPES.indexOf(name)] ?? 0);
      return { blendshapes: { data: checked('blendshapes', weights), dims: [1, weights.length] },
        head_rotation: { data: checked('head rotation', pose.rotation), dims: [1, 3] },
        head_translation: translation, camera_center: camera };
    }
    if (this.flameMotion) { // sdk/flame_motion.py `FlameMotion.drive`: the motion carries its own head pose
      const n = this.width - TABLE_POSE_COLUMNS;
      return { expression: { data: checked('expression', row.slice(0, n)), dims: [1, n] },
        flame_pose: { data: checked('flame pose', row.slice(n, n + 15)), dims: [1, 15] },
        head_translation: { data: checked('head translation', row.slice(n + 15, n + 18)), dims: [1, 3] },
        camera_center: camera };
    }
    const n = this.width - 3;
    const flamePose = new Float32Array(15);
    flamePose.set(pose.rotation, 0);
    flamePose.set(row.subarray(n, n + 3), 6); // jaw; neck and eyes stay 0
    return { expression: { data: checked('expression', row.slice(0, n)), dims: [1, n] },
      flame_pose: { data: checked('flame pose', flamePose), dims: [1, 15] },
      head_translation: translation, camera_center: camera };
  }
}
