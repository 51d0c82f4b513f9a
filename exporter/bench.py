"""`gt-bench`: per-stage timings and FPS of the runtime vs the torch reference on the demo speaker.

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

from .demo_audio import synth_speech

app = typer.Typer(add_completion=False, help=__doc__)

def _machine() -> dict:
    import moderngl

    from gaussiantalker.runtime.gl_context import create_context, describe_context

    ctx = create_context()
    info = {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
            "python": platform.python_version(), "torch": torch.__version__,
            "gl": describe_context(ctx), "moderngl": moderngl.__version__}
    ctx.release()
    return info


def bench_runtime(bundle: Path, size: int, audio: np.ndarray, sample_rate: int, warmup: int) -> dict:
    """Pipelined wall time per frame over the clip, then clean sequential per-stage medians."""
    from gaussiantalker.runtime.head import TalkingHead

    from .bench_worker import measure_frames

    with TalkingHead(bundle, resolution=(size, size)) as head:
        return measure_frames(head, audio, sample_rate, warmup)


def bench_torch(speaker, size: int, audio: np.ndarray, frames: int) -> dict:
    """Median ms of a full torch reference frame (deformation + tiled reference rasterizer)."""
    from .verify import driven_clip

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
    from gaussiantalker.sdk.bundle import BundleWriter

    from .onnx_export import add_graph
    from .translator import MotionTranslator, count_parameters, paper_translator_config, translator_onnx

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


@app.command()
def main(
    checkpoint: Path = typer.Option(None, "--checkpoint", help="speaker checkpoint [default: untrained demo]"),
    gaussians: int = typer.Option(20_000, "--gaussians", help="demo speaker size when no checkpoint is given"),
    sizes: str = typer.Option("256,512", "--sizes", help="square resolutions to bench"),
    seconds: float = typer.Option(6.0, "--seconds", help="audio length driven through the runtime"),
    torch_frames: int = typer.Option(3, "--torch-frames", help="frames rendered by the torch reference"),
    paper_translator: bool = typer.Option(False, "--paper-translator", help="also export/run the ~300M translator"),
    json_path: Path = typer.Option(None, "--json", help="write results as JSON"),
    baseline: Path = typer.Option(None, "--baseline", help="another checkout of the SDK: measure both side by side "
                                  "(alternating rounds) and print the per-stage table with speed-ups"),
    rounds: int = typer.Option(3, "--rounds", min=1, help="with --baseline: rounds per version and case"),
    scaling: str = typer.Option(None, "--scaling", help="with --baseline: Gaussian counts to compare at the largest "
                                "size, e.g. 20000,50000,100000,200000 [default: --gaussians only]"),
    play_seconds: float = typer.Option(10.0, "--play-seconds", help="with --baseline: audio length for timing "
                                       "each version's samples/play.py at 512x512 (0: skip)"),
    sweep: bool = typer.Option(False, "--sweep", help="measure every speed/accuracy knob alone and every preset "
                               "side by side (alternating rounds) on the demo speaker and a larger synthetic one; "
                               "writes sweep.md, sweep.json and sweep.png to --out"),
    sweep_gaussians: int = typer.Option(100_000, "--sweep-gaussians", min=0, help="with --sweep: size of the "
                                        "synthetic speaker (0: demo speaker only)"),
    skip_demo: bool = typer.Option(False, "--skip-demo", help="with --sweep: the synthetic speaker only (each "
                                   "speaker can then get its own --seconds and --rounds)"),
    cases: str = typer.Option(None, "--cases", help="with --sweep: only the cases whose name or knob contains one "
                              "of these comma-separated words, e.g. 'preset,sort' [default: all]"),
    out: Path = typer.Option(Path("bench-sweep"), "--out", help="with --sweep: folder for the report files"),
    scene: Path = typer.Option(None, "--scene", help="with --sweep: each preset plain and specialised for this scene "
                               "file (docs/scene.md), side by side (use --sizes at the scene's resolution)"),
    composite: bool = typer.Option(False, "--composite", help="compositing into the reference clip of --checkpoint "
                                   "(a speaker with one): FPS composited and bare at the clip's size and 512x512, "
                                   "F's cost, seam steps (docs/compositing.md); writes --out/composite.md"),
    backends: bool = typer.Option(False, "--backends", help="onnxruntime vs MNN on --checkpoint exported with "
                                  "--mnn: each graph's ms, stages and FPS at the largest --sizes, alternating "
                                  "(docs/mnn.md); writes --out/backends.md"),
) -> None:
    """Benchmark the demo speaker through the runtime and the torch reference (or against --baseline, --sweep or
    --composite)."""
    if backends:
        if checkpoint is None:
            raise typer.BadParameter("--backends needs --checkpoint", param_hint="--checkpoint")
        from .bench_backends import run_backends_bench

        run_backends_bench(checkpoint, max(int(s) for s in sizes.split(",")), seconds, rounds, out / "backends.md")
        return
    if composite:
        if checkpoint is None:
            raise typer.BadParameter("--composite needs --checkpoint (a speaker with a reference clip)",
                                     param_hint="--checkpoint")
        from .bench_composite import run_composite_bench

        run_composite_bench(checkpoint, None, seconds, rounds, 12, out / "composite.md")
        return
    if sweep:
        if skip_demo and sweep_gaussians == 0:
            raise typer.BadParameter("--skip-demo needs a synthetic speaker (--sweep-gaussians > 0)",
                                     param_hint="--skip-demo")
        _sweep(checkpoint, gaussians, sweep_gaussians, sizes, seconds, rounds, cases, out, skip_demo, scene)
        return
    if baseline is not None:
        _compare_with_baseline(baseline, gaussians, sizes, seconds, rounds, scaling, play_seconds, json_path)
        return
    from .checkpoint import load_checkpoint
    from .demo_speaker import make_demo_speaker
    from .export import export_bundle

    if checkpoint is not None:
        speaker = load_checkpoint(checkpoint)
        speaker.reference = speaker.inpaint = None  # the bare head (compositing: exporter/bench_composite.py)
    else:
        speaker, _ = make_demo_speaker(gaussians, train_seconds=0, progress=False)
    audio = synth_speech(seconds, seed=7)
    results = {"machine": _machine(), "gaussians": speaker.gaussians.count, "audio_seconds": seconds, "sizes": {}}
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


def _compare_with_baseline(baseline: Path, gaussians: int, sizes: str, seconds: float, rounds: int,
                           scaling: str | None, play_seconds: float, json_path: Path | None) -> None:
    """`--baseline`: the side-by-side table of bench_compare, printed (and written as JSON)."""
    from dataclasses import asdict

    from .bench_compare import checkout_root, compare, format_table

    try:
        checkout_root(baseline)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--baseline") from None
    size_list = [int(s) for s in sizes.split(",")]
    result = compare(baseline, gaussians=[gaussians], sizes=size_list, seconds=seconds, rounds=rounds,
                     play_seconds=play_seconds)
    if scaling:
        counts = [int(c) for c in scaling.split(",") if int(c) != gaussians]
        scaled = compare(baseline, gaussians=counts, sizes=[max(size_list)], seconds=seconds, rounds=rounds,
                         play_seconds=0)
        result.cases.update(scaled.cases)
    result_text = format_table(result)
    typer.echo(f"machine: {json.dumps(_machine())}\n{result_text}")
    if json_path is not None:
        json_path.write_text(json.dumps({"machine": _machine(), **asdict(result)}, indent=2))
        typer.echo(f"wrote {json_path}")


def _sweep(checkpoint: Path | None, gaussians: int, large: int, sizes: str, seconds: float, rounds: int,
           cases: str | None, out: Path, skip_demo: bool = False, scene: Path | None = None) -> None:
    """`--sweep`: see bench_sweep.py; writes the markdown report, the JSON and (with matplotlib) the plot."""
    import sys
    from dataclasses import asdict

    from gaussiantalker.sdk.errors import GaussianTalkerError
    from gaussiantalker.sdk.files import atomic_write

    from .bench_report import format_report, plot_sweep
    from .bench_sweep import scene_cases, select_cases, sweep_cases, sweep_speaker
    from .checkpoint import load_checkpoint
    from .demo_speaker import make_demo_speaker

    try:
        if scene is not None:
            from gaussiantalker.sdk.scene import load_scene

            try:
                load_scene(scene)  # a bad scene file fails here, before any speaker is built
            except GaussianTalkerError as exc:
                raise typer.BadParameter(str(exc), param_hint="--scene") from None
        chosen = select_cases(sweep_cases() if scene is None else scene_cases(str(scene)), cases)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--cases") from None
    size_list = [int(s) for s in sizes.split(",")]
    if checkpoint is not None:
        demo = load_checkpoint(checkpoint)
        demo.reference = demo.inpaint = None  # the bare head (compositing: exporter/bench_composite.py)
    else:
        typer.echo("building the demo speaker (its translator trains for a few minutes; --checkpoint skips this)")
        demo, _ = make_demo_speaker(gaussians)
    speakers = [] if skip_demo else [("demo speaker", demo)]
    if large > 0:
        synthetic, _ = make_demo_speaker(large, seed=1, train_seconds=0, progress=False, config=demo.config)
        synthetic.translator.load_state_dict(demo.translator.state_dict())  # the same speech, more Gaussians
        speakers.append(("synthetic speaker", synthetic))
    out.mkdir(parents=True, exist_ok=True)
    sweeps = [sweep_speaker(name, speaker, chosen, sizes=size_list, seconds=seconds, rounds=rounds)
              for name, speaker in speakers]
    machine = _machine()
    command = "gt-bench " + " ".join(sys.argv[1:])
    report = format_report(sweeps, machine, command)
    with atomic_write(out / "sweep.md", "w") as handle:
        handle.write(report + "\n")
    with atomic_write(out / "sweep.json", "w") as handle:
        json.dump({"machine": machine, "command": command, "seconds": seconds, "rounds": rounds,
                   "speakers": [asdict(s) for s in sweeps]}, handle, indent=2)
    written = ["sweep.md", "sweep.json"]
    try:
        plot_sweep(sweeps, out / "sweep.png")
        written.append("sweep.png")
    except ImportError:
        typer.echo("matplotlib is not installed (pip install 'gaussiantalker-sdk[bench]'): no plot", err=True)
    typer.echo(report)
    typer.echo(f"wrote {', '.join(str(out / name) for name in written)}")


def main_entry() -> None:
    app(prog_name="gt-bench")
