"""The frame loops every offline way of playing a bundle walks: drives -> FrameRenderer -> (Compositor) -> frames,
and frames -> a video file. Pipelined (the default), neighbouring frames' stages overlap on worker threads
(runtime/pipeline.py, docs/speed.md): onnxruntime, numpy, the CPU splatter's kernels and PyAV release the GIL, so
the stages overlap instead of adding up. With the CPU splatter whole frames are made at once, one per core
("Whole frames at once" in docs/speed.md). The frames are the same either way.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from gaussiantalker.sdk.progress import progress_bar
from gaussiantalker.sdk.video import VideoWriter

from .compositor import Compositor
from .driver import Drive
from .frame_renderer import FrameRenderer
from .pipeline import Ahead, Sink, in_order

# Frames prepared (deformed and sorted) ahead of the draw, and frames queued for the encoder. Each prepared frame
# holds its sorted rows (52 bytes a Gaussian), each queued frame its pixels, so these bound the memory the overlap
# costs.
PREPARED_AHEAD = 2
ENCODE_AHEAD = 2


def _in_flight(workers: int) -> int:
    """The `in_order` depth for frames made whole on `workers` threads: each has one frame in hand and one queued,
    so none waits for the caller between frames."""
    return 2 * workers - 1


def bare_frames(renderer: FrameRenderer, drives: Iterable[Drive], output: str, pipelined: bool
                ) -> Iterator[np.ndarray]:
    """The head's frames. Pipelined: where the splatter can (`frames_at_once` > 1: the CPU splatter), whole
    frames on that many worker threads at once; else the next frames' drives, deformation and sort on a worker
    thread (up to PREPARED_AHEAD frames ahead) while this thread draws (a GL context is bound to the thread that
    made it)."""
    if not pipelined:
        for drive in drives:
            yield renderer.frame(drive, output)
        return
    workers = renderer.frames_at_once()
    if workers > 1:
        yield from in_order(renderer.frame, ((drive, output) for drive in drives), _in_flight(workers), "gt-frame",
                            workers=workers, initializer=renderer.begin_worker)
        return
    with Ahead((renderer.prepare(drive) for drive in drives), PREPARED_AHEAD, "gt-prepare") as prepared:
        for splats in prepared:
            yield renderer.draw(splats, output)


def composited_frames(renderer: FrameRenderer, compositor: Compositor, drives: Iterable[Drive], pipelined: bool,
                      reference_frames: Iterable[int] | None = None) -> Iterator[np.ndarray]:
    """Frame t composited into the clip's frame t (`reference_frames`: the clip frame of each drive instead, for a
    segment of a longer clip or another frame rate). Pipelined, where the splatter can (`frames_at_once` > 1),
    whole frames (deformation, sort, draw, F and the blend) on that many worker threads at once, the reference
    pictures decoded in order on one more; else three stages overlap: the next frames prepared with their reference
    pictures decoded, frame t drawn on this thread, frame t-1 composited (F and the blend) on its own thread, so
    the composite costs no frame time when the machine has cores to spare."""
    indices = itertools.count() if reference_frames is None else reference_frames  # zipped unstrict: count() is endless
    workers = renderer.frames_at_once() if pipelined else 1
    if workers > 1:
        def composited(drive: Drive, picture: np.ndarray, mask: np.ndarray) -> np.ndarray:
            return compositor.blend(renderer.frame(drive, "rgba_float"), picture, mask)

        pictures = ((drive, *compositor.picture(index)) for drive, index in zip(drives, indices, strict=False))
        with Ahead(pictures, _in_flight(workers), "gt-picture") as ahead:
            yield from in_order(composited, ahead, _in_flight(workers), "gt-frame", workers=workers,
                                initializer=renderer.begin_worker)
        return
    prepared = ((renderer.prepare(drive), *compositor.picture(index))
                for drive, index in zip(drives, indices, strict=False))
    if not pipelined:
        for splats, picture, mask in prepared:
            yield compositor.blend(renderer.draw(splats, "rgba_float"), picture, mask)
        return
    with Ahead(prepared, PREPARED_AHEAD, "gt-prepare") as ahead:
        drawn = ((renderer.draw(splats, "rgba_float"), picture, mask) for splats, picture, mask in ahead)
        yield from in_order(compositor.blend, drawn, 1, "gt-composite")


def write_frames(out: VideoWriter, frames: Iterator[np.ndarray], total: int, *, pipelined: bool, progress: bool,
                 on_frame: Callable[[np.ndarray], None] | None = None) -> None:
    """Encode `frames` into `out` (`on_frame` sees each one). Pipelined, encoding runs on its own thread while the
    next frame is made; `on_frame` may change its frame, so the encoder then gets its own copy."""
    bar = progress_bar(frames, total=total, unit="frame", disable=not progress, desc="rendering")
    if not pipelined:
        for frame in bar:
            out.write(frame)
            if on_frame is not None:
                on_frame(frame)
        return
    with Sink(out.write, ENCODE_AHEAD, "gt-encode") as encoder:
        for frame in bar:
            encoder.put(frame if on_frame is None else frame.copy())
            if on_frame is not None:
                on_frame(frame)


__all__ = ["ENCODE_AHEAD", "PREPARED_AHEAD", "bare_frames", "composited_frames", "write_frames"]
