// The bundle's ONNX graphs as onnxruntime-web sessions (runtime/onnxruntime_backend.py's job in Python): each graph
// inflated, its weights written into the protobuf (onnx_wire.js), one session per graph, its input and output
// names checked against the manifest.
//
// Backends (docs/web.md, "Graphs: WebAssembly and WebGPU"): 'wasm' (onnxruntime-web's CPU build), 'webgpu' (its
// WebGPU build, the operators WebGPU lacks on wasm), or 'auto' (the default): WebGPU where the browser offers a
// hardware adapter, else wasm. A software adapter (SwiftShader's, what headless Chromium offers) is not chosen by
// 'auto': on a CPU the wasm build is the faster one.

import * as ortWasm from 'onnxruntime-web/wasm';

import { BundleError, label } from './bundle.js';
import { inlineWeights } from './onnx_wire.js';

export const GRAPH_BACKENDS = ['auto', 'wasm', 'webgpu'];

/** Raised when the backend asked for cannot run here (WebGPU without an adapter). */
export class GraphBackendError extends Error {
  constructor(message) {
    super(message);
    this.name = 'GraphBackendError';
  }
}

/** The browser's WebGPU adapter, or null (no navigator.gpu, no adapter, or the request failed). */
async function webgpuAdapter() {
  if (typeof navigator === 'undefined' || !navigator.gpu) return null;
  try {
    return await navigator.gpu.requestAdapter();
  } catch {
    return null;
  }
}

/**
 * The onnxruntime-web build and execution providers for `choice` ('auto', 'wasm' or 'webgpu'): {name, ort,
 * executionProviders, adapter ({vendor, architecture, fallback} or null)}. GraphBackendError when 'webgpu' is asked
 * for and the browser has no adapter.
 */
export async function graphBackend(choice = 'auto') {
  if (!GRAPH_BACKENDS.includes(choice)) {
    throw new GraphBackendError(`graphs must be one of ${GRAPH_BACKENDS.join(', ')}, got ${JSON.stringify(choice)}`);
  }
  const wasm = { name: 'wasm', ort: ortWasm, executionProviders: ['wasm'], adapter: null };
  if (choice === 'wasm') return wasm;
  const adapter = await webgpuAdapter();
  const fallback = Boolean(adapter?.info?.isFallbackAdapter ?? adapter?.isFallbackAdapter);
  if (!adapter || (choice === 'auto' && fallback)) {
    if (choice === 'webgpu') {
      throw new GraphBackendError('WebGPU is not available in this browser (navigator.gpu offers no adapter); use '
        + "graphs: 'wasm' or 'auto'");
    }
    return wasm;
  }
  const ort = await import('onnxruntime-web/webgpu');
  const info = adapter.info ?? {};
  return { name: 'webgpu', ort, executionProviders: ['webgpu', 'wasm'],
    adapter: { vendor: info.vendor ?? '', architecture: info.architecture ?? '', fallback } };
}

const ORT_TYPES = { float32: 'float32', float16: 'float16', int32: 'int32', int64: 'int64', int8: 'int8',
  uint8: 'uint8', uint16: 'uint16', uint32: 'uint32' };

export class GraphSessions {
  constructor(bundle, ort, sessions, backend) {
    this.bundle = bundle;
    this.ort = ort;
    this.sessions = sessions;
    this.backend = backend; // {name, executionProviders, adapter}
    this.calls = {}; // graph name -> calls run so far: which graphs a player really used
  }

  /**
   * Sessions for every graph of `bundle` (or the `names` given). Options: `graphs` (the backend: 'auto', the
   * default, 'wasm' or 'webgpu'; graphBackend), `threads` (wasm threads; default 1, which needs no cross-origin
   * isolation); or, instead of `graphs`, an onnxruntime-web module `ort` with its `executionProviders`.
   */
  static async open(bundle, { names = null, graphs = 'auto', ort = null, executionProviders = null, threads = 1 } = {}) {
    let backend;
    if (ort !== null || executionProviders !== null) {
      backend = { name: 'custom', ort: ort ?? ortWasm, executionProviders: executionProviders ?? ['wasm'], adapter: null };
    } else {
      backend = await graphBackend(graphs);
    }
    ({ ort, executionProviders } = backend);
    if (ort.env?.wasm) ort.env.wasm.numThreads = threads;
    if (ort.env) ort.env.logLevel = 'error';
    const sessions = {};
    for (const name of names ?? bundle.graphNames()) {
      const model = inlineWeights(bundle, name, await bundle.graphBytes(name));
      let session;
      try {
        // logSeverityLevel 3: errors only (the optimizer's notes about CastLike nodes it cannot fold are not).
        session = await ort.InferenceSession.create(model, { executionProviders, graphOptimizationLevel: 'all',
          logSeverityLevel: 3 });
      } catch (error) {
        const reason = String(error?.message ?? error).split(/\s+/).join(' ').slice(0, 400);
        throw new BundleError(`${bundle.name}: ${label('graph', name)} cannot be loaded by onnxruntime-web: ${reason}`);
      }
      checkSignature(bundle, name, session);
      sessions[name] = session;
    }
    const { name, adapter } = backend;
    return new GraphSessions(bundle, ort, sessions, { name, executionProviders, adapter });
  }

  has(name) {
    return Object.hasOwn(this.sessions, name);
  }

  /** Run graph `name` on `feeds` ({input: {data: typed array, dims}}) -> {output: {data, dims}}. */
  async run(name, feeds) {
    const session = this.sessions[name];
    if (!session) throw new BundleError(`${this.bundle.name}: bundle has no ${label('graph', name)}`);
    const declared = Object.fromEntries(this.bundle.graphInfo(name).inputs.map((v) => [v.name, v.dtype]));
    const tensors = {};
    for (const [input, { data, dims }] of Object.entries(feeds)) {
      tensors[input] = new this.ort.Tensor(ORT_TYPES[declared[input]] ?? 'float32', data, dims);
    }
    const results = await session.run(tensors);
    this.calls[name] = (this.calls[name] ?? 0) + 1;
    const out = {};
    for (const [output, tensor] of Object.entries(results)) {
      out[output] = { data: tensor.data, dims: tensor.dims };
      tensor.dispose?.();
    }
    return out;
  }

  async release() {
    for (const session of Object.values(this.sessions)) await session.release();
    this.sessions = {};
  }
}

/** The manifest's input and output names must be the session's (runtime/bundle_checks.py `check_signature`). */
function checkSignature(bundle, name, session) {
  const info = bundle.graphInfo(name);
  for (const [kind, declared, actual] of [['input', info.inputs, session.inputNames],
    ['output', info.outputs, session.outputNames]]) {
    const want = declared.map((v) => v.name).sort();
    const got = [...actual].sort();
    if (want.join('\u0000') !== got.join('\u0000')) {
      throw new BundleError(`${bundle.name}: ${label('graph', name)} ${kind}s are ${JSON.stringify(got)} but the `
        + `manifest declares ${JSON.stringify(want)}`);
    }
  }
}
