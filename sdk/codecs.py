"""Buffer codecs: how a named array is stored in a bundle and decoded back. Decoding lives only here.

Each codec is a name plus JSON parameters recorded in the manifest, so reduced-precision tiers (fp16,
chunked quantisation, ...) slot in as new entries of CODECS without touching the bundle reader.
"""

from __future__ import annotations

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


@dataclass(frozen=True)
class Codec:
    """encode(array) -> (payload bytes, params); decode(payload, dtype, shape, params) -> array."""

    encode: Callable[[np.ndarray], tuple[bytes, dict]]
    decode: Callable[[bytes, str, tuple[int, ...], dict], np.ndarray]
    stored_itemsize: Callable[[str], int]
    float_only: bool = False  # decodes only to floating-point dtypes


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


CODECS: dict[str, Codec] = {
    "raw": Codec(_encode_raw, _decode_raw, lambda dtype: np.dtype(dtype).itemsize),
    "fp16": Codec(_encode_fp16, _decode_fp16, lambda dtype: 2, float_only=True),
}


def get_codec(name: str) -> Codec:
    """The codec registered under `name`; BundleError naming it otherwise."""
    try:
        return CODECS[name]
    except KeyError:
        raise BundleError(f"unknown buffer codec {name!r} (known: {', '.join(sorted(CODECS))})") from None


def expected_nbytes(codec_name: str, dtype: str, shape: tuple[int, ...]) -> int:
    """Stored size of a buffer, known from the manifest alone (checked before anything is allocated)."""
    if dtype not in SUPPORTED_DTYPES:
        raise BundleError(f"unsupported buffer dtype {dtype!r} (supported: {', '.join(SUPPORTED_DTYPES)})")
    codec = get_codec(codec_name)
    if codec.float_only and not dtype.startswith("float"):
        raise BundleError(f"codec {codec_name!r} cannot decode to dtype {dtype!r} (floating-point only)")
    count = 1
    for dim in shape:
        if not isinstance(dim, int | np.integer) or isinstance(dim, bool) or dim < 0:
            raise BundleError(f"invalid buffer shape {list(shape)}")
        count *= int(dim)  # Python ints: a huge claimed shape is a big number, never an allocation
    return count * codec.stored_itemsize(dtype)
