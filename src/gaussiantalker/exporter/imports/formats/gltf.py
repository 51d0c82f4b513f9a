"""The parts of a glTF 2.0 binary (.glb) an avatar importer reads: accessors (sparse ones included), the node
tree's transforms, a skin's joints, and animation channels sampled at a frame rate.

Written here rather than taken from a library: pygltflib parses a LAM animation.glb (6,000 accessors) in ~10 s
through its dataclass decoding and neither decodes accessors nor samples animations; trimesh drops sparse morph
targets. A .glb is a JSON chunk and a binary chunk, so the file is read as plain dicts. Only what the importer
needs is supported: numeric accessors, LINEAR and STEP interpolation.

The file is the user's (docs/untrusted-input.md, "glTF"): every index, count, offset and stride is checked against
the document and the bytes of the binary chunk before any array is made, every JSON value's type before it is used.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass

import numpy as np

from gaussiantalker.sdk.errors import ImportFormatError

GLB_MAGIC = b"glTF"
_JSON_CHUNK, _BIN_CHUNK = 0x4E4F534A, 0x004E4942
# The deepest node a transform is computed for (a skeleton is a few bones deep; each level costs a matrix product
# per sampled frame).
MAX_DEPTH = 256
# An accessor without a bufferView (all zeros, or sparse over zeros) is allocated from its count alone, so it may
# hold at most as many values as the binary chunk has bytes, or this many.
MIN_ZERO_VALUES = 4096


def parse_json(data: bytes, member: str) -> object:
    """A JSON document's bytes parsed; ImportFormatError naming `member` when it is not UTF-8 JSON, nests too deep
    or holds a number Python refuses to read (over 4300 digits)."""
    try:
        return json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        detail = "it nests too deep" if isinstance(exc, RecursionError) else " ".join(str(exc).split())[:200]
        raise ImportFormatError(f"{member} is not JSON: {detail}") from None


def as_dict(value, what: str, member: str) -> dict:
    """`value` if it is a JSON object, else ImportFormatError naming `what`."""
    if not isinstance(value, dict):
        raise ImportFormatError(f"{member}: glTF {what} must be an object, got {type(value).__name__}")
    return value


def as_list(value, what: str, member: str) -> list:
    """`value` if it is a JSON array (None: empty), else ImportFormatError naming `what`."""
    if value is None:
        return []
    if not isinstance(value, list):
        raise ImportFormatError(f"{member}: glTF {what} must be a list, got {type(value).__name__}")
    return value


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
        if not _is_int(index) or not 0 <= index < len(items) or not isinstance(items[index], dict):
            raise ImportFormatError(f"{self.member}: glTF {key} {str(index)[:40]} does not exist")
        return items[index]


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


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
        if offset + 8 + size > length:
            raise ImportFormatError(f"{member}: a glTF chunk of {size} bytes at byte {offset} runs past the file's "
                                    f"length {length} (truncated or damaged file)")
        if kind not in chunks:
            chunks[kind] = data[offset + 8: offset + 8 + size]
        offset += 8 + size + (-size % 4)
    if _JSON_CHUNK not in chunks:
        raise ImportFormatError(f"{member}: the glTF file has no JSON chunk")
    doc = parse_json(chunks[_JSON_CHUNK], f"{member}: the glTF JSON chunk")
    if not isinstance(doc, dict):
        raise ImportFormatError(f"{member}: the glTF JSON chunk is not an object")
    return Gltf(doc, chunks.get(_BIN_CHUNK, b""), member)


def _int(value, what: str, member: str, default: int | None = None) -> int:
    if value is None and default is not None:
        return default
    if not _is_int(value) or value < 0:
        raise ImportFormatError(f"{member}: {what} must be a non-negative integer, got {str(value)[:40]}")
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
    if stride < item:
        raise ImportFormatError(f"{member}: bufferView {view_index} has byteStride {stride}, less than its "
                                f"{item}-byte elements")
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
    dtype = _table_get(_COMPONENT_DTYPES, accessor.get("componentType"))
    components = _table_get(_TYPE_SIZES, accessor.get("type"))
    if dtype is None or components is None:
        raise ImportFormatError(f"{member}: accessor {index} has an unsupported type "
                                f"({str(accessor.get('componentType'))[:20]}, {str(accessor.get('type'))[:20]})")
    count = _int(accessor.get("count"), f"accessor {index} count", member)
    if accessor.get("bufferView") is None:
        if count * components > max(len(gltf.blob), MIN_ZERO_VALUES):
            raise ImportFormatError(f"{member}: accessor {index} claims {count} rows without a bufferView, more "
                                    f"than the file's {len(gltf.blob)}-byte binary chunk could describe")
        values = np.zeros((count, components), dtype)
    else:
        values = _view_array(gltf, accessor["bufferView"], accessor.get("byteOffset"), dtype, count, components)
    sparse = accessor.get("sparse")
    if sparse is not None and as_dict(sparse, f"accessor {index} sparse", member).get("count"):
        changed = _int(sparse.get("count"), f"accessor {index} sparse count", member)
        indices = as_dict(sparse.get("indices") or {}, f"accessor {index} sparse indices", member)
        data = as_dict(sparse.get("values") or {}, f"accessor {index} sparse values", member)
        index_dtype = _table_get(_COMPONENT_DTYPES, indices.get("componentType"))
        if index_dtype is None:
            raise ImportFormatError(f"{member}: sparse accessor {index} has no valid indices componentType")
        rows = _view_array(gltf, indices.get("bufferView"), indices.get("byteOffset"), index_dtype, changed,
                           1)[:, 0].astype(np.int64)
        if rows.size and (rows.min() < 0 or rows.max() >= count):
            raise ImportFormatError(f"{member}: sparse accessor {index} indexes rows outside [0, {count})")
        values[rows] = _view_array(gltf, data.get("bufferView"), data.get("byteOffset"), dtype, changed,
                                   components)
    return values


def _table_get(table: dict, key):
    """table[key], None for a missing or unhashable key (a JSON list or object where a name belongs)."""
    return table.get(key) if isinstance(key, int | str) else None


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


def _numbers(value, size: int, default: tuple, what: str, member: str) -> np.ndarray:
    """A JSON list of `size` finite numbers as float64 (`default` when absent); ImportFormatError otherwise."""
    if value is None:
        return np.asarray(default, np.float64)
    ok = isinstance(value, list) and len(value) == size and all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    try:
        array = np.asarray(value, np.float64) if ok else None
    except OverflowError:
        array = None
    if array is None or not np.isfinite(array).all():
        raise ImportFormatError(f"{member}: {what} must be {size} finite numbers, got {str(value)[:60]}")
    return array


def node_trs(gltf: Gltf, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Node `index`'s rest (translation, rotation, scale), glTF's defaults filled in (a `matrix` is refused)."""
    node = gltf.item("nodes", index)
    label = f"node {index}"
    matrix = node.get("matrix")
    if matrix is not None and not np.array_equal(_numbers(matrix, 16, (), f"{label} matrix", gltf.member),
                                                 np.eye(4).ravel()):
        raise ImportFormatError(f"{gltf.member}: {label} ({str(node.get('name'))[:40]}) stores a matrix, not "
                                "translation/rotation/scale; the importer needs TRS nodes")
    rotation = _numbers(node.get("rotation"), 4, (0.0, 0.0, 0.0, 1.0), f"{label} rotation", gltf.member)
    if not np.linalg.norm(rotation) > 0:
        raise ImportFormatError(f"{gltf.member}: {label} rotation is the zero quaternion")
    return (_numbers(node.get("translation"), 3, (0.0, 0.0, 0.0), f"{label} translation", gltf.member), rotation,
            _numbers(node.get("scale"), 3, (1.0, 1.0, 1.0), f"{label} scale", gltf.member))


def node_names(gltf: Gltf) -> list:
    """Each node's name (None when unnamed or not a string)."""
    return [node.get("name") if isinstance(node, dict) and isinstance(node.get("name"), str) else None
            for node in gltf.items("nodes")]


def parents(gltf: Gltf) -> dict[int, int]:
    """Child node index -> parent node index; ImportFormatError for a child that is not a node or has two parents."""
    nodes = gltf.items("nodes")
    up: dict[int, int] = {}
    for index, node in enumerate(nodes):
        children = as_list(as_dict(node, f"node {index}", gltf.member).get("children"), f"node {index} children",
                           gltf.member)
        for child in children:
            if not _is_int(child) or not 0 <= child < len(nodes):
                raise ImportFormatError(f"{gltf.member}: node {index} has a child {str(child)[:40]} that is not a node")
            if child in up:
                raise ImportFormatError(f"{gltf.member}: node {child} has two parents ({up[child]} and {index})")
            up[child] = index
    return up


def chain(gltf: Gltf, node: int) -> list[int]:
    """`node` and its ancestors up to the root, child first; ImportFormatError on a cycle."""
    up, out, seen = parents(gltf), [], set()
    current = node
    while current is not None:
        if current in seen:
            raise ImportFormatError(f"{gltf.member}: the glTF node tree has a cycle through node {current}")
        seen.add(current)
        out.append(current)
        if len(out) > MAX_DEPTH:
            raise ImportFormatError(f"{gltf.member}: node {node} lies over {MAX_DEPTH} levels deep in the node tree")
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
    width = {"translation": 3, "rotation": 4, "scale": 3}.get(path)
    if width is not None and values.shape[1] != width:
        raise ImportFormatError(f"{member}: an animation sampler of {path} holds {values.shape[1]} values per key, "
                                f"not {width}")
    if not (np.isfinite(times).all() and np.isfinite(values).all()):
        raise ImportFormatError(f"{member}: an animation sampler holds non-finite key times or values")
    if np.any(np.diff(times) <= 0):
        raise ImportFormatError(f"{member}: an animation sampler's key times do not increase")
    if path == "rotation" and not np.all(np.linalg.norm(values, axis=1) > 0):
        raise ImportFormatError(f"{member}: an animation sampler of rotation holds a zero quaternion")
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
    clips = [as_dict(a, f"animation {k}", gltf.member) for k, a in enumerate(gltf.items("animations"))]
    return [a["name"] if isinstance(a.get("name"), str) and a["name"] else f"animation_{k}"
            for k, a in enumerate(clips)]


def _samplers(gltf: Gltf, clip: int) -> list[dict]:
    """Clip `clip`'s samplers, each an object."""
    samplers = as_list(gltf.item("animations", clip).get("samplers"), f"animation {clip} samplers", gltf.member)
    return [as_dict(s, f"animation {clip} sampler {k}", gltf.member) for k, s in enumerate(samplers)]


def clip_duration(gltf: Gltf, clip: int) -> float:
    """Last key time of clip `clip`."""
    times = [read_accessor(gltf, s.get("input")) for s in _samplers(gltf, clip)]
    if not all(np.isfinite(t).all() for t in times):
        raise ImportFormatError(f"{gltf.member}: animation {clip} holds non-finite key times")
    return max((float(t.max(initial=0.0)) for t in times), default=0.0)


def sampled_world(skin: Gltf, node: int, animation: Gltf, clip: int, at: np.ndarray) -> np.ndarray:
    """World transforms [len(at), 4, 4] of `skin`'s `node` with clip `clip` of `animation` applied to the nodes of
    the same name (how a player binds a clip to a model), the other nodes at rest."""
    names = {name: i for i, name in enumerate(node_names(skin)) if name}
    ancestors = chain(skin, node)
    animated: dict[tuple[int, str], np.ndarray] = {}
    source_names = node_names(animation)
    entry = animation.item("animations", clip)
    samplers = _samplers(animation, clip)
    member = animation.member
    chosen: dict[tuple[int, str], int] = {}  # (skin node, path) -> sampler; a later channel wins, as before
    for k, channel in enumerate(as_list(entry.get("channels"), f"animation {clip} channels", member)):
        target = as_dict(as_dict(channel, f"animation {clip} channel {k}", member).get("target") or {},
                         f"animation {clip} channel {k} target", member)
        source = target.get("node")
        name = source_names[source] if _is_int(source) and 0 <= source < len(source_names) else None
        path = target.get("path")
        if name in names and names[name] in ancestors and path in ("translation", "rotation", "scale"):
            index = _int(channel.get("sampler"), "channel sampler", member)
            if index >= len(samplers):
                raise ImportFormatError(f"{member}: animation {clip} channel {k} uses sampler {index}, which does "
                                        "not exist")
            chosen[(names[name], path)] = index
    for (bone, path), index in chosen.items():  # each sampled once, however many channels name it
        sampler = samplers[index]
        animated[(bone, path)] = sample_channel(
            read_accessor(animation, sampler.get("input")), read_accessor(animation, sampler.get("output")),
            sampler.get("interpolation", "LINEAR"), path, at, member)
    out = np.broadcast_to(np.eye(4), (at.shape[0], 4, 4))
    for index in ancestors:
        rest = node_trs(skin, index)
        local = [animated.get((index, path), rest[k][None]) for k, path in enumerate(("translation", "rotation",
                                                                                       "scale"))]
        out = _trs_matrices(*local, at.shape[0]) @ out
    return np.ascontiguousarray(out)


def _trs_matrices(translation: np.ndarray, rotation: np.ndarray, scale: np.ndarray, count: int) -> np.ndarray:
    """[count, 4, 4] T * R * S from per-frame (or one, [1, ...]) translations, xyzw quaternions and scales."""
    matrices = np.zeros((count, 4, 4))
    matrices[:, :3, :3] = quaternion_matrix(rotation) * scale[:, None, :]
    matrices[:, :3, 3] = translation
    matrices[:, 3, 3] = 1.0
    return matrices


__all__ = ["Gltf", "animation_names", "chain", "clip_duration", "load_glb", "node_names", "node_trs", "parents",
           "quaternion_matrix", "read_accessor", "sample_channel", "sampled_world", "trs_matrix", "world_matrix"]
