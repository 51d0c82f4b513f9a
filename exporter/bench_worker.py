"""One SDK version's side of `gt-bench --baseline`: export and render on request, report timings as JSON lines.

Run as a script by whichever interpreter has the version under test on its path (`bench_compare.py` starts one
per version). It uses only API that every version of the SDK has (`load_checkpoint`, `export_bundle`,
`TalkingHead.frames/drives/render/timings`), so it can measure an older checkout as well as this one.
Requests arrive one JSON object per line on stdin; each answer is one JSON line on the original stdout (anything
the libraries print goes to stderr).
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

STAGES = ("translator", "deformation", "sort", "upload", "draw", "readback")


def measure_frames(head, audio, sample_rate: int | None, warmup: int) -> dict:
    """Pipelined wall time per frame through `head.frames`, then clean sequential per-stage medians (ms)."""
    walls = []
    clip_start = start = time.perf_counter()
    for _ in head.frames(audio, sample_rate):
        now = time.perf_counter()
        walls.append(now - start)
        start = now
    clip_seconds = time.perf_counter() - clip_start
    frames = len(walls)
    head.timings.clear()
    for drive in head.drives(audio, sample_rate):
        head.render(drive)
    stages = {"translator": 1000.0 * sum(head.timings["translator"]) / frames}
    for stage in STAGES[1:]:
        stages[stage] = 1000.0 * float(np.median(head.timings[stage][warmup:]))
    frame_ms = 1000.0 * float(np.median(walls[warmup:]))
    return {"frames": frames, "stages_ms": stages, "sequential_frame_ms": sum(stages.values()),
            "frame_ms": frame_ms, "fps": 1000.0 / frame_ms, "clip_fps": frames / clip_seconds}


class Worker:
    """Answers `export` and `frames` requests; keeps one TalkingHead per (bundle, size) between rounds."""

    def __init__(self) -> None:
        self.heads: dict[tuple[str, int], object] = {}

    def export(self, checkpoint: str, bundle: str) -> dict:
        from gaussiantalker.exporter.checkpoint import load_checkpoint
        from gaussiantalker.exporter.export import export_bundle

        start = time.perf_counter()
        export_bundle(load_checkpoint(checkpoint), bundle, progress=False)
        return {"export_s": time.perf_counter() - start}

    def frames(self, bundle: str, size: int, audio: str, warmup: int) -> dict:
        from gaussiantalker.runtime.head import TalkingHead

        key = (bundle, size)
        if key not in self.heads:
            self.heads[key] = TalkingHead(bundle, resolution=(size, size))
        return measure_frames(self.heads[key], audio, None, warmup)

    def close(self) -> None:
        for head in self.heads.values():
            head.close()


def main() -> None:
    answers = sys.stdout
    sys.stdout = sys.stderr  # library output must not corrupt the protocol
    worker = Worker()
    try:
        for line in sys.stdin:
            request = json.loads(line)
            op = request.pop("op")
            try:
                if op not in ("export", "frames"):
                    raise ValueError(f"unknown request {op!r}")
                answer = {"ok": True, **getattr(worker, op)(**request)}
            except Exception as exc:  # reported to the parent, which names the version that failed
                answer = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
            answers.write(json.dumps(answer) + "\n")
            answers.flush()
    finally:
        worker.close()


if __name__ == "__main__":
    main()
