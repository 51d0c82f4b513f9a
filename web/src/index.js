// The package's entry (`import { Player } from 'gaussiantalker-web'`): the public API of the browser player
// (docs/web.md, "The API"). Its TypeScript declarations are types/index.d.ts; the client-rendered live session's
// wire pieces are the './live' entry.

export { Bundle, readBundle } from './bundle.js';
export { Camera, CameraError } from './camera.js';
export { AudioError, Drive, DriveError, decodeAudio, resampleAudio } from './drive.js';
export { ARKIT_BLENDSHAPES } from './generated.js';
export { GRAPH_BACKENDS, GraphBackendError } from './graphs.js';
export { BundleError, Player, RenderError } from './player.js';
export { AudioStream } from './stream.js';
