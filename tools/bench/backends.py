"""onnxruntime vs MNN (docs/mnn.md), side by side in one run:

    gt-bench backends --checkpoint out/speaker.ckpt --seconds 4 --rounds 3 --out docs/bench

The speaker is exported once with `--mnn` and played bare (`composite=False`: compositing has its own bench). Each round
opens every case (backend x graph threads) in turn, alternating so the machine's noise falls on all, and measures
through the public API at 512x512: each graph alone (translator per 10 s call, deformation per frame, the inpainting
generator on a 272x400 crop when the speaker has one), the sequential per-stage ms and the pipelined FPS of
`TalkingHead.frames`. Medians over rounds; ratios against onnxruntime with its default threads.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import typer

from gaussiantalker.exporter.export.bundle_export import export_bundle
from gaussiantalker.exporter.export.checkpoint import load_checkpoint
from gaussiantalker.exporter.export.speech import synth_speech
from gaussiantalker.exporter.verify.random_inputs import random_crops
from gaussiantalker.runtime.head import TalkingHead
from gaussiantalker.sdk.progress import progress_bar

from .worker import measure_frames

# (label, backend, graph threads): each backend at its default, and both on one thread (the mobile preset's).
CASES = (("onnxruntime", "onnxruntime", None), ("onnxruntime 1 thread", "onnxruntime", 1),
         ("mnn", "mnn", None), ("mnn 2 threads", "mnn", 2))
TRANSLATOR_SECONDS = 10.0
INPAINT_CROP = (400, 272)  # rows, columns: the demo clip's face crop (docs/bench/composite.md)
CALLS = 20


def _median_ms(call, repeats: int = CALLS) -> float:
    call()  # first call: shape resize / allocation, not steady state
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        seconds.append(time.perf_counter() - start)
    return 1e3 * statistics.median(seconds)


def measure_case(bundle: Path, backend: str, threads: int | None, size: int, audio: np.ndarray, rate: int) -> dict:
    """One backend's graph costs and frame timings on `bundle` at `size`x`size`."""
    with TalkingHead(bundle, resolution=(size, size), composite=False, backend=backend, threads=threads) as head:
        speech = synth_speech(TRANSLATOR_SECONDS, seed=11)[None].astype(np.float32)
        spf = head.driver.config.samples_per_frame
        speech = speech[:, : speech.shape[1] // spf * spf]
        drive = next(iter(head.drives(audio, rate)))
        inputs = {**drive.graph_inputs(), "camera_center": head.camera.center.astype(np.float32)[None]}
        run = head.frame_renderer.graphs.run
        graphs = {"translator 10 s": _median_ms(lambda: run("translator", {"audio": speech}), 5),
                  "deformation": _median_ms(lambda: run("deform", inputs))}
        if "inpaint" in head.bundle.manifest["graphs"]:
            crop = dict(zip(("image", "mask", "coverage"), random_crops(0, [INPAINT_CROP])[0], strict=True))
            graphs["inpaint crop"] = _median_ms(lambda: head.frame_renderer.graphs.run("inpaint", crop))
        frames = measure_frames(head, audio, rate, warmup=5)
    return {"graphs_ms": graphs, **frames}


def run_backends_bench(checkpoint: Path, size: int, seconds: float, rounds: int, report: Path | None) -> dict:
    """Measure CASES alternating over `rounds` rounds; print (and write to `report`) the median table."""
    speaker = load_checkpoint(checkpoint)
    audio = synth_speech(seconds, seed=7)
    runs: dict[str, list[dict]] = {label: [] for label, _, _ in CASES}
    with tempfile.TemporaryDirectory(prefix="gt-bench-backends-") as tmp:
        bundle = Path(tmp) / "speaker_mnn.gtb"
        export_bundle(speaker, bundle, progress=False, mnn=True)
        bundle_mb = bundle.stat().st_size / 1e6
        with progress_bar(total=rounds * len(CASES), desc="gt-bench backends", unit="run") as bar:
            for _ in range(rounds):
                for label, backend, threads in CASES:
                    bar.set_postfix_str(label)
                    runs[label].append(measure_case(bundle, backend, threads, size, audio, speaker.config.sample_rate))
                    bar.update()
    table = format_table(runs, size, seconds, rounds, checkpoint, bundle_mb)
    typer.echo(table)
    if report is not None:
        report.parent.mkdir(parents=True, exist_ok=True)
        report.write_text(table + "\n")
        typer.echo(f"wrote {report}")
    return runs


def _median(runs: list[dict], *keys: str) -> float:
    values = []
    for run in runs:
        value = run
        for key in keys:
            value = value[key]
        values.append(value)
    return statistics.median(values)


def format_table(runs: dict[str, list[dict]], size: int, seconds: float, rounds: int, checkpoint: Path,
                 bundle_mb: float) -> str:
    """Markdown: per case, median graph ms, stage ms and FPS, with FPS relative to onnxruntime's default."""
    first = next(iter(runs.values()))[0]
    graph_names = list(first["graphs_ms"])
    stages = list(first["stages_ms"])
    reference_fps = _median(runs[CASES[0][0]], "fps")
    lines = [f"Command: `gt-bench backends --checkpoint {checkpoint} --seconds {seconds:g} --rounds {rounds}`; "
             f"bundle with MNN graphs {bundle_mb:.1f} MB; medians of {rounds} alternating rounds at {size}x{size}.",
             "",
             "| case | " + " | ".join(f"{g} ms" for g in graph_names) + " | ms/stage (" + " / ".join(stages)
             + ") | FPS | × FPS |",
             "|---|" + "---|" * len(graph_names) + "---|---|---|"]
    for label, case_runs in runs.items():
        graphs = " | ".join(f"{_median(case_runs, 'graphs_ms', g):.1f}" for g in graph_names)
        stage_ms = " / ".join(f"{_median(case_runs, 'stages_ms', s):.1f}" for s in stages)
        fps = _median(case_runs, "fps")
        lines.append(f"| {label} | {graphs} | {stage_ms} | {fps:.1f} | {fps / reference_fps:.2f} |")
    return "\n".join(lines)
