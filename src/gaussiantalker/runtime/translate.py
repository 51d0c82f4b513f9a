"""Audio -> per-frame FLAME drive in bounded windows, lazily, so long audio costs one window at a time.

Windows: each covers WINDOW_FRAMES video frames (10 s at 25 fps); the translator also sees CONTEXT_FRAMES of
audio on each side (1 s), so frames near a join have context on both sides.

Joins: the translator normalises each window's audio on its own, so two neighbouring windows disagree slightly
on the frames they share. Cut from one window to the next, that lands as a one-frame jump (a twitch where the face
is still). Instead, the CROSSFADE_FRAMES frames around a join (each window's frames there still have >= 15 frames
of context) are a linear cross-fade of the two windows' outputs, computed anyway from the context. The measured
disagreement, jump and cross-faded step: docs/embedding.md, "Long audio" (tests/test_stability_audio.py).

Silence gate: per-utterance normalisation amplifies a window of pure low-level noise to full scale, and the jaw
opens with no speech. A window whose audio (as the translator sees it, context included) has an RMS below
SILENCE_GATE_DBFS is driven toward the neutral face: its outputs are scaled by a gain falling linearly in dB from
1 at SILENCE_GATE_DBFS to 0 at SILENCE_GATE_DBFS - SILENCE_GATE_RAMP_DB (RMS after removing the mean, as the
translator's normalisation does). Joins between gated and ungated windows are cross-faded like any other. The
torch verification path calls this same function, so both sides gate alike. The gate knows loudness, not speech:
noise above -60 dBFS still opens the jaw, and a whole 12 s window of speech below -66 dBFS RMS (peaks near
-45 dBFS: a very quiet recording; normalise it first) stays neutral.

Memory: `iter_translate` holds one window of audio (a view), and the outputs of two windows; nothing grows with
the clip's duration beyond the decoded audio itself.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import numpy as np

from gaussiantalker.sdk.errors import AudioError

WINDOW_FRAMES = 250
CONTEXT_FRAMES = 25
# Frames around each join that are a linear cross-fade of the two windows (half on each side of the join).
CROSSFADE_FRAMES = 20
# Windows quieter than this (RMS, dB re. full scale 1.0) fade toward the neutral face; None disables the gate.
SILENCE_GATE_DBFS = -60.0
SILENCE_GATE_RAMP_DB = 6.0

Run = Callable[[np.ndarray], dict]
# A window's graph outputs -> its parameters [frames, D] (FLAME: expression then jaw pose).
ParamsOf = Callable[[dict, int], np.ndarray]


def flame_params(out: dict, frames: int) -> np.ndarray:
    """A FLAME translator window's outputs -> [frames, n_expr + 3] (expression then jaw)."""
    return np.concatenate([out["expression"][0], out["jaw_pose"][0]], axis=-1)


def frame_start(index: int, samples_per_frame: float) -> int:
    """First audio sample of video frame `index` (frames of a fractional length start at the rounded sample)."""
    return int(round(index * samples_per_frame))


def window_plan(total: int, window_frames: int = WINDOW_FRAMES, context_frames: int = CONTEXT_FRAMES
                ) -> Iterator[tuple[int, int, int, int]]:
    """(start, stop, lo, hi) per window: frames [start, stop) are its own, [lo, hi) what the translator sees."""
    for start in range(0, total, window_frames):
        yield (start, min(start + window_frames, total), max(0, start - context_frames),
               min(total, start + window_frames + context_frames))


def silence_gain(chunk: np.ndarray, gate_dbfs: float | None = SILENCE_GATE_DBFS,
                 ramp_db: float = SILENCE_GATE_RAMP_DB) -> float:
    """Gain in [0, 1] of a window's outputs: 1 at or above gate_dbfs, 0 at gate_dbfs - ramp_db and below."""
    if gate_dbfs is None:
        return 1.0
    centred = chunk.astype(np.float64) - float(np.mean(chunk, dtype=np.float64))  # the level the translator sees
    return _gain_of_power(float(np.mean(centred * centred)), gate_dbfs, ramp_db)


def silence_gain_of_sums(total: float, total_squares: float, count: int, gate_dbfs: float | None = SILENCE_GATE_DBFS,
                         ramp_db: float = SILENCE_GATE_RAMP_DB) -> float:
    """`silence_gain` of a window known by its samples' sum, sum of squares and count (a live session keeps these
    per frame instead of its past audio: mean(x^2) - mean(x)^2 is the centred level)."""
    if gate_dbfs is None:
        return 1.0
    mean = total / max(count, 1)
    return _gain_of_power(max(total_squares / max(count, 1) - mean * mean, 0.0), gate_dbfs, ramp_db)


def _gain_of_power(power: float, gate_dbfs: float, ramp_db: float) -> float:
    """The gate's gain for a window whose centred mean power is `power`: linear in dB over the ramp."""
    level_db = 10.0 * math.log10(power + 1e-30)  # scalars: math, not numpy (a live session's gate every frame)
    return min(1.0, max(0.0, (level_db - gate_dbfs) / ramp_db + 1.0))


def _check_settings(window_frames: int, context_frames: int, crossfade_frames: int) -> None:
    """ValueError for window settings whose cross-fade would need frames no window computed."""
    if window_frames < 1 or context_frames < 0 or crossfade_frames < 0:
        raise ValueError("window_frames must be >= 1 and context/cross-fade frames >= 0")
    if crossfade_frames > 2 * context_frames or crossfade_frames > window_frames:
        raise ValueError(f"crossfade_frames ({crossfade_frames}) must be <= 2 * context_frames "
                         f"({2 * context_frames}) and <= window_frames ({window_frames})")


def _run_window(run: Run, audio: np.ndarray, spf: float, lo: int, hi: int, gate_dbfs: float | None,
                params_of: ParamsOf = flame_params) -> np.ndarray:
    """Translator outputs [hi - lo, D] of frames [lo, hi) (`params_of`: FLAME's expression then jaw), gated."""
    start, stop = frame_start(lo, spf), frame_start(hi, spf)
    chunk = audio[start:stop]
    if chunk.shape[0] < stop - start:  # the clip's last partial frame: zero-pad this window only
        chunk = np.pad(chunk, (0, stop - start - chunk.shape[0]))
    chunk = np.ascontiguousarray(chunk, dtype=np.float32)
    params = params_of(run(chunk), hi - lo)
    return params * np.float32(silence_gain(chunk, gate_dbfs))


def _join(left: np.ndarray, left_lo: int, right: np.ndarray, right_lo: int, join: int, half: int,
          end: int) -> np.ndarray:
    """Frames [join - half, min(join + half, end)) as a linear cross-fade from the left to the right window."""
    frames = np.arange(join - half, min(join + half, end))
    weight = ((frames - (join - half) + 0.5) / (2 * half)).astype(np.float32)[:, None]
    return (1 - weight) * left[frames - left_lo] + weight * right[frames - right_lo]


def iter_translate(run: Run, audio: np.ndarray, samples_per_frame: float, window_frames: int = WINDOW_FRAMES,
                   context_frames: int = CONTEXT_FRAMES, crossfade_frames: int = CROSSFADE_FRAMES,
                   silence_gate_dbfs: float | None = SILENCE_GATE_DBFS, params_of: ParamsOf = flame_params,
                   split: Callable[[np.ndarray], object] | None = None) -> Iterator:
    """Yield (expression [n, n_expr], jaw_pose [n, 3]) blocks in frame order, running window k+1 only when window
    k's last frames are due (it is needed for their cross-fade); `run(audio_chunk) -> {"expression", "jaw_pose"}`.
    Another translator (an ARKit speaker's audio model) gives its own `params_of` and `split` (None: the
    parameters [n, D] as they are); `samples_per_frame` may be fractional (16 kHz at 30 fps)."""
    _check_settings(window_frames, context_frames, crossfade_frames)
    split = split or (_split if params_of is flame_params else _whole)
    total = int(np.ceil(audio.shape[0] / samples_per_frame - 1e-9))
    if total == 0:
        raise AudioError("audio is empty (0 samples)")
    half = crossfade_frames // 2
    previous, emitted = None, 0
    for start, stop, lo, hi in window_plan(total, window_frames, context_frames):
        params = _run_window(run, audio, samples_per_frame, lo, hi, silence_gate_dbfs, params_of)
        if previous is not None:
            prev_params, prev_lo = previous
            block = [prev_params[emitted - prev_lo: start - half - prev_lo]]
            if half:
                block.append(_join(prev_params, prev_lo, params, lo, start, half, total))
            emitted = min(start + half, total)
            yield split(np.concatenate(block))
        previous = (params, lo)
        last_stop = stop
    prev_params, prev_lo = previous
    if emitted < last_stop:
        yield split(prev_params[emitted - prev_lo: last_stop - prev_lo])


def _whole(params: np.ndarray) -> np.ndarray:
    return params


def _split(params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[n, n_expr + 3] -> (expression [n, n_expr], jaw_pose [n, 3])."""
    return params[:, :-3], params[:, -3:]


def translate_audio(run: Run, audio: np.ndarray, samples_per_frame: int, window_frames: int = WINDOW_FRAMES,
                    context_frames: int = CONTEXT_FRAMES, crossfade_frames: int = CROSSFADE_FRAMES,
                    silence_gate_dbfs: float | None = SILENCE_GATE_DBFS) -> tuple[np.ndarray, np.ndarray]:
    """The whole clip at once: expression [T, n_expr], jaw_pose [T, 3] (T = ceil(S / samples_per_frame))."""
    blocks = list(iter_translate(run, audio, samples_per_frame, window_frames, context_frames, crossfade_frames,
                                 silence_gate_dbfs))
    return np.concatenate([b[0] for b in blocks]), np.concatenate([b[1] for b in blocks])


def resample_rows(values: np.ndarray, rows: int) -> np.ndarray:
    """[T, D] -> [rows, D], linear in time over the same span (frame centres aligned); itself when T == rows."""
    if values.shape[0] == rows:
        return values
    if values.shape[0] == 1:
        return np.repeat(values, rows, axis=0)
    source = (np.arange(values.shape[0]) + 0.5) / values.shape[0]
    target = (np.arange(rows) + 0.5) / rows
    return np.stack([np.interp(target, source, values[:, k]) for k in range(values.shape[1])], 1).astype(np.float32)


def blendshape_params(out: dict, frames: int) -> np.ndarray:
    """An audio-to-ARKit model's window outputs -> [frames, 52]: its `blendshapes` [1, T, 52], resampled in time
    when the model's T is not the window's frame count (docs/import.md, "Audio models")."""
    values = np.asarray(out["blendshapes"], np.float32)
    if values.ndim != 3 or values.shape[0] != 1 or values.shape[1] < 1:
        raise AudioError(f"the audio model returned blendshapes of shape {list(values.shape)}, expected [1, T >= 1, K]")
    return resample_rows(values[0], frames)
