"""Buffer codecs: how a named array is stored in a bundle and decoded back. Decoding lives only here.

Each codec is a name plus JSON parameters recorded in the manifest; a bundle reader needs nothing else. Decoding
happens once, when a bundle is loaded (graph weights become float32 initializers), never per frame. The codecs
(docs/precision.md says what each costs and buys on the demo speaker):

* `raw`: the array's own bytes (fp32 for floats). Lossless.
* `fp16`: IEEE half floats; relative error <= 2^-11.
* `q16`, `q8`, `q4`: chunked min/max quantisation, the scheme of compressed splat formats. The array (C order)
  is cut into chunks of `chunk` consecutive values (256 by default); a chunk stores its minimum and step as float32
  and each value as a `bits`-bit code, value = minimum + code * step (error <= step / 2 = chunk range /
  (2^(bits+1) - 2)). The exporter lays per-Gaussian buffers out component-major ([3, N], ...), so a chunk holds one
  quantity of neighbouring Gaussians.
* `index`: non-negative integers in the smallest unsigned type that holds the largest (uint8/16/32). Lossless.
* `vq`: a codebook. The array's last axis indexes vectors (a per-Gaussian buffer [D, N]: Gaussian n's D values); a
  table of `entries` vectors in float16 is stored, then each vector's index into it in ceil(log2 entries) bits.
  A 256-entry table of a Gaussian's colour is 1 byte a Gaussian against 3 at q8 (sdk/kmeans.py makes the table).

Any codec may be made sparse (params `"sparse": {"nnz": K}`): the payload is then a bitmask of the array's
nonzero elements (one bit per element in C order, the first in the lowest bit of byte 0, `ceil(count / 8)` bytes,
spare bits zero), followed by the codec's own payload of those K values as a 1-D array. A morph basis that is
mostly zeros (an avatar's blendshapes each move one region of the face) takes a fraction of its dense bytes. With
`"sparse": {"nnz": K, "mask_zlib": M}` the bitmask is stored as a zlib stream (RFC 1950) of M bytes, which must
inflate to exactly the bitmask's bytes: the nonzeros of a morph basis lie in runs (one face region per shape), so
the mask deflates about 6x (docs/bundle-format.md, "Codecs").
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .errors import BundleError

# Every dtype a bundle buffer or graph tensor may have: (numpy name, ONNX TensorProto.DataType code, onnxruntime's
# type string). The one table; the maps below are derived from it.
_DTYPES = (
    ("float32", 1, "tensor(float)"),
    ("float16", 10, "tensor(float16)"),
    ("int32", 6, "tensor(int32)"),
    ("int64", 7, "tensor(int64)"),
    ("int8", 3, "tensor(int8)"),
    ("uint8", 2, "tensor(uint8)"),
    ("uint16", 4, "tensor(uint16)"),
    ("uint32", 12, "tensor(uint32)"),
)
# dtypes a buffer may declare (the decoded array's dtype); anything else in a manifest is refused.
SUPPORTED_DTYPES = tuple(name for name, _, _ in _DTYPES)
# ONNX TensorProto.DataType code -> numpy dtype name.
ONNX_DTYPES = {code: name for name, code, _ in _DTYPES}
# onnxruntime's NodeArg.type string -> numpy dtype name.
ORT_DTYPES = {ort_type: name for name, _, ort_type in _DTYPES}
FP16_MAX = 65504.0
# Values per quantisation chunk unless the encoder is told otherwise; the largest a manifest may declare.
DEFAULT_CHUNK = 256
MAX_CHUNK = 1 << 20
# The most dimensions a buffer may have, and the bound on its element count (numpy's limits, with margin).
MAX_NDIM = 32
MAX_ELEMENTS = 1 << 56
# Unsigned types the `index` codec may store, smallest first.
INDEX_TYPES = ("uint8", "uint16", "uint32")
# Bits per value of the quantising codecs (`q16`, `q8`, `q4`).
QUANT_BITS = (16, 8, 4)
# The most vectors a `vq` codebook may hold (16-bit indices), and its size when the encoder is not told.
MAX_CODEBOOK = 1 << 16
DEFAULT_CODEBOOK = 256


def dtype_table() -> dict[str, tuple[int, int]]:
    """Each supported dtype's (ONNX TensorProto.DataType code, bytes per element): what the browser player's
    codecs read from web/src/generated.js."""
    return {name: (code, np.dtype(name).itemsize) for name, code, _ in _DTYPES}
# What a decoded float32 value may reach: a quantised chunk whose minimum + step * max code exceeds it is damaged.
_FLOAT32_MAX = float(np.finfo(np.float32).max)


@dataclass(frozen=True)
class Codec:
    """encode(array) -> (payload bytes, params); decode(payload, dtype, shape, params) -> array;
    stored_nbytes(dtype, shape, params) -> the payload size the manifest implies (BundleError for bad params)."""

    encode: Callable[[np.ndarray], tuple[bytes, dict]]
    decode: Callable[[bytes, str, tuple[int, ...], dict], np.ndarray]
    stored_nbytes: Callable[[str, tuple[int, ...], dict], int]
    float_only: bool = False  # decodes only to floating-point dtypes
    int_only: bool = False  # decodes only to integer dtypes
    lossless: bool = True


def _count(shape: tuple[int, ...]) -> int:
    count = 1
    for dim in shape:
        count *= int(dim)  # Python ints: a huge claimed shape is a big number, never an allocation
    return count


def _encode_raw(array: np.ndarray) -> tuple[bytes, dict]:
    return np.ascontiguousarray(array).astype(array.dtype.newbyteorder("<"), copy=False).tobytes(), {}


def _decode_raw(payload: bytes, dtype: str, shape: tuple[int, ...], params: dict) -> np.ndarray:
    return np.frombuffer(payload, dtype=np.dtype(dtype).newbyteorder("<")).astype(dtype).reshape(shape)


def _encode_fp16(array: np.ndarray) -> tuple[bytes, dict]:
    if array.dtype.kind != "f":
        raise BundleError(f"codec fp16 stores floating-point arrays only, got {array.dtype}")
    finite = array[np.isfinite(array)]
    if finite.size and np.abs(finite).max() > FP16_MAX:
        raise BundleError(f"codec fp16 cannot hold values up to {np.abs(finite).max():.4g} (max {FP16_MAX})")
    return array.astype("<f2").tobytes(), {}


def _decode_fp16(payload: bytes, dtype: str, shape: tuple[int, ...], params: dict) -> np.ndarray:
    return np.frombuffer(payload, dtype="<f2").astype(dtype).reshape(shape)


# -- chunked min/max quantisation --------------------------------------------------------------------------------


def _chunk_param(params: dict, codec: str) -> int:
    chunk = params.get("chunk")
    if not isinstance(chunk, int) or isinstance(chunk, bool) or not 1 <= chunk <= MAX_CHUNK:
        raise BundleError(f"codec {codec!r} needs an integer chunk in 1..{MAX_CHUNK}, got {chunk!r}")
    return chunk


def _chunk_count(count: int, chunk: int) -> int:
    return -(-count // chunk)


def _code_nbytes(count: int, bits: int) -> int:
    return -(-count * bits // 8)


def _quant_nbytes(bits: int) -> Callable[[str, tuple[int, ...], dict], int]:
    def nbytes(dtype: str, shape: tuple[int, ...], params: dict) -> int:
        count = _count(shape)
        return 8 * _chunk_count(count, _chunk_param(params, f"q{bits}")) + _code_nbytes(count, bits)
    return nbytes


def _quant_encoder(bits: int, chunk: int = DEFAULT_CHUNK) -> Callable[[np.ndarray], tuple[bytes, dict]]:
    levels = (1 << bits) - 1

    def encode(array: np.ndarray) -> tuple[bytes, dict]:
        if array.dtype.kind != "f":
            raise BundleError(f"codec q{bits} stores floating-point arrays only, got {array.dtype}")
        if not np.all(np.isfinite(array)):
            raise BundleError(f"codec q{bits} stores finite arrays only")
        values = np.asarray(array, dtype=np.float64).reshape(-1)
        count, n_chunks = values.size, _chunk_count(values.size, chunk)
        if count == 0:
            return b"", {"chunk": chunk}
        blocks = np.pad(values, (0, n_chunks * chunk - count), mode="edge").reshape(n_chunks, chunk)
        low, high = blocks.min(axis=1), blocks.max(axis=1)
        low = low.astype(np.float32).astype(np.float64)  # what the decoder will read
        exact = (high - low) / levels
        step = exact.astype(np.float32)
        # float32 steps are rounded up, so the chunk's top value never needs a code past `levels` (a step rounded
        # down, or to zero below float32's subnormals, would clip it); unless that would take the top code past
        # float32's largest value, where it is rounded down instead.
        short = step.astype(np.float64) < exact
        step[short] = np.nextafter(step[short], np.float32(np.inf))
        over = low + step.astype(np.float64) * levels > _FLOAT32_MAX
        step[over] = np.nextafter(step[over], np.float32(0))
        step = step.astype(np.float64)
        safe = np.where(step > 0, step, 1.0)
        codes = np.clip(np.rint((blocks - low[:, None]) / safe[:, None]), 0, levels)
        codes = codes.reshape(-1)[:count].astype(np.uint16 if bits > 8 else np.uint8)
        if bits == 4:
            codes = np.pad(codes, (0, codes.size % 2))
            codes = codes[0::2] | (codes[1::2] << 4)  # two codes per byte, the first in the low nibble
        packed = codes.astype("<u2" if bits > 8 else np.uint8).tobytes()
        return low.astype("<f4").tobytes() + step.astype("<f4").tobytes() + packed, {"chunk": chunk}
    return encode


def _quant_decoder(bits: int) -> Callable[[bytes, str, tuple[int, ...], dict], np.ndarray]:
    levels = (1 << bits) - 1

    def decode(payload: bytes, dtype: str, shape: tuple[int, ...], params: dict) -> np.ndarray:
        chunk = _chunk_param(params, f"q{bits}")
        count = _count(shape)
        n_chunks = _chunk_count(count, chunk)
        low = np.frombuffer(payload, "<f4", n_chunks, 0).astype(np.float64)
        step = np.frombuffer(payload, "<f4", n_chunks, 4 * n_chunks).astype(np.float64)
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(step)) and np.all(step >= 0)
                and np.all(np.abs(low) <= _FLOAT32_MAX) and np.all(low + step * levels <= _FLOAT32_MAX)):
            raise BundleError(f"codec q{bits}: damaged chunk parameters (a minimum or step is not finite, a step "
                              f"is negative, or a chunk's range exceeds float32)")
        raw = np.frombuffer(payload, "<u2" if bits > 8 else np.uint8, offset=8 * n_chunks)
        if bits == 4:
            codes = np.empty(raw.size * 2, np.uint8)
            codes[0::2], codes[1::2] = raw & 0x0F, raw >> 4
            codes = codes[:count]
        else:
            codes = raw
        chunk_of = np.arange(count) // chunk  # [count]
        values = low[chunk_of] + codes.astype(np.float64) * step[chunk_of]
        return values.astype(dtype).reshape(shape)
    return decode


# -- narrow integer indices --------------------------------------------------------------------------------------


def _index_type(params: dict) -> str:
    stored = params.get("stored")
    if stored not in INDEX_TYPES:
        raise BundleError(f"codec 'index' needs stored in {', '.join(INDEX_TYPES)}, got {stored!r}")
    return stored


def _encode_index(array: np.ndarray) -> tuple[bytes, dict]:
    if array.dtype.kind not in "iu":
        raise BundleError(f"codec index stores integer arrays only, got {array.dtype}")
    low = int(array.min()) if array.size else 0
    high = int(array.max()) if array.size else 0
    if low < 0:
        raise BundleError(f"codec index stores non-negative integers only (minimum {low})")
    stored = next((t for t in INDEX_TYPES if high <= np.iinfo(t).max), None)
    if stored is None:
        raise BundleError(f"codec index cannot hold {high} (largest uint32 {np.iinfo(np.uint32).max})")
    return array.astype(np.dtype(stored).newbyteorder("<")).tobytes(), {"stored": stored}


def _decode_index(payload: bytes, dtype: str, shape: tuple[int, ...], params: dict) -> np.ndarray:
    stored = np.dtype(_index_type(params)).newbyteorder("<")
    values = np.frombuffer(payload, dtype=stored)
    if values.size and int(values.max()) > np.iinfo(dtype).max:
        raise BundleError(f"codec index: stored value {int(values.max())} does not fit dtype {dtype}")
    return values.astype(dtype).reshape(shape)


# -- codebooks ----------------------------------------------------------------------------------------------------


def _entries_param(params: dict) -> int:
    entries = params.get("entries")
    if not isinstance(entries, int) or isinstance(entries, bool) or not 1 <= entries <= MAX_CODEBOOK:
        raise BundleError(f"codec 'vq' needs an integer entries in 1..{MAX_CODEBOOK}, got {entries!r}")
    return entries


def index_bits(entries: int) -> int:
    """Bits a `vq` index takes: ceil(log2 entries), at least 1."""
    return max(1, (int(entries) - 1).bit_length())


def _vq_layout(shape: tuple[int, ...]) -> tuple[int, int]:
    """(vectors N, values per vector D) of a `vq` array: N along the last axis, D the product of the others."""
    vectors = int(shape[-1]) if shape else 1
    return vectors, _count(tuple(shape[:-1]))


def _vq_nbytes(dtype: str, shape: tuple[int, ...], params: dict) -> int:
    entries = _entries_param(params)
    vectors, width = _vq_layout(shape)
    return 2 * entries * width + _code_nbytes(vectors, index_bits(entries))


def _vq_encoder(entries: int = DEFAULT_CODEBOOK) -> Callable[[np.ndarray], tuple[bytes, dict]]:
    def encode(array: np.ndarray) -> tuple[bytes, dict]:
        from .kmeans import closest, kmeans  # the encoder's alone: a reader never runs k-means

        if array.dtype.kind != "f":
            raise BundleError(f"codec vq stores floating-point arrays only, got {array.dtype}")
        if not np.all(np.isfinite(array)) or (array.size and np.abs(array).max() > FP16_MAX):
            raise BundleError(f"codec vq stores finite arrays within float16's range (max {FP16_MAX}) only")
        _entries_param({"entries": entries})
        vectors, width = _vq_layout(tuple(array.shape))
        if array.size == 0:
            return b"\0" * _vq_nbytes("", tuple(array.shape), {"entries": 1}), {"entries": 1}
        x = np.asarray(array, np.float64).reshape(width, vectors).T  # [N, D]
        k = min(entries, vectors)
        centres, _ = kmeans(x, k)
        table = centres.astype("<f2")
        index = closest(x, table.astype(np.float64))  # each vector to its nearest centre as the reader sees it
        bits = index_bits(k)
        packed = np.packbits(((index[:, None] >> np.arange(bits)) & 1).astype(np.uint8).reshape(-1),
                             bitorder="little")
        return table.tobytes() + packed.tobytes(), {"entries": k}
    return encode


def _decode_vq(payload: bytes, dtype: str, shape: tuple[int, ...], params: dict) -> np.ndarray:
    entries = _entries_param(params)
    vectors, width = _vq_layout(shape)
    table = np.frombuffer(payload, "<f2", entries * width, 0).reshape(entries, width)
    if not np.all(np.isfinite(table)):
        raise BundleError("codec vq: the codebook holds a value that is not finite")
    bits = index_bits(entries)
    stream = np.unpackbits(np.frombuffer(payload, np.uint8, offset=2 * entries * width), bitorder="little")
    if stream[vectors * bits:].any():
        raise BundleError("codec vq: bits are set past the last index")
    index = (stream[:vectors * bits].reshape(vectors, bits).astype(np.int64) << np.arange(bits)).sum(1)
    if vectors and int(index.max()) >= entries:
        raise BundleError(f"codec vq: index {int(index.max())} past the codebook's {entries} entries")
    return np.ascontiguousarray(table.astype(dtype)[index].T).reshape(shape)


CODECS: dict[str, Codec] = {
    "raw": Codec(_encode_raw, _decode_raw, lambda dtype, shape, params: _count(shape) * np.dtype(dtype).itemsize),
    "fp16": Codec(_encode_fp16, _decode_fp16, lambda dtype, shape, params: 2 * _count(shape), float_only=True,
                  lossless=False),
    **{f"q{bits}": Codec(_quant_encoder(bits), _quant_decoder(bits), _quant_nbytes(bits), float_only=True,
                         lossless=False) for bits in QUANT_BITS},
    "index": Codec(_encode_index, _decode_index,
                   lambda dtype, shape, params: _count(shape) * np.dtype(_index_type(params)).itemsize,
                   int_only=True),
    "vq": Codec(_vq_encoder(), _decode_vq, _vq_nbytes, float_only=True, lossless=False),
}


# -- the sparse layer --------------------------------------------------------------------------------------------


def _is_count(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _sparse_param(params: dict, count: int) -> tuple[int, int | None, dict]:
    """(nnz, the zlib mask's stored bytes or None for a plain bitmask, the inner codec's params) of a sparse entry;
    BundleError for a malformed or impossible one."""
    sparse = params.get("sparse")
    nnz = sparse.get("nnz") if isinstance(sparse, dict) else None
    zipped = sparse.get("mask_zlib") if isinstance(sparse, dict) else None
    bound = zlib_bound(_mask_nbytes(count))
    if (not _is_count(nnz) or nnz > count or set(sparse) - {"nnz", "mask_zlib"}
            or ("mask_zlib" in sparse and not (_is_count(zipped) and zipped <= bound))):
        raise BundleError(f"sparse buffer needs {{\"nnz\": K}} with 0 <= K <= {count} (its element count), and "
                          f"optionally \"mask_zlib\": M, at most {bound} bytes; got "
                          f"{json.dumps(sparse)[:80]}")
    return nnz, zipped, {key: value for key, value in params.items() if key != "sparse"}


def _mask_nbytes(count: int) -> int:
    return -(-count // 8)


def zlib_bound(nbytes: int) -> int:
    """The most bytes zlib's stream of `nbytes` bytes takes (stored blocks: 5 bytes per 65,535, plus the 2-byte
    header and 4-byte checksum), so a mask's claimed size is bounded by the mask it stands for."""
    return nbytes + 5 * (nbytes // 65535 + 1) + 6


def _inflated_mask(stored: bytes, nbytes: int) -> bytes:
    """The bitmask a zlib-stored mask holds: exactly `nbytes` bytes, the stream complete and its checksum right,
    nothing after it; BundleError otherwise. Inflating stops one byte past the mask, however the stream claims."""
    inflater = zlib.decompressobj()
    try:
        mask = inflater.decompress(stored, nbytes + 1)
    except zlib.error as exc:
        raise BundleError(f"sparse buffer's zlib mask is damaged ({exc})") from None
    if len(mask) != nbytes or not inflater.eof or inflater.unused_data or inflater.unconsumed_tail:
        raise BundleError(f"sparse buffer's zlib mask does not inflate to exactly its {nbytes} bytes")
    return mask


def decode_buffer(payload: bytes, codec_name: str, dtype: str, shape: tuple[int, ...], params: dict) -> np.ndarray:
    """A buffer's stored bytes (their length already checked with expected_nbytes) -> its array."""
    codec = get_codec(codec_name)
    if "sparse" not in params:
        return codec.decode(payload, dtype, shape, params)
    count = _count(shape)
    nnz, zipped, inner = _sparse_param(params, count)
    mask_bytes = _mask_nbytes(count)
    stored = mask_bytes if zipped is None else zipped
    packed = payload[:stored] if zipped is None else _inflated_mask(payload[:stored], mask_bytes)
    mask = np.unpackbits(np.frombuffer(packed, np.uint8, mask_bytes), bitorder="little")
    if mask[count:].any():
        raise BundleError("sparse buffer's mask has bits set past its last element")
    mask = mask[:count].astype(bool)
    if int(mask.sum()) != nnz:
        raise BundleError(f"sparse buffer's mask marks {int(mask.sum())} nonzero elements, its nnz says {nnz}")
    values = codec.decode(payload[stored:], dtype, (nnz,), inner)
    out = np.zeros(count, dtype)
    out[mask] = values
    return out.reshape(shape)


def get_codec(name: str) -> Codec:
    """The codec registered under `name`; BundleError naming it otherwise."""
    try:
        return CODECS[name]
    except KeyError:
        raise BundleError(f"unknown buffer codec {name!r} (known: {', '.join(CODECS)})") from None


def expected_nbytes(codec_name: str, dtype: str, shape: tuple[int, ...], params: dict | None = None) -> int:
    """Stored size of a buffer, known from the manifest alone (checked before anything is allocated)."""
    if dtype not in SUPPORTED_DTYPES:
        raise BundleError(f"unsupported buffer dtype {dtype!r} (supported: {', '.join(SUPPORTED_DTYPES)})")
    codec = get_codec(codec_name)
    if codec.float_only and not dtype.startswith("float"):
        raise BundleError(f"codec {codec_name!r} cannot decode to dtype {dtype!r} (floating-point only)")
    if codec.int_only and dtype.startswith("float"):
        raise BundleError(f"codec {codec_name!r} cannot decode to dtype {dtype!r} (integers only)")
    for dim in shape:
        if not isinstance(dim, int | np.integer) or isinstance(dim, bool) or dim < 0:
            raise BundleError(f"invalid buffer shape {str(list(shape))[:120]}")
    # A shape numpy cannot make is damage even when a zero dimension leaves nothing to store: at most MAX_NDIM
    # dimensions, whose product (zeros aside) stays below MAX_ELEMENTS.
    spread = 1
    for dim in shape:
        spread *= max(int(dim), 1)
    if len(shape) > MAX_NDIM or spread >= MAX_ELEMENTS:
        raise BundleError(f"invalid buffer shape {str(list(shape))[:120]} (at most {MAX_NDIM} dimensions, fewer "
                          f"than {MAX_ELEMENTS} elements)")
    shape, params = tuple(int(d) for d in shape), params or {}
    if "sparse" in params:
        nnz, zipped, inner = _sparse_param(params, _count(shape))
        mask = _mask_nbytes(_count(shape)) if zipped is None else zipped
        return mask + codec.stored_nbytes(dtype, (nnz,), inner)
    return codec.stored_nbytes(dtype, shape, params)


def encode_buffer(array: np.ndarray, codec_name: str, chunk: int | None = None,
                  sparse: bool = False) -> tuple[bytes, dict]:
    """Encode `array` with codec `codec_name`; `chunk` is the codec's size: a quantised codec's values per chunk,
    `vq`'s codebook entries (default 256 for both). `sparse`: only its nonzero elements, after a bitmask of where
    they are (a -0.0 is stored as a zero), zlib-compressed where that is smaller."""
    if sparse:
        flat = np.ascontiguousarray(array).reshape(-1)
        mask = flat != 0
        payload, params = encode_buffer(flat[mask], codec_name, chunk)
        packed = np.packbits(mask, bitorder="little").tobytes()
        zipped = zlib.compress(packed, 9)
        layout = {"nnz": int(mask.sum())}
        if len(zipped) < len(packed):
            packed, layout = zipped, {**layout, "mask_zlib": len(zipped)}
        return packed + payload, {**params, "sparse": layout}
    codec = get_codec(codec_name)
    if chunk is not None and codec_name.startswith("q"):
        _chunk_param({"chunk": chunk}, codec_name)
        return _quant_encoder(int(codec_name[1:]), chunk)(array)
    if chunk is not None and codec_name == "vq":
        return _vq_encoder(_entries_param({"entries": chunk}))(array)
    return codec.encode(array)
