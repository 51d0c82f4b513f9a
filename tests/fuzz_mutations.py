"""Seeded mutations of valid files for tests/test_fuzz_readers.py (a numpy Generator drives every choice, so a
case is reproduced from its seed and index): byte-level (bit flips, truncations, splices, inserted and deleted runs,
integer fields set to 0, -1 or huge), JSON value-level (values swapped for huge numbers, negative counts, wrong
types, deep nesting, keys dropped), zip-level (members renamed out of their folder, duplicated, their stated sizes,
methods and flags changed in the central directory or the local header) and npy-level (headers that lie about
shape or dtype, pickled object arrays). Nothing here calls the SDK.
"""

from __future__ import annotations

import io
import json
import re
import struct
import warnings
import zipfile

import numpy as np

# Integers a header field is set to: zero, all ones (-1), sign bits, huge, just past the data.
SPECIAL_U32 = (0, 0xFFFFFFFF, 0x7FFFFFFF, 0x80000000, 1 << 30)
SPECIAL_U64 = (0, (1 << 64) - 1, 1 << 63, 1 << 62, 1 << 40)
# JSON values a mutated field takes: huge and negative counts, wrong types, numbers Python refuses to read.
SPECIAL_JSON = (0, -1, -(2**31), 2**31, 2**63, 10**30, 1e308, -1e308, 1.5, None, True, False, "x", "", [], {},
                [1, 2], {"a": 1}, 10**400, "__INF__", "__NAN__", "__BIGINT__")
_DEEP = "__DEEP_{}__"
_RUN_MAX = 64


def _random_bytes(rng: np.random.Generator, size: int) -> bytes:
    return rng.integers(0, 256, size, dtype=np.uint8).tobytes()


def mutate_bytes(data: bytes, rng: np.random.Generator, protect: int = 0) -> tuple[bytes, str]:
    """One byte-level mutation of `data` (bytes before `protect` kept, e.g. a magic number), and its name."""
    data = bytearray(data)
    n = len(data)
    if n <= protect:
        return bytes(data) + _random_bytes(rng, int(rng.integers(1, _RUN_MAX))), "append"
    kind = int(rng.integers(8))
    at = int(rng.integers(protect, n))
    if kind == 0:
        for _ in range(int(rng.integers(1, 9))):
            data[int(rng.integers(protect, n))] ^= 1 << int(rng.integers(8))
        return bytes(data), "bit flips"
    if kind == 1:
        return bytes(data[:at]), f"truncated at {at}"
    if kind == 2:
        data[at:at] = _random_bytes(rng, int(rng.integers(1, _RUN_MAX)))
        return bytes(data), f"inserted run at {at}"
    if kind == 3:
        del data[at:at + int(rng.integers(1, _RUN_MAX))]
        return bytes(data), f"deleted run at {at}"
    if kind == 4:
        source, length = int(rng.integers(n)), int(rng.integers(1, 4 * _RUN_MAX))
        data[at:at + length] = data[source:source + length]
        return bytes(data), f"spliced {source} -> {at}"
    if kind == 5 and n - at >= 4:
        value = SPECIAL_U32[int(rng.integers(len(SPECIAL_U32)))]
        data[at:at + 4] = struct.pack("<I", value)
        return bytes(data), f"u32 at {at} = {value:#x}"
    if kind == 6 and n - at >= 8:
        value = SPECIAL_U64[int(rng.integers(len(SPECIAL_U64)))]
        data[at:at + 8] = struct.pack("<Q", value)
        return bytes(data), f"u64 at {at} = {value:#x}"
    data[at:at + int(rng.integers(1, _RUN_MAX))] = _random_bytes(rng, int(rng.integers(1, _RUN_MAX)))
    return bytes(data), f"random run at {at}"


def mutate_field_bytes(data: bytes, rng: np.random.Generator, fields: list[tuple[int, int]]) -> tuple[bytes, str]:
    """Set one integer field (offset, size 2/4/8, little-endian) to a special value: 0, -1, huge, or off by one."""
    offset, size = fields[int(rng.integers(len(fields)))]
    current = int.from_bytes(data[offset:offset + size], "little")
    top = (1 << (8 * size)) - 1
    value = [0, top, top >> 1, current + 1, max(current - 1, 0), current * 2, int(rng.integers(0, 1 << 31)) & top][
        int(rng.integers(7))] & top
    out = bytearray(data)
    out[offset:offset + size] = value.to_bytes(size, "little")
    return bytes(out), f"field at {offset} ({size} bytes) {current} -> {value}"


# -- JSON ---------------------------------------------------------------------------------------------------------


def _paths(value, path=(), out=None, limit: int = 40) -> list[tuple]:
    """Paths (keys and indices) to every node of a JSON value (at most `limit` items of each list)."""
    out = [] if out is None else out
    out.append(path)
    if isinstance(value, dict):
        for key, item in value.items():
            _paths(item, path + (key,), out, limit)
    elif isinstance(value, list):
        for index, item in enumerate(value[:limit]):
            _paths(item, path + (index,), out, limit)
    return out


def mutate_json(document, rng: np.random.Generator) -> tuple[object, str]:
    """A mutated deep copy of a JSON document (1 to 3 edits) and a description. Deep nesting and the special
    numbers are markers that `dumps` writes as text."""
    document = json.loads(json.dumps(document))
    names = []
    for _ in range(int(rng.integers(1, 4))):
        paths = _paths(document)
        path = paths[int(rng.integers(len(paths)))]
        if not path:
            continue
        parent = document
        for key in path[:-1]:
            parent = parent[key]
        key, current = path[-1], parent[path[-1]]
        kind = int(rng.integers(6))
        if kind <= 1:
            new = SPECIAL_JSON[int(rng.integers(len(SPECIAL_JSON)))]
        elif kind == 2:
            new = _DEEP.format(int(rng.integers(100, 200_000)))
        elif kind == 3 and isinstance(current, int | float) and not isinstance(current, bool):
            new = current * [-1, 1000, 10**9, 0, 2**40][int(rng.integers(5))]
        elif kind == 4 and isinstance(current, list) and current:
            cut = int(rng.integers(len(current)))
            new = current * int(rng.integers(2, 4)) if rng.random() < 0.5 else current[:cut]
        else:
            if isinstance(parent, dict):
                del parent[key]
            else:
                parent.pop(key)
            names.append(f"dropped {path}"[:80])
            continue
        parent[key] = new
        names.append(f"{path} = {str(new)[:30]}"[:80])
    return document, "; ".join(names) or "unchanged"


def dumps(document) -> bytes:
    """JSON text of a mutated document, its markers written out: deep nesting, Infinity, NaN, a 5000-digit int."""
    text = json.dumps(document)
    text = re.sub(r'"__DEEP_(\d+)__"', lambda m: "[" * int(m.group(1)) + "]" * int(m.group(1)), text)
    text = text.replace('"__INF__"', "Infinity").replace('"__NAN__"', "NaN").replace('"__BIGINT__"', "9" * 5000)
    return text.encode()


# -- glTF binary --------------------------------------------------------------------------------------------------


def glb_split(data: bytes) -> tuple[dict, bytes]:
    """(JSON document, the bytes after the JSON chunk) of a .glb written with its JSON chunk first."""
    length = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + length]), data[20 + length:]


def glb_join(text: bytes, rest: bytes) -> bytes:
    """A .glb of a JSON chunk's text (padded) and the chunks after it, with correct lengths."""
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + rest
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def glb_fields(data: bytes) -> list[tuple[int, int]]:
    """The integer fields of a .glb's container: header version and length, each chunk's length and type."""
    fields, offset = [(4, 4), (8, 4)], 12
    while offset + 8 <= len(data):
        fields += [(offset, 4), (offset + 4, 4)]
        offset += 8 + struct.unpack_from("<I", data, offset)[0]
    return fields


# -- zip ----------------------------------------------------------------------------------------------------------


def write_zip(members: list[tuple[str, bytes]], method: int = zipfile.ZIP_STORED) -> bytes:
    """A zip of (name, bytes) members in order, names written as given (duplicates and '..' included)."""
    buffer = io.BytesIO()
    with warnings.catch_warnings(), zipfile.ZipFile(buffer, "w", method) as archive:
        warnings.simplefilter("ignore", UserWarning)  # "Duplicate name": written on purpose
        for name, data in members:
            archive.writestr(zipfile.ZipInfo(name, (2024, 1, 1, 0, 0, 0)), data, compress_type=method)
    return buffer.getvalue()


def zip_fields(data: bytes) -> list[tuple[str, int, int]]:
    """(name, offset, size) of every integer field of every entry's local header and central directory record that
    says how to read it: flags, method, CRC, compressed and uncompressed sizes, name and extra lengths, offset."""
    fields = []
    for match in re.finditer(rb"PK\x03\x04", data):
        at = match.start()
        fields += [("local flags", at + 6, 2), ("local method", at + 8, 2), ("local crc", at + 14, 4),
                   ("local compressed size", at + 18, 4), ("local size", at + 22, 4), ("local name length", at + 26, 2),
                   ("local extra length", at + 28, 2)]
    for match in re.finditer(rb"PK\x01\x02", data):
        at = match.start()
        fields += [("flags", at + 8, 2), ("method", at + 10, 2), ("crc", at + 16, 4), ("compressed size", at + 20, 4),
                   ("size", at + 24, 4), ("name length", at + 28, 2), ("extra length", at + 30, 2),
                   ("header offset", at + 42, 4)]
    for match in re.finditer(rb"PK\x05\x06", data):
        at = match.start()
        fields += [("entries", at + 10, 2), ("directory size", at + 12, 4), ("directory offset", at + 16, 4)]
    return [field for field in fields if field[1] + field[2] <= len(data)]


def mutate_zip_field(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """One zip header field (zip_fields) set to 0, all ones, half, off by one, double or random."""
    fields = zip_fields(data)
    name, offset, size = fields[int(rng.integers(len(fields)))]
    out, what = mutate_field_bytes(data, rng, [(offset, size)])
    return out, f"zip {name}: {what}"


UNSAFE_NAMES = ("../{name}", "../../{name}", "/{name}", "/tmp/{name}", "{folder}\\{name}", "..\\{name}",
                "C:/{name}", "c:\\{name}", "{folder}/../../{name}", "{folder}/./../{name}")


def unsafe_name(rng: np.random.Generator, folder: str, name: str) -> str:
    """A member name that climbs out of its folder, or would on some system."""
    return UNSAFE_NAMES[int(rng.integers(len(UNSAFE_NAMES)))].format(folder=folder, name=name)


# -- npy / npz ----------------------------------------------------------------------------------------------------


def npy_bytes(descr: str, shape_text: str, data: bytes, fortran: bool = False) -> bytes:
    """A version 1.0 .npy file with the header written as given (so it may lie about shape or dtype)."""
    header = f"{{'descr': {descr!r}, 'fortran_order': {fortran}, 'shape': {shape_text}, }}"
    header += " " * (-(10 + len(header) + 1) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode("latin-1") + data


def npz_bytes(arrays: dict[str, np.ndarray], compressed: bool = False) -> bytes:
    """An npz of arrays as np.savez writes it (object arrays pickled, as np.savez does by default)."""
    buffer = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buffer, **arrays)
    return buffer.getvalue()


def mutate_npz_arrays(arrays: dict[str, np.ndarray], rng: np.random.Generator) -> tuple[bytes, str]:
    """An npz whose arrays (or raw npy members) are changed: shapes, dtypes, values, keys, or lying headers."""
    arrays = dict(arrays)
    key = list(arrays)[int(rng.integers(len(arrays)))]
    value = np.asarray(arrays[key])
    kind = int(rng.integers(12))
    members = None
    if kind == 0:
        del arrays[key]
        what = f"dropped {key}"
    elif kind == 1:
        arrays[key] = value.reshape(-1)
        what = f"{key} flattened"
    elif kind == 2:
        arrays[key] = value[..., : max(value.shape[-1] - 1, 0)] if value.ndim else value[None]
        what = f"{key} one column short"
    elif kind == 3:
        arrays[key] = np.concatenate([value, value], axis=0) if value.ndim else value
        what = f"{key} twice the rows"
    elif kind == 4:
        filled = value.astype(np.float64).copy()
        filled.reshape(-1)[: max(1, filled.size // 7)] = [np.nan, np.inf, -np.inf, 1e300, -1e38][int(rng.integers(5))]
        arrays[key] = filled
        what = f"{key} with non-finite or huge values"
    elif kind == 5:
        dtype = np.dtype([np.int8, np.uint64, np.float16, np.bool_, "U5", "S3", np.complex64][int(rng.integers(7))])
        try:
            arrays[key] = value.astype(dtype)
        except (ValueError, OverflowError, TypeError):  # a string that is no number of that type
            arrays[key] = np.zeros(value.shape, dtype)
        what = f"{key} as {dtype}"
    elif kind == 6:
        arrays[key] = np.array([{"a": 1}, None], dtype=object)
        what = f"{key} a pickled object array"
    elif kind == 7:
        arrays[key] = np.zeros((0,) * max(value.ndim, 1), value.dtype)
        what = f"{key} empty"
    elif kind == 8:
        arrays[key] = np.ascontiguousarray(value.T) if value.ndim >= 2 else value
        what = f"{key} transposed"
    else:
        members = {k: _npy(v) for k, v in arrays.items()}
        descr, shape_text, body = _lie(value, rng)
        members[key] = npy_bytes(descr, shape_text, body, fortran=bool(rng.integers(2)))
        what = f"{key} header: descr {descr!r} shape {shape_text}"
    if members is None:
        return npz_bytes(arrays, compressed=bool(rng.integers(2))), what
    return write_zip([(f"{k}.npy", v) for k, v in members.items()], zipfile.ZIP_DEFLATED if rng.integers(2)
                     else zipfile.ZIP_STORED), what


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=True)
    return buffer.getvalue()


def _lie(value: np.ndarray, rng: np.random.Generator) -> tuple[str, str, bytes]:
    """(descr, shape text, data) of a header that lies about the array it precedes."""
    body = np.ascontiguousarray(value).tobytes()
    descr = value.dtype.str
    shape = list(value.shape) or [1]
    kind = int(rng.integers(6))
    if kind == 0:
        shape[0] = [10**10, 2**40, 2**62, 10**30, -1, 0][int(rng.integers(6))]
    elif kind == 1:
        shape = shape + [10**6, 10**6]
    elif kind == 2:
        descr = ["|O", "<U0", "|V8", "<c16", ">f8", "<M8[s]", "|b1", "<f2"][int(rng.integers(8))]
    elif kind == 3:
        return descr, "(" + "(" * 300 + ")" * 300 + ",)", body
    elif kind == 4:
        return descr, f"({'1, ' * 70})", body
    else:
        body = body[: int(rng.integers(len(body) + 1))]
    return descr, "(" + "".join(f"{n}, " for n in shape) + ")", body


__all__ = ["SPECIAL_JSON", "UNSAFE_NAMES", "dumps", "glb_fields", "glb_join", "glb_split", "mutate_bytes",
           "mutate_field_bytes", "mutate_json", "mutate_npz_arrays", "mutate_zip_field", "npy_bytes", "npz_bytes",
           "unsafe_name", "write_zip", "zip_fields"]
