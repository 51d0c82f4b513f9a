"""`gt-bench avatar`'s speed measure (tools/bench/avatar.py): alternating rounds of an imported avatar's bundles
playing a motion and the demo speaker's bundle playing speech, the same number of frames each, steady-state ms per
frame."""

from __future__ import annotations

import statistics
import time
from itertools import islice
from pathlib import Path

import numpy as np

from gaussiantalker.exporter.export.speech import synth_speech
from gaussiantalker.runtime.head import TalkingHead
from gaussiantalker.sdk.progress import progress_bar

from .worker import steady_frame_ms

WARMUP_FRAMES = 5  # first frames of each played clip left out of the steady-state rate
DEMO_LABEL = "demo speaker fp32"


def timed_play(frames) -> list[float]:
    """Wall seconds between consecutive frames of a frame iterator (the first counts from the call)."""
    walls = []
    start = time.perf_counter()
    for _ in frames:
        now = time.perf_counter()
        walls.append(now - start)
        start = now
    return walls


def steady_ms(walls: list[float]) -> float:
    """Ms per frame once the pipeline is full (`steady_frame_ms`, WARMUP_FRAMES left out)."""
    return steady_frame_ms(walls, WARMUP_FRAMES)


def fps_rounds(avatar_bundles: dict[str, Path], demo_bundle: Path, motion: np.ndarray, frames: int, rounds: int,
               size: int, settings: dict[str, dict] | None = None) -> dict:
    """Alternating rounds at `size`²: each avatar bundle (with its `settings` entry's TalkingHead keywords, if any)
    plays `frames` frames of `motion` (a motion table its `TalkingHead.frames(motion=...)` takes: ARKit weights
    [T, 52] or a FLAME table [T, E + 18]), the demo speaker as many frames of synthetic speech; per case the per-round
    ms/frame and FPS and their medians, and the avatar/demo FPS ratios."""
    clip = np.resize(motion, (frames, motion.shape[1]))  # the motion's first frames, repeated if it is shorter
    settings = settings or {}
    heads = {f"avatar {name}": TalkingHead(path, resolution=(size, size), **settings.get(name, {}))
             for name, path in avatar_bundles.items()}
    demo = heads[DEMO_LABEL] = TalkingHead(demo_bundle, resolution=(size, size), composite=False)
    audio = synth_speech(frames / demo.fps + 1.0, seed=7)  # a second more, so the clip has `frames` frames
    runs: dict[str, list[float]] = {label: [] for label in heads}
    try:
        with progress_bar(total=rounds * len(heads), desc=f"FPS at {size}²", unit="run") as bar:
            for _ in range(rounds):
                for label, head in heads.items():
                    bar.set_postfix_str(label)
                    if head is demo:
                        walls = timed_play(islice(head.frames(audio, demo.sample_rate), frames))
                    else:
                        walls = timed_play(head.frames(motion=clip))
                    runs[label].append(steady_ms(walls))
                    bar.update()
    finally:
        for head in heads.values():
            head.close()
    cases = {label: {"frame_ms_rounds": ms, "fps_rounds": [1e3 / m for m in ms], "frame_ms": statistics.median(ms),
                     "fps": 1e3 / statistics.median(ms)} for label, ms in runs.items()}
    demo_fps = cases[DEMO_LABEL]["fps"]
    ratios = {label: case["fps"] / demo_fps for label, case in cases.items() if label.startswith("avatar")}
    return {"size": size, "frames": frames, "rounds": rounds, "cases": cases, "fps_vs_demo": ratios}


__all__ = ["DEMO_LABEL", "WARMUP_FRAMES", "fps_rounds", "steady_ms", "timed_play"]
