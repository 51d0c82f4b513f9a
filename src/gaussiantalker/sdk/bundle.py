"""The `.gtb` bundle: one file holding a JSON manifest, ONNX graphs and binary buffers, each checksummed.

Layout (all integers little-endian):

    offset 0   magic  b"GTBUNDLE"                 8 bytes
           8   format major, minor                 2 x uint16
          12   reserved (0)                        uint32
          16   manifest length in bytes            uint64
          24   SHA-256 of the manifest bytes       32 bytes
          56   padding to HEADER_SIZE (64)
          64   manifest (UTF-8 JSON), then zero padding to a 64-byte boundary = payload start
               payload: every entry's bytes at payload start + entry["offset"], 64-byte aligned

Every entry (graph or buffer) records offset, nbytes and sha256, so truncation, a flipped byte or a manifest
that lies about sizes is reported with the entry's name before anything is decoded or handed to a driver.
"""

from __future__ import annotations

import hashlib
import json
import os
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .binary_layout import field_layout, fields_struct
from .codecs import decode_buffer, encode_buffer, expected_nbytes, zlib_bound
from .errors import BundleError
from .files import StagedFile, atomic_write
from .json_bounds import MAX_JSON_DEPTH, MAX_JSON_INT, nests_deeper_than, no_constant

MAGIC = b"GTBUNDLE"
FORMAT_MAJOR = 1
# 1.1: graphs may be stored zlib-compressed ("compression": "zlib", "raw_nbytes"); 1.2: so may sparse buffers'
# masks ("sparse": {"nnz": K, "mask_zlib": M}); 1.3: buffers may be stored zlib-compressed as graphs are, and the `vq`
# (codebook) codec
FORMAT_MINOR = 3
HEADER_SIZE = 64
ALIGN = 64
MAX_MANIFEST_BYTES = 16 * 1024 * 1024
MAX_MANIFEST_DEPTH = MAX_JSON_DEPTH  # objects and arrays nested deeper are refused (sdk/json_bounds.py)
# Largest graph a compressed entry may inflate to (protobuf's own 2 GiB limit): checked before inflating.
MAX_GRAPH_BYTES = 2**31 - 1
# How a graph or buffer entry may be stored compressed (its "compression" field).
GRAPH_COMPRESSIONS = ("zlib",)
# The manifest's "driver" of a FLAME speaker that only FLAME parameters drive (no translator graph: an imported
# avatar without an audio model, or a scene specialised for FLAME drives; docs/bundle-format.md).
FLAME_DRIVER = "flame"
# The graph that runs the translator a frame at a time, its state carried between calls (docs/live.md, "Streaming
# translators"), stored beside the windowed `translator` graph where the translator has a streaming form.
STREAM_GRAPH = "translator_stream"
# The same stream making no frame's features again (the speaker's own translator: its state is the streaming
# graph's), which a live session calls while the window's loudness holds (docs/live.md, "The speaker's own
# translator"); bundles without it run STREAM_GRAPH for every call.
STEADY_STREAM_GRAPH = "translator_stream_steady"
# The same translator streamed with a shorter delay (its rows lag the audio by half the frames), refreshing and steady,
# which a live session whose lookahead is shorter than the main stream's delay runs instead: its calls then make no
# provisional rows (docs/live.md, "A stream for a short lookahead"). Bundles without them run the main stream.
SHORT_STREAM_GRAPH = "translator_stream_short"
SHORT_STEADY_STREAM_GRAPH = "translator_stream_short_steady"
# Each stream's (refreshing, steady) graphs, the main stream first.
STREAM_GRAPHS = ((STREAM_GRAPH, STEADY_STREAM_GRAPH), (SHORT_STREAM_GRAPH, SHORT_STEADY_STREAM_GRAPH))
# The header's fields in order (little-endian struct codes), padded with zeros to HEADER_SIZE: the one layout,
# which web/src/generated.js carries to the browser player as HEADER_LAYOUT (docs/bundle-format.md, "Header").
HEADER_FIELDS = (("magic", "8s"), ("major", "H"), ("minor", "H"), ("reserved", "I"), ("manifest_length", "Q"),
                 ("manifest_sha256", "32s"))
_HEADER = fields_struct(HEADER_FIELDS)


def header_layout() -> dict[str, tuple[int, int]]:
    """Each header field's (offset, size) in bytes, and "padding": where the zero padding starts and its size."""
    return {**field_layout(HEADER_FIELDS), "padding": (_HEADER.size, HEADER_SIZE - _HEADER.size)}


def _align(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _content_key(array: np.ndarray, codec: str, chunk: int | None, sparse: bool) -> tuple:
    """What makes two buffers the same: their values (dtype, shape, bytes) and how they are coded."""
    data = np.ascontiguousarray(array)
    return str(data.dtype), tuple(data.shape), hashlib.sha256(data.tobytes()).hexdigest(), codec, chunk, bool(sparse)


@dataclass
class BundleWriter:
    """Collects graphs and buffers, then writes the bundle atomically (temp file + rename)."""

    metadata: dict = field(default_factory=dict)
    deflate: bool = False  # every buffer's payload stored as a zlib stream where that is smaller (`add_buffer`)
    _payload: list[bytes] = field(default_factory=list)
    _size: int = 0
    _buffers: dict = field(default_factory=dict)
    _graphs: dict = field(default_factory=dict)
    _stored: dict = field(default_factory=dict)  # buffer name -> its encoded payload (see `decoded_buffer`)
    _by_content: dict = field(default_factory=dict)  # (dtype, shape, sha256 of the array, codec, chunk, sparse) -> name

    def _append(self, data: bytes) -> dict:
        offset = self._size
        self._payload.append(data)
        padded = _align(len(data))
        if padded > len(data):
            self._payload.append(b"\0" * (padded - len(data)))
        self._size += padded
        return {"offset": offset, "nbytes": len(data), "sha256": _sha256(data)}

    def add_buffer(self, name: str, array: np.ndarray, codec: str = "raw", chunk: int | None = None,
                   sparse: bool = False, compress: bool | None = None) -> None:
        """Store `array` under `name`, encoded with `codec` (decoded back to the array's dtype; `chunk`: a quantised
        codec's values per chunk, `vq`'s entries; `sparse`: its nonzero elements only, after a bitmask;
        sdk/codecs.py). `compress`: the codec's payload stored as a zlib stream where that is smaller (default:
        the writer's `deflate`)."""
        if name in self._buffers:
            raise BundleError(f"buffer {name!r} added twice")
        array = np.asarray(array)
        try:
            payload, params = encode_buffer(array, codec, chunk, sparse)
        except BundleError as exc:
            raise BundleError(f"buffer {name!r}: {exc}") from None
        if expected_nbytes(codec, str(array.dtype), tuple(array.shape), params) != len(payload):
            raise BundleError(f"codec {codec!r} produced {len(payload)} bytes for buffer {name!r}")
        zipped = zlib.compress(payload, 9) if (self.deflate if compress is None else compress) else payload
        entry = self._append(zipped if len(zipped) < len(payload) else payload)
        if len(zipped) < len(payload):
            entry.update(compression="zlib", raw_nbytes=len(payload))
        entry.update(dtype=str(array.dtype), shape=list(array.shape), codec={"name": codec, **params})
        self._buffers[name] = entry
        self._stored[name] = payload
        self._by_content.setdefault(_content_key(array, codec, chunk, sparse), name)

    def find_buffer(self, array: np.ndarray, codec: str = "raw", chunk: int | None = None,
                    sparse: bool = False) -> str | None:
        """The name of a buffer already added with the same values and coding (graphs that share weights point
        at one buffer), None if there is none."""
        return self._by_content.get(_content_key(np.asarray(array), codec, chunk, sparse))

    def decoded_buffer(self, name: str) -> np.ndarray:
        """Buffer `name` as a reader will decode it (a lossy codec's values, not the array that was added)."""
        entry = self._buffers[name]
        codec = entry["codec"]
        return decode_buffer(self._stored[name], codec["name"], entry["dtype"], tuple(entry["shape"]),
                             _codec_params(codec))

    def add_graph(self, name: str, onnx_bytes: bytes, inputs: list[dict], outputs: list[dict],
                  initializers: dict[str, str] | None = None, compress: bool = True) -> None:
        """Store an ONNX graph; `initializers` maps its external initializer names to the buffers holding them.
        `compress`: stored zlib-compressed (lossless; how much it saves: docs/bundle-format.md, "Graphs")."""
        if name in self._graphs:
            raise BundleError(f"graph {name!r} added twice")
        for buffer_name in (initializers or {}).values():
            if buffer_name not in self._buffers:
                raise BundleError(f"graph {name!r} refers to unknown buffer {buffer_name!r}")
        entry = self._append(zlib.compress(onnx_bytes, 9) if compress else onnx_bytes)
        if compress:
            entry.update(compression="zlib", raw_nbytes=len(onnx_bytes))
        entry.update(inputs=inputs, outputs=outputs, initializers=dict(initializers or {}))
        self._graphs[name] = entry
        self._stored[("graph", name)] = onnx_bytes

    def graph_names(self) -> list[str]:
        return sorted(self._graphs)

    def graph_info(self, name: str) -> dict:
        return self._graphs[name]

    def graph_onnx(self, name: str) -> bytes:
        """Graph `name`'s ONNX bytes as added (uncompressed; its weights are external, see `decoded_buffer`)."""
        return self._stored[("graph", name)]

    def manifest(self) -> dict:
        return {
            "format": "gaussiantalker-bundle",
            "version": [FORMAT_MAJOR, FORMAT_MINOR],
            **self.metadata,
            "graphs": self._graphs,
            "buffers": self._buffers,
            "payload_size": self._size,
        }

    def write(self, path: str | os.PathLike | StagedFile) -> int:
        """Write the bundle to `path` atomically (a failure never leaves a partial file there), or into a file
        the caller staged with `atomic_path` (written in place: it is a temporary file already). Returns bytes."""
        try:
            manifest_bytes = json.dumps(self.manifest(), sort_keys=True, allow_nan=False).encode("utf-8")
        except ValueError as exc:  # NaN or an infinity, which JSON has no number for
            raise BundleError(f"cannot write the manifest: {exc} (NaN and infinities are not JSON)") from None
        header = _HEADER.pack(MAGIC, FORMAT_MAJOR, FORMAT_MINOR, 0, len(manifest_bytes),
                              hashlib.sha256(manifest_bytes).digest())
        header += b"\0" * (HEADER_SIZE - len(header))
        manifest_padded = manifest_bytes + b"\0" * (_align(len(manifest_bytes)) - len(manifest_bytes))
        staging = open(path.path, "wb") if isinstance(path, StagedFile) else atomic_write(path)
        with staging as handle:
            handle.write(header)
            handle.write(manifest_padded)
            for chunk in self._payload:
                handle.write(chunk)
        return HEADER_SIZE + len(manifest_padded) + self._size


class _Manifest(dict):
    """The parsed manifest: a dict whose missing top-level sections raise BundleError naming them, not KeyError."""

    def __init__(self, path: Path, data: dict) -> None:
        super().__init__(data)
        self.path = path

    def __missing__(self, key):
        raise BundleError(f"{self.path}: manifest has no {key!r} section")


def _unique_keys(pairs: list[tuple[str, object]]) -> dict:
    """A JSON object's pairs as a dict; a key given twice is refused (two readers could take different values)."""
    data = dict(pairs)
    if len(data) != len(pairs):
        seen: set[str] = set()
        key = next(k for k, _ in pairs if k in seen or seen.add(k))
        raise ValueError(f"key {key[:80]!r} appears twice in one object")
    return data


def _label(kind: str, name: str) -> str:
    """How an entry is named in errors (a name the manifest made long is cut short)."""
    return f"{kind} {name[:100]!r}" + ("..." if len(name) > 100 else "")


def _codec_params(codec: dict) -> dict:
    """A manifest codec entry's parameters (everything but its name)."""
    return {k: v for k, v in codec.items() if k != "name"}


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and -MAX_JSON_INT <= value <= MAX_JSON_INT


def _is_sha256(value) -> bool:
    return isinstance(value, str) and len(value) == 64 and all(c in "0123456789abcdef" for c in value)


def _check_tensor_list(label: str, values) -> None:
    """A graph's declared inputs or outputs: a list of {name: str, dtype: str, shape: [int | str, ...]}."""
    ok = isinstance(values, list) and all(
        isinstance(v, dict) and isinstance(v.get("name"), str) and isinstance(v.get("dtype"), str)
        and isinstance(v.get("shape"), list) and all(_is_int(d) or isinstance(d, str) for d in v["shape"])
        for v in values)
    if not ok:
        raise BundleError(f"{label} is malformed (each needs a name, a dtype and a shape list)")


class Bundle:
    """A bundle opened for reading: the manifest is parsed and checked up front; entries are read on demand."""

    def __init__(self, path: str | os.PathLike, verify_checksums: bool = True) -> None:
        self.path = Path(path)
        self.verify_checksums = verify_checksums
        if not self.path.is_file():
            raise BundleError(f"bundle {self.path} does not exist or is not a file")
        self.file_size = self.path.stat().st_size
        with open(self.path, "rb") as handle:
            self.manifest, self.payload_start = self._read_manifest(handle)
        self._check_entries()

    def _read_manifest(self, handle) -> tuple[_Manifest, int]:
        major, minor, manifest_len, digest = self._read_header(handle)
        manifest_bytes = handle.read(manifest_len)
        if hashlib.sha256(manifest_bytes).digest() != digest:
            raise BundleError(f"{self.path}: manifest checksum mismatch (corrupt manifest or header)")
        try:
            manifest = json.loads(manifest_bytes.decode("utf-8"), object_pairs_hook=_unique_keys,
                                  parse_constant=no_constant)
            if nests_deeper_than(manifest, MAX_MANIFEST_DEPTH):
                raise RecursionError
        except (UnicodeDecodeError, ValueError, RecursionError) as exc:
            detail = "it nests too deep" if isinstance(exc, RecursionError) else " ".join(str(exc).split())[:200]
            raise BundleError(f"{self.path}: manifest is not valid JSON: {detail}") from None
        if not isinstance(manifest, dict) or manifest.get("format") != "gaussiantalker-bundle":
            raise BundleError(f"{self.path}: manifest does not describe a gaussiantalker-bundle")
        version = manifest.get("version")
        if not (isinstance(version, list) and len(version) == 2 and all(map(_is_int, version))
                and version == [major, minor]):
            raise BundleError(f"{self.path}: header says format version {major}.{minor} but the manifest says "
                              f"{manifest.get('version')!r} (corrupt header)")
        payload_start = HEADER_SIZE + _align(manifest_len)
        padding = handle.read(payload_start - HEADER_SIZE - manifest_len)
        if HEADER_SIZE + manifest_len + len(padding) < payload_start:
            raise BundleError(f"{self.path}: truncated after the manifest (the payload starts at byte "
                              f"{payload_start}, the file ends at {self.file_size})")
        if padding.strip(b"\0"):
            raise BundleError(f"{self.path}: padding after the manifest is not zero (corrupt file)")
        return _Manifest(self.path, manifest), payload_start

    def _read_header(self, handle) -> tuple[int, int, int, bytes]:
        raw = handle.read(HEADER_SIZE)
        if len(raw) < HEADER_SIZE:
            raise BundleError(f"{self.path}: truncated inside the header ({len(raw)} of {HEADER_SIZE} bytes)")
        magic, major, minor, reserved, manifest_len, digest = _HEADER.unpack_from(raw)
        if magic != MAGIC:
            raise BundleError(f"{self.path}: not a GaussianTalker bundle (bad magic {magic!r})")
        if major != FORMAT_MAJOR:
            raise BundleError(f"{self.path}: bundle format version {major}.{minor} is not supported by this "
                              f"runtime (reads {FORMAT_MAJOR}.x); re-export with a matching gt-export")
        if reserved or raw[_HEADER.size:].strip(b"\0"):
            raise BundleError(f"{self.path}: reserved header bytes are not zero (corrupt header)")
        if manifest_len > MAX_MANIFEST_BYTES:
            raise BundleError(f"{self.path}: manifest claims {manifest_len} bytes, over the {MAX_MANIFEST_BYTES} "
                              f"limit (corrupt header)")
        if HEADER_SIZE + manifest_len > self.file_size:
            raise BundleError(f"{self.path}: truncated inside the manifest: it needs bytes {HEADER_SIZE}.."
                              f"{HEADER_SIZE + manifest_len}, the file ends at {self.file_size} (or the header's "
                              f"manifest length is corrupt)")
        return major, minor, manifest_len, digest

    def _check_entries(self) -> None:
        payload_size = self.manifest.get("payload_size")
        if not _is_int(payload_size) or payload_size < 0:
            raise BundleError(f"{self.path}: manifest has no valid payload_size")
        for kind in ("graphs", "buffers"):
            if not isinstance(self.manifest.get(kind), dict):
                raise BundleError(f"{self.path}: manifest has no {kind!r} table")
        labelled = [(_label(kind[:-1], name), entry) for kind in ("buffers", "graphs")
                    for name, entry in self.manifest[kind].items()]
        for label, entry in labelled:
            self._check_entry(label, entry, payload_size)
        self._check_truncation(labelled, payload_size)
        for name, entry in self.manifest["buffers"].items():
            self._check_buffer(name, entry)
        for name, entry in self.manifest["graphs"].items():
            self._check_graph(name, entry)

    def _check_entry(self, label: str, entry: dict, payload_size: int) -> None:
        if not isinstance(entry, dict):
            raise BundleError(f"{self.path}: {label} entry is malformed")
        offset, nbytes = entry.get("offset"), entry.get("nbytes")
        if not (_is_int(offset) and _is_int(nbytes) and offset >= 0 and nbytes >= 0):
            raise BundleError(f"{self.path}: {label} has an invalid offset/size")
        if offset + nbytes > payload_size:
            raise BundleError(f"{self.path}: {label} lies outside the payload (offset {offset}, {nbytes} bytes, "
                              f"payload {payload_size})")
        if not _is_sha256(entry.get("sha256")):
            raise BundleError(f"{self.path}: {label} has no valid sha256")

    def _check_truncation(self, labelled: list[tuple[str, dict]], payload_size: int) -> None:
        """Name the first entry the file cuts short, before anything is read."""
        for label, entry in sorted(labelled, key=lambda item: item[1]["offset"]):
            start = self.payload_start + entry["offset"]
            if start + entry["nbytes"] > self.file_size:
                raise BundleError(f"{self.path}: truncated inside {label}: it needs bytes {start}.."
                                  f"{start + entry['nbytes']}, the file ends at {self.file_size}")
        entries_end = max((entry["offset"] + entry["nbytes"] for _, entry in labelled), default=0)
        if payload_size != _align(entries_end):
            raise BundleError(f"{self.path}: manifest payload_size {payload_size} disagrees with its entries "
                              f"(they end at {entries_end}; corrupt manifest)")
        if self.payload_start + payload_size > self.file_size:
            raise BundleError(f"{self.path}: truncated inside the padding after the last entry (the payload ends "
                              f"at byte {self.payload_start + payload_size}, the file at {self.file_size})")

    def _check_buffer(self, name: str, entry: dict) -> None:
        """dtype, shape and codec must be well-formed and account for exactly the stored bytes."""
        shape, dtype, codec = entry.get("shape"), entry.get("dtype"), entry.get("codec")
        if not (isinstance(shape, list) and all(_is_int(d) for d in shape) and isinstance(dtype, str)
                and isinstance(codec, dict) and isinstance(codec.get("name"), str)):
            raise BundleError(f"{self.path}: {_label('buffer', name)} has a malformed dtype, shape or codec "
                              f"({repr(dtype)[:40]}, {repr(shape)[:80]}, {repr(codec)[:80]})")
        try:
            wanted = expected_nbytes(codec["name"], dtype, tuple(shape), _codec_params(codec))
        except BundleError as exc:
            raise BundleError(f"{self.path}: {_label('buffer', name)}: {exc}") from None
        compression = entry.get("compression")
        if compression is None:
            if wanted != entry["nbytes"]:
                raise BundleError(f"{self.path}: {_label('buffer', name)} declares dtype {dtype} shape {shape} "
                                  f"({wanted} bytes) but stores {entry['nbytes']} bytes")
            return
        self._check_compression(_label("buffer", name), compression, entry.get("raw_nbytes"))
        if entry["raw_nbytes"] != wanted or entry["nbytes"] > zlib_bound(wanted):
            raise BundleError(f"{self.path}: {_label('buffer', name)} declares dtype {dtype} shape {shape} ({wanted} "
                              f"bytes) but its stream's raw_nbytes is {entry['raw_nbytes']} and it stores "
                              f"{entry['nbytes']} bytes (at most {zlib_bound(wanted)} for that)")

    def _check_compression(self, label: str, compression: object, raw: object) -> None:
        """A compressed entry names a known compression and an inflated size no larger than a graph may be."""
        if compression not in GRAPH_COMPRESSIONS:
            raise BundleError(f"{self.path}: {label} has unknown compression {str(compression)[:40]!r} (this "
                              f"runtime reads: {', '.join(GRAPH_COMPRESSIONS)})")
        if not (_is_int(raw) and 0 <= raw <= MAX_GRAPH_BYTES):
            raise BundleError(f"{self.path}: {label} has an invalid raw_nbytes {repr(raw)[:40]}")

    def _check_graph(self, name: str, entry: dict) -> None:
        """Declared inputs/outputs are well-formed; every initializer maps to a buffer the bundle holds."""
        initializers = entry.get("initializers", {})
        if not (isinstance(initializers, dict) and all(isinstance(v, str) for v in initializers.values())):
            raise BundleError(f"{self.path}: {_label('graph', name)} has a malformed initializers table")
        for buffer_name in initializers.values():
            if buffer_name not in self.manifest["buffers"]:
                raise BundleError(f"{self.path}: {_label('graph', name)} needs unknown {_label('buffer', buffer_name)}")
        for kind in ("inputs", "outputs"):
            _check_tensor_list(f"{self.path}: {_label('graph', name)} {kind}", entry.get(kind))
        if entry.get("compression") is not None:
            self._check_compression(_label("graph", name), entry["compression"], entry.get("raw_nbytes"))

    @property
    def version(self) -> tuple[int, int]:
        """(major, minor) format version, the same in the header and the manifest."""
        return tuple(self.manifest["version"])

    def _read_entry(self, label: str, entry: dict) -> bytes:
        with open(self.path, "rb") as handle:
            handle.seek(self.payload_start + entry["offset"])
            data = handle.read(entry["nbytes"])
        if len(data) != entry["nbytes"]:  # the file shrank after it was opened
            raise BundleError(f"{self.path}: truncated inside {label}")
        if self.verify_checksums and _sha256(data) != entry.get("sha256"):
            raise BundleError(f"{self.path}: checksum mismatch in {label} (the file is corrupt)")
        return data

    def graph_names(self) -> list[str]:
        return sorted(self.manifest["graphs"])

    def has_buffer(self, name: str) -> bool:
        return name in self.manifest["buffers"]

    def buffer(self, name: str) -> np.ndarray:
        """Decode buffer `name` to a numpy array of its declared dtype and shape."""
        entry = self.manifest["buffers"].get(name)
        if entry is None:
            raise BundleError(f"{self.path}: bundle has no {_label('buffer', name)}")
        data = self._read_entry(_label("buffer", name), entry)
        if entry.get("compression") is not None:
            data = self._inflate(_label("buffer", name), data, entry["raw_nbytes"])
        codec = entry["codec"]
        try:
            return decode_buffer(data, codec["name"], entry["dtype"], tuple(entry["shape"]), _codec_params(codec))
        except BundleError as exc:
            raise BundleError(f"{self.path}: {_label('buffer', name)}: {exc}") from None

    def graph_info(self, name: str) -> dict:
        entry = self.manifest["graphs"].get(name)
        if entry is None:
            raise BundleError(f"{self.path}: bundle has no {_label('graph', name)} (it holds: "
                              f"{', '.join(self.graph_names()) or 'no graphs'})")
        return entry

    def graph_bytes(self, name: str) -> bytes:
        """The graph's ONNX bytes (checksummed, inflated if stored compressed)."""
        entry = self.graph_info(name)
        data = self._read_entry(_label("graph", name), entry)
        if entry.get("compression") is None:
            return data
        return self._inflate(_label("graph", name), data, entry["raw_nbytes"])

    def _inflate(self, label: str, data: bytes, raw: int) -> bytes:
        """A zlib-stored entry's bytes: exactly `raw` of them (never more are inflated), the stream complete."""
        inflater = zlib.decompressobj()
        try:
            inflated = inflater.decompress(data, raw + 1)  # at most one byte past the declared size (0: no limit)
        except zlib.error as exc:
            raise BundleError(f"{self.path}: {label} does not inflate ({exc})") from None
        if len(inflated) != raw or not inflater.eof or inflater.unconsumed_tail or inflater.unused_data:
            raise BundleError(f"{self.path}: {label} does not inflate to its declared {raw} bytes")
        return inflated

    def verify_all(self) -> None:
        """Read every entry and check its checksum (what `gt-export --verify` and loaders call)."""
        for name in self.manifest["graphs"]:
            self.graph_bytes(name)
        for name in self.manifest["buffers"]:
            self.buffer(name)
