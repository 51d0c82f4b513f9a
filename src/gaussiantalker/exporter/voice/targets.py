"""Timed phonemes -> ARKit-52 targets per video frame: co-articulated visemes, blinks and brows (docs/voice.md,
"Targets").

Co-articulation follows Cohen and Massaro's dominance model: every viseme segment pulls each articulator group (jaw,
lips) toward its pose with a dominance that is full over the segment and falls off outside it as a Gaussian of
the distance (its own widths before and after: lip rounding is anticipated ~0.1 s, a bilabial's grip fades in
~20 ms), and a frame's pose is the dominance-weighted mean. Lip closure is blended the same way as its own channel
and mouthClose = closure x jawOpen, so /p b m/ close the lips whatever the neighbouring vowels do to the jaw.

Vocal effort: the jaw and what rides on it open wider the louder a frame is against the loudest frame of the
~1 s around it (EFFORT_*): louder syllables open more, and a quiet tail closes, as real speakers' jaws do; it is
what ties the jaw to the loudness the model hears.

Blinks and brows keep their own rhythms: a blink at the start of every pause that follows speech (phrase rhythm),
brows raised on primary-stressed syllables, strongest on a phrase's first accent and falling off after it (stress
rhythm and declination), the inner brows on a question's last accent.

Frames: frame k covers [k / fps, (k + 1) / fps) of the audio and is the mean of SUBSAMPLES instants across it, so a
closure shorter than a frame still shows in it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gaussiantalker.sdk.rig import ARKIT_BLENDSHAPES, ARKIT_COUNT

from .espeak import PAUSE, SAMPLE_RATE, Phoneme
from .visemes import DOMINANCE, VOWEL_VISEMES, channel_groups, pose, visemes_of

FPS = 25
SUBSAMPLES = 4  # instants per frame averaged into it
ROUNDED = ("O", "U", "W", "Y", "CH", "RR")  # visemes whose lip rounding is anticipated
# Gaussian widths (s) of a segment's dominance before (anticipation) and after (carry-over) it, per group.
JAW_WIDTH = (0.05, 0.05)
LIP_WIDTH = (0.06, 0.06)
ROUNDED_LIP_WIDTH = (0.12, 0.06)
GRIP_WIDTH = (0.018, 0.018)  # bilabials and labiodentals: both groups let go fast
GRIP_VISEMES = ("PP", "FF")
SILENCE_WIDTH = (0.06, 0.08)  # the mouth leaves rest ~60 ms before the sound and returns ~80 ms after it

# Blinks: at the start of a pause of at least BLINK_PAUSE_S after speech; closing, closed, opening (s).
BLINK_PAUSE_S = 0.15
BLINK_DELAY_S = 0.04
BLINK_SHAPE_S = (0.07, 0.03, 0.12)
# Brows: a raise on each primary-stressed vowel, rising from RISE_S before the vowel to its centre, falling over
# FALL_S after it; a phrase's first accent FIRST_ACCENT high, later ones LATER_ACCENT; questions raise the inner
# brows on their last accent by QUESTION_INNER.
BROW_RISE_S, BROW_FALL_S = 0.1, 0.35
FIRST_ACCENT, LATER_ACCENT, QUESTION_INNER = 0.45, 0.2, 0.5
OUTER_SHARE, INNER_SHARE = 0.8, 0.6  # brow raise -> browOuterUp, browInnerUp
# Vocal effort: jaw channels x (1 - EFFORT_SHARE + EFFORT_SHARE * effort), effort = the frame's level (dB) within
# EFFORT_RANGE_DB below the loudest frame from EFFORT_BEFORE_S before it to EFFORT_AFTER_S after it (the span the
# model sees in a live session).
EFFORT_SHARE, EFFORT_RANGE_DB = 0.7, 24.0
EFFORT_BEFORE_S, EFFORT_AFTER_S = 0.8, 0.16
QUESTION_MARKS = "?¿？"
CLAUSE_ENDS = ".,;:!?¿？。、"


@dataclass(frozen=True)
class Segment:
    """One viseme over [start, end) seconds."""

    viseme: str
    start: float
    end: float


def frame_count(seconds: float, fps: int = FPS) -> int:
    """Frames of a clip: ceil(seconds * fps)."""
    return int(np.ceil(seconds * fps - 1e-9))


def segments(phonemes: Sequence[Phoneme], seconds: float) -> list[Segment]:
    """Viseme segments of a phoneme list, with silence before the first and after the last phoneme."""
    out = []
    first = phonemes[0].start if phonemes else seconds
    out.append(Segment("sil", -1.0, first))
    for phoneme in phonemes:
        start = phoneme.start
        for viseme, share in visemes_of(phoneme.ipa):
            end = start + share * (phoneme.end - phoneme.start)
            out.append(Segment(viseme, start, end))
            start = end
    out.append(Segment("sil", phonemes[-1].end if phonemes else seconds, seconds + 1.0))
    return out


def _widths(viseme: str) -> tuple[tuple[float, float], tuple[float, float]]:
    """(jaw, lips) dominance widths (before, after) of a viseme."""
    if viseme in GRIP_VISEMES:
        return GRIP_WIDTH, GRIP_WIDTH
    if viseme == "sil":
        return SILENCE_WIDTH, SILENCE_WIDTH
    return JAW_WIDTH, ROUNDED_LIP_WIDTH if viseme in ROUNDED else LIP_WIDTH


def _reach(times: np.ndarray, start: np.ndarray, end: np.ndarray, before: np.ndarray, after: np.ndarray
           ) -> np.ndarray:
    """[segments, times] dominance shape: 1 inside a segment, a Gaussian of the distance outside it."""
    t = times[None, :]
    early = np.maximum(start[:, None] - t, 0.0) / before[:, None]
    late = np.maximum(t - end[:, None], 0.0) / after[:, None]
    return np.exp(-(early * early + late * late))


def sample_times(frames: int, fps: int = FPS) -> np.ndarray:
    """The instants averaged into each frame, [frames * SUBSAMPLES] seconds."""
    return (np.arange(frames * SUBSAMPLES) + 0.5) / (fps * SUBSAMPLES)


def _per_frame(values: np.ndarray) -> np.ndarray:
    """[frames * SUBSAMPLES, ...] -> [frames, ...] means."""
    return values.reshape(-1, SUBSAMPLES, *values.shape[1:]).mean(axis=1)


def _weighted_sum(weight: np.ndarray, values: np.ndarray) -> np.ndarray:
    """weight.T @ values ([N, T], [N, C] -> [T, C]) summed in segment order by numpy's own loops, not BLAS: a
    multi-threaded BLAS splits the sum differently from run to run, and training data must be the same bits."""
    return np.einsum("nt,nc->tc", weight, values, optimize=False)


def mouth(segs: Sequence[Segment], frames: int, fps: int = FPS) -> np.ndarray:
    """The co-articulated mouth [frames, 52] (jaw and lip channels, mouthClose from the closure)."""
    times = sample_times(frames, fps)
    start = np.array([s.start for s in segs])
    end = np.array([s.end for s in segs])
    widths = [_widths(s.viseme) for s in segs]
    jaw_mask, lip_mask = channel_groups()
    poses = np.stack([pose(s.viseme) for s in segs]).astype(np.float64)  # [N, 52]
    out = np.zeros((times.size, ARKIT_COUNT))
    closure = None
    for group, mask in ((0, jaw_mask), (1, lip_mask)):
        alpha = np.array([DOMINANCE[s.viseme][group] for s in segs])
        reach = _reach(times, start, end, np.array([w[group][0] for w in widths]),
                       np.array([w[group][1] for w in widths]))
        weight = alpha[:, None] * reach  # [N, T]
        total = weight.sum(axis=0) + 1e-12
        out[:, mask] = _weighted_sum(weight, poses[:, mask]) / total[:, None]
        if group == 1:
            closure = _weighted_sum(weight, np.array([DOMINANCE[s.viseme][2] for s in segs])[:, None])[:, 0] / total
    out[:, ARKIT_BLENDSHAPES.index("mouthClose")] = closure * out[:, ARKIT_BLENDSHAPES.index("jawOpen")]
    return _per_frame(out)


def _clauses(phonemes: Sequence[Phoneme], text: str) -> list[tuple[list[int], bool]]:
    """Phrases as (indices of their spoken phonemes, is a question): a phrase ends at clause punctuation in the
    text (espeak-ng's short pauses between words do not end one); a question when that punctuation is '?'."""
    phrases: dict[int, list[int]] = {}
    for i, phoneme in enumerate(phonemes):
        if phoneme.ipa != PAUSE:
            clause = sum(ch in CLAUSE_ENDS for ch in text[:phoneme.text_position])
            phrases.setdefault(clause, []).append(i)
    out = []
    for run in phrases.values():
        position = phonemes[run[-1]].text_position
        end = next((ch for ch in text[position:] if ch in CLAUSE_ENDS), "")
        out.append((run, end in QUESTION_MARKS))
    return out


def frame_levels(audio: np.ndarray, frames: int, fps: int = FPS, sample_rate: int = SAMPLE_RATE) -> np.ndarray:
    """RMS level (dB re. full scale, floored at -120) of each frame's samples [k / fps, (k + 1) / fps)."""
    bounds = np.round(np.arange(frames + 1) * sample_rate / fps).astype(int)
    padded = np.zeros(bounds[-1])
    padded[: min(audio.shape[0], bounds[-1])] = audio[: bounds[-1]]
    energy = np.add.reduceat(padded * padded, bounds[:-1]) / np.diff(bounds)
    return 10.0 * np.log10(energy + 1e-12)


def effort(audio: np.ndarray, frames: int, fps: int = FPS) -> np.ndarray:
    """Vocal effort [frames] in 0..1: each frame's level within EFFORT_RANGE_DB below the loudest frame around it."""
    level = frame_levels(audio, frames, fps)
    before, after = round(EFFORT_BEFORE_S * fps), round(EFFORT_AFTER_S * fps)
    padded = np.concatenate([np.full(before, -120.0), level, np.full(after, -120.0)])
    windows = np.lib.stride_tricks.sliding_window_view(padded, before + after + 1)
    reference = windows.max(axis=1)
    return np.clip((level - reference + EFFORT_RANGE_DB) / EFFORT_RANGE_DB, 0.0, 1.0)


def _bump(times: np.ndarray, onset: float, peak: float, fall: float) -> np.ndarray:
    """0 before `onset`, a raised-cosine rise to 1 at `peak`, a raised-cosine fall to 0 at `fall`."""
    rise = np.clip((times - onset) / max(peak - onset, 1e-6), 0.0, 1.0)
    drop = np.clip((times - peak) / max(fall - peak, 1e-6), 0.0, 1.0)
    return np.where(times <= peak, 0.5 - 0.5 * np.cos(np.pi * rise), 0.5 + 0.5 * np.cos(np.pi * drop))


def blinks(phonemes: Sequence[Phoneme], frames: int, fps: int = FPS) -> np.ndarray:
    """Eyelid closure [frames] in 0..1: a blink at each pause of >= BLINK_PAUSE_S that follows speech (a run of
    pauses counts as one)."""
    times = sample_times(frames, fps)
    out = np.zeros(times.size)
    close, hold, open_ = BLINK_SHAPE_S
    for start, end, after_speech in _pauses(phonemes):
        if after_speech and end - start >= BLINK_PAUSE_S:
            begin = start + BLINK_DELAY_S
            lid = np.clip(np.minimum((times - begin) / close, 1.0 - (times - begin - close - hold) / open_), 0, 1)
            out = np.maximum(out, lid * (times >= begin))
    return _per_frame(out)


def _pauses(phonemes: Sequence[Phoneme]) -> list[tuple[float, float, bool]]:
    """(start, end, follows speech) of each run of consecutive pauses (espeak-ng often writes a pause as two)."""
    runs: list[tuple[float, float, bool]] = []
    previous = None
    for phoneme in phonemes:
        if phoneme.ipa == PAUSE:
            if previous == PAUSE and runs:
                runs[-1] = (runs[-1][0], phoneme.end, runs[-1][2])
            else:
                runs.append((phoneme.start, phoneme.end, previous is not None))
        previous = phoneme.ipa if phoneme.ipa == PAUSE else "speech"
    return runs


def brows(phonemes: Sequence[Phoneme], text: str, frames: int, fps: int = FPS) -> tuple[np.ndarray, np.ndarray]:
    """(outer brow raise, inner brow raise) [frames] from the accents: primary-stressed vowels (docstring above)."""
    times = sample_times(frames, fps)
    outer, inner = np.zeros(times.size), np.zeros(times.size)
    for run, question in _clauses(phonemes, text):
        accents = [i for i in run if phonemes[i].stress == 1 and visemes_of(phonemes[i].ipa)[0][0] in VOWEL_VISEMES]
        for rank, i in enumerate(accents):
            p = phonemes[i]
            centre = 0.5 * (p.start + p.end)
            shape = _bump(times, p.start - BROW_RISE_S, centre, centre + BROW_FALL_S)
            height = FIRST_ACCENT if rank == 0 else LATER_ACCENT
            outer = np.maximum(outer, OUTER_SHARE * height * shape)
            inner = np.maximum(inner, INNER_SHARE * height * shape)
            if question and rank == len(accents) - 1:
                inner = np.maximum(inner, QUESTION_INNER * shape)
    return _per_frame(outer), _per_frame(inner)


def arkit_targets(phonemes: Sequence[Phoneme], text: str, audio: np.ndarray, fps: int = FPS) -> np.ndarray:
    """ARKit weights [frames, 52] (ARKIT_BLENDSHAPES order, 0..1) of a clip (mono, SAMPLE_RATE) whose phonemes
    and text are known; frames = ceil(duration * fps)."""
    seconds = audio.shape[0] / SAMPLE_RATE
    frames = frame_count(seconds, fps)
    out = mouth(segments(phonemes, seconds), frames, fps)
    jaw = channel_groups()[0]
    jaw[ARKIT_BLENDSHAPES.index("mouthClose")] = True  # closure x jawOpen: scaled with the jaw, the lips stay shut
    out[:, jaw] *= (1.0 - EFFORT_SHARE + EFFORT_SHARE * effort(audio, frames, fps))[:, None]
    lid = blinks(phonemes, frames, fps)
    outer, inner = brows(phonemes, text, frames, fps)
    for name, values in (("eyeBlinkLeft", lid), ("eyeBlinkRight", lid), ("browOuterUpLeft", outer),
                         ("browOuterUpRight", outer), ("browInnerUp", inner)):
        out[:, ARKIT_BLENDSHAPES.index(name)] = values
    return np.clip(out, 0.0, 1.0).astype(np.float32)


__all__ = ["FPS", "Segment", "arkit_targets", "blinks", "brows", "frame_count", "mouth", "sample_times",
           "segments"]
