"""`gt-bench stream-calls`: what one call of a bundle's streaming translator graph costs, per sessions stacked on the
batch axis and frames a call, as a live server's pool calls it (docs/live.md, "Sessions batched together"); several
bundles (the same speaker exported by two commits) side by side in alternating rounds, onnxruntime on one thread.

Each case feeds noise at speech level from each bundle's rest state, committing one frame (the rest, if any, are
provisional: what a 30 fps avatar's calls on the 25 fps voice look like). A round times `calls` calls of every bundle
in turn (the other order every other round); the report gives each bundle's median over rounds, ms a call and a
session-frame, and its ratio to the first bundle: the median of the rounds' own ratios.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np

from .compare import in_turn, median_ratio


def _feeds(spec, sessions: int, frames: int) -> tuple[np.ndarray, np.ndarray]:
    audio = (np.random.default_rng(sessions * 100 + frames).standard_normal((sessions, frames, spec.frame_samples))
             * 0.05).astype(np.float32)
    return audio, np.repeat(spec.rest_state[None], sessions, axis=0)


def run_stream_calls(bundles: list[Path], cases: list[tuple[int, int]], rounds: int, calls: int = 20,
                     progress: bool = True, graph: str = "refreshing") -> dict:
    """Median ms a call of each bundle's streaming graph for each (sessions, frames) case, alternating bundles
    within every round. `graph` "refreshing": `translator_stream`; "steady": its steady form (the calls a live
    session makes while the loudness holds), which every bundle must have."""
    from tqdm import tqdm

    from gaussiantalker.runtime.stages import open_driver

    if graph not in ("refreshing", "steady"):
        raise ValueError(f"graph must be 'refreshing' or 'steady', got {graph!r}")
    refresh = graph == "refreshing"

    drivers = []
    for path in bundles:
        driver = open_driver(path, threads=1)
        if not driver.has_stream:
            raise ValueError(f"{path}: the bundle has no streaming translator graph (re-export it)")
        if not refresh and not driver.stream_spec.steady:
            raise ValueError(f"{path}: the bundle's stream has no steady graph (only the speaker's own translator "
                             "has one)")
        drivers.append(driver)
    times = {(b, case): [] for b in range(len(bundles)) for case in cases}
    for round_index in tqdm(range(rounds), desc="rounds", disable=not progress):
        for case in cases:
            for b, driver in in_turn(list(enumerate(drivers)), round_index):
                audio, state = _feeds(driver.stream_spec, *case)
                driver.run_stream(audio, state, 1, refresh)  # warm: the shapes' first call allocates
                began = time.perf_counter()
                for _ in range(calls):
                    driver.run_stream(audio, state, 1, refresh)
                times[(b, case)].append((time.perf_counter() - began) / calls)
    rows = []
    for sessions, frames in cases:
        medians = [statistics.median(times[(b, (sessions, frames))]) * 1e3 for b in range(len(bundles))]
        ratios = [median_ratio(times[(b, (sessions, frames))], times[(0, (sessions, frames))])
                  for b in range(len(bundles))]
        rows.append({"sessions": sessions, "frames": frames, "ms_per_call": medians,
                     "ms_per_session_frame": [m / (sessions * frames) for m in medians],
                     "ratio_to_first": ratios})
    return {"bundles": [str(p) for p in bundles], "graph": graph, "rounds": rounds, "calls_per_round": calls,
            "cases": rows}


def stream_calls_table(result: dict) -> str:
    """One row a case: each bundle's ms a call (a session-frame) and its ratio to the first bundle."""
    names = [Path(p).name if Path(p).name not in [Path(q).name for q in result["bundles"][:i]] else p
             for i, p in enumerate(result["bundles"])]
    header = "| sessions a call | frames a call | " + " | ".join(
        f"{name}: ms a call (a session-frame)" for name in names) + " | " + " | ".join(
        f"{name} / {names[0]}" for name in names[1:]) + " |"
    lines = [header, "|" + "---:|" * (2 + len(names) + len(names) - 1)]
    for row in result["cases"]:
        cells = [f"{c:.3f} ({s:.4f})" for c, s in zip(row["ms_per_call"], row["ms_per_session_frame"], strict=True)]
        ratios = [f"{r:.2f}×" for r in row["ratio_to_first"][1:]]
        lines.append(f"| {row['sessions']} | {row['frames']} | " + " | ".join(cells + ratios) + " |")
    return "\n".join(lines)
