"""`gt-bench live-pool`: the CPU a live server's pool spends a session-second, measured without sockets, an event loop
or a wall clock, so that versions of the per-frame code compare within a few percent (docs/live.md, "One pool
thread and the voice's MatMul graph"). `gt-bench live-clients` measures the whole server under load, but its runs
vary by 15% and more at the knee.

N paced streaming sessions (`LiveSession(output=None, clock_grid_s=...)`, as the server makes them) run on a fake
clock: each speaks the sample speech in 20 ms chunks from its own start (staggered by 13 ms), then idles, its voice
given as the checkout's server gives it (fed by the pool thread to the sessions it takes up, or, before that,
pushed at each chunk's time); at every tick of the server's clock grid the pool's work is done as
`serve/drive_sessions.py` does it: the steady frames planned together (`runtime/live_steady.py`, where the
checkout has it), every session's planned stream call stacked into one (`run_stream_jobs`), then each session's due
frame made and encoded as a frame packet.
The process's CPU over that loop, over the sessions' seconds, is the result; each round runs in a fresh process, the
new checkout's and a baseline checkout's (its `src/` first on PYTHONPATH) alternating.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
import types
from collections.abc import Callable
from pathlib import Path

CHUNK_S = 0.02
STAGGER_S = 0.013
SPEECH_S = 4.0
# The loop's parts, timed apart: the voices' pushes (or feeds), planning the due sessions' translator calls
# (`stream_job`), running them (`run_stream_jobs`, onnxruntime and the stacking), making the frames (`step`),
# encoding the packets.
PHASES = ("push", "plan", "translate", "frames", "encode")


def pool_run(bundle: str, sessions: int, seconds: float, lookahead_ms: float = 160.0) -> dict:
    """One run in this process: CPU seconds of the pool's work for `sessions` sessions over `seconds` of fake
    clock, with the frames made and the translator calls run."""
    import numpy as np

    import gaussiantalker.runtime.live as live_module
    from gaussiantalker.runtime import LiveSession
    from gaussiantalker.runtime.stages import open_driver
    from gaussiantalker.runtime.translate_stream import run_stream_jobs
    from gaussiantalker.sdk.audio import load_audio
    from gaussiantalker.serve.drive_sessions import clock_grid_s
    from gaussiantalker.serve.wire import encode_drive, encode_frame_packet

    clock = [1000.0]
    live_module.time = types.SimpleNamespace(monotonic=lambda: clock[0], perf_counter=time.perf_counter,
                                             time=time.time)
    driver = open_driver(bundle, threads=1)
    driver.open_stream()
    speech = load_audio(Path(__file__).resolve().parents[2] / "samples" / "demo_speech.wav", driver.sample_rate)
    speech = np.asarray(speech[: int(SPEECH_S * driver.sample_rate)], np.float32)
    tick = clock_grid_s(driver.fps)
    lives = [LiveSession(driver, lookahead_ms=lookahead_ms, audio_rate=driver.sample_rate, output=None,
                         clock_grid_s=tick, streaming=True) for _ in range(sessions)]
    starts = [clock[0] + STAGGER_S * k for k in range(sessions)]
    voices = _Voices(lives, speech, driver.sample_rate, starts)
    try:  # the steady frames planned together and every frame made as arrays, as the checkout's pool does it
        from gaussiantalker.runtime.live_rows import make_rows  # noqa: F401
        from gaussiantalker.runtime.live_steady import SteadyFrames
        steady = SteadyFrames()
    except ImportError:  # an older checkout: each session's frame its own
        steady = None
    end = clock[0] + seconds
    frames = calls = rows = 0
    phases = dict.fromkeys(PHASES, 0.0)  # CPU seconds of each part of the loop
    clock_of = time.process_time
    began = clock_of()
    while clock[0] < end:
        t0 = clock_of()
        due = [k for k, live in enumerate(lives) if live.due <= clock[0]]  # as the server's pool picks them
        for k in range(sessions) if voices.every_tick else due:
            voices.feed(k, clock[0])
        due = [lives[k] for k in due]
        t1 = clock_of()
        planned = steady.plan(due, clock[0]) if steady is not None else [None] * len(due)
        jobs = [job for job in (live.stream_job() if mine is None else mine.job
                                for live, mine in zip(due, planned, strict=True)) if job is not None]
        t2 = clock_of()
        if jobs:
            calls += len(run_stream_jobs(jobs, driver.run_stream, driver.stream_rows))
            rows += sum(job.audio.shape[0] for job in jobs)
        t3 = clock_of()
        if steady is None:  # each frame made and encoded alone
            made = [frame for frame in (live.step() for live in due) if frame is not None]
            t4 = clock_of()
            for frame in made:
                encode_frame_packet(encode_drive(frame.index, frame.pts, frame.drive, frame.speaking, 0), frame.audio)
            frames += len(made)
        else:  # the frames made as arrays and packed as one, as `serve/drive_sessions.py` does
            made_rows = _rows_of(due, planned, steady)
            t4 = clock_of()
            frames += _packed(made_rows) if made_rows is not None else 0
        for phase, spent in zip(PHASES, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, clock_of() - t4), strict=True):
            phases[phase] += spent
        clock[0] += tick
    cpu = clock_of() - began
    return {"cpu_s": cpu, "frames": frames, "calls": calls, "rows": rows,
            "cpu_s_per_session_s": cpu / (sessions * seconds), "us_per_frame": 1e6 * cpu / max(frames, 1),
            **{f"{phase}_us_per_frame": 1e6 * spent / max(frames, 1) for phase, spent in phases.items()}}


def _rows_of(due: list, planned: list, steady):
    """The tick's frames as the server's pool makes them: each session's plan (its steady frame's, or its step's),
    then the frames as arrays (`make_rows`); None when no frame is due."""
    from gaussiantalker.runtime.live_rows import make_rows

    made = []
    for live, mine in zip(due, planned, strict=True):
        taken = steady.take(mine) if mine is not None else None
        taken = taken or live.next_plan()
        if taken is not None:
            made.append((live, *taken))
    if not made:
        return None
    rows = make_rows([item[0] for item in made], [item[1] for item in made])
    for live, _, due_time in made:
        live.keep_pace(due_time)
    return rows


def _packed(rows) -> int:
    """The frames' packets, cut one `bytes` a frame as the pool hands them out; how many."""
    import numpy as np

    from gaussiantalker.serve.wire import DRIVE_HEADER, PACKET_HEADER, frame_packets

    values = rows.values()
    message_end = PACKET_HEADER.size + DRIVE_HEADER.size + 4 * values.shape[1]
    groups: dict[int, list[int]] = {}
    for k, audio in enumerate(rows.audio):
        groups.setdefault(audio.shape[0], []).append(k)
    for group in groups.values():
        packets = frame_packets(rows.lives[0].driver.rig, rows.indices[group], rows.pts[group], values[group],
                                rows.speaking[group], np.zeros(len(group), np.int64),
                                np.stack([rows.audio[k] for k in group]))
        for packet in packets:
            packet[PACKET_HEADER.size:message_end].tobytes(), packet.tobytes()
    return len(rows.audio)


class _Voices:
    """The sessions' voices as the checkout's server gives them: fed by the pool thread to the sessions it takes up
    (`PacedVoice`), or, in a checkout from before it, pushed chunk by chunk at each chunk's time (the event loop's
    timers, counted here all the same); a flush after the last chunk either way."""

    def __init__(self, lives: list, speech, rate: int, starts: list[float]) -> None:
        try:
            from gaussiantalker.serve.voices import PacedVoice
        except ImportError:  # an older checkout
            PacedVoice = None
        self.every_tick = PacedVoice is None
        self.lives, self.speech, self.rate, self.starts = lives, speech, rate, starts
        self.paced = None if PacedVoice is None else [PacedVoice(live, speech, rate, CHUNK_S, start)
                                                      for live, start in zip(lives, starts, strict=True)]
        self.chunk = int(rate * CHUNK_S)
        self.pushed = [0] * len(lives)

    def feed(self, k: int, now: float) -> None:
        if self.paced is not None:
            self.paced[k].feed(now)
            return
        count = -(-self.speech.shape[0] // self.chunk)
        while self.pushed[k] < count and self.starts[k] + self.pushed[k] * CHUNK_S <= now:
            first = self.pushed[k] * self.chunk
            self.lives[k].push(self.speech[first:first + self.chunk], self.rate)
            self.pushed[k] += 1
            if self.pushed[k] == count:
                self.lives[k].flush()


def run_in_checkout(src: Path | None, module: str, function: str, *args: str | int | float) -> dict:
    """`module`'s `function(*args)` (a function of tools/bench that returns a JSON-able dict; plain arguments, passed
    by their repr) in a fresh process whose gaussiantalker is `src`'s (an older checkout's src/, first on
    PYTHONPATH and the working folder; None: this checkout's); its dict."""
    root = Path(__file__).resolve().parents[2]
    paths = [str(src if src is not None else root / "src"), str(root),
             *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    code = f"import json; from {module} import {function}; print(json.dumps({function}(*{args!r})))"
    done = subprocess.run([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": os.pathsep.join(paths)},
                          cwd=src or root, capture_output=True, text=True, timeout=900)
    if done.returncode != 0:
        raise RuntimeError(f"the run failed ({'baseline' if src else 'new'}): {done.stderr.strip()[-800:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def alternate_rounds(baseline: Path | None, sessions: list[int], rounds: int, desc: str, progress: bool,
                     run: Callable[[str, Path | None, int], dict]) -> dict[tuple[str, int], list[dict]]:
    """`run(label, src, n)` for every number of sessions and version ("old": the `baseline` checkout's src/, if
    any, then "new": this one's, src None), in alternating rounds (old then new, then new then old, ...); each
    version's results by (label, n), in round order."""
    from tqdm import tqdm

    from .compare import in_turn

    versions = ([("old", baseline / "src")] if baseline is not None else []) + [("new", None)]
    runs: dict[tuple[str, int], list[dict]] = {(label, n): [] for label, _ in versions for n in sessions}
    with tqdm(total=rounds * len(sessions) * len(versions), desc=desc, disable=not progress) as bar:
        for round_index in range(rounds):
            for n in sessions:
                for label, src in in_turn(versions, round_index):
                    runs[(label, n)].append(run(label, src, n))
                    bar.update()
    return runs


def run_live_pool(bundle: Path, sessions: list[int], seconds: float, rounds: int, lookahead_ms: float = 160.0,
                  baseline: Path | None = None, baseline_bundle: Path | None = None, progress: bool = True) -> dict:
    """Every (sessions, server) in alternating rounds (old, new, old, new ...), each a fresh process."""
    served = {"old": baseline_bundle or bundle, "new": bundle}
    runs = alternate_rounds(baseline, sessions, rounds, "pool runs", progress,
                            lambda label, src, n: run_in_checkout(src, "tools.bench.live_pool", "pool_run",
                                                                  str(served[label]), n, seconds, lookahead_ms))
    rows = median_rows(runs, sessions, ("cpu_s_per_session_s", "us_per_frame",
                                        *(f"{phase}_us_per_frame" for phase in PHASES)), ("calls", "rows", "frames"))
    return {"bundle": str(bundle), "baseline": None if baseline is None else str(baseline), "seconds": seconds,
            "lookahead_ms": lookahead_ms, "rounds": rounds, "rows": rows}


def median_rows(runs: dict[tuple[str, int], list[dict]], sessions: list[int], medians: tuple[str, ...],
                firsts: tuple[str, ...]) -> list[dict]:
    """One row a number of sessions from `alternate_rounds`' results: each version's rounds, the median of each
    of `medians` (the first is the one compared: "ratio", new over old where there is an old, the median of each
    round's own ratio, the two versions run back to back there, so the machine's drift between rounds cancels) and
    `firsts` as the first round has them (counts every round shares)."""
    from .compare import median_ratio

    rows = []
    for n in sessions:
        row: dict = {"sessions": n}
        for label in ("old", "new"):
            got = runs.get((label, n))
            if got:
                row[label] = {"rounds": got, **{key: statistics.median(r[key] for r in got) for key in medians},
                              **{key: got[0][key] for key in firsts}}
        if "old" in row:
            row["ratio"] = median_ratio([r[medians[0]] for r in row["new"]["rounds"]],
                                        [r[medians[0]] for r in row["old"]["rounds"]])
        rows.append(row)
    return rows


def live_pool_table(result: dict) -> str:
    """One row a number of sessions: each server's median CPU a session-second and a frame, its calls and rows."""
    old = result["baseline"] is not None
    head = "| sessions | " + ("old: CPU s per session-s (µs a frame) | " if old else "") + \
        "new: CPU s per session-s (µs a frame) | " + ("new / old | " if old else "") + \
        "frames | translator calls | rows |"
    lines = [head, "|" + "---:|" * (head.count("|") - 1)]
    for row in result["rows"]:
        cells = [str(row["sessions"])]
        for label in (["old"] if old else []) + ["new"]:
            cells.append(f"{row[label]['cpu_s_per_session_s']:.4f} ({row[label]['us_per_frame']:.0f})")
        if old:
            cells.append(f"{row['ratio']:.2f}×")
        cells += [str(row["new"]["frames"]), str(row["new"]["calls"]), str(row["new"]["rows"])]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n\n" + phases_table(result)


def phases_table(result: dict) -> str:
    """Where a frame's CPU goes: each version's median µs a frame in each part of the loop (`PHASES`; both versions
    run this checkout's `pool_run`, which times them)."""
    labels = [label for label in ("old", "new") if result["rows"] and label in result["rows"][0]]
    head = "| sessions | version | " + " | ".join(f"{phase} µs a frame" for phase in PHASES) + " |"
    lines = [head, "|" + "---:|" * 2 + "---:|" * len(PHASES)]
    for row in result["rows"]:
        for label in labels:
            cells = [str(row["sessions"]), label] + [f"{row[label][f'{phase}_us_per_frame']:.1f}" for phase in PHASES]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
