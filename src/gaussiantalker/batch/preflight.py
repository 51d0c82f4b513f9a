"""Checks of a whole job list against its bundles before anything renders (docs/batch.md, "The job list"): each
bundle opens, and each job's output works with it (size, codec, crf, compositing, a motion on a composited head),
every problem named with its line; and one run at a time per output folder."""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from gaussiantalker.sdk.errors import GaussianTalkerError

from .job_file import listing
from .jobs import BatchError, Job
from .manifest import MANIFEST_NAME

try:
    import fcntl
except ImportError:  # Windows: no advisory locks through fcntl; runs there are not guarded (docs/batch.md)
    fcntl = None



def check_outputs(jobs: Sequence[Job], outdir: Path, jobs_path: str | os.PathLike = "job list") -> None:
    """BatchError naming every job whose bundle does not open or whose output it cannot make (manifest reads only:
    each bundle is opened once, no graph is loaded)."""
    from gaussiantalker.runtime import TalkingHead
    from gaussiantalker.sdk.bundle import Bundle

    bundles: dict[Path, Bundle | str] = {}
    views: dict[tuple, object] = {}
    problems = []
    for job in jobs:
        if job.bundle not in bundles:
            try:
                bundles[job.bundle] = Bundle(job.bundle)
            except (GaussianTalkerError, OSError, ValueError) as exc:
                bundles[job.bundle] = " ".join(str(exc).split())
        bundle = bundles[job.bundle]
        if isinstance(bundle, str):
            problems.append(f"line {job.line}: bundle: {bundle}")
            continue
        try:
            key = (job.bundle, job.resolution, job.composite)
            if key not in views:
                views[key] = TalkingHead.output_view(bundle, resolution=job.resolution, composite=job.composite)
            view = views[key]
            view.plan_video(outdir / job.out, codec=job.codec, crf=job.crf)
            if job.motion is not None and view.composite:
                raise BatchError("a composited head follows the reference clip and its audio; a motion plays on "
                                 "the bare head: set composite false")
        except GaussianTalkerError as exc:
            problems.append(f"line {job.line}: {' '.join(str(exc).split())}")
    if problems:
        raise BatchError(listing(Path(jobs_path), problems))


@contextmanager
def one_run_at_a_time(outdir: Path) -> Iterator[None]:
    """Hold a lock on OUTDIR's manifest for the run: a second `gt-render` into the same folder (on this machine, or
    on another through a shared file system that supports locks) is refused instead of mixing its files with this
    one's. (The manifest itself, not a lock file of its own: nothing is left behind in the folder.)"""
    if fcntl is None:
        yield
        return
    handle = open(outdir / MANIFEST_NAME, "ab")  # noqa: SIM115 - held open for the run
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise BatchError(f"{outdir}: another gt-render is writing this folder; wait for it to end, or use "
                             "another output folder") from None
        yield
    finally:
        handle.close()
