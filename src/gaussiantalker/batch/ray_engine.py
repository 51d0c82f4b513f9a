"""The Ray engine (extra `ray`): the jobs' steps (batch/job_steps.py) on actors of a Ray cluster, each actor a worker
keeping its loaded heads between calls, placed by Ray where its CPUs are free (docs/batch.md, "On a Ray cluster").

Ray restarts an actor whose process or node died and reruns the call it was running (`max_restarts`,
`max_task_retries`); a call that outlives its retries comes back as a failed job. Every node writes the outputs
under the same OUTDIR path: a shared file system, or object storage mounted at that path."""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from pathlib import Path

from .engine import JobResult, one_line
from .job_steps import Call, Outcome, run_programs
from .jobs import BatchError, Job
from .local import RETRIES, usable_cores


def _ray():
    try:
        import ray
    except ImportError:
        raise BatchError("--ray needs Ray: pip install 'gaussiantalker[ray]'") from None
    return ray


class RayEngine:
    """`with RayEngine(address) as engine:` connects to the cluster at `address` (None: `RAY_ADDRESS`, else a
    local Ray started for the run) and runs jobs on `workers` actors (None: one per CPU of the cluster), each
    taking `threads` CPUs (the CPU splatter's threads)."""

    def __init__(self, address: str | None = None, *, workers: int | None = None, threads: int = 1,
                 retries: int = RETRIES) -> None:
        if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
            raise ValueError(f"workers must be a whole number >= 1, got {workers!r}")
        self.address = address or os.environ.get("RAY_ADDRESS") or None
        self.workers, self.threads, self.retries = workers, threads, retries
        self._connected_here = False

    def __enter__(self) -> RayEngine:
        ray = _ray()
        if not ray.is_initialized():
            options = {"address": self.address} if self.address else {"num_cpus": usable_cores(),
                                                                      "include_dashboard": False}
            try:
                ray.init(**options, log_to_driver=False, logging_level="WARNING")
            except (ConnectionError, ValueError, RuntimeError) as exc:
                raise BatchError(f"cannot reach the Ray cluster at {self.address or 'a local Ray'}: "
                                 f"{one_line(exc)}") from None
            self._connected_here = True
        return self

    def __exit__(self, *exc) -> None:
        if self._connected_here:
            _ray().shutdown()
            self._connected_here = False

    def actor_count(self) -> int:
        """The actors a run starts: `workers`, or as many as the cluster's CPUs hold at `threads` each."""
        if self.workers is not None:
            return self.workers
        cpus = int(_ray().cluster_resources().get("CPU", 1))
        return max(1, cpus // self.threads)

    def run(self, jobs: Sequence[Job], outdir: Path, segment_s: float | None = None) -> Iterator[JobResult]:
        """Yield each job's result as it finishes; the run's actors end with it."""
        if not self._connected_here and not _ray().is_initialized():
            raise BatchError("use the Ray engine in a `with RayEngine(...)` block (it connects there)")
        calls = ActorCalls(self.actor_count(), self.threads, self.retries)
        try:
            yield from run_programs(jobs, Path(outdir).absolute(), segment_s, calls)
        finally:
            calls.close()


class ActorCalls:
    """Calls on a fixed set of actors, one call an actor at a time; a call goes to an idle actor that last ran
    the same head when there is one (its bundle is loaded there). Written here rather than with
    `ray.util.ActorPool`, which does not say which call an actor that died was running."""

    def __init__(self, count: int, threads: int, retries: int) -> None:
        ray = _ray()
        worker_class = ray.remote(BatchActor).options(
            num_cpus=threads, max_restarts=retries, max_task_retries=retries,
            runtime_env={"env_vars": {"NUMBA_NUM_THREADS": str(threads), "OMP_NUM_THREADS": str(threads)}})
        self.retries = retries
        self.actors = [worker_class.remote() for _ in range(count)]
        self.idle = list(self.actors)
        self.last_head: dict[int, tuple] = {}
        self.running: dict = {}  # ObjectRef -> (call, actor)

    def free(self) -> int:
        return len(self.idle)

    def submit(self, call: Call) -> None:
        head = call.job.head_key()
        actor = next((a for a in self.idle if self.last_head.get(id(a)) == head), self.idle[0])
        self.idle.remove(actor)
        self.last_head[id(actor)] = head
        self.running[actor.run.remote(call)] = (call, actor)

    def wait(self) -> list[tuple[Call, Outcome]]:
        ray = _ray()
        if not self.running:
            return []
        ready, _ = ray.wait(list(self.running), num_returns=1)
        done = []
        for ref in ready:
            call, actor = self.running.pop(ref)
            self.idle.append(actor)
            try:
                done.append((call, Outcome(ray.get(ref))))
            except ray.exceptions.RayActorError:
                reason = f"its Ray worker died {self.retries + 1} times (killed, out of memory, or its node lost)"
                done.append((call, Outcome(JobResult(call.job.out, False, reason=reason), self.retries + 1)))
            except ray.exceptions.RayError as exc:
                done.append((call, Outcome(JobResult(call.job.out, False, reason=one_line(exc)))))
        return done

    def places(self) -> list[tuple[int, str]]:
        """Each actor's (process id, node id)."""
        return _ray().get([actor.place.remote() for actor in self.actors])

    def close(self) -> None:
        ray = _ray()
        for actor in self.actors:
            ray.kill(actor)
        self.actors, self.idle, self.running = [], [], {}


class BatchActor:
    """A Ray actor that is one batch worker (batch/worker.py): its heads stay loaded between calls."""

    def run(self, call: Call) -> object:
        from .worker import run_call

        return run_call(call)

    def place(self) -> tuple[int, str]:
        """(process id, Ray node id) of this actor."""
        import ray

        return os.getpid(), ray.get_runtime_context().get_node_id()
