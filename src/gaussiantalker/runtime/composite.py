"""Compositing the rendered face into the reference frame: I = (1 - M) I_ori + M F(I_gau + (1 - M) I_ori).

I_gau is the splatter's premultiplied colour C (no background), M the clip's facial mask, F the inpainting
generator (the bundle's `inpaint` graph) or, for a speaker without one, the non-learned OpenCV fallback. F runs
only on the crop around the mask's support (plus a margin, rounded up to the graph's size multiple); every pixel
where M is 0 is the reference frame's, bit for bit (docs/compositing.md).

The arithmetic around F is two passes over the crop (`crop_inputs`, `blend_crop`), in numba where it is installed
(`composite_kernels`: one pass each, ~2 ms a frame at 480x600 on 2 cores, against ~4.3 ms for numpy's dozen
passes, temporaries and transposes) and in numpy otherwise; both do the same float32 steps in the same order, so
the frames are the same (docs/compositing.md, "Around F, two passes").
"""

from __future__ import annotations

import functools
import importlib.util
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from gaussiantalker.sdk.errors import RenderError
from gaussiantalker.sdk.image import to_uint8
from gaussiantalker.sdk.reference_clip import CROP_MARGIN_PX, CROP_MULTIPLE

# The fallback fills what lies behind the face at this fraction of the crop's size (cv2.inpaint's cost grows with
# the hole's area; the fill is smooth anyway), with this neighbourhood radius (pixels at that size).
FALLBACK_SCALE = 0.25
FALLBACK_RADIUS_PX = 3

# F on a crop: (x [h, w, 3], mask [h, w], render [h, w, 4] premultiplied (C, 1 - T)) float32 -> F(x) [h, w, 3].
# The generator sees x, M and the render's coverage 1 - T; the fallback also uses C.
# An inpainter may also offer `chw(image [1, 3, h, w], mask [1, 1, h, w], coverage [1, 1, h, w]) -> [3, h, w]`
# (the graph's own layout), which `composite` then calls instead, with no transposes.
Inpainter = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class CropBox:
    """Rows [top, top + height) and columns [left, left + width) of the frame F runs on; `pad` extra rows/columns
    (bottom, right) of edge pixels when the frame is smaller than a multiple of CROP_MULTIPLE."""

    top: int
    left: int
    height: int
    width: int
    pad_bottom: int = 0
    pad_right: int = 0

    @property
    def rows(self) -> slice:
        return slice(self.top, self.top + self.height)

    @property
    def columns(self) -> slice:
        return slice(self.left, self.left + self.width)


def _span(lo: int, hi: int, size: int, margin: int, multiple: int) -> tuple[int, int, int]:
    """[start, start + length) holding [lo, hi) plus `margin`, length a multiple, inside [0, size) if it fits;
    returns (start, length, pad) where pad > 0 only when size itself is too short."""
    want = min(hi + margin, size) - max(lo - margin, 0)
    length = -(-want // multiple) * multiple
    if length > size:
        return 0, size, length - size
    centre = (lo + hi) // 2
    start = int(np.clip(centre - length // 2, 0, size - length))
    return start, length, 0


def crop_box(mask: np.ndarray, margin: int = CROP_MARGIN_PX, multiple: int = CROP_MULTIPLE) -> CropBox | None:
    """The crop F needs for `mask` [H, W]: its support (M > 0) plus `margin`, sides rounded up to `multiple`.
    None if the mask is empty (nothing to composite: the frame is the reference's)."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    columns = np.flatnonzero(mask.any(axis=0))
    top, height, pad_bottom = _span(int(rows[0]), int(rows[-1]) + 1, mask.shape[0], margin, multiple)
    left, width, pad_right = _span(int(columns[0]), int(columns[-1]) + 1, mask.shape[1], margin, multiple)
    return CropBox(top, left, height, width, pad_bottom, pad_right)


def _padded(array: np.ndarray, box: CropBox) -> np.ndarray:
    if not (box.pad_bottom or box.pad_right):
        return array
    pad = [(0, box.pad_bottom), (0, box.pad_right)] + [(0, 0)] * (array.ndim - 2)
    return np.pad(array, pad, mode="edge")


def opencv_fallback(x: np.ndarray, mask: np.ndarray, render: np.ndarray) -> np.ndarray:
    """The non-learned F for speakers without a trained generator (named so in reports): what lies behind the
    face is filled by cv2.inpaint (Telea) from the frame outside the mask, at FALLBACK_SCALE of the crop's size
    (only its smooth colours matter), and the render is composited over that fill by its own coverage:
    F = C + (1 - A) fill. Covered pixels keep the render; the mask's rim, where the render is absent, takes the
    surrounding frame's colours."""
    try:
        import cv2  # optional: only bundles without an inpainting generator need it
    except ImportError:
        raise RenderError("this bundle has no inpainting generator, and its fallback needs OpenCV: pip install "
                          "'gaussiantalker-sdk[opencv]' (or composite=False for the bare head)") from None
    height, width = mask.shape
    small = (max(1, round(width * FALLBACK_SCALE)), max(1, round(height * FALLBACK_SCALE)))
    image = cv2.resize(to_uint8(x), small, interpolation=cv2.INTER_AREA)
    holes = (cv2.resize(mask, small, interpolation=cv2.INTER_LINEAR) > 0.0).astype(np.uint8)
    holes = cv2.dilate(holes, np.ones((3, 3), np.uint8))  # downsampling blends mask pixels into the edge
    fill = cv2.inpaint(image, holes, FALLBACK_RADIUS_PX, cv2.INPAINT_TELEA)
    fill = cv2.resize(fill, (width, height), interpolation=cv2.INTER_LINEAR).astype(np.float32) / np.float32(255.0)
    coverage = render[..., 3:4]
    inside = mask[..., None] > 0.0
    return np.where(inside, render[..., :3] + (1.0 - coverage) * fill, x).astype(np.float32)


def crop_inputs(head, reference, mask, top, left, image, masks, coverage, original) -> None:
    """F's inputs on the crop at (top, left), edge pixels repeated past the frame (np.pad's "edge"), into the given
    arrays: masks [h, w] M, coverage [h, w] the render's 1 - T, original [h, w, 3] = (I_ori / 255) (1 - M) and
    image [3, h, w] = C + original (F's input, channel-first). numpy; `composite_kernels` does the same in one
    numba pass where numba is installed."""
    height, width = masks.shape
    rows = np.minimum(np.arange(top, top + height), mask.shape[0] - 1)[:, None]
    columns = np.minimum(np.arange(left, left + width), mask.shape[1] - 1)[None, :]
    masks[...] = mask[rows, columns]
    render = head[rows, columns]
    coverage[...] = render[..., 3]
    original[...] = reference[rows, columns]
    original *= np.float32(1.0 / 255.0)
    original *= 1.0 - masks[..., None]
    image[...] = (render[..., :3] + original).transpose(2, 0, 1)


def blend_crop(filled, masks, original, top, left, height, width, out) -> None:
    """out[top + y, left + x] = to_uint8((1 - M) I_ori + M F) where M > 0 on the crop's [height, width], from F's
    output `filled` [3, h, w] (numpy; see `crop_inputs`)."""
    blended = filled.transpose(1, 2, 0) * masks[..., None]
    blended += original
    np.clip(blended, 0.0, 1.0, out=blended)
    blended *= np.float32(255.0)
    blended += np.float32(0.5)
    pixels = blended.astype(np.uint8)[:height, :width]
    inside = masks[:height, :width] > 0.0
    np.copyto(out[top: top + height, left: left + width], pixels, where=inside[..., None])


@functools.cache
def _passes():
    """The two passes around F: numba's (`composite_kernels`) where numba is installed (the `cpu` extra), else
    numpy's; the same float32 steps, so the same frames. Looked up once per process, not per frame."""
    if importlib.util.find_spec("numba") is None:
        return crop_inputs, blend_crop
    from .composite_kernels import blend_crop as blend_with_numba
    from .composite_kernels import crop_inputs as inputs_with_numba

    return inputs_with_numba, blend_with_numba


def _checked_output(filled, shape: tuple[int, int, int]) -> np.ndarray:
    """F's output as an array, or RenderError when its shape is not the crop's `shape`."""
    filled = np.asarray(filled)
    if filled.shape != shape:
        raise RenderError(f"the inpainter returned shape {list(filled.shape)} for a crop that needs {list(shape)}")
    return filled


def composite(head: np.ndarray, reference: np.ndarray, mask: np.ndarray, inpaint: Inpainter,
              box: CropBox | None = None) -> np.ndarray:
    """The composited frame uint8 [H, W, 3] from the premultiplied render `head` [H, W, 4] (C, 1 - T), the
    reference frame uint8 [H, W, 3] and its mask float32 [H, W]; `box` defaults to `crop_box(mask)`."""
    if head.shape[:2] != reference.shape[:2] or mask.shape != reference.shape[:2]:
        raise RenderError(f"render {head.shape[:2]}, reference frame {reference.shape[:2]} and mask {mask.shape} "
                          f"must have the same size")
    box = crop_box(mask) if box is None else box
    out = reference.copy()
    if box is None:
        return out
    height, width = box.height + box.pad_bottom, box.width + box.pad_right
    image = np.empty((1, 3, height, width), dtype=np.float32)
    masks = np.empty((1, 1, height, width), dtype=np.float32)
    coverage = np.empty((1, 1, height, width), dtype=np.float32)
    original = np.empty((height, width, 3), dtype=np.float32)  # (1 - M) I_ori, in F's input and in the output
    fill_inputs, blend_back = _passes()
    fill_inputs(np.ascontiguousarray(head, dtype=np.float32), np.ascontiguousarray(reference, dtype=np.uint8),
                np.ascontiguousarray(mask, dtype=np.float32), box.top, box.left, image[0], masks[0, 0],
                coverage[0, 0], original)
    if hasattr(inpaint, "chw"):
        filled = _checked_output(inpaint.chw(image, masks, coverage), (3, height, width))
    else:  # the Inpainter protocol: channel-last crops, the render as (C, 1 - T)
        render = _padded(head[box.rows, box.columns], box)
        x = np.ascontiguousarray(image[0].transpose(1, 2, 0))
        filled = _checked_output(inpaint(x, masks[0, 0], np.ascontiguousarray(render)), (height, width, 3))
        filled = filled.transpose(2, 0, 1)
    # F's output is sanitised and clamped: both terms of the blend are finite
    blend_back(np.ascontiguousarray(filled, dtype=np.float32), masks[0, 0], original, box.top, box.left,
               box.height, box.width, out)
    return out


def warm_up() -> None:
    """Compile (or load from numba's cache) both passes on a tiny frame, so a render loop never compiles."""
    mask = np.zeros((4, 4), dtype=np.float32)
    mask[1, 1] = 1.0
    composite(np.zeros((4, 4, 4), dtype=np.float32), np.zeros((4, 4, 3), dtype=np.uint8), mask,
              lambda x, m, render: x)


class _GraphInpainter:
    """F as the bundle's `inpaint` graph: `chw` feeds the graph its own channel-first layout; calling it is the
    channel-last Inpainter protocol."""

    def __init__(self, run: Callable[[str, dict[str, np.ndarray]], dict[str, np.ndarray]]) -> None:
        self._run = run

    def chw(self, image: np.ndarray, mask: np.ndarray, coverage: np.ndarray) -> np.ndarray:
        """image [1, 3, h, w], mask and coverage [1, 1, h, w] float32 -> F(image) [3, h, w]."""
        return self._run("inpaint", {"image": image, "mask": mask, "coverage": coverage})["inpainted"][0]

    def __call__(self, x: np.ndarray, mask: np.ndarray, render: np.ndarray) -> np.ndarray:
        feeds = (np.ascontiguousarray(x.transpose(2, 0, 1)[None], dtype=np.float32),
                 np.ascontiguousarray(mask[None, None], dtype=np.float32),
                 np.ascontiguousarray(render[None, None, ..., 3], dtype=np.float32))
        return self.chw(*feeds).transpose(1, 2, 0)


def graph_inpainter(run: Callable[[str, dict[str, np.ndarray]], dict[str, np.ndarray]]) -> Inpainter:
    """F as the bundle's `inpaint` graph (`run` is the graph backend's run): HWC crops in, HWC out; `chw` too."""
    return _GraphInpainter(run)
