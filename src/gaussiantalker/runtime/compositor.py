"""The last stage of a frame's path (docs/embedding.md, "Stages"; docs/compositing.md): a bare head's premultiplied
render goes into the reference clip's picture at the same video frame, through F and the facial mask
(runtime/composite.py holds the formula)."""

from __future__ import annotations

import time

import numpy as np

from gaussiantalker.sdk.bundle import Bundle
from gaussiantalker.sdk.drive import track_row
from gaussiantalker.sdk.errors import BundleError, RenderError
from gaussiantalker.sdk.reference_clip import ReferenceClip

from .backend import GraphBackend
from .composite import Inpainter, composite, graph_inpainter, opencv_fallback, warm_up
from .timings import Timings


class Compositor:
    """The reference clip (played forth and back), its masks and F: `frame(head, index)` composites one frame."""

    def __init__(self, reference: ReferenceClip, inpaint: Inpainter, *, timings: Timings | None = None) -> None:
        self.reference, self.inpaint = reference, inpaint
        self.timings = timings if timings is not None else Timings()
        warm_up()

    @classmethod
    def from_bundle(cls, bundle: Bundle, reference: ReferenceClip, pose_track: np.ndarray | None,
                    graphs: GraphBackend, *, timings: Timings | None = None) -> Compositor:
        """The bundle's compositor: its `inpaint` graph as F (else the OpenCV fallback); BundleError when the clip
        and the pose track the head follows disagree in length."""
        if pose_track is None or len(pose_track) != len(reference):
            raise BundleError(f"{bundle.path}: the reference clip has {len(reference)} frames but the pose "
                              f"track has {0 if pose_track is None else len(pose_track)} rows")
        inpaint = graph_inpainter(graphs.run) if "inpaint" in bundle.manifest["graphs"] else opencv_fallback
        return cls(reference, inpaint, timings=timings)

    def picture(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """The reference frame and mask video frame `index` is composited into (the clip forth and back), timed."""
        start = time.perf_counter()
        row = track_row(len(self.reference), int(index))
        picture, mask = self.reference.frame(row), self.reference.mask(row)
        self.timings.record("reference", time.perf_counter() - start)
        return picture, mask

    def blend(self, head: np.ndarray, picture: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """The formula on the mask's crop (F and the blend), timed: uint8 [H, W, 3]."""
        start = time.perf_counter()
        frame = composite(head, picture, mask, self.inpaint)
        self.timings.record("composite", time.perf_counter() - start)
        return frame

    def frame(self, head: np.ndarray, index: int) -> np.ndarray:
        """Video frame `index` composited: the premultiplied render `head` [H, W, 4] (output="rgba_float") into
        the reference picture the clip shows at that frame, uint8 [H, W, 3]."""
        return self.blend(head, *self.picture(index))


def check_composited_output(compositor: Compositor | None, output: str) -> None:
    """RenderError unless a head with this compositor can return composited frames of kind `output`."""
    if compositor is None:
        raise RenderError("compositing is off for this head (no reference clip, or composite=False)")
    if output != "uint8":
        raise RenderError(f"composited frames are uint8 RGB; output={output!r} needs the bare head: "
                          "TalkingHead(..., composite=False)")


__all__ = ["Compositor", "check_composited_output"]
