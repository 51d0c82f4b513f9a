"""`gt-bench pipeline BUNDLE`: the pipelined frame loop against the serial one (and another checkout), alternating.

What a user runs on a CPU-only machine, with the CPU tile splatter: `TalkingHead.frames` on the bare head at
--size, the same composited at the reference clip's size, `samples/play.py` bare and composited (whole commands:
interpreter, imports, bundle load, kernel cache, render, encoding). Each is timed for every variant: "on" and
"off" are this checkout with `pipeline=True` / `False` (play.py: `--no-pipeline`); with --before, "before" is
that checkout as it is. Every measurement runs in a fresh interpreter with its version first on the import path
(`compare.Version`); the variants alternate within each round and the order rotates round by round, so a shared
machine's noise falls on all of them. The report gives medians over rounds, real-time factors (wall / audio
seconds), ratios against "on", the stage medians `TalkingHead.timings` recorded, and the load average seen before
each measurement.
"""

from __future__ import annotations

import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
import wave
from pathlib import Path

import numpy as np

from gaussiantalker.sdk.progress import progress_bar

from .compare import Version, checkout_root, checkout_top, this_version_root

CASES = ("frames", "frames-composite", "play", "play-composite")
STAGE_NAMES = ("translator", "deformation", "sort", "upload", "draw", "readback", "reference", "composite")

# Run in the variant's interpreter: render the audio through TalkingHead.frames and print the wall time, the
# frame count and each stage's median (ms) as one JSON line.
FRAMES_SNIPPET = """
import json, statistics, sys, time
from gaussiantalker.runtime import TalkingHead
bundle, audio, size, pipeline = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
keywords = {} if pipeline == "default" else {"pipeline": pipeline == "on"}
if size:
    keywords.update(resolution=(size, size), composite=False)
head = TalkingHead(bundle, renderer="cpu", **keywords)
samples = getattr(head, "driver", head).load_audio(audio)  # before the stages, the head had load_audio
start = time.perf_counter()
count = sum(1 for _ in head.frames(samples, head.sample_rate))
seconds = time.perf_counter() - start
stages = {name: 1000 * statistics.median(values) for name, values in head.timings.items() if values}
print(json.dumps({"seconds": seconds, "frames": count, "audio_s": samples.shape[0] / head.sample_rate,
                  "size": list(head.frame_size), "stages_ms": stages}))
"""
WARM_SNIPPET = """
try:
    from gaussiantalker.runtime.splat.cpu import warm_up
except ImportError:  # a checkout whose CPU splatter is runtime/cpu_splatter.py
    from gaussiantalker.runtime.cpu_splatter import warm_up
warm_up()
"""


def write_trimmed_wav(source: Path, seconds: float, path: Path) -> float:
    """The first `seconds` of `source` (0: all of it) as a 16 kHz 16-bit mono wav at `path`; its length (s)."""
    from gaussiantalker.sdk.audio import load_audio

    rate = 16_000
    audio = load_audio(source, rate)
    if seconds > 0:
        audio = audio[: int(round(seconds * rate))]
    with wave.open(str(path), "wb") as out:
        out.setnchannels(1)
        out.setsampwidth(2)
        out.setframerate(rate)
        out.writeframes((np.clip(audio, -1, 1) * 32767).astype("<i2").tobytes())
    return audio.shape[0] / rate


def _run(version: Version, args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    done = subprocess.run([sys.executable, *args], env=version.env(), cwd=cwd, capture_output=True, text=True,
                          timeout=3600)
    if done.returncode != 0:
        raise RuntimeError(f"{version.label}: {shlex.join(args[:3])} ... failed:\n{done.stderr[-2000:]}")
    return done


def measure(case: str, variant: str, version: Version, bundle: Path, audio: Path, size: int, tmp: Path) -> dict:
    """One timed run of `case` for `variant` ("before", "off" or "on")."""
    pipeline = "default" if variant == "before" else variant
    if case.startswith("frames"):
        done = _run(version, ["-c", FRAMES_SNIPPET, str(bundle), str(audio),
                              str(size if case == "frames" else 0), pipeline], tmp)
        return json.loads(done.stdout.strip().splitlines()[-1])
    player = checkout_top(version.root) / "samples" / "play.py"
    args = [str(player), str(bundle), "--audio", str(audio), "--renderer", "cpu", "-o", str(tmp / f"{variant}.mp4"),
            "-q"]
    if case == "play":
        args += ["-r", str(size), "--no-composite"]
    if variant == "off":
        args.append("--no-pipeline")
    start = time.perf_counter()
    _run(version, args, tmp)
    return {"seconds": time.perf_counter() - start}


def bench_pipeline(bundle: Path, *, audio: Path, seconds: float, size: int, rounds: int, cases: list[str],
                   baseline: Path | None = None, progress: bool = True) -> dict:
    """Every case for every variant, `rounds` rounds, the variants' order rotating; see the module docstring."""
    unknown = sorted(set(cases) - set(CASES))
    if unknown:
        raise ValueError(f"unknown cases {unknown}; choose from {', '.join(CASES)}")
    with tempfile.TemporaryDirectory(prefix="gt-bench-pipeline-") as folder:
        tmp = Path(folder)
        this = Version.make("this", this_version_root(), tmp)
        versions = {"on": this, "off": this}
        if baseline is not None:
            versions = {"before": Version.make("before", checkout_root(baseline), tmp), **versions}
        clip = tmp / "speech.wav"
        audio_s = write_trimmed_wav(audio, seconds, clip)
        for version in {id(v): v for v in versions.values()}.values():  # compile or load the kernels once each
            _run(version, ["-c", WARM_SNIPPET], tmp)
        variants = list(versions)
        runs: dict[str, dict[str, list[dict]]] = {case: {v: [] for v in variants} for case in cases}
        plan = [(r, case, variants[(i + r) % len(variants)])
                for r in range(rounds) for case in cases for i in range(len(variants))]
        for r, case, variant in progress_bar(plan, desc="pipeline bench", unit="run", disable=not progress):
            load = os.getloadavg()[0]
            result = measure(case, variant, versions[variant], bundle, clip, size, tmp)
            result.update(round=r, load_1min=load)
            runs[case][variant].append(result)
        descriptions = {label: version.description for label, version in versions.items()}
    return {"bundle": str(bundle), "audio_s": audio_s, "size": size, "rounds": rounds, "versions": descriptions,
            "runs": runs, "summary": summarise(runs, audio_s)}


def summarise(runs: dict[str, dict[str, list[dict]]], audio_s: float) -> dict:
    """Per case and variant: median wall seconds, real-time factor, ms per frame, ratio of each variant's median
    to "on"'s (> 1: "on" is faster), stage medians."""
    summary = {}
    for case, by_variant in runs.items():
        rows = {}
        for variant, results in by_variant.items():
            wall = statistics.median(r["seconds"] for r in results)
            row = {"seconds": wall, "rtf": wall / audio_s, "rounds": [round(r["seconds"], 3) for r in results]}
            if results and "frames" in results[0]:
                row["ms_per_frame"] = 1000 * statistics.median(r["seconds"] / r["frames"] for r in results)
                row["stages_ms"] = {name: statistics.median(r["stages_ms"].get(name, 0.0) for r in results)
                                    for name in STAGE_NAMES if any(name in r["stages_ms"] for r in results)}
            rows[variant] = row
        for row in rows.values():
            row["ratio_to_on"] = row["seconds"] / rows["on"]["seconds"]
        summary[case] = rows
    return summary


def format_report(result: dict, machine: dict, command: str) -> str:
    """The Markdown page of a run."""
    loads = [r["load_1min"] for case in result["runs"].values() for rs in case.values() for r in rs]
    lines = [
        "# Pipelined frame loop against the serial one",
        "",
        f"`{command}`",
        "",
        f"Machine: {machine.get('cpu')}, {machine.get('cores')} cores, Python {machine.get('python')}; the CPU tile "
        f"splatter draws. Audio: {result['audio_s']:.1f} s. Rounds: {result['rounds']} (variants alternating, "
        f"order rotating). Load average (1 min) before each run: median {statistics.median(loads):.2f}, "
        f"min {min(loads):.2f}, max {max(loads):.2f}.",
        "",
        "Versions: " + "; ".join(f"{label}: {text}" for label, text in result["versions"].items())
        + " (\"off\" and \"on\" are this checkout with the pipeline off and on).",
        "",
        "| case | variant | median s | RTF | ms / frame | ratio to on | rounds (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for case, rows in result["summary"].items():
        for variant, row in rows.items():
            per_frame = f"{row['ms_per_frame']:.1f}" if "ms_per_frame" in row else ""
            lines.append(f"| {case} | {variant} | {row['seconds']:.2f} | {row['rtf']:.2f} | {per_frame} | "
                         f"{row['ratio_to_on']:.2f} | {', '.join(f'{s:.2f}' for s in row['rounds'])} |")
    stage_rows = [(case, variant, row["stages_ms"]) for case, rows in result["summary"].items()
                  for variant, row in rows.items() if "stages_ms" in row]
    if stage_rows:
        names = [n for n in STAGE_NAMES if any(n in s for _, _, s in stage_rows)]
        lines += ["", "Stage medians (ms, `TalkingHead.timings`; in a pipelined run the stages overlap, so they "
                  "add up to more than the frame):", "",
                  "| case | variant | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
        for case, variant, stages in stage_rows:
            lines.append(f"| {case} | {variant} | " + " | ".join(f"{stages.get(n, 0.0):.2f}" for n in names) + " |")
    return "\n".join(lines) + "\n"


__all__ = ["CASES", "bench_pipeline", "format_report", "summarise", "write_trimmed_wav"]
