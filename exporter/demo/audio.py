"""Loudness-derived motion targets for the demo speaker's translator training (the speech itself: export/speech.py).

numpy only (no torch), so samples and the runtime side can compute the same targets.
"""

from __future__ import annotations

import numpy as np

from gaussiantalker.sdk.audio import pad_to_frames, write_wav
from gaussiantalker.sdk.config import AUDIO_NORM_EPS, DEFAULT_FPS, DEFAULT_SAMPLE_RATE

__all__ = ["loudness_envelope", "jaw_target_from_audio", "spectral_tilt", "normalize_audio", "smooth_frames",
           "pad_to_frames", "write_wav"]

SAMPLE_RATE = DEFAULT_SAMPLE_RATE
FPS = DEFAULT_FPS
# Floor of the per-frame RMS before taking dB, so digital silence gives a finite level (-100 dBFS).
RMS_FLOOR = 1e-5


def _check_mono(audio: np.ndarray) -> np.ndarray:
    """Return `audio` as a 1-D float64 array, or raise ValueError naming the problem."""
    a = np.asarray(audio, dtype=np.float64)
    if a.ndim != 1:
        raise ValueError(f"expected mono audio of shape [samples], got shape {a.shape}")
    return a


def normalize_audio(audio: np.ndarray) -> np.ndarray:
    """Per-utterance zero-mean unit-variance normalisation, the same as the translator's first step."""
    a = _check_mono(audio)
    if a.size == 0:
        return a
    centred = a - a.mean()
    return centred / np.sqrt(np.mean(centred * centred) + AUDIO_NORM_EPS)


def loudness_envelope(audio: np.ndarray, sample_rate: int = SAMPLE_RATE, fps: int = FPS) -> np.ndarray:
    """Per-video-frame RMS level in dB (re. 1.0, floored at -100 dB), frame t covering [spf*t, spf*(t+1))."""
    spf = sample_rate // fps
    frames = pad_to_frames(audio, spf).reshape(-1, spf)
    rms = np.sqrt(np.mean(frames * frames, axis=1))
    return (20.0 * np.log10(np.maximum(rms, RMS_FLOOR))).astype(np.float32)


def smooth_frames(x: np.ndarray, taps: int = 3) -> np.ndarray:
    """Binomial smoothing along time with edge replication (keeps constant tracks, incl. zero, unchanged)."""
    kernel = np.array([1.0])
    for _ in range(taps - 1):
        kernel = np.convolve(kernel, [0.5, 0.5])
    half = taps // 2
    padded = np.concatenate([np.full(half, x[0]), x, np.full(half, x[-1])]) if x.size else x
    return np.convolve(padded, kernel, mode="valid") if x.size else x


def jaw_target_from_audio(
    audio: np.ndarray,
    sample_rate: int = SAMPLE_RATE,
    fps: int = FPS,
    max_angle: float = 0.3,
    floor_db: float = -24.0,
    full_db: float = 6.0,
    normalize: bool = True,
) -> np.ndarray:
    """Jaw opening (rad) per frame from loudness: 0 below floor_db, max_angle at full_db, lightly smoothed.

    With normalize=True the level is measured on the per-utterance-normalised clip (the translator's own view
    of the audio), so the target is gain-invariant and a function of what the model sees; digital silence
    stays 0.
    """
    spf = sample_rate // fps
    a = pad_to_frames(audio, spf)
    if normalize:
        a = normalize_audio(a)
    level = loudness_envelope(a, sample_rate, fps).astype(np.float64)
    opening = np.clip((level - floor_db) / (full_db - floor_db), 0.0, 1.0)
    return (max_angle * smooth_frames(opening, 3)).astype(np.float32)


def spectral_tilt(
    audio: np.ndarray,
    sample_rate: int = SAMPLE_RATE,
    fps: int = FPS,
    split_hz: float = 2000.0,
    gate_db: float = -40.0,
) -> np.ndarray:
    """Per-frame high/low band energy ratio mapped to (-1, 1) (tanh of dB/20); >0 = fricative-like.

    Frames more than |gate_db| below the clip's loudest frame (pauses, noise floor) give 0.
    """
    spf = sample_rate // fps
    frames = pad_to_frames(audio, spf).reshape(-1, spf)
    if frames.shape[0] == 0:
        return np.zeros(0, dtype=np.float32)
    spec = np.abs(np.fft.rfft(frames * np.hanning(spf), axis=1)) ** 2
    high = np.fft.rfftfreq(spf, 1.0 / sample_rate) >= split_hz
    e_high, e_low = spec[:, high].sum(axis=1), spec[:, ~high].sum(axis=1)
    floor = spf * RMS_FLOOR**2
    tilt = np.tanh(10.0 * np.log10((e_high + floor) / (e_low + floor)) / 20.0)
    level = loudness_envelope(audio, sample_rate, fps)
    tilt[level < max(float(level.max()) + gate_db, 20.0 * np.log10(RMS_FLOOR) + 1.0)] = 0.0
    return tilt.astype(np.float32)


