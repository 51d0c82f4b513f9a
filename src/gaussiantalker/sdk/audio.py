"""Audio input: any array layout/dtype/rate or any ffmpeg-readable file -> mono float32 at 16 kHz.

Decoding files goes through the ffmpeg binary that imageio-ffmpeg ships (no system ffmpeg needed), into a
temporary file read back in one allocation, so a long file costs its decoded size (64 kB per second at 16 kHz)
and no more; ffmpeg also resamples what it decodes. In-memory arrays at another rate are resampled here, after
the channels are averaged, by libsoxr (python-soxr). A library rather than our own filter: any rate in
1000..384000 Hz must work, and a rational polyphase filter sized for the exact ratio blows up at odd rates
(16000/383999 would need a 7.7 M-tap filter). libsoxr handles any ratio exactly, band-limited, in bounded memory
(it streams the input in blocks into one output allocation), and fast (docs/embedding.md, "Audio input").
"""

from __future__ import annotations

import os
import subprocess
import tempfile
import wave
from pathlib import Path

import numpy as np
import soxr

from .config import DEFAULT_SAMPLE_RATE
from .errors import AudioError

TARGET_SAMPLE_RATE = DEFAULT_SAMPLE_RATE
MAX_CHANNELS = 16
MIN_SAMPLE_RATE, MAX_SAMPLE_RATE = 1000, 384000
# Largest |sample| accepted for float audio. Full scale is 1.0; floats holding PCM values by mistake (up to int32
# full scale) still work because the translator normalises each window. Beyond this a sample is not audio, and
# the translator's float32 variance (sum of squares) would overflow (at ~1.8e19) and give NaN.
MAX_SAMPLE_MAGNITUDE = 2.0**31
SMALL_CHUNK_SAMPLES = 1 << 16  # as_mono checks a float32 chunk up to this size in one pass with a temporary copy
# libsoxr quality preset, chosen by measurement (tests/test_stability_audio.py records the tone rows): "HQ" keeps
# tones' frequency and level far beyond what speech features need and suppresses aliases; "VHQ" costs more time for
# precision float32 features cannot use; "MQ"/"LQ" droop near the passband edge; "QQ" filters no aliases at all.
# The figures: docs/embedding.md, "Audio input".
RESAMPLE_QUALITY = "HQ"


def _check_rate(sample_rate) -> int:
    """The sample rate as an int, or AudioError naming the accepted range."""
    try:
        as_float = float(sample_rate)
        ok = not isinstance(sample_rate, bool) and np.isfinite(as_float) and as_float == int(as_float)
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok or not MIN_SAMPLE_RATE <= as_float <= MAX_SAMPLE_RATE:
        raise AudioError(f"sample rate must be an integer in {MIN_SAMPLE_RATE}..{MAX_SAMPLE_RATE} Hz, "
                         f"got {sample_rate!r}")
    return int(as_float)


def _check_float_values(samples: np.ndarray) -> None:
    """AudioError for NaN/Inf or out-of-range float samples (checked before any cast, without big temporaries)."""
    if samples.size == 0:
        return
    lo, hi = samples.min(), samples.max()
    if not (np.isfinite(lo) and np.isfinite(hi)):
        bad = ~np.isfinite(samples)
        first = np.unravel_index(int(np.argmax(bad)), samples.shape)
        where = int(first[0]) if samples.ndim == 1 else tuple(int(i) for i in first)
        raise AudioError(f"audio has {int(bad.sum())} non-finite (NaN/Inf) samples; first at index {where}")
    peak = max(abs(float(lo)), abs(float(hi)))
    if peak > MAX_SAMPLE_MAGNITUDE:
        raise AudioError(f"audio samples reach {peak:.3g}; float audio must stay within ±{MAX_SAMPLE_MAGNITUDE:.0f} "
                         f"(full scale is ±1)")


def _to_float(samples: np.ndarray) -> np.ndarray:
    """Integer PCM -> [-1, 1) float32; float input checked and kept (as float32)."""
    if samples.dtype.kind == "f":
        _check_float_values(samples)
        return samples.astype(np.float32, copy=False)
    if samples.dtype.kind in "iu":
        info = np.iinfo(samples.dtype)
        scale = float(2 ** (info.bits - 1))
        out = samples.astype(np.float32)
        if samples.dtype.kind == "u":
            out -= np.float32(scale)
        out *= np.float32(1.0 / scale)
        return out
    if samples.dtype == np.bool_:
        raise AudioError("audio must be numeric samples, got a boolean array")
    raise AudioError(f"audio dtype {samples.dtype} is not supported (use int16/int32/float32/float64)")


def _to_mono(samples: np.ndarray) -> np.ndarray:
    """[S], [S, C] or [C, S] (C <= MAX_CHANNELS) -> [S] by averaging channels."""
    if samples.ndim == 1:
        return samples
    if samples.ndim != 2:
        raise AudioError(f"audio must be 1-D or 2-D (samples x channels), got shape {samples.shape}")
    if samples.shape[1] <= MAX_CHANNELS and samples.shape[1] <= samples.shape[0]:
        return samples.mean(axis=1, dtype=np.float32)
    if samples.shape[0] <= MAX_CHANNELS:
        return samples.mean(axis=0, dtype=np.float32)
    raise AudioError(f"cannot tell channels from samples in audio of shape {samples.shape} "
                     f"(at most {MAX_CHANNELS} channels)")


def resampled_length(samples: int, source_rate: int, target_rate: int = TARGET_SAMPLE_RATE) -> int:
    """Output length of `resample`: round(S * target / source), at least 1 sample for non-empty audio."""
    if samples == 0:
        return 0
    return max(1, round(samples * int(target_rate) / int(source_rate)))


def resample(samples: np.ndarray, source_rate: int, target_rate: int = TARGET_SAMPLE_RATE) -> np.ndarray:
    """Band-limited resampling (libsoxr, RESAMPLE_QUALITY) of mono float audio to `resampled_length` samples.

    libsoxr compensates its filter's delay (output sample n lies at time n / target: nothing to trim at the start)
    and returns floor(S * target / source + 0.5) samples. That is this length except (a) when S * target / source
    is exactly half-way, where Python's round goes to even: one sample fewer, trimmed; and (b) when the whole clip
    is shorter than half an output sample: libsoxr returns none, and one zero sample is given so that a non-empty
    clip never becomes empty. Memory: the output plus libsoxr's block buffers (it takes the input in blocks of ~3
    output seconds); the input is not copied when it is already contiguous float32.
    """
    if source_rate == target_rate or samples.size == 0:
        return samples
    length = resampled_length(samples.shape[0], source_rate, target_rate)
    mono = np.ascontiguousarray(samples, dtype=np.float32)
    out = soxr.resample(mono, int(source_rate), int(target_rate), quality=RESAMPLE_QUALITY)
    if out.shape[0] >= length:
        return out[:length]
    padded = np.zeros(length, np.float32)  # case (b) only: at most one sample is missing
    padded[: out.shape[0]] = out
    return padded


def as_mono(samples, sample_rate) -> tuple[np.ndarray, int]:
    """Any in-memory audio (int PCM or float; [S], [S, C] or [C, S]) -> (mono float32 [S], its checked rate), not
    resampled; empty stays empty. AudioError naming what is wrong with it."""
    if type(sample_rate) is int and MIN_SAMPLE_RATE <= sample_rate <= MAX_SAMPLE_RATE and \
            isinstance(samples, np.ndarray) and samples.dtype == np.float32 and samples.ndim == 1 and \
            samples.size <= SMALL_CHUNK_SAMPLES and samples.flags.c_contiguous and \
            bool(np.maximum.reduce(np.abs(samples), initial=0.0) <= MAX_SAMPLE_MAGNITUDE):
        # A live voice's chunk (mono float32, 50 a second a session): one pass checks it (NaN compares False);
        # its temporary is small, which a long clip's would not be.
        return samples, sample_rate
    rate = _check_rate(sample_rate)
    try:
        samples = np.asarray(samples)
    except (TypeError, ValueError) as exc:
        raise AudioError(f"audio is not a numeric array: {exc}") from exc
    if samples.size == 0:
        return np.zeros(0, np.float32), rate
    return np.ascontiguousarray(_to_mono(_to_float(samples)), dtype=np.float32), rate


def prepare_audio(samples: np.ndarray, sample_rate: int, target_rate: int = TARGET_SAMPLE_RATE) -> np.ndarray:
    """Any in-memory audio -> mono float32 at target_rate; AudioError naming what is wrong with it."""
    mono, rate = as_mono(samples, sample_rate)
    if mono.size == 0:
        raise AudioError("audio is empty (0 samples)")
    return np.ascontiguousarray(resample(mono, rate, target_rate), dtype=np.float32)


def pad_to_frames(audio: np.ndarray, samples_per_frame: int) -> np.ndarray:
    """Zero-pad mono audio to a whole number of video frames (frame t covers samples [spf*t, spf*(t+1)))."""
    frames = -(-audio.shape[0] // samples_per_frame)
    padded = np.zeros(frames * samples_per_frame, dtype=np.float32)
    padded[: audio.shape[0]] = audio
    return padded


def _ffmpeg_exe() -> str:
    import imageio_ffmpeg

    return imageio_ffmpeg.get_ffmpeg_exe()


def _ffmpeg_problem(path: Path, stderr: bytes) -> str:
    """ffmpeg's last error line, rephrased where it is cryptic (a file without an audio stream)."""
    lines = stderr.decode("utf-8", "replace").strip().splitlines()
    text = " ".join(lines)
    if "matches no streams" in text or "does not contain any stream" in text:
        return f"audio file {path} has no audio stream"
    return f"cannot decode audio file {path}: {lines[-1] if lines else 'ffmpeg failed'}"


def load_audio(path: str | os.PathLike, target_rate: int = TARGET_SAMPLE_RATE) -> np.ndarray:
    """Decode any ffmpeg-readable file (wav, mp3, m4a, a video's audio track...) to mono float32."""
    path = Path(path)
    if not path.exists():
        raise AudioError(f"audio file {path} does not exist")
    if not path.is_file():
        raise AudioError(f"audio file {path} is not a file")
    rate = _check_rate(target_rate)
    with tempfile.TemporaryDirectory(prefix="gt-audio-") as tmp:
        raw = Path(tmp) / "audio.f32"
        cmd = [_ffmpeg_exe(), "-nostdin", "-v", "error", "-i", str(path), "-map", "0:a:0", "-ac", "1", "-ar",
               str(rate), "-f", "f32le", "-y", str(raw)]
        result = subprocess.run(cmd, capture_output=True, check=False)
        if result.returncode != 0:
            raise AudioError(_ffmpeg_problem(path, result.stderr))
        samples = np.fromfile(raw, dtype="<f4") if raw.exists() else np.zeros(0, np.float32)
    if samples.size == 0:
        raise AudioError(f"audio file {path} holds no audio samples")
    try:
        return prepare_audio(samples, rate, rate)
    except AudioError as exc:
        raise AudioError(f"audio file {path}: {exc}") from None


def to_pcm16(samples: np.ndarray) -> np.ndarray:
    """Float audio in [-1, 1] as int16 PCM: x * 32768 rounded, clipped to int16 (int16 samples / 32768 come back
    exactly), what a live transport sends."""
    scaled = np.multiply(np.asarray(samples, np.float32), np.float32(32768.0))
    np.rint(scaled, out=scaled)  # ufuncs in place: np.clip and np.round cost twice as much on a frame's samples
    np.minimum(scaled, np.float32(32767.0), out=scaled)
    np.maximum(scaled, np.float32(-32768.0), out=scaled)
    return scaled.astype(np.int16)


def write_wav(path: str | os.PathLike, samples: np.ndarray, sample_rate: int = TARGET_SAMPLE_RATE) -> None:
    """Write mono float audio as 16-bit PCM WAV (stdlib `wave`)."""
    pcm = np.clip(np.asarray(samples, dtype=np.float64), -1.0, 1.0 - 1.0 / 32768) * 32768.0
    with wave.open(str(path), "wb") as handle:
        handle.setnchannels(1)
        handle.setsampwidth(2)
        handle.setframerate(int(sample_rate))
        handle.writeframes(np.round(pcm).astype("<i2").tobytes())
