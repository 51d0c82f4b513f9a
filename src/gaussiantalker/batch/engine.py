"""What an engine is to a batch: it takes checked jobs and an output folder and yields each job's result as it
finishes. The local engine (batch/local.py) runs worker processes on this machine, the Ray engine (batch/ray.py)
actors on a cluster; both run the jobs' steps through batch/job_steps.py, and the runner above them (batch/runner.py)
keeps the manifest and the progress."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from .jobs import Job

MAX_REASON_CHARS = 300


@dataclass(frozen=True)
class JobResult:
    """One job's outcome: ok with its output's sha256, or failed with a one-line reason."""

    out: str
    ok: bool
    reason: str = ""
    output: str | None = None  # sha256 of the file now under OUTDIR/out
    seconds: float = 0.0  # wall seconds in the worker
    video_s: float = 0.0  # seconds of video made
    attempts: int = 1
    segments: int = 1  # files its frames were rendered into (more than one: split, then joined)


class Engine(Protocol):
    """Renders jobs into `outdir`, each output renamed onto its final name only when complete."""

    def run(self, jobs: Sequence[Job], outdir: Path, segment_s: float | None = None) -> Iterator[JobResult]:
        """Yield one result per job, in the order they finish; jobs longer than `segment_s` (None: never) are
        split into segments (batch/job_steps.py)."""
        ...


def one_line(exc: BaseException) -> str:
    """An exception as one bounded line: the SDK's errors by their message, anything else with its type."""
    from gaussiantalker.sdk.errors import GaussianTalkerError

    text = " ".join(str(exc).split()) or type(exc).__name__
    if not isinstance(exc, GaussianTalkerError):
        text = f"{type(exc).__name__}: {text}"
    return text if len(text) <= MAX_REASON_CHARS else text[:MAX_REASON_CHARS - 3] + "..."
