"""One render job of a job list (docs/batch.md): its inputs, its output name under OUTDIR and its settings, and the
error a batch raises on purpose."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from gaussiantalker.sdk.errors import GaussianTalkerError

# Bumped when what a job renders changes for the same inputs and settings: every recorded job is then redone.
JOB_FORMAT_VERSION = 1


class BatchError(GaussianTalkerError):
    """A job list or a batch's output folder cannot be used: bad lines (each named by its line number), a manifest
    that is not one, an output folder that is not a folder."""


@dataclass(frozen=True)
class Job:
    """A checked job: absolute input paths, `out` relative to OUTDIR, and the head settings it renders with."""

    line: int  # its line in the job file, for messages
    bundle: Path
    out: str  # a relative POSIX path under OUTDIR, no '..'
    audio: Path | None = None
    motion: Path | None = None
    resolution: tuple[int, int] | None = None  # None: the bundle's
    composite: bool | None = None  # None: whether the bundle has a reference clip (False with a camera)
    camera: tuple[float, float] | None = None  # (yaw, pitch) degrees about the head's centre; None: the bundle's
    codec: str | None = None  # None: the container's default
    crf: int | None = None  # None: the codec's default
    fps: float | None = None  # frames per second of the video; None: the speaker's

    def inputs(self) -> dict[str, Path]:
        """The input files whose digests decide whether a recorded output is still this job's."""
        found = {"bundle": self.bundle, "audio": self.audio, "motion": self.motion}
        return {name: path for name, path in found.items() if path is not None}

    def settings_digest(self) -> str:
        """sha256 of everything but the input files' contents that decides the output's frames and file."""
        settings = {"version": JOB_FORMAT_VERSION, "out": self.out, "inputs": sorted(self.inputs()),
                    "resolution": self.resolution, "composite": self.composite, "camera": self.camera,
                    "codec": self.codec, "crf": self.crf, "fps": self.fps}
        return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()

    def head_key(self) -> tuple:
        """What a loaded TalkingHead depends on: jobs with the same key share one head in a worker."""
        return str(self.bundle), self.resolution, self.composite, self.camera
