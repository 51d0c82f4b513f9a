// TypeScript declarations of gaussiantalker-web's public API (src/index.js). Kept beside the JavaScript by hand;
// tests/test_web_package.py compiles an app against them with `tsc --strict` and plays a bundle from the packed
// tarball.

/** Every error the player throws carries one line that names the problem. */
export class BundleError extends Error {}
export class CameraError extends Error {}
export class DriveError extends Error {}
export class AudioError extends Error {}
export class RenderError extends Error {}
export class GraphBackendError extends Error {}

/** The 52 ARKit blendshape names, in the order ARKit speakers' weights use. */
export const ARKIT_BLENDSHAPES: readonly string[];
/** The graph backends `Player.load` takes: WebGPU where the browser has a hardware adapter ('auto'), or one. */
export const GRAPH_BACKENDS: readonly GraphBackend[];
export type GraphBackend = 'auto' | 'wasm' | 'webgpu';

/** A pinhole camera, OpenCV convention (x right, y down, z forward; pixel centres at +0.5). */
export interface CameraDict {
  width: number;
  height: number;
  fx: number;
  fy: number;
  cx: number;
  cy: number;
  /** World-to-camera rotation, 3 rows of 3. */
  R: number[][];
  /** World-to-camera translation. */
  t: number[];
  near?: number;
}

export class Camera {
  constructor(fields: CameraDict);
  readonly width: number;
  readonly height: number;
  readonly fx: number;
  readonly fy: number;
  readonly cx: number;
  readonly cy: number;
  readonly R: number[][];
  readonly t: number[];
  readonly near: number;
  static fromDict(data: CameraDict): Camera;
  toDict(): CameraDict;
  /** The same view at another frame size. */
  resized(width: number, height: number): Camera;
  /** The camera's centre in the world, -Rᵀt. */
  center(): number[];
  /** Swung about `target`: yaw about the camera's up axis, then pitch about its right axis (degrees). */
  orbited(yawDeg: number, pitchDeg: number, target: ArrayLike<number>): Camera;
  /** Moved toward `target` (factor < 1) or away (factor > 1). */
  dollied(factor: number, target: ArrayLike<number>): Camera;
}

/** A bundle read and checked (header, manifest, every entry's size and SHA-256). */
export class Bundle {
  readonly name: string;
  readonly manifest: Record<string, unknown>;
  hasBuffer(name: string): boolean;
}

export interface ReadBundleOptions {
  /** Labels errors. */
  name?: string;
  verifyChecksums?: boolean;
}

export function readBundle(buffer: ArrayBuffer | Uint8Array, options?: ReadBundleOptions): Promise<Bundle>;

/** Any audio file the browser decodes, as mono float32 at `sampleRate`. */
export function decodeAudio(bytes: ArrayBuffer | Uint8Array, sampleRate: number): Promise<Float32Array>;
/** Mono float32 samples from one rate to another. */
export function resampleAudio(samples: Float32Array, fromRate: number, toRate: number): Promise<Float32Array>;

/** A tensor fed to a graph. */
export interface GraphInput {
  data: Float32Array;
  dims: number[];
}

/** What `Player.renderFrame` draws: the deform graph's inputs of a frame (a `Drive`, or a live session's `WireDrive`
 * from 'gaussiantalker-web/live'). */
export interface DrawableDrive {
  graphInputs(index: number, center: ArrayLike<number>): Record<string, GraphInput>;
}

/** Per-frame drive rows of one clip and the head's pose track. */
export class Drive implements DrawableDrive {
  readonly rig: 'flame' | 'arkit';
  readonly frames: number;
  readonly width: number;
  readonly rows: Float32Array;
  graphInputs(index: number, center: ArrayLike<number>): Record<string, GraphInput>;
}

/** Audio pushed as it arrives through the bundle's streaming translator (`Player.openAudioStream`). */
export class AudioStream {
  /** Frames ready so far: frames [0, frames) of `drive()` can be drawn. */
  readonly frames: number;
  /** How many frames the rows lag the audio (the translator's lookahead). */
  readonly delay: number;
  /** Mono float32 samples at the player's `sampleRate`, any length; resolves to the frames ready. */
  push(samples: Float32Array): Promise<number>;
  /** The last frames, their lookahead zero-padded; resolves to the frames ready. */
  end(): Promise<number>;
  drive(): Drive;
}

export interface Rig {
  kind: 'flame' | 'arkit';
  fps: number;
  sampleRate: number;
}

export interface PlayerOptions {
  /** Labels errors (default: the URL's file name, or 'bundle'). */
  name?: string;
  /** The output size; the bundle's camera is resized to it. */
  width?: number;
  height?: number;
  /** Draw through this camera instead of the bundle's. */
  camera?: Camera | CameraDict;
  /** RGB in 0..1 (default: the bundle's). */
  background?: [number, number, number];
  /** Override the bundle's runtime defaults (docs/precision.md). */
  renderTarget?: 'float32' | 'float16' | 'uint8';
  renderScale?: number;
  sortKeyBits?: 16 | 32;
  sortInterval?: number;
  /** false: draw quads only. */
  pointSprites?: boolean;
  /** The WebGL2 canvas to draw with (default: an OffscreenCanvas). */
  canvas?: HTMLCanvasElement | OffscreenCanvas | null;
  /** Audio's frames composited into the bundle's reference clip (default: where it has a clip and an inpainting
   * graph), at the clip's size or width x height; false: the bare head. */
  composite?: boolean;
  graphs?: GraphBackend;
  /** onnxruntime-web wasm threads (default 1). */
  threads?: number;
  /** Bring your own onnxruntime-web module and execution providers. */
  ort?: unknown;
  executionProviders?: unknown[];
}

export type FrameOutput = 'uint8' | 'float' | 'rgba_float';

export interface FrameTimings {
  graphs: number;
  sort: number;
  upload?: number;
  draw?: number;
  readback?: number;
  /** Composited frames: decoding the clip's picture and mask, and the inpainting graph with the blend. */
  reference?: number;
  composite?: number;
}

export interface Frame {
  /** uint8: RGB rows top first; float: float32 RGB over the background; rgba_float: premultiplied RGBA. */
  pixels: Uint8Array | Float32Array;
  width: number;
  height: number;
  timings: FrameTimings;
  /** Gaussians drawn. */
  splats: number;
}

/** A LAM motion file (bsData.json): ARKit weights per frame. */
export interface ArkitMotion {
  names: string[];
  metadata?: { fps?: number };
  frames: { weights: number[] }[];
}

/** An app's own FLAME parameters, rows of numbers per frame (GaussianAvatars' flame_param.npz keys). */
export interface FlameArrays {
  expr: number[][];
  rotation?: number[][];
  neck_pose?: number[][];
  jaw_pose?: number[][];
  eyes_pose?: number[][];
  translation?: number[][];
}

export class Player {
  /** Load a bundle (bytes, or a URL to fetch) and make it ready to draw. */
  static load(source: ArrayBuffer | Uint8Array | string | URL, options?: PlayerOptions): Promise<Player>;
  readonly rig: Rig;
  readonly fps: number;
  readonly sampleRate: number;
  /** [width, height] of the frames. */
  readonly frameSize: [number, number];
  readonly camera: Camera;
  readonly bundle: Bundle;
  /** Whether audio's frames are composited into the bundle's reference clip. */
  readonly composited: boolean;
  /** Draw through another camera (a novel view), resized to width x height when given. */
  setCamera(camera: Camera | CameraDict, width?: number, height?: number): void;
  /** The median rest-pose Gaussian: the point to orbit about. */
  headCentre(): Promise<number[]>;
  /** Any audio file the browser decodes, through the bundle's translator or audio model. */
  driveFromAudioFile(bytes: ArrayBuffer | Uint8Array): Promise<Drive>;
  /** Mono float32 samples at any rate. */
  driveFromAudio(samples: Float32Array, sampleRate: number): Promise<Drive>;
  /** Audio pushed as it arrives (a DriveError for a bundle without a streaming translator). */
  openAudioStream(): Promise<AudioStream>;
  /** ARKit speakers: a LAM motion file; FLAME speakers: a FLAME motion npz's bytes or its arrays; null: the bundle's
   * own motion track. */
  driveFromMotion(motion?: string | ArrayBuffer | Uint8Array | ArkitMotion | FlameArrays | null,
                  where?: string): Drive;
  /** ARKit speakers: weights [frames x 52] in ARKIT_BLENDSHAPES order, flat or rows, at `fps`. */
  driveFromWeights(weights: ArrayLike<number> | number[][], fps?: number): Drive;
  /** Frame `index`; an audio drive of a composited player gives composited uint8 frames (other outputs need the
   * bare head). */
  renderFrame(drive: DrawableDrive, index: number, options?: { output?: FrameOutput }): Promise<Frame>;
  /** The frame put on a 2D canvas (resized to it). */
  renderToCanvas(drive: DrawableDrive, index: number, canvas: HTMLCanvasElement | OffscreenCanvas): Promise<Frame>;
  /** Free the graph sessions, GL objects and the sorting worker. */
  release(): Promise<void>;
}
