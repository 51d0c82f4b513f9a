"""Audio -> per-frame FLAME drive in bounded windows, so long audio never builds one huge attention matrix."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from gaussiantalker.sdk.audio import pad_to_frames

# A window covers this many video frames of output (10 s at 25 fps); each side gets CONTEXT_FRAMES of extra
# audio that the translator sees but whose frames are discarded, so window joins have full context on both sides.
WINDOW_FRAMES = 250
CONTEXT_FRAMES = 25


def translate_audio(run: Callable[[np.ndarray], dict], audio: np.ndarray, samples_per_frame: int,
                    window_frames: int = WINDOW_FRAMES, context_frames: int = CONTEXT_FRAMES
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Run the translator (`run(audio_chunk) -> {"expression", "jaw_pose"}`) over windows and stitch them."""
    audio = pad_to_frames(audio, samples_per_frame)
    total = audio.shape[0] // samples_per_frame
    expressions, jaws = [], []
    for start in range(0, total, window_frames):
        stop = min(start + window_frames, total)
        lo, hi = max(0, start - context_frames), min(total, stop + context_frames)
        out = run(audio[lo * samples_per_frame: hi * samples_per_frame])
        expressions.append(out["expression"][0, start - lo: stop - lo])
        jaws.append(out["jaw_pose"][0, start - lo: stop - lo])
    return np.concatenate(expressions), np.concatenate(jaws)
