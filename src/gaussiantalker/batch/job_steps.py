"""A job as the steps a worker runs (docs/batch.md, "Long audio"): `start` renders a short job whole, or makes a long
job's drives once and cuts them into segments; each `segment` renders its frames into a file of its own; `join`
copies the segments' packets into the output with the whole clip's audio. `run_programs` feeds the steps of many
jobs to any engine's `CallPool` (local processes or Ray actors), which only runs calls.

The order of calls is the engines' common part: a started job's calls go before a new job's, so jobs finish in
turn and at most a pool's worth of jobs hold their drives in this process at once."""

from __future__ import annotations

from collections import deque
from collections.abc import Generator, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

from .engine import JobResult
from .jobs import Job
from .outputs import remove_partials

DEFAULT_SEGMENT_S = 60.0


@dataclass(frozen=True)
class Call:
    """One step of one job for a worker: `step` names the function of batch/worker.py, `args` its arguments."""

    step: str  # "start", "segment" or "join"
    job: Job
    outdir: str
    args: tuple = ()

    @property
    def key(self) -> str:
        """Names the call among a run's calls (its retries count under it)."""
        return f"{self.job.out}:{self.step}:{self.args[1] if self.step == 'segment' else ''}"


@dataclass(frozen=True)
class Split:
    """What `start` returns for a job longer than a segment: its drives, and the frame range of each segment."""

    drives: list
    shown: list[int]  # the speaker frame each drive's video frame shows (its reference picture when composited)
    ranges: list[tuple[int, int]]  # [first, end) frames of each segment, in order
    composited: bool
    fps: float
    seconds: float  # spent making the drives


@dataclass(frozen=True)
class SegmentDone:
    """A segment's frames written to its own file (a hidden name beside the output)."""

    path: str
    frames: int
    seconds: float


@dataclass(frozen=True)
class Outcome:
    """What a call returned (a JobResult when it failed, or ended the job), and how often it ran."""

    value: object
    attempts: int = 1


class CallPool(Protocol):
    """An engine's workers: `free()` slots, `submit` a call, `wait` for at least one finished call."""

    def free(self) -> int: ...

    def submit(self, call: Call) -> None: ...

    def wait(self) -> list[tuple[Call, Outcome]]: ...


Program = Generator[list[Call], list[Outcome], JobResult]


def job_program(job: Job, outdir: Path, segment_s: float | None) -> Program:
    """The steps of one job: start; then, if it was split, its segments (all at once) and the join."""
    first = (yield [Call("start", job, str(outdir), (segment_s,))])[0]
    if isinstance(first.value, JobResult):
        return _with_attempts(first.value, first.attempts)
    split: Split = first.value
    calls = [Call("segment", job, str(outdir), (split.drives[start:end], index, split.shown[start:end],
                                                split.composited, split.fps))
             for index, (start, end) in enumerate(split.ranges)]
    del split.drives[:]  # each segment call holds its own slice: this process keeps none
    parts = yield calls
    attempts = max([first.attempts] + [part.attempts for part in parts])
    failed = [part.value for part in parts if isinstance(part.value, JobResult)]
    if failed:
        return _with_attempts(failed[0], attempts)
    done: list[SegmentDone] = [part.value for part in parts]
    joined = (yield [Call("join", job, str(outdir), (done, split.fps))])[0]
    result = joined.value
    if result.ok:
        result = JobResult(result.out, True, output=result.output,
                           seconds=split.seconds + sum(part.seconds for part in done) + result.seconds,
                           video_s=result.video_s, segments=len(done))
    return _with_attempts(result, max(attempts, joined.attempts))


def _with_attempts(result: JobResult, attempts: int) -> JobResult:
    return replace(result, attempts=max(attempts, result.attempts))


def run_programs(jobs: Sequence[Job], outdir: Path, segment_s: float | None, pool: CallPool) -> Iterator[JobResult]:
    """Run every job's program on `pool`, yielding each JobResult as its job ends; the files a job's steps left
    beside its output (segments, a killed worker's partial files) are removed when it ends."""
    waiting = deque(jobs)
    ready: deque[tuple[int, Call]] = deque()  # calls of started programs, in the order they were asked for
    programs: dict[int, tuple[Program, Job, list[Call], dict[str, Outcome]]] = {}
    next_id = 0

    def advance(program_id: int, sent: list[Outcome] | None) -> JobResult | None:
        program, job, _, _ = programs[program_id]
        try:
            calls = next(program) if sent is None else program.send(sent)
        except StopIteration as stop:
            del programs[program_id]
            remove_partials(outdir / job.out)
            return stop.value
        programs[program_id] = (program, job, calls, {})
        ready.extend((program_id, call) for call in calls)
        return None

    in_flight: dict[str, int] = {}
    while waiting or programs:
        while pool.free() > 0 and (ready or waiting):
            if not ready:
                job = waiting.popleft()
                programs[next_id] = (job_program(job, outdir, segment_s), job, [], {})
                next_id += 1
                ended = advance(next_id - 1, None)
                if ended is not None:
                    yield ended
                continue
            program_id, call = ready.popleft()
            in_flight[call.key] = program_id
            pool.submit(call)
        if not in_flight:
            continue
        for call, outcome in pool.wait():
            program_id = in_flight.pop(call.key)
            _, _, calls, outcomes = programs[program_id]
            outcomes[call.key] = outcome
            if len(outcomes) == len(calls):
                ended = advance(program_id, [outcomes[c.key] for c in calls])
                if ended is not None:
                    yield ended
