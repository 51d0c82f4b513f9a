"""What runs inside a worker process: its loaded TalkingHeads (kept between jobs, a few at most) and one job's
render into a partial file renamed onto its final name when complete (docs/batch.md, "The local engine")."""

from __future__ import annotations

import contextlib
import os
import time
from collections import OrderedDict
from pathlib import Path

from gaussiantalker.sdk.errors import GaussianTalkerError

from .digests import file_digest
from .engine import JobResult, one_line
from .jobs import Job
from .outputs import partial_path

MAX_HEADS = 4  # loaded heads a worker keeps (each holds its bundle's graphs and a splatter)
# Graph threads of every batch head: the workers are the parallelism, and onnxruntime's results depend on its thread
# count, so one thread makes a job's frames the same whatever the worker count (docs/batch.md).
GRAPH_THREADS = 1
_heads: OrderedDict = OrderedDict()


def init_worker(threads: int) -> None:
    """Set a fresh worker's thread budget before numba loads: the CPU splatter's threads, so N workers share the
    cores instead of each taking all of them."""
    os.environ["NUMBA_NUM_THREADS"] = str(threads)
    os.environ["OMP_NUM_THREADS"] = str(threads)


def loaded_head(job: Job):
    """The worker's TalkingHead for this job's bundle and output settings, loaded once; the least recently used
    is closed beyond MAX_HEADS."""
    from gaussiantalker.runtime import TalkingHead

    key = job.head_key()
    if key in _heads:
        _heads.move_to_end(key)
        return _heads[key]
    head = TalkingHead(job.bundle, resolution=job.resolution, composite=job.composite, threads=GRAPH_THREADS,
                       renderer="auto")
    _heads[key] = head
    while len(_heads) > MAX_HEADS:
        _heads.popitem(last=False)[1].close()
    return head


def drop_head(job: Job) -> None:
    """Close and forget a head whose render failed in an unexpected way (its state is not trusted)."""
    head = _heads.pop(job.head_key(), None)
    if head is not None:
        with contextlib.suppress(Exception):
            head.close()


def render_job(job: Job, outdir: str) -> JobResult:
    """Render one job into OUTDIR/job.out through a partial file; a failure removes it and is returned, not
    raised (the SDK's errors with their message, anything else with its type)."""
    start = time.perf_counter()
    target = Path(outdir) / job.out
    partial = partial_path(target)
    frames = 0

    def count(_frame) -> None:
        nonlocal frames
        frames += 1

    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        head = loaded_head(job)
        head.write_video(partial, job.audio, motion=job.motion, on_frame=count)
        digest = file_digest(partial)
        os.replace(partial, target)
        return JobResult(job.out, True, output=digest, seconds=time.perf_counter() - start,
                         video_s=frames / head.fps)
    except Exception as exc:
        partial.unlink(missing_ok=True)
        if not isinstance(exc, GaussianTalkerError):
            drop_head(job)
        return JobResult(job.out, False, reason=one_line(exc), seconds=time.perf_counter() - start)
