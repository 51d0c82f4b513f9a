"""Compositing the rendered face into the reference frame: I = (1 - M) I_ori + M F(I_gau + (1 - M) I_ori).

I_gau is the splatter's premultiplied colour C (no background), M the clip's facial mask, F the inpainting
generator (the bundle's `inpaint` graph) or, for a speaker without one, the non-learned OpenCV fallback. F runs
only on the crop around the mask's support (plus a margin, rounded up to the graph's size multiple); every pixel
where M is 0 is the reference frame's, bit for bit (docs/compositing.md).
"""

from __future__ import annotations

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
    m = _padded(mask[box.rows, box.columns], box)
    keep = 1.0 - m[..., None]  # [h, w, 1]
    original = _padded(reference[box.rows, box.columns], box).astype(np.float32)
    original *= np.float32(1.0 / 255.0)
    render = _padded(head[box.rows, box.columns], box)
    original *= keep  # (1 - M) I_ori, both in F's input and in the output
    x = render[..., :3] + original  # F's input: the render plus the frame outside the mask
    filled = inpaint(x, m, np.ascontiguousarray(render))
    # (1 - M) I_ori + M F, rounded to 8 bits as to_uint8 does (both terms are finite: F's output is sanitised and
    # clamped), in place: this runs on every composited frame.
    filled *= m[..., None]
    filled += original
    np.clip(filled, 0.0, 1.0, out=filled)
    filled *= np.float32(255.0)
    filled += np.float32(0.5)
    blended = filled.astype(np.uint8)[: box.height, : box.width]
    inside = mask[box.rows, box.columns] > 0.0
    np.copyto(out[box.rows, box.columns], blended, where=inside[..., None])
    return out


def graph_inpainter(run: Callable[[str, dict[str, np.ndarray]], dict[str, np.ndarray]]) -> Inpainter:
    """F as the bundle's `inpaint` graph (`run` is the graph backend's run): HWC crops in, HWC out."""

    def inpaint(x: np.ndarray, mask: np.ndarray, render: np.ndarray) -> np.ndarray:
        feeds = {"image": np.ascontiguousarray(x.transpose(2, 0, 1)[None]),
                 "mask": np.ascontiguousarray(mask[None, None], dtype=np.float32),
                 "coverage": np.ascontiguousarray(render[None, None, ..., 3], dtype=np.float32)}
        return run("inpaint", feeds)["inpainted"][0].transpose(1, 2, 0)

    return inpaint
