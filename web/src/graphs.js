// The bundle's ONNX graphs as onnxruntime-web sessions (runtime/onnxruntime_backend.py's job in Python): each graph
// inflated, its weights written into the protobuf (onnx_wire.js), one session per graph, its input and output
// names checked against the manifest.
//
// Execution providers: 'wasm' (onnxruntime-web's CPU backend) is the default and what the fidelity tests run.
// WebGPU is the next step: pass `executionProviders: ['webgpu', 'wasm']` together with the `ort` module of
// `onnxruntime-web/webgpu` (the seam is the `ort` and `executionProviders` options below; nothing else here
// depends on the backend).

import * as ortWasm from 'onnxruntime-web/wasm';

import { BundleError, label } from './bundle.js';
import { inlineWeights } from './onnx_wire.js';

const ORT_TYPES = { float32: 'float32', float16: 'float16', int32: 'int32', int64: 'int64', int8: 'int8',
  uint8: 'uint8', uint16: 'uint16', uint32: 'uint32' };

export class GraphSessions {
  constructor(bundle, ort, sessions) {
    this.bundle = bundle;
    this.ort = ort;
    this.sessions = sessions;
  }

  /**
   * Sessions for every graph of `bundle` (or the `names` given). Options: `ort` (an onnxruntime-web module; default
   * the wasm build), `executionProviders` (default ['wasm']), `threads` (wasm threads; default 1, which needs no
   * cross-origin isolation).
   */
  static async open(bundle, { names = null, ort = ortWasm, executionProviders = ['wasm'], threads = 1 } = {}) {
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
    return new GraphSessions(bundle, ort, sessions);
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
