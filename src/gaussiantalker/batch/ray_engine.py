"""The Ray engine (extra `ray`): the jobs' steps (batch/job_steps.py) on actors of a Ray cluster, each actor a worker
keeping its loaded heads between calls, placed by Ray where its CPUs are free (docs/batch.md, "On a Ray cluster").

Ray restarts an actor whose process or node died (`max_restarts`); the call it was running is rerun on another
actor (`ActorCalls`); a call that outlives its retries comes back as a failed job. Every node writes the outputs
under the same OUTDIR path: a shared file system, or object storage mounted at that path."""

from __future__ import annotations

import os
import signal
import threading
from collections import Counter, deque
from collections.abc import Iterator, Sequence
from pathlib import Path

from .engine import JobResult, one_line
from .job_steps import Call, Outcome, run_programs
from .jobs import BatchError, Job
from .local import RETRIES, usable_cores

# How long a run waits for a dead actor to come back when no other actor is left to rerun its call on.
COMEBACK_S = 300.0


def _ray():
    try:
        import ray
    except ImportError:
        raise BatchError("--ray needs Ray: pip install 'gaussiantalker[ray]'") from None
    return ray


def _restore(handlers: dict) -> None:
    """Put back the signal handlers `ray.init` replaced: the application's, not Ray's, stay in force (signal
    handlers can only be set from the main thread; elsewhere ray.init sets none either)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for number, handler in handlers.items():
        if handler is not None and signal.getsignal(number) is not handler:
            signal.signal(number, handler)


class RayEngine:
    """`with RayEngine(address) as engine:` connects, at the first run with a job to do, to the cluster at
    `address` (None: `RAY_ADDRESS`, else a local Ray started for the run; disconnected when the block ends) and runs
    jobs on `workers` actors (None: one per CPU of the cluster), each taking `threads` CPUs (the CPU splatter's
    threads)."""

    def __init__(self, address: str | None = None, *, workers: int | None = None, threads: int = 1,
                 retries: int = RETRIES) -> None:
        if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
            raise ValueError(f"workers must be a whole number >= 1, got {workers!r}")
        self.address = address or os.environ.get("RAY_ADDRESS") or None
        self.workers, self.threads, self.retries = workers, threads, retries
        self._connected_here = False

    def __enter__(self) -> RayEngine:
        _ray()  # a missing extra is named before any job is looked at
        return self

    def connect(self) -> None:
        """Join the cluster (or start the local Ray) unless this process is already connected: done by the first
        run that has a job to do, so a run with nothing left to render starts no Ray."""
        ray = _ray()
        if ray.is_initialized():
            return
        options = {"address": self.address} if self.address else {"num_cpus": usable_cores(),
                                                                  "include_dashboard": False}
        handlers = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}
        try:
            ray.init(**options, log_to_driver=False, logging_level="WARNING")
        except (ConnectionError, ValueError, RuntimeError) as exc:
            raise BatchError(f"cannot reach the Ray cluster at {self.address or 'a local Ray'}: "
                             f"{one_line(exc)}") from None
        finally:
            _restore(handlers)
        self._connected_here = True

    def __exit__(self, *exc) -> None:
        if self._connected_here:
            _ray().shutdown()
            self._connected_here = False

    def actor_count(self) -> int:
        """The actors a run starts: `workers`, or as many as the cluster's CPUs hold at `threads` each."""
        if self.workers is not None:
            return self.workers
        self.connect()
        cpus = int(_ray().cluster_resources().get("CPU", 1))
        return max(1, cpus // self.threads)

    def run(self, jobs: Sequence[Job], outdir: Path, segment_s: float | None = None) -> Iterator[JobResult]:
        """Yield each job's result as it finishes; the run's actors end with it."""
        if not jobs:
            return
        self.connect()
        calls = ActorCalls(self.actor_count(), self.threads, self.retries)
        try:
            yield from run_programs(jobs, Path(outdir).absolute(), segment_s, calls)
        finally:
            calls.close()


class ActorCalls:
    """Calls on a fixed set of actors, one call an actor at a time; a call goes to an idle actor that last ran
    the same head when there is one (its bundle is loaded there).

    An actor whose process or node died fails the call it was running at once (`max_task_retries=0`); the call is
    rerun here on another actor, at most `retries` times, while Ray restarts the dead one where a CPU is free
    (`max_restarts=-1`) and a probe call puts it back among the idle once it answers. Rerunning the call here
    rather than through Ray's own task retries keeps the pool going when the dead actor cannot come back soon (its
    node lost, and every other CPU held by the other actors), and counts each call's attempts for the manifest.
    Written here rather than with `ray.util.ActorPool`, which does not say which call an actor that died was
    running."""

    def __init__(self, count: int, threads: int, retries: int, *, comeback_s: float = COMEBACK_S) -> None:
        ray = _ray()
        worker_class = ray.remote(BatchActor).options(
            num_cpus=threads, max_restarts=-1, max_task_retries=0,
            runtime_env={"env_vars": {"NUMBA_NUM_THREADS": str(threads), "OMP_NUM_THREADS": str(threads)}})
        self.retries, self.comeback_s = retries, comeback_s
        self.actors = [worker_class.remote() for _ in range(count)]
        self.idle = list(self.actors)
        self.last_head: dict[int, tuple] = {}
        self.running: dict = {}  # ObjectRef -> (call, actor)
        self.probing: dict = {}  # ObjectRef of a probe -> an actor that died, until it answers again
        self.rerun: deque[Call] = deque()  # calls whose actor died, to run again first
        self.attempts: Counter[str] = Counter()

    def free(self) -> int:
        return max(0, len(self.idle) - len(self.rerun))

    def submit(self, call: Call) -> None:
        head = call.job.head_key()
        actor = next((a for a in self.idle if self.last_head.get(id(a)) == head), self.idle[0])
        self.idle.remove(actor)
        self.last_head[id(actor)] = head
        self.attempts[call.key] += 1
        self.running[actor.run.remote(call)] = (call, actor)

    def wait(self) -> list[tuple[Call, Outcome]]:
        """At least one finished call (calls whose actor died are rerun first, on another actor)."""
        ray = _ray()
        while True:
            while self.rerun and self.idle:
                self.submit(self.rerun.popleft())
            if not self.running and not self.rerun:
                return []
            waiting_on_probes = not self.running
            refs = [*self.running, *self.probing]
            ready = ray.wait(refs, num_returns=1, timeout=self.comeback_s if waiting_on_probes else None)[0] \
                if refs else []
            if not ready:  # every actor is dead and none came back
                return [(call, self._gave_up(call, f"no Ray worker answered for {self.comeback_s:g} s after its "
                                                   "worker died")) for call in self._drain_rerun()]
            done = []
            for ref in ready:
                if ref in self.probing:
                    self._probed(ref)
                    continue
                call, actor = self.running.pop(ref)
                try:
                    value = ray.get(ref)
                except ray.exceptions.RayActorError:
                    self.probing[actor.place.remote()] = actor
                    if self.attempts[call.key] <= self.retries:
                        self.rerun.append(call)
                    else:
                        done.append((call, self._gave_up(call, f"its Ray worker died {self.attempts[call.key]} "
                                                               "times (killed, out of memory, or its node lost)")))
                    continue
                except ray.exceptions.RayError as exc:
                    value = JobResult(call.job.out, False, reason=one_line(exc))
                self.idle.append(actor)
                done.append((call, Outcome(value, self.attempts[call.key])))
            if done:
                return done

    def _probed(self, ref) -> None:
        """A dead actor's probe answered: idle again (restarted), or gone for good."""
        actor = self.probing.pop(ref)
        try:
            _ray().get(ref)
        except _ray().exceptions.RayError:
            self.actors.remove(actor)
            return
        self.idle.append(actor)

    def _gave_up(self, call: Call, reason: str) -> Outcome:
        attempts = self.attempts[call.key]
        return Outcome(JobResult(call.job.out, False, reason=reason, attempts=attempts), attempts)

    def _drain_rerun(self) -> list[Call]:
        calls, self.rerun = list(self.rerun), deque()
        return calls

    def places(self) -> list[tuple[int, str]]:
        """Each actor's (process id, node id)."""
        return _ray().get([actor.place.remote() for actor in self.actors])

    def close(self) -> None:
        ray = _ray()
        for actor in self.actors:
            ray.kill(actor)
        self.actors, self.idle, self.running, self.probing = [], [], {}, {}


class BatchActor:
    """A Ray actor that is one batch worker (batch/worker.py): its heads stay loaded between calls."""

    def run(self, call: Call) -> object:
        from .worker import run_call

        return run_call(call)

    def place(self) -> tuple[int, str]:
        """(process id, Ray node id) of this actor."""
        import ray

        return os.getpid(), ray.get_runtime_context().get_node_id()
