// The header of a .npy array (numpy's format 1.0 and 2.0), read as numpy reads it: a Python dict literal giving
// 'descr', 'fortran_order' and 'shape' (docs/untrusted-input.md, "Zip archives").
//
// Written here because no npm package reads a .npy header with numpy's verdicts: numpy evaluates the header as a
// Python literal, so this reads the literal subset numpy can be given (dicts, tuples, lists, strings, integers,
// True/False/None, comments and line joins) and refuses the rest, as numpy does. Anything else a header could
// spell (floats, sets, bytes) is refused too, which is numpy's verdict for a header of an array of numbers.

export const NPY_MAGIC = [0x93, 0x4e, 0x55, 0x4d, 0x50, 0x59]; // \x93NUMPY
const MAX_HEADER_CHARS = 10000; // numpy's max_header_size
const MAX_NESTING = 200; // Python's parser refuses deeper brackets
const MAX_INT_DIGITS = 4300; // Python's limit on a decimal integer literal

/** Raised for a header numpy would not read; the caller names the member. */
export class NpyHeaderError extends Error {}

// -- a Python literal, the subset numpy's headers can hold --------------------------------------------------------

const STRING_PREFIX = /^[uUrR]?$/;

class LiteralReader {
  constructor(text) {
    this.text = text;
    this.at = 0;
    this.depth = 0; // open brackets: newlines inside them are whitespace
  }

  fail(what) {
    throw new NpyHeaderError(`cannot parse header: ${what} at character ${this.at}`);
  }

  /** Skip spaces, tabs, form feeds, comments, line joins and (inside brackets) newlines. */
  skip() {
    const t = this.text;
    for (;;) {
      const c = t[this.at];
      if (c === ' ' || c === '\t' || c === '\f') this.at++;
      else if (c === '#') while (this.at < t.length && t[this.at] !== '\n' && t[this.at] !== '\r') this.at++;
      else if (c === '\\' && (t[this.at + 1] === '\n' || t[this.at + 1] === '\r')) this.at += t[this.at + 1] === '\r' && t[this.at + 2] === '\n' ? 3 : 2;
      else if ((c === '\n' || c === '\r') && this.depth > 0) this.at++;
      else return;
    }
  }

  /** The whole text as one value, then only whitespace, comments and newlines. */
  document() {
    this.skip();
    const value = this.value();
    for (;;) {
      this.skip();
      const c = this.text[this.at];
      if (c === undefined) return value;
      if (c !== '\n' && c !== '\r') this.fail('unexpected text after the literal');
      this.at++;
    }
  }

  value() {
    this.skip();
    const c = this.text[this.at];
    if (c === '{') return this.dict();
    if (c === '(') return this.group();
    if (c === '[') return this.sequence('[', ']').items;
    if (c === '-' || c === '+') {
      this.at++;
      this.skip();
      if (!/[0-9]/.test(this.text[this.at] ?? '')) this.fail('a sign that does not precede a number');
      const n = this.number();
      return c === '-' ? -n : n;
    }
    if (c !== undefined && /[0-9]/.test(c)) return this.number();
    if (c === "'" || c === '"') return this.string('');
    const word = /^[A-Za-z_][A-Za-z0-9_]*/.exec(this.text.slice(this.at, this.at + 64));
    if (word) {
      const name = word[0];
      const next = this.text[this.at + name.length];
      if ((next === "'" || next === '"') && STRING_PREFIX.test(name)) {
        this.at += name.length;
        return this.string(name);
      }
      if (name === 'True' || name === 'False' || name === 'None') {
        this.at += name.length;
        return name === 'None' ? null : name === 'True';
      }
    }
    return this.fail('not a literal numpy writes');
  }

  open(bracket) {
    if (++this.depth > MAX_NESTING) this.fail('too many nested brackets');
    this.at++;
  }

  close() {
    this.depth--;
    this.at++;
  }

  /** Items up to `end`, comma separated, a trailing comma allowed. */
  sequence(start, end) {
    this.open(start);
    const items = [];
    let comma = false;
    for (;;) {
      this.skip();
      if (this.text[this.at] === end) {
        this.close();
        return { items, comma };
      }
      items.push(this.value());
      this.skip();
      comma = this.text[this.at] === ',';
      if (comma) this.at++;
      else if (this.text[this.at] !== end) this.fail(`expected ',' or '${end}'`);
    }
  }

  /** A tuple (marked as one), or a parenthesised value. */
  group() {
    const { items, comma } = this.sequence('(', ')');
    if (items.length === 1 && !comma) return items[0];
    return { tuple: items };
  }

  dict() {
    this.open('{');
    const entries = new Map();
    for (;;) {
      this.skip();
      if (this.text[this.at] === '}') {
        this.close();
        return { dict: entries };
      }
      const key = this.value();
      this.skip();
      if (this.text[this.at] !== ':') this.fail("expected ':'");
      this.at++;
      const value = this.value();
      // Only string keys can be numpy's three; any other key (hashable or not) makes the header one numpy refuses.
      if (typeof key !== 'string') this.fail('a key that is not a string');
      entries.set(key, { key, value });
      this.skip();
      if (this.text[this.at] === ',') this.at++;
      else if (this.text[this.at] !== '}') this.fail("expected ',' or '}'");
    }
  }

  /** A decimal, hex, octal or binary integer with Python's underscores; a float or complex is refused. */
  number() {
    const rest = this.text.slice(this.at, this.at + 4400);
    const match = /^(?:0[xX](?:_?[0-9a-fA-F])+|0[oO](?:_?[0-7])+|0[bB](?:_?[01])+|0(?:_?0)*|[1-9](?:_?[0-9])*)/.exec(rest);
    if (!match || /^[.eEjJ0-9a-zA-Z_]/.test(rest.slice(match[0].length))) this.fail('not an integer');
    if (/^[1-9]/.test(match[0]) && match[0].replaceAll('_', '').length > MAX_INT_DIGITS) this.fail('an integer too long');
    this.at += match[0].length;
    let digits = match[0].replaceAll('_', '');
    if (/^0[oObBxX]/.test(digits)) digits = digits[0] + digits[1].toLowerCase() + digits.slice(2);
    return BigInt(digits);
  }

  /** A quoted string (prefix u or r, or none); the escapes Python reads in such a string. */
  string(prefix) {
    const quote = this.text[this.at];
    const raw = /r/i.test(prefix);
    const triple = this.text.startsWith(quote.repeat(3), this.at);
    this.at += triple ? 3 : 1;
    let out = '';
    for (;;) {
      if (this.at >= this.text.length) this.fail('an unterminated string');
      const c = this.text[this.at];
      if (triple ? this.text.startsWith(quote.repeat(3), this.at) : c === quote) {
        this.at += triple ? 3 : 1;
        return out;
      }
      if (!triple && (c === '\n' || c === '\r')) this.fail('an unterminated string');
      if (c === '\\') {
        const next = this.text[this.at + 1];
        if (next === undefined) this.fail('an unterminated string');
        if (raw) {
          out += c + next;
          this.at += 2;
          continue;
        }
        const simple = { n: '\n', t: '\t', r: '\r', '\\': '\\', "'": "'", '"': '"', a: '\x07', b: '\b', f: '\f', v: '\v',
          '\n': '' };
        if (next in simple) {
          out += simple[next];
          this.at += 2;
          continue;
        }
        // \x, \u, \N{...} and octal escapes are never in a header numpy writes; refused rather than half-read.
        this.fail('a string escape numpy headers do not use');
      }
      out += c;
      this.at++;
    }
  }
}

// -- dtype descriptors ---------------------------------------------------------------------------------------------

// numpy's one-character type codes (and the type numbers it also reads as characters) of numbers: [kind, size].
// float128 ('g', 'f16') is left out: numpy reads it, the browser has no such float, so it is refused.
const TYPE_CODES = {
  '?': ['b', 1], b: ['i', 1], B: ['u', 1], h: ['i', 2], H: ['u', 2], i: ['i', 4], I: ['u', 4], l: ['i', 8], L: ['u', 8],
  q: ['i', 8], Q: ['u', 8], n: ['i', 8], N: ['u', 8], p: ['i', 8], P: ['u', 8], e: ['f', 2], f: ['f', 4], d: ['f', 8],
  '\x00': ['b', 1], '\x01': ['i', 1], '\x02': ['u', 1], '\x03': ['i', 2], '\x04': ['u', 2],
  '\x05': ['i', 4], '\x06': ['u', 4], '\x07': ['i', 8], '\x08': ['u', 8], '\t': ['i', 8], '\n': ['u', 8],
  '\x0b': ['f', 4], '\x0c': ['f', 8], '\x17': ['f', 2],
};
// Kind letter + byte count that numpy reads: booleans, integers and floats.
const SIZED = { b: [1], i: [1, 2, 4, 8], u: [1, 2, 4, 8], f: [2, 4, 8] };

/**
 * A descr string -> {kind: 'b'|'i'|'u'|'f', size, bigEndian} for the dtypes of numbers numpy reads from it, {kind:
 * 'S'|'U', size} for strings (which no motion holds), null for any other descriptor (complex, dates, objects, records:
 * refused by the reader, as in Python; and float128, which only Python reads).
 */
export function parseDescr(descr) {
  if (typeof descr !== 'string') return null;
  const match = /^([<>|=]?)(.+)$/s.exec(descr);
  if (!match) return null;
  const [, order, body] = match;
  let kind;
  let size;
  if (body === 'c') return { kind: 'S', size: 1 };
  if (body.length === 1 && body in TYPE_CODES) [kind, size] = TYPE_CODES[body];
  else if (/^[SaU][0-9]+$/.test(body)) {
    const chars = Number(body.slice(1));
    if (!(chars > 0 && Number.isSafeInteger(chars))) return null;
    return body[0] === 'U' ? { kind: 'U', size: 4 * chars, bigEndian: order === '>' } : { kind: 'S', size: chars };
  }
  else {
    const sized = /^([biuf])([0-9]+)$/.exec(body);
    if (!sized || !SIZED[sized[1]].includes(Number(sized[2])) || sized[2].startsWith('0')) return null;
    [kind, size] = [sized[1], Number(sized[2])];
  }
  return { kind, size, bigEndian: order === '>' && size > 1 };
}

// -- the header ----------------------------------------------------------------------------------------------------

/**
 * The header at the start of a member's bytes -> {shape: BigInt[], fortran, dtype (parseDescr's), dataStart}.
 * NpyHeaderError for what numpy refuses, and for a version other than 1.0 and 2.0 (the Python reader's bound).
 */
export function readNpyHeader(bytes) {
  if (bytes.length < 8) throw new NpyHeaderError(`EOF reading the magic string: ${bytes.length} of 8 bytes`);
  if (!NPY_MAGIC.every((b, i) => bytes[i] === b)) throw new NpyHeaderError('the magic string is not \\x93NUMPY');
  const [major, minor] = [bytes[6], bytes[7]];
  if (!((major === 1 || major === 2) && minor === 0)) {
    throw new NpyHeaderError(`npy format version ${major}.${minor} is not read (1.0 and 2.0 are)`);
  }
  const lengthBytes = major === 1 ? 2 : 4;
  if (bytes.length < 8 + lengthBytes) throw new NpyHeaderError('EOF reading the array header length');
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const length = major === 1 ? view.getUint16(8, true) : view.getUint32(8, true);
  const start = 8 + lengthBytes;
  if (bytes.length < start + length) {
    throw new NpyHeaderError(`EOF reading the array header: ${bytes.length - start} of ${length} bytes`);
  }
  if (length > MAX_HEADER_CHARS) throw new NpyHeaderError(`header length ${length} is over numpy's ${MAX_HEADER_CHARS}`);
  // Latin-1, byte for byte (TextDecoder's 'latin1' is windows-1252).
  const header = Array.from(bytes.subarray(start, start + length), (b) => String.fromCharCode(b)).join('');
  if (header.includes('\0')) throw new NpyHeaderError('the header holds a NUL character');
  const parsed = new LiteralReader(header.replace(/^[ \t]+/, '')).document();
  const entries = parsed?.dict;
  if (!entries) throw new NpyHeaderError('the header is not a dictionary');
  const keys = [...entries.values()].map((e) => e.key);
  const expected = ['descr', 'fortran_order', 'shape'];
  if (keys.length !== 3 || !expected.every((k) => keys.includes(k))) {
    throw new NpyHeaderError('the header does not hold exactly descr, fortran_order and shape');
  }
  const field = (name) => entries.get(name).value;
  const shape = field('shape');
  if (!(shape && Array.isArray(shape.tuple) && shape.tuple.every((n) => typeof n === 'bigint' || typeof n === 'boolean'))) {
    throw new NpyHeaderError('shape is not a tuple of integers');
  }
  if (typeof field('fortran_order') !== 'boolean') throw new NpyHeaderError('fortran_order is not a bool');
  const dtype = parseDescr(field('descr'));
  return { shape: shape.tuple.map((n) => BigInt(n)), fortran: field('fortran_order'), dtype,
    descr: field('descr'), dataStart: start + length };
}
