"""Run a job list into an output folder with any engine: skip what the manifest proves done, render the rest,
record each result as it comes, show one bar over the jobs (docs/batch.md)."""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from gaussiantalker.sdk.progress import progress_bar

from .digests import DigestCache
from .engine import Engine, JobResult
from .job_file import read_jobs
from .job_steps import DEFAULT_SEGMENT_S
from .jobs import BatchError, Job
from .local import LocalEngine
from .manifest import Manifest, Record
from .outputs import remove_partials
from .preflight import check_outputs, one_run_at_a_time

MIN_SEGMENT_S = 0.1  # below it a segment's own costs (a file, a head's first frame) outweigh its frames


@dataclass
class BatchSummary:
    """What a run did: outputs made, skipped (already done) and failed (with reasons), video made, wall time."""

    done: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)  # out -> one-line reason
    video_s: float = 0.0  # seconds of video made by this run
    wall_s: float = 0.0

    def describe(self) -> str:
        """One line for a terminal or a log."""
        rate = self.video_s / self.wall_s if self.wall_s > 0 else 0.0
        return (f"{len(self.done)} rendered, {len(self.skipped)} already done, {len(self.failed)} failed; "
                f"{self.video_s:.1f} s of video in {self.wall_s:.1f} s ({rate:.2f} s of video per second)")


def render_jobs(jobs_path: str | os.PathLike, outdir: str | os.PathLike, *, workers: int | None = None,
                force: bool = False, progress: bool = True, segment_s: float | None = DEFAULT_SEGMENT_S,
                ray: bool | str = False) -> BatchSummary:
    """Render a job list file into `outdir`: on local worker processes, or with `ray` on a Ray cluster (True: the
    one `RAY_ADDRESS` names, else a local Ray started for the run; a string: that address). Jobs longer than
    `segment_s` seconds (None: none) render in segments on several workers. BatchError (every bad line) before
    anything renders."""
    jobs = read_jobs(jobs_path)
    check_segment_s(segment_s)
    options = {"force": force, "progress": progress, "segment_s": segment_s, "jobs_name": str(jobs_path)}
    if ray is False:
        return run_jobs(jobs, outdir, LocalEngine(workers), **options)
    from .ray_engine import RayEngine

    with RayEngine(None if ray is True else ray, workers=workers) as engine:
        return run_jobs(jobs, outdir, engine, **options)


def check_segment_s(segment_s: float | None) -> None:
    """BatchError unless `segment_s` is None or a length a segment can have."""
    if segment_s is not None and not (isinstance(segment_s, int | float) and MIN_SEGMENT_S <= segment_s < 1e9):
        raise BatchError(f"segment_s must be at least {MIN_SEGMENT_S} seconds (or None: never split), "
                         f"got {segment_s!r}")


def run_jobs(jobs: Sequence[Job], outdir: str | os.PathLike, engine: Engine, *, force: bool = False,
             progress: bool = True, segment_s: float | None = DEFAULT_SEGMENT_S,
             jobs_name: str = "job list") -> BatchSummary:
    """Render checked jobs into `outdir` with `engine`, skipping those the manifest proves done unless `force`:
    first every job's output is checked against its bundle (BatchError naming each bad one, `jobs_name` the list's
    name in it), and the folder is locked against a second run."""
    start = time.perf_counter()
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise BatchError(f"{outdir}: the output folder is a file")
    check_outputs(jobs, outdir, jobs_name)
    outdir.mkdir(parents=True, exist_ok=True)
    with one_run_at_a_time(outdir):
        return _run_locked(jobs, outdir, engine, force, progress, segment_s, start)


def _run_locked(jobs: Sequence[Job], outdir: Path, engine: Engine, force: bool, progress: bool,
                segment_s: float | None, start: float) -> BatchSummary:
    manifest, digest = Manifest(outdir), DigestCache()
    summary = BatchSummary()
    todo, inputs = [], {}
    for job in jobs:
        inputs[job.out] = {name: digest(path) for name, path in job.inputs().items()}
        if not force and manifest.done(job.out, inputs[job.out], job.settings_digest(), outdir):
            summary.skipped.append(job.out)
        else:
            remove_partials(outdir / job.out)  # left by a run that was killed
            todo.append(job)
    todo.sort(key=lambda job: repr(job.head_key()))  # jobs of one head in a row: each worker loads it once
    by_out = {job.out: job for job in todo}
    bar = progress_bar(total=len(jobs), initial=len(summary.skipped), unit="job", disable=not progress)
    try:
        for result in engine.run(todo, outdir, segment_s):
            job = by_out[result.out]
            manifest.append(_record(job, result, inputs[job.out]))
            if result.ok:
                summary.done.append(result.out)
                summary.video_s += result.video_s
            else:
                (outdir / job.out).unlink(missing_ok=True)  # an older output of other inputs is not this job's
                summary.failed[result.out] = result.reason
            bar.update(1)
            bar.set_postfix_str(f"{summary.video_s / max(time.perf_counter() - start, 1e-9):.2f} s video/s")
    finally:
        bar.close()
    summary.wall_s = time.perf_counter() - start
    return summary


def _record(job: Job, result: JobResult, inputs: dict[str, str]) -> Record:
    return Record(out=job.out, inputs=inputs, settings=job.settings_digest(), status="ok" if result.ok else "failed",
                  output=result.output, reason=result.reason, seconds=round(result.seconds, 3),
                  video_s=round(result.video_s, 3), attempts=result.attempts, segments=result.segments)
