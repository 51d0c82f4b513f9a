"""Audio input conversions and the mp4 writer (frame count, audio stream, atomic output)."""

from __future__ import annotations

import numpy as np
import pytest

from gaussiantalker.sdk.audio import load_audio, prepare_audio, write_wav
from gaussiantalker.sdk.errors import AudioError
from gaussiantalker.sdk.video import VideoWriter, probe_video


def _tone(seconds=0.5, rate=16000):
    t = np.arange(int(seconds * rate)) / rate
    return (0.4 * np.sin(2 * np.pi * 220 * t)).astype(np.float32)


@pytest.mark.parametrize("dtype, scale", [(np.int16, 32767), (np.int32, 2**31 - 1), (np.float64, 1.0)])
def test_integer_and_float_layouts(dtype, scale):
    tone = _tone()
    out = prepare_audio((tone * scale).astype(dtype), 16000)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, tone, atol=1e-4)


@pytest.mark.parametrize("rate", [8000, 22050, 44100, 48000])
def test_resampled_to_16k(rate):
    out = prepare_audio(_tone(1.0, rate), rate)
    assert abs(out.shape[0] - 16000) <= 1


def test_stereo_either_layout_is_averaged():
    tone = _tone()
    stereo = np.stack([tone, -tone * 0 + tone], axis=1)
    np.testing.assert_allclose(prepare_audio(stereo, 16000), tone, atol=1e-6)
    np.testing.assert_allclose(prepare_audio(stereo.T, 16000), tone, atol=1e-6)


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
