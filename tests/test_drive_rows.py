"""The live path's one-pass checks (sdk/drive.py `blendshape_drive_of`, `frame_drive_of`, `PoseTrack`; sdk/audio.py
`as_mono`'s chunk path, `to_pcm16`): each gives what the field-by-field path gives, and refuses what it refuses
with the same named error, so making a drive per session and frame cheaper loses no check."""

from __future__ import annotations

import numpy as np
import pytest

from gaussiantalker.sdk.audio import as_mono, to_pcm16
from gaussiantalker.sdk.drive import (
    MAX_DRIVE_MAGNITUDE,
    BlendshapeDrive,
    FrameDrive,
    HeadPose,
    PoseTrack,
    blendshape_drive_of,
    frame_drive_of,
    pose_track_frame,
)
from gaussiantalker.sdk.errors import AudioError, DriveError

RNG = np.random.default_rng(7)
POSE = HeadPose.make(np.array([0.1, -0.2, 0.05]), np.array([0.0, 0.01, -0.02]))
BAD_VALUES = [np.nan, np.inf, -np.inf, 2 * MAX_DRIVE_MAGNITUDE]


def _same(a, b, fields: tuple[str, ...]) -> None:
    assert type(a) is type(b)
    for name in fields:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype == np.float32 and x.shape == y.shape and np.array_equal(x, y), name


def test_blendshape_row_gives_what_make_gives():
    row = RNG.random(52).astype(np.float32)
    fast = blendshape_drive_of(row, POSE)
    _same(fast, BlendshapeDrive.make(row, POSE), ("blendshapes", "head_rotation", "head_translation"))
    row[0] = 5.0  # the drive holds its own copy of the row
    assert fast.blendshapes[0] != 5.0
    # anything but a float32 [52] row goes the long way, with its errors
    _same(blendshape_drive_of(row.astype(np.float64), POSE), BlendshapeDrive.make(row.astype(np.float64), POSE),
          ("blendshapes",))
    with pytest.raises(DriveError, match="blendshapes must have shape"):
        blendshape_drive_of(row[:51], POSE)


@pytest.mark.parametrize("bad", BAD_VALUES)
def test_a_bad_blendshape_row_is_named(bad):
    row = RNG.random(52).astype(np.float32)
    row[17] = bad
    with pytest.raises(DriveError, match=r"blendshapes (has non-finite values|exceeds the supported magnitude)"):
        blendshape_drive_of(row, POSE)


def test_flame_row_gives_what_make_gives():
    n_expr = 10
    params = (RNG.standard_normal(n_expr + 3) * 0.3).astype(np.float32)
    fast = frame_drive_of(n_expr, params, POSE)
    slow = FrameDrive.make(n_expr, params[:n_expr], params[n_expr:], head_pose=POSE)
    _same(fast, slow, ("expression", "flame_pose", "head_translation"))
    params[0] = 9.0
    assert fast.expression[0] != 9.0


@pytest.mark.parametrize("bad", BAD_VALUES)
def test_a_bad_flame_row_is_named(bad):
    params = np.zeros(13, np.float32)
    params[11] = bad  # the jaw
    with pytest.raises(DriveError, match=r"jaw pose (has non-finite values|exceeds the supported magnitude)"):
        frame_drive_of(10, params, POSE)


def test_pose_track_frames_match_and_bad_tracks_are_named():
    track = (RNG.standard_normal((7, 6)) * 0.1).astype(np.float32)
    checked = PoseTrack(track)
    for index in range(30):  # forth and back, past the end several times
        _same(checked.frame(index), pose_track_frame(track, index), ("rotation", "translation"))
    frame = checked.frame(3)
    frame.rotation[0] = 42.0  # a frame's arrays are its own
    assert checked.frame(3).rotation[0] != 42.0
    broken = track.copy()
    broken[4, 2] = np.nan
    with pytest.raises(DriveError, match="pose track has non-finite values"):
        PoseTrack(broken)
    with pytest.raises(DriveError, match=r"pose track must have shape \[T, 6\]"):
        PoseTrack(track[:, :5])


def test_a_voice_chunk_is_checked_in_one_pass():
    chunk = (RNG.standard_normal(320) * 0.3).astype(np.float32)
    mono, rate = as_mono(chunk, 16000)
    assert rate == 16000 and mono.dtype == np.float32 and np.array_equal(mono, chunk)
    for bad, message in ((np.nan, "non-finite"), (np.inf, "non-finite"), (3e9, "float audio must stay within")):
        broken = chunk.copy()
        broken[100] = bad
        with pytest.raises(AudioError, match=message):
            as_mono(broken, 16000)
    with pytest.raises(AudioError, match="sample rate must be an integer"):
        as_mono(chunk, 999)


def test_pcm16_rounds_and_clips():
    samples = np.array([0.0, 0.5, -0.5, 1.0, -1.0, 1.5, -1.5, 1 / 65536, 3 / 65536, -3 / 65536, 32767.4 / 32768],
                       np.float32)
    expected = np.clip(np.round(samples.astype(np.float64) * 32768.0), -32768, 32767).astype(np.int16)
    assert np.array_equal(to_pcm16(samples), expected)
    noise = (RNG.standard_normal(4096) * 0.5).astype(np.float32)
    reference = np.clip(np.round(noise * np.float32(32768.0)), -32768, 32767).astype(np.int16)
    assert np.array_equal(to_pcm16(noise), reference)


def test_many_drives_at_once_carry_each_drives_values():
    """frame_drive_rows / blendshape_drive_rows / PoseTrack.rows_at (a pool's frames made together) against a drive
    made a row at a time, then encoded: the same values, and None (each row then made alone, which names the error)
    as soon as one row holds a value the drive refuses."""
    from gaussiantalker.sdk.drive import blendshape_drive_rows, frame_drive_rows
    from gaussiantalker.serve.wire import encode_drive, encode_frame_packet, frame_packets

    track = PoseTrack(RNG.standard_normal((7, 6)).astype(np.float32) * 0.1)
    indices = np.array([0, 3, 6, 7, 12, 13, 40])
    poses = track.rows_at(indices)
    for k, index in enumerate(indices):
        pose = track.frame(int(index))
        assert np.array_equal(poses[k], np.concatenate([pose.rotation, pose.translation]))
    n_expr = 10
    flame = RNG.standard_normal((len(indices), n_expr + 3)).astype(np.float32)
    arkit = RNG.random((len(indices), 52)).astype(np.float32)
    audio = (RNG.standard_normal((len(indices), 640)) * 0.3).astype(np.float32)
    speaking, epochs, pts = indices % 2 == 0, indices // 5, indices / 25.0
    for rig, rows, values in (("flame", flame, frame_drive_rows(n_expr, flame, poses)),
                              ("arkit", arkit, blendshape_drive_rows(arkit, poses))):
        packets = frame_packets(rig, indices, pts, values, speaking, epochs, audio)
        for k, index in enumerate(indices):
            pose = track.frame(int(index))
            drive = frame_drive_of(n_expr, rows[k], pose) if rig == "flame" else blendshape_drive_of(rows[k], pose)
            expected = encode_frame_packet(encode_drive(int(index), float(pts[k]), drive, bool(speaking[k]),
                                                        int(epochs[k])), audio[k])
            assert packets[k].tobytes() == expected, (rig, k)
    for bad in BAD_VALUES:
        broken = flame.copy()
        broken[3, 1] = bad
        assert frame_drive_rows(n_expr, broken, poses) is None
        broken = arkit.copy()
        broken[5, 0] = bad
        assert blendshape_drive_rows(broken, poses) is None
    assert frame_drive_rows(n_expr, flame[:, :-1], poses) is None  # not the rig's row length
