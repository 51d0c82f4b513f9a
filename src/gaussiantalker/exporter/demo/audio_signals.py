"""Per-frame motion signals for the demo speaker's translator training (the speech itself: export/speech.py).

Each signal is a deterministic function of the audio alone (so the translator can learn it), with its own time
behaviour: mouth opening from loudness, spread vs round lips from the vowel spectrum, lip closure before
plosive-like onsets, fricative energy, phrase emphasis and softness, blinks at pause onsets, a slow warmth from
the long-window level. `train_translator.motion_targets` maps them to FLAME coefficients (docs/demo-speaker.md).
numpy only (no torch), so samples and the runtime side can compute the same targets.
"""

from __future__ import annotations

import numpy as np

from gaussiantalker.sdk.audio import pad_to_frames, write_wav
from gaussiantalker.sdk.config import AUDIO_NORM_EPS, DEFAULT_FPS, DEFAULT_SAMPLE_RATE

__all__ = ["loudness_envelope", "jaw_target_from_audio", "spectral_tilt", "normalize_audio", "smooth_frames",
           "gaussian_smooth", "motion_signals", "MOTION_SIGNALS", "pad_to_frames", "write_wav"]

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




# ---- motion signals -------------------------------------------------------------------------------------------
# Their names, in the column order of `motion_signals`; each lies in [0, 1].
MOTION_SIGNALS = ("open", "spread", "round", "closure", "fricative", "emphasis", "soft", "blink", "warmth")
JAW_FLOOR_DB = -24.0  # jaw_target_from_audio's floor: below it (re. the utterance RMS) a frame counts as quiet
VOWEL_SPLIT_DB = -20.0  # F2 band over F1/F2-back band (dB) between back/round (u, o, a) and front/spread (i, e)
VOWEL_WIDTH_DB = 8.0  # tanh width of that split
ONSET_DB = -12.0  # a plosive-like onset reaches this level (re. the utterance RMS) within 2 frames of a quiet run
ONSET_QUIET_FRAMES = 2  # ...after at least this many quiet frames
CLOSURE_FRAMES = 3  # lips pressed this many frames before the onset
PAUSE_FRAMES = 7  # a quiet run this long (280 ms at 25 fps) is a pause, longer than any gap inside a phrase
PAUSE_SPEECH_FRAMES = 3  # ...after at least this many frames of speech
BLINK_FRAMES = 4  # eyes closed this many frames from the pause's first frame
EMPHASIS_SIGMA_S, CONTEXT_SIGMA_S = 0.4, 0.8  # phrase level and its surrounding level (Gaussian windows, s)


def gaussian_smooth(x: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing along time (sigma in frames) with edge replication; constant tracks stay unchanged."""
    if x.size == 0 or sigma <= 0:
        return np.asarray(x, dtype=np.float64)
    half = int(np.ceil(3.0 * sigma))
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    padded = np.concatenate([np.full(half, x[0]), x, np.full(half, x[-1])])
    return np.convolve(padded, kernel / kernel.sum(), mode="valid")


def _band_energies(frames: np.ndarray, sample_rate: int, bands: tuple[tuple[float, float], ...]) -> np.ndarray:
    """Per-frame energy [T, len(bands)] of a Hann-windowed frame in each [lo, hi) Hz band."""
    spf = frames.shape[1]
    spec = np.abs(np.fft.rfft(frames * np.hanning(spf), axis=1)) ** 2
    freqs = np.fft.rfftfreq(spf, 1.0 / sample_rate)
    return np.stack([spec[:, (freqs >= lo) & (freqs < hi)].sum(axis=1) for lo, hi in bands], 1)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of each run of True in a 1-D bool array."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def _closure(level: np.ndarray, voiced: np.ndarray) -> np.ndarray:
    """1 on the CLOSURE_FRAMES frames before each plosive-like onset: a quiet run of >= ONSET_QUIET_FRAMES frames
    followed within 2 frames by a voiced frame at >= ONSET_DB; 0 elsewhere."""
    out = np.zeros(level.size)
    for start, stop in _runs(level < JAW_FLOOR_DB):
        after = slice(stop, min(stop + 2, level.size))
        if stop - start >= ONSET_QUIET_FRAMES and np.any((level[after] >= ONSET_DB) & voiced[after]):
            out[max(0, stop - CLOSURE_FRAMES) : stop] = 1.0
    return out


def _blinks(level: np.ndarray) -> np.ndarray:
    """1 on the BLINK_FRAMES frames from the start of each pause (a quiet run of >= PAUSE_FRAMES frames that
    follows >= PAUSE_SPEECH_FRAMES frames of speech); 0 elsewhere, so never during continuous speech."""
    out = np.zeros(level.size)
    quiet = level < JAW_FLOOR_DB
    for start, stop in _runs(quiet):
        spoken = start >= PAUSE_SPEECH_FRAMES and not quiet[start - PAUSE_SPEECH_FRAMES : start].any()
        if stop - start >= PAUSE_FRAMES and spoken:
            out[start : start + BLINK_FRAMES] = 1.0
    return out


def motion_signals(audio: np.ndarray, sample_rate: int = SAMPLE_RATE, fps: int = FPS) -> np.ndarray:
    """Per-frame motion signals [T, len(MOTION_SIGNALS)] in [0, 1], from the per-utterance-normalised audio
    (the translator's own view, so they are gain-invariant); digital silence gives all zeros.

    open: jaw_target_from_audio / its max angle (loudness). spread / round: front (F2 high: i, e) vs back
    (u, o, a) vowel spectrum, in voiced frames. closure: frames before plosive-like onsets. fricative: high-band
    energy (spectral_tilt > 0). emphasis / soft: the phrase's level above / below its surrounding level while
    speaking (brows). blink: pause onsets. warmth: the long-window level (a slow smile).
    """
    spf = sample_rate // fps
    a = normalize_audio(pad_to_frames(_check_mono(audio), spf))
    frames = a.reshape(-1, spf)
    t = frames.shape[0]
    if t == 0:
        return np.zeros((0, len(MOTION_SIGNALS)), np.float32)
    max_angle = 0.3
    opening = jaw_target_from_audio(a, sample_rate, fps, max_angle=max_angle, floor_db=JAW_FLOOR_DB,
                                    normalize=False).astype(np.float64) / max_angle
    level = loudness_envelope(a, sample_rate, fps).astype(np.float64)
    fricative = np.clip(3.0 * smooth_frames(spectral_tilt(a, sample_rate, fps).astype(np.float64), 7), 0.0, 1.0)
    floor = spf * RMS_FLOOR**2
    bands = _band_energies(frames, sample_rate, ((600.0, 1300.0), (1500.0, 2800.0)))
    f2_db = 10.0 * np.log10((bands[:, 1] + floor) / (bands[:, 0] + floor))
    voiced = np.clip((level - JAW_FLOOR_DB) / 10.0, 0.0, 1.0) * (1.0 - fricative)
    vowel = smooth_frames(voiced * np.tanh((f2_db - VOWEL_SPLIT_DB) / VOWEL_WIDTH_DB), 3)
    phrase = gaussian_smooth(opening, EMPHASIS_SIGMA_S * fps)
    context = gaussian_smooth(opening, CONTEXT_SIGMA_S * fps)
    speaking = np.clip(gaussian_smooth((level >= JAW_FLOOR_DB).astype(np.float64), 0.2 * fps) / 0.5, 0.0, 1.0)
    signals = {
        "open": opening,
        "spread": np.clip(vowel, 0.0, 1.0),
        "round": np.clip(-vowel, 0.0, 1.0),
        "closure": smooth_frames(_closure(level, voiced > 0.5), 3),
        "fricative": fricative,
        "emphasis": np.clip((phrase - context) / 0.15, 0.0, 1.0),
        "soft": np.clip((context - phrase) / 0.15, 0.0, 1.0) * speaking,
        "blink": smooth_frames(_blinks(level), 3),
        "warmth": np.clip((context - 0.35) / 0.4, 0.0, 1.0),
    }
    return np.stack([signals[name] for name in MOTION_SIGNALS], 1).astype(np.float32)
