"""The local engine: worker processes on this machine, each keeping its loaded heads between jobs
(batch/worker.py), and a pool recreated when a worker dies (docs/batch.md, "The local engine")."""

from __future__ import annotations

import multiprocessing
import os
from collections import Counter, deque
from collections.abc import Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from .engine import JobResult, one_line
from .jobs import Job
from .outputs import remove_partials
from .worker import init_worker, render_job

RETRIES = 2  # times a job is rerun after the worker running it died


def usable_cores() -> int:
    """The cores this process may run on (a container's or taskset's limit, not the machine's)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


class LocalEngine:
    """Runs jobs on `workers` processes (default: one per usable core), each with cores / workers threads."""

    def __init__(self, workers: int | None = None, retries: int = RETRIES) -> None:
        if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
            raise ValueError(f"workers must be a whole number >= 1, got {workers!r}")
        self.workers = workers or usable_cores()
        self.retries = retries
        self.threads = max(1, usable_cores() // self.workers)

    def run(self, jobs: Sequence[Job], outdir: Path) -> Iterator[JobResult]:
        """Yield each job's result as it finishes; a job whose worker died is rerun on a fresh pool, at most
        `retries` times (every job running when a pool broke counts it: which worker died is not known)."""
        pending = deque(jobs)
        attempts: Counter[str] = Counter()
        while pending:
            yield from self._pool_run(pending, attempts, Path(outdir))

    def _pool_run(self, pending: deque[Job], attempts: Counter[str], outdir: Path) -> Iterator[JobResult]:
        """Run jobs from `pending` on one pool until they are all done or the pool breaks (then the jobs it was
        running are back at the front of `pending`, or failed once out of retries)."""
        pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=init_worker, initargs=(self.threads,))
        running: dict[Future, Job] = {}
        broken = False
        try:
            while pending or running:
                # At most one job a worker: each running job is on a worker, so a broken pool's jobs were all started.
                while pending and not broken and len(running) < self.workers:
                    job = pending.popleft()
                    try:
                        running[pool.submit(render_job, job, str(outdir))] = job
                    except BrokenProcessPool:
                        pending.appendleft(job)
                        broken = True
                        break
                    attempts[job.out] += 1
                if not running:
                    break
                finished, _ = wait(running, return_when=FIRST_COMPLETED)
                for future in finished:
                    job = running.pop(future)
                    result = self._result(future, job, attempts[job.out], outdir)
                    if result is None:
                        broken = True
                        pending.appendleft(job)
                    else:
                        yield result
        finally:
            pool.shutdown(wait=True, cancel_futures=True)

    def _result(self, future: Future, job: Job, attempt: int, outdir: Path) -> JobResult | None:
        """The job's result, or None when its worker died and it has retries left."""
        try:
            result = future.result()
        except BrokenProcessPool:
            remove_partials(outdir / job.out)
            if attempt <= self.retries:
                return None
            return JobResult(job.out, False, reason=f"its worker process died {attempt} times (killed, or out of "
                             "memory)", attempts=attempt)
        except Exception as exc:  # an error the worker could not even return as a result
            remove_partials(outdir / job.out)
            return JobResult(job.out, False, reason=one_line(exc), attempts=attempt)
        return JobResult(result.out, result.ok, result.reason, result.output, result.seconds, result.video_s,
                         attempt)
