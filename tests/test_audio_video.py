"""Audio input conversions and the mp4 writer (frame count, audio stream, atomic output)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from gaussiantalker.sdk.audio import load_audio, prepare_audio, resampled_length, write_wav
from gaussiantalker.sdk.errors import AudioError
from gaussiantalker.sdk.video import VideoWriter, probe_video


def _tone(seconds=0.5, rate=16000, freq=220.0, amplitude=0.4):
    t = np.arange(int(seconds * rate)) / rate
    return (amplitude * np.sin(2 * np.pi * freq * t)).astype(np.float32)


@pytest.mark.parametrize("dtype, scale", [(np.int16, 32767), (np.int32, 2**31 - 1), (np.float64, 1.0)])
def test_integer_and_float_layouts(dtype, scale):
    tone = _tone()
    out = prepare_audio((tone * scale).astype(dtype), 16000)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, tone, atol=1e-4)


@pytest.mark.parametrize("rate", [8000, 22050, 44100, 48000])
def test_resampled_to_16k(rate):
    out = prepare_audio(_tone(1.0, rate), rate)
    assert out.shape == (16000,) and out.dtype == np.float32


@pytest.mark.parametrize("samples, source, target, expected", [
    (88200, 44100, 16000, 32000), (44101, 44100, 16000, 16000), (1, 44100, 16000, 1),  # < half a sample: 1, not 0
    (3, 96000, 16000, 1),  # 0.5 exactly: Python's round gives 0, kept at 1
    (5, 32000, 16000, 2), (7, 32000, 16000, 4),  # half-way: round half to even (libsoxr alone gives 3 and 4)
    (767998, 383999, 16000, 32000), (383999, 383999, 16000, 16000), (1000, 383999, 16000, 42),
    (2000, 1000, 16000, 32000), (1, 1000, 16000, 16), (3, 1001, 16000, 48),
    (95998, 47999, 16000, 32000), (22050, 22050, 16000, 16000), (12345, 11025, 16000, 17916),
    (16000, 16000, 16000, 16000), (16000, 16000, 8000, 8000), (16001, 16000, 44100, 44103)])
def test_resampled_length_is_exact(samples, source, target, expected):
    """round(S * target / source) samples (at least one), whatever the ratio; a 16 kHz clip is passed through."""
    assert resampled_length(samples, source, target) == expected == max(1, round(samples * target / source))
    audio = np.random.default_rng(samples).uniform(-0.5, 0.5, samples).astype(np.float32)
    out = prepare_audio(audio, source, target)
    assert out.shape == (expected,) and out.dtype == np.float32 and np.isfinite(out).all()


def _peak_hz(audio, rate=16000):
    """Frequency of the strongest spectral peak (Hann window, parabolic interpolation of the log magnitude)."""
    spectrum = np.abs(np.fft.rfft(audio * np.hanning(audio.size)))
    k = int(np.argmax(spectrum[1:-1])) + 1
    a, b, c = np.log(spectrum[k - 1: k + 2] + 1e-30)
    return (k + 0.5 * (a - c) / (a - 2 * b + c)) * rate / audio.size


@pytest.mark.parametrize("rate, freq, max_error_db", [
    (383999, 1000.0, -90), (383999, 4000.0, -90), (47999, 4000.0, -90), (11025, 4000.0, -80), (1000, 300.0, -80),
    (1001, 400.0, -65), (44100, 7000.0, -55)])  # 400 Hz of 500.5 and 7 kHz of 8 kHz: near the transition band
def test_tone_survives_an_odd_rate(rate, freq, max_error_db):
    """Frequency within 0.01 Hz, level within 0.01 dB, and the waveform itself within max_error_db of the ideal sine
    on the 16 kHz grid (so no delay). The old approximate-ratio path gave -0.41 dB and a -26 dB error at 47999 Hz,
    4 kHz."""
    out = prepare_audio(_tone(2.0, rate, freq, 0.5), rate)
    ideal = _tone(2.0, 16000, freq, 0.5)[: out.size].astype(np.float64)
    inner, ideal = out[800:-800].astype(np.float64), ideal[800:-800]  # edges ring: the tone starts abruptly
    level_db = 10 * np.log10(np.mean(inner**2) / np.mean(ideal**2))
    error_db = 10 * np.log10(np.mean((inner - ideal) ** 2) / np.mean(ideal**2))
    assert abs(_peak_hz(out) - freq) < 0.01 and abs(level_db) < 0.01 and error_db < max_error_db


def test_above_the_new_nyquist_is_filtered_out():
    """A 10 kHz tone cannot exist at 16 kHz: it must not come back as a 6 kHz alias."""
    out = prepare_audio(_tone(1.0, 44100, 10000.0, 0.5), 44100)
    assert np.sqrt(np.mean(out[800:-800].astype(np.float64) ** 2)) < 1e-4 * 0.5


def test_audio_module_imports_neither_scipy_nor_torch():
    """The torch-free runtime's audio path must not pull in scipy (or torch), resampling included."""
    code = ("import sys, numpy as np\n"
            "from gaussiantalker.sdk.audio import prepare_audio\n"
            "prepare_audio(np.ones((44100, 2), np.float32), 44100)\n"
            "prepare_audio(np.ones(1000, np.int16), 383999)\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('scipy', 'torch')))\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "[]"


def test_stereo_either_layout_is_averaged():
    """Channels that differ (a 220 Hz tone and a quieter 330 Hz one): only their mean passes, not either one."""
    left, right = _tone(), _tone(freq=330.0, amplitude=0.2)
    mean = 0.5 * (left + right)
    for stereo in (np.stack([left, right], axis=1), np.stack([left, right], axis=0)):  # [S, 2] and [2, S]
        out = prepare_audio(stereo, 16000)
        np.testing.assert_allclose(out, mean, atol=1e-6)
        assert np.abs(out - left).max() > 0.1 and np.abs(out - right).max() > 0.1
    resampled = prepare_audio(np.stack([left, right], axis=1), 16000, 8000)  # averaged, then resampled
    np.testing.assert_allclose(resampled, prepare_audio(mean, 16000, 8000), atol=1e-6)


def test_bad_audio_is_named():
    with pytest.raises(AudioError, match="empty"):
        prepare_audio(np.zeros(0, np.float32), 16000)
    bad = _tone()
    bad[10] = np.nan
    with pytest.raises(AudioError, match="non-finite .* index 10"):
        prepare_audio(bad, 16000)
    with pytest.raises(AudioError, match="sample rate"):
        prepare_audio(_tone(), 0)
    with pytest.raises(AudioError, match="1-D or 2-D"):
        prepare_audio(np.zeros((2, 2, 2)), 16000)


def test_file_round_trip_and_unreadable_file(tmp_path):
    tone = _tone()
    write_wav(tmp_path / "a.wav", tone)
    np.testing.assert_allclose(load_audio(tmp_path / "a.wav"), tone, atol=1e-3)
    (tmp_path / "junk.mp3").write_bytes(b"not audio at all" * 10)
    with pytest.raises(AudioError, match="cannot decode"):
        load_audio(tmp_path / "junk.mp3")
    with pytest.raises(AudioError, match="does not exist"):
        load_audio(tmp_path / "missing.wav")


def test_video_has_frames_and_audio(tmp_path):
    with VideoWriter(tmp_path / "v.mp4", 25, (32, 24), audio=_tone(1.0)) as out:
        for i in range(25):
            out.write(np.full((24, 32, 3), i * 9, np.uint8))
    info = probe_video(tmp_path / "v.mp4")
    assert info["frames"] == 25 and info["has_audio"]


def test_failed_video_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError, match="boom"), VideoWriter(tmp_path / "v.mp4", 25, (32, 24)) as out:
        out.write(np.zeros((24, 32, 3), np.uint8))
        raise RuntimeError("boom")
    assert not (tmp_path / "v.mp4").exists()
