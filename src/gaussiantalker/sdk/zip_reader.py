"""Zip archives from users (avatar zips, npz files) read within bounds (docs/untrusted-input.md, "Zip archives").

A zip's central directory states each member's sizes; they are trusted only as far as the bytes present allow. A
member is read only when it is not encrypted, uses a method zipfile inflates, states an uncompressed size within
the caller's budget and at most MAX_RATIO times its compressed size, and then inflates to exactly that size
(zipfile stops at the stated size and checks the CRC). An npz member's array header is checked against its stated
size before any array is allocated, and pickled (object) arrays are refused. Every failure is the caller's error
type, naming the archive and the member; nothing here extracts to disk, so a member's name never becomes a path.
"""

from __future__ import annotations

import lzma
import os
import re
import struct
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from .codecs import MAX_NDIM

# Uncompressed size a member may state per compressed byte (plus MIN_BUDGET): deflate's own limit is 1032:1, so
# only bzip2 or lzma bombs and lying headers exceed it.
MAX_RATIO = 1100
MIN_BUDGET = 1 << 16
# Every array of one npz file together, uncompressed: far above FLAME's model (~50 MB) or a tracked sequence.
MAX_NPZ_BYTES = 2 << 30
METHODS = (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA)
# What zipfile and its decompressors raise on damaged archives and members.
READ_ERRORS = (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, ValueError, zlib.error, lzma.LZMAError,
               NotImplementedError, struct.error, RuntimeError)
NPY_MAGIC = b"\x93NUMPY"
# dtype kinds an npz array may have: booleans, integers, floats and strings (FLAME npz files record their version).
NPZ_KINDS = "biufUS"
_DRIVE = re.compile(r"[A-Za-z]:")


def _line(exc: BaseException) -> str:
    """An exception as one short line (zipfile's and numpy's messages may span lines)."""
    return " ".join(str(exc).split())[:200] or type(exc).__name__


def open_zip(path: str | os.PathLike, error: type[Exception], what: str) -> zipfile.ZipFile:
    """The archive opened for reading; `error` naming the file when it is missing or not a readable zip."""
    path = Path(path)
    if not path.is_file():
        raise error(f"{what} {path} does not exist")
    try:
        return zipfile.ZipFile(path)
    except READ_ERRORS as exc:
        raise error(f"{what} {path} is not a readable zip file: {_line(exc)}") from None


def unsafe_name(name: str) -> str | None:
    """Why a member name could climb out of the folder it would be extracted to (None: it cannot): an absolute
    path, a drive letter, a backslash or a '..' component."""
    if name.startswith("/"):
        return "is an absolute path"
    if _DRIVE.match(name):
        return "starts with a drive letter"
    if "\\" in name:
        return "holds a backslash"
    if ".." in name.split("/"):
        return "climbs out of its folder ('..')"
    return None


def check_member(info: zipfile.ZipInfo, label: str, error: type[Exception], budget: int) -> None:
    """`error` unless member `info` can be read within `budget` bytes: not encrypted, a known method, a stated
    size within the budget and the ratio."""
    if info.flag_bits & 0x1:
        raise error(f"{label} is encrypted")
    if info.compress_type not in METHODS:
        raise error(f"{label} uses compression method {info.compress_type}, which is not read (stored, deflate, "
                    "bzip2, lzma are)")
    if info.file_size > budget:
        raise error(f"{label} states {info.file_size} bytes uncompressed, over the {budget} bytes left to read")
    if info.file_size > MAX_RATIO * info.compress_size + MIN_BUDGET:
        raise error(f"{label} states {info.file_size} bytes uncompressed from {info.compress_size} compressed, "
                    f"more than {MAX_RATIO} times as many (a zip bomb or a damaged header)")


def read_member(archive: zipfile.ZipFile, info: zipfile.ZipInfo, label: str, error: type[Exception],
                budget: int) -> bytes:
    """Member `info`'s bytes, checked (check_member) and inflated to exactly its stated size."""
    check_member(info, label, error, budget)
    try:
        with archive.open(info) as member:
            data = member.read(info.file_size + 1)
    except READ_ERRORS as exc:
        raise error(f"{label} is damaged: {_line(exc)}") from None
    if len(data) != info.file_size:
        raise error(f"{label} holds {len(data)} bytes, not the {info.file_size} its header states")
    return data


# -- npz ---------------------------------------------------------------------------------------------------------


def _npy_header(member, label: str, error: type[Exception]) -> tuple[tuple[int, ...], bool, np.dtype]:
    """(shape, fortran order, dtype) from an npy stream's header, checked; `error` otherwise."""
    try:
        version = np.lib.format.read_magic(member)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(member)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(member)
        else:
            raise error(f"{label}: npy format version {version[0]}.{version[1]} is not read (1.0 and 2.0 are)")
    except error:
        raise
    except READ_ERRORS + (SyntaxError, tokenize.TokenError) as exc:  # numpy parses the header as Python
        raise error(f"{label} is not a readable npy array: {_line(exc)}") from None
    if dtype.hasobject or dtype.names is not None or dtype.subdtype is not None or dtype.kind not in NPZ_KINDS \
            or dtype.itemsize == 0:
        raise error(f"{label} holds dtype {dtype.str}; an npz of numbers holds booleans, integers, floats or "
                    "strings (never pickled objects)")
    if len(shape) > MAX_NDIM or not all(isinstance(n, int) and n >= 0 for n in shape):
        raise error(f"{label} has an invalid shape {shape!r}")
    return tuple(int(n) for n in shape), bool(fortran), dtype


def _npz_members(archive: zipfile.ZipFile, path: Path, error: type[Exception]) -> dict[str, zipfile.ZipInfo]:
    """key -> member of every `KEY.npy` in the archive; a key stored twice is refused."""
    members: dict[str, zipfile.ZipInfo] = {}
    for info in archive.infolist():
        if info.filename.endswith(".npy"):
            key = info.filename[:-4]
            if key in members:
                raise error(f"{path}: the npz holds {info.filename} twice")
            members[key] = info
    return members


def _open_npz(path: Path, error: type[Exception], what: str) -> zipfile.ZipFile:
    """The npz archive, after its first bytes show a zip (np.load would unpickle other files; never done here)."""
    try:
        with path.open("rb") as handle:
            magic = handle.read(len(NPY_MAGIC))
    except FileNotFoundError:
        raise error(f"{path} does not exist") from None
    except OSError as exc:
        raise error(f"cannot read {path} ({what}): {exc.strerror or exc}") from None
    if magic.startswith(NPY_MAGIC):
        raise error(f"{path} is one array, not {what}")
    if not magic.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        raise error(f"cannot read {path} ({what}): not an npz (zip) file")
    try:
        return zipfile.ZipFile(path)
    except READ_ERRORS as exc:
        raise error(f"cannot read {path} ({what}): {_line(exc)}") from None


def read_npz(path: str | os.PathLike, error: type[Exception], what: str, keys: tuple[str, ...] | None = None,
             max_bytes: int = MAX_NPZ_BYTES) -> dict[str, np.ndarray]:
    """The arrays of an npz file (only `keys`, those present, when given), never unpickling; each member's header
    is checked against its stated size and `max_bytes` before its array is allocated. `error` naming the file and
    `what` it should be otherwise."""
    path = Path(path)
    with _open_npz(path, error, what) as archive:
        members = _npz_members(archive, path, error)
        budget, arrays = max_bytes, {}
        for key, info in members.items():
            if keys is not None and key not in keys:
                continue
            label = f"{path}: member {info.filename}"
            check_member(info, label, error, budget)
            try:
                with archive.open(info) as member:
                    shape, fortran, dtype = _npy_header(member, label, error)
                    count = 1
                    for n in shape:
                        count *= n
                    nbytes = count * dtype.itemsize
                    if member.tell() + nbytes > info.file_size:
                        raise error(f"{label}: its header declares {list(shape)} {dtype.str} ({nbytes} bytes), more "
                                    f"than the member's {info.file_size} bytes hold")
                    data = member.read(nbytes)
            except error:
                raise
            except READ_ERRORS as exc:
                raise error(f"{label} is damaged: {_line(exc)}") from None
            if len(data) != nbytes:
                raise error(f"{label} ends after {len(data)} of its {nbytes} bytes of data")
            budget -= info.file_size
            array = np.frombuffer(data, dtype, count).copy()
            arrays[key] = array.reshape(shape[::-1]).T if fortran else array.reshape(shape)
    return arrays


def npz_shape(path: str | os.PathLike, key: str, error: type[Exception], what: str) -> tuple[int, ...] | None:
    """The shape of array `key` of an npz from its header alone (None when the npz has no such array)."""
    path = Path(path)
    with _open_npz(path, error, what) as archive:
        info = _npz_members(archive, path, error).get(key)
        if info is None:
            return None
        label = f"{path}: member {info.filename}"
        check_member(info, label, error, MAX_NPZ_BYTES)
        try:
            with archive.open(info) as member:
                return _npy_header(member, label, error)[0]
        except error:
            raise
        except READ_ERRORS as exc:
            raise error(f"{label} is damaged: {_line(exc)}") from None


__all__ = ["MAX_NPZ_BYTES", "MAX_RATIO", "check_member", "npz_shape", "open_zip", "read_member", "read_npz",
           "unsafe_name"]
