"""Deterministic speech-like synthetic audio and loudness-derived motion targets for the demo speaker.

numpy only (no torch), so samples and the runtime side can make the same demo clip. The audio is a crude
source-filter model of speech: syllables of a glottal-pulse source (f0 with declination and jitter) shaped by
vowel formant resonances, fricative noise bursts, word and phrase pauses, and varying loudness. It is not
intelligible; it only needs the rhythm and loudness structure that drives a talking head's jaw.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gaussiantalker.sdk.audio import pad_to_frames, write_wav
from gaussiantalker.sdk.config import AUDIO_NORM_EPS, DEFAULT_FPS, DEFAULT_SAMPLE_RATE

__all__ = ["synth_speech", "loudness_envelope", "jaw_target_from_audio", "spectral_tilt", "normalize_audio",
           "smooth_frames", "pad_to_frames", "write_wav"]

SAMPLE_RATE = DEFAULT_SAMPLE_RATE
FPS = DEFAULT_FPS
# Floor of the per-frame RMS before taking dB, so digital silence gives a finite level (-100 dBFS).
RMS_FLOOR = 1e-5

# (F1, F2, F3) in Hz of a few vowels (Peterson & Barney averages, adult male).
_VOWEL_FORMANTS = (
    (730.0, 1090.0, 2440.0),  # a
    (270.0, 2290.0, 3010.0),  # i
    (530.0, 1840.0, 2480.0),  # e
    (660.0, 1720.0, 2410.0),  # ae
    (300.0, 870.0, 2240.0),  # u
    (570.0, 840.0, 2410.0),  # o
    (440.0, 1020.0, 2240.0),  # schwa-ish
    (490.0, 1350.0, 1690.0),  # er
)
_FORMANT_BANDWIDTHS = (80.0, 100.0, 140.0)
_FILTER_TAIL = 1024  # samples of resonator ring-out kept after each segment (overlap-added)


@dataclass
class _Voice:
    """Per-clip speaker traits: mean pitch and formant scaling."""

    f0: float
    formant_scale: float


def _resonator_response(freqs: np.ndarray, centre: float, bandwidth: float, sample_rate: int) -> np.ndarray:
    """Complex response of a unit-DC-gain 2-pole resonator (one formant) at `freqs` Hz."""
    r = np.exp(-np.pi * bandwidth / sample_rate)
    theta = 2.0 * np.pi * centre / sample_rate
    z1 = np.exp(-2j * np.pi * freqs / sample_rate)
    a1, a2 = -2.0 * r * np.cos(theta), r * r
    return (1.0 + a1 + a2) / (1.0 + a1 * z1 + a2 * z1 * z1)


def _filter_fft(signal: np.ndarray, response_fn, sample_rate: int) -> np.ndarray:
    """Filter `signal` (zero-padded by the ring-out tail) in the frequency domain; returns len + tail samples."""
    n = signal.size + _FILTER_TAIL
    spec = np.fft.rfft(signal, n)
    freqs = np.fft.rfftfreq(n, 1.0 / sample_rate)
    return np.fft.irfft(spec * response_fn(freqs), n)


def _unit_rms(x: np.ndarray) -> np.ndarray:
    """Scale to unit RMS (so segment gains are in meaningful units); zero stays zero."""
    rms = float(np.sqrt(np.mean(x * x)))
    return x / rms if rms > 0 else x


def _envelope(length: int, shape: float = 0.5) -> np.ndarray:
    """Smooth attack/release amplitude envelope of a syllable segment."""
    return np.sin(np.pi * (np.arange(length) + 0.5) / length) ** shape


def _glottal_source(f0_start: float, f0_end: float, length: int, rng: np.random.Generator, sr: int) -> np.ndarray:
    """Rosenberg glottal-flow derivative pulse train with an f0 glide, jitter and a little aspiration noise."""
    jitter = np.convolve(rng.standard_normal(length + 159), np.ones(160) / 160.0, mode="valid") * 0.25
    f0 = np.linspace(f0_start, f0_end, length) * (1.0 + jitter)
    phase = rng.uniform() + np.cumsum(f0 / sr)
    frac = phase % 1.0
    open_t, close_t = 0.4, 0.16
    flow = np.where(
        frac < open_t,
        0.5 * (1.0 - np.cos(np.pi * frac / open_t)),
        np.where(frac < open_t + close_t, np.cos(0.5 * np.pi * (frac - open_t) / close_t), 0.0),
    )
    source = np.diff(flow, prepend=flow[0])
    return _unit_rms(source) + 0.05 * rng.standard_normal(length) * flow


def _voiced_segment(
    length: int, f0: tuple[float, float], voice: _Voice, rng: np.random.Generator, sr: int
) -> np.ndarray:
    """One vowel nucleus: glottal source through three formant resonators, unit RMS, with its ring-out tail."""
    formants = np.array(_VOWEL_FORMANTS[rng.integers(len(_VOWEL_FORMANTS))]) * voice.formant_scale
    formants *= rng.uniform(0.93, 1.07, size=3)

    def response(freqs: np.ndarray) -> np.ndarray:
        h = np.ones_like(freqs, dtype=np.complex128)
        for centre, bandwidth in zip(formants, _FORMANT_BANDWIDTHS, strict=True):
            h = h * _resonator_response(freqs, centre, bandwidth, sr)
        return h

    source = _glottal_source(f0[0], f0[1], length, rng, sr) * _envelope(length, rng.uniform(0.3, 0.8))
    return _unit_rms(_filter_fft(source, response, sr))


def _fricative_segment(length: int, rng: np.random.Generator, sr: int) -> np.ndarray:
    """One unvoiced fricative burst: white noise band-passed around 2.5-6.5 kHz, unit RMS."""
    centre, width = rng.uniform(2500.0, 6500.0), rng.uniform(1200.0, 2500.0)

    def response(freqs: np.ndarray) -> np.ndarray:
        return np.exp(-0.5 * ((freqs - centre) / width) ** 2)

    noise = rng.standard_normal(length) * _envelope(length, 0.7)
    return _unit_rms(_filter_fft(noise, response, sr))


def _add(out: np.ndarray, start: int, segment: np.ndarray) -> None:
    """Overlap-add `segment` into `out` at `start`, truncated at the buffer end."""
    stop = min(out.size, start + segment.size)
    if stop > start:
        out[start:stop] += segment[: stop - start]


def _render_word(out, t, voice, f0_at, gain, rng, sr) -> float:
    """Render one word of 1-3 syllables starting at time t (s); returns the time where it ends."""
    for _ in range(int(rng.integers(1, 4))):
        syllable_gain = gain * 10.0 ** (rng.uniform(-6.0, 0.0) / 20.0)
        if rng.random() < 0.35:
            dur = rng.uniform(0.04, 0.09)
            _add(out, int(t * sr), 0.25 * syllable_gain * _fricative_segment(int(dur * sr), rng, sr))
            t += dur * 0.8
        dur = rng.uniform(0.10, 0.22)
        accent = rng.uniform(0.95, 1.12)
        f0 = (f0_at(t) * accent, f0_at(t + dur) * rng.uniform(0.92, 1.02))
        _add(out, int(t * sr), syllable_gain * _voiced_segment(int(dur * sr), f0, voice, rng, sr))
        t += dur + rng.uniform(0.0, 0.05)
    return t


def synth_speech(seconds: float, seed: int, sample_rate: int = SAMPLE_RATE) -> np.ndarray:
    """Deterministic speech-like mono audio (float32, peak 0.55-0.75) so demos and training need no recordings."""
    n = int(round(seconds * sample_rate))
    if n <= 0:
        raise ValueError(f"synth_speech needs a positive duration, got {seconds} s")
    rng = np.random.default_rng(seed)
    sr = sample_rate
    voice = _Voice(f0=float(rng.uniform(95.0, 210.0)), formant_scale=float(rng.uniform(0.95, 1.15)))
    out = np.zeros(n + _FILTER_TAIL)
    t = float(rng.uniform(0.02, 0.12)) * min(1.0, seconds)
    while t < seconds:
        n_words, phrase_start = int(rng.integers(2, 6)), t
        phrase_len = max(n_words * 0.45, 0.5)
        f0_hi, f0_lo = voice.f0 * rng.uniform(1.05, 1.2), voice.f0 * rng.uniform(0.8, 0.95)

        def f0_at(time: float, _s=phrase_start, _l=phrase_len, _h=f0_hi, _o=f0_lo) -> float:
            return float(np.clip(_h + (_o - _h) * (time - _s) / _l, 90.0, 250.0))

        phrase_gain = 10.0 ** (rng.uniform(-6.0, 0.0) / 20.0)
        for _ in range(n_words):
            word_gain = phrase_gain * 10.0 ** (rng.uniform(-10.0, 0.0) / 20.0)
            t = _render_word(out, t, voice, f0_at, word_gain, rng, sr) + rng.uniform(0.05, 0.2)
            if t >= seconds:
                break
        t += rng.uniform(0.25, 0.6)
    audio = out[:n]
    peak = float(np.max(np.abs(audio)))
    if peak > 0:
        audio = audio * (rng.uniform(0.55, 0.75) / peak)
    audio = audio + 2e-4 * rng.standard_normal(n)  # faint noise floor, as a real recording has
    return audio.astype(np.float32)


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


