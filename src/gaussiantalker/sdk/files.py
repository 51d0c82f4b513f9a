"""Atomic file writes: every file the SDK produces (bundle, checkpoint, video) appears whole or not at all.

`atomic_path(target)` hands out a unique temporary path in the target's own folder (so the final rename never
crosses a file system), and on success fsyncs it and renames it onto the target; on any exception, Ctrl-C or
SIGTERM the temporary file is removed and the target is left as it was. Only SIGKILL (or a power cut) can leave
a temporary file behind: a hidden `.NAME.XXXXXXXX.tmp` (with the target's suffix after it when asked for one,
for writers such as ffmpeg that choose a format from the extension).

`atomic_files(folder)` does the same for a set of files (an image sequence): they are written in a hidden staging
folder inside `folder` and moved into it only when all are written.
"""

from __future__ import annotations

import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

# Signals that normally kill the process without unwinding; while a file is being staged (in the main thread,
# where a handler may be set, and only if the application left the default action) they raise SystemExit
# instead, so the temporary file is cleaned up. The application's own handlers are never replaced.
_UNWINDING_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))


class StagedFile:
    """A temporary file beside `target` that becomes the target (or another name in its folder) on `commit`."""

    def __init__(self, target: Path, path: Path) -> None:
        self.target = target
        self.path = path
        self.committed_to: Path | None = None

    def commit(self, destination: str | os.PathLike | None = None) -> Path:
        """fsync the staged file and rename it onto `destination` (default: the target), in the same folder."""
        destination = self.target if destination is None else Path(destination)
        if destination.resolve().parent != self.path.resolve().parent:
            raise ValueError(f"{destination} is not in the staging folder {self.path.parent} (no atomic rename)")
        _fsync_file(self.path)
        os.replace(self.path, destination)
        _fsync_directory(destination.parent)
        self.committed_to = destination
        return destination


@contextmanager
def atomic_path(target: str | os.PathLike, suffix: str = ".tmp") -> Iterator[StagedFile]:
    """Stage a write to `target`: yields a StagedFile whose `.path` the caller writes (by any means).

    On normal exit the file is committed onto the target unless the caller committed it elsewhere already; on
    any exception or signal it is removed. The folder is created if missing; the file gets ordinary permissions.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=suffix, dir=target.parent)
    os.close(fd)
    staged = StagedFile(target, Path(name))
    try:
        os.chmod(staged.path, 0o666 & ~_current_umask())  # mkstemp makes 0600; these are ordinary files
        with _signals_unwind():
            yield staged
            if staged.committed_to is None:
                staged.commit()
    finally:
        if staged.committed_to is None:
            staged.path.unlink(missing_ok=True)


@contextmanager
def atomic_write(target: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """`with atomic_write(path) as handle: handle.write(...)`: the file appears at `path` only when complete."""
    with atomic_path(target) as staged, open(staged.path, mode) as handle:
        yield handle


@contextmanager
def atomic_files(folder: str | os.PathLike) -> Iterator[Path]:
    """Stage a set of new files for `folder`: yields a hidden temporary folder inside it to write them in.

    On normal exit each staged file is fsynced and renamed into `folder` (replacing a file of the same name); on
    any exception or signal the staged folder is removed and `folder` keeps only what it had. (Used for image
    sequences: no frame file appears under its final name before the whole sequence is written.)
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".gt-staged-", dir=folder))
    try:
        with _signals_unwind():
            yield staging
            for staged in sorted(staging.iterdir()):
                _fsync_file(staged)
                os.chmod(staged, 0o666 & ~_current_umask())
                os.replace(staged, folder / staged.name)
            _fsync_directory(folder)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


@contextmanager
def _signals_unwind() -> Iterator[None]:
    """While active, SIGTERM/SIGHUP with the default action raise SystemExit(128 + signal) (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {}
    for signum in _UNWINDING_SIGNALS:
        if signal.getsignal(signum) is signal.SIG_DFL:
            previous[signum] = signal.signal(signum, _raise_system_exit)
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def _raise_system_exit(signum: int, frame) -> None:
    raise SystemExit(128 + signum)


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _fsync_file(path: Path) -> None:
    """Flush a closed file's data to disk (the writer may have been another process, such as ffmpeg)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_directory(directory: Path) -> None:
    """Make a rename durable (POSIX); a no-op where directories cannot be opened (Windows)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
