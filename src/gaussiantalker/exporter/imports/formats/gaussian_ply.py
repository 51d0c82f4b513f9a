"""3D Gaussian Splatting point clouds in PLY (the INRIA layout: x, y, z, f_dc_0..2, f_rest_*, opacity, scale_*,
rot_*), read into checked float32 arrays.

The header is parsed here and every element's count checked against the bytes the file holds before anything is
allocated (docs/untrusted-input.md, "PLY"). A binary file whose elements up to `vertex` have only scalar properties
(every Gaussian PLY) is then read directly as one structured array; anything else (ASCII, list properties) goes to
plyfile with the counts already bounded.
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass

import numpy as np
from plyfile import PlyData

from gaussiantalker.sdk.errors import ImportFormatError

REQUIRED_FIELDS = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                   "rot_0", "rot_1", "rot_2", "rot_3")
# The header ends within this many bytes (a Gaussian PLY's is ~2 kB: one line per property).
MAX_HEADER_BYTES = 1 << 20
_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
          "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
          "double": "f8", "float64": "f8"}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
_F_REST = re.compile(r"f_rest_(\d{1,6})\Z")


@dataclass
class GaussianCloud:
    """One PLY's Gaussians: xyz [N, 3], f_dc [N, 3], f_rest [N, R, 3] (R = 0 without higher SH), opacity logit [N],
    log-scale [N, 3], quaternion (w, x, y, z) [N, 4], and any extra scalar fields by name."""

    xyz: np.ndarray
    f_dc: np.ndarray
    f_rest: np.ndarray
    opacity: np.ndarray
    log_scale: np.ndarray
    rotation: np.ndarray
    extra: dict

    @property
    def count(self) -> int:
        return int(self.xyz.shape[0])


@dataclass
class _Element:
    name: str
    count: int
    scalars: list  # (name, numpy type code) of the scalar properties, in file order
    lists: list  # the list properties' names
    min_row_bytes: int  # the fewest bytes one row can take


def _parse_header(data: bytes, member: str) -> tuple[str | None, int, list[_Element]]:
    """(byte order or None for ASCII, offset of the body, elements) of a PLY header; ImportFormatError on anything
    malformed, and when the elements need more bytes than the body holds."""
    if not data.startswith(b"ply"):
        raise ImportFormatError(f"{member}: not a readable PLY file: it does not start with 'ply'")
    end = re.search(rb"(?:\r?\n)end_header[ \t]*\r?\n", data[:MAX_HEADER_BYTES])
    if end is None:
        raise ImportFormatError(f"{member}: not a readable PLY file: no 'end_header' line in its first "
                                f"{MAX_HEADER_BYTES} bytes")
    lines = data[:end.start()].decode("latin-1").replace("\r", "").split("\n")
    if lines[0].strip() != "ply":
        raise ImportFormatError(f"{member}: not a readable PLY file: its first line is not 'ply'")
    order, elements = "missing", []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        bad = f"{member}: not a readable PLY file: header line {number} {line[:60]!r}"
        if words[0] == "format":
            if len(words) != 3 or words[1] not in _FORMATS or words[2] != "1.0":
                raise ImportFormatError(f"{bad} is not a PLY 1.0 format (ascii, binary_little_endian, "
                                        "binary_big_endian)")
            order = _FORMATS[words[1]]
        elif words[0] == "element":
            if len(words) != 3 or not re.fullmatch(r"\d{1,15}", words[2]):
                raise ImportFormatError(f"{bad} is not 'element NAME COUNT'")
            if any(e.name == words[1] for e in elements):
                raise ImportFormatError(f"{bad}: element {words[1]!r} appears twice")
            elements.append(_Element(words[1], int(words[2]), [], [], 0))
        elif words[0] == "property" and elements:
            element = elements[-1]
            if len(words) == 3 and words[1] in _TYPES:
                element.scalars.append((words[2], _TYPES[words[1]]))
            elif len(words) == 5 and words[1] == "list" and words[2] in _TYPES and words[3] in _TYPES:
                element.lists.append(words[4])
                element.min_row_bytes += np.dtype(_TYPES[words[2]]).itemsize  # the length of an empty list
            else:
                raise ImportFormatError(f"{bad} is not 'property TYPE NAME' or 'property list TYPE TYPE NAME'")
            names = [name for name, _ in element.scalars] + element.lists
            if len(set(names)) != len(names):
                raise ImportFormatError(f"{bad}: property {words[-1]!r} appears twice in element {element.name!r}")
        else:
            raise ImportFormatError(f"{bad} is not a PLY header line")
    if order == "missing":
        raise ImportFormatError(f"{member}: not a readable PLY file: no 'format' line")
    body = end.end()
    available = len(data) - body
    needed = 0
    for element in elements:
        if element.count and not (element.scalars or element.lists):
            raise ImportFormatError(f"{member}: the PLY's element {element.name!r} has {element.count} rows and no "
                                    "properties")
        if order is None:  # ASCII: at least one character and a separator per value, a newline per row
            element.min_row_bytes = max(1, 2 * (len(element.scalars) + len(element.lists)))
        else:
            element.min_row_bytes += sum(np.dtype(t).itemsize for _, t in element.scalars)
        needed += element.count * element.min_row_bytes
        if needed > available:
            raise ImportFormatError(f"{member}: the PLY declares {element.count} {element.name!r} rows, more than "
                                    f"its {available} bytes of data can hold (truncated or damaged file)")
    return order, body, elements


def _read_vertices(data: bytes, member: str) -> np.ndarray:
    """The `vertex` element as a structured array (its counts checked against the bytes first)."""
    order, body, elements = _parse_header(data, member)
    names = [element.name for element in elements]
    if "vertex" not in names:
        raise ImportFormatError(f"{member}: the PLY has no 'vertex' element")
    before = elements[: names.index("vertex") + 1]
    if order is not None and not any(element.lists for element in before):
        offset = body
        for element in before:
            dtype = np.dtype([(name, order + code) for name, code in element.scalars])
            rows = np.frombuffer(data, dtype, element.count, offset) if element.count else np.zeros(0, dtype)
            offset += element.count * dtype.itemsize
        return rows
    try:
        ply = PlyData.read(io.BytesIO(data))
        vertex = ply["vertex"].data
    except Exception as exc:  # plyfile raises assorted errors on damaged bodies; the counts are bounded above
        raise ImportFormatError(f"{member}: not a readable PLY file: {_one_line(exc)}") from None
    lists = [name for name in vertex.dtype.names or () if vertex.dtype[name].kind not in "biuf"]
    if lists:
        raise ImportFormatError(f"{member}: the PLY's vertex property {lists[0]!r} is a list; a Gaussian PLY's "
                                "vertex properties are numbers")
    return vertex


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text[:200] or type(exc).__name__


def read_gaussian_ply(data: bytes, member: str) -> GaussianCloud:
    """Parse a Gaussian PLY; ImportFormatError naming `member` and the field that is missing or not finite."""
    vertex = _read_vertices(data, member)
    names = vertex.dtype.names or ()
    missing = [name for name in REQUIRED_FIELDS if name not in names]
    if missing:
        raise ImportFormatError(f"{member}: the PLY's vertex element lacks field(s) {', '.join(missing)} "
                                f"(a Gaussian PLY has {', '.join(REQUIRED_FIELDS)})")
    if len(vertex) == 0:
        raise ImportFormatError(f"{member}: the PLY holds no Gaussians")

    def stack(fields: list[str]) -> np.ndarray:
        with np.errstate(invalid="ignore"):  # a signalling NaN in the file: refused below, not warned about
            out = np.stack([np.asarray(vertex[name], np.float64) for name in fields], axis=-1)
        bad = ~np.isfinite(out)
        if bad.any():
            row, column = np.argwhere(bad)[0]
            raise ImportFormatError(f"{member}: field {fields[column]} of Gaussian {row} is {out[row, column]} "
                                    f"({int(bad.any(axis=1).sum())} Gaussians have non-finite values)")
        return out.astype(np.float32)

    rest_names = [n for n in names if n.startswith("f_rest_")]
    numbers = sorted(int(m.group(1)) for n in rest_names if (m := _F_REST.match(n)))
    if numbers != list(range(len(rest_names))):
        raise ImportFormatError(f"{member}: the PLY's f_rest fields must be f_rest_0 .. f_rest_{len(rest_names) - 1}, "
                                f"got {', '.join(rest_names[:4])}{', ...' if len(rest_names) > 4 else ''}")
    rest_names = [f"f_rest_{k}" for k in numbers]
    if len(rest_names) % 3:
        raise ImportFormatError(f"{member}: {len(rest_names)} f_rest fields is not a multiple of 3")
    f_rest = stack(rest_names) if rest_names else np.zeros((len(vertex), 0), np.float32)
    # The INRIA layout stores f_rest channel-major: all of red's coefficients, then green's, then blue's.
    f_rest = f_rest.reshape(len(vertex), 3, -1).transpose(0, 2, 1)
    known = set(REQUIRED_FIELDS) | set(rest_names) | {"nx", "ny", "nz"}
    return GaussianCloud(
        xyz=stack(["x", "y", "z"]), f_dc=stack(["f_dc_0", "f_dc_1", "f_dc_2"]), f_rest=np.ascontiguousarray(f_rest),
        opacity=stack(["opacity"])[:, 0], log_scale=stack(["scale_0", "scale_1", "scale_2"]),
        rotation=stack(["rot_0", "rot_1", "rot_2", "rot_3"]),
        extra={n: np.array(vertex[n]) for n in names if n not in known})


__all__ = ["GaussianCloud", "REQUIRED_FIELDS", "read_gaussian_ply"]
