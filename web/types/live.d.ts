// TypeScript declarations of 'gaussiantalker-web/live' (src/live.js): the pieces of a live session that a server
// drives and the page draws (gt-serve --client-render): the wire's drive messages and frame packets, the queue of
// received drives, and the clock they are drawn on.

import type { DrawableDrive, GraphInput } from './index.js';

export class DriveFormatError extends Error {}

/** A decoded drive message. */
export interface DecodedDrive {
  index: number;
  /** Seconds on the session's audio clock. */
  pts: number;
  /** Barge-ins so far. */
  epoch: number;
  speaking: boolean;
  rig: 'flame' | 'arkit';
  values: Float32Array;
  split: number;
}

/** A drive message's fields; DriveFormatError for one that is truncated, lies about its count or is unknown. */
export function decodeDrive(message: ArrayBuffer | ArrayBufferView): DecodedDrive;

/** A frame packet (one WebSocket message): its drive and its int16 audio. */
export function decodeFramePacket(message: ArrayBuffer | ArrayBufferView): { drive: DecodedDrive; audio: Int16Array };

/** One received drive as `Player.renderFrame` draws it (the index is ignored: the drive is one frame). */
export class WireDrive implements DrawableDrive {
  constructor(decoded: DecodedDrive, rigNames?: readonly string[]);
  graphInputs(index: number, center: ArrayLike<number>): Record<string, GraphInput>;
}

/** Received drives in pts order; a barge-in drops the older epoch's; `take` gives the drive to show now. */
export class DriveQueue {
  constructor(options?: { limit?: number });
  readonly length: number;
  bargeIn(epoch: number, firstIndex?: number | null): void;
  push(drive: DecodedDrive): boolean;
  take(clock: number): DecodedDrive | null;
}

/** The pts being heard now, from the drives' arrival and the audio receiver's playout delay (WebRTC). */
export class LiveClock {
  constructor(options?: { windowS?: number });
  readonly ready: boolean;
  observe(pts: number, arrival?: number): void;
  now(time?: number): number;
}

/** Plays frame packets' audio on a continuous WebAudio schedule; `now()` is the pts being heard. */
export class LiveAudio {
  constructor(options?: { context?: AudioContext | null; bufferS?: number; maxAheadS?: number; volume?: number });
  schedule(pts: number, samples: Int16Array, sampleRate: number, options?: { epoch?: number; index?: number }
  ): number | null;
  now(): number;
}

/** Bytes of a drive message's header and of a frame packet's header (docs/live.md). */
export const DRIVE_HEADER_BYTES: number;
export const FRAME_HEADER_BYTES: number;
