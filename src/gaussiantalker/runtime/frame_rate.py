"""Video at a frame rate other than the speaker's (docs/video.md, "Frame rate"): the drives, made at the speaker's
fps, sampled at the output's frame times. A bare head's drive at a time between two speaker frames is their
linear blend (smooth motion at any rate; the FLAME and head rotations are axis-angle vectors that change little in a
frame, where a blend is as good as a slerp); a composited frame takes the nearest speaker frame's drive and its
reference picture together, so the head stays on the clip's pose (frames repeat or drop, as a frame-rate converter
does)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from fractions import Fraction
from typing import TYPE_CHECKING

import numpy as np

from gaussiantalker.sdk.video import video_rate

if TYPE_CHECKING:
    from .driver import Drive


def resampled(drives: Sequence[Drive], source_fps: float, fps: float, count: int, *,
              blend: bool) -> tuple[list[Drive], list[int]]:
    """`count` drives at `fps` from `drives` at `source_fps`, and the source frame nearest each (the reference
    picture a composited frame takes). `blend`: the two neighbouring drives blended linearly; else the nearest.
    A time that falls on a source frame gets that drive itself."""
    if not drives:
        raise ValueError("no drives to resample")
    step = Fraction(source_fps) / video_rate(fps)
    last = len(drives) - 1
    out, nearest = [], []
    for index in range(count):
        position = index * step
        below = min(math.floor(position), last)
        weight = position - below if below < last else Fraction(0)
        near = min(below + (1 if weight >= Fraction(1, 2) else 0), last)
        nearest.append(near)
        if weight == 0 or not blend:
            out.append(drives[near])
        else:
            out.append(_blend(drives[below], drives[below + 1], float(weight)))
    return out, nearest


def _blend(first: Drive, second: Drive, weight: float) -> Drive:
    """(1 - weight) * first + weight * second, field by field (every field of a drive is a float vector)."""
    fields = {field.name: ((1.0 - weight) * np.asarray(getattr(first, field.name), np.float64)
                           + weight * np.asarray(getattr(second, field.name), np.float64)).astype(np.float32)
              for field in dataclasses.fields(first)}
    return type(first)(**fields)
