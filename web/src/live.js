// Live sessions rendered by the client (docs/live.md, "Live, rendered by the client"): the server runs only the
// driver and sends each frame's drive on a data channel, stamped with its pts on the session's audio clock; the
// page renders a drive when the audio it hears reaches that pts.
//
//   decodeDrive(arrayBuffer)        -> {index, pts, epoch, speaking, rig, values, split}  (DriveFormatError)
//   new DriveQueue()                drives keyed by pts; barge-in epochs; take(clock) -> the drive to show now
//   new LiveClock()                 the pts being heard now, from the drives' arrival and the audio receiver's
//                                   playout delay
//   new WireDrive(decoded, player)  what Player.renderFrame draws (duck-typed like drive.js's Drive)

import { ARKIT_BLENDSHAPES } from './generated.js';

export class DriveFormatError extends Error {
  constructor(message) {
    super(message);
    this.name = 'DriveFormatError';
  }
}

// The wire format (samples/live_server.py encode_drive): little-endian, a 28-byte header then `count` float32.
export const DRIVE_HEADER_BYTES = 28;
const MAGIC = [0x47, 0x54, 0x4c, 0x44]; // "GTLD"
const VERSION = 1;
const POSE_VALUES = { 0: 18, 1: 6 }; // values after `split`: FLAME flame_pose[15] + translation, ARKit rotation + translation

/** A drive message (ArrayBuffer or a typed array) -> its fields; DriveFormatError for one that is truncated, lies
 * about its count, or is of an unknown kind. No count is trusted beyond the bytes present. */
export function decodeDrive(message) {
  const bytes = message instanceof ArrayBuffer ? new Uint8Array(message)
    : new Uint8Array(message.buffer, message.byteOffset, message.byteLength);
  if (bytes.length < DRIVE_HEADER_BYTES) {
    throw new DriveFormatError(`drive message truncated: ${bytes.length} bytes, the header alone is ${DRIVE_HEADER_BYTES}`);
  }
  if (!MAGIC.every((b, i) => bytes[i] === b)) throw new DriveFormatError('not a drive message (bad magic)');
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const version = view.getUint8(4);
  const rig = view.getUint8(5);
  const flags = view.getUint8(6);
  const dtype = view.getUint8(7);
  if (version !== VERSION || dtype !== 0) {
    throw new DriveFormatError(`drive message version ${version} dtype ${dtype}: only version ${VERSION} float32 is read`);
  }
  if (!(rig in POSE_VALUES)) throw new DriveFormatError(`drive message has unknown rig code ${rig}`);
  const index = view.getUint32(8, true);
  const epoch = view.getUint32(12, true);
  const pts = view.getFloat64(16, true);
  const count = view.getUint16(24, true);
  const split = view.getUint16(26, true);
  const body = bytes.length - DRIVE_HEADER_BYTES;
  if (count * 4 !== body) {
    throw new DriveFormatError(`drive message claims ${count} values (${count * 4} bytes) but carries ${body} bytes`);
  }
  if (split + POSE_VALUES[rig] !== count) {
    throw new DriveFormatError(`drive message splits ${count} values at ${split}: the pose needs ${POSE_VALUES[rig]}`);
  }
  if (!(Number.isFinite(pts) && pts >= 0)) throw new DriveFormatError(`drive message pts ${pts} is not a finite time >= 0`);
  const values = new Float32Array(count);
  for (let i = 0; i < count; i++) {
    values[i] = view.getFloat32(DRIVE_HEADER_BYTES + 4 * i, true);
    if (!Number.isFinite(values[i])) throw new DriveFormatError('drive message has non-finite values');
  }
  return { index, pts, epoch, speaking: Boolean(flags & 1), rig: rig ? 'arkit' : 'flame', values, split };
}

/** One received drive as Player.renderFrame draws it (index ignored: the drive is one frame). */
export class WireDrive {
  constructor(decoded, rigNames = ARKIT_BLENDSHAPES) {
    Object.assign(this, { decoded, rigNames, frames: 1, rig: decoded.rig });
  }

  graphInputs(index, center) {
    const { values, split, rig } = this.decoded;
    const camera = { data: Float32Array.from(center), dims: [1, 3] };
    const translation = { data: values.slice(values.length - 3), dims: [1, 3] };
    if (rig === 'arkit') {
      const weights = values.subarray(0, split);
      const named = this.rigNames === ARKIT_BLENDSHAPES ? Float32Array.from(weights)
        : Float32Array.from(this.rigNames, (name) => weights[ARKIT_BLENDSHAPES.indexOf(name)] ?? 0);
      return { blendshapes: { data: named, dims: [1, named.length] },
        head_rotation: { data: values.slice(split, split + 3), dims: [1, 3] }, head_translation: translation,
        camera_center: camera };
    }
    return { expression: { data: values.slice(0, split), dims: [1, split] },
      flame_pose: { data: values.slice(split, split + 15), dims: [1, 15] }, head_translation: translation,
      camera_center: camera };
  }
}

/** Received drives keyed by pts. `push` keeps them in pts order whatever order they arrive in (the channel is
 * unordered); a newer epoch (a barge-in) drops every queued drive of an older epoch at or past the new epoch's
 * first index, and refuses such drives arriving later. `take(clock)` returns the newest drive whose pts the clock
 * has reached (older ones are skipped: their moment has passed), or null. */
export class DriveQueue {
  constructor({ limit = 250 } = {}) {
    Object.assign(this, { limit, items: [], epoch: 0, epochStart: 0, received: 0, stale: 0, skipped: 0, dropped: 0 });
  }

  /** A barge-in heard on the control channel (epoch) or from a drive (epoch, its index). */
  bargeIn(epoch, firstIndex = null) {
    if (epoch < this.epoch) return;
    if (epoch > this.epoch) {
      this.epoch = epoch;
      this.epochStart = firstIndex ?? Infinity;
    } else if (firstIndex !== null) {
      this.epochStart = Math.min(this.epochStart, firstIndex);
    }
    const before = this.items.length;
    this.items = this.items.filter((d) => !this.isStale(d));
    this.dropped += before - this.items.length;
  }

  isStale(drive) {
    return drive.epoch < this.epoch && drive.index >= this.epochStart;
  }

  push(drive) {
    this.received += 1;
    if (drive.epoch >= this.epoch) this.bargeIn(drive.epoch, drive.index);
    if (this.isStale(drive)) {
      this.stale += 1;
      return false;
    }
    let i = this.items.length;
    while (i > 0 && this.items[i - 1].pts > drive.pts) i--;
    this.items.splice(i, 0, drive);
    if (this.items.length > this.limit) this.items.shift();
    return true;
  }

  take(clock) {
    let chosen = null;
    while (this.items.length && this.items[0].pts <= clock) {
      if (chosen) this.skipped += 1;
      chosen = this.items.shift();
    }
    return chosen;
  }

  get length() { return this.items.length; }
}

/** The pts being heard now. A drive leaves the server with its audio frame (one paced loop makes both), so a drive
 * arriving at time a with pts p says the audio of p left the server at about a - p + p (the data channel is faster
 * than the audio path); the smallest arrival - pts over the last `windowS` seconds is the send clock, and the
 * audio is heard `audioDelay` later (the receiver's jitter buffer, from its getStats, and the output latency). */
export class LiveClock {
  constructor({ windowS = 2.0 } = {}) {
    Object.assign(this, { windowS, samples: [], audioDelay: 0.0 });
  }

  observe(pts, arrival = performance.now() / 1000) {
    this.samples.push([arrival, arrival - pts]);
    while (this.samples.length && this.samples[0][0] < arrival - this.windowS) this.samples.shift();
  }

  get ready() { return this.samples.length > 0; }

  /** The pts whose sound plays now (NaN before any drive). */
  now(time = performance.now() / 1000) {
    if (!this.samples.length) return NaN;
    let offset = Infinity;
    for (const [, o] of this.samples) offset = Math.min(offset, o);
    return time - offset - this.audioDelay;
  }

  /** Update audioDelay from an RTCRtpReceiver's stats: the jitter buffer's delay of the samples emitted since the
   * last call (Chromium's inbound-rtp jitterBufferDelay / jitterBufferEmittedCount), plus `outputLatency`. */
  async measure(receiver, outputLatency = 0) {
    const stats = await receiver.getStats();
    for (const report of stats.values()) {
      if (report.type !== 'inbound-rtp' || report.kind !== 'audio') continue;
      const last = this.lastStats;
      this.lastStats = { delay: report.jitterBufferDelay ?? 0, count: report.jitterBufferEmittedCount ?? 0 };
      const count = this.lastStats.count - (last?.count ?? 0);
      if (count > 0) this.audioDelay = (this.lastStats.delay - (last?.delay ?? 0)) / count + outputLatency;
    }
    return this.audioDelay;
  }
}
