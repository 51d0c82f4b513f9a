"""Deterministic speech-like synthetic audio: the test signal export measures on and verify drives clips with.

numpy only (no torch), so samples and the runtime side can make the same clip. The audio is a crude
source-filter model of speech: syllables of a glottal-pulse source (f0 with declination and jitter) shaped by
vowel formant resonances, fricative noise bursts, word and phrase pauses, and varying loudness. It is not
intelligible; it only needs the rhythm and loudness structure that drives a talking head's jaw.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gaussiantalker.sdk.config import DEFAULT_SAMPLE_RATE

__all__ = ["SAMPLE_RATE", "VOWELS", "synth_speech", "synth_vowels"]

SAMPLE_RATE = DEFAULT_SAMPLE_RATE

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
VOWELS = ("a", "i", "e", "ae", "u", "o", "schwa", "er")  # names of _VOWEL_FORMANTS' rows
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
    length: int, f0: tuple[float, float], voice: _Voice, rng: np.random.Generator, sr: int, vowel: int | None = None
) -> np.ndarray:
    """One vowel nucleus (a random one, or VOWELS[vowel]): glottal source through three formant resonators, unit
    RMS, with its ring-out tail."""
    index = rng.integers(len(_VOWEL_FORMANTS)) if vowel is None else vowel
    formants = np.array(_VOWEL_FORMANTS[index]) * voice.formant_scale
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


def synth_vowels(
    layout: list[tuple[str | None, float]], seed: int = 0, sample_rate: int = SAMPLE_RATE
) -> np.ndarray:
    """Audio of known vowels: `layout` is (vowel name from VOWELS, or None for silence, seconds) in order; each
    vowel is one voiced nucleus at a fixed pitch. Same scale and noise floor as synth_speech (for tests whose
    expected behaviour depends on the vowel or on where the pauses are)."""
    rng = np.random.default_rng(seed)
    sr = sample_rate
    voice = _Voice(f0=120.0, formant_scale=1.0)
    n = int(round(sum(seconds for _, seconds in layout) * sr))
    if n <= 0:
        raise ValueError("synth_vowels needs a layout of positive total duration")
    out = np.zeros(n + _FILTER_TAIL)
    start = 0.0
    for name, seconds in layout:
        if name is not None:
            if name not in VOWELS:
                raise ValueError(f"unknown vowel {name!r}; expected one of {VOWELS}")
            segment = _voiced_segment(int(seconds * sr), (120.0, 112.0), voice, rng, sr, VOWELS.index(name))
            _add(out, int(start * sr), segment)
        start += seconds
    audio, peak = out[:n], float(np.max(np.abs(out[:n])))
    audio = (audio * (0.65 / peak) if peak > 0 else audio) + 2e-4 * rng.standard_normal(n)
    return audio.astype(np.float32)
