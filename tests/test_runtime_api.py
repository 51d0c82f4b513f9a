"""The embedding API of the torch-free runtime: few lines in, frames out; bad input named."""

from __future__ import annotations

import types

import numpy as np
import pytest

from gaussiantalker.exporter.export.speech import synth_speech
from gaussiantalker.runtime import TalkingHead
from gaussiantalker.sdk.camera import Camera
from gaussiantalker.sdk.drive import HeadPose
from gaussiantalker.sdk.errors import AudioError, BundleError, DriveError


@pytest.fixture(scope="module")
def bundle(small_export):
    """The small speaker's bundle (the API does not depend on the speaker)."""
    return small_export.path


@pytest.fixture(scope="module")
def head(bundle):
    with TalkingHead(bundle, resolution=(64, 48)) as talking_head:
        yield talking_head


def test_frames_stream_from_audio_array(head):
    audio = synth_speech(0.5, seed=2)  # 8000 samples -> 12.5 frames -> 13 (last one zero-padded)
    frames = head.frames(audio, sample_rate=16000)
    assert isinstance(frames, types.GeneratorType)
    frames = list(frames)
    assert len(frames) == head.driver.frame_count(audio.shape[0]) == 13
    assert all(f.shape == (48, 64, 3) and f.dtype == np.uint8 for f in frames)


def test_other_sample_rates_are_resampled(head):
    audio = synth_speech(0.4, seed=2, sample_rate=44100)
    frames = list(head.frames(audio, sample_rate=44100))
    assert len(frames) == 10


def test_render_explicit_flame_parameters_and_head_pose(head):
    neutral = head.render_params(output="float")
    open_jaw = head.render_params(jaw_pose=[0.3, 0, 0], output="float")
    turned = head.render_params(head_rotation=[0, 0.4, 0], output="float")
    assert np.isfinite(neutral).all() and neutral.dtype == np.float32
    assert np.abs(open_jaw - neutral).max() > 0.1
    assert np.abs(turned - neutral).max() > 0.1


def test_app_supplied_head_pose(head):
    audio = synth_speech(0.2, seed=4)
    fixed = list(head.frames(audio, 16000, head_pose=HeadPose.make([0, 0.3, 0])))
    per_frame = list(head.frames(audio, 16000, head_pose=lambda i: HeadPose.make([0, 0.3, 0])))
    track = list(head.frames(audio, 16000, head_pose=np.tile([0, 0.3, 0, 0, 0, 0], (3, 1))))
    for a, b, c in zip(fixed, per_frame, track, strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)


def test_camera_background_and_resolution_are_settable(bundle):
    with TalkingHead(bundle, resolution=(40, 40), background=(0, 0, 0)) as dark:
        corner = dark.render_params()[0, 0]
        assert corner.tolist() == [0, 0, 0]
        dark.camera = Camera.looking_at([0.5, 0, 0.7], [0, 0, 0], [0, 1, 0], 30, 20, 30.0)
        assert dark.render_params().shape == (20, 30, 3)


def test_bad_drive_and_audio_are_named(head):
    with pytest.raises(DriveError, match="expression must have shape \\(20,\\)"):
        head.render_params(expression=np.zeros(7))
    with pytest.raises(DriveError, match="jaw pose has non-finite"):
        head.render_params(jaw_pose=[np.nan, 0, 0])
    with pytest.raises(AudioError, match="needs its sample_rate"):
        list(head.frames(np.zeros(640, np.float32)))
    with pytest.raises(AudioError, match="empty"):
        list(head.frames(np.zeros(0, np.float32), 16000))


def test_bad_bundle_is_named(tmp_path):
    with pytest.raises(BundleError, match="does not exist"):
        TalkingHead(tmp_path / "nope.gtb")
    (tmp_path / "bad.gtb").write_bytes(b"hello world, not a bundle" * 4)
    with pytest.raises(BundleError, match="bad magic"):
        TalkingHead(tmp_path / "bad.gtb")
