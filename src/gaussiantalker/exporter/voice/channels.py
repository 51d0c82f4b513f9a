"""The channel a real call puts between a voice and the driver, as training augmentations (docs/voice.md,
"Augmentation"): a telephone line (G.711 mu-law at 8 kHz, 300-3400 Hz), an Opus voice codec at a low bit rate
(PyAV's libopus, as WebRTC carries it), a band-limited microphone or headset, and speed perturbation (tempo and
pitch together, the phoneme timings scaled with it).

Each takes and returns float32 mono at SAMPLE_RATE with the same number of samples and no delay (tested: the
cross-correlation with the input peaks at lag 0), so a crop's targets stay aligned with its audio.
"""

from __future__ import annotations

import io

import av
import numpy as np

from gaussiantalker.sdk.audio import resample

SAMPLE_RATE = 16000
TELEPHONE_RATE, TELEPHONE_BAND_HZ = 8000, (300.0, 3400.0)
MU = 255.0
OPUS_RATE = 48000  # libopus's native rate


def _same_length(y: np.ndarray, n: int) -> np.ndarray:
    return np.pad(y, (0, max(0, n - y.size)))[:n].astype(np.float32)


def band_pass(x: np.ndarray, low_hz: float, high_hz: float, rate: int = SAMPLE_RATE) -> np.ndarray:
    """Zero-phase band-pass by FFT mask with 100 Hz cosine edges (no delay, unlike a causal filter)."""
    n = x.size
    size = 1 << int(np.ceil(np.log2(max(n, 2))))
    spectrum = np.fft.rfft(x.astype(np.float64), size)
    hz = np.fft.rfftfreq(size, 1.0 / rate)
    edge = 100.0
    gain = np.clip((hz - (low_hz - edge)) / edge, 0.0, 1.0) * np.clip(((high_hz + edge) - hz) / edge, 0.0, 1.0)
    gain = 0.5 - 0.5 * np.cos(np.pi * gain)
    return np.fft.irfft(spectrum * gain, size)[:n].astype(np.float32)


def mu_law(x: np.ndarray) -> np.ndarray:
    """G.711-style 8-bit mu-law companding and back (the quantisation noise a phone line adds)."""
    x = np.clip(x.astype(np.float64), -1.0, 1.0)
    code = np.round(np.sign(x) * np.log1p(MU * np.abs(x)) / np.log1p(MU) * 127.0) / 127.0
    return (np.sign(code) * np.expm1(np.abs(code) * np.log1p(MU)) / MU).astype(np.float32)


def telephone(x: np.ndarray) -> np.ndarray:
    """A narrow-band phone call: 300-3400 Hz, 8 kHz, mu-law, back at SAMPLE_RATE."""
    narrow = resample(band_pass(x, *TELEPHONE_BAND_HZ), SAMPLE_RATE, TELEPHONE_RATE)
    return _same_length(resample(mu_law(narrow), TELEPHONE_RATE, SAMPLE_RATE), x.size)


def opus(x: np.ndarray, kbps: float) -> np.ndarray:
    """Encoded with libopus at `kbps` (VoIP application default) in Ogg and decoded again; Ogg's pre-skip removes
    the codec's delay."""
    buffer = io.BytesIO()
    with av.open(buffer, "w", format="ogg") as container:
        stream = container.add_stream("libopus", rate=OPUS_RATE)
        stream.bit_rate = int(kbps * 1000)
        stream.layout = "mono"
        frame = av.AudioFrame.from_ndarray(np.ascontiguousarray(x, np.float32)[None], format="flt", layout="mono")
        frame.sample_rate = SAMPLE_RATE
        to_codec = av.AudioResampler(format="s16", layout="mono", rate=OPUS_RATE)
        for piece in to_codec.resample(frame) + to_codec.resample(None):
            container.mux(stream.encode(piece))
        container.mux(stream.encode(None))
    buffer.seek(0)
    decoded = []
    with av.open(buffer) as container:
        back = av.AudioResampler(format="flt", layout="mono", rate=SAMPLE_RATE)
        for frame in container.decode(audio=0):
            decoded += [piece.to_ndarray()[0] for piece in back.resample(frame)]
        decoded += [piece.to_ndarray()[0] for piece in back.resample(None)]
    return _same_length(np.concatenate(decoded) if decoded else np.zeros(0, np.float32), x.size)


def low_pass(x: np.ndarray, cutoff_hz: float) -> np.ndarray:
    """A band-limited microphone or headset (no delay)."""
    return band_pass(x, 0.0, cutoff_hz)


def speed(x: np.ndarray, factor: float) -> np.ndarray:
    """The audio played `factor` times faster (tempo and pitch together): round(x.size / factor) samples."""
    return _same_length(resample(x, int(round(SAMPLE_RATE * factor)), SAMPLE_RATE),
                        int(round(x.size / factor)))


__all__ = ["band_pass", "low_pass", "mu_law", "opus", "speed", "telephone"]
