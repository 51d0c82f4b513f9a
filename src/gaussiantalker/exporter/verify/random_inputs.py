"""Random inputs verification compares graphs on (beside export/probes.py's speech clips): noise crops for the
inpainter graph and random drives for the deformation graph."""

from __future__ import annotations

import numpy as np

from gaussiantalker.sdk.drive import BlendshapeDrive, FrameDrive, HeadPose


def random_crops(seed: int, sizes) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(image, mask, coverage) NCHW crops of uniform noise, one per (height, width) in `sizes`."""
    rng = np.random.default_rng(seed)
    return [(rng.random((1, 3, h, w), np.float32), rng.random((1, 1, h, w), np.float32),
             rng.random((1, 1, h, w), np.float32)) for h, w in sizes]


def random_drives(n_expr: int, count: int, seed: int) -> list[FrameDrive]:
    """A neutral drive, then `count - 1` random ones (expression, jaw, neck, eyes, head pose)."""
    rng = np.random.default_rng(seed)
    drives = [FrameDrive.make(n_expr)]
    for _ in range(count - 1):
        drives.append(FrameDrive.make(
            n_expr, rng.normal(0, 1, n_expr), rng.normal(0, 0.15, 3) * [1, 0.2, 0.2], rng.normal(0, 0.1, 3),
            rng.normal(0, 0.1, 6), HeadPose.make(rng.normal(0, 0.2, 3), rng.normal(0, 0.01, 3))))
    return drives


def random_blendshape_drives(names: tuple[str, ...], count: int, seed: int) -> list[BlendshapeDrive]:
    """A neutral ARKit drive, then `count - 1` random ones: each blendshape on with probability 0.3 (uniform in
    [0, 1]), a random head pose."""
    rng = np.random.default_rng(seed)
    drives = [BlendshapeDrive.make(names=names)]
    for _ in range(count - 1):
        weights = rng.uniform(0.0, 1.0, len(names)) * (rng.random(len(names)) < 0.3)
        drives.append(BlendshapeDrive.make(weights, HeadPose.make(rng.normal(0, 0.2, 3), rng.normal(0, 0.01, 3)),
                                           names))
    return drives


__all__ = ["random_blendshape_drives", "random_crops", "random_drives"]
