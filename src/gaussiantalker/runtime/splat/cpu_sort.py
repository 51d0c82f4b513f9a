"""The CPU splatter's `prepare` when it sorts every frame (32-bit keys, the contract's, or 16-bit ones): cull,
depth-order and pack a frame's Gaussians in two numba passes and one sort (of 64-bit keys, or of 16-bit ones as
`stable_argsort_16bit` makes them), instead of numpy's pack, finiteness reduction and gather (docs/speed.md, "The
steps since"). The order is `depth_order`'s exactly (docs/numerics.md): a stable sort
on float32 view depth, rows behind the near plane or holding a non-finite value culled.

numpy's version makes three [N, 13] temporaries (the packed rows, their finiteness, the gathered rows) and walks
them in separate passes; here one pass computes each Gaussian's depth and verdict from the four arrays the
deformation graph returns, and one writes the sorted rows straight from them. Both run on the calling thread
(0.5 ms for 20k Gaussians, as fast as on two): a pipelined frame loop prepares on a worker while the blend holds
both cores, and a parallel pass there would only compete with it.
"""

from __future__ import annotations

import numpy as np

from gaussiantalker.sdk.camera import Camera

from ..jit import njit
from .common import FLOATS_PER_SPLAT
from .depth_sort import stable_argsort_16bit, stable_argsort_positive

_CULLED = np.float32(np.inf)  # a culled Gaussian's depth: its key sorts after every kept one (kept depths are finite)


@njit(inline="always", cache=True)
def _finite_row(a, i, width):
    ok = True
    for k in range(width):
        ok &= np.isfinite(a[i, k])
    return ok


@njit(nogil=True, cache=True, error_model="numpy")
def _depths(means, cov3d, rgb, opacity, r, t, near, depth):
    """depth[i] = Gaussian i's float32 view depth (R mean + t).z, summed left to right as `view_depth` does, where it
    is drawn (z >= near and all 13 of its values finite), else +inf."""
    for i in range(means.shape[0]):
        z = means[i, 0] * r[0] + means[i, 1] * r[1] + means[i, 2] * r[2] + t
        keep = (z >= near and np.isfinite(z) and np.isfinite(opacity[i]) and _finite_row(means, i, 3)
                and _finite_row(cov3d, i, 6) and _finite_row(rgb, i, 3))
        depth[i] = z if keep else _CULLED


@njit(nogil=True, cache=True, error_model="numpy")
def _gather(means, cov3d, rgb, opacity, order, rows):
    """rows[j] = Gaussian order[j]'s packed row: mean xyz, cov xx xy xz yy yz zz, rgb, opacity."""
    for j in range(order.shape[0]):
        i = order[j]
        for k in range(3):
            rows[j, k] = means[i, k]
        for k in range(6):
            rows[j, 3 + k] = cov3d[i, k]
        for k in range(3):
            rows[j, 9 + k] = rgb[i, k]
        rows[j, 12] = opacity[i]


def sorted_packed_rows(means: np.ndarray, cov3d: np.ndarray, rgb: np.ndarray, opacity: np.ndarray,
                       camera: Camera, key_bits: int = 32) -> np.ndarray:
    """`pack_gaussians(...)[depth_order(..., camera, key_bits)]` for checked float32 arrays (`checked_gaussians`):
    the rows [n, 13] to draw, front to back (`key_bits` 16: depth quantised as `stable_argsort_16bit` does)."""
    n = means.shape[0]
    depth = np.empty(n, dtype=np.float32)
    r = camera.R[2].astype(np.float32)
    _depths(means, cov3d, rgb, opacity, r, np.float32(camera.t[2]), np.float32(camera.near), depth)
    if key_bits == 16:  # the kept depths alone set the 16-bit keys' range, as depth_order's do
        kept_index = np.flatnonzero(depth != _CULLED)
        order = kept_index[stable_argsort_16bit(depth[kept_index])]
    else:  # +inf's bits order after every finite positive float32's, so the culled come last in the stable order
        order = stable_argsort_positive(depth)[:n - int(np.count_nonzero(depth == _CULLED))]
    rows = np.empty((order.shape[0], FLOATS_PER_SPLAT), dtype=np.float32)
    _gather(means, cov3d, rgb, opacity, order, rows)
    return rows


def warm_up() -> None:
    """Compile (or load from the cache) both passes on one Gaussian."""
    one = np.zeros((1, 3), dtype=np.float32)
    sorted_packed_rows(one, np.zeros((1, 6), dtype=np.float32), one, np.ones(1, dtype=np.float32),
                       Camera(3, 2, 2.0, 2.0, 1.5, 1.0))


__all__ = ["sorted_packed_rows", "warm_up"]
