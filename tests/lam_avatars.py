"""Small LAM-format avatar zips for the tests, written from the glTF 2.0 and PLY specifications (no avatar is
committed): an ellipsoid head mesh with a few sparse ARKit morph targets, a skeleton hip -> neck -> head (LAM's
renderer needs the bone named "hip") under a Z-up, centimetre root like LAM's, an animation.glb whose clips turn
the head, an offset.ply of one Gaussian per vertex. `expected_centres` computes where LAM's renderer puts each
Gaussian with this module's own maths, so the importer is checked against the format, not against itself.
"""

from __future__ import annotations

import io
import json
import struct
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT_ROTATION = (np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5))  # glTF (x, y, z, w): +90 degrees about x, as LAM's root
ROOT_SCALE = 0.01  # the skeleton in centimetres
HIP_LOCAL = (0.0, 0.0, -140.0)  # under the root: 1.4 m up in the world (y)
NECK_LOCAL = (0.0, 0.0, -10.0)  # 0.1 m above the hip
HEAD_LOCAL = (0.0, 0.0, -10.0)  # 0.1 m above the neck
MORPHS = {  # name -> (which vertices move: a predicate on the rest position relative to the head centre, delta m)
    "jawOpen": (lambda p: p[:, 1] < -0.03, (0.0, -0.02, 0.005)),
    "eyeBlinkLeft": (lambda p: (p[:, 1] > 0.02) & (p[:, 0] > 0.02), (0.0, -0.006, 0.0)),
    "mouthSmileLeft": (lambda p: (p[:, 1] < 0.0) & (p[:, 0] > 0.0) & (p[:, 2] > 0.05), (0.008, 0.006, 0.0)),
    "browInnerUp": (lambda p: p[:, 1] > 0.05, (0.0, 0.01, 0.0)),
}
HEAD_CENTRE = np.array([0.0, 1.6, 0.0])


def quat_matrix(q) -> np.ndarray:
    """(x, y, z, w) -> 3x3."""
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def axis_angle_quat(axis, angle: float) -> tuple[float, float, float, float]:
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    s = np.sin(angle / 2)
    return (*(axis * s), np.cos(angle / 2))


def trs(t=(0, 0, 0), r=(0, 0, 0, 1), s=(1, 1, 1)) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quat_matrix(r) * np.asarray(s, np.float64)
    m[:3, 3] = t
    return m


@dataclass
class AvatarSpec:
    """What to write: mesh resolution, seed, clips (name -> list of (time, head rotation angle about local x)),
    and which members to leave out or spoil (for bad-input tests)."""

    rings: int = 8
    segments: int = 12
    seed: int = 0
    clips: dict = field(default_factory=lambda: {"idle": [(0.0, 0.0), (0.5, 0.3), (1.0, 0.0)],
                                                 "speak": [(0.0, 0.0), (0.2, -0.2)]})
    folder: str | None = "avatar"
    motion: bool = True
    skip: tuple[str, ...] = ()
    vertex_order_length: int | None = None
    extra_names: tuple[str, ...] = ()
    neck_below: float | None = None  # vertices lower than this (m, from HEAD_CENTRE) skinned to the neck, not the head
    subdivided: bool = False  # the grid's triangles split in four, as LAM's subdivided FLAME (indices written)


def _grid_vertices(spec: AvatarSpec) -> np.ndarray:
    """[rings x segments, 3] an ellipsoid around HEAD_CENTRE (metres)."""
    theta = np.linspace(0.15, np.pi - 0.15, spec.rings)
    phi = np.linspace(0, 2 * np.pi, spec.segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    points = np.stack([0.08 * np.sin(t) * np.cos(p), 0.11 * np.cos(t), 0.09 * np.sin(t) * np.sin(p)], -1)
    return points.reshape(-1, 3) + HEAD_CENTRE


def _grid_faces(spec: AvatarSpec) -> np.ndarray:
    """[F, 3] two triangles per quad of the ring grid (closed round the segments)."""
    ring, seg = np.meshgrid(np.arange(spec.rings - 1), np.arange(spec.segments), indexing="ij")
    here, right = ring * spec.segments + seg, ring * spec.segments + (seg + 1) % spec.segments
    below, below_right = here + spec.segments, right + spec.segments
    return np.concatenate([np.stack([here, right, below], -1).reshape(-1, 3),
                           np.stack([right, below_right, below], -1).reshape(-1, 3)])


def _edges(spec: AvatarSpec) -> np.ndarray:
    """[E, 2] the grid's edges (a < b), in the order their midpoint vertices follow the grid's."""
    faces = _grid_faces(spec)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(edges, axis=0)


def mesh_faces(spec: AvatarSpec) -> np.ndarray:
    """[F, 3] the head mesh's triangles: the grid's, or each split in four through its edges' midpoints."""
    faces = _grid_faces(spec)
    if not spec.subdivided:
        return faces
    edges = _edges(spec)
    mid_of = {tuple(e): len(_grid_vertices(spec)) + k for k, e in enumerate(edges.tolist())}
    out = []
    for a, b, c in faces.tolist():
        ab, bc, ca = (mid_of[tuple(sorted(pair))] for pair in ((a, b), (b, c), (c, a)))
        out += [(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)]
    return np.array(out, np.int64)


def rest_vertices(spec: AvatarSpec) -> np.ndarray:
    """[V, 3] the head mesh's vertices (metres): the grid's, then (subdivided) each edge's midpoint."""
    grid = _grid_vertices(spec)
    if not spec.subdivided:
        return grid
    edges = _edges(spec)
    return np.concatenate([grid, (grid[edges[:, 0]] + grid[edges[:, 1]]) / 2])


def morph_deltas(spec: AvatarSpec) -> dict[str, np.ndarray]:
    """name -> [V, 3] delta (zero where the morph does not reach); an edge's midpoint moves as the mean of its
    ends, as a subdivided mesh's morph targets do."""
    rest = _grid_vertices(spec) - HEAD_CENTRE
    edges = _edges(spec)
    out = {}
    for name, (where, delta) in MORPHS.items():
        d = np.zeros_like(rest)
        d[where(rest)] = delta
        out[name] = np.concatenate([d, (d[edges[:, 0]] + d[edges[:, 1]]) / 2]) if spec.subdivided else d
    return out


def gaussians(spec: AvatarSpec) -> dict[str, np.ndarray]:
    """Per-vertex Gaussian attributes as offset.ply stores them."""
    rng = np.random.default_rng(spec.seed)
    count = rest_vertices(spec).shape[0]
    rotation = rng.normal(size=(count, 4))
    return {"xyz": rng.uniform(-0.004, 0.004, (count, 3)), "f_dc": rng.uniform(0.05, 0.95, (count, 3)),
            "opacity": rng.uniform(1.0, 4.0, count), "scale": np.log(rng.uniform(0.006, 0.014, (count, 3))),
            "rot": rotation / np.linalg.norm(rotation, axis=1, keepdims=True)}


class _Glb:
    """Accumulates a glTF document and its binary chunk."""

    def __init__(self) -> None:
        self.doc = {"asset": {"version": "2.0"}, "buffers": [], "bufferViews": [], "accessors": []}
        self.blob = bytearray()

    def view(self, data: bytes) -> int:
        while len(self.blob) % 4:
            self.blob.append(0)
        self.doc["bufferViews"].append({"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data)})
        self.blob += data
        return len(self.doc["bufferViews"]) - 1

    def accessor(self, array: np.ndarray, kind: str) -> int:
        array = np.ascontiguousarray(array, np.float32)
        entry = {"bufferView": self.view(array.tobytes()), "componentType": 5126, "count": int(array.shape[0]),
                 "type": kind}
        if kind == "VEC3":
            entry["min"], entry["max"] = array.min(0).tolist(), array.max(0).tolist()
        self.doc["accessors"].append(entry)
        return len(self.doc["accessors"]) - 1

    def sparse_accessor(self, delta: np.ndarray) -> int:
        rows = np.flatnonzero(np.abs(delta).sum(1) > 0).astype(np.uint32)
        entry = {"componentType": 5126, "count": int(delta.shape[0]), "type": "VEC3",
                 "sparse": {"count": int(rows.size),
                            "indices": {"bufferView": self.view(rows.tobytes()), "componentType": 5125},
                            "values": {"bufferView": self.view(np.ascontiguousarray(delta[rows], np.float32)
                                                               .tobytes())}}}
        self.doc["accessors"].append(entry)
        return len(self.doc["accessors"]) - 1

    def bytes(self) -> bytes:
        while len(self.blob) % 4:
            self.blob.append(0)
        self.doc["buffers"] = [{"byteLength": len(self.blob)}]
        text = json.dumps(self.doc).encode()
        text += b" " * (-len(text) % 4)
        body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(self.blob), 0x004E4942) \
            + bytes(self.blob)
        return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


HEAD_NODE = 3


def _skeleton_nodes() -> list[dict]:
    return [{"name": "Armature", "rotation": list(ROOT_ROTATION), "scale": [ROOT_SCALE] * 3, "children": [1]},
            {"name": "hip", "translation": list(HIP_LOCAL), "children": [2]},
            {"name": "neck", "translation": list(NECK_LOCAL), "children": [3]},
            {"name": "head", "translation": list(HEAD_LOCAL)}]


def world(locals_: list[np.ndarray]) -> list[np.ndarray]:
    """World matrices of the chain root -> hip -> neck -> head from their local matrices."""
    out, current = [], np.eye(4)
    for local in locals_:
        current = current @ local
        out.append(current)
    return out


def rest_worlds() -> list[np.ndarray]:
    """World matrices of the joints hip, neck, head at rest."""
    return world([trs(r=ROOT_ROTATION, s=[ROOT_SCALE] * 3), trs(t=HIP_LOCAL), trs(t=NECK_LOCAL),
                  trs(t=HEAD_LOCAL)])[1:]


def skin_glb(spec: AvatarSpec) -> bytes:
    glb = _Glb()
    rest = rest_vertices(spec)
    names = list(MORPHS) + list(spec.extra_names)
    deltas = morph_deltas(spec)
    targets = [{"POSITION": glb.sparse_accessor(deltas.get(name, np.zeros_like(rest)))} for name in names]
    count = rest.shape[0]
    skin_joint = np.full(count, 2, np.uint16)  # skin joint 2, the head
    if spec.neck_below is not None:
        skin_joint[rest[:, 1] - HEAD_CENTRE[1] < spec.neck_below] = 1  # the neck
    if "joint index" in spec.skip:
        skin_joint[0] = 7  # the skin has 3 joints
    joints_view = glb.view(np.stack([skin_joint] + [np.zeros(count, np.uint16)] * 3, 1).tobytes())
    glb.doc["accessors"].append({"bufferView": joints_view, "componentType": 5123, "count": count, "type": "VEC4"})
    joints = len(glb.doc["accessors"]) - 1
    weights = glb.accessor(np.tile([1.0, 0.0, 0.0, 0.0], (count, 1)), "VEC4")
    primitive = {"attributes": {"POSITION": glb.accessor(rest, "VEC3"), "JOINTS_0": joints, "WEIGHTS_0": weights},
                 "targets": targets}
    if spec.subdivided:
        glb.doc["accessors"].append({"bufferView": glb.view(mesh_faces(spec).astype(np.uint32).tobytes()),
                                     "componentType": 5125, "count": mesh_faces(spec).size, "type": "SCALAR"})
        primitive["indices"] = len(glb.doc["accessors"]) - 1
    inverse_bind = np.stack([np.linalg.inv(m).T for m in rest_worlds()])  # column-major, as glTF stores them
    nodes = _skeleton_nodes()
    nodes[0]["children"] = [1, 4]
    nodes.append({"name": "head_mesh", "mesh": 0, "skin": 0})
    glb.doc.update({"scene": 0, "scenes": [{"nodes": [0]}], "nodes": nodes,
                    "meshes": [{"name": "head", "primitives": [primitive], "extras": {"targetNames": names}}],
                    "skins": [{"joints": [1, 2, HEAD_NODE],
                               "inverseBindMatrices": glb.accessor(inverse_bind.reshape(3, 16), "MAT4")}]})
    if "skin" in spec.skip:
        del glb.doc["skins"]
    if "morphs" in spec.skip:
        del primitive["targets"]
    return glb.bytes()


def animation_glb(spec: AvatarSpec) -> bytes:
    glb = _Glb()
    animations = []
    for name, keys in spec.clips.items():
        times = np.array([[t] for t, _ in keys], np.float32)
        values = np.array([axis_angle_quat((1, 0, 0), angle) for _, angle in keys], np.float32)
        animations.append({"name": name, "samplers": [{"input": glb.accessor(times, "SCALAR"),
                                                       "output": glb.accessor(values, "VEC4"),
                                                       "interpolation": "LINEAR"}],
                           "channels": [{"sampler": 0, "target": {"node": HEAD_NODE, "path": "rotation"}}]})
    glb.doc.update({"scene": 0, "scenes": [{"nodes": [0]}], "nodes": _skeleton_nodes(), "animations": animations})
    return glb.bytes()


def head_motion(angle: float) -> np.ndarray:
    """The head bone's world motion (4x4) when its local rotation is `angle` about local x."""
    rest = rest_worlds()
    posed = world([trs(r=ROOT_ROTATION, s=[ROOT_SCALE] * 3), trs(t=HIP_LOCAL), trs(t=NECK_LOCAL),
                   trs(t=HEAD_LOCAL, r=axis_angle_quat((1, 0, 0), angle))])
    return posed[3] @ np.linalg.inv(rest[2])


def expected_centres(spec: AvatarSpec, weights: dict[str, float], angle: float = 0.0) -> np.ndarray:
    """[V, 3] where LAM's renderer draws the Gaussians: head motion x (vertex + morphs + offset)."""
    points = rest_vertices(spec) + gaussians(spec)["xyz"]
    deltas = morph_deltas(spec)
    for name, weight in weights.items():
        points = points + weight * deltas[name]
    motion = head_motion(angle)
    return points @ motion[:3, :3].T + motion[:3, 3]


def offset_ply(spec: AvatarSpec) -> bytes:
    g = gaussians(spec)
    fields = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
              "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    if "ply_field" in spec.skip:
        fields.remove("opacity")
    count = g["xyz"].shape[0]
    columns = {"x": g["xyz"][:, 0], "y": g["xyz"][:, 1], "z": g["xyz"][:, 2], "nx": np.zeros(count),
               "ny": np.zeros(count), "nz": np.zeros(count), "opacity": g["opacity"],
               **{f"f_dc_{k}": g["f_dc"][:, k] for k in range(3)}, **{f"scale_{k}": g["scale"][:, k] for k in range(3)},
               **{f"rot_{k}": g["rot"][:, k] for k in range(4)}}
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {count}\n" + \
        "".join(f"property float {name}\n" for name in fields) + "end_header\n"
    body = np.stack([columns[name] for name in fields], 1).astype("<f4").tobytes()
    return header.encode() + body


def motion_json(frames: int = 12, fps: float = 30.0) -> dict:
    """A bsData.json-like motion (LAM's audio-to-expression output) of the morphs above."""
    from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES

    t = np.arange(frames) / fps
    weights = np.zeros((frames, len(ARKIT_BLENDSHAPES)))
    weights[:, ARKIT_BLENDSHAPES.index("jawOpen")] = 0.5 + 0.5 * np.sin(2 * np.pi * 2 * t)
    weights[:, ARKIT_BLENDSHAPES.index("eyeBlinkLeft")] = (np.arange(frames) % 6 == 0).astype(float)
    return {"names": list(ARKIT_BLENDSHAPES), "metadata": {"fps": fps, "frame_count": frames},
            "frames": [{"weights": w.tolist(), "time": float(ti), "rotation": []} for w, ti in zip(weights, t,
                                                                                                    strict=True)]}


def write_avatar_zip(path: str | Path, spec: AvatarSpec | None = None) -> Path:
    """Write a LAM-format avatar zip (members in `spec.folder`, with macOS junk beside them) and return its path."""
    spec = spec or AvatarSpec()
    path = Path(path)
    count = rest_vertices(spec).shape[0]
    members = {"skin.glb": skin_glb(spec), "offset.ply": offset_ply(spec), "animation.glb": animation_glb(spec),
               "vertex_order.json": json.dumps(list(range(spec.vertex_order_length or count))).encode()}
    if spec.motion:
        members["bsData.json"] = json.dumps(motion_json()).encode()
    prefix = f"{spec.folder}/" if spec.folder else ""
    with zipfile.ZipFile(path, "w") as archive:
        if prefix:
            archive.writestr(prefix, b"")  # the folder's own entry, as zip tools write (LAM's renderer needs it)
        for name, data in members.items():
            if name not in spec.skip:
                archive.writestr(prefix + name, data)
        archive.writestr(f"__MACOSX/{prefix}._skin.glb", b"junk")
        archive.writestr(f"{prefix}.DS_Store", b"junk")
    return path


def read_zip_member(path: Path, name: str) -> bytes:
    with zipfile.ZipFile(path) as archive:
        return archive.read(name)


__all__ = ["AvatarSpec", "expected_centres", "head_motion", "io", "motion_json", "write_avatar_zip"]


def energy_audio_model(path: str | Path, frame_samples: int = 533, width: int = 52, gain: float = 8.0) -> Path:
    """A tiny audio-to-ARKit ONNX model (onnx.helper, no torch): jawOpen = gain x mean |audio| over each
    `frame_samples` block, every other weight 0; T = floor(S / frame_samples) frames."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES

    kernel = np.zeros((width, 1, frame_samples), np.float32)
    kernel[min(ARKIT_BLENDSHAPES.index("jawOpen"), width - 1), 0, :] = gain / frame_samples
    nodes = [helper.make_node("Abs", ["pcm"], ["level"]),
             helper.make_node("Unsqueeze", ["level", "axis1"], ["level3"]),
             helper.make_node("Conv", ["level3", "kernel"], ["per_frame"], strides=[frame_samples]),
             helper.make_node("Transpose", ["per_frame"], ["arkit"], perm=[0, 2, 1])]
    graph = helper.make_graph(
        nodes, "energy", [helper.make_tensor_value_info("pcm", TensorProto.FLOAT, [1, "samples"])],
        [helper.make_tensor_value_info("arkit", TensorProto.FLOAT, [1, "frames", width])],
        [numpy_helper.from_array(kernel, "kernel"), numpy_helper.from_array(np.array([1], np.int64), "axis1")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.save(model, str(path))
    return Path(path)
