"""The parts of a glTF 2.0 binary (.glb) an avatar importer reads: accessors (sparse ones included), the node
tree's transforms, a skin's joints, and animation channels sampled at a frame rate.

Written here rather than taken from a library: pygltflib parses a LAM animation.glb (6,000 accessors) in ~10 s
through its dataclass decoding and neither decodes accessors nor samples animations; trimesh drops sparse morph
targets. A .glb is a JSON chunk and a binary chunk, so the file is read as plain dicts. Only what the importer
needs is supported: numeric accessors, LINEAR and STEP interpolation.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass

import numpy as np

from gaussiantalker.sdk.errors import ImportFormatError

GLB_MAGIC = b"glTF"
_JSON_CHUNK, _BIN_CHUNK = 0x4E4F534A, 0x004E4942


@dataclass
class Gltf:
    """A parsed .glb: its JSON document (`doc`), binary chunk (`blob`) and the member name errors cite."""

    doc: dict
    blob: bytes
    member: str

    def items(self, key: str) -> list:
        """The document's top-level list `key` (nodes, meshes, accessors, ...), [] if absent."""
        value = self.doc.get(key, [])
        if not isinstance(value, list):
            raise ImportFormatError(f"{self.member}: glTF '{key}' must be a list")
        return value

    def item(self, key: str, index) -> dict:
        """Entry `index` of list `key`, ImportFormatError if it does not exist."""
        items = self.items(key)
        if not isinstance(index, int) or not 0 <= index < len(items) or not isinstance(items[index], dict):
            raise ImportFormatError(f"{self.member}: glTF {key} {index!r} does not exist")
        return items[index]

_COMPONENT_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
                     5126: np.float32}
_TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def load_glb(data: bytes, member: str) -> Gltf:
    """Parse a .glb file's bytes (header, JSON chunk, binary chunk); ImportFormatError naming `member`."""
    if len(data) < 20 or data[:4] != GLB_MAGIC:
        raise ImportFormatError(f"{member}: not a binary glTF file (.glb): it does not start with 'glTF'")
    _, version, length = struct.unpack_from("<4sII", data, 0)
    if version != 2 or length > len(data):
        raise ImportFormatError(f"{member}: glTF version {version} with length {length} (file {len(data)} bytes): "
                                "need an untruncated glTF 2.0 binary")
    chunks, offset = {}, 12
    while offset + 8 <= length:
        size, kind = struct.unpack_from("<II", data, offset)
        chunks.setdefault(kind, data[offset + 8: offset + 8 + size])
        offset += 8 + size + (-size % 4)
    if _JSON_CHUNK not in chunks:
        raise ImportFormatError(f"{member}: the glTF file has no JSON chunk")
    try:
        doc = json.loads(chunks[_JSON_CHUNK].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ImportFormatError(f"{member}: the glTF JSON chunk is not JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise ImportFormatError(f"{member}: the glTF JSON chunk is not an object")
    return Gltf(doc, chunks.get(_BIN_CHUNK, b""), member)


def _int(value, what: str, member: str, default: int | None = None) -> int:
    if value is None and default is not None:
        return default
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise ImportFormatError(f"{member}: {what} must be a non-negative integer, got {value!r}")
    return value


def _view_array(gltf: Gltf, view_index, byte_offset, dtype, count: int, components: int) -> np.ndarray:
    """`count` x `components` values of `dtype` from a buffer view (tightly packed or strided)."""
    view = gltf.item("bufferViews", view_index)
    member = gltf.member
    view_start = _int(view.get("byteOffset"), "bufferView byteOffset", member, 0)
    view_length = _int(view.get("byteLength"), "bufferView byteLength", member)
    start = view_start + _int(byte_offset, "accessor byteOffset", member, 0)
    item = np.dtype(dtype).itemsize * components
    stride = _int(view.get("byteStride"), "bufferView byteStride", member, 0) or item
    end = start + stride * (count - 1) + item if count else start
    if end > view_start + view_length or end > len(gltf.blob):
        raise ImportFormatError(f"{member}: accessor data runs past bufferView {view_index} or the binary chunk")
    raw = np.frombuffer(gltf.blob, np.uint8, end - start, start)
    if stride == item:
        return raw.view(dtype).reshape(count, components).copy()
    rows = np.lib.stride_tricks.as_strided(raw, (count, item), (stride, 1))
    return np.ascontiguousarray(rows).view(dtype).reshape(count, components)


def read_accessor(gltf: Gltf, index) -> np.ndarray:
    """Accessor `index` as [count, components] (its own dtype); sparse values applied over the base values."""
    accessor = gltf.item("accessors", index)
    member = gltf.member
    dtype = _COMPONENT_DTYPES.get(accessor.get("componentType"))
    components = _TYPE_SIZES.get(accessor.get("type"))
    if dtype is None or components is None:
        raise ImportFormatError(f"{member}: accessor {index} has an unsupported type "
                                f"({accessor.get('componentType')}, {accessor.get('type')})")
    count = _int(accessor.get("count"), f"accessor {index} count", member)
    if accessor.get("bufferView") is None:
        values = np.zeros((count, components), dtype)
    else:
        values = _view_array(gltf, accessor["bufferView"], accessor.get("byteOffset"), dtype, count, components)
    sparse = accessor.get("sparse")
    if isinstance(sparse, dict) and sparse.get("count"):
        changed = _int(sparse.get("count"), f"accessor {index} sparse count", member)
        indices, data = sparse.get("indices") or {}, sparse.get("values") or {}
        index_dtype = _COMPONENT_DTYPES.get(indices.get("componentType"))
        if index_dtype is None:
            raise ImportFormatError(f"{member}: sparse accessor {index} has no valid indices componentType")
        rows = _view_array(gltf, indices.get("bufferView"), indices.get("byteOffset"), index_dtype, changed,
                           1)[:, 0].astype(np.int64)
        if rows.size and (rows.min() < 0 or rows.max() >= count):
            raise ImportFormatError(f"{member}: sparse accessor {index} indexes rows outside [0, {count})")
        values[rows] = _view_array(gltf, data.get("bufferView"), data.get("byteOffset"), dtype, changed,
                                   components)
    return values


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """glTF quaternion (x, y, z, w) [..., 4] -> rotation matrices [..., 3, 3] (normalised first)."""
    q = np.asarray(q, np.float64)
    x, y, z, w = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def trs_matrix(translation, rotation, scale) -> np.ndarray:
    """4x4 T * R * S of a node's (translation, rotation quaternion xyzw, scale)."""
    matrix = np.eye(4)
    matrix[:3, :3] = quaternion_matrix(np.asarray(rotation, np.float64)) * np.asarray(scale, np.float64)
    matrix[:3, 3] = translation
    return matrix


def node_trs(gltf: Gltf, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Node `index`'s rest (translation, rotation, scale), glTF's defaults filled in (a `matrix` is refused)."""
    node = gltf.item("nodes", index)
    matrix = node.get("matrix")
    if matrix is not None and not np.allclose(np.asarray(matrix, np.float64), np.eye(4).ravel()):
        raise ImportFormatError(f"{gltf.member}: node {node.get('name', index)!r} stores a matrix, not "
                                "translation/rotation/scale; the importer needs TRS nodes")
    try:
        return (np.asarray(node.get("translation", (0.0, 0.0, 0.0)), np.float64).reshape(3),
                np.asarray(node.get("rotation", (0.0, 0.0, 0.0, 1.0)), np.float64).reshape(4),
                np.asarray(node.get("scale", (1.0, 1.0, 1.0)), np.float64).reshape(3))
    except (TypeError, ValueError):
        raise ImportFormatError(f"{gltf.member}: node {node.get('name', index)!r} has a malformed "
                                "translation/rotation/scale") from None


def node_names(gltf: Gltf) -> list:
    """Each node's name (None when unnamed)."""
    return [node.get("name") if isinstance(node, dict) else None for node in gltf.items("nodes")]


def parents(gltf: Gltf) -> dict[int, int]:
    """Child node index -> parent node index."""
    return {child: index for index, node in enumerate(gltf.items("nodes")) for child in node.get("children", [])}


def chain(gltf: Gltf, node: int) -> list[int]:
    """`node` and its ancestors up to the root, child first; ImportFormatError on a cycle."""
    up, out = parents(gltf), []
    current = node
    while current is not None:
        if current in out:
            raise ImportFormatError(f"{gltf.member}: the glTF node tree has a cycle through node {current}")
        out.append(current)
        current = up.get(current)
    return out


def world_matrix(gltf: Gltf, node: int, trs: dict[int, tuple] | None = None) -> np.ndarray:
    """4x4 world transform of `node`: its chain of local TRS up to the root (`trs` overrides some nodes' TRS)."""
    matrix = np.eye(4)
    for index in chain(gltf, node):
        local = (trs or {}).get(index) or node_trs(gltf, index)
        matrix = trs_matrix(*local) @ matrix
    return matrix


def _slerp(a: np.ndarray, b: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Shortest-path spherical interpolation of unit quaternions [T, 4] (glTF's LINEAR for rotations)."""
    dot = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(dot < 0, -b, b)
    angle = np.arccos(np.clip(np.abs(dot), -1.0, 1.0))
    sin = np.sin(angle)
    near = sin < 1e-6  # nearly equal: linear interpolation is exact to rounding
    safe = np.where(near, 1.0, sin)
    wa = np.where(near, 1.0 - weight, np.sin((1.0 - weight) * angle) / safe)
    wb = np.where(near, weight, np.sin(weight * angle) / safe)
    out = wa * a + wb * b
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def sample_channel(times: np.ndarray, values: np.ndarray, interpolation: str, path: str, at: np.ndarray,
                   member: str) -> np.ndarray:
    """Values [len(at), C] of an animation sampler at times `at` (clamped to its key range)."""
    times = np.asarray(times, np.float64).reshape(-1)
    if times.size == 0 or values.shape[0] != times.shape[0]:
        raise ImportFormatError(f"{member}: an animation sampler has {times.size} key times and "
                                f"{values.shape[0]} values")
    values = np.asarray(values, np.float64).reshape(times.shape[0], -1)
    if interpolation not in ("LINEAR", "STEP"):
        raise ImportFormatError(f"{member}: animation interpolation {interpolation!r} is not supported (LINEAR "
                                "and STEP are)")
    if times.shape[0] == 1:
        return np.repeat(values, at.shape[0], axis=0)
    at = np.clip(at, times[0], times[-1])
    right = np.clip(np.searchsorted(times, at, side="right"), 1, times.shape[0] - 1)
    left = right - 1
    if interpolation == "STEP":
        return values[np.where(at >= times[right], right, left)]
    span = np.maximum(times[right] - times[left], 1e-12)
    weight = ((at - times[left]) / span)[:, None]
    if path == "rotation":
        return _slerp(values[left], values[right], weight)
    return values[left] * (1 - weight) + values[right] * weight


def animation_names(gltf: Gltf) -> list[str]:
    """The clip names of a glTF file, in file order (unnamed clips as "animation_K")."""
    return [a.get("name") or f"animation_{k}" for k, a in enumerate(gltf.items("animations"))]


def clip_duration(gltf: Gltf, clip: int) -> float:
    """Last key time of clip `clip`."""
    samplers = gltf.item("animations", clip).get("samplers", [])
    return max((float(read_accessor(gltf, s.get("input")).max(initial=0.0)) for s in samplers), default=0.0)


def sampled_world(skin: Gltf, node: int, animation: Gltf, clip: int, at: np.ndarray) -> np.ndarray:
    """World transforms [len(at), 4, 4] of `skin`'s `node` with clip `clip` of `animation` applied to the nodes of
    the same name (how a player binds a clip to a model), the other nodes at rest."""
    names = {name: i for i, name in enumerate(node_names(skin)) if name}
    ancestors = chain(skin, node)
    animated: dict[tuple[int, str], np.ndarray] = {}
    source_names = node_names(animation)
    entry = animation.item("animations", clip)
    samplers = entry.get("samplers", [])
    for channel in entry.get("channels", []):
        target = channel.get("target") or {}
        name = source_names[target["node"]] if isinstance(target.get("node"), int) and \
            0 <= target["node"] < len(source_names) else None
        path = target.get("path")
        if name in names and names[name] in ancestors and path in ("translation", "rotation", "scale"):
            sampler = samplers[_int(channel.get("sampler"), "channel sampler", animation.member)]
            animated[(names[name], path)] = sample_channel(
                read_accessor(animation, sampler.get("input")), read_accessor(animation, sampler.get("output")),
                sampler.get("interpolation", "LINEAR"), path, at, animation.member)
    rest = {index: node_trs(skin, index) for index in ancestors}
    out = np.empty((at.shape[0], 4, 4))
    for frame in range(at.shape[0]):
        matrix = np.eye(4)
        for index in ancestors:
            local = tuple(animated[(index, path)][frame] if (index, path) in animated else rest[index][k]
                          for k, path in enumerate(("translation", "rotation", "scale")))
            matrix = trs_matrix(*local) @ matrix
        out[frame] = matrix
    return out


__all__ = ["Gltf", "animation_names", "chain", "clip_duration", "load_glb", "node_names", "node_trs", "parents",
           "quaternion_matrix", "read_accessor", "sample_channel", "sampled_world", "trs_matrix", "world_matrix"]
