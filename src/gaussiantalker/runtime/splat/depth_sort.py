"""Depth order of a frame's Gaussians (numpy): near-plane and non-finite culling, then a stable front-to-back sort.

The contract's order is a stable sort on float32 view depth (`depth_order`). Two runtime knobs trade it for speed
(`RenderSettings`, docs/precision.md): `sort_key_bits=16` sorts depth quantised to 65536 levels over the frame's
depth range (numpy's stable sort of uint16 keys is a radix sort, faster than the exact 64-bit key sort:
docs/precision.md, "Knobs"), and `sort_interval=k` sorts only every k-th frame and reuses that order in between
(`DepthSorter`).
"""

from __future__ import annotations

import numpy as np

from gaussiantalker.sdk.camera import Camera

KEY_LEVELS_16 = 65535  # largest 16-bit depth key


def view_depth(means: np.ndarray, camera: Camera) -> np.ndarray:
    """Camera-space z = (R mean + t).z in float32, summed left to right, so the torch side can match it. # [N]"""
    r = camera.R[2].astype(np.float32)
    t = np.float32(camera.t[2])
    with np.errstate(invalid="ignore", over="ignore"):
        return means[:, 0] * r[0] + means[:, 1] * r[1] + means[:, 2] * r[2] + t


def stable_argsort_positive(z: np.ndarray) -> np.ndarray:
    """np.argsort(z, kind="stable") for finite z > 0 (float32), faster (docs/numerics.md): one sort of uint64 keys.

    A positive float32's bit pattern orders like its value, so key = bits << 32 | index sorts by z and then by
    index, which is exactly the stable order; the keys are unique, so any sort algorithm gives that order.
    """
    key = z.astype(np.float32).view(np.uint32).astype(np.uint64) << np.uint64(32)
    key |= np.arange(len(z), dtype=np.uint64)
    key.sort()
    return (key & np.uint64(0xFFFFFFFF)).astype(np.intp)


def stable_argsort_16bit(z: np.ndarray) -> np.ndarray:
    """Stable argsort of finite z on 16-bit keys: z quantised to 65536 levels over [min z, max z].

    Gaussians closer than (max z - min z) / 65535 in depth may swap order (ties keep index order); for a head
    ~0.3 m deep that is ~5 um. numpy sorts 16-bit keys with a radix sort.
    """
    if len(z) == 0:
        return np.zeros(0, dtype=np.intp)
    lo, hi = np.float64(z.min()), np.float64(z.max())
    scale = KEY_LEVELS_16 / (hi - lo) if hi > lo else 0.0
    key = np.minimum((z - lo) * scale, KEY_LEVELS_16).astype(np.uint16)
    return np.argsort(key, kind="stable")


def visible(packed: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(view depth [N], mask [N] of rows to draw: finite and z >= near)."""
    z = view_depth(packed[:, 0:3], camera)  # [N]
    with np.errstate(invalid="ignore"):
        keep = (z >= np.float32(camera.near)) & np.isfinite(z) & np.isfinite(packed).all(axis=1)
    return z, keep


def depth_order(packed: np.ndarray, camera: Camera, key_bits: int = 32) -> np.ndarray:
    """Indices of the Gaussians to draw, front to back: stable sort on z, culling z < near and non-finite rows.
    `key_bits=16` sorts quantised depth (`stable_argsort_16bit`) instead of exact float32 depth."""
    z, keep = visible(packed, camera)
    kept = np.flatnonzero(keep)
    # near > 0, so every kept z is finite and positive
    sort = stable_argsort_positive if key_bits == 32 else stable_argsort_16bit
    return kept[sort(z[kept])]


class DepthSorter:
    """`depth_order` with a sort interval: a full sort every `interval` frames, the last order reused in between.

    A reused order still culls each frame afresh (rows behind the near plane or non-finite are dropped); a frame
    that would draw a row the last sort did not hold, another Gaussian count or another camera view sorts anew.
    Calls must come in frame order (TalkingHead prepares one frame at a time).
    """

    def __init__(self, interval: int = 1, key_bits: int = 32) -> None:
        self.interval = interval
        self.key_bits = key_bits
        self._order: np.ndarray | None = None  # last full sort's kept indices, front to back
        self._view: tuple | None = None  # (N, camera view) that order was made for
        self._age = 0  # frames since the last full sort

    def order(self, packed: np.ndarray, camera: Camera) -> np.ndarray:
        """Indices of the rows to draw, front to back (see the class docstring)."""
        if self.interval == 1:
            return depth_order(packed, camera, self.key_bits)
        view = (len(packed), camera.R.tobytes(), camera.t.tobytes(), camera.width, camera.height, camera.near)
        if self._order is not None and self._age < self.interval - 1 and view == self._view:
            _, keep = visible(packed, camera)
            reused = self._order[keep[self._order]]
            if np.count_nonzero(keep) == len(reused):  # no newly visible row: the reused order is complete
                self._age += 1
                return reused
        self._order = depth_order(packed, camera, self.key_bits)
        self._view, self._age = view, 0
        return self._order
