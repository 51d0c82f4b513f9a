"""The local engine: worker processes on this machine, each keeping its loaded heads between calls
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
from .job_steps import Call, Outcome, run_programs
from .jobs import Job
from .worker import init_worker, run_call

RETRIES = 2  # times a call is rerun after the worker running it died


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

    def run(self, jobs: Sequence[Job], outdir: Path, segment_s: float | None = None) -> Iterator[JobResult]:
        """Yield each job's result as it finishes (its steps: batch/job_steps.py)."""
        calls = ProcessCalls(self.workers, self.threads, self.retries)
        try:
            yield from run_programs(jobs, Path(outdir), segment_s, calls)
        finally:
            calls.close()


class ProcessCalls:
    """A process pool that runs calls, at most one a worker, recreated when a worker dies: every call that was
    running then is rerun on the new pool, at most `retries` times (which worker died is not known)."""

    def __init__(self, workers: int, threads: int, retries: int) -> None:
        self.workers, self.threads, self.retries = workers, threads, retries
        self.attempts: Counter[str] = Counter()
        self._pool: ProcessPoolExecutor | None = None
        self._running: dict[Future, Call] = {}
        self._retry: deque[Call] = deque()

    def free(self) -> int:
        return self.workers - len(self._running) - len(self._retry)

    def submit(self, call: Call) -> None:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=init_worker, initargs=(self.threads,))
        self.attempts[call.key] += 1
        try:
            self._running[self._pool.submit(run_call, call)] = call
        except BrokenProcessPool:
            self.attempts[call.key] -= 1
            self._retry.append(call)

    def wait(self) -> list[tuple[Call, Outcome]]:
        """At least one finished call (calls whose worker died are rerun first, on a fresh pool)."""
        while True:
            if self._retry:
                self._restart()
            if not self._running:
                return []
            finished, _ = wait(self._running, return_when=FIRST_COMPLETED)
            done = []
            for future in finished:
                call = self._running.pop(future)
                outcome = self._outcome(future, call)
                if outcome is None:
                    self._retry.append(call)
                else:
                    done.append((call, outcome))
            if done:
                return done

    def _outcome(self, future: Future, call: Call) -> Outcome | None:
        """The call's outcome, or None when its worker died and it has retries left."""
        attempt = self.attempts[call.key]
        try:
            return Outcome(future.result(), attempt)
        except BrokenProcessPool:
            if attempt <= self.retries:
                return None
            return Outcome(JobResult(call.job.out, False, reason=f"its worker process died {attempt} times "
                                     "(killed, or out of memory)", attempts=attempt), attempt)
        except Exception as exc:  # an error the worker could not even return as a result
            return Outcome(JobResult(call.job.out, False, reason=one_line(exc), attempts=attempt), attempt)

    def _restart(self) -> None:
        """A fresh pool (the broken one's other calls fail there too and come back here), the dead calls on it."""
        if self._running:
            return  # wait for the broken pool's other futures first: they all fail at once
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        retry, self._retry = self._retry, deque()
        for call in retry:
            self.submit(call)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
