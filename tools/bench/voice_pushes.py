"""`gt-bench voice-pushes`: the CPU a live server's event loop spends pushing its own voices (docs/live.md, "Load"):
`serve/voices.py`'s `push_real_time` speaking the sample speech in 20 ms chunks at real time for N sessions on one
asyncio loop, into paced live sessions on a driver as the server makes them (drives, no frames made: the pool's
work is `gt-bench live-pool`'s). Starts are spread over one chunk, as sessions that began at different moments. Each
round a fresh process, an older checkout's (`--baseline-checkout`, its `src/` first on the path) and this one's
alternating; the result is the process's CPU over the run, a chunk and a session-second.
"""

from __future__ import annotations

import time
from pathlib import Path

from .live_pool import alternate_rounds, median_rows, run_in_checkout


def pushes_run(bundle: str, sessions: int, seconds: float, chunk_ms: float = 20.0) -> dict:
    """One run in this process: CPU seconds of `sessions` voices of `seconds` each pushed at real time."""
    import asyncio

    import numpy as np

    from gaussiantalker.runtime import LiveSession
    from gaussiantalker.runtime.stages import open_driver
    from gaussiantalker.sdk.audio import load_audio
    from gaussiantalker.serve.drive_sessions import clock_grid_s
    from gaussiantalker.serve.voices import push_real_time

    driver = open_driver(bundle, threads=1)
    rate = driver.sample_rate
    speech = load_audio(Path(__file__).resolve().parents[2] / "samples" / "demo_speech.wav", rate)
    speech = np.resize(np.asarray(speech, np.float32), int(seconds * rate))  # repeated if the sample is shorter
    lives = [LiveSession(driver, audio_rate=rate, output=None, clock_grid_s=clock_grid_s(driver.fps))
             for _ in range(sessions)]
    chunk_s = chunk_ms / 1000

    async def voice(k: int, live) -> None:
        await asyncio.sleep(chunk_s * k / sessions)
        await push_real_time(live, speech, rate, chunk_s)

    async def all_voices() -> None:
        await asyncio.gather(*(voice(k, live) for k, live in enumerate(lives)))

    began = time.process_time()
    asyncio.run(all_voices())
    cpu = time.process_time() - began
    step = max(1, int(rate * chunk_s))
    chunks = sessions * -(-speech.shape[0] // step)
    queued = sum(round(live.queued_s * rate) for live in lives)
    return {"cpu_s": cpu, "chunks": chunks, "queued_samples": queued, "us_per_chunk": 1e6 * cpu / chunks,
            "cpu_s_per_session_s": cpu / (sessions * seconds)}


def run_voice_pushes(bundle: Path, sessions: list[int], seconds: float, rounds: int, chunk_ms: float = 20.0,
                     baseline: Path | None = None, progress: bool = True) -> dict:
    """Every (sessions, version) in alternating rounds (old, new, old, new ...), each a fresh process."""

    def run(label: str, src: Path | None, n: int) -> dict:
        return run_in_checkout(src, "tools.bench.voice_pushes", "pushes_run", str(bundle), n, seconds, chunk_ms)

    runs = alternate_rounds(baseline, sessions, rounds, "voice runs", progress, run)
    rows = median_rows(runs, sessions, ("us_per_chunk", "cpu_s_per_session_s"), ("chunks",))
    return {"bundle": str(bundle), "baseline": None if baseline is None else str(baseline), "seconds": seconds,
            "chunk_ms": chunk_ms, "rounds": rounds, "rows": rows}


def voice_pushes_table(result: dict) -> str:
    """One row a number of sessions: each version's median µs a chunk and CPU s a session-second."""
    old = result["baseline"] is not None
    labels = (["old"] if old else []) + ["new"]
    head = "| sessions | " + "".join(f"{label}: µs a chunk (CPU s per session-s) | " for label in labels) + \
        ("new / old | " if old else "") + "chunks |"
    lines = [head, "|" + "---:|" * (head.count("|") - 1)]
    for row in result["rows"]:
        cells = [str(row["sessions"])]
        cells += [f"{row[label]['us_per_chunk']:.1f} ({row[label]['cpu_s_per_session_s']:.4f})" for label in labels]
        if old:
            cells.append(f"{row['ratio']:.2f}×")
        cells.append(str(row["new"]["chunks"]))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
