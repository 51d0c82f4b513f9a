"""The two passes around F (runtime/composite.py) as numba kernels: one pass each over the crop instead of numpy's
dozen, for the CPU extra's installs. The same float32 steps in the same order as composite.py's numpy functions of
the same names, so the frames are the same (tests/test_compositing.py compares them).
"""

from __future__ import annotations

import numpy as np

from .jit import njit, prange

_ONE = np.float32(1.0)
_INV_255 = np.float32(1.0 / 255.0)
_255 = np.float32(255.0)
_HALF = np.float32(0.5)
_ZERO = np.float32(0.0)


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def crop_inputs(head, reference, mask, top, left, image, masks, coverage, original):
    """F's inputs on the crop at (top, left), edge pixels repeated past the frame (np.pad's "edge"): M, the render's
    coverage 1 - T, original = (I_ori / 255) (1 - M) [h, w, 3] and F's image C + original [3, h, w]."""
    height, width = masks.shape
    rows, columns = mask.shape
    for y in prange(height):
        source_y = min(top + y, rows - 1)
        for x in range(width):
            source_x = min(left + x, columns - 1)
            m = mask[source_y, source_x]
            keep = _ONE - m
            masks[y, x] = m
            coverage[y, x] = head[source_y, source_x, 3]
            for c in range(3):
                value = (np.float32(reference[source_y, source_x, c]) * _INV_255) * keep
                original[y, x, c] = value
                image[c, y, x] = head[source_y, source_x, c] + value


@njit(parallel=True, nogil=True, cache=True, error_model="numpy")
def blend_crop(filled, masks, original, top, left, height, width, out):
    """out[top + y, left + x] = to_uint8((1 - M) I_ori + M F) where M > 0 on the crop's [height, width] (F's
    output `filled` [3, h, w]; the clamp, * 255, + 0.5 and truncation of `to_uint8`)."""
    for y in prange(height):
        for x in range(width):
            m = masks[y, x]
            if m > _ZERO:
                for c in range(3):
                    value = min(max(filled[c, y, x] * m + original[y, x, c], _ZERO), _ONE)
                    out[top + y, left + x, c] = np.uint8(value * _255 + _HALF)


__all__ = ["blend_crop", "crop_inputs"]
