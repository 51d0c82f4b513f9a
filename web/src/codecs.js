// Buffer codecs of a .gtb bundle: the stored size each implies (checked before anything is read) and decoding.
// The same codecs, parameters and arithmetic as sdk/codecs.py (docs/bundle-format.md, "Codecs"): quantised values
// are computed in double precision and rounded once to the dtype, so the decoded weights equal the Python
// runtime's bit for bit.

import { Unzlib } from 'fflate';

import {
  DTYPE_TABLE, FLOAT32_MAX, INDEX_TYPES, MAX_CHUNK, MAX_CODEBOOK, MAX_ELEMENTS as MAX_ELEMENTS_NUMBER, MAX_NDIM,
  QUANT_BITS,
} from './generated.js';

export class BundleError extends Error {
  constructor(message) {
    super(message);
    this.name = 'BundleError';
  }
}

// The dtypes' ONNX codes and sizes, the bounds and the codecs' parameters come from sdk/codecs.py through
// generated.js (one definition); only each dtype's typed array is the browser's own.
const ARRAYS = { float32: Float32Array, float16: Uint16Array, int32: Int32Array, int64: BigInt64Array,
  int8: Int8Array, uint8: Uint8Array, uint16: Uint16Array, uint32: Uint32Array }; // float16: raw half bits

/** dtype -> [ONNX TensorProto.DataType, bytes per element, typed array constructor]. */
export const DTYPES = Object.fromEntries(Object.entries(DTYPE_TABLE).map(([name, [code, size]]) => {
  const array = ARRAYS[name];
  if (!array || array.BYTES_PER_ELEMENT !== size) throw new Error(`codecs.js has no ${size}-byte array for ${name}`);
  return [name, [code, size, array]];
}));
export const ONNX_DTYPES = Object.fromEntries(Object.entries(DTYPES).map(([name, [code]]) => [code, name]));
export { MAX_CHUNK, MAX_CODEBOOK, MAX_NDIM };
export const MAX_ELEMENTS = BigInt(MAX_ELEMENTS_NUMBER);
const INDEX_ARRAYS = Object.fromEntries(INDEX_TYPES.map((name) => [name, [DTYPES[name][1], DTYPES[name][2]]]));
const INTEGER_MAX = { int32: 2 ** 31 - 1, int64: Number.MAX_SAFE_INTEGER, int8: 127, uint8: 255, uint16: 65535,
  uint32: 2 ** 32 - 1 };
const QUANT_CODECS = Object.fromEntries(QUANT_BITS.map((bits) => [`q${bits}`, bits]));

const isFloat = (dtype) => dtype.startsWith('float');

function chunkParam(params, codec) {
  const chunk = params.chunk;
  if (!Number.isInteger(chunk) || chunk < 1 || chunk > MAX_CHUNK) {
    throw new BundleError(`codec '${codec}' needs an integer chunk in 1..${MAX_CHUNK}, got ${JSON.stringify(chunk)}`);
  }
  return chunk;
}

function indexType(params) {
  if (!Object.hasOwn(INDEX_ARRAYS, params.stored)) {
    throw new BundleError(`codec 'index' needs stored in ${INDEX_TYPES.join(', ')}, got `
      + `${JSON.stringify(params.stored)}`);
  }
  return params.stored;
}

/** A `vq` entry's codebook size (sdk/codecs.py `_entries_param`), or BundleError. */
function entriesParam(params) {
  const entries = params.entries;
  if (!Number.isInteger(entries) || entries < 1 || entries > MAX_CODEBOOK) {
    throw new BundleError(`codec 'vq' needs an integer entries in 1..${MAX_CODEBOOK}, got ${JSON.stringify(entries)}`);
  }
  return entries;
}

/** Bits a `vq` index takes: ceil(log2 entries), at least 1 (sdk/codecs.py `index_bits`). */
const indexBits = (entries) => Math.max(1, 32 - Math.clz32(entries - 1));

/** [vectors N, values per vector D] of a `vq` shape, BigInts: N along the last axis (1 for a 0-d shape), D the
 * product of the other dimensions. */
function vqLayout(shape) {
  return [shape.length ? BigInt(shape[shape.length - 1]) : 1n, count(shape.slice(0, -1))];
}

/** The most bytes zlib's stream of `nbytes` bytes takes (sdk/codecs.py `zlib_bound`), a BigInt. */
export function zlibBound(nbytes) {
  return nbytes + 5n * (nbytes / 65535n + 1n) + 6n;
}

/** A sparse entry's [nnz, the zlib mask's stored bytes or null, the inner codec's params] (sdk/codecs.py
 * `_sparse_param`), or BundleError. */
function sparseParam(params, n) {
  const sparse = params.sparse;
  const plain = sparse !== null && typeof sparse === 'object' && !Array.isArray(sparse);
  const nnz = plain ? sparse.nnz : undefined;
  const zipped = plain && Object.hasOwn(sparse, 'mask_zlib') ? sparse.mask_zlib : null;
  const bound = zlibBound((n + 7n) / 8n);
  if (!Number.isInteger(nnz) || nnz < 0 || BigInt(nnz) > n
      || Object.keys(sparse).some((key) => key !== 'nnz' && key !== 'mask_zlib')
      || (zipped !== null && !(Number.isInteger(zipped) && zipped >= 0 && BigInt(zipped) <= bound))) {
    throw new BundleError(`sparse buffer needs {"nnz": K} with 0 <= K <= ${n} (its element count), and `
      + `optionally "mask_zlib": M, at most ${bound} bytes; got ${JSON.stringify(sparse)}`.slice(0, 200));
  }
  const { sparse: _, ...inner } = params;
  return [nnz, zipped, inner];
}

/** Adler-32 of `bytes` (RFC 1950), which fflate's inflater does not check and Python's zlib does. */
function adler32(bytes) {
  let a = 1;
  let b = 0;
  for (let i = 0; i < bytes.length; i += 3800) { // 3800 sums stay exact in doubles before the modulo
    const end = Math.min(i + 3800, bytes.length);
    for (let k = i; k < end; k++) {
      a += bytes[k];
      b += a;
    }
    a %= 65521;
    b %= 65521;
  }
  return ((b << 16) | a) >>> 0;
}

// Stored bytes handed to fflate a push at a time: it inflates each push whole, so a stream that inflates past the
// bytes wanted is stopped within one push's output (DEFLATE expands at most 1032:1), never inflated to its end.
const INFLATE_STEP = 16384;

/** The exactly `nbytes` bytes a zlib stream (RFC 1950) inflates to: the stream complete and its checksum (the last
 * four bytes) right, as sdk/bundle.py `_inflate` and sdk/codecs.py `_inflated_mask` want. Otherwise throws
 * `refuse(detail)`: detail the inflater's message where the stream is damaged, null where it inflates to other than
 * `nbytes` bytes. Output past `nbytes` is never kept. fflate does not say where the DEFLATE data ended, so bytes
 * between its end and the checksum, which Python refuses, are not looked at; the bytes returned are still exactly
 * the checksummed ones. */
export function inflateExactly(stored, nbytes, refuse) {
  const out = new Uint8Array(nbytes);
  let produced = 0;
  let overflow = false;
  const inflater = new Unzlib((chunk) => {
    const kept = chunk.subarray(0, Math.max(nbytes - produced, 0)); // never past the bytes wanted
    overflow ||= kept.length < chunk.length;
    out.set(kept, produced);
    produced += kept.length;
  });
  try {
    for (let at = 0; at < stored.length && !overflow; at += INFLATE_STEP) {
      inflater.push(stored.subarray(at, at + INFLATE_STEP), false);
    }
    if (!overflow) inflater.push(new Uint8Array(0), true);
  } catch (error) {
    throw refuse(error.message);
  }
  const view = new DataView(stored.buffer, stored.byteOffset, stored.byteLength);
  if (overflow || produced !== nbytes || stored.length < 6 || view.getUint32(stored.length - 4) !== adler32(out)) {
    throw refuse(null);
  }
  return out;
}

/** The bitmask a zlib-stored mask holds (sdk/codecs.py `_inflated_mask`): exactly `nbytes` bytes; BundleError
 * otherwise. */
function inflatedMask(stored, nbytes) {
  return inflateExactly(stored, nbytes, (detail) => new BundleError(detail === null
    ? `sparse buffer's zlib mask does not inflate to exactly its ${nbytes} bytes`
    : `sparse buffer's zlib mask is damaged (${detail})`));
}

/** A sparse buffer: the bitmask of its nonzero elements (C order, lowest bit first; stored as it is or as a zlib
 * stream), then the codec's payload of those values; scattered into zeros. The mask must mark exactly nnz elements
 * and leave its spare bits clear. */
function decodeSparse(payload, codec, dtype, n, params) {
  const [nnz, zipped, inner] = sparseParam(params, BigInt(n));
  const maskBytes = Math.ceil(n / 8);
  const stored = zipped === null ? maskBytes : zipped;
  const bytes = zipped === null ? payload : inflatedMask(payload.subarray(0, stored), maskBytes);
  let marked = 0;
  for (let i = 0; i < maskBytes; i++) {
    let byte = bytes[i];
    if (i === maskBytes - 1 && n % 8 && byte >> (n % 8)) {
      throw new BundleError('sparse buffer\'s mask has bits set past its last element');
    }
    for (; byte; byte &= byte - 1) marked += 1;
  }
  if (marked !== nnz) throw new BundleError(`sparse buffer's mask marks ${marked} nonzero elements, its nnz says ${nnz}`);
  const values = decodeBuffer(payload.subarray(stored), codec, dtype, [nnz], inner);
  const out = new values.constructor(n);
  for (let i = 0, k = 0; i < n; i++) {
    if (bytes[i >> 3] & (1 << (i & 7))) out[i] = values[k++];
  }
  return out;
}

/** Element count of a shape as a BigInt (a huge claimed shape is a big number, never an allocation). */
function count(shape) {
  return shape.reduce((n, d) => n * BigInt(d), 1n);
}

/** Stored bytes implied by codec, dtype, shape and parameters (a BigInt), or BundleError: sdk/codecs.py
 * `expected_nbytes`, checked against the entry's nbytes before anything is allocated. */
export function expectedNbytes(codec, dtype, shape, params) {
  if (!Object.hasOwn(DTYPES, dtype)) {
    throw new BundleError(`unsupported buffer dtype '${dtype}' (supported: ${Object.keys(DTYPES).join(', ')})`);
  }
  if (!['raw', 'fp16', 'q16', 'q8', 'q4', 'index', 'vq'].includes(codec)) {
    throw new BundleError(`unknown buffer codec '${codec}' (known: raw, fp16, q16, q8, q4, index, vq)`);
  }
  const floatOnly = codec === 'fp16' || codec === 'vq' || Object.hasOwn(QUANT_CODECS, codec);
  if (floatOnly && !isFloat(dtype)) {
    throw new BundleError(`codec '${codec}' cannot decode to dtype '${dtype}' (floating-point only)`);
  }
  if (codec === 'index' && isFloat(dtype)) {
    throw new BundleError(`codec '${codec}' cannot decode to dtype '${dtype}' (integers only)`);
  }
  const spread = shape.reduce((n, d) => n * BigInt(Math.max(d, 1)), 1n);
  if (shape.length > MAX_NDIM || spread >= MAX_ELEMENTS) {
    throw new BundleError(`invalid buffer shape ${`[${shape.join(', ')}]`.slice(0, 120)} (at most ${MAX_NDIM} dimensions, `
      + `fewer than ${MAX_ELEMENTS} elements)`);
  }
  const n = count(shape);
  if (Object.hasOwn(params, 'sparse')) {
    const [nnz, zipped, inner] = sparseParam(params, n);
    return (zipped === null ? (n + 7n) / 8n : BigInt(zipped)) + expectedNbytes(codec, dtype, [nnz], inner);
  }
  if (codec === 'raw') return n * BigInt(DTYPES[dtype][1]);
  if (codec === 'fp16') return 2n * n;
  if (codec === 'index') return n * BigInt(INDEX_ARRAYS[indexType(params)][0]);
  if (codec === 'vq') {
    const entries = entriesParam(params);
    const [vectors, width] = vqLayout(shape);
    return 2n * BigInt(entries) * width + (vectors * BigInt(indexBits(entries)) + 7n) / 8n;
  }
  const bits = BigInt(QUANT_CODECS[codec]);
  const chunk = BigInt(chunkParam(params, codec));
  return 8n * ((n + chunk - 1n) / chunk) + (n * bits + 7n) / 8n;
}

/** IEEE binary16 bits -> number. */
export function halfToFloat(h) {
  const sign = h & 0x8000 ? -1 : 1;
  const exponent = (h >> 10) & 0x1f;
  const fraction = h & 0x3ff;
  if (exponent === 0) return sign * fraction * 2 ** -24;
  if (exponent === 31) return fraction ? NaN : sign * Infinity;
  return sign * (1 + fraction / 1024) * 2 ** (exponent - 15);
}

/** A number -> IEEE binary16 bits, rounded to nearest even as numpy's astype(float16). */
export function floatToHalf(value) {
  if (Number.isNaN(value)) return 0x7e00;
  const sign = value < 0 || Object.is(value, -0) ? 0x8000 : 0;
  const a = Math.abs(value);
  if (a >= 65520) return sign | 0x7c00; // rounds past the largest half: infinity
  if (a < 2 ** -14) { // subnormal (or zero): units of 2^-24
    return sign | roundEven(a * 2 ** 24);
  }
  let exponent = Math.floor(Math.log2(a));
  if (2 ** exponent > a) exponent -= 1; // log2 rounding
  if (2 ** (exponent + 1) <= a) exponent += 1;
  const mantissa = roundEven((a / 2 ** exponent - 1) * 1024);
  return sign | ((((exponent + 15) << 10) + mantissa) & 0xffff); // a mantissa of 1024 carries into the exponent
}

function roundEven(x) {
  const floor = Math.floor(x);
  const rest = x - floor;
  if (rest > 0.5 || (rest === 0.5 && floor % 2 === 1)) return floor + 1;
  return floor;
}

/** Numbers (already rounded as float32 or exact) -> the typed array of `dtype`. */
function fromNumbers(values, dtype) {
  if (dtype === 'float32') return Float32Array.from(values);
  if (dtype === 'float16') return Uint16Array.from(values, floatToHalf);
  throw new BundleError(`cannot store numbers as ${dtype}`);
}

/** Copy of `bytes` as a typed array of `Type` (the copy makes it aligned; Uint8Array's own slice, which copies
 * even where `bytes` is a node Buffer, whose slice is a view). */
function view(bytes, Type) {
  const copy = Uint8Array.prototype.slice.call(bytes);
  return new Type(copy.buffer, copy.byteOffset, copy.byteLength / Type.BYTES_PER_ELEMENT);
}

function decodeQuantised(bytes, dtype, n, params, codec) {
  const bits = QUANT_CODECS[codec];
  const levels = 2 ** bits - 1;
  const chunk = chunkParam(params, codec);
  const chunks = Math.ceil(n / chunk);
  const data = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const low = new Float64Array(chunks);
  const step = new Float64Array(chunks);
  for (let c = 0; c < chunks; c++) {
    low[c] = data.getFloat32(4 * c, true);
    step[c] = data.getFloat32(4 * (chunks + c), true);
    if (!(Number.isFinite(low[c]) && Number.isFinite(step[c]) && step[c] >= 0 && Math.abs(low[c]) <= FLOAT32_MAX
          && low[c] + step[c] * levels <= FLOAT32_MAX)) {
      throw new BundleError(`codec q${bits}: damaged chunk parameters (a minimum or step is not finite, a step `
        + 'is negative, or a chunk\'s range exceeds float32)');
    }
  }
  const base = 8 * chunks;
  const values = new Float64Array(n);
  for (let i = 0; i < n; i++) {
    let code;
    if (bits === 16) code = data.getUint16(base + 2 * i, true);
    else if (bits === 8) code = bytes[base + i];
    else code = i % 2 === 0 ? bytes[base + (i >> 1)] & 0x0f : bytes[base + (i >> 1)] >> 4;
    const c = Math.floor(i / chunk);
    values[i] = low[c] + code * step[c]; // double precision, rounded once below (docs/bundle-format.md)
  }
  return fromNumbers(values, dtype);
}

/** A codebook (docs/bundle-format.md, "vq"): K x D binary16 values, then N indices of b bits each in one bit stream
 * (index n's bit j is stream bit n * b + j, the lowest bit of each byte first); value (d, n) = codebook[index n][d],
 * the half converted exactly (float16: its bits). The codebook must be finite, every index below K and the bits
 * past the last index clear. */
function decodeVq(bytes, dtype, shape, params) {
  const entries = entriesParam(params);
  const [vectors, width] = vqLayout(shape).map(Number);
  const table = view(bytes.subarray(0, 2 * entries * width), Uint16Array); // little-endian halves, read as fp16's
  if (table.some((h) => (h & 0x7c00) === 0x7c00)) {
    throw new BundleError('codec vq: the codebook holds a value that is not finite');
  }
  const bits = indexBits(entries);
  const codes = bytes.subarray(2 * entries * width);
  const used = vectors * bits;
  const last = Math.floor(used / 8);
  if ((used % 8 && codes[last] >> (used % 8)) || codes.subarray(Math.ceil(used / 8)).some((b) => b !== 0)) {
    throw new BundleError('codec vq: bits are set past the last index');
  }
  const index = new Uint16Array(vectors); // b <= 16
  let largest = 0;
  for (let n = 0, at = 0; n < vectors; n++, at += bits) {
    const i = Math.floor(at / 8); // b + 7 <= 23 bits lie in bytes i..i+2 (past the end reads as 0)
    index[n] = ((codes[i] | (codes[i + 1] << 8) | (codes[i + 2] << 16)) >>> (at % 8)) & (2 ** bits - 1);
    largest = Math.max(largest, index[n]);
  }
  if (vectors && largest >= entries) {
    throw new BundleError(`codec vq: index ${largest} past the codebook's ${entries} entries`);
  }
  const values = dtype === 'float16' ? table : Float32Array.from(table, halfToFloat);
  const out = new values.constructor(vectors * width);
  for (let d = 0; d < width; d++) {
    for (let n = 0; n < vectors; n++) out[d * vectors + n] = values[index[n] * width + d];
  }
  return out;
}

/** Decode one buffer's stored bytes (length already checked) -> typed array of its dtype (int64: BigInt64Array,
 * float16: Uint16Array of half bits). */
export function decodeBuffer(bytes, codec, dtype, shape, params) {
  const n = Number(count(shape));
  if (Object.hasOwn(params, 'sparse')) return decodeSparse(bytes, codec, dtype, n, params);
  if (codec === 'raw') return view(bytes, DTYPES[dtype][2]);
  if (codec === 'fp16') {
    const halves = view(bytes, Uint16Array);
    return dtype === 'float16' ? halves : Float32Array.from(halves, halfToFloat);
  }
  if (Object.hasOwn(QUANT_CODECS, codec)) return decodeQuantised(bytes, dtype, n, params, codec);
  if (codec === 'vq') return decodeVq(bytes, dtype, shape, params);
  const stored = view(bytes, INDEX_ARRAYS[indexType(params)][1]);
  let largest = 0;
  for (const v of stored) largest = v > largest ? v : largest;
  if (largest > INTEGER_MAX[dtype]) {
    throw new BundleError(`codec index: stored value ${largest} does not fit dtype ${dtype}`);
  }
  if (dtype === 'int64') return BigInt64Array.from(stored, (v) => BigInt(v));
  return DTYPES[dtype][2].from(stored);
}
