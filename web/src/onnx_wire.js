// A bundle's ONNX graphs carry their weights outside the protobuf (docs/bundle-format.md, "Weights"):
// onnxruntime-web has no AddExternalInitializers, so the weights are written into the protobuf before a session is
// made, as docs/porting.md (1.4) says: each fed top-level initializer gets `raw_data` (TensorProto field 9) = the
// decoded buffer's little-endian bytes, loses `external_data` (13) and `data_location` (14).
// The same walk checks what runtime/bundle_checks.py `check_initializers` checks: every fed initializer exists
// with the buffer's dtype and dims, and no other tensor wants external data.
// Written by hand over the protobuf wire format, as runtime/onnx_wire.py is: five fields of TensorProto and the
// messages that lead to them; the onnx schema and a protobuf library are not shipped to the browser for that.
//
// Field numbers from onnx.proto: ModelProto.graph 7, .functions 25; FunctionProto.node 7; GraphProto.node 1,
// .initializer 5, .sparse_initializer 15; NodeProto.attribute 5; AttributeProto.t 5, .g 6, .tensors 10,
// .graphs 11, .sparse_tensor 22, .sparse_tensors 23; SparseTensorProto.values 1, .indices 2; TensorProto.dims 1,
// .data_type 2, .name 8, .raw_data 9, .external_data 13, .data_location 14 (1 = EXTERNAL).

import { BundleError, ONNX_DTYPES } from './codecs.js';
import { MAX_MESSAGE_DEPTH } from './generated.js';

export { MAX_MESSAGE_DEPTH };

function varint(bytes, pos) {
  let result = 0n;
  let shift = 0n;
  for (;;) {
    if (pos >= bytes.length || shift > 63n) throw new Error('truncated or oversized varint');
    const byte = bytes[pos++];
    result |= BigInt(byte & 0x7f) << shift;
    if (byte < 0x80) return [result, pos];
    shift += 7n;
  }
}

/** The fields of one message: {number, wire, start, end (of the whole field), value (BigInt) or body (bytes)}. */
function* fields(bytes) {
  let pos = 0;
  while (pos < bytes.length) {
    const start = pos;
    let key;
    [key, pos] = varint(bytes, pos);
    const wire = Number(key & 7n);
    const number = Number(key >> 3n);
    let value = null;
    let body = null;
    if (wire === 0) {
      [value, pos] = varint(bytes, pos);
    } else if (wire === 1 || wire === 5) {
      pos += wire === 1 ? 8 : 4;
    } else if (wire === 2) {
      let size;
      [size, pos] = varint(bytes, pos);
      if (BigInt(pos) + size > BigInt(bytes.length)) throw new Error('a field runs past the end of its message');
      body = bytes.subarray(pos, pos + Number(size));
      pos += Number(size);
    } else {
      throw new Error(`unsupported protobuf wire type ${wire}`);
    }
    if (pos > bytes.length) throw new Error('a field runs past the end of its message');
    yield { number, wire, start, end: pos, value, body };
  }
}

const int64 = (v) => (v >= 1n << 63n ? v - (1n << 64n) : v);

function tensorInfo(bytes, topLevel) {
  const info = { name: '', dims: [], dataType: 0, external: false, topLevel };
  for (const f of fields(bytes)) {
    if (f.number === 1 && f.wire === 0) info.dims.push(Number(int64(f.value)));
    else if (f.number === 1 && f.wire === 2) {
      let pos = 0;
      while (pos < f.body.length) {
        let dim;
        [dim, pos] = varint(f.body, pos);
        info.dims.push(Number(int64(dim)));
      }
    } else if (f.number === 2 && f.wire === 0) info.dataType = Number(f.value);
    else if (f.number === 8 && f.wire === 2) info.name = new TextDecoder().decode(f.body);
    else if (f.number === 14 && f.wire === 0) info.external = f.value === 1n;
  }
  return info;
}

const CHILDREN = {
  model: { 7: 'graph', 25: 'function' },
  function: { 7: 'node' },
  graph: { 1: 'node', 5: 'tensor', 15: 'sparse' },
  node: { 5: 'attribute' },
  attribute: { 5: 'tensor', 6: 'subgraph', 10: 'tensor', 11: 'subgraph', 22: 'sparse', 23: 'sparse' },
  sparse: { 1: 'tensor', 2: 'tensor' },
};

/** Every TensorProto reachable from a message of `kind`, as runtime/onnx_wire.py `_walk`. */
function* walk(kind, bytes, topLevel = false, depth = 0) {
  if (depth > MAX_MESSAGE_DEPTH) {
    throw new Error(`its messages nest more than ${MAX_MESSAGE_DEPTH} deep (subgraphs within subgraphs)`);
  }
  for (const f of fields(bytes)) {
    const child = f.wire === 2 ? CHILDREN[kind][f.number] : undefined;
    if (child === 'tensor') yield tensorInfo(f.body, topLevel && kind === 'graph');
    else if (child) yield* walk(child === 'subgraph' ? 'graph' : child, f.body, kind === 'model', depth + 1);
  }
}

function encodeVarint(n) {
  const out = [];
  let v = BigInt(n);
  while (v >= 0x80n) {
    out.push(Number(v & 0x7fn) | 0x80);
    v >>= 7n;
  }
  out.push(Number(v));
  return Uint8Array.from(out);
}

/** A length-delimited field: key, length, body parts. */
function lengthField(number, parts) {
  const size = parts.reduce((n, p) => n + p.length, 0);
  return [encodeVarint((number << 3) | 2), encodeVarint(size), ...parts];
}

function concat(parts) {
  const out = new Uint8Array(parts.reduce((n, p) => n + p.length, 0));
  let pos = 0;
  for (const p of parts) {
    out.set(p, pos);
    pos += p.length;
  }
  return out;
}

/** A TensorProto's bytes with `raw` as its data and no external reference. */
function inlinedTensor(bytes, raw) {
  const parts = [];
  for (const f of fields(bytes)) {
    if (f.number !== 9 && f.number !== 13 && f.number !== 14) parts.push(bytes.subarray(f.start, f.end));
  }
  parts.push(...lengthField(9, [raw]));
  return parts;
}

function inlinedGraph(bytes, weights) {
  const parts = [];
  for (const f of fields(bytes)) {
    if (f.number === 5 && f.wire === 2) {
      const info = tensorInfo(f.body, true);
      if (Object.hasOwn(weights, info.name)) {
        parts.push(...lengthField(5, inlinedTensor(f.body, weights[info.name])));
        continue;
      }
    }
    parts.push(bytes.subarray(f.start, f.end));
  }
  return parts;
}

/**
 * The graph `graphName` of `bundle` ready for onnxruntime-web: its ONNX bytes with every fed initializer's decoded
 * buffer written in. `onnx`: the graph's (inflated) ONNX bytes. Throws BundleError naming the graph.
 */
export function inlineWeights(bundle, graphName, onnx) {
  const where = `${bundle.name}: graph '${graphName}'`;
  const feeds = bundle.graphInfo(graphName).initializers ?? {};
  let tensors;
  try {
    tensors = [...walk('model', onnx)];
  } catch (error) {
    throw new BundleError(`${where} is not a valid ONNX model (${error.message})`);
  }
  const topLevel = new Map(tensors.filter((t) => t.topLevel).map((t) => [t.name, t]));
  for (const t of tensors) {
    if (t.external && !(t.topLevel && Object.hasOwn(feeds, t.name))) {
      throw new BundleError(`${where} tensor '${t.name.slice(0, 100)}' wants external data the bundle does not supply `
        + '(refused: the runtime reads nothing outside the bundle)');
    }
  }
  const weights = {};
  for (const [init, bufferName] of Object.entries(feeds)) {
    const tensor = topLevel.get(init);
    if (!tensor) {
      throw new BundleError(`${where} has no initializer '${init}' (the manifest feeds it from buffer '${bufferName}')`);
    }
    const entry = bundle.manifest.buffers[bufferName];
    const dtype = ONNX_DTYPES[tensor.dataType] ?? `ONNX type ${tensor.dataType}`;
    if (dtype !== entry.dtype || tensor.dims.join(',') !== entry.shape.join(',') || tensor.dims.length !== entry.shape.length) {
      throw new BundleError(`${where} initializer '${init}' is ${dtype} [${tensor.dims.join(', ')}] but buffer `
        + `'${bufferName}' is ${entry.dtype} [${entry.shape.join(', ')}]`);
    }
    const { data } = bundle.buffer(bufferName);
    weights[init] = new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
  }
  const parts = [];
  for (const f of fields(onnx)) {
    if (f.number === 7 && f.wire === 2) parts.push(...lengthField(7, [concat(inlinedGraph(f.body, weights))]));
    else parts.push(onnx.subarray(f.start, f.end));
  }
  return concat(parts);
}
