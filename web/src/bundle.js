// Reads a .gtb bundle from an ArrayBuffer and checks it before anything is decoded: header, manifest digest, the
// entry table, every buffer's dtype/shape/codec against its stored size, and every entry's SHA-256
// (crypto.subtle). The checks and messages are those of sdk/bundle.py (docs/bundle-format.md, "What the reader
// checks, and refuses"); every size is bounded by the bytes present, no count in the file is trusted.

import { BundleError, decodeBuffer, expectedNbytes, inflateExactly, zlibBound } from './codecs.js';
import {
  ALIGN, FORMAT_MAJOR, GRAPH_COMPRESSIONS, HEADER_LAYOUT, HEADER_SIZE, MAGIC, MAX_GRAPH_BYTES, MAX_JSON_DEPTH,
  MAX_MANIFEST_BYTES,
} from './generated.js';

// The header's layout, bounds and magic come from sdk/bundle.py through generated.js (one definition).
export { ALIGN, BundleError, FORMAT_MAJOR, HEADER_SIZE, MAGIC, MAX_GRAPH_BYTES, MAX_JSON_DEPTH, MAX_MANIFEST_BYTES };
// Objects and arrays nested deeper than MAX_JSON_DEPTH are refused, as sdk/json_bounds.py refuses them.
export const MAX_MANIFEST_DEPTH = MAX_JSON_DEPTH;
const [MAGIC_AT, MAGIC_SIZE] = HEADER_LAYOUT.magic;
const [MAJOR_AT] = HEADER_LAYOUT.major;
const [MINOR_AT] = HEADER_LAYOUT.minor;
const [RESERVED_AT] = HEADER_LAYOUT.reserved;
const [LENGTH_AT] = HEADER_LAYOUT.manifest_length;
const [DIGEST_AT] = HEADER_LAYOUT.manifest_sha256;
const [PADDING_AT] = HEADER_LAYOUT.padding;

const align = (n) => Math.ceil(n / ALIGN) * ALIGN;
const isInt = (v) => Number.isSafeInteger(v);
const isObject = (v) => v !== null && typeof v === 'object' && !Array.isArray(v);

/** How an entry is named in errors, as Python's repr quotes it (a long name is cut short). */
export function label(kind, name) {
  const text = String(name);
  return `${kind} '${text.slice(0, 100)}'${text.length > 100 ? '...' : ''}`;
}

/** The 8 magic bytes as Python's bytes repr shows them (b'...'), for the message naming a wrong magic. */
function bytesRepr(bytes) {
  let out = '';
  for (const b of bytes) {
    if (b === 0x27 || b === 0x5c) out += `\\${String.fromCharCode(b)}`;
    else if (b >= 0x20 && b < 0x7f) out += String.fromCharCode(b);
    else out += `\\x${b.toString(16).padStart(2, '0')}`;
  }
  return `b'${out}'`;
}

async function sha256Hex(bytes) {
  const digest = new Uint8Array(await crypto.subtle.digest('SHA-256', bytes));
  return Array.from(digest, (b) => b.toString(16).padStart(2, '0')).join('');
}

/** Whether a JSON text holds an object or array more than `limit` deep (the top level is 1), as sdk/json_bounds.py
 * `nests_deeper_than` says of the parsed value. */
export function nestsDeeperThan(text, limit) {
  let depth = 0;
  for (let i = 0; i < text.length; i++) {
    const ch = text[i];
    if (ch === '"') {
      let j = i + 1;
      while (j < text.length && text[j] !== '"') j += text[j] === '\\' ? 2 : 1;
      i = j;
    } else if (ch === '{' || ch === '[') {
      if (++depth > limit) return true;
    } else if (ch === '}' || ch === ']') {
      depth -= 1;
    }
  }
  return false;
}

/** The first key given twice in one object of a JSON text, or null; RangeError where it nests deeper than
 * MAX_MANIFEST_DEPTH. JSON.parse keeps the last of two keys silently; two readers could then take different values,
 * so the Python reader refuses such a manifest and so does this one.
 * Written by hand: no JSON parser of the platform reports duplicate keys. */
export function duplicateKey(text) {
  const stack = []; // per open container: a Set of keys (object) or null (array)
  let expectKey = false;
  for (let i = 0; i < text.length; i++) {
    const ch = text[i];
    if (ch === '"') {
      let j = i + 1;
      while (j < text.length && text[j] !== '"') j += text[j] === '\\' ? 2 : 1;
      const top = stack[stack.length - 1];
      if (expectKey && top) {
        const key = JSON.parse(text.slice(i, j + 1));
        if (top.has(key)) return key;
        top.add(key);
      }
      expectKey = false;
      i = j;
    } else if (ch === '{' || ch === '[') {
      stack.push(ch === '{' ? new Set() : null);
      expectKey = ch === '{';
      if (stack.length > MAX_MANIFEST_DEPTH) throw new RangeError('the manifest nests too deep');
    } else if (ch === '}' || ch === ']') {
      stack.pop();
    } else if (ch === ',') {
      expectKey = Boolean(stack[stack.length - 1]);
    }
  }
  return null;
}

/** A compressed entry (`compression` not absent or null) names a known compression and an inflated size no larger
 * than a graph may be (sdk/bundle.py `_check_compression`); `fail(why)` makes the error. */
function checkCompression(fail, what, compression, raw) {
  if (!GRAPH_COMPRESSIONS.includes(compression)) {
    throw fail(`${what} has unknown compression '${String(compression).slice(0, 40)}' (this runtime reads: `
      + `${GRAPH_COMPRESSIONS.join(', ')})`);
  }
  if (!(isInt(raw) && raw >= 0 && raw <= MAX_GRAPH_BYTES)) {
    throw fail(`${what} has an invalid raw_nbytes ${JSON.stringify(raw)?.slice(0, 40)}`);
  }
}

const isCompressed = (entry) => entry.compression !== undefined && entry.compression !== null;

function checkTensorList(where, values) {
  const ok = Array.isArray(values) && values.every((v) => isObject(v) && typeof v.name === 'string'
    && typeof v.dtype === 'string' && Array.isArray(v.shape)
    && v.shape.every((d) => isInt(d) || typeof d === 'string'));
  if (!ok) throw new BundleError(`${where} is malformed (each needs a name, a dtype and a shape list)`);
}

/** A bundle read into memory and checked; entries are decoded on demand (`buffer`, `graphBytes`). */
export class Bundle {
  constructor(name, bytes, manifest, payloadStart) {
    this.name = name;
    this.bytes = bytes;
    this.manifest = manifest;
    this.payloadStart = payloadStart;
    this.version = manifest.version;
  }

  graphNames() {
    return Object.keys(this.manifest.graphs).sort();
  }

  hasBuffer(name) {
    return Object.hasOwn(this.manifest.buffers, name);
  }

  hasGraph(name) {
    return Object.hasOwn(this.manifest.graphs, name);
  }

  entryBytes(entry) {
    const start = this.payloadStart + entry.offset;
    return this.bytes.subarray(start, start + entry.nbytes);
  }

  /** Buffer `name` decoded: {dtype, shape, data} with data a typed array of the dtype (int64: BigInt64Array). A
   * buffer stored compressed is inflated first (fflate, synchronous: exactly its raw_nbytes, never more). */
  buffer(name) {
    if (!this.hasBuffer(name)) throw new BundleError(`${this.name}: bundle has no ${label('buffer', name)}`);
    const entry = this.manifest.buffers[name];
    const { name: codec, ...params } = entry.codec;
    let data = this.entryBytes(entry);
    if (isCompressed(entry)) {
      const raw = entry.raw_nbytes;
      data = inflateExactly(data, raw, (detail) => new BundleError(`${this.name}: ${label('buffer', name)} `
        + (detail === null ? `does not inflate to its declared ${raw} bytes` : `does not inflate (${detail})`)));
    }
    try {
      return { dtype: entry.dtype, shape: entry.shape,
        data: decodeBuffer(data, codec, entry.dtype, entry.shape, params) };
    } catch (error) {
      if (error instanceof BundleError) throw new BundleError(`${this.name}: ${label('buffer', name)}: ${error.message}`);
      throw error;
    }
  }

  graphInfo(name) {
    if (!this.hasGraph(name)) {
      throw new BundleError(`${this.name}: bundle has no ${label('graph', name)} (it holds: `
        + `${this.graphNames().join(', ') || 'no graphs'})`);
    }
    return this.manifest.graphs[name];
  }

  /** The graph's ONNX bytes, inflated if stored compressed (never more than its declared raw_nbytes). */
  async graphBytes(name) {
    const entry = this.graphInfo(name);
    const data = this.entryBytes(entry);
    if (!isCompressed(entry)) return data.slice();
    const raw = entry.raw_nbytes;
    const fail = (why) => new BundleError(`${this.name}: ${label('graph', name)} ${why}`);
    const out = await inflateGraph(data, raw, fail);
    if (out === null) throw fail(`does not inflate to its declared ${raw} bytes`);
    // The stream must end with the entry, as Python's reader demands: the platform's inflater checks the Adler-32
    // but may ignore bytes after it, so the entry less its last byte must not inflate (it would, were a byte after
    // the checksum). Graphs are small protobufs (their weights are buffers), so the second pass costs little.
    const shorter = await inflateGraph(data.subarray(0, data.length - 1), raw, fail).catch(() => null);
    if (shorter !== null) throw fail(`does not inflate to its declared ${raw} bytes`);
    return out;
  }
}

/** A zlib stream's bytes if it inflates to exactly `raw` of them (never more are kept), null if to another number;
 * throws `fail(...)` where the stream is damaged. DecompressionStream('deflate') is the zlib format (RFC 1950) the
 * writer uses: the platform's inflater, which checks the stream's Adler-32. */
async function inflateGraph(data, raw, fail) {
  const out = new Uint8Array(raw);
  let filled = 0;
  const reader = new Blob([data]).stream().pipeThrough(new DecompressionStream('deflate')).getReader();
  try {
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      if (filled + value.length > raw) {
        await reader.cancel();
        return null;
      }
      out.set(value, filled);
      filled += value.length;
    }
  } catch (error) {
    throw fail(`does not inflate (${error.message})`);
  }
  return filled === raw ? out : null;
}

/** Read and check a bundle held in `buffer` (ArrayBuffer or Uint8Array); `name` labels every error. Every entry's
 * checksum is verified here, so damage fails at load, never mid-video. Throws BundleError. */
export async function readBundle(buffer, { name = 'bundle', verifyChecksums = true } = {}) {
  const bytes = buffer instanceof Uint8Array ? buffer : new Uint8Array(buffer);
  const size = bytes.byteLength;
  const fail = (why) => new BundleError(`${name}: ${why}`);
  if (size < HEADER_SIZE) throw fail(`truncated inside the header (${size} of ${HEADER_SIZE} bytes)`);
  const header = new DataView(bytes.buffer, bytes.byteOffset, HEADER_SIZE);
  const magic = bytes.subarray(MAGIC_AT, MAGIC_AT + MAGIC_SIZE);
  if (String.fromCharCode(...magic) !== MAGIC) throw fail(`not a GaussianTalker bundle (bad magic ${bytesRepr(magic)})`);
  const major = header.getUint16(MAJOR_AT, true);
  const minor = header.getUint16(MINOR_AT, true);
  if (major !== FORMAT_MAJOR) {
    throw fail(`bundle format version ${major}.${minor} is not supported by this runtime (reads ${FORMAT_MAJOR}.x); `
      + 're-export with a matching gt-export');
  }
  if (header.getUint32(RESERVED_AT, true) !== 0 || bytes.subarray(PADDING_AT, HEADER_SIZE).some((b) => b !== 0)) {
    throw fail('reserved header bytes are not zero (corrupt header)');
  }
  const manifestLength = header.getBigUint64(LENGTH_AT, true);
  if (manifestLength > BigInt(MAX_MANIFEST_BYTES)) {
    throw fail(`manifest claims ${manifestLength} bytes, over the ${MAX_MANIFEST_BYTES} limit (corrupt header)`);
  }
  const length = Number(manifestLength);
  if (HEADER_SIZE + length > size) {
    throw fail(`truncated inside the manifest: it needs bytes ${HEADER_SIZE}..${HEADER_SIZE + length}, the file ends `
      + `at ${size} (or the header's manifest length is corrupt)`);
  }
  const manifestBytes = bytes.subarray(HEADER_SIZE, HEADER_SIZE + length);
  const digest = new Uint8Array(await crypto.subtle.digest('SHA-256', manifestBytes));
  if (!digest.every((b, i) => b === bytes[DIGEST_AT + i])) throw fail('manifest checksum mismatch (corrupt manifest or header)');
  let manifest;
  try {
    const text = new TextDecoder('utf-8', { fatal: true }).decode(manifestBytes);
    manifest = JSON.parse(text);
    const twice = duplicateKey(text);
    if (twice !== null) throw new SyntaxError(`key '${twice.slice(0, 80)}' appears twice in one object`);
  } catch (error) {
    const detail = error instanceof RangeError ? 'it nests too deep' : error.message.split(/\s+/).join(' ').slice(0, 200);
    throw fail(`manifest is not valid JSON: ${detail}`);
  }
  if (!isObject(manifest) || manifest.format !== 'gaussiantalker-bundle') {
    throw fail('manifest does not describe a gaussiantalker-bundle');
  }
  const version = manifest.version;
  if (!(Array.isArray(version) && version.length === 2 && version[0] === major && version[1] === minor)) {
    throw fail(`header says format version ${major}.${minor} but the manifest says ${JSON.stringify(version)} `
      + '(corrupt header)');
  }
  const payloadStart = HEADER_SIZE + align(length);
  if (payloadStart > size) {
    throw fail(`truncated after the manifest (the payload starts at byte ${payloadStart}, the file ends at ${size})`);
  }
  if (bytes.subarray(HEADER_SIZE + length, payloadStart).some((b) => b !== 0)) {
    throw fail('padding after the manifest is not zero (corrupt file)');
  }
  checkEntries(name, manifest, payloadStart, size);
  const bundle = new Bundle(name, bytes, manifest, payloadStart);
  if (verifyChecksums) await verifyAll(bundle);
  return bundle;
}

function checkEntries(name, manifest, payloadStart, size) {
  const fail = (why) => new BundleError(`${name}: ${why}`);
  const payloadSize = manifest.payload_size;
  if (!isInt(payloadSize) || payloadSize < 0) throw fail('manifest has no valid payload_size');
  for (const kind of ['graphs', 'buffers']) {
    if (!isObject(manifest[kind])) throw fail(`manifest has no '${kind}' table`);
  }
  const labelled = [];
  for (const kind of ['buffers', 'graphs']) {
    for (const [entryName, entry] of Object.entries(manifest[kind])) labelled.push([label(kind.slice(0, -1), entryName), entry]);
  }
  for (const [what, entry] of labelled) {
    if (!isObject(entry)) throw fail(`${what} entry is malformed`);
    const { offset, nbytes } = entry;
    if (!(isInt(offset) && isInt(nbytes) && offset >= 0 && nbytes >= 0)) throw fail(`${what} has an invalid offset/size`);
    if (offset + nbytes > payloadSize) {
      throw fail(`${what} lies outside the payload (offset ${offset}, ${nbytes} bytes, payload ${payloadSize})`);
    }
    if (!(typeof entry.sha256 === 'string' && /^[0-9a-f]{64}$/.test(entry.sha256))) throw fail(`${what} has no valid sha256`);
  }
  // Name the first entry the file cuts short, before anything is read.
  for (const [what, entry] of [...labelled].sort((a, b) => a[1].offset - b[1].offset)) {
    const start = payloadStart + entry.offset;
    if (start + entry.nbytes > size) {
      throw fail(`truncated inside ${what}: it needs bytes ${start}..${start + entry.nbytes}, the file ends at ${size}`);
    }
  }
  const entriesEnd = labelled.reduce((end, [, entry]) => Math.max(end, entry.offset + entry.nbytes), 0);
  if (payloadSize !== align(entriesEnd)) {
    throw fail(`manifest payload_size ${payloadSize} disagrees with its entries (they end at ${entriesEnd}; corrupt manifest)`);
  }
  if (payloadStart + payloadSize > size) {
    throw fail(`truncated inside the padding after the last entry (the payload ends at byte ${payloadStart + payloadSize}, `
      + `the file at ${size})`);
  }
  for (const [bufferName, entry] of Object.entries(manifest.buffers)) {
    const { shape, dtype, codec } = entry;
    const what = label('buffer', bufferName);
    if (!(Array.isArray(shape) && shape.every(isInt) && typeof dtype === 'string' && isObject(codec)
          && typeof codec.name === 'string')) {
      throw fail(`${what} has a malformed dtype, shape or codec (${JSON.stringify(dtype)?.slice(0, 40)}, `
        + `${JSON.stringify(shape)?.slice(0, 80)}, ${JSON.stringify(codec)?.slice(0, 80)})`);
    }
    if (shape.some((d) => d < 0)) throw fail(`${what}: invalid buffer shape ${JSON.stringify(shape).slice(0, 120)}`);
    const { name: codecName, ...params } = codec;
    let wanted;
    try {
      wanted = expectedNbytes(codecName, dtype, shape, params);
    } catch (error) {
      if (error instanceof BundleError) throw fail(`${what}: ${error.message}`);
      throw error;
    }
    if (!isCompressed(entry)) {
      if (wanted !== BigInt(entry.nbytes)) {
        throw fail(`${what} declares dtype ${dtype} shape [${shape.join(', ')}] (${wanted} bytes) but stores `
          + `${entry.nbytes} bytes`);
      }
      continue;
    }
    // Stored as a zlib stream (format 1.3): it inflates to the codec's size, and is no larger than zlib makes it.
    checkCompression(fail, what, entry.compression, entry.raw_nbytes);
    if (BigInt(entry.raw_nbytes) !== wanted || BigInt(entry.nbytes) > zlibBound(wanted)) {
      throw fail(`${what} declares dtype ${dtype} shape [${shape.join(', ')}] (${wanted} bytes) but its stream's `
        + `raw_nbytes is ${entry.raw_nbytes} and it stores ${entry.nbytes} bytes (at most ${zlibBound(wanted)} `
        + 'for that)');
    }
  }
  for (const [graphName, entry] of Object.entries(manifest.graphs)) {
    const what = label('graph', graphName);
    const initializers = entry.initializers === undefined ? {} : entry.initializers;  // null is malformed
    if (!(isObject(initializers) && Object.values(initializers).every((v) => typeof v === 'string'))) {
      throw fail(`${what} has a malformed initializers table`);
    }
    for (const bufferName of Object.values(initializers)) {
      if (!Object.hasOwn(manifest.buffers, bufferName)) throw fail(`${what} needs unknown ${label('buffer', bufferName)}`);
    }
    for (const kind of ['inputs', 'outputs']) checkTensorList(`${name}: ${what} ${kind}`, entry[kind]);
    if (isCompressed(entry)) checkCompression(fail, what, entry.compression, entry.raw_nbytes);
  }
}

/** Check every graph's and buffer's SHA-256 (in manifest order: graphs, then buffers). */
async function verifyAll(bundle) {
  const entries = [];
  for (const kind of ['graphs', 'buffers']) {
    for (const [entryName, entry] of Object.entries(bundle.manifest[kind])) entries.push([label(kind.slice(0, -1), entryName), entry]);
  }
  const digests = await Promise.all(entries.map(([, entry]) => sha256Hex(bundle.entryBytes(entry))));
  entries.forEach(([what, entry], i) => {
    if (digests[i] !== entry.sha256) throw new BundleError(`${bundle.name}: checksum mismatch in ${what} (the file is corrupt)`);
  });
}
