"""Audio input: any array layout/dtype/rate or any ffmpeg-readable file -> mono float32 at 16 kHz.

Decoding files goes through the ffmpeg binary that imageio-ffmpeg ships (no system ffmpeg needed);
resampling arrays uses scipy's polyphase filter.
"""

from __future__ import annotations

import os
import subprocess
import wave
from fractions import Fraction
from pathlib import Path

import numpy as np

from .errors import AudioError

TARGET_SAMPLE_RATE = 16000
MAX_CHANNELS = 16


def _to_float(samples: np.ndarray) -> np.ndarray:
    """Integer PCM -> [-1, 1) float32; float input kept (as float32)."""
    if samples.dtype.kind == "f":
        return samples.astype(np.float32, copy=False)
    if samples.dtype.kind in "iu":
        info = np.iinfo(samples.dtype)
        scale = float(2 ** (info.bits - 1))
        centred = samples.astype(np.float64) - (scale if samples.dtype.kind == "u" else 0.0)
        return (centred / scale).astype(np.float32)
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
        return samples.mean(axis=1)
    if samples.shape[0] <= MAX_CHANNELS:
        return samples.mean(axis=0)
    raise AudioError(f"cannot tell channels from samples in audio of shape {samples.shape}")


def resample(samples: np.ndarray, source_rate: int, target_rate: int = TARGET_SAMPLE_RATE) -> np.ndarray:
    """Band-limited polyphase resampling (scipy) from source_rate to target_rate."""
    if source_rate == target_rate:
        return samples
    from scipy.signal import resample_poly

    ratio = Fraction(int(target_rate), int(source_rate))
    return resample_poly(samples, ratio.numerator, ratio.denominator).astype(np.float32)


def prepare_audio(samples: np.ndarray, sample_rate: int, target_rate: int = TARGET_SAMPLE_RATE) -> np.ndarray:
    """Any in-memory audio -> mono float32 at target_rate; AudioError naming what is wrong with it."""
    samples = np.asarray(samples)
    if int(sample_rate) != sample_rate or sample_rate < 1000 or sample_rate > 384000:
        raise AudioError(f"sample rate must be an integer in 1000..384000 Hz, got {sample_rate!r}")
    mono = _to_mono(_to_float(samples))
    if mono.size == 0:
        raise AudioError("audio is empty (0 samples)")
    bad = ~np.isfinite(mono)
    if bad.any():
        raise AudioError(f"audio has {int(bad.sum())} non-finite (NaN/Inf) samples; first at index "
                         f"{int(np.argmax(bad))}")
    return np.ascontiguousarray(resample(mono, int(sample_rate), target_rate), dtype=np.float32)


def pad_to_frames(audio: np.ndarray, samples_per_frame: int) -> np.ndarray:
    """Zero-pad mono audio to a whole number of video frames (frame t covers samples [spf*t, spf*(t+1)))."""
    frames = -(-audio.shape[0] // samples_per_frame)
    padded = np.zeros(frames * samples_per_frame, dtype=np.float32)
    padded[: audio.shape[0]] = audio
    return padded


def _ffmpeg_exe() -> str:
    import imageio_ffmpeg

    return imageio_ffmpeg.get_ffmpeg_exe()


def load_audio(path: str | os.PathLike, target_rate: int = TARGET_SAMPLE_RATE) -> np.ndarray:
    """Decode any ffmpeg-readable file (wav, mp3, m4a, a video's audio track...) to mono float32."""
    path = Path(path)
    if not path.is_file():
        raise AudioError(f"audio file {path} does not exist")
    cmd = [_ffmpeg_exe(), "-nostdin", "-v", "error", "-i", str(path), "-vn", "-ac", "1", "-ar",
           str(target_rate), "-f", "f32le", "-"]
    result = subprocess.run(cmd, capture_output=True, check=False)
    if result.returncode != 0:
        message = result.stderr.decode("utf-8", "replace").strip().splitlines()
        raise AudioError(f"cannot decode audio file {path}: {message[-1] if message else 'ffmpeg failed'}")
    samples = np.frombuffer(result.stdout, dtype="<f4").astype(np.float32)
    if samples.size == 0:
        raise AudioError(f"audio file {path} holds no audio samples")
    return prepare_audio(samples, target_rate, target_rate)


def write_wav(path: str | os.PathLike, samples: np.ndarray, sample_rate: int = TARGET_SAMPLE_RATE) -> None:
    """Write mono float audio as 16-bit PCM WAV (stdlib `wave`)."""
    pcm = np.clip(np.asarray(samples, dtype=np.float64), -1.0, 1.0 - 1.0 / 32768) * 32768.0
    with wave.open(str(path), "wb") as handle:
        handle.setnchannels(1)
        handle.setsampwidth(2)
        handle.setframerate(int(sample_rate))
        handle.writeframes(np.round(pcm).astype("<i2").tobytes())
