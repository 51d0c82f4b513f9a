"""sha256 digests of a job's files, read in bounded chunks: they decide whether a recorded output is still current."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

CHUNK_BYTES = 1 << 20


def file_digest(path: str | os.PathLike) -> str:
    """The sha256 of a file's bytes, streamed (bundles and outputs can be gigabytes)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(CHUNK_BYTES):
            digest.update(chunk)
    return digest.hexdigest()


class DigestCache:
    """Digests of input files within one run: a bundle shared by a thousand jobs is read once."""

    def __init__(self) -> None:
        self._known: dict[Path, str] = {}

    def __call__(self, path: Path) -> str:
        if path not in self._known:
            self._known[path] = file_digest(path)
        return self._known[path]
