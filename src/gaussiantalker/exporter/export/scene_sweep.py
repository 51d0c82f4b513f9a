"""The frames a scene specialisation is decided on: a dense sweep of the scene's pose range and drives.

Pruning and the SH refit are measured on these frames, never guessed (docs/scene.md): every corner, edge midpoint,
face centre and the centre of the head-rotation box, each at a translation corner (cycled) and with the jaw at
both ends of its range; the scene's moving joints at their extremes one at a time; each allowed expression
coefficient at +-expression_sigma; and a speech-driven clip with the head cycling through the rotation corners.
"""

from __future__ import annotations

import itertools

import numpy as np
import torch

from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.config import FLAME_JOINTS
from gaussiantalker.sdk.drive import FrameDrive
from gaussiantalker.sdk.progress import progress_bar

from ..export.probes import driven_clip
from ..model.rasterizer import render_reference
from ..model.speaker import Speaker

CLIP_FRAMES = 12


def _box_points(box: np.ndarray) -> list[np.ndarray]:
    """The distinct points lo/mid/hi per axis of a [3, 2] box: its corners first, then edge midpoints, face
    centres and the centre (27 points for a box of full dimension)."""
    corners = itertools.product(*box)
    grid = itertools.product(*[(lo, hi, 0.5 * (lo + hi)) for lo, hi in box])
    unique = dict.fromkeys(tuple(float(v) for v in p) for p in itertools.chain(corners, grid))
    return [np.array(p) for p in unique]


def sweep_drives(speaker: Speaker, ranges: np.ndarray, translation: np.ndarray, expression_allowed: np.ndarray,
                 expression_sigma: float) -> list[FrameDrive]:
    """Drives covering a scene: `ranges` [5, 3, 2] per joint and axis (radians), `translation` [3, 2] metres."""
    n_expr = speaker.config.n_expr
    jaw = FLAME_JOINTS.index("jaw")
    rest = ranges.mean(2)  # [5, 3] each joint's mid-range
    rest[1:] = np.clip(0.0, ranges[1:, :, 0], ranges[1:, :, 1])  # joints other than global: 0 if in range
    corners = [np.array(p) for p in itertools.product(*translation)]
    drives = []

    def drive(pose: np.ndarray, shift: np.ndarray, expression=None) -> FrameDrive:
        return FrameDrive(np.zeros(n_expr, np.float32) if expression is None else expression.astype(np.float32),
                          pose.reshape(-1).astype(np.float32), shift.astype(np.float32))

    rotations = _box_points(ranges[0])  # corners first
    for i, rotation in enumerate(rotations):
        for jaw_end in (0, 1):
            pose = rest.copy()
            pose[0] = rotation
            pose[jaw] = ranges[jaw, :, jaw_end]
            drives.append(drive(pose, corners[(2 * i + jaw_end) % len(corners)]))
    for joint in range(1, len(FLAME_JOINTS)):
        for axis in range(3):
            for end in (0, 1):
                if ranges[joint, axis, end] != rest[joint, axis]:
                    pose = rest.copy()
                    pose[joint, axis] = ranges[joint, axis, end]
                    drives.append(drive(pose, translation.mean(1)))
    for index in np.flatnonzero(expression_allowed):
        for sign in (-1.0, 1.0):
            expression = np.zeros(n_expr)
            expression[index] = sign * expression_sigma
            drives.append(drive(rest, translation.mean(1), expression))
    _, clip = driven_clip(speaker, CLIP_FRAMES, seed=11)
    for i, frame in enumerate(clip):
        pose = rest.copy()
        pose[0] = rotations[i % min(8, len(rotations))]  # cycling through the first 8 points (the corners)
        pose[jaw] = np.clip(frame.flame_pose[3 * jaw: 3 * jaw + 3], ranges[jaw, :, 0], ranges[jaw, :, 1])
        drives.append(drive(pose, corners[i % len(corners)], np.clip(frame.expression, -expression_sigma,
                                                                     expression_sigma) * expression_allowed))
    return drives


@torch.no_grad()
def measure_sweep(speaker: Speaker, drives: list[FrameDrive], camera: Camera, progress: bool = False
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """(max_weight [N]: each Gaussian's largest blend weight over every pixel of every drive's frame,
    directions [F, N, 3]: camera centre -> Gaussian centre per frame, for the SH refit)."""
    center = torch.from_numpy(camera.center.astype(np.float32))[None]
    max_weight = torch.zeros(speaker.gaussians.count, dtype=torch.float32)
    directions = []
    for frame in progress_bar(drives, desc="scene sweep", unit="frame", disable=not progress):
        inputs = {k: torch.from_numpy(v) for k, v in frame.graph_inputs().items()}
        means, cov3d, rgb, opacity = speaker.deform(inputs["expression"], inputs["flame_pose"],
                                                    inputs["head_translation"], center)
        render_reference(means[0], cov3d[0], rgb[0], opacity, camera, (0.0, 0.0, 0.0), max_weight=max_weight)
        directions.append(means[0] - center)
    return max_weight, torch.stack(directions)


__all__ = ["measure_sweep", "sweep_drives"]
