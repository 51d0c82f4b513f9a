// Audio pushed as it arrives, through the bundle's streaming translator graph (docs/web.md, "Streaming audio"):
// each whole frame of audio goes into the graph's state once, and each call gives the rows of the frames whose
// lookahead is in, `delay` frames behind the audio. The graph's contract and its rest state: docs/live.md,
// "Streaming translators"; the Python runtime's live sessions run the same graph (runtime/translate_stream.py, which
// also serves paced sessions: provisional lookahead, idle gaps).
//
//   const stream = await AudioStream.open(graphs, bundle, { rowsOf, rigSamplesPerFrame });
//   await stream.push(samples);   // mono float32 at the speaker's rate, any length; returns the frames ready
//   await stream.end();           // the last partial frame and the lookahead zero-padded; returns all frames
//   stream.rows, stream.width, stream.frames   // the rig's rows so far, [frames * width], frame order
//   stream.drive()                // their drive (a stream opened by Player.openAudioStream)
//
// A bundle whose stream has a steady form (the speaker's own translator) runs it for every call whose window's
// loudness held, the refreshing graph where it moved, as the Python runtime chooses (`windowLoudness`,
// `loudnessMoved` and `madeAfter`, the twins of runtime/translate_stream.py `window_loudness`, `loudness_moved` and
// `made_after`; docs/live.md, "The speaker's own translator").
//
// Each stream row is gated like a live session's (docs/embedding.md, "Silence gate"): scaled by the gain of the
// audio window a windowed call would see for it (CONTEXT_FRAMES before, the frame, `delay` after; zeros before the
// stream's start). A rig whose frames are not the stream's (a 30 fps avatar on a 25 fps voice) takes each frame at
// its centre, interpolated between the two nearest rows (rows before the first are the rest row).

import { DriveError, checkSamples, silenceGain } from './drive.js';
import {
  CONTEXT_FRAMES, LOUDNESS_RATIO, LOUDNESS_WINDOW_FRAMES, REFRESHED_FRAMES, REST_FRAMES, SILENCE_GATE_DBFS,
} from './generated.js';

export const STREAM_GRAPH = 'translator_stream';
// The stream's steady form, run while the window's loudness holds (docs/live.md, "The speaker's own translator").
export const STEADY_STREAM_GRAPH = 'translator_stream_steady';

/** Each frame's mean square (float64) of `audio` [frames * frameSamples]. */
export function framePowers(audio, frameSamples) {
  const powers = new Float64Array(Math.floor(audio.length / frameSamples));
  for (let f = 0; f < powers.length; f++) {
    let sum = 0;
    for (let i = f * frameSamples; i < (f + 1) * frameSamples; i++) sum += audio[i] * audio[i];
    powers[f] = sum / frameSamples;
  }
  return powers;
}

/**
 * The window's loudness: the mean of the last LOUDNESS_WINDOW_FRAMES frames' mean squares of `powers` (silence
 * before the first counts as zeros).
 */
export function windowLoudness(powers) {
  let sum = 0;
  for (let i = Math.max(0, powers.length - LOUDNESS_WINDOW_FRAMES); i < powers.length; i++) sum += powers[i];
  return sum / LOUDNESS_WINDOW_FRAMES;
}

/**
 * Whether a call needs the refreshing graph: the window's loudness `now` is LOUDNESS_RATIO times, or a
 * LOUDNESS_RATIO-th of, the loudness at which any of the last REFRESHED_FRAMES committed frames' features were made
 * (`made`; the rest state's: zeros).
 */
export function loudnessMoved(now, made) {
  return now > LOUDNESS_RATIO * Math.min(...made) || Math.max(...made) > LOUDNESS_RATIO * now;
}

/** `made` after a call at loudness `now` that committed `keep` frames (refreshed or not): runtime `made_after`. */
export function madeAfter(made, keep, refreshed, now) {
  if (keep <= 0) return made;
  if (refreshed || keep >= REFRESHED_FRAMES) return new Float64Array(REFRESHED_FRAMES).fill(now);
  const out = new Float64Array(REFRESHED_FRAMES);
  out.set(made.subarray(keep));
  out.fill(now, REFRESHED_FRAMES - keep);
  return out;
}

// Frames per graph call at most, so a long push holds a bounded window of audio and rows at a time.
const MAX_CALL_FRAMES = 50;

const f32 = Math.fround;

/** Whole-frame audio, the graph's state and row bookkeeping of one stream (module comment). */
export class AudioStream {
  constructor(fields) {
    Object.assign(this, fields);
  }

  /**
   * Open a stream on `graphs` (GraphSessions holding the bundle's streaming graph). `rowsOf(outputs)` -> {rows:
   * Float32Array [n * width], width}; `rigSamplesPerFrame`: the rig's samples per frame at the speaker's rate.
   */
  static async open(graphs, bundle, { rowsOf, rigSamplesPerFrame, makeDrive = null, gateDbfs = SILENCE_GATE_DBFS,
    contextFrames = CONTEXT_FRAMES } = {}) {
    if (!graphs.has(STREAM_GRAPH)) {
      throw new DriveError(`${bundle.name}: this bundle has no streaming translator graph (exported before `
        + 'streaming, or an audio model without a streaming form): translate whole clips with driveFromAudio');
    }
    const shapes = Object.fromEntries(bundle.graphInfo(STREAM_GRAPH).inputs.map((v) => [v.name, v.shape]));
    const stateSize = shapes.state?.[1];
    const frameSamples = shapes.audio?.[2];
    if (!(Number.isInteger(stateSize) && stateSize > 0 && Number.isInteger(frameSamples) && frameSamples > 0)) {
      throw new DriveError(`${bundle.name}: the streaming graph's inputs do not say their state and frame sizes`);
    }
    const steady = graphs.has(STEADY_STREAM_GRAPH);
    const run = (audio, frames, state, keep, refresh = true) => graphs.run(
      refresh || !steady ? STREAM_GRAPH : STEADY_STREAM_GRAPH, {
        audio: { data: audio, dims: [1, frames, frameSamples] }, state: { data: state, dims: [1, stateSize] },
        keep: { data: Float32Array.of(keep), dims: [1] } });
    const rest = await run(new Float32Array(REST_FRAMES * frameSamples), REST_FRAMES, new Float32Array(stateSize),
      REST_FRAMES);
    const delay = Number(rest.delay_frames.data[0]);
    if (!(Number.isInteger(delay) && delay >= 0 && delay < REST_FRAMES)) {
      throw new DriveError(`${bundle.name}: the streaming graph says its rows lag ${delay} frames; expected 0..${REST_FRAMES - 1}`);
    }
    const { rows, width } = rowsOf(rest);
    return new AudioStream({ run, steady, powers: new Float64Array(0), made: new Float64Array(REFRESHED_FRAMES),
      rowsOf, makeDrive, delay, frameSamples,
      width, gateDbfs, contextFrames,
      rigSamplesPerFrame, aligned: Math.abs(rigSamplesPerFrame - frameSamples) < 1e-9,
      restRow: rows.slice((REST_FRAMES - 1) * width, REST_FRAMES * width), state: rest.state_out.data.slice(),
      pending: new Float32Array(0), received: 0, committed: 0, history: new Float32Array(0), historyStart: 0,
      streamRows: [], rows: new Float32Array(0), frames: 0, ended: false });
  }

  /** Samples (mono float32 at the speaker's rate) arrive: every whole frame is translated; returns the frames
   * ready now (`this.frames`). */
  async push(samples) {
    if (this.ended) throw new DriveError('audio pushed after end()');
    checkSamples(samples);
    const pending = new Float32Array(this.pending.length + samples.length);
    pending.set(this.pending);
    pending.set(samples, this.pending.length);
    this.pending = pending;
    this.received += samples.length;
    await this._commit();
    this._emit(false);
    return this.frames;
  }

  /** The audio is complete: its last partial frame and the lookahead are zero-padded; returns every frame. */
  async end() {
    if (this.ended) return this.frames;
    const size = this.frameSamples;
    const padded = new Float32Array((Math.ceil(this.pending.length / size) + this.delay) * size);
    padded.set(this.pending);
    this.pending = padded;
    await this._commit();
    this.ended = true;
    this._emit(true);
    return this.frames;
  }

  async _commit() {
    const size = this.frameSamples;
    while (this.pending.length >= size) {
      const count = Math.min(Math.floor(this.pending.length / size), MAX_CALL_FRAMES);
      const audio = this.pending.slice(0, count * size);
      let powers = null; // one graph without a steady form: no gate, nothing to measure (as Python's plan())
      let refresh = true;
      let now = 0;
      if (this.steady) {
        powers = new Float64Array(this.powers.length + count);
        powers.set(this.powers);
        powers.set(framePowers(audio, size), this.powers.length);
        now = windowLoudness(powers);
        refresh = loudnessMoved(now, this.made);
      }
      const out = await this.run(audio, count, this.state, count, refresh);
      if (powers !== null) {
        this.powers = powers.slice(Math.max(0, powers.length - LOUDNESS_WINDOW_FRAMES));
        this.made = madeAfter(this.made, count, refresh, now);
      }
      this.state = out.state_out.data.slice();
      this._remember(audio);
      const { rows } = this.rowsOf(out);
      const first = this.committed - this.delay;
      this.committed += count;
      for (let k = 0; k < count; k++) {
        if (first + k < 0) continue;
        const gain = f32(silenceGain(this._gateWindow(first + k), this.gateDbfs));
        this.streamRows.push(rows.slice(k * this.width, (k + 1) * this.width).map((v) => f32(v * gain)));
      }
      this.pending = this.pending.slice(count * size);
    }
  }

  /** Keep the committed audio the gate still reads: from CONTEXT_FRAMES before the next row on. */
  _remember(audio) {
    const keepFrom = Math.max(0, this.committed - this.delay - this.contextFrames) * this.frameSamples;
    const drop = Math.max(0, keepFrom - this.historyStart);
    const history = new Float32Array(this.history.length - drop + audio.length);
    history.set(this.history.subarray(drop));
    history.set(audio, this.history.length - drop);
    this.history = history;
    this.historyStart += drop;
  }

  /** The audio a windowed call would see for row `j`: frames [j - context, j + delay + 1), zeros before 0. */
  _gateWindow(j) {
    const size = this.frameSamples;
    const window = new Float32Array((this.contextFrames + this.delay + 1) * size);
    const from = (j - this.contextFrames) * size;
    const lo = Math.max(from, this.historyStart);
    window.set(this.history.subarray(lo - this.historyStart, lo - this.historyStart + window.length - (lo - from)),
      lo - from);
    return window;
  }

  /** The drive of the frames ready so far (what Player.renderFrame draws; opened by Player.openAudioStream). */
  drive() {
    if (!this.makeDrive) throw new DriveError('this stream was opened without a player');
    return this.makeDrive(this.rows, this.width, this.frames);
  }

  _row(index) {
    return index < 0 ? this.restRow : this.streamRows[index];
  }

  /** Append every rig frame whose rows are all made (at the end: every frame of the audio received). */
  _emit(final) {
    const total = final ? Math.ceil(this.received / this.rigSamplesPerFrame - 1e-9) : Infinity;
    const ready = [];
    for (let f = this.frames; f < total; f++) {
      let row;
      if (this.aligned) {
        if (f >= this.streamRows.length) break;
        row = this.streamRows[f];
      } else {
        const centre = (f * this.rigSamplesPerFrame + this.rigSamplesPerFrame / 2) / this.frameSamples - 0.5;
        const i = Math.floor(centre);
        if (i + 1 >= this.streamRows.length) {
          if (!final || i >= this.streamRows.length) break;
        }
        const w = f32(centre - i);
        const left = this._row(i);
        const right = i + 1 < this.streamRows.length ? this._row(i + 1) : left;
        row = left.map((v, k) => f32(f32(v * f32(1 - w)) + f32(right[k] * w)));
      }
      ready.push(row);
    }
    if (!ready.length) return;
    const rows = new Float32Array((this.frames + ready.length) * this.width);
    rows.set(this.rows);
    ready.forEach((row, k) => rows.set(row, (this.frames + k) * this.width));
    this.rows = rows;
    this.frames += ready.length;
  }
}
