// Live sessions rendered by the client (docs/live.md, "Live, rendered by the client"): the server runs only the
// driver and sends each frame's drive on a data channel, stamped with its pts on the session's audio clock; the
// page renders a drive when the audio it hears reaches that pts.
//
//   decodeDrive(arrayBuffer)        -> {index, pts, epoch, speaking, rig, values, split}  (DriveFormatError)
//   new DriveQueue()                drives keyed by pts; barge-in epochs; take(clock) -> the drive to show now
//   new LiveClock()                 the pts being heard now, from the drives' arrival and the audio receiver's
//                                   playout delay
//   new WireDrive(decoded, player)  what Player.renderFrame draws (duck-typed like drive.js's Drive)
//
// Over one WebSocket (transport "ws", docs/live.md) each frame comes as a frame packet: its drive and its audio.
//
//   decodeFramePacket(arrayBuffer)  -> {drive: decodeDrive's fields, audio: Int16Array}  (DriveFormatError)
//   new LiveAudio()                 plays the packets' audio on a continuous WebAudio schedule; now() is the pts
//                                   being heard, the clock the drives are drawn on

import {
  ARKIT_BLENDSHAPES, DRIVE_HEADER_BYTES, DRIVE_LAYOUT, DRIVE_MAGIC, DRIVE_VERSION, FRAME_HEADER_BYTES, PACKET_LAYOUT,
  PACKET_MAGIC, PACKET_VERSION, POSE_VALUES, RIG_CODES, SPEAKING_FLAG,
} from './generated.js';

export { DRIVE_HEADER_BYTES, FRAME_HEADER_BYTES };

export class DriveFormatError extends Error {
  constructor(message) {
    super(message);
    this.name = 'DriveFormatError';
  }
}

// The wire format (gaussiantalker.serve.wire, docs/serve.md): a drive message is little-endian, a DRIVE_HEADER_BYTES
// header then `count` float32; its constants and its headers' field offsets come from generated.js.
const offsets = (layout) => Object.fromEntries(Object.entries(layout).map(([name, [at]]) => [name, at]));
const DRIVE_AT = offsets(DRIVE_LAYOUT);
const PACKET_AT = offsets(PACKET_LAYOUT);

/** A drive message (ArrayBuffer or a typed array) -> its fields; DriveFormatError for one that is truncated, lies
 * about its count, or is of an unknown kind. No count is trusted beyond the bytes present. */
export function decodeDrive(message) {
  const bytes = message instanceof ArrayBuffer ? new Uint8Array(message)
    : new Uint8Array(message.buffer, message.byteOffset, message.byteLength);
  if (bytes.length < DRIVE_HEADER_BYTES) {
    throw new DriveFormatError(`drive message truncated: ${bytes.length} bytes, the header alone is ${DRIVE_HEADER_BYTES}`);
  }
  if (!DRIVE_MAGIC.every((b, i) => bytes[i] === b)) throw new DriveFormatError('not a drive message (bad magic)');
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const version = view.getUint8(DRIVE_AT.version);
  const rig = view.getUint8(DRIVE_AT.rig);
  const flags = view.getUint8(DRIVE_AT.flags);
  const dtype = view.getUint8(DRIVE_AT.dtype);
  if (version !== DRIVE_VERSION || dtype !== 0) {
    throw new DriveFormatError(`drive message version ${version} dtype ${dtype}: only version ${DRIVE_VERSION} float32 is read`);
  }
  if (!(rig in POSE_VALUES)) throw new DriveFormatError(`drive message has unknown rig code ${rig}`);
  const index = view.getUint32(DRIVE_AT.index, true);
  const epoch = view.getUint32(DRIVE_AT.epoch, true);
  const pts = view.getFloat64(DRIVE_AT.pts, true);
  const count = view.getUint16(DRIVE_AT.count, true);
  const split = view.getUint16(DRIVE_AT.split, true);
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
  return { index, pts, epoch, speaking: Boolean(flags & SPEAKING_FLAG), rig: rig === RIG_CODES.arkit ? 'arkit' : 'flame',
    values, split };
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


// A frame packet (gaussiantalker.serve.wire encode_frame_packet): "GTLF", version, audio dtype, reserved u16, then
// drive_bytes (u32), the drive message, and the frame's audio (int16 LE mono) filling the rest.

/** A frame packet (ArrayBuffer or a typed array) -> {drive, audio}; DriveFormatError naming what is wrong, the
 * drive's own refusals included. drive_bytes is checked against the bytes present before anything is read. */
export function decodeFramePacket(message) {
  const bytes = message instanceof ArrayBuffer ? new Uint8Array(message)
    : new Uint8Array(message.buffer, message.byteOffset, message.byteLength);
  if (bytes.length < FRAME_HEADER_BYTES) {
    throw new DriveFormatError(
      `frame packet truncated: ${bytes.length} bytes, the header alone is ${FRAME_HEADER_BYTES}`);
  }
  if (!PACKET_MAGIC.every((b, i) => bytes[i] === b)) throw new DriveFormatError('not a frame packet (bad magic)');
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const version = view.getUint8(PACKET_AT.version);
  const dtype = view.getUint8(PACKET_AT.dtype);
  if (version !== PACKET_VERSION || dtype !== 0) {
    throw new DriveFormatError(`frame packet version ${version} audio dtype ${dtype}: only version ${PACKET_VERSION} int16 is read`);
  }
  const driveBytes = view.getUint32(PACKET_AT.drive_bytes, true);
  const rest = bytes.length - FRAME_HEADER_BYTES;
  if (driveBytes > rest) {
    throw new DriveFormatError(
      `frame packet claims a ${driveBytes}-byte drive but carries ${rest} bytes after its header`);
  }
  const audioBytes = rest - driveBytes;
  if (audioBytes % 2) throw new DriveFormatError(`frame packet audio is ${audioBytes} bytes: not whole int16 samples`);
  const drive = decodeDrive(bytes.subarray(FRAME_HEADER_BYTES, FRAME_HEADER_BYTES + driveBytes));
  const audio = new Int16Array(audioBytes / 2);
  const at = FRAME_HEADER_BYTES + driveBytes;
  for (let i = 0; i < audio.length; i++) audio[i] = view.getInt16(at + 2 * i, true);
  return { drive, audio };
}

/** Plays frame packets' audio through an AudioContext, back to back, `bufferS` (a jitter buffer) after it arrives,
 * and keeps which pts plays at which context time, so `now()` (the pts being heard) is the clock that the drives
 * are drawn on: picture and sound share the sound card's clock and cannot drift apart.
 *
 *   schedule(pts, samples, rate, {epoch, index})  queue one packet after what is queued (re-anchored to now +
 *                                                  bufferS when the queue ran dry: an underrun)
 *   now()                                          the pts heard now (NaN before anything is scheduled)
 *   bargeIn(epoch, firstIndex)                     stop the queued audio of older epochs from firstIndex on */
export class LiveAudio {
  constructor({ context = null, bufferS = 0.1, maxAheadS = 1.0, volume = 1.0 } = {}) {
    this.ctx = context ?? new AudioContext();
    this.gain = this.ctx.createGain();
    this.gain.gain.value = volume;
    this.gain.connect(this.ctx.destination);
    Object.assign(this, { bufferS, maxAheadS, segments: [], nextTime: null, epoch: 0, epochStart: Infinity,
      cut: false, scheduled: 0, underruns: 0, overruns: 0, stopped: 0, refused: 0, suspended: 0 });
  }

  /** The context time whose sound leaves the speaker now: currentTime less the output path's latency. */
  heardTime() {
    const latency = this.ctx.outputLatency || this.ctx.baseLatency || 0;
    return this.ctx.currentTime - latency;
  }

  /** Queue one packet's int16 samples (pts: the time of its first sample on the session's clock). Returns the
   * context time it starts at, or null when it is not played (a stale epoch's, one past maxAheadS, or while the
   * context is not running). */
  schedule(pts, samples, sampleRate, { epoch = 0, index = 0 } = {}) {
    if (epoch > this.epoch) this.bargeIn(epoch, index);
    if (epoch < this.epoch && index >= this.epochStart) {
      this.refused += 1;
      return null;
    }
    if (!samples.length) return null;
    if (this.ctx.state !== 'running') {
      // A context the autoplay policy holds (or one closed) plays nothing: queueing would only add delay for later.
      this.suspended += 1;
      return null;
    }
    const now = this.ctx.currentTime;
    if (this.nextTime === null || this.nextTime < now || this.cut) {
      // The first packet, an underrun (the queue ran dry) or the first after a barge-in's cut: a jitter buffer ahead.
      if (this.nextTime !== null && this.nextTime < now && !this.cut) this.underruns += 1;
      this.nextTime = Math.max(this.nextTime ?? 0, now + this.bufferS);
    } else if (this.nextTime > now + this.bufferS + this.maxAheadS) {
      // Arriving faster than it plays (a sender's clock running fast): dropping a packet keeps the delay bounded.
      this.overruns += 1;
      return null;
    }
    const buffer = this.ctx.createBuffer(1, samples.length, sampleRate);
    const channel = buffer.getChannelData(0);
    for (let i = 0; i < samples.length; i++) channel[i] = samples[i] / 32768;
    const source = this.ctx.createBufferSource();
    source.buffer = buffer;
    source.connect(this.gain);
    const start = this.nextTime;
    const duration = samples.length / sampleRate;
    source.start(start);
    this.nextTime = start + duration;
    this.cut = false;
    this.segments.push({ pts, start, duration, epoch, index, source });
    this.scheduled += 1;
    // What has been heard more than a second ago is no longer needed for the mapping.
    const heard = this.heardTime();
    while (this.segments.length > 1 && this.segments[0].start + this.segments[0].duration < heard - 1.0) {
      this.segments.shift();
    }
    return start;
  }

  /** The pts heard now: within a queued packet, its pts plus the time into it; between packets (an underrun) or
   * after the last, the end of the one heard last (the clock waits for the sound); before the first, counting
   * back from it. NaN before anything is scheduled. */
  now() {
    if (!this.segments.length) return NaN;
    const t = this.heardTime();
    const first = this.segments[0];
    if (t < first.start) return first.pts - (first.start - t);
    let last = first;
    for (const s of this.segments) {
      if (s.start > t) break;
      last = s;
    }
    return last.pts + Math.min(t - last.start, last.duration);
  }

  /** A barge-in: stop the queued sound of epochs older than `epoch` from frame `firstIndex` on (null: from the
   * first packet not yet playing), and refuse such packets arriving later, so the old speech stops at once. */
  bargeIn(epoch, firstIndex = null) {
    if (epoch < this.epoch) return;
    const t = this.ctx.currentTime;
    if (firstIndex === null) {
      const pending = this.segments.find((s) => s.epoch < epoch && s.start > t);
      const last = this.segments[this.segments.length - 1];
      firstIndex = pending ? pending.index : last ? last.index + 1 : Infinity;
    }
    this.epochStart = epoch > this.epoch ? firstIndex : Math.min(this.epochStart, firstIndex);
    this.epoch = epoch;
    const kept = [];
    let resume = null;
    for (const s of this.segments) {
      if (s.epoch < epoch && s.index >= this.epochStart && s.start + s.duration > t) {
        s.source.stop();
        this.stopped += 1;
        resume = Math.min(resume ?? Infinity, Math.max(s.start, t));
      } else {
        kept.push(s);
      }
    }
    this.segments = kept;
    // The next packet follows what still plays (a jitter buffer ahead), not the silence left by what was stopped.
    if (resume !== null) Object.assign(this, { nextTime: Math.min(this.nextTime, resume), cut: true });
  }

  get stats() {
    return { scheduled: this.scheduled, underruns: this.underruns, overruns: this.overruns, stopped: this.stopped,
      refused: this.refused, suspended: this.suspended, heardPts: this.now(), bufferS: this.bufferS,
      ahead: this.nextTime === null ? 0 : this.nextTime - this.ctx.currentTime, contextRate: this.ctx.sampleRate };
  }

  close() {
    for (const s of this.segments) s.source.stop();
    this.segments = [];
    return this.ctx.close();
  }
}
