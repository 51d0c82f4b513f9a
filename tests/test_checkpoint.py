"""speaker.ckpt: round trip, and an unsafe or broken checkpoint is refused with a named reason."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest
import torch

from gaussiantalker.exporter.export.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from gaussiantalker.sdk.drive import FrameDrive
from gaussiantalker.sdk.errors import CheckpointError


def _deform(speaker, drive):
    inputs = {k: torch.from_numpy(v) for k, v in drive.graph_inputs().items()}
    with torch.no_grad():
        return speaker.deform(inputs["expression"], inputs["flame_pose"], inputs["head_translation"],
                              torch.zeros(1, 3))


def test_round_trip_is_exact(small_speaker, tmp_path):
    path = save_checkpoint(small_speaker, tmp_path / "s.ckpt")
    loaded = load_checkpoint(path)
    drive = FrameDrive.make(small_speaker.config.n_expr, np.linspace(-1, 1, small_speaker.config.n_expr),
                            [0.2, 0.0, 0.0])
    for a, b in zip(_deform(small_speaker, drive), _deform(loaded, drive), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    audio = torch.randn(1, 640 * 5)
    with torch.no_grad():
        torch.testing.assert_close(small_speaker.translate(audio), loaded.translate(audio), rtol=0, atol=0)
    assert loaded.camera.to_dict() == small_speaker.camera.to_dict()
    assert loaded.background == small_speaker.background
    torch.testing.assert_close(loaded.pose_track, small_speaker.pose_track)


class _RunsCode:
    """Unpickling this calls os.system: a checkpoint carrying it must never be loaded."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_pickle_that_would_run_code_is_refused_and_nothing_runs(small_speaker, tmp_path):
    marker = tmp_path / "code-ran"
    path = save_checkpoint(small_speaker, tmp_path / "s.ckpt")
    payload = torch.load(path, weights_only=True)
    payload["metadata"] = _RunsCode(marker)
    torch.save(payload, tmp_path / "evil.ckpt")
    with pytest.raises(CheckpointError, match="would run code"):
        load_checkpoint(tmp_path / "evil.ckpt")
    assert not marker.exists()
    # The same file really would run code if loaded unsafely: the test's payload is not a dud.
    with open(tmp_path / "evil.ckpt", "rb"):
        torch.load(tmp_path / "evil.ckpt", weights_only=False)
    assert marker.exists()


def test_plain_pickle_and_garbage_are_refused(tmp_path):
    with open(tmp_path / "p.ckpt", "wb") as handle:
        pickle.dump({"format": "x"}, handle)
    with pytest.raises(CheckpointError, match="p.ckpt"):
        read_checkpoint(tmp_path / "p.ckpt")
    (tmp_path / "g.ckpt").write_bytes(b"\x00garbage" * 50)
    with pytest.raises(CheckpointError, match="refusing to load|cannot read"):
        read_checkpoint(tmp_path / "g.ckpt")
    with pytest.raises(CheckpointError, match="does not exist"):
        read_checkpoint(tmp_path / "missing.ckpt")


def test_missing_keys_and_wrong_shapes_are_named(small_speaker, tmp_path):
    path = save_checkpoint(small_speaker, tmp_path / "s.ckpt")
    payload = torch.load(path, weights_only=True)
    broken = dict(payload)
    del broken["gaussians"], broken["camera"]
    torch.save(broken, tmp_path / "missing.ckpt")
    with pytest.raises(CheckpointError, match="missing entries: gaussians, camera"):
        load_checkpoint(tmp_path / "missing.ckpt")

    wrong = dict(payload)
    wrong["gaussians"] = dict(payload["gaussians"])
    wrong["gaussians"]["log_scale"] = torch.zeros(7, 3)
    torch.save(wrong, tmp_path / "shape.ckpt")
    with pytest.raises(CheckpointError, match="(?s)gaussian parameters do not fit.*log_scale"):
        load_checkpoint(tmp_path / "shape.ckpt")

    wrong = dict(payload)
    wrong["flame"] = dict(payload["flame"])
    wrong["flame"]["posedirs"] = torch.zeros(3, 3)
    torch.save(wrong, tmp_path / "flame.ckpt")
    with pytest.raises(CheckpointError, match="posedirs"):
        load_checkpoint(tmp_path / "flame.ckpt")

    wrong = dict(payload)
    wrong["parent"] = payload["parent"] + 10**6
    torch.save(wrong, tmp_path / "parent.ckpt")
    with pytest.raises(CheckpointError, match="parent"):
        load_checkpoint(tmp_path / "parent.ckpt")

    wrong = dict(payload)
    wrong["version"] = 99
    torch.save(wrong, tmp_path / "version.ckpt")
    with pytest.raises(CheckpointError, match="version 99"):
        load_checkpoint(tmp_path / "version.ckpt")
