// npz files (numpy's zip of .npy arrays) read within bounds: the browser's twin of sdk/zip_reader.py `read_npz`
// (docs/untrusted-input.md, "Zip archives").
//
// The zip directory is read here rather than by a zip library because the verdicts must be the Python reader's,
// file by file (tests/test_web_fuzz.py holds them to it): the end record is found, a prefixed archive's offset
// applied, zip64 records and extra fields decoded and the local header checked as Python's zipfile does, and a
// member's CRC is checked once its stream ends. Inflating is fflate's. Every size a header states is bounded by the
// bytes present, the caller's budget and MAX_RATIO before anything is allocated for it; bzip2 and lzma members
// (which numpy never writes) are refused.

import { Inflate } from 'fflate';

import { MAX_NDIM, MAX_NPZ_BYTES, MAX_RATIO, MIN_BUDGET } from './generated.js';
import { NPY_MAGIC, NpyHeaderError, readNpyHeader } from './npy_header.js';

const EOCD = [0x05, 0x06];
const EOCD64 = [0x06, 0x06];
const LOCATOR64 = [0x06, 0x07];
const CENTRAL = [0x01, 0x02];
const LOCAL = [0x03, 0x04];
const STORED = 0;
const DEFLATED = 8;
const METHODS = [0, 8, 12, 14]; // what Python's zipfile reads: stored, deflate, bzip2, lzma
const MAX_EXTRACT_VERSION = 63;
const FLAG_ENCRYPTED = 0x1;
const FLAG_PATCHED = 0x20;
const FLAG_STRONG_ENCRYPTION = 0x40;
const FLAG_UTF8 = 0x800;
const INFLATE_STEP = 1 << 16; // compressed bytes per step: at most ~66 MB of output before the size is checked
const CP437_HIGH = String.fromCharCode(
  0x00c7, 0x00fc, 0x00e9, 0x00e2, 0x00e4, 0x00e0, 0x00e5, 0x00e7, 0x00ea, 0x00eb, 0x00e8, 0x00ef, 0x00ee, 0x00ec, 0x00c4, 0x00c5,
  0x00c9, 0x00e6, 0x00c6, 0x00f4, 0x00f6, 0x00f2, 0x00fb, 0x00f9, 0x00ff, 0x00d6, 0x00dc, 0x00a2, 0x00a3, 0x00a5, 0x20a7, 0x0192,
  0x00e1, 0x00ed, 0x00f3, 0x00fa, 0x00f1, 0x00d1, 0x00aa, 0x00ba, 0x00bf, 0x2310, 0x00ac, 0x00bd, 0x00bc, 0x00a1, 0x00ab, 0x00bb,
  0x2591, 0x2592, 0x2593, 0x2502, 0x2524, 0x2561, 0x2562, 0x2556, 0x2555, 0x2563, 0x2551, 0x2557, 0x255d, 0x255c, 0x255b, 0x2510,
  0x2514, 0x2534, 0x252c, 0x251c, 0x2500, 0x253c, 0x255e, 0x255f, 0x255a, 0x2554, 0x2569, 0x2566, 0x2560, 0x2550, 0x256c, 0x2567,
  0x2568, 0x2564, 0x2565, 0x2559, 0x2558, 0x2552, 0x2553, 0x256b, 0x256a, 0x2518, 0x250c, 0x2588, 0x2584, 0x258c, 0x2590, 0x2580,
  0x03b1, 0x00df, 0x0393, 0x03c0, 0x03a3, 0x03c3, 0x00b5, 0x03c4, 0x03a6, 0x0398, 0x03a9, 0x03b4, 0x221e, 0x03c6, 0x03b5, 0x2229,
  0x2261, 0x00b1, 0x2265, 0x2264, 0x2320, 0x2321, 0x00f7, 0x2248, 0x00b0, 0x2219, 0x00b7, 0x221a, 0x207f, 0x00b2, 0x25a0, 0x00a0,
);

const u16 = (b, at) => b[at] | (b[at + 1] << 8);
const u32 = (b, at) => (b[at] | (b[at + 1] << 8) | (b[at + 2] << 16)) + b[at + 3] * 0x1000000;
// Above 2^53 a Number rounds; every such size or offset is far past the bytes present and refused all the same.
const u64 = (b, at) => u32(b, at) + u32(b, at + 4) * 0x100000000;
const signed = (b, at, sig) => at >= 0 && at + 4 <= b.length && b[at] === 0x50 && b[at + 1] === 0x4b
  && b[at + 2] === sig[0] && b[at + 3] === sig[1];

let crcTable = null;

/** CRC-32 (zip's polynomial) of `bytes`. */
function crc32(bytes) {
  if (!crcTable) {
    crcTable = new Uint32Array(256);
    for (let n = 0; n < 256; n++) {
      let c = n;
      for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
      crcTable[n] = c >>> 0;
    }
  }
  let crc = 0xffffffff;
  for (let i = 0; i < bytes.length; i++) crc = crcTable[(crc ^ bytes[i]) & 0xff] ^ (crc >>> 8);
  return (crc ^ 0xffffffff) >>> 0;
}

/** A member name as zipfile decodes it: UTF-8 under flag bit 11 (an error if invalid), else code page 437. */
function decodeName(bytes, flags) {
  if (flags & FLAG_UTF8) return new TextDecoder('utf-8', { fatal: true }).decode(bytes);
  let name = '';
  for (const b of bytes) name += b < 0x80 ? String.fromCharCode(b) : CP437_HIGH[b - 0x80];
  return name;
}

// -- the directory -------------------------------------------------------------------------------------------------

/** The end record (zipfile `_EndRecData`, `_EndRecData64`): {size, offset, location, zip64} or null. */
function endRecord(bytes, fail) {
  const n = bytes.length;
  if (n < 22) return null;
  let at = n - 22;
  if (!(signed(bytes, at, EOCD) && bytes[n - 2] === 0 && bytes[n - 1] === 0)) {
    at = -1; // a comment follows: the last signature within 64 KiB of the end
    for (let i = n - 4, low = Math.max(n - 65536 - 22, 0); i >= low; i--) {
      if (signed(bytes, i, EOCD)) {
        at = i;
        break;
      }
    }
    if (at < 0 || at + 22 > n) return null;
  }
  const end = { size: u32(bytes, at + 12), offset: u32(bytes, at + 16), location: at, zip64: false };
  const locator = at - 20;
  if (locator < 0 || !signed(bytes, locator, LOCATOR64)) return end;
  if (u32(bytes, locator + 4) !== 0 || u32(bytes, locator + 16) > 1) fail('spans multiple disks');
  const record = locator - 56;
  if (record < 0) fail('is not a zip file (its zip64 end record would start before the file)');
  if (!signed(bytes, record, EOCD64)) return end;
  return { size: u64(bytes, record + 40), offset: u64(bytes, record + 48), location: at, zip64: true };
}

/** An entry's zip64 extra field applied to its sizes and offset (zipfile `ZipInfo._decodeExtra`). */
function decodeExtra(entry, extra, fail) {
  let rest = extra;
  while (rest.length >= 4) {
    const [type, length] = [u16(rest, 0), u16(rest, 2)];
    if (length + 4 > rest.length) fail(`has a corrupt extra field ${type.toString(16).padStart(4, '0')} (size=${length})`);
    if (type === 0x0001) {
      let data = rest.subarray(4, length + 4);
      const take = (field) => {
        if (data.length < 8) fail(`has a corrupt zip64 extra field: ${field} not found`);
        const value = u64(data, 0);
        data = data.subarray(8);
        return value;
      };
      if (entry.fileSize === 0xffffffff || entry.fileSize === 2 ** 64) entry.fileSize = take('file size');
      if (entry.compressSize === 0xffffffff) entry.compressSize = take('compress size');
      if (entry.headerOffset === 0xffffffff) entry.headerOffset = take('header offset');
    }
    rest = rest.subarray(length + 4);
  }
}

/** The central directory's entries (zipfile `_RealGetContents`). */
function directory(bytes, fail) {
  const end = endRecord(bytes, fail);
  if (!end) fail('is not a zip file (no end of central directory record)');
  const concat = end.location - end.size - end.offset - (end.zip64 ? 76 : 0);
  const start = end.offset + concat;
  if (start < 0) fail('has a bad offset for its central directory');
  const data = bytes.subarray(Math.min(start, bytes.length), Math.min(start + end.size, bytes.length));
  const entries = [];
  for (let total = 0; total < end.size;) {
    if (total + 46 > data.length) fail('has a truncated central directory');
    if (!signed(data, total, CENTRAL)) fail('has a bad magic number in its central directory');
    const [nameLength, extraLength, commentLength] = [u16(data, total + 28), u16(data, total + 30), u16(data, total + 32)];
    if (data[total + 6] > MAX_EXTRACT_VERSION) fail(`needs zip version ${(data[total + 6] / 10).toFixed(1)}`);
    const flags = u16(data, total + 8);
    const nameAt = total + 46;
    let name;
    try {
      name = decodeName(data.subarray(nameAt, nameAt + nameLength), flags);
    } catch {
      fail('names a member in invalid UTF-8');
    }
    const entry = { name: name.split('\0')[0], originalName: name, flags, method: u16(data, total + 10),
      crc: u32(data, total + 16), compressSize: u32(data, total + 20), fileSize: u32(data, total + 24),
      headerOffset: u32(data, total + 42) };
    const extraAt = nameAt + nameLength;
    decodeExtra(entry, data.subarray(Math.min(extraAt, data.length), Math.min(extraAt + extraLength, data.length)), fail);
    entry.headerOffset += concat;
    entries.push(entry);
    total += 46 + nameLength + extraLength + commentLength;
  }
  return entries;
}

// -- members -------------------------------------------------------------------------------------------------------

/** Refuse a member that cannot be read within `budget` bytes (sdk/zip_reader.py `check_member`). */
function checkMember(entry, budget, fail) {
  if (entry.flags & FLAG_ENCRYPTED) fail('is encrypted');
  if (!METHODS.includes(entry.method)) {
    fail(`uses compression method ${entry.method}, which is not read (stored, deflate, bzip2, lzma are)`);
  }
  if (entry.fileSize > budget) fail(`states ${entry.fileSize} bytes uncompressed, over the ${budget} bytes left to read`);
  if (entry.fileSize > MAX_RATIO * entry.compressSize + MIN_BUDGET) {
    fail(`states ${entry.fileSize} bytes uncompressed from ${entry.compressSize} compressed, more than ${MAX_RATIO} `
      + 'times as many (a zip bomb or a damaged header)');
  }
  if (entry.method !== STORED && entry.method !== DEFLATED) {
    fail(`is ${entry.method === 12 ? 'bzip2' : 'lzma'}-compressed, which the browser does not read (np.savez and `
      + 'np.savez_compressed write stored and deflate members)');
  }
}

/** A member's bytes, at most its stated size, and whether its stream ended (so its CRC counts), as zipfile reads
 * them: the local header checked, the data cut at the compressed size or the file's end. */
function memberBytes(bytes, entry, fail) {
  const at = entry.headerOffset;
  if (at < 0 || at + 30 > bytes.length) fail('has a truncated file header');
  if (!signed(bytes, at, LOCAL)) fail('has a bad magic number for its file header');
  const [nameLength, extraLength] = [u16(bytes, at + 26), u16(bytes, at + 28)];
  if (entry.flags & FLAG_PATCHED) fail('holds compressed patched data');
  if (entry.flags & FLAG_STRONG_ENCRYPTION) fail('is strongly encrypted');
  let localName;
  try {
    localName = decodeName(bytes.subarray(at + 30, Math.min(at + 30 + nameLength, bytes.length)), u16(bytes, at + 6));
  } catch {
    fail('names itself in invalid UTF-8 in its file header');
  }
  if (localName !== entry.originalName) fail('is named differently in the directory and its file header');
  const start = Math.min(at + 30 + nameLength + extraLength, bytes.length);
  const stop = Math.min(start + entry.compressSize, bytes.length);
  const complete = start + entry.compressSize <= bytes.length;
  const input = bytes.subarray(start, stop);
  if (entry.method === STORED) {
    const out = input.subarray(0, Math.min(input.length, entry.fileSize));
    return { out, ended: complete || out.length >= entry.fileSize };
  }
  const chunks = [];
  let produced = 0;
  const inflate = new Inflate((chunk) => {
    const kept = chunk.subarray(0, Math.max(entry.fileSize - produced, 0)); // never past the stated size
    chunks.push(kept);
    produced += kept.length;
  });
  try {
    // Pushed as not final: a stream cut short yields what it holds, as zlib's decompressor does.
    for (let i = 0; i < input.length && produced < entry.fileSize; i += INFLATE_STEP) {
      inflate.push(input.subarray(i, i + INFLATE_STEP), false);
    }
  } catch (error) {
    fail(`is damaged: ${error.message}`);
  }
  // Whether the deflate stream itself ended within the bytes present (zlib's `eof`): a final push of nothing
  // completes a finished stream and throws for one cut short.
  let ended = complete || produced >= entry.fileSize;
  if (!ended) {
    try {
      inflate.push(new Uint8Array(0), true);
      ended = true;
    } catch {
      ended = false;
    }
  }
  const out = new Uint8Array(produced);
  let offset = 0;
  for (const chunk of chunks) {
    out.set(chunk, offset);
    offset += chunk.length;
  }
  return { out, ended };
}

// -- arrays --------------------------------------------------------------------------------------------------------

function float16(bits) {
  const exponent = (bits >> 10) & 0x1f;
  const fraction = bits & 0x3ff;
  const sign = bits & 0x8000 ? -1 : 1;
  if (exponent === 0) return sign * fraction * 2 ** -24;
  if (exponent === 31) return fraction ? NaN : sign * Infinity;
  return sign * (1 + fraction / 1024) * 2 ** (exponent - 15);
}

// Element readers by kind and size: (view, index, littleEndian) -> the value as a float64.
const ELEMENT_READERS = {
  b1: (v, i) => (v.getUint8(i) ? 1 : 0),
  i1: (v, i) => v.getInt8(i),
  i2: (v, i, le) => v.getInt16(2 * i, le),
  i4: (v, i, le) => v.getInt32(4 * i, le),
  i8: (v, i, le) => Number(v.getBigInt64(8 * i, le)),
  u1: (v, i) => v.getUint8(i),
  u2: (v, i, le) => v.getUint16(2 * i, le),
  u4: (v, i, le) => v.getUint32(4 * i, le),
  u8: (v, i, le) => Number(v.getBigUint64(8 * i, le)),
  f2: (v, i, le) => float16(v.getUint16(2 * i, le)),
  f4: (v, i, le) => v.getFloat32(4 * i, le),
  f8: (v, i, le) => v.getFloat64(8 * i, le),
};

/** `count` values of a numeric dtype from `data` as float64 (numpy's cast: integers rounded to nearest). */
function numericValues(data, dtype, count) {
  const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
  const read = ELEMENT_READERS[`${dtype.kind}${dtype.size}`];
  const little = !dtype.bigEndian;
  const out = new Float64Array(count);
  for (let i = 0; i < count; i++) out[i] = read(view, i, little);
  return out;
}

/** Fortran-ordered values -> C order for `shape`. */
function toC(values, shape) {
  const dims = shape.map(Number);
  if (dims.length < 2) return values;
  const out = new Float64Array(values.length);
  const index = new Array(dims.length).fill(0);
  for (let c = 0; c < values.length; c++) {
    let f = 0;
    for (let d = dims.length - 1; d >= 0; d--) f = f * dims[d] + index[d];
    out[c] = values[f];
    for (let d = dims.length - 1; d >= 0 && ++index[d] === dims[d]; d--) index[d] = 0;
  }
  return out;
}

/**
 * The arrays of an npz file's bytes (only `keys`, when given), never unpickling: {key: {shape: number[], kind,
 * values: Float64Array in C order (numbers; null for strings)}}. Each member's header is checked against its stated
 * size and `maxBytes` before its values are read. Errors are `makeError(message)`, the message naming `where` and
 * the member.
 */
export function readNpz(bytes, { keys = null, where = 'npz', makeError = (m) => new Error(m), maxBytes = MAX_NPZ_BYTES,
  what = 'an npz file' } = {}) {
  const data = bytes instanceof Uint8Array ? bytes : new Uint8Array(bytes);
  const failAs = (label) => (message) => { throw makeError(`${label} ${message}`); };
  if (data.length >= NPY_MAGIC.length && NPY_MAGIC.every((b, i) => data[i] === b)) {
    throw makeError(`${where} is one array, not ${what}`);
  }
  if (!(signed(data, 0, LOCAL) || signed(data, 0, EOCD))) throw makeError(`cannot read ${where} (${what}): not an npz (zip) file`);
  const members = new Map();
  for (const entry of directory(data, failAs(`cannot read ${where} (${what}):`))) {
    if (!entry.name.endsWith('.npy')) continue;
    const key = entry.name.slice(0, -4);
    if (members.has(key)) throw makeError(`${where}: the npz holds ${entry.name} twice`);
    members.set(key, entry);
  }
  let budget = maxBytes;
  const arrays = {};
  for (const [key, entry] of members) {
    if (keys !== null && !keys.includes(key)) continue;
    const fail = failAs(`${where}: member ${entry.name}`);
    checkMember(entry, budget, fail);
    const { out, ended } = memberBytes(data, entry, fail);
    if (ended && crc32(out) !== entry.crc) fail('is damaged: Bad CRC-32');
    let header;
    try {
      header = readNpyHeader(out);
    } catch (error) {
      if (!(error instanceof NpyHeaderError)) throw error;
      fail(`is not a readable npy array: ${error.message.slice(0, 200)}`);
    }
    const { shape, fortran, dtype, descr } = header;
    if (dtype === null) {
      fail(`holds dtype ${typeof descr === 'string' ? JSON.stringify(descr.slice(0, 40)) : 'a record'}; an npz of numbers `
        + 'holds booleans, integers, floats or strings (never pickled objects)');
    }
    if (shape.length > MAX_NDIM || shape.some((n) => n < 0n)) fail(`has an invalid shape (${shape.join(', ')})`);
    const count = shape.reduce((a, n) => a * n, 1n);
    const nbytes = count * BigInt(dtype.size);
    if (BigInt(header.dataStart) + nbytes > BigInt(entry.fileSize)) {
      fail(`has a header that declares [${shape.join(', ')}] ${descr} (${nbytes} bytes), more than the member's `
        + `${entry.fileSize} bytes hold`);
    }
    const body = out.subarray(header.dataStart, header.dataStart + Number(nbytes));
    if (body.length !== Number(nbytes)) fail(`ends after ${body.length} of its ${nbytes} bytes of data`);
    let values = null; // strings are not read: no motion holds them
    if (dtype.kind !== 'S' && dtype.kind !== 'U') {
      values = numericValues(body, dtype, Number(count));
      if (fortran) values = toC(values, shape);
    }
    arrays[key] = { shape: shape.map(Number), kind: dtype.kind, values };
    budget -= entry.fileSize;
  }
  return arrays;
}
