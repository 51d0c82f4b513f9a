"""A speaker's bare head for the benches that export it: its reference clip and inpainting generator set aside
for a block (the sweep's bare bundles, the clip bench's clip-free bundle), so one loaded speaker serves both."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the torch speaker: imported by the benches that hold one, not by this module
    from gaussiantalker.exporter.model.speaker import Speaker


@contextlib.contextmanager
def without_clip(speaker: Speaker) -> Iterator[Speaker]:
    """`speaker` without its reference clip and inpainting generator within the block (restored after)."""
    saved = speaker.reference, speaker.inpaint
    speaker.reference = speaker.inpaint = None
    try:
        yield speaker
    finally:
        speaker.reference, speaker.inpaint = saved


__all__ = ["without_clip"]
