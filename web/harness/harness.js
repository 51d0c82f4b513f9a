// What `gt-web` (tools/browser/web_harness.py) drives over the DevTools protocol: window.gtWeb loads a bundle into the
// player, makes a drive from an audio or motion URL, and renders frames, returning their RGB bytes as base64.

import { Camera, Player, decodeAudio, readBundle } from 'gaussiantalker-web';

let player = null;
let drive = null;

async function fetchBytes(url) {
  const response = await fetch(url);
  if (!response.ok) throw new Error(`${url}: HTTP ${response.status}`);
  return new Uint8Array(await response.arrayBuffer());
}

function base64(bytes) {
  let text = '';
  for (let i = 0; i < bytes.length; i += 0x8000) text += String.fromCharCode(...bytes.subarray(i, i + 0x8000));
  return btoa(text);
}

window.gtWeb = {
  /** Read and check a bundle only: null when it is accepted, else the error's message. */
  async check(url, name) {
    try {
      await readBundle(await fetchBytes(url), { name });
      return null;
    } catch (error) {
      return `${error.name}: ${error.message}`;
    }
  },

  /** Buffer `buffer` of the bundle at `url` decoded by the player's codecs: {dtype, shape, data (base64)}. */
  async decode(url, name, buffer) {
    const bundle = await readBundle(await fetchBytes(url), { name });
    const { dtype, shape, data } = bundle.buffer(buffer);
    return { dtype, shape, data: base64(new Uint8Array(data.buffer, data.byteOffset, data.byteLength)) };
  },

  async load({ url, name, width, height, camera, background, threads, settings, composite }) {
    if (player) await player.release();
    player = await Player.load(await fetchBytes(url), { name, width, height, camera: camera ?? undefined,
      background: background ?? undefined, threads: threads ?? 1, composite: composite ?? undefined,
      ...(settings ?? {}) });
    const gl = player.splatter;
    return { rig: player.rig.kind, fps: player.fps, sampleRate: player.sampleRate, size: player.frameSize,
      composited: player.composited,
      gaussians: player.bundle.manifest.gaussians ?? null, precision: gl.precision, fallback: gl.fallback,
      renderer: gl.renderer, maxPointSize: gl.maxPointSize, extensions: gl.extensions, load: player.loadTimings,
      settings: player.settings, graphs: player.graphs.backend };
  },

  async drive({ audio, motion, weights }) {
    if (audio) drive = await player.driveFromAudioFile(await fetchBytes(audio));
    else if (weights) drive = player.driveFromWeights(weights.rows, weights.fps);
    else drive = player.driveFromMotion(motion ? await fetchBytes(motion) : null, motion ?? 'motion');
    return { frames: drive.frames, translate: player.translateSeconds ?? null };
  },

  /** Audio through the streaming translator: the file decoded at the speaker's rate, pushed `chunk` samples at a
   * time, then ended; the drive is the stream's. */
  async streamDrive({ audio, chunk }) {
    const samples = await decodeAudio(await fetchBytes(audio), player.sampleRate);
    const before = { ...player.graphs.calls };
    const stream = await player.openAudioStream();
    const ready = [];
    for (let i = 0; i < samples.length; i += chunk) ready.push(await stream.push(samples.subarray(i, i + chunk)));
    await stream.end();
    drive = stream.drive();
    // The stream's calls of each graph (its first, of silence, included): which form of the translator ran.
    const calls = Object.fromEntries(Object.entries(player.graphs.calls)
      .map(([name, count]) => [name, count - (before[name] ?? 0)]).filter(([, count]) => count > 0));
    return { frames: drive.frames, ready, delay: stream.delay, calls };
  },

  /** The drive's rows (FLAME: expression then jaw; ARKit: weights) as float32 base64, [frames, width]. */
  driveRows() {
    const rows = drive.rows;
    return { frames: drive.frames, width: drive.width,
      data: base64(new Uint8Array(rows.buffer, rows.byteOffset, rows.byteLength)) };
  },

  /** The player's camera swung about `target` and dollied (Camera.orbited, Camera.dollied): its dict. */
  orbit({ camera, yaw, pitch, target, distance }) {
    return Camera.fromDict(camera).orbited(yaw, pitch, target).dollied(distance, target).toDict();
  },

  /** The player's head centre (Player.headCentre). */
  headCentre() {
    return player.headCentre();
  },

  setCamera(camera) {
    player.setCamera(camera);
    return player.frameSize;
  },

  async render(index, output = 'uint8') {
    const frame = await player.renderFrame(drive, index, { output });
    const bytes = new Uint8Array(frame.pixels.buffer, frame.pixels.byteOffset, frame.pixels.byteLength);
    return { width: frame.width, height: frame.height, data: base64(bytes), timings: frame.timings,
      splats: frame.splats };
  },
};
window.gtWebReady = true;
