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
import struct
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .codecs import expected_nbytes, get_codec
from .errors import BundleError

MAGIC = b"GTBUNDLE"
FORMAT_MAJOR = 1
FORMAT_MINOR = 0
HEADER_SIZE = 64
ALIGN = 64
MAX_MANIFEST_BYTES = 16 * 1024 * 1024
_HEADER = struct.Struct("<8sHHIQ32s")


def _align(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@dataclass
class BundleWriter:
    """Collects graphs and buffers, then writes the bundle atomically (temp file + rename)."""

    metadata: dict = field(default_factory=dict)
    _payload: list[bytes] = field(default_factory=list)
    _size: int = 0
    _buffers: dict = field(default_factory=dict)
    _graphs: dict = field(default_factory=dict)

    def _append(self, data: bytes) -> dict:
        offset = self._size
        self._payload.append(data)
        padded = _align(len(data))
        if padded > len(data):
            self._payload.append(b"\0" * (padded - len(data)))
        self._size += padded
        return {"offset": offset, "nbytes": len(data), "sha256": _sha256(data)}

    def add_buffer(self, name: str, array: np.ndarray, codec: str = "raw") -> None:
        """Store `array` under `name`, encoded with `codec` (decoded back to the array's dtype)."""
        if name in self._buffers:
            raise BundleError(f"buffer {name!r} added twice")
        array = np.asarray(array)
        payload, params = get_codec(codec).encode(array)
        entry = self._append(payload)
        entry.update(dtype=str(array.dtype), shape=list(array.shape), codec={"name": codec, **params})
        if expected_nbytes(codec, entry["dtype"], tuple(array.shape)) != len(payload):
            raise BundleError(f"codec {codec!r} produced {len(payload)} bytes for buffer {name!r}")
        self._buffers[name] = entry

    def add_graph(self, name: str, onnx_bytes: bytes, inputs: list[dict], outputs: list[dict],
                  initializers: dict[str, str] | None = None) -> None:
        """Store an ONNX graph; `initializers` maps its external initializer names to the buffers holding them."""
        if name in self._graphs:
            raise BundleError(f"graph {name!r} added twice")
        for buffer_name in (initializers or {}).values():
            if buffer_name not in self._buffers:
                raise BundleError(f"graph {name!r} refers to unknown buffer {buffer_name!r}")
        entry = self._append(onnx_bytes)
        entry.update(inputs=inputs, outputs=outputs, initializers=dict(initializers or {}))
        self._graphs[name] = entry

    def manifest(self) -> dict:
        return {
            "format": "gaussiantalker-bundle",
            "version": [FORMAT_MAJOR, FORMAT_MINOR],
            **self.metadata,
            "graphs": self._graphs,
            "buffers": self._buffers,
            "payload_size": self._size,
        }

    def write(self, path: str | os.PathLike) -> int:
        """Write to `path` atomically: a failure never leaves a partial file there. Returns bytes written."""
        path = Path(path)
        manifest_bytes = json.dumps(self.manifest(), sort_keys=True).encode("utf-8")
        header = _HEADER.pack(MAGIC, FORMAT_MAJOR, FORMAT_MINOR, 0, len(manifest_bytes),
                              hashlib.sha256(manifest_bytes).digest())
        header += b"\0" * (HEADER_SIZE - len(header))
        manifest_padded = manifest_bytes + b"\0" * (_align(len(manifest_bytes)) - len(manifest_bytes))
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            os.chmod(tmp_name, 0o666 & ~_current_umask())  # mkstemp makes 0600; a bundle is an ordinary file
            with os.fdopen(fd, "wb") as handle:
                handle.write(header)
                handle.write(manifest_padded)
                for chunk in self._payload:
                    handle.write(chunk)
                handle.flush()
                os.fsync(handle.fileno())
            os.replace(tmp_name, path)
        except BaseException:
            Path(tmp_name).unlink(missing_ok=True)
            raise
        return HEADER_SIZE + len(manifest_padded) + self._size


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

    def _read_manifest(self, handle) -> tuple[dict, int]:
        raw = handle.read(HEADER_SIZE)
        if len(raw) < HEADER_SIZE:
            raise BundleError(f"{self.path}: truncated header ({len(raw)} of {HEADER_SIZE} bytes)")
        magic, major, minor, _reserved, manifest_len, digest = _HEADER.unpack_from(raw)
        if magic != MAGIC:
            raise BundleError(f"{self.path}: not a GaussianTalker bundle (bad magic {magic!r})")
        if major != FORMAT_MAJOR:
            raise BundleError(f"{self.path}: bundle format version {major}.{minor} is not supported by this "
                              f"runtime (reads {FORMAT_MAJOR}.x); re-export with a matching gt-export")
        if manifest_len > MAX_MANIFEST_BYTES or HEADER_SIZE + manifest_len > self.file_size:
            raise BundleError(f"{self.path}: manifest claims {manifest_len} bytes but the file has "
                              f"{self.file_size} (truncated or corrupt header)")
        manifest_bytes = handle.read(manifest_len)
        if hashlib.sha256(manifest_bytes).digest() != digest:
            raise BundleError(f"{self.path}: manifest checksum mismatch (corrupt manifest)")
        try:
            manifest = json.loads(manifest_bytes.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise BundleError(f"{self.path}: manifest is not valid JSON: {exc}") from exc
        if not isinstance(manifest, dict) or manifest.get("format") != "gaussiantalker-bundle":
            raise BundleError(f"{self.path}: manifest does not describe a gaussiantalker-bundle")
        return manifest, HEADER_SIZE + _align(manifest_len)

    def _check_entries(self) -> None:
        payload_size = self.manifest.get("payload_size")
        if not isinstance(payload_size, int) or payload_size < 0:
            raise BundleError(f"{self.path}: manifest has no valid payload_size")
        available = self.file_size - self.payload_start
        if available < payload_size:
            raise BundleError(f"{self.path}: truncated: payload should be {payload_size} bytes, file holds "
                              f"{max(available, 0)}")
        for kind in ("graphs", "buffers"):
            if not isinstance(self.manifest.get(kind), dict):
                raise BundleError(f"{self.path}: manifest has no {kind!r} table")
        for kind in ("buffers", "graphs"):
            for name, entry in self.manifest[kind].items():
                self._check_entry(f"{kind[:-1]} {name!r}", entry, payload_size)
                if kind == "graphs":
                    for buffer_name in entry.get("initializers", {}).values():
                        if buffer_name not in self.manifest["buffers"]:
                            raise BundleError(f"{self.path}: graph {name!r} needs unknown buffer {buffer_name!r}")
                if kind == "buffers":
                    shape = tuple(entry.get("shape", ()))
                    codec = entry.get("codec", {}).get("name", "?")
                    try:
                        wanted = expected_nbytes(codec, entry.get("dtype", "?"), shape)
                    except BundleError as exc:
                        raise BundleError(f"{self.path}: buffer {name!r}: {exc}") from None
                    if wanted != entry["nbytes"]:
                        raise BundleError(f"{self.path}: buffer {name!r} declares dtype {entry['dtype']} shape "
                                          f"{list(shape)} ({wanted} bytes) but stores {entry['nbytes']} bytes")

    def _check_entry(self, label: str, entry: dict, payload_size: int) -> None:
        if not isinstance(entry, dict):
            raise BundleError(f"{self.path}: {label} entry is malformed")
        offset, nbytes = entry.get("offset"), entry.get("nbytes")
        if not (isinstance(offset, int) and isinstance(nbytes, int) and offset >= 0 and nbytes >= 0):
            raise BundleError(f"{self.path}: {label} has an invalid offset/size")
        if offset + nbytes > payload_size:
            raise BundleError(f"{self.path}: {label} lies outside the payload (offset {offset}, {nbytes} bytes, "
                              f"payload {payload_size})")

    @property
    def version(self) -> tuple[int, int]:
        return tuple(self.manifest["version"])

    def _read_entry(self, label: str, entry: dict) -> bytes:
        with open(self.path, "rb") as handle:
            handle.seek(self.payload_start + entry["offset"])
            data = handle.read(entry["nbytes"])
        if len(data) != entry["nbytes"]:
            raise BundleError(f"{self.path}: {label} is truncated")
        if self.verify_checksums and _sha256(data) != entry.get("sha256"):
            raise BundleError(f"{self.path}: checksum mismatch in {label} (the file is corrupt)")
        return data

    def buffer_names(self) -> list[str]:
        return sorted(self.manifest["buffers"])

    def graph_names(self) -> list[str]:
        return sorted(self.manifest["graphs"])

    def has_buffer(self, name: str) -> bool:
        return name in self.manifest["buffers"]

    def buffer(self, name: str) -> np.ndarray:
        """Decode buffer `name` to a numpy array of its declared dtype and shape."""
        entry = self.manifest["buffers"].get(name)
        if entry is None:
            raise BundleError(f"{self.path}: bundle has no buffer {name!r}")
        data = self._read_entry(f"buffer {name!r}", entry)
        codec = entry["codec"]
        return get_codec(codec["name"]).decode(data, entry["dtype"], tuple(entry["shape"]),
                                               {k: v for k, v in codec.items() if k != "name"})

    def graph_info(self, name: str) -> dict:
        entry = self.manifest["graphs"].get(name)
        if entry is None:
            raise BundleError(f"{self.path}: bundle has no graph {name!r}")
        return entry

    def graph_bytes(self, name: str) -> bytes:
        return self._read_entry(f"graph {name!r}", self.graph_info(name))

    def verify_all(self) -> None:
        """Read every entry and check its checksum (what `gt-export --verify` and loaders call)."""
        for name in self.manifest["graphs"]:
            self.graph_bytes(name)
        for name in self.manifest["buffers"]:
            self.buffer(name)
