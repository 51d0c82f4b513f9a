"""A tiny synthetic LAM avatar zip (a few coloured splats, two morph targets, a hip/head skeleton, animation clips).

It has every file and field the web renderer reads (docs/lam-web.md, "The avatar zip"), so the harness can be
tested without a real avatar: each splat's centre is known exactly, in the rest pose and under a morph weight.
"""

from __future__ import annotations

import json
import struct
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HEAD_Y = 1.5            # the head bone's rest translation from the hip (the skinning matrix at rest is identity)
CLIPS = 12              # the renderer's animationConfig counts: hello 2, idle 1, listen 0, speak 6, think 3
CLIP_TURN_DEG = 30.0    # every clip turns the head this far about y: a frame drawn off the rest pose shows it
FLOAT, UBYTE = 5126, 5121


@dataclass
class SyntheticSplats:
    """Splats of the synthetic avatar: world centre = offset + template vertex (+ morph deltas times weights)."""

    vertices: np.ndarray                    # [N, 3] template mesh vertices
    offsets: np.ndarray                     # [N, 3] offset.ply positions
    colors: np.ndarray                      # [N, 3] in 0..1 (stored as f_dc, which the renderer reads as RGB)
    opacity: np.ndarray                     # [N] in 0..1
    scale: float                            # isotropic standard deviation (m)
    morphs: dict[str, np.ndarray] = field(default_factory=dict)  # name -> [N, 3] deltas

    def centres(self, weights: dict[str, float] | None = None) -> np.ndarray:
        """World centres under raw morph `weights` (already scaled the way the renderer scales them)."""
        out = self.vertices + self.offsets
        for name, value in (weights or {}).items():
            out = out + value * self.morphs[name]
        return out


def default_splats() -> SyntheticSplats:
    """Red, green and blue splats in front of the renderer's own camera, four out of every view near the scene
    (the renderer limits each quad's index count to the splat count, so fewer than 6 splats draw half-quads), and
    a yellow one last, in view, which the renderer does not draw (docs/lam-web.md). jawOpen moves the red splat
    down, eyeBlinkLeft the green one right."""
    centres = np.array([[0.0, 1.62, 0.0], [0.12, 1.70, -0.05], [-0.10, 1.55, 0.05],
                        [40.0, 1.6, 0.0], [-40.0, 1.6, 0.0], [0.0, 41.6, 0.0], [0.0, -38.4, 0.0],
                        [-0.12, 1.72, 0.0]])
    offsets = np.zeros_like(centres)
    offsets[0] = [0.01, -0.02, 0.005]
    offsets[2] = [-0.02, 0.01, 0.0]
    jaw = np.zeros_like(centres)
    jaw[0] = [0.0, -0.05, 0.0]
    blink = np.zeros_like(centres)
    blink[1] = [0.03, 0.0, 0.0]
    colors = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], *[[0.5, 0.5, 0.5]] * 4, [1.0, 1.0, 0.0]])
    return SyntheticSplats(centres - offsets, offsets, colors, np.full(len(centres), 0.95), 0.006,
                           {"jawOpen": jaw, "eyeBlinkLeft": blink})


class _GlbBuilder:
    """Accumulates binary accessors and writes a .glb (JSON chunk + BIN chunk)."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array: np.ndarray, kind: str, component: int, bounds: bool = False) -> int:
        data = np.ascontiguousarray(array, dtype=np.float32 if component == FLOAT else np.uint8)
        while len(self.blob) % 4:
            self.blob.append(0)
        self.views.append({"buffer": 0, "byteOffset": len(self.blob), "byteLength": data.nbytes})
        self.blob += data.tobytes()
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[kind]
        accessor = {"bufferView": len(self.views) - 1, "componentType": component, "count": data.size // width,
                    "type": kind}
        if bounds:
            flat = data.reshape(-1, width)
            accessor["min"], accessor["max"] = flat.min(0).tolist(), flat.max(0).tolist()
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def write(self, gltf: dict) -> bytes:
        gltf = {**gltf, "asset": {"version": "2.0"}, "accessors": self.accessors, "bufferViews": self.views,
                "buffers": [{"byteLength": len(self.blob)}]}
        text = json.dumps(gltf).encode()
        text += b" " * (-len(text) % 4)
        blob = bytes(self.blob) + b"\0" * (-len(self.blob) % 4)
        total = 12 + 8 + len(text) + 8 + len(blob)
        return (struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(text), 0x4E4F534A) + text
                + struct.pack("<II", len(blob), 0x004E4942) + blob)


def _skeleton_nodes() -> list[dict]:
    return [{"name": "hip", "children": [1]}, {"name": "head", "translation": [0.0, HEAD_Y, 0.0]}]


def skin_glb(splats: SyntheticSplats) -> bytes:
    """The skinned template mesh: one vertex per splat, morph targets, joints hip and head (all on head)."""
    glb = _GlbBuilder()
    count = len(splats.vertices)
    position = glb.add(splats.vertices, "VEC3", FLOAT, bounds=True)
    joints = glb.add(np.tile([1, 0, 0, 0], (count, 1)), "VEC4", UBYTE)
    weights = glb.add(np.tile([1.0, 0.0, 0.0, 0.0], (count, 1)), "VEC4", FLOAT)
    targets = [{"POSITION": glb.add(delta, "VEC3", FLOAT, bounds=True)} for delta in splats.morphs.values()]
    head_inverse = np.eye(4)
    head_inverse[3, 1] = -HEAD_Y  # column-major: the translation sits in the last column's first three entries
    inverse_binds = glb.add(np.stack([np.eye(4), head_inverse]), "MAT4", FLOAT)
    return glb.write({
        "scene": 0, "scenes": [{"nodes": [0, 2]}],
        "nodes": [*_skeleton_nodes(), {"name": "avatar", "mesh": 0, "skin": 0}],
        "meshes": [{"name": "avatar", "primitives": [{"attributes": {"POSITION": position, "JOINTS_0": joints,
                                                                     "WEIGHTS_0": weights},
                                                      "targets": targets, "mode": 4}],
                    "weights": [0.0] * len(targets), "extras": {"targetNames": list(splats.morphs)}}],
        "skins": [{"joints": [0, 1], "inverseBindMatrices": inverse_binds}],
    })


def animation_glb() -> bytes:
    """The chat-state clips: each turns the head bone by CLIP_TURN_DEG about y over one second."""
    glb = _GlbBuilder()
    times = glb.add(np.array([0.0, 1.0]), "SCALAR", FLOAT, bounds=True)
    half = np.radians(CLIP_TURN_DEG) / 2.0
    turns = glb.add(np.array([[0.0, 0.0, 0.0, 1.0], [0.0, np.sin(half), 0.0, np.cos(half)]]), "VEC4", FLOAT)
    clip = {"channels": [{"sampler": 0, "target": {"node": 1, "path": "rotation"}}],
            "samplers": [{"input": times, "output": turns, "interpolation": "LINEAR"}]}
    return glb.write({"scene": 0, "scenes": [{"nodes": [0]}], "nodes": _skeleton_nodes(),
                      "animations": [{**clip, "name": f"clip{i}"} for i in range(CLIPS)]})


def offset_ply(splats: SyntheticSplats) -> bytes:
    """The splats as LAM's offset.ply: INRIA fields, f_dc holding the colour itself, log scales, logit opacity."""
    fields = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
              "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    count = len(splats.offsets)
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {count}\n"
    header += "".join(f"property float {name}\n" for name in fields) + "end_header\n"
    logit = np.log(splats.opacity / (1.0 - splats.opacity))
    rows = np.zeros((count, len(fields)), np.float32)
    rows[:, 0:3] = splats.offsets
    rows[:, 6:9] = splats.colors
    rows[:, 9] = logit
    rows[:, 10:13] = np.log(splats.scale)
    rows[:, 13] = 1.0  # identity rotation (w first)
    return header.encode() + rows.tobytes()


def write_synthetic_avatar(path: Path, splats: SyntheticSplats | None = None, folder: str = "synthetic") -> Path:
    """Write a LAM avatar zip at `path` (one folder holding the four files the renderer reads)."""
    splats = splats or default_splats()
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr(zipfile.ZipInfo(f"{folder}/"), b"")
        archive.writestr(f"{folder}/skin.glb", skin_glb(splats))
        archive.writestr(f"{folder}/animation.glb", animation_glb())
        archive.writestr(f"{folder}/offset.ply", offset_ply(splats))
        archive.writestr(f"{folder}/vertex_order.json", json.dumps(list(range(len(splats.offsets)))))
    return path
