"""`gt-bench frames`: per-stage timings and FPS of the runtime vs the torch reference on the demo speaker.

* Stages (run one after another, so each median is clean): translator (one windowed run over the clip, divided
  by its frames), deformation (ONNX graph), sort (validate, pack, depth sort), upload, draw, readback (GL).
* FPS: audio to pixels through `TalkingHead.frames`, which overlaps frame t+1's deformation and sort with frame
  t's GL draw; steady-state median wall time per frame (first frames excluded) and the whole clip's throughput.
* Speed-up: the torch reference's median full frame (deformation + tiled reference rasterizer) over the
  runtime's median pipelined frame, for the same drives.
"""

from __future__ import annotations

import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import typer

from gaussiantalker.exporter.export.speech import synth_speech


def cpu_name() -> str:
    """The CPU's model and architecture (Linux's /proc/cpuinfo "model name"), else the architecture alone."""
    machine = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("model name") and ":" in line:
                    return f"{line.split(':', 1)[1].strip()[:80]} ({machine})"
    except OSError:
        pass
    return machine


def machine_info() -> dict:
    """The machine a benchmark ran on: CPU, cores, Python, torch, the GL context."""
    import moderngl

    from gaussiantalker.runtime.splat.gl_context import create_context, describe_context

    ctx = create_context()
    info = {"cpu": cpu_name(), "cores": os.cpu_count(),
            "python": platform.python_version(), "torch": torch.__version__,
            "gl": describe_context(ctx), "moderngl": moderngl.__version__}
    ctx.release()
    return info


def bench_runtime(bundle: Path, size: int, audio: np.ndarray, sample_rate: int, warmup: int) -> dict:
    """Pipelined wall time per frame over the clip, then clean sequential per-stage medians."""
    from gaussiantalker.runtime.head import TalkingHead

    from .worker import measure_frames

    with TalkingHead(bundle, resolution=(size, size), renderer="gl") as head:
        return measure_frames(head, audio, sample_rate, warmup)


def bench_torch(speaker, size: int, audio: np.ndarray, frames: int) -> dict:
    """Median ms of a full torch reference frame (deformation + tiled reference rasterizer)."""
    from gaussiantalker.exporter.export.probes import driven_clip

    camera = speaker.camera.resized(size, size)
    _, drives = driven_clip(speaker, frames)
    times = []
    for drive in drives:
        start = time.perf_counter()
        speaker.render(drive, camera)
        times.append(time.perf_counter() - start)
    return {"frames": frames, "frame_ms": 1000.0 * float(np.median(times))}


def bench_paper_translator(seconds: float = 10.0) -> dict:
    """Export and run the paper-size translator (wav2vec 2.0 large class) once: parameters, export and run time."""
    from gaussiantalker.exporter.export.onnx_export import add_graph
    from gaussiantalker.exporter.export.translator_graph import translator_onnx
    from gaussiantalker.exporter.model.translator import MotionTranslator, count_parameters, paper_translator_config
    from gaussiantalker.sdk.bundle import BundleWriter

    torch.manual_seed(0)
    model = MotionTranslator(paper_translator_config(), n_expr=100, speaker_id=0).eval()
    # The output head starts at zero (neutral face); randomise it so the parity check compares real values.
    torch.nn.init.normal_(model.motion_decoder.head.weight, std=0.02)
    params = count_parameters(model)
    start = time.perf_counter()
    proto = translator_onnx(model)
    export_s = time.perf_counter() - start
    with tempfile.TemporaryDirectory() as tmp:
        writer = BundleWriter({})
        add_graph(writer, "translator", proto)
        path = Path(tmp) / "paper.gtb"
        size = writer.write(path)
        from gaussiantalker.runtime.onnxruntime_backend import OnnxRuntimeBackend
        from gaussiantalker.sdk.bundle import Bundle

        backend = OnnxRuntimeBackend(Bundle(path))
        audio = synth_speech(seconds, seed=3)
        audio = audio[: len(audio) // model.samples_per_frame * model.samples_per_frame]
        start = time.perf_counter()
        out = backend.run("translator", {"audio": audio[None]})
        run_s = time.perf_counter() - start
    with torch.no_grad():
        reference = model(torch.from_numpy(audio)[None])[0].numpy()
    return {"parameters": params, "bundle_mb": size / 1e6, "export_s": export_s, "audio_s": seconds,
            "run_s": run_s, "max_abs_err": float(np.abs(reference - out["expression"]).max()),
            "output_abs_max": float(np.abs(reference).max())}


def run_frames_bench(checkpoint: Path | None, gaussians: int, sizes: str, seconds: float, torch_frames: int,
                     paper_translator: bool, json_path: Path | None) -> None:
    """Bench the speaker (the checkpoint's bare head, or an untrained demo speaker) at each size; print, and write
    the JSON to `json_path`."""
    from gaussiantalker.exporter.demo.demo_speaker import make_demo_speaker
    from gaussiantalker.exporter.export.bundle_export import export_bundle
    from gaussiantalker.exporter.export.checkpoint import load_checkpoint

    if checkpoint is not None:
        speaker = load_checkpoint(checkpoint)
        speaker.reference = speaker.inpaint = None  # the bare head (compositing: tools/bench/composite_cost.py)
    else:
        speaker, _ = make_demo_speaker(gaussians, train_seconds=0, progress=False)
    audio = synth_speech(seconds, seed=7)
    results = {"machine": machine_info(), "gaussians": speaker.gaussians.count, "audio_seconds": seconds, "sizes": {}}
    with tempfile.TemporaryDirectory() as tmp:
        bundle = Path(tmp) / "bench.gtb"
        export_bundle(speaker, bundle, progress=False)
        for size in (int(s) for s in sizes.split(",")):
            runtime = bench_runtime(bundle, size, audio, speaker.config.sample_rate, warmup=5)
            reference = bench_torch(speaker, size, audio, torch_frames)
            runtime["speedup_vs_torch"] = reference["frame_ms"] / runtime["frame_ms"]
            results["sizes"][str(size)] = {"runtime": runtime, "torch_reference": reference}
            stages = " ".join(f"{k}={v:.2f}" for k, v in runtime["stages_ms"].items())
            typer.echo(f"{size}x{size}: runtime {runtime['frame_ms']:.1f} ms/frame = {runtime['fps']:.1f} FPS "
                       f"pipelined ({runtime['clip_fps']:.1f} FPS over the whole clip); sequential stages ms: "
                       f"{stages}; torch reference {reference['frame_ms']:.0f} ms/frame; speed-up "
                       f"{runtime['speedup_vs_torch']:.1f}x")
    if paper_translator:
        results["paper_translator"] = bench_paper_translator()
        typer.echo(f"paper-size translator: {json.dumps(results['paper_translator'])}")
    if json_path is not None:
        json_path.write_text(json.dumps(results, indent=2))
        typer.echo(f"wrote {json_path}")
