"""Atomic writes (`sdk.files`): every writer (bundle, checkpoint, gt-export, video) stages beside its target."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from gaussiantalker.sdk.bundle import Bundle, BundleWriter
from gaussiantalker.sdk.files import atomic_path, atomic_write
from gaussiantalker.sdk.video import VideoWriter, probe_video


def _refuse_cross_directory_replace(monkeypatch) -> list[tuple[str, str]]:
    """Make os.replace fail with EXDEV whenever source and target folders differ (as across file systems)."""
    real_replace = os.replace
    calls: list[tuple[str, str]] = []

    def replace(src, dst, *args, **kwargs):
        calls.append((str(src), str(dst)))
        if Path(src).resolve().parent != Path(dst).resolve().parent:
            raise OSError(errno.EXDEV, "Invalid cross-device link", str(src))
        return real_replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", replace)
    return calls


def _frames(count: int, size: tuple[int, int] = (32, 24)) -> list[np.ndarray]:
    return [np.full((size[1], size[0], 3), 40 * i, dtype=np.uint8) for i in range(count)]


def test_atomic_write_places_a_whole_file_with_ordinary_permissions(tmp_path):
    target = tmp_path / "sub" / "out.bin"
    with atomic_write(target) as handle:
        handle.write(b"hello")
        assert not target.exists()  # nothing under the name until the write is complete
    assert target.read_bytes() == b"hello"
    assert sorted(p.name for p in target.parent.iterdir()) == ["out.bin"]
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask


@pytest.mark.parametrize("error", [OSError(28, "No space left on device"), KeyboardInterrupt()],
                         ids=["OSError", "KeyboardInterrupt"])
def test_failed_write_keeps_the_old_file_and_leaves_no_temp(tmp_path, error):
    target = tmp_path / "out.bin"
    target.write_bytes(b"good")
    with pytest.raises(type(error)), atomic_write(target) as handle:
        handle.write(b"half")
        raise error
    assert target.read_bytes() == b"good"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.bin"]


def test_concurrent_writers_to_one_target_never_share_a_temp_file(tmp_path):
    """Two saves of the same file at once each stage their own temp file; the last to finish wins, whole."""
    target = tmp_path / "speaker.ckpt"
    with atomic_path(target) as first, atomic_path(target) as second:
        assert first.path != second.path and first.path.parent == second.path.parent == tmp_path
        first.path.write_bytes(b"first" * 1000)
        second.path.write_bytes(b"second" * 1000)
    assert target.read_bytes() == b"first" * 1000  # the outer context commits last
    assert sorted(p.name for p in tmp_path.iterdir()) == ["speaker.ckpt"]

    def save(payload: bytes) -> None:
        with atomic_write(target) as handle:
            for _ in range(50):
                handle.write(payload)

    threads = [threading.Thread(target=save, args=(bytes([65 + i]) * 4096,)) for i in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    data = target.read_bytes()
    assert len(data) == 50 * 4096 and len(set(data)) == 1  # one writer's complete file, never a mix
    assert sorted(p.name for p in tmp_path.iterdir()) == ["speaker.ckpt"]


def test_commit_elsewhere_and_refusal_across_folders(tmp_path):
    target = tmp_path / "speaker.gtb"
    with atomic_path(target) as staged:
        staged.path.write_bytes(b"unverified")
        placed = staged.commit(tmp_path / "speaker.unverified.gtb")
    assert placed.read_bytes() == b"unverified" and not target.exists()
    with pytest.raises(ValueError, match="not in the staging folder"), atomic_path(target) as staged:
        staged.commit(tmp_path / "elsewhere" / "speaker.gtb")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["speaker.unverified.gtb"]


SIGTERM_WRITER = """
import sys, time
from pathlib import Path
from gaussiantalker.sdk.files import atomic_write
with atomic_write(sys.argv[1]) as handle:
    handle.write(b"partial")
    handle.flush()
    Path(sys.argv[2]).touch()
    time.sleep(60)
"""


def test_sigterm_while_staging_removes_the_temp_file(tmp_path):
    """A library caller that installed no handler: SIGTERM mid-write unwinds (exit 143) and cleans up."""
    target, marker = tmp_path / "out.bin", tmp_path / "writing"
    target.write_bytes(b"good")
    process = subprocess.Popen([sys.executable, "-c", SIGTERM_WRITER, str(target), str(marker)])
    deadline = time.monotonic() + 60
    while not marker.exists():
        assert process.poll() is None and time.monotonic() < deadline, "the writer never started writing"
        time.sleep(0.02)
    process.send_signal(signal.SIGTERM)
    assert process.wait(timeout=30) == 128 + signal.SIGTERM
    assert target.read_bytes() == b"good"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.bin", "writing"]


def test_staging_leaves_the_applications_signal_handlers_alone(tmp_path):
    def handler(signum, frame):
        pass

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        with atomic_write(tmp_path / "out.bin") as handle:
            assert signal.getsignal(signal.SIGTERM) is handler
            handle.write(b"x")
        assert signal.getsignal(signal.SIGTERM) is handler
    finally:
        signal.signal(signal.SIGTERM, previous)
    with atomic_write(tmp_path / "out.bin") as handle:  # default action: unwinding only while staging
        assert signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL
        handle.write(b"y")
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


def test_video_survives_a_target_on_another_file_system(tmp_path, monkeypatch):
    """The temporary video is staged beside the target, so the final rename never crosses file systems."""
    calls = _refuse_cross_directory_replace(monkeypatch)
    target = tmp_path / "talk.mp4"
    with VideoWriter(target, 25, (32, 24), audio=np.zeros(16000, np.float32)) as out:
        for frame in _frames(5):
            out.write(frame)
    assert probe_video(target)["frames"] == 5 and probe_video(target)["has_audio"]
    assert calls and all(Path(src).parent == tmp_path for src, _ in calls)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["talk.mp4"]


SHM = Path("/dev/shm")
HAS_SECOND_FILE_SYSTEM = SHM.is_dir() and os.stat(SHM).st_dev != os.stat(tempfile.gettempdir()).st_dev


# CI's and the developers' machines have /dev/shm as a tmpfs beside a disk-backed /tmp, so this runs there.
@pytest.mark.skipif(not HAS_SECOND_FILE_SYSTEM, reason="no /dev/shm on another file system than the temp folder")
def test_video_on_a_real_second_file_system():
    """Where /dev/shm is another file system than the temp folder, write the video there for real."""
    with tempfile.TemporaryDirectory(dir=SHM) as folder:
        target = Path(folder) / "talk.mp4"
        with VideoWriter(target, 25, (32, 24)) as out:
            for frame in _frames(3):
                out.write(frame)
        assert probe_video(target)["frames"] == 3
        assert sorted(p.name for p in Path(folder).iterdir()) == ["talk.mp4"]


def test_failed_video_leaves_nothing_under_its_name(tmp_path):
    target = tmp_path / "talk.mp4"
    with pytest.raises(RuntimeError, match="render failed"), VideoWriter(target, 25, (32, 24)) as out:
        out.write(_frames(1)[0])
        raise RuntimeError("render failed")
    assert list(tmp_path.iterdir()) == []


def test_bundle_and_checkpoint_writers_stage_beside_their_target(tmp_path, monkeypatch, small_speaker):
    from gaussiantalker.exporter.export.checkpoint import load_checkpoint, save_checkpoint

    calls = _refuse_cross_directory_replace(monkeypatch)
    writer = BundleWriter(metadata={})
    writer.add_buffer("x", np.arange(10, dtype=np.float32))
    writer.write(tmp_path / "b.gtb")
    np.testing.assert_array_equal(Bundle(tmp_path / "b.gtb").buffer("x"), np.arange(10, dtype=np.float32))
    save_checkpoint(small_speaker, tmp_path / "s.ckpt")
    assert load_checkpoint(tmp_path / "s.ckpt").gaussians.count == small_speaker.gaussians.count
    assert len(calls) == 2 and all(Path(src).parent == tmp_path for src, _ in calls)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.gtb", "s.ckpt"]
