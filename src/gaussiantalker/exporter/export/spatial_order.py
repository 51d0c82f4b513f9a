"""Spatial order of a speaker's Gaussians: their Morton (Z-order) order in space, so that Gaussians next to each
other in a per-Gaussian buffer are neighbours on the face (docs/precision.md, "Spatial order").

Order changes no frame (the splatters sort by depth every frame), but it changes what a chunked codec sees: a
quantisation chunk of 256 neighbours spans a small range of positions, and runs of similar values deflate. The
order is a Morton curve over the Gaussians' positions at the neutral drive, quantised to a 2^MORTON_BITS grid over
their bounding box. An ARKit rig whose midpoint vertices are derived (`midpoints`) keeps its Gaussians in two groups,
those on stored vertices first (in Morton order), so the graph still slices rather than gathers
(exporter/export/arkit_graph.py); those on derived vertices follow their ends' places (`spatial_order`).
"""

from __future__ import annotations

import numpy as np
import torch

from gaussiantalker.sdk.drive import BlendshapeDrive, FrameDrive, HeadPose

from ..model.arkit_speaker import ArkitSpeaker
from ..model.speaker import Speaker
from .morph_midpoints import find_midpoints
from .prune import gaussian_subset

# Grid cells per axis of the Morton code: 1,024 (30-bit codes), finer than any two Gaussians of a 100k head apart.
MORTON_BITS = 10


def morton_order(points: np.ndarray, bits: int = MORTON_BITS) -> np.ndarray:
    """The permutation sorting points [N, 3] by the Morton code of their cell on a 2^bits grid over their bounding
    box (ties in the points' order)."""
    points = np.asarray(points, np.float64)
    low, high = points.min(axis=0), points.max(axis=0)
    cells = np.rint((points - low) / np.maximum(high - low, 1e-12) * (2**bits - 1)).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(bits):
        for axis in range(3):
            code |= ((cells[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def neutral_positions(speaker: Speaker | ArkitSpeaker) -> np.ndarray:
    """[N, 3] the Gaussians' world positions at the neutral drive (no expression, the head unrotated)."""
    if isinstance(speaker, ArkitSpeaker):
        drive = BlendshapeDrive.make(None, HeadPose.make([0.0, 0.0, 0.0]), speaker.config.blendshapes)
    else:
        drive = FrameDrive.make(speaker.config.n_expr)
    center = torch.from_numpy(speaker.camera.center.astype(np.float32))[None]
    with torch.no_grad():
        means = speaker.deform_drive(drive, center)[0]
    return means[0].double().numpy()


def _midpoint_table(speaker: Speaker | ArkitSpeaker, midpoints: bool) -> np.ndarray:
    """[M, 3] (v, a, b) of the rig's derived vertices (`find_midpoints`), empty unless an ARKit rig derives them."""
    rig = getattr(speaker, "rig", None)
    if isinstance(speaker, ArkitSpeaker) and midpoints and rig.faces is not None:
        return find_midpoints(rig.rest.numpy(), rig.morphs.numpy(), rig.faces.numpy())
    return np.zeros((0, 3), np.int64)


def spatial_order(speaker: Speaker | ArkitSpeaker, midpoints: bool = False) -> np.ndarray:
    """[N] the Gaussians' new order: Morton order of their neutral positions; for an ARKit rig that derives its
    midpoint vertices (`midpoints`), the Gaussians on stored vertices first in that order, then those on derived
    vertices ordered by their two ends' places in it (nearest first), so each derived row's ends
    (`midpoint_ends`) follow the ones before, which deflates better than their own Morton order (a measured
    6 kB less on LAM's p2-1, docs/precision.md)."""
    count = speaker.gaussians.count
    rank = np.empty(count, np.int64)
    rank[morton_order(neutral_positions(speaker))] = np.arange(count)
    table = _midpoint_table(speaker, midpoints)
    if not len(table):
        return np.argsort(rank, kind="stable")
    rig = speaker.rig
    vertex = speaker.gaussians.vertex.numpy()
    ends_of = np.full((rig.rest.shape[0], 2), -1, np.int64)
    ends_of[table[:, 0]] = table[:, 1:]
    derived = ends_of[vertex, 0] >= 0
    direct = np.flatnonzero(~derived)
    direct = direct[np.argsort(rank[direct], kind="stable")]
    # Each vertex's place: its first direct Gaussian's, else after every direct one in Morton order of its rest point.
    vertex_rank = len(direct) + np.argsort(morton_order(rig.rest.double().numpy()), kind="stable")
    vertex_rank[vertex[direct[::-1]]] = np.arange(len(direct))[::-1]
    others = np.flatnonzero(derived)
    end_ranks = np.sort(vertex_rank[ends_of[vertex[others]]], axis=1)
    others = others[np.lexsort((rank[others], end_ranks[:, 1], end_ranks[:, 0]))]
    return np.concatenate([direct, others])


def in_spatial_order(speaker: Speaker | ArkitSpeaker, midpoints: bool = False) -> Speaker | ArkitSpeaker:
    """A copy of `speaker` with its Gaussians in `spatial_order`."""
    return gaussian_subset(speaker, torch.from_numpy(spatial_order(speaker, midpoints)))


__all__ = ["MORTON_BITS", "in_spatial_order", "morton_order", "neutral_positions", "spatial_order"]
