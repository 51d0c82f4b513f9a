"""One SDK version's side of `gt-bench compare` (and one case's side of `gt-bench sweep`): export and render
on request, report timings as JSON lines.

Run as a script by whichever interpreter has the version under test on its path (`compare.py` starts one
per version, `sweep.py` one per case). The `export` and `frames` requests use only API that every version of
the SDK has (`load_checkpoint`, `export_bundle`, `TalkingHead.frames/drives/render/timings`), so they can measure
an older checkout as well as this one; `frames` with settings, `translate`, `memory` and `release` are the sweep's.
Requests arrive one JSON object per line on stdin; each answer is one JSON line on the original stdout (anything
the libraries print goes to stderr).
"""

from __future__ import annotations

import inspect
import json
import sys
import time
from pathlib import Path

import numpy as np

STAGES = ("translator", "deformation", "sort", "upload", "draw", "readback")


def steady_frame_ms(walls: list[float], warmup: int) -> float:
    """Ms per frame of a played clip once its pipeline is full: the mean gap between frames after the first `warmup`
    (fewer on a short clip). A loop that makes whole frames at once, as the CPU splatter's does, hands them over in
    bursts (gaps near 0, then one as long as the batch), so a median gap is not its frame time; the mean is the
    clip's rate."""
    steady = walls[min(warmup, len(walls) // 2):]
    return 1000.0 * float(np.mean(steady))


def measure_frames(head, audio, sample_rate: int | None, warmup: int, keep: list | None = None) -> dict:
    """Pipelined wall time per frame through `head.frames` (`steady_frame_ms`), then clean sequential per-stage
    medians (ms). `keep`: a list that receives the pipelined frames."""
    walls = []
    clip_start = start = time.perf_counter()
    for frame in head.frames(audio, sample_rate):
        now = time.perf_counter()
        walls.append(now - start)
        if keep is not None:
            keep.append(frame)
        start = now
    clip_seconds = time.perf_counter() - clip_start
    frames = len(walls)
    head.timings.clear()
    for drive in head.drives(audio, sample_rate):
        head.render(drive)
    stages = {"translator": 1000.0 * sum(head.timings["translator"]) / frames}
    for stage in STAGES[1:]:
        stages[stage] = 1000.0 * float(np.median(head.timings[stage][warmup:]))
    frame_ms = steady_frame_ms(walls, warmup)
    return {"frames": frames, "stages_ms": stages, "sequential_frame_ms": sum(stages.values()),
            "frame_ms": frame_ms, "fps": 1000.0 / frame_ms, "clip_fps": frames / clip_seconds}


def gl_pinned(talking_head: type, settings: dict) -> dict:
    """`settings` drawing with the OpenGL splatter, which every version has (the renderer keyword and the "auto"
    default came later), so that versions are compared on one renderer; a renderer given is kept."""
    if "renderer" in settings or "renderer" not in inspect.signature(talking_head.__init__).parameters:
        return settings
    return {**settings, "renderer": "gl"}


class Worker:
    """Answers `export`, `frames`, `translate` and `memory` requests; keeps one TalkingHead per (bundle, size,
    settings) between rounds unless asked to reopen it."""

    def __init__(self) -> None:
        self.heads: dict[tuple[str, int, str], object] = {}

    def export(self, checkpoint: str, bundle: str) -> dict:
        try:
            from gaussiantalker.exporter.export.bundle_export import export_bundle
            from gaussiantalker.exporter.export.checkpoint import load_checkpoint
        except ImportError:  # a `compare --baseline` checkout of an earlier layout
            try:
                from gaussiantalker.exporter.export.checkpoint import load_checkpoint
                from gaussiantalker.exporter.export.export import export_bundle
            except ImportError:  # the exporter without sub-packages
                from gaussiantalker.exporter.checkpoint import load_checkpoint
                from gaussiantalker.exporter.export import export_bundle

        start = time.perf_counter()
        speaker = load_checkpoint(checkpoint)
        speaker.reference = speaker.inpaint = None  # the bare head (compositing has its own bench)
        export_bundle(speaker, bundle, progress=False)
        return {"export_s": time.perf_counter() - start}

    def frames(self, bundle: str, size: int, audio: str, warmup: int, settings: dict | None = None,
               save: str | None = None, reopen: bool = False) -> dict:
        """Time the clip (see `measure_frames`). `settings`: TalkingHead keyword arguments (runtime knobs); `save`:
        write the pipelined frames there (.npy); `reopen`: load the bundle afresh and report the load time."""
        from gaussiantalker.runtime.head import TalkingHead

        key = (bundle, size, json.dumps(settings or {}, sort_keys=True))
        if reopen and key in self.heads:
            self.heads.pop(key).close()
        load_s = None
        if key not in self.heads:
            start = time.perf_counter()
            self.heads[key] = TalkingHead(bundle, resolution=(size, size), **gl_pinned(TalkingHead, settings or {}))
            load_s = time.perf_counter() - start
        kept = [] if save else None
        result = measure_frames(self.heads[key], audio, None, warmup, kept)
        if save:
            np.save(save, np.stack(kept))
        return {**result, "load_s": load_s}

    def translate(self, bundle: str, audio: str, save: str) -> dict:
        """The translator's expression and jaw pose for the clip, written to `save` (.npz)."""
        from gaussiantalker.runtime.head import TalkingHead

        # Drawn with nothing: pinned to the OpenGL splatter, whose set-up is a context, not the CPU splatter's
        # kernels (compiled again in a process whose package path numba's cache has not seen).
        with TalkingHead(bundle, **gl_pinned(TalkingHead, {})) as head:
            # This file runs in every version a comparison loads: the head's own names work in all of them (the
            # stages' names in new ones; docs/embedding.md "Renamed names").
            driver = getattr(head, "driver", head)
            expression, jaw = driver.translate(driver.load_audio(audio))
        np.savez(save, expression=expression, jaw=jaw)
        return {}

    def memory(self) -> dict:
        """Peak resident memory of this process so far (MB): what playing its bundles took."""
        try:  # Linux: the high-water mark of this process's own memory (ru_maxrss would also count the parent's
            # memory at fork time, which exec leaves in the rusage maximum)
            status = Path("/proc/self/status").read_text()
            return {"peak_rss_mb": int(status.split("VmHWM:")[1].split()[0]) / 1e3}
        except (OSError, IndexError, ValueError):
            import resource

            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # bytes on macOS, kB elsewhere
            return {"peak_rss_mb": peak / (1e6 if sys.platform == "darwin" else 1e3)}

    def release(self) -> dict:
        """Close every open TalkingHead."""
        self.close()
        self.heads.clear()
        return {}

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
                if op not in ("export", "frames", "translate", "memory", "release"):
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
